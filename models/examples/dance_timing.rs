//! Time a music-to-dance generation on a synthetic song (no audio decoding involved):
//!
//!     cargo run --release -p choreo-models --example dance_timing -- PACKAGE_DIR SECONDS [CHUNK]
//!
//! Prints one JSON-like line: frames, windows, chunks, evaluations, ORT and total seconds.

use std::path::PathBuf;

use choreo_models::{
    DanceOptions, ModelPackage, OrtRuntime, RuntimeOptions, generate_dance, locate_library,
};
use ndarray::Array2;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let dir = PathBuf::from(
        args.get(1)
            .ok_or("usage: dance_timing PACKAGE_DIR SECONDS [CHUNK]")?,
    );
    let seconds: f64 = args.get(2).ok_or("missing SECONDS")?.parse()?;
    let ort = OrtRuntime::load(&locate_library(None))?;
    let mut package = ModelPackage::load(&dir, &RuntimeOptions::default(), &ort)?;
    let frames = (seconds * package.manifest().dance_spec()?.audio.frame_rate()) as usize + 1;
    // A 2 Hz energy pulse over a tilted spectrum: something for the music conditioning to follow.
    let mel = Array2::from_shape_fn((80, frames), |(b, f)| {
        if f % 16 < 3 {
            -20.0 - b as f32 * 0.3
        } else {
            -60.0 - b as f32 * 0.3
        }
    });
    let mut options = DanceOptions::default();
    if let Some(chunk) = args.get(3) {
        options.chunk_windows = chunk.parse()?;
    }
    let dance = generate_dance(&mut package, mel.view(), &options, &mut |_, _| {})?;
    let s = dance.stats;
    println!(
        "{{\"frames\": {}, \"windows\": {}, \"chunks\": {}, \"evaluations\": {}, \"rows\": {}, \"ort_s\": {:.3}, \"total_s\": {:.3}, \"outside_ort\": {:.3}}}",
        s.frames,
        s.windows,
        s.chunks,
        s.evaluations,
        s.rows,
        s.ort_seconds,
        s.total_seconds,
        1.0 - s.ort_seconds / s.total_seconds
    );
    Ok(())
}
