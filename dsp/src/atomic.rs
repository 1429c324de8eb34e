//! Atomic file output, the one implementation every crate uses: write under a hidden temporary
//! name in the target's directory (same filesystem, so the rename is atomic), fsync the file,
//! rename it over the target, fsync the directory. A reader sees the old file or the complete new
//! one, never a partial one, and once this returns the new file survives a power cut.
//! Every step's error is reported (a directory that cannot be fsynced is an error: the rename
//! would not be durable).

use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

static TEMP_COUNTER: AtomicU64 = AtomicU64::new(0);

/// The directory holding `path` (`.` for a bare file name).
pub fn parent_dir(path: &Path) -> &Path {
    match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    }
}

/// A fresh temporary name beside `path`: `.<name>.tmp-<pid>-<n>` (hidden, unique within the
/// process and across processes).
pub fn temp_path(path: &Path) -> PathBuf {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let n = TEMP_COUNTER.fetch_add(1, Ordering::Relaxed);
    parent_dir(path).join(format!(".{name}.tmp-{}-{n}", std::process::id()))
}

/// fsync a directory, so that renames and creations in it are durable.
pub fn sync_dir(dir: &Path) -> std::io::Result<()> {
    std::fs::File::open(dir)?.sync_all()
}

/// Make a complete temporary file durable under its final name: fsync `tmp`, rename it to
/// `path`, fsync `path`'s directory. For files another library wrote (HDF5) under `tmp`.
pub fn commit_atomic(tmp: &Path, path: &Path) -> std::io::Result<()> {
    std::fs::File::open(tmp)?.sync_all()?;
    std::fs::rename(tmp, path)?;
    sync_dir(parent_dir(path))
}

/// Write a file atomically through the temporary name `tmp` (which must be in `path`'s
/// directory): `write` fills it, then [`commit_atomic`]. On error the temporary file is removed
/// and the target is untouched.
pub fn write_atomic_with(
    tmp: &Path,
    path: &Path,
    write: impl FnOnce(&mut dyn Write) -> std::io::Result<()>,
) -> std::io::Result<()> {
    let result = (|| {
        let file = std::fs::File::create(tmp)?;
        let mut w = std::io::BufWriter::new(file);
        write(&mut w)?;
        w.into_inner()
            .map_err(std::io::IntoInnerError::into_error)?
            .sync_all()?;
        std::fs::rename(tmp, path)
    })();
    if let Err(e) = result {
        let _ = std::fs::remove_file(tmp);
        return Err(e);
    }
    sync_dir(parent_dir(path))
}

/// Check that the temporary file of an atomic write of `path` can be created (and remove it
/// again): a long job refuses a missing or unwritable folder before its work, not after it.
pub fn probe_writable(path: &Path) -> std::io::Result<()> {
    let probe = temp_path(path);
    std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(&probe)?;
    std::fs::remove_file(&probe)
}

/// Write `bytes` to `path` atomically under a [`temp_path`].
pub fn write_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    write_atomic_with(&temp_path(path), path, |w| w.write_all(bytes))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn replaces_the_target_and_leaves_no_temporary() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.json");
        std::fs::write(&p, b"old").unwrap();
        write_atomic(&p, b"new content").unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"new content");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn a_failing_writer_keeps_the_old_file() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.json");
        std::fs::write(&p, b"old").unwrap();
        let e = write_atomic_with(&temp_path(&p), &p, |w| {
            w.write_all(b"half")?;
            Err(std::io::Error::other("disk on fire"))
        })
        .unwrap_err();
        assert_eq!(e.to_string(), "disk on fire");
        assert_eq!(std::fs::read(&p).unwrap(), b"old");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn errors_are_reported() {
        let dir = tempfile::tempdir().unwrap();
        // A target directory that does not exist: creating the temporary file fails.
        let p = dir.path().join("missing").join("a.json");
        assert!(write_atomic(&p, b"x").is_err());
        // Committing a temporary file that does not exist fails instead of renaming nothing.
        let q = dir.path().join("b.json");
        assert!(commit_atomic(&dir.path().join(".b.json.tmp"), &q).is_err());
        assert!(!q.exists());
    }

    #[test]
    fn the_probe_refuses_a_missing_folder_and_leaves_nothing_behind() {
        let dir = tempfile::tempdir().unwrap();
        probe_writable(&dir.path().join("a.h5")).unwrap();
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
        assert!(probe_writable(&dir.path().join("missing").join("a.h5")).is_err());
    }

    #[test]
    fn temp_names_are_hidden_unique_and_beside_the_target() {
        let a = temp_path(Path::new("out/x.h5"));
        let b = temp_path(Path::new("out/x.h5"));
        assert_ne!(a, b);
        assert_eq!(a.parent(), Some(Path::new("out")));
        assert!(
            a.file_name()
                .unwrap()
                .to_str()
                .unwrap()
                .starts_with(".x.h5.tmp-")
        );
        assert_eq!(temp_path(Path::new("y.npy")).parent(), Some(Path::new(".")));
    }
}
