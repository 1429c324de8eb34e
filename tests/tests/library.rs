//! The bundled `library` package end to end (issue 24): different songs get different dances,
//! the provenance names the library clips a dance used with their attribution, `--seed` still
//! decides the dance, and quiet steady music gets a calm, even dance. Build first:
//! `cargo build --release -p choreod`.

use std::path::{Path, PathBuf};

use ndarray::{Axis, s};

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

/// A click track: a 1 kHz blip every 2/3 s (90 BPM) for 40 s at `amplitude` (sox).
fn clicks_90_bpm(out: &Path, amplitude: &str) {
    let status = std::process::Command::new("sox")
        .args(["-n", "-r", "22050", "-c", "1"])
        .arg(out)
        .args(["synth", "0.08", "sine", "1000", "fade", "0", "0.08", "0.07"])
        .args(["vol", amplitude, "pad", "0.25", "0.3367", "repeat", "59"])
        .status()
        .expect("sox (installed by scripts/setup)");
    assert!(status.success());
}

/// Mean joint speed (m/s) of each whole 2.5 s window of a dance, the first one skipped (the
/// dance starts from rest).
fn window_speeds(path: &Path) -> Vec<f64> {
    let m = choreo_datasets::read_motion_file(path).expect("read motion file");
    let j = m.joints.mapv(f64::from);
    let steps = &j.slice(s![1.., .., ..]) - &j.slice(s![..-1, .., ..]);
    // Per frame step: the joints' mean distance moved, times the frame rate.
    let speed = steps
        .map_axis(Axis(2), |d| d.dot(&d).sqrt())
        .mean_axis(Axis(1))
        .expect("joints")
        * f64::from(m.fps);
    let stride = (2.5 * m.fps).round() as usize;
    speed
        .as_slice()
        .expect("contiguous")
        .chunks_exact(stride)
        .skip(1)
        .map(|w| w.iter().sum::<f64>() / w.len() as f64)
        .collect()
}

/// Quiet steady music gets a calm, even dance: 90 BPM clicks at -30 dBFS, every 2.5 s window
/// within 1.25x of every other (scripts/bench-library's reaction counts 1.25x as a change, so a
/// steady song must not vary that much by itself) and slower than the same clicks loud (-3 dB).
/// Measured: the quiet dance 0.39-0.42 m/s per window (the package without its calm gate
/// 0.44-0.79, 1.78x), the loud one 0.95-1.07.
#[test]
fn quiet_steady_music_is_danced_calmly_and_evenly() {
    let d = tempfile::tempdir().expect("temporary folder");
    let (quiet, loud) = (d.path().join("quiet.wav"), d.path().join("loud.wav"));
    clicks_90_bpm(&quiet, "0.0316");
    clicks_90_bpm(&loud, "0.7");
    let (qd, ld) = (d.path().join("quiet.h5"), d.path().join("loud.h5"));
    dance(&quiet, &qd, "0");
    dance(&loud, &ld, "0");
    let (q, l) = (window_speeds(&qd), window_speeds(&ld));
    assert!(q.len() >= 12, "{} windows", q.len());
    let (lo, hi) = q
        .iter()
        .fold((f64::MAX, 0.0f64), |(a, b), &v| (a.min(v), b.max(v)));
    assert!(
        hi / lo <= 1.25,
        "quiet clicks danced unevenly: windows {lo:.2}-{hi:.2} m/s ({:.2}x)",
        hi / lo
    );
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    assert!(
        mean(&q) < 0.8 * mean(&l),
        "quiet clicks {:.2} m/s, loud {:.2}: not calmer",
        mean(&q),
        mean(&l)
    );
}
