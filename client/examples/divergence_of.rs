//! Recomputes the divergence of a finished demo or session folder:
//! `cargo run --example divergence_of -- DIR` (reads DIR/*/report.json): each site's
//! worst divergence and when. `ALL=1`: the whole series; `EVENTS=1`: every site's grasps
//! and releases from its recording (DIR/NAME/NAME.cosrec), to see which site grasped when;
//! `TOOLS=T0,T1`: every site's recorded tools between simulated times T0 and T1 (s).
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
    if std::env::var_os("EVENTS").is_some() {
        for name in ["instructor", "trainee", "trainee-a", "trainee-b"] {
            let p = dir.join(name).join(format!("{name}.cosrec"));
            let Ok(rec) = debrief::Recording::open(&p) else {
                continue;
            };
            for e in rec.events().filter(|e| {
                matches!(
                    e.kind,
                    debrief::EventKind::Grasp | debrief::EventKind::GraspRelease
                )
            }) {
                println!(
                    "{name}: {:.3} s step {} {:?} {:?} {}",
                    e.time, e.step, e.tool, e.kind, e.detail
                );
            }
        }
    }
    if let Ok(window) = std::env::var("TOOLS") {
        let (t0, t1) = window.split_once(',').expect("TOOLS=T0,T1");
        let (t0, t1): (f64, f64) = (t0.parse()?, t1.parse()?);
        for name in ["instructor", "trainee", "trainee-a", "trainee-b"] {
            let p = dir.join(name).join(format!("{name}.cosrec"));
            let Ok(rec) = debrief::Recording::open(&p) else {
                continue;
            };
            for step in rec.steps().filter(|s| s.time >= t0 && s.time <= t1) {
                for s in &step.samples {
                    let st = s.state();
                    println!(
                        "{name}: {:.3} tool {} pos mm [{:.3} {:.3} {:.3}] jaw {:.3} grasped {} contact N {:.3}",
                        step.time,
                        s.tool,
                        st.position[0] * 1e3,
                        st.position[1] * 1e3,
                        st.position[2] * 1e3,
                        st.jaw,
                        st.grasped,
                        nalgebra::Vector3::from(st.contact_force).norm()
                    );
                }
            }
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
