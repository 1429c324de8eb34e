//! Reader of the golden `.npz` fixtures made by `make_fact35.py` (numpy's zip of `.npy`
//! files; little-endian `<f4`, `<f8`, `<i8` arrays in C order).
#![allow(clippy::unwrap_used)] // test helpers: a panic is a failed test

use std::collections::HashMap;
use std::io::Read;
use std::path::{Path, PathBuf};

/// `dsp/tests/golden/fact35`.
pub fn dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests")
        .join("golden")
        .join("fact35")
}

/// One array: shape and values widened to f64.
#[derive(Debug, Clone)]
pub struct Array {
    pub shape: Vec<usize>,
    pub data: Vec<f64>,
}

impl Array {
    pub fn f32(&self) -> Vec<f32> {
        self.data.iter().map(|&x| x as f32).collect()
    }

    pub fn usize(&self) -> Vec<usize> {
        self.data.iter().map(|&x| x as usize).collect()
    }

    pub fn scalar(&self) -> f64 {
        assert_eq!(self.data.len(), 1, "not a scalar: {:?}", self.shape);
        self.data[0]
    }
}

/// All arrays of `name` (without `.npz`).
pub fn load(name: &str) -> HashMap<String, Array> {
    let path = dir().join(format!("{name}.npz"));
    let file = std::fs::File::open(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let mut zip = zip::ZipArchive::new(file).unwrap();
    let mut out = HashMap::new();
    for i in 0..zip.len() {
        let mut entry = zip.by_index(i).unwrap();
        let key = entry.name().trim_end_matches(".npy").to_string();
        let mut bytes = Vec::new();
        entry.read_to_end(&mut bytes).unwrap();
        out.insert(key, parse_npy(&bytes));
    }
    out
}

fn parse_npy(bytes: &[u8]) -> Array {
    assert_eq!(&bytes[..6], b"\x93NUMPY");
    let (hlen, start) = if bytes[6] == 1 {
        (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10)
    } else {
        (
            u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
            12,
        )
    };
    let header = std::str::from_utf8(&bytes[start..start + hlen]).unwrap();
    let fortran = header.contains("'fortran_order': True");
    let s = header.find("'shape': (").unwrap() + 10;
    let e = s + header[s..].find(')').unwrap();
    let shape: Vec<usize> = header[s..e]
        .split(',')
        .map(str::trim)
        .filter(|x| !x.is_empty())
        .map(|x| x.parse().unwrap())
        .collect();
    let body = &bytes[start + hlen..];
    let data: Vec<f64> = if header.contains("'<f4'") {
        body.chunks_exact(4)
            .map(|c| f64::from(f32::from_le_bytes(c.try_into().unwrap())))
            .collect()
    } else if header.contains("'<f8'") {
        body.chunks_exact(8)
            .map(|c| f64::from_le_bytes(c.try_into().unwrap()))
            .collect()
    } else if header.contains("'<i8'") {
        body.chunks_exact(8)
            .map(|c| i64::from_le_bytes(c.try_into().unwrap()) as f64)
            .collect()
    } else {
        panic!("unsupported dtype: {header}");
    };
    assert_eq!(data.len(), shape.iter().product::<usize>(), "{header}");
    // librosa returns some arrays in Fortran order; hand every array out in C order.
    let data = match (&shape[..], fortran) {
        ([rows, cols], true) => (0..rows * cols)
            .map(|i| data[(i % cols) * rows + i / cols])
            .collect(),
        _ => data,
    };
    Array { shape, data }
}

/// Largest |a − b| over each row of two `(rows, cols)` arrays, divided by that row's range in
/// `want`; returns the worst row and its ratio.
pub fn worst_row_error(got: &[f64], want: &[f64], rows: usize) -> (usize, f64) {
    assert_eq!(got.len(), want.len(), "lengths differ");
    let cols = want.len() / rows;
    (0..rows)
        .map(|r| {
            let w = &want[r * cols..(r + 1) * cols];
            let g = &got[r * cols..(r + 1) * cols];
            let lo = w.iter().copied().fold(f64::INFINITY, f64::min);
            let hi = w.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            let range = (hi - lo).max(1e-12);
            let err = g
                .iter()
                .zip(w)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f64::max);
            (r, err / range)
        })
        .fold((0, 0.0), |b, x| if x.1 > b.1 { x } else { b })
}
