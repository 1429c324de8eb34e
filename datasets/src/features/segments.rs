//! Content longer than a model's window: equal, evenly spaced, overlapping segments, and their
//! outputs cross-faded back into one sequence.
//!
//! Segments are stitched in HumanML3D feature space, not in joint space, because
//! - the root channels are per-frame velocities and a height: blending them and integrating once
//!   (`recover_from_ric`) gives one continuous trajectory, while joints recovered per segment
//!   each start at their own origin and heading and would have to be re-aligned first;
//! - the output's `/motion/features` and its joints then agree (joints are recovered from the
//!   stitched features), with no second feature extraction;
//! - every segment is conditioned on the same content frames where they overlap (trajectory and
//!   content latent), so the two outputs differ there only in style detail, which a linear
//!   cross-fade of root-relative positions averages without a visible seam.
//!
//! The default overlap, [`default_overlap`], is a quarter of the window (49 frames, 2.45 s, for
//! MCM-LDM's 196): longer than a step or beat, at most 4/3 the network evaluations of unsegmented
//! content. EDGE (`long_ddim_sample`) overlaps half its windows because they share no condition
//! but the music; here the content already fixes timing and path.

use std::ops::Range;

use ndarray::{Array2, ArrayView2};

use crate::error::{Error, Result};

/// The overlap used when the caller does not choose: a quarter of `max_frames`.
pub fn default_overlap(max_frames: usize) -> usize {
    max_frames / 4
}

/// Frame ranges covering `0..frames`: one range when `frames <= max_frames`, else equal ranges
/// of `max_frames` with evenly spaced starts, neighbours sharing at least `overlap` frames.
pub fn plan_segments(
    frames: usize,
    max_frames: usize,
    overlap: usize,
) -> Result<Vec<Range<usize>>> {
    if frames == 0 || max_frames == 0 || overlap >= max_frames {
        return Err(Error::motion(format!(
            "cannot cut {frames} frames into segments of {max_frames} overlapping by {overlap}"
        )));
    }
    if frames <= max_frames {
        return Ok(std::iter::once(0..frames).collect());
    }
    let stride = max_frames - overlap;
    let spare = frames - max_frames;
    let gaps = spare.div_ceil(stride);
    Ok((0..=gaps)
        .map(|k| {
            // Rounded even spacing: consecutive starts differ by at most `stride`.
            let start = (k * spare + gaps / 2) / gaps;
            start..start + max_frames
        })
        .collect())
}

/// One (frames, D) sequence from per-segment outputs (`outputs[k]` covers `segments[k]`, as
/// [`plan_segments`] gave them). Where segments overlap, each is weighted by a linear ramp
/// that rises over its overlap with the previous segment and falls over its overlap with the
/// next, `(i + 1) / (o + 1)` for the i-th of o shared frames, normalised by the weights'
/// sum: a cross-fade that never uses a segment's outermost value at full weight.
pub fn stitch_segments(
    frames: usize,
    segments: &[Range<usize>],
    outputs: &[ArrayView2<'_, f32>],
) -> Result<Array2<f32>> {
    let dim = outputs.first().map_or(0, |o| o.shape()[1]);
    if segments.len() != outputs.len()
        || segments.is_empty()
        || segments
            .iter()
            .zip(outputs)
            .any(|(s, o)| s.end > frames || s.start >= s.end || o.shape() != [s.end - s.start, dim])
    {
        return Err(Error::motion(format!(
            "{} segment outputs do not match {} segments of {frames} frames",
            outputs.len(),
            segments.len()
        )));
    }
    // f64 sums: up to three segments meet at a frame.
    let mut sum = Array2::<f64>::zeros((frames, dim));
    let mut weight = vec![0.0f64; frames];
    for (k, (seg, out)) in segments.iter().zip(outputs).enumerate() {
        let len = seg.end - seg.start;
        let fade_in = k
            .checked_sub(1)
            .map_or(0, |p| segments[p].end.saturating_sub(seg.start));
        let fade_out = segments
            .get(k + 1)
            .map_or(0, |n| seg.end.saturating_sub(n.start));
        for i in 0..len {
            let mut w = 1.0f64;
            if fade_in > 0 {
                w = w.min((i + 1) as f64 / (fade_in + 1) as f64);
            }
            if fade_out > 0 {
                w = w.min((len - i) as f64 / (fade_out + 1) as f64);
            }
            let f = seg.start + i;
            weight[f] += w;
            for d in 0..dim {
                sum[[f, d]] += w * f64::from(out[[i, d]]);
            }
        }
    }
    if let Some(f) = weight.iter().position(|w| *w <= 0.0) {
        return Err(Error::motion(format!("frame {f} is in no segment")));
    }
    Ok(Array2::from_shape_fn((frames, dim), |(f, d)| {
        (sum[[f, d]] / weight[f]) as f32
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn short_content_is_one_segment() {
        for frames in [196, 5] {
            let segs = plan_segments(frames, 196, 49).unwrap();
            assert_eq!((segs.len(), segs[0].clone()), (1, 0..frames));
        }
    }

    #[test]
    fn segments_cover_the_content_with_at_least_the_overlap() {
        for frames in [197, 300, 343, 344, 500, 1000, 4321] {
            let segs = plan_segments(frames, 196, 49).unwrap();
            assert_eq!(segs[0].start, 0, "{frames}");
            assert_eq!(segs.last().unwrap().end, frames, "{frames}");
            for s in &segs {
                assert_eq!(s.end - s.start, 196, "{frames}: {s:?}");
            }
            for w in segs.windows(2) {
                assert!(w[1].start > w[0].start, "{frames}: {w:?}");
                assert!(w[0].end - w[1].start >= 49, "{frames}: {w:?}");
            }
            // As few segments as the overlap allows: one fewer would leave a gap.
            let need = (frames - 196).div_ceil(196 - 49) + 1;
            assert_eq!(segs.len(), need, "{frames}");
        }
        assert!(plan_segments(300, 196, 196).is_err());
        assert!(plan_segments(0, 196, 49).is_err());
    }

    #[test]
    fn segments_of_one_sequence_stitch_back_to_it() {
        // 344 frames: starts 0, 74, 148, so three segments meet on frames 148..196.
        for frames in [344, 777] {
            let whole =
                Array2::from_shape_fn((frames, 3), |(f, d)| ((f * 7 + d * 13) % 101) as f32);
            let segs = plan_segments(frames, 196, 49).unwrap();
            let outs: Vec<ArrayView2<'_, f32>> = segs
                .iter()
                .map(|s| whole.slice(ndarray::s![s.clone(), ..]))
                .collect();
            let back = stitch_segments(frames, &segs, &outs).unwrap();
            // The normalised weights sum to one: only f32 rounding of values ≤ 100 remains.
            let worst = (&back - &whole)
                .mapv(f32::abs)
                .fold(0.0f32, |a, b| a.max(*b));
            assert!(worst < 1e-4, "{frames}: worst {worst}");
        }
    }

    #[test]
    fn overlap_is_a_linear_cross_fade() {
        // Two segments of 10 sharing 4 frames: 0 from the first, 1 from the second.
        let segs = vec![0..10, 6..16];
        let a = Array2::<f32>::zeros((10, 1));
        let b = Array2::<f32>::ones((10, 1));
        let out = stitch_segments(16, &segs, &[a.view(), b.view()]).unwrap();
        let got: Vec<f32> = out.column(0).to_vec();
        let mut want = vec![0.0f32; 6];
        want.extend((1..=4).map(|j| j as f32 / 5.0));
        want.extend(vec![1.0f32; 6]);
        for (g, w) in got.iter().zip(&want) {
            assert!((g - w).abs() < 1e-6, "got {got:?}, want {want:?}");
        }
    }

    #[test]
    fn mismatched_outputs_are_refused() {
        let segs = vec![0..10, 6..16];
        let a = Array2::<f32>::zeros((10, 2));
        let b = Array2::<f32>::zeros((9, 2));
        assert!(stitch_segments(16, &segs, &[a.view(), b.view()]).is_err());
        assert!(stitch_segments(16, &segs, &[a.view()]).is_err());
        assert!(stitch_segments(12, &segs, &[a.view(), a.view()]).is_err());
    }
}
