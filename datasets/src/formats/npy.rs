//! `.npy` files (NumPy format 1.0-3.0, https://numpy.org/doc/stable/reference/generated/numpy.lib.format.html):
//! a reader for little-endian f32/f64 C-order arrays. The data must be exactly what the header
//! declares (so the file holds every value) and within the element cap of [`crate::limits`].
//! [`write_npy`] hands arrays to `choreo_dsp::write_npy_f32`, the project's one `.npy` writer.

use std::collections::BTreeMap;
use std::io::Read;
use std::path::Path;

use choreo_dsp::quote;
use ndarray::{ArrayD, ArrayViewD, IxDyn};

use crate::error::{Error, Result, io_err};

/// Longest header accepted (NumPy itself writes < 1 KiB; its reader caps at 10 000 bytes).
const MAX_HEADER: usize = 65_536;
const MAGIC: &[u8; 6] = b"\x93NUMPY";

/// Read a `.npy` array of dtype `<f4` or `<f8` in C order as f32 (f64 values are rounded).
pub fn read_npy(path: &Path) -> Result<ArrayD<f32>> {
    let bytes = std::fs::read(path).map_err(io_err(path))?;
    npy_from_bytes(path, ".npy", &bytes)
}

/// Most arrays an `.npz` may hold.
const MAX_NPZ_ARRAYS: usize = 64;

/// Read every array of a NumPy `.npz` (a zip of `.npy` files, stored or deflated) as f32,
/// keyed by name without `.npy`. Each member's declared size is checked against the element
/// cap before it is inflated, and it must inflate to exactly that size.
pub fn read_npz(path: &Path) -> Result<BTreeMap<String, ArrayD<f32>>> {
    let cap = (crate::limits::max_elements() as u64) * 8 + MAX_HEADER as u64 + 16;
    read_npz_within(path, cap)
}

/// [`read_npz`] with `cap` bytes for all members together: a member may declare at most what
/// is left of it, so an archive of many small bombs inflates no more than one could.
fn read_npz_within(path: &Path, cap: u64) -> Result<BTreeMap<String, ArrayD<f32>>> {
    let file = std::fs::File::open(path).map_err(io_err(path))?;
    let mut zip = zip::ZipArchive::new(file)
        .map_err(|e| Error::invalid(path, format!("not an .npz (zip) file: {e}")))?;
    if zip.len() > MAX_NPZ_ARRAYS {
        return Err(Error::invalid(
            path,
            format!(
                ".npz holds {} members, more than {MAX_NPZ_ARRAYS}",
                zip.len()
            ),
        ));
    }
    let mut left = cap;
    let mut out = BTreeMap::new();
    for i in 0..zip.len() {
        let mut member = zip
            .by_index(i)
            .map_err(|e| Error::invalid(path, format!(".npz member {i}: {e}")))?;
        let name = member.name().to_string();
        let Some(key) = name.strip_suffix(".npy") else {
            return Err(Error::invalid(
                path,
                format!(".npz member {} is not an .npy", quote(&name)),
            ));
        };
        let size = member.size();
        if size > left {
            return Err(Error::invalid(
                path,
                format!(
                    ".npz member {} declares {size} bytes, more than the {left} left of the \
                     {cap} its members may hold together",
                    quote(&name)
                ),
            ));
        }
        left -= size;
        let mut bytes = Vec::with_capacity(size as usize);
        (&mut member)
            .take(size + 1)
            .read_to_end(&mut bytes)
            .map_err(|e| Error::invalid(path, format!(".npz member {}: {e}", quote(&name))))?;
        if bytes.len() as u64 != size {
            return Err(Error::invalid(
                path,
                format!(".npz member {} is not the size it declares", quote(&name)),
            ));
        }
        let what = format!(".npz member {}", quote(&name));
        out.insert(key.to_string(), npy_from_bytes(path, &what, &bytes)?);
    }
    Ok(out)
}

/// Write float32 arrays as an uncompressed `.npz` (numpy's `np.savez` layout), atomically.
pub fn write_npz(path: &Path, arrays: &[(&str, ArrayViewD<'_, f32>)]) -> Result<()> {
    let werr = |e: std::io::Error| Error::Io {
        path: path.to_path_buf(),
        source: e,
    };
    let mut zip = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    let options = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Stored)
        .large_file(true);
    for (name, a) in arrays {
        zip.start_file(format!("{name}.npy"), options)
            .map_err(|e| werr(std::io::Error::other(e)))?;
        let a = a.as_standard_layout();
        choreo_dsp::write_npy_to(&mut zip, a.shape(), a.as_slice().unwrap_or_default())
            .map_err(werr)?;
    }
    let bytes = zip
        .finish()
        .map_err(|e| werr(std::io::Error::other(e)))?
        .into_inner();
    choreo_dsp::atomic::write_atomic(path, &bytes).map_err(werr)
}

/// Parse one `.npy` held in memory; `what` names it in messages.
fn npy_from_bytes(path: &Path, what: &str, bytes: &[u8]) -> Result<ArrayD<f32>> {
    let file_len = bytes.len() as u64;
    let pre = bytes.get(..10).ok_or_else(|| {
        Error::invalid(
            path,
            format!("{what}: not a .npy file (shorter than its preamble)"),
        )
    })?;
    if &pre[..6] != MAGIC {
        return Err(Error::invalid(
            path,
            format!("{what}: not a .npy file (bad magic)"),
        ));
    }
    let (header_len, prefix) = match pre[6] {
        1 => (usize::from(u16::from_le_bytes([pre[8], pre[9]])), 10usize),
        2 | 3 => {
            let b = bytes
                .get(10..12)
                .ok_or_else(|| Error::invalid(path, format!("{what} header truncated")))?;
            (
                u32::from_le_bytes([pre[8], pre[9], b[0], b[1]]) as usize,
                12usize,
            )
        }
        v => {
            return Err(Error::invalid(
                path,
                format!("{what} format version {v} is not supported (1-3)"),
            ));
        }
    };
    if header_len > MAX_HEADER {
        return Err(Error::invalid(
            path,
            format!("{what} header of {header_len} bytes exceeds {MAX_HEADER}"),
        ));
    }
    if (prefix + header_len) as u64 > file_len {
        return Err(Error::invalid(path, format!("{what} header truncated")));
    }
    let header = String::from_utf8_lossy(&bytes[prefix..prefix + header_len]);
    let (descr, fortran, shape) =
        parse_header(&header).map_err(|r| Error::invalid(path, format!("{what} header: {r}")))?;
    if fortran {
        return Err(Error::invalid(
            path,
            format!("{what}: Fortran-order arrays are not supported (save with C order)"),
        ));
    }
    let size = match descr.as_str() {
        "<f4" => 4,
        "<f8" => 8,
        other => {
            return Err(Error::invalid(
                path,
                format!(
                    "{what} dtype {} is not supported (float32 or float64, little-endian)",
                    quote(other)
                ),
            ));
        }
    };
    let count = crate::limits::elements(path, ".npy array", &shape)?;
    let raw = &bytes[prefix + header_len..];
    if raw.len() != count * size {
        return Err(Error::invalid(
            path,
            format!(
                "{what} shape {shape:?} of {descr} needs {} data bytes, file has {}",
                count * size,
                raw.len()
            ),
        ));
    }
    let data: Vec<f32> = if size == 4 {
        raw.chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect()
    } else {
        raw.chunks_exact(8)
            .map(|c| f64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]) as f32)
            .collect()
    };
    ArrayD::from_shape_vec(IxDyn(&shape), data).map_err(|e| Error::invalid(path, e.to_string()))
}

/// Parse `{'descr': '<f4', 'fortran_order': False, 'shape': (2, 3), }`.
fn parse_header(h: &str) -> std::result::Result<(String, bool, Vec<usize>), String> {
    let field = |key: &str| -> std::result::Result<&str, String> {
        let k = format!("'{key}':");
        let at = h.find(&k).ok_or_else(|| format!("no '{key}'"))?;
        Ok(h[at + k.len()..].trim_start())
    };
    let d = field("descr")?;
    let descr = d
        .strip_prefix('\'')
        .and_then(|r| r.split('\'').next())
        .ok_or("descr is not a string (structured dtypes are not supported)")?
        .to_owned();
    let fo = field("fortran_order")?;
    let fortran = if fo.starts_with("True") {
        true
    } else if fo.starts_with("False") {
        false
    } else {
        return Err("fortran_order is not True/False".into());
    };
    let sh = field("shape")?;
    let inner = sh
        .strip_prefix('(')
        .and_then(|r| r.split(')').next())
        .ok_or("shape is not a tuple")?;
    let mut shape = Vec::new();
    for part in inner.split(',').map(str::trim).filter(|p| !p.is_empty()) {
        let part = part.trim_end_matches('L');
        shape.push(
            part.parse::<usize>()
                .map_err(|_| format!("shape entry {} is not a size", quote(part)))?,
        );
        if shape.len() > 32 {
            return Err("more than 32 dimensions".into());
        }
    }
    Ok((descr, fortran, shape))
}

/// Write an f32 array of any layout as `.npy` (atomically, by `choreo_dsp::write_npy_f32`).
pub fn write_npy(path: &Path, a: ArrayViewD<'_, f32>) -> Result<()> {
    let a = a.as_standard_layout();
    let data = a.as_slice().unwrap_or_default();
    Ok(choreo_dsp::write_npy_f32(path, a.shape(), data)?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array3;

    #[test]
    fn round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.npy");
        let a = Array3::from_shape_fn((4, 22, 3), |(t, j, k)| (t * 66 + j * 3 + k) as f32 * 0.5)
            .into_dyn();
        write_npy(&p, a.view()).unwrap();
        assert_eq!(
            std::fs::metadata(&p).unwrap().len() % 64,
            (4 * 22 * 3 * 4) % 64
        );
        assert_eq!(read_npy(&p).unwrap(), a);
    }

    fn npy(header: &str, body: &[u8]) -> Vec<u8> {
        let mut b = MAGIC.to_vec();
        b.extend_from_slice(&[1, 0]);
        b.extend_from_slice(&(header.len() as u16).to_le_bytes());
        b.extend_from_slice(header.as_bytes());
        b.extend_from_slice(body);
        b
    }

    #[test]
    fn bad_files_give_clear_errors() {
        let dir = tempfile::tempdir().unwrap();
        let cases: Vec<(&str, Vec<u8>, &str)> = vec![
            ("magic.npy", b"PK\x03\x04 zip archive".to_vec(), "bad magic"),
            (
                "dtype.npy",
                npy(
                    "{'descr': '<i8', 'fortran_order': False, 'shape': (1,), }\n",
                    &[0; 8],
                ),
                "dtype '<i8'",
            ),
            (
                "fortran.npy",
                npy(
                    "{'descr': '<f4', 'fortran_order': True, 'shape': (2, 2), }\n",
                    &[0; 16],
                ),
                "Fortran",
            ),
            (
                "short.npy",
                npy(
                    "{'descr': '<f4', 'fortran_order': False, 'shape': (3, 2), }\n",
                    &[0; 16],
                ),
                "needs 24",
            ),
            (
                "huge.npy",
                npy(
                    "{'descr': '<f4', 'fortran_order': False, 'shape': (4000000000, 4000000000), }\n",
                    &[0; 16],
                ),
                "exceeds the limit",
            ),
            (
                "big-endian.npy",
                npy(
                    "{'descr': '>f4', 'fortran_order': False, 'shape': (1,), }\n",
                    &[0; 4],
                ),
                "'>f4'",
            ),
        ];
        for (name, bytes, want) in cases {
            let p = dir.path().join(name);
            std::fs::write(&p, bytes).unwrap();
            let e = read_npy(&p).unwrap_err().to_string();
            assert!(e.contains(name) && e.contains(want), "{name}: {e}");
        }
        // A v2 header claiming 4 GiB must be refused before allocating it.
        let mut b = MAGIC.to_vec();
        b.extend_from_slice(&[2, 0]);
        b.extend_from_slice(&u32::MAX.to_le_bytes());
        let p = dir.path().join("hdr.npy");
        std::fs::write(&p, b).unwrap();
        assert!(read_npy(&p).unwrap_err().to_string().contains("exceeds"));
    }

    /// Members are bounded together, not one by one: two arrays that each fit the cap but not
    /// both are refused before the second is inflated; with room for both they read back.
    #[test]
    fn npz_members_share_one_size_budget() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("two.npz");
        let a = ndarray::Array1::from_shape_fn(100, |i| i as f32).into_dyn();
        write_npz(&p, &[("a", a.view()), ("b", a.view())]).unwrap();
        // Each member: a 128-byte header and 400 bytes of data.
        let e = read_npz_within(&p, 700).unwrap_err().to_string();
        assert!(e.contains("b.npy") && e.contains("together"), "{e}");
        let both = read_npz_within(&p, 1056).unwrap();
        assert_eq!((both["a"].clone(), both["b"].clone()), (a.clone(), a));
    }
}
