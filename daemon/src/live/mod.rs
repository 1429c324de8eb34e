//! Live input: a sound card in, dance out in real time.
//!
//! Threads of a session:
//! - the audio callback ([`capture`]): copies samples into a lock-free ring, nothing else;
//! - the feature thread: drains the ring, mixes to mono and feeds [`choreo_dsp::LogMelStream`]
//!   (the streaming code files use too), which resamples and computes log-mel frames; it never
//!   waits for the generator, so a slow generator can never stall capture;
//! - the generator (the calling thread): feeds the heard mel to a [`choreo_models::LiveDance`],
//!   which every hop generates the newest window and fits its new frames to the session's rigid
//!   skeleton, with as many steps as the time budget allows ([`engine`]), and writes them to the
//!   HDF5 file (flushed at least once a second, with the mel heard so far);
//! - the player ([`player`]): sends each frame at its time on a schedule tied to the audio (a
//!   window's frames leave one frame period apart, the latency budget absorbing the generator's
//!   jitter) to the viewer's WebSocket ([`viewer`], [`LiveViewer`]) and as VMC bone messages
//!   over OSC/UDP ([`vmc`]).
//!
//! When the input delivers nothing, every thread waits (sleeps) and the viewer shows "waiting
//! for audio"; `--duration` counts audio heard, `--max-wall-time` the clock.
//!
//! The generator and the feature thread run at a raised priority ([`priority`], `--nice`) when
//! the system allows it.
//!
//! `choreod live` runs one session; `choreod serve` runs them beside the watch folder
//! ([`source`]).

pub mod capture;
pub mod engine;
pub mod metrics;
pub mod player;
pub mod priority;
pub mod source;
pub mod viewer;
pub mod vmc;

use std::net::{SocketAddr, UdpSocket};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, mpsc};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use ndarray::{Array2, Array3, ArrayView2};
use serde::Serialize;
use tokio::sync::broadcast;

use choreo_datasets::{MelAttachment, MotionAppender, MotionFile, Provenance, SkeletonKind};
use choreo_dsp::{FeatureStream, LogMelStream, MelOptions};
use choreo_models::{DanceOptions, LiveDance, LiveFrames, Manifest, ModelPackage, SamplerKind};

use engine::StepController;
pub use metrics::LiveMetrics;
use player::{PlayoutClock, ToPlayer};

/// Flush the HDF5 file at least this often (a crash loses at most this much).
const FLUSH_INTERVAL: Duration = Duration::from_millis(500);
/// Share of the hop the denoising may take; the rest absorbs jitter, decoding and sinks.
const BUDGET_SHARE: f64 = 0.6;
/// No new audio for this long: the session is waiting for audio (the viewer says so).
const WAITING_AFTER: Duration = Duration::from_secs(1);
/// How often the session logs its latency line.
const REPORT_INTERVAL: Duration = Duration::from_secs(10);

/// What a session does.
#[derive(Debug, Clone)]
pub struct LiveOptions {
    /// Input device name; `None` = the default input.
    pub device: Option<String>,
    /// Seconds between windows.
    pub hop_s: f64,
    /// Most steps per window (`None`: the package's).
    pub steps: Option<usize>,
    /// Fewest steps per window when the machine is slow.
    pub min_steps: usize,
    /// Emit latency the step count is adapted to hold ([`StepController`]).
    pub latency_budget: Duration,
    /// Sampler options (seed, sampler, guidance).
    pub dance: DanceOptions,
    /// Stop after this many seconds of audio heard (`None`: until SIGINT/SIGTERM).
    pub duration_s: Option<f64>,
    /// Stop after this much time on the clock, audio or not (`None`: no limit).
    pub max_wall: Option<Duration>,
    pub output: Option<PathBuf>,
    pub osc: Option<SocketAddr>,
    /// Nice value of the generator and feature threads (0: left as it is).
    pub nice: i32,
}

/// The viewer of live sessions: its page and WebSocket outlive any one session (`choreod serve`
/// keeps it up while sessions restart).
#[derive(Debug)]
pub struct LiveViewer {
    server: viewer::Viewer,
    frames: broadcast::Sender<Arc<str>>,
}

impl LiveViewer {
    /// Serve the page for `manifest`'s skeleton on `bind` (loopback; port 0 picks one); its
    /// server thread runs as an output thread of sessions at nice value `nice`
    /// ([`priority::raise_output_thread`]).
    pub fn start(bind: SocketAddr, manifest: &Manifest, nice: i32) -> anyhow::Result<Self> {
        if !bind.ip().is_loopback() {
            bail!("viewer address {bind}: the viewer listens on loopback addresses only");
        }
        let skeleton = session_skeleton(manifest)?;
        let info = viewer::SkeletonInfo::of(manifest.motion.fps, &skeleton);
        let (frames, _) = broadcast::channel::<Arc<str>>(256);
        // Started from a thread at the output priority: the server's thread inherits it.
        let server = std::thread::scope(|s| {
            s.spawn(|| {
                priority::raise_output_thread(nice);
                viewer::serve(bind, &info, Some(frames.clone()), None)
            })
            .join()
        })
        .map_err(|_| anyhow::anyhow!("starting the viewer panicked"))??;
        Ok(Self { server, frames })
    }

    /// Where it listens.
    pub fn addr(&self) -> SocketAddr {
        self.server.addr
    }
}

/// The skeleton a package's live output has.
fn session_skeleton(manifest: &Manifest) -> anyhow::Result<SkeletonKind> {
    manifest.motion.skeleton_kind().with_context(|| {
        format!(
            "the model package makes skeleton {:?}, which has no motion-file layout",
            manifest.motion.skeleton
        )
    })
}

/// Check `options` against the package before anything starts: the skeleton, and the hop (at
/// most half a window, so half of every window stays seed). Returns the hop in frames.
pub fn check_options(manifest: &Manifest, options: &LiveOptions) -> anyhow::Result<usize> {
    let skeleton = session_skeleton(manifest)?;
    if options.osc.is_some() && skeleton != SkeletonKind::Smpl24 {
        bail!(
            "VMC output (OSC) maps SMPL-24 joints to humanoid bones; the package makes {}",
            skeleton.name()
        );
    }
    if !options.hop_s.is_finite() || options.hop_s <= 0.0 {
        bail!("the hop must be > 0 seconds, got {}", options.hop_s);
    }
    let window = manifest.dance_spec()?.window_frames;
    let hop = ((options.hop_s * manifest.motion.fps).round() as usize).max(1);
    if hop > window / 2 {
        bail!(
            "a hop of {} s is {hop} frames; at most half the package's {window}-frame window",
            options.hop_s
        );
    }
    Ok(hop)
}

/// The session's outcome (`--stats`).
#[derive(Debug, Default, Serialize)]
pub struct LiveStats {
    pub audio_s: f64,
    pub frames: usize,
    pub windows: usize,
    pub skipped_frames: usize,
    pub mel_frames: usize,
    pub overruns: u64,
    pub dropped_samples: u64,
    pub device_losses: u64,
    pub reconnects: u64,
    pub steps_min: usize,
    pub steps_max: usize,
    pub steps_mean: f64,
    /// Emit time minus the capture time of the newest sample the frame's window used.
    pub latency_ms_p50: f64,
    pub latency_ms_p99: f64,
    pub latency_ms_max: f64,
    /// Seconds of audio per second spent generating.
    pub realtime_factor: f64,
    /// Process CPU time over wall time (1.0 = one core busy).
    pub cpu_share: f64,
    /// Nice value the generator thread ran at (the one asked for unless the system refused).
    pub nice: i32,
    /// Frames the player did not send because they came after their time (a window over the
    /// latency budget).
    pub late_frames: usize,
    /// Times the player's schedule was re-timed to a moved audio clock (a reconnect).
    pub resyncs: usize,
    /// Seconds the session waited with no audio arriving.
    pub waiting_s: f64,
    /// Whether the output file was written (no motion, no file).
    pub output_written: bool,
}

/// Mel frames shared by the feature thread and the generator.
#[derive(Debug, Default)]
struct Heard {
    /// New frames (time-major) not yet taken by the generator, and when the newest sample of
    /// each arrived.
    pending: Vec<f32>,
    pending_ready_at: Vec<Instant>,
    audio_samples: u64,
    sample_rate: u32,
    error: Option<String>,
}

/// Run one session until `--duration` of audio was heard or `stop` is set. Frames go to
/// `viewer` when given; counters to `metrics`. The motion file is finished (renamed into place)
/// however the session ends, an error included: what was recorded is kept.
pub fn run_session(
    package: &mut ModelPackage,
    options: &LiveOptions,
    viewer: Option<&LiveViewer>,
    metrics: &LiveMetrics,
    stop: Arc<AtomicBool>,
) -> anyhow::Result<LiveStats> {
    let manifest = package.manifest().clone();
    let hop = check_options(&manifest, options)?;
    let skeleton = session_skeleton(&manifest)?;
    let fps = manifest.motion.fps;
    let a = manifest.dance_spec()?.audio;
    let mel_options = a.mel_options();
    let ceiling = options.steps.unwrap_or(manifest.sampler.steps).max(1);
    // Before any thread starts: the capture's threads inherit it too.
    let nice = priority::raise_current_thread(options.nice);
    let model_sha256 =
        choreo_datasets::sha256_file(&package.dir().join(choreo_models::MANIFEST_FILE))
            .with_context(|| format!("reading the manifest of {}", package.dir().display()))?;
    let started_utc = choreo_datasets::now_utc();

    // Capture first: a device that is not there fails before any file is made.
    let capture = capture::start(options.device.clone())?;
    let provenance = Provenance {
        source_name: format!("live input {}", capture.device),
        model_name: manifest.name.clone(),
        model_sha256,
        steps: ceiling as u32,
        started_utc,
        ..session_sampler(&manifest, &options.dance)
    };
    let appender = match &options.output {
        Some(path) => {
            let mut header = MotionFile::from_joints(
                fps as f32,
                skeleton.clone(),
                Array3::zeros((0, skeleton.num_joints(), 3)),
            );
            header.mel = Some(MelAttachment {
                data: Array2::zeros((0, a.n_mels)),
                sample_rate: a.sample_rate,
                n_fft: a.n_fft as u32,
                hop: a.hop as u32,
                fmin: a.fmin as f32,
                fmax: a.fmax as f32,
            });
            Some(MotionAppender::create(path, &header)?)
        }
        None => None,
    };
    let osc = match options.osc {
        Some(target) => {
            let socket = UdpSocket::bind(if target.is_ipv4() {
                "0.0.0.0:0"
            } else {
                "[::]:0"
            })
            .context("cannot open a UDP socket for OSC")?;
            socket
                .connect(target)
                .with_context(|| format!("cannot send OSC to {target}"))?;
            Some(socket)
        }
        None => None,
    };

    let counters = capture.counters.clone();
    let heard = Arc::new(Mutex::new(Heard::default()));
    let feature_stop = Arc::new(AtomicBool::new(false));
    let started = Instant::now();
    let feature_thread = {
        let heard = heard.clone();
        let feature_stop = feature_stop.clone();
        let wanted = options.nice;
        std::thread::Builder::new()
            .name("live-features".into())
            .spawn(move || {
                priority::raise_current_thread(wanted);
                feature_loop(capture, mel_options, &heard, &feature_stop);
            })?
    };
    let (play_tx, play_rx) = mpsc::channel::<ToPlayer>();
    let frames_tx = viewer.map(|v| v.frames.clone());
    let clock = PlayoutClock::new(fps, hop, options.latency_budget);
    let options_nice = options.nice;
    let player = std::thread::Builder::new()
        .name("live-player".into())
        .spawn(move || {
            priority::raise_output_thread(options_nice);
            player::play(play_rx, clock, fps, frames_tx.as_ref(), osc.as_ref())
        })?;

    let mut sinks = Sinks {
        appender,
        play: play_tx,
    };
    // Nothing between here and `session_ended` returns early.
    metrics.session_started(counters.clone(), nice);
    let result = generate_loop(
        package,
        options,
        (hop, ceiling),
        &heard,
        &mut sinks,
        metrics,
        &stop,
    );
    metrics.session_ended();
    feature_stop.store(true, Ordering::SeqCst);
    let _ = feature_thread.join();
    let Sinks { appender, play, .. } = sinks;
    drop(play);
    let played = player.join().unwrap_or_default();
    let mut written = false;
    // No motion, no file: dropping the appender removes its temporary file.
    if let Some(mut app) = appender.filter(|app| app.frames() > 0) {
        // Mel frames heard after the last window.
        let rest = std::mem::take(&mut lock(&heard).pending);
        let provenance = Provenance {
            finished_utc: choreo_datasets::now_utc(),
            ..provenance
        };
        let finished = append_mel(&mut app, &rest, a.n_mels)
            .and_then(|()| app.finish(Some(&provenance)).map_err(anyhow::Error::from));
        match (&result, finished) {
            (Ok(_), Err(e)) => return Err(e),
            // The session's own error (returned below) says more than a failed finish after it.
            (Err(_), Err(e)) => {
                tracing::error!(error = %format!("{e:#}"), "cannot finish the session file");
            }
            (_, Ok(())) => written = true,
        }
    }
    let mut stats = result?;
    stats.output_written = written;
    stats.late_frames = played.late_frames;
    stats.resyncs = played.resyncs;

    let wall = started.elapsed().as_secs_f64();
    stats.cpu_share = process_cpu_seconds().map_or(0.0, |c| c / wall.max(1e-9));
    stats.overruns = counters.overruns.load(Ordering::Relaxed);
    stats.dropped_samples = counters.dropped_samples.load(Ordering::Relaxed);
    stats.device_losses = counters.device_losses.load(Ordering::Relaxed);
    stats.reconnects = counters.reconnects.load(Ordering::Relaxed);
    stats.nice = nice;
    Ok(stats)
}

/// The sampler half of a live take's provenance: the package's sampler with the session's
/// overrides, as every window runs it.
fn session_sampler(manifest: &Manifest, dance: &DanceOptions) -> Provenance {
    let kind = dance.sampler.unwrap_or(manifest.sampler.kind);
    Provenance {
        sampler: kind.as_str().to_string(),
        // eta only moves DDIM.
        eta: match kind {
            SamplerKind::Ddim => dance.eta.unwrap_or(manifest.sampler.eta),
            _ => 0.0,
        },
        guidance: dance.guidance.unwrap_or(manifest.sampler.guidance),
        seed: dance.seed,
        chunk_windows: 1,
        // Live windows are not traced back to their clips; the attribution still travels.
        library: manifest.library_line(&[]),
        ..Provenance::default()
    }
}

/// Where emitted frames go: the session file and the player.
struct Sinks {
    appender: Option<MotionAppender>,
    play: mpsc::Sender<ToPlayer>,
}

impl Sinks {
    /// Hand frames to the file and, when they were made from audio heard at `heard_at`, to the
    /// player (held frames of a skip are only written: they are late by definition).
    fn emit(&mut self, frames: LiveFrames, heard_at: Option<Instant>) -> anyhow::Result<()> {
        if let Some(app) = &mut self.appender {
            app.append(frames.pose.joints.view())?;
        }
        if let Some(heard_at) = heard_at {
            // The player is gone only when the session ends.
            let _ = self.play.send(ToPlayer::Frames {
                first: frames.first,
                pose: frames.pose,
                heard_at,
            });
        }
        Ok(())
    }
}

fn lock(heard: &Mutex<Heard>) -> std::sync::MutexGuard<'_, Heard> {
    // A panicked feature thread leaves plain data behind; keep using it.
    heard
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

fn append_mel(app: &mut MotionAppender, frames: &[f32], n_mels: usize) -> anyhow::Result<()> {
    let view = ArrayView2::from_shape((frames.len() / n_mels, n_mels), frames)?;
    app.append_mel(view)?;
    Ok(())
}

/// Drain the capture rings into the mel stream until `stop`.
fn feature_loop(
    capture: capture::Capture,
    mel_options: MelOptions,
    heard: &Mutex<Heard>,
    stop: &AtomicBool,
) {
    let mut stream = match LogMelStream::new(&mel_options) {
        Ok(s) => s,
        Err(e) => {
            lock(heard).error = Some(format!("mel stream: {e}"));
            return;
        }
    };
    let n_mels = mel_options.n_mels;
    let mut current: Option<capture::Connection> = None;
    let mut interleaved: Vec<f32> = Vec::new();
    let mut mono: Vec<f32> = Vec::new();
    let mut taken = 0usize;
    while !stop.load(Ordering::SeqCst) {
        // A new connection replaces the current one once the old ring is drained.
        if current
            .as_ref()
            .is_none_or(|c| c.ring.is_abandoned() && c.ring.is_empty())
            && let Ok(next) = capture.connections.try_recv()
        {
            current = Some(next);
        }
        let Some(conn) = current.as_mut() else {
            std::thread::sleep(Duration::from_millis(5));
            continue;
        };
        let available = conn.ring.slots();
        let whole = available - available % conn.channels;
        if whole == 0 {
            std::thread::sleep(Duration::from_millis(5));
            continue;
        }
        interleaved.clear();
        if let Ok(chunk) = conn.ring.read_chunk(whole) {
            let (a, b) = chunk.as_slices();
            interleaved.extend_from_slice(a);
            interleaved.extend_from_slice(b);
            chunk.commit_all();
        }
        let arrived = Instant::now();
        choreo_dsp::mix_to_mono(&interleaved, conn.channels, &mut mono);
        if let Err(e) = stream.accept_waveform(conn.sample_rate, &mono) {
            lock(heard).error = Some(format!("audio from the device: {e}"));
            return;
        }
        let ready = stream.frames_ready();
        let mut h = lock(heard);
        h.audio_samples += mono.len() as u64;
        h.sample_rate = conn.sample_rate;
        if ready > taken {
            if let Ok(frames) = stream.frames(taken, ready - taken) {
                h.pending.extend(frames.iter());
            }
            h.pending_ready_at
                .extend(std::iter::repeat_n(arrived, ready - taken));
            drop(h);
            stream.discard_frames_before(ready);
            taken = ready;
        }
        debug_assert_eq!(n_mels, stream.feature_dim());
    }
}

/// Steps of the timed silent window in [`calibrate`] (at least the floor, at most the ceiling).
const CALIBRATION_STEPS: usize = 4;

/// Two windows of silence through a throwaway [`LiveDance`] before the session's first: ONNX
/// Runtime's first runs allocate (the first window ran slow), and the second, timed, gives
/// `controller` its time per step, so the first heard window already fits the latency budget
/// instead of running the ceiling's steps.
fn calibrate(
    package: &mut ModelPackage,
    manifest: &Manifest,
    hop: usize,
    dance: &DanceOptions,
    controller: &mut StepController,
) -> anyhow::Result<()> {
    let audio = manifest.dance_spec()?.audio;
    let mut warm = LiveDance::new(manifest, hop)?;
    // A constant log-mel: silence, whatever its level (HeardMel clamps relative to the max).
    let silence = vec![0.0f32; audio.n_mels * audio.music_frames];
    let probe = CALIBRATION_STEPS.clamp(controller.floor(), controller.ceiling());
    let mut timed = None;
    for steps in [1, probe] {
        let mut options = dance.clone();
        options.steps = Some(steps);
        let mut made = None;
        // A window needs its music heard: at most a few windows' worth of silence.
        for _ in 0..4 {
            warm.push_mel(&silence)?;
            let started = Instant::now();
            if warm.step(package, &options)?.is_some() {
                made = Some(started.elapsed());
                break;
            }
        }
        timed = made.map(|took| (steps, took));
    }
    match timed {
        Some((steps, took)) => {
            tracing::debug!(steps, ms = took.as_millis(), "live: calibration window");
            controller.calibrate(steps, took);
        }
        None => {
            tracing::warn!("live: no calibration window could be made; starting at the ceiling")
        }
    }
    Ok(())
}

/// The generator: one window per hop until the duration is reached or `stop`.
fn generate_loop(
    package: &mut ModelPackage,
    options: &LiveOptions,
    (hop, ceiling): (usize, usize),
    heard: &Mutex<Heard>,
    sinks: &mut Sinks,
    metrics: &LiveMetrics,
    stop: &AtomicBool,
) -> anyhow::Result<LiveStats> {
    let manifest = package.manifest().clone();
    let fps = manifest.motion.fps;
    let n_mels = manifest.dance_spec()?.audio.n_mels;
    let mut controller = StepController::new(
        options.min_steps,
        ceiling,
        Duration::from_secs_f64(hop as f64 / fps * BUDGET_SHARE),
        options.latency_budget,
    );
    calibrate(package, &manifest, hop, &options.dance, &mut controller)?;
    let mut live = LiveDance::new(&manifest, hop)?;
    // Arrival time of mel frames `mel_first..` (the ones a window may still use).
    let mut ready_at: std::collections::VecDeque<Instant> = std::collections::VecDeque::new();
    let mut mel_first = 0usize;
    let mut latencies_ms: Vec<f64> = Vec::new();
    let mut steps_used: Vec<usize> = Vec::new();
    let mut stats = LiveStats::default();
    let mut last_flush = Instant::now();
    let mut generate_s = 0.0f64;
    let mut audio_s = 0.0f64;
    let started = Instant::now();
    let mut waiting = Waiting::new(started);
    let mut report = Report::new(started);
    loop {
        // Take what the feature thread heard.
        {
            let mut h = lock(heard);
            if let Some(e) = h.error.take() {
                bail!("{e}");
            }
            if !h.pending.is_empty() {
                if let Some(app) = &mut sinks.appender {
                    append_mel(app, &h.pending, n_mels)?;
                }
                live.push_mel(&h.pending)?;
                h.pending.clear();
            }
            ready_at.extend(h.pending_ready_at.drain(..));
            if h.sample_rate > 0 {
                audio_s = h.audio_samples as f64 / f64::from(h.sample_rate);
            }
        }
        if let Some(status) = waiting.observe(audio_s, Instant::now()) {
            let _ = sinks.play.send(ToPlayer::Status(status));
        }
        report.maybe_log(&waiting);
        let done = options.duration_s.is_some_and(|d| audio_s >= d);
        let out_of_time = options.max_wall.is_some_and(|m| started.elapsed() >= m);
        if out_of_time {
            tracing::info!(
                audio_s,
                "the wall-clock limit (--max-wall-time) was reached; stopping"
            );
        }
        if stop.load(Ordering::SeqCst) || done || out_of_time {
            break;
        }
        let steps = controller.steps();
        let mut dance = options.dance.clone();
        dance.steps = Some(steps);
        let Some(step) = live.step(package, &dance)? else {
            std::thread::sleep(Duration::from_millis(2));
            continue;
        };
        if let Some(held) = step.held {
            let skip = held.pose.joints.dim().0;
            tracing::warn!(skipped_frames = skip, "live generation is behind; skipping");
            stats.skipped_frames += skip;
            metrics.skipped(skip);
            sinks.emit(held, None)?;
        }
        let took = step.denoise;
        generate_s += took.as_secs_f64();
        let window = step.window;
        let newest_sample = ready_at[window.mel_needed - 1 - mel_first];
        let fresh = step.fresh.pose.joints.dim().0;
        sinks.emit(step.fresh, Some(newest_sample))?;
        let latency = newest_sample.elapsed();
        controller.observe(steps, took, latency);
        metrics.window(steps, fresh, latency);
        report.window(steps, latency);
        latencies_ms.extend(std::iter::repeat_n(latency.as_secs_f64() * 1000.0, fresh));
        steps_used.push(steps);
        stats.windows += 1;
        // Later windows start at or after this one's start.
        ready_at.drain(
            ..window
                .mel_start
                .saturating_sub(mel_first)
                .min(ready_at.len()),
        );
        mel_first = mel_first.max(window.mel_start);
        if let Some(app) = &sinks.appender
            && last_flush.elapsed() >= FLUSH_INTERVAL
        {
            app.flush()?;
            last_flush = Instant::now();
        }
    }
    stats.audio_s = audio_s;
    stats.frames = live.frames();
    stats.mel_frames = live.mel_heard();
    stats.realtime_factor = if generate_s > 0.0 {
        stats.frames as f64 / fps / generate_s
    } else {
        0.0
    };
    latencies_ms.sort_by(f64::total_cmp);
    stats.latency_ms_p50 = percentile(&latencies_ms, 0.5);
    stats.latency_ms_p99 = percentile(&latencies_ms, 0.99);
    stats.latency_ms_max = latencies_ms.last().copied().unwrap_or(0.0);
    stats.steps_min = steps_used.iter().copied().min().unwrap_or(0);
    stats.steps_max = steps_used.iter().copied().max().unwrap_or(0);
    stats.steps_mean = if steps_used.is_empty() {
        0.0
    } else {
        steps_used.iter().sum::<usize>() as f64 / steps_used.len() as f64
    };
    stats.waiting_s = waiting.total().as_secs_f64();
    Ok(stats)
}

/// Whether the session is waiting for audio: no new sample for [`WAITING_AFTER`].
struct Waiting {
    last_audio_s: f64,
    last_change: Instant,
    /// Since when it is waiting.
    since: Option<Instant>,
    /// When the viewer was last told.
    told: Option<Instant>,
    total: Duration,
}

impl Waiting {
    fn new(now: Instant) -> Self {
        Self {
            last_audio_s: 0.0,
            last_change: now,
            since: None,
            told: None,
            total: Duration::ZERO,
        }
    }

    /// The audio heard so far is `audio_s` at `now`. Returns the status for the viewer when
    /// it is due: on entering the wait and once a second while it lasts (a page opened during
    /// the wait learns it too). Entering and leaving the wait is logged.
    fn observe(&mut self, audio_s: f64, now: Instant) -> Option<&'static str> {
        if audio_s > self.last_audio_s {
            self.last_audio_s = audio_s;
            self.last_change = now;
            if let Some(since) = self.since.take() {
                let waited = now.duration_since(since) + WAITING_AFTER;
                self.total += waited;
                tracing::warn!(waited_s = waited.as_secs(), "audio arrives again");
            }
            return None;
        }
        if now.duration_since(self.last_change) < WAITING_AFTER {
            return None;
        }
        if self.since.is_none() {
            self.since = Some(now);
            tracing::warn!(
                audio_s = self.last_audio_s,
                "no audio from the input for {} s: waiting for audio",
                WAITING_AFTER.as_secs()
            );
        }
        if self
            .told
            .is_some_and(|t| now.duration_since(t) < Duration::from_secs(1))
        {
            return None;
        }
        self.told = Some(now);
        Some("waiting for audio")
    }

    /// Time spent waiting so far.
    fn total(&self) -> Duration {
        self.total
            + self
                .since
                .map_or(Duration::ZERO, |s| s.elapsed() + WAITING_AFTER)
    }
}

/// The periodic latency line (every [`REPORT_INTERVAL`]).
struct Report {
    last: Instant,
    latencies_ms: Vec<f64>,
    steps: Vec<usize>,
}

impl Report {
    fn new(now: Instant) -> Self {
        Self {
            last: now,
            latencies_ms: Vec::new(),
            steps: Vec::new(),
        }
    }

    fn window(&mut self, steps: usize, latency: Duration) {
        self.latencies_ms.push(latency.as_secs_f64() * 1000.0);
        self.steps.push(steps);
    }

    fn maybe_log(&mut self, waiting: &Waiting) {
        if self.last.elapsed() < REPORT_INTERVAL {
            return;
        }
        self.last = Instant::now();
        if self.latencies_ms.is_empty() {
            tracing::info!(
                waiting_s = waiting.total().as_secs(),
                "live: no window in the last {} s",
                REPORT_INTERVAL.as_secs()
            );
            return;
        }
        self.latencies_ms.sort_by(f64::total_cmp);
        tracing::info!(
            windows = self.latencies_ms.len(),
            latency_ms_p50 = percentile(&self.latencies_ms, 0.5).round(),
            latency_ms_max = self.latencies_ms.last().copied().unwrap_or(0.0).round(),
            steps_min = self.steps.iter().copied().min().unwrap_or(0),
            steps_max = self.steps.iter().copied().max().unwrap_or(0),
            "live: latency over the last {} s",
            REPORT_INTERVAL.as_secs()
        );
        self.latencies_ms.clear();
        self.steps.clear();
    }
}

/// The `p` quantile of `sorted` by nearest rank; 0 when empty.
fn percentile(sorted: &[f64], p: f64) -> f64 {
    sorted
        .get(((sorted.len() as f64 - 1.0) * p).round() as usize)
        .copied()
        .unwrap_or(0.0)
}

/// User + system CPU seconds of this process (Linux `/proc/self/stat`, clock ticks of 1/100 s,
/// the kernel's USER_HZ on every Linux architecture choreod builds for).
fn process_cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    let after = stat.rsplit_once(')')?.1;
    let fields: Vec<&str> = after.split_whitespace().collect();
    // Fields after the command: state(3) ... utime(14) stime(15), 1-based in proc(5).
    let utime: f64 = fields.get(11)?.parse().ok()?;
    let stime: f64 = fields.get(12)?.parse().ok()?;
    Some((utime + stime) / 100.0)
}
