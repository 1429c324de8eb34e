//! The command line as a user meets it: --version, --help, check-config, exit codes, usage
//! errors for out-of-range flags, an output that is an input, and error lines that cut long
//! input text short.

use std::process::Output;

use choreod_tests::{
    aistpp, choreod, cmu_bvh, fails_with, motion_file, one_error_line, package, path_arg as s, py,
    run, stdout, usage_error, workspace_root,
};

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

/// README: "Every verb has `--help` with examples".
#[test]
fn every_verb_has_help_with_examples() {
    let verbs: [&[&str]; 14] = [
        &["dance"],
        &["features"],
        &["stylize"],
        &["convert"],
        &["render"],
        &["mel"],
        &["beats"],
        &["eval"],
        &["prep"],
        &["models", "check"],
        &["serve"],
        &["live"],
        &["view"],
        &["check-config"],
    ];
    for verb in verbs {
        let out = run(&[verb, &["--help"]].concat());
        assert!(out.status.success(), "{verb:?}");
        let text = stdout(&out);
        assert!(
            text.contains("Examples:"),
            "{verb:?} --help has no examples"
        );
        // An example too long for the help's width is broken with a `\`, never wrapped by the
        // help (issue 23 item 10: `stylize --help` printed `--style-guidance 0.5` on a line of
        // its own). Example lines start `  choreod` (or `  #`, `  systemctl`); a deeper line
        // continues a command whose line ends with `\`.
        let block = text.split("Examples:").nth(1).unwrap_or_default();
        let mut previous = "";
        for line in block.lines().skip(1).take_while(|l| !l.trim().is_empty()) {
            let indent = line.len() - line.trim_start().len();
            let first = line.split_whitespace().next().unwrap_or_default();
            let fine = match indent {
                0 => true,
                2 => ["choreod", "systemctl"].contains(&first) || first.starts_with('#'),
                _ => previous.ends_with('\\'),
            };
            assert!(
                fine,
                "{verb:?} --help: a wrapped example line {line:?}:\n{text}"
            );
            previous = line;
        }
    }
}

#[test]
fn no_verb_is_a_usage_error() {
    assert_eq!(run(&[]).status.code(), Some(2));
    assert_eq!(run(&["frobnicate"]).status.code(), Some(2));
    // As README "Usage" documents: the parser's `error:` line, the verb's usage, the hint.
    let missing = run(&["dance", "song.ogg"]);
    assert_eq!(missing.status.code(), Some(2));
    let err = choreod_tests::stderr(&missing);
    assert!(
        err.starts_with("error: the following required arguments were not provided")
            && err.contains("\nUsage: choreod dance")
            && err
                .trim_end()
                .ends_with("For more information, try '--help'."),
        "{err}"
    );
}

#[test]
fn a_batch_of_zero_is_a_usage_error_not_a_batch_of_one() {
    let fixture = choreod_tests::fixtures()
        .join("audio")
        .join("vibe_ace_22k_mono.ogg");
    let audio = fixture.to_str().unwrap();
    let dir = tempfile::tempdir().unwrap();
    let output = dir.path().join("out.h5");
    let out_arg = output.to_str().unwrap();
    for (verb_args, flag) in [
        (
            vec!["dance", audio, "-o", out_arg, "--chunk-windows", "0"],
            "--chunk-windows",
        ),
        (
            vec![
                "stylize",
                "--content",
                audio,
                "--style",
                audio,
                "-o",
                out_arg,
                "--chunk-segments",
                "0",
            ],
            "--chunk-segments",
        ),
    ] {
        let out = run(&verb_args);
        // Refused by the parser (usage error, exit 2) before any input is read.
        assert_eq!(
            out.status.code(),
            Some(2),
            "{flag}: {}",
            choreod_tests::stderr(&out)
        );
        let err = choreod_tests::stderr(&out);
        let first = err.lines().next().unwrap_or_default();
        assert!(
            first.contains(flag) && first.contains("must be at least 1"),
            "{err}"
        );
        assert!(!output.exists());
    }
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
    // The example leaves workers and ORT threads to the machine: the CPUs shared out, one
    // thread each (2 CPUs: 2 workers x 1 thread, the fastest measured there).
    let text = stdout(&out);
    let after = |key: &str| -> usize {
        let rest = &text[text.find(key).unwrap_or_else(|| panic!("{key} in {text}")) + key.len()..];
        let digits: String = rest.chars().take_while(char::is_ascii_digit).collect();
        digits
            .parse()
            .unwrap_or_else(|_| panic!("a number after {key}: {text}"))
    };
    let (workers, threads) = (after("workers "), after("intra "));
    let cpus = std::thread::available_parallelism().map_or(1, std::num::NonZero::get);
    assert!(
        workers * threads <= cpus && workers * threads + workers > cpus,
        "{workers} x {threads} on {cpus} CPUs: {text}"
    );
    if cpus == 2 {
        assert_eq!((workers, threads), (2, 1), "{text}");
    }
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
    let example = example_config();
    // The example leaves the key commented out (its default follows the machine).
    assert!(
        example.contains("# workers = 2"),
        "the example's workers line moved"
    );
    let text = example.replace("# workers = 2", "workers = -3");
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

#[test]
fn input_text_in_error_lines_is_cut_short() {
    let d = tempfile::tempdir().unwrap();
    let token = "A".repeat(10 << 20);
    let check = |out: &Output| {
        let line = one_error_line(out);
        assert!(line.len() < 400, "{} bytes: {}", line.len(), &line[..400]);
        assert!(line.contains(&format!("…' ({} bytes)", 10 << 20)), "{line}");
    };
    // A 10 MB token where the BVH's first keyword belongs.
    let bvh = d.path().join("token.bvh");
    std::fs::write(&bvh, cmu_bvh().replacen("HIERARCHY", &token, 1)).unwrap();
    check(&run(&[
        "convert",
        &s(&bvh),
        "-o",
        &s(&d.path().join("x.npy")),
    ]));
    // ... and as a beat time of `eval --beats`.
    let beats = d.path().join("beats.txt");
    std::fs::write(&beats, format!("0.5\n{token}\n")).unwrap();
    check(&run(&["eval", &aistpp(), "--beats", &s(&beats)]));
    // A .npy header holds at most 64 KiB: its dtype is cut as well.
    let npy = d.path().join("dtype.npy");
    py("cli/input_text_in_error_lines_is_cut_short", &[&s(&npy)]);
    let line = one_error_line(&run(&[
        "convert",
        &s(&npy),
        "-o",
        &s(&d.path().join("y.h5")),
    ]));
    assert!(line.len() < 400 && line.contains("(60000 bytes)"), "{line}");
}

#[test]
fn out_of_range_flags_are_usage_errors() {
    // A missing song: the parser must refuse the flag before anything is read.
    let song = "missing.ogg";
    usage_error(
        &["dance", song, "-o", "x.h5", "--guidance", "1e30"],
        "--guidance",
        "0..=100",
    );
    usage_error(
        &["dance", song, "-o", "x.h5", "--eta", "1e300"],
        "--eta",
        "0..=1",
    );
    usage_error(
        &["dance", song, "-o", "x.h5", "--intra-threads", "100000"],
        "--intra-threads",
        "0..=",
    );
    usage_error(
        &["dance", song, "-o", "x.h5", "--max-duration", "nan"],
        "--max-duration",
        "0.1..=86400",
    );
    usage_error(
        &["mel", song, "-o", "x.npy", "--max-duration", "inf"],
        "--max-duration",
        "0.1..=86400",
    );
    let m = aistpp();
    usage_error(
        &[
            "stylize",
            "--content",
            &m,
            "--style",
            &m,
            "-o",
            "x.h5",
            "--guidance=-1",
        ],
        "--guidance",
        "0..=100",
    );
    usage_error(
        &[
            "stylize",
            "--content",
            &m,
            "--style",
            &m,
            "-o",
            "x.h5",
            "--mode",
            "inversion",
            "--style-guidance",
            "1e30",
        ],
        "--style-guidance",
        "0..=100",
    );
    usage_error(
        &[
            "stylize",
            "--content",
            &m,
            "--style",
            &m,
            "-o",
            "x.h5",
            "--intra-threads",
            "2000",
        ],
        "--intra-threads",
        "0..=",
    );
}

#[test]
fn an_output_that_is_an_input_is_refused_and_the_input_kept() {
    let d = tempfile::tempdir().unwrap();
    let h5 = motion_file(d.path());
    let before = std::fs::read(&h5).unwrap();
    let link = d.path().join("link.h5");
    std::os::unix::fs::symlink(&h5, &link).unwrap();
    let dotted = format!("{}/./ok.h5", d.path().display());
    for output in [s(&h5), dotted, s(&link)] {
        let out = run(&["convert", &s(&h5), "-o", &output]);
        fails_with(
            &out,
            2,
            &["is the same file as the input", "choose another output"],
        );
    }
    let out = run(&[
        "stylize",
        "--content",
        &aistpp(),
        "--style",
        &s(&h5),
        "-o",
        &s(&link),
        "--model",
        &package("style-gaussian"),
    ]);
    fails_with(&out, 2, &["-o", "is the same file as --style"]);
    assert_eq!(
        std::fs::read(&h5).unwrap(),
        before,
        "the input was replaced"
    );
}

#[test]
fn check_config_prints_the_paths_it_resolved() {
    // Issue 23 item 10: paths are relative to the config's folder; check-config printed them as
    // written (`config/../.choreod/inbox`), not where the daemon will look.
    let dir = tempfile::tempdir().unwrap();
    std::fs::create_dir(dir.path().join("sub")).unwrap();
    let text = example_config().replace("../.choreod/", "./sub/../");
    let path = config_in(dir.path(), &text);
    let out = choreod()
        .current_dir(dir.path().parent().unwrap())
        .args(["check-config"])
        .arg(std::path::Path::new(dir.path().file_name().unwrap()).join("choreod.toml"))
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", choreod_tests::stderr(&out));
    let text = stdout(&out);
    let root = std::fs::canonicalize(path.parent().unwrap()).unwrap();
    for (key, folder) in [
        ("paths.inbox", "inbox"),
        ("paths.output", "output"),
        ("paths.state", "state"),
    ] {
        let want = format!("{key:<13} = {}", root.join(folder).display());
        assert!(
            text.lines().any(|l| l == want),
            "no line {want:?} in:\n{text}"
        );
    }
}

#[test]
fn dance_hints_paths_a_shell_reads_back_and_says_how_far_it_is() {
    // Issue 23 item 10: the "look at it" hint pasted names with spaces unquoted, and with
    // stderr not a terminal (a log) a long song ran with no progress at all.
    let dir = tempfile::tempdir().unwrap();
    let song = dir.path().join("my song's.ogg");
    std::fs::copy(
        workspace_root().join("daemon/assets/audio/vibe_ace_44k_stereo.ogg"),
        &song,
    )
    .unwrap();
    let out = dir.path().join("the dance.h5");
    let result = run(&[
        "dance",
        song.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--steps",
        "2",
    ]);
    let err = choreod_tests::stderr(&result);
    assert!(result.status.success(), "{err}");
    let progress = format!("dancing to {}: ", song.display());
    assert!(
        err.lines()
            .any(|l| l.starts_with(&progress) && l.contains(" steps, ") && l.ends_with(" s")),
        "{err}"
    );
    let hint = err
        .lines()
        .find_map(|l| l.strip_prefix("look at it: "))
        .unwrap_or_else(|| panic!("no hint: {err}"));
    // The shell's own reading of the hint.
    let words = std::process::Command::new("sh")
        .args([
            "-c",
            "eval \"set -- $1\"; printf '%s\\n' \"$@\"",
            "sh",
            hint,
        ])
        .output()
        .unwrap();
    let words: Vec<String> = String::from_utf8_lossy(&words.stdout)
        .lines()
        .map(String::from)
        .collect();
    let want = [
        "choreod",
        "view",
        out.to_str().unwrap(),
        "--audio",
        song.to_str().unwrap(),
    ];
    assert_eq!(words, want, "{hint}");
}
