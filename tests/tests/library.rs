//! The bundled `library` package end to end (issue 24): different songs get different dances,
//! the provenance names the library clips a dance used with their attribution, and `--seed`
//! still decides the dance. Build first: `cargo build --release -p choreod`.

use std::path::{Path, PathBuf};

use choreod_tests::{fixtures, py_json, run, stderr};

/// `choreod dance SONG -o OUT --seed SEED` with the bundled default package.
fn dance(song: &Path, out: &Path, seed: &str) {
    let result = run(&[
        "dance",
        song.to_str().expect("utf-8 path"),
        "-o",
        out.to_str().expect("utf-8 path"),
        "--seed",
        seed,
    ]);
    assert!(result.status.success(), "{}", stderr(&result));
}

fn song(name: &str) -> PathBuf {
    fixtures().join("audio").join(name)
}

/// The pose overlap of dance `a` against dance `b` and both provenance `library` lines
/// (tests/py/dance/pose_overlap.py).
fn overlap(a: &Path, b: &Path) -> serde_json::Value {
    py_json(
        "dance/pose_overlap",
        &[
            a.to_str().expect("utf-8 path"),
            b.to_str().expect("utf-8 path"),
        ],
    )
}

/// A pop song and a string orchestra: with the old default (one AIST++ loop retimed) 91 % of
/// the pop song's frames lie within 3 cm of a pose of the orchestra's dance (issue 24 measured
/// 0.89-1.0 on eight inputs). The library's dances share at most half their poses (issue 24's
/// target 0.5; measured in BENCHMARKS.md, "library"). Both files name the library clips they
/// were played from and carry the CMU acknowledgement and the AIST++ attribution.
#[test]
fn different_songs_get_different_dances_named_in_their_provenance() {
    let d = tempfile::tempdir().expect("temporary folder");
    let (pop, strings) = (d.path().join("pop.h5"), d.path().join("strings.h5"));
    dance(&song("vibe_ace_44k_stereo.ogg"), &pop, "0");
    dance(&song("hungarian_dance_5_44k_stereo.ogg"), &strings, "0");
    let m = overlap(&pop, &strings);
    let share = m["overlap"].as_f64().expect("overlap number");
    assert!(
        share <= 0.5,
        "pose overlap between the two songs' dances {share:.2} > 0.5"
    );
    for key in ["library_a", "library_b"] {
        let line = m[key]
            .as_str()
            .unwrap_or_else(|| panic!("no provenance library: {m}"));
        assert!(
            line.starts_with("clips used: ") && !line.contains("not identified"),
            "{line}"
        );
        assert!(
            line.contains("cmu_") || line.contains("aistpp_"),
            "no library clip named: {line}"
        );
        assert!(
            line.contains("mocap.cs.cmu.edu")
                && line.contains("NSF EIA-0196217")
                && line.contains("AIST++")
                && line.contains("CC BY 4.0"),
            "attribution missing: {line}"
        );
    }
    assert_ne!(
        m["library_a"], m["library_b"],
        "both songs danced from the same clips"
    );
}

/// Same song and seed: the same dance, bit for bit; another seed: another dance (the softmax
/// over the library's candidates is sampled by the sampler's noise).
#[test]
fn the_seed_decides_the_dance() {
    let d = tempfile::tempdir().expect("temporary folder");
    let clip = d.path().join("clip.ogg");
    let status = std::process::Command::new("sox")
        .arg(song("vibe_ace_44k_stereo.ogg"))
        .arg(&clip)
        .args(["trim", "20", "15"])
        .status()
        .expect("sox (installed by scripts/setup)");
    assert!(status.success());
    let (a, b, c) = (
        d.path().join("a.h5"),
        d.path().join("b.h5"),
        d.path().join("c.h5"),
    );
    dance(&clip, &a, "3");
    dance(&clip, &b, "3");
    dance(&clip, &c, "4");
    let joints = |p: &Path| {
        choreo_datasets::read_motion_file(p)
            .expect("read motion file")
            .joints
    };
    assert_eq!(joints(&a), joints(&b), "same seed, different dance");
    let m = overlap(&a, &c);
    let share = m["overlap"].as_f64().expect("overlap number");
    // Seeds pick other segments or other beats of them: most frames move away by more than 3 cm.
    assert!(share < 0.5, "seeds 3 and 4 share {share:.2} of their poses");
}
