//! Detection: the two-level hierarchy over the tet forest (roots, then leaves), the
//! candidate triangles of a query box, and each tool sample's nearest surface point (see
//! the module docs of [`super`]).

use std::collections::HashMap;

use nalgebra::Vector3;
use sim_lattice::TetId;

use super::{Cand, ContactPipeline, Hit, STRETCH, Topology};
use crate::cut::predicates::orient3d;
use crate::engine::Simulation;
use crate::tools::ToolSet;

type V3 = Vector3<f64>;

impl ContactPipeline {
    pub(super) fn refresh_topology(&mut self, sim: &Simulation) {
        let lat = sim.lattice();
        if self.topo.generation == Some(lat.topology_generation())
            && self.topo.root_node_start.len() == lat.root_count() as usize + 1
        {
            return;
        }
        self.state.stats.cache_rebuilds += 1;
        let roots = lat.root_count() as usize;
        let leaves = lat.leaves();
        // Leaves per root.
        let mut count = vec![0u32; roots + 1];
        for t in leaves {
            count[t.root as usize + 1] += 1;
        }
        for r in 0..roots {
            count[r + 1] += count[r];
        }
        let mut fill = count.clone();
        let mut root_leaves = vec![0u32; leaves.len()];
        for (i, t) in leaves.iter().enumerate() {
            let slot = &mut fill[t.root as usize];
            root_leaves[*slot as usize] = i as u32;
            *slot += 1;
        }
        // Unique nodes per root.
        let mut root_node_start = Vec::with_capacity(roots + 1);
        let mut root_nodes = Vec::new();
        root_node_start.push(0u32);
        let mut buf: Vec<u32> = Vec::new();
        for r in 0..roots {
            buf.clear();
            for &li in &root_leaves[count[r] as usize..count[r + 1] as usize] {
                buf.extend(lat.leaf_tet_nodes(li as usize).iter().map(|n| n.0));
            }
            buf.sort_unstable();
            buf.dedup();
            root_nodes.extend_from_slice(&buf);
            root_node_start.push(root_nodes.len() as u32);
        }
        // Triangles per leaf (by the hosts of their vertices).
        let leaf_index: HashMap<TetId, u32> = leaves
            .iter()
            .enumerate()
            .map(|(i, t)| (*t, i as u32))
            .collect();
        let mut pairs: Vec<(u32, u32)> = Vec::with_capacity(3 * self.tri_owner.len());
        let mut gid = 0u32;
        for surf in sim.surfaces() {
            let host_leaf: Vec<u32> = (0..surf.embedding.len())
                .map(|v| {
                    let (t, _, _) = surf.embedding.host(v);
                    leaf_index.get(&t).copied().unwrap_or(u32::MAX)
                })
                .collect();
            for tri in &surf.rest.triangles {
                let mut ls = tri.map(|v| host_leaf[v as usize]);
                ls.sort_unstable();
                for k in 0..3 {
                    if ls[k] != u32::MAX && (k == 0 || ls[k] != ls[k - 1]) {
                        pairs.push((ls[k], gid));
                    }
                }
                gid += 1;
            }
        }
        pairs.sort_unstable();
        let mut leaf_tri_start = vec![0u32; leaves.len() + 1];
        for &(l, _) in &pairs {
            leaf_tri_start[l as usize + 1] += 1;
        }
        for l in 0..leaves.len() {
            leaf_tri_start[l + 1] += leaf_tri_start[l];
        }
        let mut leaf_reach = vec![0.0f64; leaves.len()];
        for &(l, t) in &pairs {
            leaf_reach[l as usize] =
                leaf_reach[l as usize].max(STRETCH * self.tri_edge[t as usize]);
        }
        let root_reach = (0..roots)
            .map(|r| {
                root_leaves[count[r] as usize..count[r + 1] as usize]
                    .iter()
                    .map(|&l| leaf_reach[l as usize])
                    .fold(0.0, f64::max)
            })
            .collect();
        self.topo = Topology {
            generation: Some(lat.topology_generation()),
            leaf_reach,
            root_reach,
            root_node_start,
            root_nodes,
            root_leaf_start: count,
            root_leaves,
            leaf_tri_start,
            leaf_tris: pairs.into_iter().map(|(_, t)| t).collect(),
        };
    }

    pub(super) fn refit_roots(&mut self, sim: &Simulation) {
        let x = sim.positions();
        let roots = self.topo.root_node_start.len() - 1;
        self.root_lo.resize(roots, V3::zeros());
        self.root_hi.resize(roots, V3::zeros());
        for r in 0..roots {
            let (a, b) = (
                self.topo.root_node_start[r] as usize,
                self.topo.root_node_start[r + 1] as usize,
            );
            let mut lo = V3::repeat(f64::INFINITY);
            let mut hi = V3::repeat(f64::NEG_INFINITY);
            for &n in &self.topo.root_nodes[a..b] {
                let p = &x[n as usize];
                lo = lo.inf(p);
                hi = hi.sup(p);
            }
            self.root_lo[r] = lo;
            self.root_hi[r] = hi;
        }
    }

    /// Candidate triangles whose vertices may lie within `margin` of the box `lo..hi`.
    pub(super) fn candidates(&mut self, sim: &Simulation, lo: V3, hi: V3) -> Vec<Cand> {
        // A triangle within the margin of the box has a vertex within its own (deformed)
        // longest edge of the margin box, and that vertex's host leaf contains it.
        let (mlo, mhi) = (
            lo.add_scalar(-self.params.margin),
            hi.add_scalar(self.params.margin),
        );
        let lat = sim.lattice();
        let x = sim.positions();
        self.stamp = self.stamp.wrapping_add(1);
        if self.stamp == 0 {
            self.tri_stamp.iter_mut().for_each(|s| *s = 0);
            self.stamp = 1;
        }
        let mut tris: Vec<u32> = Vec::new();
        let stats = &mut self.state.stats;
        for r in 0..self.root_lo.len() {
            stats.root_tests += 1;
            let reach = self.topo.root_reach[r];
            if !overlaps(
                &self.root_lo[r],
                &self.root_hi[r],
                &mlo.add_scalar(-reach),
                &mhi.add_scalar(reach),
            ) {
                continue;
            }
            let (a, b) = (
                self.topo.root_leaf_start[r] as usize,
                self.topo.root_leaf_start[r + 1] as usize,
            );
            for &li in &self.topo.root_leaves[a..b] {
                stats.leaf_tests += 1;
                let nodes = lat.leaf_tet_nodes(li as usize);
                let mut llo = V3::repeat(f64::INFINITY);
                let mut lhi = V3::repeat(f64::NEG_INFINITY);
                for n in nodes {
                    llo = llo.inf(&x[n.0 as usize]);
                    lhi = lhi.sup(&x[n.0 as usize]);
                }
                let reach = self.topo.leaf_reach[li as usize];
                if !overlaps(&llo, &lhi, &mlo.add_scalar(-reach), &mhi.add_scalar(reach)) {
                    continue;
                }
                let (ta, tb) = (
                    self.topo.leaf_tri_start[li as usize] as usize,
                    self.topo.leaf_tri_start[li as usize + 1] as usize,
                );
                for &t in &self.topo.leaf_tris[ta..tb] {
                    if self.tri_stamp[t as usize] != self.stamp {
                        self.tri_stamp[t as usize] = self.stamp;
                        tris.push(t);
                    }
                }
            }
        }
        stats.candidate_triangles += tris.len() as u64;
        let m = self.params.margin;
        let mut out = Vec::with_capacity(tris.len());
        for t in tris {
            let v = self.tri_vertices(sim, t);
            let tlo = v[0].inf(&v[1]).inf(&v[2]).add_scalar(-m);
            let thi = v[0].sup(&v[1]).sup(&v[2]).add_scalar(m);
            if !overlaps(&tlo, &thi, &lo, &hi) {
                continue;
            }
            let n = (v[1] - v[0]).cross(&(v[2] - v[0]));
            let nn = n.norm();
            if nn <= 0.0 || !nn.is_finite() {
                continue;
            }
            out.push(Cand {
                tri: t,
                v,
                lo: tlo,
                hi: thi,
                n: n / nn,
            });
        }
        out
    }

    /// Deformed vertices of global triangle `t`, interpolated from the node positions.
    /// (Cached for the pass: `x` does not change during a pass.)
    pub(super) fn tri_vertices(&mut self, sim: &Simulation, t: u32) -> [V3; 3] {
        let (s, k) = self.tri_owner[t as usize];
        let surf = &sim.surfaces()[s as usize];
        let tri = surf.rest.triangles[k as usize];
        let x = sim.positions();
        let base = self.vert_base[s as usize];
        tri.map(|v| {
            let g = (base + v) as usize;
            if self.vert_stamp[g] != self.pass {
                // After a cut: the copy on the vertex's side (virtual nodes included).
                let (n, w) = sim.surface_vertex_host(s as usize, v as usize);
                self.vert_pos[g] =
                    x[n[0]] * w[0] + x[n[1]] * w[1] + x[n[2]] * w[2] + x[n[3]] * w[3];
                self.vert_stamp[g] = self.pass;
            }
            self.vert_pos[g]
        })
    }

    /// Contact weight of the point with barycentrics `bary` on global triangle `t`, at
    /// this pass's positions. Each vertex has `ω_v = clamp(J / J_fade, 0, 1)`, with
    /// `J = det F` of its host leaf and `J_fade` the [`ContactParams::fade_volume_ratio`]
    /// (non-positive or NaN `J`: 0). The point's weight is 0 when a vertex's is (the
    /// triangle is inside out), else the vertices' weights interpolated, so that it is
    /// continuous across the edges between triangles. Computed only for the triangles
    /// samples end up nearest to, and cached per vertex for the pass.
    fn contact_weight(&mut self, sim: &Simulation, t: u32, bary: &[f64; 3]) -> f64 {
        let (s, k) = self.tri_owner[t as usize];
        let base = self.vert_base[s as usize];
        let x = sim.positions();
        let corners = sim.surfaces()[s as usize].rest.triangles[k as usize];
        let mut weight = 0.0;
        for (v, b) in corners.into_iter().zip(bary) {
            let g = (base + v) as usize;
            if self.weight_stamp[g] != self.pass {
                let (n, _) = sim.surface_vertex_host(s as usize, v as usize);
                // A ratio of two orientations of the same node order: the order's sign
                // cancels, and the sign of the deformed one is exact (every site agrees on
                // which leaves are inverted).
                let rest = n.map(|d| sim.dof_rest_position(d));
                let j = orient3d(&x[n[0]], &x[n[1]], &x[n[2]], &x[n[3]])
                    / orient3d(&rest[0], &rest[1], &rest[2], &rest[3]);
                self.vert_weight[g] = if j > 0.0 {
                    (j / self.params.fade_volume_ratio).clamp(0.0, 1.0)
                } else {
                    0.0
                };
                self.weight_stamp[g] = self.pass;
            }
            if self.vert_weight[g] <= 0.0 {
                return 0.0;
            }
            weight += b * self.vert_weight[g];
        }
        weight
    }

    /// Node weights of a point on global triangle `t` with barycentrics `bary`.
    pub(super) fn tri_weights(
        &self,
        sim: &Simulation,
        t: u32,
        bary: &[f64; 3],
        out: &mut Vec<(u32, f64)>,
    ) {
        out.clear();
        let (s, k) = self.tri_owner[t as usize];
        let surf = &sim.surfaces()[s as usize];
        let tri = surf.rest.triangles[k as usize];
        for (v, b) in tri.iter().zip(bary) {
            let (n, w) = sim.surface_vertex_host(s as usize, *v as usize);
            for j in 0..4 {
                out.push((n[j] as u32, b * w[j]));
            }
        }
    }

    /// Nearest surface point within the margin of every sample of tool `ti`.
    pub(super) fn detect(
        &mut self,
        sim: &Simulation,
        tools: &ToolSet,
        ti: usize,
    ) -> Vec<Option<Hit>> {
        let tool = &tools.tools[ti];
        let samples = tool.world_samples();
        let mut hits = vec![None; samples.len()];
        let (lo, hi) = tool.aabb(0.0);
        let cands = self.candidates(sim, lo, hi);
        if cands.is_empty() {
            return hits;
        }
        let m = self.params.margin;
        let mut tests = 0u64;
        for (s, hit) in samples.iter().zip(hits.iter_mut()) {
            let mut best: Option<Hit> = None;
            for c in &cands {
                if !contains(&c.lo, &c.hi, s) {
                    continue;
                }
                tests += 1;
                let (p, bary) = closest_point_triangle(s, &c.v[0], &c.v[1], &c.v[2]);
                let dist = (s - p).norm();
                if dist > m {
                    continue;
                }
                let better = match &best {
                    None => true,
                    Some(b) => {
                        if dist < b.dist - 1e-12 * m {
                            true
                        } else if dist <= b.dist + 1e-12 * m {
                            // Shared edge or vertex: prefer the face that sees the sample
                            // most squarely (decides inside/outside correctly at edges).
                            let d = s - p;
                            d.dot(&c.n).abs() > (s - b.point).dot(&b.normal).abs()
                        } else {
                            false
                        }
                    }
                };
                if better {
                    best = Some(Hit {
                        weight: 1.0,
                        tri: c.tri,
                        bary,
                        point: p,
                        normal: c.n,
                        dist,
                    });
                }
            }
            // An inverted leaf turns the triangles it hosts inside out: their normals point
            // into the tissue, so a sample nearest to one would read as deep and push the
            // tissue further through itself, and the next triangle out would read deeper
            // still. Such a sample touches nothing until the elements' own restoring force
            // (the inversion rule of `sim_fem::polar`) has brought them back out; nearer
            // inversion it touches more softly (`ContactParams::fade_volume_ratio`), so
            // that contact does not switch off in one step.
            if let Some(b) = &mut best {
                b.weight = self.contact_weight(sim, b.tri, &b.bary);
            }
            if best.is_some_and(|b| b.weight <= 0.0) {
                self.state.stats.samples_on_inverted += 1;
                best = None;
            }
            *hit = best;
        }
        self.state.stats.narrow_tests += tests;
        // Friction anchors need the candidates again only on slip; keep them.
        self.last_cands = cands;
        hits
    }
}

#[inline]
fn overlaps(alo: &V3, ahi: &V3, blo: &V3, bhi: &V3) -> bool {
    (0..3).all(|k| alo[k] <= bhi[k] && blo[k] <= ahi[k])
}

#[inline]
fn contains(lo: &V3, hi: &V3, p: &V3) -> bool {
    (0..3).all(|k| lo[k] <= p[k] && p[k] <= hi[k])
}

/// Closest point to `p` on triangle `abc` and its barycentrics (Ericson, Real-Time
/// Collision Detection §5.1.5).
pub fn closest_point_triangle(p: &V3, a: &V3, b: &V3, c: &V3) -> (V3, [f64; 3]) {
    let ab = b - a;
    let ac = c - a;
    let ap = p - a;
    let d1 = ab.dot(&ap);
    let d2 = ac.dot(&ap);
    if d1 <= 0.0 && d2 <= 0.0 {
        return (*a, [1.0, 0.0, 0.0]);
    }
    let bp = p - b;
    let d3 = ab.dot(&bp);
    let d4 = ac.dot(&bp);
    if d3 >= 0.0 && d4 <= d3 {
        return (*b, [0.0, 1.0, 0.0]);
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        let v = d1 / (d1 - d3);
        return (a + ab * v, [1.0 - v, v, 0.0]);
    }
    let cp = p - c;
    let d5 = ab.dot(&cp);
    let d6 = ac.dot(&cp);
    if d6 >= 0.0 && d5 <= d6 {
        return (*c, [0.0, 0.0, 1.0]);
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        let w = d2 / (d2 - d6);
        return (a + ac * w, [1.0 - w, 0.0, w]);
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        let w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        return (b + (c - b) * w, [0.0, 1.0 - w, w]);
    }
    let denom = 1.0 / (va + vb + vc);
    let v = vb * denom;
    let w = vc * denom;
    (a + ab * v + ac * w, [1.0 - v - w, v, w])
}
