//! Unit tests of the cut: exact predicates, volume fractions against sampled volumes,
//! separation of a refined block, surface cutting and capping, and order independence of
//! the topology.

use std::path::Path;

use nalgebra::Vector3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use sim_scene::{Scene, TriMesh};

use super::separate::{fractions, leaf_components};
use super::*;
use crate::{SimOptions, Simulation};

type V3 = Vector3<f64>;

fn plane_x(x: f64, half: f64) -> Vec<[V3; 3]> {
    let p = |y: f64, z: f64| V3::new(x, y, z);
    vec![
        [p(-half, -half), p(half, -half), p(half, half)],
        [p(-half, -half), p(half, half), p(-half, half)],
    ]
}

fn cut_op(site: u32, seq: u32, tris: &[[V3; 3]]) -> TopologyOp {
    TopologyOp::Cut(CutOp {
        id: OpId { site, seq },
        triangles: tris.iter().map(|t| t.map(|p| [p.x, p.y, p.z])).collect(),
    })
}

#[test]
fn segment_crossing_is_exact_and_ties_go_to_the_positive_side() {
    let tri = [
        V3::new(0., 0., 0.),
        V3::new(1., 0., 0.),
        V3::new(0., 1., 0.),
    ];
    let cross = |a: V3, b: V3| predicates::segment_crossing(&tri, &a, &b);
    assert_eq!(
        cross(V3::new(0.2, 0.2, -1.), V3::new(0.2, 0.2, 1.)),
        Some(0.5)
    );
    assert_eq!(cross(V3::new(0.8, 0.8, -1.), V3::new(0.8, 0.8, 1.)), None);
    // On the plane counts as the side where orient3d is positive: below a triangle that is
    // counter-clockwise seen from above (-z here).
    assert!(predicates::side(&tri, &V3::new(0.2, 0.2, -1.)));
    assert!(cross(V3::new(0.2, 0.2, 0.), V3::new(0.2, 0.2, -1.)).is_none());
    assert!(cross(V3::new(0.2, 0.2, 0.), V3::new(0.2, 0.2, 1.)).is_some());
    // Through the triangle's edge: the closed triangle counts.
    assert!(cross(V3::new(0.5, 0.0, -1.), V3::new(0.5, 0.0, 1.)).is_some());
    // Tiny offsets that round-off would get wrong are decided exactly.
    let eps = f64::EPSILON * 0.25;
    assert!(cross(V3::new(0.1, 0.1, eps), V3::new(0.1, 0.1, -eps)).is_some());
    assert!(!predicates::non_degenerate(&[
        V3::new(0., 0., 0.),
        V3::new(1., 1., 1.),
        V3::new(2., 2., 2.)
    ]));
}

/// Volume fraction on the corner side of a plane, by sampling the tet on a barycentric
/// grid (an independent reference).
fn sampled_fraction(p: &[V3; 4], x0: f64, mask: u8) -> f64 {
    let n = 60;
    let (mut inside, mut total) = (0usize, 0usize);
    // Side of the copy: the side of its first real corner.
    let k = (0..4).find(|k| mask & (1 << k) != 0).expect("a corner");
    let positive = p[k].x >= x0;
    for i in 0..n {
        for j in 0..n - i {
            for l in 0..n - i - j {
                let (a, b, c) = (
                    (i as f64 + 0.25) / n as f64,
                    (j as f64 + 0.25) / n as f64,
                    (l as f64 + 0.25) / n as f64,
                );
                let q = p[0] + a * (p[1] - p[0]) + b * (p[2] - p[0]) + c * (p[3] - p[0]);
                total += 1;
                if (q.x >= x0) == positive {
                    inside += 1;
                }
            }
        }
    }
    inside as f64 / total as f64
}

#[test]
fn volume_fractions_match_sampled_volumes_and_sum_to_one() {
    let mut rng = ChaCha8Rng::seed_from_u64(12);
    let mut checked = 0;
    while checked < 40 {
        let p: [V3; 4] = std::array::from_fn(|_| {
            V3::new(
                rng.random_range(0.0..1.0),
                rng.random_range(0.0..1.0),
                rng.random_range(0.0..1.0),
            )
        });
        let vol = ((p[1] - p[0]).cross(&(p[2] - p[0])))
            .dot(&(p[3] - p[0]))
            .abs()
            / 6.0;
        if vol < 0.01 {
            continue;
        }
        let x0 = rng.random_range(0.2..0.8);
        let sheet = Sheet::new(plane_x(x0, 10.0));
        let (masks, cut) = leaf_components(&sheet, &p);
        if masks.len() < 2 {
            continue;
        }
        assert_eq!(masks.len(), 2, "a plane makes two components");
        let f = fractions(&p, &cut, &masks);
        assert_eq!(f[0] + f[1], 1.0);
        for (m, fi) in masks.iter().zip(&f) {
            let reference = sampled_fraction(&p, x0, *m);
            // The sampling grid's error is about 3/n of the volume.
            assert!(
                (fi - reference).abs() < 0.05,
                "mask {m:04b}: fraction {fi}, sampled {reference}"
            );
        }
        checked += 1;
    }
}

/// The 8 × 4 × 4 cm block on a 2 cm lattice (max depth 3), fixed at x = 0, with `extra`
/// scene text appended (also the clip tests' scene).
pub(crate) fn block_scene(extra: &str) -> Simulation {
    let text = format!(
        r#"
[material.soft]
young = 2.0e4
poisson = 0.4
density = 1000.0

[[body]]
name = "block"
box = {{ min = [0.0, 0.0, 0.0], max = [0.08, 0.04, 0.04] }}
cell = 0.02
max_depth = 3
material = "soft"

[[fix]]
box = {{ min = [-0.001, -1.0, -1.0], max = [0.001, 1.0, 1.0] }}
{extra}
"#
    );
    let scene = Scene::from_str(&text, Path::new("."), "block.toml").expect("scene");
    let options = SimOptions::from_scene(&scene.scene);
    Simulation::new(scene, options).expect("simulation")
}

/// Connected groups of degrees of freedom over the element copies.
fn part_count(sep: &Separation) -> usize {
    let n = sep.dof_count();
    let mut parent: Vec<usize> = (0..n).collect();
    fn find(p: &mut [usize], mut i: usize) -> usize {
        while p[i] != i {
            p[i] = p[p[i]];
            i = p[i];
        }
        i
    }
    let mut used = vec![false; n];
    for c in &sep.copies {
        for k in 0..4 {
            used[c.dofs[k]] = true;
            let (a, b) = (find(&mut parent, c.dofs[0]), find(&mut parent, c.dofs[k]));
            parent[a.max(b)] = a.min(b);
        }
    }
    (0..n)
        .filter(|&d| used[d] && find(&mut parent, d) == d)
        .count()
}

#[test]
fn a_plane_separates_a_refined_block_into_two_parts_with_real_nodes_on_their_side() {
    let mut sim = block_scene("");
    let volume = sim.element_rest_volume();
    let x0 = 0.0313;
    let change = sim
        .apply_topology_op(cut_op(0, 0, &plane_x(x0, 1.0)))
        .expect("cut");
    assert!(change.applied && change.crossed > 0 && change.virtual_nodes > 0);
    assert!(
        change.refined > 0,
        "refined to the deepest level along the cut"
    );
    let sep = sim.separation().expect("cut").clone();
    assert_eq!(part_count(&sep), 2);
    let lat = sim.lattice();
    for &t in &sep.crossed {
        assert_eq!(
            t.level(),
            lat.params().max_depth,
            "crossed leaves are deepest"
        );
        let nodes = lat.tet_nodes(t);
        for c in sep.copies_of(t) {
            for k in 0..4 {
                if c.mask & (1 << k) != 0 {
                    // A real corner is on the side of the copy's other real corners.
                    let first = (0..4).find(|j| c.mask & (1 << j) != 0).unwrap();
                    let side = |n: sim_lattice::NodeId| lat.node_rest(n).x >= x0;
                    assert_eq!(side(nodes[k]), side(nodes[first]));
                    assert!(c.dofs[k] < sep.capacity, "real corners keep lattice slots");
                }
            }
        }
    }
    assert!((sim.element_rest_volume() - volume).abs() < 1e-15);
    // Both sides' surfaces are closed, and the parts follow their own nodes.
    let s = &sim.surfaces()[0];
    assert!(s.rest.is_closed() && s.rest.is_outward_oriented());
    // Less the hair-thin offsets of the cut vertices (1e-4 of their edges).
    assert!((s.rest.signed_volume() - volume).abs() < 1e-4 * volume);
}

fn cube_mesh(size: f64) -> TriMesh {
    let v = |x: f64, y: f64, z: f64| V3::new(x * size, y * size, z * size);
    TriMesh {
        vertices: vec![
            v(0., 0., 0.),
            v(1., 0., 0.),
            v(1., 1., 0.),
            v(0., 1., 0.),
            v(0., 0., 1.),
            v(1., 0., 1.),
            v(1., 1., 1.),
            v(0., 1., 1.),
        ],
        triangles: vec![
            [0, 2, 1],
            [0, 3, 2],
            [4, 5, 6],
            [4, 6, 7],
            [0, 1, 5],
            [0, 5, 4],
            [1, 2, 6],
            [1, 6, 5],
            [2, 3, 7],
            [2, 7, 6],
            [3, 0, 4],
            [3, 4, 7],
        ],
    }
}

#[test]
fn a_cut_surface_is_two_closed_outward_parts_and_a_partial_cut_is_reported() {
    let cube = cube_mesh(1.0);
    assert!(cube.is_outward_oriented());
    let cut = cut_surface(&cube, &Sheet::new(plane_x(0.3, 5.0))).expect("through cut");
    assert_eq!(cut.loops, 2, "one loop per side");
    assert!(cut.mesh.is_closed() && cut.mesh.is_outward_oriented());
    // Each side's cap is a unit square (two triangles at least); the volume is the cube's
    // less the two hair-thin offsets (1e-4 of the edges next to the cut).
    assert!(cut.cap_triangles >= 4);
    assert!((cut.mesh.signed_volume() - 1.0).abs() < 1e-3);
    // A sheet that ends inside the surface cannot be capped.
    let half = vec![[
        V3::new(0.3, -1.0, -1.0),
        V3::new(0.3, 3.0, -1.0),
        V3::new(0.3, -1.0, 0.5),
    ]];
    assert!(matches!(
        cut_surface(&cube, &Sheet::new(half)),
        Err(SurfaceCutError::Partial { .. })
    ));
}

/// The (leaf, mask, fraction) of every copy: the element set independent of node ids.
fn element_set(sim: &Simulation) -> Vec<(u32, u32, u8, u64)> {
    sim.separation()
        .expect("cut")
        .copies
        .iter()
        .map(|c| (c.leaf.root, c.leaf.heap, c.mask, c.fraction.to_bits()))
        .collect()
}

#[test]
fn the_same_ops_in_any_order_with_duplicates_give_the_same_topology() {
    let op1 = cut_op(1, 0, &plane_x(0.0313, 1.0));
    let yz = |y: f64| {
        let p = |x: f64, z: f64| V3::new(x, y, z);
        vec![
            [p(0.04, -1.0), p(1.0, -1.0), p(1.0, 1.0)],
            [p(0.04, -1.0), p(1.0, 1.0), p(0.04, 1.0)],
        ]
    };
    let op2 = cut_op(2, 0, &yz(0.0213));

    let mut a = block_scene("");
    for op in [&op1, &op2, &op1] {
        a.apply_topology_op(op.clone()).unwrap();
    }
    let mut b = block_scene("");
    for op in [&op2, &op1, &op2, &op2] {
        b.apply_topology_op(op.clone()).unwrap();
    }
    assert_eq!(a.topology().epoch(), 2);
    assert_eq!(a.topology().digest(), b.topology().digest());
    assert_eq!(element_set(&a), element_set(&b));
    assert_eq!(a.lattice().leaf_count(), b.lattice().leaf_count());
    assert_eq!(
        a.separation().unwrap().virtual_nodes.len(),
        b.separation().unwrap().virtual_nodes.len()
    );
    // A site that lost op1 recovers it from another site's log (a snapshot).
    let mut c = block_scene("");
    c.apply_topology_op(op2.clone()).unwrap();
    assert_ne!(c.topology().digest(), a.topology().digest());
    for op in a.topology().ops().cloned().collect::<Vec<_>>() {
        c.apply_topology_op(op).unwrap();
    }
    assert_eq!(c.topology().digest(), a.topology().digest());
    assert_eq!(element_set(&c), element_set(&a));
    // Three parts: the x cut separates the fixed end, the y cut splits the other side.
    assert_eq!(part_count(a.separation().unwrap()), 3);
    // Rejected: a degenerate triangle.
    let bad = cut_op(3, 0, &[[V3::zeros(), V3::x(), 2.0 * V3::x()]]);
    assert!(matches!(
        a.apply_topology_op(bad),
        Err(crate::SimError::Topology(_))
    ));
}
