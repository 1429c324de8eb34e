//! `choreod serve` operations (issue 7): files waiting before start, SIGTERM in the middle of a
//! job (finished, or left to resume), the same name twice, a slow writer, limits, symlinks,
//! Opus, and the HTTP endpoint.
//!
//! Needs the binary: `cargo build -p choreod` (or `--release`) first.

use std::io::Write;
use std::time::{Duration, Instant};

use choreod_tests::daemon::{Home, drop_file, wav_bytes};

fn report(home: &Home, name: &str) -> serde_json::Value {
    let file = home
        .names("state/failed")
        .into_iter()
        .find(|n| n.ends_with(&format!("__{name}.error.json")))
        .unwrap_or_else(|| panic!("no report for {name}: {:?}", home.names("state/failed")));
    let text = std::fs::read_to_string(home.state().join("failed").join(file)).expect("report");
    serde_json::from_str(&text).expect("report is JSON")
}

fn frames(home: &Home, h5: &str) -> usize {
    choreo_datasets::read_motion_file(&home.out().join(h5))
        .expect("a complete motion file")
        .joints
        .shape()[0]
}

#[test]
fn files_waiting_before_start_and_the_same_name_twice() {
    let mut home = Home::new("");
    drop_file(&home.inbox(), "early.wav", &wav_bytes(1.0, 1));
    drop_file(&home.inbox(), "song.wav", &wav_bytes(1.0, 2));
    drop_file(&home.inbox(), "song.flac.wav", &wav_bytes(1.0, 3));
    let mut daemon = home.start();
    home.wait_for_outcomes(3, &[], Duration::from_secs(60), &mut daemon);
    assert_eq!(home.names("out"), ["early.h5", "song.flac.h5", "song.h5"]);

    // The same name again (different music): a new output name, the first one untouched.
    let first = std::fs::read(home.out().join("song.h5")).unwrap();
    drop_file(&home.inbox(), "song.wav", &wav_bytes(2.0, 4));
    home.wait_for_outcomes(4, &[], Duration::from_secs(60), &mut daemon);
    assert_eq!(
        home.names("out"),
        ["early.h5", "song-2.h5", "song.flac.h5", "song.h5"]
    );
    assert_eq!(std::fs::read(home.out().join("song.h5")).unwrap(), first);
    assert_eq!(
        (frames(&home, "song.h5"), frames(&home, "song-2.h5")),
        (30, 60)
    );
    assert_eq!(home.names("state/done").len(), 4);
}

#[test]
fn sigterm_mid_job_lets_it_finish() {
    // 40 s of music at 500 steps: ~2 s of work in a release build, long enough to signal
    // while it runs (we signal as soon as the log says it started).
    let mut home =
        Home::new("[serve]\nsettle_ms = 100\nshutdown_timeout_s = 120\n\n[job]\nsteps = 500\n");
    let mut daemon = home.start();
    drop_file(&home.inbox(), "long.wav", &wav_bytes(40.0, 5));
    daemon.wait_log("job started", Duration::from_secs(30));
    daemon.term();
    let status = daemon
        .wait_exit(Duration::from_secs(120))
        .expect("exits after finishing the job");
    assert!(status.success(), "{status}; log:\n{}", daemon.log_text());
    let log = daemon.log_text();
    assert!(
        log.contains("shutting down") && log.contains("job done"),
        "{log}"
    );
    assert!(
        log.find("shutting down") < log.find("job done"),
        "the signal came while the job ran: {log}"
    );
    assert_eq!(home.names("out"), ["long.h5"]);
    assert_eq!(frames(&home, "long.h5"), 1200);
    assert!(home.names("state/work").is_empty());
}

#[test]
fn sigterm_past_the_timeout_leaves_the_job_to_resume() {
    let mut home =
        Home::new("[serve]\nsettle_ms = 100\nshutdown_timeout_s = 0\n\n[job]\nsteps = 500\n");
    let mut daemon = home.start();
    drop_file(&home.inbox(), "long.wav", &wav_bytes(40.0, 6));
    daemon.wait_log("job started", Duration::from_secs(30));
    let t0 = Instant::now();
    daemon.term();
    let status = daemon
        .wait_exit(Duration::from_secs(10))
        .expect("exits at once with timeout 0");
    assert!(status.success(), "{status}; log:\n{}", daemon.log_text());
    assert!(
        t0.elapsed() < Duration::from_secs(2),
        "took {:?}",
        t0.elapsed()
    );
    assert!(
        daemon.log_text().contains("leaving unfinished jobs"),
        "{}",
        daemon.log_text()
    );
    // No output (not even under a temporary name that a reader could take for one), and the
    // job is still claimed.
    assert!(
        home.names("out").iter().all(|n| n.starts_with('.')),
        "{:?}",
        home.names("out")
    );
    assert_eq!(
        home.names("state/work").len(),
        1,
        "{:?} {:?}\n{}",
        home.names("state/failed"),
        home.names("state/done"),
        daemon.log_text()
    );

    let mut daemon = home.start();
    home.wait_for_outcomes(1, &[], Duration::from_secs(120), &mut daemon);
    assert_eq!(
        home.names("out"),
        ["long.h5"],
        "resumed, and the stale temporary file removed"
    );
    assert_eq!(frames(&home, "long.h5"), 1200);
    assert!(
        daemon.log_text().contains("resuming jobs"),
        "{}",
        daemon.log_text()
    );
}

#[test]
fn slow_writer_is_not_picked_up_before_it_closes_the_file() {
    // Pauses between pieces (400 ms) are longer than settle_ms (200 ms): only the close tells
    // the daemon the file is complete.
    let mut home = Home::new("");
    let mut daemon = home.start();
    home.wait_healthy(&mut daemon);
    let bytes = wav_bytes(2.0, 7);
    let path = home.inbox().join("slow.wav");
    let mut f = std::fs::File::create(&path).unwrap();
    let pieces = 6;
    let piece = bytes.len().div_ceil(pieces);
    for chunk in bytes.chunks(piece) {
        f.write_all(chunk).unwrap();
        f.flush().unwrap();
        std::thread::sleep(Duration::from_millis(400));
        assert!(
            path.exists(),
            "taken while still being written; log:\n{}",
            daemon.log_text()
        );
        assert!(home.names("state/work").is_empty());
    }
    drop(f);
    home.wait_for_outcomes(1, &[], Duration::from_secs(60), &mut daemon);
    assert_eq!(home.names("out"), ["slow.h5"]);
    assert_eq!(
        frames(&home, "slow.h5"),
        60,
        "the whole 2 s song was danced"
    );
}

#[test]
fn limits_symlinks_and_opus_fail_or_skip_clearly_and_the_daemon_keeps_running() {
    let mut home = Home::new(
        "[limits]\nmax_file_mb = 0.05\nmin_audio_seconds = 0.5\n\n[serve]\nsettle_ms = 100\n\n[job]\nsteps = 2\n",
    );
    let mut daemon = home.start();
    home.wait_healthy(&mut daemon);
    // 2 s of 16-bit 16 kHz mono = 64 KB > 0.05 MiB (52 KB); 1 s = 32 KB passes.
    drop_file(&home.inbox(), "big.wav", &wav_bytes(2.0, 8));
    drop_file(&home.inbox(), "small.wav", &wav_bytes(1.0, 9));
    // A symlink pointing out of the inbox is never followed nor moved.
    let outside = home.path().join("outside.wav");
    std::fs::write(&outside, wav_bytes(1.0, 10)).unwrap();
    std::os::unix::fs::symlink(&outside, home.inbox().join("link.wav")).unwrap();
    // Opus passes intake and fails with the decoder's message.
    let opus = home.path().join("x.opus");
    let made = std::process::Command::new("ffmpeg")
        .args([
            "-loglevel",
            "error",
            "-y",
            "-f",
            "lavfi",
            "-i",
            "sine=frequency=440:duration=1",
            "-c:a",
            "libopus",
        ])
        .arg(&opus)
        .status()
        .expect("ffmpeg (installed by scripts/setup) makes an Opus file");
    assert!(made.success());
    std::fs::rename(&opus, home.inbox().join("x.opus")).unwrap();

    home.wait_for_outcomes(3, &["link.wav"], Duration::from_secs(60), &mut daemon);
    assert_eq!(home.names("out"), ["small.h5"]);
    let big = report(&home, "big.wav");
    assert_eq!(big["stage"], "intake", "{big}");
    assert!(
        big["reason"]
            .as_str()
            .unwrap()
            .contains("limits.max_file_mb"),
        "{big}"
    );
    let o = report(&home, "x.opus");
    assert_eq!(o["stage"], "decode", "{o}");
    // The file as the user dropped it, not its path inside the state folder's work/.
    let reason = o["reason"].as_str().unwrap();
    assert!(
        reason.starts_with("x.opus: Opus is not supported")
            && reason.contains("`ffmpeg -i x.opus x.flac`")
            && !reason.contains("work/"),
        "{o}"
    );
    assert!(outside.exists() && home.inbox().join("link.wav").exists());
    let (status, body) = home.http_get("/healthz").unwrap();
    assert!(
        status.contains(" 200 ") && body == "ok\n",
        "{status} {body}"
    );
}

#[test]
fn full_disk_fails_the_job_and_the_daemon_keeps_serving() {
    // No filesystem here has a petabyte free: every job meets a "full" disk.
    let mut home = Home::new("[limits]\nmin_free_disk_mb = 1e9\n");
    let mut daemon = home.start();
    drop_file(&home.inbox(), "a.wav", &wav_bytes(1.0, 11));
    home.wait_for_outcomes(1, &[], Duration::from_secs(60), &mut daemon);
    drop_file(&home.inbox(), "b.wav", &wav_bytes(1.0, 12));
    home.wait_for_outcomes(2, &[], Duration::from_secs(60), &mut daemon);
    assert!(home.names("out").is_empty());
    for name in ["a.wav", "b.wav"] {
        let r = report(&home, name);
        assert_eq!(r["stage"], "write", "{r}");
        assert!(r["reason"].as_str().unwrap().contains("disk full"), "{r}");
    }
    assert!(daemon.try_status().is_none(), "still running");
}

#[test]
fn healthz_and_metrics_answer_in_prometheus_format() {
    let mut home = Home::new("");
    let mut daemon = home.start();
    home.wait_healthy(&mut daemon);
    drop_file(&home.inbox(), "a.wav", &wav_bytes(1.0, 13));
    drop_file(&home.inbox(), "b.mp3", b"garbage");
    home.wait_for_outcomes(2, &[], Duration::from_secs(60), &mut daemon);
    // The counters follow the outcome (the input's move to done/ or failed/) by a moment.
    let t0 = Instant::now();
    while home.metric("choreod_jobs_total{outcome=\"done\"}") != Some(1.0)
        && t0.elapsed() < Duration::from_secs(10)
    {
        std::thread::sleep(Duration::from_millis(20));
    }
    let (status, body) = home.http_get("/metrics").unwrap();
    assert!(status.contains(" 200 "), "{status}");
    for line in [
        "choreod_jobs_total{outcome=\"done\"} 1",
        "choreod_jobs_total{outcome=\"failed\"} 1",
        "choreod_job_failures_total{stage=\"decode\"} 1",
        "choreod_queue_depth 0",
        "choreod_jobs_in_flight 0",
        "choreod_workers 2",
        "choreod_stage_duration_seconds_count{stage=\"generate\"} 1",
        "choreod_stage_duration_seconds_bucket{stage=\"total\",le=\"+Inf\"} 1",
        "choreod_audio_seconds_total 1",
        "# TYPE choreod_stage_duration_seconds histogram",
    ] {
        assert!(body.contains(line), "missing {line:?} in:\n{body}");
    }
    let rtf: f64 = body
        .lines()
        .find_map(|l| l.strip_prefix("choreod_realtime_factor "))
        .expect("realtime factor")
        .parse()
        .unwrap();
    assert!(rtf > 0.0 && rtf.is_finite(), "{rtf}");
    for line in body
        .lines()
        .filter(|l| !l.starts_with('#') && !l.is_empty())
    {
        let (_, value) = line.rsplit_once(' ').unwrap();
        assert!(value.parse::<f64>().is_ok(), "not a sample: {line}");
    }
    let (status, _) = home.http_get("/nope").unwrap();
    assert!(status.contains(" 404 "), "{status}");
}

#[test]
fn a_slow_job_does_not_block_the_others() {
    // Two workers: while one dances 40 s of music at 500 steps (~2 s), the other takes the
    // short songs dropped after it.
    let mut home = Home::new("[serve]\nsettle_ms = 100\nworkers = 2\n\n[job]\nsteps = 500\n");
    let mut daemon = home.start();
    drop_file(&home.inbox(), "long.wav", &wav_bytes(40.0, 14));
    daemon.wait_log("job started", Duration::from_secs(30));
    for i in 0..3 {
        drop_file(
            &home.inbox(),
            &format!("short-{i}.wav"),
            &wav_bytes(1.0, 15 + i),
        );
    }
    let t0 = Instant::now();
    while home
        .names("out")
        .iter()
        .filter(|n| n.starts_with("short"))
        .count()
        < 3
    {
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "log:\n{}",
            daemon.log_text()
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    assert!(
        !home.out().join("long.h5").exists(),
        "the short songs finished while the long one still ran"
    );
    home.wait_for_outcomes(4, &[], Duration::from_secs(120), &mut daemon);
}

#[test]
fn refuses_to_start_on_a_bad_config_or_a_spool_in_use() {
    let mut home = Home::new("");
    std::fs::remove_dir(home.inbox()).unwrap();
    let mut daemon = home.start();
    let status = daemon.wait_exit(Duration::from_secs(30)).expect("exits");
    assert_eq!(status.code(), Some(3), "{}", daemon.log_text());
    let log = daemon.log_text();
    assert!(
        log.contains("choreod: error: ") && log.contains("`paths.inbox`"),
        "{log}"
    );
    assert!(log.contains("does not exist"), "{log}");

    std::fs::create_dir(home.inbox()).unwrap();
    let mut first = home.start();
    home.wait_healthy(&mut first);
    // Same state folder, another metrics port.
    let text = std::fs::read_to_string(home.path().join("choreod.toml")).unwrap();
    let other = choreod_tests::daemon::free_port();
    let text = text.replace(&format!(":{}\"", home.port), &format!(":{other}\""));
    std::fs::write(home.path().join("choreod.toml"), text).unwrap();
    let mut second = home.start();
    let status = second
        .wait_exit(Duration::from_secs(30))
        .expect("the second one exits");
    assert_eq!(status.code(), Some(4), "{}", second.log_text());
    assert!(
        second.log_text().contains("another choreod serve"),
        "{}",
        second.log_text()
    );
    assert!(first.try_status().is_none(), "the first one keeps running");
}
