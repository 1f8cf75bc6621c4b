//! The multigrid hierarchy of the lattice for sim-fem's MG-PCG
//! ([`sim_fem::LinearSolver::MgPcg`]): nested node sets by grid level, with the
//! prolongation of the bisection hierarchy (weight 1 for a node the coarser level keeps,
//! ½ and ½ from the ends of the edge a node bisects).
//!
//! A node's grid level is the number of trailing zero bits its integer grid coordinates
//! share: cube corners of the root cells have at least `log2(units_per_cell)`, the
//! midpoints of the first bisections of a cell one less, and so on. Level `k` of the
//! hierarchy holds the nodes whose level is at least `t₀ + k` (`t₀` the finest level
//! present). A node dropped on the way to level `k + 1` is the midpoint of its parent
//! edge (the lattice's bisection record) or, for a cube corner, of the edge of the
//! doubled Kuhn cube through it (the root cubes are mirror images of each other, so the
//! cube of twice the size is again a reflected Kuhn cube, whose diagonals run from the
//! corner ≡ 0 to the corner ≡ 2 (mod 4) in units of the node's spacing). A node whose
//! parents are missing (the edge leaves the domain) stays on the coarser level: on
//! adaptive lattices and odd cell counts the coarse levels are then not a uniform grid,
//! but every prolongation is still exact linear interpolation on the levels it links or
//! the identity, and the Galerkin products keep the coarse operators consistent.

use std::collections::HashMap;

use sim_fem::FemError;
use sim_fem::mg::{Hierarchy, Prolongation};
use sim_lattice::{Lattice, NodeId};

/// At most this many levels (a lattice of 2⁴⁰ cells would need more).
const MAX_LEVELS: usize = 40;

/// Level of a grid point: trailing zero bits shared by its coordinates (0 coordinates
/// do not count; the origin gets 62).
fn grid_level(g: [i64; 3]) -> u32 {
    g.iter()
        .map(|&c| if c == 0 { 62 } else { c.trailing_zeros() })
        .min()
        .unwrap_or(62)
        .min(62)
}

/// The hierarchy over the lattice's node slots (the FEM node numbering of
/// [`crate::Simulation`]: dead slots get empty rows). Stops when a level has fewer than
/// 8 nodes or no node could be dropped.
pub fn lattice_hierarchy(lattice: &Lattice) -> Result<Hierarchy, FemError> {
    let cap = lattice.node_capacity();
    let live: Vec<NodeId> = lattice.nodes().collect();
    let by_grid: HashMap<[i64; 3], usize> = live
        .iter()
        .map(|&n| (lattice.node_grid(n), n.0 as usize))
        .collect();
    let level: Vec<u32> = (0..cap)
        .map(|i| {
            let n = NodeId(i as u32);
            if lattice.node_alive(n) {
                grid_level(lattice.node_grid(n))
            } else {
                0
            }
        })
        .collect();
    let Some(t0) = live.iter().map(|n| level[n.0 as usize]).min() else {
        return Ok(Hierarchy::default());
    };
    // Position of each slot in the current level (`usize::MAX`: not in it); the finest
    // level is the slot numbering itself.
    let mut pos: Vec<usize> = (0..cap).collect();
    let mut current: Vec<usize> = live.iter().map(|n| n.0 as usize).collect();
    let mut current_len = cap;
    let mut levels = Vec::new();
    for k in 0..MAX_LEVELS {
        let t = t0 + k as u32;
        if current.len() < 8 || t >= 62 {
            break;
        }
        let in_level = |s: usize, pos: &[usize]| pos[s] != usize::MAX;
        // Parents (slots) of each node of level t, if both are kept.
        let parents = |s: usize, pos: &[usize]| -> Option<(usize, usize)> {
            let n = NodeId(s as u32);
            let (a, b) = match lattice.node_parent_edge(n) {
                Some((a, b)) => (a.0 as usize, b.0 as usize),
                None => {
                    let g = lattice.node_grid(n);
                    let step = 1i64 << t;
                    let mut lo = g;
                    let mut hi = g;
                    for ax in 0..3 {
                        if level_of_coord(g[ax]) == t {
                            let up = g[ax] + step;
                            let (x0, x1) = if up.rem_euclid(4 * step) == 0 {
                                (up, g[ax] - step)
                            } else {
                                (g[ax] - step, up)
                            };
                            lo[ax] = x0;
                            hi[ax] = x1;
                        }
                    }
                    (*by_grid.get(&lo)?, *by_grid.get(&hi)?)
                }
            };
            let kept = |p: usize| in_level(p, pos) && level[p] > t;
            (kept(a) && kept(b)).then_some((a, b))
        };
        let mut coarse = Vec::new();
        let mut interp = Vec::new();
        for &s in &current {
            match (level[s] == t).then(|| parents(s, &pos)).flatten() {
                Some(ab) => interp.push((s, ab)),
                None => coarse.push(s),
            }
        }
        if interp.is_empty() {
            // Nothing dropped at level t: done if no node lies above it, else try the
            // next level (no prolongation for this one).
            if current.iter().all(|&s| level[s] <= t) {
                break;
            }
            continue;
        }
        let mut coarse_pos = vec![usize::MAX; cap];
        for (i, &s) in coarse.iter().enumerate() {
            coarse_pos[s] = i;
        }
        let mut rows = vec![Vec::new(); current_len];
        for &s in &coarse {
            rows[pos[s]] = vec![(coarse_pos[s], 1.0)];
        }
        for &(s, (a, b)) in &interp {
            rows[pos[s]] = vec![(coarse_pos[a], 0.5), (coarse_pos[b], 0.5)];
        }
        levels.push(Prolongation::from_rows(coarse.len(), &rows)?);
        current_len = coarse.len();
        pos = coarse_pos;
        current = coarse;
    }
    Ok(Hierarchy { levels })
}

/// Trailing zero bits of one coordinate (0 counts as 62).
fn level_of_coord(c: i64) -> u32 {
    if c == 0 {
        62
    } else {
        c.trailing_zeros().min(62)
    }
}

#[cfg(test)]
mod tests;
