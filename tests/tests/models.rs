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
        "1 tensor computed once per batch of music",
        "hoisting    ok",
        "valid",
    ] {
        assert!(text.contains(want), "no {want:?} in:\n{text}");
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
