//! `choreod dance` end to end: the file, the stats and the windows it writes, given noise,
//! refused packages and options, a missing output folder, a dance that is not a body, and
//! what the bundled package gives a long song, measured as a viewer would notice it.
//! Build first: `cargo build --release -p choreod`.

use std::process::Command;

use choreod_tests::{
    choreod, fixtures, not_music, one_error_line, py, run, stderr, stdout, workspace_root,
};

/// A song of 2.5 minutes made from the shared fixtures (Hungarian Dance No. 5, Vibe Ace,
/// Hungarian Dance No. 5 again: 153 s, 61 windows), so that many windows are stitched,
/// including those across the changes of music where neighbouring windows disagree most.
fn long_song(dir: &std::path::Path) -> std::path::PathBuf {
    let audio = fixtures().join("audio");
    let (hungarian, vibe) = (
        audio.join("hungarian_dance_5_44k_stereo.ogg"),
        audio.join("vibe_ace_44k_stereo.ogg"),
    );
    let song = dir.join("long.ogg");
    let status = Command::new("sox")
        .args([&hungarian, &vibe, &hungarian, &song])
        .status()
        .expect("sox (installed by scripts/setup)");
    assert!(status.success(), "sox could not join the fixtures");
    song
}

/// Issue 24: at the stitches between windows a bone turned by up to 140° in 1/30 s (the
/// per-bone slerp folded an elbow where two windows' forearms were ~170° apart). Every bone's
/// largest turn between two frames must stay near what the bundled package's own source dance
/// does (its windows replay it up to ~1.24x faster) and within the 60° whatever the
/// package (the bundled library's source clips turn a bone by up to 84° per frame at 30 fps in
/// flips and capture glitches, which the package never plays, so 60° is the bound; the AIST++
/// loop of `exemplar`: 21.7°, so 26.9°); every frame a rigid skeleton; toes never below the
/// floor. With the library, the song's 61 windows cross a chunk border (32 windows), where a
/// window that does not continue its predecessor used to jump (a 137° turn).
#[test]
fn a_long_song_is_danced_without_snaps_between_windows() {
    let d = tempfile::tempdir().unwrap();
    let song = long_song(d.path());
    let out = d.path().join("long.h5");
    let result = run(&["dance", song.to_str().unwrap(), "-o", out.to_str().unwrap()]);
    assert!(result.status.success(), "{}", stderr(&result));
    let source = workspace_root().join("models/packages/library-source");
    py(
        "dance/no_snaps_between_windows",
        &[out.to_str().unwrap(), source.to_str().unwrap()],
    );
}

/// `choreod dance` on the bundled clip with the bundled model; returns the `--stats` JSON.
fn dance(out: &std::path::Path, extra: &[&str]) -> serde_json::Value {
    let song = workspace_root().join("daemon/assets/audio/vibe_ace_44k_stereo.ogg");
    let mut args = vec![
        "dance",
        song.to_str().expect("test setup"),
        "-o",
        out.to_str().expect("test setup"),
        "--stats",
    ];
    args.extend_from_slice(extra);
    let result = run(&args);
    assert!(
        result.status.success(),
        "choreod {args:?}: {}",
        choreod_tests::stderr(&result)
    );
    assert!(out.is_file());
    let line = stdout(&result);
    // scripts/bench-lodge finds the line by its first key.
    assert!(line.starts_with("{\"decode_s\""), "{line}");
    serde_json::from_str(line.trim()).expect("one JSON line on stdout")
}

#[test]
fn dance_writes_the_file_the_stats_and_the_windows() {
    let d = tempfile::tempdir().unwrap();
    let (h5, windows) = (d.path().join("a.h5"), d.path().join("w.npy"));
    let w = windows.to_str().unwrap();
    let stats = dance(
        &h5,
        &[
            "--steps",
            "6",
            "--sampler",
            "dpmsolver++",
            "--save-windows",
            w,
        ],
    );
    let num = |k: &str| {
        stats[k]
            .as_f64()
            .unwrap_or_else(|| panic!("{k} in {stats}"))
    };
    for key in [
        "decode_s",
        "resample_s",
        "mel_s",
        "features_total_s",
        "generate_s",
        "ort_s",
        "write_s",
        "total_s",
        "realtime_factor",
    ] {
        assert!(num(key) >= 0.0, "{key} in {stats}");
    }
    // The clip is 61.5 s (decoded), 30 fps; windows of 150 frames every 75.
    let audio_s = num("audio_s");
    assert!((audio_s - 61.5).abs() < 0.1, "{stats}");
    let frames = (audio_s * 30.0).round();
    assert_eq!(num("frames"), frames);
    assert_eq!(num("fps"), 30.0);
    let windows_n = ((frames - 150.0) / 75.0).ceil() + 1.0;
    assert_eq!(num("windows"), windows_n);
    assert_eq!(num("steps"), 6.0);
    // One chunk (32 windows), guidance off: one network call per step.
    assert_eq!(num("network_evaluations"), 6.0);
    assert_eq!(num("batch_rows"), 6.0 * windows_n);
    assert!(num("total_s") >= num("generate_s") && num("generate_s") >= num("ort_s"));
    // The package's music-only work is hoisted: its prologue runs once for the one chunk's
    // sampling, and once more for the library's `source` read after it (t = 0, one call).
    assert_eq!(num("prologue_runs"), 2.0);
    // Where ORT's time went: the one network, its 6 steps plus the `source` read, the hoisted
    // prologue's share inside its seconds, all of it within generation.
    let components = stats["components"].as_array().expect("components");
    assert_eq!(components.len(), 1, "{stats}");
    let denoiser = &components[0];
    assert_eq!(denoiser["role"], "denoiser", "{stats}");
    assert_eq!(denoiser["runs"], 7, "{stats}");
    assert_eq!(denoiser["prologue_runs"], 2, "{stats}");
    let seconds = denoiser["seconds"].as_f64().unwrap();
    let prologue = denoiser["prologue_seconds"].as_f64().unwrap();
    assert!(prologue > 0.0 && prologue < seconds, "{stats}");
    assert!((seconds - num("ort_s")).abs() < 1e-6, "{stats}");
    py(
        "dance/dance_writes_the_file_the_stats_and_the_windows",
        &[
            h5.to_str().unwrap(),
            w,
            &format!("{frames}"),
            &format!("{windows_n}"),
        ],
    );
}

/// A package of another task is refused before any work: exit 4, one line naming the task.
#[test]
fn dance_with_a_style_transfer_package_exits_4() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("x.h5");
    let song = workspace_root().join("daemon/assets/audio/vibe_ace_44k_stereo.ogg");
    let model = workspace_root().join("models/packages/style-gaussian");
    let result = run(&[
        "dance",
        song.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
        "--model",
        model.to_str().unwrap(),
    ]);
    assert_eq!(result.status.code(), Some(4));
    let line = choreod_tests::one_error_line(&result);
    assert!(
        line.contains("style-gaussian")
            && line.contains("task: is style-transfer, this needs a music-to-dance package"),
        "{line}"
    );
    assert!(!out.exists());
}

/// `--eta` only moves DDIM: with another sampler (given, or the package's) it is refused, not
/// silently ignored.
#[test]
fn eta_with_a_sampler_other_than_ddim_is_refused() {
    let d = tempfile::tempdir().unwrap();
    let out = d.path().join("x.h5");
    let song = workspace_root().join("daemon/assets/audio/vibe_ace_44k_stereo.ogg");
    for sampler in ["ddpm", "dpmsolver++"] {
        let result = run(&[
            "dance",
            song.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
            "--sampler",
            sampler,
            "--eta",
            "0.5",
        ]);
        assert_eq!(result.status.code(), Some(1), "{sampler}");
        let line = choreod_tests::one_error_line(&result);
        assert!(
            line.contains("--eta applies to the ddim sampler only") && line.contains(sampler),
            "{line}"
        );
        assert!(!out.exists());
    }
}

#[test]
fn dance_from_given_noise_is_a_function_of_the_noise() {
    let d = tempfile::tempdir().unwrap();
    let noise = d.path().join("xT.npy");
    let (n, a, b) = (
        noise.to_str().unwrap(),
        d.path().join("a.h5"),
        d.path().join("b.h5"),
    );
    py("dance/noise", &[n]);
    // Deterministic DDIM, chunks of 4 windows (so chunk borders are in-painted too): the seed
    // no longer matters.
    let common = [
        "--steps",
        "5",
        "--eta",
        "0",
        "--chunk-windows",
        "4",
        "--init-noise",
        n,
    ];
    dance(&a, &[&common[..], &["--seed", "1"]].concat());
    dance(&b, &[&common[..], &["--seed", "2"]].concat());
    py(
        "dance/dance_from_given_noise_is_a_function_of_the_noise",
        &[a.to_str().unwrap(), b.to_str().unwrap(), n],
    );
    // Noise of the wrong shape: one line naming it, nothing written.
    py("dance/noise_of_the_wrong_shape", &[n]);
    let c = d.path().join("c.h5");
    let song = workspace_root().join("daemon/assets/audio/vibe_ace_44k_stereo.ogg");
    let out = run(&[
        "dance",
        song.to_str().unwrap(),
        "-o",
        c.to_str().unwrap(),
        "--init-noise",
        n,
    ]);
    let line = one_error_line(&out);
    assert!(
        line.contains("initial noise") && line.contains("(3, 150, 71)"),
        "{line}"
    );
    assert!(!c.exists());
}

#[test]
fn a_missing_output_folder_is_refused_before_any_work() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("missing");
    let in_missing = missing.join("out.h5");
    let (out, windows) = (dir.path().join("out.h5"), missing.join("windows.npy"));
    // The input does not exist either: an up-front check reports the folder, not the input.
    let input = dir.path().join("no-such-song.ogg");
    let cases: [Vec<&std::ffi::OsStr>; 3] = [
        vec![
            "dance".as_ref(),
            input.as_ref(),
            "-o".as_ref(),
            in_missing.as_ref(),
        ],
        vec![
            "dance".as_ref(),
            input.as_ref(),
            "-o".as_ref(),
            out.as_ref(),
            "--save-windows".as_ref(),
            windows.as_ref(),
        ],
        vec![
            "stylize".as_ref(),
            "--content".as_ref(),
            input.as_ref(),
            "--style".as_ref(),
            input.as_ref(),
            "-o".as_ref(),
            in_missing.as_ref(),
        ],
    ];
    for args in cases {
        let result = choreod().args(&args).output().unwrap();
        assert_eq!(result.status.code(), Some(1), "{args:?}");
        let line = one_error_line(&result);
        assert!(
            line.contains(&format!("in the folder {}", missing.display()))
                && line.contains("No such file or directory")
                && !line.contains("no-such-song"),
            "{line}"
        );
    }
    // The probe leaves nothing behind.
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
}

#[test]
fn a_dance_that_is_not_a_body_is_warned_about() {
    // Issue 23 item 6: the untrained mofusion-ref makes a "dance" 2.2 km wide; `render` refuses
    // it, `dance` said nothing. The bundled exemplar's dance is a body and gets no warning.
    let dir = tempfile::tempdir().expect("test setup");
    let song = workspace_root().join("daemon/assets/audio/vibe_ace_44k_stereo.ogg");
    let song = song.to_str().expect("test setup");
    let model = workspace_root().join("models/packages/mofusion-ref");
    for (model, warned) in [(Some(model), true), (None, false)] {
        let out = dir.path().join("d.h5");
        let mut args = vec!["dance", song, "-o", out.to_str().expect("test setup")];
        if let Some(m) = &model {
            args.extend(["--model", m.to_str().expect("test setup")]);
        }
        let result = run(&args);
        let err = choreod_tests::stderr(&result);
        assert!(result.status.success(), "{err}");
        assert_eq!(
            err.contains("the dance is not a body"),
            warned,
            "{args:?}: {err}"
        );
    }
}

/// Issue 24 item 4: speech and noise are danced, but `dance` says in one warning line that they
/// have no steady beat and what it danced instead, `--stats` says `no_steady_beat` and the
/// motion file's provenance keeps the sentence (`source_beat`). The two fixture songs, a
/// steady pop song and the rubato Hungarian Dance No. 5, get none of it.
#[test]
fn speech_and_noise_are_danced_with_one_warning_that_they_have_no_beat() {
    let d = tempfile::tempdir().unwrap();
    let [speech, noise] = not_music(d.path());
    let audio = fixtures().join("audio");
    let cases = [
        (speech, true),
        (noise, true),
        (audio.join("hungarian_dance_5_44k_stereo.ogg"), false),
        (audio.join("vibe_ace_44k_stereo.ogg"), false),
    ];
    for (song, no_beat) in cases {
        let out = d.path().join("d.h5");
        let result = run(&[
            "dance",
            song.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
            "--steps",
            "2",
            "--stats",
        ]);
        let err = stderr(&result);
        assert!(result.status.success(), "{}: {err}", song.display());
        let name = song.file_name().unwrap().to_str().unwrap();
        let warnings: Vec<&str> = err.lines().filter(|l| l.contains("WARN")).collect();
        let stats: serde_json::Value =
            serde_json::from_str(stdout(&result).trim()).expect("one JSON line on stdout");
        let provenance = choreo_datasets::read_motion_file(&out)
            .expect("a motion file")
            .provenance
            .expect("provenance");
        if no_beat {
            assert!(
                warnings.len() == 1
                    && warnings[0].contains(name)
                    && warnings[0].contains("no steady beat")
                    && warnings[0].contains("danced anyway"),
                "one warning line for {name}: {err}"
            );
            assert_eq!(stats["beat"], "no_steady_beat", "{name}: {stats}");
            let recorded = provenance.source_beat.unwrap_or_default();
            assert!(
                recorded.starts_with("no steady beat") && recorded.contains("danced anyway"),
                "{name}: {recorded}"
            );
        } else {
            assert!(warnings.is_empty(), "no warning for {name}: {err}");
            assert_eq!(stats["beat"], "steady", "{name}: {stats}");
            assert_eq!(provenance.source_beat, None, "{name}");
        }
    }
}
