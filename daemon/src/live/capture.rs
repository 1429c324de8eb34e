//! Sound-card capture with cpal. The audio callback only converts samples to f32 and copies
//! whole frames into a lock-free single-producer ring (`rtrb`): no allocation, lock or I/O runs
//! in it. A full ring drops the block and counts an overrun. A supervisor thread owns the cpal
//! stream and reconnects with exponential backoff when the device is lost (an error from the
//! stream, or no audio for [`STALL_TIMEOUT`]); each connection gets a fresh ring, handed to the
//! reader with the connection's channel count and rate.
//!
//! A source that connects but delivers nothing (a pipe with no writer, a stopped feed) is not a
//! flapping device, and an open stream with nothing to read is not idle: through ALSA's pulse
//! plugin, cpal's capture thread wakes from `poll` at once, finds less than a period and polls
//! again, a whole core for as long as the stream is open. So after a connection that never
//! delivered, the stream is closed and the source is probed: a connection open for
//! [`PROBE_TIMEOUT`], then none for [`PROBE_WAIT_START`], doubling up to [`PROBE_WAIT_MAX`]
//! (audio that comes back is heard within that). Only losing a delivering device and audio
//! coming back are warnings.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use cpal::traits::{DeviceTrait, HostTrait, StreamTrait};
use cpal::{FromSample, SampleFormat, SizedSample};

/// Ring capacity in seconds of audio: the reader drains every few milliseconds, so two seconds
/// only fill up when the reader thread is starved for that long.
const RING_SECONDS: u32 = 2;
/// No callback for this long counts as a lost device (a server can vanish without an error).
const STALL_TIMEOUT: Duration = Duration::from_secs(2);
/// Reconnect backoff: first wait, doubling up to the cap.
const BACKOFF_START: Duration = Duration::from_millis(100);
const BACKOFF_MAX: Duration = Duration::from_secs(2);
/// How long a probe connection waits for its first audio: a working source delivers its
/// first period within tens of milliseconds.
const PROBE_TIMEOUT: Duration = Duration::from_millis(500);
/// Wait between probes of a silent source: first, doubling up to the cap. At the cap a silent
/// source costs a 0.5 s probe every 8.5 s.
const PROBE_WAIT_START: Duration = Duration::from_secs(2);
const PROBE_WAIT_MAX: Duration = Duration::from_secs(8);

/// Counters shared between the callback, the supervisor and the session (all monotonic).
#[derive(Debug, Default)]
pub struct CaptureCounters {
    /// Callbacks whose block did not fit in the ring (the block is dropped).
    pub overruns: AtomicU64,
    /// Samples (all channels) dropped by overruns.
    pub dropped_samples: AtomicU64,
    /// Successful reconnections after a lost device.
    pub reconnects: AtomicU64,
    /// Times the device was lost.
    pub device_losses: AtomicU64,
    /// Milliseconds since the session start of the latest callback (stall detection).
    last_callback_ms: AtomicU64,
}

/// One connection's ring, read by the session.
#[derive(Debug)]
pub struct Connection {
    /// Interleaved f32 samples.
    pub ring: rtrb::Consumer<f32>,
    pub channels: usize,
    pub sample_rate: u32,
}

/// A running capture: connections arrive on `connections`; dropping it stops the stream.
#[derive(Debug)]
pub struct Capture {
    /// The device's description, as `--list-devices` prints it.
    pub device: String,
    pub connections: mpsc::Receiver<Connection>,
    pub counters: Arc<CaptureCounters>,
    stop: Arc<AtomicBool>,
    supervisor: Option<JoinHandle<()>>,
}

impl Drop for Capture {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(h) = self.supervisor.take() {
            let _ = h.join();
        }
    }
}

/// Input devices of the default host, one line each: id (what `--device` takes), description,
/// default channels/rate/format.
pub fn list_devices() -> anyhow::Result<Vec<String>> {
    let host = cpal::default_host();
    without_stderr(|| {
        let devices = host
            .input_devices()
            .context("cannot list the sound system's input devices")?;
        let mut lines = Vec::new();
        for d in devices {
            let desc = match d.default_input_config() {
                Ok(c) => format!(
                    "{} ch, {} Hz, {}",
                    c.channels(),
                    c.sample_rate(),
                    c.sample_format()
                ),
                Err(e) => format!("not usable: {e}"),
            };
            let id = d.id().map_or_else(|_| "?".to_owned(), |id| id.to_string());
            lines.push(format!("{id}\t{d}\t{desc}"));
        }
        Ok(lines)
    })
}

/// Run `f` with file descriptor 2 on /dev/null, and alsa-lib's messages caught ([`quietly`]):
/// alsa-lib loads its JACK plugin to probe that PCM, and libjack prints "cannot connect to
/// server" lines straight to stderr, with no handler to catch them. Only where no other thread
/// logs (the whole process's stderr is gone meanwhile).
fn without_stderr<T>(f: impl FnOnce() -> T) -> T {
    use std::os::fd::AsFd;
    let saved = rustix::io::dup(std::io::stderr().as_fd()).ok();
    let null = rustix::fs::open(
        "/dev/null",
        rustix::fs::OFlags::WRONLY | rustix::fs::OFlags::CLOEXEC,
        rustix::fs::Mode::empty(),
    )
    .ok();
    let silenced = match (&saved, &null) {
        (Some(_), Some(null)) => rustix::stdio::dup2_stderr(null).is_ok(),
        _ => false,
    };
    let value = quietly(f);
    if silenced && let Some(saved) = &saved {
        let _ = rustix::stdio::dup2_stderr(saved);
    }
    value
}

/// Start capturing from the input device `device` (its id or description as `--list-devices`
/// prints them; the default input device when `None`). Fails when the device cannot be opened
/// the first time; later losses are retried for as long as the capture lives.
pub fn start(device: Option<String>) -> anyhow::Result<Capture> {
    let counters = Arc::new(CaptureCounters::default());
    let stop = Arc::new(AtomicBool::new(false));
    let (tx, rx) = mpsc::channel();
    let epoch = Instant::now();
    // The first connection is made here so that a wrong device name is an immediate error.
    // No other thread of the session runs yet: stderr may be silenced around it.
    let first = without_stderr(|| connect(device.as_deref(), None, &counters, epoch))?;
    let rate = first.1.sample_rate;
    tracing::info!(device = %first.2, channels = first.1.channels, sample_rate = rate, "capturing");
    let device_name = first.2;
    let _ = tx.send(first.1);
    let supervisor = {
        let (counters, stop) = (counters.clone(), stop.clone());
        let mut stream = Some(first.0);
        std::thread::Builder::new()
            .name("live-capture".into())
            .spawn(move || {
                supervise(
                    &mut stream,
                    device.as_deref(),
                    rate,
                    &tx,
                    &counters,
                    &stop,
                    epoch,
                )
            })
            .context("cannot start the capture thread")?
    };
    Ok(Capture {
        device: device_name,
        connections: rx,
        counters,
        stop,
        supervisor: Some(supervisor),
    })
}

/// Watch the stream; on loss drop it and reconnect with backoff until `stop`.
fn supervise(
    stream: &mut Option<(cpal::Stream, Arc<AtomicBool>)>,
    device: Option<&str>,
    rate: u32,
    tx: &mpsc::Sender<Connection>,
    counters: &Arc<CaptureCounters>,
    stop: &AtomicBool,
    epoch: Instant,
) {
    let mut backoff = BACKOFF_START;
    // Connections in a row that delivered no audio, and when the current one was made.
    let mut silent = 0u32;
    let mut connected_ms = epoch.elapsed().as_millis() as u64;
    // No reconnect before this (probing a silent source).
    let mut probe_at_ms = 0u64;
    while !stop.load(Ordering::SeqCst) {
        std::thread::sleep(Duration::from_millis(50));
        let now_ms = epoch.elapsed().as_millis() as u64;
        match stream {
            Some((_, failed)) => {
                let last_ms = counters.last_callback_ms.load(Ordering::Relaxed);
                let delivered = last_ms > connected_ms;
                if delivered && silent > 0 {
                    tracing::warn!("audio arrives from the input device again");
                    silent = 0;
                }
                let timeout = if delivered || silent == 0 {
                    STALL_TIMEOUT
                } else {
                    PROBE_TIMEOUT
                };
                let stalled = now_ms.saturating_sub(last_ms) > timeout.as_millis() as u64;
                if failed.load(Ordering::SeqCst) || stalled {
                    counters.device_losses.fetch_add(1, Ordering::Relaxed);
                    if delivered {
                        tracing::warn!(stalled, "input device lost; reconnecting with backoff");
                    } else {
                        silent += 1;
                        let wait =
                            (PROBE_WAIT_START * 2u32.pow((silent - 1).min(8))).min(PROBE_WAIT_MAX);
                        probe_at_ms = now_ms + wait.as_millis() as u64;
                        tracing::debug!(
                            silent,
                            wait_ms = wait.as_millis() as u64,
                            "still no audio; probing again later"
                        );
                    }
                    *stream = None;
                }
            }
            None if now_ms < probe_at_ms => {}
            None => match connect(device, Some(rate), counters, epoch) {
                Ok((s, conn, _)) => {
                    counters.reconnects.fetch_add(1, Ordering::Relaxed);
                    connected_ms = epoch.elapsed().as_millis() as u64;
                    if silent == 0 {
                        // After a connection that delivered: the device came back.
                        tracing::warn!(
                            channels = conn.channels,
                            sample_rate = conn.sample_rate,
                            "input device reconnected"
                        );
                    }
                    *stream = Some(s);
                    backoff = BACKOFF_START;
                    if tx.send(conn).is_err() {
                        return;
                    }
                }
                Err(e) => {
                    tracing::info!(error = %format!("{e:#}"), retry_in_ms = backoff.as_millis() as u64, "reconnect failed");
                    std::thread::sleep(backoff);
                    backoff = (backoff * 2).min(BACKOFF_MAX);
                }
            },
        }
    }
}

type LiveStream = (cpal::Stream, Arc<AtomicBool>);

/// Open the device and start a stream into a new ring. `rate`: the rate of the first
/// connection, asked for again so the feature stream keeps one rate across reconnects.
fn connect(
    name: Option<&str>,
    rate: Option<u32>,
    counters: &Arc<CaptureCounters>,
    epoch: Instant,
) -> anyhow::Result<(LiveStream, Connection, String)> {
    let host = cpal::default_host();
    let device = match name {
        None => host
            .default_input_device()
            .context("no default input device (see `choreod live --list-devices`)")?,
        Some(want) => quietly(|| {
            host.input_devices()
                .map(|mut all| all.find(|d| names_device(want, d)))
        })
        .context("cannot list input devices")?
        .with_context(|| {
            format!("no input device named '{want}' (see `choreod live --list-devices`)")
        })?,
    };
    let default = device
        .default_input_config()
        .with_context(|| format!("input device '{device}' has no usable configuration"))?;
    let mut config = default.config();
    if let Some(r) = rate {
        config.sample_rate = r;
    }
    let channels = usize::from(config.channels);
    if channels == 0 || config.sample_rate == 0 {
        bail!(
            "input device '{device}' reports {channels} channels at {} Hz",
            config.sample_rate
        );
    }
    let capacity = (config.sample_rate * RING_SECONDS) as usize * channels;
    let (producer, consumer) = rtrb::RingBuffer::new(capacity);
    let failed = Arc::new(AtomicBool::new(false));
    counters
        .last_callback_ms
        .store(epoch.elapsed().as_millis() as u64, Ordering::Relaxed);
    let sink = RingSink {
        producer,
        channels,
        counters: counters.clone(),
        epoch,
    };
    let on_error = {
        let failed = failed.clone();
        move |e: cpal::Error| {
            // Runs on the audio thread: set a flag, the supervisor logs and reconnects.
            if !matches!(e.kind(), cpal::ErrorKind::DeviceChanged) {
                failed.store(true, Ordering::SeqCst);
            }
        }
    };
    let stream = match default.sample_format() {
        SampleFormat::F32 => build::<f32>(&device, &config, sink, on_error),
        SampleFormat::F64 => build::<f64>(&device, &config, sink, on_error),
        SampleFormat::I8 => build::<i8>(&device, &config, sink, on_error),
        SampleFormat::I16 => build::<i16>(&device, &config, sink, on_error),
        SampleFormat::I32 => build::<i32>(&device, &config, sink, on_error),
        SampleFormat::I64 => build::<i64>(&device, &config, sink, on_error),
        SampleFormat::U8 => build::<u8>(&device, &config, sink, on_error),
        SampleFormat::U16 => build::<u16>(&device, &config, sink, on_error),
        SampleFormat::U32 => build::<u32>(&device, &config, sink, on_error),
        SampleFormat::U64 => build::<u64>(&device, &config, sink, on_error),
        other => {
            bail!("input device '{device}' delivers {other} samples, which choreod does not read")
        }
    }
    .with_context(|| format!("cannot open input device '{device}'"))?;
    stream
        .play()
        .with_context(|| format!("cannot start input device '{device}'"))?;
    tracing::debug!(device = %device, channels, sample_rate = config.sample_rate, format = %default.sample_format(), "stream open");
    Ok((
        (stream, failed),
        Connection {
            ring: consumer,
            channels,
            sample_rate: config.sample_rate,
        },
        device.to_string(),
    ))
}

/// Run `f` (device enumeration) with alsa-lib's complaints about the PCMs it probes (the JACK,
/// OSS and surround plugins with nothing behind them) caught instead of printed on stderr; they
/// are logged at debug level.
fn quietly<T>(f: impl FnOnce() -> T) -> T {
    let caught = alsa::Output::local_error_handler().ok();
    let value = f();
    if let Some(caught) = caught {
        caught.borrow().buffer_string(|text| {
            let text = String::from_utf8_lossy(text);
            if !text.trim().is_empty() {
                tracing::debug!(messages = %text.trim(), "alsa-lib while listing devices");
            }
        });
    }
    value
}

/// Whether `--device want` names `device`: its description, its id (`alsa:pulse`), or its id
/// without the host (`pulse`), as `--list-devices` prints them.
fn names_device(want: &str, device: &cpal::Device) -> bool {
    device.to_string() == want
        || device
            .id()
            .is_ok_and(|id| id.to_string() == want || id.id() == want)
}

/// What the audio callback owns.
struct RingSink {
    producer: rtrb::Producer<f32>,
    channels: usize,
    counters: Arc<CaptureCounters>,
    epoch: Instant,
}

impl RingSink {
    /// The callback body: whole frames into the ring, or an overrun. No allocation, no lock.
    fn push<T: SizedSample>(&mut self, data: &[T])
    where
        f32: FromSample<T>,
    {
        self.counters
            .last_callback_ms
            .store(self.epoch.elapsed().as_millis() as u64, Ordering::Relaxed);
        let n = data.len() - data.len() % self.channels;
        match self.producer.write_chunk_uninit(n) {
            Ok(chunk) => {
                chunk.fill_from_iter(data[..n].iter().map(|s| f32::from_sample_(*s)));
            }
            Err(_) => {
                self.counters.overruns.fetch_add(1, Ordering::Relaxed);
                self.counters
                    .dropped_samples
                    .fetch_add(n as u64, Ordering::Relaxed);
            }
        }
    }
}

fn build<T>(
    device: &cpal::Device,
    config: &cpal::StreamConfig,
    mut sink: RingSink,
    on_error: impl FnMut(cpal::Error) + Send + 'static,
) -> Result<cpal::Stream, cpal::Error>
where
    T: SizedSample,
    f32: FromSample<T>,
{
    device.build_input_stream::<T, _, _>(
        *config,
        move |data: &[T], _| sink.push(data),
        on_error,
        None,
    )
}
