//! `cosurg score`: skill measures of one site's acts from a recording (or a directory of
//! recordings), against a reference site or recording; text, JSON or HTML.

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use clap::Args;
use debrief::report::text_table;
use debrief::{Recording, ScoreSettings, Session, SiteTracks, html_report, score_site};

#[derive(Debug, Args)]
pub struct ScoreArgs {
    /// A recording (.cosrec) or a directory of recordings (one per site).
    pub recording: PathBuf,
    /// The site to score.
    #[arg(long)]
    pub site: String,
    /// Reference: a site of the same session, or a recording file/directory (its
    /// recording site is the reference; `SITE@PATH` picks another site in it).
    #[arg(long)]
    pub reference: Option<String>,
    /// Print the scores as JSON instead of a table.
    #[arg(long)]
    pub json: bool,
    /// Also write a self-contained HTML report here.
    #[arg(long)]
    pub html: Option<PathBuf>,
    /// Tip speed below which the tool is idle (mm/s).
    #[arg(long, default_value_t = 5.0)]
    pub idle_speed: f64,
}

/// Finds the recording holding `site` in a session, with a helpful error.
fn pick<'a>(session: &'a Session, site: &str, what: &str) -> Result<&'a Recording> {
    session.recording_for(site).with_context(|| {
        format!(
            "{what} site {site:?} not found (recordings of: {})",
            session.sites().join(", ")
        )
    })
}

pub fn score(args: ScoreArgs) -> Result<()> {
    let session = Session::open(&args.recording)
        .with_context(|| format!("opening {}", args.recording.display()))?;
    let rec = pick(&session, &args.site, "scored")?;
    if args.idle_speed.is_nan() || args.idle_speed < 0.0 {
        bail!(
            "--idle-speed must be a speed in mm/s ≥ 0, got {}",
            args.idle_speed
        );
    }
    let settings = ScoreSettings {
        idle_speed_m_s: args.idle_speed * 1e-3,
        ..ScoreSettings::default()
    };
    let ref_session;
    let reference: Option<(&Recording, String)> = match &args.reference {
        None => None,
        Some(r) => {
            let (site, path) = match r.split_once('@') {
                Some((s, p)) => (Some(s.to_string()), PathBuf::from(p)),
                None => (None, PathBuf::from(r)),
            };
            if path.exists() {
                ref_session = Session::open(&path)
                    .with_context(|| format!("opening the reference {}", path.display()))?;
                let site = site.unwrap_or_else(|| ref_session.recordings[0].header.site.clone());
                Some((pick(&ref_session, &site, "reference")?, site))
            } else if site.is_none() && !r.contains(['/', '\\']) && !r.ends_with(".cosrec") {
                Some((pick(&session, r, "reference")?, r.clone()))
            } else {
                bail!("reference recording {} does not exist", path.display());
            }
        }
    };
    let report = score_site(
        rec,
        &args.site,
        reference.as_ref().map(|(r, s)| (*r, s.as_str())),
        &settings,
    )?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    } else {
        println!(
            "site {} in {} ({}, recording {}){}",
            report.site,
            rec.path
                .as_ref()
                .map_or(String::new(), |p| p.display().to_string()),
            report.scene,
            report.recording_tail,
            report
                .reference
                .as_ref()
                .map_or(String::new(), |r| format!(", reference {r}"))
        );
        if rec.header.role == debrief::COORDINATOR_ROLE {
            println!(
                "from the coordinator's recording: tool poses only (forces, grasp state and damage are not relayed; their columns read 0)"
            );
        }
        print!("{}", text_table(&report));
        println!(
            "units: path/depth mm, forces N (Fc contact, Fg grasp), damage mm³·s (strain > {}), DTW mm per matched pair; LDLJ closer to 0 = smoother",
            report
                .damage_strain_threshold
                .map_or("–".into(), |t| t.to_string())
        );
    }
    if let Some(path) = &args.html {
        let mine = SiteTracks::new(rec, &args.site, &settings)?;
        let theirs = reference
            .as_ref()
            .map(|(r, s)| SiteTracks::new(r, s, &settings))
            .transpose()?;
        let html = html_report(&report, &mine, theirs.as_ref())?;
        std::fs::write(path, html).with_context(|| format!("writing {}", path.display()))?;
        eprintln!("wrote {}", path.display());
    }
    Ok(())
}
