//! The one `.npy` writer (format version 1.0, little-endian float32, C order), written
//! atomically through [`crate::atomic`]. Format: `numpy:numpy/lib/format.py` (magic
//! `\x93NUMPY`, u16 header length, header padded with spaces and a newline so that data starts
//! at a multiple of 64 bytes).

use std::io::Write;
use std::path::Path;

use crate::error::{Error, Result};

/// Write `data` (C order, `shape`) as a float32 `.npy` at `path`, atomically.
pub fn write_npy_f32(path: &Path, shape: &[usize], data: &[f32]) -> Result<()> {
    let expected = shape.iter().product::<usize>();
    if expected != data.len() {
        return Err(Error::ShapeMismatch {
            shape: shape.to_vec(),
            expected,
            got: data.len(),
        });
    }
    crate::atomic::write_atomic_with(&crate::atomic::temp_path(path), path, |w| {
        write_npy_to(w, shape, data)
    })
    .map_err(|io| Error::Write {
        path: path.to_path_buf(),
        io,
    })
}

/// Write `data` (C order, `shape`, whose product must be its length) as float32 `.npy` bytes
/// to `w` (an `.npz` member, or the file of [`write_npy_f32`]).
pub fn write_npy_to(w: &mut dyn Write, shape: &[usize], data: &[f32]) -> std::io::Result<()> {
    if shape.iter().product::<usize>() != data.len() {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            "npy shape does not match the data",
        ));
    }
    let shape_txt = match shape {
        [one] => format!("({one},)"),
        _ => format!(
            "({})",
            shape
                .iter()
                .map(usize::to_string)
                .collect::<Vec<_>>()
                .join(", ")
        ),
    };
    let mut header = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': {shape_txt}, }}");
    // magic(6) + version(2) + len(2) + header + '\n' must be a multiple of 64.
    let total = 10 + header.len() + 1;
    header.push_str(&" ".repeat(total.next_multiple_of(64) - total));
    header.push('\n');
    let hlen = u16::try_from(header.len()).map_err(|_| {
        std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            "npy header longer than 65535 bytes",
        )
    })?;
    w.write_all(b"\x93NUMPY\x01\x00")?;
    w.write_all(&hlen.to_le_bytes())?;
    w.write_all(header.as_bytes())?;
    for chunk in data.chunks(16 * 1024) {
        let bytes: Vec<u8> = chunk.iter().flat_map(|v| v.to_le_bytes()).collect();
        w.write_all(&bytes)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_is_aligned_and_data_follows() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("x.npy");
        write_npy_f32(&p, &[2, 3], &[0.0, 1.0, 2.0, 3.0, 4.0, 5.5]).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        assert_eq!(&bytes[..8], b"\x93NUMPY\x01\x00");
        let hlen = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
        assert_eq!((10 + hlen) % 64, 0);
        let header = std::str::from_utf8(&bytes[10..10 + hlen]).unwrap();
        assert!(header.contains("'shape': (2, 3)"), "{header}");
        assert_eq!(bytes.len(), 10 + hlen + 24);
        let last = f32::from_le_bytes(bytes[bytes.len() - 4..].try_into().unwrap());
        assert_eq!(last, 5.5);
        assert!(write_npy_f32(&p, &[2, 2], &[1.0]).is_err());
        // No temporary file is left behind.
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }
}
