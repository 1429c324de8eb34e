//! In-process timing of the audio front end, for `scripts/bench-mel`.
//!
//! `cargo run --release -p choreo-dsp --example bench_mel -- REPS FILE...` prints one JSON line
//! per file: min/median seconds of the whole pipeline (`load_log_mel`: decode on one thread,
//! resample + mel on the other), of decoding alone, and of the mel stage alone (16 kHz PCM →
//! log-mel), plus the per-stage split of the fastest pipeline run.

use std::path::Path;
use std::time::Instant;

use choreo_dsp::{DecodeOptions, MelOptions, decode_file, load_log_mel, log_mel, resample_to};

fn stats(mut v: Vec<f64>) -> (f64, f64) {
    v.sort_by(f64::total_cmp);
    (v[0], v[v.len() / 2])
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let reps: usize = args
        .next()
        .ok_or("usage: bench_mel REPS FILE...")?
        .parse()?;
    let decode = DecodeOptions::default();
    let mel = MelOptions::default();
    for file in args {
        let path = Path::new(&file);
        // Warm-up (page cache, FFT plans).
        let _ = load_log_mel(path, &decode, &mel)?;
        let mut pipeline = Vec::new();
        let mut split = None;
        for _ in 0..reps {
            let (_, s) = load_log_mel(path, &decode, &mel)?;
            if split
                .as_ref()
                .is_none_or(|b: &choreo_dsp::Stats| s.total_s < b.total_s)
            {
                split = Some(s);
            }
            pipeline.push(s.total_s);
        }
        let mut dec = Vec::new();
        let mut audio = None;
        for _ in 0..reps {
            let t = Instant::now();
            let a = decode_file(path, &decode)?;
            dec.push(t.elapsed().as_secs_f64());
            audio = Some(a);
        }
        let audio = audio.ok_or("no repetitions")?;
        let y = resample_to(&audio.samples, audio.sample_rate, 16_000)?;
        let mut mel_only = Vec::new();
        for _ in 0..reps {
            let t = Instant::now();
            let m = log_mel(&y, &mel)?;
            mel_only.push(t.elapsed().as_secs_f64());
            std::hint::black_box(m);
        }
        let (pmin, pmed) = stats(pipeline);
        let (dmin, dmed) = stats(dec);
        let (mmin, mmed) = stats(mel_only);
        let s = split.ok_or("no repetitions")?;
        println!(
            "{{\"file\":\"{file}\",\"pipeline_min\":{pmin:.5},\"pipeline_median\":{pmed:.5},\"decode_min\":{dmin:.5},\"decode_median\":{dmed:.5},\"mel_min\":{mmin:.5},\"mel_median\":{mmed:.5},\"best_split\":{{\"decode_s\":{:.5},\"resample_s\":{:.5},\"mel_s\":{:.5},\"total_s\":{:.5}}},\"frames\":{}}}",
            s.decode_s, s.resample_s, s.mel_s, s.total_s, s.frames
        );
    }
    Ok(())
}
