//! Shared helpers for the dsp integration tests: fixture paths and a tiny float32 `.npy` reader.
#![allow(dead_code)] // each test binary uses a subset of the helpers
#![allow(clippy::unwrap_used)] // test helpers: a panic is a failed test

use std::path::{Path, PathBuf};

/// `<workspace>/../shared/fixtures`.
pub fn fixtures() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .join("..")
        .join("shared")
        .join("fixtures")
}

/// The reference prefix of a fixture clip, e.g. `vibe_ace_22k_mono`.
pub fn reference(name: &str, ext: &str) -> PathBuf {
    fixtures().join("reference").join(format!("{name}.{ext}"))
}

/// The three clips with librosa references.
pub const CLIPS: [&str; 3] = [
    "hungarian_dance_5_44k_stereo",
    "vibe_ace_22k_mono",
    "vibe_ace_44k_stereo",
];

/// Read a little-endian float32 C-order `.npy` (version 1/2): (shape, data).
pub fn read_npy_f32(path: &Path) -> (Vec<usize>, Vec<f32>) {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    assert_eq!(&bytes[..6], b"\x93NUMPY", "{}", path.display());
    let (hlen, start) = if bytes[6] == 1 {
        (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10)
    } else {
        (
            u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
            12,
        )
    };
    let header = std::str::from_utf8(&bytes[start..start + hlen]).unwrap();
    assert!(header.contains("'<f4'"), "{header}");
    assert!(header.contains("'fortran_order': False"), "{header}");
    let s = header.find("'shape': (").unwrap() + 10;
    let e = s + header[s..].find(')').unwrap();
    let shape: Vec<usize> = header[s..e]
        .split(',')
        .map(str::trim)
        .filter(|x| !x.is_empty())
        .map(|x| x.parse().unwrap())
        .collect();
    let data: Vec<f32> = bytes[start + hlen..]
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect();
    assert_eq!(
        data.len(),
        shape.iter().product::<usize>(),
        "{}",
        path.display()
    );
    (shape, data)
}

/// Reference JSON of a clip.
pub fn reference_json(name: &str) -> serde_json::Value {
    let text = std::fs::read_to_string(reference(name, "json")).unwrap();
    serde_json::from_str(&text).unwrap()
}

/// Percentile (0..=100) of absolute values, nearest-rank.
pub fn percentile(mut v: Vec<f32>, p: f64) -> f32 {
    v.sort_by(f32::total_cmp);
    let idx = ((p / 100.0) * (v.len() - 1) as f64).round() as usize;
    v[idx]
}
