//! The heads-up display (egui): site, role, times and network figures, region owners,
//! the active tool's force as a bar, key help, and the instructor's session controls.

use three_d::egui;

use crate::camera::View;
use crate::frame::{Role, SessionCommand, ViewFrame};
use crate::render::{level_colour, tissue_colour};

/// Force at which the force bar is full (N).
pub const FORCE_BAR_FULL: f64 = 5.0;

fn opt(v: Option<f64>, f: impl Fn(f64) -> String) -> String {
    v.map(f).unwrap_or_else(|| "–".to_string())
}

fn swatch(ui: &mut egui::Ui, c: [u8; 3], label: &str) {
    ui.horizontal(|ui| {
        let (rect, _) = ui.allocate_exact_size(egui::vec2(12.0, 12.0), egui::Sense::hover());
        ui.painter()
            .rect_filled(rect, 2.0, egui::Color32::from_rgb(c[0], c[1], c[2]));
        ui.label(label);
    });
}

/// Lays out the HUD for `frame`; returns the session commands the user clicked (only
/// ever non-empty for the instructor role).
pub fn hud(
    ctx: &egui::Context,
    frame: &ViewFrame,
    active_tool: Option<usize>,
    wireframe: bool,
    orbit: bool,
) -> Vec<SessionCommand> {
    let h = &frame.hud;
    let mut out = Vec::new();
    egui::Window::new("cosurg")
        .default_pos(egui::pos2(8.0, 8.0))
        .resizable(false)
        .collapsible(true)
        .show(ctx, |ui| {
            egui::Grid::new("hud-grid").num_columns(2).show(ui, |ui| {
                let mut row = |k: &str, v: String| {
                    ui.label(k);
                    ui.monospace(v);
                    ui.end_row();
                };
                row("site", h.site.clone());
                row("role", h.role.as_str().to_string());
                row("sim time", format!("{:.3} s", h.sim_time));
                row("lag", opt(h.lag, |v| format!("{:.0} ms", v * 1e3)));
                row("step p99", opt(h.step_p99_ms, |v| format!("{v:.2} ms")));
                row("keyframes/s", opt(h.keyframes_per_s, |v| format!("{v:.1}")));
                row(
                    "bytes/s",
                    opt(h.bytes_per_s, |v| format!("{:.1} kB/s", v / 1e3)),
                );
                row(
                    "divergence",
                    opt(h.divergence, |v| format!("{:.2} mm", v * 1e3)),
                );
                row(
                    "teaching",
                    if h.teaching { "on" } else { "off" }.to_string(),
                );
                row(
                    "camera",
                    if orbit { "orbit" } else { "laparoscope" }.to_string(),
                );
            });
            if let Some(n) = &h.notice {
                ui.colored_label(egui::Color32::from_rgb(255, 200, 90), n);
            }
            if !h.region_owners.is_empty() {
                ui.separator();
                ui.label("region owners");
                for r in &h.region_owners {
                    ui.monospace(format!("{}: {}", r.region, r.site));
                }
            }
            if let Some(tool) = active_tool.and_then(|i| frame.tools.get(i)) {
                ui.separator();
                let f = tool.force.norm();
                ui.label(format!(
                    "tool {} — jaw {:.0}°{}",
                    tool.name,
                    tool.jaw.to_degrees(),
                    if tool.grasping { ", grasping" } else { "" }
                ));
                ui.add(
                    egui::ProgressBar::new((f / FORCE_BAR_FULL).clamp(0.0, 1.0) as f32)
                        .text(format!("force {f:.2} N")),
                );
            }
            ui.separator();
            ui.horizontal(|ui| {
                swatch(ui, tissue_colour(crate::TissueKind::Parenchyma), "liver");
                swatch(
                    ui,
                    tissue_colour(crate::TissueKind::Gallbladder),
                    "gallbladder",
                );
                swatch(ui, tissue_colour(crate::TissueKind::Vessel), "vessels");
            });
            if wireframe {
                ui.horizontal(|ui| {
                    for level in 0..5u8 {
                        swatch(ui, level_colour(level), &format!("L{level}"));
                    }
                });
            }
            ui.small("drag: move tool · wheel: depth · space: jaws · T: next tool");
            ui.small("right drag: orbit · C: laparoscope/orbit · W: lattice");
            if h.role == Role::Instructor {
                ui.separator();
                ui.horizontal(|ui| {
                    if ui.button("reset scene").clicked() {
                        out.push(SessionCommand::Reset);
                    }
                    let (label, cmd) = if h.teaching {
                        ("stop teaching", SessionCommand::TeachingStop)
                    } else {
                        ("start teaching", SessionCommand::TeachingStart)
                    };
                    if ui.button(label).clicked() {
                        out.push(cmd);
                    }
                });
            }
        });
    out
}

/// Colour of the remote tools' labels (as their ghosts).
const LABEL_COLOUR: egui::Color32 = egui::Color32::from_rgb(190, 215, 255);

/// Writes the name of the site that moves each remote tool beside its tip (below the HUD
/// window). `size_px`: viewport in physical pixels; `dpr`: physical pixels per point.
pub fn tool_labels(
    ctx: &egui::Context,
    frame: &ViewFrame,
    view: &View,
    size_px: (f64, f64),
    dpr: f64,
) {
    let painter = ctx.layer_painter(egui::LayerId::new(
        egui::Order::Background,
        egui::Id::new("tool-labels"),
    ));
    for tool in &frame.tools {
        let Some(site) = &tool.site else { continue };
        let Some((x, y)) = view.project(&tool.shaft.a, size_px.0, size_px.1) else {
            continue;
        };
        let at = egui::pos2((x / dpr) as f32 + 8.0, (y / dpr) as f32 - 4.0);
        painter.text(
            at,
            egui::Align2::LEFT_BOTTOM,
            format!("{site}: {}", tool.name),
            egui::FontId::proportional(15.0),
            LABEL_COLOUR,
        );
    }
}
