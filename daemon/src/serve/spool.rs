//! The job spool on disk: how an inbox file becomes exactly one visible outcome, crash-safely.
//!
//! ```text
//! <state>/work/<id>/<name>             claimed input (the rename out of the inbox is the claim)
//! <state>/work/<id>/job.json           job record: name, output name, attempts, failure
//! <state>/done/<id>__<name>            input of a job whose motion file is durable
//! <state>/failed/<id>__<name>          input of a failed job ...
//! <state>/failed/<id>__<name>.error.json   ... and its report {stage, reason, time, attempts}
//! <state>/.choreod.running             present while a daemon runs; found at start = unclean exit;
//!                                      holds the fatal signal's name when the daemon crashed
//! ```
//!
//! A daemon holds an exclusive `flock` on the state folder and on the output folder themselves
//! (no lock file): one daemon per state folder and per output folder.
//!
//! Names: `done/`, `failed/` and output names are derived from the input's name and shortened
//! ([`fit_name`]) to at most [`MAX_DERIVED_NAME`] bytes so that they, their `.error.json` and
//! every temporary name fit NAME_MAX (255 bytes); the full name stays in the record and report.
//! An inbox name that is not UTF-8 is claimed under its lossy UTF-8 form, the original bytes
//! kept (escaped as `\xNN`) in the record's and report's `original_file`.
//!
//! Crash evidence: a record is marked `running` (durably) when its attempt starts. After an
//! unclean exit the records still marked `running` are *suspects*: they run again one at a
//! time, marked `solo`, before anything else. Only a crash of the daemon (a fatal signal, whose
//! name the handler of [`super::fatal`] writes into the running marker) while a job ran solo
//! counts against that job (`crashes`): a `kill -9` from outside costs no job an attempt.
//!
//! Every step is a rename or an atomic write (temporary `.choreod-tmp-*` name, fsync, rename,
//! fsync of the directory), ordered so that a `kill -9` between any two steps leaves a state that
//! [`Spool::recover`] finishes or resumes: the motion file is committed before the input moves to
//! `done/`; a failure is written into the record before the report and the move to `failed/`.

use std::collections::HashSet;
use std::fs::{self, File};
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::sync::atomic::{AtomicU32, Ordering};

use anyhow::{Context, bail};

use crate::exit::NotReady;
use serde::{Deserialize, Serialize};

/// Extensions (lower case) the inbox accepts; everything else is left alone. Opus is accepted
/// on purpose so that it fails with the decoder's message instead of sitting in the inbox.
pub const SUPPORTED_EXTENSIONS: &[&str] = &[
    "wav", "flac", "mp3", "ogg", "oga", "m4a", "mp4", "aac", "aif", "aiff", "opus",
];

/// Prefix of every temporary file the spool writes; cleaned at start-up.
const TMP_PREFIX: &str = ".choreod-tmp-";
const RECORD: &str = "job.json";
const RUNNING_MARKER: &str = ".choreod.running";
/// Longest name derived from an input's name (output, `done/` and `failed/` entries): with
/// `.error.json` (11 bytes) and the longest temporary prefix (`.choreod-tmp-<pid>-`, 24 bytes;
/// the motion writer's `.<name>.tmp-<pid>-<n>` adds about as much) it stays under NAME_MAX.
pub const MAX_DERIVED_NAME: usize = 200;
/// Linux NAME_MAX: the longest file name, in bytes.
const NAME_MAX: usize = 255;
const ERROR_SUFFIX: &str = ".error.json";
/// Separates the job id from the original name in `done/` and `failed/`; ids never contain it.
const SEP: &str = "__";

/// Extensions (lower case) the style inbox accepts: every motion format `choreod stylize` reads.
pub const MOTION_EXTENSIONS: &[&str] = &choreo_datasets::MOTION_EXTENSIONS;

/// What a job makes of its input.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum JobKind {
    /// A song from `paths.inbox`, danced (records written before kinds existed have none).
    #[default]
    Dance,
    /// A motion from `style.inbox`, stylized with `style.style`.
    Stylize,
}

impl JobKind {
    /// The extensions (lower case) of the inputs of this kind; the two lists share none.
    fn extensions(self) -> &'static [&'static str] {
        match self {
            Self::Dance => SUPPORTED_EXTENSIONS,
            Self::Stylize => MOTION_EXTENSIONS,
        }
    }

    /// The kind of a claimed input found without its record (by its extension).
    fn of_name(name: &str) -> Self {
        if is_candidate_name(name, Self::Stylize) {
            Self::Stylize
        } else {
            Self::Dance
        }
    }
}

/// Whether an inbox file name is an input of `kind` to take: not hidden, not a temporary name,
/// and with one of the kind's extensions.
pub fn is_candidate_name(name: &str, kind: JobKind) -> bool {
    if name.starts_with('.') || name.ends_with('~') {
        return false;
    }
    let lower = name.to_ascii_lowercase();
    if lower.ends_with(".tmp") || lower.ends_with(".part") {
        return false;
    }
    match Path::new(&lower).extension().and_then(|e| e.to_str()) {
        Some(ext) => kind.extensions().contains(&ext),
        None => false,
    }
}

/// Why a job failed, as written to `<name>.error.json`.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct Failure {
    /// `intake`, `decode`, `generate`, `write` or `crash`.
    pub stage: String,
    /// One line, naming the file.
    pub reason: String,
    /// UTC, RFC 3339.
    pub time: String,
}

/// The durable record of one job (`work/<id>.job.json`).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct JobRecord {
    pub id: String,
    /// Dance or stylize; absent (dance) in records written before style jobs existed.
    #[serde(default)]
    pub kind: JobKind,
    /// The input's original file name.
    pub name: String,
    /// The motion file's name in the output folder, decided at claim time so that a resumed
    /// job keeps it and two inputs with the same stem never share one.
    pub output: String,
    /// The inbox name, with bytes that are not UTF-8 escaped as `\xNN`, when `name` had to
    /// differ from it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub original: Option<String>,
    /// Attempts started; written and fsynced before each attempt runs.
    pub attempts: u32,
    /// An attempt started and has no outcome yet (written with `attempts`).
    #[serde(default)]
    pub running: bool,
    /// The running attempt runs alone: if the daemon dies now, this job is the cause.
    #[serde(default)]
    pub solo: bool,
    /// Times the daemon died while this job ran alone.
    #[serde(default)]
    pub crashes: u32,
    /// Set once the job has failed; the rest of the failure path is replayed on recovery.
    #[serde(default)]
    pub failure: Option<Failure>,
    /// How far the running attempt has got (dance jobs that run a second or more).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub progress: Option<JobProgress>,
}

/// A running dance job's denoising steps (a LODGE song's: both stages together).
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct JobProgress {
    pub steps_done: usize,
    pub steps_total: usize,
    /// When this was recorded (ISO-8601 UTC).
    pub updated_utc: String,
}

/// The spool directories and the output names reserved by jobs in flight.
#[derive(Debug)]
pub struct Spool {
    output: PathBuf,
    work: PathBuf,
    done: PathBuf,
    failed: PathBuf,
    reserved: Mutex<HashSet<String>>,
    seq: AtomicU32,
    running_marker: PathBuf,
    /// The last daemon on this spool did not exit cleanly (its running marker was still there).
    unclean_start: bool,
    /// ... and it crashed: the fatal signal its handler wrote into the marker.
    died_of: Option<String>,
    // Held for the life of the spool: one daemon per state folder and per output folder.
    _locks: [File; 2],
}

/// Lock the folder `dir` itself (flock on its descriptor, released when the process dies);
/// refused with [`NotReady`] (exit code 4) while another daemon holds it.
fn lock_folder(dir: &Path, what: &str) -> anyhow::Result<File> {
    let lock = File::open(dir).with_context(|| format!("opening {}", dir.display()))?;
    if rustix::fs::flock(&lock, rustix::fs::FlockOperation::NonBlockingLockExclusive).is_err() {
        return Err(NotReady(format!(
            "{} is locked: another choreod serve uses this {what} folder (each daemon needs its own)",
            dir.display()
        ))
        .into());
    }
    Ok(lock)
}

/// A job found in `work/` at start-up.
#[derive(Debug)]
pub struct Recovered {
    pub record: JobRecord,
    /// It was running when the last daemon died: run it alone.
    pub suspect: bool,
}

impl Spool {
    /// Create the spool folders under `state`, take the lock and remove stale temporary files.
    pub fn open(state: &Path, output: &Path) -> anyhow::Result<Self> {
        let work = state.join("work");
        let done = state.join("done");
        let failed = state.join("failed");
        for dir in [&work, &done, &failed] {
            fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        }
        let locks = [lock_folder(state, "state")?, lock_folder(output, "output")?];
        let running_marker = state.join(RUNNING_MARKER);
        let unclean_start = running_marker.exists();
        let died_of = fs::read_to_string(&running_marker)
            .ok()
            .and_then(|text| text.lines().next().map(str::to_string))
            .filter(|signal| !signal.is_empty());
        let spool = Self {
            output: output.to_path_buf(),
            work,
            done,
            failed,
            reserved: Mutex::new(HashSet::new()),
            seq: AtomicU32::new(0),
            running_marker,
            unclean_start,
            died_of,
            _locks: locks,
        };
        spool.clean_temporaries()?;
        if !unclean_start {
            write_atomic(&spool.running_marker, b"")?;
        }
        Ok(spool)
    }

    /// Empty the running marker (what it said about the last run is used by [`Self::recover`])
    /// and open it for [`super::fatal::record_fatal_signals`].
    pub fn arm_running_marker(&self) -> anyhow::Result<File> {
        write_atomic(&self.running_marker, b"")?;
        fs::OpenOptions::new()
            .append(true)
            .open(&self.running_marker)
            .with_context(|| format!("opening {}", self.running_marker.display()))
    }

    /// The daemon stops cleanly: jobs left in `work/` were not running when it died.
    pub fn mark_clean_exit(&self) -> anyhow::Result<()> {
        fs::remove_file(&self.running_marker)
            .with_context(|| format!("removing {}", self.running_marker.display()))?;
        sync_dir(self.running_marker.parent().unwrap_or(Path::new(".")))
    }

    /// Remove temporary files a crash left behind: ours in the spool folders, and the motion
    /// writer's (`.<name>.h5.tmp-<pid>-<n>`, see datasets motion_file.rs) in the output folder.
    fn clean_temporaries(&self) -> anyhow::Result<()> {
        let mut dirs = vec![
            self.work.clone(),
            self.done.clone(),
            self.failed.clone(),
            self.output.clone(),
        ];
        for name in list(&self.work)? {
            let job_dir = self.work.join(name);
            if job_dir.is_dir() {
                dirs.push(job_dir);
            }
        }
        for dir in &dirs {
            for name in list(dir)? {
                let ours = name.starts_with(TMP_PREFIX);
                let writer =
                    *dir == self.output && name.starts_with('.') && name.contains(".h5.tmp-");
                if ours || writer {
                    let path = dir.join(&name);
                    tracing::info!(file = %path.display(), "removing a temporary file left by a crash");
                    fs::remove_file(&path)
                        .with_context(|| format!("removing {}", path.display()))?;
                }
            }
        }
        Ok(())
    }

    /// Find the jobs left in `work/` by an earlier run and make each whole again: an input
    /// without a record gets one, a record without an input is dropped (its outcome is already
    /// visible, or the input vanished), an empty job folder is removed. After an unclean exit a
    /// job that ran alone is charged a crash, and the jobs that were running become suspects.
    /// Returns the jobs to run, oldest first.
    pub fn recover(&self) -> anyhow::Result<Vec<Recovered>> {
        let mut records = Vec::new();
        let mut orphans = Vec::new();
        for id in list(&self.work)? {
            let dir = self.work.join(&id);
            if !dir.is_dir() || id.contains(SEP) {
                tracing::warn!(file = %dir.display(), "unexpected file in the spool; leaving it");
                continue;
            }
            let files = list(&dir)?;
            let inputs: Vec<&String> = files.iter().filter(|n| n.as_str() != RECORD).collect();
            let record_path = dir.join(RECORD);
            let record = if files.iter().any(|n| n == RECORD) {
                let text = fs::read_to_string(&record_path)
                    .with_context(|| format!("reading {}", record_path.display()))?;
                // Records are written atomically, so a bad one is not a torn write: someone edited it.
                let r: JobRecord = serde_json::from_str(&text).with_context(|| {
                    format!(
                        "{}: not a job record; move the folder away to start",
                        record_path.display()
                    )
                })?;
                Some(r)
            } else {
                None
            };
            match (record, inputs.as_slice()) {
                (Some(r), _) if self.input_path(&r).exists() => records.push(r),
                (Some(r), _) => {
                    tracing::info!(job = %r.id, file = %r.name, "outcome already visible; dropping the record");
                    self.remove_job_dir(&r.id)?;
                }
                // The daemon died between the claim (rename) and writing the record.
                (None, [input]) => orphans.push((id.clone(), (*input).clone())),
                (None, []) => self.remove_job_dir(&id)?,
                (None, _) => {
                    tracing::warn!(dir = %dir.display(), "job folder with several files and no record; leaving it")
                }
            }
        }
        self.lock_reserved()
            .extend(records.iter().map(|r| r.output.clone()));
        for (id, name) in orphans {
            let kind = JobKind::of_name(&name);
            let record = JobRecord::new(id, kind, self.reserve_output(&name), name, None);
            self.save(&record)?;
            records.push(record);
        }
        records.sort_by(|a, b| a.id.cmp(&b.id));
        if self.unclean_start {
            match &self.died_of {
                Some(signal) => {
                    tracing::warn!(
                        signal,
                        "the last daemon crashed; a job running alone is charged"
                    )
                }
                None => tracing::info!(
                    "the last daemon was killed from outside (no crash recorded); no job is charged"
                ),
            }
        }
        let mut jobs = Vec::with_capacity(records.len());
        for mut record in records {
            let before = (record.running, record.solo, record.crashes);
            let suspect = self.unclean_start && record.running;
            if let Some(signal) = self.died_of.as_deref().filter(|_| record.solo) {
                record.crashes += 1;
                tracing::warn!(job = %record.id, file = %record.name, crashes = record.crashes, signal, "the daemon crashed while this job ran alone");
            }
            // A suspect stays marked running until it runs again, so that another crash before
            // then keeps it a suspect.
            record.running = suspect;
            record.solo = false;
            if (record.running, record.solo, record.crashes) != before {
                self.save(&record)?;
            }
            jobs.push(Recovered { record, suspect });
        }
        Ok(jobs)
    }

    /// Claim an inbox file: rename it into `work/<id>/` (the claim), then write its record.
    /// `Ok(None)` when the file vanished before it could be claimed (another daemon took it).
    /// When the record cannot be written (disk full, …) the claim is rolled back: the file goes
    /// back into the inbox under its name and the error is returned, so the intake retries.
    pub fn claim(&self, inbox_file: &Path, kind: JobKind) -> anyhow::Result<Option<JobRecord>> {
        let raw = inbox_file
            .file_name()
            .with_context(|| format!("{}: no file name", inbox_file.display()))?;
        let (name, original) = match raw.to_str() {
            Some(n) => (n.to_string(), None),
            None => (
                fit_name(&raw.to_string_lossy(), NAME_MAX),
                Some(escape_bytes(raw.as_encoded_bytes())),
            ),
        };
        let id = self.next_id();
        let dir = self.work.join(&id);
        fs::create_dir(&dir).with_context(|| format!("creating {}", dir.display()))?;
        let claimed = dir.join(&name);
        match fs::rename(inbox_file, &claimed) {
            Ok(()) => {}
            Err(e) => {
                let _ = fs::remove_dir(&dir);
                if e.kind() == std::io::ErrorKind::NotFound {
                    return Ok(None);
                }
                return Err(e).with_context(|| format!("claiming {}", inbox_file.display()));
            }
        }
        let record = JobRecord::new(id, kind, self.reserve_output(&name), name, original);
        let saved = self.save(&record).and_then(|()| sync_dir(&self.work));
        if let Err(e) = saved {
            self.lock_reserved().remove(&record.output);
            // No-replace: a new file under the same name may have arrived meanwhile.
            let back = rustix::fs::renameat_with(
                rustix::fs::CWD,
                &claimed,
                rustix::fs::CWD,
                inbox_file,
                rustix::fs::RenameFlags::NOREPLACE,
            );
            match back {
                Ok(()) => {
                    let _ = fs::remove_dir(&dir);
                }
                // Left claimed without a record: the next start adopts it (see `recover`).
                Err(back) => tracing::error!(
                    file = %inbox_file.display(),
                    error = %back,
                    "cannot put the file back into the inbox; the next start resumes it"
                ),
            }
            return Err(e.context(format!(
                "claiming {}: cannot write the job record; the file stays in the inbox",
                inbox_file.display()
            )));
        }
        if let Some(inbox) = inbox_file.parent() {
            sync_dir(inbox)?;
        }
        Ok(Some(record))
    }

    /// A job id: milliseconds since the epoch and a per-process counter, sortable by arrival.
    fn next_id(&self) -> String {
        let ms = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_millis());
        let n = self.seq.fetch_add(1, Ordering::Relaxed) % 10_000;
        format!("{ms}-{n:04}")
    }

    /// `<stem>.h5`, else `<stem>-2.h5`, `<stem>-3.h5`, …: the first name neither in the output
    /// folder nor reserved by a job in flight.
    fn reserve_output(&self, input_name: &str) -> String {
        let stem = Path::new(input_name).file_stem().map_or_else(
            || input_name.to_string(),
            |s| s.to_string_lossy().into_owned(),
        );
        let mut reserved = self.lock_reserved();
        let mut n = 1u32;
        loop {
            let candidate = fit_name(
                &if n == 1 {
                    format!("{stem}.h5")
                } else {
                    format!("{stem}-{n}.h5")
                },
                MAX_DERIVED_NAME,
            );
            if !reserved.contains(&candidate) && !self.output.join(&candidate).exists() {
                reserved.insert(candidate.clone());
                return candidate;
            }
            n += 1;
        }
    }

    /// Give `record` a new output name (its own was taken by a file this job did not write)
    /// and save it.
    pub fn move_output(&self, record: &mut JobRecord) -> anyhow::Result<()> {
        record.output = self.reserve_output(&record.name);
        self.save(record)
    }

    fn lock_reserved(&self) -> std::sync::MutexGuard<'_, HashSet<String>> {
        // A poisoned lock only means a thread panicked while holding it; the set is still valid.
        self.reserved
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// The claimed input of `record`.
    pub fn input_path(&self, record: &JobRecord) -> PathBuf {
        self.work.join(&record.id).join(&record.name)
    }

    /// `reason` with the job's private folder (`work/<id>/`) taken out of the paths in it, so
    /// that they name files as the user dropped them (`x.opus`, not `<state>/work/<id>/x.opus`,
    /// a folder that is gone once the job has failed).
    pub fn as_user_knows_it(&self, record: &JobRecord, reason: &str) -> String {
        let job_dir = format!("{}/", self.work.join(&record.id).display());
        reason.replace(&job_dir, "")
    }

    fn record_path(&self, record: &JobRecord) -> PathBuf {
        self.work.join(&record.id).join(RECORD)
    }

    /// Remove a finished job's folder (its record, and nothing else is left in it).
    fn remove_job_dir(&self, id: &str) -> anyhow::Result<()> {
        let dir = self.work.join(id);
        match fs::remove_file(dir.join(RECORD)) {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => {
                return Err(e).with_context(|| format!("removing {}", dir.join(RECORD).display()));
            }
        }
        fs::remove_dir(&dir).with_context(|| format!("removing {}", dir.display()))?;
        sync_dir(&self.work)
    }

    /// Write the record atomically and durably.
    pub fn save(&self, record: &JobRecord) -> anyhow::Result<()> {
        #[cfg(test)]
        if tests::RECORD_WRITES_FAIL.get() {
            return Err(std::io::Error::from(std::io::ErrorKind::StorageFull))
                .with_context(|| format!("writing {}", self.record_path(record).display()));
        }
        let text = serde_json::to_vec_pretty(record).context("serialising a job record")?;
        write_atomic(&self.record_path(record), &text)
    }

    /// The motion file is durable: move the input to `done/` and drop the record.
    pub fn succeed(&self, record: &JobRecord) -> anyhow::Result<()> {
        let target = self.done.join(record.outcome_name());
        rename_durably(&self.input_path(record), &target)?;
        self.remove_job_dir(&record.id)?;
        self.lock_reserved().remove(&record.output);
        Ok(())
    }

    /// Fail the job: record the failure, write the report, move the input to `failed/`, drop
    /// the record. Safe to call again for a record that already carries its failure.
    pub fn fail(&self, record: &mut JobRecord, failure: Failure) -> anyhow::Result<()> {
        if record.failure.is_none() {
            record.failure = Some(failure);
            self.save(record)?;
        }
        let Some(failure) = record.failure.as_ref() else {
            bail!("job {} lost its failure", record.id)
        };
        let base = record.outcome_name();
        let mut report = serde_json::json!({
            "id": record.id,
            "file": record.name,
            "stage": failure.stage,
            "reason": failure.reason,
            "time": failure.time,
            "attempts": record.attempts,
        });
        if let Some(original) = &record.original {
            report["original_file"] = original.as_str().into();
        }
        let text = serde_json::to_vec_pretty(&report).context("serialising an error report")?;
        write_atomic(&self.failed.join(format!("{base}{ERROR_SUFFIX}")), &text)?;
        rename_durably(&self.input_path(record), &self.failed.join(&base))?;
        self.remove_job_dir(&record.id)?;
        self.lock_reserved().remove(&record.output);
        Ok(())
    }
}

impl JobRecord {
    fn new(
        id: String,
        kind: JobKind,
        output: String,
        name: String,
        original: Option<String>,
    ) -> Self {
        Self {
            id,
            kind,
            name,
            output,
            original,
            attempts: 0,
            running: false,
            solo: false,
            crashes: 0,
            failure: None,
            progress: None,
        }
    }

    /// The input's name in `done/` or `failed/`: `<id>__<name>`, shortened to fit.
    fn outcome_name(&self) -> String {
        fit_name(&format!("{}{SEP}{}", self.id, self.name), MAX_DERIVED_NAME)
    }
}

/// `name` when it has at most `max` bytes, else a deterministic shorter name: the stem cut on a
/// character boundary, `~`, 16 hex digits of a hash of the whole name (so two long names that
/// share a prefix stay apart), and the extension.
pub fn fit_name(name: &str, max: usize) -> String {
    if name.len() <= max {
        return name.to_string();
    }
    let ext = Path::new(name)
        .extension()
        .and_then(|e| e.to_str())
        .filter(|e| e.len() <= 16)
        .map_or(String::new(), |e| format!(".{e}"));
    let hash = format!("~{:016x}", fnv1a(name.as_bytes()));
    let mut cut = max.saturating_sub(hash.len() + ext.len()).min(name.len());
    while !name.is_char_boundary(cut) {
        cut -= 1;
    }
    format!("{}{hash}{ext}", &name[..cut])
}

/// 64-bit FNV-1a (a stable, documented hash: names must not change between Rust versions).
/// Constants from the FNV specification (draft-eastlake-fnv, section 2.1).
fn fnv1a(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325, |h, b| {
        (h ^ u64::from(*b)).wrapping_mul(0x0000_0100_0000_01b3)
    })
}

/// Bytes as text: valid UTF-8 as is, every other byte as `\xNN`.
fn escape_bytes(bytes: &[u8]) -> String {
    let mut out = String::new();
    for chunk in bytes.utf8_chunks() {
        out.push_str(chunk.valid());
        for b in chunk.invalid() {
            out.push_str(&format!("\\x{b:02x}"));
        }
    }
    out
}

/// Names in `dir` (not following symlinks; names that are not UTF-8 skipped: the spool makes
/// none).
fn list(dir: &Path) -> anyhow::Result<Vec<String>> {
    let mut names = Vec::new();
    for entry in fs::read_dir(dir).with_context(|| format!("listing {}", dir.display()))? {
        let entry = entry.with_context(|| format!("listing {}", dir.display()))?;
        match entry.file_name().into_string() {
            Ok(n) => names.push(n),
            Err(n) => {
                tracing::debug!(dir = %dir.display(), name = ?n, "skipping a file name that is not UTF-8")
            }
        }
    }
    names.sort();
    Ok(names)
}

fn file_name(path: &Path) -> anyhow::Result<String> {
    path.file_name()
        .and_then(|n| n.to_str())
        .map(str::to_string)
        .with_context(|| format!("{}: no UTF-8 file name", path.display()))
}

/// fsync a directory so that renames and creations in it survive a power cut.
pub fn sync_dir(dir: &Path) -> anyhow::Result<()> {
    File::open(dir)
        .and_then(|d| d.sync_all())
        .with_context(|| format!("syncing {}", dir.display()))
}

/// Write under a temporary name in the same folder, fsync, rename into place, fsync the folder.
fn write_atomic(path: &Path, bytes: &[u8]) -> anyhow::Result<()> {
    let dir = path.parent().context("a spool file has a parent folder")?;
    let tmp = dir.join(format!(
        "{TMP_PREFIX}{}-{}",
        std::process::id(),
        file_name(path)?
    ));
    choreo_dsp::atomic::write_atomic_with(&tmp, path, |w| w.write_all(bytes))
        .with_context(|| format!("writing {}", path.display()))
}

fn rename_durably(from: &Path, to: &Path) -> anyhow::Result<()> {
    fs::rename(from, to)
        .with_context(|| format!("moving {} to {}", from.display(), to.display()))?;
    if let Some(dir) = to.parent() {
        sync_dir(dir)?;
    }
    if let Some(dir) = from.parent() {
        sync_dir(dir)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spool() -> (tempfile::TempDir, Spool) {
        let dir = tempfile::tempdir().unwrap();
        for d in ["inbox", "out", "state"] {
            fs::create_dir(dir.path().join(d)).unwrap();
        }
        let s = Spool::open(&dir.path().join("state"), &dir.path().join("out")).unwrap();
        (dir, s)
    }

    fn failure() -> Failure {
        Failure {
            stage: "decode".into(),
            reason: "bad".into(),
            time: "t".into(),
        }
    }

    #[test]
    fn candidate_names() {
        for ok in ["a.wav", "B.FLAC", "x.y.mp3", "s.opus", "t.aiff"] {
            assert!(is_candidate_name(ok, JobKind::Dance), "{ok}");
        }
        for no in [
            ".a.wav",
            "a.wav.tmp",
            "a.part",
            "a.wav~",
            ".choreod-tmp-1",
            "a.txt",
            "wav",
            "a.h5",
        ] {
            assert!(!is_candidate_name(no, JobKind::Dance), "{no}");
        }
    }

    #[test]
    fn motion_names_are_style_inputs_and_never_songs() {
        for ok in ["walk.bvh", "d.PKL", "f.npy", "m.h5", "m.hdf5", "x.pickle"] {
            assert!(is_candidate_name(ok, JobKind::Stylize), "{ok}");
            assert!(!is_candidate_name(ok, JobKind::Dance), "{ok}");
            assert_eq!(JobKind::of_name(ok), JobKind::Stylize, "{ok}");
        }
        for no in ["a.wav", ".walk.bvh", "walk.bvh.part", "walk.txt"] {
            assert!(!is_candidate_name(no, JobKind::Stylize), "{no}");
        }
        assert_eq!(JobKind::of_name("a.wav"), JobKind::Dance);
    }

    #[test]
    fn a_record_without_a_kind_is_a_dance_and_an_orphan_gets_its_kind_from_its_name() {
        let (dir, s) = spool();
        // A record written before kinds existed.
        let old: JobRecord =
            serde_json::from_str(r#"{"id":"1-0000","name":"a.wav","output":"a.h5","attempts":0}"#)
                .unwrap();
        assert_eq!(old.kind, JobKind::Dance);
        let inbox = dir.path().join("inbox");
        fs::write(inbox.join("walk.bvh"), b"x").unwrap();
        let claimed = s
            .claim(&inbox.join("walk.bvh"), JobKind::Stylize)
            .unwrap()
            .unwrap();
        let text = fs::read_to_string(
            dir.path()
                .join(format!("state/work/{}/job.json", claimed.id)),
        )
        .unwrap();
        let record: serde_json::Value = serde_json::from_str(&text).unwrap();
        assert_eq!(record["kind"], "stylize", "{text}");
        // Claimed just before a crash, without its record.
        fs::create_dir(dir.path().join("state/work/5-0000")).unwrap();
        fs::write(dir.path().join("state/work/5-0000/run.pkl"), b"x").unwrap();
        drop(s);
        let s = Spool::open(&dir.path().join("state"), &dir.path().join("out")).unwrap();
        let kinds: Vec<(String, JobKind)> = s
            .recover()
            .unwrap()
            .into_iter()
            .map(|r| (r.record.name, r.record.kind))
            .collect();
        assert_eq!(
            kinds,
            [
                ("walk.bvh".to_string(), JobKind::Stylize),
                ("run.pkl".to_string(), JobKind::Stylize)
            ]
        );
    }

    #[test]
    fn same_stem_gets_distinct_outputs_and_claim_moves_the_input() {
        let (dir, s) = spool();
        let inbox = dir.path().join("inbox");
        fs::write(inbox.join("song.wav"), b"1").unwrap();
        let a = s
            .claim(&inbox.join("song.wav"), JobKind::Dance)
            .unwrap()
            .unwrap();
        fs::write(inbox.join("song.wav"), b"2").unwrap();
        let b = s
            .claim(&inbox.join("song.wav"), JobKind::Dance)
            .unwrap()
            .unwrap();
        fs::write(dir.path().join("out/song-3.h5"), b"taken").unwrap();
        fs::write(inbox.join("song.flac"), b"3").unwrap();
        let c = s
            .claim(&inbox.join("song.flac"), JobKind::Dance)
            .unwrap()
            .unwrap();
        assert_eq!(
            (a.output.as_str(), b.output.as_str(), c.output.as_str()),
            ("song.h5", "song-2.h5", "song-4.h5")
        );
        assert_ne!(a.id, b.id);
        assert!(!inbox.join("song.wav").exists());
        assert_eq!(fs::read(s.input_path(&b)).unwrap(), b"2");
        assert!(
            s.claim(&inbox.join("gone.wav"), JobKind::Dance)
                .unwrap()
                .is_none()
        );
    }

    #[test]
    fn a_moved_output_name_is_free_and_survives_a_restart() {
        let (dir, s) = spool();
        let inbox = dir.path().join("inbox");
        fs::write(inbox.join("a.wav"), b"1").unwrap();
        let mut a = s
            .claim(&inbox.join("a.wav"), JobKind::Dance)
            .unwrap()
            .unwrap();
        // Files this job did not write took its name and the next one while it was down.
        for taken in ["out/a.h5", "out/a-2.h5"] {
            fs::write(dir.path().join(taken), b"not ours").unwrap();
        }
        s.move_output(&mut a).unwrap();
        assert_eq!(a.output, "a-3.h5");
        drop(s);
        let s = Spool::open(&dir.path().join("state"), &dir.path().join("out")).unwrap();
        let jobs = s.recover().unwrap();
        assert_eq!(jobs[0].record.output, "a-3.h5", "the new name is durable");
    }

    #[test]
    fn recovery_keeps_the_output_name_and_adopts_unrecorded_inputs() {
        let (dir, s) = spool();
        let inbox = dir.path().join("inbox");
        fs::write(inbox.join("a.wav"), b"1").unwrap();
        let mut a = s
            .claim(&inbox.join("a.wav"), JobKind::Dance)
            .unwrap()
            .unwrap();
        a.attempts = 2;
        s.save(&a).unwrap();
        // An input claimed just before a crash, without its record; an empty job folder.
        fs::create_dir(dir.path().join("state/work/5-0000")).unwrap();
        fs::write(dir.path().join("state/work/5-0000/a.wav"), b"2").unwrap();
        fs::create_dir(dir.path().join("state/work/6-0000")).unwrap();
        fs::write(dir.path().join("state/work/5-0000/.choreod-tmp-9-x"), b"").unwrap();
        fs::write(dir.path().join("out/.a.h5.tmp-9-0"), b"").unwrap();
        drop(s);
        let s = Spool::open(&dir.path().join("state"), &dir.path().join("out")).unwrap();
        let jobs: Vec<JobRecord> = s.recover().unwrap().into_iter().map(|r| r.record).collect();
        assert_eq!(jobs.len(), 2);
        let old = jobs.iter().find(|r| r.id == a.id).unwrap();
        assert_eq!((old.output.as_str(), old.attempts), ("a.h5", 2));
        let adopted = jobs.iter().find(|r| r.id == "5-0000").unwrap();
        assert_eq!(adopted.output, "a-2.h5");
        assert!(
            !dir.path()
                .join("state/work/5-0000/.choreod-tmp-9-x")
                .exists()
        );
        assert!(!dir.path().join("state/work/6-0000").exists());
        assert!(!dir.path().join("out/.a.h5.tmp-9-0").exists());
    }

    #[test]
    fn fail_writes_report_then_moves_input_and_is_idempotent_on_replay() {
        let (dir, s) = spool();
        let inbox = dir.path().join("inbox");
        fs::write(inbox.join("b.ogg"), b"x").unwrap();
        let mut r = s
            .claim(&inbox.join("b.ogg"), JobKind::Dance)
            .unwrap()
            .unwrap();
        r.failure = Some(failure());
        s.save(&r).unwrap(); // as if the daemon died right after recording the failure
        let mut replay: JobRecord = serde_json::from_slice(
            &fs::read(dir.path().join(format!("state/work/{}/job.json", r.id))).unwrap(),
        )
        .unwrap();
        s.fail(
            &mut replay,
            Failure {
                stage: "other".into(),
                reason: "ignored".into(),
                time: "t".into(),
            },
        )
        .unwrap();
        let base = format!("{}__b.ogg", r.id);
        let report: serde_json::Value = serde_json::from_slice(
            &fs::read(dir.path().join(format!("state/failed/{base}.error.json"))).unwrap(),
        )
        .unwrap();
        assert_eq!(report["stage"], "decode", "the first recorded failure wins");
        assert!(dir.path().join("state/failed").join(&base).exists());
        assert_eq!(
            list(&dir.path().join("state/work")).unwrap(),
            Vec::<String>::new()
        );
    }

    #[test]
    fn second_spool_on_the_same_state_or_output_is_refused() {
        let (dir, _s) = spool();
        let e = Spool::open(&dir.path().join("state"), &dir.path().join("out")).unwrap_err();
        assert!(e.to_string().contains("locked"), "{e}");
        assert!(e.downcast_ref::<NotReady>().is_some(), "exit code 4: {e}");
        fs::create_dir(dir.path().join("state2")).unwrap();
        let e = Spool::open(&dir.path().join("state2"), &dir.path().join("out")).unwrap_err();
        assert!(e.to_string().contains("output folder"), "{e}");
    }

    thread_local! {
        /// Make `Spool::save` fail as on a full disk (the e2e test uses a real full tmpfs).
        pub static RECORD_WRITES_FAIL: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
    }

    #[test]
    fn a_claim_whose_record_cannot_be_written_is_rolled_back() {
        let (dir, s) = spool();
        let inbox = dir.path().join("inbox");
        fs::write(inbox.join("full.wav"), b"song").unwrap();
        RECORD_WRITES_FAIL.set(true);
        let e = s
            .claim(&inbox.join("full.wav"), JobKind::Dance)
            .unwrap_err();
        RECORD_WRITES_FAIL.set(false);
        assert!(format!("{e:#}").contains("stays in the inbox"), "{e:#}");
        assert_eq!(fs::read(inbox.join("full.wav")).unwrap(), b"song");
        assert!(list(&dir.path().join("state/work")).unwrap().is_empty());
        // Space is back: the retry claims it, under the output name the failed claim released.
        let r = s
            .claim(&inbox.join("full.wav"), JobKind::Dance)
            .unwrap()
            .unwrap();
        assert_eq!(r.output, "full.h5");
    }

    #[test]
    fn long_names_derive_names_that_fit_and_keep_the_original() {
        let (dir, s) = spool();
        let inbox = dir.path().join("inbox");
        // 251 bytes, multi-byte characters across the cut, and a twin sharing the prefix.
        let stem = "é".repeat(123);
        let (a, b) = (format!("{stem}a.wav"), format!("{stem}b.wav"));
        assert_eq!(a.len(), 251);
        // The twins' derived names differ only by the hash of the whole name (checked first:
        // were they equal, reserving an output name below would never end).
        assert_ne!(
            fit_name(&a, MAX_DERIVED_NAME),
            fit_name(&b, MAX_DERIVED_NAME)
        );
        for name in [&a, &b] {
            fs::write(inbox.join(name), b"x").unwrap();
        }
        let mut ra = s.claim(&inbox.join(&a), JobKind::Dance).unwrap().unwrap();
        let rb = s.claim(&inbox.join(&b), JobKind::Dance).unwrap().unwrap();
        assert_eq!(ra.name, a, "the record keeps the full name");
        assert!(
            ra.output.len() <= MAX_DERIVED_NAME && ra.output.ends_with(".h5"),
            "{}",
            ra.output
        );
        assert_ne!(ra.output, rb.output);
        s.fail(&mut ra, failure()).unwrap();
        s.succeed(&rb).unwrap();
        let failed = list(&dir.path().join("state/failed")).unwrap();
        assert_eq!(failed.len(), 2, "input and report: {failed:?}");
        for n in failed
            .iter()
            .chain(&list(&dir.path().join("state/done")).unwrap())
        {
            assert!(
                n.len() <= MAX_DERIVED_NAME + ERROR_SUFFIX.len(),
                "{} bytes: {n}",
                n.len()
            );
            assert!(n.starts_with(&ra.id) || n.starts_with(&rb.id), "{n}");
        }
        let report_name = failed.iter().find(|n| n.ends_with(ERROR_SUFFIX)).unwrap();
        let report: serde_json::Value = serde_json::from_slice(
            &fs::read(dir.path().join("state/failed").join(report_name)).unwrap(),
        )
        .unwrap();
        assert_eq!(report["file"], a.as_str());
        // Deterministic: the same name always shortens the same way.
        assert_eq!(fit_name(&a, 100), fit_name(&a, 100));
        assert_eq!(fit_name("short.wav", 100), "short.wav");
    }

    #[test]
    fn a_name_that_is_not_utf8_is_claimed_and_reported_with_its_bytes() {
        use std::os::unix::ffi::OsStrExt;
        let (dir, s) = spool();
        let inbox = dir.path().join("inbox");
        let raw = std::ffi::OsStr::from_bytes(b"caf\xe9 song.wav");
        fs::write(inbox.join(raw), b"x").unwrap();
        let mut r = s.claim(&inbox.join(raw), JobKind::Dance).unwrap().unwrap();
        assert_eq!(r.name, "caf\u{fffd} song.wav");
        assert_eq!(r.original.as_deref(), Some("caf\\xe9 song.wav"));
        assert_eq!(r.output, "caf\u{fffd} song.h5");
        s.fail(&mut r, failure()).unwrap();
        let report: serde_json::Value = serde_json::from_slice(
            &fs::read(
                dir.path()
                    .join(format!("state/failed/{}__{}.error.json", r.id, r.name)),
            )
            .unwrap(),
        )
        .unwrap();
        assert_eq!(report["original_file"], "caf\\xe9 song.wav");
        assert!(fs::read_dir(&inbox).unwrap().next().is_none());
    }

    #[test]
    fn after_an_unclean_exit_running_jobs_are_suspects_and_only_a_solo_crash_is_charged() {
        let (dir, s) = spool();
        let inbox = dir.path().join("inbox");
        let mut jobs = Vec::new();
        for name in ["solo.wav", "beside.wav", "queued.wav"] {
            fs::write(inbox.join(name), b"x").unwrap();
            jobs.push(s.claim(&inbox.join(name), JobKind::Dance).unwrap().unwrap());
        }
        let mark_running = |s: &Spool, jobs: &mut [JobRecord]| {
            jobs[0].running = true;
            jobs[0].solo = true;
            jobs[1].running = true;
            for j in jobs.iter() {
                s.save(j).unwrap();
            }
        };
        mark_running(&s, &mut jobs);
        let marker = dir.path().join("state").join(RUNNING_MARKER);
        let reopen = || Spool::open(&dir.path().join("state"), &dir.path().join("out")).unwrap();
        // kill -9 from outside: the running marker stays, empty. Suspects, nobody charged.
        drop(s);
        assert_eq!(fs::read(&marker).unwrap(), b"");
        let s = reopen();
        let found = s.recover().unwrap();
        let by_name = |found: &[Recovered], n: &str| {
            let r = found.iter().find(|r| r.record.name == n).unwrap();
            (r.suspect, r.record.crashes)
        };
        assert_eq!(
            by_name(&found, "solo.wav"),
            (true, 0),
            "killed, not crashed"
        );
        assert_eq!(by_name(&found, "beside.wav"), (true, 0));
        assert_eq!(
            by_name(&found, "queued.wav"),
            (false, 0),
            "it was not running"
        );
        // The daemon runs them again and crashes: the handler wrote the signal into the marker.
        let mut armed = s.arm_running_marker().unwrap();
        mark_running(&s, &mut jobs);
        std::io::Write::write_all(&mut armed, b"SIGSEGV\n").unwrap();
        drop(s);
        let s = reopen();
        let found = s.recover().unwrap();
        assert_eq!(
            by_name(&found, "solo.wav"),
            (true, 1),
            "crashed while alone"
        );
        assert_eq!(
            by_name(&found, "beside.wav"),
            (true, 0),
            "not alone: no evidence"
        );
        // Killed again before the suspects ran: still suspects, no new charge.
        drop(s);
        let s = reopen();
        let found = s.recover().unwrap();
        assert_eq!(by_name(&found, "solo.wav"), (true, 1));
        // Armed again, the marker forgets the last crash.
        drop(s.arm_running_marker().unwrap());
        assert_eq!(fs::read(&marker).unwrap(), b"");
        s.mark_clean_exit().unwrap();
        drop(s);
        let found = reopen().recover().unwrap();
        assert!(
            found.iter().all(|r| !r.suspect),
            "a clean exit leaves no suspects"
        );
    }
}
