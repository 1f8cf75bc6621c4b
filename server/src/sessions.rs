//! The sessions a coordinator hosts: the sessions file (`cosurg-server --sessions FILE.toml`)
//! and their persistence in the state directory, so that a restart resumes every session.
//!
//! ```toml
//! # one [[session]] table per session
//! [[session]]
//! name = "lap-chole"            # what sites give with --session
//! token = "s3cret"              # the instructor's secret of this session
//! scene_hash = "9f2c…"          # optional: hex SHA-256 of the required scene
//! max_sites = 8                 # optional: default 16
//!
//! [[session]]
//! name = "appendectomy"
//! token = "other-secret"
//! ```
//!
//! The state directory's `sessions.toml` has the same format (mode 0600: it holds the
//! instructor tokens). Sessions from a `--sessions` file and sessions created at run time
//! (`AdminAction::CreateSession`, authorised by the operator's `--admin-token`) are written
//! there; on start the coordinator resumes them, with the sessions given on its command line
//! replacing persisted ones of the same name. Invitations are per session: they name their
//! session, which the coordinator checks (the invitation key is the state directory's).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

/// File name of the persisted sessions inside the state directory.
pub const SESSIONS_FILE: &str = "sessions.toml";

/// Default maximum number of sites of a session.
pub const DEFAULT_MAX_SITES: u16 = 16;

/// Longest session name (bytes).
pub const MAX_SESSION_NAME: usize = 64;

/// One hosted session.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SessionSpec {
    pub name: String,
    /// The instructor's secret.
    pub token: String,
    /// Required scene (hex SHA-256); absent: the first site to join fixes it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scene_hash: Option<String>,
    #[serde(default = "default_max_sites")]
    pub max_sites: u16,
}

fn default_max_sites() -> u16 {
    DEFAULT_MAX_SITES
}

/// The content of a sessions file.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SessionsFile {
    #[serde(default, rename = "session")]
    pub sessions: Vec<SessionSpec>,
}

/// A sessions file that cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum SessionsError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: {detail}")]
    Parse { path: PathBuf, detail: String },
    #[error("{path}: session {name:?}: {detail}")]
    Invalid {
        path: PathBuf,
        name: String,
        detail: String,
    },
}

/// Why a session name or spec is not acceptable (also the text of a refusal).
pub fn check_spec(spec: &SessionSpec) -> Result<(), String> {
    let n = &spec.name;
    if n.trim().is_empty() || n.len() > MAX_SESSION_NAME || n.chars().any(char::is_control) {
        return Err(format!(
            "session name must be 1..={MAX_SESSION_NAME} bytes without control characters"
        ));
    }
    if spec.token.is_empty() {
        return Err("the instructor token must not be empty".into());
    }
    if let Some(h) = &spec.scene_hash
        && (h.is_empty() || !h.chars().all(|c| c.is_ascii_hexdigit()))
    {
        return Err(format!("scene_hash {h:?} is not hex"));
    }
    if spec.max_sites == 0 {
        return Err("max_sites must be at least 1".into());
    }
    Ok(())
}

impl SessionsFile {
    /// Parse and check the sessions file text (`path` names it in errors). Names must be
    /// unique.
    pub fn parse(text: &str, path: &Path) -> Result<Self, SessionsError> {
        let file: SessionsFile = toml::from_str(text).map_err(|e| SessionsError::Parse {
            path: path.to_path_buf(),
            detail: e.to_string(),
        })?;
        let mut seen = BTreeMap::new();
        for s in &file.sessions {
            let invalid = |detail: String| SessionsError::Invalid {
                path: path.to_path_buf(),
                name: s.name.clone(),
                detail,
            };
            check_spec(s).map_err(invalid)?;
            if seen.insert(s.name.clone(), ()).is_some() {
                return Err(invalid("defined twice".into()));
            }
        }
        Ok(file)
    }

    /// Read a sessions file; a missing file is an error.
    pub fn load(path: &Path) -> Result<Self, SessionsError> {
        let text = std::fs::read_to_string(path).map_err(|source| SessionsError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Self::parse(&text, path)
    }

    /// The sessions persisted in state directory `dir` (none if it has no sessions file).
    pub fn load_persisted(dir: &Path) -> Result<Self, SessionsError> {
        let path = dir.join(SESSIONS_FILE);
        if !path.exists() {
            return Ok(Self::default());
        }
        Self::load(&path)
    }

    /// Add or replace (by name) sessions.
    pub fn upsert(&mut self, specs: impl IntoIterator<Item = SessionSpec>) {
        for s in specs {
            match self.sessions.iter_mut().find(|x| x.name == s.name) {
                Some(x) => *x = s,
                None => self.sessions.push(s),
            }
        }
    }

    /// Write to state directory `dir` (mode 0600, it holds the instructor tokens).
    pub fn save_persisted(&self, dir: &Path) -> Result<(), SessionsError> {
        let path = dir.join(SESSIONS_FILE);
        let io = |source| SessionsError::Io {
            path: path.clone(),
            source,
        };
        std::fs::create_dir_all(dir).map_err(io)?;
        let text = format!(
            "# Sessions this coordinator hosts (resumed on restart). Holds instructor tokens.\n{}",
            toml::to_string(self).map_err(|e| SessionsError::Parse {
                path: path.clone(),
                detail: e.to_string(),
            })?
        );
        crate::tls::write_private_file(&path, text.as_bytes()).map_err(io)
    }

    /// Add or replace `specs` in the state directory's sessions file.
    pub fn persist(
        dir: &Path,
        specs: impl IntoIterator<Item = SessionSpec>,
    ) -> Result<(), SessionsError> {
        let mut file = Self::load_persisted(dir)?;
        file.upsert(specs);
        file.save_persisted(dir)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_checks_and_round_trips_through_the_state_directory() {
        let p = Path::new("sessions.toml");
        let f = SessionsFile::parse(
            "[[session]]\nname = \"a\"\ntoken = \"ta\"\nscene_hash = \"AB12\"\n\n[[session]]\nname = \"b\"\ntoken = \"tb\"\nmax_sites = 4\n",
            p,
        )
        .unwrap();
        assert_eq!(f.sessions.len(), 2);
        assert_eq!(f.sessions[0].max_sites, DEFAULT_MAX_SITES);
        assert_eq!(f.sessions[1].max_sites, 4);
        assert_eq!(f.sessions[0].scene_hash.as_deref(), Some("AB12"));

        let e = SessionsFile::parse(
            "[[session]]\nname = \"a\"\ntoken = \"x\"\n[[session]]\nname = \"a\"\ntoken = \"y\"\n",
            p,
        )
        .unwrap_err();
        assert!(e.to_string().contains("defined twice"), "{e}");
        let e = SessionsFile::parse("[[session]]\nname = \"a\"\ntoken = \"\"\n", p).unwrap_err();
        assert!(e.to_string().contains("token must not be empty"), "{e}");
        let e = SessionsFile::parse("[[session]]\nname = \"a\"\ntokn = \"x\"\n", p).unwrap_err();
        assert!(e.to_string().contains("sessions.toml"), "{e}");
        let e = SessionsFile::parse(
            "[[session]]\nname = \"a\"\ntoken = \"x\"\nscene_hash = \"zz\"\n",
            p,
        )
        .unwrap_err();
        assert!(e.to_string().contains("not hex"), "{e}");

        let dir = tempfile::tempdir().unwrap();
        assert!(
            SessionsFile::load_persisted(dir.path())
                .unwrap()
                .sessions
                .is_empty()
        );
        SessionsFile::persist(dir.path(), f.sessions.clone()).unwrap();
        let mut changed = f.sessions[1].clone();
        changed.token = "tb2".into();
        SessionsFile::persist(dir.path(), [changed.clone()]).unwrap();
        let back = SessionsFile::load_persisted(dir.path()).unwrap();
        assert_eq!(back.sessions, vec![f.sessions[0].clone(), changed]);
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let mode = std::fs::metadata(dir.path().join(SESSIONS_FILE))
                .unwrap()
                .permissions()
                .mode();
            assert_eq!(mode & 0o777, 0o600);
        }
    }
}
