//! Camera maths (laparoscope and orbit camera) and the mapping of mouse motion to tool
//! motion. Pure nalgebra, no graphics: unit tested against independent projections.
//!
//! Units: m and radians unless a name says degrees; pixels are physical pixels with y
//! growing downwards (as in window events).

use nalgebra::Vector3;

use crate::frame::CameraPort;

type V3 = Vector3<f64>;

/// A pinhole camera: eye, looked-at point, world up hint and vertical field of view.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct View {
    /// Camera position (m).
    pub eye: V3,
    /// Point looked at (m).
    pub target: V3,
    /// Up hint (world +z unless looking straight along it).
    pub up: V3,
    /// Vertical field of view (rad).
    pub fov_y: f64,
}

impl View {
    /// Unit viewing direction.
    pub fn forward(&self) -> V3 {
        (self.target - self.eye).normalize()
    }
    /// Unit right vector of the image plane.
    pub fn right(&self) -> V3 {
        let f = self.forward();
        let r = f.cross(&self.up);
        if r.norm() < 1e-9 {
            // looking along the up hint: any perpendicular will do
            f.cross(&V3::y()).normalize()
        } else {
            r.normalize()
        }
    }
    /// Unit up vector of the image plane.
    pub fn image_up(&self) -> V3 {
        self.right().cross(&self.forward())
    }
    /// Distance from the eye to the target (m).
    pub fn distance(&self) -> f64 {
        (self.target - self.eye).norm()
    }
    /// Depth of a point along the viewing direction (m).
    pub fn depth_of(&self, p: &V3) -> f64 {
        (p - self.eye).dot(&self.forward())
    }
    /// World length of one pixel at `depth` (m) for a viewport `height_px` tall.
    pub fn metres_per_pixel(&self, depth: f64, height_px: f64) -> f64 {
        2.0 * depth * (self.fov_y / 2.0).tan() / height_px
    }
    /// Pixel position `(x right, y down)` of a world point in a viewport of
    /// `width_px` × `height_px` (square pixels), or `None` behind the camera.
    pub fn project(&self, p: &V3, width_px: f64, height_px: f64) -> Option<(f64, f64)> {
        let depth = self.depth_of(p);
        if depth <= 1e-6 {
            return None;
        }
        let s = self.metres_per_pixel(depth, height_px);
        let d = p - self.eye;
        Some((
            0.5 * width_px + d.dot(&self.right()) / s,
            0.5 * height_px - d.dot(&self.image_up()) / s,
        ))
    }
}

/// The laparoscope: sits at the port and looks at the port's target.
pub fn laparoscope(port: &CameraPort) -> View {
    View {
        eye: port.position,
        target: port.target,
        up: V3::z(),
        fov_y: port.fov_deg.to_radians(),
    }
}

/// A free orbit camera around a target: spherical coordinates with +z up.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Orbit {
    /// Centre of the orbit (m).
    pub target: V3,
    /// Distance from the target (m, > 0).
    pub distance: f64,
    /// Angle about +z from +x (rad).
    pub azimuth: f64,
    /// Angle above the xy plane (rad), kept inside ±85°.
    pub elevation: f64,
    /// Vertical field of view (rad).
    pub fov_y: f64,
}

const MAX_ELEVATION: f64 = 85.0 * std::f64::consts::PI / 180.0;

impl Orbit {
    /// The orbit camera that starts exactly where `view` is.
    pub fn from_view(view: &View) -> Orbit {
        let d = view.eye - view.target;
        let distance = d.norm();
        Orbit {
            target: view.target,
            distance,
            azimuth: d.y.atan2(d.x),
            elevation: (d.z / distance)
                .clamp(-1.0, 1.0)
                .asin()
                .clamp(-MAX_ELEVATION, MAX_ELEVATION),
            fov_y: view.fov_y,
        }
    }
    /// Rotates by `d_azimuth` and `d_elevation` (rad); the distance does not change.
    pub fn rotate(&mut self, d_azimuth: f64, d_elevation: f64) {
        self.azimuth += d_azimuth;
        self.elevation = (self.elevation + d_elevation).clamp(-MAX_ELEVATION, MAX_ELEVATION);
    }
    /// Multiplies the distance by `factor` (> 0), keeping it above 1 cm.
    pub fn zoom(&mut self, factor: f64) {
        self.distance = (self.distance * factor).max(0.01);
    }
    /// The camera.
    pub fn view(&self) -> View {
        let (sa, ca) = self.azimuth.sin_cos();
        let (se, ce) = self.elevation.sin_cos();
        View {
            eye: self.target + self.distance * V3::new(ce * ca, ce * sa, se),
            target: self.target,
            up: V3::z(),
            fov_y: self.fov_y,
        }
    }
}

/// Which camera the window uses.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum CameraMode {
    /// The scene's laparoscope (default), looking in from its port.
    Laparoscope,
    /// Free orbit camera (the `C` key toggles).
    Orbit(Orbit),
}

/// New position of a point dragged by `(dx, dy)` pixels (x right, y down) in a viewport
/// `height_px` tall: the point moves in the plane through it parallel to the image, so
/// that it stays under the cursor.
pub fn drag_in_view_plane(view: &View, point: &V3, dx: f64, dy: f64, height_px: f64) -> V3 {
    let depth = view.depth_of(point).max(1e-4);
    let s = view.metres_per_pixel(depth, height_px);
    point + view.right() * (dx * s) - view.image_up() * (dy * s)
}

/// Depth change per wheel notch (m).
pub const WHEEL_DEPTH_STEP: f64 = 0.004;

/// New position of a point pushed along the viewing direction by `notches` of the wheel
/// (positive = away from the camera).
pub fn push_along_view(view: &View, point: &V3, notches: f64) -> V3 {
    point + view.forward() * (notches * WHEEL_DEPTH_STEP)
}

#[cfg(test)]
mod tests;
