//! End-to-end: `choreod stylize` with the shipped style-transfer packages, against independent
//! references: the style-gaussian closed form (computed here in numpy from its README's
//! formula), and `models/packages/stylize_reference.py` (numpy + onnxruntime, the diffusers
//! DDIM formulas written out) on `mcm-ldm-ref`.
//! Build first: `cargo build --release -p choreod` (the tests run the binary).
// The helpers below are test code too; clippy's allow-unwrap-in-tests covers only #[test] fns.
#![allow(clippy::unwrap_used)]

use std::path::{Path, PathBuf};

use choreod_tests::{
    ok, one_error_line, package, path_arg as s, py, python_cmd, run, workspace_root,
};

fn bundled(name: &str) -> String {
    s(&workspace_root().join("daemon/assets/motion").join(name))
}

fn cmu_bvh() -> String {
    bundled("cmu_01_01_8s_30fps.bvh")
}

fn aistpp_pkl() -> String {
    bundled("aistpp_gBR_sBM_cAll_d04_mBR0_ch01.pkl")
}

/// HumanML3D features of the bundled AIST++ dance (choreod convert: SMPL-24 at 60 fps → t2m-22
/// at 20 fps), cut into a content and a style clip from different parts of the dance.
struct Clips {
    dir: tempfile::TempDir,
}

impl Clips {
    fn new() -> Self {
        let dir = tempfile::tempdir().unwrap();
        let all = dir.path().join("all.npy");
        ok(&["convert", &aistpp_pkl(), "--to", "features", "-o", &s(&all)]);
        py(
            "stylize/clips",
            &[
                &s(&all),
                &s(&dir.path().join("content.npy")),
                &s(&dir.path().join("style.npy")),
            ],
        );
        Clips { dir }
    }

    fn path(&self, name: &str) -> PathBuf {
        self.dir.path().join(name)
    }

    fn content(&self) -> String {
        s(&self.path("content.npy"))
    }

    fn style(&self) -> String {
        s(&self.path("style.npy"))
    }
}

/// `choreod stylize` of the content clip with the style clip, plus `extra` flags.
fn stylize_features(clips: &Clips, out: &str, extra: &[&str]) {
    let (content, style) = (clips.content(), clips.style());
    let mut args = vec![
        "stylize",
        "--content",
        &content,
        "--style",
        &style,
        "-o",
        out,
    ];
    args.extend_from_slice(extra);
    ok(&args);
}

#[test]
fn inversion_converges_to_the_gaussian_closed_form_as_steps_grow() {
    let clips = Clips::new();
    let oracle = package("style-gaussian-oracle");
    let (o30, o200) = (s(&clips.path("o30.h5")), s(&clips.path("o200.h5")));
    for (out, steps) in [(&o30, "30"), (&o200, "200")] {
        stylize_features(
            &clips,
            out,
            &["--model", &oracle, "--mode", "inversion", "--steps", steps],
        );
    }
    py(
        "stylize/inversion_converges_to_the_gaussian_closed_form_as_steps_grow",
        &[&clips.content(), &clips.style(), &o30, &o200],
    );
}

#[test]
fn default_package_is_exactly_the_closed_form_in_both_modes_with_every_sampler() {
    let clips = Clips::new();
    let (t, i) = (s(&clips.path("t.h5")), s(&clips.path("i.h5")));
    let (ddpm, dpm) = (s(&clips.path("ddpm.h5")), s(&clips.path("dpm.h5")));
    stylize_features(&clips, &t, &[]);
    stylize_features(&clips, &i, &["--mode", "inversion"]);
    // Any sampler of transfer mode: x0_hat is the map at every step, and the last step of each
    // returns x0_hat (DDIM with set_alpha_to_one, DDPM's posterior at t = 0, DPM-Solver++ to
    // sigma 0), whatever its noise.
    stylize_features(
        &clips,
        &ddpm,
        &["--sampler", "ddpm", "--steps", "20", "--seed", "4"],
    );
    stylize_features(&clips, &dpm, &["--sampler", "dpmsolver++", "--steps", "15"]);
    py(
        "stylize/default_package_is_exactly_the_closed_form_in_both_modes_with_every_sampler",
        &[&clips.content(), &clips.style(), &t, &i],
    );
}

#[test]
fn transfer_with_guidance_1_and_the_content_as_style_returns_the_content() {
    let clips = Clips::new();
    let out = s(&clips.path("same.h5"));
    ok(&[
        "stylize",
        "--content",
        &clips.content(),
        "--style",
        &clips.content(),
        "--guidance",
        "1",
        "-o",
        &out,
    ]);
    py(
        "stylize/transfer_with_guidance_1_and_the_content_as_style_returns_the_content",
        &[&clips.content(), &out],
    );
}

/// The Python reference loop on `content` and the style clip, with `args`.
fn reference(clips: &Clips, content: &str, out: &str, args: &[&str]) {
    let script = workspace_root().join("models/packages/stylize_reference.py");
    let o = python_cmd()
        .arg(&script)
        .args(["--content", content, "--style", &clips.style(), "-o", out])
        .args(args)
        .output()
        .expect("run stylize_reference.py");
    assert!(
        o.status.success(),
        "stylize_reference.py failed: {}",
        String::from_utf8_lossy(&o.stderr)
    );
}

/// mcm-ldm-ref with the manifest's identity mean/std replaced by the dance's own statistics
/// (the ONNX files are the package's; their sha256 in the manifest still hold), so that
/// normalising and denormalising are exercised; and a fixed x_T (7, 16) for transfer mode.
fn normalised_mcm_package(clips: &Clips) -> (String, String) {
    let dir = clips.path("mcm-normalised");
    std::fs::create_dir(&dir).unwrap();
    let src = workspace_root().join("models/packages/mcm-ldm-ref");
    for entry in std::fs::read_dir(&src).unwrap() {
        let p = entry.unwrap().path();
        std::fs::copy(&p, dir.join(p.file_name().unwrap())).unwrap();
    }
    let noise = s(&clips.path("xT.npy"));
    py(
        "stylize/normalised_mcm_package",
        &[&s(&dir), &s(&clips.path("all.npy")), &noise],
    );
    (s(&dir), noise)
}

#[test]
fn mcm_ldm_ref_matches_the_python_reference_loop_in_both_modes() {
    let clips = Clips::new();
    let (model, noise) = normalised_mcm_package(&clips);
    let cases: [(&str, Vec<&str>); 2] = [
        (
            "transfer",
            vec!["--guidance", "2.5", "--steps", "20", "--init-noise", &noise],
        ),
        (
            "inversion",
            vec![
                "--mode",
                "inversion",
                // Not 1 - 2 wc + ws = 0 (e.g. wc 1.5, ws 2), for which swapping the c and u
                // rows gives the same result.
                "--content-guidance",
                "1.5",
                "--style-guidance",
                "3",
                "--steps",
                "15",
            ],
        ),
    ];
    for (mode, flags) in cases {
        let (ours, theirs) = (
            s(&clips.path(&format!("{mode}.h5"))),
            s(&clips.path(&format!("{mode}.npy"))),
        );
        let mut args = vec!["--model", &model];
        args.extend(flags.iter().copied());
        stylize_features(&clips, &ours, &args);
        let mut ref_args = vec!["--model", model.as_str(), "--threads", "1"];
        ref_args.extend(flags.iter().copied());
        reference(&clips, &clips.content(), &theirs, &ref_args);
        py(
            "stylize/mcm_ldm_ref_matches_the_python_reference_loop_in_both_modes",
            &[&ours, &theirs, mode],
        );
    }
}

#[test]
fn every_input_format_stylizes_end_to_end() {
    let clips = Clips::new();
    let d = clips.dir.path();
    let (j22, j24, h5) = (d.join("j22.npy"), d.join("j24.npy"), d.join("a.h5"));
    ok(&["convert", &clips.content(), "-o", &s(&j22)]);
    ok(&["convert", &aistpp_pkl(), "-o", &s(&j24)]);
    ok(&["convert", &aistpp_pkl(), "-o", &s(&h5)]);
    // (input, extra flags, expected output frames at 20 fps)
    let cases: [(String, &[&str], usize); 6] = [
        (clips.content(), &[], 150),
        // Joints → features: one frame fewer (velocities).
        (s(&j22), &[], 149),
        // 720 frames at 60 fps → 240 joint frames at 20 fps → 239 feature frames.
        (s(&j24), &["--fps", "60"], 239),
        (cmu_bvh(), &[], 159),
        (aistpp_pkl(), &[], 239),
        (s(&h5), &[], 239),
    ];
    let style = clips.style();
    for (k, (content, extra, frames)) in cases.iter().enumerate() {
        let out = s(&d.join(format!("out{k}.h5")));
        let mut args = vec![
            "stylize",
            "--content",
            content.as_str(),
            "--style",
            &style,
            "-o",
            &out,
        ];
        args.extend_from_slice(extra);
        ok(&args);
        py(
            "stylize/every_input_format_stylizes_end_to_end",
            &[&out, content, &frames.to_string(), &clips.style()],
        );
    }
    // BVH output too.
    let bvh = s(&d.join("out.bvh"));
    ok(&[
        "stylize",
        "--content",
        &cmu_bvh(),
        "--style",
        &aistpp_pkl(),
        "-o",
        &bvh,
    ]);
    let text = std::fs::read_to_string(&bvh).unwrap();
    assert!(
        text.starts_with("HIERARCHY") && text.contains("Frames: 159"),
        "{}",
        &text[..200.min(text.len())]
    );
}

#[test]
fn default_package_keeps_root_path_feet_and_bone_lengths() {
    let clips = Clips::new();
    let d = clips.dir.path();
    let (out, content_joints) = (s(&d.join("out.h5")), s(&d.join("cj.npy")));
    ok(&[
        "stylize",
        "--content",
        &clips.content(),
        "--style",
        &cmu_bvh(),
        "-o",
        &out,
        "--mode",
        "inversion",
    ]);
    // The content's joints, recovered from its features by `convert` (recover_from_ric).
    ok(&["convert", &clips.content(), "-o", &content_joints]);
    py(
        "stylize/default_package_keeps_root_path_feet_and_bone_lengths",
        &[&out, &content_joints],
    );
}

#[test]
fn stylized_output_is_one_rigid_body_and_its_bvh_is_its_joints() {
    // Issue 23 item 7: the joints recovered from stylized features were not one skeleton
    // (neck to collar 16–25 cm), so the BVH (a rigid armature) differed from the .h5 by up to
    // 6.3 cm. The output is now fitted to the content's body: every bone keeps one length, and
    // the BVH stylize writes is the .h5's joints.
    let d = tempfile::tempdir().unwrap();
    let (h5, bvh) = (s(&d.path().join("out.h5")), s(&d.path().join("out.bvh")));
    for out in [&h5, &bvh] {
        ok(&[
            "stylize",
            "--content",
            &cmu_bvh(),
            "--style",
            &aistpp_pkl(),
            "-o",
            out,
        ]);
    }
    py("stylize/rigid_body_and_its_bvh", &[&h5, &bvh]);
}

#[test]
fn long_content_is_segmented_and_stitched_as_the_reference_per_segment() {
    let clips = Clips::new();
    let (model, noise) = normalised_mcm_package(&clips);
    let (long, out) = (s(&clips.path("long.npy")), s(&clips.path("long.h5")));
    // 400 frames (the dance twice over, cut); mcm-ldm-ref takes 196 frames per segment with an
    // overlap of at least 196/4 = 49: three segments, evenly spaced starts 0, 102, 204
    // (datasets::plan_segments; half-window overlaps would need four).
    let segs: Vec<String> = (0..3)
        .map(|k| s(&clips.path(&format!("seg{k}.npy"))))
        .collect();
    py(
        "stylize/long_content_is_segmented_and_stitched_as_the_reference_per_segment",
        &[
            &s(&clips.path("all.npy")),
            &long,
            &segs[0],
            &segs[1],
            &segs[2],
        ],
    );
    let flags = ["--guidance", "2.5", "--steps", "10", "--init-noise", &noise];
    let style = clips.style();
    let mut args = vec!["stylize", "--content", &long, "--style", &style];
    args.extend(["--model", &model, "-o", &out, "--stats"]);
    args.extend(flags);
    let stats: serde_json::Value = serde_json::from_str(ok(&args).trim()).unwrap();
    assert_eq!(
        (stats["segments"].clone(), stats["frames"].clone()),
        (3.into(), 400.into())
    );
    // The per-network profile counts the same calls as the sampler's own count.
    let components = stats["components"].as_array().expect("components");
    let denoiser = components.iter().find(|c| c["role"] == "denoiser");
    assert_eq!(
        denoiser.map(|d| d["runs"].clone()),
        Some(stats["denoiser_calls"].clone()),
        "{stats}"
    );
    // The reference loop on each segment (the same x_T: a (7, 16) noise is every segment's),
    // cross-faded here by the rule of datasets/src/segments.rs's docs: over the o frames two
    // neighbours share, the earlier weighs (o - i)/(o + 1), the later (i + 1)/(o + 1) at the
    // i-th shared frame; elsewhere a segment weighs 1.
    let mut ref_args = vec!["--model", model.as_str(), "--threads", "1"];
    ref_args.extend(flags);
    let refs: Vec<String> = (0..3)
        .map(|k| s(&clips.path(&format!("ref{k}.npy"))))
        .collect();
    for (seg, r) in segs.iter().zip(&refs) {
        reference(&clips, seg, r, &ref_args);
    }
    py(
        "stylize/long_content_is_segmented_and_stitched_as_the_reference_per_segment_2",
        &[&out, &refs[0], &refs[1], &refs[2]],
    );
}

#[test]
fn a_style_embedding_stands_for_the_style_motion() {
    let clips = Clips::new();
    let (by_motion, by_embedding) = (s(&clips.path("m.h5")), s(&clips.path("e.h5")));
    stylize_features(&clips, &by_motion, &[]);
    // style-gaussian's style vector from its README: [mean, population std, 1] over the frames
    // of the latent (284 channels: features with dims 0..3 zeroed, the ric slots 4..67 holding
    // bone vectors x10, then the 21 bone lengths x10).
    let embedding = s(&clips.path("style-vector.npy"));
    py("stylize/style_vector", &[&clips.style(), &embedding]);
    ok(&[
        "stylize",
        "--content",
        &clips.content(),
        "--style-embedding",
        &embedding,
        "-o",
        &by_embedding,
    ]);
    py(
        "stylize/a_style_embedding_stands_for_the_style_motion",
        &[&by_motion, &by_embedding],
    );
    // An embedding of the wrong size is one error line.
    let short = s(&clips.path("short-vector.npy"));
    py("stylize/wrong_size_embedding", &[&short]);
    let line = one_error_line(&run(&[
        "stylize",
        "--content",
        &clips.content(),
        "--style-embedding",
        &short,
        "-o",
        &by_embedding,
    ]));
    assert!(
        line.contains("512 values") && line.contains("569"),
        "{line}"
    );
}

#[test]
fn bad_inputs_fail_with_one_line() {
    let clips = Clips::new();
    let d = clips.dir.path();
    let out = s(&d.join("out.h5"));
    // A BVH whose arm joints have names no rig knows.
    let renamed = d.join("renamed.bvh");
    let text = std::fs::read_to_string(cmu_bvh()).unwrap();
    std::fs::write(&renamed, text.replace("LeftForeArm", "Flipper")).unwrap();
    let short = d.join("short.npy");
    let nan = d.join("nan.npy");
    py(
        "stylize/bad_inputs_fail_with_one_line",
        &[&clips.content(), &s(&short), &s(&nan)],
    );
    let (style, content) = (clips.style(), clips.content());
    let (renamed, short, nan) = (s(&renamed), s(&short), s(&nan));
    let missing = s(&d.join("missing.bvh"));
    let mcm = package("mcm-ldm-ref");
    let cases: [(Vec<&str>, &str); 9] = [
        (vec!["--content", &renamed, "--style", &style], "left_elbow"),
        (
            vec!["--content", &content, "--style", &short],
            "at least 40",
        ),
        (vec!["--content", &nan, "--style", &style], "NaN"),
        (vec!["--content", &content, "--style", &nan], "NaN"),
        (
            vec![
                "--content",
                &content,
                "--style",
                &style,
                "--guidance",
                "2",
                "--mode",
                "inversion",
            ],
            "--content-guidance",
        ),
        // Inversion computes x_T from the content: a seed would be silently ignored.
        (
            vec![
                "--content",
                &content,
                "--style",
                &style,
                "--seed",
                "3",
                "--mode",
                "inversion",
            ],
            "--seed",
        ),
        (
            vec!["--content", &missing, "--style", &style],
            "missing.bvh",
        ),
        // x_T of the wrong shape (mcm-ldm-ref's latent is (7, 16); this is a style clip).
        (
            vec![
                "--content",
                &content,
                "--style",
                &style,
                "--model",
                &mcm,
                "--init-noise",
                &style,
            ],
            "initial noise",
        ),
        (
            vec![
                "--content",
                &content,
                "--style",
                &style,
                "--mode",
                "inversion",
                "--sampler",
                "ddpm",
            ],
            "inversion mode inverts and denoises with DDIM",
        ),
    ];
    for (args, needle) in cases {
        let mut all = vec!["stylize", "-o", &out];
        all.extend(args.iter().copied());
        let line = one_error_line(&run(&all));
        assert!(line.contains(needle), "{args:?}: {line}");
        assert!(!Path::new(&out).exists());
    }
}
