//! Short-time Fourier transform as librosa's `stft` computes it (`librosa:core/spectrum.py`,
//! 0.7.2 and 0.10): centred frames padded by `n_fft / 2` (reflect in 0.7.2, zeros from 0.10 on),
//! the window applied in float64, a float64 FFT, and the result stored as complex64 — so
//! values here are the same float32 numbers librosa holds, up to the FFT's last bits.

use std::sync::Arc;

use realfft::{RealFftPlanner, RealToComplex};
use rustfft::num_complex::Complex;

use crate::error::{Error, Result};

/// How the signal is extended by `n_fft / 2` samples on each side before framing.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PadMode {
    /// Zeros (`np.pad(mode="constant")`, librosa ≥ 0.10's default).
    Constant,
    /// Mirror without repeating the edge (`np.pad(mode="reflect")`, librosa 0.7–0.9's default).
    Reflect,
}

/// Analysis window of [`Stft`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Window {
    /// Periodic Hann (`scipy.signal.get_window("hann", n, fftbins=True)`).
    Hann,
    /// All ones (`"ones"`, the boxcar the CQT frames use).
    Ones,
}

/// A planned STFT of one size.
pub struct Stft {
    n_fft: usize,
    hop: usize,
    pad: PadMode,
    window: Vec<f64>,
    fft: Arc<dyn RealToComplex<f64>>,
}

impl std::fmt::Debug for Stft {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Stft")
            .field("n_fft", &self.n_fft)
            .field("hop", &self.hop)
            .field("pad", &self.pad)
            .finish_non_exhaustive()
    }
}

impl Stft {
    /// Plan an STFT. Errors: `n_fft` odd or below 2, `hop` zero.
    pub fn new(n_fft: usize, hop: usize, window: Window, pad: PadMode) -> Result<Self> {
        if n_fft < 2 || !n_fft.is_multiple_of(2) || n_fft > 1 << 20 {
            return Err(Error::BadOption {
                name: "n_fft",
                value: n_fft.to_string(),
                reason: "must be even, in 2..=1048576",
            });
        }
        if hop == 0 {
            return Err(Error::BadOption {
                name: "hop_length",
                value: hop.to_string(),
                reason: "must be positive",
            });
        }
        let window = match window {
            Window::Hann => (0..n_fft)
                .map(|k| 0.5 - 0.5 * (2.0 * std::f64::consts::PI * k as f64 / n_fft as f64).cos())
                .collect(),
            Window::Ones => vec![1.0; n_fft],
        };
        let fft = RealFftPlanner::<f64>::new().plan_fft_forward(n_fft);
        Ok(Self {
            n_fft,
            hop,
            pad,
            window,
            fft,
        })
    }

    /// Bins per frame, `n_fft / 2 + 1`.
    pub fn n_bins(&self) -> usize {
        self.n_fft / 2 + 1
    }

    /// Frames of a signal of `len` samples: `1 + len / hop`.
    pub fn frame_count(&self, len: usize) -> usize {
        1 + len / self.hop
    }

    /// The shortest signal this STFT accepts: reflect padding needs more than `n_fft / 2`
    /// samples (numpy would mirror repeatedly; librosa's framing then rejects such input).
    pub fn min_len(&self) -> usize {
        match self.pad {
            PadMode::Reflect => self.n_fft / 2 + 1,
            PadMode::Constant => 1,
        }
    }

    /// Sample `j` of the padded signal (`j` counts from the start of the padding).
    fn padded(&self, y: &[f32], j: usize) -> f32 {
        let p = self.n_fft / 2;
        let n = y.len();
        if j >= p && j - p < n {
            return y[j - p];
        }
        match self.pad {
            PadMode::Constant => 0.0,
            PadMode::Reflect if j < p => y[p - j],
            PadMode::Reflect => y[2 * (n - 1) + p - j],
        }
    }

    /// Run `each(frame_index, spectrum)` on every frame, spectra as complex64.
    /// Errors: a signal shorter than [`Stft::min_len`].
    pub fn for_each_frame(
        &self,
        y: &[f32],
        mut each: impl FnMut(usize, &[Complex<f32>]),
    ) -> Result<()> {
        if y.len() < self.min_len() {
            return Err(Error::BadOption {
                name: "signal length",
                value: y.len().to_string(),
                reason: "too short for the analysis window",
            });
        }
        let mut frame = self.fft.make_input_vec();
        let mut spec = self.fft.make_output_vec();
        let mut scratch = self.fft.make_scratch_vec();
        let mut out = vec![Complex::new(0.0f32, 0.0); self.n_bins()];
        let p = self.n_fft / 2;
        for t in 0..self.frame_count(y.len()) {
            let start = t * self.hop;
            // Fast path: the frame lies inside the signal.
            if start >= p && start - p + self.n_fft <= y.len() {
                let s = &y[start - p..start - p + self.n_fft];
                for ((f, &x), &w) in frame.iter_mut().zip(s).zip(&self.window) {
                    *f = w * f64::from(x);
                }
            } else {
                for (k, (f, &w)) in frame.iter_mut().zip(&self.window).enumerate() {
                    *f = w * f64::from(self.padded(y, start + k));
                }
            }
            // Lengths match the plan by construction.
            if self
                .fft
                .process_with_scratch(&mut frame, &mut spec, &mut scratch)
                .is_err()
            {
                spec.fill(Complex::new(0.0, 0.0));
            }
            for (o, c) in out.iter_mut().zip(&spec) {
                *o = Complex::new(c.re as f32, c.im as f32);
            }
            each(t, &out);
        }
        Ok(())
    }

    /// `np.abs(stft(y))` time-major: `(frames, n_bins)` float32 magnitudes (`hypot` of the
    /// complex64 parts, rounded to float32 as numpy's complex64 `abs` does).
    pub fn magnitudes(&self, y: &[f32]) -> Result<Vec<f32>> {
        let nb = self.n_bins();
        let mut mags = vec![0.0f32; self.frame_count(y.len()) * nb];
        self.for_each_frame(y, |t, spec| {
            for (m, c) in mags[t * nb..(t + 1) * nb].iter_mut().zip(spec) {
                *m = f64::from(c.re).hypot(f64::from(c.im)) as f32;
            }
        })?;
        Ok(mags)
    }
}

/// librosa's `power_to_db(S, ref=1, amin=1e-10, top_db=80)` in float32, in place.
pub fn power_to_db(values: &mut [f32], top_db: Option<f32>) {
    for v in values.iter_mut() {
        *v = 10.0 * v.max(1e-10).log10();
    }
    if let Some(top) = top_db {
        crate::mel::clamp_top_db(values, top);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reflect_padding_mirrors_without_the_edge() {
        let s = Stft::new(8, 2, Window::Ones, PadMode::Reflect).unwrap();
        let y = [1.0f32, 2.0, 3.0, 4.0, 5.0, 6.0];
        // np.pad([1..6], 4, mode="reflect") = 5 4 3 2 | 1 2 3 4 5 6 | 5 4 3 2
        let padded: Vec<f32> = (0..14).map(|j| s.padded(&y, j)).collect();
        assert_eq!(
            padded,
            [5., 4., 3., 2., 1., 2., 3., 4., 5., 6., 5., 4., 3., 2.]
        );
        let c = Stft::new(8, 2, Window::Ones, PadMode::Constant).unwrap();
        assert_eq!(c.padded(&y, 0), 0.0);
        assert_eq!(c.padded(&y, 13), 0.0);
    }

    #[test]
    fn ones_window_dc_bin_is_the_frame_sum() {
        let s = Stft::new(4, 4, Window::Ones, PadMode::Constant).unwrap();
        let y = [1.0f32, 2.0, 3.0, 4.0, 5.0];
        let mut dc = Vec::new();
        s.for_each_frame(&y, |_, spec| dc.push(spec[0].re)).unwrap();
        // Frames: [0 0 1 2], [3 4 5 0] → sums 3, 12.
        assert_eq!(dc, vec![3.0, 12.0]);
    }
}
