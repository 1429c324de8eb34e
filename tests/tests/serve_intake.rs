//! `choreod serve` taking files from its inbox: files waiting before start, the same name twice,
//! slow writers and slow uploads under hidden or `.part` names, names near NAME_MAX and not
//! UTF-8, limits, symlinks, Opus, truncated and too short or too long audio, a full disk or
//! state filesystem, a slow job beside quick ones, a burst of 200 files, a file name that tries
//! to forge a log line, and two daemons on one output folder: each input gets exactly one
//! outcome.
//!
//! Needs the binary: `cargo build --release -p choreod` first. Mounting a small tmpfs needs root
//! (CI runs as root); without it those tests say why and skip.

use std::collections::BTreeMap;
use std::ffi::OsStr;
use std::io::Write;
use std::os::unix::ffi::OsStrExt;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use choreod_tests::daemon::{
    Home, PATIENCE, corrupt_bytes, drop_file, exit_code, frames, names, pcm16_wav, source_sha256,
    wav_bytes,
};
use choreod_tests::endless_package;

fn report(home: &Home, name: &str) -> serde_json::Value {
    let file = home
        .names("state/failed")
        .into_iter()
        .find(|n| n.ends_with(&format!("__{name}.error.json")))
        .unwrap_or_else(|| panic!("no report for {name}: {:?}", home.names("state/failed")));
    let text = std::fs::read_to_string(home.state().join("failed").join(file)).expect("report");
    serde_json::from_str(&text).expect("report is JSON")
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
        (
            frames(&home.out().join("song.h5")),
            frames(&home.out().join("song-2.h5"))
        ),
        (30, 60)
    );
    assert_eq!(home.names("state/done").len(), 4);
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
        frames(&home.out().join("slow.h5")),
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
fn long_and_non_utf8_names_each_get_one_outcome_that_survives_a_restart() {
    let mut home = Home::new("");
    let long_good = format!("{}.wav", "ü".repeat(123)); // 250 bytes
    let long_bad = format!("{}.mp3", "b".repeat(246));
    let raw_good = OsStr::from_bytes(b"caf\xe9-good.wav");
    let raw_bad = OsStr::from_bytes(b"caf\xe9-bad.wav");
    for (raw, bytes) in [
        (OsStr::new(&long_good), wav_bytes(1.0, 1)),
        (OsStr::new(&long_bad), corrupt_bytes(2)),
        (raw_good, wav_bytes(1.0, 3)),
        (raw_bad, corrupt_bytes(0)),
    ] {
        let tmp = home.inbox().join(".uploading");
        std::fs::write(&tmp, bytes).unwrap();
        std::fs::rename(&tmp, home.inbox().join(raw)).unwrap();
    }
    let mut daemon = home.start();
    home.wait_for_outcomes(4, &[], PATIENCE, &mut daemon);
    assert_eq!(
        home.outcomes(),
        (2, 2),
        "{:?} {:?}",
        home.names("out"),
        home.names("state/failed")
    );
    for sub in ["out", "state/done", "state/failed"] {
        for n in home.names(sub) {
            assert!(n.len() <= 255, "{sub}/{n}: {} bytes", n.len());
        }
    }
    let reports = home.reports();
    let files: Vec<&str> = reports
        .iter()
        .map(|r| r["file"].as_str().unwrap())
        .collect();
    assert!(
        files.contains(&long_bad.as_str()),
        "the full name is reported: {files:?}"
    );
    let raw_report = reports
        .iter()
        .find(|r| r.get("original_file").is_some())
        .expect("report of the raw name");
    assert_eq!(raw_report["original_file"], "caf\\xe9-bad.wav");
    assert_eq!(raw_report["stage"], "decode");

    // Nothing is replayed at the next start.
    daemon.term();
    assert_eq!(exit_code(&mut daemon), 0);
    let mut daemon = home.start();
    home.wait_healthy(&mut daemon);
    assert!(home.names("state/work").is_empty());
    assert_eq!(home.outcomes(), (2, 2));
    assert!(
        !daemon.log_text().contains("claimed"),
        "{}",
        daemon.log_text()
    );
}

/// A tmpfs of `size` mounted on a fresh folder, unmounted on drop.
struct Tmpfs(PathBuf);

impl Tmpfs {
    fn mount(size: &str) -> Result<Self, String> {
        let dir = std::env::temp_dir().join(format!("choreod-tmpfs-{}", std::process::id()));
        std::fs::create_dir_all(&dir).map_err(|e| e.to_string())?;
        let out = std::process::Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={size}"), "tmpfs"])
            .arg(&dir)
            .output()
            .map_err(|e| format!("cannot run mount: {e}"))?;
        if !out.status.success() {
            let _ = std::fs::remove_dir(&dir);
            return Err(String::from_utf8_lossy(&out.stderr).trim().to_string());
        }
        Ok(Self(dir))
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = std::process::Command::new("umount")
            .arg("-l")
            .arg(&self.0)
            .status();
        let _ = std::fs::remove_dir(&self.0);
    }
}

#[test]
fn full_state_filesystem_at_claim_keeps_the_file_in_the_inbox_until_space_frees() {
    let fs = match Tmpfs::mount("4m") {
        Ok(fs) => fs,
        Err(e) => {
            eprintln!(
                "skipped: cannot mount a small tmpfs ({e}); the spool unit test covers the rollback"
            );
            return;
        }
    };
    for d in ["inbox", "state"] {
        std::fs::create_dir(fs.0.join(d)).unwrap();
    }
    let mut home = Home::with_paths(
        "",
        &fs.0.join("inbox").display().to_string(),
        &fs.0.join("state").display().to_string(),
    );
    let inbox = fs.0.join("inbox");
    let mut daemon = home.start();
    home.wait_healthy(&mut daemon);
    // The song waits under a hidden name; then the filesystem is filled to the last byte.
    let hidden = inbox.join(".song.wav.uploading");
    std::fs::write(&hidden, wav_bytes(1.0, 7)).unwrap();
    let filler = fs.0.join("filler");
    {
        use std::io::Write;
        let mut f = std::fs::File::create(&filler).unwrap();
        let block = vec![0u8; 4096];
        while f.write_all(&block).is_ok() {}
        while f.write_all(&block[..1]).is_ok() {}
    }
    std::fs::rename(&hidden, inbox.join("song.wav")).unwrap();
    daemon.wait_until("failing claims", PATIENCE, || {
        home.metric("choreod_claim_failures_total").unwrap_or(0.0) >= 2.0
    });
    let (status, body) = home.http_get("/healthz").unwrap();
    assert!(
        status.contains(" 503 ") && body.contains("claims failing"),
        "{status} {body}"
    );
    assert_eq!(names(&inbox), ["song.wav"], "the claim was rolled back");
    assert!(daemon.log_text().contains("cannot claim; will retry"));

    std::fs::remove_file(&filler).unwrap();
    daemon.wait_until("the song done", PATIENCE, || {
        home.names("out") == ["song.h5"]
    });
    daemon.wait_until("health back", PATIENCE, || {
        home.http_get("/healthz")
            .is_ok_and(|(s, _)| s.contains(" 200 "))
    });
    drop(daemon);
}

#[test]
fn a_file_is_taken_when_complete_and_truncated_audio_fails() {
    let mut home = Home::new("[serve]\nsettle_ms = 1500\nworkers = 2\n");
    // A writer busy before the daemon starts, holding the file open across a pause longer than
    // settle_ms (the start-up scan sees no close event: it must not take half a song).
    let song = wav_bytes(6.0, 9);
    let held = home.inbox().join("held.wav");
    let mut writer = std::fs::File::create(&held).unwrap();
    use std::io::Write;
    writer.write_all(&song[..song.len() / 3]).unwrap();
    let mut daemon = home.start();
    home.wait_healthy(&mut daemon);
    std::thread::sleep(Duration::from_millis(2500));
    writer.write_all(&song[song.len() / 3..]).unwrap();
    drop(writer);
    // A writer appending in bursts, closing after each, with pauses shorter than settle_ms.
    let bursts = home.inbox().join("bursts.wav");
    for chunk in song.chunks(song.len() / 8 + 1) {
        std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&bursts)
            .unwrap()
            .write_all(chunk)
            .unwrap();
        std::thread::sleep(Duration::from_millis(300));
    }
    // A WAV cut after 60 bytes: 8 samples of audio.
    drop_file(&home.inbox(), "cut.wav", &wav_bytes(6.0, 10)[..60]);
    home.wait_for_outcomes(3, &[], PATIENCE, &mut daemon);
    assert_one_whole_dance_each(&home, &["bursts.h5", "held.h5"]);
    let r = home.reports();
    assert_eq!(r.len(), 1);
    assert_eq!(r[0]["stage"], "decode");
    assert!(
        r[0]["reason"]
            .as_str()
            .unwrap()
            .contains("shorter than the minimum of"),
        "{}",
        r[0]
    );
}

/// The first `seconds` of a real song (the Vibe Ace fixture, 22.05 kHz mono) as a 16-bit WAV
/// file cut there: what a truncated download or copy leaves.
fn truncated_real_song(seconds: f64) -> Vec<u8> {
    let song = choreod_tests::fixtures().join("audio/vibe_ace_22k_mono.ogg");
    let audio = choreo_dsp::decode_file(&song, &choreo_dsp::DecodeOptions::default())
        .expect("the fixture decodes");
    let whole = pcm16_wav(audio.sample_rate, &audio.samples);
    let keep = (seconds * f64::from(audio.sample_rate)).round() as usize;
    whole[..44 + 2 * keep].to_vec()
}

#[test]
fn audio_shorter_than_one_model_window_is_refused_by_dance_and_serve() {
    // The shipped package's window: 150 frames at 30 fps (models/packages/exemplar).
    let dir = tempfile::tempdir().unwrap();
    let (short, long) = (
        dir.path().join("cut-4.9s.wav"),
        dir.path().join("cut-5.1s.wav"),
    );
    std::fs::write(&short, truncated_real_song(4.9)).unwrap();
    std::fs::write(&long, truncated_real_song(5.1)).unwrap();
    let dance = |input: &Path, extra: &[&str]| {
        let out = dir.path().join("dance.h5");
        let _ = std::fs::remove_file(&out);
        let result = choreod_tests::choreod()
            .arg("dance")
            .arg(input)
            .arg("-o")
            .arg(&out)
            .args(["--steps", "2"])
            .args(extra)
            .output()
            .unwrap();
        (result, out)
    };
    let (refused, out) = dance(&short, &[]);
    // The decoder also warns that the file ends mid-stream (its header promises the whole song).
    let stderr = choreod_tests::stderr(&refused);
    let errors: Vec<&str> = stderr
        .lines()
        .filter(|l| l.starts_with("choreod: error: "))
        .collect();
    assert_eq!(errors.len(), 1, "one error line: {stderr}");
    assert!(
        stderr.contains("truncated") && !stderr.contains("panicked"),
        "{stderr}"
    );
    let line = errors[0];
    assert_eq!(refused.status.code(), Some(1), "{line}");
    assert!(
        line.contains("cut-4.9s.wav: 4.900 s of audio, shorter than the minimum of 5.000 s (one motion window of model library: 150 frames at 30 fps)"),
        "{line}"
    );
    assert!(!out.exists(), "no dance from a truncated file");
    let (done, out) = dance(&long, &[]);
    assert!(done.status.success(), "{}", choreod_tests::stderr(&done));
    assert_eq!(frames(&out), 153, "5.1 s at 30 fps");
    // A lower minimum is a choice the user can make.
    let (done, _) = dance(&short, &["--min-duration", "4"]);
    assert!(done.status.success(), "{}", choreod_tests::stderr(&done));

    // The daemon, with the default minimum (no `limits.min_audio_seconds`).
    let mut home = Home::new(
        "[limits]\nmin_free_disk_mb = 1.0\n\n[serve]\nsettle_ms = 100\n\n[job]\nsteps = 2\n",
    );
    std::fs::copy(&short, home.inbox().join("short.wav")).unwrap();
    std::fs::copy(&long, home.inbox().join("long.wav")).unwrap();
    let mut daemon = home.start();
    home.wait_for_outcomes(2, &[], PATIENCE, &mut daemon);
    assert_eq!(home.names("out"), ["long.h5"]);
    let r = home.reports();
    assert_eq!(
        (r[0]["file"].as_str(), r[0]["stage"].as_str()),
        (Some("short.wav"), Some("decode"))
    );
    assert!(
        r[0]["reason"]
            .as_str()
            .unwrap()
            .contains("4.900 s of audio, shorter than the minimum of 5.000 s"),
        "{}",
        r[0]
    );
}

#[test]
fn too_long_a_song_is_refused_naming_the_flag_and_the_config_key() {
    let dir = tempfile::tempdir().unwrap();
    let song = dir.path().join("cut-5.1s.wav");
    std::fs::write(&song, truncated_real_song(5.1)).unwrap();
    let out = dir.path().join("dance.h5");
    let refused = choreod_tests::choreod()
        .arg("dance")
        .arg(&song)
        .arg("-o")
        .arg(&out)
        .args(["--max-duration", "5"])
        .output()
        .unwrap();
    let stderr = choreod_tests::stderr(&refused);
    let line = stderr
        .lines()
        .find(|l| l.starts_with("choreod: error: "))
        .unwrap_or_default();
    assert_eq!(refused.status.code(), Some(1), "{stderr}");
    // The knob the user can turn, not the library's field (`max_duration_s`).
    assert!(
        line.ends_with(
            "cut-5.1s.wav: audio is longer than the limit of 5 s (--max-duration / limits.max_audio_seconds)"
        ),
        "{line}"
    );
    assert!(!out.exists());

    let mut home = Home::new(
        "[limits]\nmin_free_disk_mb = 1.0\nmax_audio_seconds = 5.0\n\n[serve]\nsettle_ms = 100\n",
    );
    std::fs::copy(&song, home.inbox().join("long.wav")).unwrap();
    let mut daemon = home.start();
    home.wait_for_outcomes(1, &[], PATIENCE, &mut daemon);
    let r = home.reports();
    let reason = r[0]["reason"].as_str().unwrap();
    assert!(
        reason.contains("limits.max_audio_seconds") && !reason.contains("max_duration_s"),
        "{}",
        r[0]
    );
}

#[test]
fn a_slow_upload_under_a_hidden_or_part_name_then_renamed_is_one_job() {
    // Pauses of 300 ms, with the file closed in between, three times settle_ms: under its
    // final name this would be several jobs (the documented rule); under a hidden or `.part`
    // name the daemon does not look at it until the rename.
    let mut home = Home::new("[serve]\nsettle_ms = 100\nworkers = 2\n");
    let mut daemon = home.start();
    home.wait_healthy(&mut daemon);
    let song = wav_bytes(6.0, 21);
    let uploads = [
        (".hidden-upload.wav", "hidden.wav"),
        ("part-upload.wav.part", "part.wav"),
    ];
    for chunk in song.chunks(song.len() / 6 + 1) {
        for (temporary, _) in uploads {
            use std::io::Write;
            std::fs::OpenOptions::new()
                .create(true)
                .append(true)
                .open(home.inbox().join(temporary))
                .unwrap()
                .write_all(chunk)
                .unwrap();
        }
        std::thread::sleep(Duration::from_millis(300));
    }
    assert!(home.names("state/work").is_empty() && home.outcomes() == (0, 0));
    for (temporary, name) in uploads {
        std::fs::rename(home.inbox().join(temporary), home.inbox().join(name)).unwrap();
    }
    home.wait_for_outcomes(2, &[], PATIENCE, &mut daemon);
    assert_one_whole_dance_each(&home, &["hidden.h5", "part.h5"]);
    assert_eq!(home.names("state/done").len(), 2);
}

/// `out/` holds exactly these motion files, each of a whole 6 s song (one job per upload).
fn assert_one_whole_dance_each(home: &Home, outputs: &[&str]) {
    assert_eq!(home.names("out"), outputs, "one job each");
    for h5 in outputs {
        let n = frames(&home.out().join(h5));
        assert_eq!(n, 180, "{h5}: the whole 6 s song at 30 fps");
    }
}

#[test]
fn a_file_name_cannot_forge_a_log_line_or_reach_the_terminal_raw() {
    let mut home = Home::new("");
    let name = "x\nchoreod: error: FORGED\x1b[2J\u{202e}.wav";
    drop_file(&home.inbox(), name, &wav_bytes(2.0, 1));
    let mut daemon = home.start();
    home.wait_for_outcomes(1, &[], PATIENCE, &mut daemon);
    daemon.term();
    assert_eq!(exit_code(&mut daemon), 0);
    let log = daemon.log_text();
    assert!(
        !log.lines().any(|l| l.starts_with("choreod: error: FORGED")),
        "a forged line:\n{log}"
    );
    assert!(
        !log.contains('\x1b') && !log.contains('\u{202e}'),
        "{log:?}"
    );
    assert!(
        log.contains("x\\nchoreod: error: FORGED\\u001b[2J\\u202e.wav"),
        "the name, escaped:\n{log}"
    );
    // The CLI's one error line too.
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("evil\x1b]0;pwned\x07.bvh");
    std::fs::write(&bad, b"not a bvh").unwrap();
    let out = choreod_tests::run(&[
        "convert",
        bad.to_str().unwrap(),
        "-o",
        dir.path().join("o.npy").to_str().unwrap(),
    ]);
    let line = choreod_tests::one_error_line(&out);
    assert!(
        !line.contains('\x1b')
            && !line.contains('\x07')
            && line.contains("evil\\u001b]0;pwned\\u0007.bvh"),
        "{line:?}"
    );
}

#[test]
fn two_daemons_on_one_output_folder_never_share_an_output_name() {
    // Daemon A dies in the middle of song.wav, whose output name song.h5 its record holds.
    // While it is down, daemon B (its own state, the same inbox and the same output folder)
    // dances another song.wav into song.h5. Before: A restarted beside B, found song.h5
    // "already complete" and moved its own song to done/ with B's dance: one motion file for
    // two songs. Now: A is refused while B runs, and once B is gone A dances its song under
    // a free name. [limits] without the audio limit keeps the configs readable by older
    // binaries; the songs are longer than the 5 s default minimum.
    let limits = "[limits]\nmin_free_disk_mb = 1.0\n";
    // A's song takes long enough (≈ 1 s idle at 300 steps) to be killed in the middle.
    let mut a = Home::new(&format!(
        "{limits}\n[serve]\nsettle_ms = 100\nworkers = 1\n\n[job]\nsteps = 300\n"
    ));
    let mut b = Home::with_paths(
        &format!("{limits}\n[serve]\nsettle_ms = 100\nworkers = 1\n"),
        &a.inbox().display().to_string(),
        "state",
    );
    let config = std::fs::read_to_string(b.config()).unwrap();
    let out_b = b.out().display().to_string();
    let out_a = a.out().display().to_string();
    let shared_output = config.replace("output = \"out\"", &format!("output = \"{out_a}\""));
    assert_ne!(shared_output, config);
    std::fs::write(b.config(), shared_output).unwrap();
    std::fs::remove_dir(&out_b).unwrap();

    let first = wav_bytes(30.0, 1);
    let second = wav_bytes(6.0, 2);
    let mut daemon_a = a.start();
    drop_file(&a.inbox(), "song.wav", &first);
    daemon_a.wait_log("job started", PATIENCE);
    daemon_a.kill9();
    assert_eq!(a.names("state/work").len(), 1, "A died in the middle");
    assert!(a.names("out").is_empty(), "A died before writing");

    let mut daemon_b = b.start();
    drop_file(&a.inbox(), "song.wav", &second);
    daemon_b.wait_until("B's song.h5", PATIENCE, || b.names("state/done").len() == 1);
    assert_eq!(a.names("out"), ["song.h5"]);

    // A back while B runs: the output folder is B's now.
    let mut daemon_a = a.start();
    let Some(status) = daemon_a.wait_exit(Duration::from_secs(20)) else {
        panic!(
            "A runs beside B on one output folder: out/ {:?}, A's done/ {:?}; log:\n{}",
            a.names("out"),
            a.names("state/done"),
            daemon_a.log_text()
        );
    };
    assert_eq!(status.code(), Some(4), "{}", daemon_a.log_text());
    assert!(
        daemon_a.log_text().contains(&format!("{out_a} is locked")),
        "{}",
        daemon_a.log_text()
    );
    daemon_b.term();
    assert_eq!(exit_code(&mut daemon_b), 0, "{}", daemon_b.log_text());

    // B gone: A resumes its song and must not take B's song.h5 for its own.
    let mut daemon_a = a.start();
    daemon_a.wait_until("A's song done", PATIENCE, || {
        a.names("state/work").is_empty() && a.names("state/done").len() == 1
    });
    let done_input = |home: &Home| {
        let done = home.names("state/done");
        choreo_datasets::sha256_file(&home.state().join("done").join(&done[0])).unwrap()
    };
    let (song_a, song_b) = (done_input(&a), done_input(&b));
    let outputs = a.names("out");
    let danced: BTreeMap<String, String> = outputs
        .iter()
        .map(|n| (source_sha256(&a.out().join(n)), n.clone()))
        .collect();
    assert_eq!(
        danced.len(),
        2,
        "one dance per song: {outputs:?}; log:\n{}",
        daemon_a.log_text()
    );
    assert_eq!(danced[&song_b], "song.h5", "B's dance keeps its name");
    assert!(danced.contains_key(&song_a), "A's song danced: {danced:?}");
}

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

#[test]
fn serve_fails_every_song_of_a_model_that_loops_for_ever_and_keeps_serving() {
    let d = tempfile::tempdir().unwrap();
    let pkg = endless_package(d.path());
    let mut home = Home::new(&format!(
        "[runtime]\ndefault_model = \"{pkg}\"\n\n[job]\nsteps = 2\ntime_limit_s = 2\n"
    ));
    let mut daemon = home.start();
    home.wait_healthy(&mut daemon);
    for k in 0..3 {
        drop_file(&home.inbox(), &format!("song-{k}.wav"), &wav_bytes(2.0, k));
    }
    // Two workers, three jobs of 2 s each: under 10 s; a hang would never end.
    home.wait_for_outcomes(3, &[], Duration::from_secs(60), &mut daemon);
    let reports = home.reports();
    assert_eq!(reports.len(), 3, "one outcome per song: {reports:?}");
    for r in &reports {
        let reason = r["reason"].as_str().unwrap_or_default();
        assert!(
            reason.contains(
                "component denoiser: stopped at the time limit of 2 s (job.time_limit_s)"
            ),
            "{r}"
        );
        assert_eq!(r["stage"].as_str(), Some("generate"), "{r}");
    }
    assert!(home.names("out").iter().all(|n| !n.ends_with(".h5")));
    let (status, _) = home.http_get("/healthz").expect("healthz");
    assert!(status.contains(" 200 "), "{status}");
    daemon.term();
    let exit = daemon.wait_exit(Duration::from_secs(20));
    assert!(exit.is_some_and(|e| e.success()), "{exit:?}");
}

#[test]
fn a_song_cut_short_is_danced_with_its_damage_recorded_or_failed_when_configured() {
    // Issue 23 item 8: the first 200 kB of a real 1.45 MB OGG (a cut download), as the issue
    // cut its song. It decodes to 5.6 s of a 54 s song; the dance of what decodes is made, but
    // the provenance, the job's log lines (with its job id) and `choreod dance`'s one warning
    // say so, and a config key fails it instead.
    let dir = tempfile::tempdir().unwrap();
    let whole = std::fs::read(choreod_tests::fixtures().join("audio/vibe_ace_44k_stereo.ogg"))
        .expect("fixture");
    let cut = dir.path().join("cut.ogg");
    std::fs::write(&cut, &whole[..200_000]).unwrap();
    let damage = |h5: &Path| {
        choreo_datasets::read_motion_file(h5)
            .expect("a complete motion file")
            .provenance
            .expect("provenance")
            .source_damage
            .unwrap_or_default()
    };

    let out = dir.path().join("dance.h5");
    let done = choreod_tests::choreod()
        .arg("dance")
        .arg(&cut)
        .arg("-o")
        .arg(&out)
        .args(["--steps", "2"])
        .output()
        .unwrap();
    let stderr = choreod_tests::stderr(&done);
    assert!(done.status.success(), "{stderr}");
    let warnings: Vec<&str> = stderr.lines().filter(|l| l.contains("WARN")).collect();
    assert!(
        warnings.len() == 1
            && warnings[0].contains("cut.ogg")
            && warnings[0].contains("ends mid-stream"),
        "one warning line: {stderr}"
    );
    assert!(
        damage(&out).starts_with("the file ends mid-stream: "),
        "{}",
        damage(&out)
    );

    // The daemon, by default: done, the damage in the provenance and the job's log lines.
    let mut home = Home::new(
        "[limits]\nmin_free_disk_mb = 1.0\n\n[serve]\nsettle_ms = 100\n\n[job]\nsteps = 2\n",
    );
    std::fs::copy(&cut, home.inbox().join("cut.ogg")).unwrap();
    let mut daemon = home.start();
    home.wait_for_outcomes(1, &[], PATIENCE, &mut daemon);
    assert_eq!(home.names("out"), ["cut.h5"]);
    assert!(damage(&home.out().join("cut.h5")).contains("ends mid-stream"));
    let log = daemon.log_text();
    let job_id = |line: &str| {
        line.split(|c: char| c.is_whitespace() || c == '{' || c == '}' || c == ',')
            .find_map(|w| w.strip_prefix("job="))
            .map(|id| id.trim_matches('"').to_string())
    };
    let started = log
        .lines()
        .find(|l| l.contains("job started"))
        .and_then(job_id)
        .unwrap_or_else(|| panic!("no job id on the start line: {log}"));
    for needle in [
        "ends mid-stream (truncated?)",
        "job done with part of the song",
    ] {
        let line = log
            .lines()
            .find(|l| l.contains(needle) && l.contains("WARN"))
            .unwrap_or_else(|| panic!("no WARN line with {needle:?}: {log}"));
        assert_eq!(job_id(line).as_deref(), Some(started.as_str()), "{line}");
    }
    drop(daemon);

    // limits.fail_truncated_audio = true: failed at the decode stage, naming the key.
    let mut home = Home::new(
        "[limits]\nmin_free_disk_mb = 1.0\nfail_truncated_audio = true\n\n[serve]\nsettle_ms = 100\n\n[job]\nsteps = 2\n",
    );
    std::fs::copy(&cut, home.inbox().join("cut.ogg")).unwrap();
    let mut daemon = home.start();
    home.wait_for_outcomes(1, &[], PATIENCE, &mut daemon);
    assert!(home.names("out").is_empty());
    let r = home.reports();
    let reason = r[0]["reason"].as_str().unwrap();
    assert_eq!(r[0]["stage"], "decode");
    assert!(
        reason.contains("cut.ogg")
            && reason.contains("ends mid-stream")
            && reason.contains("limits.fail_truncated_audio"),
        "{reason}"
    );
}

#[test]
fn speech_and_noise_are_danced_with_their_missing_beat_in_the_log_and_the_provenance() {
    // Issue 24 item 4: the daemon dances speech and noise as `choreod dance` does, and records
    // that they had no steady beat: a WARN line of the job (its id and file in the span), the
    // job's `job done` line (`beat`), the motion file's provenance (`source_beat`). A song
    // gets none of it.
    let dir = tempfile::tempdir().unwrap();
    let [speech, noise] = choreod_tests::not_music(dir.path());
    let mut home = Home::new(
        "[limits]\nmin_free_disk_mb = 1.0\n\n[serve]\nsettle_ms = 100\n\n[job]\nsteps = 2\n",
    );
    std::fs::copy(&speech, home.inbox().join("speech.wav")).unwrap();
    std::fs::copy(&noise, home.inbox().join("noise.wav")).unwrap();
    std::fs::copy(
        choreod_tests::fixtures().join("audio/vibe_ace_44k_stereo.ogg"),
        home.inbox().join("song.ogg"),
    )
    .unwrap();
    let mut daemon = home.start();
    home.wait_for_outcomes(3, &[], PATIENCE, &mut daemon);
    let log = daemon.log_text();
    for (file, no_beat) in [
        ("speech.wav", true),
        ("noise.wav", true),
        ("song.ogg", false),
    ] {
        let h5 = home
            .out()
            .join(file.replace(".wav", ".h5").replace(".ogg", ".h5"));
        let recorded = choreo_datasets::read_motion_file(&h5)
            .expect("a complete motion file")
            .provenance
            .expect("provenance")
            .source_beat;
        let in_span = format!("file={file}");
        let job_lines: Vec<&str> = log.lines().filter(|l| l.contains(&in_span)).collect();
        let done = job_lines
            .iter()
            .find(|l| l.contains("job done"))
            .unwrap_or_else(|| panic!("no job done line for {file}: {log}"));
        let warned: Vec<&&str> = job_lines
            .iter()
            .filter(|l| l.contains("WARN") && l.contains("beat"))
            .collect();
        if no_beat {
            let recorded = recorded.unwrap_or_default();
            assert!(
                recorded.starts_with("no steady beat") && recorded.contains("danced anyway"),
                "{file}: {recorded}"
            );
            assert!(
                warned.len() == 1 && warned[0].contains("no steady beat"),
                "one warning for {file}: {log}"
            );
            assert!(done.contains("no_steady_beat"), "{done}");
        } else {
            assert_eq!(recorded, None, "{file}");
            assert!(warned.is_empty(), "{warned:?}");
            assert!(
                done.contains("beat=steady") || done.contains("beat=\"steady\""),
                "{done}"
            );
        }
    }
}

/// The share of steps done `/metrics` shows for each running job (`choreod_job_progress_ratio`).
fn progress_ratios(home: &Home) -> Vec<f64> {
    let Ok((_, body)) = home.http_get("/metrics") else {
        return Vec::new();
    };
    body.lines()
        .filter(|l| l.starts_with("choreod_job_progress_ratio{job=\""))
        .filter_map(|l| l.rsplit(' ').next()?.parse().ok())
        .collect()
}

/// `serve` runs a LODGE package as its model (issue 25 item 5): the song is danced as `dance`
/// makes it (raw features, the licence in the provenance), and while it runs (minutes with a
/// released-size package) its share of steps done rises in `/metrics` and in its `job.json`
/// (`progress`, saved at most once a second), and leaves `/metrics` when the job ends.
#[test]
fn a_lodge_package_is_served_with_the_jobs_progress_in_its_record_and_metrics() {
    let model = choreod_tests::package("lodge-tiny-random");
    let mut home = Home::new(&format!(
        "[runtime]\ndefault_model = '{model}'\nort_intra_threads = 1\n\n\
         [serve]\nsettle_ms = 100\nworkers = 1\n\n[job]\nseed = 1\n"
    ));
    let mut daemon = home.start();
    home.wait_healthy(&mut daemon);
    drop_file(&home.inbox(), "song.wav", &wav_bytes(45.0, 3));
    let (mut ratios, mut recorded) = (Vec::new(), Vec::new());
    let t0 = Instant::now();
    while home.outcomes() == (0, 0) {
        assert!(
            t0.elapsed() < PATIENCE && daemon.try_status().is_none(),
            "no outcome; log:\n{}",
            daemon.log_text()
        );
        ratios.extend(progress_ratios(&home));
        for id in home.names("state/work") {
            let record = home.state().join("work").join(id).join("job.json");
            let Ok(text) = std::fs::read(record) else {
                continue;
            };
            let Ok(v) = serde_json::from_slice::<serde_json::Value>(&text) else {
                continue;
            };
            if let Some(p) = v.get("progress") {
                recorded.push((p["steps_done"].as_u64(), p["steps_total"].as_u64()));
            }
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    home.wait_for_outcomes(1, &[], PATIENCE, &mut daemon);
    let motion = choreo_datasets::read_motion_file(&home.out().join("song.h5")).expect("dance");
    assert_eq!(
        motion.features.map(|f| f.representation).as_deref(),
        Some("lodge-smplx139")
    );
    let licence = motion.provenance.expect("provenance").license;
    assert!(
        licence.starts_with("licence: choreod test fixture"),
        "{licence}"
    );

    assert!(
        ratios.iter().any(|r| *r > 0.0 && *r < 1.0),
        "a running job's share in /metrics: {ratios:?}"
    );
    assert!(
        ratios.windows(2).all(|w| w[0] <= w[1]),
        "never falls: {ratios:?}"
    );
    assert!(
        !recorded.is_empty(),
        "no progress in job.json ({:?} of work)",
        t0.elapsed()
    );
    let total = recorded[0].1.expect("steps_total");
    assert!(
        recorded
            .iter()
            .all(|(done, t)| *t == Some(total) && done.is_some_and(|d| d > 0 && d <= total)),
        "{recorded:?}"
    );
    assert!(
        recorded.windows(2).all(|w| w[0].0 <= w[1].0),
        "{recorded:?}"
    );
    assert!(
        progress_ratios(&home).is_empty(),
        "the job left /metrics when it ended"
    );
}
