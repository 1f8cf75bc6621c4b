use super::*;
use three_d::{Camera, Viewport, radians, vec3};

fn port() -> CameraPort {
    CameraPort {
        position: V3::new(-0.02, -0.2, -0.09),
        target: V3::new(0.025, -0.03, -0.025),
        fov_deg: 50.0,
    }
}

/// three-d's own camera (independent code: matrices in f32) for the same view.
fn three_d_camera(v: &View, w: u32, h: u32) -> Camera {
    let f = |p: V3| vec3(p.x as f32, p.y as f32, p.z as f32);
    Camera::new_perspective(
        Viewport::new_at_origo(w, h),
        f(v.eye),
        f(v.target),
        f(v.up),
        radians(v.fov_y as f32),
        0.001,
        10.0,
    )
}

#[test]
fn laparoscope_sits_at_the_port_and_looks_at_the_target() {
    let v = laparoscope(&port());
    assert_eq!(v.eye, port().position);
    let expected = (port().target - port().position).normalize();
    assert!((v.forward() - expected).norm() < 1e-12);
    // the target projects to the centre of the image (three-d's projection)
    let cam = three_d_camera(&v, 640, 480);
    let t = port().target;
    let px = cam.pixel_at_position(vec3(t.x as f32, t.y as f32, t.z as f32));
    assert!(
        (px.x - 320.0).abs() < 0.01 && (px.y - 240.0).abs() < 0.01,
        "{px:?}"
    );
    // the image's up vector has a positive world-z component (the horizon is level)
    assert!(v.image_up().z > 0.0);
    assert!(v.right().z.abs() < 1e-12);
}

#[test]
fn orbit_keeps_its_distance_and_target() {
    let start = laparoscope(&port());
    let mut orbit = Orbit::from_view(&start);
    // starting the orbit does not move the camera
    assert!((orbit.view().eye - start.eye).norm() < 1e-12);
    let d0 = start.distance();
    for (da, de) in [(0.3, 0.1), (-1.2, 0.5), (2.0, -2.0), (0.0, 3.0)] {
        orbit.rotate(da, de);
        let v = orbit.view();
        assert!(((v.eye - port().target).norm() - d0).abs() < 1e-12);
        assert_eq!(v.target, port().target);
        assert!(v.forward().z.abs() <= (85f64).to_radians().sin() + 1e-12);
    }
    orbit.zoom(0.5);
    assert!(((orbit.view().eye - port().target).norm() - d0 * 0.5).abs() < 1e-12);
}

#[test]
fn a_drag_of_n_pixels_moves_the_point_n_pixels_on_screen() {
    let v = laparoscope(&port());
    let (w, h) = (1280u32, 720u32);
    let cam = three_d_camera(&v, w, h);
    let f = |p: V3| vec3(p.x as f32, p.y as f32, p.z as f32);
    let tool = V3::new(0.04, -0.09, -0.035);
    let before = cam.pixel_at_position(f(tool));
    for (dx, dy) in [(40.0, 0.0), (0.0, 25.0), (-13.0, 31.0)] {
        let moved = drag_in_view_plane(&v, &tool, dx, dy, h as f64);
        // the depth is unchanged: the motion is in the view plane
        assert!((v.depth_of(&moved) - v.depth_of(&tool)).abs() < 1e-12);
        let after = cam.pixel_at_position(f(moved));
        // window y grows downwards, three-d's pixel y upwards; f32 projection: 0.05 px
        assert!(
            ((after.x - before.x) as f64 - dx).abs() < 0.05,
            "dx {dx}: {before:?} -> {after:?}"
        );
        assert!(
            ((before.y - after.y) as f64 - dy).abs() < 0.05,
            "dy {dy}: {before:?} -> {after:?}"
        );
    }
    // expected world distance: 2 d tan(fov/2) / h per pixel
    let d = (tool - v.eye).dot(&v.forward());
    let moved = drag_in_view_plane(&v, &tool, 100.0, 0.0, h as f64);
    let expected = 100.0 * 2.0 * d * (25f64.to_radians()).tan() / h as f64;
    assert!(((moved - tool).norm() - expected).abs() < 1e-12);
}

#[test]
fn the_wheel_moves_along_the_view_direction() {
    let v = laparoscope(&port());
    let tool = V3::new(0.04, -0.09, -0.035);
    let pushed = push_along_view(&v, &tool, 3.0);
    assert!((v.depth_of(&pushed) - v.depth_of(&tool) - 3.0 * WHEEL_DEPTH_STEP).abs() < 1e-12);
    let cam = three_d_camera(&v, 800, 600);
    let f = |p: V3| vec3(p.x as f32, p.y as f32, p.z as f32);
    // pushing along the ray through the target keeps the target's pixel
    let t = push_along_view(&v, &port().target, 2.0);
    let px = cam.pixel_at_position(f(t));
    assert!((px.x - 400.0).abs() < 0.01 && (px.y - 300.0).abs() < 0.01);
}

#[test]
fn projection_agrees_with_three_d() {
    let v = laparoscope(&port());
    let (w, h) = (1280u32, 720u32);
    let cam = three_d_camera(&v, w, h);
    let f = |p: V3| vec3(p.x as f32, p.y as f32, p.z as f32);
    for p in [
        V3::new(0.04, -0.09, -0.035),
        V3::new(0.0, -0.05, 0.01),
        port().target,
    ] {
        let (x, y) = v.project(&p, w as f64, h as f64).unwrap();
        let px = cam.pixel_at_position(f(p));
        // three-d's pixel y grows upwards; f32 projection: 0.05 px
        assert!((x - px.x as f64).abs() < 0.05, "{p}: {x} vs {px:?}");
        assert!(
            (y - (h as f64 - px.y as f64)).abs() < 0.05,
            "{p}: {y} vs {px:?}"
        );
    }
    // behind the camera: no pixel
    let behind = v.eye - v.forward() * 0.1;
    assert!(v.project(&behind, w as f64, h as f64).is_none());
}
