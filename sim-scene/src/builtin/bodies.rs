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
//! Tool scripts ([`Scripts`]): the forceps grasps the fundus, lifts it 2 cm and holds it,
//! the hook sweeps along the bed from the fundus to the neck between the two bodies and
//! back out (2.5–9.5 s), the clip applier clips the cystic duct on the hilum's side (10.5–13 s) and
//! again on the gallbladder's side (13–15.5 s), and the blade divides the duct between
//! the clips (15.5–17 s).

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

/// The scene's tool scripts, and the trainee's second clip.
#[derive(Clone, Debug)]
pub struct Scripts {
    /// `bodies_grasp_lift`: the instructor's forceps lifts the fundus (0–3 s) and holds it
    /// (to 10.5 s, then parked closed: it keeps holding).
    pub forceps: ToolScript,
    /// `bodies_hook_dissect`: trainee B's hook dissects the bed (2.5–9.5 s).
    pub hook: ToolScript,
    /// `bodies_clip_duct`: the instructor's clip applier clips the duct on the hilum's
    /// side ([`CLIP_HILUM`] along it, 10.5–13 s).
    pub clip: ToolScript,
    /// `bodies_second_clip`: trainee A takes the clip applier and clips the duct on the
    /// gallbladder's side ([`CLIP_NECK`], 13–15.5 s). Not a scene script: `cosurg demo`
    /// gives it to trainee A.
    pub second_clip: ToolScript,
    /// `bodies_cut_duct`: the instructor's blade divides the duct between the clips
    /// ([`CUT_AT`], 15.5–17 s).
    pub blade: ToolScript,
}

/// Where the clips and the cut are, as fractions of the duct's length from the neck.
pub const CLIP_HILUM: f64 = 0.75;
/// See [`CLIP_HILUM`].
pub const CLIP_NECK: f64 = 0.35;
/// See [`CLIP_HILUM`].
pub const CUT_AT: f64 = 0.55;

/// Where the duct's axis hangs once the bed is dissected and the forceps holds the
/// gallbladder up (from 9.5 s on the demo's clock; static until the cut), as offsets from
/// its rest position (m) at [`CLIP_NECK`], [`CUT_AT`] and [`CLIP_HILUM`]: measured with
/// `cosurg run` (scene probes on the duct's axis at those fractions, dt 2 ms, at 10 s; at
/// 11 s within 10 µm of it), on the scene with fill weighting and the gallbladder's surface
/// at level 4 (2026-11-29: with fill weighting the duct's lattice hull no longer weighs as
/// much as the vessel, and the duct hung 3.1, 2.4 and 1.6 mm low where it hung 7.8, 6.2 and
/// 4.3 mm low without it; with the finer gallbladder its neck hangs lower, and the duct
/// 4.4, 3.3 and 2.1 mm low). The clips and the blade
/// aim there, as a surgeon aims at the duct where it is; the demo's end-to-end test
/// checks that both clips and the cut land.
const DUCT_SAG: [(f64, [f64; 3]); 3] = [
    (CLIP_NECK, [0.00035, 0.00002, -0.00437]),
    (CUT_AT, [0.00003, -0.00007, -0.00326]),
    (CLIP_HILUM, [0.00013, -0.00012, -0.00213]),
];

/// A point of the duct's axis at `f` (fraction from the neck) where it hangs after the
/// dissection ([`DUCT_SAG`]; rest position for other fractions).
fn hanging_duct(f: f64) -> V3 {
    let duct = cystic_duct();
    let sag = DUCT_SAG
        .iter()
        .find(|(g, _)| *g == f)
        .map_or(V3::zeros(), |(_, d)| V3::from(*d));
    duct.a + (duct.b - duct.a) * f + sag
}

/// A tool lying across the duct, horizontal, its tip on the artery's side: the shaft
/// (tool +z, tip → hinge) along `across`, jaws opening up and down (tool ±y along world
/// z), so that the duct runs between the jaws (tool x).
fn across_duct(across: &V3) -> UnitQuaternion<f64> {
    let z = across.normalize();
    let x = V3::z().cross(&z).normalize();
    // z × x is world up for a horizontal z: (x, up, z) is right-handed.
    let m = nalgebra::Matrix3::from_columns(&[x, z.cross(&x), z]);
    UnitQuaternion::from_rotation_matrix(&nalgebra::Rotation3::from_matrix_unchecked(m))
}

/// The tool scripts ([`Scripts`]).
pub fn scripts() -> Scripts {
    let gb = gallbladder();
    let u = gb.axis();
    // Forceps: along the gallbladder's axis to the fundus, close 6 mm inside, lift 2 cm,
    // and hold: while the bed is dissected, and on (the instrument parked with its jaws
    // closed) while the duct is clipped and divided.
    let q = pointing(&u);
    let grasp = gb.fundus + u * 0.006;
    let start = gb.fundus - u * 0.04;
    let lift = V3::new(0.0, 0.0, 0.02);
    let mut forceps = ToolScript {
        title: Some("forceps grasps the fundus, lifts it 2 cm and holds it".into()),
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
            waypoint(
                10.5,
                grasp + lift,
                q,
                0.0,
                "hold (the forceps keeps the gallbladder up while the duct is clipped and cut)",
            ),
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
    // Out the way it came, along the (released) bed: straight down from the neck would
    // plough through the gallbladder.
    track.push(waypoint(
        9.5,
        bed(0.0) - V3::new(0.0, 0.05, 0.0),
        qh,
        0.0,
        "withdraw along the bed",
    ));
    hook.tracks.insert("hook".into(), track);
    // The clip applier and the blade lie across the duct (horizontal, tip towards the
    // artery, which runs 9 mm away on that side).
    let duct = cystic_duct();
    let along = (duct.b - duct.a).normalize();
    let across = along.cross(&V3::z()).normalize();
    let at = hanging_duct;
    let qa = across_duct(&across);
    // Clip: from 3.5 cm out, jaws open, advance until the tip is 4 mm past the duct's
    // axis (the 12 mm jaws straddle it), close (the clip is placed), open, withdraw.
    let clip_track = |p: V3, t0: f64, who: &str| {
        let out = p + across * 0.035;
        vec![
            waypoint(t0, out, qa, 0.0, &format!("{who} takes the clip applier")),
            waypoint(t0 + 0.5, p + across * 0.03, qa, JAW_OPEN, "open the jaws"),
            waypoint(
                t0 + 1.3,
                p - across * 0.004,
                qa,
                JAW_OPEN,
                "jaws around the duct",
            ),
            waypoint(
                t0 + 1.6,
                p - across * 0.004,
                qa,
                0.0,
                "close: the clip is placed",
            ),
            waypoint(t0 + 1.8, p - across * 0.004, qa, JAW_OPEN, "open"),
            waypoint(t0 + 2.4, out, qa, JAW_OPEN, "withdraw"),
            waypoint(t0 + 2.5, out, qa, 0.0, ""),
        ]
    };
    let mut clip = ToolScript {
        title: Some("clip applier clips the cystic duct on the hilum's side".into()),
        ..Default::default()
    };
    clip.tracks.insert(
        "clip applier".into(),
        clip_track(at(CLIP_HILUM), 10.5, "the instructor"),
    );
    let mut second_clip = ToolScript {
        title: Some("clip applier clips the cystic duct on the gallbladder's side".into()),
        ..Default::default()
    };
    let mut second = clip_track(at(CLIP_NECK), 13.0, "trainee A");
    // Trainee A takes the applier where the instructor left it.
    second[0].pose.position = at(CLIP_HILUM) + across * 0.035;
    second_clip.tracks.insert("clip applier".into(), second);
    // Blade: its edge lies across the duct from 6 mm on the artery's side of the duct's
    // axis (between duct and artery) outwards, parked 1 cm below the duct, and is swept
    // up through it: the cut plane is perpendicular to the duct and stops short of the
    // artery.
    let cut = at(CUT_AT) - across * 0.006;
    let mut blade = ToolScript {
        title: Some("blade divides the cystic duct between the clips".into()),
        ..Default::default()
    };
    blade.tracks.insert(
        "blade".into(),
        vec![
            waypoint(
                15.5,
                cut - V3::new(0.0, 0.0, 0.01),
                qa,
                0.0,
                "under the duct, between the clips",
            ),
            waypoint(15.8, cut - V3::new(0.0, 0.0, 0.01), qa, 0.0, ""),
            waypoint(
                16.8,
                cut + V3::new(0.0, 0.0, 0.025),
                qa,
                0.0,
                "up through the duct",
            ),
        ],
    );
    Scripts {
        forceps,
        hook,
        clip,
        second_clip,
        blade,
    }
}
