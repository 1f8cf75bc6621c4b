//! How commands name a scene: a path to a TOML file, or `builtin:NAME` for the scenes
//! compiled into the binary (`cholecystectomy-bodies`, the default, `cholecystectomy` and
//! `cantilever`).

use anyhow::{Result, anyhow};
use sim_core::sim_scene::{LoadedScene, Scene, builtin};

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
