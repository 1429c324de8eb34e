//! `choreod live` against a real sound server: each test starts its own PulseAudio (own runtime
//! directory and socket, so tests run in parallel) with `module-pipe-source`, and feeds a real
//! song into its FIFO at real-time pace. cpal captures it through ALSA's pulse plugin exactly
//! as from a sound card. Needs `pulseaudio`, `pactl`, `chromium`, `ffmpeg` and python-osc in
//! the venv (scripts/setup installs them).
// Helpers outside #[test] functions unwrap too: a failed step is a failed test.
#![allow(clippy::unwrap_used)]

use std::io::{BufRead, BufReader, Write};
use std::net::UdpSocket;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use choreod_tests::daemon::free_port;
use choreod_tests::{choreod, fixtures, python_cmd, stderr, stdout};

const RATE: usize = 16_000;

/// A private PulseAudio server with a pipe source as the default input.
struct Pulse {
    dir: tempfile::TempDir,
}

impl Pulse {
    fn start() -> Pulse {
        let dir = tempfile::tempdir().unwrap();
        let p = Pulse { dir };
        let socket = p.dir.path().join("native");
        let status = p
            .cmd("pulseaudio")
            .args([
                "-n",
                "--daemonize=yes",
                "--exit-idle-time=-1",
                "--disallow-exit",
                "--use-pid-file=yes",
                "--log-target=stderr",
                "-L",
                &format!(
                    "module-native-protocol-unix socket={} auth-anonymous=1",
                    socket.display()
                ),
            ])
            .stderr(Stdio::null())
            .status()
            .expect("pulseaudio installed (scripts/setup)");
        assert!(status.success(), "pulseaudio did not start");
        let t0 = Instant::now();
        while !socket.exists() {
            assert!(t0.elapsed() < Duration::from_secs(10), "pulseaudio socket");
            std::thread::sleep(Duration::from_millis(20));
        }
        p.load_source();
        p
    }

    fn fifo(&self) -> PathBuf {
        self.dir.path().join("in.fifo")
    }

    /// A command with this server's environment (libpulse and ALSA's pulse plugin read it).
    fn cmd(&self, program: impl AsRef<std::ffi::OsStr>) -> Command {
        let mut c = Command::new(program);
        self.env(&mut c);
        c
    }

    fn env(&self, c: &mut Command) {
        let d = self.dir.path();
        c.env("XDG_RUNTIME_DIR", d)
            .env("PULSE_RUNTIME_PATH", d)
            .env("PULSE_STATE_PATH", d)
            .env("HOME", d)
            .env(
                "PULSE_SERVER",
                format!("unix:{}", d.join("native").display()),
            );
    }

    fn pactl(&self, args: &[&str]) {
        let out = self.cmd("pactl").args(args).output().expect("pactl");
        assert!(out.status.success(), "pactl {args:?}: {}", stderr(&out));
    }

    fn load_source(&self) {
        self.pactl(&[
            "load-module",
            "module-pipe-source",
            "source_name=filesrc",
            &format!("file={}", self.fifo().display()),
            "format=s16le",
            &format!("rate={RATE}"),
            "channels=1",
        ]);
        self.pactl(&["set-default-source", "filesrc"]);
    }

    fn unload_source(&self) {
        self.pactl(&["unload-module", "module-pipe-source"]);
    }
}

impl Drop for Pulse {
    fn drop(&mut self) {
        let _ = self.cmd("pulseaudio").arg("-k").status();
    }
}

/// The song as 16 kHz mono s16le, and the same samples as a WAV file (for the offline mel).
fn song(dir: &Path) -> (Vec<u8>, PathBuf) {
    let raw = dir.join("song.raw");
    let wav = dir.join("song.wav");
    let src = fixtures().join("audio").join("vibe_ace_44k_stereo.ogg");
    for (args, out) in [
        (vec!["-f", "s16le", "-ac", "1", "-ar", "16000"], &raw),
        (vec!["-c:a", "pcm_s16le", "-ac", "1", "-ar", "16000"], &wav),
    ] {
        let status = Command::new("ffmpeg")
            .args(["-loglevel", "error", "-y", "-i"])
            .arg(&src)
            .args(args)
            .arg(out)
            .status()
            .expect("ffmpeg installed (scripts/setup)");
        assert!(status.success());
    }
    (std::fs::read(&raw).unwrap(), wav)
}

/// Write `samples` into the FIFO at real-time pace, in 20 ms blocks, reopening the FIFO when
/// the source goes away and comes back; stops at the end or when `stop` is set.
fn feed(fifo: PathBuf, samples: Vec<u8>, stop: Arc<AtomicBool>) -> std::thread::JoinHandle<()> {
    std::thread::spawn(move || {
        use std::os::unix::fs::OpenOptionsExt;
        let block = RATE / 50 * 2;
        let t0 = Instant::now();
        let mut out: Option<std::fs::File> = None;
        for (i, chunk) in samples.chunks(block).enumerate() {
            if stop.load(Ordering::SeqCst) {
                return;
            }
            let due = t0 + Duration::from_millis(20 * i as u64);
            std::thread::sleep(due.saturating_duration_since(Instant::now()));
            if out.is_none() {
                // Non-blocking open: fails (ENXIO) while no source reads the FIFO.
                out = std::fs::OpenOptions::new()
                    .write(true)
                    .custom_flags(libc_o_nonblock())
                    .open(&fifo)
                    .ok();
            }
            if let Some(f) = out.as_mut()
                && f.write_all(chunk).is_err()
            {
                out = None;
            }
        }
    })
}

/// O_NONBLOCK on Linux (asm-generic/fcntl.h: 00004000).
fn libc_o_nonblock() -> i32 {
    0o4000
}

fn live(pulse: &Pulse, args: &[&str]) -> Child {
    let mut c = choreod();
    pulse.env(&mut c);
    c.arg("live")
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn choreod live")
}

fn finish(child: Child) -> serde_json::Value {
    let out = child.wait_with_output().unwrap();
    assert!(
        out.status.success(),
        "choreod live failed: {}",
        stderr(&out)
    );
    serde_json::from_str(stdout(&out).trim()).expect("--stats JSON line")
}

/// Run a Python snippet with `args`; its stdout is one JSON line.
fn py(script: &str, args: &[&str]) -> serde_json::Value {
    let out = python_cmd()
        .arg("-c")
        .arg(script)
        .args(args)
        .output()
        .expect("run python");
    assert!(out.status.success(), "python: {}", stderr(&out));
    serde_json::from_str(stdout(&out).trim()).expect("python JSON")
}

/// h5py's view of a motion file: frames, joints, mel frames.
const H5_SUMMARY: &str = r#"
import h5py, json, sys
with h5py.File(sys.argv[1], "r") as f:
    j = f["motion/joints"]
    m = f["audio/mel"]
    ok = bool(__import__("numpy").isfinite(j[:]).all())
    print(json.dumps({"frames": j.shape[0], "joints": j.shape[1], "mel": list(m.shape),
                      "finite": ok, "format": f.attrs["format"]}))
"#;

/// Captured mel against the offline mel of the same samples, aligned by the best lag of the
/// frame-energy envelopes.
const MEL_COMPARE: &str = r#"
import h5py, json, sys, numpy as np
with h5py.File(sys.argv[1], "r") as f:
    cap = f["audio/mel"][:].astype(np.float64)
ref = np.load(sys.argv[2]).T.astype(np.float64)
floor = ref.max() - 80.0
cap = np.maximum(cap, floor)
# The feed starts before choreod listens, so the capture starts somewhere in the song:
# cap[i] ~ ref[i + k] for the best k.
n = len(cap) - 8
env_c, env_r = cap[:n].mean(1), ref.mean(1)
best = max(range(0, len(ref) - n), key=lambda k: np.corrcoef(env_c, env_r[k:k + n])[0, 1])
a, b = cap[:n], ref[best:best + n]
diff = np.abs(a - b)
loud = b > floor + 20
print(json.dumps({"lag": best, "frames": n, "median_db": float(np.median(diff[loud])),
                  "p90_db": float(np.percentile(diff[loud], 90)),
                  "corr": float(np.corrcoef(a.ravel(), b.ravel())[0, 1])}))
"#;

/// Receive VMC bundles for `seconds` with python-osc and check every message.
const OSC_RECEIVER: &str = r#"
import json, socket, sys, time, math
from pythonosc.osc_bundle import OscBundle
from pythonosc.osc_message import OscMessage
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.bind(("127.0.0.1", int(sys.argv[1])))
s.settimeout(0.5)
print("ready", flush=True)
end = time.time() + float(sys.argv[2])
times, names, bad, bones = [], set(), 0, 0
while time.time() < end:
    try:
        data = s.recv(65536)
    except socket.timeout:
        continue
    times.append(time.time())
    b = OscBundle(data)
    addrs = [m.address for m in b]
    if "/VMC/Ext/OK" not in addrs or "/VMC/Ext/T" not in addrs or "/VMC/Ext/Root/Pos" not in addrs:
        bad += 1
    for m in b:
        if m.address == "/VMC/Ext/Bone/Pos":
            p = m.params
            if len(p) != 8 or not isinstance(p[0], str) or not all(isinstance(v, float) for v in p[1:]):
                bad += 1
                continue
            if abs(math.sqrt(sum(v * v for v in p[4:])) - 1.0) > 1e-3:
                bad += 1
            names.add(p[0]); bones += 1
span = times[-1] - times[0] if len(times) > 1 else 0.0
print(json.dumps({"bundles": len(times), "rate": (len(times) - 1) / span if span else 0.0,
                  "names": sorted(names), "bad": bad, "bones": bones}))
"#;

/// A headless Chromium showing `url`, driven through the DevTools protocol.
struct Browser {
    child: Child,
    socket: tungstenite::WebSocket<tungstenite::stream::MaybeTlsStream<std::net::TcpStream>>,
    _profile: tempfile::TempDir,
    next_id: u64,
}

impl Browser {
    fn open(url: &str) -> Browser {
        let profile = tempfile::tempdir().unwrap();
        let port = free_port();
        let mut child = Command::new("/usr/bin/chromium")
            .args([
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                "--disable-quic",
                "--no-first-run",
                "--disable-background-networking",
                "--disable-component-update",
                "--disable-sync",
                "--window-size=640,480",
                &format!("--remote-debugging-port={port}"),
                &format!("--user-data-dir={}", profile.path().display()),
                url,
            ])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("chromium installed (scripts/setup)");
        let t0 = Instant::now();
        let ws_url = loop {
            if t0.elapsed() > Duration::from_secs(20) {
                // Do not leave the browser behind when the test fails.
                let _ = child.kill();
                let _ = child.wait();
                panic!("chromium DevTools did not answer on port {port}");
            }
            if let Ok(list) = http_get(port, "/json/list")
                && let Ok(v) = serde_json::from_str::<serde_json::Value>(&list)
                && let Some(u) = v.as_array().and_then(|a| {
                    a.iter()
                        .find(|t| t["type"] == "page")
                        .and_then(|t| t["webSocketDebuggerUrl"].as_str())
                })
            {
                break u.to_owned();
            }
            std::thread::sleep(Duration::from_millis(100));
        };
        let socket = match tungstenite::connect(ws_url.as_str()) {
            Ok((socket, _)) => socket,
            Err(e) => {
                let _ = child.kill();
                let _ = child.wait();
                panic!("DevTools socket {ws_url}: {e}");
            }
        };
        Browser {
            child,
            socket,
            _profile: profile,
            next_id: 0,
        }
    }

    /// Evaluate a JS expression in the page (its value as JSON).
    fn eval(&mut self, expression: &str) -> serde_json::Value {
        self.next_id += 1;
        let id = self.next_id;
        let msg = serde_json::json!({"id": id, "method": "Runtime.evaluate",
            "params": {"expression": expression, "returnByValue": true}});
        self.socket
            .send(tungstenite::Message::text(msg.to_string()))
            .unwrap();
        loop {
            let m = self.socket.read().expect("DevTools reply");
            if let Ok(text) = m.to_text()
                && let Ok(v) = serde_json::from_str::<serde_json::Value>(text)
                && v["id"] == id
            {
                return v["result"]["result"]["value"].clone();
            }
        }
    }

    /// What the page shows: frame index, frames received, joints, and canvas pixels that are
    /// not the background (a drawn skeleton).
    fn state(&mut self) -> serde_json::Value {
        let v = self.eval(
            r#"JSON.stringify({
                mode: document.getElementById("mode").textContent,
                frame: +document.getElementById("frame").textContent,
                joints: +document.getElementById("joints").textContent,
                inked: (() => { const c = document.getElementById("view");
                    const d = c.getContext("2d").getImageData(0, 0, c.width, c.height).data;
                    let n = 0;
                    for (let i = 0; i < d.length; i += 4)
                        if (d[i] !== 0x16 || d[i + 1] !== 0x18 || d[i + 2] !== 0x1d) n++;
                    return n; })()})"#,
        );
        serde_json::from_str(v.as_str().unwrap_or("{}")).unwrap()
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn http_get(port: u16, path: &str) -> std::io::Result<String> {
    use std::io::Read;
    let mut s = std::net::TcpStream::connect(("127.0.0.1", port))?;
    s.set_read_timeout(Some(Duration::from_secs(5)))?;
    write!(
        s,
        "GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: close\r\n\r\n"
    )?;
    // Chromium keeps the connection open: read the headers, then Content-Length bytes.
    let mut data = Vec::new();
    let mut buf = [0u8; 8192];
    loop {
        let n = s.read(&mut buf)?;
        if n == 0 {
            break;
        }
        data.extend_from_slice(&buf[..n]);
        let text = String::from_utf8_lossy(&data);
        if let Some((head, body)) = text.split_once("\r\n\r\n") {
            let len = head
                .lines()
                .find_map(|l| {
                    let (k, v) = l.split_once(':')?;
                    k.eq_ignore_ascii_case("content-length")
                        .then(|| v.trim().parse::<usize>().ok())?
                })
                .unwrap_or(usize::MAX);
            if body.len() >= len {
                return Ok(body.to_owned());
            }
        }
    }
    let text = String::from_utf8_lossy(&data).into_owned();
    Ok(text
        .split_once("\r\n\r\n")
        .map_or(text.clone(), |(_, b)| b.to_owned()))
}

/// Wait for the viewer URL line on choreod's stderr; the rest of stderr keeps draining.
fn viewer_url(child: &mut Child) -> String {
    let err = child.stderr.take().unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(err).lines().map_while(Result::ok) {
            if let Some(url) = line.strip_prefix("viewer: ") {
                let _ = tx.send(url.to_owned());
            }
        }
    });
    rx.recv_timeout(Duration::from_secs(30))
        .expect("choreod printed the viewer URL")
}

#[test]
fn live_session_captures_the_song_and_feeds_every_sink() {
    let work = tempfile::tempdir().unwrap();
    let pulse = Pulse::start();
    let (raw, wav) = song(work.path());
    let reference = work.path().join("ref.npy");
    let out = choreod()
        .args(["mel"])
        .arg(&wav)
        .arg("-o")
        .arg(&reference)
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", stderr(&out));

    // The OSC receiver listens before choreod sends.
    let osc_port = UdpSocket::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let mut receiver = python_cmd()
        .args(["-c", OSC_RECEIVER, &osc_port.to_string(), "9"])
        .stdout(Stdio::piped())
        .spawn()
        .expect("python");
    let mut rstdout = BufReader::new(receiver.stdout.take().unwrap());
    let mut ready = String::new();
    rstdout.read_line(&mut ready).unwrap();
    assert_eq!(ready.trim(), "ready");

    let stop = Arc::new(AtomicBool::new(false));
    let feeder = feed(pulse.fifo(), raw, stop.clone());
    let h5 = work.path().join("take.h5");
    let mut child = live(
        &pulse,
        &[
            "-o",
            h5.to_str().unwrap(),
            "--duration",
            "12",
            "--stats",
            "--viewer",
            "127.0.0.1:0",
            "--osc",
            &format!("127.0.0.1:{osc_port}"),
        ],
    );
    let url = viewer_url(&mut child);

    // The viewer in a real browser: joints, a drawn skeleton, a frame counter that advances.
    let mut browser = Browser::open(&url);
    std::thread::sleep(Duration::from_secs(3));
    let first = browser.state();
    std::thread::sleep(Duration::from_secs(2));
    let second = browser.state();
    drop(browser);
    assert_eq!(first["mode"], "live", "{first}");
    assert_eq!(second["joints"], 24, "{second}");
    assert!(
        first["frame"].as_i64().unwrap() >= 0,
        "no frame yet: {first}"
    );
    assert!(
        second["frame"].as_i64() > first["frame"].as_i64(),
        "frame counter did not advance: {first} then {second}"
    );
    assert!(
        second["inked"].as_i64().unwrap() > 500,
        "blank canvas: {second}"
    );

    let stats = finish(child);
    stop.store(true, Ordering::SeqCst);
    feeder.join().unwrap();

    // Capture: nothing dropped, the song heard.
    assert_eq!(stats["overruns"], 0, "{stats}");
    assert_eq!(stats["reconnects"], 0, "{stats}");
    let frames = stats["frames"].as_u64().unwrap();
    // 12 s of audio at 30 fps, emitted in 0.5 s hops: at least 11 s of motion.
    assert!(frames >= 330, "{stats}");
    let file = py(H5_SUMMARY, &[h5.to_str().unwrap()]);
    assert_eq!(file["frames"].as_u64(), Some(frames), "{file}");
    assert_eq!(file["joints"], 24);
    assert_eq!(file["finite"], true);
    assert_eq!(file["format"], "choreod-motion");
    assert_eq!(file["mel"][1], 80);
    assert_eq!(file["mel"][0], stats["mel_frames"]);

    // The captured mel is the offline mel of the same samples. Tolerance: the server
    // resamples 16 kHz → 48 kHz (cpal opens the device at its default rate) and choreod back
    // to 16 kHz, and the capture starts at an arbitrary sample, i.e. up to half a hop
    // (256 samples) off the offline frame grid, which this lag search cannot undo. The offline
    // mel of the same song shifted by 64 / 128 / 256 samples gives median 0.33 / 0.65 / 1.29 dB,
    // p90 0.94 / 1.85 / 3.61 dB, correlation 0.999 / 0.997 / 0.989 over loud bins (> floor +
    // 20 dB); captures measured median 0.28-1.09 dB, p90 0.91-3.49 dB. The bounds are the
    // half-hop worst case plus ~25 % for the two resamplers. A wrong band, scale or resampling
    // ratio gives errors of tens of dB (stereo taken as mono: median 13.8 dB, corr 0.81).
    let cmp = py(
        MEL_COMPARE,
        &[h5.to_str().unwrap(), reference.to_str().unwrap()],
    );
    eprintln!("mel comparison: {cmp}");
    assert!(cmp["frames"].as_u64().unwrap() >= 300, "{cmp}");
    assert!(cmp["median_db"].as_f64().unwrap() < 1.6, "{cmp}");
    assert!(cmp["p90_db"].as_f64().unwrap() < 4.5, "{cmp}");
    assert!(cmp["corr"].as_f64().unwrap() > 0.98, "{cmp}");

    // VMC over OSC: well-formed bones at the motion's 30 fps.
    let mut line = String::new();
    rstdout.read_line(&mut line).unwrap();
    receiver.wait().unwrap();
    let osc: serde_json::Value = serde_json::from_str(line.trim()).expect("receiver JSON");
    eprintln!("osc: {osc}");
    assert_eq!(osc["bad"], 0, "{osc}");
    assert!(osc["bundles"].as_u64().unwrap() >= 150, "{osc}");
    let rate = osc["rate"].as_f64().unwrap();
    assert!((25.0..=35.0).contains(&rate), "{osc}");
    let names: Vec<&str> = osc["names"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|n| n.as_str())
        .collect();
    assert_eq!(names.len(), 22, "{osc}");
    for n in [
        "Hips",
        "Spine",
        "Chest",
        "UpperChest",
        "Neck",
        "Head",
        "LeftUpperLeg",
        "RightHand",
    ] {
        assert!(names.contains(&n), "{n} missing: {osc}");
    }

    // The finished file in the viewer: `choreod view` plays it back.
    let mut view = choreod()
        .arg("view")
        .arg(&h5)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut url = String::new();
    BufReader::new(view.stdout.take().unwrap())
        .read_line(&mut url)
        .unwrap();
    let mut browser = Browser::open(url.trim());
    std::thread::sleep(Duration::from_secs(2));
    let a = browser.state();
    std::thread::sleep(Duration::from_millis(700));
    let b = browser.state();
    drop(browser);
    let _ = view.kill();
    let _ = view.wait();
    assert_eq!(a["mode"], "file", "{a}");
    assert_eq!(a["joints"], 24, "{a}");
    assert!(
        b["frame"].as_i64() != a["frame"].as_i64(),
        "playback stuck: {a} {b}"
    );
    assert!(b["inked"].as_i64().unwrap() > 500, "blank canvas: {b}");
}

#[test]
fn device_loss_reconnects_and_the_file_stays_valid() {
    let work = tempfile::tempdir().unwrap();
    let pulse = Pulse::start();
    let (raw, _) = song(work.path());
    let stop = Arc::new(AtomicBool::new(false));
    let feeder = feed(pulse.fifo(), raw, stop.clone());
    let h5 = work.path().join("loss.h5");
    let child = live(
        &pulse,
        &["-o", h5.to_str().unwrap(), "--duration", "10", "--stats"],
    );
    std::thread::sleep(Duration::from_secs(4));
    pulse.unload_source();
    std::thread::sleep(Duration::from_secs(2));
    pulse.load_source();
    let stats = finish(child);
    stop.store(true, Ordering::SeqCst);
    feeder.join().unwrap();
    assert!(stats["device_losses"].as_u64().unwrap() >= 1, "{stats}");
    assert!(stats["reconnects"].as_u64().unwrap() >= 1, "{stats}");
    let file = py(H5_SUMMARY, &[h5.to_str().unwrap()]);
    assert_eq!(file["frames"], stats["frames"], "{file}");
    assert!(file["frames"].as_u64().unwrap() >= 270, "{file} {stats}");
    assert_eq!(file["finite"], true);
}

#[test]
fn kill_9_leaves_a_readable_file_with_the_flushed_frames() {
    let work = tempfile::tempdir().unwrap();
    let pulse = Pulse::start();
    let (raw, _) = song(work.path());
    let stop = Arc::new(AtomicBool::new(false));
    let feeder = feed(pulse.fifo(), raw, stop.clone());
    let h5 = work.path().join("crash.h5");
    let mut child = live(&pulse, &["-o", h5.to_str().unwrap()]);
    std::thread::sleep(Duration::from_secs(6));
    child.kill().unwrap(); // SIGKILL
    child.wait().unwrap();
    stop.store(true, Ordering::SeqCst);
    feeder.join().unwrap();
    assert!(
        !h5.exists(),
        "an unfinished session must not appear under its final name"
    );
    let temp: Vec<PathBuf> = std::fs::read_dir(work.path())
        .unwrap()
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.file_name()
                .is_some_and(|n| n.to_string_lossy().starts_with(".crash.h5.tmp-"))
        })
        .collect();
    assert_eq!(temp.len(), 1, "{temp:?}");
    let file = py(H5_SUMMARY, &[temp[0].to_str().unwrap()]);
    // ~6 s in, flushed every 0.5 s: at least 3 s of motion and its mel are on disk.
    assert!(file["frames"].as_u64().unwrap() >= 90, "{file}");
    assert!(file["mel"][0].as_u64().unwrap() >= 90, "{file}");
    assert_eq!(file["finite"], true);
}
