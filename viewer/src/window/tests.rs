use std::sync::Arc;

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use three_d::{Event, Key, Modifiers, MouseButton, PhysicalPoint};

use super::*;
use crate::frame::{CameraPort, HudInfo, Segment, SurfaceTopology, ToolView};
use sim_core::sim_scene::ToolKind;

fn tool(name: &str, at: Vector3<f64>, site: Option<&str>) -> ToolView {
    ToolView {
        name: name.into(),
        kind: ToolKind::Forceps,
        pose: Isometry3::from_parts(Translation3::from(at), UnitQuaternion::identity()),
        jaw: 0.6,
        radius: 0.0025,
        parts: vec![],
        shaft: Segment { a: at, b: at },
        force: Vector3::zeros(),
        grasping: false,
        site: site.map(str::to_string),
    }
}

fn frame() -> ViewFrame {
    ViewFrame {
        topology: Arc::new(SurfaceTopology {
            triangles: vec![],
            vertex_tissue: vec![],
        }),
        positions: vec![],
        vessels: vec![],
        clips: vec![],
        lattice: None,
        tools: vec![
            tool("forceps", Vector3::new(0.04, -0.1, -0.04), None),
            tool("remote", Vector3::new(0.0, -0.1, -0.04), Some("B")),
            tool("probe", Vector3::new(0.03, 0.0, -0.05), None),
        ],
        guide: vec![],
        forces: vec![],
        hud: HudInfo::default(),
        port: CameraPort {
            position: Vector3::new(-0.03, -0.22, -0.1),
            target: Vector3::new(0.02, -0.03, -0.02),
            fov_deg: 55.0,
        },
    }
}

fn drag(button: MouseButton, dx: f32, dy: f32) -> Event {
    Event::MouseMotion {
        button: Some(button),
        delta: (dx, dy),
        position: PhysicalPoint { x: 100.0, y: 100.0 },
        modifiers: Modifiers::default(),
        handled: false,
    }
}

fn key(kind: Key) -> Event {
    Event::KeyPress {
        kind,
        modifiers: Modifiers::default(),
        handled: false,
    }
}

#[test]
fn left_drag_moves_the_active_tool_in_the_view_plane() {
    let f = frame();
    let mut hands = Hands::default();
    let mut out = Vec::new();
    let start = f.tools[0].pose.translation.vector;
    hands.handle(
        &drag(MouseButton::Left, 30.0, -12.0),
        &f,
        720.0,
        1.0,
        &mut out,
    );
    hands.handle(
        &drag(MouseButton::Left, 10.0, 2.0),
        &f,
        720.0,
        1.0,
        &mut out,
    );
    let view = camera::laparoscope(&f.port);
    // two drags add up to one of (40, -10) pixels (the plane's scale is set by the
    // unchanged depth)
    let expected = camera::drag_in_view_plane(&view, &start, 40.0, -10.0, 720.0);
    match out.last() {
        Some(ToolCommand::MoveTo(p)) => assert!((p - expected).norm() < 1e-12, "{p} vs {expected}"),
        other => panic!("expected a move, got {other:?}"),
    }
    assert_eq!(out.len(), 2);
    // a handled event (egui took it) does nothing
    let mut handled = drag(MouseButton::Left, 50.0, 0.0);
    if let Event::MouseMotion { handled: h, .. } = &mut handled {
        *h = true;
    }
    hands.handle(&handled, &f, 720.0, 1.0, &mut out);
    assert_eq!(out.len(), 2);
}

#[test]
fn keys_close_jaws_and_cycle_local_tools() {
    let f = frame();
    let mut hands = Hands::default();
    let mut out = Vec::new();
    hands.handle(&key(Key::Space), &f, 720.0, 1.0, &mut out);
    hands.handle(&key(Key::Space), &f, 720.0, 1.0, &mut out);
    assert_eq!(out, [ToolCommand::Jaw(true), ToolCommand::Jaw(false)]);
    out.clear();
    hands.handle(&key(Key::T), &f, 720.0, 1.0, &mut out);
    // the remote tool (index 1) is skipped: the hands only hold local tools
    assert_eq!(hands.active_tool, Some(2));
    hands.handle(&key(Key::T), &f, 720.0, 1.0, &mut out);
    assert_eq!(hands.active_tool, Some(0));
    assert_eq!(out, [ToolCommand::NextTool, ToolCommand::NextTool]);
}

#[test]
fn right_drag_orbits_at_constant_distance_and_c_returns_to_the_laparoscope() {
    let f = frame();
    let mut hands = Hands::default();
    let mut out = Vec::new();
    let lap = camera::laparoscope(&f.port);
    hands.handle(
        &drag(MouseButton::Right, 50.0, 20.0),
        &f,
        720.0,
        1.0,
        &mut out,
    );
    assert!(out.is_empty(), "the camera button does not move the tool");
    let v = hands.view(&f);
    assert!(matches!(hands.mode, CameraMode::Orbit(_)));
    assert!((v.distance() - lap.distance()).abs() < 1e-12);
    assert!((v.eye - lap.eye).norm() > 1e-3, "the camera moved");
    hands.handle(&key(Key::C), &f, 720.0, 1.0, &mut out);
    assert_eq!(hands.view(&f), lap);
}

#[test]
fn the_wheel_pushes_the_tool_along_the_view() {
    let f = frame();
    let mut hands = Hands::default();
    let mut out = Vec::new();
    let start = f.tools[0].pose.translation.vector;
    let wheel = Event::MouseWheel {
        delta: (0.0, 48.0), // two notches
        position: PhysicalPoint { x: 10.0, y: 10.0 },
        modifiers: Modifiers::default(),
        handled: false,
    };
    hands.handle(&wheel, &f, 720.0, 1.0, &mut out);
    let view = camera::laparoscope(&f.port);
    let expected = camera::push_along_view(&view, &start, 2.0);
    assert_eq!(out, [ToolCommand::MoveTo(expected)]);
}
