//! A running dance job's progress, for jobs that take minutes (a LODGE song): the steps done
//! in `/metrics` (`choreod_job_progress_ratio{job="<id>"}`, at every step) and in the job
//! record (`progress`, saved at most once a second and only when it moved by 5 % or more:
//! a short job writes no extra record).

use std::time::{Duration, Instant};

use super::Shared;
use super::spool::{JobProgress, JobRecord};

/// Least time between two saves of the record.
const SAVE_EVERY: Duration = Duration::from_secs(1);
/// Least change, in percent of the steps, between two saves of the record.
const SAVE_STEP_PERCENT: usize = 5;

/// Reports one job's steps while it lives; dropped, the job leaves `/metrics`.
pub struct ProgressReport<'a> {
    shared: &'a Shared,
    /// A copy of the job's record, saved with its progress (the worker's own copy records the
    /// outcome later, which drops the progress).
    record: JobRecord,
    last_save: Instant,
    saved_percent: usize,
    save_failed: bool,
}

impl<'a> ProgressReport<'a> {
    /// Start reporting `record`'s job (its attempt already saved).
    pub fn new(shared: &'a Shared, record: &JobRecord) -> Self {
        shared.metrics.set_progress(&record.id, 0.0);
        Self {
            shared,
            record: record.clone(),
            last_save: Instant::now(),
            saved_percent: 0,
            save_failed: false,
        }
    }

    /// `done` of `total` steps are done.
    pub fn step(&mut self, done: usize, total: usize) {
        let total = total.max(1);
        let done = done.min(total);
        self.shared
            .metrics
            .set_progress(&self.record.id, done as f64 / total as f64);
        let percent = done * 100 / total;
        if self.last_save.elapsed() < SAVE_EVERY || percent < self.saved_percent + SAVE_STEP_PERCENT
        {
            return;
        }
        self.record.progress = Some(JobProgress {
            steps_done: done,
            steps_total: total,
            updated_utc: choreo_datasets::now_utc(),
        });
        // A failed save waits its second too: a full disk is not retried at every step.
        self.last_save = Instant::now();
        match self.shared.spool.save(&self.record) {
            Ok(()) => self.saved_percent = percent,
            // Progress is a courtesy: the job goes on; one warning per job.
            Err(e) if !self.save_failed => {
                self.save_failed = true;
                tracing::warn!(error = format!("{e:#}"), "cannot record the job's progress");
            }
            Err(_) => {}
        }
    }
}

impl Drop for ProgressReport<'_> {
    fn drop(&mut self) {
        self.shared.metrics.clear_progress(&self.record.id);
    }
}
