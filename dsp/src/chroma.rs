//! Chroma energy normalised statistics (CENS) from librosa 0.7.2's constant-Q transform:
//! tuning estimation (`librosa:core/pitch.py` `piptrack`, `estimate_tuning`, `pitch_tuning`),
//! the recursive CQT (`librosa:core/constantq.py` `cqt`, `__cqt_filter_fft`,
//! `__early_downsample`; `librosa:filters.py` `constant_q`, `constant_q_lengths`;
//! `librosa:util/utils.py` `sparsify_rows`) and `chroma_cens` (`librosa:feature/spectral.py`).
//!
//! The CQT filters one octave at a time: the top octave's 12 filters are built once at the
//! full rate, their FFT kept sparse (the smallest coefficients summing to < 1 % of each row's
//! magnitude dropped), and each lower octave reuses them on the signal halved by resampy's
//! `kaiser_fast` filter with `fft_basis *= √2` per octave.

use rustfft::FftPlanner;
use rustfft::num_complex::Complex;

use crate::error::{Error, Result};
use crate::kaiser::{KaiserFilter, resample_kaiser};
use crate::soxr::resample_soxr_hq;
use crate::spectrum::{PadMode, Stft, Window};

/// Hann's equivalent noise bandwidth in bins as librosa tabulates it
/// (`librosa:filters.py` `WINDOW_BANDWIDTHS["hann"]`).
const HANN_BANDWIDTH: f64 = 1.500_183_105_468_75;

/// `note_to_hz("C1")` = 440 · 2^((24 − 69) / 12).
fn c1_hz() -> f64 {
    440.0 * 2f64.powf((24.0 - 69.0) / 12.0)
}

/// `estimate_tuning(y, sr, bins_per_octave)` from the magnitudes of librosa's default STFT of
/// `y` (`n_fft` 2048, hop 512, Hann; `mags` time-major `(frames, n_fft / 2 + 1)`): parabolic
/// peak interpolation in each frame (`piptrack`: bins 150 Hz ≤ f < min(4 kHz, sr/2) that are
/// local maxima above 0.1 × the frame's maximum), the peaks at least as strong as their median
/// kept, and the most common deviation from the equal-tempered grid in a 0.01-bin histogram.
/// Float32 arithmetic where librosa's arrays are float32. Returns the tuning in fractions of a
/// bin, in [-0.5, 0.5).
pub fn estimate_tuning(
    mags: &[f32],
    n_fft: usize,
    sample_rate: f64,
    bins_per_octave: usize,
) -> f64 {
    let nb = n_fft / 2 + 1;
    let fmax = 4000.0f64.min(sample_rate / 2.0);
    // fft_frequencies: np.linspace(0, sr / 2, nb)
    let step = (sample_rate / 2.0) / (nb - 1) as f64;
    let in_band = |k: usize| {
        let f = if k == nb - 1 {
            sample_rate / 2.0
        } else {
            k as f64 * step
        };
        (150.0..fmax).contains(&f)
    };
    let tiny = f32::MIN_POSITIVE;
    let mut pitches: Vec<f32> = Vec::new();
    let mut strengths: Vec<f32> = Vec::new();
    for s in mags.chunks_exact(nb) {
        let ref_value = 0.1f32 * s.iter().copied().fold(f32::NEG_INFINITY, f32::max);
        let masked = |k: usize| if s[k] > ref_value { s[k] } else { 0.0 };
        for k in 1..nb - 1 {
            if !in_band(k) {
                continue;
            }
            // util.localmax with edge padding: x[k] > x[k-1] and x[k] >= x[k+1].
            let x = masked(k);
            if !(x > masked(k - 1) && x >= masked(k + 1)) {
                continue;
            }
            let avg = 0.5f32 * (s[k + 1] - s[k - 1]);
            let mut shift = 2.0f32 * s[k] - s[k + 1] - s[k - 1];
            if shift.abs() < tiny {
                shift += 1.0;
            }
            let shift = avg / shift;
            let dskew = 0.5f32 * avg * shift;
            let pitch = ((k as f64 + f64::from(shift)) * sample_rate / n_fft as f64) as f32;
            if pitch > 0.0 {
                pitches.push(pitch);
                strengths.push(s[k] + dskew);
            }
        }
    }
    if pitches.is_empty() {
        return 0.0;
    }
    let threshold = median_f32(&strengths);
    let residuals: Vec<f32> = pitches
        .iter()
        .zip(&strengths)
        .filter(|&(_, &m)| m >= threshold)
        .map(|(&f, _)| {
            // bins_per_octave * hz_to_octs(f) = bpo * log2(f / (440 / 16)), mod 1, in float32.
            let octs = (f / 27.5f32).log2();
            let r = (bins_per_octave as f32 * octs).rem_euclid(1.0);
            if r >= 0.5 { r - 1.0 } else { r }
        })
        .collect();
    // np.histogram(residual, np.linspace(-0.5, 0.5, 101)): half-open bins, the last closed.
    let n_edges = 101;
    let edge = |i: usize| {
        if i == n_edges - 1 {
            0.5
        } else {
            -0.5 + i as f64 * (1.0 / (n_edges - 1) as f64)
        }
    };
    let mut counts = [0usize; 100];
    for &r in &residuals {
        let r = f64::from(r);
        let mut i = ((r + 0.5) * 100.0).floor().clamp(0.0, 99.0) as usize;
        // Settle the bin by the edges themselves, as numpy's search does.
        while i > 0 && r < edge(i) {
            i -= 1;
        }
        while i < 99 && r >= edge(i + 1) {
            i += 1;
        }
        if r >= edge(0) && r <= edge(100) {
            counts[i] += 1;
        }
    }
    let best = counts
        .iter()
        .enumerate()
        .fold((0, 0), |b, (i, &c)| if c > b.1 { (i, c) } else { b })
        .0;
    edge(best)
}

/// numpy's median of float32 values (mean of the two middle values for an even count, in f32).
fn median_f32(values: &[f32]) -> f32 {
    let mut v = values.to_vec();
    v.sort_by(f32::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        (v[n / 2 - 1] + v[n / 2]) / 2.0
    }
}

/// A CQT option that cannot work.
fn bad(name: &'static str, value: String, reason: &'static str) -> Error {
    Error::BadOption {
        name,
        value,
        reason,
    }
}

/// The octave count of `n_bins`, which must be a positive multiple of `bins_per_octave` (≥ 2).
fn octaves(n_bins: usize, bins_per_octave: usize) -> Result<usize> {
    if bins_per_octave < 2 || n_bins == 0 || !n_bins.is_multiple_of(bins_per_octave) {
        return Err(bad(
            "n_bins",
            n_bins.to_string(),
            "must be a positive multiple of bins_per_octave (at least 2)",
        ));
    }
    Ok(n_bins / bins_per_octave)
}

/// The signal is shorter than the CQT's decimation needs.
fn too_short(len: usize) -> Error {
    bad("signal length", len.to_string(), "too short for the CQT")
}

/// One sparse row of the CQT's frequency-domain basis.
struct SparseRow {
    cols: Vec<usize>,
    vals: Vec<Complex<f64>>,
}

/// librosa 0.7.2 `np.abs(cqt(y, sr, hop_length, fmin=C1, n_bins, bins_per_octave, tuning))`,
/// `(n_bins, frames)` row-major, float64 as librosa's array (its CQT products are complex128).
/// `n_bins` must be a multiple of `bins_per_octave`; `hop` must be divisible by
/// `2^(octaves − 1)`. Errors: those, a pass band beyond Nyquist, a signal too short.
pub fn cqt_magnitude_07(
    y: &[f32],
    sample_rate: f64,
    hop: usize,
    n_bins: usize,
    bins_per_octave: usize,
    tuning: f64,
    sparsity: f64,
) -> Result<(Vec<f64>, usize)> {
    let n_octaves = octaves(n_bins, bins_per_octave)?;
    let bpo = bins_per_octave as f64;
    let fmin = c1_hz() * 2f64.powf(tuning / bpo);
    let freq = |k: usize| fmin * 2f64.powf(k as f64 / bpo);
    let q = 1.0 / (2f64.powf(1.0 / bpo) - 1.0);
    let mut fmin_t = freq(n_bins - bins_per_octave);
    let fmax_t = freq(n_bins - 1);
    let filter_cutoff = fmax_t * (1.0 + 0.5 * HANN_BANDWIDTH / q);
    let nyquist = sample_rate / 2.0;
    if filter_cutoff > nyquist {
        return Err(bad(
            "sample rate",
            sample_rate.to_string(),
            "the CQT's top filters lie beyond Nyquist",
        ));
    }
    let fast_bw = KaiserFilter::Fast.rolloff();
    let mut res = if filter_cutoff < fast_bw * nyquist {
        KaiserFilter::Fast
    } else {
        KaiserFilter::Best
    };
    // __early_downsample: halve the rate while the top octave still fits kaiser_fast's band.
    let mut my_y = y.to_vec();
    let mut sr = sample_rate;
    let mut my_hop = hop;
    let count1 = ((fast_bw * nyquist / filter_cutoff).log2().ceil() as i64 - 2).max(0);
    let count2 = (hop.trailing_zeros() as i64 - n_octaves as i64 + 1).max(0);
    let early = count1.min(count2);
    if early > 0 && res == KaiserFilter::Fast {
        let factor = 1usize << early;
        if my_y.len() < factor {
            return Err(too_short(y.len()));
        }
        my_hop /= factor;
        let new_sr = sr / factor as f64;
        my_y = resample_kaiser(&my_y, sr, new_sr, res, true)?;
        sr = new_sr;
    }
    let mut responses: Vec<(Vec<f64>, usize)> = Vec::new();
    let mut octaves_left = n_octaves;
    if res == KaiserFilter::Best {
        // The top octave at the full rate, then kaiser_fast halvings for the rest.
        let (basis, n_fft) = filter_fft(sr, fmin_t, bins_per_octave, sparsity);
        responses.push(response(
            &my_y,
            n_fft,
            my_hop,
            &basis,
            1.0,
            PadMode::Reflect,
        )?);
        fmin_t /= 2.0;
        octaves_left -= 1;
        res = KaiserFilter::Fast;
    }
    if (my_hop.trailing_zeros() as usize) + 1 < octaves_left {
        return Err(bad(
            "hop_length",
            hop.to_string(),
            "must be a multiple of 2^(octaves - 1)",
        ));
    }
    let (basis, n_fft) = filter_fft(sr, fmin_t, bins_per_octave, sparsity);
    let mut gain = 1.0f64;
    for i in 0..octaves_left {
        if i > 0 {
            if my_y.len() < 2 {
                return Err(too_short(y.len()));
            }
            my_y = resample_kaiser(&my_y, 2.0, 1.0, res, true)?;
            gain *= std::f64::consts::SQRT_2;
            my_hop /= 2;
        }
        responses.push(response(
            &my_y,
            n_fft,
            my_hop,
            &basis,
            gain,
            PadMode::Reflect,
        )?);
    }
    // __trim_stack: the common frame count, lowest octave first.
    let frames = responses.iter().map(|r| r.1).min().unwrap_or(0);
    let mut out = vec![0.0f64; n_bins * frames];
    // constant_q_lengths(sr, fmin, n_bins) at the rate after early downsampling:
    // C /= sqrt(lengths).
    for (o, (resp, _)) in responses.iter().rev().enumerate() {
        for b in 0..bins_per_octave {
            let row = o * bins_per_octave + b;
            let length = q * sr / freq(row);
            let norm = length.sqrt();
            for t in 0..frames {
                out[row * frames + t] = resp[t * bins_per_octave + b] / norm;
            }
        }
    }
    Ok((out, frames))
}

/// librosa 0.10.1 `np.abs(cqt(y, sr, hop_length, fmin=C1, n_bins, bins_per_octave, tuning))`
/// (`vqt` with `gamma=0`, `res_type="soxr_hq"`), `(n_bins, frames)` row-major in float64 (librosa
/// holds it in complex64; the difference is float32 rounding). Each octave gets its own filters
/// (`filters.wavelet` with per-bin bandwidths from `_relative_bandwidth`), built at that
/// octave's rate, the signal halved by soxr between octaves; `n_bins` must be a multiple of
/// `bins_per_octave`. Errors: as [`cqt_magnitude_07`].
pub fn cqt_magnitude_010(
    y: &[f32],
    sample_rate: f64,
    hop: usize,
    n_bins: usize,
    bins_per_octave: usize,
    tuning: f64,
    sparsity: f64,
) -> Result<(Vec<f64>, usize)> {
    let n_octaves = octaves(n_bins, bins_per_octave)?;
    let bpo = bins_per_octave as f64;
    let fmin = c1_hz() * 2f64.powf(tuning / bpo);
    // interval_frequencies(intervals="equal"): fmin × (2^octave ⊗ 2^(k / bpo)), sorted.
    let freqs: Vec<f64> = (0..n_bins)
        .map(|k| {
            let octave = (k / bins_per_octave) as f64;
            2f64.powf(octave) * 2f64.powf((k % bins_per_octave) as f64 / bpo) * fmin
        })
        .collect();
    let alpha = relative_bandwidth(&freqs);
    let filter_cutoff = freqs
        .iter()
        .zip(&alpha)
        .map(|(f, a)| f * (1.0 + 0.5 * HANN_BANDWIDTH / (1.0 / a)))
        .fold(f64::NEG_INFINITY, f64::max);
    let nyquist = sample_rate / 2.0;
    if filter_cutoff > nyquist {
        return Err(bad(
            "sample rate",
            sample_rate.to_string(),
            "the CQT's top filters lie beyond Nyquist",
        ));
    }
    // __early_downsample(_count): halve while the top filter stays two octaves under Nyquist.
    let count1 = ((nyquist / filter_cutoff).log2().ceil() as i64 - 2).max(0);
    let count2 = (hop.trailing_zeros() as i64 - n_octaves as i64 + 1).max(0);
    let early = count1.min(count2);
    let mut my_y = y.to_vec();
    let mut sr = sample_rate;
    let mut my_hop = hop;
    if early > 0 {
        let factor = 1usize << early;
        if my_y.len() < factor {
            return Err(too_short(y.len()));
        }
        my_hop /= factor;
        my_y = resample_soxr_hq(&my_y, factor as f64, 1.0, true)?;
        sr /= factor as f64;
    }
    let mut my_sr = sr;
    let mut responses: Vec<(Vec<f64>, usize)> = Vec::with_capacity(n_octaves);
    for i in 0..n_octaves {
        let top = n_bins - i * bins_per_octave;
        let range = top - bins_per_octave..top;
        let (basis, n_fft) = wavelet_fft(
            my_sr,
            &freqs[range.clone()],
            &alpha[range],
            sparsity,
            (sr / my_sr).sqrt(),
        );
        responses.push(response(
            &my_y,
            n_fft,
            my_hop,
            &basis,
            1.0,
            PadMode::Constant,
        )?);
        if my_hop.is_multiple_of(2) && i + 1 < n_octaves {
            if my_y.len() < 2 {
                return Err(too_short(y.len()));
            }
            my_hop /= 2;
            my_sr /= 2.0;
            my_y = resample_soxr_hq(&my_y, 2.0, 1.0, true)?;
        }
    }
    // __trim_stack (top octave first, placed from the last row down), then V /= sqrt(lengths)
    // at the rate after early downsampling.
    let frames = responses.iter().map(|r| r.1).min().unwrap_or(0);
    let lengths = wavelet_lengths(&freqs, &alpha, sr);
    let mut out = vec![0.0f64; n_bins * frames];
    for (i, (resp, _)) in responses.iter().enumerate() {
        let first = n_bins - (i + 1) * bins_per_octave;
        for b in 0..bins_per_octave {
            let row = first + b;
            let norm = lengths[row].sqrt();
            for t in 0..frames {
                out[row * frames + t] = resp[t * bins_per_octave + b] / norm;
            }
        }
    }
    Ok((out, frames))
}

/// `filters._relative_bandwidth`: each bin's bandwidth from its neighbours' log-frequency
/// spacing (one-sided at the ends), `alpha = (2^(2/bpo) − 1) / (2^(2/bpo) + 1)`.
fn relative_bandwidth(freqs: &[f64]) -> Vec<f64> {
    let n = freqs.len();
    let logf: Vec<f64> = freqs.iter().map(|f| f.log2()).collect();
    (0..n)
        .map(|i| {
            let bpo = if i == 0 {
                1.0 / (logf[1] - logf[0])
            } else if i == n - 1 {
                1.0 / (logf[n - 1] - logf[n - 2])
            } else {
                2.0 / (logf[i + 1] - logf[i - 1])
            };
            let r = 2f64.powf(2.0 / bpo);
            (r - 1.0) / (r + 1.0)
        })
        .collect()
}

/// `filters.wavelet_lengths` with gamma 0 and filter_scale 1: Q = 1 / alpha, length = Q · sr / f.
fn wavelet_lengths(freqs: &[f64], alpha: &[f64], sr: f64) -> Vec<f64> {
    freqs
        .iter()
        .zip(alpha)
        .map(|(f, a)| (1.0 / a) * sr / (f + 0.0))
        .collect()
}

/// `__vqt_filter_fft(sr, freqs, filter_scale=1, norm=1, sparsity, window="hann", gamma=0,
/// dtype=complex64, alpha)` followed by `fft_basis *= gain`: sparse complex64 rows of the FFT of
/// the `filters.wavelet` filters, and the FFT size.
fn wavelet_fft(
    sr: f64,
    freqs: &[f64],
    alpha: &[f64],
    sparsity: f64,
    gain: f64,
) -> (Vec<SparseRow>, usize) {
    let lengths = wavelet_lengths(freqs, alpha, sr);
    let max_len = lengths.iter().copied().fold(0.0, f64::max);
    let n_fft = 2f64.powf(max_len.log2().ceil()) as usize;
    let rows = lengths
        .iter()
        .zip(freqs)
        .map(|(&ilen, &freq)| {
            let buf = padded_filter_fft(ilen, freq, sr, n_fft);
            let mut row = sparsify(&buf, sparsity);
            for v in &mut row.vals {
                // Stored complex64, then scaled in place on that array.
                let v32 = round_c32(*v);
                *v = round_c32(v32 * gain);
            }
            row
        })
        .collect();
    (rows, n_fft)
}

/// A complex value rounded to complex64's precision.
fn round_c32(c: Complex<f64>) -> Complex<f64> {
    Complex::new(f64::from(c.re as f32), f64::from(c.im as f32))
}

/// The FFT (first `n_fft / 2 + 1` bins) of one Hann-windowed, L1-normalised complex sinusoid of
/// frequency `freq` and length `ilen` (`np.arange(-ilen // 2, ilen // 2)` samples), centred in
/// `n_fft` samples, stored as complex64 and scaled by `ilen / n_fft` (librosa's filters before
/// their FFT, identical in 0.7.2's `constant_q` and 0.10's `wavelet`).
fn padded_filter_fft(ilen: f64, freq: f64, sr: f64, n_fft: usize) -> Vec<Complex<f64>> {
    // np.arange(-ilen // 2, ilen // 2): float start/stop, ceil(stop - start) points.
    let start = (-ilen / 2.0).floor();
    let stop = (ilen / 2.0).floor();
    let n = (stop - start).ceil() as usize;
    // Periodic Hann of the filter's length (librosa's __float_window at an integer size).
    let sig: Vec<Complex<f64>> = (0..n)
        .map(|i| {
            let t = start + i as f64;
            let w = 0.5 - 0.5 * (2.0 * std::f64::consts::PI * i as f64 / n as f64).cos();
            Complex::from_polar(1.0, t * 2.0 * std::f64::consts::PI * freq / sr) * w
        })
        .collect();
    let l1: f64 = sig.iter().map(|c| c.norm()).sum();
    let l1 = if l1 < f64::MIN_POSITIVE { 1.0 } else { l1 };
    // util.pad_center into n_fft, stored as complex64, then scaled by length / n_fft (in place
    // on the complex64 array).
    let lpad = (n_fft - n) / 2;
    let mut buf = vec![Complex::new(0.0f64, 0.0); n_fft];
    for (b, s) in buf[lpad..lpad + n].iter_mut().zip(&sig) {
        *b = round_c32(round_c32(s / l1) * (ilen / n_fft as f64));
    }
    FftPlanner::<f64>::new()
        .plan_fft_forward(n_fft)
        .process(&mut buf);
    buf.truncate(n_fft / 2 + 1);
    buf
}

/// `__cqt_filter_fft(sr, fmin, n_bins=bpo, bpo, filter_scale=1, norm=1, sparsity)`: sparse rows
/// of the FFT of the time-domain filters, and the FFT size.
fn filter_fft(sr: f64, fmin: f64, bpo: usize, sparsity: f64) -> (Vec<SparseRow>, usize) {
    let q = 1.0 / (2f64.powf(1.0 / bpo as f64) - 1.0);
    let lengths: Vec<f64> = (0..bpo)
        .map(|k| q * sr / (fmin * 2f64.powf(k as f64 / bpo as f64)))
        .collect();
    let max_len = lengths.iter().copied().fold(0.0, f64::max);
    let n_fft = 2f64.powf(max_len.log2().ceil()) as usize;
    let rows = lengths
        .iter()
        .map(|&ilen| {
            let buf = padded_filter_fft(ilen, q * sr / ilen, sr, n_fft);
            sparsify(&buf, sparsity)
        })
        .collect();
    (rows, n_fft)
}

/// `sparsify_rows` for one row: drop the smallest magnitudes whose sum stays below
/// `quantile` of the row's total.
fn sparsify(row: &[Complex<f64>], quantile: f64) -> SparseRow {
    let mags: Vec<f64> = row.iter().map(|c| c.norm()).collect();
    let total: f64 = mags.iter().sum();
    let mut sorted = mags.clone();
    sorted.sort_by(f64::total_cmp);
    // threshold_idx = argmin(cumsum(sorted / total) < quantile): the first index not below.
    let mut cum = 0.0;
    let mut j = sorted.len() - 1;
    for (i, m) in sorted.iter().enumerate() {
        cum += m / total;
        if cum >= quantile {
            j = i;
            break;
        }
    }
    let threshold = sorted[j];
    let (cols, vals) = row
        .iter()
        .zip(&mags)
        .enumerate()
        .filter(|(_, (_, m))| **m >= threshold)
        .map(|(k, (c, _))| (k, *c))
        .unzip();
    SparseRow { cols, vals }
}

/// `|fft_basis · stft(y, n_fft, hop, window="ones", pad_mode)|` × `gain`, time-major
/// `(frames, rows)`, and the frame count.
fn response(
    y: &[f32],
    n_fft: usize,
    hop: usize,
    basis: &[SparseRow],
    gain: f64,
    pad: PadMode,
) -> Result<(Vec<f64>, usize)> {
    let stft = Stft::new(n_fft, hop, Window::Ones, pad)?;
    let frames = stft.frame_count(y.len());
    let mut out = vec![0.0f64; frames * basis.len()];
    stft.for_each_frame(y, |t, spec| {
        for (r, row) in basis.iter().enumerate() {
            let mut acc = Complex::new(0.0f64, 0.0);
            for (&k, v) in row.cols.iter().zip(&row.vals) {
                let s = spec[k];
                acc += v * Complex::new(f64::from(s.re), f64::from(s.im));
            }
            out[t * basis.len() + r] = acc.norm() * gain;
        }
    })?;
    Ok((out, frames))
}

/// librosa's `chroma_cens` from a CQT magnitude `(n_bins, frames)` starting at C with
/// `bins_per_octave` a multiple of 12 (12 in librosa 0.7.2, 36 from 0.10 on): bins folded into 12
/// pitch classes by `filters.cq_to_chroma` (each class takes its `bpo / 12` bins centred on the
/// pitch, every octave), each frame L1-normalised, quantised with steps 0.4 / 0.2 / 0.1 / 0.05
/// (weight 0.25 each), smoothed along time by a 41-point Hann (symmetric, 43 points with zero
/// ends, unit sum, zero-filled boundaries) and L2-normalised. Returns `(12, frames)` row-major.
pub fn chroma_cens(cqt: &[f64], n_bins: usize, bins_per_octave: usize, frames: usize) -> Vec<f64> {
    const N_CHROMA: usize = 12;
    let n_merge = (bins_per_octave / N_CHROMA).max(1);
    let mut chroma = vec![0.0f64; N_CHROMA * frames];
    for b in 0..n_bins {
        // cq_to_chroma is 0/1: np.repeat(eye(12), n_merge) rolled left by n_merge // 2.
        let c = ((b % bins_per_octave + n_merge / 2) % bins_per_octave) / n_merge;
        for t in 0..frames {
            chroma[c * frames + t] += cqt[b * frames + t];
        }
    }
    normalize_columns(&mut chroma, frames, 1);
    let quant: Vec<f64> = chroma
        .iter()
        .map(|&x| {
            [0.4, 0.2, 0.1, 0.05]
                .iter()
                .map(|&s| if x > s { 0.25 } else { 0.0 })
                .sum()
        })
        .collect();
    // scipy get_window("hann", 43, fftbins=False) / sum.
    let n = 43usize;
    let win: Vec<f64> = (0..n)
        .map(|k| 0.5 - 0.5 * (2.0 * std::f64::consts::PI * k as f64 / (n - 1) as f64).cos())
        .collect();
    let wsum: f64 = win.iter().sum();
    let win: Vec<f64> = win.iter().map(|w| w / wsum).collect();
    let half = n / 2;
    let mut cens = vec![0.0f64; N_CHROMA * frames];
    for c in 0..N_CHROMA {
        let q = &quant[c * frames..(c + 1) * frames];
        for t in 0..frames {
            // convolve2d(mode="same", boundary="fill"): out[t] = Σ_j q[t + half - j] w[j].
            let mut acc = 0.0;
            for (j, w) in win.iter().enumerate() {
                let idx = t as isize + half as isize - j as isize;
                if idx >= 0 && (idx as usize) < frames {
                    acc += q[idx as usize] * w;
                }
            }
            cens[c * frames + t] = acc;
        }
    }
    normalize_columns(&mut cens, frames, 2);
    cens
}

/// `util.normalize(S, norm, axis=0)` for `norm` 1 or 2 on a `(rows, frames)` array: columns
/// whose norm is below the smallest normal f64 are left as they are.
fn normalize_columns(x: &mut [f64], frames: usize, norm: u8) {
    let rows = x.len() / frames.max(1);
    for t in 0..frames {
        let len = match norm {
            1 => (0..rows).map(|r| x[r * frames + t].abs()).sum::<f64>(),
            _ => (0..rows)
                .map(|r| x[r * frames + t].powi(2))
                .sum::<f64>()
                .sqrt(),
        };
        let len = if len < f64::MIN_POSITIVE { 1.0 } else { len };
        for r in 0..rows {
            x[r * frames + t] /= len;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sparsify_drops_only_the_smallest_one_percent() {
        let row: Vec<Complex<f64>> = [50.0, 30.0, 19.5, 0.3, 0.2]
            .iter()
            .map(|&m| Complex::new(m, 0.0))
            .collect();
        let s = sparsify(&row, 0.01);
        // 0.2 + 0.3 = 0.5 % of 100 < 1 %; adding 19.5 exceeds it: keep 50, 30, 19.5.
        assert_eq!(s.cols, vec![0, 1, 2]);
    }

    #[test]
    fn cens_columns_have_unit_l2_norm_and_silence_stays_zero() {
        let frames = 50;
        let mut cqt = vec![0.0; 84 * frames];
        for t in 10..frames {
            cqt[36 * frames + t] = 1.0; // a C
            cqt[40 * frames + t] = 0.5; // an E
        }
        let c = chroma_cens(&cqt, 84, 12, frames);
        for t in 0..frames {
            let n: f64 = (0..12).map(|r| c[r * frames + t].powi(2)).sum();
            assert!(n == 0.0 || (n - 1.0).abs() < 1e-12, "frame {t}: {n}");
        }
        assert!(c[frames - 1] > c[4 * frames + frames - 1]);
    }
}
