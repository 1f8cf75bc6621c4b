//! The window's pictures of a recorded session: [`RecordedSession`] turns recordings into
//! [`viewer::ViewFrame`]s at any recorded time (the viewer's [`ReplaySource`]).
//!
//! The recording gives the organ surface (its declared rest shape and triangles, then its
//! frames); the scene gives what a recording does not hold: tissue colours (looked up at
//! the rest shape, as the live window does), the laparoscope port and the tools' geometry
//! (by name, else kind, else scene index). No simulation is built. The surface is the
//! first chosen site's recorded surface (the latest frame at or before the time: surfaces
//! are recorded every 0.5 s by default, so the surface moves in steps; a coordinator's
//! recording has none, and the organ is drawn at rest from another recording's
//! declaration); vessels and clips are not recorded and are not drawn. Tools are every chosen
//! site's own tools at their latest recorded sample (250 Hz by default; a coordinator's
//! recording: every pose relayed), the first site's in the local colour and the others'
//! in the remote colour (overlay), with their recorded contact plus grasp force as an
//! arrow.

use std::sync::Arc;

use anyhow::{Result, bail};
use debrief::{Recording, SurfaceDecl, SurfaceShape, ToolState, Track};
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion, Vector3};
use sim_core::sim_scene::LoadedScene;
use sim_core::{Tool, ToolInput};
use viewer::frame::{port_of, tissue_at};
use viewer::replay::ReplaySource;
use viewer::{ForceArrow, HudInfo, Role, SurfaceTopology, ViewFrame};

/// Depth below the surface at which a vertex's tissue is looked up (m), as the live
/// window does: a vertex exactly on an inclusion's boundary takes the tissue inside.
const TISSUE_PROBE_DEPTH: f64 = 0.0015;

/// One site's part of the picture.
struct SiteFrames {
    site: String,
    /// Tool geometry (from the scene, by tool name or kind) and the recorded track.
    tools: Vec<(Tool, Track)>,
}

/// Recordings of one session drawn with a scene.
pub struct RecordedSession {
    base: ViewFrame,
    /// Recorded frames of every scene surface, with its first vertex in the frame.
    surfaces: Vec<(usize, Vec<SurfaceShape>)>,
    sites: Vec<SiteFrames>,
    span: (f64, f64),
    label: String,
}

/// `state` as a tool input.
fn input_of(s: &ToolState) -> ToolInput {
    let [w, x, y, z] = s.orientation;
    ToolInput {
        pose: Isometry3::from_parts(
            Translation3::new(s.position[0], s.position[1], s.position[2]),
            UnitQuaternion::from_quaternion(Quaternion::new(w, x, y, z)),
        ),
        jaw: s.jaw,
    }
}

/// The tracks a recording holds of `site`'s own tools: a site's recording holds its own
/// tool and what it saw of the others (`remote`); a coordinator's holds every site's.
fn own_tracks(rec: &Recording, site: &str) -> Vec<Track> {
    rec.site_tracks(site)
        .into_iter()
        .filter(|t| !t.is_empty())
        .collect()
}

impl RecordedSession {
    /// The picture of `sites` (each from the recording that holds it best, see
    /// [`debrief::Session::recording_for`]) drawn with `scene`.
    pub fn new(scene: &LoadedScene, session: &debrief::Session, sites: &[String]) -> Result<Self> {
        // The surfaces drawn: the first site's recording's, else any recording's (a
        // coordinator's recording has none: the organ is then drawn at rest).
        let first = sites
            .first()
            .and_then(|s| session.recording_for(s))
            .filter(|r| !r.surfaces().is_empty())
            .or_else(|| session.recordings.iter().find(|r| !r.surfaces().is_empty()));
        let decls: Vec<SurfaceDecl> = first
            .map(|r| r.surfaces().into_iter().cloned().collect())
            .unwrap_or_default();
        let base = base_frame(scene, &decls);
        let mut surfaces = Vec::new();
        let mut out_sites = Vec::new();
        let mut span: Option<(f64, f64)> = None;
        let mut widen = |a: f64, b: f64| {
            span = Some(span.map_or((a, b), |(x, y)| (x.min(a), y.max(b))));
        };
        for (k, site) in sites.iter().enumerate() {
            let Some(rec) = session.recording_for(site) else {
                bail!(
                    "site {site:?} not found (recordings of: {})",
                    session.sites().join(", ")
                );
            };
            if !rec.header.scene.contains(&scene.hash) {
                tracing::warn!(
                    "recording {} was made with scene {:?}; drawing it with {} ({}; a session on another lattice needs its --cell here)",
                    rec.path
                        .as_ref()
                        .map_or("?".into(), |p| p.display().to_string()),
                    rec.header.scene,
                    scene.file,
                    scene.hash
                );
            }
            if k == 0 {
                surfaces = surfaces_of(rec, &decls);
                for (_, shapes) in &surfaces {
                    if let (Some(a), Some(b)) = (shapes.first(), shapes.last()) {
                        widen(a.time, b.time);
                    }
                }
            }
            let mut tools = Vec::new();
            for track in own_tracks(rec, site) {
                let Some(decl) = track.decl.as_ref() else {
                    continue;
                };
                let spec = scene
                    .scene
                    .tools
                    .iter()
                    .find(|s| s.name == decl.name)
                    .or_else(|| {
                        scene
                            .scene
                            .tools
                            .iter()
                            .find(|s| format!("{:?}", s.kind).eq_ignore_ascii_case(&decl.kind))
                    })
                    .or_else(|| {
                        // a coordinator's recording read alone: `#N`, the scene's tool N
                        decl.name
                            .strip_prefix('#')
                            .and_then(|n| n.parse::<usize>().ok())
                            .and_then(|n| scene.scene.tools.get(n))
                    });
                let Some(spec) = spec else {
                    tracing::warn!(
                        "tool {:?} of {site} is not in the scene; not drawn",
                        decl.name
                    );
                    continue;
                };
                widen(track.times[0], track.times[track.times.len() - 1]);
                tools.push((Tool::from_spec(spec), track));
            }
            out_sites.push(SiteFrames {
                site: site.clone(),
                tools,
            });
        }
        let Some(span) = span else {
            bail!("nothing to replay: no surface frames or tool samples of {sites:?}");
        };
        Ok(RecordedSession {
            base,
            surfaces,
            sites: out_sites,
            span,
            label: sites.join(" + "),
        })
    }
}

/// The picture at rest of the recorded surfaces (their triangles and rest shapes), with
/// the scene's tissue colours and camera; vessels are not recorded and not drawn.
fn base_frame(scene: &LoadedScene, decls: &[SurfaceDecl]) -> ViewFrame {
    let mut triangles = Vec::new();
    let mut positions: Vec<Vector3<f64>> = Vec::new();
    for d in decls {
        let base = positions.len() as u32;
        triangles.extend(d.triangles.iter().map(|t| t.map(|i| i + base)));
        positions.extend(d.rest.iter().map(|p| Vector3::from(p.map(f64::from))));
    }
    // Area-weighted vertex normals (triangles are outward-oriented).
    let mut normals = vec![Vector3::zeros(); positions.len()];
    for t in &triangles {
        let [a, b, c] = t.map(|i| i as usize);
        if a.max(b).max(c) >= positions.len() {
            continue;
        }
        let n = (positions[b] - positions[a]).cross(&(positions[c] - positions[a]));
        for i in [a, b, c] {
            normals[i] += n;
        }
    }
    let vertex_tissue = positions
        .iter()
        .zip(&normals)
        .map(|(p, n)| {
            tissue_at(
                scene,
                &(p - n.try_normalize(1e-30).unwrap_or_default() * TISSUE_PROBE_DEPTH),
            )
        })
        .collect();
    ViewFrame {
        topology: Arc::new(SurfaceTopology {
            triangles,
            vertex_tissue,
        }),
        positions,
        vessels: Vec::new(),
        clips: Vec::new(),
        lattice: None,
        tools: Vec::new(),
        guide: Vec::new(),
        forces: Vec::new(),
        hud: HudInfo::default(),
        port: port_of(scene),
    }
}

/// Frames of `rec`'s surfaces when it declares the drawn surfaces `decls` (same count,
/// names and vertex counts), with each one's first vertex in the frame.
fn surfaces_of(rec: &Recording, decls: &[SurfaceDecl]) -> Vec<(usize, Vec<SurfaceShape>)> {
    let own = rec.surfaces();
    let same = own.len() == decls.len()
        && own
            .iter()
            .zip(decls)
            .all(|(a, b)| a.name == b.name && a.rest.len() == b.rest.len());
    if !same {
        if !own.is_empty() {
            tracing::warn!("recorded surfaces differ from the drawn ones: surface not replayed");
        }
        return Vec::new();
    }
    let mut offset = 0;
    own.iter()
        .map(|d| {
            let o = offset;
            offset += d.rest.len();
            (o, rec.surface_shapes(d.id))
        })
        .collect()
}

/// Index of the latest of `times` at or before `t` (the first if `t` is before all).
fn at_or_before(times: impl Fn(usize) -> f64, len: usize, t: f64) -> Option<usize> {
    if len == 0 {
        return None;
    }
    let (mut lo, mut hi) = (0, len);
    while lo < hi {
        let mid = (lo + hi) / 2;
        if times(mid) <= t + 1e-9 {
            lo = mid + 1;
        } else {
            hi = mid;
        }
    }
    Some(lo.saturating_sub(1))
}

impl ReplaySource for RecordedSession {
    fn span(&self) -> (f64, f64) {
        self.span
    }

    fn frame_at(&mut self, t: f64) -> ViewFrame {
        let t = t.clamp(self.span.0, self.span.1);
        let mut frame = self.base.clone();
        for (offset, shapes) in &self.surfaces {
            if let Some(i) = at_or_before(|i| shapes[i].time, shapes.len(), t) {
                for (dst, p) in frame.positions[*offset..]
                    .iter_mut()
                    .zip(&shapes[i].vertices)
                {
                    *dst = Vector3::new(p[0], p[1], p[2]);
                }
            }
        }
        for (k, site) in self.sites.iter_mut().enumerate() {
            for (tool, track) in &mut site.tools {
                let Some(i) = at_or_before(|i| track.times[i], track.len(), t) else {
                    continue;
                };
                let s = &track.states[i];
                tool.set_input(&input_of(s), 0.0);
                let force = Vector3::from(s.contact_force) + Vector3::from(s.grasp_force);
                if force.norm() > 1e-6 {
                    frame.forces.push(ForceArrow {
                        origin: tool.tip(),
                        force,
                    });
                }
                let who = (k > 0).then(|| site.site.clone());
                frame
                    .tools
                    .push(viewer::frame::tool_view(tool, force, s.grasped > 0, who));
            }
        }
        frame.hud = HudInfo {
            site: format!("replay: {}", self.label),
            role: Role::Observer,
            sim_time: t,
            ..HudInfo::default()
        };
        frame
    }
}

#[cfg(test)]
mod tests {
    use super::at_or_before;

    #[test]
    fn latest_at_or_before() {
        let times = [1.0, 2.0, 3.0];
        let f = |i: usize| times[i];
        assert_eq!(at_or_before(f, 3, 0.5), Some(0));
        assert_eq!(at_or_before(f, 3, 2.0), Some(1));
        assert_eq!(at_or_before(f, 3, 2.5), Some(1));
        assert_eq!(at_or_before(f, 3, 9.0), Some(2));
        assert_eq!(at_or_before(f, 0, 1.0), None);
    }
}
