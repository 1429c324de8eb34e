//! Helpers for the `choreod serve` tests (`tests/tests/serve_*.rs`): a temporary daemon home
//! with its config, a guard that kills the daemon on drop, synthetic songs, and waiting.

use std::collections::BTreeMap;
use std::fs;
use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, ExitStatus, Stdio};
use std::time::{Duration, Instant};

/// A daemon home: `inbox/`, `out/`, `state/`, `choreod.toml`, and the daemon's stderr logs.
#[derive(Debug)]
pub struct Home {
    pub dir: tempfile::TempDir,
    pub port: u16,
    starts: usize,
}

impl Home {
    /// Folders plus a config with `extra` TOML appended (e.g. `[serve]\nworkers = 2\n`).
    /// Sections given in `extra` replace the defaults written here ([serve], [job], [limits]).
    pub fn new(extra: &str) -> Self {
        Self::with_paths(extra, "inbox", "state")
    }

    /// Like [`Home::new`], with `paths.inbox` and `paths.state` as given (relative to the home,
    /// or absolute: another home's inbox, a folder on another filesystem). Relative ones are
    /// created.
    pub fn with_paths(extra: &str, inbox: &str, state: &str) -> Self {
        let dir = tempfile::Builder::new()
            .prefix("choreod-serve-")
            .tempdir()
            .expect("temp dir");
        for d in ["inbox", "out", "state", inbox, state] {
            fs::create_dir_all(dir.path().join(d)).expect("mkdir");
        }
        let port = free_port();
        let mut text = format!(
            "[paths]\ninbox = \"{inbox}\"\noutput = \"out\"\nstate = \"{state}\"\n\n\
             [metrics]\nbind = \"127.0.0.1:{port}\"\n\n"
        );
        text.push_str(extra);
        if !extra.contains("[limits]") {
            // Temporary folders on small CI disks may have less than the 256 MiB default free.
            // The synthetic songs are 1-4 s, shorter than the model's 5 s window, the default
            // minimum (tested in daemon_hardening with a truncated real song).
            text.push_str("\n[limits]\nmin_free_disk_mb = 1.0\nmin_audio_seconds = 0.5\n");
        }
        if !extra.contains("[serve]") {
            text.push_str("\n[serve]\nsettle_ms = 200\nworkers = 2\n");
        }
        if !extra.contains("[job]") {
            // Two denoising steps keep a 1-2 s song at tens of milliseconds.
            text.push_str("\n[job]\nsteps = 2\n");
        }
        fs::write(dir.path().join("choreod.toml"), text).expect("write config");
        Self {
            dir,
            port,
            starts: 0,
        }
    }

    pub fn path(&self) -> &Path {
        self.dir.path()
    }
    pub fn config(&self) -> PathBuf {
        self.path().join("choreod.toml")
    }
    pub fn inbox(&self) -> PathBuf {
        self.path().join("inbox")
    }
    pub fn out(&self) -> PathBuf {
        self.path().join("out")
    }
    pub fn state(&self) -> PathBuf {
        self.path().join("state")
    }

    /// Start `choreod serve` on this home; stderr goes to `log-<n>.txt`.
    pub fn start(&mut self) -> Daemon {
        self.start_with_env(&[])
    }

    /// [`Home::start`] with extra environment variables (e.g. `CHOREOD_FAULT`).
    pub fn start_with_env(&mut self, env: &[(&str, &str)]) -> Daemon {
        self.starts += 1;
        let log = self.path().join(format!("log-{}.txt", self.starts));
        let err = fs::File::create(&log).expect("log file");
        let child = crate::choreod()
            .envs(env.iter().copied())
            .args(["--log-level", "info", "serve", "--config"])
            .arg(self.path().join("choreod.toml"))
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(err)
            .spawn()
            .expect("spawn choreod serve");
        Daemon {
            child: Some(child),
            log,
        }
    }

    /// Sorted names in a folder of the home (`"inbox"`, `"out"`, `"state/done"`, …).
    pub fn names(&self, sub: &str) -> Vec<String> {
        names(&self.path().join(sub))
    }

    /// Motion files in `out/` plus error reports in `state/failed/`.
    pub fn outcomes(&self) -> (usize, usize) {
        let h5 = self
            .names("out")
            .iter()
            .filter(|n| n.ends_with(".h5") && !n.starts_with('.'))
            .count();
        let reports = self
            .names("state/failed")
            .iter()
            .filter(|n| n.ends_with(".error.json"))
            .count();
        (h5, reports)
    }

    /// Wait until `want` outcomes exist, the inbox holds only `ignored` and `state/work` is empty.
    pub fn wait_for_outcomes(
        &self,
        want: usize,
        ignored: &[&str],
        timeout: Duration,
        daemon: &mut Daemon,
    ) {
        let t0 = Instant::now();
        loop {
            let (h5, reports) = self.outcomes();
            let idle = self.names("inbox") == ignored && self.names("state/work").is_empty();
            if h5 + reports >= want && idle {
                return;
            }
            if let Some(status) = daemon.try_status() {
                panic!(
                    "daemon exited early ({status}); log:\n{}",
                    daemon.log_text()
                );
            }
            assert!(
                t0.elapsed() < timeout,
                "timed out after {timeout:?}: {h5} motion files + {reports} reports of {want}; inbox {:?}, work {:?}; log:\n{}",
                self.names("inbox").len(),
                self.names("state/work"),
                daemon.log_text()
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// The error reports in `state/failed/`, parsed, in name order.
    pub fn reports(&self) -> Vec<serde_json::Value> {
        self.names("state/failed")
            .iter()
            .filter(|n| n.ends_with(".error.json"))
            .map(|n| {
                let text = fs::read(self.state().join("failed").join(n)).expect("report");
                serde_json::from_slice(&text).expect("report is JSON")
            })
            .collect()
    }

    /// GET `path` on the metrics endpoint: (status line, body).
    pub fn http_get(&self, path: &str) -> std::io::Result<(String, String)> {
        http_get(
            self.port,
            path,
            "Host: localhost\r\n",
            Duration::from_secs(5),
        )
    }

    /// A gauge or counter without labels from `/metrics` (`None` when unreachable or absent).
    pub fn metric(&self, name: &str) -> Option<f64> {
        let (_, body) = self.http_get("/metrics").ok()?;
        body.lines()
            .find_map(|l| l.strip_prefix(name)?.strip_prefix(' ')?.parse().ok())
    }

    /// Wait until `/healthz` answers 200.
    pub fn wait_healthy(&self, daemon: &mut Daemon) {
        let t0 = Instant::now();
        while t0.elapsed() < Duration::from_secs(30) {
            if let Ok((status, _)) = self.http_get("/healthz")
                && status.contains(" 200 ")
            {
                return;
            }
            if let Some(status) = daemon.try_status() {
                panic!("daemon exited ({status}); log:\n{}", daemon.log_text());
            }
            std::thread::sleep(Duration::from_millis(25));
        }
        panic!("daemon not healthy after 30 s; log:\n{}", daemon.log_text());
    }
}

/// A running daemon; killed (SIGKILL) and reaped when dropped, so a failing test never leaves
/// one behind.
#[derive(Debug)]
pub struct Daemon {
    child: Option<Child>,
    pub log: PathBuf,
}

impl Daemon {
    pub fn pid(&self) -> u32 {
        self.child.as_ref().map_or(0, Child::id)
    }

    /// `kill -9` and reap.
    pub fn kill9(&mut self) {
        if let Some(mut c) = self.child.take() {
            let _ = c.kill();
            let _ = c.wait();
        }
    }

    /// Send SIGTERM (through `kill(1)`: the tests have no libc binding).
    pub fn term(&self) {
        // `kill -TERM 0` would signal the whole process group, test runner included.
        assert!(
            self.child.is_some(),
            "no daemon to signal: it was killed already"
        );
        let status = std::process::Command::new("kill")
            .args(["-TERM", &self.pid().to_string()])
            .status()
            .expect("run kill");
        assert!(status.success(), "kill -TERM failed");
    }

    /// Wait for the exit for at most `timeout`; `None` when it is still running.
    pub fn wait_exit(&mut self, timeout: Duration) -> Option<ExitStatus> {
        let t0 = Instant::now();
        loop {
            if let Some(s) = self.try_status() {
                return Some(s);
            }
            if t0.elapsed() >= timeout {
                return None;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// The exit status if it has exited.
    pub fn try_status(&mut self) -> Option<ExitStatus> {
        self.child
            .as_mut()
            .and_then(|c| c.try_wait().ok().flatten())
    }

    pub fn log_text(&self) -> String {
        fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// Poll `done` until it holds, failing with `what` and the log after `timeout` or when the
    /// daemon exits.
    pub fn wait_until(&mut self, what: &str, timeout: Duration, mut done: impl FnMut() -> bool) {
        let t0 = Instant::now();
        while !done() {
            if let Some(status) = self.try_status() {
                panic!(
                    "daemon exited ({status}) waiting for {what}; log:\n{}",
                    self.log_text()
                );
            }
            assert!(
                t0.elapsed() < timeout,
                "no {what} after {timeout:?}; log:\n{}",
                self.log_text()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// Wait until the log contains `needle`.
    pub fn wait_log(&mut self, needle: &str, timeout: Duration) {
        let t0 = Instant::now();
        while !self.log_text().contains(needle) {
            if let Some(status) = self.try_status() {
                panic!(
                    "daemon exited ({status}) before logging {needle:?}; log:\n{}",
                    self.log_text()
                );
            }
            assert!(
                t0.elapsed() < timeout,
                "no {needle:?} in the log after {timeout:?}:\n{}",
                self.log_text()
            );
            std::thread::sleep(Duration::from_millis(10));
        }
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        self.kill9();
    }
}

/// A port that was free a moment ago (bind port 0, read it, release it).
pub fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .expect("free port")
}

/// Sorted file names in `dir` (empty when it does not exist).
pub fn names(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = fs::read_dir(dir)
        .map(|rd| {
            rd.filter_map(Result::ok)
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .collect()
        })
        .unwrap_or_default();
    v.sort();
    v
}

/// A 16 kHz mono 16-bit WAV: a tone (frequency varies with `variant`, so songs differ) with a
/// click every half second (a 120 BPM beat).
pub fn wav_bytes(seconds: f64, variant: u32) -> Vec<u8> {
    let rate = 16_000u32;
    let n = (seconds * f64::from(rate)).round() as u32;
    let freq = 220.0 + 7.0 * f64::from(variant % 200);
    let samples: Vec<f32> = (0..n)
        .map(|i| {
            let t = f64::from(i) / f64::from(rate);
            let beat = (t % 0.5) < 0.01;
            let v =
                0.3 * (2.0 * std::f64::consts::PI * freq * t).sin() + if beat { 0.5 } else { 0.0 };
            (v * 0.9) as f32
        })
        .collect();
    pcm16_wav(rate, &samples)
}

/// A mono 16-bit PCM WAV of `samples` (in [-1, 1]) at `rate` Hz: a 44-byte header, then the
/// samples, 2 bytes each.
pub fn pcm16_wav(rate: u32, samples: &[f32]) -> Vec<u8> {
    let data_len = 2 * samples.len() as u32;
    let mut out = Vec::with_capacity(44 + data_len as usize);
    out.extend_from_slice(b"RIFF");
    out.extend_from_slice(&(36 + data_len).to_le_bytes());
    out.extend_from_slice(b"WAVEfmt ");
    out.extend_from_slice(&16u32.to_le_bytes());
    out.extend_from_slice(&1u16.to_le_bytes()); // PCM
    out.extend_from_slice(&1u16.to_le_bytes()); // mono
    out.extend_from_slice(&rate.to_le_bytes());
    out.extend_from_slice(&(rate * 2).to_le_bytes());
    out.extend_from_slice(&2u16.to_le_bytes());
    out.extend_from_slice(&16u16.to_le_bytes());
    out.extend_from_slice(b"data");
    out.extend_from_slice(&data_len.to_le_bytes());
    for &v in samples {
        out.extend_from_slice(&((v.clamp(-1.0, 1.0) * 32767.0) as i16).to_le_bytes());
    }
    out
}

/// Bytes that no decoder accepts, in one of a few flavours (garbage, empty, text, a WAV
/// header whose format chunk is cut off).
pub fn corrupt_bytes(variant: u32) -> Vec<u8> {
    match variant % 4 {
        0 => (0..4096u32)
            .map(|i| (i.wrapping_mul(2_654_435_761).wrapping_add(variant) >> 13) as u8)
            .collect(),
        1 => Vec::new(),
        2 => b"this is not audio\n".repeat(50),
        _ => wav_bytes(1.0, variant)[..30].to_vec(),
    }
}

/// Write `bytes` as `inbox/<name>` the way a careful client does: to a hidden temporary name,
/// then renamed in (so the daemon sees the file complete at once).
pub fn drop_file(inbox: &Path, name: &str, bytes: &[u8]) {
    let tmp = inbox.join(format!(".{name}.uploading"));
    fs::write(&tmp, bytes).expect("write song");
    fs::rename(&tmp, inbox.join(name)).expect("rename song");
}

/// A small deterministic generator (xorshift64*) for test schedules; seed printed by callers.
#[derive(Debug)]
pub struct Rng(u64);

impl Rng {
    pub fn new(seed: u64) -> Self {
        Self(seed.max(1))
    }
    /// Uniform in `lo..hi`.
    pub fn range(&mut self, lo: u64, hi: u64) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        lo + self.0.wrapping_mul(0x2545_F491_4F6C_DD1D) % (hi - lo).max(1)
    }
}

/// Generous bound for a few short jobs on a loaded 2-core machine; only a failure waits it out.
pub const PATIENCE: Duration = Duration::from_secs(120);

pub fn exit_code(daemon: &mut Daemon) -> i32 {
    daemon
        .wait_exit(PATIENCE)
        .expect("the daemon refuses to start and exits")
        .code()
        .expect("an exit code, not a signal")
}

/// Frames in a motion file the daemon or `dance` wrote.
pub fn frames(h5: &Path) -> usize {
    choreo_datasets::read_motion_file(h5)
        .expect("a complete motion file")
        .joints
        .shape()[0]
}

/// Good songs for the crash tests: `n` songs of `base_s` to `base_s` + 4 s (at 250 steps a
/// 6 s song is a job of a few hundred ms on an idle 2-core machine).
pub fn drop_songs(home: &Home, n: u32, base_s: f64) -> Vec<String> {
    (0..n)
        .map(|i| {
            let name = format!("song-{i:02}.wav");
            drop_file(
                &home.inbox(),
                &name,
                &wav_bytes(base_s + f64::from(i % 5), i),
            );
            name
        })
        .collect()
}

/// The log without its colour codes (the human format colours even when stderr is a file).
pub fn plain(log: &str) -> String {
    let mut out = String::with_capacity(log.len());
    let mut rest = log;
    while let Some(i) = rest.find('\x1b') {
        out.push_str(&rest[..i]);
        rest = &rest[i..];
        rest = rest.find('m').map_or("", |m| &rest[m + 1..]);
    }
    out.push_str(rest);
    out
}

/// Check from one daemon's log (lines are written in order) that every job that ran alone
/// started when no other job was running and that no job started beside it; returns how many
/// ran alone. A job logs "job started" after it is let in and "job done"/"job failed" before
/// it leaves, so the order of those lines is the order of the gate.
pub fn assert_suspects_ran_alone(log: &str) -> usize {
    let mut running: BTreeMap<String, bool> = BTreeMap::new();
    let mut alone = 0;
    for line in plain(log).lines() {
        let Some(id) = line
            .split("job{job=")
            .nth(1)
            .and_then(|rest| rest.split(' ').next())
        else {
            continue;
        };
        if line.contains(" job started ") {
            let solo = line.contains("alone=true");
            assert!(
                !running.values().any(|&s| s) && (!solo || running.is_empty()),
                "{id} started beside {running:?} (alone = {solo}):\n{log}"
            );
            alone += usize::from(solo);
            running.insert(id.to_string(), solo);
        } else if line.contains(" job done ") || line.contains(" job failed ") {
            running.remove(id);
        }
    }
    alone
}

/// How many suspects a daemon said it resumes (0 when it resumed none).
pub fn suspects_announced(log: &str) -> usize {
    plain(log)
        .lines()
        .find(|l| l.contains("resuming jobs left by the last run"))
        .and_then(|l| {
            l.split("suspects=")
                .nth(1)?
                .split_whitespace()
                .next()?
                .parse()
                .ok()
        })
        .unwrap_or(0)
}

/// A client that holds a connection to the metrics endpoint open without finishing a request:
/// it sends `drip` one byte every `interval` (nothing at all when `drip` is empty) and reports
/// when it saw the server close the connection, `None` if it was still open after `give_up`.
pub fn hanging_client(
    port: u16,
    drip: &'static [u8],
    interval: Duration,
    give_up: Duration,
) -> std::thread::JoinHandle<Option<Instant>> {
    use std::io::{ErrorKind, Read, Write};
    let mut stream = std::net::TcpStream::connect(("127.0.0.1", port)).expect("connect");
    let t0 = Instant::now();
    std::thread::spawn(move || {
        // Reading is how a closed connection shows: EOF or a reset. Anything the server says
        // first (such as a 408) is read and the wait goes on until it closes.
        stream
            .set_read_timeout(Some(interval))
            .expect("set a read timeout");
        let mut bytes = drip.iter();
        let mut buf = [0u8; 512];
        while t0.elapsed() < give_up {
            if let Some(b) = bytes.next()
                && stream.write_all(&[*b]).is_err()
            {
                return Some(Instant::now());
            }
            match stream.read(&mut buf) {
                Ok(0) => return Some(Instant::now()),
                Ok(_) => {}
                Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => {}
                Err(_) => return Some(Instant::now()),
            }
        }
        None
    })
}

/// The SHA-256 (hex) of the input a motion file's provenance names.
pub fn source_sha256(h5: &Path) -> String {
    choreo_datasets::read_motion_file(h5)
        .expect("a complete motion file")
        .provenance
        .expect("a daemon's motion file has provenance")
        .source_sha256
}

/// One raw HTTP/1.1 GET of `path` on the loopback `port` with extra `headers` (each ending
/// `\r\n`) and a read timeout: (status line, body), or the I/O error (a reset, a timeout).
pub fn http_get(
    port: u16,
    path: &str,
    headers: &str,
    timeout: Duration,
) -> std::io::Result<(String, String)> {
    let mut s = TcpStream::connect(("127.0.0.1", port))?;
    s.set_read_timeout(Some(timeout))?;
    write!(
        s,
        "GET {path} HTTP/1.1\r\n{headers}Connection: close\r\n\r\n"
    )?;
    let mut text = String::new();
    s.read_to_string(&mut text)?;
    let (head, body) = text.split_once("\r\n\r\n").unwrap_or((&text, ""));
    Ok((
        head.lines().next().unwrap_or("").to_string(),
        body.to_string(),
    ))
}
