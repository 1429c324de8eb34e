//! Hostile `.h5` files read in isolation (issue 20, item 2): two motion files that crash
//! Debian's libhdf5 1.10.8 with SIGSEGV (made here by `tests/tools/hostile_h5.py`) fail with one
//! error line in every verb that reads `.h5`, and the daemon that finds them in its inboxes
//! keeps serving, with exactly one outcome per file.
//!
//! Needs the binary: `cargo build --release -p choreod` first.

use std::fs;
use std::path::{Path, PathBuf};
use std::process::{Output, Stdio};
use std::time::{Duration, Instant};

use choreod_tests::daemon::{Home, drop_file, wav_bytes};
use choreod_tests::{choreod, one_error_line, python_cmd, run, workspace_root};

const PATIENCE: Duration = Duration::from_secs(120);
const PKL: &str = "aistpp_gBR_sBM_cAll_d04_mBR0_ch01.pkl";
/// What the one line says when the reader child died.
const CRASHED: &str =
    "the HDF5 reader crashed (signal 11 SIGSEGV) — the file is corrupt or hostile";

fn asset(name: &str) -> PathBuf {
    workspace_root().join("daemon/assets/motion").join(name)
}

fn text(path: &Path) -> &str {
    path.to_str().expect("temporary paths are UTF-8")
}

/// `good.h5` (the AIST++ dance, written by choreod), `heap-flip.h5` and `short-chunk.h5`
/// (see the tool's docs) in `dir`.
fn make_files(dir: &Path) -> [PathBuf; 3] {
    let good = dir.join("good.h5");
    let out = run(&["convert", text(&asset(PKL)), "-o", text(&good)]);
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

/// Run a verb with a bound: `view` serves until stopped when it can read its file.
fn run_bounded(args: &[&str]) -> Output {
    let mut child = choreod()
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn choreod");
    let t0 = Instant::now();
    while child.try_wait().expect("wait").is_none() {
        if t0.elapsed() > Duration::from_secs(60) {
            let _ = child.kill();
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    child.wait_with_output().expect("output")
}

#[test]
fn every_verb_that_reads_h5_says_one_line_when_the_reader_crashes() {
    let dir = tempfile::tempdir().expect("temp dir");
    let [good, flip, short] = make_files(dir.path());
    let out_npy = dir.path().join("o.npy");
    let out_png = dir.path().join("o.png");
    let out_h5 = dir.path().join("o.h5");
    let pkl = asset(PKL);
    for hostile in [&flip, &short] {
        let h = text(hostile);
        let verbs: [Vec<&str>; 5] = [
            vec!["convert", h, "-o", text(&out_npy)],
            vec!["render", h, "-o", text(&out_png)],
            vec![
                "stylize",
                "--content",
                h,
                "--style",
                text(&pkl),
                "-o",
                text(&out_h5),
            ],
            vec!["eval", h],
            vec!["view", h, "--bind", "127.0.0.1:0"],
        ];
        for args in verbs {
            let out = run_bounded(&args);
            // Before: exit 139 (SIGSEGV) and no line at all.
            assert_eq!(out.status.code(), Some(1), "{args:?}: {out:?}");
            let line = one_error_line(&out);
            assert!(
                line.starts_with(&format!("choreod: error: {h}: ")),
                "{args:?}: {line}"
            );
            // The bit flip gets past any check before reading: only the child's death says it.
            if hostile == &flip {
                assert!(line.ends_with(CRASHED), "{args:?}: {line}");
            }
        }
    }
    // The same reader reads a good file whole: what choreod wrote comes back through the child.
    let out = run(&["convert", text(&good), "-o", text(&out_npy)]);
    assert!(out.status.success(), "{out:?}");
    let joints = choreo_datasets::read_npy(&out_npy).expect("npy");
    let m = choreo_datasets::read_motion_file(&good).expect("read in-process");
    assert_eq!(joints.shape(), m.joints.shape());
    assert_eq!(
        joints.iter().copied().collect::<Vec<f32>>(),
        m.joints.iter().copied().collect::<Vec<f32>>()
    );
}

#[test]
fn the_daemon_survives_hdf5_crashes_in_both_inboxes_and_gives_each_file_one_outcome() {
    let mut home =
        Home::new("[style]\nenabled = true\ninbox = \"style-in\"\nstyle = \"style.pkl\"\n");
    let style_in = home.path().join("style-in");
    fs::create_dir(&style_in).expect("mkdir style-in");
    fs::copy(asset(PKL), home.path().join("style.pkl")).expect("style reference");
    let made = tempfile::tempdir().expect("temp dir");
    let [good, flip, short] = make_files(made.path());
    let bytes = |p: &Path| fs::read(p).expect("read");
    let mut daemon = home.start();
    home.wait_healthy(&mut daemon);
    // The style inbox takes motion files; the song inbox gets the same bytes under audio names
    // (its decoder must refuse them, not libhdf5).
    for (name, file) in [
        ("heap-flip.h5", &flip),
        ("short-chunk.hdf5", &short),
        ("heap-flip-again.h5", &flip),
        ("good.h5", &good),
    ] {
        drop_file(&style_in, name, &bytes(file));
    }
    drop_file(&home.inbox(), "heap-flip.wav", &bytes(&flip));
    drop_file(&home.inbox(), "short-chunk.mp3", &bytes(&short));
    home.wait_for_outcomes(6, &[], PATIENCE, &mut daemon);
    // Still serving: healthy, and a song dropped now is danced.
    assert!(
        home.http_get("/healthz")
            .expect("healthz")
            .0
            .contains(" 200 ")
    );
    drop_file(&home.inbox(), "after.wav", &wav_bytes(2.0, 1));
    home.wait_for_outcomes(7, &[], PATIENCE, &mut daemon);
    assert!(daemon.try_status().is_none(), "{}", daemon.log_text());

    assert_eq!(home.names("out"), ["after.h5", "good.h5"]);
    let reports = home.reports();
    assert_eq!(reports.len(), 5, "{reports:?}");
    let report = |file: &str| {
        reports
            .iter()
            .find(|r| r["file"] == file)
            .unwrap_or_else(|| panic!("no report for {file}: {reports:?}"))
    };
    for file in ["heap-flip.h5", "heap-flip-again.h5"] {
        let r = report(file);
        assert_eq!(r["stage"], "crash", "{r}");
        assert!(
            r["reason"].as_str().expect("reason").contains(CRASHED),
            "{r}"
        );
    }
    let r = report("short-chunk.hdf5");
    assert!(r["stage"] == "crash" || r["stage"] == "stylize", "{r}");
    for file in ["heap-flip.wav", "short-chunk.mp3"] {
        assert_eq!(report(file)["stage"], "decode", "{}", report(file));
    }
    // Each input moved once: to done/ or failed/.
    assert_eq!(home.names("state/done").len(), 2);
    assert_eq!(home.names("state/failed").len(), 10);
    daemon.term();
    let status = daemon.wait_exit(PATIENCE).expect("exits after SIGTERM");
    assert!(status.success(), "{status}");
}

/// Whether an strace line is libhdf5 opening `file`: its `open` has no `O_CLOEXEC` (choreod's
/// own opens, Rust's `File::open`, always set it; see `NO_HDF5_LOCKS` in the harness).
fn hdf5_open_of(line: &str, file: &str) -> bool {
    line.contains(&format!("\"{file}\"")) && line.contains("openat(") && !line.contains("O_CLOEXEC")
}

#[test]
fn eval_reads_a_prep_shard_only_in_reader_children() {
    let dir = tempfile::tempdir().expect("temp dir");
    let shard = dir.path().join("shard.h5");
    let out = python_cmd()
        .arg(workspace_root().join("tests/tools/hostile_h5.py"))
        .args(["shard", text(&shard)])
        .output()
        .expect("python");
    assert!(out.status.success(), "{out:?}");
    let trace = dir.path().join("strace.txt");
    let out = std::process::Command::new("strace")
        .args(["-f", "-qq", "-e", "trace=openat", "-o", text(&trace)])
        .arg(choreod_tests::choreod_bin())
        .args(["eval", text(&shard)])
        .env("HDF5_USE_FILE_LOCKING", "FALSE")
        .output()
        .expect("strace (scripts/setup installs it)");
    assert!(out.status.success(), "{out:?}");
    // The shard's sequence was read and evaluated.
    let report = String::from_utf8_lossy(&out.stdout);
    assert!(
        report.contains("shard.h5:gBR_sBM_cAll_d04_mBR0_ch01: 120 frames at 60 fps"),
        "{report}"
    );
    // With -f every line starts with the pid; choreod's own is the first line's.
    let log = fs::read_to_string(&trace).expect("strace log");
    let main_pid = log
        .split_whitespace()
        .next()
        .expect("a traced call")
        .to_string();
    let hdf5_opens: Vec<&str> = log
        .lines()
        .filter(|l| hdf5_open_of(l, text(&shard)))
        .collect();
    // Format, sequence list, and the sequence: each in a child.
    assert!(hdf5_opens.len() >= 3, "{log}");
    assert!(
        hdf5_opens
            .iter()
            .all(|l| !l.starts_with(&format!("{main_pid} "))),
        "libhdf5 opened the shard in choreod itself: {hdf5_opens:?}"
    );
}
