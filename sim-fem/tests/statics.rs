//! Static solves: cantilever vs Timoshenko, co-rotational vs StVK at small loads, large
//! rotations, and the volume of a body rotated by 90°.

mod common;
use common::*;

use cosurg_sim_fem::{Material, Model, StaticParams, StiffnessMode};
use nalgebra::Rotation3;

const L: f64 = 0.4;
const W: f64 = 0.1;

/// Timoshenko tip deflection (m) of a cantilever under a tip shear force `p` (N):
/// `δ = P L³/(3 E I) + P L/(κ G A)`, `I = W⁴/12`, `A = W²`, `G = E/(2(1+ν))`, with
/// Cowper's shear coefficient for a rectangle `κ = 10(1+ν)/(12+11ν)`.
fn timoshenko(p: f64, e: f64, nu: f64) -> f64 {
    let i = W.powi(4) / 12.0;
    let a = W * W;
    let g = e / (2.0 * (1.0 + nu));
    let kappa = 10.0 * (1.0 + nu) / (12.0 + 11.0 * nu);
    p * L.powi(3) / (3.0 * e * i) + p * L / (kappa * g * a)
}

fn static_tip(cells: [usize; 3], model: Model, p: f64, e: f64, nu: f64) -> (f64, V3, usize) {
    let (mesh, mut sys) = beam(cells, Material::new(e, nu, 1000.0), true);
    let f = tip_load(&mesh, V3::new(0.0, 0.0, -p));
    let mut x = mesh.rest.clone();
    let st = sys
        .solve_static(model, &mut x, &f, &StaticParams::default())
        .unwrap();
    assert!(st.converged, "{cells:?} {model:?}: {st:?}");
    (
        -tip_displacement(&mesh, &x).z,
        tip_displacement(&mesh, &x),
        st.iterations,
    )
}

#[test]
fn cantilever_converges_to_timoshenko() {
    // E = 1e5 Pa, ν = 0.3, P = 1e-3 N (δ ≈ 2.6e-5 m: linear regime).
    let (e, nu, p) = (1e5, 0.3, 1e-3);
    let reference = timoshenko(p, e, nu);
    let mut errs = Vec::new();
    for cells in [[4, 1, 1], [8, 2, 2], [16, 4, 4], [32, 8, 8]] {
        let (d, _, _) = static_tip(cells, Model::Linear, p, e, nu);
        let err = (d - reference) / reference;
        eprintln!("{cells:?}: tip {d:.6e} m, Timoshenko {reference:.6e} m, rel. error {err:+.4}");
        errs.push(err);
    }
    // Kuhn tets are too stiff at coarse meshes: errors negative and shrinking, the
    // error ratio per halving tending to the asymptotic O(h²) value 1/4.
    for w in errs.windows(2) {
        assert!(w[0] < 0.0 && w[1].abs() < 0.7 * w[0].abs(), "{errs:?}");
    }
    // Finest (12,288 tets): within 10 %.
    assert!(errs[3].abs() < 0.10, "{errs:?}");
    // For information: Richardson extrapolation from the last three meshes (not yet in
    // the asymptotic range, so no assertion on it).
    let d: Vec<f64> = errs.iter().map(|e| (1.0 + e) * reference).collect();
    let q = (d[3] - d[2]) / (d[2] - d[1]);
    let extrapolated = d[3] + (d[3] - d[2]) * q / (1.0 - q);
    let e_ex = (extrapolated - reference) / reference;
    eprintln!("observed ratio {q:.3}, extrapolated {extrapolated:.6e} m, rel. error {e_ex:+.4}");
}

#[test]
fn corotational_and_stvk_agree_to_first_order() {
    // Difference of the two models ∝ load²: halving P quarters ‖x_cr − x_stvk‖.
    let (e, nu) = (1e5, 0.45);
    let cells = [8, 2, 2];
    let mut diffs = Vec::new();
    for p in [0.4, 0.2, 0.1] {
        let (mesh, mut sys) = beam(cells, Material::new(e, nu, 1000.0), true);
        let f = tip_load(&mesh, V3::new(0.0, 0.0, -p));
        let mut xc = mesh.rest.clone();
        let mut xs = mesh.rest.clone();
        let sp = StaticParams::default();
        assert!(
            sys.solve_static(Model::Corotational, &mut xc, &f, &sp)
                .unwrap()
                .converged
        );
        assert!(
            sys.solve_static(Model::StVK, &mut xs, &f, &sp)
                .unwrap()
                .converged
        );
        let d: Vec<V3> = xc.iter().zip(&xs).map(|(a, b)| a - b).collect();
        let u: Vec<V3> = xc.iter().zip(&mesh.rest).map(|(a, b)| a - b).collect();
        eprintln!(
            "P = {p} N: |u| = {:.3e} m, |x_cr − x_stvk| = {:.3e} m",
            norm(&u),
            norm(&d)
        );
        diffs.push(norm(&d));
    }
    for w in diffs.windows(2) {
        let ratio = w[0] / w[1];
        assert!((3.5..4.5).contains(&ratio), "ratio {ratio} (expect 4)");
    }
}

#[test]
fn large_rotation_static_newton_converges() {
    // E = 1e5 Pa, ν = 0.45, dead tip load 60 N on 192 tets: tip rotation > 60°.
    let (mesh, mut sys) = beam([8, 2, 2], Material::new(1e5, 0.45, 1000.0), true);
    let f = tip_load(&mesh, V3::new(0.0, 0.0, -60.0));
    for model in [Model::StVK, Model::Corotational] {
        let mut x = mesh.rest.clone();
        let sp = StaticParams {
            initial_increment: 0.25,
            ..Default::default()
        };
        let st = sys.solve_static(model, &mut x, &f, &sp).unwrap();
        // Tip rotation: angle of the tip face's vertical centre line.
        let top = mesh.node(8, 1, 2);
        let bottom = mesh.node(8, 1, 0);
        let d = (x[top] - x[bottom]).normalize();
        let angle = d.z.clamp(-1.0, 1.0).acos().to_degrees();
        eprintln!(
            "{model:?}: {} Newton iterations, {} increments ({} rejected), residual {:.2e} N \
             (tol {:.1e} N), {} CG iterations, tip rotation {angle:.1}°",
            st.iterations,
            st.load_steps,
            st.rejected_steps,
            st.residual,
            st.tolerance,
            st.cg_iterations
        );
        assert!(st.converged && st.residual <= st.tolerance);
        assert!(angle > 60.0, "{model:?}: only {angle}°");
    }
}

#[test]
fn volume_under_90_degree_rotation() {
    // Beam E = 1e6 Pa, ν = 0.45 under gravity; the clamped face is rotated about the
    // y axis through (0, 0, 0) in 10 increments of 9°, static solve after each.
    let mat = Material::new(1e6, 0.45, 1000.0);
    let (mesh, mut sys) = beam([8, 2, 2], mat, true);
    let v0 = sys.rest_volume();
    let f = vec![V3::zeros(); mesh.rest.len()];
    let sp = StaticParams {
        gravity: V3::new(0.0, 0.0, -9.81),
        ..Default::default()
    };
    for model in [Model::Corotational, Model::Linear] {
        let mut x = mesh.rest.clone();
        for k in 1..=10 {
            let r = Rotation3::from_axis_angle(&V3::y_axis(), -(9.0 * k as f64).to_radians());
            for (i, fx) in sys.fixed().to_vec().iter().enumerate() {
                if *fx {
                    x[i] = r * mesh.rest[i];
                }
            }
            let st = sys.solve_static(model, &mut x, &f, &sp).unwrap();
            assert!(st.converged, "{model:?} step {k}: {st:?}");
        }
        let dv = sys.deformed_volume(&x) / v0 - 1.0;
        eprintln!("{model:?}: relative volume change after 90° = {dv:+.4}");
        match model {
            Model::Corotational => assert!(dv.abs() < 0.01),
            _ => assert!(dv > 0.05, "linear should grow: {dv}"),
        }
        let _ = StiffnessMode::Template;
    }
}
