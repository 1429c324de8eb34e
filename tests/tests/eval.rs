//! End-to-end: `choreod eval` as a user runs it — numbers equal to the reference code's on the
//! committed joints, labelled conventions, feature files, and every edge case a clear result or
//! one error line. Build first: `cargo build --release -p choreod`.

use std::path::{Path, PathBuf};

use choreo_datasets::{MotionFile, Provenance, SkeletonKind, read_npy, write_motion_file};
use choreod_tests::{
    fixtures, one_error_line, py, python_cmd, run, stderr, stdout, workspace_root,
};
use ndarray::{Array3, Ix3, s};
use serde_json::Value;

fn eval_fixtures() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../datasets/tests/fixtures/eval")
}

fn reference_numbers() -> Value {
    let text = std::fs::read_to_string(eval_fixtures().join("reference_numbers.json"))
        .expect("reference numbers");
    serde_json::from_str(&text).expect("json")
}

/// Frames `from..to` of the committed AIST++ joints (60 fps).
fn base(from: usize, to: usize) -> Array3<f32> {
    read_npy(&eval_fixtures().join("base_joints.npy"))
        .expect("base joints")
        .into_dimensionality::<Ix3>()
        .expect("(T, 24, 3)")
        .slice(s![from..to, .., ..])
        .to_owned()
}

fn write(dir: &Path, name: &str, joints: Array3<f32>) -> String {
    let path = dir.join(name);
    write_motion_file(
        &path,
        &MotionFile::from_joints(60.0, SkeletonKind::Smpl24, joints),
    )
    .expect("write motion");
    path.display().to_string()
}

/// Beats at 0.25 s + k·0.5 s, as the reference script's one-hot (frames 15 + 30k at 60 fps).
fn beats_file(dir: &Path) -> String {
    let path = dir.join("beats.txt");
    let text: String = (0..8)
        .map(|k| format!("{}\n", 0.25 + 0.5 * f64::from(k)))
        .collect();
    std::fs::write(&path, text).expect("beats");
    path.display().to_string()
}

fn json(args: &[&str]) -> Value {
    let out = run(args);
    assert!(out.status.success(), "choreod {args:?}: {}", stderr(&out));
    serde_json::from_str(&stdout(&out)).expect("one JSON object")
}

fn num(v: &Value) -> f64 {
    v.as_f64().unwrap_or_else(|| panic!("not a number: {v}"))
}

#[test]
fn one_motion_scores_as_the_reference_code_and_writes_its_features() {
    let d = tempfile::tempdir().expect("tmp");
    let generated = write(d.path(), "w0.h5", base(0, 200));
    let beats = beats_file(d.path());
    let feats = d.path().join("features");
    let report = json(&[
        "eval",
        &generated,
        "--beats",
        &beats,
        "--json",
        "--features-out",
        &feats.display().to_string(),
    ]);
    let want = &reference_numbers()["files"]["w0"];
    let got = &report["generated"][0];
    // Tolerances as datasets/tests/eval_parity.rs (float32 in the reference, f64 here).
    for (key, rel) in [
        ("bas_motion_beats", 1e-6),
        ("bas_music_beats", 1e-6),
        ("pfc", 1e-6),
        ("skate_ratio", 1e-12),
    ] {
        let (g, w) = (num(&got[key]), num(&want[key]));
        assert!(
            (g - w).abs() <= rel * w.abs().max(1.0),
            "{key}: {g} vs reference {w}"
        );
    }
    // --features-out: float32 vectors equal to the reference's float32 features.
    for (file, key) in [("kinetic", "kinetic"), ("geometric", "geometric")] {
        let a = read_npy(&feats.join(format!("00000_w0.{file}.npy"))).expect("feature file");
        let w: Vec<f64> = want[key]
            .as_array()
            .expect("array")
            .iter()
            .map(num)
            .collect();
        assert_eq!(a.len(), w.len(), "{file} length");
        for (g, w) in a.iter().zip(&w) {
            assert!(
                (f64::from(*g) - w).abs() <= 1e-6 * w.abs().max(1e-6),
                "{file}: {g} vs {w}"
            );
        }
    }
    // The conventions are part of the output.
    let bas = report["conventions"]["bas"]
        .as_str()
        .expect("bas convention");
    assert!(bas.contains("60 fps") && bas.contains("50 ms"), "{bas}");
}

#[test]
fn text_output_labels_both_conventions_and_the_slip() {
    let d = tempfile::tempdir().expect("tmp");
    let generated: Vec<String> = [0, 40, 80]
        .iter()
        .map(|&s| write(d.path(), &format!("g{s}.h5"), base(s, s + 200)))
        .collect();
    let refs = d.path().join("refs");
    std::fs::create_dir(&refs).expect("mkdir");
    for s in [10, 50, 90] {
        write(&refs, &format!("r{s}.h5"), base(s, s + 200));
    }
    let beats = beats_file(d.path());
    let mut args = vec!["eval"];
    args.extend(generated.iter().map(String::as_str));
    let refs_s = refs.display().to_string();
    args.extend(["--reference", &refs_s, "--beats", &beats]);
    let out = run(&args);
    assert!(out.status.success(), "{}", stderr(&out));
    let text = stdout(&out);
    for label in [
        "fid_k ",
        "fid_k_fixed_accel",
        "fid_g",
        "div_k_reference",
        "bas_motion_beats",
        "bas_music_beats",
        "precedence slip",
        "sigma = 3 frames = 50 ms",
        "set: 3 generated, 3 reference",
    ] {
        assert!(text.contains(label), "missing '{label}' in:\n{text}");
    }
    assert!(!text.contains("undefined"), "{text}");
    // Scored at 30 fps the tolerance in seconds doubles, and the output says so.
    args.extend(["--bas-fps", "30"]);
    let text = stdout(&run(&args));
    assert!(text.contains("sigma = 3 frames = 100 ms"), "{text}");
}

#[test]
fn edge_cases_are_clear_results_not_crashes() {
    let d = tempfile::tempdir().expect("tmp");
    let beats = beats_file(d.path());
    // A motionless body has no kinematic beats: mint's rule scores 0, Bailando's is undefined.
    let frozen = base(0, 1)
        .broadcast((120, 24, 3))
        .expect("broadcast")
        .to_owned();
    let still = write(d.path(), "still.h5", frozen);
    let r = json(&["eval", &still, "--beats", &beats, "--json"]);
    assert_eq!(r["generated"][0]["motion_beats"], 0);
    assert_eq!(num(&r["generated"][0]["bas_motion_beats"]), 0.0);
    assert!(r["generated"][0]["bas_music_beats"].is_null());
    // A song without beats: both BAS undefined, everything else reported.
    let empty = d.path().join("none.txt");
    std::fs::write(&empty, "").expect("write");
    let generated = write(d.path(), "g.h5", base(0, 200));
    let r = json(&[
        "eval",
        &generated,
        "--beats",
        &empty.display().to_string(),
        "--json",
    ]);
    assert!(r["generated"][0]["bas_motion_beats"].is_null());
    assert!(r["set"]["pfc"].is_number());
    // A reference set of one file: FID undefined, with the reason.
    let one_ref = write(d.path(), "ref.h5", base(50, 250));
    let out = run(&["eval", &generated, &still, "--reference", &one_ref]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(
        stdout(&out).contains("fid_k                undefined (the reference set has 1 motion(s); FID needs at least 2)"),
        "{}",
        stdout(&out)
    );
    // A single-frame file and NaN joints: one error line naming the file.
    let single = write(d.path(), "single.h5", base(0, 1));
    let line = one_error_line(&run(&["eval", &single]));
    assert!(
        line.contains("single.h5") && line.contains("at least 3 frames"),
        "{line}"
    );
    let mut nan = base(0, 100);
    nan[[40, 5, 1]] = f32::NAN;
    let nan = write(d.path(), "nan.h5", nan);
    let line = one_error_line(&run(&["eval", &nan]));
    assert!(
        line.contains("nan.h5") && line.contains("non-finite"),
        "{line}"
    );
    // A beats file that is not numbers; an empty directory.
    let bad = d.path().join("bad.txt");
    std::fs::write(&bad, "0.5\nsoon\n").expect("write");
    let line = one_error_line(&run(&[
        "eval",
        &generated,
        "--beats",
        &bad.display().to_string(),
    ]));
    assert!(line.contains("line 2"), "{line}");
    let empty_dir = d.path().join("empty");
    std::fs::create_dir(&empty_dir).expect("mkdir");
    let line = one_error_line(&run(&["eval", &empty_dir.display().to_string()]));
    assert!(line.contains("no motion files"), "{line}");
    // --music and --beats together is a usage error.
    let out = run(&["eval", &generated, "--beats", &beats, "--music", &beats]);
    assert_eq!(out.status.code(), Some(2));
}

/// `choreod dance SONG --seed S` into `out` (10 steps: the test needs distinct generations, not
/// good ones).
fn dance(song: &Path, out: &Path, seed: u32) -> String {
    let o = run(&[
        "dance",
        song.to_str().expect("utf-8 path"),
        "-o",
        out.to_str().expect("utf-8 path"),
        "--seed",
        &seed.to_string(),
        "--steps",
        "10",
    ]);
    assert!(o.status.success(), "dance: {}", stderr(&o));
    out.display().to_string()
}

#[test]
fn multimodality_is_positive_for_distinct_generations_and_zero_for_equal_ones() {
    let d = tempfile::tempdir().expect("tmp");
    let audio = fixtures().join("audio");
    let vibe = audio.join("vibe_ace_22k_mono.ogg");
    let a = dance(&vibe, &d.path().join("a.h5"), 1);
    let b = dance(&vibe, &d.path().join("b.h5"), 2);
    let other = dance(
        &audio.join("hungarian_dance_5_44k_stereo.ogg"),
        &d.path().join("other.h5"),
        1,
    );
    let again = d.path().join("a_again.h5");
    std::fs::copy(&a, &again).expect("copy");
    let again = again.display().to_string();
    // Two generations of vibe_ace (grouped by the song's sha256 in their provenance) and one
    // of another song: the metric is the mean distance within vibe_ace's pair.
    let distinct = json(&["eval", &a, &b, &other, "--json"]);
    let mm = num(&distinct["set"]["multimodality_k"]);
    assert!(mm.is_finite() && mm > 0.0, "multimodality {mm}");
    // The same pair, identical: 0, while the set as a whole still differs (Div_k > 0), so the
    // grouping by song is what makes it 0.
    let equal = json(&["eval", &a, &again, &other, "--json"]);
    assert_eq!(num(&equal["set"]["multimodality_k"]), 0.0);
    assert!(num(&equal["set"]["div_k"]) > 0.0);
    // One generation per song: undefined, and the text says which metric it is.
    let single = json(&["eval", &a, &other, "--json"]);
    assert!(
        single["set"]["multimodality_k"].is_null(),
        "{}",
        single["set"]
    );
    let text = run(&["eval", &a, &b]);
    assert!(
        stdout(&text).contains("multimodality_k"),
        "{}",
        stdout(&text)
    );
}

#[test]
fn eval_reads_real_prep_shards_as_their_sequences() {
    // A small AIST++ tree in the official layout (the fixture motion, varied), prepared by
    // `choreod prep`, then scored straight from the shard directory.
    let d = tempfile::tempdir().expect("tmp");
    let fx = fixtures();
    let tree = d.path().join("aistpp");
    let synthetic = workspace_root().join("tests/tools/prep_synthetic.py");
    let out = python_cmd()
        .arg(&synthetic)
        .arg("aistpp")
        .arg(&tree)
        .arg("--pkl")
        .arg(fx.join("motion/aistpp_gBR_sBM_cAll_d04_mBR0_ch01.pkl"))
        .arg("--audio-dir")
        .arg(fx.join("audio"))
        .args(["--count", "3", "--music-ids", "1"])
        .output()
        .expect("run the venv python");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let shards = d.path().join("shards");
    let o = run(&[
        "prep",
        "aistpp",
        tree.to_str().expect("utf-8"),
        "-o",
        shards.to_str().expect("utf-8"),
    ]);
    assert!(o.status.success(), "prep: {}", stderr(&o));
    let shards_s = shards.display().to_string();
    let report = json(&["eval", &shards_s, "--json"]);
    let files = report["generated"].as_array().expect("generated");
    assert_eq!(files.len(), 3, "every sequence of every shard");
    // Each sequence scores as its joints60 dataset does on its own (read with h5py, written as
    // .npy, evaluated at 60 fps): the shard reader hands over exactly those frames.
    for f in files {
        let name = f["name"].as_str().expect("name");
        let (shard, seq) = name.rsplit_once(':').expect("SHARD:SEQUENCE");
        assert!(
            shard.ends_with(".h5") && shard.starts_with(&shards_s),
            "{name}"
        );
        let npy = d.path().join(format!("{seq}.npy"));
        py(
            "eval/shard_sequence_as_npy",
            &[shard, seq, npy.to_str().expect("utf-8")],
        );
        let alone = json(&[
            "eval",
            npy.to_str().expect("utf-8"),
            "--fps",
            "60",
            "--json",
        ]);
        let alone = &alone["generated"][0];
        for key in ["frames", "motion_beats"] {
            assert_eq!(f[key], alone[key], "{name}: {key}");
        }
        // The music beats prep stored with the sequence (frames at the shard's 30 fps) are
        // used: the same BAS as those beats given by hand as seconds.
        let beats = d.path().join(format!("{seq}.beats.txt"));
        py(
            "eval/shard_beats_as_seconds",
            &[shard, seq, beats.to_str().expect("utf-8")],
        );
        let by_hand = json(&[
            "eval",
            npy.to_str().expect("utf-8"),
            "--fps",
            "60",
            "--beats",
            beats.to_str().expect("utf-8"),
            "--json",
        ]);
        let by_hand = &by_hand["generated"][0];
        for key in ["bas_music_beats", "bas_motion_beats"] {
            assert_eq!(num(&f[key]), num(&by_hand[key]), "{name}: {key}");
        }
        assert_eq!(num(&f["fps"]), 60.0, "{name}");
        // Same frames, same code: equal to the last bit.
        for key in ["pfc", "skate_ratio", "foot_sliding_m"] {
            assert_eq!(num(&f[key]), num(&alone[key]), "{name}: {key}");
        }
    }
}

#[test]
fn music_that_is_not_a_motions_song_is_refused_naming_the_motion() {
    // A dance whose provenance names vibe_ace (by sha256), scored with --music hungarian_dance:
    // its BAS would be about the wrong song.
    let d = tempfile::tempdir().expect("tmp");
    let audio = fixtures().join("audio");
    let (own, other) = (
        audio.join("vibe_ace_22k_mono.ogg"),
        audio.join("hungarian_dance_5_44k_stereo.ogg"),
    );
    let mut motion = MotionFile::from_joints(60.0, SkeletonKind::Smpl24, base(0, 200));
    motion.provenance = Some(Provenance {
        source_name: "vibe_ace_22k_mono.ogg".into(),
        source_sha256: choreo_datasets::sha256_file(&own).expect("sha256"),
        ..Provenance::default()
    });
    let danced = d.path().join("danced.h5");
    write_motion_file(&danced, &motion).expect("write");
    let danced = danced.display().to_string();
    let (own, other) = (own.display().to_string(), other.display().to_string());
    let line = one_error_line(&run(&["eval", &danced, "--music", &other]));
    assert!(
        line.contains("danced.h5")
            && line.contains("vibe_ace_22k_mono.ogg")
            && line.contains("--any-music"),
        "{line}"
    );
    // Forced: scored, with a warning naming the motion.
    let out = run(&["eval", &danced, "--music", &other, "--any-music"]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(
        stderr(&out).contains("WARN") && stderr(&out).contains("danced.h5"),
        "{}",
        stderr(&out)
    );
    // Its own song, and a motion with no provenance (a capture), are scored without a word.
    let capture = write(d.path(), "capture.h5", base(50, 250));
    let out = run(&["eval", &danced, &capture, "--music", &own]);
    assert!(
        out.status.success() && !stderr(&out).contains("WARN"),
        "{}",
        stderr(&out)
    );
}

#[test]
fn diversity_of_two_self_scaled_motions_is_undefined_and_constant_reference_features_are_warned() {
    let d = tempfile::tempdir().expect("tmp");
    let g: Vec<String> = [0, 40, 80]
        .iter()
        .map(|&s| write(d.path(), &format!("g{s}.h5"), base(s, s + 200)))
        .collect();
    // Two motions z-scored with their own statistics are 2·√(features that differ) apart,
    // whatever they are: undefined, with the reason. Three give a number.
    let two = json(&["eval", &g[0], &g[1], "--json"]);
    for key in ["div_k", "div_g"] {
        let why = two["set"][key]["undefined"]
            .as_str()
            .unwrap_or_else(|| panic!("{key}: {}", two["set"][key]));
        assert!(why.contains("at least 3"), "{why}");
    }
    let three = json(&["eval", &g[0], &g[1], &g[2], "--json"]);
    assert!(num(&three["set"]["div_k"]) > 0.0);
    // A reference of three copies of one motion: no feature varies, FID divides by 1e-10.
    let refs: Vec<String> = (0..3)
        .map(|k| write(d.path(), &format!("r{k}.h5"), base(100, 300)))
        .collect();
    let mut args = vec![
        "eval",
        g[0].as_str(),
        g[1].as_str(),
        g[2].as_str(),
        "--reference",
    ];
    args.extend(refs.iter().map(String::as_str));
    let out = run(&args);
    assert!(out.status.success(), "{}", stderr(&out));
    let err = stderr(&out);
    assert!(
        err.contains(
            "kinetic features are the same in all 3 reference motions but not in the generated ones"
        ),
        "{err}"
    );
    // A varied reference: no warning.
    let varied: Vec<String> = [10, 50, 90]
        .iter()
        .map(|&s| write(d.path(), &format!("v{s}.h5"), base(s, s + 200)))
        .collect();
    let mut args = vec![
        "eval",
        g[0].as_str(),
        g[1].as_str(),
        g[2].as_str(),
        "--reference",
    ];
    args.extend(varied.iter().map(String::as_str));
    let out = run(&args);
    assert!(
        out.status.success() && !stderr(&out).contains("are the same in all"),
        "{}",
        stderr(&out)
    );
}
