//! Is there a steady beat to dance to? A cheap verdict from a song's log-mel (dB, `(n_mels, T)`),
//! for the dance pipeline to say so when the input is speech, noise or a drone.
//!
//! Three measures, about 15 000 multiply-adds per second of audio together (80 bands × 31 frames
//! for the envelope, 40 lags × 250 frames for one periodicity window a second):
//! - **onset strength**: the mean over frames of the onset envelope, the positive frame-to-frame
//!   rise in dB averaged over bands (librosa's `onset_strength` without its centring shift),
//!   dB per frame. A drone or silence has none.
//! - **periodicity**: in 8 s windows every second, the envelope's autocorrelation (mean removed,
//!   Hann-weighted, divided by its value at lag 0) at its highest point between lags of 0.3 s and
//!   1.5 s (200 and 40 BPM: the beat tracker's range); the median over the windows. A steady beat
//!   repeats its onsets at one lag for seconds on end; speech, noise and applause do not.
//! - **loudness fluctuation**: in 2 s windows every second, the standard deviation of the frame
//!   loudness (the mean of the frame's dB over bands); the median over the windows, dB. Noise is
//!   flat (≈ 0.2 dB); music and speech are not.
//!
//! The thresholds come from a calibration set, measured with this code through `choreod beats
//! --json` (the issue-24 session's report has the table): 57 pieces of music (the fixture songs;
//! Debian's game music: Wesnoth's orchestral pieces, Drascula's, Endgame: Singularity's
//! electronic ones) and 14 inputs that are not music (espeak-ng speech in several voices and
//! rates, dry, in room noise and with reverb; white and pink noise; two drones; a whale-like
//! tonal glide; applause), each whole and as a 15 s excerpt. Held out: 58 more pieces (Wesnoth,
//! Drascula, Hyperrogue, ASC, Frets on Fire rock) and 14 more non-music clips (other voices,
//! brown and quiet noise, a drone, the glide with reverb, sparse applause, a crowd of voices):
//! all 14 clips warned, whole and excerpted; of the pieces one, Wesnoth's 10 s near-silent
//! `silence.ogg`.
//!
//! The verdict: no onsets below [`MIN_ONSET_DB`]; a steady beat from [`MIN_PERIODICITY`] up. Below
//! it, periodicity alone cannot tell slow, rubato or ambient music (20 of the 114 calibration
//! measurements of music score 0.13–0.26) from speech and noise (0.10–0.26), so the texture
//! decides: an envelope unlike any of that music — flat as noise ([`NOISE_FLUCTUATION_DB`]),
//! bursting as speech or applause ([`BURST_ONSET_DB`]) or nearly silent between rare onsets
//! ([`SPARSE_ONSET_DB`]) — has no beat; the rest is music with a weak beat, not warned about.

use ndarray::ArrayView2;

/// Mean onset strength below which there are no onsets at all, dB per frame. Calibration: the
/// drones 0.020–0.050 (whole or excerpt); the quietest music 0.307 (a slow choral piece).
pub const MIN_ONSET_DB: f64 = 0.1;
/// Periodicity from which a beat is steady. Calibration: non-music other than drones at most
/// 0.264 (applause, 15 s); the rubato fixture (Hungarian Dance 5) 0.293 on 15 s, 0.313 whole;
/// the other fixture 0.51–0.64. The margins are thin (0.006 and 0.023): the texture rules below
/// carry the speech and noise that come close.
pub const MIN_PERIODICITY: f64 = 0.27;
/// Loudness fluctuation below which a weakly periodic input is noise, dB. Calibration: white,
/// pink noise ≤ 0.24; music below [`MIN_PERIODICITY`] ≥ 1.00.
pub const NOISE_FLUCTUATION_DB: f64 = 0.6;
/// Mean onset strength above which a weakly periodic input is bursts with gaps (speech, a crowd,
/// applause), dB per frame. Calibration: speech (dry, in room noise, with reverb), crowd and
/// applause ≥ 1.82; music below [`MIN_PERIODICITY`] ≤ 0.885.
pub const BURST_ONSET_DB: f64 = 1.4;
/// Mean onset strength below which a weakly periodic input is a few onsets in near-silence (a
/// tonal glide, a whale), dB per frame. Calibration: the glide 0.151 whole, 0.204 on 15 s (with
/// reverb, held out: 0.275–0.294); music below [`MIN_PERIODICITY`] ≥ 0.571.
pub const SPARSE_ONSET_DB: f64 = 0.3;

/// Periodicity window and hop, seconds (librosa's tempogram window is 8 s too).
const PERIODICITY_WINDOW_S: f64 = 8.0;
/// Loudness window, seconds.
const LOUDNESS_WINDOW_S: f64 = 2.0;
/// Windows start every second.
const HOP_S: f64 = 1.0;
/// Beat periods searched, seconds: 200 to 40 BPM.
const PERIOD_RANGE_S: (f64, f64) = (0.3, 1.5);

/// What [`beat_presence`] found.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BeatVerdict {
    /// A beat repeats for seconds on end.
    Steady,
    /// A weak or changing beat in something that sounds like music (slow, rubato, ambient).
    Weak,
    /// No steady beat: onsets without a period, as speech, noise or applause have.
    NoSteadyBeat,
    /// Hardly any onsets: a drone, a sustained tone, silence.
    NoOnsets,
}

impl BeatVerdict {
    /// Whether a dance of this input should say that it had no beat to follow.
    pub fn lacks_beat(self) -> bool {
        matches!(self, Self::NoSteadyBeat | Self::NoOnsets)
    }

    /// The verdict's name in reports: `steady`, `weak`, `no_steady_beat`, `no_onsets`.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Steady => "steady",
            Self::Weak => "weak",
            Self::NoSteadyBeat => "no_steady_beat",
            Self::NoOnsets => "no_onsets",
        }
    }
}

/// The measures and the verdict.
#[derive(Debug, Clone, Copy, PartialEq)]
#[non_exhaustive]
pub struct BeatPresence {
    /// The verdict.
    pub verdict: BeatVerdict,
    /// Mean onset strength, dB per frame.
    pub onset_db: f64,
    /// Median windowed autocorrelation peak at 40–200 BPM, 0..1.
    pub periodicity: f64,
    /// Median short-time loudness fluctuation, dB.
    pub fluctuation_db: f64,
}

impl BeatPresence {
    /// What input without a beat sounds like, from the measure that decided it: `None` for
    /// input with a beat.
    pub fn sounds_like(&self) -> Option<&'static str> {
        match self.verdict {
            BeatVerdict::Steady | BeatVerdict::Weak => None,
            BeatVerdict::NoOnsets => Some("a drone, a held tone or silence"),
            _ if self.fluctuation_db < NOISE_FLUCTUATION_DB => Some("noise (its loudness is flat)"),
            _ if self.onset_db > BURST_ONSET_DB => Some("speech or applause (bursts and gaps)"),
            _ => Some("a tonal glide or a whale's song (rare onsets in near-silence)"),
        }
    }
}

/// Measure and judge the beat of `log_mel` (dB, `(n_mels, T)` as [`crate::log_mel`] makes it)
/// at `frame_rate` frames per second. Shorter than one periodicity window, the whole input is
/// one window; with fewer frames than the longest period searched there is no periodicity (0).
pub fn beat_presence(log_mel: ArrayView2<'_, f32>, frame_rate: f64) -> BeatPresence {
    let (bands, frames) = log_mel.dim();
    let mut envelope = vec![0.0f64; frames];
    let mut loudness = vec![0.0f64; frames];
    let per_band = 1.0 / bands.max(1) as f64;
    for (t, frame) in log_mel.columns().into_iter().enumerate() {
        loudness[t] = frame.iter().map(|&v| f64::from(v)).sum::<f64>() * per_band;
        if t > 0 {
            let before = log_mel.column(t - 1);
            envelope[t] = frame
                .iter()
                .zip(before)
                .map(|(&now, &then)| f64::from((now - then).max(0.0)))
                .sum::<f64>()
                * per_band;
        }
    }
    let onset_db = mean(&envelope);
    let periodicity = periodicity(&envelope, frame_rate);
    let fluctuation_db = fluctuation(&loudness, frame_rate);
    let verdict = if onset_db < MIN_ONSET_DB {
        BeatVerdict::NoOnsets
    } else if periodicity >= MIN_PERIODICITY {
        BeatVerdict::Steady
    } else if fluctuation_db < NOISE_FLUCTUATION_DB
        || !(SPARSE_ONSET_DB..=BURST_ONSET_DB).contains(&onset_db)
    {
        BeatVerdict::NoSteadyBeat
    } else {
        BeatVerdict::Weak
    };
    BeatPresence {
        verdict,
        onset_db,
        periodicity,
        fluctuation_db,
    }
}

fn mean(x: &[f64]) -> f64 {
    if x.is_empty() {
        0.0
    } else {
        x.iter().sum::<f64>() / x.len() as f64
    }
}

fn median(mut x: Vec<f64>) -> f64 {
    if x.is_empty() {
        return 0.0;
    }
    x.sort_by(f64::total_cmp);
    let m = x.len();
    if m % 2 == 1 {
        x[m / 2]
    } else {
        0.5 * (x[m / 2 - 1] + x[m / 2])
    }
}

/// Start frames of windows of `win` frames every `hop` over `frames` (one window of all frames
/// when shorter).
fn window_starts(frames: usize, win: usize, hop: usize) -> impl Iterator<Item = usize> {
    let last = frames.saturating_sub(win);
    (0..=last).step_by(hop.max(1))
}

fn periodicity(envelope: &[f64], frame_rate: f64) -> f64 {
    let win = ((PERIODICITY_WINDOW_S * frame_rate).round() as usize).min(envelope.len());
    let hop = (HOP_S * frame_rate).round() as usize;
    let lo = ((PERIOD_RANGE_S.0 * frame_rate).round() as usize).max(1);
    let hi = (PERIOD_RANGE_S.1 * frame_rate).round() as usize;
    if win <= hi {
        return 0.0;
    }
    let hann: Vec<f64> = (0..win)
        .map(|k| 0.5 - 0.5 * (2.0 * std::f64::consts::PI * k as f64 / (win - 1) as f64).cos())
        .collect();
    let mut x = vec![0.0f64; win];
    let peaks = window_starts(envelope.len(), win, hop).map(|start| {
        let part = &envelope[start..start + win];
        let m = mean(part);
        for ((xi, &v), &w) in x.iter_mut().zip(part).zip(&hann) {
            *xi = (v - m) * w;
        }
        let lag = |l: usize| -> f64 { x[..win - l].iter().zip(&x[l..]).map(|(a, b)| a * b).sum() };
        let energy = lag(0);
        if energy <= f64::MIN_POSITIVE {
            return 0.0;
        }
        (lo..=hi).map(lag).fold(f64::NEG_INFINITY, f64::max) / energy
    });
    median(peaks.collect())
}

fn fluctuation(loudness: &[f64], frame_rate: f64) -> f64 {
    let win = ((LOUDNESS_WINDOW_S * frame_rate).round() as usize).min(loudness.len());
    let hop = (HOP_S * frame_rate).round() as usize;
    if win < 2 {
        return 0.0;
    }
    let spreads = window_starts(loudness.len(), win, hop).map(|start| {
        let part = &loudness[start..start + win];
        let m = mean(part);
        (part.iter().map(|v| (v - m).powi(2)).sum::<f64>() / win as f64).sqrt()
    });
    median(spreads.collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mel::{MelOptions, log_mel};

    const SR: u32 = 16_000;

    /// The log-mel the dance packages use (16 kHz, n_fft 2048, hop 512, 80 bands, top_db 80).
    fn presence(y: &[f32]) -> BeatPresence {
        let opts = MelOptions::default();
        let mel = log_mel(y, &opts).unwrap();
        beat_presence(mel.view(), f64::from(SR) / opts.hop_length as f64)
    }

    /// Deterministic white noise in [-1, 1).
    fn noise(n: usize, seed: u64) -> Vec<f32> {
        let mut v = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
        (0..n)
            .map(|_| {
                v ^= v << 13;
                v ^= v >> 7;
                v ^= v << 17;
                (v >> 40) as f32 / (1u64 << 23) as f32 - 1.0
            })
            .collect()
    }

    #[test]
    fn a_click_track_has_a_steady_beat() {
        // 15 s of 10 ms noise bursts every 0.5 s (120 BPM) over quiet noise.
        let mut y: Vec<f32> = noise(SR as usize * 15, 1)
            .iter()
            .map(|v| 0.01 * v)
            .collect();
        let burst = noise(160, 2);
        for b in 0..30 {
            let s = b * SR as usize / 2;
            for (k, v) in burst.iter().enumerate() {
                y[s + k] += 0.8 * v;
            }
        }
        let p = presence(&y);
        assert_eq!(p.verdict, BeatVerdict::Steady, "{p:?}");
        // Every onset repeats two beats later (31.25 frames, the nearest lag 31): 0.83 here, far
        // above the threshold; the 0.5 s lag itself falls between frames 15 and 16.
        assert!(p.periodicity > 0.7, "{p:?}");
    }

    #[test]
    fn white_noise_has_no_steady_beat() {
        let y: Vec<f32> = noise(SR as usize * 15, 3).iter().map(|v| 0.3 * v).collect();
        let p = presence(&y);
        assert_eq!(p.verdict, BeatVerdict::NoSteadyBeat, "{p:?}");
        assert_eq!(p.sounds_like(), Some("noise (its loudness is flat)"));
        // Flat loudness: what makes it noise rather than a piece with a weak beat.
        assert!(p.fluctuation_db < NOISE_FLUCTUATION_DB, "{p:?}");
        assert!(p.periodicity < MIN_PERIODICITY, "{p:?}");
    }

    #[test]
    fn a_drone_and_silence_have_no_onsets() {
        let drone: Vec<f32> = (0..SR as usize * 15)
            .map(|i| {
                let t = i as f32 / SR as f32;
                0.3 * (2.0 * std::f32::consts::PI * 110.0 * t).sin()
                    + 0.2 * (2.0 * std::f32::consts::PI * 165.0 * t).sin()
            })
            .collect();
        let p = presence(&drone);
        assert_eq!(p.verdict, BeatVerdict::NoOnsets, "{p:?}");
        let p = presence(&vec![0.0; SR as usize * 15]);
        assert_eq!(p.verdict, BeatVerdict::NoOnsets, "{p:?}");
        assert_eq!(p.onset_db, 0.0);
    }

    #[test]
    fn bursts_with_gaps_at_no_fixed_period_are_speech_like_not_a_beat() {
        // Syllable-like bursts (50–300 ms of noise) separated by irregular gaps (30–600 ms), as
        // speech is: strong onsets, no period.
        let mut y = vec![0.0f32; SR as usize * 15];
        let mut v = 0x1234_5678u64;
        let mut next = |lo: f64, hi: f64| {
            v ^= v << 13;
            v ^= v >> 7;
            v ^= v << 17;
            lo + (hi - lo) * ((v >> 11) as f64 / (1u64 << 53) as f64)
        };
        let mut t = 0.0;
        let source = noise(y.len(), 5);
        while t < 14.5 {
            let len = next(0.05, 0.3);
            let (a, b) = (
                (t * f64::from(SR)) as usize,
                ((t + len) * f64::from(SR)) as usize,
            );
            for i in a..b.min(y.len()) {
                y[i] = 0.5 * source[i];
            }
            t += len + next(0.03, 0.6);
        }
        let p = presence(&y);
        assert_eq!(p.verdict, BeatVerdict::NoSteadyBeat, "{p:?}");
        assert!(p.onset_db > BURST_ONSET_DB, "{p:?}");
        assert_eq!(
            p.sounds_like(),
            Some("speech or applause (bursts and gaps)")
        );
    }

    #[test]
    fn no_period_but_a_loudness_that_moves_is_a_weak_beat_not_warned_about() {
        // Noise whose level steps to a new value (uniform in ±3 dB) after irregular 0.3–1.2 s:
        // moderate onsets, no period, loudness moving by dB as slow music's does. Periodicity
        // alone would call it beatless; its texture is not speech's, noise's or a drone's.
        let source = noise(SR as usize * 15, 7);
        let mut v = 0x0bad_5eedu64;
        let mut next = |lo: f64, hi: f64| {
            v ^= v << 13;
            v ^= v >> 7;
            v ^= v << 17;
            lo + (hi - lo) * ((v >> 11) as f64 / (1u64 << 53) as f64)
        };
        let mut y = Vec::with_capacity(source.len());
        while y.len() < source.len() {
            let gain = 0.2 * 10f64.powf(next(-3.0, 3.0) / 20.0);
            let n = (next(0.3, 1.2) * f64::from(SR)) as usize;
            let at = y.len();
            y.extend(
                source[at..(at + n).min(source.len())]
                    .iter()
                    .map(|s| (f64::from(*s) * gain) as f32),
            );
        }
        let p = presence(&y);
        assert_eq!(p.verdict, BeatVerdict::Weak, "{p:?}");
        assert!(!p.verdict.lacks_beat() && p.sounds_like().is_none());
    }

    #[test]
    fn measures_match_the_calibration_script_on_a_hand_made_envelope() {
        // A log-mel whose one band steps up 6 dB every 16 frames (0.512 s at 31.25 fps) and
        // falls back the frame after: onset 6/1 dB on those frames, 0 elsewhere.
        let frames = 500;
        let mel =
            ndarray::Array2::from_shape_fn(
                (1, frames),
                |(_, t)| {
                    if t % 16 == 0 { -20.0 } else { -26.0 }
                },
            );
        let p = beat_presence(mel.view(), 31.25);
        // Mean onset: one 6 dB rise per 16 frames, the first frame has none.
        let rises = (1..frames).filter(|t| t % 16 == 0).count() as f64;
        assert!(
            (p.onset_db - 6.0 * rises / frames as f64).abs() < 1e-12,
            "{p:?}"
        );
        // A perfect period inside the search range. Reference: numpy (np.hanning windows of
        // 250 frames every 31, mean removed, np.dot per lag 9..=47, over lag 0, np.median) gives
        // 0.9731843427918486; sums in another order differ in the 15th digit.
        assert!(
            (p.periodicity - 0.973_184_342_791_848_6).abs() < 1e-9,
            "{p:?}"
        );
        // Constant loudness but for the steps: 6 dB every 16 frames in 2 s windows.
        assert!(p.fluctuation_db > 1.0, "{p:?}");
        assert_eq!(p.verdict, BeatVerdict::Steady);
    }
}
