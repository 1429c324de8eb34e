//! Music analysis end to end: `choreod mel`, `choreod beats` and `choreod features`.

use choreod_tests::{choreod, fixtures, one_error_line, py, run, stdout};

fn reference(name: &str) -> std::path::PathBuf {
    fixtures().join("reference").join(name)
}

#[test]
fn mel_writes_a_numpy_loadable_librosa_matching_array_and_stats() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("m.npy");
    let audio = fixtures().join("audio").join("vibe_ace_44k_stereo.ogg");
    let o = run(&[
        "mel",
        audio.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--stats",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let text = stdout(&o);
    let lines: Vec<&str> = text.lines().collect();
    assert_eq!(lines.len(), 1, "--stats prints one JSON line: {text}");
    let stats: serde_json::Value = serde_json::from_str(lines[0]).unwrap();
    for key in ["decode_s", "resample_s", "mel_s", "total_s"] {
        assert!(
            stats[key].as_f64().is_some_and(|v| v >= 0.0),
            "{key} in {text}"
        );
    }
    assert_eq!(stats["frames"], 1921);
    // numpy loads it; the values match librosa's (same bound as the dsp parity test: mean
    // |Δ| ≤ 0.1 dB end to end; decoder/resampler differences sit near the noise floor).
    py(
        "music/mel_matches_librosa",
        &[
            out.to_str().unwrap(),
            reference("vibe_ace_44k_stereo.logmel.npy")
                .to_str()
                .unwrap(),
        ],
    );
}

#[test]
fn mel_flags_change_the_shape() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("m.npy");
    let audio = fixtures().join("audio").join("vibe_ace_22k_mono.ogg");
    let o = run(&[
        "mel",
        audio.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--n-mels",
        "40",
        "--hop",
        "256",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let bytes = std::fs::read(&out).unwrap();
    let header = String::from_utf8_lossy(&bytes[10..128]);
    assert!(header.contains("'shape': (40, "), "{header}");
}

#[test]
fn mel_errors_are_one_line_naming_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("m.npy");
    let missing = dir.path().join("missing.ogg");
    let line = one_error_line(&run(&[
        "mel",
        missing.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
    ]));
    assert!(line.contains("missing.ogg"), "{line}");
    let empty = dir.path().join("empty.wav");
    std::fs::write(&empty, b"").unwrap();
    let line = one_error_line(&run(&[
        "mel",
        empty.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
    ]));
    assert!(
        line.contains("empty.wav") && line.contains("empty"),
        "{line}"
    );
    let long = fixtures().join("audio").join("vibe_ace_22k_mono.ogg");
    let line = one_error_line(&run(&[
        "mel",
        long.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--max-duration",
        "2",
    ]));
    assert!(
        line.contains("longer than the limit of 2 s (--max-duration)"),
        "{line}"
    );
    assert!(!out.exists(), "no output on failure");
}

#[test]
fn beats_prints_tempo_and_times() {
    let audio = fixtures()
        .join("audio")
        .join("hungarian_dance_5_44k_stereo.ogg");
    let o = run(&["beats", audio.to_str().unwrap(), "--json"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let v: serde_json::Value = serde_json::from_str(stdout(&o).trim()).unwrap();
    let tempo = v["tempo_bpm"].as_f64().unwrap();
    let times: Vec<f64> = v["beat_times_s"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| t.as_f64().unwrap())
        .collect();
    assert!(tempo > 40.0 && tempo < 320.0, "{tempo}");
    // The check `dance` makes for input that is not music: the rubato fixture has a beat.
    assert_eq!(v["beat"], "steady", "{v}");
    assert!(v["beat_periodicity"].as_f64().unwrap() >= choreo_dsp::MIN_PERIODICITY);
    assert!(
        times.len() > 10 && times.windows(2).all(|w| w[1] > w[0]),
        "{times:?}"
    );
    let text = run(&["beats", audio.to_str().unwrap()]);
    assert!(stdout(&text).starts_with("tempo "), "{}", stdout(&text));
}

/// A reader that stops early (`choreod beats song | head -1`) closes the pipe: that is the
/// reader's choice, not a bug in choreod (exit 101) — `println!` panicked on EPIPE here.
#[test]
fn beats_into_a_closed_pipe_is_not_an_error() {
    let audio = fixtures().join("audio").join("vibe_ace_44k_stereo.ogg");
    let mut child = choreod()
        .args(["beats", audio.to_str().unwrap()])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("spawn choreod");
    // Closed before choreod has decoded the song, so its first write meets EPIPE.
    drop(child.stdout.take());
    let o = child.wait_with_output().unwrap();
    assert!(
        o.status.success(),
        "{:?}: {}",
        o.status,
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(
        o.stderr.is_empty(),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
}

/// `choreod features --set fact35` as a user runs it, for both reference librosas: the written
/// `.npy` equals the golden features librosa itself made from the same FLAC (dsp's fixtures;
/// the bounds are dsp's: continuous columns within 1e-3 of their range, one-hot columns
/// identical), and the two versions give different arrays (0.10 pads, resamples and folds chroma
/// differently).
#[test]
fn features_writes_librosas_own_numbers_for_each_version() {
    let dir = tempfile::tempdir().unwrap();
    let golden = choreod_tests::workspace_root().join("dsp/tests/golden/fact35");
    let audio = golden.join("beat_vibe_ace.flac");
    let mut outs = Vec::new();
    for (flag, tag) in [("0.7", "lr07"), ("0.10", "lr010")] {
        let out = dir.path().join(format!("{tag}.npy"));
        let o = run(&[
            "features",
            audio.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
            "--set",
            "fact35",
            "--librosa",
            flag,
        ]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let golden_features = golden.join(format!("beat_vibe_ace_30_{tag}.npz"));
        eprintln!("--librosa {flag}:");
        py(
            "music/features_match_golden",
            &[out.to_str().unwrap(), golden_features.to_str().unwrap()],
        );
        outs.push(std::fs::read(&out).unwrap());
    }
    assert_ne!(outs[0], outs[1], "the two versions gave the same bytes");
}

#[test]
fn features_refuses_rates_the_field_does_not_use_as_a_usage_error() {
    let dir = tempfile::tempdir().unwrap();
    let audio = fixtures().join("audio").join("vibe_ace_44k_stereo.ogg");
    let out = dir.path().join("f.npy");
    let o = run(&[
        "features",
        audio.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--set",
        "fact35",
        "--fps",
        "45",
    ]);
    assert_eq!(
        o.status.code(),
        Some(2),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(String::from_utf8_lossy(&o.stderr).contains("30 or 60 fps"));
    assert!(!out.exists());
}
