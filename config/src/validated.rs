//! The checked configuration the daemon runs with, and the pure validation that produces it.

use std::fmt;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use crate::error::{ConfigError, ConfigErrors, Result};
use crate::raw::RawConfig;

/// Where the daemon reads songs, writes dances and keeps its job journal.
#[derive(Debug, Clone, PartialEq)]
pub struct PathsConfig {
    /// `paths.inbox`: songs dropped here become jobs. Required.
    pub inbox: PathBuf,
    /// `paths.output`: finished motion files appear here. Required.
    pub output: PathBuf,
    /// `paths.state`: job spool, failed inputs and error reports. Required.
    pub state: PathBuf,
}

/// How the watch-folder service schedules work.
#[derive(Debug, Clone, PartialEq)]
pub struct ServeConfig {
    /// `serve.workers`: jobs run at once. Default: from the CPUs, see [`serve_threads`] (2 on
    /// 2 CPUs, the fastest there, see BENCHMARKS.md).
    pub workers: usize,
    /// `serve.queue_capacity`: jobs accepted but not started before intake waits. Default: 64.
    pub queue_capacity: usize,
    /// `serve.settle_ms`: a file must be unchanged this long after close-write. Default: 500.
    pub settle_ms: u64,
    /// `serve.max_attempts`: a job that killed the daemon this often while running alone is
    /// failed. Default: 3.
    pub max_attempts: u32,
    /// `serve.shutdown_timeout_s`: on SIGTERM, in-flight jobs get this long. Default: 30.
    pub shutdown_timeout_s: f64,
}

/// ONNX Runtime and the model used when a job names none.
#[derive(Debug, Clone, PartialEq)]
pub struct RuntimeConfig {
    /// `runtime.ort_library`: path to `libonnxruntime.so`. Default: none, meaning the
    /// `ORT_DYLIB_PATH` environment variable, then `.venv/libonnxruntime.so` of the checkout.
    pub ort_library: Option<PathBuf>,
    /// `runtime.ort_intra_threads`: threads inside one ONNX operator, per job. Default: the
    /// CPUs shared out among the workers, see [`serve_threads`] (1 on 2 CPUs with two workers,
    /// the fastest there; see BENCHMARKS.md).
    pub ort_intra_threads: usize,
    /// `runtime.ort_inter_threads`: operators run in parallel. Default: 1.
    pub ort_inter_threads: usize,
    /// `runtime.default_model`: model package directory. Default: `models/packages/library`
    /// of the checkout.
    pub default_model: Option<PathBuf>,
}

/// Bounds on what a job may read, checked before allocating.
#[derive(Debug, Clone, PartialEq)]
pub struct LimitsConfig {
    /// `limits.max_file_mb`: larger inputs are refused. Default: 512.
    pub max_file_bytes: u64,
    /// `limits.max_audio_seconds`: longer songs are refused. Default: 1200 (20 min).
    pub max_audio_seconds: f64,
    /// `limits.min_audio_seconds`: shorter songs are refused. Default (`None`): one motion
    /// window of the model package (5 s for the shipped ones) — anything shorter is a truncated
    /// file or a clip the model only pads.
    pub min_audio_seconds: Option<f64>,
    /// `limits.min_free_disk_mb`: below this free space in `paths.output` a job fails before
    /// writing. Default: 256.
    pub min_free_disk_bytes: u64,
    /// `limits.fail_truncated_audio`: a song whose file ends mid-stream fails (stage `decode`)
    /// instead of being danced as far as it decodes. Default: false — the audio before the
    /// damage is real music and its dance is right for it (a cut download is still a song); the
    /// job's log line and the motion file's provenance (`source_damage`) say it was partial.
    pub fail_truncated_audio: bool,
}

/// The HTTP endpoint with `/healthz` and `/metrics`.
#[derive(Debug, Clone, PartialEq)]
pub struct MetricsConfig {
    /// `metrics.enabled`. Default: true.
    pub enabled: bool,
    /// `metrics.bind`. Default: `127.0.0.1:9464` (loopback only).
    pub bind: SocketAddr,
}

/// How the daemon dances each song (the `choreod dance` flags, for every job).
#[derive(Debug, Clone, PartialEq)]
pub struct JobConfig {
    /// `job.seed`: seed of all noise; the same song, seed and model give the same dance. Default: 0.
    pub seed: u64,
    /// `job.steps`: denoising steps. Default: none, meaning the model package's `sampler.steps`.
    pub steps: Option<usize>,
    /// `job.guidance`: guidance scale on the music (1 = off). Default: none, meaning the
    /// package's `sampler.guidance`.
    pub guidance: Option<f32>,
    /// `job.chunk_windows`: windows denoised together in one batch (bounds memory). Default:
    /// None, the library's (`choreo_models::DanceOptions`).
    pub chunk_windows: Option<usize>,
    /// `job.time_limit_s`: a dance or style job still running after this many seconds is
    /// stopped and failed (a model that runs too long, or for ever). Default:
    /// [`JobConfig::DEFAULT_TIME_LIMIT_S`].
    pub time_limit_s: f64,
}

impl JobConfig {
    /// The default `job.time_limit_s` (and `choreod dance` / `stylize --time-limit`), seconds:
    /// an hour, about 16 times what the paper-size `mofusion-ref` needs for the longest song
    /// `limits.max_audio_seconds` allows by default (20 min at a real-time factor of 5.3 with
    /// guidance on 2 cores: BENCHMARKS.md, "Music to dance").
    pub const DEFAULT_TIME_LIMIT_S: f64 = 3600.0;
}

/// A live audio source run beside the watch folder (the `choreod live` flags; same defaults).
#[derive(Debug, Clone, PartialEq)]
pub struct LiveConfig {
    /// `live.enabled`: run it. Default: false.
    pub enabled: bool,
    /// `live.device`: input device as `choreod live --list-devices` prints it. Default: none,
    /// meaning the system's default input. Not checked here: a device that is missing (not
    /// plugged in yet) is a warning at run time, retried until it appears.
    pub device: Option<String>,
    /// `live.model`: model package. Default: none, meaning the one `choreod serve` uses.
    pub model: Option<PathBuf>,
    /// `live.hop_s`: seconds between windows. Default: 0.5. At most half the package's window
    /// (checked against the package when serve starts).
    pub hop_s: f64,
    /// `live.steps`: most denoising steps per window. Default: none, meaning the package's.
    pub steps: Option<usize>,
    /// `live.min_steps`: fewest steps per window when the machine is slow. Default: 2.
    pub min_steps: usize,
    /// `live.latency_budget_s`: the emit latency (audio in to motion out) the step count is
    /// adapted to hold: windows slower than 0.8 of it get fewer steps. Default: 0.25.
    pub latency_budget_s: f64,
    /// `live.sampler`: `ddim`, `ddpm` or `dpmsolver++`. Default: none, meaning the package's.
    pub sampler: Option<Sampler>,
    /// `live.seed`: seed of all noise. Default: 0.
    pub seed: u64,
    /// `live.intra_threads`: ONNX Runtime threads inside one operator (0 = one per CPU choreod
    /// may use, [`available_cpus`]). Default: 0.
    pub intra_threads: usize,
    /// `live.output`: folder of the session files (`live-<UTC time>.h5`). Default: `paths.output`.
    pub output: PathBuf,
    /// `live.viewer`: loopback address of the viewer page and its WebSocket. Default: none (no
    /// viewer).
    pub viewer: Option<SocketAddr>,
    /// `live.osc`: where VMC bone messages go (OSC over UDP). Default: none.
    pub osc: Option<SocketAddr>,
    /// `live.nice`: nice value of the session's generation and capture threads, -20..19; 0
    /// leaves them as they are. Default: [`LiveConfig::DEFAULT_NICE`].
    pub nice: i32,
}

impl LiveConfig {
    /// The default `live.nice` (and `choreod live --nice`). The kernel's CFS gives a nice -10
    /// thread 9548/1024 ≈ 9.3 times the CPU share of a nice 0 one (`sched_prio_to_weight` in
    /// Linux's kernel/sched/core.c), enough to stay ahead of compilers and batch jobs, while
    /// -11..-20 is left for the sound server itself (PipeWire, JACK).
    pub const DEFAULT_NICE: i32 = -10;
    /// The default `live.hop_s` (and `choreod live --hop`), seconds: each window emits this much
    /// new motion.
    pub const DEFAULT_HOP_S: f64 = 0.5;
    /// The default `live.min_steps` (and `choreod live --min-steps`).
    pub const DEFAULT_MIN_STEPS: usize = 2;
    /// The default `live.latency_budget_s` (and `choreod live --latency-budget`), seconds: the
    /// issue's target, p99 <= 250 ms end to end with the default package.
    pub const DEFAULT_LATENCY_BUDGET_S: f64 = 0.25;
}

/// A second watch folder whose motion files are stylized (`choreod stylize`, for every file).
#[derive(Debug, Clone, PartialEq)]
pub struct StyleConfig {
    /// `style.inbox`: motion files dropped here become style-transfer jobs. Required when
    /// `style.enabled`.
    pub inbox: PathBuf,
    /// `style.style`: the style reference motion every job uses. Required when `style.enabled`.
    pub style: PathBuf,
    /// `style.model`: style-transfer package. Default: none, meaning the bundled
    /// `models/packages/style-gaussian` (as `choreod stylize`).
    pub model: Option<PathBuf>,
    /// `style.mode`: `transfer` or `inversion`. Default: `transfer`.
    pub mode: StyleMode,
    /// `style.guidance`: style guidance of transfer mode. Default: none, meaning the package's.
    pub guidance: Option<f32>,
    /// `style.steps`: denoising steps. Default: none, meaning the package's.
    pub steps: Option<usize>,
}

/// How `[style]` jobs use the style (choreo-models' `StyleMode`; the config crate sits below the
/// models crate, so the spellings are repeated here).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum StyleMode {
    #[default]
    Transfer,
    Inversion,
}

impl StyleMode {
    /// Both modes.
    pub const ALL: [Self; 2] = [Self::Transfer, Self::Inversion];

    /// The config file's spelling.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Transfer => "transfer",
            Self::Inversion => "inversion",
        }
    }
}

/// The samplers `live.sampler` takes: choreo-models' `SamplerKind` (the config crate sits below
/// the models crate; the daemon maps one onto the other and tests that the spellings agree).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Sampler {
    Ddim,
    Ddpm,
    DpmSolverPlusPlus,
}

impl Sampler {
    /// Every sampler, in the order error messages list them.
    pub const ALL: [Self; 3] = [Self::Ddim, Self::Ddpm, Self::DpmSolverPlusPlus];

    /// The config file's spelling.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Ddim => "ddim",
            Self::Ddpm => "ddpm",
            Self::DpmSolverPlusPlus => "dpmsolver++",
        }
    }
}

/// Log output format.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LogFormat {
    /// Human-readable lines (default).
    Human,
    /// One JSON object per line.
    Json,
}

/// A validated configuration: every value in range, every path absolute or resolved.
#[derive(Debug, Clone, PartialEq)]
pub struct Config {
    pub paths: PathsConfig,
    pub serve: ServeConfig,
    pub runtime: RuntimeConfig,
    pub limits: LimitsConfig,
    pub metrics: MetricsConfig,
    pub job: JobConfig,
    pub live: LiveConfig,
    /// `[style]`: `None` unless `style.enabled`.
    pub style: Option<StyleConfig>,
    /// `log.format`: `human` or `json`. Default: `human`.
    pub log_format: LogFormat,
    /// `log.level`: a tracing filter such as `info` or `choreod=debug`. Default: `info`.
    pub log_level: String,
}

const MB: f64 = 1024.0 * 1024.0;

/// ONNX Runtime threads one worker gets by default before another worker is added: past a few
/// threads one generation's operators (batches of a few windows) gain little from more, while
/// another job in flight overlaps its serial work (decode, mel, sampler loop, write).
const THREADS_PER_WORKER: usize = 4;
/// Most workers chosen by default: each holds its own model sessions (memory × workers).
const MAX_DEFAULT_WORKERS: usize = 8;

/// CPUs this process may use: `std::thread::available_parallelism`, which counts the CPU
/// affinity mask and cgroup quotas (a container limited to 2 CPUs gets 2). ONNX Runtime's own
/// default counts the host's cores instead, so choreod passes thread counts explicitly.
pub fn available_cpus() -> usize {
    std::thread::available_parallelism().map_or(1, std::num::NonZero::get)
}

/// `serve.workers` and `runtime.ort_intra_threads` on `cpus` CPUs, each the configured value
/// when set. Unset ones share out the CPUs so that every CPU has work and none has two
/// (workers × threads ≤ cpus, given at least one of each):
/// - neither set: workers = `cpus / 4`, at least `min(2, cpus)` and at most 8; threads =
///   `cpus / workers` (2 CPUs: 2 × 1, the fastest measured there, BENCHMARKS.md "Daemon
///   throughput"; 8: 2 × 4; 32: 8 × 4);
/// - workers set: threads = `cpus / workers`, at least 1;
/// - threads set: workers = `cpus / threads`, at least 1 and at most 8.
///
/// Both set is taken as given (the daemon warns at start when it oversubscribes).
pub fn serve_threads(
    cpus: usize,
    workers: Option<usize>,
    intra_threads: Option<usize>,
) -> (usize, usize) {
    let cpus = cpus.max(1);
    let share = |n: usize| (cpus / n.max(1)).max(1);
    match (workers, intra_threads) {
        (Some(w), Some(t)) => (w, t),
        (Some(w), None) => (w, share(w)),
        (None, Some(t)) => (share(t).min(MAX_DEFAULT_WORKERS), t),
        (None, None) => {
            let w = (cpus / THREADS_PER_WORKER).clamp(cpus.min(2), MAX_DEFAULT_WORKERS);
            (w, share(w))
        }
    }
}

impl RawConfig {
    /// Check every value and produce a [`Config`], or every problem found.
    ///
    /// Pure: touches no file. Relative paths are joined to `base` (the config file's directory).
    pub fn validate(self, base: &Path) -> Result<Config> {
        let mut errs = Vec::new();
        let mut path = |key: &'static str, v: Option<String>, hint: &'static str| match v {
            Some(s) if s.trim().is_empty() => {
                errs.push(ConfigError::Invalid {
                    key,
                    value: "\"\"".into(),
                    reason: "empty".into(),
                });
                PathBuf::new()
            }
            Some(s) => base.join(s),
            None => {
                errs.push(ConfigError::Missing { key, hint });
                PathBuf::new()
            }
        };
        let paths = PathsConfig {
            inbox: path(
                "paths.inbox",
                self.paths.inbox,
                "the folder songs are dropped into",
            ),
            output: path(
                "paths.output",
                self.paths.output,
                "the folder dances are written to",
            ),
            state: path(
                "paths.state",
                self.paths.state,
                "the folder for the job spool",
            ),
        };

        let mut int = |key: &'static str, v: Option<i64>, default: i64, min: i64, max: i64| {
            let v = v.unwrap_or(default);
            if v < min || v > max {
                errs.push(ConfigError::Invalid {
                    key,
                    value: v.to_string(),
                    reason: format!("must be between {min} and {max}"),
                });
                default
            } else {
                v
            }
        };
        let workers_set = self
            .serve
            .workers
            .map(|v| int("serve.workers", Some(v), 2, 1, 256) as usize);
        let queue_capacity = int(
            "serve.queue_capacity",
            self.serve.queue_capacity,
            64,
            1,
            1_000_000,
        ) as usize;
        let settle_ms = int("serve.settle_ms", self.serve.settle_ms, 500, 0, 3_600_000) as u64;
        let max_attempts = int("serve.max_attempts", self.serve.max_attempts, 3, 1, 100) as u32;
        let seed = int("job.seed", self.job.seed, 0, 0, i64::MAX) as u64;
        let steps = self
            .job
            .steps
            .map(|v| int("job.steps", Some(v), 50, 1, 10_000) as usize);
        let chunk_windows = self
            .job
            .chunk_windows
            .map(|v| int("job.chunk_windows", Some(v), 1, 1, 4096) as usize);
        // More ONNX Runtime threads than CPUs this process may use only oversubscribe them
        // (affinity and cgroup quotas included), as the `--intra-threads` flag says.
        let cpus = available_cpus() as i64;
        let intra_set = self
            .runtime
            .ort_intra_threads
            .map(|v| int("runtime.ort_intra_threads", Some(v), 1, 1, cpus) as usize);
        let (workers, intra) = serve_threads(cpus as usize, workers_set, intra_set);
        let inter = int(
            "runtime.ort_inter_threads",
            self.runtime.ort_inter_threads,
            1,
            1,
            cpus,
        );
        let live_raw = self.live;
        let live_steps = live_raw
            .steps
            .map(|v| int("live.steps", Some(v), 50, 1, 10_000) as usize);
        let live_min_steps = int(
            "live.min_steps",
            live_raw.min_steps,
            LiveConfig::DEFAULT_MIN_STEPS as i64,
            1,
            10_000,
        ) as usize;
        let live_seed = int("live.seed", live_raw.seed, 0, 0, i64::MAX) as u64;
        let live_intra = int("live.intra_threads", live_raw.intra_threads, 0, 0, cpus) as usize;
        let live_nice = int(
            "live.nice",
            live_raw.nice,
            LiveConfig::DEFAULT_NICE.into(),
            -20,
            19,
        ) as i32;
        let style_raw = self.style;
        let style_steps = style_raw
            .steps
            .map(|v| int("style.steps", Some(v), 50, 1, 10_000) as usize);

        let mut float = |key: &'static str, v: Option<f64>, default: f64, min: f64, max: f64| {
            let v = v.unwrap_or(default);
            if !v.is_finite() || v < min || v > max {
                errs.push(ConfigError::Invalid {
                    key,
                    value: v.to_string(),
                    reason: format!("must be between {min} and {max}"),
                });
                default
            } else {
                v
            }
        };
        let shutdown_timeout_s = float(
            "serve.shutdown_timeout_s",
            self.serve.shutdown_timeout_s,
            30.0,
            0.0,
            3600.0,
        );
        let max_file_mb = float(
            "limits.max_file_mb",
            self.limits.max_file_mb,
            512.0,
            0.001,
            1e6,
        );
        let max_audio_seconds = float(
            "limits.max_audio_seconds",
            self.limits.max_audio_seconds,
            1200.0,
            0.1,
            86400.0,
        );
        let min_audio_seconds = self.limits.min_audio_seconds.map(|v| {
            float(
                "limits.min_audio_seconds",
                Some(v),
                0.0,
                0.0,
                max_audio_seconds,
            )
        });
        let time_limit_s = float(
            "job.time_limit_s",
            self.job.time_limit_s,
            JobConfig::DEFAULT_TIME_LIMIT_S,
            0.1,
            86400.0,
        );
        let min_free_disk_mb = float(
            "limits.min_free_disk_mb",
            self.limits.min_free_disk_mb,
            256.0,
            0.0,
            1e9,
        );

        let guidance = self
            .job
            .guidance
            .map(|v| float("job.guidance", Some(v), 1.0, 0.0, 100.0) as f32);
        let style_guidance = style_raw
            .guidance
            .map(|v| float("style.guidance", Some(v), 1.0, 0.0, 100.0) as f32);
        // Above 0 (a hop of 0 never advances); the package's window bounds it further.
        let hop_s = float(
            "live.hop_s",
            live_raw.hop_s,
            LiveConfig::DEFAULT_HOP_S,
            0.001,
            60.0,
        );
        let latency_budget_s = float(
            "live.latency_budget_s",
            live_raw.latency_budget_s,
            LiveConfig::DEFAULT_LATENCY_BUDGET_S,
            0.001,
            60.0,
        );

        let bind_text = self.metrics.bind.unwrap_or_else(|| "127.0.0.1:9464".into());
        let bind = match bind_text.parse::<SocketAddr>() {
            // The endpoint has no authentication: it stays on this machine.
            Ok(a) if !a.ip().is_loopback() => {
                errs.push(ConfigError::Invalid {
                    key: "metrics.bind",
                    value: format!("{bind_text:?}"),
                    reason: "not a loopback address; the endpoint listens on loopback only \
                             (127.0.0.0/8 or [::1]); put a proxy in front to expose it"
                        .into(),
                });
                SocketAddr::from(([127, 0, 0, 1], 9464))
            }
            Ok(a) => a,
            Err(e) => {
                errs.push(ConfigError::Invalid {
                    key: "metrics.bind",
                    value: format!("{bind_text:?}"),
                    reason: format!("{e}; expected an address such as 127.0.0.1:9464"),
                });
                SocketAddr::from(([127, 0, 0, 1], 9464))
            }
        };

        let mut address = |key: &'static str, v: Option<String>, loopback_only: bool| {
            let text = v?;
            match text.parse::<SocketAddr>() {
                Ok(a) if loopback_only && !a.ip().is_loopback() => {
                    errs.push(ConfigError::Invalid {
                        key,
                        value: format!("{text:?}"),
                        reason: "the viewer listens on loopback addresses only (127.0.0.1, ::1)"
                            .into(),
                    });
                    None
                }
                Ok(a) => Some(a),
                Err(e) => {
                    errs.push(ConfigError::Invalid {
                        key,
                        value: format!("{text:?}"),
                        reason: format!("{e}; expected an address such as 127.0.0.1:8080"),
                    });
                    None
                }
            }
        };
        let viewer = address("live.viewer", live_raw.viewer, true);
        let osc = address("live.osc", live_raw.osc, false);
        let live_sampler = live_raw.sampler.as_deref().and_then(|name| {
            let found = Sampler::ALL.into_iter().find(|s| s.as_str() == name);
            if found.is_none() {
                let names: Vec<&str> = Sampler::ALL.iter().map(|s| s.as_str()).collect();
                errs.push(ConfigError::Invalid {
                    key: "live.sampler",
                    value: format!("{name:?}"),
                    reason: format!("must be one of {}", names.join(", ")),
                });
            }
            found
        });

        let style_mode = match style_raw.mode.as_deref() {
            None => StyleMode::default(),
            Some(name) => StyleMode::ALL
                .into_iter()
                .find(|m| m.as_str() == name)
                .unwrap_or_else(|| {
                    errs.push(ConfigError::Invalid {
                        key: "style.mode",
                        value: format!("{name:?}"),
                        reason: "must be \"transfer\" or \"inversion\"".into(),
                    });
                    StyleMode::default()
                }),
        };
        if style_mode == StyleMode::Inversion && style_guidance.is_some() {
            errs.push(ConfigError::Invalid {
                key: "style.guidance",
                value: format!("{}", style_raw.guidance.unwrap_or_default()),
                reason: "weights transfer mode; inversion mode uses the package's content and \
                         style weights"
                    .into(),
            });
        }
        let style = if style_raw.enabled.unwrap_or(false) {
            let mut required = |key: &'static str, v: Option<String>, hint: &'static str| match v {
                Some(s) if !s.trim().is_empty() => base.join(s),
                _ => {
                    errs.push(ConfigError::Missing { key, hint });
                    PathBuf::new()
                }
            };
            Some(StyleConfig {
                inbox: required(
                    "style.inbox",
                    style_raw.inbox,
                    "the folder motions to stylize are dropped into",
                ),
                style: required(
                    "style.style",
                    style_raw.style,
                    "the style reference motion file",
                ),
                model: style_raw
                    .model
                    .filter(|s| !s.trim().is_empty())
                    .map(|s| base.join(s)),
                mode: style_mode,
                guidance: style_guidance,
                steps: style_steps,
            })
        } else {
            None
        };

        let log_format = match self.log.format.as_deref().unwrap_or("human") {
            "human" => LogFormat::Human,
            "json" => LogFormat::Json,
            other => {
                errs.push(ConfigError::Invalid {
                    key: "log.format",
                    value: format!("{other:?}"),
                    reason: "must be \"human\" or \"json\"".into(),
                });
                LogFormat::Human
            }
        };

        let log_level = self.log.level.unwrap_or_else(|| "info".into());
        if let Some(problem) = log_filter_problem(&log_level) {
            errs.push(ConfigError::Invalid {
                key: "log.level",
                value: format!("{log_level:?}"),
                reason: format!(
                    "{problem}; expected a level (trace, debug, info, warn, error, off) or \
                     target=level pairs such as \"info,choreod=debug\""
                ),
            });
        }

        let optional_path =
            |v: Option<String>| v.filter(|s| !s.trim().is_empty()).map(|s| base.join(s));
        let live = LiveConfig {
            enabled: live_raw.enabled.unwrap_or(false),
            device: live_raw.device.filter(|d| !d.trim().is_empty()),
            model: optional_path(live_raw.model),
            hop_s,
            steps: live_steps,
            min_steps: live_min_steps,
            latency_budget_s,
            sampler: live_sampler,
            seed: live_seed,
            intra_threads: live_intra,
            output: optional_path(live_raw.output).unwrap_or_else(|| paths.output.clone()),
            viewer,
            osc,
            nice: live_nice,
        };
        let config = Config {
            paths,
            serve: ServeConfig {
                workers,
                queue_capacity,
                settle_ms,
                max_attempts,
                shutdown_timeout_s,
            },
            runtime: RuntimeConfig {
                ort_library: optional_path(self.runtime.ort_library),
                ort_intra_threads: intra,
                ort_inter_threads: inter as usize,
                default_model: optional_path(self.runtime.default_model),
            },
            limits: LimitsConfig {
                max_file_bytes: (max_file_mb * MB) as u64,
                max_audio_seconds,
                min_audio_seconds,
                min_free_disk_bytes: (min_free_disk_mb * MB) as u64,
                fail_truncated_audio: self.limits.fail_truncated_audio.unwrap_or(false),
            },
            metrics: MetricsConfig {
                enabled: self.metrics.enabled.unwrap_or(true),
                bind,
            },
            job: JobConfig {
                seed,
                steps,
                guidance,
                chunk_windows,
                time_limit_s,
            },
            live,
            style,
            log_format,
            log_level,
        };
        if errs.is_empty() {
            Ok(config)
        } else {
            Err(ConfigErrors {
                path: None,
                errors: errs,
            })
        }
    }
}

impl Config {
    /// Check the environment the config points at: every directory exists, is a directory and
    /// is writable (claiming renames files out of the inbox); the three are distinct and none
    /// lies inside another; the inbox and the state folder are on one filesystem (the claim is a
    /// rename); the default model, when set, is a model package. With `[live]` enabled, its
    /// output folder too (it may be `paths.output` itself) and its model. Run before anything
    /// starts.
    pub fn preflight(&self) -> Result<()> {
        let mut errs = Vec::new();
        let mut dirs = vec![
            ("paths.inbox", &self.paths.inbox, true),
            ("paths.output", &self.paths.output, true),
            ("paths.state", &self.paths.state, true),
        ];
        if self.live.enabled && self.live.output != self.paths.output {
            dirs.push(("live.output", &self.live.output, true));
        }
        if let Some(style) = &self.style {
            dirs.push(("style.inbox", &style.inbox, true));
        }
        for &(key, dir, must_write) in &dirs {
            let problem = match std::fs::metadata(dir) {
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => Some(format!(
                    "directory does not exist (create it with `mkdir -p {}`)",
                    dir.display()
                )),
                Err(e) => Some(format!("cannot access: {e}")),
                Ok(m) if !m.is_dir() => Some("is not a directory".to_string()),
                Ok(_) if must_write => probe_writable(dir)
                    .err()
                    .map(|e| format!("not writable: {e}")),
                Ok(_) => None,
            };
            if let Some(reason) = problem {
                errs.push(ConfigError::Directory {
                    key,
                    path: dir.clone(),
                    reason,
                });
            }
        }
        if errs.is_empty() {
            errs.extend(overlapping_paths(&dirs));
        }
        let inboxes = std::iter::once(("paths.inbox", &self.paths.inbox))
            .chain(self.style.as_ref().map(|s| ("style.inbox", &s.inbox)));
        for (inbox_key, inbox) in inboxes {
            if errs.is_empty()
                && let Err(reason) = probe_same_filesystem(inbox_key, inbox, &self.paths.state)
            {
                errs.push(ConfigError::Directory {
                    key: "paths.state",
                    path: self.paths.state.clone(),
                    reason,
                });
            }
        }
        if let Some(style) = &self.style
            && !style.style.is_file()
        {
            errs.push(ConfigError::Directory {
                key: "style.style",
                path: style.style.clone(),
                reason: "not a file (the style reference motion: .bvh, .pkl, .npy or .h5)".into(),
            });
        }
        let live_model = self.live.model.as_ref().filter(|_| self.live.enabled);
        let style_model = self.style.as_ref().and_then(|s| s.model.as_ref());
        for (key, model) in [
            ("runtime.default_model", self.runtime.default_model.as_ref()),
            ("live.model", live_model),
            ("style.model", style_model),
        ] {
            if let Some(model) = model
                && !model.join(MODEL_MANIFEST).is_file()
            {
                errs.push(ConfigError::Directory {
                    key,
                    path: model.clone(),
                    reason: format!("not a model package (no {MODEL_MANIFEST} in it)"),
                });
            }
        }
        if let Some(lib) = &self.runtime.ort_library
            && !lib.is_file()
        {
            errs.push(ConfigError::Directory {
                key: "runtime.ort_library",
                path: lib.clone(),
                reason: "file does not exist (run scripts/setup, or point it at libonnxruntime.so)"
                    .into(),
            });
        }
        if errs.is_empty() {
            Ok(())
        } else {
            Err(ConfigErrors {
                path: None,
                errors: errs,
            })
        }
    }
}

/// Why `filter` is not a usable `log.level`, if it is not. The daemon builds its filter with the
/// same parser; tracing reads a bare word as a target name ("verbose" would silence everything),
/// so a directive without `=` must be a level.
fn log_filter_problem(filter: &str) -> Option<String> {
    if let Err(e) = tracing_subscriber::EnvFilter::builder().parse(filter) {
        return Some(e.to_string());
    }
    const LEVELS: &[&str] = &["trace", "debug", "info", "warn", "error", "off"];
    filter
        .split(',')
        .map(str::trim)
        .find(|d| !d.contains('=') && !LEVELS.contains(&d.to_ascii_lowercase().as_str()))
        .map(|d| format!("{d:?} is not a level"))
}

/// The manifest file every model package holds (choreo-models `MANIFEST_FILE`; the config crate
/// sits below the models crate, so the name is repeated here).
const MODEL_MANIFEST: &str = "choreod-model.toml";

/// The same folder named twice, or one inside another: outputs or spool files would land in the
/// inbox (and be taken as songs), or the spool would be scanned as output.
fn overlapping_paths(dirs: &[(&'static str, &PathBuf, bool)]) -> Vec<ConfigError> {
    let real: Vec<_> = dirs
        .iter()
        .map(|(key, dir, _)| {
            (
                *key,
                std::fs::canonicalize(dir).unwrap_or_else(|_| dir.to_path_buf()),
            )
        })
        .collect();
    let mut errs = Vec::new();
    for (i, (key_a, a)) in real.iter().enumerate() {
        for (key_b, b) in &real[i + 1..] {
            let reason = if a == b {
                format!("the same folder as `{key_a}`")
            } else if b.starts_with(a) {
                format!("inside `{key_a}` ({})", a.display())
            } else if a.starts_with(b) {
                format!("contains `{key_a}` ({})", a.display())
            } else {
                continue;
            };
            errs.push(ConfigError::Directory {
                key: key_b,
                path: b.clone(),
                reason: format!("{reason}; the inboxes, output and state must be separate folders"),
            });
        }
    }
    errs
}

/// Rename a probe file from the inbox into the state folder: the claim of every song is such a
/// rename, and across filesystems (or bind mounts) it fails with EXDEV.
fn probe_same_filesystem(
    inbox_key: &str,
    inbox: &Path,
    state: &Path,
) -> std::result::Result<(), String> {
    let name = format!(".choreod-rename-probe-{}", std::process::id());
    let (from, to) = (inbox.join(&name), state.join(&name));
    std::fs::write(&from, b"")
        .map_err(|e| format!("cannot write a probe into {inbox_key}: {e}"))?;
    let renamed = std::fs::rename(&from, &to);
    let _ = std::fs::remove_file(if renamed.is_ok() { &to } else { &from });
    match renamed {
        Ok(()) => Ok(()),
        Err(e) if e.kind() == std::io::ErrorKind::CrossesDevices => Err(format!(
            "not on the filesystem of {inbox_key} ({}): inbox files are claimed by renaming \
             them into the state folder, which cannot cross filesystems; put both on one \
             filesystem",
            inbox.display()
        )),
        Err(e) => Err(format!(
            "cannot rename a probe from {inbox_key} into it: {e}"
        )),
    }
}

fn probe_writable(dir: &Path) -> std::io::Result<()> {
    let probe = dir.join(format!(".choreod-write-probe-{}", std::process::id()));
    std::fs::write(&probe, b"")?;
    std::fs::remove_file(&probe)
}

/// A path from the config as the daemon will use it: absolute, with symlinks and `..` resolved
/// when it exists (paths are relative to the config file's folder, which the user may not see
/// from the path as written).
fn resolved(path: &Path) -> String {
    std::fs::canonicalize(path)
        .or_else(|_| std::path::absolute(path))
        .unwrap_or_else(|_| path.to_path_buf())
        .display()
        .to_string()
}

impl fmt::Display for Config {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let p = &self.paths;
        writeln!(f, "paths.inbox   = {}", resolved(&p.inbox))?;
        writeln!(f, "paths.output  = {}", resolved(&p.output))?;
        writeln!(f, "paths.state   = {}", resolved(&p.state))?;
        let s = &self.serve;
        writeln!(
            f,
            "serve         = workers {}, queue {}, settle {} ms, max attempts {}, shutdown timeout {} s",
            s.workers, s.queue_capacity, s.settle_ms, s.max_attempts, s.shutdown_timeout_s
        )?;
        let r = &self.runtime;
        let show =
            |p: &Option<PathBuf>| p.as_ref().map_or("(default)".to_string(), |p| resolved(p));
        writeln!(
            f,
            "runtime       = ORT library {}, intra {} / inter {} threads, default model {}",
            show(&r.ort_library),
            r.ort_intra_threads,
            r.ort_inter_threads,
            show(&r.default_model)
        )?;
        let l = &self.limits;
        writeln!(
            f,
            "limits        = file {:.0} MB, audio {} to {} s, min free disk {:.0} MB, truncated audio {}",
            l.max_file_bytes as f64 / MB,
            l.min_audio_seconds
                .map_or_else(|| "one model window".to_string(), |s| s.to_string()),
            l.max_audio_seconds,
            l.min_free_disk_bytes as f64 / MB,
            if l.fail_truncated_audio {
                "fails"
            } else {
                "danced as far as it decodes"
            }
        )?;
        writeln!(
            f,
            "metrics       = {}",
            if self.metrics.enabled {
                format!("http://{}/metrics", self.metrics.bind)
            } else {
                "off".into()
            }
        )?;
        let j = &self.job;
        let or_package = |v: Option<String>| v.unwrap_or_else(|| "(package's)".to_string());
        writeln!(
            f,
            "job           = seed {}, steps {}, guidance {}, {} windows per batch, time limit {} s",
            j.seed,
            or_package(j.steps.map(|s| s.to_string())),
            or_package(j.guidance.map(|g| g.to_string())),
            j.chunk_windows
                .map_or_else(|| "(default)".to_string(), |c| c.to_string()),
            j.time_limit_s
        )?;
        let l = &self.live;
        if l.enabled {
            let addr = |a: Option<SocketAddr>| a.map_or("off".to_string(), |a| a.to_string());
            writeln!(
                f,
                "live          = device {}, model {}, hop {} s, steps {} (min {}), latency budget \
                 {} s, sampler {}, seed {}, nice {}, sessions in {}, viewer {}, osc {}",
                l.device.as_deref().unwrap_or("(default input)"),
                show(&l.model),
                l.hop_s,
                or_package(l.steps.map(|s| s.to_string())),
                l.min_steps,
                l.latency_budget_s,
                or_package(l.sampler.map(|s| s.as_str().to_string())),
                l.seed,
                l.nice,
                resolved(&l.output),
                addr(l.viewer),
                addr(l.osc)
            )?;
        } else {
            writeln!(f, "live          = off")?;
        }
        match &self.style {
            Some(st) => writeln!(
                f,
                "style         = inbox {}, style {}, model {}, mode {:?}, guidance {}, steps {}",
                resolved(&st.inbox),
                resolved(&st.style),
                show(&st.model),
                st.mode,
                or_package(st.guidance.map(|g| g.to_string())),
                or_package(st.steps.map(|s| s.to_string())),
            )?,
            None => writeln!(f, "style         = off")?,
        }
        write!(
            f,
            "log           = {:?}, level {}",
            self.log_format, self.log_level
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> Result<Config> {
        RawConfig::parse(text)?.validate(Path::new("/base"))
    }

    const MINIMAL: &str = "[paths]\ninbox = \"in\"\noutput = \"/abs/out\"\nstate = \"st\"\n";

    #[test]
    fn minimal_config_gets_documented_defaults() {
        let c = parse(MINIMAL).unwrap();
        assert_eq!(c.paths.inbox, Path::new("/base/in"));
        assert_eq!(c.paths.output, Path::new("/abs/out"));
        let (workers, threads) = serve_threads(available_cpus(), None, None);
        assert_eq!(
            (c.serve.workers, c.runtime.ort_intra_threads),
            (workers, threads)
        );
        assert_eq!(c.limits.max_audio_seconds, 1200.0);
        assert_eq!(c.limits.min_audio_seconds, None, "the model's window");
        assert_eq!(c.metrics.bind.to_string(), "127.0.0.1:9464");
        assert_eq!(c.log_format, LogFormat::Human);
    }

    #[test]
    fn misspelt_key_is_named_with_its_table_and_line() {
        let e = parse("[paths]\ninbx = \"in\"\n").unwrap_err().to_string();
        assert!(e.contains("line 2, key `paths.inbx`"), "{e}");
        assert!(e.contains("unknown field"), "{e}");
        assert!(!e.contains('\n'), "one line: {e}");
    }

    #[test]
    fn unset_workers_and_threads_share_out_the_cpus_without_oversubscribing() {
        // (cpus, workers set, threads set) -> (workers, threads)
        for (cpus, w, t, want) in [
            (1, None, None, (1, 1)),
            (2, None, None, (2, 1)),
            (3, None, None, (2, 1)),
            (4, None, None, (2, 2)),
            (8, None, None, (2, 4)),
            (16, None, None, (4, 4)),
            (64, None, None, (8, 8)),
            (2, Some(1), None, (1, 2)),
            (8, Some(3), None, (3, 2)),
            (4, Some(6), None, (6, 1)),
            (2, None, Some(2), (1, 2)),
            (8, None, Some(1), (8, 1)),
            (64, None, Some(1), (8, 1)),
            (2, Some(2), Some(2), (2, 2)),
        ] {
            assert_eq!(
                serve_threads(cpus, w, t),
                want,
                "{cpus} CPUs, {w:?} x {t:?}"
            );
        }
        for cpus in 1..=80 {
            for set in [None, Some(1), Some(2), Some(3)] {
                for (w, t) in [
                    serve_threads(cpus, None, None),
                    serve_threads(cpus, set, None),
                    serve_threads(cpus, None, set),
                ] {
                    assert!(w >= 1 && t >= 1, "{cpus}: {w} x {t}");
                    // Oversubscribed only by a given count that alone exceeds the CPUs.
                    assert!(
                        w * t <= cpus || set.is_some_and(|s| s > cpus),
                        "{cpus}: {w} x {t}"
                    );
                }
                let (w, t) = serve_threads(cpus, None, None);
                assert!(
                    w * t > cpus - w.min(cpus),
                    "{cpus}: {w} x {t} leaves a worker's share idle"
                );
            }
        }
        let c = parse(&format!("{MINIMAL}[serve]\nworkers = 1\n")).unwrap();
        assert_eq!(c.runtime.ort_intra_threads, available_cpus());
    }

    #[test]
    fn thread_counts_beyond_the_cpus_are_named() {
        let cpus = std::thread::available_parallelism().map_or(1, std::num::NonZero::get);
        for (table, key) in [
            ("runtime", "ort_intra_threads"),
            ("runtime", "ort_inter_threads"),
            ("live", "intra_threads"),
        ] {
            let e = parse(&format!("{MINIMAL}[{table}]\n{key} = {}\n", cpus + 1))
                .unwrap_err()
                .to_string();
            assert!(
                e.contains(&format!("`{table}.{key}` = {}", cpus + 1))
                    && e.contains(&format!("and {cpus}")),
                "{e}"
            );
            assert!(parse(&format!("{MINIMAL}[{table}]\n{key} = {cpus}\n")).is_ok());
        }
    }

    #[test]
    fn negative_workers_is_named() {
        let e = parse(&format!("{MINIMAL}[serve]\nworkers = -2\n"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("`serve.workers` = -2"), "{e}");
    }

    #[test]
    fn all_problems_are_reported_together() {
        let e = parse("[serve]\nworkers = 0\n[metrics]\nbind = \"nowhere\"\n").unwrap_err();
        let keys: Vec<String> = e.errors.iter().map(ToString::to_string).collect();
        assert_eq!(e.errors.len(), 5, "{keys:?}"); // three missing paths + workers + bind
        assert!(keys.iter().any(|k| k.contains("missing key `paths.state`")));
        assert!(keys.iter().any(|k| k.contains("metrics.bind")));
        for open in ["0.0.0.0:9464", "[::]:9464", "192.168.1.2:9464"] {
            let e = parse(&format!("{MINIMAL}[metrics]\nbind = \"{open}\"\n")).unwrap_err();
            assert_eq!(e.errors.len(), 1, "{open}: {e}");
            assert!(
                e.to_string().contains("metrics.bind") && e.to_string().contains("loopback"),
                "{e}"
            );
        }
    }

    #[test]
    fn job_section_defaults_and_ranges() {
        let c = parse(MINIMAL).unwrap();
        assert_eq!(
            c.job,
            JobConfig {
                seed: 0,
                steps: None,
                guidance: None,
                chunk_windows: None,
                time_limit_s: JobConfig::DEFAULT_TIME_LIMIT_S,
            }
        );
        let c = parse(&format!(
            "{MINIMAL}[job]\nseed = 7\nsteps = 2\nguidance = 1.5\ntime_limit_s = 2.5\n"
        ))
        .unwrap();
        assert_eq!(
            (c.job.seed, c.job.steps, c.job.guidance, c.job.time_limit_s),
            (7, Some(2), Some(1.5), 2.5)
        );
        let e = parse(&format!(
            "{MINIMAL}[job]\nsteps = 0\nseed = -1\ntime_limit_s = 0\n"
        ))
        .unwrap_err();
        let text = e.to_string();
        assert_eq!(e.errors.len(), 3, "{text}");
        assert!(
            text.contains("`job.steps` = 0")
                && text.contains("`job.seed` = -1")
                && text.contains("`job.time_limit_s` = 0: must be between 0.1 and 86400"),
            "{text}"
        );
    }

    #[test]
    fn min_audio_seconds_is_bounded_by_the_maximum() {
        let c = parse(&format!("{MINIMAL}[limits]\nmin_audio_seconds = 1.5\n")).unwrap();
        assert_eq!(c.limits.min_audio_seconds, Some(1.5));
        let e = parse(&format!(
            "{MINIMAL}[limits]\nmax_audio_seconds = 60.0\nmin_audio_seconds = 61.0\n"
        ))
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("`limits.min_audio_seconds` = 61") && e.contains("between 0 and 60"),
            "{e}"
        );
    }

    #[test]
    fn live_section_defaults_are_the_live_commands() {
        let c = parse(MINIMAL).unwrap();
        let l = &c.live;
        assert!(!l.enabled);
        assert_eq!(
            (l.hop_s, l.min_steps, l.seed, l.intra_threads),
            (0.5, 2, 0, 0)
        );
        assert_eq!(l.latency_budget_s, 0.25);
        assert_eq!(l.nice, -10);
        assert_eq!((l.steps, &l.sampler, &l.device), (None, &None, &None));
        assert_eq!((l.viewer, l.osc), (None, None));
        // Sessions go beside the dances unless told otherwise.
        assert_eq!(l.output, Path::new("/abs/out"));
        let c = parse(&format!(
            "{MINIMAL}[live]\nenabled = true\ndevice = \"alsa:pulse\"\nhop_s = 0.25\n\
             sampler = \"dpmsolver++\"\nlatency_budget_s = 0.4\nnice = -5\noutput = \"takes\"\nviewer = \"127.0.0.1:8080\"\n\
             osc = \"192.168.1.5:39539\"\n"
        ))
        .unwrap();
        let l = &c.live;
        assert!(l.enabled);
        assert_eq!(l.device.as_deref(), Some("alsa:pulse"));
        assert_eq!(l.sampler, Some(Sampler::DpmSolverPlusPlus));
        assert_eq!(l.latency_budget_s, 0.4);
        assert_eq!(l.nice, -5);
        assert_eq!(l.output, Path::new("/base/takes"));
        assert_eq!(l.viewer.unwrap().to_string(), "127.0.0.1:8080");
        assert_eq!(l.osc.unwrap().to_string(), "192.168.1.5:39539");
        assert!(c.to_string().contains("viewer 127.0.0.1:8080"), "{c}");
        assert!(c.to_string().contains("nice -5,"), "{c}");
    }

    #[test]
    fn live_section_problems_are_named() {
        let e = parse(&format!(
            "{MINIMAL}[live]\nhop_s = 0\nmin_steps = 0\nsampler = \"euler\"\nlatency_budget_s = -1\n\
             nice = -21\nviewer = \"0.0.0.0:8080\"\nosc = \"vseeface\"\n"
        ))
        .unwrap_err();
        let text = e.to_string();
        assert_eq!(e.errors.len(), 7, "{text}");
        for key in [
            "`live.hop_s` = 0",
            "`live.min_steps` = 0",
            "`live.latency_budget_s` = -1",
            "`live.nice` = -21",
            "`live.sampler` = \"euler\"",
            "`live.viewer` = \"0.0.0.0:8080\": the viewer listens on loopback",
            "`live.osc` = \"vseeface\"",
        ] {
            assert!(text.contains(key), "{key}: {text}");
        }
        let e = parse(&format!("{MINIMAL}[live]\nport = 1\n")).unwrap_err();
        assert!(e.to_string().contains("key `live.port`"), "{e}");
    }

    #[test]
    fn preflight_checks_the_live_folder_and_model_only_when_enabled() {
        let dir = tempfile::tempdir().unwrap();
        let off = config_in(
            dir.path(),
            "a",
            "b",
            "c",
            "[live]\noutput = \"gone\"\nmodel = \"m\"\n",
        );
        off.preflight().unwrap();
        let on = config_in(
            dir.path(),
            "a",
            "b",
            "c",
            "[live]\nenabled = true\noutput = \"gone\"\nmodel = \"m\"\n",
        );
        let e = on.preflight().unwrap_err().to_string();
        assert!(
            e.contains("`live.output`") && e.contains("does not exist"),
            "{e}"
        );
        assert!(
            e.contains("`live.model`") && e.contains("not a model package"),
            "{e}"
        );
        // Sessions inside the inbox would be taken for songs.
        let inside = config_in(
            dir.path(),
            "a",
            "b",
            "c",
            "[live]\nenabled = true\noutput = \"a/live\"\n",
        );
        std::fs::create_dir_all(dir.path().join("a/live")).unwrap();
        let e = inside.preflight().unwrap_err().to_string();
        assert!(
            e.contains("`live.output`") && e.contains("inside `paths.inbox`"),
            "{e}"
        );
        // The default: paths.output itself.
        config_in(dir.path(), "a", "b", "c", "[live]\nenabled = true\n")
            .preflight()
            .unwrap();
    }

    #[test]
    fn wrong_type_is_named() {
        let e = parse(&format!(
            "{MINIMAL}[limits]\nmax_audio_seconds = \"long\"\n"
        ))
        .unwrap_err();
        assert!(e.to_string().contains("limits.max_audio_seconds"), "{e}");
    }

    #[test]
    fn preflight_names_a_missing_directory() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir(dir.path().join("in")).unwrap();
        std::fs::create_dir(dir.path().join("out")).unwrap();
        let text = "[paths]\ninbox = \"in\"\noutput = \"out\"\nstate = \"gone\"\n";
        let c = RawConfig::parse(text)
            .unwrap()
            .validate(dir.path())
            .unwrap();
        let e = c.preflight().unwrap_err().to_string();
        assert!(
            e.contains("`paths.state`") && e.contains("does not exist"),
            "{e}"
        );
        std::fs::create_dir(dir.path().join("gone")).unwrap();
        c.preflight().unwrap();
    }

    #[test]
    fn invalid_log_level_is_named() {
        for bad in ["verbose", "choreod=loud", "info,,", "info,[x"] {
            let e = parse(&format!("{MINIMAL}[log]\nlevel = \"{bad}\"\n")).unwrap_err();
            assert!(e.to_string().contains("`log.level`"), "{bad}: {e}");
        }
        parse(&format!(
            "{MINIMAL}[log]\nlevel = \"choreod=debug,ort=warn\"\n"
        ))
        .unwrap();
    }

    #[test]
    fn style_section_is_off_by_default_and_names_its_problems() {
        assert_eq!(parse(MINIMAL).unwrap().style, None);
        // Keys of a disabled section are still checked, but nothing is required.
        assert_eq!(
            parse(&format!("{MINIMAL}[style]\nmode = \"inversion\"\n"))
                .unwrap()
                .style,
            None
        );
        let c = parse(&format!(
            "{MINIMAL}[style]\nenabled = true\ninbox = \"si\"\nstyle = \"s.bvh\"\nsteps = 20\n"
        ))
        .unwrap();
        assert_eq!(
            c.style,
            Some(StyleConfig {
                inbox: PathBuf::from("/base/si"),
                style: PathBuf::from("/base/s.bvh"),
                model: None,
                mode: StyleMode::Transfer,
                guidance: None,
                steps: Some(20),
            })
        );
        let e = parse(&format!(
            "{MINIMAL}[style]\nenabled = true\nmode = \"blend\"\nsteps = 0\n"
        ))
        .unwrap_err()
        .to_string();
        for part in [
            "`style.inbox`",
            "`style.style`",
            "`style.mode` = \"blend\"",
            "`style.steps` = 0",
        ] {
            assert!(e.contains(part), "{part} in {e}");
        }
        let e = parse(&format!(
            "{MINIMAL}[style]\nmode = \"inversion\"\nguidance = 2\n"
        ))
        .unwrap_err()
        .to_string();
        assert!(e.contains("`style.guidance`"), "{e}");
    }

    #[test]
    fn preflight_checks_the_style_inbox_file_and_model() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("s.bvh"), b"HIERARCHY").unwrap();
        let style = |inbox: &str, style: &str| {
            format!("[style]\nenabled = true\ninbox = \"{inbox}\"\nstyle = \"{style}\"\n")
        };
        std::fs::create_dir_all(dir.path().join("si")).unwrap();
        config_in(dir.path(), "a", "b", "c", &style("si", "s.bvh"))
            .preflight()
            .unwrap();
        let e = config_in(dir.path(), "a", "b", "c", &style("a", "s.bvh"))
            .preflight()
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("`style.inbox`") && e.contains("the same folder as `paths.inbox`"),
            "{e}"
        );
        std::fs::create_dir_all(dir.path().join("c/si")).unwrap();
        let e = config_in(dir.path(), "a", "b", "c", &style("c/si", "s.bvh"))
            .preflight()
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("`style.inbox`") && e.contains("inside `paths.state`"),
            "{e}"
        );
        let e = config_in(
            dir.path(),
            "a",
            "b",
            "c",
            &format!("{}model = \"m\"\n", style("si", "gone.bvh")),
        )
        .preflight()
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("`style.style`") && e.contains("gone.bvh") && e.contains("not a file"),
            "{e}"
        );
        assert!(
            e.contains("`style.model`") && e.contains("not a model package"),
            "{e}"
        );
    }

    #[test]
    fn preflight_refuses_a_style_inbox_on_another_filesystem() {
        // As for paths.inbox: /dev/shm is a tmpfs, the temporary folder is on the disk.
        let tmp = tempfile::tempdir().unwrap();
        let Ok(shm) = tempfile::tempdir_in("/dev/shm") else {
            eprintln!("skipped: no /dev/shm to put a style inbox on another filesystem");
            return;
        };
        let dev = |p: &Path| std::os::unix::fs::MetadataExt::dev(&std::fs::metadata(p).unwrap());
        if dev(tmp.path()) == dev(shm.path()) {
            eprintln!("skipped: /dev/shm and the temporary folder share a filesystem here");
            return;
        }
        std::fs::write(tmp.path().join("s.bvh"), b"x").unwrap();
        let c = config_in(
            tmp.path(),
            "a",
            "b",
            "c",
            &format!(
                "[style]\nenabled = true\ninbox = \"{}\"\nstyle = \"s.bvh\"\n",
                shm.path().display()
            ),
        );
        let e = c.preflight().unwrap_err().to_string();
        assert!(
            e.contains("`paths.state`") && e.contains("not on the filesystem of style.inbox"),
            "{e}"
        );
    }

    /// A config in a temporary folder with the three paths given relative to it (created).
    fn config_in(dir: &Path, inbox: &str, output: &str, state: &str, extra: &str) -> Config {
        for d in [inbox, output, state] {
            std::fs::create_dir_all(dir.join(d)).unwrap();
        }
        let text = format!(
            "[paths]\ninbox = \"{inbox}\"\noutput = \"{output}\"\nstate = \"{state}\"\n{extra}"
        );
        RawConfig::parse(&text).unwrap().validate(dir).unwrap()
    }

    #[test]
    fn preflight_refuses_overlapping_folders() {
        let dir = tempfile::tempdir().unwrap();
        for (inbox, output, state, key, what) in [
            (
                "in",
                "in",
                "st",
                "`paths.output`",
                "the same folder as `paths.inbox`",
            ),
            (
                "in",
                "out",
                "in/st",
                "`paths.state`",
                "inside `paths.inbox`",
            ),
            (
                "in/x",
                "out",
                "in",
                "`paths.state`",
                "contains `paths.inbox`",
            ),
            (
                "in",
                "st/out",
                "st",
                "`paths.state`",
                "contains `paths.output`",
            ),
        ] {
            let c = config_in(dir.path(), inbox, output, state, "");
            let e = c.preflight().unwrap_err().to_string();
            assert!(
                e.contains(key) && e.contains(what),
                "{inbox} {output} {state}: {e}"
            );
        }
        config_in(dir.path(), "a", "b", "c", "")
            .preflight()
            .unwrap();
    }

    #[test]
    fn preflight_refuses_a_missing_default_model() {
        let dir = tempfile::tempdir().unwrap();
        let c = config_in(
            dir.path(),
            "a",
            "b",
            "c",
            "[runtime]\ndefault_model = \"m\"\n",
        );
        let e = c.preflight().unwrap_err().to_string();
        assert!(
            e.contains("`runtime.default_model`") && e.contains("not a model package"),
            "{e}"
        );
        std::fs::create_dir(dir.path().join("m")).unwrap();
        assert!(
            c.preflight().is_err(),
            "a folder without a manifest is no package"
        );
        std::fs::write(dir.path().join("m").join(MODEL_MANIFEST), "").unwrap();
        c.preflight().unwrap();
    }

    #[test]
    fn preflight_refuses_inbox_and_state_on_different_filesystems() {
        // /dev/shm is a tmpfs on Linux machines; the temporary folder is on the disk.
        let tmp = tempfile::tempdir().unwrap();
        let Ok(shm) = tempfile::tempdir_in("/dev/shm") else {
            eprintln!("skipped: no /dev/shm to put a state folder on another filesystem");
            return;
        };
        let dev = |p: &Path| std::os::unix::fs::MetadataExt::dev(&std::fs::metadata(p).unwrap());
        if dev(tmp.path()) == dev(shm.path()) {
            eprintln!("skipped: /dev/shm and the temporary folder share a filesystem here");
            return;
        }
        let state = shm.path().display().to_string();
        let c = config_in(tmp.path(), "in", "out", &state, "");
        let e = c.preflight().unwrap_err().to_string();
        assert!(
            e.contains("`paths.state`") && e.contains("cannot cross filesystems"),
            "{e}"
        );
        assert_eq!(
            std::fs::read_dir(tmp.path().join("in")).unwrap().count(),
            0,
            "the probe left nothing in the inbox"
        );
        // The output may live anywhere: it is written, not renamed into.
        let out = shm.path().display().to_string();
        config_in(tmp.path(), "in", &out, "st", "")
            .preflight()
            .unwrap();
    }

    #[test]
    fn example_config_in_the_repository_is_valid() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("choreod.example.toml");
        let c = crate::load(&path).unwrap();
        assert_eq!(
            (c.serve.workers, c.runtime.ort_intra_threads),
            serve_threads(available_cpus(), None, None)
        );
    }
}
