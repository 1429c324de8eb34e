//! `choreod models check DIR` as a user runs it, manifests no song can pass, ONNX Runtime's own
//! messages, and the package builders' skeleton table.

use std::path::Path;
use std::process::Output;
use std::time::{Duration, Instant};

use choreod_tests::{
    edited_package, endless_package, fails_with, fixtures, one_error_line, path_arg as s, py, run,
    run_within, stderr, stdout, workspace_root,
};

fn exemplar() -> std::path::PathBuf {
    workspace_root()
        .join("models")
        .join("packages")
        .join("exemplar")
}

#[test]
fn the_shipped_exemplar_package_checks_out() {
    let dir = exemplar();
    let out = run(&["models", "check", dir.to_str().unwrap()]);
    let text = stdout(&out);
    assert!(
        out.status.success(),
        "{text}{}",
        choreod_tests::stderr(&out)
    );
    for want in [
        "exemplar",
        "music-to-dance",
        "smpl24",
        "150 frames",
        "ddim 50 steps",
        "[N, 157, 80]",
        "test run    ok",
        // The beat-retimed candidates (whole, and the first half the data term reads) and their
        // music logits move out of the step loop, and the split graph agrees.
        "3 tensors computed once per batch",
        "hoisting    ok",
        "valid",
    ] {
        assert!(text.contains(want), "no {want:?} in:\n{text}");
    }
}

/// The style-transfer packages this repository builds load, and every component runs.
#[test]
fn the_style_transfer_packages_check_out() {
    for (name, latent, style) in [
        ("style-gaussian", "[N, T, 284]", "[N, 569]"),
        ("style-gaussian-oracle", "[N, T, 284]", "[N, 569]"),
        ("mcm-ldm-ref", "[N, 7, 16]", "[N, 32]"),
    ] {
        let dir = workspace_root().join("models").join("packages").join(name);
        let out = run(&["models", "check", dir.to_str().unwrap()]);
        let text = stdout(&out);
        assert!(
            out.status.success(),
            "{name}: {text}{}",
            choreod_tests::stderr(&out)
        );
        for want in [
            name,
            "task        style-transfer",
            "t2m22",
            "segments    content up to",
            "component   vae_encoder",
            "component   vae_decoder",
            "component   style_encoder",
            "component   denoiser",
            latent,
            style,
            "test run    ok",
            "valid",
        ] {
            assert!(text.contains(want), "{name}: no {want:?} in:\n{text}");
        }
        assert!(!text.contains("audio "), "{name}: {text}");
    }
}

#[test]
fn a_tampered_package_exits_4_with_one_line_naming_package_and_component() {
    let tmp = tempfile::tempdir().unwrap();
    let pkg = tmp.path().join("pkg");
    std::fs::create_dir(&pkg).unwrap();
    for f in ["choreod-model.toml", "denoiser.onnx"] {
        std::fs::copy(exemplar().join(f), pkg.join(f)).unwrap();
    }
    let mut onnx = std::fs::read(pkg.join("denoiser.onnx")).unwrap();
    onnx.truncate(onnx.len() / 2);
    std::fs::write(pkg.join("denoiser.onnx"), onnx).unwrap();
    let out = run(&["models", "check", pkg.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(4));
    let line = one_error_line(&out);
    assert!(
        line.contains(pkg.to_str().unwrap())
            && line.contains("component denoiser")
            && line.contains("sha256"),
        "{line}"
    );
}

#[test]
fn a_manifest_error_names_the_key() {
    let tmp = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(exemplar().join("choreod-model.toml")).unwrap();
    std::fs::write(
        tmp.path().join("choreod-model.toml"),
        text.replace("format_version = 1", "format_version = 9"),
    )
    .unwrap();
    let out = run(&["models", "check", tmp.path().to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(4));
    let line = one_error_line(&out);
    assert!(
        line.contains("format_version") && line.contains("upgrade choreod"),
        "{line}"
    );
}

/// `models check` of a package whose denoiser.onnx is `make(path)`; None if it hangs 20 s.
fn check_with_denoiser(make: impl FnOnce(&std::path::Path)) -> Option<std::process::Output> {
    let tmp = tempfile::tempdir().expect("test setup");
    let pkg = tmp.path().join("pkg");
    std::fs::create_dir(&pkg).expect("test setup");
    std::fs::copy(
        exemplar().join("choreod-model.toml"),
        pkg.join("choreod-model.toml"),
    )
    .expect("test setup");
    make(&pkg.join("denoiser.onnx"));
    let mut child = choreod_tests::choreod()
        .args(["models", "check", pkg.to_str().expect("test setup")])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("test setup");
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(20);
    while std::time::Instant::now() < deadline {
        if child.try_wait().expect("test setup").is_some() {
            return Some(child.wait_with_output().expect("test setup"));
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    child.kill().expect("test setup");
    child.wait().expect("test setup");
    None
}

#[test]
fn a_fifo_or_a_device_as_component_file_is_refused_unread() {
    // A FIFO nobody writes to would block the read forever; a symlink to /dev/zero would be
    // read until memory runs out (issue 12 item 12).
    let fifo = check_with_denoiser(|p| {
        let ok = std::process::Command::new("mkfifo")
            .arg(p)
            .status()
            .unwrap();
        assert!(ok.success());
    })
    .expect("models check hung on a FIFO");
    let zero = check_with_denoiser(|p| std::os::unix::fs::symlink("/dev/zero", p).unwrap())
        .expect("models check hung on /dev/zero");
    for (what, out) in [("FIFO", fifo), ("/dev/zero", zero)] {
        assert_eq!(out.status.code(), Some(4), "{what}");
        let line = one_error_line(&out);
        assert!(
            line.contains("component denoiser") && line.contains("not a regular file"),
            "{what}: {line}"
        );
    }
}

/// The figure after `key` in `text` ("max 1.234e-2" → 0.01234).
fn figure_after(text: &str, key: &str) -> f64 {
    let rest = &text[text
        .find(key)
        .unwrap_or_else(|| panic!("no {key:?} in:\n{text}"))
        + key.len()..];
    let number: String = rest
        .trim_start()
        .chars()
        .take_while(|c| c.is_ascii_digit() || matches!(c, '.' | 'e' | '-' | '+'))
        .collect();
    number
        .parse()
        .unwrap_or_else(|_| panic!("no number after {key:?} in:\n{text}"))
}

/// An int8 copy made by models/packages/quantize.py is smaller, loads, dances, is measured
/// against its float32 source by `models check --against`, and refuses a package that is not
/// its source.
#[test]
fn an_int8_package_is_checked_against_its_float32_source() {
    let tmp = tempfile::tempdir().expect("test setup");
    let source = workspace_root().join("models/packages/mofusion-ref");
    let int8 = tmp.path().join("mofusion-int8");
    let made = choreod_tests::python_cmd()
        .arg(workspace_root().join("models/packages/quantize.py"))
        .arg(&source)
        .arg("-o")
        .arg(&int8)
        .output()
        .expect("run quantize.py");
    assert!(made.status.success(), "{}", choreod_tests::stderr(&made));
    // Weights stored as int8 with a scale per channel: 58 % of this tiny network's float32 file
    // (the weights alone shrink to 25 %; scales and the quantise / dequantise nodes add the rest).
    let size = |dir: &std::path::Path| std::fs::metadata(dir.join("denoiser.onnx")).unwrap().len();
    assert!(
        size(&int8) * 10 < size(&source) * 7,
        "int8 {} bytes, float32 {} bytes",
        size(&int8),
        size(&source)
    );

    let (src, q) = (source.to_str().unwrap(), int8.to_str().unwrap());
    let out = run(&["models", "check", q, "--against", src]);
    let text = stdout(&out);
    assert!(
        out.status.success(),
        "{text}{}",
        choreod_tests::stderr(&out)
    );
    assert!(text.contains("quantized   from mofusion-ref"), "{text}");
    let against = |text: &str| -> String {
        let line = text.lines().find(|l| l.starts_with("against "));
        line.unwrap_or_else(|| panic!("no against line in:\n{text}"))
            .to_string()
    };
    let line = against(&text);
    let (max, rms) = (figure_after(&line, "max"), figure_after(&line, "rms"));
    // Quantised outputs differ from the float32 ones (a copy would give 0) and stay finite;
    // random weights make the size of the difference meaningless (quantize.py's docstring).
    assert!(
        max > 0.0 && max.is_finite() && rms > 0.0 && rms.is_finite(),
        "{text}"
    );
    // The same comparison of the source with itself is exactly zero: the measure compares
    // like with like.
    let same = stdout(&run(&["models", "check", src, "--against", src]));
    let line = against(&same);
    assert_eq!(
        (figure_after(&line, "max"), figure_after(&line, "rms")),
        (0.0, 0.0),
        "{same}"
    );

    let exemplar = exemplar();
    let wrong = run(&[
        "models",
        "check",
        q,
        "--against",
        exemplar.to_str().unwrap(),
    ]);
    assert_eq!(wrong.status.code(), Some(4));
    let line = one_error_line(&wrong);
    assert!(
        line.contains("quantization.source_sha256.denoiser")
            && line.contains("not this package's source"),
        "{line}"
    );

    let song = workspace_root().join("daemon/assets/audio/vibe_ace_44k_stereo.ogg");
    let motion = tmp.path().join("int8.h5");
    let danced = run(&[
        "dance",
        song.to_str().unwrap(),
        "-o",
        motion.to_str().unwrap(),
        "--model",
        q,
        "--steps",
        "5",
    ]);
    assert!(
        danced.status.success(),
        "{}",
        choreod_tests::stderr(&danced)
    );
    assert!(motion.is_file());
}

#[test]
fn models_check_refuses_manifests_no_song_can_pass() {
    let d = tempfile::tempdir().unwrap();
    for (name, from, to, want) in [
        (
            "rate",
            "sample_rate = 16000",
            "sample_rate = 4000000000",
            "audio.sample_rate: 4000000000: must be in 1..=768000 Hz",
        ),
        (
            "fft",
            "n_fft = 2048",
            "n_fft = 2147483648",
            "audio.n_fft: 2147483648: must be in 16..=65536",
        ),
        (
            "fps",
            "fps = 30.0",
            "fps = 1e-300",
            "motion.fps: must be in 1..=1000 frames per second, got 1e-300",
        ),
        (
            "guidance",
            "guidance = 1.0",
            "guidance = 1e30",
            "sampler.guidance: must be in 0..=100",
        ),
    ] {
        let pkg = edited_package(d.path(), name, |t| t.replacen(from, to, 1));
        let out = run(&["models", "check", &pkg]);
        fails_with(
            &out,
            4,
            &[&format!("model package {pkg}: choreod-model.toml: {want}")],
        );
    }
}

#[test]
fn onnx_runtime_messages_do_not_precede_the_error_line() {
    let d = tempfile::tempdir().unwrap();
    // A denoiser that fails inside ONNX Runtime at run time (an index out of range), which
    // ONNX Runtime used to log itself, in colour, before choreod's line.
    let pkg = edited_package(d.path(), "broken", |t| t);
    let onnx = Path::new(&pkg).join("denoiser.onnx");
    py(
        "models/onnx_runtime_messages_do_not_precede_the_error_line",
        &[&s(&onnx)],
    );
    let out = run(&["models", "check", &pkg]);
    fails_with(
        &out,
        4,
        &[
            "component denoiser: run failed",
            "indices element out of data bounds",
        ],
    );
    assert!(!stderr(&out).contains('\u{1b}'), "{}", stderr(&out));
}

/// The package builders' SMPL table (`models/packages/pkg_common.py`, which makes the bundled
/// packages' rest offsets and skeleton) is choreo_datasets' own, digit for digit: one table.
#[test]
fn the_package_builders_skeleton_table_is_choreo_datasets_own() {
    use choreo_datasets::skeleton::{SMPL24_OFFSETS, SMPL24_PARENTS};
    let packages = workspace_root().join("models/packages");
    let table = choreod_tests::py_json("models/skeleton_table", &[packages.to_str().unwrap()]);
    let parents: Vec<i64> = table["parents"]
        .as_array()
        .expect("parents")
        .iter()
        .map(|p| p.as_i64().expect("an index"))
        .collect();
    let want: Vec<i64> = SMPL24_PARENTS.iter().map(|&p| i64::from(p)).collect();
    assert_eq!(parents, want);
    let offsets = table["offsets"].as_array().expect("offsets");
    assert_eq!(offsets.len(), SMPL24_OFFSETS.len());
    for (j, (row, ours)) in offsets.iter().zip(SMPL24_OFFSETS).enumerate() {
        for c in 0..3 {
            // Both are the published decimal digits: as f32 they are the same number.
            let theirs = row[c].as_f64().expect("a number") as f32;
            assert_eq!(theirs, ours[c], "joint {j} axis {c}");
        }
    }
}

#[test]
fn megabyte_keys_and_values_in_a_config_or_manifest_give_a_short_line() {
    let d = tempfile::tempdir().unwrap();
    let big = "A".repeat(1 << 20);
    let short = |out: &Output, code: i32| {
        let line = one_error_line(out);
        assert_eq!(
            out.status.code(),
            Some(code),
            "{}",
            &line[..line.len().min(400)]
        );
        // A megabyte in, under a kilobyte out (the config's other problems included).
        assert!(line.len() < 1000, "{} bytes: {}", line.len(), &line[..1000]);
        // Cut, with the length (1 MiB and the few bytes of a key's table or a value's quotes).
        assert!(line.contains("…' (10485"), "{line}");
        line
    };
    // The config: a 1 MB unknown key (TOML's message quotes it, and the line names it), and a
    // 1 MB value of a known key.
    let config = d.path().join("choreod.toml");
    std::fs::write(&config, format!("[job]\n{big} = 1\n")).unwrap();
    let line = short(&run(&["check-config", &s(&config)]), 3);
    assert!(
        line.contains("line 2, key `'job.AAAA") && line.contains("unknown field `'AAAA"),
        "{line}"
    );
    std::fs::write(&config, format!("[log]\nlevel = \"{big}\"\n")).unwrap();
    let line = short(&run(&["check-config", &s(&config)]), 3);
    assert!(line.contains("invalid `log.level`"), "{line}");
    // A manifest: a 1 MB `format` value and a 1 MB unknown key.
    let pkg = edited_package(d.path(), "format", |t| {
        t.replacen(
            "format = \"choreod-model\"",
            &format!("format = \"{big}\""),
            1,
        )
    });
    let line = short(&run(&["models", "check", &pkg]), 4);
    assert!(
        line.contains("choreod-model.toml: format: is 'AAAA"),
        "{line}"
    );
    let pkg = edited_package(d.path(), "key", |t| {
        t.replacen("[motion]", &format!("{big} = 1\n\n[motion]"), 1)
    });
    let line = short(&run(&["models", "check", &pkg]), 4);
    assert!(line.contains("unknown field `'AAAA"), "{line}");
}

#[test]
fn a_model_that_loops_for_ever_is_stopped_at_the_time_limit() {
    let d = tempfile::tempdir().unwrap();
    let pkg = endless_package(d.path());
    // The limit plus start-up; without a limit these runs never end.
    let bound = Duration::from_secs(20);
    let started = Instant::now();
    let out = run_within(bound, &["models", "check", &pkg, "--time-limit", "2"]);
    fails_with(
        &out,
        4,
        &[&format!(
            "model package {pkg}: component denoiser: stopped at the time limit of 2 s (--time-limit)"
        )],
    );
    assert!(started.elapsed() >= Duration::from_secs(2), "stopped early");
    let song = s(&fixtures().join("audio/vibe_ace_22k_mono.ogg"));
    let output = d.path().join("dance.h5");
    let out = run_within(
        bound,
        &[
            "dance",
            &song,
            "-o",
            &s(&output),
            "--model",
            &pkg,
            "--time-limit",
            "3",
        ],
    );
    fails_with(
        &out,
        1,
        &[
            &format!("generating a dance for {song}"),
            "component denoiser: stopped at the time limit of 3 s (--time-limit)",
        ],
    );
    assert!(!output.exists());
}

/// `models check` shows a LODGE package's own values: its licence, both stages with Global's
/// guidance and Local's ramp, the cosine schedule (its offset and cap, alphas in float32 — not
/// the linear schedules' beta range, which it ignores) and the package's own timesteps (the
/// committed manifest's `sampler.timesteps`: 999, 979, ..., 19) without the generic sampler's
/// `steps_offset` and single `guidance 1`, which LODGE does not use. Both layouts of the
/// music branch's outputs (the tokens; each layer's cross-attention keys and values).
#[test]
fn a_lodge_package_check_shows_its_own_schedule_and_guidance() {
    for package in ["lodge-tiny-random", "lodge-tiny-random-kv"] {
        check_lodge_package(package);
    }
}

fn check_lodge_package(package: &str) {
    let out = run(&["models", "check", &choreod_tests::package(package)]);
    let text = stdout(&out);
    assert!(
        out.status.success(),
        "{text}{}",
        choreod_tests::stderr(&out)
    );
    for want in [
        "licence: choreod test fixture (random weights)",
        "lodge       global 1024 music frames -> 104 keyframes (guidance 2), local 256 frames \
         (guidance ramp 0..4 capped at 2), 16 genres",
        "schedule    1000 steps, cosine betas (s 0.008, capped at 0.999), alphas multiplied in \
         float32, predicts x0, clip_sample",
        "sampler     ddim 50 steps at timesteps 999, 979, ..., 19, eta 1",
        "valid",
    ] {
        assert!(text.contains(want), "no {want:?} in:\n{text}");
    }
    for unwanted in ["0.0001..0.02", "guidance 1", "steps_offset"] {
        assert!(!text.contains(unwanted), "{unwanted:?} in:\n{text}");
    }
}
