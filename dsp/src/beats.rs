//! Tempo estimation and dynamic-programming beat tracking in librosa's manner (librosa 0.11:
//! `librosa:beat.py` `beat_track`, `__beat_tracker`; `librosa:feature/rhythm.py` `tempo`,
//! `tempogram`), after Ellis (2007).
//!
//! Tempo: autocorrelation tempogram of the onset envelope (8 s Hann windows, centred with
//! linear-ramp padding, each lag profile normalised by its maximum), averaged over time,
//! weighted by a log-normal prior around `start_bpm` (σ = `std_bpm` octaves), tempi above
//! `max_tempo` excluded. Beats: onsets normalised by their standard deviation, smoothed by a
//! Gaussian of the beat period, a DP with penalty `tightness (ln(Δ/period))²`, backtracking from
//! the last strong local maximum, weak leading/trailing beats trimmed.

use crate::error::Result;
use crate::onset::{OnsetOptions, onset_strength};

/// Parameters of the tracker; defaults are librosa's.
#[non_exhaustive]
#[derive(Debug, Clone, PartialEq)]
pub struct BeatOptions {
    /// Centre of the tempo prior, BPM. Default: 120.
    pub start_bpm: f64,
    /// Width of the prior in octaves. Default: 1.0.
    pub std_bpm: f64,
    /// Tempo ceiling, BPM. Default: 320.
    pub max_tempo: f64,
    /// Autocorrelation window, seconds. Default: 8.
    pub ac_size_s: f64,
    /// DP tightness. Default: 100.
    pub tightness: f64,
    /// Drop weak leading/trailing beats. Default: true.
    pub trim: bool,
    /// Onset analysis. Default: librosa's (`OnsetOptions::default()`).
    pub onset: OnsetOptions,
}

impl Default for BeatOptions {
    fn default() -> Self {
        Self {
            start_bpm: 120.0,
            std_bpm: 1.0,
            max_tempo: 320.0,
            ac_size_s: 8.0,
            tightness: 100.0,
            trim: true,
            onset: OnsetOptions::default(),
        }
    }
}

/// Result of [`track_beats`].
#[non_exhaustive]
#[derive(Debug, Clone)]
pub struct Beats {
    /// Estimated tempo, BPM (0 when the envelope is all zero).
    pub tempo_bpm: f64,
    /// Beat positions, onset-envelope frames.
    pub beat_frames: Vec<usize>,
    /// Beat positions, seconds (`frame * hop / sr`).
    pub beat_times_s: Vec<f64>,
    /// The onset strength envelope used.
    pub onset_envelope: Vec<f32>,
}

/// Onset envelope, tempo and beats of `samples` at `sample_rate`.
pub fn track_beats(samples: &[f32], sample_rate: u32, opts: &BeatOptions) -> Result<Beats> {
    let env = onset_strength(samples, sample_rate, &opts.onset)?;
    Ok(track_beats_from_onsets(env, sample_rate, opts))
}

/// Tempo and beats from an onset envelope computed with `opts.onset.hop_length` at `sample_rate`.
pub fn track_beats_from_onsets(env: Vec<f32>, sample_rate: u32, opts: &BeatOptions) -> Beats {
    let hop = opts.onset.hop_length.max(1);
    let sr = f64::from(sample_rate.max(1));
    let empty = |env| Beats {
        tempo_bpm: 0.0,
        beat_frames: Vec::new(),
        beat_times_s: Vec::new(),
        onset_envelope: env,
    };
    if !env.iter().any(|&x| x != 0.0) {
        return empty(env);
    }
    let onsets: Vec<f64> = env.iter().map(|&x| f64::from(x)).collect();
    let bpm = estimate_tempo(&onsets, sr, hop, opts);
    let frame_rate = sr / hop as f64;
    let fpb = (frame_rate * 60.0 / bpm).round_ties_even();
    if !(fpb >= 1.0 && fpb.is_finite()) {
        return empty(env);
    }
    let localscore = local_score(&normalize(&onsets), fpb);
    let (backlink, cumscore) = dp(&localscore, fpb, opts.tightness);
    let mut beats = vec![false; onsets.len()];
    let mut n = last_beat(&cumscore, LastBeatRule::AtLeastHalfMedian) as isize;
    while n >= 0 {
        beats[n as usize] = true;
        n = backlink[n as usize];
    }
    trim_beats(&localscore, &mut beats, opts.trim);
    let beat_frames: Vec<usize> = beats
        .iter()
        .enumerate()
        .filter(|(_, b)| **b)
        .map(|(i, _)| i)
        .collect();
    let beat_times_s = beat_frames.iter().map(|&f| (f * hop) as f64 / sr).collect();
    Beats {
        tempo_bpm: bpm,
        beat_frames,
        beat_times_s,
        onset_envelope: env,
    }
}

/// `librosa.feature.tempo` with the default (mean) aggregation.
pub(crate) fn estimate_tempo(onsets: &[f64], sr: f64, hop: usize, opts: &BeatOptions) -> f64 {
    // time_to_frames(ac_size): floor(floor(t * sr) / hop)
    let win = (((opts.ac_size_s * sr).floor() as usize) / hop).max(2);
    let tg = mean_tempogram(onsets, win);
    let mut best = (f64::NEG_INFINITY, 1usize);
    for (lag, &v) in tg.iter().enumerate().skip(1) {
        let bpm = 60.0 * sr / (hop as f64 * lag as f64);
        if bpm >= opts.max_tempo {
            continue;
        }
        let prior = -0.5 * ((bpm.log2() - opts.start_bpm.log2()) / opts.std_bpm).powi(2);
        let score = (1e6 * v).ln_1p() + prior;
        if score > best.0 {
            best = (score, lag);
        }
    }
    60.0 * sr / (hop as f64 * best.1 as f64)
}

/// Time-averaged autocorrelation tempogram (`librosa.feature.tempogram`, norm = inf).
fn mean_tempogram(onsets: &[f64], win: usize) -> Vec<f64> {
    let n = onsets.len();
    let half = win / 2;
    // np.pad(mode="linear_ramp", end_values=0): ramps from 0 towards the edge values.
    let mut padded = Vec::with_capacity(n + 2 * half);
    let (first, last) = (onsets[0], onsets[n - 1]);
    padded.extend((0..half).map(|j| first * j as f64 / half as f64));
    padded.extend_from_slice(onsets);
    padded.extend((0..half).map(|k| last * (half - 1 - k) as f64 / half as f64));
    // Pad on the right so every frame start 0..n has a full window (np.pad gave win//2 each side;
    // for odd win the frame count is n anyway, for even win the last frame needs one more zero).
    padded.resize(n + win, 0.0);
    let window: Vec<f64> = (0..win)
        .map(|k| 0.5 - 0.5 * (2.0 * std::f64::consts::PI * k as f64 / win as f64).cos())
        .collect();
    let mut acc = vec![0.0f64; win];
    let mut x = vec![0.0f64; win];
    let mut ac = vec![0.0f64; win];
    for t in 0..n {
        for ((xi, &p), &w) in x.iter_mut().zip(&padded[t..t + win]).zip(&window) {
            *xi = p * w;
        }
        autocorrelate(&x, &mut ac);
        let norm = ac.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let norm = if norm < f64::MIN_POSITIVE { 1.0 } else { norm };
        for (s, a) in acc.iter_mut().zip(&ac) {
            *s += a / norm;
        }
    }
    acc.iter().map(|s| s / n as f64).collect()
}

/// `ac[lag] = Σ_i x[i] · x[i + lag]` for every lag, each sum in `i` order from −0.0 (as
/// `Iterator::sum`), so the values are those of one sum per lag, bit for bit. Four lags share
/// a pass: four independent addition chains instead of one keep the CPU's adders busy (the
/// tempogram's 384-frame windows made this half of a whole `features` run).
fn autocorrelate(x: &[f64], ac: &mut [f64]) {
    let win = x.len();
    let mut lag = 0;
    while lag + 4 <= win {
        // The four sums share their first `common` terms; the shorter lags have a few more.
        let common = win - lag - 3;
        let (b0, b1, b2, b3) = (&x[lag..], &x[lag + 1..], &x[lag + 2..], &x[lag + 3..]);
        let (mut s0, mut s1, mut s2, mut s3) = (-0.0f64, -0.0f64, -0.0f64, -0.0f64);
        for (i, &xi) in x[..common].iter().enumerate() {
            s0 += xi * b0[i];
            s1 += xi * b1[i];
            s2 += xi * b2[i];
            s3 += xi * b3[i];
        }
        for i in common..win - lag {
            s0 += x[i] * b0[i];
        }
        for i in common..win - lag - 1 {
            s1 += x[i] * b1[i];
        }
        for i in common..win - lag - 2 {
            s2 += x[i] * b2[i];
        }
        ac[lag..lag + 4].copy_from_slice(&[s0, s1, s2, s3]);
        lag += 4;
    }
    for (l, a) in ac.iter_mut().enumerate().skip(lag) {
        *a = x[..win - l].iter().zip(&x[l..]).map(|(a, b)| a * b).sum();
    }
}

/// Divide by the sample standard deviation (ddof 1) plus the smallest normal f32, as librosa.
fn normalize(onsets: &[f64]) -> Vec<f64> {
    let n = onsets.len() as f64;
    let mean = onsets.iter().sum::<f64>() / n;
    let var = onsets.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0).max(1.0);
    let d = var.sqrt() + f64::from(f32::MIN_POSITIVE);
    onsets.iter().map(|x| x / d).collect()
}

/// Same-mode convolution with a Gaussian of the beat period, including librosa's boundary
/// (the k-range excludes the very first onset sample, as `__beat_local_score` does).
fn local_score(onsets: &[f64], fpb: f64) -> Vec<f64> {
    let half = fpb as usize;
    let window: Vec<f64> = (0..2 * half + 1)
        .map(|k| (-0.5 * ((k as f64 - fpb) * 32.0 / fpb).powi(2)).exp())
        .collect();
    let kk = window.len();
    let n = onsets.len();
    (0..n)
        .map(|i| {
            let lo = (i + kk / 2 + 1).saturating_sub(n);
            let hi = (i + kk / 2).min(kk);
            (lo..hi).map(|k| window[k] * onsets[i + kk / 2 - k]).sum()
        })
        .collect()
}

/// The DP of `__beat_track_dp` (static tempo).
fn dp(localscore: &[f64], fpb: f64, tightness: f64) -> (Vec<isize>, Vec<f64>) {
    let n = localscore.len();
    let max = localscore.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let thresh = 0.01 * max;
    let mut backlink = vec![-1isize; n];
    let mut cum = vec![0.0f64; n];
    let mut first_beat = true;
    let near = (fpb / 2.0).round_ties_even() as isize;
    let far = (2.0 * fpb) as isize;
    let lfpb = fpb.ln();
    for i in 0..n {
        let mut best = f64::NEG_INFINITY;
        let mut loc_best = -1isize;
        let mut loc = i as isize - near;
        while loc >= i as isize - far && loc >= 0 {
            let d = ((i as isize - loc) as f64).ln() - lfpb;
            let score = cum[loc as usize] - tightness * d * d;
            if score > best {
                best = score;
                loc_best = loc;
            }
            loc -= 1;
        }
        cum[i] = if loc_best >= 0 {
            localscore[i] + best
        } else {
            localscore[i]
        };
        if first_beat && localscore[i] < thresh {
            backlink[i] = -1;
        } else {
            backlink[i] = loc_best;
            first_beat = false;
        }
    }
    (backlink, cum)
}

/// Last local maximum of the cumulative score above half the median of local maxima.
/// How the last beat is chosen among the cumulative score's local maxima, relative to half their
/// median: librosa 0.10.2 on (`__last_beat_selector`) keeps a maximum at or above it; 0.7.2
/// through 0.10.1 (`__last_beat`: `cumscore * mask * 2 > median`) only one strictly above.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum LastBeatRule {
    AtLeastHalfMedian,
    AboveHalfMedian,
}

/// The last local maximum of `cum` (`util.localmax`, edge-padded: `x[i] > x[i-1]` and
/// `x[i] >= x[i+1]`) that passes `rule`; the last frame when there is none (where librosa's
/// median of nothing is NaN and fails).
pub(crate) fn last_beat(cum: &[f64], rule: LastBeatRule) -> usize {
    let n = cum.len();
    let is_max = |i: usize| {
        let prev = cum[i.saturating_sub(1)];
        let next = cum[(i + 1).min(n - 1)];
        cum[i] > prev && cum[i] >= next
    };
    let mut maxima: Vec<f64> = (0..n).filter(|&i| is_max(i)).map(|i| cum[i]).collect();
    if maxima.is_empty() {
        return n - 1;
    }
    maxima.sort_by(f64::total_cmp);
    let m = maxima.len();
    let median = if m % 2 == 1 {
        maxima[m / 2]
    } else {
        0.5 * (maxima[m / 2 - 1] + maxima[m / 2])
    };
    let passes = |i: usize| match rule {
        LastBeatRule::AtLeastHalfMedian => cum[i] >= 0.5 * median,
        LastBeatRule::AboveHalfMedian => cum[i] * 2.0 > median,
    };
    (0..n)
        .rev()
        .find(|&i| is_max(i) && passes(i))
        .unwrap_or(n - 1)
}

fn trim_beats(localscore: &[f64], beats: &mut [bool], trim: bool) {
    let n = localscore.len();
    let threshold = if trim {
        let strengths: Vec<f64> = localscore
            .iter()
            .zip(beats.iter())
            .filter(|(_, b)| **b)
            .map(|(s, _)| *s)
            .collect();
        // np.hanning(5) = [0, .5, 1, .5, 0]; full convolution sliced [2 : n + 2].
        let w = [0.0, 0.5, 1.0, 0.5, 0.0];
        let nb = strengths.len();
        let full: Vec<f64> = (0..nb + 4)
            .map(|k| {
                (0..5)
                    .filter(|&j| k >= j && k - j < nb)
                    .map(|j| w[j] * strengths[k - j])
                    .sum()
            })
            .collect();
        let end = (n + 2).min(full.len());
        let smooth = if end > 2 { &full[2..end] } else { &full[0..0] };
        if smooth.is_empty() {
            0.0
        } else {
            0.5 * (smooth.iter().map(|x| x * x).sum::<f64>() / smooth.len() as f64).sqrt()
        }
    } else {
        0.0
    };
    let mut i = 0;
    while i < n && localscore[i] <= threshold {
        beats[i] = false;
        i += 1;
    }
    let mut j = n;
    while j > 0 && localscore[j - 1] <= threshold {
        beats[j - 1] = false;
        j -= 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn four_lags_at_a_time_give_each_lags_own_sum_bit_for_bit() {
        // Values of mixed sign and magnitude, where any reordering of a sum shows in the bits.
        let mut v = 0x2545_f491_4f6c_dd1du64;
        let mut next = || {
            v ^= v << 13;
            v ^= v >> 7;
            v ^= v << 17;
            (v >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
        };
        for win in [1usize, 2, 3, 4, 5, 7, 8, 383, 384] {
            let x: Vec<f64> = (0..win)
                .map(|k| next() * 10f64.powi((k % 7) as i32 - 3))
                .collect();
            let mut ac = vec![0.0; win];
            autocorrelate(&x, &mut ac);
            for (lag, a) in ac.iter().enumerate() {
                let one: f64 = x[..win - lag]
                    .iter()
                    .zip(&x[lag..])
                    .map(|(a, b)| a * b)
                    .sum();
                assert_eq!(a.to_bits(), one.to_bits(), "win {win}, lag {lag}");
            }
        }
    }

    #[test]
    fn a_maximum_at_exactly_half_the_median_is_the_last_beat_only_for_the_newer_rule() {
        // Local maxima 2, 2, 1: median 2, half of it 1, which the last maximum (frame 5) equals.
        let cum = [0.0, 2.0, 0.0, 2.0, 0.0, 1.0, 0.0];
        assert_eq!(last_beat(&cum, LastBeatRule::AtLeastHalfMedian), 5);
        assert_eq!(last_beat(&cum, LastBeatRule::AboveHalfMedian), 3);
        // No local maximum at all: the last frame.
        assert_eq!(
            last_beat(&[1.0, 1.0, 1.0], LastBeatRule::AboveHalfMedian),
            2
        );
    }

    #[test]
    fn click_track_at_120_bpm_gives_120_bpm_and_beats_every_half_second() {
        let sr = 16_000u32;
        let mut y = vec![0.0f32; sr as usize * 20];
        // A 10 ms 1 kHz burst every 0.5 s.
        for b in 0..40 {
            let s = b * sr as usize / 2;
            for k in 0..160 {
                y[s + k] = (2.0 * std::f32::consts::PI * 1000.0 * k as f32 / sr as f32).sin();
            }
        }
        let beats = track_beats(&y, sr, &BeatOptions::default()).unwrap();
        // 31.25 fps: lag 16 frames = 117.2 BPM is the nearest tempogram bin to 120 (lag 15 = 125).
        assert!(
            (beats.tempo_bpm - 117.1875).abs() < 1e-6 || (beats.tempo_bpm - 125.0).abs() < 1e-6,
            "{}",
            beats.tempo_bpm
        );
        assert!(beats.beat_times_s.len() >= 30, "{:?}", beats.beat_times_s);
        let gaps: Vec<f64> = beats.beat_times_s.windows(2).map(|w| w[1] - w[0]).collect();
        let mean_gap = gaps.iter().sum::<f64>() / gaps.len() as f64;
        // One frame is 32 ms; the mean inter-beat interval must be within a frame of 0.5 s.
        assert!((mean_gap - 0.5).abs() < 0.032, "{mean_gap}");
    }

    #[test]
    fn silence_has_no_beats() {
        let b = track_beats(&vec![0.0; 16_000 * 3], 16_000, &BeatOptions::default()).unwrap();
        assert_eq!(b.tempo_bpm, 0.0);
        assert!(b.beat_times_s.is_empty());
    }
}
