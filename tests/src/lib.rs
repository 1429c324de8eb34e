//! Helpers shared by the end-to-end tests in `tests/tests/`: find the `choreod` binary, the
//! workspace and the shared fixtures, and run the binary as a user would.

pub mod browser;
pub mod daemon;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// The workspace root (the directory holding the top-level `Cargo.toml`).
pub fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("tests/ sits inside the workspace")
        .to_path_buf()
}

/// `../shared/fixtures` beside the checkout (CI clones with `shared/` next to it).
pub fn fixtures() -> PathBuf {
    let dir = workspace_root().join("..").join("shared").join("fixtures");
    assert!(
        dir.is_dir(),
        "shared fixtures not found at {}",
        dir.display()
    );
    dir
}

/// The `choreod` binary under test: `$CHOREOD_BIN` when set (e.g. an older build, to show a
/// test failed before a fix), else the release build when present (scripts/check builds it),
/// else the debug build.
pub fn choreod_bin() -> PathBuf {
    if let Some(bin) = std::env::var_os("CHOREOD_BIN") {
        let bin = PathBuf::from(bin);
        assert!(bin.is_file(), "CHOREOD_BIN={} is not a file", bin.display());
        return bin;
    }
    let target = std::env::var_os("CARGO_TARGET_DIR")
        .map_or_else(|| workspace_root().join("target"), PathBuf::from);
    let release = target.join("release").join("choreod");
    let debug = target.join("debug").join("choreod");
    let bin = if release.exists() { release } else { debug };
    assert!(
        bin.exists(),
        "choreod binary not built: run `cargo build --release -p choreod`"
    );
    bin
}

/// Children of the test process never take HDF5 file locks. Tests write HDF5 files in-process
/// on several threads at once, and HDF5 opens files without close-on-exec: a child spawned by
/// another thread while a file is open inherits the descriptor and its flock, and holds it for
/// its whole life, so a later reader of that file fails with "unable to lock file" (seen in
/// CI). choreod's own children (the HDF5 reader) are short-lived and open no file before they
/// read theirs, so this is a property of the harness.
const NO_HDF5_LOCKS: (&str, &str) = ("HDF5_USE_FILE_LOCKING", "FALSE");

/// A `choreod` command with a clean, predictable environment.
pub fn choreod() -> Command {
    let mut cmd = Command::new(choreod_bin());
    cmd.env_remove("RUST_LOG");
    cmd.env(NO_HDF5_LOCKS.0, NO_HDF5_LOCKS.1);
    cmd
}

/// Run `choreod` with `args` and return its output.
pub fn run(args: &[&str]) -> Output {
    choreod().args(args).output().expect("spawn choreod")
}

/// stdout as text.
pub fn stdout(out: &Output) -> String {
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// stderr as text.
pub fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// Assert a failed run printed exactly one error line (no panic, no backtrace) and return it.
pub fn one_error_line(out: &Output) -> String {
    assert!(
        !out.status.success(),
        "expected failure, got success: {}",
        stdout(out)
    );
    let err = stderr(out);
    let lines: Vec<&str> = err.lines().filter(|l| !l.trim().is_empty()).collect();
    assert_eq!(lines.len(), 1, "expected one error line, got:\n{err}");
    assert!(
        lines[0].starts_with("choreod: error: "),
        "not an error line: {err}"
    );
    assert!(
        !err.contains("panicked") && !err.contains("RUST_BACKTRACE"),
        "{err}"
    );
    lines[0].to_string()
}

/// A command running the project's Python (see [`python`]), without HDF5 file locks (see
/// [`choreod`]).
pub fn python_cmd() -> Command {
    let mut cmd = Command::new(python());
    cmd.env(NO_HDF5_LOCKS.0, NO_HDF5_LOCKS.1);
    cmd
}

/// The project's Python (the venv made by scripts/setup), for h5py/numpy checks.
pub fn python() -> PathBuf {
    std::env::var_os("CHOREOD_PYTHON").map_or_else(
        || workspace_root().join(".venv").join("bin").join("python"),
        PathBuf::from,
    )
}
