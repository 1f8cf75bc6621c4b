//! Parsing, loading and hashing of scenes, and what a loaded scene offers.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use nalgebra::Vector3;
use sha2::{Digest, Sha256};

use super::{Aabb, Body, BodyShape, FileReader, LoadedScene, NodeSelection, Scene, SceneError};
use crate::mesh::{MeshError, MeshFormat, TriMesh};
use crate::script::ToolScript;

/// SHA-256 (lower-case hex) identifying a scene and everything it references.
///
/// Hashed, in order: the ASCII tag `cosurg-scene-v1`, then for the scene text and each
/// referenced file (in the order they are referenced: bodies in order — the body mesh
/// then its inclusion meshes — then tool scripts in tool order; a file referenced twice
/// counts once): the file's name as written in the scene (`""` for the scene text) and its
/// bytes, each preceded by its length as a little-endian u64. Line endings are not
/// normalised, so the hash identifies the exact bytes.
pub fn scene_hash<'a>(
    scene_text: &[u8],
    files: impl IntoIterator<Item = (&'a str, &'a [u8])>,
) -> String {
    let mut h = Sha256::new();
    h.update(b"cosurg-scene-v1");
    let mut put = |name: &str, bytes: &[u8]| {
        h.update((name.len() as u64).to_le_bytes());
        h.update(name.as_bytes());
        h.update((bytes.len() as u64).to_le_bytes());
        h.update(bytes);
    };
    put("", scene_text);
    for (name, bytes) in files {
        put(name, bytes);
    }
    hex::encode(h.finalize())
}

/// Deserialises TOML, reporting errors as (key path, "message (line L, column C)").
pub(crate) fn parse_toml<T: serde::de::DeserializeOwned>(
    text: &str,
) -> Result<T, (Option<String>, String)> {
    let locate = |e: &toml::de::Error| -> String {
        match e.span() {
            Some(span) => {
                let before = &text[..span.start.min(text.len())];
                let line = before.matches('\n').count() + 1;
                let col = before.len() - before.rfind('\n').map_or(0, |i| i + 1) + 1;
                format!("{} (line {line}, column {col})", e.message().trim_end())
            }
            None => e.message().trim_end().to_string(),
        }
    };
    let de = toml::Deserializer::parse(text).map_err(|e| (None, locate(&e)))?;
    serde_path_to_error::deserialize(de).map_err(|e| {
        let path = e.path().to_string();
        let inner = e.into_inner();
        let msg = inner.message();
        let mut key = if path == "." { String::new() } else { path };
        // the path ends at the table that lacks a required key: name the key
        if let Some(rest) = msg.strip_prefix("missing field `")
            && let Some(end) = rest.find('`')
        {
            if !key.is_empty() {
                key.push('.');
            }
            key.push_str(&rest[..end]);
        }
        ((!key.is_empty()).then_some(key), locate(&inner))
    })
}

impl Scene {
    /// Parses TOML text without validating (use [`Scene::validate`] next).
    pub fn parse(text: &str, file: &str) -> Result<Scene, SceneError> {
        parse_toml(text).map_err(|(key, message)| SceneError::Parse {
            file: file.to_string(),
            key,
            message,
        })
    }

    /// Serialises the scene back to TOML (a parse of the output equals `self`).
    pub fn to_toml(&self) -> String {
        toml::to_string(self).expect("scene serialises")
    }

    /// Every referenced file as `(key, path as written)`, in hashing order.
    pub fn referenced_files(&self) -> Vec<(String, PathBuf)> {
        let mut out: Vec<(String, PathBuf)> = Vec::new();
        let mut push = |key: String, p: &PathBuf| {
            if !out.iter().any(|(_, q)| q == p) {
                out.push((key, p.clone()));
            }
        };
        for (i, b) in self.bodies.iter().enumerate() {
            if let Some(m) = &b.mesh {
                push(format!("body[{i}].mesh"), m);
            }
            for (j, inc) in b.inclusions.iter().enumerate() {
                if let Some(m) = &inc.mesh {
                    push(format!("body[{i}].inclusion[{j}].mesh"), m);
                }
            }
        }
        for (i, t) in self.tools.iter().enumerate() {
            if let Some(s) = &t.script {
                push(format!("tool[{i}].script"), s);
            }
        }
        out
    }

    /// Reads, parses and validates a scene file and every file it references (relative
    /// paths are resolved against the scene file's directory).
    pub fn load(path: impl AsRef<Path>) -> Result<LoadedScene, SceneError> {
        let path = path.as_ref();
        let label = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|source| SceneError::Io {
            file: label.clone(),
            source,
        })?;
        let base = path.parent().unwrap_or(Path::new("")).to_path_buf();
        Self::from_str(&text, &base, &label)
    }

    /// Like [`Scene::load`] for scene text already in memory; referenced files are read
    /// relative to `base_dir`; `file_label` names the scene in errors.
    #[allow(clippy::should_implement_trait)]
    pub fn from_str(
        text: &str,
        base_dir: &Path,
        file_label: &str,
    ) -> Result<LoadedScene, SceneError> {
        let mut loaded = Self::from_parts(text, file_label, &mut |rel: &Path| {
            let full = if rel.is_absolute() {
                rel.to_path_buf()
            } else {
                base_dir.join(rel)
            };
            std::fs::read(&full).map_err(|e| (full, e))
        })?;
        loaded.base_dir = Some(base_dir.to_path_buf());
        Ok(loaded)
    }

    /// Like [`Scene::from_str`], with referenced files supplied by `read` (given the path
    /// as written; returns the bytes, or the resolved path and the error).
    pub fn from_parts(
        text: &str,
        file_label: &str,
        read: &mut FileReader<'_>,
    ) -> Result<LoadedScene, SceneError> {
        let file = file_label;
        let scene = Scene::parse(text, file)?;
        scene.validate(file)?;
        let mut meshes = BTreeMap::new();
        let mut scripts = BTreeMap::new();
        let mut blobs: Vec<(String, Vec<u8>)> = Vec::new();
        for (key, rel) in scene.referenced_files() {
            let is_script = key.ends_with(".script");
            if !is_script && MeshFormat::from_path(&rel).is_none() {
                return Err(SceneError::Mesh {
                    file: file.to_string(),
                    key,
                    source: MeshError::UnsupportedFormat { path: rel },
                });
            }
            let bytes = read(&rel).map_err(|(path, source)| SceneError::MissingFile {
                file: file.to_string(),
                key: key.clone(),
                path,
                source,
            })?;
            if is_script {
                let label = rel.display().to_string();
                let script = ToolScript::parse(
                    std::str::from_utf8(&bytes).map_err(|_| {
                        SceneError::invalid(file, &key, format!("{label}: not UTF-8 text"))
                    })?,
                    &label,
                )
                .map_err(|e| SceneError::invalid(file, &key, e.to_string()))?;
                for (i, t) in scene.tools.iter().enumerate() {
                    if t.script.as_ref() == Some(&rel) {
                        let mut own = script.clone();
                        if !own.tracks.contains_key(&t.name) {
                            // a single-track script drives whichever tool references it
                            if own.tracks.len() != 1 {
                                return Err(SceneError::invalid(
                                    file,
                                    format!("tool[{i}].script"),
                                    format!(
                                        "{label} has no poses for tool \"{}\" (tools: {:?})",
                                        t.name,
                                        script.tools().collect::<Vec<_>>()
                                    ),
                                ));
                            }
                            let track = own.tracks.pop_first().map(|(_, k)| k).unwrap_or_default();
                            own.tracks.insert(t.name.clone(), track);
                        }
                        scripts.insert(t.name.clone(), own);
                    }
                }
            } else {
                let mesh_err = |source| SceneError::Mesh {
                    file: file.to_string(),
                    key: key.clone(),
                    source,
                };
                let format = MeshFormat::from_path(&rel)
                    .ok_or_else(|| mesh_err(MeshError::UnsupportedFormat { path: rel.clone() }))?;
                let mesh = TriMesh::from_bytes(&bytes, format, &rel).map_err(mesh_err)?;
                if !mesh.is_closed() {
                    return Err(mesh_err(MeshError::Invalid {
                        path: rel.clone(),
                        message: format!(
                            "mesh is not closed: {} edges are not shared by exactly two triangles",
                            mesh.non_manifold_or_boundary_edges()
                        ),
                    }));
                }
                if !mesh.is_consistently_oriented() {
                    return Err(mesh_err(MeshError::Invalid {
                        path: rel.clone(),
                        message: "mesh triangles are not consistently oriented".into(),
                    }));
                }
                if mesh.signed_volume() <= 0.0 {
                    return Err(mesh_err(MeshError::Invalid {
                        path: rel.clone(),
                        message: "mesh is oriented inward (negative volume); flip its triangles"
                            .into(),
                    }));
                }
                meshes.insert(rel.clone(), mesh);
            }
            blobs.push((rel.to_string_lossy().into_owned(), bytes));
        }
        let hash = scene_hash(
            text.as_bytes(),
            blobs.iter().map(|(n, b)| (n.as_str(), b.as_slice())),
        );
        tracing::info!(scene = file, %hash, bodies = scene.bodies.len(), "scene loaded");
        Ok(LoadedScene {
            scene,
            meshes,
            scripts,
            file: file.to_string(),
            base_dir: None,
            hash,
        })
    }
}

impl LoadedScene {
    /// Changes the scene in memory (e.g. a benchmark overriding `young` or `cell`),
    /// validates it again and updates [`hash`](Self::hash) so that results still name
    /// exactly what ran: the new hash is [`scene_hash`] of the modified scene's canonical
    /// TOML ([`Scene::to_toml`]) with one extra entry named `base` holding the previous
    /// hash (hex). Referenced files cannot be swapped: every mesh and script the modified
    /// scene names must already be loaded. On error the scene is left unchanged.
    pub fn modify(&mut self, f: impl FnOnce(&mut Scene)) -> Result<(), SceneError> {
        let mut scene = self.scene.clone();
        f(&mut scene);
        scene.validate(&self.file)?;
        for (key, rel) in scene.referenced_files() {
            let loaded = if key.ends_with(".script") {
                self.scene
                    .tools
                    .iter()
                    .any(|t| t.script.as_ref() == Some(&rel))
            } else {
                self.meshes.contains_key(&rel)
            };
            if !loaded {
                return Err(SceneError::invalid(
                    &self.file,
                    key,
                    format!(
                        "{} is not loaded; a modified scene cannot add files",
                        rel.display()
                    ),
                ));
            }
        }
        let hash = scene_hash(scene.to_toml().as_bytes(), [("base", self.hash.as_bytes())]);
        tracing::info!(scene = %self.file, old = %self.hash, new = %hash, "scene modified");
        self.scene = scene;
        self.hash = hash;
        Ok(())
    }

    /// Every body on a lattice of `cell` (m) instead of its own, through
    /// [`LoadedScene::modify`] (validated, re-hashed).
    pub fn set_cell(&mut self, cell: f64) -> Result<(), SceneError> {
        self.modify(|s| s.bodies.iter_mut().for_each(|b| b.cell = cell))
    }

    /// [`Scene::validate_selection`] with this scene's file label.
    pub fn validate_selection(&self, nodes: &[Vector3<f64>]) -> Result<NodeSelection, SceneError> {
        self.scene.validate_selection(&self.file, nodes)
    }

    /// The loaded mesh of a path as written in the scene.
    pub fn mesh(&self, rel: &Path) -> Option<&TriMesh> {
        self.meshes.get(rel)
    }

    /// The loaded mesh of a body with `mesh = ...`.
    pub fn body_mesh(&self, body: &Body) -> Option<&TriMesh> {
        body.mesh.as_deref().and_then(|m| self.meshes.get(m))
    }

    /// Bounding box of body `i` (its box, or its mesh's bounding box).
    pub fn body_bounds(&self, i: usize) -> Option<Aabb> {
        let b = self.scene.bodies.get(i)?;
        match b.shape() {
            BodyShape::Box(bx) => Some(*bx),
            BodyShape::Mesh(m) => self.meshes.get(m)?.bounding_box(),
        }
    }
}
