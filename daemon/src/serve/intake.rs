//! The watch-folder source: inotify (notify 8) on the inbox plus scans, a settle rule, and the
//! claim of each complete file into the spool.
//!
//! A file is taken when (1) its name is a candidate of the folder's kind
//! ([`spool::is_candidate_name`]), (2) it is a
//! regular file by `lstat` — symlinks are never followed, so nothing outside the inbox is ever
//! read or moved — (3) it has been closed after its last write (inotify `IN_CLOSE_WRITE`, or it
//! was moved in, or found by a scan), (4) its size and mtime stayed unchanged for
//! `serve.settle_ms`, and (5) no process holds it open for writing ([`open_for_writing`], from
//! `/proc`) — which catches a writer that was busy when the daemon started or when inotify lost
//! events. A file that was written to but whose close was never seen (lost events) is taken
//! after [`STUCK_OPEN`] without change, if no writer holds it.

use std::collections::HashMap;
use std::fs;
use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::sync::mpsc;
use std::time::{Duration, Instant, SystemTime};

use anyhow::Context;
use notify::event::{AccessKind, AccessMode, CreateKind, ModifyKind, RenameMode};
use notify::{EventKind, RecursiveMode, Watcher};

use super::spool::{self, JobKind, JobRecord};
use super::{Job, SourceContext};

/// How often the tracked files are checked for settling.
const TICK: Duration = Duration::from_millis(50);
/// How often the inbox is rescanned, in case inotify dropped events (queue overflow).
const RESCAN: Duration = Duration::from_secs(2);
/// A file written to but never seen closed is taken after this long unchanged.
const STUCK_OPEN: Duration = Duration::from_secs(60);

/// The inbox folder as a source of jobs.
#[derive(Debug, Clone)]
pub struct WatchFolder {
    pub inbox: PathBuf,
    /// What the inbox's files become: songs to dance or motions to stylize.
    pub kind: JobKind,
    pub settle: Duration,
}

#[derive(Debug)]
struct Tracked {
    /// Written to since the last close-write we saw.
    open: bool,
    /// Not a regular file (a symlink, a folder, …): kept so that rescans do not warn again,
    /// until an event on the name makes it worth another look.
    ignored: bool,
    size: u64,
    mtime: Option<SystemTime>,
    since: Instant,
}

impl WatchFolder {
    /// Run until shutdown: claim every complete inbox file and queue it as a job.
    pub fn run(&self, ctx: &SourceContext) -> anyhow::Result<()> {
        let (tx, rx) = mpsc::channel();
        let mut watcher = notify::recommended_watcher(move |res| {
            let _ = tx.send(res);
        })
        .context("starting the inotify watcher")?;
        watcher
            .watch(&self.inbox, RecursiveMode::NonRecursive)
            .with_context(|| format!("watching {}", self.inbox.display()))?;
        tracing::info!(inbox = %self.inbox.display(), kind = ?self.kind, settle_ms = self.settle.as_millis() as u64, "watching the inbox");

        let mut tracked: HashMap<PathBuf, Tracked> = HashMap::new();
        // Files that arrived while the daemon was down count as closed.
        self.scan(&mut tracked)?;
        let mut last_scan = Instant::now();
        while !ctx.shutdown.load(Ordering::Relaxed) {
            match rx.recv_timeout(TICK) {
                Ok(Ok(event)) => self.on_event(&event, &mut tracked),
                Ok(Err(e)) => {
                    tracing::warn!(error = %e, "inotify error; rescanning the inbox");
                    self.scan(&mut tracked)?;
                }
                Err(mpsc::RecvTimeoutError::Timeout) => {}
                Err(mpsc::RecvTimeoutError::Disconnected) => {
                    anyhow::bail!("the inotify watcher stopped")
                }
            }
            // Drain what else arrived before looking at the clock.
            while let Ok(Ok(event)) = rx.try_recv() {
                self.on_event(&event, &mut tracked);
            }
            if last_scan.elapsed() >= RESCAN {
                self.scan(&mut tracked)?;
                last_scan = Instant::now();
            }
            for path in self.settled(&mut tracked) {
                tracked.remove(&path);
                let t0 = Instant::now();
                if !self.take(&path, ctx)? {
                    break;
                }
                if t0.elapsed() > 2 * TICK {
                    // We waited for queue room: the other files' state may be stale, and
                    // events piled up. Look again before taking more.
                    break;
                }
            }
        }
        Ok(())
    }

    fn on_event(&self, event: &notify::Event, tracked: &mut HashMap<PathBuf, Tracked>) {
        if event.need_rescan() {
            // Handled by the next periodic scan; make it come now.
            let _ = self.scan(tracked);
        }
        let paths: Vec<&PathBuf> = match event.kind {
            // A rename within the inbox reports [from, to]: only `to` is a file now.
            EventKind::Modify(ModifyKind::Name(RenameMode::Both)) => {
                event.paths.iter().skip(1).collect()
            }
            _ => event.paths.iter().collect(),
        };
        for path in paths {
            if !self.is_inbox_candidate(path) {
                continue;
            }
            let open = match event.kind {
                EventKind::Access(AccessKind::Close(AccessMode::Write)) => Some(false),
                EventKind::Modify(ModifyKind::Name(RenameMode::To | RenameMode::Both)) => {
                    Some(false)
                }
                EventKind::Create(CreateKind::File | CreateKind::Any) => Some(true),
                EventKind::Modify(ModifyKind::Data(_) | ModifyKind::Any) => Some(true),
                EventKind::Remove(_) | EventKind::Modify(ModifyKind::Name(RenameMode::From)) => {
                    tracked.remove(path);
                    None
                }
                _ => None,
            };
            if let Some(open) = open {
                let t = tracked.entry(path.clone()).or_insert_with(|| Tracked {
                    open,
                    ignored: false,
                    size: u64::MAX,
                    mtime: None,
                    since: Instant::now(),
                });
                t.open = open;
                t.ignored = false;
                t.since = Instant::now();
            }
        }
    }

    fn is_inbox_candidate(&self, path: &Path) -> bool {
        path.parent() == Some(self.inbox.as_path())
            && path
                .file_name()
                .is_some_and(|n| spool::is_candidate_name(&n.to_string_lossy(), self.kind))
    }

    /// Add inbox files not yet tracked (as closed: nobody is known to be writing them). Names
    /// that are not UTF-8 are taken too (the spool claims them under their lossy form).
    fn scan(&self, tracked: &mut HashMap<PathBuf, Tracked>) -> anyhow::Result<()> {
        let listing = fs::read_dir(&self.inbox)
            .with_context(|| format!("listing {}", self.inbox.display()))?;
        for entry in listing {
            let path = entry
                .with_context(|| format!("listing {}", self.inbox.display()))?
                .path();
            if self.is_inbox_candidate(&path) && !tracked.contains_key(&path) {
                tracked.insert(
                    path,
                    Tracked {
                        open: false,
                        ignored: false,
                        size: u64::MAX,
                        mtime: None,
                        since: Instant::now(),
                    },
                );
            }
        }
        Ok(())
    }

    /// Paths whose file is complete, oldest first; updates size/mtime of the others.
    fn settled(&self, tracked: &mut HashMap<PathBuf, Tracked>) -> Vec<PathBuf> {
        let mut ready = Vec::new();
        tracked.retain(|path, t| {
            let meta = match fs::symlink_metadata(path) {
                Ok(m) => m,
                Err(_) => return false, // gone; a new event brings it back
            };
            if !meta.file_type().is_file() {
                if !t.ignored {
                    tracing::warn!(file = %path.display(), "ignoring: not a regular file (symlinks are never followed)");
                    t.ignored = true;
                }
                return true;
            }
            let mtime = meta.modified().ok();
            if meta.len() != t.size || mtime != t.mtime {
                t.size = meta.len();
                t.mtime = mtime;
                t.since = Instant::now();
                return true;
            }
            let quiet = t.since.elapsed();
            if (!t.open && quiet >= self.settle) || quiet >= STUCK_OPEN.max(self.settle) {
                if open_for_writing(path, &meta) {
                    // Still being written: look again after another quiet period.
                    t.since = Instant::now();
                } else {
                    ready.push((t.since, path.clone()));
                }
            }
            true
        });
        ready.sort();
        ready.into_iter().map(|(_, p)| p).collect()
    }

    /// Claim `path` and queue it. `Ok(false)` when shutdown came while waiting for queue room
    /// (the claimed job stays in `work/` and resumes at the next start).
    fn take(&self, path: &Path, ctx: &SourceContext) -> anyhow::Result<bool> {
        let record: JobRecord = match ctx.spool.claim(path, self.kind) {
            Ok(Some(r)) => r,
            Ok(None) => return Ok(true),
            Err(e) => {
                // One unclaimable file (permissions, disk full, …) must not stop the intake: it
                // stays in the inbox, the next scan retries it, and /healthz shows the failures.
                ctx.metrics.claim_result(false);
                tracing::warn!(file = %path.display(), error = format!("{e:#}"), "cannot claim; will retry");
                return Ok(true);
            }
        };
        ctx.metrics.claim_result(true);
        tracing::info!(job = %record.id, file = %record.name, output = %record.output, "claimed");
        Ok(ctx.enqueue(Job {
            record,
            suspect: false,
        }))
    }
}

/// Whether a process we can see (any, as root; our own user's otherwise) holds `path` open for
/// writing: one of its `/proc/<pid>/fd/*` links is this file (same device and inode) and the
/// `flags` in `/proc/<pid>/fdinfo/<fd>` include O_WRONLY or O_RDWR.
fn open_for_writing(path: &Path, meta: &fs::Metadata) -> bool {
    use std::os::unix::fs::MetadataExt;
    const ACCESS_MODE: u32 = 0o3; // O_ACCMODE; O_RDONLY is 0
    let Ok(procs) = fs::read_dir("/proc") else {
        return false;
    };
    for process in procs.flatten() {
        if !process
            .file_name()
            .as_encoded_bytes()
            .iter()
            .all(u8::is_ascii_digit)
        {
            continue;
        }
        let Ok(fds) = fs::read_dir(process.path().join("fd")) else {
            continue; // gone, or another user's
        };
        for fd in fds.flatten() {
            // The link text names the file; compare names first, then device and inode.
            let same_name =
                fs::read_link(fd.path()).is_ok_and(|target| target.file_name() == path.file_name());
            let same_file = same_name
                && fs::metadata(fd.path())
                    .is_ok_and(|m| m.dev() == meta.dev() && m.ino() == meta.ino());
            if !same_file {
                continue;
            }
            let info = fs::read_to_string(process.path().join("fdinfo").join(fd.file_name()))
                .unwrap_or_default();
            let flags = info
                .lines()
                .find_map(|l| l.strip_prefix("flags:"))
                .and_then(|f| u32::from_str_radix(f.trim(), 8).ok())
                .unwrap_or(0);
            if flags & ACCESS_MODE != 0 {
                return true;
            }
        }
    }
    false
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn settle_waits_for_close_and_quiet() {
        let dir = tempfile::tempdir().unwrap();
        let w = WatchFolder {
            inbox: dir.path().to_path_buf(),
            kind: JobKind::Dance,
            settle: Duration::from_millis(100),
        };
        let song = dir.path().join("a.wav");
        fs::write(&song, b"abc").unwrap();
        std::os::unix::fs::symlink("/etc/passwd", dir.path().join("link.wav")).unwrap();
        let mut tracked = HashMap::new();
        w.scan(&mut tracked).unwrap();
        assert_eq!(tracked.len(), 2);
        assert!(
            w.settled(&mut tracked).is_empty(),
            "first look only records size and mtime"
        );
        assert!(
            tracked[&dir.path().join("link.wav")].ignored,
            "the symlink is ignored, once"
        );
        tracked.get_mut(&song).unwrap().open = true;
        std::thread::sleep(Duration::from_millis(150));
        assert!(w.settled(&mut tracked).is_empty(), "still open for writing");
        tracked.get_mut(&song).unwrap().open = false;
        assert_eq!(w.settled(&mut tracked), vec![song.clone()]);
        fs::write(&song, b"abcdef").unwrap();
        assert!(
            w.settled(&mut tracked).is_empty(),
            "a size change restarts the settle time"
        );
    }

    #[test]
    fn a_file_held_open_for_writing_is_not_taken_even_when_quiet() {
        // A writer that was busy before the daemon started: the scan sees the file as closed.
        let dir = tempfile::tempdir().unwrap();
        let w = WatchFolder {
            inbox: dir.path().to_path_buf(),
            kind: JobKind::Dance,
            settle: Duration::from_millis(50),
        };
        let song = dir.path().join("slow.wav");
        let mut writer = fs::File::create(&song).unwrap();
        std::io::Write::write_all(&mut writer, b"RIFF half a song").unwrap();
        let reader = fs::File::open(&song).unwrap(); // readers do not count
        let mut tracked = HashMap::new();
        w.scan(&mut tracked).unwrap();
        assert!(w.settled(&mut tracked).is_empty(), "first look");
        std::thread::sleep(Duration::from_millis(120));
        assert!(
            w.settled(&mut tracked).is_empty(),
            "quiet, but a writer holds it"
        );
        drop(writer);
        std::thread::sleep(Duration::from_millis(120));
        assert_eq!(w.settled(&mut tracked), vec![song], "the writer closed it");
        drop(reader);
    }
}
