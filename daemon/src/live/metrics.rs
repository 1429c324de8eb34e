//! Counters and gauges of live sessions, rendered into serve's `/metrics` (Prometheus text
//! exposition 0.0.4). Counters add up over all the sessions one live source runs; the running
//! session's capture counters are read at scrape time, so a device loss and its reconnect show
//! while the session goes on.

use std::collections::VecDeque;
use std::fmt::Write as _;
use std::sync::atomic::{AtomicBool, AtomicI32, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::time::Duration;

use super::capture::CaptureCounters;

/// Windows the latency quantiles are taken over: 2 minutes at the default 0.5 s hop, long
/// enough for a p99 to mean something, short enough to follow a change of load.
const LATENCY_WINDOWS: usize = 256;

/// The capture counters, in the order of [`CAPTURE_METRICS`].
fn capture_values(c: &CaptureCounters) -> [u64; 4] {
    [
        c.device_losses.load(Ordering::Relaxed),
        c.reconnects.load(Ordering::Relaxed),
        c.overruns.load(Ordering::Relaxed),
        c.dropped_samples.load(Ordering::Relaxed),
    ]
}

const CAPTURE_METRICS: [(&str, &str); 4] = [
    (
        "choreod_live_device_losses_total",
        "Times the live input device was lost (an error from the stream, or no audio for 2 s).",
    ),
    (
        "choreod_live_reconnects_total",
        "Successful reconnections of the live input after a lost device.",
    ),
    (
        "choreod_live_capture_overruns_total",
        "Audio callbacks whose block did not fit in the capture ring (the block is dropped).",
    ),
    (
        "choreod_live_dropped_samples_total",
        "Samples (all channels) dropped by capture overruns.",
    ),
];

/// Everything the live source reports. Written by the session's generator, read by `/metrics`.
#[derive(Debug, Default)]
pub struct LiveMetrics {
    sessions: AtomicU64,
    running: AtomicBool,
    capture: Mutex<CaptureTotals>,
    windows: AtomicU64,
    frames: AtomicU64,
    skips: AtomicU64,
    skipped_frames: AtomicU64,
    steps: AtomicU64,
    nice: AtomicI32,
    latency: Mutex<Latency>,
}

#[derive(Debug, Default)]
struct CaptureTotals {
    /// Sums over the finished sessions.
    finished: [u64; 4],
    /// The running session's counters.
    current: Option<Arc<CaptureCounters>>,
}

#[derive(Debug, Default)]
struct Latency {
    /// Seconds, the newest last.
    recent: VecDeque<f64>,
    // Accumulated over the whole run, so f64.
    sum: f64,
    count: u64,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    // Plain numbers: a panicked writer leaves nothing inconsistent behind.
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

impl LiveMetrics {
    /// A session started capturing with `counters`, its generator at nice value `nice`.
    pub fn session_started(&self, counters: Arc<CaptureCounters>, nice: i32) {
        self.sessions.fetch_add(1, Ordering::Relaxed);
        self.nice.store(nice, Ordering::Relaxed);
        self.running.store(true, Ordering::Relaxed);
        lock(&self.capture).current = Some(counters);
    }

    /// The running session ended: its capture counters join the totals (under one lock, so a
    /// scrape never counts them twice or not at all).
    pub fn session_ended(&self) {
        let mut c = lock(&self.capture);
        if let Some(current) = c.current.take() {
            for (total, v) in c.finished.iter_mut().zip(capture_values(&current)) {
                *total += v;
            }
        }
        self.running.store(false, Ordering::Relaxed);
    }

    /// A window was generated with `steps` and its `frames` new frames emitted `latency` after
    /// the newest sample it used arrived.
    pub fn window(&self, steps: usize, frames: usize, latency: Duration) {
        self.windows.fetch_add(1, Ordering::Relaxed);
        self.frames.fetch_add(frames as u64, Ordering::Relaxed);
        self.steps.store(steps as u64, Ordering::Relaxed);
        let mut l = lock(&self.latency);
        if l.recent.len() == LATENCY_WINDOWS {
            l.recent.pop_front();
        }
        l.recent.push_back(latency.as_secs_f64());
        l.sum += latency.as_secs_f64();
        l.count += 1;
    }

    /// Generation fell behind and `frames` frames were skipped (the last pose held).
    pub fn skipped(&self, frames: usize) {
        self.skips.fetch_add(1, Ordering::Relaxed);
        self.skipped_frames
            .fetch_add(frames as u64, Ordering::Relaxed);
        self.frames.fetch_add(frames as u64, Ordering::Relaxed);
    }

    /// Append the live metrics to a Prometheus text exposition.
    pub fn render(&self, o: &mut String) {
        let capture = {
            let c = lock(&self.capture);
            let mut v = c.finished;
            if let Some(current) = &c.current {
                for (total, n) in v.iter_mut().zip(capture_values(current)) {
                    *total += n;
                }
            }
            v
        };
        let counters = [
            (
                "choreod_live_sessions_total",
                "Live sessions started (one per capture; a failed start is retried with backoff).",
                self.sessions.load(Ordering::Relaxed),
            ),
            (
                "choreod_live_windows_total",
                "Live windows generated.",
                self.windows.load(Ordering::Relaxed),
            ),
            (
                "choreod_live_frames_total",
                "Live motion frames emitted (held frames of skips included).",
                self.frames.load(Ordering::Relaxed),
            ),
            (
                "choreod_live_skips_total",
                "Times live generation fell behind and skipped frames.",
                self.skips.load(Ordering::Relaxed),
            ),
            (
                "choreod_live_skipped_frames_total",
                "Live frames skipped (the last pose held) because generation fell behind.",
                self.skipped_frames.load(Ordering::Relaxed),
            ),
        ];
        let capture = CAPTURE_METRICS
            .iter()
            .zip(capture)
            .map(|((name, help), v)| (*name, *help, v));
        for (name, help, v) in counters.into_iter().chain(capture) {
            let _ = writeln!(o, "# HELP {name} {help}\n# TYPE {name} counter\n{name} {v}");
        }
        let gauges = [
            (
                "choreod_live_running",
                "1 while a live session captures, else 0.",
                u64::from(self.running.load(Ordering::Relaxed)),
            ),
            (
                "choreod_live_steps",
                "Denoising steps of the latest live window.",
                self.steps.load(Ordering::Relaxed),
            ),
        ];
        let nice = (
            "choreod_live_nice",
            "Nice value of the latest live session's generator thread (below 0: raised priority).",
            i64::from(self.nice.load(Ordering::Relaxed)),
        );
        let gauges = gauges
            .into_iter()
            .map(|(name, help, v)| (name, help, v as i64))
            .chain([nice]);
        for (name, help, v) in gauges {
            let _ = writeln!(o, "# HELP {name} {help}\n# TYPE {name} gauge\n{name} {v}");
        }
        let l = lock(&self.latency);
        let mut sorted: Vec<f64> = l.recent.iter().copied().collect();
        sorted.sort_by(f64::total_cmp);
        let name = "choreod_live_latency_seconds";
        let _ = writeln!(
            o,
            "# HELP {name} Emit time of a live window's frames minus the arrival time of the \
             newest sample it used; quantiles over the last {LATENCY_WINDOWS} windows.\n\
             # TYPE {name} summary"
        );
        for q in [0.5, 0.99] {
            let _ = writeln!(
                o,
                "{name}{{quantile=\"{q}\"}} {}",
                super::percentile(&sorted, q)
            );
        }
        let _ = writeln!(o, "{name}_sum {}\n{name}_count {}", l.sum, l.count);
        let name = "choreod_live_last_latency_seconds";
        let _ = writeln!(
            o,
            "# HELP {name} Latency of the latest live window.\n# TYPE {name} gauge\n{name} {}",
            l.recent.back().copied().unwrap_or(0.0)
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn value(text: &str, sample: &str) -> f64 {
        text.lines()
            .find_map(|l| l.strip_prefix(sample)?.strip_prefix(' '))
            .unwrap_or_else(|| panic!("no {sample} in {text}"))
            .parse()
            .unwrap()
    }

    #[test]
    fn capture_counters_add_up_over_sessions_and_show_while_running() {
        let m = LiveMetrics::default();
        let first = Arc::new(CaptureCounters::default());
        m.session_started(first.clone(), -7);
        first.reconnects.fetch_add(2, Ordering::Relaxed);
        first.overruns.fetch_add(1, Ordering::Relaxed);
        let mut text = String::new();
        m.render(&mut text);
        assert_eq!(value(&text, "choreod_live_reconnects_total"), 2.0);
        assert_eq!(value(&text, "choreod_live_running"), 1.0);
        assert_eq!(value(&text, "choreod_live_nice"), -7.0);
        m.session_ended();
        // The ended session's counters are kept once, not twice.
        let second = Arc::new(CaptureCounters::default());
        m.session_started(second.clone(), 0);
        second.reconnects.fetch_add(1, Ordering::Relaxed);
        second.device_losses.fetch_add(1, Ordering::Relaxed);
        let mut text = String::new();
        m.render(&mut text);
        assert_eq!(value(&text, "choreod_live_reconnects_total"), 3.0);
        assert_eq!(value(&text, "choreod_live_device_losses_total"), 1.0);
        assert_eq!(value(&text, "choreod_live_capture_overruns_total"), 1.0);
        assert_eq!(value(&text, "choreod_live_sessions_total"), 2.0);
        assert_eq!(value(&text, "choreod_live_nice"), 0.0);
        m.session_ended();
        let mut text = String::new();
        m.render(&mut text);
        assert_eq!(value(&text, "choreod_live_reconnects_total"), 3.0);
        assert_eq!(value(&text, "choreod_live_running"), 0.0);
    }

    #[test]
    fn windows_frames_steps_and_latency_quantiles() {
        let m = LiveMetrics::default();
        // 100 windows of 10..1000 ms: p50 = 500 or 510 ms, p99 = 990 ms by nearest rank.
        for i in 1..=100u64 {
            m.window(20, 15, Duration::from_millis(i * 10));
        }
        m.window(7, 15, Duration::from_millis(40));
        m.skipped(12);
        let mut text = String::new();
        m.render(&mut text);
        assert_eq!(value(&text, "choreod_live_windows_total"), 101.0);
        assert_eq!(
            value(&text, "choreod_live_frames_total"),
            101.0 * 15.0 + 12.0
        );
        assert_eq!(value(&text, "choreod_live_skips_total"), 1.0);
        assert_eq!(value(&text, "choreod_live_skipped_frames_total"), 12.0);
        assert_eq!(value(&text, "choreod_live_steps"), 7.0);
        assert_eq!(value(&text, "choreod_live_last_latency_seconds"), 0.04);
        let p99 = value(&text, "choreod_live_latency_seconds{quantile=\"0.99\"}");
        assert!((p99 - 0.99).abs() < 1e-9, "{p99}");
        let p50 = value(&text, "choreod_live_latency_seconds{quantile=\"0.5\"}");
        assert!((0.49..=0.51).contains(&p50), "{p50}");
        assert_eq!(value(&text, "choreod_live_latency_seconds_count"), 101.0);
        // 10 + 20 + ... + 1000 ms = 50.5 s, plus 0.04 s.
        let sum = value(&text, "choreod_live_latency_seconds_sum");
        assert!((sum - 50.54).abs() < 1e-9, "{sum}");
        for name in ["choreod_live_windows_total", "choreod_live_latency_seconds"] {
            assert!(text.contains(&format!("# HELP {name} ")), "{text}");
        }
        assert!(text.contains("# TYPE choreod_live_latency_seconds summary"));
        for line in text.lines().filter(|l| !l.starts_with('#')) {
            let v = line.rsplit(' ').next().unwrap();
            assert!(v.parse::<f64>().is_ok(), "not a sample line: {line}");
        }
    }
}
