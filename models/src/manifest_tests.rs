use std::path::Path;

use super::*;
use crate::test_support::{ANY_SHA, manifest_text};

fn parse(text: &str) -> Result<Manifest> {
    Manifest::parse(Path::new("/pkg/tiny"), text)
}

/// The error text, which must name the package and the key.
fn error_of(text: &str) -> String {
    let e = parse(text).unwrap_err();
    assert!(e.is_environment());
    let msg = e.to_string();
    assert!(msg.contains("/pkg/tiny"), "{msg}");
    msg
}

#[test]
fn the_contract_example_parses() {
    let m = parse(&manifest_text(ANY_SHA)).unwrap();
    assert_eq!(m.task, Task::MusicToDance);
    assert_eq!((m.motion.window_frames, m.motion.overlap_frames()), (8, 4));
    assert_eq!(m.audio.frame_rate(), 31.25);
    let o = m.sampler_options();
    assert_eq!(
        (o.kind, o.steps, o.steps_offset, o.guidance),
        (SamplerKind::Ddim, 10, 1, Guidance::Off)
    );
    assert_eq!(m.components["denoiser"].inputs[2].shape[1], Dim::Fixed(6));
    assert_eq!(m.schedule().unwrap().train_steps(), 1000);
}

#[test]
fn format_and_version_are_checked_first() {
    let base = manifest_text(ANY_SHA);
    let newer = base.replace("format_version = 1", "format_version = 2\nnew_key = 3");
    let msg = error_of(&newer);
    assert!(
        msg.contains("format_version") && msg.contains("upgrade choreod"),
        "{msg}"
    );
    let msg = error_of(&base.replace("format = \"choreod-model\"", "format = \"other\""));
    assert!(msg.contains("format:") && msg.contains("other"), "{msg}");
}

#[test]
fn unknown_keys_and_bad_values_name_the_key() {
    let base = manifest_text(ANY_SHA);
    let cases = [
        (
            base.replace("top_db = 80.0", "top_db = 80.0\ntop_dB = 1"),
            "top_dB",
        ),
        (
            base.replace("stride_frames = 4", "stride_frames = 2"),
            "motion.stride_frames",
        ),
        (base.replace("std = [1.0,", "std = [0.0,"), "motion.std"),
        (base.replace("mean = [0.0,", "mean = ["), "motion.mean"),
        (
            base.replace("beta_schedule = \"linear\"", "beta_schedule = \"sigmoid\""),
            "sigmoid",
        ),
        (
            base.replace("\nsteps = 10", "\nsteps = 2000"),
            "sampler.steps",
        ),
        (
            base.replace("file = \"denoiser.onnx\"", "file = \"../../etc/passwd\""),
            "components.denoiser.file",
        ),
        (base.replace(ANY_SHA, "abc"), "components.denoiser.sha256"),
        (
            base.replace("name = \"cond\"", "name = \"condition\""),
            "components.denoiser.inputs",
        ),
        (
            base.replace("[\"N\", 6, 80]", "[\"N\", 7, 80]"),
            "components.denoiser.inputs",
        ),
        (
            base.replace("dtype = \"int64\"", "dtype = \"float32\""),
            "components.denoiser.inputs",
        ),
        (
            base.replace(
                "representation = \"smpl24-rootpos-rootrel\"",
                "representation = \"rot6d\"",
            ),
            "motion.representation",
        ),
        (
            base.replace("[components.denoiser]", "[components.encoder]"),
            "components.denoiser",
        ),
        (base.replace("fps = 30.0", "fps = -1.0"), "motion.fps"),
    ];
    for (text, key) in cases {
        let msg = error_of(&text);
        assert!(msg.contains(key), "expected {key:?} in: {msg}");
    }
}

#[test]
fn a_missing_or_huge_manifest_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let msg = Manifest::load(dir.path()).unwrap_err().to_string();
    assert!(
        msg.contains(MANIFEST_FILE) && msg.contains(&dir.path().display().to_string()),
        "{msg}"
    );
    let f = std::fs::File::create(dir.path().join(MANIFEST_FILE)).unwrap();
    f.set_len(MAX_MANIFEST_BYTES + 1).unwrap();
    let msg = Manifest::load(dir.path()).unwrap_err().to_string();
    assert!(msg.contains("bytes"), "{msg}");
    std::fs::write(dir.path().join(MANIFEST_FILE), b"format = [\x00").unwrap();
    let msg = Manifest::load(dir.path()).unwrap_err().to_string();
    assert!(msg.contains("line 1"), "{msg}");
}
