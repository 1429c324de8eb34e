//! How far a motion file is from a rigid skeleton, before and after `fit_rigid_pose`.
//!
//! usage: rigid_spans IN.h5
//! Prints one JSON line: for the shoulder (collar) span (13–14, SMPL `linshoulder`–`rinshoulder`), the hip span (1–2) and the worst of every
//! joint–child and sibling–sibling distance of the skeleton, the range (max − min over frames, m)
//! before and after the fit, the count of frames whose shoulder or hip span is more than 1 mm off
//! its median before the fit, and the largest distance any joint moved.

use std::path::Path;

use choreo_datasets::{fit_rigid_pose, read_motion_file};
use ndarray::{Array3, Axis};

fn span(j: &Array3<f32>, a: usize, b: usize) -> Vec<f32> {
    j.axis_iter(Axis(0))
        .map(|f| {
            (0..3)
                .map(|c| (f[[a, c]] - f[[b, c]]).powi(2))
                .sum::<f32>()
                .sqrt()
        })
        .collect()
}

fn range(v: &[f32]) -> f32 {
    v.iter().cloned().fold(f32::MIN, f32::max) - v.iter().cloned().fold(f32::MAX, f32::min)
}

fn frames_off_median(v: &[f32], tol: f32) -> Vec<usize> {
    let mut s = v.to_vec();
    s.sort_by(f32::total_cmp);
    let med = s[s.len() / 2];
    (0..v.len()).filter(|f| (v[*f] - med).abs() > tol).collect()
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    if args.len() != 2 {
        return Err("usage: rigid_spans IN.h5".into());
    }
    let m = read_motion_file(Path::new(&args[1]))?;
    let fit = fit_rigid_pose(&m.skeleton, m.joints.view())?;
    let parents = m.skeleton.parents();
    let mut pairs = Vec::new();
    for k in 0..parents.len() {
        let cs: Vec<usize> = (0..parents.len())
            .filter(|c| parents[*c] == k as i32)
            .collect();
        for (i, a) in cs.iter().enumerate() {
            pairs.push((k, *a));
            pairs.extend(cs[i + 1..].iter().map(|b| (*a, *b)));
        }
    }
    let worst = |j: &Array3<f32>| {
        pairs
            .iter()
            .map(|(a, b)| range(&span(j, *a, *b)))
            .fold(0.0, f32::max)
    };
    let mut off: Vec<usize> = frames_off_median(&span(&m.joints, 13, 14), 1e-3);
    off.extend(frames_off_median(&span(&m.joints, 1, 2), 1e-3));
    off.sort_unstable();
    off.dedup();
    let moved = m
        .joints
        .iter()
        .zip(fit.joints.iter())
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    println!(
        "{{\"frames\": {}, \"shoulder_span_range_m\": [{}, {}], \"hip_span_range_m\": [{}, {}], \"worst_rigid_pair_range_m\": [{}, {}], \"frames_span_off_median_over_1mm\": {}, \"max_joint_move_m\": {}}}",
        m.joints.shape()[0],
        range(&span(&m.joints, 13, 14)),
        range(&span(&fit.joints, 13, 14)),
        range(&span(&m.joints, 1, 2)),
        range(&span(&fit.joints, 1, 2)),
        worst(&m.joints),
        worst(&fit.joints),
        off.len(),
        moved
    );
    Ok(())
}
