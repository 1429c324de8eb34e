//! A closed-form denoiser in pure Rust: the optimal denoiser of the empirical distribution of K
//! exemplar windows. It makes the samplers testable without ONNX Runtime: with one exemplar
//! every correct sampler must return it. It shares the shipped `exemplar` package's posterior
//! (the data term below), not its music stage: the package retimes its candidates onto the
//! song's beat (models/packages/exemplar/README.md, checked by `build.py check` against a numpy
//! reference), while this twin's music logit is a small energy-envelope cosine whose only job
//! is to make `cond` matter in the guidance tests.
//!
//! `x0_hat = sum_i w_i e_i` with `w = softmax_i(-||x_t - sqrt(ab_t) e_i||^2 / (2 (1 - ab_t)) +
//! cond · music_logit_i)`: the posterior mean of x_0 given x_t when x_0 is uniform over the
//! exemplars (Karras et al. 2022, eq. 57 discussion); `eps = (x_t - sqrt(ab_t) x0_hat) /
//! sqrt(1 - ab_t)`.

use ndarray::{Array1, Array3, ArrayView3, Axis, s};

use crate::diffusion::sampler::Denoiser;
use crate::diffusion::schedule::NoiseSchedule;
use crate::diffusion::scheduler::Prediction;
use crate::error::{Error, Result};

/// The optimal denoiser over a fixed set of windows.
#[derive(Debug, Clone)]
pub struct ExemplarDenoiser {
    exemplars: Array3<f32>,
    alphas_cumprod: Vec<f64>,
    prediction: Prediction,
    music_weight: f64,
    /// Per exemplar, its per-frame speed envelope (T), centred and unit-norm.
    speed_envelopes: Vec<Vec<f64>>,
}

impl ExemplarDenoiser {
    /// `exemplars` (K, T, D) in normalised units. `music_weight` is lambda of the music logit:
    /// lambda × cosine similarity between the window's mel energy envelope and exemplar i's
    /// joint-speed envelope (both centred, resampled to T); 0 ignores the music.
    pub fn new(
        exemplars: Array3<f32>,
        schedule: &NoiseSchedule,
        prediction: Prediction,
        music_weight: f64,
    ) -> Result<Self> {
        let (k, t, d) = exemplars.dim();
        if k == 0 || t < 2 || d == 0 {
            return Err(Error::Input {
                what: "exemplars".into(),
                reason: format!(
                    "need K >= 1 windows of T >= 2 frames, got {:?}",
                    exemplars.dim()
                ),
            });
        }
        let speed_envelopes = exemplars
            .outer_iter()
            .map(|e| {
                let mut env: Vec<f64> = (0..t)
                    .map(|f| {
                        let (a, b) = if f + 1 < t { (f, f + 1) } else { (f - 1, f) };
                        let diff = &e.row(b) - &e.row(a);
                        diff.iter()
                            .map(|v| f64::from(*v).powi(2))
                            .sum::<f64>()
                            .sqrt()
                    })
                    .collect();
                centre_and_normalise(&mut env);
                env
            })
            .collect();
        Ok(Self {
            exemplars,
            alphas_cumprod: schedule.alphas_cumprod().to_vec(),
            prediction,
            music_weight,
            speed_envelopes,
        })
    }

    /// The music logit of every exemplar for one window's music (F, M).
    fn music_logits(&self, music: ndarray::ArrayView2<'_, f32>) -> Vec<f64> {
        let t = self.exemplars.dim().1;
        let f = music.nrows();
        if self.music_weight == 0.0 || f == 0 {
            return vec![0.0; self.speed_envelopes.len()];
        }
        let energy: Vec<f64> = music
            .axis_iter(Axis(0))
            .map(|row| row.iter().map(|v| f64::from(*v)).sum::<f64>() / row.len().max(1) as f64)
            .collect();
        // Nearest-frame resampling of the mel envelope onto the T motion frames.
        let mut env: Vec<f64> = (0..t).map(|i| energy[(i * f / t).min(f - 1)]).collect();
        centre_and_normalise(&mut env);
        self.speed_envelopes
            .iter()
            .map(|s| self.music_weight * s.iter().zip(&env).map(|(a, b)| a * b).sum::<f64>())
            .collect()
    }
}

fn centre_and_normalise(v: &mut [f64]) {
    let mean = v.iter().sum::<f64>() / v.len().max(1) as f64;
    v.iter_mut().for_each(|x| *x -= mean);
    let norm = v.iter().map(|x| x * x).sum::<f64>().sqrt();
    if norm > 1e-12 {
        v.iter_mut().for_each(|x| *x /= norm);
    }
}

impl Denoiser for ExemplarDenoiser {
    fn predict(
        &mut self,
        x_t: ArrayView3<'_, f32>,
        t: &[i64],
        music: ArrayView3<'_, f32>,
        cond: &[f32],
    ) -> Result<Array3<f32>> {
        let (n, frames, dim) = x_t.dim();
        if (frames, dim) != (self.exemplars.dim().1, self.exemplars.dim().2)
            || t.len() != n
            || cond.len() != n
            || music.dim().0 != n
        {
            return Err(Error::Input {
                what: "exemplar denoiser".into(),
                reason: format!(
                    "inconsistent batch: x_t {:?}, t {}, music {:?}",
                    x_t.dim(),
                    t.len(),
                    music.dim()
                ),
            });
        }
        let mut out = Array3::<f32>::zeros((n, frames, dim));
        for row in 0..n {
            let ab = usize::try_from(t[row])
                .ok()
                .and_then(|i| self.alphas_cumprod.get(i))
                .copied()
                .ok_or_else(|| Error::Input {
                    what: "exemplar denoiser".into(),
                    reason: format!("timestep {} outside the schedule", t[row]),
                })?;
            let (sa, sb) = (ab.sqrt(), (1.0 - ab).sqrt());
            let x = x_t.slice(s![row, .., ..]);
            let logits = if cond[row] > 0.0 {
                self.music_logits(music.slice(s![row, .., ..]))
            } else {
                vec![0.0; self.speed_envelopes.len()]
            };
            // f64: squared distances over T·D entries are summed, then exponentiated.
            let mut scores: Array1<f64> = self
                .exemplars
                .outer_iter()
                .zip(&logits)
                .map(|(e, logit)| {
                    let d2: f64 = x
                        .iter()
                        .zip(e.iter())
                        .map(|(&xv, &ev)| (f64::from(xv) - sa * f64::from(ev)).powi(2))
                        .sum();
                    -d2 / (2.0 * (1.0 - ab)) + logit
                })
                .collect();
            let max = scores.fold(f64::NEG_INFINITY, |a, &b| a.max(b));
            scores.mapv_inplace(|v| (v - max).exp());
            let total = scores.sum();
            let mut o = out.slice_mut(s![row, .., ..]);
            for (e, w) in self.exemplars.outer_iter().zip(scores.iter()) {
                let w = (w / total) as f32;
                o.zip_mut_with(&e, |acc, &ev| *acc += w * ev);
            }
            if self.prediction == Prediction::Epsilon {
                o.zip_mut_with(&x, |x0, &xv| {
                    *x0 = ((f64::from(xv) - sa * f64::from(*x0)) / sb) as f32;
                });
            }
        }
        Ok(out)
    }
}
