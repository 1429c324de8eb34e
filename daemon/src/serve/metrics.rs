//! Counters of the service and its HTTP endpoint: `/healthz` and `/metrics` in the Prometheus
//! text exposition format (version 0.0.4), served by axum on a tokio runtime of its own thread.
//!
//! Health checks come first, whatever other clients do. Every connection is its own task. A
//! connection must send its first bytes within [`FIRST_BYTE_TIMEOUT`] and its whole request
//! head within [`HEADER_TIMEOUT`] or is closed: until then it holds no slot (at most
//! [`MAX_WAITING`] wait). Then it takes one of [`MAX_CONNECTIONS`] slots, of which
//! [`HEALTH_SLOTS`] only a request starting `GET /healthz` may take, and is closed after
//! [`CONNECTION_TIMEOUT`] at most. With no slot free the connection is closed at once. (A
//! per-address limit would not help: on loopback every client has the same address.)

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use anyhow::Context;
use axum::Router;
use axum::extract::State;
use axum::http::{StatusCode, header};
use axum::response::IntoResponse;
use axum::routing::get;
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::service::TowerToHyperService;
use tokio::sync::{OwnedSemaphorePermit, Semaphore};

use crate::exit::NotReady;
use crate::live::LiveMetrics;
use crate::stylize::StyleCache;

/// A client must send its first bytes within this (a scrape or probe sends its request at once).
const FIRST_BYTE_TIMEOUT: Duration = Duration::from_secs(1);
/// A client must send its whole request head within this.
const HEADER_TIMEOUT: Duration = Duration::from_secs(5);
/// Longest request head accepted (a scrape or probe sends a few hundred bytes).
const MAX_HEAD_BYTES: usize = 8192;
/// No connection lives longer than this, whatever the client does.
const CONNECTION_TIMEOUT: Duration = Duration::from_secs(30);
/// Connections that have not sent a byte yet; each waits [`FIRST_BYTE_TIMEOUT`] at most.
const MAX_WAITING: usize = 512;
/// Connections served at once; scrapers and health checks need a handful.
const MAX_CONNECTIONS: usize = 64;
/// Of those, kept for health checks: slow clients of `/metrics` cannot take them.
const HEALTH_SLOTS: usize = 8;
/// `/healthz` says "claims failing" after this many failed claims in a row (one more than a
/// single transient failure: the retry after a rescan failed too).
const CLAIM_FAILURES_UNHEALTHY: u32 = 2;

/// Histogram bucket bounds in seconds: a 1 s clip takes ~40 ms, a 20 min song with a big model
/// minutes, so the buckets span 10 ms to 10 min.
const BUCKETS: &[f64] = &[
    0.01, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 120.0, 300.0, 600.0,
];

/// Stages timed per job, in the order printed.
pub const STAGES: &[&str] = &["features", "generate", "write", "total"];

/// Failure stages counted (see spool `Failure::stage`).
const FAIL_STAGES: &[&str] = &[
    "intake", "decode", "generate", "write", "stylize", "panic", "crash",
];

#[derive(Debug, Default)]
struct Histogram {
    counts: Vec<u64>,
    sum: f64,
    count: u64,
}

impl Histogram {
    fn observe(&mut self, v: f64) {
        if self.counts.is_empty() {
            self.counts = vec![0; BUCKETS.len()];
        }
        for (c, bound) in self.counts.iter_mut().zip(BUCKETS) {
            if v <= *bound {
                *c += 1;
            }
        }
        self.sum += v;
        self.count += 1;
    }
}

/// Everything `/metrics` reports. Shared by the workers, the intake and the HTTP thread.
#[derive(Debug, Default)]
pub struct Metrics {
    pub done: AtomicU64,
    failed: Mutex<Vec<u64>>,
    pub queue_depth: AtomicUsize,
    pub in_flight: AtomicUsize,
    pub workers: AtomicUsize,
    pub ready: AtomicBool,
    /// Claims that failed (the file stays in the inbox and is retried), in total and in a row.
    pub claim_failures: AtomicU64,
    pub claims_failing: AtomicU32,
    // Accumulated over many jobs, so f64 (see house style on accumulation).
    timing: Mutex<Timing>,
    /// The live source's (`[live]` enabled).
    pub live: Option<Arc<LiveMetrics>>,
    /// Running dance jobs' share of steps done, by job id.
    progress: Mutex<BTreeMap<String, f64>>,
    /// The style inbox's encoded style reference (`[style]` enabled).
    pub styles: Option<Arc<StyleCache>>,
}

#[derive(Debug, Default)]
struct Timing {
    stages: Vec<Histogram>,
    audio_s: f64,
    work_s: f64,
    last_rtf: f64,
}

impl Metrics {
    /// Count a claim's outcome: a failure keeps `/healthz` from "ok" while they repeat.
    pub fn claim_result(&self, ok: bool) {
        if ok {
            self.claims_failing.store(0, Ordering::Relaxed);
        } else {
            self.claim_failures.fetch_add(1, Ordering::Relaxed);
            self.claims_failing.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// `/healthz`: status and one-line body.
    fn health(&self) -> (StatusCode, String) {
        let failing = self.claims_failing.load(Ordering::Relaxed);
        if !self.ready.load(Ordering::Relaxed) {
            (
                StatusCode::SERVICE_UNAVAILABLE,
                "starting or stopping\n".into(),
            )
        } else if failing >= CLAIM_FAILURES_UNHEALTHY {
            (
                StatusCode::SERVICE_UNAVAILABLE,
                format!("claims failing: {failing} in a row (see the log)\n"),
            )
        } else {
            (StatusCode::OK, "ok\n".into())
        }
    }

    /// A running job's share of steps done (0..=1).
    pub fn set_progress(&self, job: &str, ratio: f64) {
        self.lock_progress().insert(job.to_string(), ratio);
    }

    /// The job has ended: it leaves `choreod_job_progress_ratio`.
    pub fn clear_progress(&self, job: &str) {
        self.lock_progress().remove(job);
    }

    fn lock_progress(&self) -> std::sync::MutexGuard<'_, BTreeMap<String, f64>> {
        self.progress
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Count a failed job by the stage it failed in.
    pub fn failed(&self, stage: &str) {
        let i = FAIL_STAGES
            .iter()
            .position(|s| *s == stage)
            .unwrap_or(FAIL_STAGES.len() - 1);
        let mut f = self
            .failed
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        if f.is_empty() {
            f.resize(FAIL_STAGES.len(), 0);
        }
        f[i] += 1;
    }

    /// Count a finished job with its stage durations (same order as [`STAGES`]) and music length.
    pub fn succeeded(&self, stage_s: [f64; 4], audio_s: f64) {
        self.done.fetch_add(1, Ordering::Relaxed);
        let mut t = self
            .timing
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        if t.stages.is_empty() {
            t.stages.resize_with(STAGES.len(), Histogram::default);
        }
        for (h, v) in t.stages.iter_mut().zip(stage_s) {
            h.observe(v);
        }
        t.audio_s += audio_s;
        t.work_s += stage_s[3];
        t.last_rtf = if stage_s[3] > 0.0 {
            audio_s / stage_s[3]
        } else {
            0.0
        };
    }

    /// The Prometheus text exposition.
    pub fn render(&self) -> String {
        let mut o = String::new();
        let _ = writeln!(
            o,
            "# HELP choreod_jobs_total Jobs finished, by outcome.\n# TYPE choreod_jobs_total counter"
        );
        let _ = writeln!(
            o,
            "choreod_jobs_total{{outcome=\"done\"}} {}",
            self.done.load(Ordering::Relaxed)
        );
        let failed = self
            .failed
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .clone();
        let failed_total: u64 = failed.iter().sum();
        let _ = writeln!(o, "choreod_jobs_total{{outcome=\"failed\"}} {failed_total}");
        let _ = writeln!(
            o,
            "# HELP choreod_job_failures_total Failed jobs, by the stage they failed in.\n# TYPE choreod_job_failures_total counter"
        );
        for (i, stage) in FAIL_STAGES.iter().enumerate() {
            let _ = writeln!(
                o,
                "choreod_job_failures_total{{stage=\"{stage}\"}} {}",
                failed.get(i).copied().unwrap_or(0)
            );
        }
        let gauges = [
            (
                "choreod_queue_depth",
                "Jobs claimed and waiting for a worker.",
                self.queue_depth.load(Ordering::Relaxed),
            ),
            (
                "choreod_jobs_in_flight",
                "Jobs being worked on.",
                self.in_flight.load(Ordering::Relaxed),
            ),
            (
                "choreod_workers",
                "Worker threads.",
                self.workers.load(Ordering::Relaxed),
            ),
            (
                "choreod_claims_failing",
                "Claims of inbox files that failed in a row (the files stay in the inbox).",
                self.claims_failing.load(Ordering::Relaxed) as usize,
            ),
        ];
        for (name, help, v) in gauges {
            let _ = writeln!(o, "# HELP {name} {help}\n# TYPE {name} gauge\n{name} {v}");
        }
        // Job ids are digits and '-' (spool `next_id`): no label escaping needed.
        let _ = writeln!(
            o,
            "# HELP choreod_job_progress_ratio Share of a running dance job's denoising steps done, by job id.\n# TYPE choreod_job_progress_ratio gauge"
        );
        for (job, ratio) in self.lock_progress().iter() {
            let _ = writeln!(o, "choreod_job_progress_ratio{{job=\"{job}\"}} {ratio}");
        }
        let _ = writeln!(
            o,
            "# HELP choreod_claim_failures_total Claims of inbox files that failed.\n# TYPE choreod_claim_failures_total counter\nchoreod_claim_failures_total {}",
            self.claim_failures.load(Ordering::Relaxed)
        );
        let t = self
            .timing
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let _ = writeln!(
            o,
            "# HELP choreod_stage_duration_seconds Seconds per stage of successful jobs.\n# TYPE choreod_stage_duration_seconds histogram"
        );
        for (i, stage) in STAGES.iter().enumerate() {
            let empty = Histogram::default();
            let h = t.stages.get(i).unwrap_or(&empty);
            for (j, bound) in BUCKETS.iter().enumerate() {
                let c = h.counts.get(j).copied().unwrap_or(0);
                let _ = writeln!(
                    o,
                    "choreod_stage_duration_seconds_bucket{{stage=\"{stage}\",le=\"{bound}\"}} {c}"
                );
            }
            let _ = writeln!(
                o,
                "choreod_stage_duration_seconds_bucket{{stage=\"{stage}\",le=\"+Inf\"}} {}",
                h.count
            );
            let _ = writeln!(
                o,
                "choreod_stage_duration_seconds_sum{{stage=\"{stage}\"}} {}",
                h.sum
            );
            let _ = writeln!(
                o,
                "choreod_stage_duration_seconds_count{{stage=\"{stage}\"}} {}",
                h.count
            );
        }
        let _ = writeln!(
            o,
            "# HELP choreod_audio_seconds_total Seconds of music danced.\n# TYPE choreod_audio_seconds_total counter\nchoreod_audio_seconds_total {}",
            t.audio_s
        );
        let _ = writeln!(
            o,
            "# HELP choreod_job_seconds_total Seconds spent on successful jobs.\n# TYPE choreod_job_seconds_total counter\nchoreod_job_seconds_total {}",
            t.work_s
        );
        let overall = if t.work_s > 0.0 {
            t.audio_s / t.work_s
        } else {
            0.0
        };
        let _ = writeln!(
            o,
            "# HELP choreod_realtime_factor Seconds of music per second of work (all jobs so far).\n# TYPE choreod_realtime_factor gauge\nchoreod_realtime_factor {overall}"
        );
        let _ = writeln!(
            o,
            "# HELP choreod_last_job_realtime_factor Real-time factor of the last job.\n# TYPE choreod_last_job_realtime_factor gauge\nchoreod_last_job_realtime_factor {}",
            t.last_rtf
        );
        if let Some(styles) = &self.styles {
            let _ = writeln!(
                o,
                "# HELP choreod_style_encodings_total Times the style reference was read and run through the style encoder (once, and again when its file changes).\n# TYPE choreod_style_encodings_total counter\nchoreod_style_encodings_total {}",
                styles.encodings()
            );
        }
        if let Some(live) = &self.live {
            live.render(&mut o);
        }
        o
    }
}

/// Bind `addr` (a taken port refuses the start-up with [`NotReady`], exit code 4) and serve
/// requests on a thread of its own.
pub fn serve(addr: SocketAddr, metrics: Arc<Metrics>) -> anyhow::Result<SocketAddr> {
    let listener = std::net::TcpListener::bind(addr).map_err(|e| {
        NotReady(format!(
            "cannot listen on {addr} for the metrics endpoint (metrics.bind): {e}"
        ))
    })?;
    listener
        .set_nonblocking(true)
        .context("metrics endpoint socket")?;
    let bound = listener.local_addr().context("metrics endpoint address")?;
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("starting the metrics endpoint's runtime")?;
    std::thread::Builder::new()
        .name("metrics".into())
        .spawn(move || runtime.block_on(accept_loop(listener, metrics)))
        .context("starting the metrics thread")?;
    Ok(bound)
}

async fn accept_loop(listener: std::net::TcpListener, metrics: Arc<Metrics>) {
    let listener = match tokio::net::TcpListener::from_std(listener) {
        Ok(l) => l,
        Err(e) => {
            tracing::error!(error = %e, "metrics endpoint stopped");
            return;
        }
    };
    let app = Router::new()
        .route("/healthz", get(healthz))
        .route("/metrics", get(prometheus))
        .fallback(|| async { (StatusCode::NOT_FOUND, "try /healthz or /metrics\n") })
        .with_state(metrics);
    let slots = Arc::new(Slots {
        waiting: Arc::new(Semaphore::new(MAX_WAITING)),
        health: Arc::new(Semaphore::new(HEALTH_SLOTS)),
        any: Arc::new(Semaphore::new(MAX_CONNECTIONS - HEALTH_SLOTS)),
    });
    loop {
        let stream = match listener.accept().await {
            Ok((stream, _)) => stream,
            Err(e) => {
                // Out of file descriptors and the like: wait instead of spinning.
                tracing::warn!(error = %e, "metrics endpoint accept failed");
                tokio::time::sleep(Duration::from_millis(100)).await;
                continue;
            }
        };
        let Ok(waiting) = Arc::clone(&slots.waiting).try_acquire_owned() else {
            tracing::debug!("metrics endpoint: too many silent connections; closing one");
            continue;
        };
        let service = TowerToHyperService::new(app.clone());
        let slots = Arc::clone(&slots);
        tokio::spawn(async move {
            let Some(slot) = slots.admit(&stream).await else {
                return;
            };
            drop(waiting);
            let connection = hyper::server::conn::http1::Builder::new()
                .timer(TokioTimer::new())
                .header_read_timeout(HEADER_TIMEOUT)
                .serve_connection(TokioIo::new(stream), service);
            if let Ok(Err(e)) = tokio::time::timeout(CONNECTION_TIMEOUT, connection).await {
                tracing::debug!(error = %e, "metrics request");
            }
            drop(slot);
        });
    }
}

/// The endpoint's connection slots.
#[derive(Debug)]
struct Slots {
    /// Connections that have sent nothing yet.
    waiting: Arc<Semaphore>,
    /// For requests starting `GET /healthz` only.
    health: Arc<Semaphore>,
    /// For any request.
    any: Arc<Semaphore>,
}

impl Slots {
    /// Wait for the connection's request head and give it a slot: `None` (close it) when it
    /// sent nothing within [`FIRST_BYTE_TIMEOUT`], no whole head within [`HEADER_TIMEOUT`]
    /// (checked here, not left to hyper, whose timer starts only when it gets the connection),
    /// closed, or no slot is free for it.
    async fn admit(&self, stream: &tokio::net::TcpStream) -> Option<OwnedSemaphorePermit> {
        const PROBE: &[u8] = b"GET /healthz";
        let start = tokio::time::Instant::now();
        let mut head = vec![0u8; MAX_HEAD_BYTES];
        let mut n = 0;
        while !head[..n].windows(4).any(|w| w == b"\r\n\r\n") {
            if n == head.len() {
                return None;
            }
            let deadline = start
                + if n == 0 {
                    FIRST_BYTE_TIMEOUT
                } else {
                    HEADER_TIMEOUT
                };
            // Checked here too: `timeout_at` returns a peek that is ready at once (bytes
            // waiting) however late it is.
            if tokio::time::Instant::now() >= deadline {
                tracing::debug!(
                    bytes = n,
                    "metrics endpoint: no whole request in time; closing"
                );
                return None;
            }
            match tokio::time::timeout_at(deadline, stream.peek(&mut head)).await {
                Ok(Ok(got)) if got > n => n = got,
                Ok(Ok(got)) if got > 0 => {
                    // Nothing new yet: look again soon (peek returns what is already there).
                    tokio::time::sleep(Duration::from_millis(20)).await;
                }
                _ => {
                    tracing::debug!(bytes = n, "metrics endpoint: no request in time; closing");
                    return None;
                }
            }
        }
        let health = head.starts_with(PROBE);
        let slot = match Arc::clone(&self.any).try_acquire_owned() {
            Ok(slot) => Ok(slot),
            Err(_) if health => Arc::clone(&self.health).try_acquire_owned(),
            Err(e) => Err(e),
        };
        if slot.is_err() {
            tracing::debug!(health, "metrics endpoint busy; closing a connection");
        }
        slot.ok()
    }
}

async fn healthz(State(metrics): State<Arc<Metrics>>) -> impl IntoResponse {
    let (status, body) = metrics.health();
    (status, [(header::CONTENT_TYPE, "text/plain")], body)
}

async fn prometheus(State(metrics): State<Arc<Metrics>>) -> impl IntoResponse {
    (
        [(header::CONTENT_TYPE, "text/plain; version=0.0.4")],
        metrics.render(),
    )
}

#[cfg(test)]
mod tests {
    use std::io::{Read, Write};
    use std::net::TcpStream;

    use super::*;

    #[test]
    fn histogram_buckets_are_cumulative_and_render_parses() {
        let m = Metrics::default();
        m.succeeded([0.02, 0.3, 0.01, 0.4], 2.0);
        m.succeeded([0.02, 20.0, 0.01, 25.0], 10.0);
        m.failed("decode");
        let text = m.render();
        assert!(
            text.contains("choreod_jobs_total{outcome=\"done\"} 2"),
            "{text}"
        );
        assert!(
            text.contains("choreod_jobs_total{outcome=\"failed\"} 1"),
            "{text}"
        );
        assert!(
            text.contains("choreod_job_failures_total{stage=\"decode\"} 1"),
            "{text}"
        );
        assert!(
            text.contains("choreod_stage_duration_seconds_bucket{stage=\"total\",le=\"0.5\"} 1"),
            "{text}"
        );
        assert!(
            text.contains("choreod_stage_duration_seconds_bucket{stage=\"total\",le=\"30\"} 2"),
            "{text}"
        );
        assert!(
            text.contains("choreod_stage_duration_seconds_count{stage=\"generate\"} 2"),
            "{text}"
        );
        // 12 s of music in 25.4 s of work.
        let rtf: f64 = text
            .lines()
            .find_map(|l| l.strip_prefix("choreod_realtime_factor "))
            .unwrap()
            .parse()
            .unwrap();
        assert!((rtf - 12.0 / 25.4).abs() < 1e-9, "{rtf}");
        for line in text.lines().filter(|l| !l.starts_with('#')) {
            let value = line.rsplit(' ').next().unwrap();
            assert!(value.parse::<f64>().is_ok(), "not a sample line: {line}");
        }
    }

    fn get(addr: SocketAddr, path: &str) -> String {
        let mut s = TcpStream::connect(addr).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
        write!(
            s,
            "GET {path} HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n"
        )
        .unwrap();
        let mut r = String::new();
        s.read_to_string(&mut r).unwrap();
        r
    }

    #[test]
    fn endpoint_answers_healthz_and_metrics() {
        let m = Arc::new(Metrics::default());
        let addr = serve("127.0.0.1:0".parse().unwrap(), m.clone()).unwrap();
        assert!(get(addr, "/healthz").starts_with("HTTP/1.1 503"));
        m.ready.store(true, Ordering::Relaxed);
        assert!(get(addr, "/healthz").starts_with("HTTP/1.1 200"));
        let r = get(addr, "/metrics");
        assert!(
            r.starts_with("HTTP/1.1 200") && r.contains("choreod_queue_depth 0"),
            "{r}"
        );
        assert!(get(addr, "/nope").starts_with("HTTP/1.1 404"));
        m.claim_result(false);
        assert!(
            get(addr, "/healthz").starts_with("HTTP/1.1 200"),
            "one failure may be transient"
        );
        m.claim_result(false);
        let r = get(addr, "/healthz");
        assert!(
            r.starts_with("HTTP/1.1 503") && r.contains("claims failing: 2"),
            "{r}"
        );
        assert!(get(addr, "/metrics").contains("choreod_claim_failures_total 2"));
        m.claim_result(true);
        assert!(get(addr, "/healthz").starts_with("HTTP/1.1 200"));
        let taken = serve(addr, m).unwrap_err();
        assert!(taken.downcast_ref::<NotReady>().is_some(), "{taken:#}");
    }

    #[test]
    fn slow_and_idle_clients_do_not_block_healthz() {
        let m = Arc::new(Metrics::default());
        m.ready.store(true, Ordering::Relaxed);
        let addr = serve("127.0.0.1:0".parse().unwrap(), m).unwrap();
        // Idle connections that never send a byte, and one that sends a byte every 1.5 s.
        let idle: Vec<TcpStream> = (0..8).map(|_| TcpStream::connect(addr).unwrap()).collect();
        let mut slow = TcpStream::connect(addr).unwrap();
        let t0 = std::time::Instant::now();
        let dripper = std::thread::spawn(move || {
            for b in b"GET /healthz HTTP/1.1\r\nHost: x".iter() {
                if slow.write_all(&[*b]).is_err() {
                    // Closed by the server: the header-read timeout ended it.
                    return Some(t0.elapsed());
                }
                std::thread::sleep(Duration::from_millis(1500));
            }
            None
        });
        for _ in 0..3 {
            let t = std::time::Instant::now();
            assert!(get(addr, "/healthz").starts_with("HTTP/1.1 200"));
            // Generous for a loaded 2-core machine; the old one-at-a-time server took forever.
            assert!(t.elapsed() < Duration::from_secs(2), "{:?}", t.elapsed());
            std::thread::sleep(Duration::from_millis(700));
        }
        let closed_after = dripper.join().unwrap().expect("the slow client is cut off");
        // HEADER_TIMEOUT, plus one drip interval to notice, plus slack for a loaded machine.
        assert!(
            closed_after < HEADER_TIMEOUT + Duration::from_secs(6),
            "{closed_after:?}"
        );
        drop(idle);
    }
}
