//! The cholecystectomy scene with separate bodies (`scenes/cholecystectomy-bodies.toml`):
//! a liver body and a gallbladder body joined along the bed by an attachment layer, the
//! cystic duct and artery as thin bodies from the gallbladder's neck to a fixed hilum.
//!
//! All bodies share one lattice (cube cells of 2 cm), and bodies whose cells touch share
//! nodes, i.e. are one elastic body. So the liver's underside is flattened just above the
//! grid plane z = −0.02 m ([`LIVER_FLOOR`]) and the gallbladder hangs with its top below
//! z = −0.04 m: one empty cell layer separates the two, and the bed's springs span it
//! (2–3.5 cm long). The duct and the artery start inside the gallbladder's neck (their
//! cells overlap the gallbladder's: they are joined to it elastically) and end at the hilum,
//! whose nodes are fixed, also below z = −0.04 m.
//!
//! Tool scripts: the forceps grasps the fundus and lifts it 2 cm (0–10.5 s), the hook
//! sweeps along the bed from the fundus to the neck between the two bodies (2.5–9 s),
//! and the blade cuts the cystic duct near the hilum (10–12 s).

use nalgebra::{UnitQuaternion, Vector3};

use super::{Gallbladder, JAW_OPEN, liver_distance, pointing, radial_mesh, stitch_rings, waypoint};
use crate::mesh::TriMesh;
use crate::script::ToolScript;

type V3 = Vector3<f64>;

/// Height (m) of the liver's flattened underside: just above the grid plane z = −0.02 m.
pub const LIVER_FLOOR: f64 = -0.0195;

/// The gallbladder of the bodies scene: the shape of [`super::gallbladder`], lowered so
/// that its top stays below z = −0.041 m.
pub fn gallbladder() -> Gallbladder {
    Gallbladder {
        fundus: V3::new(0.035, -0.074, -0.060),
        neck: V3::new(0.027, 0.004, -0.052),
        max_radius: 0.015,
    }
}

/// The fixed hilum: where the duct and the artery end (m).
pub const HILUM: [f64; 3] = [0.0, 0.05, -0.054];

/// A straight vessel: a capsule from `a` to `b` with radius `radius` (m).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Vessel {
    /// Start, inside the gallbladder's neck.
    pub a: V3,
    /// End at the hilum.
    pub b: V3,
    /// Radius (m).
    pub radius: f64,
}

/// The cystic duct: from inside the neck to the hilum, radius 2.5 mm.
pub fn cystic_duct() -> Vessel {
    let gb = gallbladder();
    Vessel {
        a: gb.neck - gb.axis() * 0.006,
        b: V3::from(HILUM),
        radius: 0.0025,
    }
}

/// The cystic artery: from the gallbladder's body near the neck, beside the duct, to the
/// hilum, radius 1.5 mm.
pub fn cystic_artery() -> Vessel {
    let gb = gallbladder();
    Vessel {
        a: gb.fundus + gb.axis() * (0.75 * gb.length()) + V3::new(-0.006, 0.0, 0.0),
        b: V3::from(HILUM) + V3::new(-0.006, -0.004, -0.004),
        radius: 0.0015,
    }
}

impl Vessel {
    /// Closed, outward capsule surface: `rings` rings of `segments` vertices plus two
    /// poles, rings denser toward the poles.
    pub fn mesh(&self, rings: usize, segments: usize) -> TriMesh {
        let axis = self.b - self.a;
        let len = axis.norm();
        let u = axis / len;
        let e1 = u
            .cross(&V3::z())
            .try_normalize(1e-9)
            .unwrap_or_else(|| u.cross(&V3::x()).normalize());
        let e2 = u.cross(&e1);
        // Capsule profile: hemispherical caps of the radius at both ends.
        let total = len + 2.0 * self.radius;
        let radius_at = |t: f64| {
            let d = t.min(total - t);
            if d >= self.radius {
                self.radius
            } else {
                (self.radius * self.radius - (self.radius - d).powi(2))
                    .max(0.0)
                    .sqrt()
            }
        };
        let start = self.a - u * self.radius;
        let mut m = TriMesh::default();
        m.vertices.push(start);
        for i in 1..rings + 1 {
            let s = 0.5 * (1.0 - (std::f64::consts::PI * i as f64 / (rings + 1) as f64).cos());
            let t = s * total;
            for j in 0..segments {
                let th = 2.0 * std::f64::consts::PI * j as f64 / segments as f64;
                let dir = e1 * th.cos() + e2 * th.sin();
                m.vertices.push(start + u * t + dir * radius_at(t));
            }
        }
        m.vertices.push(self.b + u * self.radius);
        stitch_rings(&mut m, rings, segments);
        m
    }
}

/// Signed distance (approximate, m) of the liver body: the liver lobe with its underside
/// cut flat at [`LIVER_FLOOR`] (a smooth maximum, so the floor is never lower).
pub fn liver_distance_flat(p: &V3) -> f64 {
    let (a, b, k) = (liver_distance(p), LIVER_FLOOR - p.z, 0.004);
    let h = (0.5 + 0.5 * (a - b) / k).clamp(0.0, 1.0);
    b + (a - b) * h + k * h * (1.0 - h)
}

/// The generated meshes: (liver, gallbladder, cystic duct, cystic artery), unrounded.
pub fn meshes() -> [TriMesh; 4] {
    [
        radial_mesh(&liver_distance_flat),
        gallbladder().mesh(24, 24),
        cystic_duct().mesh(16, 10),
        cystic_artery().mesh(16, 8),
    ]
}

/// The tool scripts: (forceps `bodies_grasp_lift`, hook `bodies_hook_dissect`, blade
/// `bodies_cut_duct`).
pub fn scripts() -> (ToolScript, ToolScript, ToolScript) {
    let gb = gallbladder();
    let u = gb.axis();
    // Forceps: along the gallbladder's axis to the fundus, close 6 mm inside, lift 2 cm,
    // hold while the bed is dissected, release, withdraw.
    let q = pointing(&u);
    let grasp = gb.fundus + u * 0.006;
    let start = gb.fundus - u * 0.04;
    let lift = V3::new(0.0, 0.0, 0.02);
    let mut forceps = ToolScript {
        title: Some(
            "forceps grasps the fundus, lifts it 2 cm, holds it while the bed is dissected".into(),
        ),
        ..Default::default()
    };
    forceps.tracks.insert(
        "forceps".into(),
        vec![
            waypoint(
                0.0,
                start,
                q,
                JAW_OPEN,
                "approach the fundus with open jaws",
            ),
            waypoint(1.5, grasp, q, JAW_OPEN, ""),
            waypoint(2.0, grasp, q, 0.0, "close the jaws on the fundus"),
            waypoint(3.0, grasp + lift, q, 0.0, "lift 2 cm"),
            waypoint(9.5, grasp + lift, q, 0.0, "hold"),
            waypoint(10.0, grasp + lift, q, JAW_OPEN, "release"),
            waypoint(10.5, start + lift, q, JAW_OPEN, "withdraw"),
        ],
    );
    // Hook: from the front into the gap between the liver's floor and the gallbladder, at
    // the height of the bed's springs, then along the bed from the fundus to the neck.
    let bed = |s: f64| {
        let p = gb.fundus + u * (s * gb.length());
        V3::new(p.x, p.y, 0.5 * (LIVER_FLOOR + p.z + gb.radius(s)))
    };
    let qh = pointing(&V3::new(0.0, 1.0, 0.3).normalize());
    let mut hook = ToolScript {
        title: Some("hook dissects the gallbladder bed from the fundus to the neck".into()),
        ..Default::default()
    };
    let mut track = vec![
        waypoint(
            0.0,
            bed(0.0) - V3::new(0.0, 0.05, 0.0),
            qh,
            0.0,
            "wait in front of the fundus",
        ),
        waypoint(2.5, bed(0.0) - V3::new(0.0, 0.05, 0.0), qh, 0.0, ""),
        waypoint(3.5, bed(0.05), qh, 0.0, "enter the bed under the liver"),
    ];
    for (i, s) in [0.25, 0.45, 0.65, 0.85, 1.0].iter().enumerate() {
        track.push(waypoint(
            4.5 + i as f64,
            bed(*s),
            qh,
            0.0,
            if i == 0 {
                "along the bed toward the neck"
            } else {
                ""
            },
        ));
    }
    track.push(waypoint(
        9.0,
        bed(1.0) - V3::new(0.0, 0.0, 0.03),
        qh,
        0.0,
        "withdraw",
    ));
    hook.tracks.insert("hook".into(), track);
    // Blade: vertical edge, swept horizontally across the duct at 70 % of its length.
    let duct = cystic_duct();
    let along = (duct.b - duct.a).normalize();
    let across = along.cross(&V3::z()).normalize();
    let at = duct.a + (duct.b - duct.a) * 0.7;
    let low = V3::new(0.0, 0.0, -0.025);
    let qb = UnitQuaternion::identity();
    let mut blade = ToolScript {
        title: Some("blade cuts the cystic duct near the hilum".into()),
        ..Default::default()
    };
    blade.tracks.insert(
        "blade".into(),
        vec![
            waypoint(
                0.0,
                at + low - across * 0.035,
                qb,
                0.0,
                "wait beside the duct",
            ),
            waypoint(10.5, at + low - across * 0.035, qb, 0.0, ""),
            waypoint(11.5, at + low + across * 0.035, qb, 0.0, "through the duct"),
        ],
    );
    (forceps, hook, blade)
}
