//! Skill measures per act (see `docs/debrief.md` for definitions and sources).
//!
//! Units: m, s, N; positions are tool tips. Derivatives come from positions low-pass
//! filtered forward and backward (second-order Butterworth, `filter_cutoff_hz`, zero
//! phase) after odd reflection at both ends, then central differences.

use serde::{Deserialize, Serialize};

use crate::format::{EventKind, ToolState};
use crate::reader::{Recording, Track};

type P3 = [f64; 3];

fn sub(a: P3, b: P3) -> P3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn dot(a: P3, b: P3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn norm(a: P3) -> f64 {
    dot(a, a).sqrt()
}

/// Knobs of the measures (defaults stated in `docs/debrief.md`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ScoreSettings {
    /// Below this tip speed the tool counts as idle (m/s).
    pub idle_speed_m_s: f64,
    /// Cut-off of the zero-phase low-pass applied before differentiating (Hz).
    pub filter_cutoff_hz: f64,
    /// Contact force above which a tool not grasping is dissecting (N).
    pub contact_threshold_n: f64,
    /// Runs of grasp or contact separated by less than this merge into one act (s).
    pub merge_gap_s: f64,
    /// Shorter acts are dropped (s).
    pub min_act_s: f64,
    /// A contact run ending less than this before a grasp of the same tool is the
    /// grasp's approach, not a dissection (s).
    pub approach_s: f64,
    /// Points each path is resampled to (uniformly in time) before DTW.
    pub dtw_points: usize,
    /// Sakoe–Chiba band half-width as a fraction of `dtw_points`.
    pub dtw_band_fraction: f64,
}

impl Default for ScoreSettings {
    fn default() -> Self {
        ScoreSettings {
            idle_speed_m_s: 0.005,
            filter_cutoff_hz: 10.0,
            contact_threshold_n: 0.05,
            merge_gap_s: 0.2,
            min_act_s: 0.1,
            approach_s: 0.5,
            dtw_points: 500,
            dtw_band_fraction: 0.2,
        }
    }
}

/// Path length: sum of the segment lengths (m).
pub fn path_length(p: &[P3]) -> f64 {
    p.windows(2).map(|w| norm(sub(w[1], w[0]))).sum::<f64>() + 0.0 // not −0.0 when empty
}

/// Economy of motion: path length over the straight distance between the ends
/// (≥ 1; `None` when the ends are closer than 1 mm, where the ratio means nothing).
pub fn economy(p: &[P3]) -> Option<f64> {
    let (a, b) = (p.first()?, p.last()?);
    let d = norm(sub(*b, *a));
    (d >= 1e-3).then(|| path_length(p) / d)
}

/// Second-order Butterworth low-pass run forward and backward (zero phase), with odd
/// reflection of `pad` samples at both ends; returns the padded, filtered signal.
fn filtfilt_padded(x: &[f64], fs: f64, fc: f64, pad: usize) -> Vec<f64> {
    let n = x.len();
    let mut y = Vec::with_capacity(n + 2 * pad);
    for i in (1..=pad).rev() {
        y.push(2.0 * x[0] - x[i.min(n - 1)]);
    }
    y.extend_from_slice(x);
    for i in 1..=pad {
        y.push(2.0 * x[n - 1] - x[(n - 1).saturating_sub(i)]);
    }
    if fc.is_nan() || fc <= 0.0 || fc >= 0.45 * fs {
        return y;
    }
    let k = (std::f64::consts::PI * fc / fs).tan();
    let s2 = std::f64::consts::SQRT_2;
    let nrm = 1.0 / (1.0 + s2 * k + k * k);
    let b0 = k * k * nrm;
    let (b1, b2) = (2.0 * b0, b0);
    let a1 = 2.0 * (k * k - 1.0) * nrm;
    let a2 = (1.0 - s2 * k + k * k) * nrm;
    let run = |v: &mut Vec<f64>| {
        let (mut x1, mut x2, mut y1, mut y2) = (v[0], v[0], v[0], v[0]);
        for s in v.iter_mut() {
            let x0 = *s;
            let y0 = b0 * x0 + b1 * x1 + b2 * x2 - a1 * y1 - a2 * y2;
            (x2, x1, y2, y1) = (x1, x0, y1, y0);
            *s = y0;
        }
    };
    run(&mut y);
    y.reverse();
    run(&mut y);
    y.reverse();
    y
}

/// Central differences (one-sided at the ends) of `x` sampled every `dt`.
fn derivative(x: &[f64], dt: f64) -> Vec<f64> {
    let n = x.len();
    if n < 2 {
        return vec![0.0; n];
    }
    (0..n)
        .map(|i| {
            let (a, b) = (i.saturating_sub(1), (i + 1).min(n - 1));
            (x[b] - x[a]) / ((b - a) as f64 * dt)
        })
        .collect()
}

/// Filtered kinematics of a sampled path: positions, velocity, jerk per axis.
struct Kinematics {
    pos: Vec<P3>,
    vel: Vec<P3>,
    jerk: Vec<P3>,
    dt: f64,
}

fn kinematics(times: &[f64], p: &[P3], cutoff_hz: f64) -> Option<Kinematics> {
    let n = p.len();
    if n < 3 || times.len() != n {
        return None;
    }
    let dt = (times[n - 1] - times[0]) / (n - 1) as f64;
    if dt.is_nan() || dt <= 0.0 {
        return None;
    }
    let fs = 1.0 / dt;
    // Pad by three filter time constants (and at least the stencil of the jerk).
    let pad = ((3.0 * fs / cutoff_hz.max(1e-3)).ceil() as usize).clamp(4, n - 1);
    let mut pos = vec![[0.0; 3]; n];
    let mut vel = vec![[0.0; 3]; n];
    let mut jerk = vec![[0.0; 3]; n];
    for k in 0..3 {
        let x: Vec<f64> = p.iter().map(|q| q[k]).collect();
        let xf = filtfilt_padded(&x, fs, cutoff_hz, pad);
        let v = derivative(&xf, dt);
        let j = derivative(&derivative(&v, dt), dt);
        for i in 0..n {
            pos[i][k] = xf[i + pad];
            vel[i][k] = v[i + pad];
            jerk[i][k] = j[i + pad];
        }
    }
    Some(Kinematics { pos, vel, jerk, dt })
}

/// Log dimensionless jerk (Hogan & Sternad 2009; the speed-normalised form of
/// Balasubramanian et al. 2015): `LDLJ = −ln( T³ / v_peak² · ∫ |d³x/dt³|² dt )`, T the
/// duration, v_peak the peak speed. Sign convention: closer to zero (less negative) is
/// smoother; a minimum-jerk reach scores −ln(204.8) = −5.322. `None` for fewer than
/// three samples or a tool that does not move (v_peak < 1 µm/s).
pub fn ldlj(times: &[f64], p: &[P3], cutoff_hz: f64) -> Option<f64> {
    let k = kinematics(times, p, cutoff_hz)?;
    let t = times[times.len() - 1] - times[0];
    let vpeak = k.vel.iter().map(|v| norm(*v)).fold(0.0, f64::max);
    if vpeak < 1e-6 {
        return None;
    }
    let j2: Vec<f64> = k.jerk.iter().map(|j| dot(*j, *j)).collect();
    let integral: f64 = j2.windows(2).map(|w| 0.5 * (w[0] + w[1]) * k.dt).sum();
    let dlj = t.powi(3) / (vpeak * vpeak) * integral;
    (dlj > 0.0).then(|| -dlj.ln())
}

/// Time (s) during which the filtered tip speed is below `threshold` (m/s).
pub fn idle_time(times: &[f64], p: &[P3], threshold: f64, cutoff_hz: f64) -> f64 {
    let Some(k) = kinematics(times, p, cutoff_hz) else {
        return 0.0;
    };
    (0..p.len() - 1)
        .filter(|&i| norm(k.vel[i]) < threshold && norm(k.vel[i + 1]) < threshold)
        .map(|i| times[i + 1] - times[i])
        .sum::<f64>()
        + 0.0 // an empty float sum is −0.0
}

/// Rotates the tool frame's +z (the shaft) by `q = [w, x, y, z]`.
pub fn shaft_axis(q: [f64; 4]) -> P3 {
    let [w, x, y, z] = q;
    [
        2.0 * (x * z + w * y),
        2.0 * (y * z - w * x),
        1.0 - 2.0 * (x * x + y * y),
    ]
}

/// Depth travelled along the shaft: `Σ |Δp · axis|` (m), with the shaft's direction at
/// the start of each segment.
pub fn depth_along_shaft(states: &[ToolState]) -> f64 {
    states
        .windows(2)
        .map(|w| {
            dot(
                sub(w[1].position, w[0].position),
                shaft_axis(w[0].orientation),
            )
            .abs()
        })
        .sum()
}

/// Resamples a timed path to `n` points uniformly in time (linear interpolation).
pub fn resample(times: &[f64], p: &[P3], n: usize) -> Vec<P3> {
    if p.is_empty() || n == 0 {
        return Vec::new();
    }
    if p.len() == 1 || n == 1 {
        return vec![p[0]; n];
    }
    let (t0, t1) = (times[0], times[times.len() - 1]);
    let mut j = 0;
    (0..n)
        .map(|i| {
            let t = t0 + (t1 - t0) * i as f64 / (n - 1) as f64;
            while j + 2 < times.len() && times[j + 1] < t {
                j += 1;
            }
            let span = times[j + 1] - times[j];
            let a = if span > 0.0 {
                ((t - times[j]) / span).clamp(0.0, 1.0)
            } else {
                0.0
            };
            [0, 1, 2].map(|k| p[j][k] + a * (p[j + 1][k] - p[j][k]))
        })
        .collect()
}

/// Dynamic-time-warping distance between two point sequences with a Sakoe–Chiba band
/// of half-width `band` (widened to the length difference): the sum of Euclidean
/// distances along the cheapest warping path divided by the number of matched pairs on
/// it (m). O(n·band). `None` if either is empty.
pub fn dtw_mean_distance(a: &[P3], b: &[P3], band: usize) -> Option<f64> {
    let (n, m) = (a.len(), b.len());
    if n == 0 || m == 0 {
        return None;
    }
    let w = band.max(n.abs_diff(m));
    let inf = (f64::INFINITY, 0u32);
    // Rows of (cost, pairs); only the band of each row is valid.
    let mut prev = vec![inf; m + 1];
    let mut cur = vec![inf; m + 1];
    prev[0] = (0.0, 0);
    for i in 1..=n {
        cur.fill(inf);
        let centre = (i as f64 * m as f64 / n as f64).round() as usize;
        let lo = centre.saturating_sub(w).max(1);
        let hi = (centre + w).min(m);
        for j in lo..=hi {
            let d = norm(sub(a[i - 1], b[j - 1]));
            let mut best = prev[j - 1];
            for c in [prev[j], cur[j - 1]] {
                if c.0 < best.0 {
                    best = c;
                }
            }
            if best.0.is_finite() {
                cur[j] = (best.0 + d, best.1 + 1);
            }
        }
        std::mem::swap(&mut prev, &mut cur);
    }
    let (cost, pairs) = prev[m];
    (cost.is_finite() && pairs > 0).then(|| cost / f64::from(pairs))
}

/// What an act is.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ActKind {
    /// The tool's whole recorded track.
    Session,
    /// Grasp to release.
    Grasp,
    /// Contact without grasping.
    Dissection,
    /// Between cut-start and cut-stop events.
    Cut,
}

/// One act of one tool: samples `first..=last` of its track.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Act {
    pub kind: ActKind,
    pub tool: String,
    pub tool_kind: String,
    /// Ordinal among the tool's acts of this kind (0-based).
    pub index: usize,
    pub start_s: f64,
    pub end_s: f64,
    #[serde(skip)]
    pub first: usize,
    #[serde(skip)]
    pub last: usize,
}

impl Act {
    /// `grasp 2 of forceps` style label.
    pub fn label(&self) -> String {
        let k = serde_json::to_value(self.kind)
            .ok()
            .and_then(|v| v.as_str().map(str::to_owned))
            .unwrap_or_default();
        format!("{k} {} of {}", self.index + 1, self.tool)
    }
}

/// Runs of samples where `on` holds, merged over gaps shorter than `gap` s and
/// dropped when shorter than `min` s: (first, last) sample indices.
fn runs(times: &[f64], on: impl Fn(usize) -> bool, gap: f64, min: f64) -> Vec<(usize, usize)> {
    let mut out: Vec<(usize, usize)> = Vec::new();
    let mut start = None;
    for i in 0..=times.len() {
        let active = i < times.len() && on(i);
        match (active, start) {
            (true, None) => start = Some(i),
            (false, Some(s)) => {
                let e = i - 1;
                match out.last_mut() {
                    Some(last) if times[s] - times[last.1] < gap => last.1 = e,
                    _ => out.push((s, e)),
                }
                start = None;
            }
            _ => {}
        }
    }
    out.retain(|&(s, e)| times[e] - times[s] >= min);
    out
}

/// The acts of one track: its whole span, grasp runs (grasped > 0), dissection runs
/// (contact force above the threshold while not grasping, not the approach to a grasp)
/// and cuts (between `cut-start` and `cut-stop` events of the tool).
pub fn find_acts(track: &Track, cuts: &[(f64, f64)], s: &ScoreSettings) -> Vec<Act> {
    find_acts_with(
        track,
        &EventActs {
            cuts: cuts.to_vec(),
            grasps: Vec::new(),
        },
        s,
    )
}

/// Act intervals (start, end) in s that a recording's events give for one tool.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct EventActs {
    /// `cut-start` → `cut-stop`.
    pub cuts: Vec<(f64, f64)>,
    /// `grasp` → `grasp-release`: used only for a track without grasp state (a
    /// coordinator's recording of tool poses), whose samples never show a grasp.
    pub grasps: Vec<(f64, f64)>,
}

/// Like [`find_acts`], with the grasp and cut intervals of the tool's events: cuts
/// always come from events; grasps from the samples' grasp state when the track has
/// any, else from the events.
pub fn find_acts_with(track: &Track, events: &EventActs, s: &ScoreSettings) -> Vec<Act> {
    let cuts = &events.cuts;
    let (name, kind) = track
        .decl
        .as_ref()
        .map(|d| (d.name.clone(), d.kind.clone()))
        .unwrap_or_default();
    let t = &track.times;
    if t.is_empty() {
        return Vec::new();
    }
    let mk = |kind_: ActKind, index: usize, (first, last): (usize, usize)| Act {
        kind: kind_,
        tool: name.clone(),
        tool_kind: kind.clone(),
        index,
        start_s: t[first],
        end_s: t[last],
        first,
        last,
    };
    let mut acts = vec![mk(ActKind::Session, 0, (0, t.len() - 1))];
    let st = &track.states;
    let grasps = if st.iter().any(|x| x.grasped > 0) || events.grasps.is_empty() {
        runs(t, |i| st[i].grasped > 0, s.merge_gap_s, s.min_act_s)
    } else {
        events
            .grasps
            .iter()
            .filter_map(|&(a, b)| sample_range(t, a, b))
            .filter(|&(f, l)| t[l] - t[f] >= s.min_act_s)
            .collect()
    };
    let contact = runs(
        t,
        |i| st[i].grasped == 0 && norm(st[i].contact_force) > s.contact_threshold_n,
        s.merge_gap_s,
        s.min_act_s,
    );
    let dissections: Vec<(usize, usize)> = contact
        .into_iter()
        .filter(|&(_, e)| {
            !grasps
                .iter()
                .any(|&(gs, _)| t[gs] >= t[e] && t[gs] - t[e] < s.approach_s)
        })
        .collect();
    acts.extend(
        grasps
            .into_iter()
            .enumerate()
            .map(|(i, r)| mk(ActKind::Grasp, i, r)),
    );
    acts.extend(
        dissections
            .into_iter()
            .enumerate()
            .map(|(i, r)| mk(ActKind::Dissection, i, r)),
    );
    for (i, &(a, b)) in cuts.iter().enumerate() {
        if let Some(r) = sample_range(t, a, b) {
            acts.push(mk(ActKind::Cut, i, r));
        }
    }
    acts
}

/// The (first, last) samples of `times` within `[a, b]`, if at least two.
fn sample_range(times: &[f64], a: f64, b: f64) -> Option<(usize, usize)> {
    let first = times.partition_point(|&x| x < a);
    let last = times.partition_point(|&x| x <= b);
    (last > first + 1).then(|| (first, last - 1))
}

/// The act intervals of `tool`'s events (or of events naming no tool) of `site` in a
/// recording. An interval still open at the end of the recording (a site killed
/// mid-cut) runs to the end of the track.
pub fn event_acts(rec: &Recording, site: &str, tool: &str) -> EventActs {
    let mut out = EventActs::default();
    let (mut cut, mut grasp) = (None, None);
    for e in rec.events() {
        if e.site != site || e.tool.as_deref().is_some_and(|t| t != tool) {
            continue;
        }
        match e.kind {
            EventKind::CutStart => cut = cut.or(Some(e.time)),
            EventKind::CutStop => {
                if let Some(a) = cut.take() {
                    out.cuts.push((a, e.time));
                }
            }
            EventKind::Grasp => grasp = grasp.or(Some(e.time)),
            EventKind::GraspRelease => {
                if let Some(a) = grasp.take() {
                    out.grasps.push((a, e.time));
                }
            }
            _ => {}
        }
    }
    out.cuts.extend(cut.map(|a| (a, f64::INFINITY)));
    out.grasps.extend(grasp.map(|a| (a, f64::INFINITY)));
    out
}

/// Cut intervals of `tool` (or of every tool when the event names none) in a recording
/// (see [`event_acts`]).
pub fn cut_intervals(rec: &Recording, site: &str, tool: &str) -> Vec<(f64, f64)> {
    event_acts(rec, site, tool).cuts
}

/// The measures of one act.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Measures {
    pub duration_s: f64,
    pub path_length_m: f64,
    pub straight_distance_m: f64,
    pub economy: Option<f64>,
    pub idle_time_s: f64,
    pub depth_along_shaft_m: f64,
    pub peak_speed_m_s: f64,
    pub ldlj: Option<f64>,
    pub contact_force_peak_n: f64,
    pub contact_force_rms_n: f64,
    pub grasp_force_peak_n: f64,
    pub grasp_force_rms_n: f64,
    /// ∫ damaged volume dt over the act (m³·s), if the recording has damage.
    pub damage_m3_s: Option<f64>,
    /// Largest damaged volume during the act (m³).
    pub damage_peak_m3: Option<f64>,
    /// DTW mean distance per matched pair to the reference act (m).
    pub dtw_to_reference_m: Option<f64>,
    /// Which reference act was compared.
    pub reference_act: Option<String>,
}

fn peak_rms(x: impl Iterator<Item = f64> + Clone) -> (f64, f64) {
    let n = x.clone().count();
    if n == 0 {
        return (0.0, 0.0);
    }
    let peak = x.clone().fold(0.0, f64::max);
    let rms = (x.map(|v| v * v).sum::<f64>() / n as f64).sqrt();
    (peak, rms)
}

/// Measures of `act` on `track`; `damage` is the recording's (time, m³) series.
pub fn measure(track: &Track, act: &Act, damage: &[(f64, f64)], s: &ScoreSettings) -> Measures {
    let range = act.first..=act.last.min(track.len().saturating_sub(1));
    let times = &track.times[range.clone()];
    let states = &track.states[range];
    let raw: Vec<P3> = states.iter().map(|x| x.position).collect();
    let kin = kinematics(times, &raw, s.filter_cutoff_hz);
    let smooth = kin.as_ref().map_or(raw.clone(), |k| k.pos.clone());
    let peak_speed = kin
        .as_ref()
        .map_or(0.0, |k| k.vel.iter().map(|v| norm(*v)).fold(0.0, f64::max));
    let (cp, cr) = peak_rms(states.iter().map(|x| norm(x.contact_force)));
    let (gp, gr) = peak_rms(states.iter().map(|x| norm(x.grasp_force)));
    let in_act: Vec<(f64, f64)> = damage
        .iter()
        .copied()
        .filter(|(t, _)| *t >= act.start_s && *t <= act.end_s)
        .collect();
    let (damage_m3_s, damage_peak_m3) = if in_act.is_empty() {
        (None, None)
    } else {
        let integral = in_act
            .windows(2)
            .map(|w| 0.5 * (w[0].1 + w[1].1) * (w[1].0 - w[0].0))
            .sum();
        let peak = in_act.iter().map(|d| d.1).fold(0.0, f64::max);
        (Some(integral), Some(peak))
    };
    Measures {
        duration_s: act.end_s - act.start_s,
        path_length_m: path_length(&smooth),
        straight_distance_m: match (smooth.first(), smooth.last()) {
            (Some(a), Some(b)) => norm(sub(*b, *a)),
            _ => 0.0,
        },
        economy: economy(&smooth),
        idle_time_s: idle_time(times, &raw, s.idle_speed_m_s, s.filter_cutoff_hz),
        depth_along_shaft_m: depth_along_shaft(states),
        peak_speed_m_s: peak_speed,
        ldlj: ldlj(times, &raw, s.filter_cutoff_hz),
        contact_force_peak_n: cp,
        contact_force_rms_n: cr,
        grasp_force_peak_n: gp,
        grasp_force_rms_n: gr,
        damage_m3_s,
        damage_peak_m3,
        dtw_to_reference_m: None,
        reference_act: None,
    }
}

/// DTW between the tips of two acts, each resampled to `dtw_points` (m).
pub fn dtw_between(
    a: &Track,
    act_a: &Act,
    b: &Track,
    act_b: &Act,
    s: &ScoreSettings,
) -> Option<f64> {
    let cut = |t: &Track, act: &Act| {
        let r = act.first..=act.last.min(t.len().saturating_sub(1));
        let p: Vec<P3> = t.states[r.clone()].iter().map(|x| x.position).collect();
        resample(&t.times[r], &p, s.dtw_points)
    };
    let (pa, pb) = (cut(a, act_a), cut(b, act_b));
    let band = (s.dtw_band_fraction * s.dtw_points as f64).ceil() as usize;
    dtw_mean_distance(&pa, &pb, band.max(1))
}

/// Filtered tip speed of each sample (m/s).
pub fn speeds(times: &[f64], p: &[P3], cutoff_hz: f64) -> Vec<f64> {
    match kinematics(times, p, cutoff_hz) {
        Some(k) => k.vel.iter().map(|v| norm(*v)).collect(),
        None => vec![0.0; p.len()],
    }
}

#[cfg(test)]
mod tests;
