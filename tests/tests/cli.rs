//! The command line as a user meets it: --version, --help, check-config, exit codes.

use choreod_tests::{choreod, one_error_line, run, stdout, workspace_root};

#[test]
fn version_names_the_onnx_runtime_it_loads() {
    let out = run(&["--version"]);
    assert!(out.status.success(), "{}", choreod_tests::stderr(&out));
    let text = stdout(&out);
    assert!(
        text.starts_with(&format!("choreod {}", env!("CARGO_PKG_VERSION"))),
        "{text}"
    );
    // scripts/setup pins onnxruntime 1.31.1; the version comes from the library itself.
    let ort_line = text.lines().nth(1).expect("second line names onnxruntime");
    assert!(ort_line.starts_with("onnxruntime 1.31."), "{ort_line}");
    assert!(ort_line.contains("libonnxruntime.so"), "{ort_line}");
}

#[test]
fn a_missing_onnx_runtime_is_one_actionable_line_and_exit_4() {
    let out = choreod()
        .arg("--version")
        .env("ORT_DYLIB_PATH", "/nonexistent")
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(4));
    let line = one_error_line(&out);
    assert!(
        line.contains("/nonexistent") && line.contains("scripts/setup"),
        "{line}"
    );
}

#[test]
fn a_library_that_is_not_onnx_runtime_is_refused_cleanly() {
    // Any shared library without ONNX Runtime's entry point: the C library is on every machine.
    let libc = [
        "/lib/x86_64-linux-gnu/libc.so.6",
        "/usr/lib/x86_64-linux-gnu/libc.so.6",
    ]
    .into_iter()
    .find(|p| std::path::Path::new(p).exists())
    .expect("libc.so.6");
    let out = choreod()
        .arg("--version")
        .env("ORT_DYLIB_PATH", libc)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(4));
    let line = one_error_line(&out);
    assert!(line.contains("OrtGetApiBase"), "{line}");
}

#[test]
fn help_lists_verbs_and_exit_codes() {
    let out = run(&["--help"]);
    assert!(out.status.success());
    let text = stdout(&out);
    assert!(
        text.contains("check-config") && text.contains("Exit codes"),
        "{text}"
    );
}

#[test]
fn no_verb_is_a_usage_error() {
    assert_eq!(run(&[]).status.code(), Some(2));
    assert_eq!(run(&["frobnicate"]).status.code(), Some(2));
}

fn example_config() -> String {
    let path = workspace_root().join("config").join("choreod.example.toml");
    std::fs::read_to_string(path).expect("config/choreod.example.toml is readable")
}

/// Write `text` as `dir/choreod.toml` with its directories moved into `dir` (which get created).
fn config_in(dir: &std::path::Path, text: &str) -> std::path::PathBuf {
    for d in ["inbox", "output", "state"] {
        std::fs::create_dir_all(dir.join(d)).expect("create test directory");
    }
    let text = text.replace("../.choreod/", &format!("{}/", dir.display()));
    let path = dir.join("choreod.toml");
    std::fs::write(&path, text).expect("write test config");
    path
}

#[test]
fn the_example_config_is_valid() {
    let dir = tempfile::tempdir().unwrap();
    let path = config_in(dir.path(), &example_config());
    let out = run(&["check-config", path.to_str().unwrap()]);
    assert!(out.status.success(), "{}", choreod_tests::stderr(&out));
    assert!(stdout(&out).contains("workers 2"));
}

#[test]
fn a_misspelt_key_is_named_with_exit_3() {
    let dir = tempfile::tempdir().unwrap();
    let text = example_config().replace("settle_ms = 500", "setle_ms = 500");
    let out = run(&[
        "check-config",
        config_in(dir.path(), &text).to_str().unwrap(),
    ]);
    assert_eq!(out.status.code(), Some(3));
    assert!(one_error_line(&out).contains("`serve.setle_ms`"));
}

#[test]
fn a_negative_worker_count_is_named_with_exit_3() {
    let dir = tempfile::tempdir().unwrap();
    let text = example_config().replace("workers = 2", "workers = -3");
    let out = run(&[
        "check-config",
        config_in(dir.path(), &text).to_str().unwrap(),
    ]);
    assert_eq!(out.status.code(), Some(3));
    assert!(one_error_line(&out).contains("`serve.workers` = -3"));
}

#[test]
fn a_missing_directory_is_named_with_exit_3() {
    let dir = tempfile::tempdir().unwrap();
    let path = config_in(dir.path(), &example_config());
    std::fs::remove_dir(dir.path().join("output")).unwrap();
    let out = run(&["check-config", path.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(3));
    let line = one_error_line(&out);
    assert!(
        line.contains("`paths.output`") && line.contains("does not exist"),
        "{line}"
    );
}

#[test]
fn a_missing_directory_key_is_named_with_exit_3() {
    let dir = tempfile::tempdir().unwrap();
    let text: String = example_config()
        .lines()
        .filter(|l| !l.starts_with("inbox ="))
        .collect::<Vec<_>>()
        .join("\n");
    let out = run(&[
        "check-config",
        config_in(dir.path(), &text).to_str().unwrap(),
    ]);
    assert_eq!(out.status.code(), Some(3));
    assert!(one_error_line(&out).contains("missing key `paths.inbox`"));
}

#[test]
fn json_logs_are_json_lines() {
    let dir = tempfile::tempdir().unwrap();
    let path = config_in(dir.path(), &example_config());
    let out = choreod()
        .args([
            "--log-format",
            "json",
            "--log-level",
            "debug",
            "check-config",
        ])
        .arg(&path)
        .output()
        .unwrap();
    assert!(out.status.success());
    let err = choreod_tests::stderr(&out);
    assert!(err.lines().count() >= 1, "check-config logs at info level");
    for line in err.lines() {
        let v: serde_json::Value =
            serde_json::from_str(line).unwrap_or_else(|e| panic!("{e}: {line}"));
        assert!(v.get("level").is_some(), "{line}");
    }
}
