//! Divergence between sites, recomputed from their surface recordings (`.surf`, one
//! record of every embedded-surface vertex every 50 ms of simulated time).
//!
//! The reference for a vertex at a mark is the site that owned the vertex's region at
//! that simulated time (from the sites' ownership logs); where nobody owned it, the
//! first site (the instructor) is the reference. A site is never compared with itself.
//! Divergence = distance between the same vertex on the two sites at the same simulated
//! time (mm).

use std::collections::HashMap;

use anyhow::{Context, Result, bail};
use sim_core::sim_scene::surf::SurfaceRecording;
use sim_core::sync::RegionMap;
use sim_core::{SimOptions, Simulation};

use crate::plot::Series;
use crate::site::SiteReport;

/// Region of every recorded surface vertex (in recording order), from the rest pose.
fn vertex_regions(scene: sim_core::sim_scene::LoadedScene) -> Result<Vec<u32>> {
    let options = SimOptions::from_scene(&scene.scene);
    let sim = Simulation::new(scene, options)?;
    let map = RegionMap::for_simulation(&sim);
    let mut out = Vec::new();
    for s in sim.surfaces() {
        for i in 0..s.embedding.len() {
            let (tet, _, _) = s.embedding.host(i);
            out.push(map.region_of_root(tet.root).unwrap_or(u32::MAX));
        }
    }
    Ok(out)
}

/// Fills `divergence_max_mm` / `divergence_rms_mm` of every site report and returns, per
/// site, the max divergence (mm) at each mark.
pub fn fill_divergence(reports: &mut [SiteReport]) -> Result<Vec<Series>> {
    if reports.len() < 2 {
        return Ok(Vec::new());
    }
    let scene = crate::scene_arg::builtin_by_hash(&reports[0].scene_hash, reports[0].cell_m)
        .with_context(|| {
            format!(
                "divergence: the runs' scene (hash {}{}) is not a built-in scene",
                reports[0].scene_hash,
                reports[0]
                    .cell_m
                    .map_or(String::new(), |c| format!(", cell {c} m"))
            )
        })?;
    let regions = vertex_regions(scene)?;
    let mut recs = Vec::new();
    for r in reports.iter() {
        let path = r
            .surf_file
            .as_ref()
            .with_context(|| format!("site {} wrote no surface recording", r.name))?;
        let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
        let rec = SurfaceRecording::from_bytes(&bytes)
            .with_context(|| format!("parsing {}", path.display()))?;
        if rec.vertex_count() != regions.len() {
            bail!(
                "{}: {} vertices, expected {}",
                path.display(),
                rec.vertex_count(),
                regions.len()
            );
        }
        recs.push(rec);
    }
    // Owner of a region at simulated time t (by index into `reports`).
    let owner_at = |region: u32, t: f64| -> Option<usize> {
        reports.iter().position(|r| {
            r.owned
                .iter()
                .any(|&(reg, from, to)| reg == region && t >= from && t <= to)
        })
    };
    // Align records by their simulated-time mark (a late joiner starts recording later).
    let mark_of =
        |rec: &SurfaceRecording, i: usize| (rec.records[i].time_s / rec.interval_s).round() as i64;
    let index: Vec<HashMap<i64, usize>> = recs
        .iter()
        .map(|rec| {
            (0..rec.records.len())
                .map(|i| (mark_of(rec, i), i))
                .collect()
        })
        .collect();
    let mut marks: Vec<i64> = index[0]
        .keys()
        .copied()
        .filter(|m| index.iter().all(|ix| ix.contains_key(m)))
        .collect();
    marks.sort_unstable();
    let mut max = vec![0.0f64; reports.len()];
    let mut sum_sq = vec![0.0f64; reports.len()];
    let mut count = vec![0usize; reports.len()];
    let mut series: Vec<Vec<(f64, f64)>> = vec![Vec::new(); reports.len()];
    let mut owner_cache: HashMap<u32, Option<usize>> = HashMap::new();
    for m in marks {
        let at: Vec<usize> = index.iter().map(|ix| ix[&m]).collect();
        let t = recs[0].records[at[0]].time_s;
        owner_cache.clear();
        let mut mark_max = vec![0.0f64; reports.len()];
        for (v, &region) in regions.iter().enumerate() {
            let reference = owner_cache
                .entry(region)
                .or_insert_with(|| owner_at(region, t))
                .unwrap_or(0);
            let p = recs[reference].records[at[reference]].vertices[v];
            for (s, rec) in recs.iter().enumerate() {
                if s == reference {
                    continue;
                }
                let q = rec.records[at[s]].vertices[v];
                let d2: f64 = (0..3)
                    .map(|k| (f64::from(p[k]) - f64::from(q[k])).powi(2))
                    .sum();
                let d_mm = d2.sqrt() * 1e3;
                mark_max[s] = mark_max[s].max(d_mm);
                sum_sq[s] += d_mm * d_mm;
                count[s] += 1;
            }
        }
        if tracing::enabled!(tracing::Level::DEBUG) {
            for (s, rec) in recs.iter().enumerate() {
                if mark_max[s] > 5.0 {
                    let worst = regions
                        .iter()
                        .enumerate()
                        .map(|(v, &region)| {
                            let r = owner_cache.get(&region).copied().flatten().unwrap_or(0);
                            let p = recs[r].records[at[r]].vertices[v];
                            let q = rec.records[at[s]].vertices[v];
                            let d: f32 = (0..3).map(|k| (p[k] - q[k]).powi(2)).sum();
                            (d, v, region, r)
                        })
                        .max_by(|a, b| a.0.total_cmp(&b.0));
                    tracing::debug!(t, site = s, mm = mark_max[s], ?worst, "divergence");
                }
            }
        }
        for s in 0..reports.len() {
            max[s] = max[s].max(mark_max[s]);
            if count[s] > 0 {
                series[s].push((t, mark_max[s]));
            }
        }
    }
    let mut out = Vec::new();
    for (s, r) in reports.iter_mut().enumerate() {
        if count[s] > 0 {
            r.divergence_max_mm = Some(max[s]);
            r.divergence_rms_mm = Some((sum_sq[s] / count[s] as f64).sqrt());
            out.push(Series {
                label: r.name.clone(),
                points: std::mem::take(&mut series[s]),
            });
        }
    }
    Ok(out)
}
