//! Recomputes the divergence of a finished demo or session folder:
//! `cargo run --example divergence_of -- DIR` (reads DIR/*/report.json): each site's
//! worst divergence and when.
fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt().with_env_filter("debug").init();
    let dir = std::path::PathBuf::from(std::env::args().nth(1).expect("DIR"));
    let mut reports = Vec::new();
    for name in ["instructor", "trainee", "trainee-a", "trainee-b"] {
        let p = dir.join(name).join("report.json");
        if let Ok(text) = std::fs::read_to_string(&p) {
            reports.push(serde_json::from_str::<cosurg::site::SiteReport>(&text)?);
        }
    }
    let series = cosurg::divergence::fill_divergence(&mut reports)?;
    for s in &series {
        let worst = s
            .points
            .iter()
            .copied()
            .fold((0.0, 0.0), |w, p| if p.1 > w.1 { p } else { w });
        println!(
            "{}: worst {:.2} mm at t = {:.2} s",
            s.label, worst.1, worst.0
        );
        let near: Vec<String> = s
            .points
            .iter()
            .filter(|p| (p.0 - worst.0).abs() <= 0.2)
            .map(|p| format!("{:.2}: {:.2}", p.0, p.1))
            .collect();
        println!("  around it: {}", near.join(", "));
        if std::env::var_os("ALL").is_some() {
            let all: Vec<String> = s
                .points
                .iter()
                .map(|p| format!("{:.2}: {:.2}", p.0, p.1))
                .collect();
            println!("  all: {}", all.join(", "));
        }
    }
    for r in &reports {
        println!(
            "{} {:?} {:?}",
            r.name, r.divergence_max_mm, r.divergence_rms_mm
        );
    }
    Ok(())
}
