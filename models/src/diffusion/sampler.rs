//! The denoising loop: any [`Scheduler`], classifier-free guidance, in-painting and EDGE's
//! overlap consistency between consecutive windows.

use std::time::Instant;

use ndarray::{Array3, ArrayView3, Axis, Zip, s};

use crate::diffusion::noise::NoiseSource;
use crate::diffusion::schedule::NoiseSchedule;
use crate::diffusion::scheduler::{
    Ddim, Ddpm, DpmSolverPlusPlus, Prediction, Scheduler, SchedulerConfig, TimestepSpacing,
};
use crate::error::{Error, Result};

/// A network that predicts epsilon or x0 from a batch of noisy windows.
///
/// Rows of `x_t` (N, T, D), `t` (N), `music` (N, F, M) and `cond` (N) belong together; `cond` is
/// 1 for conditional rows, 0 for unconditional ones (the network substitutes its null
/// conditioning) and 2 for "content + style" rows of the two-weight guidance.
///
/// Errors: every error means the model cannot be used for this job (the ONNX wrapper names the
/// package and component); the sampler stops and returns it. Non-finite outputs are errors.
pub trait Denoiser {
    /// Predict for every row; returns an array shaped like `x_t`.
    fn predict(
        &mut self,
        x_t: ArrayView3<'_, f32>,
        t: &[i64],
        music: ArrayView3<'_, f32>,
        cond: &[f32],
    ) -> Result<Array3<f32>>;

    /// The sampler is done with this batch of music and condition: release what was kept for
    /// it (e.g. hoisted per-batch results). Default: nothing to release.
    fn finish_batch(&mut self) {}

    /// Which library clip each finished window `x0` (N, T, D) with its `music` comes from, for
    /// the provenance: `None` when the network does not say (the default).
    fn sources(
        &mut self,
        _x0: ArrayView3<'_, f32>,
        _music: ArrayView3<'_, f32>,
    ) -> Result<Option<Vec<usize>>> {
        Ok(None)
    }
}

/// Which reverse process to run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
#[non_exhaustive]
pub enum SamplerKind {
    /// Ancestral DDPM with the "fixed_small" posterior variance ([`Ddpm`]).
    Ddpm,
    /// DDIM; `eta` 0 is deterministic, 1 matches DDPM's variance ([`Ddim`]).
    Ddim,
    /// DPM-Solver++ (2M), deterministic ([`DpmSolverPlusPlus`]).
    #[serde(rename = "dpmsolver++")]
    DpmSolverPlusPlus,
}

impl SamplerKind {
    /// The manifest and command-line spelling.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Ddpm => "ddpm",
            Self::Ddim => "ddim",
            Self::DpmSolverPlusPlus => "dpmsolver++",
        }
    }
}

/// Classifier-free guidance. All rows it needs go through the network in ONE batched call.
#[derive(Debug, Clone, Copy, PartialEq)]
#[non_exhaustive]
pub enum Guidance {
    /// Conditional rows only.
    Off,
    /// `u + w (c - u)` with c = cond 1, u = cond 0 (Ho & Salimans 2022). w = 1 is [`Guidance::Off`].
    Single(f32),
    /// Two weights for style transfer: `u + wc (c - u) + ws (cs - c)` with u = cond 0 (null),
    /// c = cond 1 (content), cs = cond 2 (content and style), after MulSMo's content/style
    /// weights. The cond codes are provisional until a style-transfer package exists.
    Double {
        /// Content weight wc.
        content: f32,
        /// Style weight ws.
        style: f32,
    },
}

impl Guidance {
    /// One weight, as in the manifest and `--guidance`: 1.0 means off (no unconditional pass).
    pub fn from_scale(w: f32) -> Self {
        if w == 1.0 { Self::Off } else { Self::Single(w) }
    }

    /// Fold the network's row groups (cond, uncond, content + style; `n` rows each, in the
    /// order of the cond codes) into one prediction per sample.
    pub fn combine(self, mut out: Array3<f32>, n: usize) -> Array3<f32> {
        match self {
            Self::Off => out,
            Self::Single(w) => {
                let (c, u) = out.view_mut().split_at(Axis(0), n);
                let mut c = c;
                Zip::from(&mut c)
                    .and(&u)
                    .for_each(|c, &u| *c = u + w * (*c - u));
                out.slice_move(s![..n, .., ..])
            }
            Self::Double { content, style } => {
                let (c, rest) = out.view_mut().split_at(Axis(0), n);
                let (u, cs) = rest.split_at(Axis(0), n);
                let mut c = c;
                Zip::from(&mut c).and(&u).and(&cs).for_each(|c, &u, &cs| {
                    *c = u + content * (*c - u) + style * (cs - *c);
                });
                out.slice_move(s![..n, .., ..])
            }
        }
    }

    /// The cond value of each row group, in batch order.
    pub fn cond_codes(self) -> &'static [f32] {
        match self {
            Self::Off => &[1.0],
            Self::Single(_) => &[1.0, 0.0],
            Self::Double { .. } => &[1.0, 0.0, 2.0],
        }
    }
}

/// Sampler settings (diffusers names in parentheses).
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub struct SamplerOptions {
    /// DDPM or DDIM. Default: DDIM.
    pub kind: SamplerKind,
    /// Number of denoising steps (`num_inference_steps`). Default: 50.
    pub steps: usize,
    /// DDIM stochasticity (`eta`); ignored by DDPM. Default: 0.0.
    pub eta: f64,
    /// Added to every "leading" timestep (`steps_offset`). Default: 1 (Stable Diffusion / MLD
    /// configs).
    pub steps_offset: usize,
    /// Timestep spacing; None is the scheduler's diffusers default ("leading" for DDPM and
    /// DDIM, "linspace" for DPM-Solver++). Default: None.
    pub spacing: Option<TimestepSpacing>,
    /// DDIM: alpha_bar after the last step is 1 (true) or `alphas_cumprod[0]` (false)
    /// (`set_alpha_to_one`). Default: false.
    pub set_alpha_to_one: bool,
    /// What the network predicts (`prediction_type`). Default: epsilon.
    pub prediction: Prediction,
    /// Clamp the x0 estimate to [-1, 1] (`clip_sample`, `clip_sample_range` 1). Default: false.
    pub clip_sample: bool,
    /// Classifier-free guidance. Default: off.
    pub guidance: Guidance,
    /// Evaluate the guidance row groups (cond, uncond, ...) in one batched call (true) or one
    /// call per group (false; only to measure what batching gains). Default: true.
    pub batch_guidance: bool,
}

impl Default for SamplerOptions {
    fn default() -> Self {
        Self {
            kind: SamplerKind::Ddim,
            steps: 50,
            eta: 0.0,
            steps_offset: 1,
            spacing: None,
            set_alpha_to_one: false,
            prediction: Prediction::Epsilon,
            clip_sample: false,
            guidance: Guidance::Off,
            batch_guidance: true,
        }
    }
}

/// Frames whose values are known (seed motion, in-betweening keys): at every step they are
/// replaced by their forward-diffused values q(x_t | x_0) (MoFusion), and by the values
/// themselves at the end.
#[derive(Debug, Clone, Copy)]
pub struct Known<'a> {
    /// Known values, (N, T, D) like the sample; only entries under `mask` are read.
    pub values: ArrayView3<'a, f32>,
    /// True where the value is known, (N, T, D).
    pub mask: ArrayView3<'a, bool>,
    /// True: the result holds the known values exactly (in-painting: the last step puts them
    /// in). False: they guide every step but the last, as EDGE's chain copy guides the windows
    /// of a batch, and the result keeps what the model made of them there.
    pub exact: bool,
}

/// One batched sampling job.
#[derive(Debug, Clone, Copy)]
pub struct SampleRequest<'a> {
    /// Music features per row, (N, F, M).
    pub music: ArrayView3<'a, f32>,
    /// Frames per window T and feature dimension D.
    pub window: (usize, usize),
    /// Optional in-painting constraint.
    pub known: Option<Known<'a>>,
    /// x_T, (N, T, D) like the sample; None draws it from the noise source. Known entries are
    /// then re-noised with x_T's values at them, so with a deterministic scheduler the result
    /// depends on x_T and not on the noise source.
    pub init: Option<ArrayView3<'a, f32>>,
    /// EDGE `long_ddim_sample` consistency: after every step but the last, the first `overlap`
    /// frames of window i+1 become the last `overlap` frames of window i (EDGE:
    /// `x[1:, :half] = x[:-1, half:]`). 0 = independent rows. Must be at most T/2.
    pub chain_overlap: usize,
}

/// Counters of one sampling run.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct SampleStats {
    /// Calls of [`Denoiser::predict`] (one per step when guidance is batched).
    pub calls: usize,
    /// Batch rows evaluated in total (calls × rows per call).
    pub rows: usize,
    /// Seconds spent inside [`Denoiser::predict`].
    pub denoiser_seconds: f64,
}

/// A configured sampler: schedule, timesteps and options.
#[derive(Debug, Clone)]
pub struct Sampler {
    schedule: NoiseSchedule,
    options: SamplerOptions,
    timesteps: Vec<i64>,
}

impl Sampler {
    /// Check `options` against `schedule` and compute the timesteps.
    pub fn new(schedule: NoiseSchedule, options: SamplerOptions) -> Result<Self> {
        let bad = |reason: String| Err(Error::Schedule { reason });
        if !(options.eta.is_finite() && options.eta >= 0.0) {
            return bad(format!("eta must be finite and >= 0, got {}", options.eta));
        }
        let weights: &[f32] = match &options.guidance {
            Guidance::Off => &[],
            Guidance::Single(w) => std::slice::from_ref(w),
            Guidance::Double { content, style } => &[*content, *style],
        };
        if weights.iter().any(|w| !w.is_finite()) {
            return bad(format!(
                "guidance weights must be finite, got {:?}",
                options.guidance
            ));
        }
        let mut sampler = Self {
            schedule,
            options,
            timesteps: Vec::new(),
        };
        sampler.timesteps = sampler.scheduler()?.timesteps().to_vec();
        Ok(sampler)
    }

    /// A fresh scheduler of this sampler's kind with its timesteps set (multistep schedulers
    /// keep history, so each batch gets its own).
    pub fn scheduler(&self) -> Result<Box<dyn Scheduler>> {
        let o = &self.options;
        let config = |default: TimestepSpacing| SchedulerConfig {
            prediction: o.prediction,
            clip_sample: o.clip_sample,
            spacing: o.spacing.unwrap_or(default),
            steps_offset: o.steps_offset,
            set_alpha_to_one: o.set_alpha_to_one,
        };
        let schedule = self.schedule.clone();
        let mut scheduler: Box<dyn Scheduler> = match o.kind {
            SamplerKind::Ddim => {
                Box::new(Ddim::new(schedule, config(TimestepSpacing::Leading), o.eta))
            }
            SamplerKind::Ddpm => Box::new(Ddpm::new(schedule, config(TimestepSpacing::Leading))),
            SamplerKind::DpmSolverPlusPlus => Box::new(DpmSolverPlusPlus::new(
                schedule,
                config(TimestepSpacing::Linspace),
            )),
        };
        scheduler.set_timesteps(o.steps)?;
        Ok(scheduler)
    }

    /// The timesteps, largest first.
    pub fn timesteps(&self) -> &[i64] {
        &self.timesteps
    }

    /// The options.
    pub fn options(&self) -> &SamplerOptions {
        &self.options
    }

    /// The schedule.
    pub fn schedule(&self) -> &NoiseSchedule {
        &self.schedule
    }

    /// Denoise a batch from x_T (`request.init`, or noise from `noise`). `progress(done, total)`
    /// is called after every step. The denoiser is told when the batch is done
    /// ([`Denoiser::finish_batch`]), also on error.
    pub fn sample(
        &self,
        denoiser: &mut dyn Denoiser,
        request: &SampleRequest<'_>,
        noise: &mut NoiseSource,
        progress: &mut dyn FnMut(usize, usize),
    ) -> Result<(Array3<f32>, SampleStats)> {
        let result = self.sample_batch(denoiser, request, noise, progress);
        denoiser.finish_batch();
        result
    }

    fn sample_batch(
        &self,
        denoiser: &mut dyn Denoiser,
        request: &SampleRequest<'_>,
        noise: &mut NoiseSource,
        progress: &mut dyn FnMut(usize, usize),
    ) -> Result<(Array3<f32>, SampleStats)> {
        let (n, f, m) = request.music.dim();
        let (frames, dim) = request.window;
        let shape = (n, frames, dim);
        let input = |reason: String| {
            Err(Error::Input {
                what: "sampling request".into(),
                reason,
            })
        };
        if n == 0 || frames == 0 || dim == 0 {
            return input(format!("empty batch or window: {shape:?}"));
        }
        if 2 * request.chain_overlap > frames {
            return input(format!(
                "chain overlap {} exceeds half the window ({frames} frames)",
                request.chain_overlap
            ));
        }
        if let Some(k) = &request.known
            && (k.values.dim() != shape || k.mask.dim() != shape)
        {
            return input(format!(
                "known values {:?} / mask {:?} must be shaped like the sample {shape:?}",
                k.values.dim(),
                k.mask.dim()
            ));
        }
        if let Some(init) = &request.init
            && init.dim() != shape
        {
            return input(format!(
                "initial noise {:?} must be shaped like the sample {shape:?}",
                init.dim()
            ));
        }
        let mut scheduler = self.scheduler()?;
        let codes = self.options.guidance.cond_codes();
        let groups = codes.len();
        let rows = n * groups;
        // Built once; only x_in and t_in change per step.
        let mut music_in = Array3::<f32>::zeros((rows, f, m));
        let mut cond_in = Vec::with_capacity(rows);
        for (g, &code) in codes.iter().enumerate() {
            music_in
                .slice_mut(s![g * n..(g + 1) * n, .., ..])
                .assign(&request.music);
            cond_in.extend(std::iter::repeat_n(code, n));
        }
        let mut x_in = Array3::<f32>::zeros((rows, frames, dim));
        let mut t_in = vec![0i64; rows];
        let mut z = Array3::<f32>::zeros(shape);
        let mut x = match &request.init {
            Some(init) => init.as_standard_layout().into_owned(),
            None => {
                let mut x = Array3::<f32>::zeros(shape);
                fill_noise(noise, &mut x);
                x
            }
        };
        if let Some(k) = &request.known {
            let ab = self.schedule.alpha_bar(self.timesteps[0], 1.0);
            diffuse_known(&mut x, k, ab, request.init.as_ref(), noise);
        }
        let mut stats = SampleStats::default();
        let total = self.timesteps.len();
        for (i, &t) in self.timesteps.iter().enumerate() {
            for g in 0..groups {
                x_in.slice_mut(s![g * n..(g + 1) * n, .., ..]).assign(&x);
            }
            t_in.fill(t);
            let started = Instant::now();
            let out = if self.options.batch_guidance || groups == 1 {
                stats.calls += 1;
                denoiser.predict(x_in.view(), &t_in, music_in.view(), &cond_in)?
            } else {
                let mut out = Array3::<f32>::zeros((rows, frames, dim));
                for g in 0..groups {
                    let r = g * n..(g + 1) * n;
                    let part = denoiser.predict(
                        x_in.slice(s![r.clone(), .., ..]),
                        &t_in[r.clone()],
                        music_in.slice(s![r.clone(), .., ..]),
                        &cond_in[r.clone()],
                    )?;
                    if part.dim() != (n, frames, dim) {
                        return Err(Error::Input {
                            what: "denoiser output".into(),
                            reason: format!(
                                "shape {:?}, expected {:?}",
                                part.dim(),
                                (n, frames, dim)
                            ),
                        });
                    }
                    out.slice_mut(s![r, .., ..]).assign(&part);
                    stats.calls += 1;
                }
                out
            };
            stats.denoiser_seconds += started.elapsed().as_secs_f64();
            stats.rows += rows;
            if out.dim() != (rows, frames, dim) {
                return Err(Error::Input {
                    what: "denoiser output".into(),
                    reason: format!("shape {:?}, expected {:?}", out.dim(), (rows, frames, dim)),
                });
            }
            let guided = self.options.guidance.combine(out, n);
            let step_noise = if scheduler.needs_noise(i) {
                fill_noise(noise, &mut z);
                Some(standard_slice(&z)?)
            } else {
                None
            };
            scheduler.step(
                x.as_slice_mut().ok_or_else(not_contiguous)?,
                standard_slice(&guided)?,
                i,
                step_noise,
            )?;
            let last = i + 1 == total;
            if !last && request.chain_overlap > 0 && n > 1 {
                let ov = request.chain_overlap;
                // Disjoint regions (overlap <= T/2), so a snapshot is not needed.
                let tail = x.slice(s![..n - 1, frames - ov.., ..]).to_owned();
                x.slice_mut(s![1.., ..ov, ..]).assign(&tail);
            }
            if let Some(k) = &request.known {
                if last && k.exact {
                    Zip::from(&mut x)
                        .and(k.values)
                        .and(k.mask)
                        .for_each(|x, &v, &known| {
                            if known {
                                *x = v;
                            }
                        });
                } else if !last {
                    diffuse_known(
                        &mut x,
                        k,
                        scheduler.alpha_bar_after(i),
                        request.init.as_ref(),
                        noise,
                    );
                }
            }
            progress(i + 1, total);
        }
        Ok((x, stats))
    }
}

fn not_contiguous() -> Error {
    Error::Input {
        what: "sample".into(),
        reason: "not a contiguous array".into(),
    }
}

fn standard_slice(a: &Array3<f32>) -> Result<&[f32]> {
    a.as_slice().ok_or_else(not_contiguous)
}

fn fill_noise(noise: &mut NoiseSource, a: &mut Array3<f32>) {
    match a.as_slice_mut() {
        Some(slice) => noise.fill(slice),
        None => a.iter_mut().for_each(|v| *v = noise.normal() as f32),
    }
}

/// Known entries := sqrt(ab) x0 + sqrt(1 - ab) z (forward diffusion q(x_t | x_0)). z is x_T at
/// that entry when x_T was given (so a deterministic sampler stays a function of x_T), else
/// drawn from `noise`.
fn diffuse_known(
    x: &mut Array3<f32>,
    known: &Known<'_>,
    ab: f64,
    init: Option<&ArrayView3<'_, f32>>,
    noise: &mut NoiseSource,
) {
    let (a, b) = (ab.sqrt() as f32, (1.0 - ab).max(0.0).sqrt() as f32);
    match init {
        Some(init) => Zip::from(x)
            .and(known.values)
            .and(known.mask)
            .and(init)
            .for_each(|x, &v, &m, &z| {
                if m {
                    *x = a * v + b * z;
                }
            }),
        // Noise only for known entries (usually a few seed frames), drawn in memory order.
        None => Zip::from(x)
            .and(known.values)
            .and(known.mask)
            .for_each(|x, &v, &m| {
                if m {
                    *x = a * v + b * noise.normal() as f32;
                }
            }),
    }
}

#[cfg(test)]
#[path = "sampler_tests.rs"]
mod tests;
