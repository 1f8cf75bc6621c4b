//! Response: penalty contact with damping and regularised Coulomb friction, grasp
//! capture and holding, and each tool's reaction and local model (see the module docs of
//! [`super`]).

use nalgebra::{Matrix3, Vector3};
use sim_lattice::Embedding;

use super::detection::closest_point_triangle;
use super::{Anchor, ContactPipeline, ContactPoint, Grasp, Hit};
use crate::engine::Simulation;
use crate::tools::ToolSet;

type V3 = Vector3<f64>;

impl ContactPipeline {
    /// Adds force `f` (N) applied at `point` with node `weights` (and, if given, the
    /// spring matrix `k` of its stiffness, lumped by rows) to the output, and its reaction
    /// to tool `ti`.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn apply(
        &mut self,
        ti: usize,
        tip: &V3,
        weights: &[(u32, f64)],
        point: &V3,
        f: &V3,
        k: Option<&Matrix3<f64>>,
    ) {
        let sum_abs: f64 = weights.iter().map(|(_, w)| w.abs()).sum();
        for &(n, w) in weights {
            let i = n as usize;
            if i >= self.state.node_force.len() {
                continue;
            }
            if !self.node_mark[i] {
                self.node_mark[i] = true;
                self.touched.push(n);
            }
            self.state.node_force[i] += f * w;
            if let Some(k) = k {
                self.node_k[i] += k * (w.abs() * sum_abs);
            }
        }
        let t = &mut self.state.tools[ti];
        t.force -= f;
        t.torque -= (point - tip).cross(f);
    }

    /// Adds a spring of tool-side stiffness `k` at lever arm `r` to tool `ti`'s model.
    pub(super) fn add_local(&mut self, ti: usize, r: &V3, k: &Matrix3<f64>) {
        let rx = r.cross_matrix();
        let s = &mut self.state.tools[ti].local.stiffness;
        let kr = k * rx;
        let rk = rx * k;
        let rkr = rx * k * rx;
        for i in 0..3 {
            for j in 0..3 {
                s[(i, j)] -= k[(i, j)];
                s[(i, 3 + j)] += kr[(i, j)];
                s[(3 + i, j)] -= rk[(i, j)];
                s[(3 + i, 3 + j)] += rkr[(i, j)];
            }
        }
    }

    /// Point on global triangle `t` at `bary` (m).
    pub(super) fn tri_point(&mut self, sim: &Simulation, t: u32, bary: &[f64; 3]) -> V3 {
        let v = self.tri_vertices(sim, t);
        v[0] * bary[0] + v[1] * bary[1] + v[2] * bary[2]
    }

    /// Nearest point to `q` on the last query's candidate triangles.
    pub(super) fn project(&self, q: &V3) -> Option<(u32, [f64; 3])> {
        let mut best: Option<(u32, [f64; 3], f64)> = None;
        for c in &self.last_cands {
            let (p, bary) = closest_point_triangle(q, &c.v[0], &c.v[1], &c.v[2]);
            let d = (p - q).norm_squared();
            if best.as_ref().is_none_or(|b| d < b.2) {
                best = Some((c.tri, bary, d));
            }
        }
        best.map(|(t, b, _)| (t, b))
    }

    /// Penalty, damping and friction forces of tool `ti`'s penetrating samples.
    pub(super) fn respond(
        &mut self,
        sim: &Simulation,
        tools: &ToolSet,
        ti: usize,
        hits: &[Option<Hit>],
        dt: f64,
    ) {
        let tool = &tools.tools[ti];
        let tip = tool.tip();
        let v = sim.velocities();
        let mut w: Vec<(u32, f64)> = Vec::with_capacity(12);
        let mut wa: Vec<(u32, f64)> = Vec::with_capacity(12);
        for (si, hit) in hits.iter().enumerate() {
            let s = tool.world_samples()[si];
            let Some(h) = hit.filter(|h| (h.point - s).dot(&h.normal) > 0.0) else {
                self.memory[ti].anchors[si] = None;
                continue;
            };
            // Softer on tissue collapsing towards inversion (`Hit::weight`).
            let mut p = self.params;
            p.stiffness *= h.weight;
            p.damping *= h.weight;
            p.tangential_stiffness *= h.weight;
            let n = h.normal;
            let depth = (h.point - s).dot(&n);
            self.tri_weights(sim, h.tri, &h.bary, &mut w);
            let vp: V3 = w.iter().map(|&(i, wi)| v[i as usize] * wi).sum();
            let vt = tool.point_velocity(&s);
            let fn_spring = p.stiffness * depth;
            let nn = n * n.transpose();
            // Damping −c (v_p − v_t)·n: the tissue part is implicit (c/dt in the stiffness
            // block), the tool part explicit; off when the total would pull.
            let damped = fn_spring + p.damping * (vp - vt).dot(&n) > 0.0 && p.damping > 0.0;
            let mut f = -n * fn_spring;
            let mut kn = nn * p.stiffness;
            if damped {
                f += n * (p.damping * vt.dot(&n));
                kn += nn * (p.damping / dt);
            }
            self.apply(ti, &tip, &w, &h.point, &f, Some(&kn));
            let mut total = f;
            let mut k_tool = nn * p.stiffness;
            // Friction: spring from the surface anchor to the sample, capped at μ k_c d.
            let mut sticking = false;
            if p.friction > 0.0 && p.tangential_stiffness > 0.0 {
                let cap = p.friction * fn_spring;
                let proj = Matrix3::identity() - nn;
                let mut anchor = self.memory[ti].anchors[si].unwrap_or(Anchor {
                    tri: h.tri,
                    bary: h.bary,
                });
                let mut a = self.tri_point(sim, anchor.tri, &anchor.bary);
                let mut ft = -(proj * (a - s)) * p.tangential_stiffness;
                sticking = ft.norm() <= cap;
                if !sticking {
                    // Slide the anchor so that the spring sits at the cap.
                    let ratio = cap / ft.norm();
                    let q = s + proj * (a - s) * ratio;
                    if let Some((tri, bary)) = self.project(&q) {
                        anchor = Anchor { tri, bary };
                        a = self.tri_point(sim, tri, &bary);
                        ft = -(proj * (a - s)) * p.tangential_stiffness;
                    }
                    let norm = ft.norm();
                    if norm > cap && norm > 0.0 {
                        ft *= cap / norm;
                    }
                }
                self.memory[ti].anchors[si] = Some(anchor);
                self.tri_weights(sim, anchor.tri, &anchor.bary, &mut wa);
                let kt = proj * p.tangential_stiffness;
                self.apply(ti, &tip, &wa, &a, &ft, sticking.then_some(&kt));
                if sticking {
                    k_tool += kt;
                }
                total += ft;
            }
            self.add_local(ti, &(s - tip), &k_tool);
            let (surface, triangle) = self.tri_owner[h.tri as usize];
            let rest_pose = &sim.surfaces()[surface as usize].rest;
            let corners = rest_pose.triangles[triangle as usize];
            let rest: V3 = (0..3)
                .map(|j| rest_pose.vertices[corners[j] as usize] * h.bary[j])
                .sum();
            let t = &mut self.state.tools[ti];
            t.max_depth = t.max_depth.max(depth);
            t.contacts.push(ContactPoint {
                sample: si,
                surface: surface as usize,
                triangle: triangle as usize,
                bary: h.bary,
                point: h.point,
                rest,
                normal: n,
                weight: h.weight,
                depth,
                force: total,
                sticking,
            });
        }
        self.state.stats.contacts += self.state.tools[ti].contacts.len() as u64;
    }

    /// Attaches the surface points nearest to the jaw samples (within the capture
    /// distance, or under the surface) to the jaws.
    pub(super) fn capture(
        &mut self,
        sim: &Simulation,
        tools: &ToolSet,
        ti: usize,
        hits: &[Option<Hit>],
    ) -> Option<Grasp> {
        let tool = &tools.tools[ti];
        let min_sep = 0.25 * tool.radius;
        let mut rest: Vec<V3> = Vec::new();
        let mut cur: Vec<V3> = Vec::new();
        for (si, h) in hits.iter().enumerate() {
            let Some(h) = h else { continue };
            let s = tool.world_samples()[si];
            let inside = (h.point - s).dot(&h.normal) > 0.0;
            if !(inside || h.dist <= self.params.grasp_capture) {
                continue;
            }
            if cur.iter().any(|c| (c - h.point).norm() < min_sep) {
                continue;
            }
            let (sidx, k) = self.tri_owner[h.tri as usize];
            let surf = &sim.surfaces()[sidx as usize];
            let tri = surf.rest.triangles[k as usize];
            rest.push(
                (0..3)
                    .map(|j| surf.rest.vertices[tri[j] as usize] * h.bary[j])
                    .sum(),
            );
            cur.push(h.point);
        }
        if rest.is_empty() {
            return None;
        }
        let embedding = match Embedding::new(sim.lattice(), &rest) {
            Ok(e) => e,
            Err(e) => {
                tracing::warn!(error = %e, tool = %tool.name, "grasp: cannot embed points");
                return None;
            }
        };
        let mut pos = vec![V3::zeros(); rest.len()];
        embedding.interpolate(sim.lattice(), sim.positions(), &mut pos);
        let inv = tool.pose().rotation.inverse();
        let offsets = pos.iter().map(|p| inv * (p - tool.tip())).collect();
        tracing::debug!(tool = %tool.name, t = sim.time(), points = rest.len(), "grasp");
        Some(Grasp {
            embedding,
            offsets,
            alive: vec![true; rest.len()],
        })
    }

    /// Grasp springs of tool `ti`; `None` when every point tore loose.
    pub(super) fn apply_grasp(
        &mut self,
        sim: &Simulation,
        tools: &ToolSet,
        ti: usize,
        mut grasp: Grasp,
        dt: f64,
    ) -> Option<Grasp> {
        let tool = &tools.tools[ti];
        let tip = tool.tip();
        let p = self.params;
        grasp.embedding.update(sim.lattice());
        let count = grasp.embedding.len();
        let mut pos = vec![V3::zeros(); count];
        grasp
            .embedding
            .interpolate(sim.lattice(), sim.positions(), &mut pos);
        let k = Matrix3::identity() * (p.grasp_stiffness + p.grasp_damping / dt);
        let k_tool = Matrix3::identity() * p.grasp_stiffness;
        let tears = self.grasp_tears.get(ti).copied().unwrap_or(true);
        let mut w: Vec<(u32, f64)> = Vec::with_capacity(4);
        for (j, pj) in pos.iter().enumerate() {
            if !grasp.alive[j] {
                continue;
            }
            let target = tip + tool.pose().rotation * grasp.offsets[j];
            if tears && (target - pj).norm() > p.grasp_tear {
                grasp.alive[j] = false;
                continue;
            }
            let vt = tool.point_velocity(&target);
            let f = (target - pj) * p.grasp_stiffness + vt * p.grasp_damping;
            let (_, wts, nodes) = grasp.embedding.host(j);
            w.clear();
            w.extend((0..4).map(|i| (nodes[i].0, wts[i])));
            self.apply(ti, &tip, &w, pj, &f, Some(&k));
            self.add_local(ti, &(target - tip), &k_tool);
            let rest: V3 = (0..4)
                .map(|i| sim.lattice().node_rest(nodes[i]) * wts[i])
                .sum();
            let t = &mut self.state.tools[ti];
            t.grasped += 1;
            t.grasped_points.push(*pj);
            t.grasped_rest.push(rest);
        }
        if self.state.tools[ti].grasped == 0 {
            tracing::debug!(tool = %tool.name, t = sim.time(), "grasp torn loose");
            return None;
        }
        Some(grasp)
    }
}
