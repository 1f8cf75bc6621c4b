//! Unit tests of clips: one clip per closing of the jaws on tissue, ends that follow an
//! affine motion of the lattice exactly, a clip that stays with its side of a cut, and
//! clip and cut ops that commute.

use nalgebra::{Matrix3, UnitQuaternion, Vector3};

use super::*;
use crate::Simulation;
use crate::cut::CutOp;
use crate::tools::ToolInput;

type V3 = Vector3<f64>;

/// The 8 × 4 × 4 cm block of the cut tests (fixed at x = 0) with a clip applier whose
/// closed jaws are 1 cm long, pointing down.
fn block_with_applier() -> Simulation {
    crate::cut::tests::block_scene(
        r#"
[[tool]]
name = "clip applier"
kind = "clip-applier"
position = [0.06, 0.02, 0.1]
length = 0.01
"#,
    )
}

fn drive(
    sim: &mut Simulation,
    clips: &mut ClipApplication,
    tools: &mut ToolSet,
    tip: V3,
    jaw: f64,
) -> usize {
    let input = ToolInput::new(tip, UnitQuaternion::identity(), jaw);
    tools.tools[0].set_input(&input, sim.options().dt);
    clips.update(sim, tools).expect("clip")
}

fn cut_plane_x(x: f64) -> TopologyOp {
    let p = |y: f64, z: f64| [x, y, z];
    TopologyOp::Cut(CutOp {
        id: OpId { site: 2, seq: 0 },
        triangles: vec![
            [p(-1.0, -1.0), p(1.0, -1.0), p(1.0, 1.0)],
            [p(-1.0, -1.0), p(1.0, 1.0), p(-1.0, 1.0)],
        ],
    })
}

#[test]
fn one_clip_per_closing_of_the_jaws_on_tissue_and_none_in_air() {
    let mut sim = block_with_applier();
    let mut tools = ToolSet::from_specs(&sim.scene().scene.tools);
    let mut clips = ClipApplication::new(&tools, 1);
    let air = V3::new(0.06, 0.02, 0.1);
    let inside = V3::new(0.06, 0.02, 0.015);
    // Closing in the air: nothing to clip.
    assert_eq!(drive(&mut sim, &mut clips, &mut tools, air, 0.6), 0);
    assert_eq!(drive(&mut sim, &mut clips, &mut tools, air, 0.0), 0);
    // Open, move into the block, close: one clip; staying closed adds none.
    assert_eq!(drive(&mut sim, &mut clips, &mut tools, inside, 0.6), 0);
    assert_eq!(drive(&mut sim, &mut clips, &mut tools, inside, 0.0), 1);
    assert_eq!(drive(&mut sim, &mut clips, &mut tools, inside, 0.0), 0);
    // Open and close again: a second clip.
    assert_eq!(drive(&mut sim, &mut clips, &mut tools, inside, 0.6), 0);
    assert_eq!(drive(&mut sim, &mut clips, &mut tools, inside, 0.05), 1);
    assert_eq!(clips.made.len(), 2);
    assert_eq!(sim.clips().len(), 2);
    assert_eq!(sim.topology().epoch(), 2);
    // The ends are where the jaws closed (tip and hinge), within rounding: the rest
    // mapping and the embedding are inverse maps on the undeformed block.
    for [a, b] in sim.clip_positions() {
        assert!((a - inside).norm() < 1e-12, "tip end {a:?}");
        assert!(
            (b - (inside + V3::new(0.0, 0.0, 0.01))).norm() < 1e-12,
            "hinge end {b:?}"
        );
    }
    // A clip without length is refused with a clear error.
    let bad = TopologyOp::Clip(ClipOp {
        id: OpId {
            site: 3,
            seq: CLIP_SEQ_BASE,
        },
        ends: [[0.01, 0.01, 0.01]; 2],
    });
    match sim.apply_topology_op(bad) {
        Err(SimError::Topology(e)) => assert!(e.contains("apart"), "{e}"),
        other => panic!("expected a topology error, got {other:?}"),
    }
}

#[test]
fn clip_ends_follow_an_affine_motion_of_the_tissue_exactly() {
    let mut sim = block_with_applier();
    let op = TopologyOp::Clip(ClipOp {
        id: OpId {
            site: 1,
            seq: CLIP_SEQ_BASE,
        },
        ends: [[0.0537, 0.0123, 0.0071], [0.0611, 0.0291, 0.0302]],
    });
    sim.apply_topology_op(op.clone()).expect("clip");
    // An affine map of every node (rotation, stretch and shear, then a shift): embedded
    // points reproduce it exactly, up to rounding.
    let a = Matrix3::new(1.1, 0.2, -0.05, -0.1, 0.9, 0.15, 0.05, -0.2, 1.2)
        * UnitQuaternion::from_euler_angles(0.3, -0.2, 0.5).to_rotation_matrix();
    let shift = V3::new(0.01, -0.02, 0.03);
    let n = sim.positions().len();
    for d in 0..n {
        let p = a * sim.lattice().node_rest(sim_lattice::NodeId(d as u32)) + shift;
        if sim.lattice().node_alive(sim_lattice::NodeId(d as u32)) {
            sim.set_dof_state(d, p, V3::zeros());
        }
    }
    let TopologyOp::Clip(c) = &op else {
        unreachable!()
    };
    let [ra, rb] = c.end_points();
    let [wa, wb] = sim.clip_positions()[0];
    assert!((wa - (a * ra + shift)).norm() < 1e-12);
    assert!((wb - (a * rb + shift)).norm() < 1e-12);
}

#[test]
fn a_clip_stays_with_its_side_of_a_cut_in_either_order() {
    let far = TopologyOp::Clip(ClipOp {
        id: OpId {
            site: 1,
            seq: CLIP_SEQ_BASE,
        },
        ends: [[0.06, 0.02, 0.015], [0.06, 0.02, 0.025]],
    });
    let near = TopologyOp::Clip(ClipOp {
        id: OpId {
            site: 1,
            seq: CLIP_SEQ_BASE + 1,
        },
        ends: [[0.012, 0.02, 0.015], [0.012, 0.02, 0.025]],
    });
    let cut = cut_plane_x(0.0313);
    let mut a = block_with_applier();
    for op in [&far, &near, &cut, &far] {
        a.apply_topology_op(op.clone()).expect("op");
    }
    let mut b = block_with_applier();
    for op in [&cut, &near, &cut, &far] {
        b.apply_topology_op(op.clone()).expect("op");
    }
    assert_eq!(a.topology().epoch(), 3);
    assert_eq!(a.topology().digest(), b.topology().digest());
    assert_eq!(a.clip_positions(), b.clip_positions());
    // The free part falls under gravity and takes its clip along; the clip on the part
    // fixed at x = 0 stays within a few mm (that part only sags).
    let start = a.clip_positions();
    for _ in 0..100 {
        a.step().expect("step");
    }
    let t = a.time();
    let end = a.clip_positions();
    let drop = |i: usize| start[i][0].z - end[i][0].z;
    // Free fall would be g t² / 2; the free part starts at rest and falls freely.
    let free_fall = 0.5 * 9.81 * t * t;
    assert!(
        drop(0) > 0.5 * free_fall,
        "the clip on the free part fell {:.4} m in {t} s (free fall {free_fall:.4} m)",
        drop(0)
    );
    assert!(
        drop(1).abs() < 0.005,
        "the clip on the fixed part moved {:.4} m",
        drop(1)
    );
}
