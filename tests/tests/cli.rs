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

/// `choreod dance` on the bundled clip with the bundled model; returns the `--stats` JSON.
fn dance(out: &std::path::Path, extra: &[&str]) -> serde_json::Value {
    let song = workspace_root().join("daemon/assets/audio/vibe_ace_44k_stereo.ogg");
    let mut args = vec![
        "dance",
        song.to_str().expect("test setup"),
        "-o",
        out.to_str().expect("test setup"),
        "--stats",
    ];
    args.extend_from_slice(extra);
    let result = run(&args);
    assert!(
        result.status.success(),
        "choreod {args:?}: {}",
        choreod_tests::stderr(&result)
    );
    assert!(out.is_file());
    serde_json::from_str(stdout(&result).trim()).expect("one JSON line on stdout")
}

/// Runs a Python snippet (numpy, h5py) with `args`; it must print "ok".
fn py(script: &str, args: &[&str]) {
    let out = std::process::Command::new(choreod_tests::python())
        .arg("-c")
        .arg(script)
        .args(args)
        .output()
        .expect("run the venv python");
    assert!(
        out.status.success() && String::from_utf8_lossy(&out.stdout).trim() == "ok",
        "python: {}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn dance_writes_the_file_the_stats_and_the_windows() {
    let d = tempfile::tempdir().unwrap();
    let (h5, windows) = (d.path().join("a.h5"), d.path().join("w.npy"));
    let w = windows.to_str().unwrap();
    let stats = dance(
        &h5,
        &[
            "--steps",
            "6",
            "--sampler",
            "dpmsolver++",
            "--save-windows",
            w,
        ],
    );
    let num = |k: &str| {
        stats[k]
            .as_f64()
            .unwrap_or_else(|| panic!("{k} in {stats}"))
    };
    for key in [
        "decode_s",
        "resample_s",
        "mel_s",
        "features_total_s",
        "generate_s",
        "ort_s",
        "write_s",
        "total_s",
        "realtime_factor",
    ] {
        assert!(num(key) >= 0.0, "{key} in {stats}");
    }
    // The clip is 61.5 s (decoded), 30 fps; windows of 150 frames every 75.
    let audio_s = num("audio_s");
    assert!((audio_s - 61.5).abs() < 0.1, "{stats}");
    let frames = (audio_s * 30.0).round();
    assert_eq!(num("frames"), frames);
    assert_eq!(num("fps"), 30.0);
    let windows_n = ((frames - 150.0) / 75.0).ceil() + 1.0;
    assert_eq!(num("windows"), windows_n);
    assert_eq!(num("steps"), 6.0);
    // One chunk (32 windows), guidance off: one network call per step.
    assert_eq!(num("network_evaluations"), 6.0);
    assert_eq!(num("batch_rows"), 6.0 * windows_n);
    assert!(num("total_s") >= num("generate_s") && num("generate_s") >= num("ort_s"));
    // The exemplar's music-only work is hoisted: its prologue runs once for the one chunk.
    assert_eq!(num("prologue_runs"), 1.0);
    py(
        r#"
import sys, h5py, numpy as np
f = h5py.File(sys.argv[1], "r")
assert int(f.attrs["format_version"]) == 2
j = f["motion/joints"]
assert j.shape == (int(sys.argv[3]), 24, 3) and np.isfinite(j[...]).all(), j.shape
p = f["provenance"].attrs
assert p["sampler"] == "dpmsolver++" and int(p["steps"]) == 6, dict(p)
assert float(p["eta"]) == 0.0 and int(p["chunk_windows"]) == 32 and p["init_noise_sha256"] == ""
assert float(p["guidance"]) == 1.0 and int(p["seed"]) == 0
w = np.load(sys.argv[2])
assert w.dtype == np.float32 and w.shape == (int(sys.argv[4]), 150, 72), w.shape
print("ok")
"#,
        &[
            h5.to_str().unwrap(),
            w,
            &format!("{frames}"),
            &format!("{windows_n}"),
        ],
    );
}

/// A package of another task is refused before any work: exit 4, one line naming the task.
#[test]
fn dance_with_a_style_transfer_package_exits_4() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("x.h5");
    let song = workspace_root().join("daemon/assets/audio/vibe_ace_44k_stereo.ogg");
    let model = workspace_root().join("models/packages/style-gaussian");
    let result = run(&[
        "dance",
        song.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--model",
        model.to_str().unwrap(),
    ]);
    assert_eq!(result.status.code(), Some(4));
    let line = choreod_tests::one_error_line(&result);
    assert!(
        line.contains("style-gaussian")
            && line.contains("task: is style-transfer, this needs a music-to-dance package"),
        "{line}"
    );
    assert!(!out.exists());
}

/// `--eta` only moves DDIM: with another sampler (given, or the package's) it is refused, not
/// silently ignored.
#[test]
fn eta_with_a_sampler_other_than_ddim_is_refused() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("x.h5");
    let song = workspace_root().join("daemon/assets/audio/vibe_ace_44k_stereo.ogg");
    for sampler in ["ddpm", "dpmsolver++"] {
        let result = run(&[
            "dance",
            song.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
            "--sampler",
            sampler,
            "--eta",
            "0.5",
        ]);
        assert_eq!(result.status.code(), Some(1), "{sampler}");
        let line = choreod_tests::one_error_line(&result);
        assert!(
            line.contains("--eta applies to the ddim sampler only") && line.contains(sampler),
            "{line}"
        );
        assert!(!out.exists());
    }
}

#[test]
fn dance_from_given_noise_is_a_function_of_the_noise() {
    let d = tempfile::tempdir().unwrap();
    let noise = d.path().join("xT.npy");
    let (n, a, b) = (
        noise.to_str().unwrap(),
        d.path().join("a.h5"),
        d.path().join("b.h5"),
    );
    py(
        "import sys, numpy as np\n\
         np.save(sys.argv[1], np.random.default_rng(5).standard_normal((150, 72)).astype(np.float32))\n\
         print('ok')",
        &[n],
    );
    // Deterministic DDIM, chunks of 4 windows (so chunk borders are in-painted too): the seed
    // no longer matters.
    let common = [
        "--steps",
        "5",
        "--eta",
        "0",
        "--chunk-windows",
        "4",
        "--init-noise",
        n,
    ];
    dance(&a, &[&common[..], &["--seed", "1"]].concat());
    dance(&b, &[&common[..], &["--seed", "2"]].concat());
    py(
        r#"
import sys, h5py, hashlib, numpy as np
a, b = (h5py.File(p, "r") for p in sys.argv[1:3])
assert np.array_equal(a["motion/joints"][...], b["motion/joints"][...])
p = a["provenance"].attrs
assert p["init_noise_sha256"] == hashlib.sha256(open(sys.argv[3], "rb").read()).hexdigest()
assert int(p["chunk_windows"]) == 4 and p["sampler"] == "ddim" and int(p["seed"]) == 1
print("ok")
"#,
        &[a.to_str().unwrap(), b.to_str().unwrap(), n],
    );
    // Noise of the wrong shape: one line naming it, nothing written.
    py(
        "import sys, numpy as np\nnp.save(sys.argv[1], np.zeros((3, 150, 71), np.float32))\nprint('ok')",
        &[n],
    );
    let c = d.path().join("c.h5");
    let song = workspace_root().join("daemon/assets/audio/vibe_ace_44k_stereo.ogg");
    let out = run(&[
        "dance",
        song.to_str().unwrap(),
        "-o",
        c.to_str().unwrap(),
        "--init-noise",
        n,
    ]);
    let line = one_error_line(&out);
    assert!(
        line.contains("initial noise") && line.contains("(3, 150, 71)"),
        "{line}"
    );
    assert!(!c.exists());
}

#[test]
fn a_missing_output_folder_is_refused_before_any_work() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("missing");
    let in_missing = missing.join("out.h5");
    let (out, windows) = (dir.path().join("out.h5"), missing.join("windows.npy"));
    // The input does not exist either: an up-front check reports the folder, not the input.
    let input = dir.path().join("no-such-song.ogg");
    let cases: [Vec<&std::ffi::OsStr>; 3] = [
        vec![
            "dance".as_ref(),
            input.as_ref(),
            "-o".as_ref(),
            in_missing.as_ref(),
        ],
        vec![
            "dance".as_ref(),
            input.as_ref(),
            "-o".as_ref(),
            out.as_ref(),
            "--save-windows".as_ref(),
            windows.as_ref(),
        ],
        vec![
            "stylize".as_ref(),
            "--content".as_ref(),
            input.as_ref(),
            "--style".as_ref(),
            input.as_ref(),
            "-o".as_ref(),
            in_missing.as_ref(),
        ],
    ];
    for args in cases {
        let result = choreod().args(&args).output().unwrap();
        assert_eq!(result.status.code(), Some(1), "{args:?}");
        let line = one_error_line(&result);
        assert!(
            line.contains(&format!("in the folder {}", missing.display()))
                && line.contains("No such file or directory")
                && !line.contains("no-such-song"),
            "{line}"
        );
    }
    // The probe leaves nothing behind.
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
}

#[test]
fn a_dance_that_is_not_a_body_is_warned_about() {
    // Issue 23 item 6: the untrained mofusion-ref makes a "dance" 2.2 km wide; `render` refuses
    // it, `dance` said nothing. The bundled exemplar's dance is a body and gets no warning.
    let dir = tempfile::tempdir().expect("test setup");
    let song = workspace_root().join("daemon/assets/audio/vibe_ace_44k_stereo.ogg");
    let song = song.to_str().expect("test setup");
    let model = workspace_root().join("models/packages/mofusion-ref");
    for (model, warned) in [(Some(model), true), (None, false)] {
        let out = dir.path().join("d.h5");
        let mut args = vec!["dance", song, "-o", out.to_str().expect("test setup")];
        if let Some(m) = &model {
            args.extend(["--model", m.to_str().expect("test setup")]);
        }
        let result = run(&args);
        let err = choreod_tests::stderr(&result);
        assert!(result.status.success(), "{err}");
        assert_eq!(
            err.contains("the dance is not a body"),
            warned,
            "{args:?}: {err}"
        );
    }
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
