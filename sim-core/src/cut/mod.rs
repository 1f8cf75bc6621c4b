//! Cutting: topology operations on the embedded lattice, shared across sites.
//!
//! A cut is a [`CutOp`]: the triangles a blade swept, in **rest** coordinates (m). The cut
//! topology of a simulation is a pure function of the *set* of cut ops it has applied
//! (their triangles are taken in [`OpId`] order), so sites that receive the same ops in any
//! order, with duplicates, end with the same topology:
//!
//! 1. the lattice is refined to its deepest level wherever a sheet may touch a leaf
//!    ([`sheet::Sheet::may_touch_tet`]);
//! 2. every leaf the sheets separate is duplicated per material component
//!    ([`separate::separate`], the virtual node algorithm);
//! 3. every body's surface is cut and capped ([`surface::cut_surface`]).
//!
//! Every decision in these steps is made with exact predicates ([`predicates`]); the op's
//! triangles are carried as exact `f64` values, so every site decides identically. The
//! [`TopologyLog`] keeps the ops, the topology epoch (how many distinct ops are applied)
//! and a digest of the ops and the resulting element set.
//!
//! The blade that produces the ops is [`blade::BladeStrokes`]: it maps the blade's swept
//! edge from world to rest coordinates on the cutting site only (the one place where
//! floating-point state enters), and the op carries the result.

pub mod blade;
pub mod predicates;
pub mod separate;
pub mod sheet;
pub mod surface;
#[cfg(test)]
pub(crate) mod tests;

use std::collections::BTreeMap;

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

pub use blade::BladeStrokes;
pub use separate::{ElementCopy, Separation};
pub use sheet::Sheet;
pub use surface::{CutSurface, SurfaceCutError, cut_surface};

type V3 = Vector3<f64>;

/// Identity and canonical order of a topology operation: the site that made it and that
/// site's sequence number.
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize, Default,
)]
pub struct OpId {
    /// Originating site.
    pub site: u32,
    /// Sequence number at that site (from 0).
    pub seq: u32,
}

/// A cut: the triangles a blade swept, in rest coordinates (m).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CutOp {
    /// Identity and order.
    pub id: OpId,
    /// Swept triangles `[[x, y, z]; 3]`, rest coordinates (m), each with a non-zero area.
    pub triangles: Vec<[[f64; 3]; 3]>,
}

impl CutOp {
    /// The op's triangles as vectors.
    pub fn sheet_triangles(&self) -> impl Iterator<Item = [V3; 3]> + '_ {
        self.triangles
            .iter()
            .map(|t| t.map(|p| V3::new(p[0], p[1], p[2])))
    }

    /// Checks that every coordinate is finite and every triangle has an area.
    pub fn validate(&self) -> Result<(), String> {
        if self.triangles.is_empty() {
            return Err(format!("cut {:?} has no triangle", self.id));
        }
        for (i, t) in self.sheet_triangles().enumerate() {
            if t.iter().any(|p| !p.iter().all(|c| c.is_finite())) {
                return Err(format!("cut {:?}: triangle {i} is not finite", self.id));
            }
            if !predicates::non_degenerate(&t) {
                return Err(format!("cut {:?}: triangle {i} has no area", self.id));
            }
        }
        Ok(())
    }

    /// Bytes of the op as carried (postcard-like fixed size: id + length + 9 f64 per
    /// triangle).
    pub fn wire_bytes(&self) -> usize {
        8 + 4 + 72 * self.triangles.len()
    }
}

/// A release of attachment springs (dissection, [`crate::attach`]): springs of one layer,
/// by index. Releasing is idempotent and commutative (a released spring stays released).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ReleaseOp {
    /// Identity and order.
    pub id: OpId,
    /// Attachment layer (scene order).
    pub layer: u32,
    /// Spring indices in the layer, ascending.
    pub springs: Vec<u32>,
}

impl ReleaseOp {
    /// Bytes of the op as carried (id + layer + length + 4 per spring).
    pub fn wire_bytes(&self) -> usize {
        8 + 4 + 4 + 4 * self.springs.len()
    }
}

/// A topology operation: a cut, a release of attachment springs, a clip, or a refinement
/// decision. Cuts, releases and clips are kept in the [`TopologyLog`]; refinements are not
/// (they are transient, and the regions' tree states carry them: [`crate::adapt`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum TopologyOp {
    /// A blade's cut.
    Cut(CutOp),
    /// A hook's release of attachment springs.
    Release(ReleaseOp),
    /// A clip applier's clip ([`crate::clip`]).
    Clip(crate::clip::ClipOp),
    /// Tool-following refinement decided on one site ([`crate::adapt::RefineOp`]).
    Refine(crate::adapt::RefineOp),
}

impl TopologyOp {
    /// The op's identity.
    pub fn id(&self) -> OpId {
        match self {
            TopologyOp::Cut(c) => c.id,
            TopologyOp::Release(r) => r.id,
            TopologyOp::Clip(c) => c.id,
            TopologyOp::Refine(r) => r.id,
        }
    }
    /// Bytes of the op as carried.
    pub fn wire_bytes(&self) -> usize {
        match self {
            TopologyOp::Cut(c) => c.wire_bytes(),
            TopologyOp::Release(r) => r.wire_bytes(),
            TopologyOp::Clip(c) => c.wire_bytes(),
            TopologyOp::Refine(r) => r.wire_bytes(),
        }
    }
}

/// The topology operations a simulation applied, in canonical ([`OpId`]) order.
#[derive(Clone, Debug, Default)]
pub struct TopologyLog {
    ops: BTreeMap<OpId, TopologyOp>,
    digest: u64,
}

impl TopologyLog {
    /// The topology epoch: how many distinct operations are applied.
    pub fn epoch(&self) -> u32 {
        self.ops.len() as u32
    }
    /// The operations in canonical order.
    pub fn ops(&self) -> impl Iterator<Item = &TopologyOp> {
        self.ops.values()
    }
    /// Whether an op with this id is applied.
    pub fn contains(&self, id: OpId) -> bool {
        self.ops.contains_key(&id)
    }
    /// Digest of the ops and the separated element set (see [`TopologyLog::digest`]).
    pub fn digest(&self) -> u64 {
        self.digest
    }
    /// Bytes of the whole log as carried.
    pub fn wire_bytes(&self) -> usize {
        self.ops.values().map(TopologyOp::wire_bytes).sum()
    }
    pub(crate) fn insert(&mut self, op: TopologyOp) -> bool {
        self.ops.insert(op.id(), op).is_none()
    }
    /// Every cut's triangles, in canonical order.
    pub(crate) fn sheet(&self) -> Sheet {
        Sheet::new(
            self.ops
                .values()
                .flat_map(|o| match o {
                    TopologyOp::Cut(c) => c.sheet_triangles().collect::<Vec<_>>(),
                    TopologyOp::Release(_) | TopologyOp::Clip(_) | TopologyOp::Refine(_) => {
                        Vec::new()
                    }
                })
                .collect(),
        )
    }
    /// Every clip's rest ends, in canonical order (ends `2 i`, `2 i + 1` of clip `i`).
    pub(crate) fn clip_ends(&self) -> Vec<V3> {
        self.ops
            .values()
            .filter_map(|o| match o {
                TopologyOp::Clip(c) => Some(c.end_points()),
                _ => None,
            })
            .flatten()
            .collect()
    }
    /// Whether any applied op is a cut.
    pub fn has_cut(&self) -> bool {
        self.ops.values().any(|o| matches!(o, TopologyOp::Cut(_)))
    }
    /// Recomputes the digest: SHA-256 (first 8 bytes, little endian) over every op (id
    /// and the bits of its coordinates, or its layer and spring indices, or its clip's
    /// ends), every crossed
    /// leaf's copies (tree root, heap index, component mask, volume-fraction bits) and
    /// every attachment layer's released springs. Lattice node ids are not hashed: they
    /// differ between sites.
    pub(crate) fn update_digest(&mut self, separation: Option<&Separation>, released: &[Vec<u32>]) {
        let mut h = Sha256::new();
        for op in self.ops.values() {
            match op {
                TopologyOp::Cut(c) => {
                    h.update(b"cut");
                    h.update(c.id.site.to_le_bytes());
                    h.update(c.id.seq.to_le_bytes());
                    for t in &c.triangles {
                        for p in t {
                            for v in p {
                                h.update(v.to_bits().to_le_bytes());
                            }
                        }
                    }
                }
                TopologyOp::Release(r) => {
                    h.update(b"release");
                    h.update(r.id.site.to_le_bytes());
                    h.update(r.id.seq.to_le_bytes());
                    h.update(r.layer.to_le_bytes());
                    for s in &r.springs {
                        h.update(s.to_le_bytes());
                    }
                }
                TopologyOp::Clip(c) => {
                    h.update(b"clip");
                    h.update(c.id.site.to_le_bytes());
                    h.update(c.id.seq.to_le_bytes());
                    for v in c.ends.iter().flatten() {
                        h.update(v.to_bits().to_le_bytes());
                    }
                }
                // Never logged (`Simulation::apply_topology_op`).
                TopologyOp::Refine(_) => {}
            }
        }
        if let Some(separation) = separation {
            for &t in &separation.crossed {
                for c in separation.copies_of(t) {
                    h.update(t.root.to_le_bytes());
                    h.update(t.heap.to_le_bytes());
                    h.update([c.mask]);
                    h.update(c.fraction.to_bits().to_le_bytes());
                }
            }
        }
        for (layer, springs) in released.iter().enumerate() {
            h.update(b"released");
            h.update((layer as u32).to_le_bytes());
            for s in springs {
                h.update(s.to_le_bytes());
            }
        }
        let d = h.finalize();
        self.digest = u64::from_le_bytes(d[..8].try_into().expect("8 bytes"));
    }
}
