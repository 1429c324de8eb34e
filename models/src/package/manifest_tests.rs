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
    let dance = m.dance_spec().unwrap();
    assert_eq!((dance.window_frames, dance.overlap_frames()), (8, 4));
    assert_eq!(dance.audio.frame_rate(), 31.25);
    let o = m.sampler_options();
    assert_eq!(
        (o.kind, o.steps, o.steps_offset, o.guidance),
        (SamplerKind::Ddim, 10, 1, Guidance::Off)
    );
    assert_eq!(
        m.components[&Role::Denoiser].inputs[2].shape[1],
        Dim::Fixed(6)
    );
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
            base.replace("[components.denoiser]", "[components.vae_encoder]"),
            "components.denoiser",
        ),
        (
            base.replace("[components.denoiser]", "[components.encoder]"),
            "unknown variant `encoder`",
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

/// The three style-transfer packages this repository builds (models/packages/build.py).
const STYLE_PACKAGES: [&str; 3] = [
    include_str!("../../packages/style-gaussian/choreod-model.toml"),
    include_str!("../../packages/style-gaussian-oracle/choreod-model.toml"),
    include_str!("../../packages/mcm-ldm-ref/choreod-model.toml"),
];

/// `text` without the table `header` (from its header line to the next table).
fn without_table(text: &str, header: &str) -> String {
    let start = text.find(header).expect("table present");
    let end = text[start + header.len()..]
        .find("\n[")
        .map_or(text.len(), |k| start + header.len() + k + 1);
    format!("{}{}", &text[..start], &text[end..])
}

/// `text` without the line that starts with `key`.
fn without_line(text: &str, key: &str) -> String {
    let lines: Vec<&str> = text.lines().filter(|l| !l.starts_with(key)).collect();
    assert!(lines.len() < text.lines().count(), "{key} present");
    lines.join("\n")
}

#[test]
fn the_style_transfer_packages_parse_with_their_own_sections() {
    for text in STYLE_PACKAGES {
        let m = parse(text).unwrap();
        assert_eq!(m.task, Task::StyleTransfer);
        assert!(m.audio.is_none());
        assert_eq!(
            m.components.keys().copied().collect::<Vec<_>>(),
            [
                Role::Denoiser,
                Role::VaeEncoder,
                Role::VaeDecoder,
                Role::StyleEncoder
            ]
        );
        let msg = m.dance_spec().unwrap_err().to_string();
        assert!(
            msg.contains("task") && msg.contains("music-to-dance"),
            "{msg}"
        );
    }
    let mcm = parse(STYLE_PACKAGES[2]).unwrap();
    let want = StyleSpec {
        max_frames: 196,
        min_frames: 40,
        content_guidance: 1.0,
        style_guidance: 2.5,
        inversion_steps: 30,
    };
    assert_eq!(mcm.style_spec().unwrap(), want);
    // Without the optional keys, the contract's defaults (wc 1, ws 2.5, 30 inversion steps).
    let mut text = STYLE_PACKAGES[0].to_string();
    for key in ["content_guidance", "style_guidance", "inversion_steps"] {
        text = without_line(&text, key);
    }
    let bare = parse(&text).unwrap().style_spec().unwrap();
    assert_eq!(
        (
            bare.content_guidance,
            bare.style_guidance,
            bare.inversion_steps
        ),
        (1.0, 2.5, 30)
    );
    let music = parse(&manifest_text(ANY_SHA)).unwrap();
    let msg = music.style_spec().unwrap_err().to_string();
    assert!(msg.contains("style-transfer"), "{msg}");
}

#[test]
fn each_task_needs_its_own_sections_and_refuses_the_others() {
    let dance = manifest_text(ANY_SHA);
    let style = STYLE_PACKAGES[2];
    let style_encoder = &style[style.find("[components.style_encoder]").unwrap()
        ..style.find("[components.denoiser]").unwrap()];
    let cases = [
        // music-to-dance
        (without_table(&dance, "[audio]"), "audio: missing"),
        (
            without_line(&dance, "window_frames"),
            "motion.window_frames: missing",
        ),
        (
            without_line(&dance, "stride_frames"),
            "motion.stride_frames: missing",
        ),
        (
            dance.replace("stride_frames = 4", "stride_frames = 4\nmax_frames = 10"),
            "motion.max_frames: is not a key of music-to-dance packages",
        ),
        (
            dance.replace("guidance = 1.0", "guidance = 1.0\ninversion_steps = 5"),
            "sampler.inversion_steps: is not a key of music-to-dance",
        ),
        (
            format!("{dance}\n{style_encoder}"),
            "components.style_encoder: music-to-dance packages have no style_encoder",
        ),
        // style-transfer
        (
            without_line(style, "max_frames"),
            "motion.max_frames: missing",
        ),
        (
            without_line(style, "min_frames"),
            "motion.min_frames: missing",
        ),
        (
            without_table(style, "[components.style_encoder]"),
            "components.style_encoder: missing",
        ),
        (
            without_table(style, "[components.vae_decoder]"),
            "components.vae_decoder: missing",
        ),
        (
            format!("{style}\n[audio]\nsample_rate = 16000\nn_fft = 2048\nhop = 512\nn_mels = 80\nfmin = 0.0\nfmax = 8000.0\ntop_db = 80.0\nmusic_frames = 157\n"),
            "audio: is not a key of style-transfer packages",
        ),
        (
            style.replace("min_frames = 40", "min_frames = 40\nwindow_frames = 150"),
            "motion.window_frames: is not a key of style-transfer",
        ),
        (
            style.replace("min_frames = 40", "min_frames = 400"),
            "motion.min_frames",
        ),
        (
            style.replace("dim = 263", "dim = 72"),
            "motion.mean",
        ),
        (
            style.replace("representation = \"humanml3d263\"", "representation = \"rot6d\""),
            "motion: style transfer needs representation",
        ),
        (
            style.replace("content_guidance = 1.0", "content_guidance = -1.0"),
            "sampler.content_guidance",
        ),
        (
            style.replace("inversion_steps = 30", "inversion_steps = 0"),
            "sampler.inversion_steps",
        ),
        // The contract's tensors: names, dtypes, shapes, the latent the same everywhere.
        (
            style.replace(
                "{ name = \"trajectory\", dtype = \"float32\", shape = [\"N\", \"T\", 3] }",
                "{ name = \"trajectory\", dtype = \"float32\", shape = [\"N\", \"T\", 4] }",
            ),
            "components.denoiser.inputs: tensor trajectory",
        ),
        (
            style.replace(
                "{ name = \"latent\", dtype = \"float32\", shape = [\"N\", 7, 16] },",
                "{ name = \"latent\", dtype = \"float32\", shape = [\"N\", 7, 17] },",
            ),
            "components.vae_decoder.inputs: tensor latent",
        ),
        (
            style.replace("outputs = [ { name = \"style\"", "outputs = [ { name = \"styles\""),
            "components.style_encoder.outputs: no tensor named \"style\"",
        ),
        (
            style.replace(
                "{ name = \"t\", dtype = \"int64\", shape = [\"N\"] },",
                "{ name = \"t\", dtype = \"float32\", shape = [\"N\"] },",
            ),
            "components.denoiser.inputs: tensor t is float32",
        ),
        (
            style.replace(
                "{ name = \"t\", dtype = \"int64\", shape = [\"N\"] },",
                "{ name = \"t\", dtype = \"int64\", shape = [\"N\"] },\n  { name = \"music\", dtype = \"float32\", shape = [\"N\"] },",
            ),
            "components.denoiser.inputs: tensor 'music' is not in the style-transfer contract",
        ),
    ];
    for (text, want) in cases {
        let msg = error_of(&text);
        assert!(msg.contains(want), "expected {want:?} in: {msg}");
    }
}

fn lodge_text() -> String {
    std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("packages/lodge-tiny-random/choreod-model.toml"),
    )
    .unwrap()
}

#[test]
fn a_lodge_manifest_parses_into_its_typed_sections() {
    let m = parse(&lodge_text()).unwrap();
    assert_eq!(m.task, Task::Lodge);
    let l = m.lodge_spec().unwrap();
    assert!(!l.license.commercial_use || l.license.name.contains("fixture"));
    assert_eq!(l.audio.librosa, choreo_dsp::LibrosaVersion::V07);
    assert_eq!((l.audio.fps, l.timesteps.len()), (30, 50));
    assert_eq!((l.rest_joints.len(), l.normalizer.scale.len()), (165, 139));
    assert_eq!(l.section.genres.len(), 16);
    assert_eq!(l.genre_id("popping"), Some(1));
    assert_eq!(l.genre_id("Dai"), Some(6));
    assert_eq!(l.genre_id("15"), Some(15));
    assert_eq!((l.genre_id("16"), l.genre_id("Polka")), (None, None));
    assert_eq!(l.section.local.guidance_ramp, [0.0, 4.0]);
    assert!(m.dance_spec().is_err() && m.style_spec().is_err());
}

/// Hostile or broken LODGE manifests: one line naming the key, never a panic.
#[test]
fn hostile_lodge_manifests_name_the_key_in_one_line() {
    let base = lodge_text();
    let replace = |from: &str, to: &str| {
        assert!(base.contains(from), "{from}");
        base.replacen(from, to, 1)
    };
    let cases = [
        (replace("[license]\n", "[licence]\n"), "licence"),
        (
            replace(
                "name = \"choreod test fixture (random weights)\"",
                "name = \"\"",
            ),
            "license.name",
        ),
        (
            replace("librosa = \"0.7.2\"", "librosa = \"9.9\""),
            "librosa",
        ),
        (
            replace("features = \"fact35\"", "features = \"mfcc\""),
            "features",
        ),
        (replace("dim = 35\n", "dim = 35\nn_mels = 80\n"), "n_mels"),
        (
            replace("rest_joints = [\n", "rest_joints = [ 1e300,\n"),
            "motion.rest_joints",
        ),
        (
            replace("scale = [\n", "scale = [ 0.0,\n"),
            "motion.normalizer.scale",
        ),
        (
            replace("kind = \"minmax\"", "kind = \"zscore\""),
            "motion.normalizer",
        ),
        (replace("jazz = 5", "jazz = 99"), "lodge.genre_aliases"),
        (replace("jazz = 5", "jazz = -1"), "lodge.genre_aliases"),
        (
            replace("guidance_ramp = [0.0, 4.0]", "guidance_ramp = [0.0, 1e30]"),
            "lodge.local.guidance_ramp",
        ),
        (
            replace("guidance_ramp = [0.0, 4.0]", "guidance_ramp = [0.0]"),
            "line",
        ),
        (
            replace("music_frames = 1024", "music_frames = 4096"),
            "lodge",
        ),
        (
            replace("style_noise = 256", "style_noise = 100000000"),
            "lodge.local.style_noise",
        ),
        (
            replace("timesteps = [999, 979", "timesteps = [979, 999"),
            "sampler.timesteps",
        ),
        (
            replace("timesteps = [999, 979", "timesteps = [99999, 979"),
            "sampler.timesteps",
        ),
        (
            replace("beta_schedule = \"cosine\"", "beta_schedule = \"linear\""),
            "diffusion",
        ),
        (
            replace("cosine_s = 0.008", "cosine_s = 0.5"),
            "diffusion.cosine_s",
        ),
        (
            replace(
                "representation = \"lodge-smplx139\"",
                "representation = \"x\"",
            ),
            "motion",
        ),
        (
            replace("genres = [\"Breaking\"", "genres = [\"\\u0007\""),
            "lodge.genres",
        ),
        (
            replace("[motion]\n", "[motion]\nwindow_frames = 8\n"),
            "motion.window_frames",
        ),
        (
            replace(
                "{ name = \"style_noise\", dtype = \"float32\", shape = [\"N\", 256] }",
                "{ name = \"style_noise\", dtype = \"float32\", shape = [\"N\", 255] }",
            ),
            "components.local_denoiser.inputs",
        ),
    ];
    for (text, key) in cases {
        let msg = error_of(&text);
        assert!(msg.contains(key), "{key}: {msg}");
        assert!(!msg.contains('\n') && msg.len() < 600, "{key}: {msg}");
    }
    // A music-to-dance manifest refuses fact35 audio.
    let dance = manifest_text(ANY_SHA).replacen("[audio]\n", "[audio]\nfeatures = \"fact35\"\n", 1);
    let msg = error_of(&dance);
    assert!(
        msg.contains("audio.sample_rate is not a key of fact35 audio"),
        "{msg}"
    );
}

/// An int8 package's `[quantization]` section parses, and a section that names other
/// components, a malformed digest or a non-finite error is refused naming the key.
#[test]
fn a_quantization_section_names_its_source_exactly() {
    let sha = "a".repeat(64);
    let section = format!(
        "\n[quantization]\nscheme = \"int8\"\nsource = \"tiny\"\nmax_relative_error = 0.5\n\
         rms_relative_error = 0.25\n[quantization.source_sha256]\ndenoiser = \"{sha}\"\n\
         [quantization.fp32_nodes]\ndenoiser = [\"conv_1\"]\n"
    );
    let base = manifest_text(ANY_SHA);
    let m = parse(&format!("{base}{section}")).unwrap();
    let q = m.quantization.as_ref().unwrap();
    assert_eq!((q.source.as_str(), q.rms_relative_error), ("tiny", 0.25));
    assert_eq!(q.source_sha256[&Role::Denoiser], sha);
    assert_eq!(q.fp32_nodes[&Role::Denoiser], ["conv_1"]);
    assert!(parse(&base).unwrap().quantization.is_none());
    for (bad, key) in [
        (
            section.replace("denoiser = \"", "vae_encoder = \""),
            "quantization.source_sha256",
        ),
        (
            section.replace(&sha, "xyz"),
            "quantization.source_sha256.denoiser",
        ),
        (
            section.replace("0.5", "nan"),
            "quantization.max_relative_error",
        ),
        (
            section.replace("0.25", "-1.0"),
            "quantization.rms_relative_error",
        ),
        (
            section.replace("denoiser = [", "style_encoder = ["),
            "quantization.fp32_nodes.style_encoder",
        ),
    ] {
        let msg = error_of(&format!("{base}{bad}"));
        assert!(msg.contains(key), "{key}: {msg}");
    }
}

/// The optional `source` output (issue 24): refused without `[library]`, which it indexes;
/// with it the provenance line names each clip used once, sorted, with the attribution; and
/// `[library]` is a music-to-dance key.
#[test]
fn a_source_output_needs_the_library_it_names() {
    let with_source = manifest_text(ANY_SHA).replace(
        r#"outputs = [ { name = "pred", dtype = "float32", shape = ["N", 8, 72] } ]"#,
        r#"outputs = [ { name = "pred", dtype = "float32", shape = ["N", 8, 72] }, { name = "source", dtype = "float32", shape = ["N", 1] } ]"#,
    );
    assert!(with_source.contains("\"source\""), "test setup");
    let msg = error_of(&with_source);
    assert!(msg.contains("library") && msg.contains("source"), "{msg}");
    let library = "\n[library]\nclips = [\"salsa_a\", \"break_b\", \"modern_c\"]\n\
                   attribution = \"Thanks to the capture lab.\"\n";
    let text = with_source.replacen(
        "task = \"music-to-dance\"\n",
        &format!("task = \"music-to-dance\"\n{library}"),
        1,
    );
    let m = parse(&text).unwrap();
    assert!(m.declares_source());
    assert_eq!(
        m.library_line(&[2, 0, 2, 9]).unwrap(),
        "clips used: modern_c, salsa_a; attribution: Thanks to the capture lab."
    );
    assert_eq!(
        m.library_line(&[]).unwrap(),
        "clips used: not identified; attribution: Thanks to the capture lab."
    );
    // The output's shape is the contract's.
    let wide = text.replace(r#"shape = ["N", 1]"#, r#"shape = ["N", 2]"#);
    assert!(error_of(&wide).contains("source"));
    // Without the output, [library] alone is fine (the attribution still travels) and no
    // package without it has a library line.
    let plain = manifest_text(ANY_SHA);
    assert!(parse(&plain).unwrap().library_line(&[0]).is_none());
}
