//! `choreod models check DIR` as a user runs it.

use choreod_tests::{one_error_line, run, stdout, workspace_root};

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
        // The music envelope moves out of the step loop, and the split graph agrees.
        "1 tensor computed once per batch",
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
