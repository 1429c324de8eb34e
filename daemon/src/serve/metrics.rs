//! Counters of the service and a tiny HTTP/1.1 endpoint: `/healthz` and `/metrics` in the
//! Prometheus text exposition format (version 0.0.4).

use std::fmt::Write as _;
use std::io::{BufRead, BufReader, Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use anyhow::Context;

/// Histogram bucket bounds in seconds: a 1 s clip takes ~40 ms, a 20 min song with a big model
/// minutes, so the buckets span 10 ms to 10 min.
const BUCKETS: &[f64] = &[
    0.01, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 120.0, 300.0, 600.0,
];

/// Stages timed per job, in the order printed.
pub const STAGES: &[&str] = &["features", "generate", "write", "total"];

/// Failure stages counted (see spool `Failure::stage`).
const FAIL_STAGES: &[&str] = &["intake", "decode", "generate", "write", "crash"];

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
    // Accumulated over many jobs, so f64 (see house style on accumulation).
    timing: Mutex<Timing>,
}

#[derive(Debug, Default)]
struct Timing {
    stages: Vec<Histogram>,
    audio_s: f64,
    work_s: f64,
    last_rtf: f64,
}

impl Metrics {
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
        ];
        for (name, help, v) in gauges {
            let _ = writeln!(o, "# HELP {name} {help}\n# TYPE {name} gauge\n{name} {v}");
        }
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
        o
    }
}

/// Bind `addr` (fails the start-up when taken) and serve requests on a thread of its own.
pub fn serve(addr: SocketAddr, metrics: Arc<Metrics>) -> anyhow::Result<SocketAddr> {
    let listener = TcpListener::bind(addr)
        .with_context(|| format!("binding the metrics endpoint {addr} (metrics.bind)"))?;
    let bound = listener.local_addr().context("metrics endpoint address")?;
    std::thread::Builder::new()
        .name("metrics".into())
        .spawn(move || {
            for stream in listener.incoming() {
                match stream {
                    // One request per connection, answered inline: scrapes are rare and tiny.
                    Ok(s) => {
                        if let Err(e) = answer(s, &metrics) {
                            tracing::debug!(error = %e, "metrics request");
                        }
                    }
                    Err(e) => tracing::warn!(error = %e, "metrics endpoint accept failed"),
                }
            }
        })
        .context("starting the metrics thread")?;
    Ok(bound)
}

fn answer(stream: TcpStream, metrics: &Metrics) -> std::io::Result<()> {
    // A client that never sends its request must not hold the endpoint.
    stream.set_read_timeout(Some(Duration::from_secs(2)))?;
    stream.set_write_timeout(Some(Duration::from_secs(2)))?;
    let mut reader = BufReader::new(stream.try_clone()?);
    let mut request_line = String::new();
    // Bound the request line; the headers are read and dropped, also bounded.
    reader.by_ref().take(8192).read_line(&mut request_line)?;
    let mut header = String::new();
    for _ in 0..100 {
        header.clear();
        if reader.by_ref().take(8192).read_line(&mut header)? == 0 || header.trim().is_empty() {
            break;
        }
    }
    let mut parts = request_line.split_whitespace();
    let method = parts.next().unwrap_or("");
    let path = parts.next().unwrap_or("");
    let (status, content_type, body) = match (method, path) {
        ("GET" | "HEAD", "/healthz") if metrics.ready.load(Ordering::Relaxed) => {
            ("200 OK", "text/plain", "ok\n".to_string())
        }
        ("GET" | "HEAD", "/healthz") => (
            "503 Service Unavailable",
            "text/plain",
            "starting\n".to_string(),
        ),
        ("GET" | "HEAD", "/metrics") => ("200 OK", "text/plain; version=0.0.4", metrics.render()),
        ("GET" | "HEAD", _) => (
            "404 Not Found",
            "text/plain",
            "try /healthz or /metrics\n".to_string(),
        ),
        _ => (
            "405 Method Not Allowed",
            "text/plain",
            "GET only\n".to_string(),
        ),
    };
    let mut out = stream;
    write!(
        out,
        "HTTP/1.1 {status}\r\nContent-Type: {content_type}\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
        body.len()
    )?;
    if method != "HEAD" {
        out.write_all(body.as_bytes())?;
    }
    out.flush()
}

#[cfg(test)]
mod tests {
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

    #[test]
    fn endpoint_answers_healthz_and_metrics() {
        let m = Arc::new(Metrics::default());
        let addr = serve("127.0.0.1:0".parse().unwrap(), m.clone()).unwrap();
        let get = |path: &str| {
            let mut s = TcpStream::connect(addr).unwrap();
            write!(s, "GET {path} HTTP/1.1\r\nHost: x\r\n\r\n").unwrap();
            let mut r = String::new();
            s.read_to_string(&mut r).unwrap();
            r
        };
        assert!(get("/healthz").starts_with("HTTP/1.1 503"));
        m.ready.store(true, Ordering::Relaxed);
        assert!(get("/healthz").starts_with("HTTP/1.1 200"));
        let r = get("/metrics");
        assert!(
            r.starts_with("HTTP/1.1 200") && r.contains("choreod_queue_depth 0"),
            "{r}"
        );
        assert!(get("/nope").starts_with("HTTP/1.1 404"));
    }
}
