//! Unit tests of the private parts of the sync layer (the public API is tested in
//! `sim-core/tests/sync.rs`).

use super::motion::{Motion, MotionSet};
use super::*;

fn keyframe(sim_time: f64, positions: Vec<[f64; 3]>, velocities: Vec<[f64; 3]>) -> RegionKeyframe {
    RegionKeyframe {
        region: 0,
        keyframe_id: 1,
        sim_time,
        tree_bits: Vec::new(),
        positions,
        velocities,
    }
}

/// `x + v d + ½ a d²`, `v + a d`, with `d` clamped to the horizon on both sides.
#[test]
fn motion_is_second_order_and_holds_past_the_horizon() {
    let m = Motion {
        x: V3::new(1.0, 0.0, 0.0),
        v: V3::new(0.0, 2.0, 0.0),
        a: V3::new(0.0, 0.0, -4.0),
        t0: 10.0,
    };
    let (x, v) = m.eval(10.25, 0.5);
    assert!((x - V3::new(1.0, 0.5, -0.125)).norm() < 1e-12);
    assert!((v - V3::new(0.0, 2.0, -1.0)).norm() < 1e-12);
    assert_eq!(m.eval(11.0, 0.5), m.eval(10.5, 0.5));
    assert_eq!(m.eval(9.0, 0.5), m.eval(9.5, 0.5));
}

/// The acceleration is the velocity difference between keyframes over their time
/// difference, clamped in magnitude; the first keyframe has none.
#[test]
fn motion_set_estimates_and_clamps_acceleration() {
    let grids = [[0, 0, 0], [2, 0, 0]];
    let mut set = MotionSet::default();
    set.take_keyframe(
        &grids,
        &keyframe(1.0, vec![[0.0; 3]; 2], vec![[0.0; 3]; 2]),
        50.0,
    );
    assert_eq!(set.motions[&grids[0]].a, V3::zeros());
    // 0.1 s later: node 0 gained 1 m/s (10 m/s²), node 1 gained 100 m/s (clamped to 50).
    set.take_keyframe(
        &grids,
        &keyframe(
            1.1,
            vec![[0.0; 3]; 2],
            vec![[1.0, 0.0, 0.0], [0.0, 100.0, 0.0]],
        ),
        50.0,
    );
    assert!((set.motions[&grids[0]].a - V3::new(10.0, 0.0, 0.0)).norm() < 1e-9);
    assert!((set.motions[&grids[1]].a - V3::new(0.0, 50.0, 0.0)).norm() < 1e-9);
    assert_eq!(set.motions[&grids[1]].t0, 1.1);
}

/// A tree delta against a keyframe toggles exactly the tets it names.
#[test]
fn xor_state_toggles_named_tets() {
    use sim_lattice::{RegionState, TetId};
    let roots = [0, 1];
    let tet = |root, heap| TetId { root, heap };
    let base = RegionState::from_split_tets(&roots, [tet(0, 1), tet(0, 2), tet(1, 1)]);
    let delta = RegionState::from_split_tets(&roots, [tet(0, 2), tet(1, 2)]);
    let want = RegionState::from_split_tets(&roots, [tet(0, 1), tet(1, 1), tet(1, 2)]);
    assert_eq!(super::frame::xor_state(&base, &delta), want);
    assert_eq!(
        RegionState::from_bytes(&encode_tree_xor(&base, &want)).unwrap(),
        RegionState::from_split_tets(&roots, [tet(0, 2), tet(1, 2)])
    );
}
