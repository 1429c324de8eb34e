//! Band-limited sinc resampling exactly as resampy 0.3.x computes it (the resampler behind
//! librosa 0.7.2's `load` and its CQT octave halvings).
//!
//! The filter tables are generated here from resampy's published parameters
//! (`resampy:resampy/filters.py` `sinc_window`, with the Kaiser parameters of
//! `resampy/data/kaiser_{best,fast}.npz` in resampy 0.3.0/0.3.1): the right wing of a
//! `rolloff`-scaled sinc with `num_zeros` zero crossings and `2^precision` table entries per
//! crossing, tapered by the right half of a symmetric Kaiser window of length `2n + 1`. The
//! interpolation loop follows `resampy:resampy/interpn.py` `_resample_loop`: linear interpolation
//! between table entries, left wing then right wing, the output accumulated in the input's
//! float32 (each `+=` rounds to f32, as numba does for a float32 output array).

use std::collections::HashMap;
use std::sync::OnceLock;

use crate::error::{Error, Result};

/// resampy's two precomputed filters.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum KaiserFilter {
    /// `kaiser_best`: 50 zero crossings, 2^13 entries per crossing, rolloff 0.9173.
    Best,
    /// `kaiser_fast`: 24 zero crossings, 2^9 entries per crossing, rolloff 0.8682.
    Fast,
}

/// Parameters of one filter table.
struct Spec {
    num_zeros: usize,
    precision_bits: u32,
    /// Kaiser β and rolloff to full double precision: the values that regenerate resampy
    /// 0.3.1's `half_window` arrays bit for bit with `scipy.signal.windows.kaiser` and
    /// `np.sinc` (recovered from the stored tables; the docstring rounds them to 12.9846 /
    /// 0.917347 and 9.90322 / 0.868212).
    beta: f64,
    rolloff: f64,
}

impl KaiserFilter {
    fn spec(self) -> Spec {
        match self {
            Self::Best => Spec {
                num_zeros: 50,
                precision_bits: 13,
                beta: 12.984_585_247_040_012,
                rolloff: 0.917_347_371_260_876_1,
            },
            Self::Fast => Spec {
                num_zeros: 24,
                precision_bits: 9,
                beta: 9.903_224_416_455_275,
                rolloff: 0.868_212_038_837_778_4,
            },
        }
    }

    /// The filter's roll-off as a fraction of Nyquist (librosa 0.7.2's `BW_BEST` / `BW_FASTEST`).
    pub fn rolloff(self) -> f64 {
        self.spec().rolloff
    }

    /// The right wing of the interpolation filter and its entries per zero crossing.
    pub fn table(self) -> (&'static [f64], usize) {
        static BEST: OnceLock<Vec<f64>> = OnceLock::new();
        static FAST: OnceLock<Vec<f64>> = OnceLock::new();
        let cell = match self {
            Self::Best => &BEST,
            Self::Fast => &FAST,
        };
        let s = self.spec();
        (
            cell.get_or_init(|| half_window(&s)),
            1usize << s.precision_bits,
        )
    }
}

/// `sinc_window(num_zeros, precision, window=kaiser(beta), rolloff)`.
fn half_window(s: &Spec) -> Vec<f64> {
    let n = (1usize << s.precision_bits) * s.num_zeros;
    let i0_beta = bessel_i0(s.beta);
    // np.linspace(0, num_zeros, n + 1): i * step, the last point exactly num_zeros.
    let step = s.num_zeros as f64 / n as f64;
    (0..=n)
        .map(|i| {
            let x = if i == n {
                s.num_zeros as f64
            } else {
                i as f64 * step
            };
            let sinc = s.rolloff * np_sinc(s.rolloff * x);
            // scipy kaiser(2n+1)[n + i]: alpha = n, r = (n + i - alpha) / alpha.
            let r = i as f64 / n as f64;
            let taper = bessel_i0(s.beta * (1.0 - r * r).max(0.0).sqrt()) / i0_beta;
            taper * sinc
        })
        .collect()
}

/// numpy's normalised sinc, `sin(πx) / (πx)`, 1 at 0.
fn np_sinc(x: f64) -> f64 {
    if x == 0.0 {
        1.0
    } else {
        let y = std::f64::consts::PI * x;
        y.sin() / y
    }
}

/// Modified Bessel function of the first kind, order 0, by its power series
/// `Σ ((x/2)^k / k!)^2` (converges for every finite x; terms stop mattering below 1e-17 of the sum).
fn bessel_i0(x: f64) -> f64 {
    let q = 0.25 * x * x;
    let mut term = 1.0;
    let mut sum = 1.0;
    let mut k = 1.0;
    while term > sum * 1e-17 {
        term *= q / (k * k);
        sum += term;
        k += 1.0;
    }
    sum
}

/// librosa 0.7.2 `resample(y, orig_sr, target_sr, res_type, fix=True, scale)`: resampy's output
/// (`int(len * ratio)` samples), zero-padded or cut to `ceil(len * ratio)`, divided by
/// `sqrt(ratio)` when `scale`. Equal rates return a copy.
///
/// Errors: a non-positive or non-finite rate, or an input too short to yield one sample.
pub fn resample_kaiser(
    x: &[f32],
    orig_sr: f64,
    target_sr: f64,
    filter: KaiserFilter,
    scale: bool,
) -> Result<Vec<f32>> {
    if orig_sr == target_sr && orig_sr > 0.0 && orig_sr.is_finite() {
        return Ok(x.to_vec());
    }
    let (ratio, n_fixed) = librosa_resample_len(x.len(), orig_sr, target_sr)?;
    let n_out = (x.len() as f64 * ratio) as usize;
    if n_out < 1 {
        return Err(too_short_to_resample(x.len()));
    }
    let mut y = resampy(x, ratio, n_out, filter);
    y.resize(n_fixed, 0.0);
    if scale {
        // y_hat /= np.sqrt(ratio) on a float32 array: f32 division by the rounded f64 root.
        let s = ratio.sqrt();
        for v in &mut y {
            *v = (f64::from(*v) / s) as f32;
        }
    }
    Ok(y)
}

/// librosa's `resample` rates checked: the ratio and `fix=True`'s length `ceil(len × ratio)`.
pub(crate) fn librosa_resample_len(
    len: usize,
    orig_sr: f64,
    target_sr: f64,
) -> Result<(f64, usize)> {
    for (name, v) in [("orig_sr", orig_sr), ("target_sr", target_sr)] {
        if !(v > 0.0 && v.is_finite()) {
            return Err(Error::BadOption {
                name,
                value: v.to_string(),
                reason: "must be a positive sample rate",
            });
        }
    }
    let ratio = target_sr / orig_sr;
    Ok((ratio, (len as f64 * ratio).ceil() as usize))
}

pub(crate) fn too_short_to_resample(len: usize) -> Error {
    Error::BadOption {
        name: "signal length",
        value: len.to_string(),
        reason: "too short to resample",
    }
}

/// `resampy.resample(x, 1, ratio, filter)` into `n_out` samples.
fn resampy(x: &[f32], ratio: f64, n_out: usize, filter: KaiserFilter) -> Vec<f32> {
    let (table, num_table) = filter.table();
    // resample(): interp_win = sample_ratio * interp_win when downsampling, and the deltas
    // np.diff(interp_win, append=interp_win[-1]).
    let gain = if ratio < 1.0 { ratio } else { 1.0 };
    let win: Vec<f64> = table.iter().map(|w| gain * w).collect();
    let delta: Vec<f64> = (0..win.len())
        .map(|k| {
            if k + 1 < win.len() {
                win[k + 1] - win[k]
            } else {
                0.0
            }
        })
        .collect();
    // `scale` enters the numba kernel as float32 (its guvectorize signature).
    let scale = f64::from(ratio.min(1.0) as f32);
    let time_increment = 1.0 / ratio;
    let mut y = vec![0.0f32; n_out];
    let threads = if n_out >= 1 << 16 {
        std::thread::available_parallelism().map_or(1, |n| n.get().min(2))
    } else {
        1
    };
    let per = n_out.div_ceil(threads);
    std::thread::scope(|s| {
        for (c, chunk) in y.chunks_mut(per).enumerate() {
            let (win, delta) = (&win, &delta);
            s.spawn(move || {
                let mut kernel = Kernel {
                    x,
                    win,
                    delta,
                    num_table,
                    scale,
                    cache: HashMap::new(),
                };
                // t_out = np.arange(n_out) * time_increment; four outputs at a time so their
                // float32 accumulation chains overlap (each chain is strictly sequential).
                let time = |j: usize| (c * per + j) as f64 * time_increment;
                let mut quads = chunk.chunks_exact_mut(4);
                let mut j = 0;
                for quad in &mut quads {
                    kernel.sample4([time(j), time(j + 1), time(j + 2), time(j + 3)], quad);
                    j += 4;
                }
                for out in quads.into_remainder() {
                    *out = kernel.sample(time(j));
                    j += 1;
                }
            });
        }
    });
    y
}

/// Interpolated filter weights of one fractional phase: left wing, right wing.
type Phase = (Vec<f64>, Vec<f64>);

/// Phases kept per thread. Common rate pairs repeat few phases (44100 → 15360 Hz: 256), and
/// the table lookups they save stride through megabytes of table; a ratio with no short period
/// stops caching here and computes the rest directly.
const MAX_CACHED_PHASES: usize = 4096;

struct Kernel<'a> {
    x: &'a [f32],
    win: &'a [f64],
    delta: &'a [f64],
    num_table: usize,
    scale: f64,
    cache: HashMap<u64, Phase>,
}

impl Kernel<'_> {
    /// One output sample at input time `time` (`_resample_loop`'s body).
    fn sample(&mut self, time: f64) -> f32 {
        let (n, key) = self.locate(time);
        match self.cache.get(&key) {
            Some(phase) => accumulate(phase, self.x, n),
            None => {
                let frac = f64::from_bits(key);
                let phase = (self.weights(frac), self.weights(self.scale - frac));
                accumulate(&phase, self.x, n)
            }
        }
    }

    /// Four samples; falls back to [`Kernel::sample`] when a phase is not cached.
    fn sample4(&mut self, times: [f64; 4], out: &mut [f32]) {
        let located = times.map(|t| self.locate(t));
        let phases: Option<Vec<&Phase>> = located.iter().map(|(_, k)| self.cache.get(k)).collect();
        match phases {
            Some(p) => {
                let ns = located.map(|(n, _)| n);
                out.copy_from_slice(&accumulate4([p[0], p[1], p[2], p[3]], self.x, ns));
            }
            None => {
                for (o, &t) in out.iter_mut().zip(&times) {
                    *o = self.sample(t);
                }
            }
        }
    }

    /// Input index and phase key of output time `time`, caching the phase's weights.
    fn locate(&mut self, time: f64) -> (usize, u64) {
        let n = time as usize;
        let frac = self.scale * (time - n as f64);
        let key = frac.to_bits();
        if !self.cache.contains_key(&key) && self.cache.len() < MAX_CACHED_PHASES {
            let phase = (self.weights(frac), self.weights(self.scale - frac));
            self.cache.insert(key, phase);
        }
        (n, key)
    }

    /// `interp_win[offset + i * index_step] + eta * interp_delta[...]` for every tap of a wing.
    fn weights(&self, frac: f64) -> Vec<f64> {
        let index_step = (self.scale * self.num_table as f64) as usize;
        let index_frac = frac * self.num_table as f64;
        let offset = index_frac as usize;
        let eta = index_frac - offset as f64;
        let taps = (self.win.len() - offset) / index_step;
        (offset..self.win.len())
            .step_by(index_step)
            .take(taps)
            .map(|k| self.win[k] + eta * self.delta[k])
            .collect()
    }
}

/// [`accumulate`] for four outputs at once, each with its own unchanged operation order.
fn accumulate4(phases: [&Phase; 4], x: &[f32], ns: [usize; 4]) -> [f32; 4] {
    let mut acc = [0.0f32; 4];
    let left: [usize; 4] = std::array::from_fn(|l| phases[l].0.len().min(ns[l] + 1));
    let longest = left.iter().copied().max().unwrap_or(0);
    for i in 0..longest {
        for l in 0..4 {
            if i < left[l] {
                let v = f64::from(x[ns[l] - i]);
                acc[l] = (f64::from(acc[l]) + phases[l].0[i] * v) as f32;
            }
        }
    }
    let right: [usize; 4] = std::array::from_fn(|l| phases[l].1.len().min(x.len() - ns[l] - 1));
    let longest = right.iter().copied().max().unwrap_or(0);
    for k in 0..longest {
        for l in 0..4 {
            if k < right[l] {
                let v = f64::from(x[ns[l] + k + 1]);
                acc[l] = (f64::from(acc[l]) + phases[l].1[k] * v) as f32;
            }
        }
    }
    acc
}

/// Left wing over x[n], x[n-1], … then right wing over x[n+1], …; each `+=` rounded to f32.
fn accumulate((left, right): &Phase, x: &[f32], n: usize) -> f32 {
    let mut acc = 0.0f32;
    for (w, &v) in left.iter().zip(x[..=n].iter().rev()) {
        acc = (f64::from(acc) + w * f64::from(v)) as f32;
    }
    for (w, &v) in right.iter().zip(&x[n + 1..]) {
        acc = (f64::from(acc) + w * f64::from(v)) as f32;
    }
    acc
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bessel_i0_matches_known_values() {
        // Abramowitz & Stegun table 9.8: I0(1) = 1.266065878, I0(5) = 27.23987182.
        assert!((bessel_i0(0.0) - 1.0).abs() < 1e-15);
        assert!((bessel_i0(1.0) - 1.266_065_877_752_008_4).abs() < 1e-14);
        assert!((bessel_i0(5.0) - 27.239_871_823_604_45).abs() < 1e-11);
    }

    #[test]
    fn tables_have_resampys_sizes_and_end_points() {
        let (best, p) = KaiserFilter::Best.table();
        assert_eq!((best.len(), p), (409_601, 8192));
        // First entry is the rolloff (sinc(0) = 1, taper 1).
        assert_eq!(best[0], KaiserFilter::Best.rolloff());
        let (fast, p) = KaiserFilter::Fast.table();
        assert_eq!((fast.len(), p), (12_289, 512));
        assert_eq!(fast[0], KaiserFilter::Fast.rolloff());
    }

    #[test]
    fn equal_rates_copy_and_bad_rates_fail() {
        let x = [0.5f32, -0.25, 0.125];
        assert_eq!(
            resample_kaiser(&x, 8000.0, 8000.0, KaiserFilter::Fast, false).unwrap(),
            x
        );
        assert!(resample_kaiser(&x, 0.0, 8000.0, KaiserFilter::Fast, false).is_err());
        assert!(resample_kaiser(&x, 8000.0, f64::NAN, KaiserFilter::Fast, false).is_err());
        assert!(resample_kaiser(&x, 8000.0, 1000.0, KaiserFilter::Fast, false).is_err());
    }
}
