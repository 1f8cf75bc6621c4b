//! Conforming bisection: the diamond around a refinement edge, refine (splitting coarser
//! neighbours first so that no hanging node appears), coarsen (merging a whole diamond back)
//! and refinement by a predicate. See the parent module's docs for the bisection rule.

#[allow(unused_imports)]
use super::*;

impl Lattice {
    // ----------------------------------------------------------------------------------
    // Refinement

    pub(super) fn ref_edge_rec(&self, r: u32) -> (NodeId, NodeId) {
        let rec = &self.tets[r as usize];
        (rec.nodes[0], rec.nodes[tag(rec.level)])
    }

    /// The tets around the refinement edge of `r`: leaves (`stop_level = None`) or the tets
    /// of `r`'s own level. Walks face to face both ways from `r`.
    pub(super) fn ring_around(
        &self,
        r: u32,
        stop_level: Option<u8>,
    ) -> Result<Vec<u32>, LatticeError> {
        let rec = &self.tets[r as usize];
        let k = tag(rec.level);
        let (u, v) = (rec.nodes[0], rec.nodes[k]);
        let (o1, o2) = others(k);
        let (w1, w2) = (rec.nodes[o1], rec.nodes[o2]);
        let mut ring = Vec::with_capacity(8);
        ring.push(r);
        if !self.walk_around(u, v, r, w1, w2, stop_level, &mut ring)? {
            self.walk_around(u, v, r, w2, w1, stop_level, &mut ring)?;
        }
        Ok(ring)
    }

    /// Walks around edge `u–v` from `start` across the face `(u, v, keep)`; returns whether
    /// the walk closed (interior edge) or hit the boundary.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn walk_around(
        &self,
        u: NodeId,
        v: NodeId,
        start: u32,
        mut keep: NodeId,
        mut opposite: NodeId,
        stop_level: Option<u8>,
        out: &mut Vec<u32>,
    ) -> Result<bool, LatticeError> {
        for _ in 0..MAX_RING {
            let Some(n) = self.neighbor_across([u, v, keep], opposite, stop_level) else {
                return Ok(false);
            };
            if n == start {
                return Ok(true);
            }
            let nodes = self.tets[n as usize].nodes;
            let face = [u, v, keep];
            if !face.iter().all(|f| nodes.contains(f)) {
                return Err(LatticeError::Internal(
                    "face neighbour does not share the face (non-conforming mesh)",
                ));
            }
            let w = *nodes
                .iter()
                .find(|x| !face.contains(x))
                .expect("a tet has a fourth vertex");
            out.push(n);
            opposite = keep;
            keep = w;
        }
        Err(LatticeError::Internal("walk around an edge did not close"))
    }

    /// The diamond of `t`: the tets of `t`'s level around its refinement edge, `t` first,
    /// in walking order around the edge (6 tets around a cube's main diagonal, 4 around a
    /// face diagonal, 8 around an axis edge; fewer at the domain boundary). Where the mesh
    /// around the edge is still coarser than `t`, the coarser leaf is listed instead (the
    /// diamond is then incomplete, and refining `t` first splits that leaf).
    pub fn diamond(&self, t: TetId) -> Result<Vec<TetId>, LatticeError> {
        let r = self.rec_of(t).ok_or(LatticeError::NoSuchTet(t))?;
        Ok(self
            .ring_around(r, Some(t.level()))?
            .into_iter()
            .map(|m| self.tets[m as usize].id)
            .collect())
    }

    /// Splits leaf `t` and, first, every coarser tet that conformity requires; splits the
    /// whole diamond of `t`'s refinement edge. Returns the number of tets split (0 when `t`
    /// is already split).
    ///
    /// # Errors
    /// [`LatticeError::NoSuchTet`] if `t` does not exist; [`LatticeError::MaxDepth`] if `t`
    /// is a leaf at `max_depth` (nothing is changed).
    pub fn refine(
        &mut self,
        t: TetId,
        events: &mut Vec<TopologyEvent>,
    ) -> Result<usize, LatticeError> {
        let r = self.rec_of(t).ok_or(LatticeError::NoSuchTet(t))?;
        if self.tets[r as usize].first_child != NONE {
            return Ok(0);
        }
        if t.level() >= self.params.max_depth {
            return Err(LatticeError::MaxDepth {
                tet: t,
                max_depth: self.params.max_depth,
            });
        }
        self.refine_rec(r, events)
    }

    pub(super) fn refine_rec(
        &mut self,
        r: u32,
        events: &mut Vec<TopologyEvent>,
    ) -> Result<usize, LatticeError> {
        let mut split = 0;
        while self.tets[r as usize].first_child == NONE {
            let (u, v) = self.ref_edge_rec(r);
            let ring = self.ring_around(r, None)?;
            // A leaf around the edge with another refinement edge is coarser: split it
            // first (Maubach's recursion), then look again.
            if let Some(&m) = ring
                .iter()
                .find(|&&m| !same_edge(self.ref_edge_rec(m), (u, v)))
            {
                if self.tets[m as usize].level >= self.tets[r as usize].level {
                    return Err(LatticeError::Internal(
                        "a neighbour around the refinement edge is not coarser",
                    ));
                }
                split += self.refine_rec(m, events)?;
                continue;
            }
            let z = self.alloc_node(midpoint(self.grid(u), self.grid(v)), (u, v), r);
            events.push(TopologyEvent::NodeAdded {
                node: z,
                edge: (u, v),
            });
            for &m in &ring {
                self.split_rec(m, z);
            }
            self.generation += 1;
            split += ring.len();
        }
        Ok(split)
    }

    pub(super) fn split_rec(&mut self, r: u32, z: NodeId) {
        let rec = self.tets[r as usize].clone();
        let k = tag(rec.level);
        let kids = child_nodes(rec.nodes, k, z);
        let fc = match self.free_pairs.pop() {
            Some(fc) => fc,
            None => {
                self.tets.push(rec.clone());
                self.tets.push(rec.clone());
                self.tets.len() as u32 - 2
            }
        };
        for (i, nodes) in kids.into_iter().enumerate() {
            let x = nodes.map(|n| self.grid(n));
            self.tets[fc as usize + i] = TetRec {
                nodes,
                first_child: NONE,
                leaf_slot: NONE,
                id: TetId {
                    root: rec.id.root,
                    heap: 2 * rec.id.heap + i as u32,
                },
                level: rec.level + 1,
                positive: orient(x[0], x[1], x[2], x[3]) > 0,
            };
        }
        self.tets[r as usize].first_child = fc;
        self.remove_leaf(r);
        self.push_leaf(fc);
        self.push_leaf(fc + 1);
    }

    /// Merges the diamond that `parent` belongs to (all tets split at `parent`'s refinement
    /// edge) back, if every one of its tets has two leaf children. Returns `Ok(false)` when
    /// `parent` is a leaf or a finer split depends on the diamond.
    pub fn coarsen(
        &mut self,
        parent: TetId,
        events: &mut Vec<TopologyEvent>,
    ) -> Result<bool, LatticeError> {
        let r = self.rec_of(parent).ok_or(LatticeError::NoSuchTet(parent))?;
        if self.tets[r as usize].first_child == NONE {
            return Ok(false);
        }
        self.coarsen_rec(r, events)
    }

    /// Merges the diamond centred at node `centre` (see [`Lattice::coarsen`]).
    pub fn coarsen_diamond(
        &mut self,
        centre: NodeId,
        events: &mut Vec<TopologyEvent>,
    ) -> Result<bool, LatticeError> {
        match self.nodes.get(centre.0 as usize) {
            Some(n) if n.alive && n.diamond != NONE => self.coarsen_rec(n.diamond, events),
            _ => Err(LatticeError::NoSuchDiamond(centre)),
        }
    }

    pub(super) fn coarsen_rec(
        &mut self,
        r: u32,
        events: &mut Vec<TopologyEvent>,
    ) -> Result<bool, LatticeError> {
        let level = self.tets[r as usize].level;
        let edge = self.ref_edge_rec(r);
        let ring = self.ring_around(r, Some(level))?;
        for &m in &ring {
            let rec = &self.tets[m as usize];
            if rec.level != level
                || !same_edge(self.ref_edge_rec(m), edge)
                || rec.first_child == NONE
            {
                return Err(LatticeError::Internal("incomplete split diamond"));
            }
            let fc = rec.first_child as usize;
            if self.tets[fc].first_child != NONE || self.tets[fc + 1].first_child != NONE {
                return Ok(false);
            }
        }
        let fc = self.tets[r as usize].first_child;
        let z = self.tets[fc as usize].nodes[tag(level)];
        for &m in &ring {
            let fc = self.tets[m as usize].first_child;
            self.remove_leaf(fc);
            self.remove_leaf(fc + 1);
            self.free_pairs.push(fc);
            self.tets[m as usize].first_child = NONE;
            self.push_leaf(m);
        }
        self.free_node(z);
        events.push(TopologyEvent::NodeRemoved { node: z });
        self.generation += 1;
        Ok(true)
    }

    /// Refines until no leaf below `max_depth` satisfies `pred`; returns the number of tets
    /// split (including splits forced by conformity). Leaves at `max_depth` are never
    /// offered to `pred`, so the loop ends.
    pub fn refine_where(
        &mut self,
        mut pred: impl FnMut(&Lattice, TetId) -> bool,
        events: &mut Vec<TopologyEvent>,
    ) -> usize {
        let mut split = 0;
        loop {
            let max = self.params.max_depth;
            let todo: Vec<TetId> = self
                .leaves
                .iter()
                .copied()
                .filter(|t| t.level() < max)
                .filter(|&t| pred(self, t))
                .collect();
            if todo.is_empty() {
                return split;
            }
            for t in todo {
                // Earlier splits in this round may already have split `t`.
                match self.refine(t, events) {
                    Ok(n) => split += n,
                    Err(e) => {
                        tracing::error!(error = %e, "refine_where: refine failed");
                        return split;
                    }
                }
            }
        }
    }

    /// The record at index `r`.
    pub(crate) fn tet_rec(&self, r: u32) -> &TetRec {
        &self.tets[r as usize]
    }
}
