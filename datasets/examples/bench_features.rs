//! HumanML3D feature-extraction throughput (run by scripts/bench-features).
//!
//! usage: bench_features OUT_DIR SEQS FRAMES THREADS
//! Writes OUT_DIR/joints.npy (the AIST++ fixture as t2m-22 joints at 20 fps),
//! OUT_DIR/target.npy (the target skeleton), OUT_DIR/features.npy (features of the first
//! FRAMES frames), then times SEQS extractions of FRAMES-frame windows on THREADS threads and
//! prints one JSON line.

use std::path::{Path, PathBuf};
use std::time::Instant;

use choreo_datasets::{AistppMotion, FeatureOptions, extract_features, resample_joints, write_npy};
use ndarray::{Array2, s};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    if args.len() != 5 {
        return Err("usage: bench_features OUT_DIR SEQS FRAMES THREADS".into());
    }
    let out = PathBuf::from(&args[1]);
    let (seqs, frames, threads): (usize, usize, usize) =
        (args[2].parse()?, args[3].parse()?, args[4].parse()?);
    let pkl = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/fixtures/motion/aistpp_gBR_sBM_cAll_d04_mBR0_ch01.pkl");
    let j = AistppMotion::read(&pkl)?.joints();
    let j = resample_joints(&j, 60.0, 20.0)?
        .slice(s![.., ..22, ..])
        .to_owned();
    if j.shape()[0] < frames {
        return Err(format!(
            "fixture has {} frames at 20 fps, fewer than {frames}",
            j.shape()[0]
        )
        .into());
    }
    write_npy(&out.join("joints.npy"), j.view().into_dyn())?;
    let opts = FeatureOptions::default();
    let tgt = opts.target_offsets.unwrap_or_default();
    let tgt = Array2::from_shape_fn((22, 3), |(a, b)| tgt[a][b]);
    write_npy(&out.join("target.npy"), tgt.view().into_dyn())?;
    let first = extract_features(j.slice(s![..frames, .., ..]), &opts)?;
    write_npy(&out.join("features.npy"), first.features.view().into_dyn())?;

    let starts = j.shape()[0] - frames + 1;
    let per = seqs / threads.max(1);
    let t0 = Instant::now();
    std::thread::scope(|sc| {
        for w in 0..threads.max(1) {
            let (j, opts) = (&j, &opts);
            sc.spawn(move || {
                for i in 0..per {
                    let st = (w * per + i) % starts;
                    let f = extract_features(j.slice(s![st..st + frames, .., ..]), opts);
                    assert!(f.is_ok());
                }
            });
        }
    });
    let dt = t0.elapsed().as_secs_f64();
    let done = per * threads.max(1);
    println!(
        "{{\"rust_seqs_per_s\": {:.1}, \"seqs\": {done}, \"seconds\": {dt:.4}, \"threads\": {threads}}}",
        done as f64 / dt
    );
    Ok(())
}
