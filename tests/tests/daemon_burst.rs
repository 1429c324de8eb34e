//! `choreod serve` under a burst (issue 7): 200 files, 10 % corrupt, dropped at once → exactly
//! 180 complete motion files and 20 error reports, nothing else.
//!
//! Needs the binary: `cargo build -p choreod` (or `--release`) first.

use std::time::{Duration, Instant};

use choreod_tests::daemon::{Home, corrupt_bytes, drop_file, wav_bytes};

/// 1.5 s songs at the exemplar package's 30 fps → round(1.5 · 30) = 45 frames
/// (models pipeline: output frames = round(duration_s · fps)).
const SONG_S: f64 = 1.5;
const FRAMES: usize = 45;

#[test]
fn burst_of_200_with_20_corrupt_gives_180_dances_and_20_reports() {
    // A small queue makes intake wait for room: backpressure is part of what is tested.
    let mut home = Home::new("[serve]\nsettle_ms = 200\nworkers = 2\nqueue_capacity = 16\n");
    let mut daemon = home.start();
    home.wait_healthy(&mut daemon);

    let inbox = home.inbox();
    let good: Vec<String> = (0..180).map(|i| format!("song-{i:03}.wav")).collect();
    let exts = ["wav", "mp3", "flac", "ogg"];
    let bad: Vec<String> = (0..20)
        .map(|i| format!("bad-{i:02}.{}", exts[i % 4]))
        .collect();
    let song = wav_bytes(SONG_S, 1);
    let t0 = Instant::now();
    for (i, name) in good.iter().enumerate() {
        drop_file(&inbox, name, &song);
        if i % 9 == 0 {
            let b = &bad[i / 9];
            drop_file(&inbox, b, &corrupt_bytes(i as u32 / 9));
        }
    }
    // Names the daemon must leave alone.
    let ignored = [".hidden.wav", "notes.txt", "upload.wav.part", "x.wav~"];
    for name in ignored {
        std::fs::write(inbox.join(name), b"not for choreod").unwrap();
    }
    home.wait_for_outcomes(200, &ignored, Duration::from_secs(240), &mut daemon);
    eprintln!("200 jobs done in {:.1} s", t0.elapsed().as_secs_f64());

    // Exactly the expected files, nothing else (no temporaries, no duplicates).
    let mut want_out: Vec<String> = good.iter().map(|n| n.replace(".wav", ".h5")).collect();
    want_out.sort();
    assert_eq!(home.names("out"), want_out);
    let mut want_failed: Vec<String> = bad
        .iter()
        .flat_map(|b| [b.clone(), format!("{b}.error.json")])
        .collect();
    want_failed.sort();
    let failed: Vec<String> = home
        .names("state/failed")
        .iter()
        .map(|n| {
            n.split_once("__")
                .expect("failed/<id>__<name>")
                .1
                .to_string()
        })
        .collect();
    let mut failed_sorted = failed.clone();
    failed_sorted.sort();
    assert_eq!(failed_sorted, want_failed);
    assert_eq!(home.names("state/done").len(), 180);
    assert!(home.names("state/work").is_empty());
    assert_eq!(home.names("inbox"), ignored);

    for name in home.names("out") {
        let m = choreo_datasets::read_motion_file(&home.out().join(&name)).unwrap();
        assert_eq!(m.joints.shape()[0], FRAMES, "{name}");
        assert!(m.joints.iter().all(|v| v.is_finite()), "{name}");
        let p = m.provenance.expect("provenance");
        assert_eq!(
            p.source_name,
            name.replace(".h5", ".wav"),
            "provenance names the song, not the spool"
        );
    }
    for name in home
        .names("state/failed")
        .iter()
        .filter(|n| n.ends_with(".error.json"))
    {
        let text = std::fs::read_to_string(home.state().join("failed").join(name)).unwrap();
        let r: serde_json::Value = serde_json::from_str(&text).unwrap();
        assert_eq!(r["stage"], "decode", "{text}");
        let file = r["file"].as_str().unwrap();
        assert!(
            name.ends_with(&format!("__{file}.error.json")),
            "{name}: {text}"
        );
        assert!(
            r["reason"].as_str().unwrap().contains(file),
            "reason names the file: {text}"
        );
        assert!(r["time"].as_str().unwrap().ends_with('Z'), "{text}");
        assert_eq!(r["attempts"], 1, "{text}");
    }

    let (status, body) = home.http_get("/metrics").unwrap();
    assert!(status.contains(" 200 "), "{status}");
    assert!(
        body.contains("choreod_jobs_total{outcome=\"done\"} 180"),
        "{body}"
    );
    assert!(
        body.contains("choreod_jobs_total{outcome=\"failed\"} 20"),
        "{body}"
    );
    assert!(
        body.contains("choreod_job_failures_total{stage=\"decode\"} 20"),
        "{body}"
    );
    assert!(body.contains("choreod_queue_depth 0"), "{body}");

    daemon.term();
    let status = daemon
        .wait_exit(Duration::from_secs(30))
        .expect("exits after SIGTERM");
    assert!(status.success(), "{status}; log:\n{}", daemon.log_text());
}
