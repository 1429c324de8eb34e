//! The two denoising loops over one chunk of segments: MCM-LDM's transfer from x_T with style
//! guidance, and MulSMo's DDIM inversion of the content latent then doubly guided denoising.
//! Each batched network call stacks the row groups its guidance combines.

use ndarray::{Array2, Array3, ArrayView2, ArrayView3, Axis, s};

use super::{StyleConfig, StyleDenoiserInputs, StyleNetworks, StylizeStats, UsedSettings, input};
use crate::diffusion::{Guidance, NoiseSource, Sampler};
use crate::error::Result;

/// One chunk of segments: content latent, trajectory, mask, and the style (1, S).
pub(super) struct Batch<'a> {
    pub(super) latent: ArrayView3<'a, f32>,
    pub(super) trajectory: ArrayView3<'a, f32>,
    pub(super) mask: ArrayView2<'a, f32>,
    pub(super) style: ArrayView2<'a, f32>,
}

/// One row group of a batched call: with or without the content latent and the style.
#[derive(Debug, Clone, Copy)]
struct Rows {
    content: bool,
    style: bool,
}

/// The denoiser's step-invariant inputs for `groups` row groups of the batch's n rows, in
/// order: content latent (or zeros), trajectory, mask, style (or zeros).
struct Conditions {
    content: Array3<f32>,
    trajectory: Array3<f32>,
    mask: Array2<f32>,
    style: Array2<f32>,
    n: usize,
}

impl Conditions {
    fn new(batch: &Batch<'_>, groups: &[Rows]) -> Self {
        let (n, a, b) = batch.latent.dim();
        let (_, length, tdim) = batch.trajectory.dim();
        let s = batch.style.ncols();
        let rows = n * groups.len();
        let mut c = Self {
            content: Array3::zeros((rows, a, b)),
            trajectory: Array3::zeros((rows, length, tdim)),
            mask: Array2::zeros((rows, length)),
            style: Array2::zeros((rows, s)),
            n,
        };
        for (g, rows) in groups.iter().enumerate() {
            let r = g * n..(g + 1) * n;
            if rows.content {
                c.content
                    .slice_mut(s![r.clone(), .., ..])
                    .assign(&batch.latent);
            }
            c.trajectory
                .slice_mut(s![r.clone(), .., ..])
                .assign(&batch.trajectory);
            c.mask.slice_mut(s![r.clone(), ..]).assign(&batch.mask);
            if rows.style {
                let style = batch.style.row(0);
                c.style
                    .slice_mut(s![r, ..])
                    .rows_mut()
                    .into_iter()
                    .for_each(|mut row| row.assign(&style));
            }
        }
        c
    }

    /// The network's output for x (n rows) at timestep t, one batched call over all groups.
    fn predict(
        &self,
        nets: &mut dyn StyleNetworks,
        x: &Array3<f32>,
        t: i64,
        stats: &mut StylizeStats,
    ) -> Result<Array3<f32>> {
        let rows = self.content.len_of(Axis(0));
        let groups = rows / self.n;
        let views: Vec<ArrayView3<'_, f32>> = (0..groups).map(|_| x.view()).collect();
        let x_in = ndarray::concatenate(Axis(0), &views)
            .map_err(|e| input("denoiser input", e.to_string()))?;
        let t_in = vec![t; rows];
        let out = nets.denoise(&StyleDenoiserInputs {
            x_t: x_in.view(),
            t: &t_in,
            content: self.content.view(),
            trajectory: self.trajectory.view(),
            mask: self.mask.view(),
            style: self.style.view(),
        })?;
        if out.dim() != x_in.dim() {
            return Err(input(
                "denoiser output",
                format!("shape {:?}, expected {:?}", out.dim(), x_in.dim()),
            ));
        }
        stats.denoiser_calls += 1;
        stats.denoiser_rows += rows;
        Ok(out)
    }
}

fn sampler_for(spec: &StyleConfig, used: &UsedSettings) -> Result<Sampler> {
    let mut o = spec.sampler.clone();
    o.kind = used.sampler;
    o.steps = used.steps;
    o.eta = used.eta;
    Sampler::new(spec.schedule.clone(), o)
}

fn slice_mut(x: &mut Array3<f32>) -> Result<&mut [f32]> {
    x.as_slice_mut()
        .ok_or_else(|| input("sample", "not a contiguous array".into()))
}

fn slice(x: &Array3<f32>) -> Result<&[f32]> {
    x.as_slice()
        .ok_or_else(|| input("sample", "not a contiguous array".into()))
}

/// MCM-LDM's reverse process from x_T with style guidance.
#[allow(clippy::too_many_arguments)]
pub(super) fn transfer(
    nets: &mut dyn StyleNetworks,
    spec: &StyleConfig,
    used: &UsedSettings,
    seed: u64,
    stream: u64,
    batch: &Batch<'_>,
    x_t: ArrayView3<'_, f32>,
    stats: &mut StylizeStats,
    tick: &mut dyn FnMut(),
) -> Result<Array3<f32>> {
    let guidance = Guidance::from_scale(used.guidance);
    // Row groups in the order Guidance::combine reads them: conditional (style), then
    // unconditional (null style); the content latent and trajectory are in both.
    let groups: &[Rows] = match guidance {
        Guidance::Off => &[Rows {
            content: true,
            style: true,
        }],
        _ => &[
            Rows {
                content: true,
                style: true,
            },
            Rows {
                content: true,
                style: false,
            },
        ],
    };
    let cond = Conditions::new(batch, groups);
    let sampler = sampler_for(spec, used)?;
    let mut scheduler = sampler.scheduler()?;
    let mut x = x_t.as_standard_layout().into_owned();
    let mut z = Array3::<f32>::zeros(x.dim());
    // Step noise of stochastic samplers: stream 1 + the chunk's first segment, apart from x_T's.
    let mut noise = NoiseSource::new(seed, 1 + stream);
    for (i, &t) in sampler.timesteps().iter().enumerate() {
        let out = cond.predict(nets, &x, t, stats)?;
        let guided = guidance.combine(out, cond.n);
        let step_noise = if scheduler.needs_noise(i) {
            noise.fill(slice_mut(&mut z)?);
            Some(slice(&z)?)
        } else {
            None
        };
        scheduler.step(slice_mut(&mut x)?, slice(&guided)?, i, step_noise)?;
        tick();
    }
    Ok(x)
}

/// MulSMo: DDIM inversion of the content latent under the content-only condition, then DDIM
/// down the same timesteps with two-weight guidance.
pub(super) fn invert_and_denoise(
    nets: &mut dyn StyleNetworks,
    spec: &StyleConfig,
    used: &UsedSettings,
    batch: &Batch<'_>,
    stats: &mut StylizeStats,
    tick: &mut dyn FnMut(),
) -> Result<Array3<f32>> {
    let (wc, ws) = used.weights.unwrap_or((1.0, 1.0));
    let sampler = sampler_for(spec, used)?;
    let mut scheduler = sampler.scheduler()?;
    // diffusers DDIMInverseScheduler: from the level of t − N/steps (the clean level below 0)
    // up to t, for t in the DDIM timesteps in ascending order.
    let ratio = (spec.schedule.train_steps() / used.steps) as i64;
    let content_only = Conditions::new(
        batch,
        &[Rows {
            content: true,
            style: false,
        }],
    );
    let mut x = batch.latent.to_owned();
    for &t in sampler.timesteps().iter().rev() {
        let eps = content_only.predict(nets, &x, t, stats)?;
        scheduler.inverse_step(slice_mut(&mut x)?, slice(&eps)?, t - ratio, t)?;
        tick();
    }
    // Guidance::Double reads the groups as c (content), u (nothing), cs (content and style).
    let guidance = Guidance::Double {
        content: wc,
        style: ws,
    };
    let cond = Conditions::new(
        batch,
        &[
            Rows {
                content: true,
                style: false,
            },
            Rows {
                content: false,
                style: false,
            },
            Rows {
                content: true,
                style: true,
            },
        ],
    );
    for (i, &t) in sampler.timesteps().iter().enumerate() {
        let out = cond.predict(nets, &x, t, stats)?;
        let guided = guidance.combine(out, cond.n);
        scheduler.step(slice_mut(&mut x)?, slice(&guided)?, i, None)?;
        tick();
    }
    Ok(x)
}
