//! Scores of one site against a reference, as JSON and as a self-contained HTML page
//! with inline SVG plots.

use std::fmt::Write as _;

use plotters::prelude::*;
use serde::{Deserialize, Serialize};

use crate::reader::{Recording, Track};
use crate::score::{
    Act, Measures, ScoreSettings, dtw_between, event_acts, find_acts_with, measure, speeds,
};

/// Why a site could not be scored.
#[derive(Debug, thiserror::Error)]
pub enum ScoreError {
    #[error("site {site:?} has no tool samples in this recording (sites with tools: {known})")]
    NoSamples { site: String, known: String },
    #[error("drawing a plot: {0}")]
    Plot(String),
}

/// One scored act.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ScoredAct {
    pub act: Act,
    pub measures: Measures,
}

/// The scores of one site.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ScoreReport {
    pub site: String,
    pub session: String,
    pub scene: String,
    /// `site@recording` of the reference, if any.
    pub reference: Option<String>,
    pub settings: ScoreSettings,
    pub damage_strain_threshold: Option<f64>,
    /// How the recording ended (complete, truncated, ...).
    pub recording_tail: String,
    pub acts: Vec<ScoredAct>,
}

/// A site's tracks in a recording, with their acts.
pub struct SiteTracks<'a> {
    pub recording: &'a Recording,
    pub site: String,
    pub tracks: Vec<Track>,
    pub acts: Vec<Vec<Act>>,
}

impl<'a> SiteTracks<'a> {
    /// Tracks and acts of `site`'s tools in `rec`.
    pub fn new(rec: &'a Recording, site: &str, s: &ScoreSettings) -> Result<Self, ScoreError> {
        let tracks: Vec<Track> = rec
            .site_tracks(site)
            .into_iter()
            .filter(|t| !t.is_empty())
            .collect();
        if tracks.is_empty() {
            let mut known: Vec<String> = rec.tools().iter().map(|t| t.site.clone()).collect();
            known.sort();
            known.dedup();
            return Err(ScoreError::NoSamples {
                site: site.into(),
                known: known.join(", "),
            });
        }
        let acts = tracks
            .iter()
            .map(|t| {
                let name = t.decl.as_ref().map_or("", |d| d.name.as_str());
                find_acts_with(t, &event_acts(rec, site, name), s)
            })
            .collect();
        Ok(SiteTracks {
            recording: rec,
            site: site.into(),
            tracks,
            acts,
        })
    }

    /// The reference's act matching `act`: same kind and ordinal on the tool of the same
    /// name, else on the first tool of the same kind.
    fn matching(&self, act: &Act) -> Option<(&Track, &Act)> {
        let pick = |by_name: bool| {
            self.tracks.iter().zip(&self.acts).find_map(|(t, acts)| {
                acts.iter()
                    .find(|a| {
                        a.kind == act.kind
                            && a.index == act.index
                            && if by_name {
                                a.tool == act.tool
                            } else {
                                a.tool_kind == act.tool_kind
                            }
                    })
                    .map(|a| (t, a))
            })
        };
        pick(true).or_else(|| pick(false))
    }
}

/// Scores `site` in `rec`, against `reference` if given.
pub fn score_site(
    rec: &Recording,
    site: &str,
    reference: Option<(&Recording, &str)>,
    s: &ScoreSettings,
) -> Result<ScoreReport, ScoreError> {
    let mine = SiteTracks::new(rec, site, s)?;
    let theirs = reference
        .map(|(r, name)| SiteTracks::new(r, name, s))
        .transpose()?;
    let damage = rec.damage();
    let mut acts = Vec::new();
    for (track, track_acts) in mine.tracks.iter().zip(&mine.acts) {
        for act in track_acts {
            let mut m = measure(track, act, &damage, s);
            if let Some((rt, ra)) = theirs.as_ref().and_then(|r| r.matching(act)) {
                m.dtw_to_reference_m = dtw_between(track, act, rt, ra, s);
                m.reference_act = Some(ra.label());
            }
            acts.push(ScoredAct {
                act: act.clone(),
                measures: m,
            });
        }
    }
    Ok(ScoreReport {
        site: site.into(),
        session: rec.header.session.clone(),
        scene: rec.header.scene.clone(),
        reference: reference.map(|(r, name)| {
            format!(
                "{name}@{}",
                r.path
                    .as_ref()
                    .map_or("<memory>".into(), |p| p.display().to_string())
            )
        }),
        settings: *s,
        damage_strain_threshold: rec.header.damage_strain_threshold,
        recording_tail: rec.tail.to_string(),
        acts,
    })
}

fn opt(v: Option<f64>, scale: f64, digits: usize) -> String {
    v.map_or("–".into(), |x| {
        let text = format!("{:.*}", digits, x * scale);
        // a rounding residue below the last digit prints as 0, not -0
        match text.strip_prefix('-') {
            Some(rest) if rest.bytes().all(|b| b == b'0' || b == b'.') => rest.to_string(),
            _ => text,
        }
    })
}

/// The table as fixed-width text (for the terminal).
pub fn text_table(r: &ScoreReport) -> String {
    let mut out = String::new();
    let _ = writeln!(
        out,
        "{:<24} {:>7} {:>8} {:>7} {:>6} {:>7} {:>7} {:>6} {:>6} {:>6} {:>9} {:>8}",
        "act",
        "time s",
        "path mm",
        "economy",
        "idle s",
        "depth mm",
        "LDLJ",
        "Fc pk",
        "Fc rms",
        "Fg pk",
        "dmg mm³s",
        "DTW mm"
    );
    for a in &r.acts {
        let m = &a.measures;
        let _ = writeln!(
            out,
            "{:<24} {:>7.2} {:>8.1} {:>7} {:>6.2} {:>7.1} {:>7} {:>6.2} {:>6.2} {:>6.2} {:>9} {:>8}",
            a.act.label(),
            m.duration_s,
            m.path_length_m * 1e3,
            opt(m.economy, 1.0, 2),
            m.idle_time_s,
            m.depth_along_shaft_m * 1e3,
            opt(m.ldlj, 1.0, 2),
            m.contact_force_peak_n,
            m.contact_force_rms_n,
            m.grasp_force_peak_n,
            opt(m.damage_m3_s, 1e9, 3),
            opt(m.dtw_to_reference_m, 1e3, 2),
        );
    }
    out
}

fn register_fonts() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        for family in ["sans-serif", "serif", "monospace"] {
            let face = epaint_default_fonts::UBUNTU_LIGHT;
            if plotters::style::register_font(family, FontStyle::Normal, face).is_err() {
                tracing::warn!("embedded plot font could not be loaded; plots lose their text");
            }
        }
    });
}

const PALETTE: [RGBColor; 6] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
];

struct Line {
    label: String,
    points: Vec<(f64, f64)>,
    dashed: bool,
}

/// Keeps at most `n` points (every k-th).
fn thin(p: Vec<(f64, f64)>, n: usize) -> Vec<(f64, f64)> {
    let k = p.len().div_ceil(n.max(1)).max(1);
    p.into_iter().step_by(k).collect()
}

fn svg_chart(title: &str, xl: &str, yl: &str, lines: &[Line]) -> Result<String, ScoreError> {
    register_fonts();
    let pl = |e: &dyn std::fmt::Display| ScoreError::Plot(e.to_string());
    let all = lines.iter().flat_map(|l| l.points.iter());
    let (mut x0, mut x1, mut y0, mut y1) = (f64::MAX, f64::MIN, f64::MAX, f64::MIN);
    for &(x, y) in all.filter(|(x, y)| x.is_finite() && y.is_finite()) {
        (x0, x1, y0, y1) = (x0.min(x), x1.max(x), y0.min(y), y1.max(y));
    }
    if x0 > x1 {
        (x0, x1, y0, y1) = (0.0, 1.0, 0.0, 1.0);
    }
    let padx = ((x1 - x0) * 0.03).max(1e-9);
    let pady = ((y1 - y0) * 0.05).max(1e-9);
    let mut svg = String::new();
    {
        let root = SVGBackend::with_string(&mut svg, (900, 420)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| pl(&e))?;
        let mut ctx = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 20))
            .margin(12)
            .x_label_area_size(40)
            .y_label_area_size(70)
            .build_cartesian_2d((x0 - padx)..(x1 + padx), (y0 - pady)..(y1 + pady))
            .map_err(|e| pl(&e))?;
        ctx.configure_mesh()
            .x_desc(xl)
            .y_desc(yl)
            .draw()
            .map_err(|e| pl(&e))?;
        for (i, l) in lines.iter().enumerate() {
            let color = PALETTE[i % PALETTE.len()];
            let style = color.stroke_width(if l.dashed { 1 } else { 2 });
            let pts: Vec<(f64, f64)> = thin(l.points.clone(), 1500);
            ctx.draw_series(LineSeries::new(pts, style))
                .map_err(|e| pl(&e))?
                .label(l.label.clone())
                .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], style));
        }
        ctx.configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .draw()
            .map_err(|e| pl(&e))?;
        root.present().map_err(|e| pl(&e))?;
    }
    Ok(svg)
}

fn esc(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

fn tool_name(t: &Track) -> String {
    t.decl.as_ref().map_or("tool".into(), |d| d.name.clone())
}

/// A self-contained HTML page: the measures per act and inline SVG plots of speed,
/// path projections (with the reference's paths) and forces over time.
pub fn html_report(
    report: &ScoreReport,
    mine: &SiteTracks,
    reference: Option<&SiteTracks>,
) -> Result<String, ScoreError> {
    let s = &report.settings;
    let speed_lines: Vec<Line> = mine
        .tracks
        .iter()
        .map(|t| Line {
            label: format!("{} {}", mine.site, tool_name(t)),
            points: t
                .times
                .iter()
                .copied()
                .zip(speeds(&t.times, &t.positions(), s.filter_cutoff_hz))
                .map(|(t, v)| (t, v * 1e3))
                .collect(),
            dashed: false,
        })
        .collect();
    let projection = |a: usize, b: usize| {
        let mut lines = Vec::new();
        for (who, dashed) in [(Some(mine), false), (reference, true)] {
            let Some(st) = who else { continue };
            for t in &st.tracks {
                lines.push(Line {
                    label: format!("{} {}", st.site, tool_name(t)),
                    points: t
                        .states
                        .iter()
                        .map(|x| (x.position[a] * 1e3, x.position[b] * 1e3))
                        .collect(),
                    dashed,
                });
            }
        }
        lines
    };
    let mut force_lines = Vec::new();
    for t in &mine.tracks {
        for (what, pick) in [("contact", 0), ("grasp", 1)] {
            let pts: Vec<(f64, f64)> = t
                .times
                .iter()
                .zip(&t.states)
                .map(|(&tt, x)| {
                    let f = if pick == 0 {
                        x.contact_force
                    } else {
                        x.grasp_force
                    };
                    (tt, (f[0] * f[0] + f[1] * f[1] + f[2] * f[2]).sqrt())
                })
                .collect();
            if pts.iter().any(|p| p.1 > 0.0) {
                force_lines.push(Line {
                    label: format!("{} {what}", tool_name(t)),
                    points: pts,
                    dashed: false,
                });
            }
        }
    }
    let damage: Vec<(f64, f64)> = mine
        .recording
        .damage()
        .into_iter()
        .map(|(t, v)| (t, v * 1e9))
        .collect();

    let mut h = String::new();
    let _ = write!(
        h,
        "<!DOCTYPE html><html><head><meta charset=\"utf-8\"><title>cosurg debrief: {}</title>\
         <style>body{{font-family:sans-serif;margin:2em;max-width:1000px}}\
         table{{border-collapse:collapse;font-size:13px}}td,th{{border:1px solid #bbb;padding:3px 6px;text-align:right}}\
         td:first-child,th:first-child{{text-align:left}}</style></head><body>",
        esc(&report.site)
    );
    let _ = write!(
        h,
        "<h1>Debrief of site {}</h1><p>Session {}, scene {}. Reference: {}. Recording: {}.</p>",
        esc(&report.site),
        esc(&report.session),
        esc(&report.scene),
        esc(report.reference.as_deref().unwrap_or("none")),
        esc(&report.recording_tail),
    );
    h.push_str(
        "<table><tr><th>act</th><th>start s</th><th>time s</th><th>path mm</th><th>economy</th>\
         <th>idle s</th><th>depth mm</th><th>peak speed mm/s</th><th>LDLJ</th><th>contact peak N</th>\
         <th>contact rms N</th><th>grasp peak N</th><th>grasp rms N</th><th>damage mm³·s</th>\
         <th>DTW mm</th><th>reference act</th></tr>",
    );
    for a in &report.acts {
        let m = &a.measures;
        let _ = write!(
            h,
            "<tr><td>{}</td><td>{:.2}</td><td>{:.2}</td><td>{:.1}</td><td>{}</td><td>{:.2}</td>\
             <td>{:.1}</td><td>{:.1}</td><td>{}</td><td>{:.3}</td><td>{:.3}</td><td>{:.3}</td>\
             <td>{:.3}</td><td>{}</td><td>{}</td><td>{}</td></tr>",
            esc(&a.act.label()),
            a.act.start_s,
            m.duration_s,
            m.path_length_m * 1e3,
            opt(m.economy, 1.0, 2),
            m.idle_time_s,
            m.depth_along_shaft_m * 1e3,
            m.peak_speed_m_s * 1e3,
            opt(m.ldlj, 1.0, 2),
            m.contact_force_peak_n,
            m.contact_force_rms_n,
            m.grasp_force_peak_n,
            m.grasp_force_rms_n,
            opt(m.damage_m3_s, 1e9, 3),
            opt(m.dtw_to_reference_m, 1e3, 2),
            esc(m.reference_act.as_deref().unwrap_or("–")),
        );
    }
    let _ = write!(
        h,
        "</table><p>Idle: filtered tip speed below {} mm/s. LDLJ = −ln(T³/v<sub>peak</sub>² ∫|jerk|² dt), \
         closer to 0 is smoother; positions low-passed at {} Hz (zero phase) before differentiating. \
         DTW: mean tip distance per matched pair after resampling each act to {} points, band ±{:.0} %. \
         Damage: volume with strain above {} integrated over time.</p>",
        s.idle_speed_m_s * 1e3,
        s.filter_cutoff_hz,
        s.dtw_points,
        s.dtw_band_fraction * 100.0,
        report
            .damage_strain_threshold
            .map_or("(not recorded)".into(), |t| t.to_string()),
    );
    h.push_str(&svg_chart(
        "Tip speed",
        "time (s)",
        "speed (mm/s)",
        &speed_lines,
    )?);
    h.push_str(&svg_chart(
        "Tip paths, top view (reference thin)",
        "x (mm)",
        "y (mm)",
        &projection(0, 1),
    )?);
    h.push_str(&svg_chart(
        "Tip paths, front view (reference thin)",
        "x (mm)",
        "z (mm)",
        &projection(0, 2),
    )?);
    if !force_lines.is_empty() {
        h.push_str(&svg_chart(
            "Forces on the tools",
            "time (s)",
            "|F| (N)",
            &force_lines,
        )?);
    }
    if !damage.is_empty() {
        h.push_str(&svg_chart(
            "Damaged tissue volume",
            "time (s)",
            "volume (mm³)",
            &[Line {
                label: "above the strain threshold".into(),
                points: damage,
                dashed: false,
            }],
        )?);
    }
    h.push_str("</body></html>\n");
    Ok(h)
}
