//! A worker thread: owns one model package (ORT sessions are used with `&mut`), takes jobs
//! from the shared queue and turns each into exactly one outcome.

use std::path::Path;
use std::sync::PoisonError;
use std::sync::atomic::Ordering;
use std::sync::mpsc::RecvTimeoutError;
use std::time::{Duration, Instant};

use choreo_models::{DanceOptions, ModelPackage};

use super::spool::{Failure, JobRecord};
use super::{Job, Shared};
use crate::dance::{InputLimits, Stage, dance_file};

/// How often an idle worker looks at the shutdown flag.
const POLL: Duration = Duration::from_millis(100);

/// Per-worker settings.
#[derive(Debug, Clone)]
pub struct WorkerOptions {
    pub dance: DanceOptions,
    pub limits: InputLimits,
    pub min_free_disk_bytes: u64,
    pub max_attempts: u32,
}

/// Take jobs until shutdown. Never starts a job after shutdown was asked for; the job being
/// worked on is finished.
pub fn run(index: usize, mut package: ModelPackage, shared: &Shared, options: &WorkerOptions) {
    loop {
        if shared.shutdown.load(Ordering::Relaxed) {
            break;
        }
        let job = {
            let rx = shared
                .queue
                .lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner);
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
        // A suspect runs alone (the write side of the gate); other jobs share the read side.
        // Taken before counting the job in flight: a job waiting here is not running.
        let _alone = job
            .suspect
            .then(|| shared.gate.write().unwrap_or_else(PoisonError::into_inner));
        let _beside_others =
            (!job.suspect).then(|| shared.gate.read().unwrap_or_else(PoisonError::into_inner));
        shared.metrics.in_flight.fetch_add(1, Ordering::Relaxed);
        run_job(index, &mut package, shared, options, job);
        shared.metrics.in_flight.fetch_sub(1, Ordering::Relaxed);
    }
    tracing::debug!(worker = index, "worker stopped");
}

fn now_utc() -> String {
    choreo_datasets::now_utc()
}

fn run_job(
    worker: usize,
    package: &mut ModelPackage,
    shared: &Shared,
    options: &WorkerOptions,
    job: Job,
) {
    let Job {
        mut record,
        suspect,
    } = job;
    let spool = &shared.spool;
    let span = tracing::info_span!("job", job = %record.id, file = %record.name, worker);
    let _enter = span.enter();
    let fail = |record: &mut JobRecord, stage: &str, reason: String| {
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
    let output = shared.sink.target(&record);
    if output.exists() {
        // Committed by an earlier run that died before moving the input: only the move is left.
        tracing::info!(output = %output.display(), "output already complete; finishing");
        finish_ok(shared, &record, None);
        return;
    }
    if record.crashes >= options.max_attempts {
        let reason = format!(
            "{}: the daemon died {} times while this job ran alone (serve.max_attempts = {}); not retrying",
            record.name, record.crashes, options.max_attempts
        );
        fail(&mut record, "crash", reason);
        return;
    }
    record.attempts += 1;
    record.running = true;
    record.solo = suspect;
    if let Err(e) = spool.save(&record) {
        tracing::error!(
            error = format!("{e:#}"),
            "cannot record the attempt; leaving the job for the next start"
        );
        return;
    }
    tracing::info!(attempt = record.attempts, alone = suspect, output = %record.output, "job started");

    match std::fs::symlink_metadata(&input) {
        Ok(m) if m.len() > options.limits.max_file_bytes => {
            let reason = format!(
                "{}: {} bytes, over limits.max_file_mb ({} bytes)",
                record.name,
                m.len(),
                options.limits.max_file_bytes
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
        dance_file(
            package,
            &input,
            &output,
            &options.dance,
            options.limits,
            &mut |_, _| {},
        )
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
        Ok(Ok(report)) => {
            tracing::info!(
                output = %output.display(),
                audio_s = report.audio_s,
                features_s = report.features_total_s,
                generate_s = report.generate_s,
                write_s = report.write_s,
                total_s = report.total_s,
                realtime_factor = report.realtime_factor,
                "job done"
            );
            finish_ok(shared, &record, Some(report));
        }
        Ok(Err(e)) => {
            let stage = match e.stage {
                Stage::Decode => "decode",
                Stage::Generate => "generate",
                Stage::Write => "write",
            };
            tracing::debug!(seconds = t0.elapsed().as_secs_f64(), "failed job's time");
            let reason = format!("{:#}", e.error).replace('\n', " ");
            fail(&mut record, stage, reason);
        }
    }
}

fn finish_ok(shared: &Shared, record: &JobRecord, report: Option<crate::dance::DanceReport>) {
    match shared.spool.succeed(record) {
        Ok(()) => match report {
            Some(r) => shared.metrics.succeeded(
                [r.features_total_s, r.generate_s, r.write_s, r.total_s],
                r.audio_s,
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
