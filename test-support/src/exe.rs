//! Executables of other packages. Cargo defines `CARGO_BIN_EXE_<name>` only for the binaries
//! of the package under test; a test of the `cosurg` binary that also spawns `cosurg-server`
//! (package `cosurg-server`) finds it next to `cosurg` in the same target directory.
//! `cargo test --workspace` builds every package's binaries before running any test;
//! `cargo test -p cosurg-cli` alone does not build `cosurg-server`, hence the message below.

use std::path::{Path, PathBuf};

/// The executable `name` in the directory of `anchor` (an executable of the package under
/// test, e.g. `env!("CARGO_BIN_EXE_cosurg")`).
///
/// # Panics
/// When it is not there, with the command that builds it: a test that needs it cannot run.
pub fn sibling_exe(anchor: &str, name: &str) -> PathBuf {
    let dir = Path::new(anchor)
        .parent()
        .unwrap_or_else(|| panic!("executable path {anchor} has no parent directory"));
    let path = dir.join(format!("{name}{}", std::env::consts::EXE_SUFFIX));
    assert!(
        path.is_file(),
        "`{name}` is not built: looked for {}. It belongs to another package; build it with \
         `cargo build --workspace --bin {name}` (same profile as this test), or run `cargo test --workspace`, \
         which builds every package's binaries first.",
        path.display()
    );
    path
}

#[cfg(test)]
mod tests {
    use super::sibling_exe;

    #[test]
    fn finds_an_executable_beside_the_anchor() {
        let dir = tempfile::tempdir().unwrap();
        let anchor = dir.path().join("anchor");
        let name = "sibling";
        let path = dir
            .path()
            .join(format!("{name}{}", std::env::consts::EXE_SUFFIX));
        std::fs::write(&path, b"").unwrap();
        assert_eq!(sibling_exe(anchor.to_str().unwrap(), name), path);
    }

    #[test]
    fn a_missing_executable_names_the_command_that_builds_it() {
        let dir = tempfile::tempdir().unwrap();
        let anchor = dir.path().join("anchor");
        let panic = std::panic::catch_unwind(|| sibling_exe(anchor.to_str().unwrap(), "absent"))
            .expect_err("must panic when the executable is missing");
        let text = panic.downcast_ref::<String>().expect("formatted message");
        assert!(text.contains("`absent` is not built"), "{text}");
        assert!(
            text.contains("cargo build --workspace --bin absent"),
            "{text}"
        );
    }
}
