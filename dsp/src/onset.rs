//! Onset strength envelope as librosa computes it (`librosa:onset.py` `onset_strength_multi`,
//! librosa 0.11): log-power mel spectrogram (128 bands up to sr/2, `power_to_db` ref 1, amin
//! 1e-10, top_db 80), spectral flux with lag 1 and max_size 1, negative changes discarded, mean
//! over bands, then shifted right by `lag + n_fft / (2 hop)` frames (centre compensation) and
//! trimmed to the spectrogram's length.

use crate::error::Result;
use crate::mel::{MelOptions, log_mel};

/// Parameters of [`onset_strength`]; defaults are librosa's.
#[non_exhaustive]
#[derive(Debug, Clone, PartialEq)]
pub struct OnsetOptions {
    /// FFT size, samples. Default: 2048.
    pub n_fft: usize,
    /// Hop, samples. Default: 512.
    pub hop_length: usize,
    /// Mel bands (librosa `melspectrogram` default). Default: 128.
    pub n_mels: usize,
    /// Frames between the compared spectra (librosa `lag`). Default: 1.
    pub lag: usize,
}

impl Default for OnsetOptions {
    fn default() -> Self {
        Self {
            n_fft: 2048,
            hop_length: 512,
            n_mels: 128,
            lag: 1,
        }
    }
}

/// Onset strength of `samples` at `sample_rate`, one value per mel frame
/// (`1 + floor(len / hop)` values). Errors: invalid options or rate.
pub fn onset_strength(samples: &[f32], sample_rate: u32, opts: &OnsetOptions) -> Result<Vec<f32>> {
    let mel = MelOptions {
        sample_rate,
        n_fft: opts.n_fft,
        hop_length: opts.hop_length,
        n_mels: opts.n_mels,
        fmin: 0.0,
        // librosa: kwargs.setdefault("fmax", 0.5 * sr)
        fmax: f64::from(sample_rate) / 2.0,
        top_db: Some(80.0),
        ..MelOptions::default()
    };
    let s = log_mel(samples, &mel)?;
    let (n_bands, t) = s.dim();
    let lag = opts.lag.max(1);
    let shift = lag + opts.n_fft / (2 * opts.hop_length);
    let mut env = vec![0.0f32; t];
    for (out_t, e) in env.iter_mut().enumerate().skip(shift) {
        // env[out_t] = flux[out_t - shift], flux[j] = mean relu(S[:, j + lag] - S[:, j]).
        let j = out_t - shift;
        if j + lag >= t {
            break;
        }
        // f64 sum: 128 terms, keeps the mean independent of summation order.
        let sum: f64 = (0..n_bands)
            .map(|m| f64::from((s[[m, j + lag]] - s[[m, j]]).max(0.0)))
            .sum();
        *e = (sum / n_bands as f64) as f32;
    }
    Ok(env)
}
