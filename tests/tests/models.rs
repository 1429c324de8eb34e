//! `choreod models check DIR` as a user runs it, manifests no song can pass, ONNX Runtime's own
//! messages, and the package builders' skeleton table.

use std::path::Path;

use choreod_tests::{
    fails_with, one_error_line, path_arg as s, py, run, stderr, stdout, workspace_root,
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

/// `models/packages/exemplar` copied to `dir/name` with `edit` applied to its manifest.
fn edited_package(dir: &Path, name: &str, edit: impl Fn(String) -> String) -> String {
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
    s(&to)
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
