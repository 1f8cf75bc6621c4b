//! How commands name a scene: a path to a TOML file, or `builtin:NAME` for the scenes
//! compiled into the binary (`cholecystectomy-bodies`, the default, `cholecystectomy` and
//! `cantilever`), optionally on a lattice of another cell size (`--cell`).

use anyhow::{Context, Result, anyhow};
use sim_core::sim_scene::{LoadedScene, Scene, builtin};

/// Help of every command's `--cell`.
pub const CELL_HELP: &str = "Lattice cell size (m) of every body, instead of the scene's: \
a finer or coarser organ (the default scene has 2 cm, 2,672 tets; 1.33 cm gives about 7,700 \
tets, 1 cm about 14,500, the gallbladder's surface one level finer than the rest as at 2 cm; \
1.5 cm is refused, since the gallbladder bed needs one empty cell between liver \
and gallbladder). The scene's hash changes with it, so every site of a session must give the \
same cell.";

/// Loads `arg`, or the built-in default scene when `None`.
pub fn load_scene(arg: Option<&str>) -> Result<LoadedScene> {
    match arg {
        None => Ok(builtin::default_scene()),
        Some(s) => match s.strip_prefix("builtin:") {
            Some(name) => builtin::by_name(name).ok_or_else(|| {
                anyhow!(
                    "unknown built-in scene {name:?} (known: {})",
                    builtin::NAMES.join(", ")
                )
            }),
            None => Ok(Scene::load(s)?),
        },
    }
}

/// [`load_scene`], then every body on a lattice of `cell` (m) when given
/// ([`LoadedScene::set_cell`]: validated, re-hashed).
pub fn load_scene_with_cell(arg: Option<&str>, cell: Option<f64>) -> Result<LoadedScene> {
    let mut scene = load_scene(arg)?;
    if let Some(cell) = cell {
        scene
            .set_cell(cell)
            .with_context(|| format!("--cell {cell}"))?;
    }
    Ok(scene)
}

/// The built-in scene whose hash is `hash`, on its own lattice or on one of `cell` (m):
/// how a finished session's reports, which carry the hash and the cell, find their scene.
pub fn builtin_by_hash(hash: &str, cell: Option<f64>) -> Option<LoadedScene> {
    builtin::NAMES.iter().find_map(|name| {
        let mut scene = builtin::by_name(name)?;
        if let Some(cell) = cell {
            scene.set_cell(cell).ok()?;
        }
        (scene.hash == hash).then_some(scene)
    })
}
