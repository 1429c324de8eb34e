//! The job spool on disk: how an inbox file becomes exactly one visible outcome, crash-safely.
//!
//! ```text
//! <state>/work/<id>/<name>             claimed input (the rename out of the inbox is the claim)
//! <state>/work/<id>/job.json           job record: name, output name, attempts, failure
//! <state>/done/<id>__<name>            input of a job whose motion file is durable
//! <state>/failed/<id>__<name>          input of a failed job ...
//! <state>/failed/<id>__<name>.error.json   ... and its report {stage, reason, time, attempts}
//! <state>/.choreod.lock                held (flock) while a daemon owns the spool
//! ```
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
use serde::{Deserialize, Serialize};

/// Extensions (lower case) the inbox accepts; everything else is left alone. Opus is accepted
/// on purpose so that it fails with the decoder's message instead of sitting in the inbox.
pub const SUPPORTED_EXTENSIONS: &[&str] = &[
    "wav", "flac", "mp3", "ogg", "oga", "m4a", "mp4", "aac", "aif", "aiff", "opus",
];

/// Prefix of every temporary file the spool writes; cleaned at start-up.
const TMP_PREFIX: &str = ".choreod-tmp-";
const RECORD: &str = "job.json";
const ERROR_SUFFIX: &str = ".error.json";
/// Separates the job id from the original name in `done/` and `failed/`; ids never contain it.
const SEP: &str = "__";

/// Whether an inbox file name is a song to take: not hidden, not a temporary name, and with a
/// supported extension.
pub fn is_candidate_name(name: &str) -> bool {
    if name.starts_with('.') || name.ends_with('~') {
        return false;
    }
    let lower = name.to_ascii_lowercase();
    if lower.ends_with(".tmp") || lower.ends_with(".part") {
        return false;
    }
    match Path::new(&lower).extension().and_then(|e| e.to_str()) {
        Some(ext) => SUPPORTED_EXTENSIONS.contains(&ext),
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
    /// The input's original file name.
    pub name: String,
    /// The motion file's name in the output folder, decided at claim time so that a resumed
    /// job keeps it and two inputs with the same stem never share one.
    pub output: String,
    /// Attempts started; written and fsynced before each attempt runs.
    pub attempts: u32,
    /// Set once the job has failed; the rest of the failure path is replayed on recovery.
    #[serde(default)]
    pub failure: Option<Failure>,
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
    // Held for the life of the spool: one daemon per state folder.
    _lock: File,
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
        let lock_path = state.join(".choreod.lock");
        let lock = File::create(&lock_path)
            .with_context(|| format!("creating {}", lock_path.display()))?;
        if rustix::fs::flock(&lock, rustix::fs::FlockOperation::NonBlockingLockExclusive).is_err() {
            bail!(
                "{} is locked: another choreod serve uses this state folder",
                lock_path.display()
            );
        }
        let spool = Self {
            output: output.to_path_buf(),
            work,
            done,
            failed,
            reserved: Mutex::new(HashSet::new()),
            seq: AtomicU32::new(0),
            _lock: lock,
        };
        spool.clean_temporaries()?;
        Ok(spool)
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
    /// visible, or the input vanished), an empty job folder is removed. Returns the jobs to run,
    /// oldest first.
    pub fn recover(&self) -> anyhow::Result<Vec<JobRecord>> {
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
            let record = JobRecord {
                output: self.reserve_output(&name),
                id,
                name,
                attempts: 0,
                failure: None,
            };
            self.save(&record)?;
            records.push(record);
        }
        records.sort_by(|a, b| a.id.cmp(&b.id));
        Ok(records)
    }

    /// Claim an inbox file: rename it into `work/<id>/` (the claim), then write its record.
    /// `Ok(None)` when the file vanished before it could be claimed.
    pub fn claim(&self, inbox_file: &Path) -> anyhow::Result<Option<JobRecord>> {
        let name = file_name(inbox_file)?;
        let id = self.next_id();
        let dir = self.work.join(&id);
        fs::create_dir(&dir).with_context(|| format!("creating {}", dir.display()))?;
        match fs::rename(inbox_file, dir.join(&name)) {
            Ok(()) => {}
            Err(e) => {
                let _ = fs::remove_dir(&dir);
                if e.kind() == std::io::ErrorKind::NotFound {
                    return Ok(None);
                }
                return Err(e).with_context(|| format!("claiming {}", inbox_file.display()));
            }
        }
        let record = JobRecord {
            id,
            output: self.reserve_output(&name),
            name,
            attempts: 0,
            failure: None,
        };
        self.save(&record)?;
        sync_dir(&self.work)?;
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
            let candidate = if n == 1 {
                format!("{stem}.h5")
            } else {
                format!("{stem}-{n}.h5")
            };
            if !reserved.contains(&candidate) && !self.output.join(&candidate).exists() {
                reserved.insert(candidate.clone());
                return candidate;
            }
            n += 1;
        }
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
        let text = serde_json::to_vec_pretty(record).context("serialising a job record")?;
        write_atomic(&self.record_path(record), &text)
    }

    /// The motion file is durable: move the input to `done/` and drop the record.
    pub fn succeed(&self, record: &JobRecord) -> anyhow::Result<()> {
        let target = self.done.join(format!("{}{SEP}{}", record.id, record.name));
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
        let base = format!("{}{SEP}{}", record.id, record.name);
        let report = serde_json::json!({
            "id": record.id,
            "file": record.name,
            "stage": failure.stage,
            "reason": failure.reason,
            "time": failure.time,
            "attempts": record.attempts,
        });
        let text = serde_json::to_vec_pretty(&report).context("serialising an error report")?;
        write_atomic(&self.failed.join(format!("{base}{ERROR_SUFFIX}")), &text)?;
        rename_durably(&self.input_path(record), &self.failed.join(&base))?;
        self.remove_job_dir(&record.id)?;
        self.lock_reserved().remove(&record.output);
        Ok(())
    }
}

/// Names in `dir` (not following symlinks; unreadable names skipped with a warning).
pub fn list(dir: &Path) -> anyhow::Result<Vec<String>> {
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
            assert!(is_candidate_name(ok), "{ok}");
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
            assert!(!is_candidate_name(no), "{no}");
        }
    }

    #[test]
    fn same_stem_gets_distinct_outputs_and_claim_moves_the_input() {
        let (dir, s) = spool();
        let inbox = dir.path().join("inbox");
        fs::write(inbox.join("song.wav"), b"1").unwrap();
        let a = s.claim(&inbox.join("song.wav")).unwrap().unwrap();
        fs::write(inbox.join("song.wav"), b"2").unwrap();
        let b = s.claim(&inbox.join("song.wav")).unwrap().unwrap();
        fs::write(dir.path().join("out/song-3.h5"), b"taken").unwrap();
        fs::write(inbox.join("song.flac"), b"3").unwrap();
        let c = s.claim(&inbox.join("song.flac")).unwrap().unwrap();
        assert_eq!(
            (a.output.as_str(), b.output.as_str(), c.output.as_str()),
            ("song.h5", "song-2.h5", "song-4.h5")
        );
        assert_ne!(a.id, b.id);
        assert!(!inbox.join("song.wav").exists());
        assert_eq!(fs::read(s.input_path(&b)).unwrap(), b"2");
        assert!(s.claim(&inbox.join("gone.wav")).unwrap().is_none());
    }

    #[test]
    fn recovery_keeps_the_output_name_and_adopts_unrecorded_inputs() {
        let (dir, s) = spool();
        let inbox = dir.path().join("inbox");
        fs::write(inbox.join("a.wav"), b"1").unwrap();
        let mut a = s.claim(&inbox.join("a.wav")).unwrap().unwrap();
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
        let jobs = s.recover().unwrap();
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
        let mut r = s.claim(&inbox.join("b.ogg")).unwrap().unwrap();
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
    fn second_spool_on_the_same_state_is_refused() {
        let (dir, _s) = spool();
        let e = Spool::open(&dir.path().join("state"), &dir.path().join("out")).unwrap_err();
        assert!(e.to_string().contains("locked"), "{e}");
    }
}
