//! Recomputes the divergence of a finished demo or session folder:
//! `cargo run --example divergence_of -- DIR` (reads DIR/*/report.json).
fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt().with_env_filter("debug").init();
    let dir = std::path::PathBuf::from(std::env::args().nth(1).expect("DIR"));
    let mut reports = Vec::new();
    for name in ["instructor", "trainee-a", "trainee-b"] {
        let p = dir.join(name).join("report.json");
        if let Ok(text) = std::fs::read_to_string(&p) {
            reports.push(serde_json::from_str::<cosurg::site::SiteReport>(&text)?);
        }
    }
    cosurg::divergence::fill_divergence(&mut reports)?;
    for r in &reports {
        println!(
            "{} {:?} {:?}",
            r.name, r.divergence_max_mm, r.divergence_rms_mm
        );
    }
    Ok(())
}
