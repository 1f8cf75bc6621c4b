//! Smoke test of `cosurg bench cantilever --quick --json`, `cosurg bench stress --quick
//! --json` and `cosurg bench coordinator --quick --json`: the JSON schema and the invariants
//! (no NaN, finite non-negative deviations, co-rotational closer to the non-linear reference
//! than linear on the soft beam; the coordinator bench's counts, not its timings).

use std::process::Command;

use serde_json::Value;

fn bench(args: &[&str]) -> Value {
    let dir = tempfile::tempdir().unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_cosurg"))
        .arg("bench")
        .args(args)
        .arg("--out")
        .arg(dir.path())
        .output()
        .expect("run cosurg");
    assert!(
        out.status.success(),
        "cosurg bench {args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).unwrap_or_else(|e| {
        panic!(
            "stdout is not JSON ({e}): {}",
            String::from_utf8_lossy(&out.stdout)
        )
    })
}

fn num(v: &Value, key: &str) -> f64 {
    v[key]
        .as_f64()
        .unwrap_or_else(|| panic!("{key} missing or not a number in {v}"))
}

#[test]
fn cantilever_quick_json() {
    let r = bench(&["cantilever", "--quick", "--json"]);
    assert!(r["scene_hash"].as_str().is_some_and(|h| h.len() >= 16));
    let runs = r["runs"].as_array().expect("runs");
    assert!(!runs.is_empty());
    for run in runs {
        for key in ["model", "material"] {
            assert!(run[key].is_string(), "{key} in {run}");
        }
        assert!(run["options"].is_object());
        for key in [
            "young",
            "cell",
            "dt",
            "step_ms_p50",
            "step_ms_p99",
            "us_per_element",
            "max_dev_m",
            "rms_dev_m",
        ] {
            let v = num(run, key);
            assert!(v.is_finite() && v >= 0.0, "{key} = {v} in {run}");
        }
        for key in ["tets", "nodes"] {
            assert!(run[key].as_u64().is_some_and(|n| n > 0), "{key} in {run}");
        }
        assert!(num(run, "rms_dev_m") <= num(run, "max_dev_m") + 1e-15);
        assert_eq!(run["non_finite"], Value::Bool(false));
        let o = &run["options"];
        for key in [
            "polar",
            "sharing_angle_deg",
            "template_stiffness",
            "skip_rest",
        ] {
            assert!(!o[key].is_null(), "options.{key} in {run}");
        }
    }
    let models: Vec<&str> = runs.iter().filter_map(|r| r["model"].as_str()).collect();
    for m in ["stvk", "linear", "corotational"] {
        assert!(models.contains(&m), "no {m} run");
    }
    let dev = |model: &str, variant: &str| {
        runs.iter()
            .find(|r| {
                r["material"] == "soft" && r["model"] == model && r["options"]["variant"] == variant
            })
            .map(|r| num(r, "max_dev_m"))
            .unwrap_or_else(|| panic!("no soft {model} {variant} run"))
    };
    let lin = dev("linear", "default");
    let corot = dev("corotational", "all-on");
    assert!(
        corot < lin,
        "soft beam: co-rotational deviation {corot} m not below linear {lin} m"
    );
    assert_eq!(dev("stvk", "reference"), 0.0);
    // On the stiff beam at dt 10 ms the 50-iteration Jacobi-PCG budget leaves the step
    // unconverged; MG-PCG converges every step and tracks the StVK reference closer
    // (0.42 against 1.35 mm when this test was written).
    let stiff = |variant: &str| {
        runs.iter()
            .find(|r| {
                r["material"] == "stiff"
                    && r["model"] == "corotational"
                    && r["options"]["variant"] == variant
            })
            .map(|r| num(r, "max_dev_m"))
            .unwrap_or_else(|| panic!("no stiff co-rotational {variant} run"))
    };
    let (budget, converged) = (stiff("all-on"), stiff("all-on-mg-pcg"));
    assert!(
        converged < 0.5 * budget,
        "stiff beam: MG-PCG deviation {converged} m not well below the budgeted {budget} m"
    );
}

#[test]
fn stress_quick_json() {
    let r = bench(&["stress", "--quick", "--json"]);
    assert!(r["scene_hash"].is_string());
    let cases = r["cases"].as_array().expect("cases");
    assert!(cases.len() >= 3);
    for c in cases {
        assert_eq!(c["nan"], Value::Bool(false), "NaN in {c}");
        assert!(c["steps"].as_u64().is_some_and(|s| s >= 2000), "{c}");
        let e = num(c, "max_energy_rel");
        assert!(e.is_finite() && e >= 0.0, "{c}");
        assert!(num(c, "max_speed").is_finite());
        assert!(c["steps_to_rest"].is_null() || c["steps_to_rest"].is_u64());
    }
    assert!(
        cases.iter().any(|c| c["max_inverted"].as_u64() > Some(0)),
        "the pull inverts elements"
    );
    for config in ["product", "cg-converged", "mg-pcg", "mg-pcg-budget"] {
        assert!(
            cases.iter().any(|c| c["config"] == config),
            "no {config} case"
        );
    }
    // After a pull through inversion the body comes back to rest and gains no energy
    // (within 5 % of what it held at release), with the real-time and the converged CG and
    // with MG-PCG:
    // shared rotations switching on inverted leaves once made it gain several times that
    // and never settle.
    for c in cases
        .iter()
        .filter(|c| c["name"].as_str().is_some_and(|n| n.starts_with("pull")))
    {
        assert!(c["steps_to_rest"].is_u64(), "pull-through never rests: {c}");
        assert!(
            num(c, "max_energy_rel") <= 1.05,
            "energy grew after release: {c}"
        );
    }
}

/// `cosurg bench scale --json ARGS` (it writes no files), parsed.
fn scale_json(args: &[&str]) -> Value {
    let out = Command::new(env!("CARGO_BIN_EXE_cosurg"))
        .args(["bench", "scale", "--json"])
        .args(args)
        .output()
        .expect("run cosurg");
    assert!(
        out.status.success(),
        "cosurg bench scale {args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).expect("JSON")
}

#[test]
fn scale_json_every_solver_converges_and_the_exponents_are_reported() {
    let r = scale_json(&["--cells", "0.05,0.025", "--dts", "0.01", "--steps", "2"]);
    let rows = r["rows"].as_array().expect("rows");
    // 2 beams × 2 meshes × 1 dt × 3 solvers, then the organ × 1 dt × 3 solvers.
    assert_eq!(rows.len(), 15, "{r}");
    for row in rows {
        let residual = num(row, "residual_max");
        assert!(residual <= 1e-6, "not converged: {row}");
        if row["solver"] == "direct" {
            assert_eq!(num(row, "iterations_max"), 0.0, "{row}");
            // Exact up to round-off, not just to the tolerance.
            assert!(residual < 1e-9, "{row}");
        }
        // The cosurg binary counts its heap: every row held some.
        assert!(num(row, "heap_peak_mib") > 0.0, "{row}");
    }
    let organ: Vec<&Value> = rows.iter().filter(|w| w["material"] == "organ").collect();
    assert_eq!(organ.len(), 3, "{r}");
    assert!(organ.iter().all(|w| w["young_pa"].is_null()), "{r}");
    // The finer beam holds more than the coarser one (8× the tets), solver by solver.
    let heap = |cell_tets: f64, solver: &str| {
        rows.iter()
            .filter(|w| {
                w["material"] == "soft" && w["solver"] == solver && num(w, "tets") == cell_tets
            })
            .map(|w| num(w, "heap_peak_mib"))
            .next()
            .expect("row")
    };
    let tets: Vec<f64> = rows
        .iter()
        .filter(|w| w["material"] == "soft")
        .map(|w| num(w, "tets"))
        .collect();
    let (small, big) = (
        tets.iter().cloned().fold(f64::MAX, f64::min),
        tets.iter().cloned().fold(0.0, f64::max),
    );
    for solver in ["jacobi-pcg", "mg-pcg", "direct"] {
        assert!(
            heap(big, solver) > 2.0 * heap(small, solver),
            "{solver}: {r}"
        );
    }
    let exps = r["exponents"].as_array().expect("exponents");
    assert_eq!(exps.len(), 6, "{r}");
    for e in exps {
        assert!(num(e, "tets_to") > num(e, "tets_from"), "{e}");
        assert!(num(e, "exponent").is_finite(), "{e}");
    }
}

/// `--repeat 3`: every row three times in rounds; a row's p50 is the median of its
/// runs' (each kept, in round order), and the exponent comes from those medians, with
/// each round's own beside it.
#[test]
fn scale_json_repeat_reports_medians_and_each_rounds_exponent() {
    let r = scale_json(&[
        "--cells",
        "0.05,0.025",
        "--dts",
        "0.01",
        "--steps",
        "2",
        "--solvers",
        "mg-pcg",
        "--no-organ",
        "--repeat",
        "3",
    ]);
    let rows = r["rows"].as_array().expect("rows");
    assert_eq!(rows.len(), 4, "{r}");
    let median = |v: &[f64]| {
        let mut v = v.to_vec();
        v.sort_by(f64::total_cmp);
        v[1]
    };
    let runs = |row: &Value| -> Vec<f64> {
        row["ms_p50_runs"]
            .as_array()
            .expect("ms_p50_runs")
            .iter()
            .map(|x| x.as_f64().expect("number"))
            .collect()
    };
    for row in rows {
        let p50s = runs(row);
        assert_eq!(p50s.len(), 3, "{row}");
        assert!(p50s.iter().all(|&t| t > 0.0), "{row}");
        assert_eq!(num(row, "ms_p50"), median(&p50s), "{row}");
        assert!(num(row, "residual_max") <= 1e-6, "{row}");
    }
    let exps = r["exponents"].as_array().expect("exponents");
    assert_eq!(exps.len(), 2, "{r}");
    for e in exps {
        let beam: Vec<&Value> = rows
            .iter()
            .filter(|w| w["material"] == e["material"])
            .collect();
        let (small, big) = (beam[0], beam[1]);
        let through = |a: f64, b: f64| (b / a).ln() / (num(big, "tets") / num(small, "tets")).ln();
        let want = through(num(small, "ms_p50"), num(big, "ms_p50"));
        assert!((num(e, "exponent") - want).abs() < 1e-12, "{e}");
        let each: Vec<f64> = e["exponent_runs"]
            .as_array()
            .expect("exponent_runs")
            .iter()
            .map(|x| x.as_f64().expect("number"))
            .collect();
        assert_eq!(each.len(), 3, "{e}");
        for (k, x) in each.iter().enumerate() {
            let want = through(runs(small)[k], runs(big)[k]);
            assert!((x - want).abs() < 1e-12, "round {k}: {e}");
        }
    }
}

/// `--organ-cells`: the organ's rows at the default 2 cm and at 1.33 cm (the finer organ
/// of `cosurg run --cell`), each converged; the finer has about 3.3× the tets.
#[test]
fn scale_json_runs_the_organ_at_each_requested_cell() {
    let r = scale_json(&[
        "--cells",
        "0.05",
        "--dts",
        "0.01",
        "--steps",
        "1",
        "--solvers",
        "mg-pcg",
        "--organ-cells",
        "0.02,0.013333333",
    ]);
    let rows = r["rows"].as_array().expect("rows");
    let organ: Vec<&Value> = rows.iter().filter(|w| w["material"] == "organ").collect();
    assert_eq!(organ.len(), 2, "{r}");
    assert_eq!(num(organ[0], "cell_m"), 0.02);
    assert_eq!(num(organ[1], "cell_m"), 0.013333333);
    for row in &organ {
        assert!(num(row, "residual_max") <= 1e-6, "not converged: {row}");
    }
    let (coarse, fine) = (num(organ[0], "tets"), num(organ[1], "tets"));
    assert!(
        fine > 2.5 * coarse,
        "{fine} tets at 1.33 cm against {coarse} at 2 cm"
    );
    // The beams report their own cell.
    assert!(
        rows.iter()
            .filter(|w| w["material"] != "organ")
            .all(|w| num(w, "cell_m") == 0.05),
        "{r}"
    );
}

#[test]
fn coordinator_quick_json() {
    // The bench starts `cosurg-server` (another package's binary) as its coordinator.
    let server = test_support::exe::sibling_exe(env!("CARGO_BIN_EXE_cosurg"), "cosurg-server");
    let r = bench(&[
        "coordinator",
        "--quick",
        "--json",
        "--server",
        server.to_str().unwrap(),
    ]);
    assert!(num(&r, "keyframe_bytes") > 0.0);
    let rows = r["rows"].as_array().expect("rows");
    assert_eq!(rows.len(), 2, "{r}");
    for (row, (sessions, per)) in rows.iter().zip([(1u64, 3u64), (2, 3)]) {
        assert_eq!(row["sessions"].as_u64(), Some(sessions), "{row}");
        assert_eq!(row["sites_per_session"].as_u64(), Some(per), "{row}");
        assert_eq!(row["sites"].as_u64(), Some(sessions * per), "{row}");
        let sent = row["datagrams_sent"].as_u64().unwrap();
        let expected = row["datagrams_expected"].as_u64().unwrap();
        let received = row["datagrams_received"].as_u64().unwrap();
        // 1 s at 60 + 20 Hz per site: each datagram goes to the session's other sites.
        assert!(sent >= sessions * per * 40, "{row}");
        assert_eq!(expected, sent * (per - 1), "{row}");
        // Loopback loses little; nothing is delivered twice or across sessions.
        assert!(
            received <= expected && received * 10 >= expected * 9,
            "{row}"
        );
        let kf_sent = row["keyframes_sent"].as_u64().unwrap();
        // 20 keyframes per second per session by default.
        assert!(kf_sent >= sessions * 10, "{row}");
        assert_eq!(
            row["keyframes_expected"].as_u64(),
            Some(kf_sent * (per - 1)),
            "{row}"
        );
        assert!(
            row["keyframes_received"].as_u64().unwrap() <= kf_sent * (per - 1),
            "{row}"
        );
        for key in [
            "relay_p50_ms",
            "relay_p99_ms",
            "coordinator_cpu_percent",
            "coordinator_rss_mib",
        ] {
            let v = num(row, key);
            assert!(v.is_finite() && v >= 0.0, "{key} in {row}");
        }
        assert!(
            num(row, "relay_p50_ms") <= num(row, "relay_p99_ms"),
            "{row}"
        );
        assert!(row["meets_goal"].is_boolean(), "{row}");
    }
}
