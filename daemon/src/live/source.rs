//! The live source of `choreod serve` (`[live]` in the config): sessions run one after another
//! on their own thread beside the watch folder, each writing `live-<UTC time>.h5` into
//! `live.output`; the viewer stays up across sessions. A session that cannot start (no such
//! device yet, the sound server restarting) or that fails is logged and retried with backoff;
//! the watch folder is never stopped by it. On shutdown the running session's file is finished.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use anyhow::Context;
use choreo_config::LiveConfig;
use choreo_models::OrtRuntime;

use super::{LiveMetrics, LiveViewer, check_options, run_session};
use crate::settings;

/// Retry backoff of a session that failed: first wait, doubling up to the cap.
const RETRY_START: Duration = Duration::from_secs(1);
const RETRY_MAX: Duration = Duration::from_secs(30);

/// A running live source; [`LiveSource::join`] waits for its last session to be finished.
#[derive(Debug)]
pub struct LiveSource {
    /// Owns the viewer too: it stops when the last session is finished.
    thread: JoinHandle<()>,
}

impl LiveSource {
    /// Load the package and check the options against it, start the viewer, then run sessions
    /// until `shutdown`, counting into `metrics`. Errors here refuse the daemon's start (a wrong
    /// hop, a taken viewer port); a missing device does not.
    pub fn start(
        config: &LiveConfig,
        ort: &OrtRuntime,
        model_dir: &Path,
        metrics: Arc<LiveMetrics>,
        shutdown: Arc<AtomicBool>,
    ) -> anyhow::Result<Self> {
        let runtime = settings::runtime(config.intra_threads);
        // Loaded on a thread at the session's priority: ONNX Runtime's worker threads start with
        // the package and inherit it (the daemon's own threads keep theirs).
        let nice = config.nice;
        let mut package = std::thread::scope(|s| {
            s.spawn(|| {
                super::priority::raise_current_thread(nice);
                settings::load_package(model_dir, &runtime, ort)
            })
            .join()
        })
        .map_err(|_| anyhow::anyhow!("loading the live package panicked"))?
        .with_context(|| format!("live.model {}", model_dir.display()))?;
        let mut options = settings::live_options(config);
        check_options(package.manifest(), &options).context("[live]")?;
        let viewer = match config.viewer {
            Some(bind) => {
                let v = LiveViewer::start(bind, package.manifest(), nice)
                    .with_context(|| format!("live.viewer {bind}"))?;
                tracing::info!(url = %format!("http://{}/", v.addr()), "live viewer listening");
                Some(v)
            }
            None => None,
        };
        let dir = config.output.clone();
        let thread = std::thread::Builder::new()
            .name("live-source".into())
            .spawn(move || {
                let mut backoff = RETRY_START;
                while !shutdown.load(Ordering::Relaxed) {
                    options.output = Some(session_path(&dir));
                    let started = Instant::now();
                    let session = run_session(
                        &mut package,
                        &options,
                        viewer.as_ref(),
                        &metrics,
                        shutdown.clone(),
                    );
                    match session {
                        Ok(stats) if !stats.output_written => tracing::info!(
                            audio_s = stats.audio_s,
                            "live session made no motion; no file written"
                        ),
                        Ok(stats) => tracing::info!(
                            file = %options.output.as_deref().unwrap_or(&dir).display(),
                            frames = stats.frames,
                            audio_s = stats.audio_s,
                            overruns = stats.overruns,
                            reconnects = stats.reconnects,
                            "live session finished"
                        ),
                        Err(e) => {
                            // A session that ran for a while earns a fresh backoff.
                            if started.elapsed() > RETRY_MAX {
                                backoff = RETRY_START;
                            }
                            tracing::warn!(
                                error = %format!("{e:#}"),
                                retry_in_s = backoff.as_secs(),
                                "live session stopped; retrying"
                            );
                            sleep_unless(&shutdown, backoff);
                            backoff = (backoff * 2).min(RETRY_MAX);
                        }
                    }
                }
            })
            .context("starting the live source")?;
        Ok(Self { thread })
    }

    /// Wait for the source to stop (after shutdown was set): the session file is finished.
    pub fn join(self) {
        if self.thread.join().is_err() {
            tracing::error!("the live source panicked");
        }
    }
}

/// `dir/live-<UTC time>.h5`, with `-2`, `-3`... when a session of the same second exists.
fn session_path(dir: &Path) -> PathBuf {
    let stamp = choreo_datasets::now_utc().replace(':', "");
    let mut path = dir.join(format!("live-{stamp}.h5"));
    let mut n = 2;
    while path.exists() {
        path = dir.join(format!("live-{stamp}-{n}.h5"));
        n += 1;
    }
    path
}

/// Sleep `d`, waking early when `flag` is set.
fn sleep_unless(flag: &AtomicBool, d: Duration) {
    let end = Instant::now() + d;
    while !flag.load(Ordering::Relaxed) && Instant::now() < end {
        std::thread::sleep(Duration::from_millis(50));
    }
}
