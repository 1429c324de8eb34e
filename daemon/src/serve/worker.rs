//! A worker thread: owns one model package (ORT sessions are used with `&mut`), takes jobs
//! from the shared queue and turns each into exactly one outcome.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::mpsc::RecvTimeoutError;
use std::sync::{Arc, Condvar, Mutex, MutexGuard, PoisonError};
use std::time::{Duration, Instant};

use choreo_models::{ModelPackage, SongOptions, StylizeOptions};

use super::progress::ProgressReport;
use super::spool::{Failure, JobKind, JobRecord};
use super::{Job, Shared};
use crate::dance::{DanceExtras, DanceReport, dance_file};
use crate::stylize::{StyleCache, StylizeJob, StylizeReport, stylize_file};

/// How often an idle worker looks at the shutdown flag.
const POLL: Duration = Duration::from_millis(100);

/// Per-worker settings.
#[derive(Debug, Clone)]
pub struct WorkerOptions {
    /// Dance jobs' settings and input limits.
    pub song: SongOptions,
    /// Style jobs' settings, with `[style]` enabled.
    pub style: Option<StyleJobOptions>,
    pub min_free_disk_bytes: u64,
    pub max_attempts: u32,
    /// `job.time_limit_s`: seconds a job's model may run.
    pub time_limit_s: f64,
    /// Test-only fault injection ([`injected_fault`]).
    pub fault: Option<Fault>,
}

/// How every style job is stylized (`[style]`).
#[derive(Debug, Clone)]
pub struct StyleJobOptions {
    /// `style.style`: the style reference motion.
    pub reference: PathBuf,
    pub options: StylizeOptions,
    /// The reference encoded once, shared by the workers (re-encoded when the file changes).
    pub styles: Arc<StyleCache>,
}

/// A worker's models: the dance package, and the style package with `[style]` enabled.
#[derive(Debug)]
pub struct Packages {
    pub dance: ModelPackage,
    pub style: Option<ModelPackage>,
}

/// What a successful job reports.
enum Report {
    Dance(DanceReport),
    Stylize(StylizeReport),
}

/// A fault injected by `CHOREOD_FAULT` into the jobs whose file name contains `text`.
#[derive(Debug, Clone)]
pub struct Fault {
    /// `panic-on`: the job panics (a bug, caught: the job fails). `abort-on`: the process aborts
    /// (SIGABRT, as a crash in a decoder or a failed allocation would end it).
    pub abort: bool,
    pub text: String,
}

/// `CHOREOD_FAULT=panic-on:<text>` or `abort-on:<text>`, read once at start (README, "Testing
/// the daemon"), so tests can drive the release binary through a job's panic or crash path.
/// Test-only; any other value is ignored with a warning.
pub fn injected_fault() -> Option<Fault> {
    let value = std::env::var("CHOREOD_FAULT").ok()?;
    let fault = [("panic-on:", false), ("abort-on:", true)]
        .into_iter()
        .find_map(|(prefix, abort)| {
            let text = value.strip_prefix(prefix).filter(|t| !t.is_empty())?;
            Some(Fault {
                abort,
                text: text.to_string(),
            })
        });
    match &fault {
        Some(f) => tracing::warn!(
            text = f.text,
            abort = f.abort,
            "fault injection on (CHOREOD_FAULT): jobs whose name contains it fail"
        ),
        None => tracing::warn!(
            value,
            "ignoring CHOREOD_FAULT: the faults are panic-on:<text> and abort-on:<text>"
        ),
    }
    fault
}

/// Take jobs until shutdown. Never starts a job after shutdown was asked for; the job being
/// worked on is finished.
pub fn run(index: usize, mut packages: Packages, shared: &Shared, options: &WorkerOptions) {
    loop {
        if shared.shutdown.load(Ordering::Relaxed) {
            break;
        }
        let job = {
            let rx = shared.queue.lock().unwrap_or_else(PoisonError::into_inner);
            rx.recv_timeout(POLL)
        };
        let job = match job {
            Ok(job) => job,
            Err(RecvTimeoutError::Timeout) => continue,
            Err(RecvTimeoutError::Disconnected) => break,
        };
        shared.metrics.queue_depth.fetch_sub(1, Ordering::Relaxed);
        if shared.shutdown.load(Ordering::Relaxed) {
            // Claimed but not started: it stays in work/ and resumes at the next start.
            break;
        }
        let _pass = shared.gate.enter(job.suspect);
        run_job(index, &mut packages, shared, options, job);
    }
    tracing::debug!(worker = index, "worker stopped");
}

/// Who may run: a suspect runs alone, every other job beside the others (up to `workers`).
///
/// Suspects wait for the running jobs to finish and, while one waits, no new job starts: the
/// suspects sit at the head of the queue, so the other worker would otherwise take job after
/// job and the suspect, held by its worker, would never get its turn (what `std::sync::RwLock`
/// did: a reader that arrives while the lock is free takes it even when a writer was woken).
/// Suspects exist only at start-up, so the others wait for them only once.
#[derive(Debug, Default)]
pub struct Gate {
    state: Mutex<GateState>,
    changed: Condvar,
}

#[derive(Debug, Default)]
struct GateState {
    /// Jobs inside, a suspect included.
    running: usize,
    /// The one inside is a suspect.
    alone: bool,
    /// Suspects waiting to go in.
    suspects_waiting: usize,
}

/// Being inside the [`Gate`]; leaving it (drop) lets the waiting jobs look again.
#[derive(Debug)]
pub struct GatePass<'a>(&'a Gate);

impl Gate {
    /// Wait until the job may run: a suspect (`alone`) until nothing else runs, any other job
    /// until no suspect runs or waits.
    pub fn enter(&self, alone: bool) -> GatePass<'_> {
        let mut state = self.state.lock().unwrap_or_else(PoisonError::into_inner);
        if alone {
            state.suspects_waiting += 1;
            while state.running > 0 {
                state = self.wait(state);
            }
            state.suspects_waiting -= 1;
        } else {
            while state.alone || state.suspects_waiting > 0 {
                state = self.wait(state);
            }
        }
        state.running += 1;
        state.alone = alone;
        GatePass(self)
    }

    fn wait<'a>(&self, state: MutexGuard<'a, GateState>) -> MutexGuard<'a, GateState> {
        self.changed
            .wait(state)
            .unwrap_or_else(PoisonError::into_inner)
    }
}

impl Drop for GatePass<'_> {
    fn drop(&mut self) {
        let mut state = self.0.state.lock().unwrap_or_else(PoisonError::into_inner);
        state.running -= 1;
        state.alone = false;
        drop(state);
        self.0.changed.notify_all();
    }
}

fn now_utc() -> String {
    choreo_datasets::now_utc()
}

fn run_job(
    worker: usize,
    packages: &mut Packages,
    shared: &Shared,
    options: &WorkerOptions,
    job: Job,
) {
    let Job {
        mut record,
        suspect,
    } = job;
    let spool = &shared.spool;
    let span = tracing::info_span!("job", job = %record.id, kind = ?record.kind, file = %record.name, worker);
    let _enter = span.enter();
    let fail = |record: &mut JobRecord, stage: &str, reason: String| {
        let reason = spool.as_user_knows_it(record, &reason);
        tracing::warn!(stage, reason = %reason, attempts = record.attempts, "job failed");
        let failure = Failure {
            stage: stage.to_string(),
            reason,
            time: now_utc(),
        };
        match spool.fail(record, failure) {
            Ok(()) => shared.metrics.failed(stage),
            // The record stays in work/; the next start replays the failure path.
            Err(e) => tracing::error!(error = format!("{e:#}"), "cannot record the failure"),
        }
    };
    if record.failure.is_some() {
        let stage = record
            .failure
            .as_ref()
            .map(|f| f.stage.clone())
            .unwrap_or_default();
        fail(&mut record, &stage, String::new());
        return;
    }
    let input = spool.input_path(&record);
    let mut output = shared.sink.target(&record);
    if output.exists() {
        if made_from(&output, &input) {
            // Committed by an earlier run that died before moving the input: only the move is
            // left.
            tracing::info!(output = %output.display(), "output already complete; finishing");
            finish_ok(shared, &record, None);
            return;
        }
        // Another input's motion file (or not a motion file) took the name while this job was
        // down: another daemon given this output folder, or a user. Never finish with it.
        let taken = output;
        if let Err(e) = spool.move_output(&mut record) {
            tracing::error!(
                error = format!("{e:#}"),
                "cannot record a new output name; leaving the job for the next start"
            );
            return;
        }
        output = shared.sink.target(&record);
        tracing::warn!(
            taken = %taken.display(),
            output = %output.display(),
            "the output name was taken by another file while this job was down; using a new one"
        );
    }
    if record.crashes >= options.max_attempts {
        let reason = format!(
            "{}: the daemon crashed while this job ran alone ({} of serve.max_attempts = {}); not retrying",
            record.name, record.crashes, options.max_attempts
        );
        fail(&mut record, "crash", reason);
        return;
    }
    record.attempts += 1;
    record.running = true;
    record.progress = None;
    record.solo = suspect;
    if let Err(e) = spool.save(&record) {
        tracing::error!(
            error = format!("{e:#}"),
            "cannot record the attempt; leaving the job for the next start"
        );
        return;
    }
    // In flight from the moment its attempt is durable: a kill -9 now makes it a suspect.
    let _in_flight = InFlight::count(&shared.metrics.in_flight);
    tracing::info!(attempt = record.attempts, alone = suspect, output = %record.output, "job started");

    match std::fs::symlink_metadata(&input) {
        Ok(m) if m.len() > options.song.max_file_bytes => {
            let reason = format!(
                "{}: {} bytes, over limits.max_file_mb ({} bytes)",
                record.name,
                m.len(),
                options.song.max_file_bytes
            );
            return fail(&mut record, "intake", reason);
        }
        Ok(_) => {}
        Err(e) => return fail(&mut record, "intake", format!("{}: {e}", input.display())),
    }
    if let Err(reason) = check_free_disk(shared.sink.dir(), options.min_free_disk_bytes) {
        return fail(&mut record, "write", reason);
    }

    let t0 = Instant::now();
    let result = crate::exit::catch_panic(|| {
        if let Some(fault) = &options.fault
            && record.name.contains(fault.text.as_str())
        {
            if fault.abort {
                std::process::abort();
            }
            panic!("fault injected by CHOREOD_FAULT=panic-on:{}", fault.text);
        }
        let deadline = Some(crate::settings::deadline(options.time_limit_s));
        packages.dance.set_deadline(deadline);
        if let Some(style) = &mut packages.style {
            style.set_deadline(deadline);
        }
        match record.kind {
            JobKind::Dance => {
                let mut progress = ProgressReport::new(shared, &record);
                dance_file(
                    &mut packages.dance,
                    &input,
                    &output,
                    &options.song,
                    &DanceExtras::default(),
                    &mut |done, total| progress.step(done, total),
                )
                .map(Report::Dance)
                .map_err(|e| (e.stage.as_str(), e.error))
            }
            JobKind::Stylize => stylize(packages, options, &input, &output)
                .map(Report::Stylize)
                .map_err(|e| (failed_stage(&e), e)),
        }
    });
    if shared.abandoned.load(Ordering::SeqCst) {
        // The process is exiting under us: the job stays in work/ and resumes at the next start.
        return;
    }
    match result {
        Err(panic) => {
            let reason = format!(
                "{}: choreod hit a bug on this input (please report it): {panic}",
                record.name
            );
            fail(&mut record, "panic", reason);
        }
        Ok(Ok(Report::Dance(report))) => {
            if report.song.audio_truncated {
                tracing::warn!(
                    output = %output.display(),
                    audio_s = report.song.audio_s,
                    "job done with part of the song: {} ends mid-stream after {:.3} s of audio \
                     (recorded as source_damage in the provenance; limits.fail_truncated_audio = \
                     true fails such jobs)",
                    record.name,
                    report.song.audio_s
                );
            }
            tracing::info!(
                output = %output.display(),
                audio_s = report.song.audio_s,
                features_s = report.song.features_total_s,
                generate_s = report.song.generate_s,
                write_s = report.write_s,
                total_s = report.total_s,
                realtime_factor = report.realtime_factor,
                beat = report.song.beat,
                "job done"
            );
            finish_ok(shared, &record, Some(report));
        }
        Ok(Ok(Report::Stylize(report))) => {
            tracing::info!(
                output = %output.display(),
                frames = report.stylized.stats.frames,
                read_s = report.stylized.read_s,
                style_reused = report.style_reused,
                stylize_s = report.stylized.stylize_s,
                write_s = report.write_s,
                total_s = report.total_s,
                "job done"
            );
            finish_ok(shared, &record, None);
        }
        Ok(Err((stage, error))) => {
            tracing::debug!(seconds = t0.elapsed().as_secs_f64(), "failed job's time");
            let mut reason = format!("{error:#}").replace('\n', " ");
            if crate::exit::stopped_at_time_limit(&error) {
                reason.push_str(" (job.time_limit_s)");
            }
            fail(&mut record, stage, reason);
        }
    }
}

/// The stage a style job failed in: `crash` when the child process reading its motion died
/// (see `choreo_datasets::isolated`), else `stylize`.
fn failed_stage(error: &anyhow::Error) -> &'static str {
    let reader_died = error.chain().any(|cause| {
        matches!(
            cause.downcast_ref::<choreo_models::Error>(),
            Some(
                choreo_models::Error::Datasets(choreo_datasets::Error::ReaderDied { .. })
                    | choreo_models::Error::StyleFile(choreo_datasets::Error::ReaderDied { .. })
            )
        )
    });
    if reader_died { "crash" } else { "stylize" }
}

/// Stylize the claimed motion `input` with the configured style into `output`.
fn stylize(
    packages: &mut Packages,
    options: &WorkerOptions,
    input: &Path,
    output: &Path,
) -> anyhow::Result<StylizeReport> {
    let (Some(package), Some(style)) = (packages.style.as_mut(), options.style.as_ref()) else {
        // Claimed by an earlier run whose config had [style] enabled.
        anyhow::bail!(
            "{}: a style job, but [style] is not enabled in the config",
            input.display()
        );
    };
    let job = StylizeJob {
        export: choreo_datasets::ExportOptions::default(),
        content: choreo_models::MotionSource::new(input),
        style: choreo_models::StyleSource::Motion(choreo_models::MotionSource::new(
            &style.reference,
        )),
        output: output.to_path_buf(),
        init_noise_sha256: String::new(),
    };
    stylize_file(package, &job, &style.styles, &style.options, &mut |_, _| {})
}

/// One job counted in `choreod_jobs_in_flight` while this lives.
struct InFlight<'a>(&'a AtomicUsize);

impl<'a> InFlight<'a> {
    fn count(gauge: &'a AtomicUsize) -> Self {
        gauge.fetch_add(1, Ordering::Relaxed);
        Self(gauge)
    }
}

impl Drop for InFlight<'_> {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::Relaxed);
    }
}

/// Whether the motion file `output` was made from `input`: its provenance names the input's
/// content (SHA-256). Another song's dance or a file that is not a motion file is not this
/// job's. A dance of identical bytes uploaded twice cannot be told apart and is accepted.
fn made_from(output: &Path, input: &Path) -> bool {
    let Ok(Some(provenance)) = choreo_datasets::read_motion_file(output).map(|m| m.provenance)
    else {
        return false;
    };
    choreo_datasets::sha256_file(input).is_ok_and(|sha| sha == provenance.source_sha256)
}

fn finish_ok(shared: &Shared, record: &JobRecord, report: Option<DanceReport>) {
    match shared.spool.succeed(record) {
        Ok(()) => match report {
            Some(r) => shared.metrics.succeeded(
                [
                    r.song.features_total_s,
                    r.song.generate_s,
                    r.write_s,
                    r.total_s,
                ],
                r.song.audio_s,
            ),
            None => {
                shared.metrics.done.fetch_add(1, Ordering::Relaxed);
            }
        },
        Err(e) => tracing::error!(
            error = format!("{e:#}"),
            "cannot move the input to done/; the next start finishes it"
        ),
    }
}

/// Refuse to start writing when the output folder's filesystem has less than `min` bytes free
/// for unprivileged users (`f_bavail`).
fn check_free_disk(dir: &Path, min: u64) -> Result<(), String> {
    if min == 0 {
        return Ok(());
    }
    let st = rustix::fs::statvfs(dir)
        .map_err(|e| format!("{}: cannot read free space: {e}", dir.display()))?;
    let free = st.f_bavail.saturating_mul(st.f_frsize);
    if free < min {
        return Err(format!(
            "{}: disk full: {:.1} MiB free, below limits.min_free_disk_mb ({:.1} MiB)",
            dir.display(),
            free as f64 / 1048576.0,
            min as f64 / 1048576.0
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_waiting_suspect_goes_before_later_jobs_and_then_two_run_together() {
        let gate = Gate::default();
        let order = Mutex::new(Vec::new());
        let running = gate.enter(false);
        std::thread::scope(|s| {
            s.spawn(|| {
                let _pass = gate.enter(true);
                order.lock().unwrap().push("suspect");
                // Long enough for a job that got in beside it to be recorded first.
                std::thread::sleep(Duration::from_millis(50));
            });
            while gate.state.lock().unwrap().suspects_waiting == 0 {
                std::thread::yield_now();
            }
            // The other worker's next job: with std's RwLock it went in beside the running
            // job while the suspect waited, and so on for every job after it.
            s.spawn(|| {
                let _pass = gate.enter(false);
                order.lock().unwrap().push("job");
            });
            std::thread::sleep(Duration::from_millis(50));
            drop(running);
        });
        assert_eq!(*order.lock().unwrap(), ["suspect", "job"]);
        let (_a, _b) = (gate.enter(false), gate.enter(false));
        let state = gate.state.lock().unwrap();
        assert_eq!((state.running, state.alone), (2, false), "two side by side");
    }

    #[test]
    fn free_disk_check_names_the_folder_and_limit() {
        let dir = tempfile::tempdir().unwrap();
        check_free_disk(dir.path(), 1).unwrap();
        let e = check_free_disk(dir.path(), u64::MAX).unwrap_err();
        assert!(
            e.contains("disk full") && e.contains(&dir.path().display().to_string()),
            "{e}"
        );
        assert!(check_free_disk(&dir.path().join("missing"), 1).is_err());
    }
}
