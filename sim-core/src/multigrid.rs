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
//! corner ≡ 0 to the corner ≡ 2 (mod 4) in units of the node's spacing).
//!
//! Where the domain ends at a coordinate that is not a multiple of the coarser spacing
//! (a box of 12 cells: the plane at 12 has no neighbour at 16), the node's edge along
//! that axis would leave the domain. That coordinate is then frozen, as the boundary at
//! 0 is: the node moves only along its other axes, so a boundary plane coarsens as a 2D
//! grid and a boundary line as a 1D one, instead of staying on every coarser level (which
//! stalled the 48 × 12 × 12-cell beam's hierarchy at 1,558 nodes). A node whose parents
//! are missing altogether (an adaptive lattice's grading) stays on the coarser level. The
//! coarse levels are then not a uniform grid, but every prolongation is still exact
//! linear interpolation (a midpoint between two kept nodes) or the identity, and the
//! Galerkin products keep the coarse operators consistent.

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
        let step = 1i64 << t;
        let in_level = |g: [i64; 3]| by_grid.get(&g).filter(|&&p| pos[p] != usize::MAX);
        // The axes along which the node of slot `s` moves to reach its parents at level
        // t (bit `ax` set), or `None` if it is not dropped at this level. A bisection
        // midpoint of level t moves along its parent edge (handled by the caller). A
        // grid node moves along every axis whose coordinate has level t, except an axis
        // on which its two neighbours at ±step do not both exist: the domain ends there
        // (a cell count that is not a power of two) and the coordinate is frozen like a
        // boundary at 0, so the node coarsens within that plane or line instead of
        // staying on every coarser level. A coordinate left below level t (a node kept
        // earlier for the same reason) is frozen as well.
        let moving_axes = |s: usize| -> Option<u8> {
            let g = lattice.node_grid(NodeId(s as u32));
            let mut axes = 0u8;
            for ax in 0..3 {
                let l = level_of_coord(g[ax]);
                if l > t {
                    continue;
                }
                let mut lo = g;
                let mut hi = g;
                lo[ax] -= step;
                hi[ax] += step;
                if l == t && in_level(lo).is_some() && in_level(hi).is_some() {
                    axes |= 1 << ax;
                }
            }
            // Dropped at level t only if no moving coordinate lies above it: the lowest
            // unfrozen coordinate level is t exactly when some axis moves.
            (axes != 0).then_some(axes)
        };
        let bisected =
            |s: usize| level[s] == t && lattice.node_parent_edge(NodeId(s as u32)).is_some();
        // Parents (slots) of a node dropped at level t, if both stay on the coarser level.
        let parents = |s: usize| -> Option<(usize, usize)> {
            let n = NodeId(s as u32);
            let (a, b) = if bisected(s) {
                let (a, b) = lattice.node_parent_edge(n)?;
                (a.0 as usize, b.0 as usize)
            } else {
                let axes = moving_axes(s)?;
                let g = lattice.node_grid(n);
                let mut lo = g;
                let mut hi = g;
                for ax in (0..3).filter(|ax| axes & (1 << ax) != 0) {
                    // The doubled Kuhn cube's diagonal runs from the corner ≡ 0 to the
                    // corner ≡ 2 (mod 4) in units of `step` (see the module docs).
                    let up = g[ax] + step;
                    let (x0, x1) = if up.rem_euclid(4 * step) == 0 {
                        (up, g[ax] - step)
                    } else {
                        (g[ax] - step, up)
                    };
                    lo[ax] = x0;
                    hi[ax] = x1;
                }
                (*in_level(lo)?, *in_level(hi)?)
            };
            let dropped = |p: usize| bisected(p) || moving_axes(p).is_some();
            let kept = |p: usize| pos[p] != usize::MAX && !dropped(p);
            (kept(a) && kept(b)).then_some((a, b))
        };
        let mut coarse = Vec::new();
        let mut interp = Vec::new();
        for &s in &current {
            match parents(s) {
                Some(ab) => interp.push((s, ab)),
                None => coarse.push(s),
            }
        }
        if interp.is_empty() {
            // Nothing dropped at level t: done if no coordinate lies above it, else try
            // the next level (no prolongation for this one).
            let above = |s: usize| {
                let g = lattice.node_grid(NodeId(s as u32));
                g.iter().any(|&c| c != 0 && level_of_coord(c) > t)
            };
            if !current.iter().any(|&s| above(s)) {
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
