//! The dynamic-programming beat tracker of librosa 0.7.2 through 0.10.1 (`librosa:beat.py`
//! `beat_track`, `__beat_tracker`, `__beat_local_score`, `__beat_track_dp`, `__last_beat`,
//! `__trim_beats`; identical in those versions, rewritten in 0.10.2 — see [`crate::track_beats`]
//! for the newer one), after Ellis (2007).
//!
//! Differences from the newer tracker that move beats: the onsets are divided by their standard
//! deviation without an epsilon; the DP lets a beat's predecessor lie before the signal start
//! (scored by the tempo penalty alone, which ends the backtrace); the last beat is the last
//! local maximum of the cumulative score strictly above half their median; and trimming keeps
//! `beats[first_strong : last_strong]`, so the last strong beat itself is dropped.

use crate::beats::{BeatOptions, LastBeatRule, estimate_tempo, last_beat};

/// Parameters of [`beat_track_dp`].
#[derive(Debug, Clone, PartialEq)]
pub struct DpBeatOptions {
    /// Centre of the tempo prior, BPM (librosa's `start_bpm`).
    pub start_bpm: f64,
    /// Penalty weight of tempo deviations (librosa's `tightness`). Default: 100.
    pub tightness: f64,
    /// Drop weak leading/trailing beats (librosa's `trim`). Default: true.
    pub trim: bool,
}

impl Default for DpBeatOptions {
    fn default() -> Self {
        Self {
            start_bpm: 120.0,
            tightness: 100.0,
            trim: true,
        }
    }
}

/// `beat_track(onset_envelope=env, sr, hop_length, start_bpm, tightness, trim)`: the tempo
/// (BPM, 0 for an all-zero envelope) and beat frames.
pub fn beat_track_dp(
    env: &[f32],
    sample_rate: f64,
    hop: usize,
    opts: &DpBeatOptions,
) -> (f64, Vec<usize>) {
    if env.len() < 2 || !env.iter().any(|&x| x != 0.0) {
        return (0.0, Vec::new());
    }
    let bpm = tempo(env, sample_rate, hop, opts.start_bpm);
    (bpm, track(env, bpm, sample_rate / hop as f64, opts))
}

/// `beat.tempo(onset_envelope=env, sr, hop_length, start_bpm)` with librosa's defaults
/// (8 s autocorrelation window, prior σ 1 octave, ceiling 320 BPM, mean over time).
pub fn tempo(env: &[f32], sample_rate: f64, hop: usize, start_bpm: f64) -> f64 {
    let onsets: Vec<f64> = env.iter().map(|&x| f64::from(x)).collect();
    let o = BeatOptions {
        start_bpm,
        ..BeatOptions::default()
    };
    estimate_tempo(&onsets, sample_rate, hop, &o)
}

fn track(env: &[f32], bpm: f64, frame_rate: f64, opts: &DpBeatOptions) -> Vec<usize> {
    if bpm.is_nan() || bpm <= 0.0 || opts.tightness.is_nan() || opts.tightness <= 0.0 {
        return Vec::new();
    }
    // Python round(): half to even.
    let period = (60.0 * frame_rate / bpm).round_ties_even();
    if !(period >= 1.0 && period.is_finite()) {
        return Vec::new();
    }
    let period = period as usize;
    let local = local_score(env, period);
    let (backlink, cum) = dp(&local, period, opts.tightness);
    let mut beats = vec![last_beat(&cum, LastBeatRule::AboveHalfMedian)];
    while let Some(&b) = beats.last() {
        match usize::try_from(backlink[b]) {
            Ok(prev) => beats.push(prev),
            Err(_) => break,
        }
    }
    beats.reverse();
    trim(&local, &beats, opts.trim)
}

/// `convolve(onsets / onsets.std(ddof=1), gaussian(period), "same")`.
fn local_score(env: &[f32], period: usize) -> Vec<f64> {
    let n = env.len();
    let mean = env.iter().map(|&x| f64::from(x)).sum::<f64>() / n as f64;
    let var = env
        .iter()
        .map(|&x| (f64::from(x) - mean).powi(2))
        .sum::<f64>()
        / (n - 1) as f64;
    // The std of a float32 array is float32, and so is the quotient.
    let norm = var.sqrt() as f32;
    let onsets: Vec<f64> = env
        .iter()
        .map(|&x| f64::from(if norm > 0.0 { x / norm } else { x }))
        .collect();
    let p = period as f64;
    let window: Vec<f64> = (0..=2 * period)
        .map(|k| (-0.5 * ((k as f64 - p) * 32.0 / p).powi(2)).exp())
        .collect();
    (0..n)
        .map(|i| {
            // out[i] = Σ_k w[k] x[i + period - k]
            let lo = (i + period + 1).saturating_sub(n);
            let hi = (i + period).min(2 * period);
            (lo..=hi).map(|k| window[k] * onsets[i + period - k]).sum()
        })
        .collect()
}

/// `__beat_track_dp`: predecessor candidates `i - 2 period ..= i - round(period / 2)`, scored
/// `-tightness ln(Δ / period)²` plus their cumulative score (candidates before the start get
/// the penalty alone); the first maximum wins.
fn dp(local: &[f64], period: usize, tightness: f64) -> (Vec<isize>, Vec<f64>) {
    let n = local.len();
    let p = period as isize;
    let near = (period as f64 / 2.0).round_ties_even() as isize;
    // window = np.arange(-2 p, -round(p / 2) + 1): offsets, farthest first.
    let offsets: Vec<isize> = (-2 * p..=-near).collect();
    let txwt: Vec<f64> = offsets
        .iter()
        .map(|&o| -tightness * ((-o) as f64 / period as f64).ln().powi(2))
        .collect();
    let max_local = local.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let mut backlink = vec![0isize; n];
    let mut cum = vec![0.0f64; n];
    let mut first_beat = true;
    for i in 0..n {
        let mut best = (f64::NEG_INFINITY, 0usize);
        for (j, (&o, &w)) in offsets.iter().zip(&txwt).enumerate() {
            let at = i as isize + o;
            let score = if at >= 0 { w + cum[at as usize] } else { w };
            if score > best.0 {
                best = (score, j);
            }
        }
        cum[i] = local[i] + best.0;
        if first_beat && local[i] < 0.01 * max_local {
            backlink[i] = -1;
        } else {
            backlink[i] = i as isize + offsets[best.1];
            first_beat = false;
        }
    }
    (backlink, cum)
}

/// `__trim_beats`: smooth the beats' local scores with Hann(5) = [0, .5, 1, .5, 0] ("same"),
/// threshold at half their RMS (0 without `trim`), keep `beats[first : last]` of those above.
fn trim(local: &[f64], beats: &[usize], trim: bool) -> Vec<usize> {
    let m = beats.len();
    let s: Vec<f64> = beats.iter().map(|&b| local[b]).collect();
    let h = [0.0, 0.5, 1.0, 0.5, 0.0];
    let smooth: Vec<f64> = (0..m)
        .map(|i| {
            (0..5)
                .filter_map(|k| {
                    (i + 2)
                        .checked_sub(k)
                        .filter(|&j| j < m)
                        .map(|j| h[k] * s[j])
                })
                .sum()
        })
        .collect();
    let threshold = if trim {
        0.5 * (smooth.iter().map(|x| x * x).sum::<f64>() / m as f64).sqrt()
    } else {
        0.0
    };
    let first = smooth.iter().position(|&x| x > threshold);
    let last = smooth.iter().rposition(|&x| x > threshold);
    match (first, last) {
        (Some(a), Some(b)) => beats[a..b].to_vec(),
        _ => Vec::new(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn clicks(n: usize, every: usize) -> Vec<f32> {
        (0..n)
            .map(|i| if i % every == 5 { 1.0 } else { 0.01 })
            .collect()
    }

    #[test]
    fn regular_clicks_give_beats_on_the_clicks_and_drop_the_last_strong_one() {
        // 30 frames/s, a click every 15 frames = 120 BPM.
        let env = clicks(600, 15);
        let (bpm, beats) = beat_track_dp(&env, 15_360.0, 512, &DpBeatOptions::default());
        assert_eq!(bpm, 120.0);
        assert!(beats.iter().all(|b| b % 15 == 5), "{beats:?}");
        // The last clicks are strong, yet trimming (beats[first:last], exclusive) drops beats at
        // the end: librosa 0.7.2's beat_track on this very envelope (sr 15360, hop 512, start
        // 120 BPM, tightness 100) returns 38 beats ending [530, 545, 560].
        assert_eq!(beats.len(), 38, "{beats:?}");
        assert_eq!(*beats.last().unwrap(), 560, "{beats:?}");
    }

    #[test]
    fn silence_has_no_tempo_and_no_beats() {
        let (bpm, beats) = beat_track_dp(&[0.0; 100], 15_360.0, 512, &DpBeatOptions::default());
        assert_eq!(bpm, 0.0);
        assert!(beats.is_empty());
    }
}
