//! `cosurg replay`: plays recordings back — in the window (play, pause, scrub on a
//! timeline, speed; every chosen site's tools over the recorded surface, `--sites A,B`
//! overlaid), as one picture without a screen (`--screenshot FILE.png --at SECONDS`),
//! headless to measure how fast frames are made (`--headless`), or as a ParaView series
//! (`--export-vtu DIR`).

use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::Args;
use debrief::{Recording, Session, StepRecord};
use nalgebra::{Quaternion, UnitQuaternion, Vector3};
use sim_core::sim_scene::vtk::{self, Cells, DataArray, Encoding, Pvd, UnstructuredGrid};
use viewer::replay::ReplaySource;

mod frames;
pub use frames::RecordedSession;

#[derive(Debug, Args)]
pub struct ReplayArgs {
    /// A recording (.cosrec) or a directory of recordings.
    pub recording: PathBuf,
    /// Write the ParaView series (one folder per recording site) into DIR.
    #[arg(long, value_name = "DIR")]
    pub export_vtu: Option<PathBuf>,
    /// Simulated time between exported frames when a recording has no surface frames (s).
    #[arg(long, default_value_t = 0.05)]
    pub frame_interval: f64,
    /// Sites to show, comma-separated: the first's surface, every one's tools overlaid
    /// (default: every recording site but the coordinator, or the coordinator's sites).
    #[arg(long, value_delimiter = ',')]
    pub sites: Vec<String>,
    /// Scene to draw with (`builtin:NAME` or a TOML file): surface topology, tool
    /// geometry, camera. Default: the built-in cholecystectomy.
    #[arg(long)]
    pub scene: Option<String>,
    /// Lattice cell size (m) the recorded session's sites gave (`cosurg join --cell`), so
    /// that the scene is the one recorded.
    #[arg(long, value_name = "M", long_help = crate::scene_arg::CELL_HELP)]
    pub cell: Option<f64>,
    /// Render the picture at `--at` off-screen into this PNG file (no window).
    #[arg(long, value_name = "FILE.png", requires = "at")]
    pub screenshot: Option<PathBuf>,
    /// Recorded time of the screenshot, from the start of the recording (s).
    #[arg(long, value_name = "SECONDS")]
    pub at: Option<f64>,
    /// Window or screenshot size.
    #[arg(long, value_name = "WxH", default_value = "1280x720", value_parser = crate::run_window::parse_size)]
    pub size: (u32, u32),
    /// Make every frame the window would show at 60 frames per recorded second, without
    /// drawing, and report how much faster than real time that ran.
    #[arg(long)]
    pub headless: bool,
}

/// What one export did.
#[derive(Clone, Debug)]
pub struct ExportStats {
    pub site: String,
    pub frames: usize,
    /// Recorded (simulated) time covered (s).
    pub recorded_s: f64,
    pub wall_s: f64,
}

/// Frames per recorded second made by `--headless` (what the window draws at 1×).
pub const HEADLESS_FPS: f64 = 60.0;

/// The sites shown by default: every site with its own recording, else the sites whose
/// tools a coordinator's recording holds.
fn default_sites(session: &Session) -> Vec<String> {
    let own: Vec<String> = session
        .recordings
        .iter()
        .filter(|r| r.header.role != debrief::COORDINATOR_ROLE)
        .map(|r| r.header.site.clone())
        .collect();
    if !own.is_empty() {
        return own;
    }
    let mut sites: Vec<String> = session
        .recordings
        .iter()
        .flat_map(|r| r.tools().into_iter().map(|t| t.site.clone()))
        .collect();
    sites.dedup();
    sites
}

pub fn replay(args: ReplayArgs) -> Result<()> {
    if args.frame_interval.is_nan() || args.frame_interval <= 0.0 {
        bail!(
            "--frame-interval must be > 0 s, got {}",
            args.frame_interval
        );
    }
    if let Some(at) = args.at
        && (at.is_nan() || at < 0.0)
    {
        bail!("--at must be a recorded time ≥ 0 s, got {at}");
    }
    let session = Session::open(&args.recording)
        .with_context(|| format!("opening {}", args.recording.display()))?;
    if let Some(dir) = &args.export_vtu {
        return export_all(&session, dir, args.frame_interval);
    }
    let sites = if args.sites.is_empty() {
        default_sites(&session)
    } else {
        args.sites.clone()
    };
    let scene = crate::scene_arg::load_scene_with_cell(args.scene.as_deref(), args.cell)?;
    let t0 = Instant::now();
    let mut source = RecordedSession::new(&scene, &session, &sites)?;
    let (a, b) = source.span();
    let load_s = t0.elapsed().as_secs_f64();
    tracing::info!(
        "loaded {} in {load_s:.3} s: {:.2} s recorded",
        sites.join(", "),
        b - a
    );
    if let Some(path) = &args.screenshot {
        let at = args.at.unwrap_or(0.0);
        let frame = source.frame_at(a + at);
        viewer::screenshot(&frame, args.size, path)
            .with_context(|| format!("screenshot at {at:.3} s"))?;
        println!(
            "wrote {} ({}x{}, {} at {:.3} s of {:.3} s recorded)",
            path.display(),
            args.size.0,
            args.size.1,
            sites.join(" + "),
            at.min(b - a),
            b - a
        );
        return Ok(());
    }
    if args.headless {
        let n = ((b - a) * HEADLESS_FPS).floor() as usize + 1;
        let t0 = Instant::now();
        let mut vertices = 0usize;
        for k in 0..n {
            let f = source.frame_at(a + k as f64 / HEADLESS_FPS);
            vertices += f.positions.len() + f.tools.len();
        }
        let wall = t0.elapsed().as_secs_f64();
        std::hint::black_box(vertices);
        println!(
            "replayed {:.2} s of {} headless: {n} frames in {wall:.3} s wall ({:.3} ms per frame), {:.1}× real time; with loading the recordings and the scene ({load_s:.3} s) {:.1}× real time",
            b - a,
            sites.join(" + "),
            1e3 * wall / n as f64,
            (b - a) / wall.max(1e-9),
            (b - a) / (wall + load_s).max(1e-9)
        );
        return Ok(());
    }
    if !crate::run_window::display_available() {
        bail!(
            "no display for the replay window (DISPLAY/WAYLAND_DISPLAY unset); use --screenshot FILE.png --at SECONDS, --headless or --export-vtu DIR"
        );
    }
    viewer::replay::run_replay_window(
        &mut source,
        viewer::WindowOptions {
            title: format!("cosurg replay — {}", sites.join(" + ")),
            size: args.size,
            ..Default::default()
        },
    )?;
    Ok(())
}

/// `--export-vtu`: every recording of the session, one folder per recording site.
fn export_all(session: &Session, dir: &Path, interval: f64) -> Result<()> {
    let t0 = Instant::now();
    let mut recorded = 0.0f64;
    for rec in &session.recordings {
        let out = if session.recordings.len() == 1 {
            dir.to_path_buf()
        } else {
            dir.join(sanitize(&rec.header.site))
        };
        let st = export_vtu(rec, &out, interval)?;
        println!(
            "site {}: {} frames over {:.2} s recorded → {}",
            st.site,
            st.frames,
            st.recorded_s,
            out.join("series.pvd").display()
        );
        recorded = recorded.max(st.recorded_s);
    }
    let wall = t0.elapsed().as_secs_f64();
    println!(
        "replayed {:.2} s of session in {:.3} s wall: {:.1}× real time",
        recorded,
        wall,
        recorded / wall.max(1e-9)
    );
    Ok(())
}

fn sanitize(name: &str) -> String {
    name.chars()
        .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
        .collect()
}

fn v3(p: [f64; 3]) -> Vector3<f64> {
    Vector3::new(p[0], p[1], p[2])
}

/// Writes `rec`'s surfaces and tools into `dir` as `series.pvd` plus one VTU per frame
/// and part. Frames are the recorded surface frames, else every `interval` s.
pub fn export_vtu(rec: &Recording, dir: &Path, interval: f64) -> Result<ExportStats> {
    let t0 = Instant::now();
    std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    let surfaces = rec.surfaces();
    let shapes: Vec<_> = surfaces.iter().map(|s| rec.surface_shapes(s.id)).collect();
    let steps: Vec<&StepRecord> = rec.steps().collect();
    let tools = rec.tools();
    // Frame times: every surface frame's time, else a regular grid over the steps.
    let mut times: Vec<f64> = shapes.iter().flatten().map(|s| s.time).collect();
    if times.is_empty()
        && let (Some(a), Some(b)) = (steps.first(), steps.last())
    {
        let n = ((b.time - a.time) / interval).floor() as usize;
        times = (0..=n).map(|i| a.time + i as f64 * interval).collect();
    }
    times.sort_by(f64::total_cmp);
    times.dedup_by(|a, b| (*a - *b).abs() < 1e-9);
    let mut pvd = Pvd::new();
    let mut cursor = vec![0usize; shapes.len()];
    for (f, &t) in times.iter().enumerate() {
        for (k, (decl, frames)) in surfaces.iter().zip(&shapes).enumerate() {
            // The latest frame of this surface at or before t.
            while cursor[k] + 1 < frames.len() && frames[cursor[k] + 1].time <= t + 1e-9 {
                cursor[k] += 1;
            }
            let Some(shape) = frames.get(cursor[k]).filter(|s| s.time <= t + 1e-9) else {
                continue;
            };
            let pts: Vec<Vector3<f64>> = shape.vertices.iter().map(|p| v3(*p)).collect();
            let disp: Vec<Vector3<f64>> = shape
                .vertices
                .iter()
                .zip(&decl.rest)
                .map(|(p, r)| v3(*p) - Vector3::new(r[0], r[1], r[2]).cast::<f64>())
                .collect();
            let grid = UnstructuredGrid::new(&pts, Cells::Triangles(&decl.triangles))
                .with_point_data(DataArray::vectors("displacement", &disp));
            let name = format!("surface_{}_{f:05}.vtu", sanitize(&decl.name));
            vtk::write_vtu_file(dir.join(&name), &grid, Encoding::Binary)?;
            pvd.push(t, k as u32, name);
        }
        // Tools: the last step record at or before t.
        let i = steps.partition_point(|s| s.time <= t + 1e-9);
        if let Some(step) = i.checked_sub(1).map(|i| steps[i])
            && !step.samples.is_empty()
        {
            let states: Vec<_> = step.samples.iter().map(|s| s.state()).collect();
            let poses: Vec<(Vector3<f64>, UnitQuaternion<f64>)> = states
                .iter()
                .map(|s| {
                    let [w, x, y, z] = s.orientation;
                    (
                        v3(s.position),
                        UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z)),
                    )
                })
                .collect();
            let jaw: Vec<f64> = states.iter().map(|s| s.jaw).collect();
            let grasped: Vec<i32> = states.iter().map(|s| s.grasped as i32).collect();
            let contact: Vec<Vector3<f64>> = states.iter().map(|s| v3(s.contact_force)).collect();
            let grasp: Vec<Vector3<f64>> = states.iter().map(|s| v3(s.grasp_force)).collect();
            let tool_index: Vec<i32> = step.samples.iter().map(|s| i32::from(s.tool)).collect();
            let name = format!("tools_{f:05}.vtu");
            let path = dir.join(&name);
            let file = std::fs::File::create(&path)
                .with_context(|| format!("creating {}", path.display()))?;
            vtk::write_poses_vtu(
                &mut BufWriter::new(file),
                &poses,
                vec![
                    DataArray::ints("tool", &tool_index),
                    DataArray::scalars("jaw_angle_rad", &jaw),
                    DataArray::ints("grasped_points", &grasped),
                    DataArray::vectors("contact_force_N", &contact),
                    DataArray::vectors("grasp_force_N", &grasp),
                ],
                Encoding::Binary,
            )
            .with_context(|| format!("writing {}", path.display()))?;
            pvd.push(t, surfaces.len() as u32, name);
        }
    }
    pvd.write_file(dir.join("series.pvd"))?;
    if !tools.is_empty() {
        let names: Vec<String> = tools
            .iter()
            .map(|t| format!("{} {} {} {}", t.id, t.site, t.name, t.kind))
            .collect();
        std::fs::write(dir.join("tools.txt"), names.join("\n") + "\n")?;
    }
    let recorded_s = rec.time_span().map_or(0.0, |(a, b)| b - a);
    Ok(ExportStats {
        site: rec.header.site.clone(),
        frames: times.len(),
        recorded_s,
        wall_s: t0.elapsed().as_secs_f64(),
    })
}
