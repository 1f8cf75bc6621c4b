//! Unit tests of the system's private kernels.

use nalgebra::{Matrix3, Rotation3, SMatrix};

use super::V3;
use super::element_blocks::{block, rotated_blocks, rotated_iso_blocks};
use crate::element::{Mat12, TetGeometry, lame};

/// Element stiffness the textbook way, `V Bᵀ D B` with Voigt strains (independent of
/// the gradient formula under test).
fn voigt_stiffness(g: &[V3; 4], v: f64, lambda: f64, mu: f64) -> Mat12 {
    let mut b = SMatrix::<f64, 6, 12>::zeros();
    for (a, ga) in g.iter().enumerate() {
        let (x, y, z) = (ga.x, ga.y, ga.z);
        let c = 3 * a;
        b[(0, c)] = x;
        b[(1, c + 1)] = y;
        b[(2, c + 2)] = z;
        b[(3, c)] = y;
        b[(3, c + 1)] = x;
        b[(4, c + 1)] = z;
        b[(4, c + 2)] = y;
        b[(5, c)] = z;
        b[(5, c + 2)] = x;
    }
    let mut d = SMatrix::<f64, 6, 6>::zeros();
    for i in 0..3 {
        for j in 0..3 {
            d[(i, j)] = lambda;
        }
        d[(i, i)] += 2.0 * mu;
        d[(i + 3, i + 3)] = mu;
    }
    b.transpose() * d * b * v
}

#[test]
fn rotated_gradient_blocks_match_rotated_voigt_stiffness() {
    let x = [
        V3::new(0.0, 0.0, 0.0),
        V3::new(0.031, 0.002, -0.004),
        V3::new(0.003, 0.027, 0.001),
        V3::new(-0.002, 0.004, 0.022),
    ];
    let geom = TetGeometry::new(&x).unwrap();
    let (lambda, mu) = lame(1e5, 0.45);
    let k = voigt_stiffness(&geom.grads, geom.volume, lambda, mu);
    let r = *Rotation3::from_scaled_axis(V3::new(0.7, -1.1, 0.4)).matrix();
    let mut big_r = Mat12::zeros();
    for a in 0..4 {
        big_r.fixed_view_mut::<3, 3>(3 * a, 3 * a).copy_from(&r);
    }
    let expect = big_r * k * big_r.transpose();
    let mut got = [Matrix3::zeros(); 10];
    rotated_iso_blocks(&geom.grads, geom.volume, lambda, mu, Some(&r), &mut got);
    let via_blocks = rotated_blocks(&k, Some(&r));
    let scale = expect.amax();
    for a in 0..4 {
        for b in 0..4 {
            let e = expect.fixed_view::<3, 3>(3 * a, 3 * b).into_owned();
            assert!(
                (block(&got, a, b) - e).amax() < 1e-12 * scale,
                "iso block ({a},{b})"
            );
            assert!(
                (block(&via_blocks, a, b) - e).amax() < 1e-12 * scale,
                "block ({a},{b})"
            );
        }
    }
}

/// A beam whose cubes' six tets share the rotation of the cube's first tet (as rotation
/// sharing does), soft enough to sag under gravity.
fn shared_rotation_beam() -> crate::FemSystem {
    let mesh = crate::mesh::kuhn_box([8, 2, 2], [0.4, 0.1, 0.1], V3::new(0.0, -0.05, -0.05));
    let rotation_sources = mesh
        .tets
        .chunks(6)
        .map(|c| crate::RotationSourceDesc {
            nodes: c[0],
            rest_inverse_edges: None,
        })
        .collect();
    let mut elements = mesh.elements(0);
    for (i, e) in elements.iter_mut().enumerate() {
        e.rotation_source = Some(i / 6);
    }
    crate::FemSystem::new(&crate::FemDesc {
        rest: mesh.rest.clone(),
        elements,
        materials: vec![crate::Material::new(2e4, 0.45, 1000.0)],
        fixed: mesh.nodes_with_x_at_most(1e-9),
        rotation_sources,
    })
    .expect("valid beam")
}

/// Assembly through the per-element cache of rotated blocks gives the same bits as
/// assembly that rotates every element afresh, in both stiffness modes that use it, while
/// the rest test keeps some rotations (cache hits) and re-extracts others (misses).
#[test]
fn cached_element_blocks_give_the_same_steps_bit_for_bit() {
    use crate::{OperatorMode, StepParams, StiffnessMode};
    for stiffness in [StiffnessMode::Gradient, StiffnessMode::Template] {
        let p = StepParams {
            gravity: V3::new(0.0, 0.0, -9.81),
            stiffness,
            operator: OperatorMode::Assembled,
            // Sources whose nodes moved less than 5 mm since their last extraction keep their rotation.
            rest_threshold: 5e-3,
            ..StepParams::default()
        };
        let (mut cached, mut fresh) = (shared_rotation_beam(), shared_rotation_beam());
        let rest = cached.mesh.rest.clone();
        let zero = vec![V3::zeros(); rest.len()];
        let (mut xc, mut vc) = (rest.clone(), zero.clone());
        let (mut xf, mut vf) = (rest.clone(), zero.clone());
        let (mut used, mut mixed) = (0, 0);
        const STEPS: usize = 40;
        for step in 0..STEPS {
            fresh.caches.element_blocks.clear();
            let sc = cached.step(&mut xc, &mut vc, &zero, 0.01, &p).unwrap();
            let sf = fresh.step(&mut xf, &mut vf, &zero, 0.01, &p).unwrap();
            assert_eq!(
                sc.cg_iterations, sf.cg_iterations,
                "{stiffness:?} step {step}"
            );
            let same = xc
                .iter()
                .chain(&vc)
                .zip(xf.iter().chain(&vf))
                .all(|(a, b)| {
                    a.iter()
                        .zip(b.iter())
                        .all(|(p, q)| p.to_bits() == q.to_bits())
                });
            assert!(same, "{stiffness:?} step {step}: states differ");
            // Steps assembled through the cache (each source is a cube's six tets) that
            // kept some rotations (hits) and extracted others (their elements' entries
            // hold the previous rotation: they must miss).
            let elements = cached.mesh.elements.len();
            if super::element_blocks::cache_pays(6 * sc.rotations_extracted, elements) {
                used += 1;
                mixed += usize::from(sc.rotations_reused > 0 && sc.rotations_extracted > 0);
            }
        }
        assert!(mixed > 0, "{stiffness:?}: used {used}, mixed {mixed}");
        let sag = largest_displacement(&xc, &rest);
        assert!(sag > 1e-3, "the beam sagged {sag} m");
    }
}

/// Largest displacement (m).
fn largest_displacement(x: &[V3], rest: &[V3]) -> f64 {
    x.iter()
        .zip(rest)
        .map(|(a, b)| (a - b).norm())
        .fold(0.0, f64::max)
}

/// A beam bent (up to 1 rad at the tip) and twisted, whose first three tenths share one
/// rotation per block of 2 × 2 × 2 cubes (48 tets: summed per source by
/// `source_stiffness.rs`) and whose last tenth one per cube (6 tets: left to the
/// per-element loops), with its deformed positions and their rotations stored.
fn block_shared_beam() -> (crate::FemSystem, Vec<V3>) {
    block_shared_beam_with(vec![crate::Material::new(2e4, 0.45, 1000.0)], |_| 0)
}

/// [`block_shared_beam`] with `materials`, element `e` taking `material_of(e)`.
fn block_shared_beam_with(
    materials: Vec<crate::Material>,
    material_of: impl Fn(usize) -> usize,
) -> (crate::FemSystem, Vec<V3>) {
    let mesh = crate::mesh::kuhn_box([8, 2, 2], [0.4, 0.1, 0.1], V3::zeros());
    let centroid = |t: &[usize; 4]| t.iter().map(|&n| mesh.rest[n]).sum::<V3>() / 4.0;
    let key = |c: V3| {
        if c.x < 0.3 {
            (0, (c.x / 0.1) as usize, 0, 0)
        } else {
            (
                1,
                (c.x / 0.05) as usize,
                (c.y / 0.05) as usize,
                (c.z / 0.05) as usize,
            )
        }
    };
    let mut keys: Vec<_> = mesh.tets.iter().map(|t| key(centroid(t))).collect();
    keys.sort();
    keys.dedup();
    let mut elements = mesh.elements(0);
    let mut source_nodes = vec![None; keys.len()];
    for (i, (e, t)) in elements.iter_mut().zip(&mesh.tets).enumerate() {
        let s = keys.binary_search(&key(centroid(t))).unwrap();
        e.rotation_source = Some(s);
        e.material = material_of(i);
        source_nodes[s].get_or_insert(*t);
    }
    let mut sys = crate::FemSystem::new(&crate::FemDesc {
        rest: mesh.rest.clone(),
        elements,
        materials,
        fixed: mesh.nodes_with_x_at_most(1e-9),
        rotation_sources: source_nodes
            .into_iter()
            .map(|n| crate::RotationSourceDesc {
                nodes: n.unwrap(),
                rest_inverse_edges: None,
            })
            .collect(),
    })
    .unwrap();
    let x: Vec<V3> = mesh
        .rest
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let bend = Rotation3::from_axis_angle(&V3::y_axis(), 2.5 * p.x);
            let twist = Rotation3::from_axis_angle(&V3::x_axis(), 1.5 * p.x);
            let ripple = V3::new(1e-3 * (i as f64).sin(), 0.0, 5e-4 * (0.3 * i as f64).cos());
            bend * twist * p + ripple
        })
        .collect();
    sys.update_rotations(&x, &crate::PolarMethod::default(), 0.0);
    (sys, x)
}

/// The stiffness modes whose element matrices the per-source sums take.
const STIFFNESS_MODES: [crate::StiffnessMode; 3] = [
    crate::StiffnessMode::Gradient,
    crate::StiffnessMode::Template,
    crate::StiffnessMode::Dense,
];

/// The one-thread co-rotational forces source by source (`source_stiffness.rs`) against the
/// per-element loop, on [`block_shared_beam`], in the three stiffness modes. The sums
/// differ by rounding only: 1e-10 of the largest force, and the energy to 1e-10
/// relative.
#[test]
fn source_forces_match_the_per_element_loop() {
    use crate::Model;
    let (mut sys, x) = block_shared_beam();
    let n = x.len();
    // (Dense mode reads the per-element matrices built here.)
    sys.ensure_dense();
    for mode in STIFFNESS_MODES {
        sys.caches.source_stiffness.clear();
        let mut per_element = vec![V3::zeros(); n];
        let e_ref = sys.elastic(&x, Model::Corotational, mode, None, Some(&mut per_element));
        // A source is summed once it holds the same elements at two refreshes running.
        sys.refresh_source_stiffness(mode);
        assert_eq!(sys.caches.source_stiffness.iter().flatten().count(), 0);
        sys.refresh_source_stiffness(mode);
        let summed = sys.caches.source_stiffness.iter().flatten().count();
        assert_eq!(summed, 3, "{mode:?}: sources summed");
        let mut by_source = vec![V3::zeros(); n];
        let e = sys.elastic(&x, Model::Corotational, mode, None, Some(&mut by_source));
        let scale = per_element.iter().map(|f| f.norm()).fold(0.0, f64::max);
        assert!(scale > 1.0, "{mode:?}: largest force {scale} N");
        for (i, (a, b)) in per_element.iter().zip(&by_source).enumerate() {
            assert!(
                (a - b).norm() <= 1e-10 * scale,
                "{mode:?} node {i}: {a} against {b}"
            );
        }
        assert!(
            (e - e_ref).abs() <= 1e-10 * e_ref.abs(),
            "{mode:?}: energy {e} against {e_ref}"
        );
    }
}

/// The one-thread assembly of `A = diag(mass_coef) + Σ coef_e R K_e Rᵀ + dt² K_c` in
/// `mode`, element by element (no source kept) and then with the sources summed
/// (`source_stiffness.rs`, refreshed twice so that they are kept); the sums stay in
/// `sys`'s caches.
fn assembled_without_and_with_sums(
    sys: &mut crate::FemSystem,
    mass_coef: &[f64],
    coef: &[f64],
    dt: f64,
    mode: crate::StiffnessMode,
) -> (Vec<Matrix3<f64>>, Vec<Matrix3<f64>>) {
    use super::operator::ElemMats;
    let assemble = |sys: &mut crate::FemSystem| {
        let elem = ElemMats::Rotated {
            coef: coef.to_vec(),
            rotated: true,
        };
        let assembled = crate::OperatorMode::Assembled;
        let op = sys.build_operator(mass_coef.to_vec(), elem, dt * dt, mode, assembled);
        let blocks = op.assembled.clone().expect("assembled");
        let buffers = op.into_buffers();
        sys.caches.recycle(buffers);
        blocks
    };
    sys.caches.source_stiffness.clear();
    let want = assemble(sys);
    sys.refresh_source_stiffness(mode);
    sys.refresh_source_stiffness(mode);
    (want, assemble(sys))
}

/// Every block of `got` within 1e-12 of the largest block of `want`.
fn assert_blocks_match(want: &[Matrix3<f64>], got: &[Matrix3<f64>], what: &str) {
    let scale = want.iter().map(|b| b.amax()).fold(0.0, f64::max);
    for (s, (w, g)) in want.iter().zip(got).enumerate() {
        assert!(
            (w - g).amax() <= 1e-12 * scale,
            "{what}, slot {s}: {w} against {g}"
        );
    }
}

/// The one-thread assembly of `coef R K Rᵀ` with sources summed (`source_stiffness.rs`)
/// against the per-element assembly, on [`block_shared_beam`]: every stored block to
/// 1e-12 of the largest, the diagonal blocks exactly symmetric (where the per-element
/// blocks are).
#[test]
fn source_assembly_matches_the_per_element_assembly() {
    use crate::StiffnessMode;
    let (mut sys, _) = block_shared_beam();
    let unit_mass = vec![1.0; sys.mesh.rest.len()];
    let (dt, beta) = (0.01, 0.0);
    let coef = vec![dt * beta + dt * dt; sys.mesh.elements.len()];
    // (Dense mode reads the per-element matrices built here.)
    sys.ensure_dense();
    for mode in STIFFNESS_MODES {
        let (want, got) = assembled_without_and_with_sums(&mut sys, &unit_mass, &coef, dt, mode);
        assert_eq!(sys.caches.source_stiffness.iter().flatten().count(), 3);
        assert_blocks_match(&want, &got, &format!("{mode:?}"));
        // (Dense per-element blocks are rotated whole and need not be exactly symmetric;
        // the sources beyond x = 0.3 m add them to the diagonal.)
        if mode == StiffnessMode::Dense {
            continue;
        }
        let pattern = sys.caches.pattern.as_ref().unwrap();
        for &d in pattern.diagonal_slots() {
            assert_eq!(got[d], got[d].transpose(), "{mode:?}: diagonal block {d}");
        }
    }
}

/// A source whose tets differ in stiffness and density but share one stiffness damping β
/// (as fill-weighted boundary tets beside whole ones do) assembles as one, matching the
/// per-element assembly with the step's own coefficients `dt β + dt²`; a source whose
/// tets' β differ keeps the per-element loop (its tets need different coefficients).
#[test]
fn a_source_of_mixed_stiffness_assembles_as_one_when_its_damping_is_shared() {
    let dt = 0.01;
    for (second_beta, sums) in [(0.01, 3), (0.02, 0)] {
        let whole = crate::Material {
            rayleigh_stiffness: 0.01,
            ..crate::Material::new(2e4, 0.45, 1000.0)
        };
        // A tet 40 % inside its body: E and ρ scaled.
        let filled = crate::Material {
            young: 0.4 * whole.young,
            density: 0.4 * whole.density,
            rayleigh_stiffness: second_beta,
            ..whole
        };
        let (mut sys, _) = block_shared_beam_with(vec![whole, filled], |e| usize::from(e % 3 == 0));
        let (mass_coef, coef) = sys.linearised_coefficients(dt);
        // (Dense mode reads the per-element matrices built here.)
        sys.ensure_dense();
        for mode in STIFFNESS_MODES {
            let (want, got) =
                assembled_without_and_with_sums(&mut sys, &mass_coef, &coef, dt, mode);
            let as_one = sys.caches.source_stiffness.iter().flatten();
            assert_eq!(
                as_one.filter(|k| k.assembles_as_one()).count(),
                sums,
                "{mode:?}, β {second_beta}"
            );
            assert_blocks_match(&want, &got, &format!("{mode:?}, β {second_beta}"));
        }
    }
}

/// A matrix that outgrows the cache is multiplied (here on one thread) from contiguous
/// upper rows (`solver/upper_product.rs`), not from full rows: the operator's products (CG's and the
/// right-hand side's) equal the symmetric upper product of its assembled blocks to
/// rounding, and no full-row copy is made.
#[test]
fn an_operator_beyond_the_cache_multiplies_by_upper_rows() {
    use super::operator::ElemMats;
    use crate::solver::LinearOperator;
    // 9,225 nodes, about 130,000 blocks: 9 MB, over the 8 MiB of `prefetch.rs`.
    let mesh = crate::mesh::kuhn_box([40, 14, 14], [0.4, 0.14, 0.14], V3::zeros());
    let mut sys = crate::FemSystem::new(&crate::FemDesc {
        rest: mesh.rest.clone(),
        elements: mesh.elements(0),
        materials: vec![crate::Material::new(2e4, 0.45, 1000.0)],
        fixed: mesh.nodes_with_x_at_most(1e-9),
        rotation_sources: Vec::new(),
    })
    .expect("valid beam");
    let n = mesh.rest.len();
    let elements = sys.mesh.elements.len();
    let elem = ElemMats::Rotated {
        coef: vec![1e-2; elements],
        rotated: true,
    };
    let op = sys.build_operator(
        vec![3.0; n],
        elem,
        1e-4,
        crate::StiffnessMode::Gradient,
        crate::OperatorMode::Assembled,
    );
    let blocks = op.assembled.clone().expect("assembled");
    assert!(
        crate::prefetch::outgrows_cache(&blocks),
        "{} blocks",
        blocks.len()
    );
    let pat = op.sys.caches.pattern.as_ref().expect("pattern");
    let p: Vec<V3> = (0..n)
        .map(|i| {
            V3::new(
                (i as f64).sin(),
                (0.3 * i as f64).cos(),
                1.0 / (1.0 + i as f64),
            )
        })
        .collect();
    let mut want = vec![V3::zeros(); n];
    pat.multiply_upper(&blocks, &p, &mut want);
    let scale = want.iter().map(|w| w.amax()).fold(0.0, f64::max);
    for pass in 0..2 {
        let mut got = vec![V3::zeros(); n];
        if pass == 0 {
            op.apply_once(&p, &mut got);
        } else {
            op.apply(&p, &mut got);
        }
        for (i, (w, g)) in want.iter().zip(&got).enumerate() {
            assert!(
                (w - g).amax() <= 1e-13 * scale,
                "pass {pass}, node {i}: {w} against {g}"
            );
        }
    }
    assert!(op.upper_rows.get().is_some() && op.full.get().is_none());
}
