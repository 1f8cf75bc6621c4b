//! Conformity, exact volume, refine/coarsen round trips, XOR state application.

mod common;

use common::*;
use cosurg_sim_lattice::{LatticeError, RegionState, StateDecodeError, TetId, TopologyEvent};
use proptest::prelude::*;

#[test]
fn kuhn_roots_are_conforming_and_mirrored() {
    let l = small_lattice(3);
    assert_eq!(l.root_count(), 30);
    assert_eq!(l.leaf_count(), 30);
    // 2×2×1 block: 3·3·2 corners, plus the extra cube's top 4.
    assert_eq!(l.node_count(), 22);
    check_invariants(&l);
    // Mirror layout: every root's refinement edge (the main diagonal) ends at the cube's
    // all-odd corner, i.e. the centres of the 2×2×2 supercubes are shared.
    for &t in l.leaves() {
        let (a, b) = l.refinement_edge(t);
        let u = l.units_per_cell();
        let odd = |g: [i64; 3]| g.iter().all(|v| (v / u).rem_euclid(2) == 1);
        let even = |g: [i64; 3]| g.iter().all(|v| (v / u).rem_euclid(2) == 0);
        assert!(even(l.node_grid(a)) && odd(l.node_grid(b)));
    }
}

#[test]
fn uniform_refinement_counts() {
    let mut l = small_lattice(3);
    let mut ev = vec![];
    let split = l.refine_where(|_, _| true, &mut ev);
    assert_eq!(l.leaf_count(), 30 * 8);
    assert_eq!(split, 30 * (1 + 2 + 4));
    check_invariants(&l);
    // Uniform 3-level refinement of cubes = the cube grid at half spacing: nodes of a
    // 5×5×3 grid minus the missing parts, counted directly.
    let nodes: std::collections::HashSet<[i64; 3]> = l.nodes().map(|n| l.node_grid(n)).collect();
    assert_eq!(nodes.len(), l.node_count());
    let added = ev
        .iter()
        .filter(|e| matches!(e, TopologyEvent::NodeAdded { .. }))
        .count();
    assert_eq!(added + 22, l.node_count());
    // Max depth is respected.
    let t = l.leaves()[0];
    assert!(matches!(
        l.refine(t, &mut ev),
        Err(LatticeError::MaxDepth { .. })
    ));
}

#[test]
fn single_refine_forces_coarser_neighbours() {
    let mut l = small_lattice(9);
    let mut ev = vec![];
    // Refine one corner deeply: conformity forces splits around it.
    for _ in 0..9 {
        let t = *l
            .leaves()
            .iter()
            .filter(|t| t.root == 0)
            .max_by_key(|t| (t.level(), std::cmp::Reverse(t.heap)))
            .unwrap();
        if t.level() >= 9 {
            break;
        }
        l.refine(t, &mut ev).unwrap();
        check_invariants(&l);
    }
    assert!(l.leaves().iter().any(|t| t.level() == 9));
    // Coarsen everything back, finest diamonds first.
    let nodes: Vec<_> = ev
        .iter()
        .filter_map(|e| match e {
            TopologyEvent::NodeAdded { node, .. } => Some(*node),
            _ => None,
        })
        .collect();
    for n in nodes.into_iter().rev() {
        assert!(l.coarsen_diamond(n, &mut ev).unwrap());
    }
    assert_eq!(l.leaf_count(), 30);
    assert_eq!(l.node_count(), 22);
    check_invariants(&l);
}

#[test]
fn region_state_bytes_round_trip_and_reject_garbage() {
    let mut l = small_lattice(6);
    let mut ev = vec![];
    for i in 0..20 {
        random_op(&mut l, true, i * 7919, &mut ev);
    }
    let s = l.region_state(&all_roots(&l));
    let bytes = s.to_bytes();
    assert_eq!(RegionState::from_bytes(&bytes).unwrap(), s);
    for cut in 0..bytes.len() {
        assert!(RegionState::from_bytes(&bytes[..cut]).is_err());
    }
    let mut long = bytes.clone();
    long.push(0);
    assert!(matches!(
        RegionState::from_bytes(&long),
        Err(StateDecodeError::Trailing(1))
    ));
    // A state whose split tet's parent is not split is refused by apply_state.
    let mut bad = vec![];
    bad.extend_from_slice(b"CSRS\x01\x01\x00\x01\x00");
    bad.extend_from_slice(&(1u64 << 2).to_le_bytes()); // heap 2 split, heap 1 not
    let bad = RegionState::from_bytes(&bad).unwrap();
    assert!(matches!(
        l.apply_state(&bad, &mut ev),
        Err(LatticeError::InvalidState(_))
    ));
}

fn ops() -> impl Strategy<Value = Vec<(bool, usize)>> {
    prop::collection::vec((prop::bool::weighted(0.7), any::<usize>()), 0..40)
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 40, ..ProptestConfig::default() })]

    #[test]
    fn random_refine_coarsen_keeps_invariants(ops in ops()) {
        let mut l = small_lattice(6);
        let mut ev = vec![];
        for (refine, pick) in ops {
            let before = node_snapshot(&l);
            ev.clear();
            random_op(&mut l, refine, pick, &mut ev);
            // Surviving node ids keep their positions; new nodes are edge midpoints.
            let removed: Vec<_> = ev.iter().filter_map(|e| match e {
                TopologyEvent::NodeRemoved { node } => Some(*node),
                _ => None,
            }).collect();
            for (n, g) in &before {
                if !removed.contains(n) {
                    prop_assert!(l.node_alive(*n));
                    prop_assert_eq!(l.node_grid(*n), *g);
                }
            }
            for e in &ev {
                if let TopologyEvent::NodeAdded { node, edge } = e
                    && l.node_alive(*node)
                {
                    let (a, b) = (l.node_grid(edge.0), l.node_grid(edge.1));
                    prop_assert_eq!(l.node_grid(*node), [0, 1, 2].map(|i| (a[i] + b[i]) / 2));
                }
            }
        }
        check_invariants(&l);
    }

    #[test]
    fn refine_then_coarsen_restores_state(ops in ops(), pick in any::<usize>()) {
        let mut l = small_lattice(6);
        let mut ev = vec![];
        for (refine, p) in ops {
            random_op(&mut l, refine, p, &mut ev);
        }
        let state = l.region_state(&all_roots(&l));
        let nodes = node_snapshot(&l);
        let leaves = sorted_leaves(&l);
        let t = l.leaves()[pick % l.leaf_count()];
        prop_assume!(t.level() < 6);
        ev.clear();
        l.refine(t, &mut ev).unwrap();
        // Merging the created diamonds in reverse order undoes the refinement exactly.
        for e in ev.clone().iter().rev() {
            if let TopologyEvent::NodeAdded { node, .. } = e {
                prop_assert!(l.coarsen_diamond(*node, &mut ev).unwrap());
            }
        }
        prop_assert_eq!(l.region_state(&all_roots(&l)), state);
        prop_assert_eq!(node_snapshot(&l), nodes);
        prop_assert_eq!(sorted_leaves(&l), leaves);
        // And directly: refining a tet whose diamond is complete, then coarsening it.
        let t = *l.leaves().iter().find(|t| t.level() < 6).unwrap();
        let before = l.region_state(&all_roots(&l));
        ev.clear();
        let n = l.refine(t, &mut ev).unwrap();
        let forced = ev.len() > 1;
        prop_assert!(n >= 1);
        if !forced {
            prop_assert!(l.coarsen(t, &mut ev).unwrap());
            prop_assert_eq!(l.region_state(&all_roots(&l)), before);
        }
    }

    #[test]
    fn xor_application_reaches_target(a_ops in ops(), b_ops in ops(), region_pick in any::<u32>()) {
        let mut a = small_lattice(6);
        let mut b = small_lattice(6);
        let mut ev = vec![];
        for (r, p) in a_ops { random_op(&mut a, r, p, &mut ev); }
        for (r, p) in b_ops { random_op(&mut b, r, p, &mut ev); }
        let roots = all_roots(&a);
        let target = b.region_state(&roots);
        let delta = a.region_state(&roots).xor(&target);
        let stats = a.apply_state(&target, &mut ev).unwrap();
        prop_assert_eq!(stats.residual, 0);
        prop_assert_eq!(stats.merges_blocked, 0);
        prop_assert_eq!(a.region_state(&roots), target.clone());
        prop_assert!(a.region_state(&roots).xor(&target).is_empty());
        prop_assert_eq!(sorted_leaves(&a), sorted_leaves(&b));
        prop_assert!(delta.len() >= stats.tets_split.min(delta.len()));
        check_invariants(&a);

        // A sub-region (one cell's roots): after applying, the region matches.
        let cell = (region_pick % (a.root_count() / 6)) * 6;
        let region: Vec<u32> = (cell..cell + 6).collect();
        let mut c = small_lattice(6);
        let sub = b.region_state(&region);
        let stats = c.apply_state(&sub, &mut ev).unwrap();
        prop_assert_eq!(stats.residual, 0);
        prop_assert_eq!(c.region_state(&region), sub);
        check_invariants(&c);
    }

    /// The constructor from split tets builds exactly the lattice's own state, whatever
    /// the order and repetition of the tets; tets of other roots and heap 0 are ignored.
    #[test]
    fn state_from_split_tets_matches_region_state(ops in ops(), region_pick in any::<u32>()) {
        let mut l = small_lattice(6);
        let mut ev = vec![];
        for (r, p) in ops { random_op(&mut l, r, p, &mut ev); }
        let all = all_roots(&l);
        let cell = (region_pick % (l.root_count() / 6)) * 6;
        let region: Vec<u32> = (cell..cell + 6).collect();
        for roots in [&all[..], &region[..]] {
            let s = l.region_state(roots);
            let mut tets: Vec<TetId> = l.region_state(&all).split_tets().collect();
            tets.reverse();
            tets.extend(s.split_tets());
            tets.push(TetId { root: roots[0], heap: 0 });
            let built = RegionState::from_split_tets(roots, tets);
            prop_assert_eq!(built.to_bytes(), s.to_bytes());
            prop_assert_eq!(built, s);
        }
    }

    /// Corrupting one bit or truncating a real encoding: an error or a state that
    /// re-encodes to itself, never a panic.
    #[test]
    fn region_state_decoder_survives_corruption(ops in ops(), flip in any::<usize>(), bit in 0u8..8, cut in any::<usize>()) {
        let mut l = small_lattice(6);
        let mut ev = vec![];
        for (r, p) in ops { random_op(&mut l, r, p, &mut ev); }
        let bytes = l.region_state(&all_roots(&l)).to_bytes();
        let mut corrupt = bytes.clone();
        let i = flip % corrupt.len();
        corrupt[i] ^= 1 << bit;
        let cut = cut % (bytes.len() + 1);
        for input in [&corrupt[..], &bytes[..cut]] {
            if let Ok(s) = RegionState::from_bytes(input) {
                prop_assert_eq!(RegionState::from_bytes(&s.to_bytes()).unwrap(), s);
            }
        }
    }

    #[test]
    fn region_state_decoder_never_panics(bytes in prop::collection::vec(any::<u8>(), 0..64)) {
        let mut with_header = b"CSRS\x01".to_vec();
        with_header.extend_from_slice(&bytes);
        for input in [&bytes, &with_header] {
            if let Ok(s) = RegionState::from_bytes(input) {
                prop_assert_eq!(RegionState::from_bytes(&s.to_bytes()).unwrap(), s);
            }
        }
    }
}

#[test]
fn apply_state_splits_outside_region_only_for_conformity() {
    let mut a = small_lattice(6);
    let mut b = small_lattice(6);
    let mut ev = vec![];
    // Refine the tets of root 0 deeply in b.
    b.refine_where(|_, t| t.root == 0 && t.level() < 5, &mut ev);
    let region = [0u32];
    let target = b.region_state(&region);
    a.apply_state(&target, &mut ev).unwrap();
    assert_eq!(a.region_state(&region), target);
    check_invariants(&a);
    // The lattice outside the region was refined no more than b (which needed the same
    // forced splits).
    assert!(a.leaf_count() <= b.leaf_count());
}

/// The root layout is one diamond hierarchy: every diamond's size follows the class that
/// the trailing zero bits of its centre give (DESIGN §2½), for interior diamonds.
#[test]
fn diamond_sizes_follow_centre_classes() {
    let cells: Vec<[i32; 3]> = (0..64)
        .map(|i| [i % 4 - 1, (i / 4) % 4 - 2, i / 16])
        .collect();
    let mut l = cosurg_sim_lattice::Lattice::from_cells(params(6), &cells).unwrap();
    let mut ev = vec![];
    l.refine_where(|_, t| t.level() < 6, &mut ev);
    let u = l.units_per_cell();
    let lo = [-u, -2 * u, 0];
    let hi = [3 * u, 2 * u, 4 * u];
    let mut seen = std::collections::HashMap::new();
    for t in all_tets(&l) {
        if l.is_leaf(t) {
            continue;
        }
        let (a, b) = l.refinement_edge(t);
        let (ga, gb) = (l.node_grid(a), l.node_grid(b));
        let c: [i64; 3] = [0, 1, 2].map(|i| (ga[i] + gb[i]) / 2);
        if (0..3).any(|i| c[i] <= lo[i] || c[i] >= hi[i]) {
            continue;
        }
        let s = c.iter().map(|v| v.trailing_zeros()).min().unwrap();
        let odd = c.iter().filter(|v| (*v >> s) & 1 == 1).count();
        let expected = match odd {
            3 => 6,
            2 => 4,
            _ => 8,
        };
        let d = l.diamond(t).unwrap();
        assert_eq!(d.len(), expected, "diamond at {c:?} (level {})", t.level());
        assert!(d.iter().all(|m| m.level() == t.level()));
        // The centre also gives the level: three tet levels per halving of the grid.
        let class = 3 - odd as u32;
        let level = 3 * (u.trailing_zeros() - 1 - s) + class;
        assert_eq!(u32::from(t.level()), level, "level of the diamond at {c:?}");
        *seen.entry(level).or_insert(0) += 1;
    }
    assert_eq!(seen.len(), 6, "interior diamonds of every level");
}
