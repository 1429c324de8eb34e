//! HDF5 helpers every file of this crate goes through: one way to open, to write attributes,
//! and to check a file before reading it.
//!
//! An HDF5 file can point outside itself (external and soft links, external raw storage,
//! virtual datasets mapping other files) and can declare datasets far larger than what it
//! stores (the library then fabricates fill values). [`open_checked`] refuses the first kind in
//! the whole file before anything is read; [`check_readable`] refuses, per dataset, shapes over
//! the element cap ([`crate::limits`]) and data that was declared but never written.

use std::path::Path;

use hdf5::dataset::Layout;
use hdf5::types::VarLenUnicode;
use hdf5::{LinkType, LocationType};

use crate::error::{Error, Result, h5_err};

/// Deepest group nesting accepted (our files nest 2 levels).
const MAX_DEPTH: usize = 16;
/// Most links visited in one file (a prep shard holds a few thousand; hard links can make a
/// small file look like an exponentially large tree).
const MAX_LINKS: usize = 1_000_000;

/// Every HDF5 file of this crate is opened through this builder, with the "strong" close
/// degree: closing (dropping) the file closes every object still open in it. With HDF5's default
/// "weak" degree one lingering object handle keeps the file, and its lock, open after the file
/// was renamed or deleted, and HDF5 recognises files by inode: a later file that reuses the inode
/// then fails to open with "unable to lock file" (seen once in the test suite).
pub(crate) fn h5_file() -> hdf5::FileBuilder {
    let mut builder = hdf5::File::with_options();
    builder.with_fapl(|p| p.fclose_degree(hdf5::file::FileCloseDegree::Strong));
    builder
}

/// Open an HDF5 file for reading after checking that nothing in it leads outside it: every link
/// is a hard link, no dataset has external storage or a virtual layout.
pub(crate) fn open_checked(path: &Path) -> Result<hdf5::File> {
    if !path.is_file() {
        return Err(Error::Io {
            path: path.to_path_buf(),
            source: std::io::Error::from(std::io::ErrorKind::NotFound),
        });
    }
    let file = h5_file()
        .open(path)
        .map_err(|e| Error::invalid(path, format!("not an HDF5 file ({e})")))?;
    let mut budget = MAX_LINKS;
    audit_group(path, &file, "", 0, &mut budget)?;
    Ok(file)
}

fn refused(path: &Path, object: &str, feature: impl Into<String>) -> Error {
    Error::Hdf5Refused {
        path: path.to_path_buf(),
        object: object.to_owned(),
        feature: feature.into(),
    }
}

fn audit_group(
    path: &Path,
    group: &hdf5::Group,
    prefix: &str,
    depth: usize,
    budget: &mut usize,
) -> Result<()> {
    let mut links = Vec::new();
    group
        .iter_visit_default(|name, info| {
            links.push((name.to_owned(), info.link_type));
            Ok(())
        })
        .map_err(h5_err(path))?;
    for (name, link_type) in links {
        let object = format!("{prefix}/{name}");
        *budget = budget
            .checked_sub(1)
            .ok_or_else(|| refused(path, &object, format!("more than {MAX_LINKS} links")))?;
        match link_type {
            LinkType::Hard => {}
            LinkType::Soft => return Err(refused(path, &object, "a soft link")),
            LinkType::External => {
                return Err(refused(path, &object, "an external or user-defined link"));
            }
        }
        match group.loc_type_by_name(&name).map_err(h5_err(path))? {
            LocationType::Group => {
                if depth >= MAX_DEPTH {
                    return Err(refused(
                        path,
                        &object,
                        format!("groups nested deeper than {MAX_DEPTH}"),
                    ));
                }
                let g = group.group(&name).map_err(h5_err(path))?;
                audit_group(path, &g, &object, depth + 1, budget)?;
            }
            LocationType::Dataset => {
                let ds = group.dataset(&name).map_err(h5_err(path))?;
                audit_dataset(path, &ds, &object)?;
            }
            LocationType::NamedDatatype => {}
            #[allow(unreachable_patterns)]
            _ => return Err(refused(path, &object, "an object of unknown type")),
        }
    }
    Ok(())
}

fn audit_dataset(path: &Path, ds: &hdf5::Dataset, object: &str) -> Result<()> {
    let dcpl = ds.dcpl().map_err(h5_err(path))?;
    if !dcpl.external().is_empty() {
        return Err(refused(path, object, "external raw-data storage"));
    }
    if dcpl.layout() == Layout::Virtual {
        return Err(refused(path, object, "a virtual dataset"));
    }
    Ok(())
}

/// Check a dataset (of a file opened with [`open_checked`]) before reading it whole: its
/// declared size is within the element cap and every value was actually written, so reading
/// allocates no more than the file can justify. Contiguous and compact data must occupy its full
/// size; chunked data must have every chunk of its extent allocated (a compressed chunk may be
/// small, but it exists only if written).
pub(crate) fn check_readable(path: &Path, ds: &hdf5::Dataset) -> Result<()> {
    let object = ds.name();
    let shape = ds.shape();
    let n = crate::limits::elements(path, &object, &shape)?;
    if n == 0 {
        return Ok(());
    }
    match ds.layout() {
        Layout::Chunked => {
            let chunk = ds.chunk().unwrap_or_default();
            if chunk.len() != shape.len() || chunk.contains(&0) {
                return Err(refused(
                    path,
                    &object,
                    "a chunked layout without chunk sizes",
                ));
            }
            let needed: usize = shape
                .iter()
                .zip(&chunk)
                .map(|(d, c)| d.div_ceil(*c))
                .product();
            let written = ds.num_chunks().unwrap_or(0);
            if written < needed {
                return Err(refused(
                    path,
                    &object,
                    format!(
                        "data declared as {shape:?} but only {written} of its {needed} chunks written"
                    ),
                ));
            }
        }
        Layout::Contiguous | Layout::Compact => {
            let size = ds.dtype().map_err(h5_err(path))?.size();
            let declared = (n as u64).saturating_mul(size as u64);
            let stored = ds.storage_size();
            if stored < declared {
                return Err(refused(
                    path,
                    &object,
                    format!(
                        "data declared as {shape:?} ({declared} bytes) but only {stored} bytes written"
                    ),
                ));
            }
        }
        other => return Err(refused(path, &object, format!("the {other:?} layout"))),
    }
    Ok(())
}

/// A string as an HDF5 variable-length UTF-8 value.
pub(crate) fn vlu(path: &Path, s: &str) -> Result<VarLenUnicode> {
    s.parse::<VarLenUnicode>().map_err(|_| {
        Error::invalid(
            path,
            format!("string {s:?} cannot be stored (contains NUL?)"),
        )
    })
}

/// Write a scalar string attribute.
pub(crate) fn put_str(path: &Path, loc: &hdf5::Location, name: &str, value: &str) -> Result<()> {
    let v = vlu(path, value)?;
    loc.new_attr::<VarLenUnicode>()
        .create(name)
        .and_then(|a| a.write_scalar(&v))
        .map_err(h5_err(path))
}

/// Write a scalar attribute.
pub(crate) fn put<T: hdf5::H5Type>(
    path: &Path,
    loc: &hdf5::Location,
    name: &str,
    value: T,
) -> Result<()> {
    loc.new_attr::<T>()
        .create(name)
        .and_then(|a| a.write_scalar(&value))
        .map_err(h5_err(path))
}

/// The venv python with h5py for tests: `$CHOREOD_PYTHON`, else `<workspace>/.venv/bin/python`.
#[cfg(test)]
pub(crate) fn venv_python() -> std::path::PathBuf {
    std::env::var_os("CHOREOD_PYTHON")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("../.venv/bin/python"))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Files made by h5py, one per hostile feature, beside a plain one (`ok.h5`), in `dir`.
    const HOSTILE: &str = r#"
import sys, os, h5py, numpy as np
d = sys.argv[1]
secret = os.path.join(d, "secret.bin")
with open(secret, "wb") as f:
    f.write(np.arange(24, dtype=np.float32).tobytes())
with h5py.File(os.path.join(d, "other.h5"), "w") as f:
    f["data"] = np.ones((2, 3), np.float32)
def mk(name):
    f = h5py.File(os.path.join(d, name), "w")
    f.create_group("g")["plain"] = np.zeros((2, 3), np.float32)
    return f
with mk("ok.h5") as f:
    pass
with mk("soft.h5") as f:
    f["g/x"] = h5py.SoftLink("/g/plain")
with mk("external_link.h5") as f:
    f["g/x"] = h5py.ExternalLink("other.h5", "/data")
with mk("external_storage.h5") as f:
    f.create_dataset("g/x", shape=(2, 3), dtype=np.float32, external=[(secret, 0, 24)])
with mk("virtual.h5") as f:
    layout = h5py.VirtualLayout(shape=(2, 3), dtype=np.float32)
    layout[:] = h5py.VirtualSource("other.h5", "data", shape=(2, 3))
    f.create_virtual_dataset("g/x", layout)
with mk("unwritten.h5") as f:
    f.create_dataset("g/x", shape=(100000, 24, 3), dtype=np.float32)
with mk("unwritten_gzip.h5") as f:
    f.create_dataset("g/x", shape=(100000, 24, 3), dtype=np.float32, chunks=(64, 24, 3), compression="gzip")
with mk("half_written.h5") as f:
    ds = f.create_dataset("g/x", shape=(1000, 24, 3), dtype=np.float32, chunks=(64, 24, 3), compression="gzip")
    ds[:500] = 1.0
with mk("written_gzip.h5") as f:
    ds = f.create_dataset("g/x", shape=(1000, 24, 3), dtype=np.float32, chunks=(64, 24, 3), compression="gzip")
    ds[:] = 0.0
print("ok")
"#;

    fn make_hostile(dir: &Path) {
        let out = std::process::Command::new(venv_python())
            .arg("-c")
            .arg(HOSTILE)
            .arg(dir)
            .output()
            .expect("run the venv python (set CHOREOD_PYTHON)");
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
    }

    /// Open, then check `/g/x` (if it exists) as a reader would before reading it.
    fn open_and_check(p: &Path) -> Result<()> {
        let f = open_checked(p)?;
        if let Ok(ds) = f.dataset("g/x") {
            check_readable(p, &ds)?;
        }
        Ok(())
    }

    #[test]
    fn links_and_storage_outside_the_file_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        make_hostile(dir.path());
        open_and_check(&dir.path().join("ok.h5")).unwrap();
        for (name, want) in [
            ("soft.h5", "a soft link"),
            ("external_link.h5", "an external or user-defined link"),
            ("external_storage.h5", "external raw-data storage"),
            ("virtual.h5", "a virtual dataset"),
        ] {
            let e = open_and_check(&dir.path().join(name)).unwrap_err();
            match &e {
                Error::Hdf5Refused {
                    object, feature, ..
                } => {
                    assert_eq!(object, "/g/x", "{name}");
                    assert_eq!(feature, want, "{name}");
                }
                other => panic!("{name}: {other}"),
            }
        }
    }

    #[test]
    fn declared_but_unwritten_data_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        make_hostile(dir.path());
        for (name, want) in [
            ("unwritten.h5", "but only 0 bytes written"),
            ("unwritten_gzip.h5", "only 0 of its 1563 chunks written"),
            ("half_written.h5", "only 8 of its 16 chunks written"),
        ] {
            let e = open_and_check(&dir.path().join(name)).unwrap_err();
            assert!(
                matches!(e, Error::Hdf5Refused { .. }) && e.to_string().contains(want),
                "{name}: {e}"
            );
        }
        // Fully written compressed data is fine, however small it is on disk.
        open_and_check(&dir.path().join("written_gzip.h5")).unwrap();
    }
}
