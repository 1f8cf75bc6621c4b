//! Playback of a recorded session in the window: play, pause, scrub on a timeline,
//! speed. The window asks a [`ReplaySource`] for the [`ViewFrame`] at a recorded time
//! and draws it with the live window's renderer and HUD; a timeline panel at the bottom
//! holds the controls. The camera is the live window's (laparoscope; right drag orbits,
//! `C` switches back).
//!
//! Keys: space plays or pauses, ← / → step 1 s back or forward, `+` / `-` double or halve
//! the speed, Home goes to the start.

use std::time::{Duration, Instant};

use three_d::{Context, Event, GUI, Key, egui};
use winit::event::{Event as WinitEvent, WindowEvent};
use winit::event_loop::ControlFlow;
use winit::platform::run_return::EventLoopExtRunReturn;

use crate::camera::CameraMode;
use crate::frame::ViewFrame;
use crate::hud::hud;
use crate::render::{DrawOptions, Renderer};
use crate::window::{Hands, ViewerError, WindowOptions, event_loop, open_window};

/// Speeds offered by the timeline (× real time).
pub const SPEEDS: [f64; 8] = [0.125, 0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0];

/// What the replay window shows: the frame at a recorded time.
pub trait ReplaySource {
    /// Recorded (simulated) time span `(start, end)` (s).
    fn span(&self) -> (f64, f64);
    /// The picture at recorded time `t` (s), clamped to the span.
    fn frame_at(&mut self, t: f64) -> ViewFrame;
}

/// The player's state: where in the recording, playing or not, how fast. Advanced by
/// wall time; scrubbing sets the time directly.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Player {
    /// Recorded time span (s).
    pub span: (f64, f64),
    /// Current recorded time (s).
    pub time: f64,
    /// Playing (else paused).
    pub playing: bool,
    /// Recorded seconds per wall second.
    pub speed: f64,
}

impl Player {
    /// At the start of `span`, playing at real time.
    pub fn new(span: (f64, f64)) -> Self {
        let span = if span.1 >= span.0 {
            span
        } else {
            (span.0, span.0)
        };
        Player {
            span,
            time: span.0,
            playing: true,
            speed: 1.0,
        }
    }

    /// Advances by `wall_s` seconds of wall time when playing; pauses at the end.
    pub fn advance(&mut self, wall_s: f64) {
        if !self.playing {
            return;
        }
        self.seek(self.time + wall_s * self.speed);
        if self.time >= self.span.1 {
            self.playing = false;
        }
    }

    /// Jumps to recorded time `t` (clamped to the span).
    pub fn seek(&mut self, t: f64) {
        self.time = if t.is_nan() {
            self.span.0
        } else {
            t.clamp(self.span.0, self.span.1)
        };
    }

    /// Play or pause; playing from the end restarts.
    pub fn toggle(&mut self) {
        if !self.playing && self.time >= self.span.1 {
            self.time = self.span.0;
        }
        self.playing = !self.playing;
    }

    /// The next faster (`up`) or slower offered speed.
    pub fn change_speed(&mut self, up: bool) {
        let i = SPEEDS
            .iter()
            .position(|&s| s >= self.speed - 1e-12)
            .unwrap_or(SPEEDS.len() - 1);
        let j = if up {
            (i + 1).min(SPEEDS.len() - 1)
        } else {
            i.saturating_sub(1)
        };
        self.speed = SPEEDS[j];
    }

    /// Applies a key press; `true` if it was a player key.
    pub fn key(&mut self, key: Key) -> bool {
        match key {
            Key::Space => self.toggle(),
            Key::ArrowLeft => self.seek(self.time - 1.0),
            Key::ArrowRight => self.seek(self.time + 1.0),
            Key::Home => self.seek(self.span.0),
            Key::End => self.seek(self.span.1),
            Key::Plus | Key::Equals => self.change_speed(true),
            Key::Minus => self.change_speed(false),
            _ => return false,
        }
        true
    }

    /// Lays out the timeline panel (play/pause, time slider, speed).
    pub fn timeline(&mut self, ui: &mut egui::Ui) {
        egui::Panel::bottom("replay-timeline").show_inside(ui, |ui| {
            ui.horizontal(|ui| {
                let label = if self.playing { "pause" } else { "play" };
                if ui.button(label).clicked() {
                    self.toggle();
                }
                let (a, b) = self.span;
                let mut t = self.time;
                ui.spacing_mut().slider_width = (ui.available_width() - 260.0).max(100.0);
                let slider = ui.add(
                    egui::Slider::new(&mut t, a..=b.max(a + 1e-6))
                        .suffix(" s")
                        .fixed_decimals(2),
                );
                if slider.changed() {
                    self.seek(t);
                }
                egui::ComboBox::from_id_salt("replay-speed")
                    .selected_text(format!("{}×", self.speed))
                    .show_ui(ui, |ui| {
                        for s in SPEEDS {
                            ui.selectable_value(&mut self.speed, s, format!("{s}×"));
                        }
                    });
                ui.monospace(format!("{:.2} / {:.2} s", self.time - a, b - a));
            });
        });
    }
}

/// Opens a window and plays `source` back until the user closes it. Blocks the calling
/// thread (any thread).
pub fn run_replay_window(
    source: &mut dyn ReplaySource,
    options: WindowOptions,
) -> Result<(), ViewerError> {
    let mut event_loop = event_loop()?;
    let (window, gl) = open_window(&event_loop, &options)?;
    let context: Context = (*gl).clone();
    let renderer = Renderer::new(&context);
    let mut gui = GUI::new(&context);
    let mut inputs = three_d::FrameInputGenerator::from_winit_window(&window);
    let mut hands = Hands {
        active_tool: None,
        ..Hands::default()
    };
    let mut player = Player::new(source.span());
    let frame_period = Duration::from_secs_f64(1.0 / options.max_fps.max(1.0));
    let mut next_frame = Instant::now();
    let mut last = Instant::now();
    let mut ignored = Vec::new();
    event_loop.run_return(|event, _, control_flow| match event {
        WinitEvent::WindowEvent { ref event, .. } => {
            inputs.handle_winit_window_event(event);
            match event {
                WindowEvent::Resized(size) => gl.resize(*size),
                WindowEvent::ScaleFactorChanged { new_inner_size, .. } => {
                    gl.resize(**new_inner_size)
                }
                WindowEvent::CloseRequested => *control_flow = ControlFlow::Exit,
                _ => {}
            }
        }
        WinitEvent::MainEventsCleared => {
            if Instant::now() >= next_frame {
                window.request_redraw();
            } else {
                *control_flow = ControlFlow::WaitUntil(next_frame);
            }
        }
        WinitEvent::RedrawRequested(_) => {
            next_frame = Instant::now() + frame_period;
            *control_flow = ControlFlow::WaitUntil(next_frame);
            player.advance(last.elapsed().as_secs_f64());
            last = Instant::now();
            let mut input = inputs.generate(&gl);
            let frame = source.frame_at(player.time);
            gui.update(
                &mut input.events,
                input.accumulated_time,
                input.viewport,
                input.device_pixel_ratio,
                |ui| {
                    hud(
                        ui.ctx(),
                        &frame,
                        None,
                        false,
                        matches!(hands.mode, CameraMode::Orbit(_)),
                    );
                    player.timeline(ui);
                },
            );
            for e in &input.events {
                if let Event::KeyPress {
                    kind,
                    handled: false,
                    ..
                } = e
                    && player.key(*kind)
                {
                    continue;
                }
                // camera only: the recording drives the tools
                hands.handle(
                    e,
                    &frame,
                    input.viewport.height as f64,
                    input.device_pixel_ratio as f64,
                    &mut ignored,
                );
                ignored.clear();
            }
            let screen = input.screen();
            renderer.draw(
                &screen,
                input.viewport,
                &frame,
                &hands.view(&frame),
                DrawOptions {
                    wireframe: false,
                    active_tool: None,
                },
            );
            if let Err(e) = screen.write(|| gui.render()) {
                tracing::warn!("HUD: {e}");
            }
            if let Err(e) = gl.swap_buffers() {
                tracing::warn!("swap buffers: {e}");
            }
        }
        _ => {}
    });
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn player_plays_pauses_at_the_end_scrubs_and_changes_speed() {
        let mut p = Player::new((1.0, 5.0));
        assert!(p.playing);
        p.advance(1.5);
        assert_eq!(p.time, 2.5);
        p.change_speed(true);
        assert_eq!(p.speed, 2.0);
        p.advance(10.0);
        assert_eq!(p.time, 5.0);
        assert!(!p.playing, "pauses at the end");
        p.toggle();
        assert!(p.playing && p.time == 1.0, "play from the end restarts");
        p.toggle();
        p.advance(1.0);
        assert_eq!(p.time, 1.0, "paused: time stands");
        p.seek(-3.0);
        assert_eq!(p.time, 1.0);
        p.seek(f64::NAN);
        assert_eq!(p.time, 1.0);
        assert!(p.key(Key::ArrowRight));
        assert_eq!(p.time, 2.0);
        for _ in 0..20 {
            p.change_speed(false);
        }
        assert_eq!(p.speed, SPEEDS[0]);
        for _ in 0..20 {
            p.change_speed(true);
        }
        assert_eq!(p.speed, SPEEDS[SPEEDS.len() - 1]);
        assert!(!p.key(Key::Q));
        let empty = Player::new((3.0, 1.0));
        assert_eq!(empty.span, (3.0, 3.0));
    }
}
