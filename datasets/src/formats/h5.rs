//! HDF5 helpers every file of this crate goes through: one way to open, to write attributes,
//! and to check a file before reading it.
//!
//! An HDF5 file can point outside itself (external and soft links, external raw storage,
//! virtual datasets mapping other files), can declare datasets far larger than what it stores
//! (the library then fabricates fill values), and can make libhdf5 itself misbehave: a chunk
//! stored shorter than its size is read past its end, a compressed chunk inflates to whatever
//! it holds (a 3 MB chunk to 3.5 GB), a chunk may be declared far larger than its dataset, and
//! a filter libhdf5 does not know makes it search a plugin directory. [`open_checked`] refuses
//! what leads outside the file and every filter but deflate, shuffle and Fletcher-32, in the
//! whole file, before anything is read; [`check_readable`] refuses, per dataset, shapes over the
//! element cap ([`crate::limits`]), data that was declared but never written, chunks larger than
//! their dataset, and chunks whose stored bytes do not decode to exactly their size (inflated
//! here with a bound first). Plugin loading is turned off for the whole process.
//!
//! Supported libhdf5: 1.10.5 (the first with chunk queries) up to 1.14.x; Debian 12's 1.10.8 is
//! what CI uses.

use std::path::Path;

use hdf5::dataset::Layout;
use hdf5::filters::Filter;
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
    disable_plugins();
    let mut builder = hdf5::File::with_options();
    builder.with_fapl(|p| p.fclose_degree(hdf5::file::FileCloseDegree::Strong));
    builder
}

/// The builder for files this crate writes: [`h5_file`] without HDF5's file lock. Every write
/// goes to a private temporary name, renamed into place once complete, so the lock guards
/// nothing; and libhdf5 opens without close-on-exec, so a child forked by another thread holds a
/// copy of the descriptor and its lock until its exec (or, if it never execs or is not ours,
/// for its life), and a reader of the finished file then fails with "unable to lock file".
pub(crate) fn h5_writer() -> hdf5::FileBuilder {
    let mut builder = h5_file();
    builder.with_fapl(|p| p.file_locking(false));
    builder
}

/// Open an HDF5 file for reading after checking that nothing in it leads outside it: every link
/// is a hard link, no dataset has external storage or a virtual layout.
pub(crate) fn open_checked(path: &Path) -> Result<hdf5::File> {
    // The system's own reason ("No such file or directory", "Permission denied"), not a
    // kind's generic text ("entity not found").
    match std::fs::metadata(path) {
        Ok(m) if m.is_file() => {}
        Ok(_) => return Err(Error::invalid(path, "not a regular file")),
        Err(source) => {
            return Err(Error::Io {
                path: path.to_path_buf(),
                source,
            });
        }
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
    let filters = dcpl
        .get_filters()
        .map_err(|e| refused(path, object, format!("an unreadable filter pipeline ({e})")))?;
    if let Some(f) = filters.iter().find(|f| !filter_allowed(f)) {
        return Err(refused(
            path,
            object,
            format!("the HDF5 filter {} ({f:?})", f.id()),
        ));
    }
    Ok(())
}

/// The filters a dataset may use: the ones built into libhdf5 that h5py's
/// `compression="gzip"`, `shuffle=True` and `fletcher32=True` write. Every other one (szip,
/// n-bit, scale-offset, any plugin's id) is refused, so libhdf5 never runs code choreod has
/// not bounded ([`check_chunks`] inflates deflate chunks itself first).
fn filter_allowed(f: &Filter) -> bool {
    matches!(f, Filter::Deflate(_) | Filter::Shuffle | Filter::Fletcher32)
}

/// Turn libhdf5's dynamic filter plugins off for the process (once): a file naming a filter it
/// does not know would otherwise make it search `HDF5_PLUGIN_PATH` (or its default directory)
/// and load and run any shared library found there.
fn disable_plugins() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        #[allow(unsafe_code)] // FFI: the one call that turns plugin loading off.
        // SAFETY: `H5PLset_loading_state(unsigned int)` takes the mask by value and only sets a
        // global of the library; `hdf5::sync::sync` initialises the library first and holds its
        // lock. (hdf5-sys declares the argument as a pointer; the C signature is used here.)
        let status = hdf5::sync::sync(|| unsafe { ffi::H5PLset_loading_state(0) });
        if status < 0 {
            tracing::warn!("libhdf5 refused to turn filter plugin loading off");
        }
    });
}

/// The libhdf5 calls `hdf5` and `hdf5-sys` do not offer as needed.
mod ffi {
    #[allow(unsafe_code)] // FFI declaration, see `disable_plugins`.
    unsafe extern "C" {
        /// `herr_t H5PLset_loading_state(unsigned int plugin_control_mask)` (H5PLpublic.h).
        pub(super) fn H5PLset_loading_state(
            plugin_control_mask: std::ffi::c_uint,
        ) -> hdf5_sys::h5::herr_t;
    }
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
            // libhdf5 allocates a whole chunk for every chunk it reads.
            let item = ds.dtype().map_err(h5_err(path))?.size() as u64;
            let chunk_values = chunk.iter().try_fold(1u64, |a, c| a.checked_mul(*c as u64));
            let chunk_bytes = chunk_values.and_then(|v| v.checked_mul(item));
            let data_bytes = n as u64 * item;
            if chunk_bytes.is_none_or(|b| b > data_bytes.max(MAX_SMALL_CHUNK_BYTES)) {
                return Err(refused(
                    path,
                    &object,
                    format!(
                        "chunks of {chunk:?} for data of {shape:?} (a chunk may exceed its \
                         dataset only up to {MAX_SMALL_CHUNK_BYTES} bytes)"
                    ),
                ));
            }
            let grid: Vec<usize> = shape
                .iter()
                .zip(&chunk)
                .map(|(d, c)| d.div_ceil(*c))
                .collect();
            let needed: usize = grid.iter().product();
            if needed > MAX_CHUNKS {
                return Err(refused(
                    path,
                    &object,
                    format!("{needed} chunks (at most {MAX_CHUNKS})"),
                ));
            }
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
            check_chunks(path, ds, &object, &chunk, &grid, chunk_bytes.unwrap_or(0))?;
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

/// A chunk may hold more than its dataset (an extendable dataset shorter than one chunk, as
/// `/motion/joints` of a short motion) up to this size: h5py's automatic chunks stay below 1 MiB.
const MAX_SMALL_CHUNK_BYTES: u64 = 1 << 20;
/// Most chunks in one dataset: each is looked up before reading (a 20-minute dance has 563 of
/// `/motion/joints`; h5py's automatic chunks of at least 8 KiB give 65,536 for 512 MiB).
const MAX_CHUNKS: usize = 1 << 20;

/// Check every chunk of a chunked dataset before libhdf5 reads it: it is stored inside the
/// file, and its stored bytes decode to exactly `chunk_bytes`. Unfiltered chunks must be stored
/// at their full size (libhdf5 would read past a shorter one); filtered chunks are read raw and
/// decoded here, inflating with a bound of `chunk_bytes`, so a decompression bomb fails after
/// at most one chunk's worth of output.
fn check_chunks(
    path: &Path,
    ds: &hdf5::Dataset,
    object: &str,
    chunk: &[usize],
    grid: &[usize],
    chunk_bytes: u64,
) -> Result<()> {
    let filters = ds
        .dcpl()
        .map_err(h5_err(path))?
        .get_filters()
        .map_err(h5_err(path))?;
    let file_bytes = std::fs::metadata(path)
        .map_err(crate::error::io_err(path))?
        .len();
    let needed: usize = grid.iter().product();
    let mut index = vec![0usize; grid.len()];
    for _ in 0..needed {
        let offset: Vec<u64> = index
            .iter()
            .zip(chunk)
            .map(|(i, c)| (i * c) as u64)
            .collect();
        let at = || format!("the chunk at {offset:?}");
        let (mask, stored) = chunk_lookup(ds, &offset)
            .ok_or_else(|| refused(path, object, format!("{} that cannot be located", at())))?;
        if stored > file_bytes {
            return Err(refused(
                path,
                object,
                format!(
                    "{} stored as {stored} bytes in a file of {file_bytes}",
                    at()
                ),
            ));
        }
        let applied: Vec<&Filter> = filters
            .iter()
            .enumerate()
            .filter(|(i, _)| mask & (1 << i) == 0)
            .map(|(_, f)| f)
            .collect();
        let decoded = if applied.is_empty() {
            stored
        } else {
            let raw = read_raw_chunk(ds, &offset, stored as usize)
                .ok_or_else(|| refused(path, object, format!("{} that cannot be read", at())))?;
            decoded_size(&raw, &applied, chunk_bytes)
                .map_err(|why| refused(path, object, format!("{} {why}", at())))?
        };
        if decoded != chunk_bytes {
            return Err(refused(
                path,
                object,
                format!("{} holding {decoded} bytes of its {chunk_bytes}", at()),
            ));
        }
        // Next chunk coordinate, last axis fastest.
        for (i, n) in index.iter_mut().zip(grid).rev() {
            *i += 1;
            if *i < *n {
                break;
            }
            *i = 0;
        }
    }
    Ok(())
}

/// The size `raw` (a chunk as stored) has after undoing `applied` (the filters it went through,
/// in pipeline order), inflating at most `limit` bytes (plus Fletcher-32 checksums).
fn decoded_size(raw: &[u8], applied: &[&Filter], limit: u64) -> std::result::Result<u64, String> {
    let mut data: Option<Vec<u8>> = None;
    let mut len = raw.len();
    let bound = limit as usize + 4 * applied.len();
    for f in applied.iter().rev() {
        match f {
            Filter::Fletcher32 => len = len.saturating_sub(4),
            Filter::Shuffle => {}
            Filter::Deflate(_) => {
                let input = data.as_deref().unwrap_or(raw);
                let out = miniz_oxide::inflate::decompress_to_vec_zlib_with_limit(
                    &input[..len.min(input.len())],
                    bound,
                )
                .map_err(|e| match e.status {
                    miniz_oxide::inflate::TINFLStatus::HasMoreOutput => {
                        format!("inflating to more than its {limit} bytes")
                    }
                    status => format!("that does not inflate ({status:?})"),
                })?;
                len = out.len();
                data = Some(out);
            }
            other => return Err(format!("filtered by {other:?}")),
        }
    }
    Ok(len as u64)
}

/// The filter mask and stored size of the chunk starting at `offset`; `None` when libhdf5
/// cannot locate it or it was never written.
#[allow(unsafe_code)] // FFI: the chunk index query hdf5 does not wrap by coordinate.
fn chunk_lookup(ds: &hdf5::Dataset, offset: &[u64]) -> Option<(u32, u64)> {
    let (mut mask, mut addr, mut size) = (0u32, 0u64, 0u64);
    // SAFETY: `offset` has one entry per dimension of the dataset (the caller builds it from
    // its chunk grid); the out-pointers point at live locals; the lock is libhdf5's.
    let status = hdf5::sync::sync(|| unsafe {
        hdf5_sys::h5d::H5Dget_chunk_info_by_coord(
            ds.id(),
            offset.as_ptr(),
            &mut mask,
            &mut addr,
            &mut size,
        )
    });
    (status >= 0 && addr != hdf5_sys::h5::HADDR_UNDEF).then_some((mask, size))
}

/// The bytes of the chunk at `offset` as stored (no filter run), `stored` long.
#[allow(unsafe_code)] // FFI: raw chunk reads are not wrapped by hdf5.
fn read_raw_chunk(ds: &hdf5::Dataset, offset: &[u64], stored: usize) -> Option<Vec<u8>> {
    let mut buf = vec![0u8; stored];
    let mut mask = 0u32;
    // SAFETY: libhdf5 writes the chunk's stored size, which `chunk_lookup` just reported as
    // `stored`, into `buf` of that length; `offset` has one entry per dimension.
    let status = hdf5::sync::sync(|| unsafe {
        hdf5_sys::h5d::H5Dread_chunk(
            ds.id(),
            hdf5_sys::h5p::H5P_DEFAULT,
            offset.as_ptr(),
            &mut mask,
            buf.as_mut_ptr().cast(),
        )
    });
    (status >= 0).then_some(buf)
}

/// A string as an HDF5 variable-length UTF-8 value.
pub(crate) fn vlu(path: &Path, s: &str) -> Result<VarLenUnicode> {
    s.parse::<VarLenUnicode>().map_err(|_| {
        Error::invalid(
            path,
            format!(
                "string {} cannot be stored (contains NUL?)",
                choreo_dsp::quote(s)
            ),
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
import sys, os, zlib, h5py, numpy as np
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
with mk("gzip_shuffle_fletcher.h5") as f:
    f.create_dataset("g/x", data=np.arange(72000, dtype=np.float32).reshape(1000, 24, 3), chunks=(64, 24, 3), compression="gzip", shuffle=True, fletcher32=True)
# One chunk of (720, 24, 3) float32 = 207,360 bytes, written raw by write_direct_chunk.
def one_chunk(f, chunks=(720, 24, 3), **kw):
    return f.create_dataset("g/x", shape=(720, 24, 3), maxshape=(None, 24, 3), chunks=chunks, dtype=np.float32, **kw)
with mk("short_chunk.h5") as f:
    one_chunk(f).id.write_direct_chunk((0, 0, 0), bytes(10))
with mk("bomb.h5") as f:
    one_chunk(f, compression="gzip").id.write_direct_chunk((0, 0, 0), zlib.compress(bytes(10 << 20)))
with mk("huge_chunk.h5") as f:
    one_chunk(f, chunks=(4000000, 24, 3), compression="gzip").id.write_direct_chunk((0, 0, 0), zlib.compress(bytes(207360)))
with mk("unknown_filter.h5") as f:
    dcpl = h5py.h5p.create(h5py.h5p.DATASET_CREATE)
    dcpl.set_chunk((720, 24, 3))
    dcpl.set_filter(32123, h5py.h5z.FLAG_OPTIONAL, ())
    space = h5py.h5s.create_simple((720, 24, 3), (h5py.h5s.UNLIMITED, 24, 3))
    x = h5py.h5d.create(f["g"].id, b"x", h5py.h5t.IEEE_F32LE, space, dcpl=dcpl)
    x.write_direct_chunk((0, 0, 0), bytes(207360), filter_mask=0)
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

    #[test]
    fn chunks_that_do_not_decode_to_their_size_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        make_hostile(dir.path());
        for (name, want) in [
            (
                "short_chunk.h5",
                "the chunk at [0, 0, 0] holding 10 bytes of its 207360",
            ),
            (
                "bomb.h5",
                "the chunk at [0, 0, 0] inflating to more than its 207360 bytes",
            ),
            (
                "huge_chunk.h5",
                "chunks of [4000000, 24, 3] for data of [720, 24, 3]",
            ),
            ("unknown_filter.h5", "the HDF5 filter 32123"),
        ] {
            let e = open_and_check(&dir.path().join(name)).unwrap_err();
            assert!(
                matches!(e, Error::Hdf5Refused { .. }) && e.to_string().contains(want),
                "{name}: {e}"
            );
        }
        // Every allowed filter at once, with edge chunks (1000 = 15 × 64 + 40), reads back.
        let p = dir.path().join("gzip_shuffle_fletcher.h5");
        open_and_check(&p).unwrap();
        let x: ndarray::Array3<f32> = open_checked(&p)
            .unwrap()
            .dataset("g/x")
            .unwrap()
            .read()
            .unwrap();
        assert_eq!(x[[999, 23, 2]], 71999.0);
    }

    #[test]
    fn no_filter_plugin_is_searched_for() {
        let dir = tempfile::tempdir().unwrap();
        make_hostile(dir.path());
        // Read past the checks: libhdf5 itself must not look for the unknown filter's plugin
        // (with loading on, its error names the plugin directory it searched).
        let f = h5_file()
            .open(dir.path().join("unknown_filter.h5"))
            .unwrap();
        let e = f.dataset("g/x").unwrap().read_raw::<f32>().unwrap_err();
        let msg = e.to_string();
        assert!(!msg.contains("directory"), "{msg}");
    }

    #[test]
    fn inflation_stops_at_the_bound() {
        let zeros = |n: usize| miniz_oxide::deflate::compress_to_vec_zlib(&vec![0u8; n], 6);
        let deflate = Filter::Deflate(6);
        assert_eq!(decoded_size(&zeros(1000), &[&deflate], 1000), Ok(1000));
        let e = decoded_size(&zeros(100 << 20), &[&deflate], 1000).unwrap_err();
        assert_eq!(e, "inflating to more than its 1000 bytes");
        assert!(decoded_size(b"not zlib", &[&deflate], 1000).is_err());
        // Fletcher-32 (last in the pipeline) strips its 4 checksum bytes before inflating.
        let mut stored = zeros(1000);
        stored.extend_from_slice(&[1, 2, 3, 4]);
        let shuffled = [&Filter::Shuffle, &deflate, &Filter::Fletcher32];
        assert_eq!(decoded_size(&stored, &shuffled, 1000), Ok(1000));
    }
}
