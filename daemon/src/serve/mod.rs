//! `choreod serve`: the crash-safe watch-folder service.
//!
//! The pipeline is sources → jobs → sinks, as enums (house style 7): [`Source::WatchFolder`]
//! claims complete inbox files into the [`spool`] and queues a [`Job`] for each; worker threads
//! (one [`ModelPackage`] each) run `dance_file` and hand the result to [`Sink::MotionFile`].
//! With `[live]` enabled, a live-audio source runs beside them on its own package and thread
//! ([`crate::live::source`]): it makes no jobs, so it is not a `Source` of the queue.
//!
//! Start-up: lock the spool, clean temporary files, resume the jobs left in `work/`, then watch.
//! Shutdown (SIGTERM/SIGINT): stop intake, let in-flight jobs finish within
//! `serve.shutdown_timeout_s`, else exit and leave them in `work/` to resume. A second signal
//! exits at once (same guarantees: outputs are atomic, jobs resume).

mod fatal;
mod intake;
mod metrics;
mod progress;
mod spool;
mod worker;

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, SyncSender, TrySendError};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::Context;
use choreo_config::Config;
use choreo_models::{ModelPackage, OrtRuntime, RuntimeOptions};

use crate::settings::{self, PackageKind};

pub use intake::WatchFolder;
use metrics::Metrics;
use spool::{JobKind, JobRecord, Spool};
use worker::{StyleJobOptions, WorkerOptions};

/// Where jobs come from.
#[derive(Debug)]
pub enum Source {
    /// Songs dropped into a folder.
    WatchFolder(WatchFolder),
}

/// Where finished dances go.
#[derive(Debug)]
pub enum Sink {
    /// One atomic HDF5 motion file per job in a folder.
    MotionFile { dir: PathBuf },
}

impl Sink {
    /// Where the result of `record` goes.
    pub fn target(&self, record: &JobRecord) -> PathBuf {
        match self {
            Sink::MotionFile { dir } => dir.join(&record.output),
        }
    }

    /// The folder whose free space bounds the sink.
    pub fn dir(&self) -> &std::path::Path {
        match self {
            Sink::MotionFile { dir } => dir,
        }
    }
}

/// One unit of work: a claimed input with its durable record.
#[derive(Debug)]
pub struct Job {
    pub record: JobRecord,
    /// Running when the last daemon died: runs alone, so a second death names it.
    pub suspect: bool,
}

/// What a source needs to feed jobs in.
#[derive(Debug)]
pub struct SourceContext {
    pub shutdown: Arc<AtomicBool>,
    pub spool: Arc<Spool>,
    queue: SyncSender<Job>,
    metrics: Arc<Metrics>,
}

impl SourceContext {
    /// Queue a claimed job, waiting for room (the queue is bounded). `false` when shutdown came
    /// first: the job stays in `work/` and resumes at the next start.
    pub fn enqueue(&self, mut job: Job) -> bool {
        loop {
            // Count before sending so a fast worker never takes the depth below zero.
            self.metrics.queue_depth.fetch_add(1, Ordering::Relaxed);
            match self.queue.try_send(job) {
                Ok(()) => return true,
                Err(TrySendError::Full(j)) => {
                    self.metrics.queue_depth.fetch_sub(1, Ordering::Relaxed);
                    job = j;
                    if self.shutdown.load(Ordering::Relaxed) {
                        return false;
                    }
                    std::thread::sleep(Duration::from_millis(20));
                }
                Err(TrySendError::Disconnected(_)) => {
                    self.metrics.queue_depth.fetch_sub(1, Ordering::Relaxed);
                    return false;
                }
            }
        }
    }
}

impl Source {
    /// Run the source on the calling thread until shutdown.
    pub fn run(&self, ctx: &SourceContext) -> anyhow::Result<()> {
        match self {
            Source::WatchFolder(w) => w.run(ctx),
        }
    }
}

/// State the workers share.
#[derive(Debug)]
pub struct Shared {
    pub shutdown: Arc<AtomicBool>,
    /// Set just before the process exits with jobs still running: their results are no longer
    /// trusted (the runtime is being torn down), so workers must not record any outcome.
    pub abandoned: AtomicBool,
    pub spool: Arc<Spool>,
    pub queue: Mutex<Receiver<Job>>,
    pub metrics: Arc<Metrics>,
    pub sink: Sink,
    /// Lets a suspect run alone and the other jobs side by side.
    pub gate: worker::Gate,
}

/// Catch SIGTERM/SIGINT: the first sets the returned flag (graceful shutdown), the second exits
/// at once with code 1. Installed first thing, so a signal during start-up (loading the config
/// and models) also stops the daemon gracefully instead of killing it.
pub fn install_signal_handlers() -> anyhow::Result<Arc<AtomicBool>> {
    let shutdown = Arc::new(AtomicBool::new(false));
    for signal in [signal_hook::consts::SIGTERM, signal_hook::consts::SIGINT] {
        signal_hook::flag::register_conditional_shutdown(signal, 1, Arc::clone(&shutdown))
            .context("installing signal handlers")?;
        signal_hook::flag::register(signal, Arc::clone(&shutdown))
            .context("installing signal handlers")?;
    }
    Ok(shutdown)
}

/// Run the service with a validated, preflighted config until `shutdown` is set (SIGTERM/SIGINT,
/// see [`install_signal_handlers`]).
pub fn run(
    config: &Config,
    ort: &OrtRuntime,
    model_dir: &std::path::Path,
    shutdown: Arc<AtomicBool>,
) -> anyhow::Result<()> {
    let live_metrics = Arc::new(crate::live::LiveMetrics::default());
    let styles = Arc::new(crate::stylize::StyleCache::default());
    let metrics = {
        let mut m = Metrics::default();
        m.live = config.live.enabled.then(|| Arc::clone(&live_metrics));
        m.styles = config.style.is_some().then(|| Arc::clone(&styles));
        Arc::new(m)
    };
    if config.metrics.enabled {
        let addr = metrics::serve(config.metrics.bind, Arc::clone(&metrics))?;
        tracing::info!(url = %format!("http://{addr}/metrics"), "metrics endpoint listening");
    }

    let spool = Arc::new(Spool::open(&config.paths.state, &config.paths.output)?);
    let mut resumed = spool.recover()?;
    if !resumed.is_empty() {
        let suspects = resumed.iter().filter(|r| r.suspect).count();
        tracing::info!(
            jobs = resumed.len(),
            suspects,
            "resuming jobs left by the last run (those running at an unclean exit first, one at a time)"
        );
    }
    // Suspects first (each runs alone), then the rest in arrival order.
    resumed.sort_by_key(|r| !r.suspect);
    // From here on a crash is told from a kill from outside (see `fatal`).
    fatal::record_fatal_signals(spool.arm_running_marker()?);

    // One package per worker, loaded before anything starts: a model that cannot load
    // refuses the start (house style 3).
    let mut runtime = RuntimeOptions::default();
    runtime.intra_threads = config.runtime.ort_intra_threads;
    runtime.inter_threads = config.runtime.ort_inter_threads;
    warn_if_oversubscribed(config);
    // Spin-waiting ORT threads of concurrent workers would take cores from each other.
    runtime.spin_threads = config.serve.workers == 1;
    let style_model = config
        .style
        .as_ref()
        .map(|s| PackageKind::Style.dir(s.model.as_deref()));
    let mut packages = Vec::with_capacity(config.serve.workers);
    for _ in 0..config.serve.workers {
        let style = match &style_model {
            Some(dir) => Some(settings::load_package(dir, &runtime, ort)?),
            None => None,
        };
        let dance = settings::load_package(model_dir, &runtime, ort)?;
        // A style package as the song model would fail every song: refuse the start instead.
        let manifest = dance.manifest();
        if manifest.task == choreo_models::Task::Lodge {
            manifest.lodge_spec()?;
        } else {
            manifest.dance_spec()?;
        }
        packages.push(worker::Packages { dance, style });
    }
    let style = match (
        &config.style,
        packages.first_mut().and_then(|p| p.style.as_mut()),
    ) {
        (Some(style), Some(package)) => Some(style_job_options(style, package, styles)?),
        _ => None,
    };
    // Before any job starts, so a live section that cannot run refuses the start.
    let live = if config.live.enabled {
        Some(crate::live::source::LiveSource::start(
            &config.live,
            ort,
            config.live.model.as_deref().unwrap_or(model_dir),
            live_metrics,
            Arc::clone(&shutdown),
        )?)
    } else {
        None
    };
    let options = WorkerOptions {
        song: settings::song_options(config),
        style,
        min_free_disk_bytes: config.limits.min_free_disk_bytes,
        max_attempts: config.serve.max_attempts,
        time_limit_s: config.job.time_limit_s,
        fault: worker::injected_fault(),
    };

    let (tx, rx) = std::sync::mpsc::sync_channel(config.serve.queue_capacity);
    let shared = Arc::new(Shared {
        shutdown: Arc::clone(&shutdown),
        abandoned: AtomicBool::new(false),
        spool: Arc::clone(&spool),
        queue: Mutex::new(rx),
        metrics: Arc::clone(&metrics),
        sink: Sink::MotionFile {
            dir: config.paths.output.clone(),
        },
        gate: worker::Gate::default(),
    });
    let mut workers = Vec::new();
    for (i, package) in packages.into_iter().enumerate() {
        let shared = Arc::clone(&shared);
        let options = options.clone();
        let handle = std::thread::Builder::new()
            .name(format!("worker-{i}"))
            .spawn(move || worker::run(i, package, &shared, &options))
            .context("starting a worker thread")?;
        workers.push(handle);
    }
    metrics.workers.store(workers.len(), Ordering::Relaxed);

    let settle = Duration::from_millis(config.serve.settle_ms);
    let mut sources = vec![Source::WatchFolder(WatchFolder {
        inbox: config.paths.inbox.clone(),
        kind: JobKind::Dance,
        settle,
    })];
    if let Some(style) = &config.style {
        sources.push(Source::WatchFolder(WatchFolder {
            inbox: style.inbox.clone(),
            kind: JobKind::Stylize,
            settle,
        }));
    }
    // Resumed jobs first, in arrival order (they are already claimed), then new files.
    let mut resumed = Some(resumed);
    let mut intakes = Vec::new();
    for (i, source) in sources.into_iter().enumerate() {
        let ctx = SourceContext {
            shutdown: Arc::clone(&shutdown),
            spool: Arc::clone(&spool),
            queue: tx.clone(),
            metrics: Arc::clone(&metrics),
        };
        let resumed = resumed.take().unwrap_or_default();
        let intake = std::thread::Builder::new()
            .name(format!("intake-{i}"))
            .spawn(move || {
                for spool::Recovered { record, suspect } in resumed {
                    if !ctx.enqueue(Job { record, suspect }) {
                        return Ok(());
                    }
                }
                let result = source.run(&ctx);
                if result.is_err() {
                    // Without intake the daemon is useless: stop everything.
                    ctx.shutdown.store(true, Ordering::Relaxed);
                }
                result
            })
            .context("starting the intake thread")?;
        intakes.push(intake);
    }
    drop(tx);
    metrics.ready.store(true, Ordering::Relaxed);
    tracing::info!(workers = workers.len(), model = %model_dir.display(), "choreod serve ready");

    while !shutdown.load(Ordering::Relaxed) {
        std::thread::sleep(Duration::from_millis(100));
    }
    metrics.ready.store(false, Ordering::Relaxed);
    tracing::info!("shutting down: intake stopped, waiting for jobs in flight");
    let intake_result = intakes
        .into_iter()
        .map(|intake| match intake.join() {
            Ok(r) => r,
            Err(_) => Err(anyhow::anyhow!("the intake thread panicked")),
        })
        .collect::<anyhow::Result<Vec<()>>>();
    let deadline = Instant::now() + Duration::from_secs_f64(config.serve.shutdown_timeout_s);
    while workers.iter().any(|w| !w.is_finished()) && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(50));
    }
    let unfinished = workers.iter().filter(|w| !w.is_finished()).count();
    if unfinished > 0 {
        shared.abandoned.store(true, Ordering::SeqCst);
        // Exiting kills them mid-job: no output appears under a final name (writes are
        // atomic) and the jobs stay in work/ to resume at the next start.
        tracing::warn!(
            jobs = unfinished,
            timeout_s = config.serve.shutdown_timeout_s,
            "leaving unfinished jobs to resume at the next start"
        );
    } else {
        for w in workers {
            let _ = w.join();
        }
    }
    if let Some(live) = live {
        live.join();
    }
    intake_result.context("watching the inbox")?;
    // Jobs left in work/ now were stopped by us, not running when the daemon died.
    spool.mark_clean_exit()?;
    tracing::info!("stopped");
    Ok(())
}

/// Log how the jobs share the CPUs, and warn when the configured workers × ORT threads exceed
/// them (both set by hand: unset ones are chosen to fit, see `choreo_config::serve_threads`).
fn warn_if_oversubscribed(config: &Config) {
    let cpus = choreo_config::available_cpus();
    let (workers, threads) = (config.serve.workers, config.runtime.ort_intra_threads);
    if workers * threads > cpus {
        tracing::warn!(
            workers,
            ort_intra_threads = threads,
            cpus,
            "serve.workers x runtime.ort_intra_threads is more threads than CPUs: jobs running \
             together will take CPUs from each other (unset either to have it chosen)"
        );
    } else {
        tracing::info!(
            workers,
            ort_intra_threads = threads,
            cpus,
            "CPUs shared out among the workers"
        );
    }
}

/// The stylize options of every style job, once the style package and the style reference are
/// known to work together: the reference is read and encoded now, into `styles` (every job
/// reuses it while the file is unchanged), and one the package cannot use refuses the start
/// (exit code 4) instead of failing every job.
fn style_job_options(
    style: &choreo_config::StyleConfig,
    package: &mut ModelPackage,
    styles: Arc<crate::stylize::StyleCache>,
) -> anyhow::Result<StyleJobOptions> {
    // The errors name the file or package already; the key says where it came from.
    let not_ready = |key: &str, e: &dyn std::fmt::Display| {
        anyhow::Error::new(crate::exit::NotReady(format!("{key}: {e}")))
    };
    choreo_models::style_config(package).map_err(|e| not_ready("style.model", &e))?;
    let source = choreo_models::StyleSource::Motion(choreo_models::MotionSource::new(&style.style));
    styles
        .get(package, &source)
        .map_err(|e| not_ready("style.style", &e))?;
    Ok(StyleJobOptions {
        reference: style.style.clone(),
        options: settings::stylize_options(style),
        styles,
    })
}
