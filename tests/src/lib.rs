//! Helpers shared by the end-to-end tests in `tests/tests/`: find the `choreod` binary, the
//! workspace and the shared fixtures, and run the binary as a user would.

pub mod browser;
pub mod daemon;

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

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
/// [`choreod`]), with choreo_datasets' skeleton tables in its environment (JSON lists:
/// `CHOREOD_SMPL24_PARENTS`, `CHOREOD_T2M22_PARENTS`), so that no script re-types them.
pub fn python_cmd() -> Command {
    use choreo_datasets::skeleton::{SMPL24_PARENTS, T2M22_PARENTS};
    let mut cmd = Command::new(python());
    cmd.env(NO_HDF5_LOCKS.0, NO_HDF5_LOCKS.1);
    let json = |parents: &[i32]| serde_json::to_string(parents).expect("a list of numbers");
    cmd.env("CHOREOD_SMPL24_PARENTS", json(&SMPL24_PARENTS));
    cmd.env("CHOREOD_T2M22_PARENTS", json(&T2M22_PARENTS));
    cmd
}

/// The project's Python (the venv made by scripts/setup), for h5py/numpy checks.
pub fn python() -> PathBuf {
    std::env::var_os("CHOREOD_PYTHON").map_or_else(
        || workspace_root().join(".venv").join("bin").join("python"),
        PathBuf::from,
    )
}

/// What the one error line ends with when the isolated HDF5 reader child died.
pub const CRASHED: &str =
    "the HDF5 reader crashed (signal 11 SIGSEGV) — the file is corrupt or hostile";

/// The bundled AIST++ dance, a file of [`motion_asset`].
pub const AISTPP_PKL: &str = "aistpp_gBR_sBM_cAll_d04_mBR0_ch01.pkl";

/// A motion file bundled with the daemon (`daemon/assets/motion/`).
pub fn motion_asset(name: &str) -> PathBuf {
    workspace_root().join("daemon/assets/motion").join(name)
}

/// A path as a command-line argument (test paths are UTF-8).
pub fn text(path: &Path) -> &str {
    path.to_str().expect("temporary paths are UTF-8")
}

/// `good.h5` (the AIST++ dance, written by choreod), `heap-flip.h5` and `short-chunk.h5`, two
/// files that crash Debian's libhdf5 1.10.8 with SIGSEGV (see `tests/tools/hostile_h5.py`), in
/// `dir`.
pub fn crashing_h5_files(dir: &Path) -> [PathBuf; 3] {
    let good = dir.join("good.h5");
    let out = run(&[
        "convert",
        text(&motion_asset(AISTPP_PKL)),
        "-o",
        text(&good),
    ]);
    assert!(out.status.success(), "{out:?}");
    let tool = workspace_root().join("tests/tools/hostile_h5.py");
    let flip = dir.join("heap-flip.h5");
    let short = dir.join("short-chunk.h5");
    for args in [
        vec!["heap-flip", text(&good), text(&flip)],
        vec!["short-chunk", text(&short)],
    ] {
        let out = python_cmd()
            .arg(&tool)
            .args(&args)
            .output()
            .expect("python");
        assert!(out.status.success(), "{args:?}: {out:?}");
    }
    [good, flip, short]
}

/// A path as a command-line argument, lossless for the UTF-8 paths tests make.
pub fn path_arg(p: &Path) -> String {
    p.display().to_string()
}

/// The shared AIST++ fixture (`.pkl`, 720 frames at 60 fps), as an argument.
pub fn aistpp() -> String {
    path_arg(&fixtures().join("motion/aistpp_gBR_sBM_cAll_d04_mBR0_ch01.pkl"))
}

/// The text of the shared CMU BVH fixture.
pub fn cmu_bvh() -> String {
    std::fs::read_to_string(fixtures().join("motion/cmu_01_01.bvh")).expect("CMU fixture")
}

/// A bundled model package (`models/packages/NAME`), as an argument.
pub fn package(name: &str) -> String {
    path_arg(&workspace_root().join("models/packages").join(name))
}

/// The AIST++ fixture as a motion file (720 frames at 60 fps) in `dir`.
pub fn motion_file(dir: &Path) -> PathBuf {
    let h5 = dir.join("ok.h5");
    let out = run(&["convert", &aistpp(), "-o", &path_arg(&h5)]);
    assert!(out.status.success(), "{}", stderr(&out));
    h5
}

/// Run choreod with at most 4 GiB of address space, so a build that tries to allocate what a
/// hostile file asks for fails there (exit 134) instead of driving the machine into swap.
pub fn run_capped(args: &[&str]) -> Output {
    Command::new("sh")
        .args(["-c", "ulimit -v 4194304 && exec \"$@\"", "sh"])
        .arg(choreod_bin())
        .args(args)
        .env_remove("RUST_LOG")
        .env(NO_HDF5_LOCKS.0, NO_HDF5_LOCKS.1)
        .output()
        .expect("spawn choreod")
}

/// A successful run's stdout.
pub fn ok(args: &[&str]) -> String {
    let out = run(args);
    assert!(
        out.status.success(),
        "choreod {args:?} failed: {}",
        stderr(&out)
    );
    stdout(&out)
}

/// A failed run: exit `code` and one error line containing every one of `want`.
pub fn fails_with(out: &Output, code: i32, want: &[&str]) -> String {
    let line = one_error_line(out);
    assert_eq!(out.status.code(), Some(code), "{line}");
    for w in want {
        assert!(line.contains(w), "{w:?} not in: {line}");
    }
    line
}

/// A usage error printed by the parser (exit 2) naming `flag` and the accepted range.
pub fn usage_error(args: &[&str], flag: &str, range: &str) {
    let out = run(args);
    let err = stderr(&out);
    assert_eq!(out.status.code(), Some(2), "choreod {args:?}: {err}");
    assert!(
        err.contains(flag) && err.contains(&format!("must be in {range}")),
        "choreod {args:?}: {err}"
    );
}

/// Run the Python helper `tests/py/NAME.py` (numpy, h5py) with `args` as sys.argv[1:] and
/// return its stdout. Every helper is called this way and has one contract: its asserts are its
/// checks (a failed one exits non-zero and its traceback fails the test); a check prints a last
/// line starting with `ok` (with what it measured, if anything), a measurement prints one JSON
/// value ([`py_json`]).
fn run_py(name: &str, args: &[&str]) -> String {
    let out = python_cmd()
        .arg(py_script(name))
        .args(args)
        .output()
        .expect("run python");
    let text = stdout(&out);
    assert!(
        out.status.success(),
        "python {name} failed: {text}{}",
        stderr(&out)
    );
    text
}

/// The helper `tests/py/NAME.py`, for helpers that run beside choreod (receivers) rather than
/// once ([`py`], [`py_json`]).
pub fn py_script(name: &str) -> PathBuf {
    workspace_root().join("tests/py").join(format!("{name}.py"))
}

/// Run the check `tests/py/NAME.py` (see [`run_py`]) and return its `ok` line.
pub fn py(name: &str, args: &[&str]) -> String {
    let text = run_py(name, args);
    let last = text.trim().lines().last().unwrap_or("").to_string();
    assert!(
        last.starts_with("ok"),
        "python {name} did not say ok: {text}"
    );
    eprintln!("{name}: {last}");
    last
}

/// Run the measurement `tests/py/NAME.py` (see [`run_py`]) and return the JSON value it printed.
pub fn py_json(name: &str, args: &[&str]) -> serde_json::Value {
    let text = run_py(name, args);
    serde_json::from_str(text.trim()).unwrap_or_else(|e| panic!("python {name}: {e}: {text}"))
}

/// `models/packages/exemplar` copied to `dir/name` with `edit` applied to its manifest.
pub fn edited_package(dir: &Path, name: &str, edit: impl Fn(String) -> String) -> String {
    let to = dir.join(name);
    std::fs::create_dir(&to).expect("package folder");
    let from = workspace_root().join("models/packages/exemplar");
    for entry in std::fs::read_dir(&from).expect("bundled exemplar") {
        let entry = entry.expect("bundled exemplar entry");
        std::fs::copy(entry.path(), to.join(entry.file_name())).expect("copy the package");
    }
    let manifest = to.join("choreod-model.toml");
    let text = std::fs::read_to_string(&manifest).expect("manifest");
    std::fs::write(&manifest, edit(text)).expect("write the manifest");
    path_arg(&to)
}

/// `models/packages/exemplar` copied to `dir/endless` with a denoiser whose ONNX `Loop` runs
/// 2^62 times (`tests/tools/hostile_onnx.py`): a valid model that never finishes.
pub fn endless_package(dir: &Path) -> String {
    let pkg = edited_package(dir, "endless", |t| t);
    let out = python_cmd()
        .arg(workspace_root().join("tests/tools/hostile_onnx.py"))
        .args(["endless-loop", &pkg])
        .output()
        .expect("run hostile_onnx.py");
    assert!(out.status.success(), "{}", stderr(&out));
    pkg
}

/// Run choreod with `args`; a run still going after `bound` is killed and fails the test
/// (choreod before the time limits hung here for ever).
pub fn run_within(bound: Duration, args: &[&str]) -> Output {
    let mut child = choreod()
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn choreod");
    let started = Instant::now();
    while child.try_wait().expect("wait for choreod").is_none() {
        if started.elapsed() > bound {
            child.kill().expect("kill choreod");
            let out = child.wait_with_output().expect("reap choreod");
            panic!(
                "choreod {args:?} still running after {bound:?}: {}{}",
                stdout(&out),
                stderr(&out)
            );
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    child.wait_with_output().expect("choreod output")
}

/// Speech and white noise, 12 s each, made in `dir` with espeak-ng and sox (both installed by
/// scripts/setup): inputs that are not music, as a user drops them by mistake or to see.
pub fn not_music(dir: &Path) -> [PathBuf; 2] {
    let speech = dir.join("speech.wav");
    let status = Command::new("espeak-ng")
        .args(["-v", "en-us", "-s", "160", "-w"])
        .arg(&speech)
        .arg(
            "It was the best of times, it was the worst of times, it was the age of wisdom, it \
             was the age of foolishness, it was the epoch of belief, it was the epoch of \
             incredulity, it was the season of light, it was the season of darkness.",
        )
        .status()
        .expect("espeak-ng (installed by scripts/setup)");
    assert!(status.success(), "espeak-ng failed");
    // Repeatable (`-R`: sox seeds its generator with a fixed number): white noise has no steady
    // beat, but a fresh draw per run scored 0.12-0.22 on the periodicity the beat check bounds
    // at 0.27 (13 draws), so about one draw in a hundred crossed it and failed a CI run.
    let noise = dir.join("noise.wav");
    let status = Command::new("sox")
        .args(["-R", "-n", "-r", "22050", "-c", "1"])
        .arg(&noise)
        .args(["synth", "12", "whitenoise", "vol", "0.5"])
        .status()
        .expect("sox (installed by scripts/setup)");
    assert!(status.success(), "sox failed");
    [speech, noise]
}
