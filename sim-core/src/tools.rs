//! Rigid tools driven from outside (haptic device, script, remote site): pose, velocity
//! estimate, jaw angle, and the contact sample points placed once on their surface.
//!
//! Tool frame (as [`sim_scene::ToolSpec`]): the tip is at the origin, the shaft runs along
//! local +z. `radius` and `length` come from the spec:
//!
//! * **probe** — a rod of radius `r` over `0 ≤ z ≤ length`, closed by a hemisphere whose
//!   lowest point is the tip.
//! * **forceps** — two jaws hinged at `(0, 0, length)`, each a half rod of radius `r`
//!   (the `±y` halves) reaching down to the tip; closed (angle 0) they form one rod. An
//!   opening angle `a` turns jaw `±` by `±a/2` about the hinge's x axis. The forceps grasps
//!   while the angle is below [`GraspThresholds::close`] and lets go above
//!   [`GraspThresholds::open`] (hysteresis).
//! * **hook** — a thin rod (radius `r/2`) along the shaft down to the tip with a barb bent
//!   towards +x and back up (`(0,0,r/2) → (2r, 0, 2r)`).

use nalgebra::{Isometry3, Matrix3, Translation3, UnitQuaternion, Vector3};
use sim_scene::{ToolKind, ToolPose, ToolSpec};

type V3 = Vector3<f64>;

/// Jaw angles (rad) at which a forceps starts and stops grasping.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GraspThresholds {
    /// Grasp when the opening angle falls below this (rad).
    pub close: f64,
    /// Release when the opening angle rises above this (rad), ≥ `close`.
    pub open: f64,
}

impl Default for GraspThresholds {
    fn default() -> Self {
        // The built-in scripts open the jaws to 0.6 rad and close them to 0.
        GraspThresholds {
            close: 0.15,
            open: 0.25,
        }
    }
}

/// One step's input for a tool: its pose (tip position in m, orientation) and jaw angle.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ToolInput {
    /// Tool frame → world.
    pub pose: Isometry3<f64>,
    /// Jaw opening angle (rad, 0 = closed); ignored by probes and hooks.
    pub jaw: f64,
}

impl ToolInput {
    /// Input from a position (m), orientation and jaw angle (rad).
    pub fn new(position: V3, orientation: UnitQuaternion<f64>, jaw: f64) -> Self {
        ToolInput {
            pose: Isometry3::from_parts(Translation3::from(position), orientation),
            jaw,
        }
    }
}

impl From<&ToolPose> for ToolInput {
    fn from(p: &ToolPose) -> Self {
        ToolInput::new(p.position, p.orientation, p.jaw)
    }
}

/// Which rigid part of a tool a sample point belongs to.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ToolPart {
    /// The rod (probe, hook).
    Body,
    /// Forceps jaw turned by `+a/2`.
    JawPlus,
    /// Forceps jaw turned by `−a/2`.
    JawMinus,
}

/// A rigid tool.
#[derive(Clone, Debug)]
pub struct Tool {
    /// Name (as in the scene and the scripts).
    pub name: String,
    /// Kind.
    pub kind: ToolKind,
    /// Radius (m).
    pub radius: f64,
    /// Length of the contact-active tip (m).
    pub length: f64,
    /// Grasp thresholds (forceps only).
    pub grasp: GraspThresholds,
    pose: Isometry3<f64>,
    jaw: f64,
    velocity: V3,
    angular_velocity: V3,
    has_input: bool,
    /// Sample points in their part's frame (the tool frame with the jaws closed).
    samples: Vec<(V3, ToolPart)>,
    /// Samples in world coordinates for the current pose and jaw angle.
    world: Vec<V3>,
}

impl Tool {
    /// A tool at the spec's initial pose with its sample points placed.
    pub fn from_spec(spec: &ToolSpec) -> Tool {
        let r = spec.radius;
        let l = spec.length;
        // Sample spacing: 0.8 r along and around (about 8 points per ring).
        let h = 0.8 * r;
        let mut samples = Vec::new();
        match spec.kind {
            ToolKind::Probe => {
                capsule_samples(
                    V3::new(0.0, 0.0, r),
                    V3::new(0.0, 0.0, l.max(r)),
                    r,
                    h,
                    |p| samples.push((p, ToolPart::Body)),
                );
            }
            ToolKind::Hook => {
                let rho = 0.5 * r;
                let a = V3::new(0.0, 0.0, rho);
                capsule_samples(a, V3::new(0.0, 0.0, l.max(rho)), rho, h * 0.5, |p| {
                    samples.push((p, ToolPart::Body))
                });
                capsule_samples(a, V3::new(2.0 * r, 0.0, 2.0 * r), rho, h * 0.5, |p| {
                    samples.push((p, ToolPart::Body))
                });
            }
            // A blade cuts (`crate::cut::blade`) and a clip applier clips (`crate::clip`);
            // neither pushes: no contact samples. (An applier's jaws closing on a vessel
            // would squeeze it between two penalty contacts, and which way it slips out is
            // a bifurcation that sites decide differently.)
            ToolKind::Blade | ToolKind::ClipApplier => {}
            ToolKind::Forceps => {
                capsule_samples(
                    V3::new(0.0, 0.0, r),
                    V3::new(0.0, 0.0, l.max(r)),
                    r,
                    h,
                    |p| {
                        let part = if p.y >= 0.0 {
                            ToolPart::JawPlus
                        } else {
                            ToolPart::JawMinus
                        };
                        samples.push((p, part));
                        // Points on the split plane belong to both jaws.
                        if p.y.abs() < 1e-12 * r {
                            samples.push((p, ToolPart::JawMinus));
                        }
                    },
                );
            }
        }
        let pose = Isometry3::from_parts(Translation3::from(spec.position), spec.rotation());
        let mut tool = Tool {
            name: spec.name.clone(),
            kind: spec.kind,
            radius: r,
            length: l,
            grasp: GraspThresholds::default(),
            pose,
            jaw: 0.0,
            velocity: V3::zeros(),
            angular_velocity: V3::zeros(),
            has_input: false,
            world: vec![V3::zeros(); samples.len()],
            samples,
        };
        tool.update_world();
        tool
    }

    /// Sets this step's pose and jaw angle; the velocities are estimated by the finite
    /// difference to the previous input over `dt` (zero for the first input).
    pub fn set_input(&mut self, input: &ToolInput, dt: f64) {
        if self.has_input && dt > 0.0 {
            self.velocity = (input.pose.translation.vector - self.pose.translation.vector) / dt;
            let dq = input.pose.rotation * self.pose.rotation.inverse();
            self.angular_velocity = dq.scaled_axis() / dt;
        } else {
            self.velocity = V3::zeros();
            self.angular_velocity = V3::zeros();
        }
        self.has_input = true;
        self.pose = input.pose;
        self.jaw = input.jaw.max(0.0);
        self.update_world();
    }

    /// Tool frame → world.
    pub fn pose(&self) -> &Isometry3<f64> {
        &self.pose
    }
    /// Tip position (m).
    pub fn tip(&self) -> V3 {
        self.pose.translation.vector
    }
    /// Jaw angle (rad).
    pub fn jaw(&self) -> f64 {
        self.jaw
    }
    /// Estimated linear velocity of the tip (m/s).
    pub fn velocity(&self) -> V3 {
        self.velocity
    }
    /// Estimated angular velocity (rad/s, world frame).
    pub fn angular_velocity(&self) -> V3 {
        self.angular_velocity
    }
    /// Velocity (m/s) of the tool's material point at world position `p` (jaw motion
    /// neglected).
    pub fn point_velocity(&self, p: &V3) -> V3 {
        self.velocity + self.angular_velocity.cross(&(p - self.tip()))
    }
    /// Number of sample points.
    pub fn sample_count(&self) -> usize {
        self.samples.len()
    }
    /// Part of sample `i`.
    pub fn sample_part(&self, i: usize) -> ToolPart {
        self.samples[i].1
    }
    /// Sample points in world coordinates (m) for the current pose and jaw angle.
    pub fn world_samples(&self) -> &[V3] {
        &self.world
    }
    /// Whether this tool is a forceps whose jaws are closed enough to start a grasp.
    pub fn wants_grasp(&self) -> bool {
        self.kind == ToolKind::Forceps && self.jaw < self.grasp.close
    }
    /// Whether a forceps holding tissue must let go.
    /// Whether this tool is a clip applier whose jaws are closed enough to leave a clip
    /// (the forceps' grasp threshold).
    pub fn jaws_closed(&self) -> bool {
        self.kind == ToolKind::ClipApplier && self.jaw < self.grasp.close
    }

    /// The clip a clip applier's closed jaws would leave, world coordinates (m): tip →
    /// `length` along the shaft; `None` for other kinds.
    pub fn clip_segment(&self) -> Option<(V3, V3)> {
        (self.kind == ToolKind::ClipApplier).then(|| {
            (
                self.tip(),
                (self.pose * nalgebra::Point3::new(0.0, 0.0, self.length)).coords,
            )
        })
    }

    pub fn wants_release(&self) -> bool {
        self.kind != ToolKind::Forceps || self.jaw > self.grasp.open
    }

    /// A blade's cutting edge in world coordinates (m): tip → `length` along the shaft;
    /// `None` for other kinds.
    pub fn blade_edge(&self) -> Option<(V3, V3)> {
        (self.kind == ToolKind::Blade).then(|| {
            (
                self.tip(),
                (self.pose * nalgebra::Point3::new(0.0, 0.0, self.length)).coords,
            )
        })
    }

    /// Axis-aligned box of the samples (m), inflated by `margin`.
    pub fn aabb(&self, margin: f64) -> (V3, V3) {
        let mut lo = V3::repeat(f64::INFINITY);
        let mut hi = V3::repeat(f64::NEG_INFINITY);
        for p in &self.world {
            lo = lo.inf(p);
            hi = hi.sup(p);
        }
        (lo.add_scalar(-margin), hi.add_scalar(margin))
    }

    /// The centre segments of the jaws (forceps) or of the rod, world coordinates (m).
    pub fn segments(&self) -> Vec<(V3, V3)> {
        let hinge = V3::new(0.0, 0.0, self.length);
        match self.kind {
            ToolKind::Forceps | ToolKind::ClipApplier => [ToolPart::JawPlus, ToolPart::JawMinus]
                .iter()
                .map(|&part| {
                    let m = self.part_matrix(part);
                    (
                        self.pose * nalgebra::Point3::from(hinge),
                        self.pose * nalgebra::Point3::from(hinge + m * (-hinge)),
                    )
                })
                .map(|(a, b)| (a.coords, b.coords))
                .collect(),
            _ => vec![(
                self.tip(),
                (self.pose * nalgebra::Point3::from(hinge)).coords,
            )],
        }
    }

    /// Rotation of a part about the hinge (tool frame).
    fn part_matrix(&self, part: ToolPart) -> Matrix3<f64> {
        let angle = match part {
            ToolPart::Body => return Matrix3::identity(),
            ToolPart::JawPlus => 0.5 * self.jaw,
            ToolPart::JawMinus => -0.5 * self.jaw,
        };
        // A positive angle about +x turns the tip (0, 0, −L from the hinge) towards +y.
        *nalgebra::Rotation3::from_axis_angle(&V3::x_axis(), angle).matrix()
    }

    fn update_world(&mut self) {
        let hinge = V3::new(0.0, 0.0, self.length);
        let mats = [
            Matrix3::identity(),
            self.part_matrix(ToolPart::JawPlus),
            self.part_matrix(ToolPart::JawMinus),
        ];
        for (w, (p, part)) in self.world.iter_mut().zip(&self.samples) {
            let local = match part {
                ToolPart::Body => *p,
                ToolPart::JawPlus => hinge + mats[1] * (p - hinge),
                ToolPart::JawMinus => hinge + mats[2] * (p - hinge),
            };
            *w = (self.pose * nalgebra::Point3::from(local)).coords;
        }
    }
}

/// Samples on a capsule `a–b` of radius `r`: rings every `h` along the axis and a
/// hemisphere cap at `a` (the tip end). Calls `push` with each point.
fn capsule_samples(a: V3, b: V3, r: f64, h: f64, mut push: impl FnMut(V3)) {
    let axis = b - a;
    let len = axis.norm();
    let d = if len > 0.0 { axis / len } else { V3::z() };
    let u = if d.x.abs() < 0.9 { V3::x() } else { V3::y() };
    let e1 = d.cross(&u).normalize();
    let e2 = d.cross(&e1);
    let around = ((2.0 * std::f64::consts::PI * r / h).ceil() as usize).max(6);
    let around = around.next_multiple_of(2);
    let rings = ((len / h).ceil() as usize).max(1);
    let ring = |c: V3, rad: f64, push: &mut dyn FnMut(V3)| {
        for k in 0..around {
            let phi = 2.0 * std::f64::consts::PI * k as f64 / around as f64;
            push(c + (e1 * phi.cos() + e2 * phi.sin()) * rad);
        }
    };
    for i in 0..=rings {
        ring(a + axis * (i as f64 / rings as f64), r, &mut push);
    }
    // Hemisphere below `a`: latitude rings down to the pole.
    let lats = ((0.5 * std::f64::consts::PI * r / h).ceil() as usize).max(2);
    for j in 1..lats {
        let theta = 0.5 * std::f64::consts::PI * j as f64 / lats as f64;
        ring(a - d * (r * theta.sin()), r * theta.cos(), &mut push);
    }
    push(a - d * r);
}

/// All tools of a scene, in scene order.
#[derive(Clone, Debug, Default)]
pub struct ToolSet {
    /// The tools.
    pub tools: Vec<Tool>,
}

impl ToolSet {
    /// Tools of the scene's `[[tool]]` entries at their initial poses.
    pub fn from_specs(specs: &[ToolSpec]) -> ToolSet {
        ToolSet {
            tools: specs.iter().map(Tool::from_spec).collect(),
        }
    }
    /// Number of tools.
    pub fn len(&self) -> usize {
        self.tools.len()
    }
    /// Whether there is no tool.
    pub fn is_empty(&self) -> bool {
        self.tools.is_empty()
    }
    /// Index of the tool called `name`.
    pub fn index(&self, name: &str) -> Option<usize> {
        self.tools.iter().position(|t| t.name == name)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec(kind: ToolKind) -> ToolSpec {
        ToolSpec {
            name: "t".into(),
            kind,
            position: V3::zeros(),
            orientation: [1.0, 0.0, 0.0, 0.0],
            radius: 0.0025,
            length: 0.02,
            script: None,
        }
    }

    #[test]
    fn probe_samples_lie_on_its_surface() {
        let t = Tool::from_spec(&spec(ToolKind::Probe));
        assert!(t.sample_count() > 50);
        let mut lowest = f64::INFINITY;
        for p in t.world_samples() {
            // distance to the axis segment (0,0,r)-(0,0,L) equals r
            let z = p.z.clamp(0.0025, 0.02);
            let d = (p - V3::new(0.0, 0.0, z)).norm();
            assert!((d - 0.0025).abs() < 1e-12, "{p:?}");
            lowest = lowest.min(p.z);
        }
        assert!(lowest.abs() < 1e-12, "the tip is at the origin");
    }

    #[test]
    fn forceps_jaws_open_symmetrically() {
        let mut t = Tool::from_spec(&spec(ToolKind::Forceps));
        let q = UnitQuaternion::identity();
        t.set_input(&ToolInput::new(V3::zeros(), q, 0.6), 0.002);
        let segs = t.segments();
        assert!((segs[0].1.y - 0.02 * 0.3f64.sin()).abs() < 1e-12);
        assert!((segs[1].1.y + 0.02 * 0.3f64.sin()).abs() < 1e-12);
        assert!(!t.wants_grasp());
        t.set_input(&ToolInput::new(V3::zeros(), q, 0.1), 0.002);
        assert!(t.wants_grasp());
    }

    #[test]
    fn velocity_is_estimated_from_pose_differences() {
        let mut t = Tool::from_spec(&spec(ToolKind::Probe));
        let q = UnitQuaternion::identity();
        t.set_input(&ToolInput::new(V3::zeros(), q, 0.0), 0.01);
        let q2 = UnitQuaternion::from_axis_angle(&V3::z_axis(), 0.01);
        t.set_input(&ToolInput::new(V3::new(0.001, 0.0, 0.0), q2, 0.0), 0.01);
        assert!((t.velocity() - V3::new(0.1, 0.0, 0.0)).norm() < 1e-12);
        assert!((t.angular_velocity() - V3::new(0.0, 0.0, 1.0)).norm() < 1e-9);
    }
}
