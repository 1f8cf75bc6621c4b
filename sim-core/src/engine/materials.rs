//! Which material each lattice tet gets, and (with the scene feature `fill_weighting`)
//! what fraction of it the bodies fill.
//!
//! **Fill weighting** (Nesme et al. 2009 build coarse elements from the matter inside
//! them; SOFA's `SparseGridTopology` `fillWeighted` weighs a boundary cell by ½): a
//! lattice hull is larger than the organ it embeds, since every cell the surface crosses
//! is whole. On the default scene at 2 cm cells, 121 cm³ of hull lies beside the 32 cm³
//! gallbladder, and without fill weighting a tet whose centre lies outside every body takes
//! the first body's material (the liver's, 2.5× stiffer than the gallbladder's), so the
//! lifted gallbladder moved like a stiff block (docs/RESULTS.md, "What sets the organ's
//! accuracy"). With it, a tet's stiffness and mass are scaled by the fraction `φ` of its
//! volume inside the bodies, estimated at [`FILL_SAMPLES`] points spread through it, and a
//! tet whose centre lies outside every body takes the material of the body most of its
//! samples lie in. A fill is at least [`FILL_FLOOR_TENTHS`] (light, soft hull tets under the
//! tools were unstable). On that scene the liver's lattice then holds 1,097 cm³ against its
//! mesh's 906 cm³ (without: 1,857), the gallbladder's 38.9 against 32.4, and the organ
//! weighs 1,209 g against the meshes' 995 g (without: 2,009 g; test
//! `sim-core/tests/fill.rs`).

use std::collections::HashMap;

use nalgebra::Vector3;
use sim_scene::{Aabb, Containment};

type V3 = Vector3<f64>;

/// Sample points of a tet for its fill: the centres of the 20 upright sub-tets of its
/// degree-4 split, `((i, j, k, l) + ¼) / 4` in barycentric coordinates with `i + j + k +
/// l = 3`. Twenty points cannot be exact for one tet: a plane cutting off the corner where
/// λ₀ > ½ (12.5 % of the volume) takes 4 of them (20 %), and so does one at λ₀ > 0.36
/// (26 %). The first version's interior points of the grid of step 1/7 sat towards the
/// centre and took 1 and 4 of 20; these reach the corners, and over a body's boundary the
/// errors average out (test `sim-core/tests/fill.rs`).
pub(super) const FILL_SAMPLES: usize = 20;

/// The fill samples' barycentric coordinates, × 16: `4 i + 1` for `i + j + k + l = 3`.
const FILL_BARYCENTRIC: [[u8; 4]; FILL_SAMPLES] = {
    let mut out = [[0u8; 4]; FILL_SAMPLES];
    let mut n = 0;
    let mut i = 0;
    while i <= 3 {
        let mut j = 0;
        while i + j <= 3 {
            let mut k = 0;
            while i + j + k <= 3 {
                let l = 3 - i - j - k;
                out[n] = [4 * i + 1, 4 * j + 1, 4 * k + 1, 4 * l + 1];
                n += 1;
                k += 1;
            }
            j += 1;
        }
        i += 1;
    }
    assert!(n == FILL_SAMPLES);
    out
};

/// Fills are whole tenths (the share of samples inside, rounded half up in integers), so
/// that the scaled materials are few (elements of one material and shape share a
/// template stiffness) and each has one bit pattern.
const TENTHS: u32 = 10;

/// The least fill, in tenths: hull tets with (nearly) no sample inside keep 0.3 of their
/// material's stiffness and mass. With 0.1, light and soft hull tets under the tools
/// rotated and inverted in the three-site demo: the energy guard's Newton steps took the
/// sites to 65–74 Hz (step p99 47–63 ms) and the trainees strayed 7–19 mm; with 0.3 the
/// demo kept 250 Hz and its trainees within 0.01 mm (docs/RESULTS.md).
pub(super) const FILL_FLOOR_TENTHS: u32 = 3;

/// Bodies fill weighting tells apart (a bit each); a scene with more is refused.
pub(super) const MAX_FILL_BODIES: usize = 64;

/// Points whose containment [`MaterialMap::material_and_fill`] keeps before it starts
/// afresh (about 40 MB): a point is asked again only when a tet comes back after
/// coarsening, and a long session refines and coarsens without end.
pub(super) const MAX_CACHED_POINTS: usize = 1 << 20;

/// Which region of space gets which material.
#[derive(Clone, Debug)]
pub(super) struct MaterialMap {
    /// Body shapes with their material index, in scene order.
    pub(super) bodies: Vec<(Region, usize)>,
    /// Inclusions with their material index and whether their boundary is refined.
    pub(super) inclusions: Vec<(Region, usize, bool)>,
}

#[derive(Clone, Debug)]
pub(super) enum Region {
    Box(Aabb),
    /// A closed mesh's inside, with the grid that answers most queries
    /// ([`Containment`]: new tets come by the hundred when the lattice refines).
    Mesh(Box<Containment>),
    Capsules(Vec<sim_scene::Capsule>),
}

impl Region {
    pub(super) fn contains(&self, p: &V3) -> bool {
        match self {
            Region::Box(b) => b.contains(p),
            Region::Mesh(m) => m.contains(p),
            Region::Capsules(c) => c.iter().any(|c| c.signed_distance(p) <= 0.0),
        }
    }
}

impl MaterialMap {
    /// The material at `p`: the last inclusion containing it, else the first body
    /// containing it, else the first body's.
    pub(super) fn material_at(&self, p: &V3) -> usize {
        let mut m = self
            .bodies
            .iter()
            .find(|(r, _)| r.contains(p))
            .or(self.bodies.first())
            .map(|(_, m)| *m)
            .unwrap_or(0);
        for (r, mi, _) in &self.inclusions {
            if r.contains(p) {
                m = *mi;
            }
        }
        m
    }

    /// Material and fill of the tet with corners `x` (rest positions, m) under fill
    /// weighting: the fill is the fraction of its [`FILL_SAMPLES`] points inside any
    /// body, in whole tenths rounded half up and at least [`FILL_FLOOR_TENTHS`]; the
    /// material is [`MaterialMap::material_at`] its centroid when a body contains the
    /// centroid, else at the first sample of the body that holds the most samples (the
    /// first such body in scene order), else at the centroid.
    ///
    /// `inside` keeps, per point asked (by its coordinates' bits), the set of bodies
    /// containing it.
    pub(super) fn material_and_fill(
        &self,
        x: &[V3; 4],
        inside: &mut HashMap<[u64; 3], u64>,
    ) -> (usize, f64) {
        let centroid = x.iter().sum::<V3>() / 4.0;
        let samples = FILL_BARYCENTRIC.map(|w| {
            (x[0] * f64::from(w[0])
                + x[1] * f64::from(w[1])
                + x[2] * f64::from(w[2])
                + x[3] * f64::from(w[3]))
                / 16.0
        });
        // Per body: samples inside it, and the first of them.
        let mut count = vec![(0usize, None); self.bodies.len()];
        let mut filled = 0;
        for p in &samples {
            let bodies = self.bodies_containing(p, inside);
            for (b, (n, first)) in count.iter_mut().enumerate() {
                if b < MAX_FILL_BODIES && bodies & (1 << b) != 0 {
                    *n += 1;
                    first.get_or_insert(*p);
                }
            }
            filled += usize::from(bodies != 0);
        }
        // Round half up: (2 · 10 · filled + samples) / (2 · samples) tenths.
        let samples_n = FILL_SAMPLES as u32;
        let tenths = (2 * TENTHS * filled as u32 + samples_n) / (2 * samples_n);
        let fill = f64::from(tenths.max(FILL_FLOOR_TENTHS)) / f64::from(TENTHS);
        let centre_inside = self.bodies_containing(&centroid, inside) != 0;
        let most = count
            .iter()
            .filter_map(|(n, first)| first.map(|p| (*n, p)))
            .fold(None, |best: Option<(usize, V3)>, (n, p)| match best {
                Some((m, _)) if m >= n => best,
                _ => Some((n, p)),
            });
        let material = match (centre_inside, most) {
            (false, Some((_, p))) => self.material_at(&p),
            _ => self.material_at(&centroid),
        };
        (material, fill)
    }

    /// Bit `b` set when body `b` contains `p` (from `inside` when asked before). A scene
    /// with fill weighting has at most [`MAX_FILL_BODIES`] bodies (`Simulation::new`).
    fn bodies_containing(&self, p: &V3, inside: &mut HashMap<[u64; 3], u64>) -> u64 {
        if inside.len() >= MAX_CACHED_POINTS {
            inside.clear();
        }
        let key = [p.x.to_bits(), p.y.to_bits(), p.z.to_bits()];
        *inside.entry(key).or_insert_with(|| {
            self.bodies
                .iter()
                .take(MAX_FILL_BODIES)
                .enumerate()
                .filter(|(_, (region, _))| region.contains(p))
                .fold(0, |bits, (b, _)| bits | 1 << b)
        })
    }
}
