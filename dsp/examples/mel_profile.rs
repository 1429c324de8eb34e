//! Where the mel stage spends its time (single thread): FFT, filterbank, log.
use std::time::Instant;

use choreo_dsp::{FrameAnalyzer, MelOptions};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let opts = MelOptions::default();
    let mut a = FrameAnalyzer::new(&opts)?;
    let frame: Vec<f32> = (0..2048)
        .map(|i| ((i * 7919 % 1000) as f32 / 500.0) - 1.0)
        .collect();
    let mut out = vec![0.0f32; 80];
    let n = 20_000;
    for _ in 0..1000 {
        a.mel_power(&frame, &mut out);
    }
    let t = Instant::now();
    for _ in 0..n {
        a.mel_power(&frame, &mut out);
    }
    let p = t.elapsed().as_secs_f64() / n as f64;
    let t = Instant::now();
    for _ in 0..n {
        a.log_mel(&frame, &mut out);
    }
    let l = t.elapsed().as_secs_f64() / n as f64;
    let t = Instant::now();
    let _a2 = FrameAnalyzer::new(&opts)?;
    println!(
        "FrameAnalyzer::new {:.1} us",
        t.elapsed().as_secs_f64() * 1e6
    );
    let big = ndarray::Array2::<f32>::zeros((5626, 80));
    let t = Instant::now();
    let tr = big.t().as_standard_layout().into_owned();
    println!("transpose {:.2} ms", t.elapsed().as_secs_f64() * 1e3);
    std::hint::black_box(tr);
    let y: Vec<f32> = (0..16_000 * 180)
        .map(|i| ((i * 7919 % 1000) as f32 / 500.0) - 1.0)
        .collect();
    let t = Instant::now();
    let m = choreo_dsp::log_mel(&y, &opts)?;
    let whole = t.elapsed().as_secs_f64();
    println!(
        "mel_power {:.2} us/frame, log_mel {:.2} us/frame, whole 180 s: {:.4} s ({} frames)",
        p * 1e6,
        l * 1e6,
        whole,
        m.ncols()
    );
    Ok(())
}
