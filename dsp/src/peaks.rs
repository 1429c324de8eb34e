//! Onset peak picking as librosa's `onset_detect` does it with its defaults
//! (`librosa:onset.py` `onset_detect`, `librosa:util/utils.py` `peak_pick`, 0.7.2 and 0.10).
//!
//! The envelope is shifted to start at 0 and scaled to peak at 1 (0.10 adds the smallest
//! normal float32 to the divisor); a frame is a peak when it equals the maximum of
//! `[n − pre_max, n + post_max)`, is at least `delta` above the mean of
//! `[n − pre_avg, n + post_avg)`, and comes more than `wait` frames after the previous peak.
//! The windows are librosa's defaults in frames, `⌊0.03 sr / hop⌋` etc.; at 15360 Hz `pre_max`
//! is 0, so the maximum test always passes and adjacent frames can both be peaks.

/// Which librosa's normalisation to follow.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PeakNormalize {
    /// 0.7.2: `env -= min; env /= max`.
    Librosa07,
    /// 0.10: `env /= max + tiny(float32)`.
    Librosa010,
}

/// `onset_detect(onset_envelope=env, sr, hop_length)` with the default windows and
/// `delta = 0.07`: peak frames, ascending.
pub fn onset_detect(env: &[f32], sample_rate: f64, hop: usize, norm: PeakNormalize) -> Vec<usize> {
    if env.is_empty() || env.iter().any(|x| !x.is_finite()) {
        return Vec::new();
    }
    let min = env.iter().copied().fold(f32::INFINITY, f32::min);
    let x: Vec<f32> = env.iter().map(|&v| v - min).collect();
    if !x.iter().any(|&v| v != 0.0) {
        return Vec::new();
    }
    let max = x.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    let div = match norm {
        PeakNormalize::Librosa07 => max,
        PeakNormalize::Librosa010 => max + f32::MIN_POSITIVE,
    };
    let x: Vec<f32> = x.iter().map(|&v| v / div).collect();
    // kwargs.setdefault("pre_max", 0.03 * sr // hop_length) etc.: float floor division.
    let frames = |seconds: f64| (seconds * sample_rate / hop as f64).floor();
    let w = PeakWindows {
        pre_max: frames(0.03),
        post_max: frames(0.0) + 1.0,
        pre_avg: frames(0.10),
        post_avg: frames(0.10) + 1.0,
        wait: frames(0.03),
        delta: 0.07,
    };
    peak_pick(&x, &w)
}

/// Windows of [`peak_pick`], in frames (librosa rounds each up to an integer).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PeakWindows {
    /// Frames before `n` in the maximum window.
    pub pre_max: f64,
    /// Frames after `n` (inclusive of `n`) in the maximum window; ≥ 1.
    pub post_max: f64,
    /// Frames before `n` in the mean window.
    pub pre_avg: f64,
    /// Frames after `n` (inclusive of `n`) in the mean window; ≥ 1.
    pub post_avg: f64,
    /// Minimum frames between peaks, exclusive.
    pub wait: f64,
    /// Threshold above the local mean.
    pub delta: f32,
}

/// `util.peak_pick(x, ...)` on a float32 signal.
pub fn peak_pick(x: &[f32], w: &PeakWindows) -> Vec<usize> {
    let n = x.len();
    let ceil = |v: f64| v.ceil().max(0.0) as usize;
    let (pre_max, post_max) = (ceil(w.pre_max), ceil(w.post_max).max(1));
    let (pre_avg, post_avg) = (ceil(w.pre_avg), ceil(w.post_avg).max(1));
    let wait = ceil(w.wait);
    let xmin = x.iter().copied().fold(f32::INFINITY, f32::min);
    // maximum_filter1d(mode="constant", cval=x.min()) over [i - pre_max, i + post_max).
    let mov_max = |i: usize| {
        let lo = i as isize - pre_max as isize;
        let hi = i + post_max;
        let mut m = if lo < 0 || hi > n {
            xmin
        } else {
            f32::NEG_INFINITY
        };
        for &v in &x[lo.max(0) as usize..hi.min(n)] {
            m = m.max(v);
        }
        m
    };
    // uniform_filter1d(mode="nearest") over [i - pre_avg, i + post_avg), in float64 then
    // stored as float32; librosa then recomputes the first pre_avg and the last post_avg
    // frames as np.mean of the part of the window inside the signal (float32 mean).
    let mov_avg = |i: usize| -> f32 {
        let lo = i as isize - pre_avg as isize;
        let hi = i + post_avg;
        if lo < 0 || hi >= n {
            let s = &x[lo.max(0) as usize..hi.min(n)];
            return numpy_sum_f32(s) / s.len() as f32;
        }
        let sum: f64 = x[lo as usize..hi].iter().map(|&v| f64::from(v)).sum();
        (sum / (pre_avg + post_avg) as f64) as f32
    };
    let mut peaks = Vec::new();
    let mut last: Option<usize> = None;
    for (i, &v) in x.iter().enumerate() {
        if v == 0.0 || v != mov_max(i) || v < mov_avg(i) + w.delta {
            continue;
        }
        if last.is_none_or(|l| i > l + wait) {
            peaks.push(i);
            last = Some(i);
        }
    }
    peaks
}

/// numpy's float32 `add.reduce` of a contiguous slice: the first element plus the pairwise sum
/// of the rest (eight partial sums for 8..=128 elements, a plain loop below 8).
fn numpy_sum_f32(a: &[f32]) -> f32 {
    let Some((&first, rest)) = a.split_first() else {
        return 0.0;
    };
    first + pairwise_f32(rest)
}

fn pairwise_f32(a: &[f32]) -> f32 {
    let n = a.len();
    if n < 8 {
        return a.iter().fold(-0.0f32, |s, &v| s + v);
    }
    if n <= 128 {
        let mut r = [0.0f32; 8];
        r.copy_from_slice(&a[..8]);
        let whole = n - n % 8;
        for chunk in a[8..whole].chunks_exact(8) {
            for (acc, &v) in r.iter_mut().zip(chunk) {
                *acc += v;
            }
        }
        let mut res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]));
        for &v in &a[whole..] {
            res += v;
        }
        return res;
    }
    let half = (n / 2) - (n / 2) % 8;
    pairwise_f32(&a[..half]) + pairwise_f32(&a[half..])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pre_max_zero_at_15360_hz_lets_adjacent_frames_both_be_peaks() {
        // 0.03 * 15360 / 512 = 0.9 → 0 frames: every frame far enough above its mean is a peak.
        let mut env = vec![0.0f32; 40];
        env[20] = 1.0;
        env[21] = 0.9;
        let p = onset_detect(&env, 15_360.0, 512, PeakNormalize::Librosa07);
        assert_eq!(p, vec![20, 21]);
        // At 30720 Hz pre_max is 1 frame and wait 1: frame 21 is not a local maximum.
        let p = onset_detect(&env, 30_720.0, 512, PeakNormalize::Librosa07);
        assert_eq!(p, vec![20]);
    }

    #[test]
    fn flat_or_non_finite_envelopes_have_no_peaks() {
        assert!(onset_detect(&[0.5; 10], 15_360.0, 512, PeakNormalize::Librosa07).is_empty());
        assert!(onset_detect(&[], 15_360.0, 512, PeakNormalize::Librosa010).is_empty());
        let mut e = vec![0.0f32; 10];
        e[3] = f32::NAN;
        assert!(onset_detect(&e, 15_360.0, 512, PeakNormalize::Librosa010).is_empty());
    }
}
