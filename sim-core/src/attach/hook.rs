//! Dissection with a hook: the springs of an attachment layer near a hook's tip are
//! released progressively, as [`ReleaseOp`]s.
//!
//! Every step, each hook this site drives gains `release_rate · dt` releases per layer.
//! The holding springs whose midpoint lies within the layer's `release_radius` of the
//! hook's tip and whose tension is at least its `release_force` are candidates (tissue
//! gives way where it is put under traction, as when the gallbladder is lifted while the
//! bed is dissected); the whole number of releases gained goes to the nearest candidates
//! (ties by spring index). The op is applied here and kept in `made` for the caller to
//! share. Without candidates the gain stops at one release, so a hook that waited does
//! not release a burst.

use nalgebra::Vector3;
use sim_scene::ToolKind;

use crate::cut::{OpId, ReleaseOp, TopologyOp};
use crate::engine::Simulation;
use crate::error::SimError;
use crate::tools::ToolSet;

type V3 = Vector3<f64>;

/// Sequence numbers of a site's releases start here, so that they never collide with the
/// same site's cuts (numbered from 0 by [`crate::cut::BladeStrokes`]).
pub const RELEASE_SEQ_BASE: u32 = 1 << 31;

/// The hooks of a simulation and the releases they made.
#[derive(Clone, Debug)]
pub struct HookDissection {
    /// This site's id in the ops it makes.
    pub site: u32,
    next_seq: u32,
    /// Releases gained and not yet spent, per tool and layer.
    gained: Vec<Vec<f64>>,
    /// Ops made so far, in order (the caller shares them with the other sites).
    pub made: Vec<TopologyOp>,
    /// Which tools may release here (default: every hook). A networked site lets only the
    /// hook it drives dissect: the others' releases arrive as their ops.
    pub enabled: Vec<bool>,
    /// Whether a release is applied here at once (default). A site under hybrid or
    /// input-only sync turns this off and applies its own releases a little later, at a
    /// simulated time it shares with the op (as it does its cuts), so that every site lets
    /// the tissue go at the same moment; meanwhile the springs stay candidates of no
    /// other release (`pending`).
    pub apply_own: bool,
    /// Springs released by an op made here and not applied yet, per layer.
    pending: Vec<std::collections::BTreeSet<u32>>,
}

impl HookDissection {
    /// Dissection by the hooks among `tools`.
    pub fn new(tools: &ToolSet, site: u32) -> Self {
        HookDissection {
            site,
            next_seq: 0,
            gained: vec![Vec::new(); tools.tools.len()],
            made: Vec::new(),
            enabled: vec![true; tools.tools.len()],
            apply_own: true,
            pending: Vec::new(),
        }
    }

    /// One step of every enabled hook; applies the releases it makes (unless
    /// [`Self::apply_own`] is off) and returns how many springs were released here.
    pub fn update(&mut self, sim: &mut Simulation, tools: &ToolSet) -> Result<usize, SimError> {
        let dt = sim.options().dt;
        let layers = sim.attachments().layers.len();
        self.gained.resize(tools.tools.len(), Vec::new());
        self.enabled.resize(tools.tools.len(), true);
        self.pending.resize(layers, Default::default());
        let mut released = 0;
        for (ti, tool) in tools.tools.iter().enumerate() {
            if tool.kind != ToolKind::Hook || !self.enabled[ti] {
                continue;
            }
            let tip = tool.tip();
            self.gained[ti].resize(layers, 0.0);
            for li in 0..layers {
                let layer = &sim.attachments().layers[li];
                let gained = &mut self.gained[ti][li];
                *gained += layer.release_rate * dt;
                let pending = &self.pending[li];
                let mut candidates: Vec<(f64, u32)> = (0..layer.springs.len())
                    .filter(|&i| !layer.is_released(i) && !pending.contains(&(i as u32)))
                    .filter_map(|i| {
                        let st = layer.state(sim.positions(), i);
                        let d = (st.midpoint - tip).norm();
                        (d <= layer.release_radius && st.tension.abs() >= layer.release_force)
                            .then_some((d, i as u32))
                    })
                    .collect();
                if candidates.is_empty() {
                    *gained = gained.min(1.0);
                    continue;
                }
                let n = (gained.floor() as usize).min(candidates.len());
                if n == 0 {
                    continue;
                }
                *gained -= n as f64;
                candidates.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
                let mut springs: Vec<u32> = candidates[..n].iter().map(|c| c.1).collect();
                springs.sort_unstable();
                let op = TopologyOp::Release(ReleaseOp {
                    id: OpId {
                        site: self.site,
                        seq: RELEASE_SEQ_BASE.wrapping_add(self.next_seq),
                    },
                    layer: li as u32,
                    springs,
                });
                self.next_seq += 1;
                if self.apply_own {
                    released += sim.apply_topology_op(op.clone())?.released;
                } else if let TopologyOp::Release(r) = &op {
                    self.pending[li].extend(&r.springs);
                }
                tracing::debug!(tool = %tool.name, springs = n, "hook released springs");
                self.made.push(op);
            }
        }
        Ok(released)
    }
}

/// Distance (m) from `p` to the nearest holding spring's midpoint of any layer (`None`
/// when none holds), e.g. to place a hook.
pub fn nearest_holding(sim: &Simulation, p: &V3) -> Option<f64> {
    sim.attachments()
        .layers
        .iter()
        .flat_map(|l| {
            (0..l.springs.len())
                .filter(|&i| !l.is_released(i))
                .map(|i| (l.state(sim.positions(), i).midpoint - p).norm())
        })
        .min_by(f64::total_cmp)
}
