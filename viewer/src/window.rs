//! The window (winit + three-d + egui) and off-screen screenshots.
//!
//! [`run_window`] runs on the thread that calls it (any thread: the event loop is
//! created with winit's any-thread option), draws the latest frame of a [`ViewSlot`] at
//! up to [`WindowOptions::max_fps`] and sends [`ViewerCommand`]s. It never touches the
//! simulation: the only shared state is the slot's pointer.

use std::path::Path;
use std::sync::mpsc::Sender;
use std::time::{Duration, Instant};

use nalgebra::Vector3;
use three_d::{
    Context, DepthTexture2D, Event, GUI, Interpolation, Key, MouseButton, RenderTarget, Texture2D,
    Viewport, WindowedContext, Wrapping,
};
use winit::event::{Event as WinitEvent, WindowEvent};
use winit::event_loop::{ControlFlow, EventLoop, EventLoopBuilder};
use winit::platform::run_return::EventLoopExtRunReturn;

use crate::camera::{self, CameraMode, Orbit, View};
use crate::frame::{Role, ToolCommand, ViewFrame, ViewSlot, ViewerCommand};
use crate::hud::{hud, tool_labels};
use crate::render::{DrawOptions, Renderer};

/// Errors of the window and of screenshots.
#[derive(Debug, thiserror::Error)]
pub enum ViewerError {
    /// No display or no OpenGL context.
    #[error(
        "cannot open a window: {0} (is DISPLAY set and an X server running? Under CI run \
         Xvfb, see DEVELOPERS.md)"
    )]
    Window(String),
    /// Writing the PNG failed.
    #[error("cannot write {path}: {message}")]
    Png {
        /// The file.
        path: String,
        /// What went wrong.
        message: String,
    },
}

/// Window settings.
#[derive(Clone, Debug)]
pub struct WindowOptions {
    /// Title bar text.
    pub title: String,
    /// Initial inner size (pixels).
    pub size: (u32, u32),
    /// Frame-rate cap (the render thread sleeps in between, leaving the cores to the
    /// simulation). The default, 32, is just above the 30 fps the window must reach:
    /// under a software renderer the window would otherwise draw as fast as it can
    /// (36–39 fps at 1280×720) and take a whole core: the simulation's step p99 was then
    /// 4.0 ms (median of four runs) against 2.8 ms capped (docs/RESULTS.md § The window).
    pub max_fps: f64,
    /// Wait for every frame to be rendered before the next (`glFinish`), so that frame
    /// times measure the rendering (benchmarks).
    pub finish_frames: bool,
    /// How much lower the window thread's priority is than the process's (Linux nice
    /// increment, added to the thread's nice value at start, at most 19; 0 = unchanged).
    /// Relative, so that a site started under `nice -n 19` does not get a window thread
    /// of *higher* priority than its simulation (as an absolute value did). Set before the OpenGL
    /// context exists, so that a software renderer's worker threads (Mesa llvmpipe)
    /// inherit it: on a machine with few cores the scheduler then prefers the simulation
    /// and haptic threads to the window's.
    pub nice: i32,
}

impl Default for WindowOptions {
    fn default() -> Self {
        WindowOptions {
            title: "cosurg".into(),
            size: (1280, 720),
            max_fps: 32.0,
            finish_frames: false,
            nice: 10,
        }
    }
}

/// A window of `options.title` and `options.size` with a GL context on it, without
/// multisampling: under Mesa's software renderer 4× multisampling cost more than half of
/// every frame (12.9 against 31 fps at 1280×720, docs/RESULTS.md § The window).
pub(crate) fn open_window(
    event_loop: &EventLoop<()>,
    options: &WindowOptions,
) -> Result<(winit::window::Window, WindowedContext), ViewerError> {
    let window = winit::window::WindowBuilder::new()
        .with_title(&options.title)
        .with_inner_size(winit::dpi::LogicalSize::new(
            options.size.0 as f64,
            options.size.1 as f64,
        ))
        .build(event_loop)
        .map_err(|e| ViewerError::Window(e.to_string()))?;
    let gl = WindowedContext::from_winit_window(
        &window,
        three_d::SurfaceSettings {
            multisamples: 0,
            ..Default::default()
        },
    )
    .map_err(|e| ViewerError::Window(e.to_string()))?;
    Ok((window, gl))
}

pub(crate) fn event_loop() -> Result<EventLoop<()>, ViewerError> {
    let mut builder = EventLoopBuilder::new();
    {
        use winit::platform::x11::EventLoopBuilderExtX11;
        EventLoopBuilderExtX11::with_any_thread(&mut builder, true);
    }
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(move || builder.build())).map_err(|e| {
        let msg = e
            .downcast_ref::<String>()
            .cloned()
            .or_else(|| e.downcast_ref::<&str>().map(|s| s.to_string()))
            .unwrap_or_else(|| "winit could not connect to a display".into());
        ViewerError::Window(msg)
    })
}

/// Lowers the calling thread's scheduling priority by `nice` (Linux: nice values are per
/// thread and inherited by threads it creates). Fails soft: a warning.
fn lower_thread_priority(nice: i32) {
    if nice == 0 {
        return;
    }
    #[cfg(target_os = "linux")]
    {
        unsafe extern "C" {
            fn getpriority(which: i32, who: u32) -> i32;
            fn setpriority(which: i32, who: u32, prio: i32) -> i32;
        }
        const PRIO_PROCESS: i32 = 0;
        // SAFETY: plain libc calls without pointers; who = 0 is the calling thread. The
        // current value is -20..=19 (a -1 that is an error reads as nice -1: harmless).
        let current = unsafe { getpriority(PRIO_PROCESS, 0) };
        let nice = (current + nice).clamp(-20, 19);
        let r = unsafe { setpriority(PRIO_PROCESS, 0, nice) };
        if r != 0 {
            tracing::warn!(nice, "could not lower the window thread's priority");
        }
    }
}

/// What the user's hands do to the view and the local tool; fed with three-d events.
#[derive(Clone, Debug)]
pub struct Hands {
    /// Camera in use.
    pub mode: CameraMode,
    /// Show the lattice wireframe.
    pub wireframe: bool,
    /// Index (among the frame's tools) of the tool the hands drive.
    pub active_tool: Option<usize>,
    /// Where the active tool is being moved to (m).
    pub tool_target: Option<Vector3<f64>>,
    /// Jaws closed.
    pub jaw_closed: bool,
}

impl Default for Hands {
    fn default() -> Self {
        Hands {
            mode: CameraMode::Laparoscope,
            wireframe: false,
            active_tool: Some(0),
            tool_target: None,
            jaw_closed: false,
        }
    }
}

/// Orbit speed (rad per pixel of right-button drag).
const ORBIT_RAD_PER_PX: f64 = 0.006;

impl Hands {
    /// The camera for `frame`.
    pub fn view(&self, frame: &ViewFrame) -> View {
        match &self.mode {
            CameraMode::Laparoscope => camera::laparoscope(&frame.port),
            CameraMode::Orbit(o) => o.view(),
        }
    }

    fn local_tools(frame: &ViewFrame) -> Vec<usize> {
        (0..frame.tools.len())
            .filter(|&i| frame.tools[i].site.is_none())
            .collect()
    }

    /// Handles one event (unless egui handled it); `height_px` is the viewport height in
    /// physical pixels, `dpr` physical pixels per logical pixel.
    pub fn handle(
        &mut self,
        event: &Event,
        frame: &ViewFrame,
        height_px: f64,
        dpr: f64,
        out: &mut Vec<ToolCommand>,
    ) {
        let local = Self::local_tools(frame);
        if self.active_tool.is_some_and(|i| !local.contains(&i)) {
            self.active_tool = local.first().copied();
        }
        let view = self.view(frame);
        let current_tip = |s: &Self| {
            s.tool_target.or_else(|| {
                s.active_tool
                    .and_then(|i| frame.tools.get(i))
                    .map(|t| t.pose.translation.vector)
            })
        };
        match event {
            Event::MouseMotion {
                button: Some(MouseButton::Left),
                delta,
                handled: false,
                ..
            } => {
                if let Some(tip) = current_tip(self) {
                    let moved = camera::drag_in_view_plane(
                        &view,
                        &tip,
                        delta.0 as f64 * dpr,
                        delta.1 as f64 * dpr,
                        height_px,
                    );
                    self.tool_target = Some(moved);
                    out.push(ToolCommand::MoveTo(moved));
                }
            }
            Event::MouseMotion {
                button: Some(MouseButton::Right | MouseButton::Middle),
                delta,
                handled: false,
                ..
            } => {
                let mut orbit = match self.mode {
                    CameraMode::Orbit(o) => o,
                    CameraMode::Laparoscope => Orbit::from_view(&view),
                };
                orbit.rotate(
                    -delta.0 as f64 * ORBIT_RAD_PER_PX,
                    delta.1 as f64 * ORBIT_RAD_PER_PX,
                );
                self.mode = CameraMode::Orbit(orbit);
            }
            Event::MouseWheel {
                delta,
                handled: false,
                modifiers,
                ..
            } => {
                // three-d scales one wheel notch to 24 units
                let notches = delta.1 as f64 / 24.0;
                if modifiers.ctrl {
                    if let CameraMode::Orbit(o) = &mut self.mode {
                        o.zoom((-notches * 0.1).exp());
                    }
                } else if let Some(tip) = current_tip(self) {
                    let moved = camera::push_along_view(&view, &tip, notches);
                    self.tool_target = Some(moved);
                    out.push(ToolCommand::MoveTo(moved));
                }
            }
            Event::KeyPress {
                kind,
                handled: false,
                ..
            } => match kind {
                Key::Space | Key::J => {
                    self.jaw_closed = !self.jaw_closed;
                    out.push(ToolCommand::Jaw(self.jaw_closed));
                }
                Key::T | Key::Tab if !local.is_empty() => {
                    let pos = self
                        .active_tool
                        .and_then(|a| local.iter().position(|&i| i == a))
                        .map(|p| (p + 1) % local.len())
                        .unwrap_or(0);
                    self.active_tool = Some(local[pos]);
                    self.tool_target = None;
                    self.jaw_closed = false;
                    out.push(ToolCommand::NextTool);
                }
                Key::C => {
                    self.mode = match self.mode {
                        CameraMode::Laparoscope => CameraMode::Orbit(Orbit::from_view(&view)),
                        CameraMode::Orbit(_) => CameraMode::Laparoscope,
                    };
                }
                Key::W => self.wireframe = !self.wireframe,
                _ => {}
            },
            _ => {}
        }
    }
}

/// Opens a window and shows the slot's latest frame until the user closes it; sends the
/// user's commands (and [`ViewerCommand::Closed`] at the end), until the user closes it
/// or the publisher calls [`ViewSlot::close`]. Blocks the calling thread.
pub fn run_window(
    slot: ViewSlot,
    commands: Sender<ViewerCommand>,
    options: WindowOptions,
) -> Result<WindowStats, ViewerError> {
    let opened = Instant::now();
    let mut stats = WindowStats::default();
    lower_thread_priority(options.nice);
    let mut event_loop = event_loop()?;
    let (window, gl) = open_window(&event_loop, &options)?;
    let context: Context = (*gl).clone();
    let renderer = Renderer::new(&context);
    let mut gui = GUI::new(&context);
    let mut inputs = three_d::FrameInputGenerator::from_winit_window(&window);
    let mut hands = Hands::default();
    let frame_period = Duration::from_secs_f64(1.0 / options.max_fps.max(1.0));
    let mut next_frame = Instant::now();
    let mut tool_commands = Vec::new();
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
            if slot.is_closed() {
                *control_flow = ControlFlow::Exit;
            } else if Instant::now() >= next_frame {
                window.request_redraw();
            } else {
                *control_flow = ControlFlow::WaitUntil(next_frame);
            }
        }
        WinitEvent::RedrawRequested(_) => {
            let drawing = Instant::now();
            next_frame = drawing + frame_period;
            *control_flow = ControlFlow::WaitUntil(next_frame);
            let mut input = inputs.generate(&gl);
            let size_px = (input.viewport.width as f64, input.viewport.height as f64);
            let dpr = input.device_pixel_ratio as f64;
            let frame = slot.latest();
            // The site says which tool is in hand (its script, or an instrument exchange,
            // may change it): the HUD's tool line and the highlight follow it.
            if let Some(i) = in_hand(&frame) {
                hands.active_tool = Some(i);
            }
            let mut session = Vec::new();
            gui.update(
                &mut input.events,
                input.accumulated_time,
                input.viewport,
                input.device_pixel_ratio,
                |ui| {
                    session = hud(
                        ui.ctx(),
                        &frame,
                        hands.active_tool,
                        hands.wireframe,
                        matches!(hands.mode, CameraMode::Orbit(_)),
                    );
                    tool_labels(ui.ctx(), &frame, &hands.view(&frame), size_px, dpr);
                },
            );
            for e in &input.events {
                hands.handle(
                    e,
                    &frame,
                    input.viewport.height as f64,
                    input.device_pixel_ratio as f64,
                    &mut tool_commands,
                );
            }
            slot.set_wants_lattice(hands.wireframe);
            let mut sent_ok = true;
            for c in tool_commands.drain(..) {
                sent_ok &= commands.send(ViewerCommand::Tool(c)).is_ok();
            }
            if frame.hud.role == Role::Instructor {
                for c in session {
                    sent_ok &= commands.send(ViewerCommand::Session(c)).is_ok();
                }
            }
            if !sent_ok {
                // the simulation has gone: nothing left to show
                *control_flow = ControlFlow::Exit;
            }
            let screen = input.screen();
            renderer.draw(
                &screen,
                input.viewport,
                &frame,
                &hands.view(&frame),
                DrawOptions {
                    wireframe: hands.wireframe,
                    active_tool: hands.active_tool,
                },
            );
            if let Err(e) = screen.write(|| gui.render()) {
                tracing::warn!("HUD: {e}");
            }
            if let Err(e) = gl.swap_buffers() {
                tracing::warn!("swap buffers: {e}");
            }
            if options.finish_frames {
                // the frame's GPU work is done (llvmpipe renders on the CPU: this is
                // what a frame costs)
                // SAFETY: glFinish on the current context of this thread, no arguments
                unsafe { three_d::context::HasContext::finish(&**context) };
            }
            stats.frame_ms.push(drawing.elapsed().as_secs_f64() * 1e3);
        }
        _ => {}
    });
    let _ = commands.send(ViewerCommand::Closed);
    stats.seconds = opened.elapsed().as_secs_f64();
    Ok(stats)
}

/// What a window did: frames drawn and their cost.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct WindowStats {
    /// Wall time the window was open (s).
    pub seconds: f64,
    /// Wall time of every frame: HUD, 3D drawing and buffer swap (ms; with
    /// [`WindowOptions::finish_frames`] until the frame is rendered).
    pub frame_ms: Vec<f64>,
}

impl WindowStats {
    /// Frames shown per second of the window's life.
    pub fn fps(&self) -> f64 {
        self.frame_ms.len() as f64 / self.seconds.max(1e-9)
    }
}

/// An RGBA8 picture, rows from the top.
#[derive(Clone, Debug, PartialEq)]
pub struct Picture {
    /// Width (pixels).
    pub width: u32,
    /// Height (pixels).
    pub height: u32,
    /// `width * height * 4` bytes, row-major from the top-left.
    pub rgba: Vec<u8>,
}

/// Renders `frame` from its laparoscope (with the HUD) off-screen at `size` pixels. Needs
/// a display for the OpenGL context (an invisible window is created); under CI use Xvfb.
pub fn render_picture(frame: &ViewFrame, size: (u32, u32)) -> Result<Picture, ViewerError> {
    let event_loop = event_loop()?;
    let window = winit::window::WindowBuilder::new()
        .with_title("cosurg screenshot")
        .with_visible(false)
        .with_inner_size(winit::dpi::PhysicalSize::new(size.0, size.1))
        .build(&event_loop)
        .map_err(|e| ViewerError::Window(e.to_string()))?;
    let gl = WindowedContext::from_winit_window(
        &window,
        three_d::SurfaceSettings {
            multisamples: 0,
            ..Default::default()
        },
    )
    .map_err(|e| ViewerError::Window(e.to_string()))?;
    let context: Context = (*gl).clone();
    let (w, h) = size;
    let color = Texture2D::new_empty::<[u8; 4]>(
        &context,
        w,
        h,
        Interpolation::Nearest,
        Interpolation::Nearest,
        None,
        Wrapping::ClampToEdge,
        Wrapping::ClampToEdge,
    );
    let depth =
        DepthTexture2D::new::<f32>(&context, w, h, Wrapping::ClampToEdge, Wrapping::ClampToEdge);
    let viewport = Viewport::new_at_origo(w, h);
    let renderer = Renderer::new(&context);
    // the hands hold the site's tool in hand, else the first of its own tools (remote
    // tools are not theirs)
    let hands = Hands {
        active_tool: in_hand(frame).or_else(|| frame.tools.iter().position(|t| t.site.is_none())),
        ..Hands::default()
    };
    let target = RenderTarget::new(color.as_color_target(None), depth.as_depth_target());
    let mut gui = GUI::new(&context);
    // a single picture: no fade-in (at a frozen time it would leave the HUD half
    // transparent and its text dim)
    gui.context().all_styles_mut(|s| s.animation_time = 0.0);
    // egui lays out on its first pass and paints windows on the second. three-d's
    // `GUI::update` keeps only the latest pass's output, and the first pass's output
    // holds the font atlas as a whole texture while later ones hold only partial
    // updates to it: each pass is rendered (uploading its textures), else egui_glow
    // patches a font texture it never created (GL_INVALID_OPERATION, no text). The 3D
    // scene is drawn (clearing the target) after the first pass and before the second.
    for pass in 0..2 {
        gui.update(&mut [], 0.0, viewport, 1.0, |ui| {
            hud(
                ui.ctx(),
                frame,
                hands.active_tool,
                frame.lattice.is_some(),
                false,
            );
            tool_labels(
                ui.ctx(),
                frame,
                &hands.view(frame),
                (w as f64, h as f64),
                1.0,
            );
        });
        if pass == 1 {
            renderer.draw(
                &target,
                viewport,
                frame,
                &hands.view(frame),
                DrawOptions {
                    wireframe: frame.lattice.is_some(),
                    active_tool: hands.active_tool,
                },
            );
        }
        target
            .write(|| gui.render())
            .map_err(|e| ViewerError::Window(e.to_string()))?;
    }
    // rows from the top already: three-d's `read_color` flips OpenGL's bottom-up rows
    let pixels: Vec<[u8; 4]> = target.read_color();
    drop(target);
    let mut rgba = Vec::with_capacity(pixels.len() * 4);
    for p in &pixels {
        rgba.extend_from_slice(&[p[0], p[1], p[2], 255]);
    }
    drop(window);
    Ok(Picture {
        width: w,
        height: h,
        rgba,
    })
}

/// Writes a picture as PNG.
pub fn write_png(picture: &Picture, path: &Path) -> Result<(), ViewerError> {
    let err = |m: String| ViewerError::Png {
        path: path.display().to_string(),
        message: m,
    };
    let file = std::fs::File::create(path).map_err(|e| err(e.to_string()))?;
    let mut enc = png::Encoder::new(std::io::BufWriter::new(file), picture.width, picture.height);
    enc.set_color(png::ColorType::Rgba);
    enc.set_depth(png::BitDepth::Eight);
    let mut w = enc.write_header().map_err(|e| err(e.to_string()))?;
    w.write_image_data(&picture.rgba)
        .map_err(|e| err(e.to_string()))?;
    Ok(())
}

/// Renders `frame` off-screen and writes it to `path` (PNG).
pub fn screenshot(
    frame: &ViewFrame,
    size: (u32, u32),
    path: &Path,
) -> Result<Picture, ViewerError> {
    let picture = render_picture(frame, size)?;
    write_png(&picture, path)?;
    Ok(picture)
}

#[cfg(test)]
mod tests;

/// Index of the tool the frame's site has in hand (its HUD's `active_tool`), if it is
/// one of the frame's tools.
fn in_hand(frame: &ViewFrame) -> Option<usize> {
    let name = frame.hud.active_tool.as_ref()?;
    frame.tools.iter().position(|t| &t.name == name)
}
