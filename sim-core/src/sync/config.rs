//! Knobs of the sync layer: extrapolation, blending and the owner's send decision
//! ([`SyncConfig`]), and how sites share the organ ([`SyncStrategy`]).

/// Knobs of extrapolation, blending and the owner's send decision.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SyncConfig {
    /// Corrections decay linearly to zero over this window (s); 0 snaps.
    pub blend_window_s: f64,
    /// Acceleration estimates are clamped to this magnitude (m/s²).
    pub max_accel_m_s2: f64,
    /// Extrapolation stops (holds) this far from the keyframe time (s).
    pub max_extrapolation_s: f64,
    /// The owner sends when its copy of the receivers' extrapolation drifts from the actual
    /// node positions by more than this (m).
    pub drift_threshold_m: f64,
    /// The owner sends a keyframe at least this often while owning (s of sim time).
    pub heartbeat_s: f64,
    /// The owner sends at most one frame per region per this interval (s of sim time);
    /// first and final keyframes are exempt.
    pub min_interval_s: f64,
    /// Keyframe tree states kept (owner and receiver) as tree-delta baselines.
    pub baseline_history: usize,
}

impl Default for SyncConfig {
    fn default() -> Self {
        SyncConfig {
            blend_window_s: 0.1,
            max_accel_m_s2: 50.0,
            max_extrapolation_s: 0.5,
            drift_threshold_m: 5e-4,
            heartbeat_s: 0.25,
            min_interval_s: 0.01,
            baseline_history: 16,
        }
    }
}

/// How sites share the organ (the sync bench compares them).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SyncStrategy {
    /// Keyframes of owned regions on dead-reckoning demand, extrapolated and blended.
    Keyframe,
    /// Every node of the organ every `every_steps` steps
    /// ([`encode_full_state`](super::encode_full_state) /
    /// [`apply_full_state`](super::apply_full_state)); receivers take the state over
    /// directly.
    FullState { every_steps: u32 },
    /// Only tool poses are shared; every site simulates everything (nothing here).
    InputOnly,
    /// Every site simulates everything from every site's tool input (as
    /// [`InputOnly`](SyncStrategy::InputOnly)), and the owners' periodic keyframes correct
    /// the followers by blended corrections ([`CorrectedRegion`](super::CorrectedRegion)).
    Hybrid,
}

impl SyncStrategy {
    /// Short name for tables and command lines: `keyframe`, `full-state`, `input-only`.
    pub fn name(&self) -> &'static str {
        match self {
            SyncStrategy::Keyframe => "keyframe",
            SyncStrategy::FullState { .. } => "full-state",
            SyncStrategy::InputOnly => "input-only",
            SyncStrategy::Hybrid => "hybrid",
        }
    }

    /// Whether every site simulates every tool from the tool inputs it receives (the
    /// remote tools touch the local organ).
    pub fn simulates_remote_tools(&self) -> bool {
        matches!(self, SyncStrategy::InputOnly | SyncStrategy::Hybrid)
    }
}

impl std::fmt::Display for SyncStrategy {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            SyncStrategy::FullState { every_steps } if *every_steps != 1 => {
                write!(f, "full-state:{every_steps}")
            }
            s => f.write_str(s.name()),
        }
    }
}

impl std::str::FromStr for SyncStrategy {
    type Err = String;
    /// `hybrid`, `keyframe`, `input-only`, `full-state` (every step) or `full-state:K`.
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "hybrid" => Ok(SyncStrategy::Hybrid),
            "keyframe" => Ok(SyncStrategy::Keyframe),
            "input-only" => Ok(SyncStrategy::InputOnly),
            "full-state" => Ok(SyncStrategy::FullState { every_steps: 1 }),
            _ => match s.strip_prefix("full-state:").map(str::parse::<u32>) {
                Some(Ok(k)) if k > 0 => Ok(SyncStrategy::FullState { every_steps: k }),
                _ => Err(format!(
                    "unknown sync strategy {s:?} (hybrid, keyframe, full-state[:K], input-only)"
                )),
            },
        }
    }
}
