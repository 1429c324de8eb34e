//! `choreod prep` (issue 6) on synthetic datasets in the official layouts, made at test time by
//! `tests/tools/prep_synthetic.py` from the fixture motion and music, corrupt members included.
//! Needs ffmpeg and the venv python (numpy, h5py), like the other h5py checks.
// The helpers below are test code too; clippy's allow-unwrap-in-tests covers only #[test] fns.
#![allow(clippy::unwrap_used)]

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use choreod_tests::{
    fails_with, fixtures, one_error_line, py, py_json, python_cmd, run, stderr, stdout,
    workspace_root,
};
use serde_json::Value;

const AIST_PKL: &str = "motion/aistpp_gBR_sBM_cAll_d04_mBR0_ch01.pkl";

struct Synth {
    _dir: tempfile::TempDir,
    aistpp: PathBuf,
    humanml3d: PathBuf,
}

fn run_python(args: &[&str]) {
    let out = python_cmd()
        .args(args)
        .output()
        .expect("run the venv python");
    assert!(
        out.status.success(),
        "python {args:?} failed:\n{}\n{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
}

/// The synthetic datasets, made once per test binary (read-only afterwards).
fn synth() -> &'static Synth {
    static S: OnceLock<Synth> = OnceLock::new();
    S.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let gen_script = workspace_root().join("tests/tools/prep_synthetic.py");
        let gen_script = gen_script.to_str().unwrap();
        let fx = fixtures();
        let aistpp = dir.path().join("aistpp");
        let humanml3d = dir.path().join("humanml3d");
        // 24 good AIST++ sequences of 6-14 s over 6 music ids, + 8 bad members.
        run_python(&[
            gen_script,
            "aistpp",
            aistpp.to_str().unwrap(),
            "--pkl",
            fx.join(AIST_PKL).to_str().unwrap(),
            "--audio-dir",
            fx.join("audio").to_str().unwrap(),
            "--count",
            "24",
            "--corrupt",
        ]);
        // HumanML3D from the fixture's SMPL joints (t2m = SMPL joints 0..21).
        let smpl = dir.path().join("smpl.npy");
        let out = run(&[
            "convert",
            fx.join(AIST_PKL).to_str().unwrap(),
            "-o",
            smpl.to_str().unwrap(),
        ]);
        assert!(out.status.success(), "{}", stderr(&out));
        run_python(&[
            gen_script,
            "humanml3d",
            humanml3d.to_str().unwrap(),
            "--smpl-joints",
            smpl.to_str().unwrap(),
            "--count",
            "40",
            "--corrupt",
        ]);
        Synth {
            _dir: dir,
            aistpp,
            humanml3d,
        }
    })
}

fn prep(args: &[&str]) -> String {
    let out = run(args);
    assert!(
        out.status.success(),
        "choreod {args:?}: {}\n{}",
        stderr(&out),
        stdout(&out)
    );
    stdout(&out)
}

/// `prep humanml3d` of the synthetic dataset into `out`, 8 sequences per shard, in one run.
fn humanml3d_whole(out: &Path) {
    prep(&[
        "prep",
        "humanml3d",
        s(&synth().humanml3d),
        "-o",
        s(out),
        "--per-shard",
        "8",
    ]);
}

fn manifest(dir: &Path, name: &str) -> Value {
    serde_json::from_str(&std::fs::read_to_string(dir.join(name)).unwrap()).unwrap()
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// sha256 of every `.h5` / `.npy` output, by file name (python hashlib: the tests crate has no
/// sha2 dependency and the value must match the manifest's independently).
fn digests(dir: &Path) -> BTreeMap<String, String> {
    let digests = py_json("prep/digests", &[s(dir)]);
    digests
        .as_object()
        .expect("file name -> sha256")
        .iter()
        .map(|(name, sha)| (name.clone(), sha.as_str().expect("hex").to_string()))
        .collect()
}

fn skip_reasons(m: &Value) -> BTreeMap<String, String> {
    m["skips"]
        .as_array()
        .unwrap()
        .iter()
        .map(|k| {
            (
                k["name"].as_str().unwrap().to_string(),
                k["reason"].as_str().unwrap().to_string(),
            )
        })
        .collect()
}

#[test]
fn aistpp_prep_writes_the_documented_layout_and_reports_every_skip() {
    let sy = synth();
    let out = tempfile::tempdir().unwrap();
    let text = prep(&[
        "prep",
        "aistpp",
        s(&sy.aistpp),
        "-o",
        s(out.path()),
        "--per-shard",
        "8",
        "--jobs",
        "2",
    ]);
    let m = manifest(out.path(), "manifest.json");
    assert_eq!(m["dataset"], "aistpp");
    assert_eq!(m["complete"], true);
    assert_eq!(m["files_found"], 32);
    let seqs: u64 = m["shards"]
        .as_array()
        .unwrap()
        .iter()
        .map(|e| e["sequences"].as_u64().unwrap())
        .sum();
    assert_eq!(seqs, 24, "{text}");
    let want: BTreeMap<String, String> = [
        ("gBR_sBM_cAll_d01_mBR0_ch9001", "corrupt"),
        ("gBR_sBM_cAll_d01_mBR0_ch9002", "non_finite"),
        ("gBR_sBM_cAll_d01_mBR0_ch9003", "too_short"),
        ("gBR_sBM_cAll_d01_mBR5_ch9004", "missing_music"),
        ("gBR_sBM_cAll_d01_mBR0_ch9005", "ignored"),
        ("gBR_sBM_cAll_d01_mBR0_ch9006", "not_in_split"),
        ("gBR_sBM_cAll_d01_mBR0_ch9007", "corrupt"),
        ("gKR_sBM_cAll_d01_mKR5_ch9008", "music_unreadable"),
    ]
    .into_iter()
    .map(|(a, b)| (a.to_string(), b.to_string()))
    .collect();
    assert_eq!(skip_reasons(&m), want);
    // The printed report names every skip with its reason.
    for (name, reason) in [
        ("ch9003", "too short"),
        ("ch9004", "missing music"),
        ("ch9005", "ignore list"),
    ] {
        assert!(
            text.lines().any(|l| l.contains(name) && l.contains(reason)),
            "{name}: {text}"
        );
    }
    assert_eq!(py_json("prep/aist_check", &[s(out.path())]), 24);

    // --shard 0/2 and 1/2 merged are the same bytes as the single run.
    let parts = tempfile::tempdir().unwrap();
    for i in 0..2 {
        prep(&[
            "prep",
            "aistpp",
            s(&sy.aistpp),
            "-o",
            s(parts.path()),
            "--per-shard",
            "8",
            "--shard",
            &format!("{i}/2"),
        ]);
    }
    assert!(parts.path().join("manifest.part-1-of-2.json").exists());
    let merged = tempfile::tempdir().unwrap();
    prep(&["prep", "merge", s(parts.path()), "-o", s(merged.path())]);
    assert_eq!(digests(merged.path()), digests(out.path()));
    let mm = manifest(merged.path(), "manifest.json");
    assert_eq!(skip_reasons(&mm), skip_reasons(&m));
    assert_eq!(mm["shards"], m["shards"]);
}

#[test]
fn aistpp_prep_writes_the_fact35_features_the_features_verb_computes() {
    let sy = synth();
    let out = tempfile::tempdir().unwrap();
    prep(&[
        "prep",
        "aistpp",
        s(&sy.aistpp),
        "-o",
        s(out.path()),
        "--per-shard",
        "8",
        "--features",
        "fact35",
        "--librosa",
        "0.10",
    ]);
    // The verb on each music file, its BPM given as the music id says (prep's start BPM).
    let feats = tempfile::tempdir().unwrap();
    for entry in std::fs::read_dir(sy.aistpp.join("music")).unwrap() {
        let wav = entry.unwrap().path();
        let id = wav.file_stem().unwrap().to_str().unwrap().to_string();
        let Some(bpm) = choreo_datasets::prep::bpm_from_music_id(&id) else {
            continue;
        };
        let npy = feats.path().join(format!("{id}.npy"));
        let out = run(&[
            "features",
            s(&wav),
            "-o",
            s(&npy),
            "--set",
            "fact35",
            "--librosa",
            "0.10",
            "--start-bpm",
            &bpm.to_string(),
        ]);
        // The synthetic set's undecodable track (mKR5) has no features and no sequence.
        assert!(
            out.status.success() || id == "mKR5",
            "{id}: {}",
            stderr(&out)
        );
    }
    let ok = py(
        "prep/fact35_check",
        &[s(out.path()), s(feats.path()), "0.10.1"],
    );
    assert_eq!(ok, "ok 24 sequences");
    // The set's librosa needs the set.
    let out = run(&[
        "prep",
        "aistpp",
        s(&sy.aistpp),
        "-o",
        s(out.path()),
        "--librosa",
        "0.10",
    ]);
    assert_eq!(out.status.code(), Some(2), "{}", stderr(&out));
}

#[test]
fn humanml3d_prep_with_mirror_writes_features_captions_and_grouped_std() {
    let sy = synth();
    let out = tempfile::tempdir().unwrap();
    let text = prep(&[
        "prep",
        "humanml3d",
        s(&sy.humanml3d),
        "-o",
        s(out.path()),
        "--mirror",
        "--per-shard",
        "16",
    ]);
    let m = manifest(out.path(), "manifest.json");
    assert_eq!(m["complete"], true, "{text}");
    let reasons = skip_reasons(&m);
    for (id, r) in [
        ("900001", "corrupt"),
        ("900002", "non_finite"),
        ("900003", "too_short"),
        ("900004", "corrupt"),
        ("900006", "not_in_split"),
        ("900007", "missing_motion"),
    ] {
        assert_eq!(
            reasons.get(id).map(String::as_str),
            Some(r),
            "{id}: {reasons:?}"
        );
    }
    assert!(
        !reasons.contains_key("900005"),
        "a missing caption file is not a skip"
    );
    assert!(
        !reasons.contains_key("M000000"),
        "a listed M id is made by --mirror: {reasons:?}"
    );
    assert!(text.contains("1 missing motion file"), "{text}");
    assert!(text.contains("no texts"), "{text}");
    // 40 good + 900005, each with its M copy.
    assert_eq!(py_json("prep/hml_check", &[s(out.path())]), 82);
}

#[test]
fn humanml3d_parts_merged_equal_the_single_run_including_mean_std() {
    let sy = synth();
    let whole = tempfile::tempdir().unwrap();
    humanml3d_whole(whole.path());
    let dirs: Vec<tempfile::TempDir> = (0..3).map(|_| tempfile::tempdir().unwrap()).collect();
    for (i, d) in dirs.iter().enumerate() {
        let t = prep(&[
            "prep",
            "humanml3d",
            s(&sy.humanml3d),
            "-o",
            s(d.path()),
            "--per-shard",
            "8",
            "--shard",
            &format!("{i}/3"),
        ]);
        assert!(
            !d.path().join("Mean.npy").exists(),
            "a part must not write Mean/Std: {t}"
        );
    }
    // Merging an incomplete set is refused.
    let bad = run(&[
        "prep",
        "merge",
        s(dirs[0].path()),
        s(dirs[1].path()),
        "-o",
        s(&dirs[0].path().join("m")),
    ]);
    let line = one_error_line(&bad);
    assert!(line.contains("planned shards"), "{line}");
    let merged = tempfile::tempdir().unwrap();
    let mut args = vec!["prep", "merge"];
    args.extend(dirs.iter().map(|d| s(d.path())));
    args.extend(["-o", s(merged.path())]);
    prep(&args);
    let a = digests(whole.path());
    assert!(a.contains_key("Mean.npy") && a.contains_key("train-00000.h5"));
    assert_eq!(digests(merged.path()), a);
    // A shard damaged after its part finished (same size, one byte flipped) is caught.
    let victim = std::fs::read_dir(dirs[1].path())
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .find(|p| p.extension().is_some_and(|x| x == "h5"))
        .unwrap();
    let mut bytes = std::fs::read(&victim).unwrap();
    let mid = bytes.len() / 2;
    bytes[mid] ^= 0x55;
    std::fs::write(&victim, bytes).unwrap();
    let mut args = vec!["prep", "merge"];
    args.extend(dirs.iter().map(|d| s(d.path())));
    let again = merged.path().join("again");
    args.extend(["-o", s(&again)]);
    let line = one_error_line(&run(&args));
    assert!(line.contains("sha256"), "{line}");
}

#[test]
fn an_interrupted_run_resumes_and_ends_identical_to_a_clean_run() {
    let sy = synth();
    let clean = tempfile::tempdir().unwrap();
    humanml3d_whole(clean.path());
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let t = prep(&[
        "prep",
        "humanml3d",
        s(&sy.humanml3d),
        "-o",
        s(d),
        "--per-shard",
        "8",
        "--max-shards",
        "2",
        "--jobs",
        "1",
    ]);
    assert!(t.contains("incomplete"), "{t}");
    let m = manifest(d, "manifest.json");
    assert_eq!(m["complete"], false);
    assert_eq!(m["shards"].as_array().unwrap().len(), 2);
    assert!(!d.join("Mean.npy").exists());
    // What a kill leaves behind: a temporary being written, and a renamed shard whose sidecar
    // was never written (a torn copy).
    std::fs::write(d.join(".train-00003.h5.tmp-4242"), b"partial").unwrap();
    let done: Vec<String> = m["shards"]
        .as_array()
        .unwrap()
        .iter()
        .map(|e| e["file"].as_str().unwrap().to_string())
        .collect();
    let victim = [
        "train-00000.h5",
        "train-00001.h5",
        "train-00002.h5",
        "train-00003.h5",
    ]
    .into_iter()
    .find(|f| !done.contains(&f.to_string()))
    .unwrap();
    std::fs::write(d.join(victim), b"not hdf5").unwrap();
    let t = prep(&[
        "prep",
        "humanml3d",
        s(&sy.humanml3d),
        "-o",
        s(d),
        "--per-shard",
        "8",
    ]);
    assert!(t.contains("2 kept"), "{t}");
    assert!(
        !d.join(".train-00003.h5.tmp-4242").exists(),
        "stale temporary left behind"
    );
    assert_eq!(manifest(d, "manifest.json")["complete"], true);
    assert_eq!(digests(d), digests(clean.path()));
    // A third run has nothing to do.
    let t = prep(&[
        "prep",
        "humanml3d",
        s(&sy.humanml3d),
        "-o",
        s(d),
        "--per-shard",
        "8",
    ]);
    assert!(t.contains("(0 written now"), "{t}");
}

#[test]
fn a_run_killed_with_sigkill_leaves_no_shard_that_looks_complete_and_resumes() {
    let sy = synth();
    let clean = tempfile::tempdir().unwrap();
    let args = |out: &Path| -> Vec<String> {
        [
            "prep",
            "humanml3d",
            s(&sy.humanml3d),
            "-o",
            s(out),
            "--mirror",
            "--per-shard",
            "1",
            "--jobs",
            "1",
        ]
        .iter()
        .map(|a| a.to_string())
        .collect()
    };
    prep(
        &args(clean.path())
            .iter()
            .map(String::as_str)
            .collect::<Vec<_>>(),
    );
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let mut child = choreod_tests::choreod()
        .args(args(d))
        .stdout(std::process::Stdio::null())
        .spawn()
        .unwrap();
    // 82 one-sequence shards, each fsynced: kill once a few are done, well before the end.
    let sidecars = || {
        std::fs::read_dir(d)
            .map(|rd| {
                rd.flatten()
                    .filter(|e| e.file_name().to_string_lossy().ends_with(".h5.json"))
                    .count()
            })
            .unwrap_or(0)
    };
    let t0 = std::time::Instant::now();
    while sidecars() < 3 && t0.elapsed() < std::time::Duration::from_secs(120) {
        std::thread::sleep(std::time::Duration::from_millis(2));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    assert!(
        !d.join("manifest.json").exists(),
        "the run finished before the kill; the test proves nothing"
    );
    // Every shard with a sidecar is complete: its bytes are what the sidecar says.
    let dig = digests(d);
    let mut complete = 0;
    for e in std::fs::read_dir(d).unwrap().flatten() {
        let n = e.file_name().to_string_lossy().into_owned();
        if let Some(shard) = n.strip_suffix(".json").filter(|x| x.ends_with(".h5")) {
            let sc: Value =
                serde_json::from_str(&std::fs::read_to_string(e.path()).unwrap()).unwrap();
            assert_eq!(
                dig.get(shard),
                sc["shard"]["sha256"].as_str().map(str::to_string).as_ref(),
                "{shard}"
            );
            complete += 1;
        }
    }
    assert!((3..82).contains(&complete), "{complete}");
    let t = prep(&args(d).iter().map(String::as_str).collect::<Vec<_>>());
    assert!(t.contains(&format!("{complete} kept")), "{t}");
    assert_eq!(digests(d), digests(clean.path()));
}

#[test]
fn fatal_problems_are_one_error_line() {
    let sy = synth();
    let out = tempfile::tempdir().unwrap();
    let missing = run(&["prep", "aistpp", "/nonexistent/aist", "-o", s(out.path())]);
    let line = one_error_line(&missing);
    assert!(line.contains("/nonexistent/aist"), "{line}");
    assert_eq!(missing.status.code(), Some(1));
    // Reusing an output directory with other parameters would mix datasets.
    prep(&[
        "prep",
        "humanml3d",
        s(&sy.humanml3d),
        "-o",
        s(out.path()),
        "--per-shard",
        "16",
    ]);
    let other = run(&[
        "prep",
        "humanml3d",
        s(&sy.humanml3d),
        "-o",
        s(out.path()),
        "--per-shard",
        "16",
        "--mirror",
    ]);
    let line = one_error_line(&other);
    assert!(line.contains("different parameters"), "{line}");
    let bad_shard = run(&[
        "prep",
        "humanml3d",
        s(&sy.humanml3d),
        "-o",
        s(out.path()),
        "--shard",
        "3/3",
    ]);
    assert!(one_error_line(&bad_shard).contains("3/3"));
}

#[test]
fn merge_refuses_shards_that_point_outside_themselves() {
    let out = tempfile::tempdir().unwrap();
    humanml3d_whole(out.path());
    // Turn train-00000's Mean/Std share into an external link to another file, and make the
    // manifest vouch for the changed shard (size and sha256), as a hostile part could.
    py("prep/external_link_share", &[s(out.path())]);
    let merged = tempfile::tempdir().unwrap();
    let line = one_error_line(&run(&[
        "prep",
        "merge",
        s(out.path()),
        "-o",
        s(merged.path()),
    ]));
    assert!(
        line.contains(
            "train-00000.h5: '/_stats/sum': an external or user-defined link is not accepted"
        ),
        "{line}"
    );
    assert!(!merged.path().join("Mean.npy").exists());
}

#[test]
fn prep_with_no_surviving_sequence_says_what_was_skipped() {
    let d = tempfile::tempdir().unwrap();
    let root = d.path().join("hml");
    py(
        "prep/prep_with_no_surviving_sequence_says_what_was_skipped",
        &[s(&root)],
    );
    let out_dir = d.path().join("out");
    let out = run(&["prep", "humanml3d", s(&root), "-o", s(&out_dir)]);
    let line = fails_with(
        &out,
        1,
        &[
            "no sequence survived: 2 skipped (2 too short)",
            "manifest.json",
        ],
    );
    assert!(!line.contains("mean/std"), "{line}");
    // The manifest it points to lists them.
    let manifest = std::fs::read_to_string(out_dir.join("manifest.json")).unwrap();
    assert!(
        manifest.contains("000001") && manifest.contains("too_short"),
        "{manifest}"
    );
    assert!(stdout(&out).is_empty() || !stdout(&out).contains("Mean.npy"));
}
