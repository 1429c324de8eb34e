//! Style transfer over a style-transfer package's four networks (`vae_encoder`, `vae_decoder`,
//! `style_encoder`, `denoiser`; contract in models/packages/README.md): MCM-LDM's latent
//! diffusion ([`StyleMode::Transfer`]) and MulSMo's inversion then guided denoising
//! ([`StyleMode::Inversion`]).
//!
//! Both loops follow `models/packages/stylize_reference.py` step by step (the independent
//! reference the end-to-end tests compare against):
//! - content c = (content − mean) / std; trajectory condition = c[:, 0..3]; c[:, 0..3] = 0;
//!   content latent = `vae_encoder(c)` (the posterior mean);
//! - style = `style_encoder(raw style with dims 0..3 zeroed)`, or a precomputed embedding; the
//!   null style is zeros;
//! - **transfer** (XingliangJin/MCM-LDM mld/models/modeltype/mld.py `_diffusion_reverse`):
//!   from x_T, the sampler's steps with classifier-free guidance on the style only,
//!   `e_null + g (e_style − e_null)`, both rows in one batched call;
//! - **inversion** (Li et al. 2024, MulSMo, arXiv 2412.09901): deterministic DDIM inversion
//!   (`DDIMInverseScheduler.step`, [`crate::Scheduler::inverse_step`], the network evaluated at the
//!   timestep moved to) of the content latent under the content-only condition, then DDIM down
//!   the same timesteps with [`Guidance::Double`], `e_u + wc (e_c − e_u) + ws (e_cs − e_c)`
//!   (u: content latent and style zeros, c: content only, cs: content and style; the trajectory
//!   is in every row, as MCM-LDM keeps it in both of its guidance rows). MulSMo's paper states
//!   the content/style weights but its text available to us gives no formula; this is the
//!   SMooDi form (Zhong et al. 2024, eq. 7) the reference loop uses.
//! - decode at the content's length; denormalise.
//!
//! Content longer than the package's `max_frames` is cut into overlapping segments
//! ([`choreo_datasets::plan_segments`]), which are denoised together as rows of one batch (in
//! chunks) and cross-faded back ([`choreo_datasets::stitch_segments`]).

mod denoise;
mod package;

pub use package::{encode_style_package, style_config, stylize_package};

use std::ops::Range;
use std::time::Instant;

use ndarray::{Array2, Array3, ArrayView1, ArrayView2, ArrayView3, ArrayViewD, Axis, s};

use crate::diffusion::{NoiseSchedule, NoiseSource, SamplerKind, SamplerOptions};
use crate::error::{Error, Result};
use denoise::{Batch, invert_and_denoise, transfer};

/// HumanML3D feature channels.
pub const STYLE_FEATURE_DIM: usize = choreo_datasets::humanml3d::FEATURE_DIM;
/// Channels of the trajectory condition: root angular velocity, root xz velocity (dims 0..3).
const TRAJECTORY_DIMS: usize = 3;

/// One batched denoiser call: every array has the same N rows.
#[derive(Debug, Clone, Copy)]
pub struct StyleDenoiserInputs<'a> {
    /// Noisy latent (N, A, B).
    pub x_t: ArrayView3<'a, f32>,
    /// Training timestep per row.
    pub t: &'a [i64],
    /// Content latent (N, A, B), zeros for rows without content.
    pub content: ArrayView3<'a, f32>,
    /// Normalised trajectory (N, T, 3).
    pub trajectory: ArrayView3<'a, f32>,
    /// Valid frames (N, T), 1 = valid.
    pub mask: ArrayView2<'a, f32>,
    /// Style vectors (N, S), zeros for the null style.
    pub style: ArrayView2<'a, f32>,
}

/// The four networks of a style-transfer package (the ONNX components, or anything with the
/// same contract). Errors mean the package cannot be used.
pub trait StyleNetworks {
    /// Normalised features (N, T, 263) with dims 0..3 zeroed → content latent (N, A, B).
    fn encode(
        &mut self,
        features: ArrayView3<'_, f32>,
        mask: ArrayView2<'_, f32>,
    ) -> Result<Array3<f32>>;
    /// Latent (N, A, B) → normalised features (N, T, 263), T = the mask's length.
    fn decode(
        &mut self,
        latent: ArrayView3<'_, f32>,
        mask: ArrayView2<'_, f32>,
    ) -> Result<Array3<f32>>;
    /// Raw-scale features (N, T, 263) with dims 0..3 zeroed → style vectors (N, S).
    fn style(
        &mut self,
        features: ArrayView3<'_, f32>,
        mask: ArrayView2<'_, f32>,
    ) -> Result<Array2<f32>>;
    /// The predicted noise (or x0) for every row, shaped like `x_t`.
    fn denoise(&mut self, inputs: &StyleDenoiserInputs<'_>) -> Result<Array3<f32>>;
    /// Length S of a style vector, when the package fixes it (checked against embeddings).
    fn style_dim(&self) -> Option<usize>;
    /// The loop is done with this batch's conditions (release per-batch caches).
    fn finish_batch(&mut self) {}
}

/// What a style-transfer package declares besides its networks (its manifest).
#[derive(Debug, Clone)]
pub struct StyleConfig {
    /// Frame rate of the features.
    pub fps: f64,
    /// Normalisation of the features, 263 each.
    pub mean: Vec<f32>,
    /// Standard deviations, 263 each.
    pub std: Vec<f32>,
    /// Longest content segment the networks take.
    pub max_frames: usize,
    /// Shortest style motion the style encoder accepts.
    pub min_frames: usize,
    /// The training noise schedule.
    pub schedule: NoiseSchedule,
    /// The package's sampler defaults (kind, steps, eta, spacing, prediction, ...).
    pub sampler: SamplerOptions,
    /// Style classifier-free guidance of transfer mode.
    pub guidance: f32,
    /// Content weight wc of inversion mode.
    pub content_guidance: f32,
    /// Style weight ws of inversion mode.
    pub style_guidance: f32,
    /// DDIM steps of inversion mode (inversion and denoising each).
    pub inversion_steps: usize,
}

/// The two loops.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum StyleMode {
    /// MCM-LDM: denoise from noise conditioned on content latent, trajectory and style.
    #[default]
    Transfer,
    /// MulSMo: invert the content latent to noise, denoise with content and style weights.
    Inversion,
}

impl StyleMode {
    /// The command-line and provenance spelling.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Transfer => "transfer",
            Self::Inversion => "inversion",
        }
    }
}

/// Where the style comes from.
#[derive(Debug, Clone, Copy)]
pub enum StyleReference<'a> {
    /// Raw HumanML3D features (T, 263) of the style motion, through the style encoder.
    Motion(ArrayView2<'a, f32>),
    /// A style vector (S) computed elsewhere (e.g. a text or image encoder's embedding).
    Embedding(ArrayView1<'a, f32>),
}

/// Knobs of [`stylize`]; `None` takes the package's default.
#[derive(Debug, Clone)]
#[non_exhaustive]
pub struct StylizeOptions {
    /// Transfer or inversion.
    pub mode: StyleMode,
    /// Style guidance g (transfer mode).
    pub guidance: Option<f32>,
    /// Content weight wc (inversion mode).
    pub content_guidance: Option<f32>,
    /// Style weight ws (inversion mode).
    pub style_guidance: Option<f32>,
    /// Steps (transfer: the sampler's; inversion: inversion and denoising each).
    pub steps: Option<usize>,
    /// Sampler of transfer mode (inversion is DDIM by definition).
    pub sampler: Option<SamplerKind>,
    /// Seed of x_T (transfer mode) and of stochastic samplers.
    pub seed: u64,
    /// x_T of transfer mode, normalised latent values: the latent's shape without N (every
    /// segment starts from it) or with N = the number of segments.
    pub init_noise: Option<ndarray::ArrayD<f32>>,
    /// Segments denoised together in one batch (bounds memory on long content); 0 is taken
    /// as 1. Default: 16.
    pub chunk_segments: usize,
}

impl Default for StylizeOptions {
    fn default() -> Self {
        Self::new(StyleMode::default())
    }
}

impl StylizeOptions {
    /// Defaults in `mode`: the package's settings, seed 0, 16 segments per batch.
    pub fn new(mode: StyleMode) -> Self {
        Self {
            mode,
            guidance: None,
            content_guidance: None,
            style_guidance: None,
            steps: None,
            sampler: None,
            seed: 0,
            init_noise: None,
            chunk_segments: 16,
        }
    }
}

/// Counters of one run.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct StylizeStats {
    /// Content frames.
    pub frames: usize,
    /// Content segments (1 unless the content is longer than `max_frames`).
    pub segments: usize,
    /// Denoising steps (inversion mode: the same number of inversion steps come first).
    pub steps: usize,
    /// Denoiser calls.
    pub denoiser_calls: usize,
    /// Denoiser rows evaluated (calls × rows per call).
    pub denoiser_rows: usize,
    /// Seconds in the VAE encoder, and in the style encoder for a [`StyleReference::Motion`].
    pub encode_s: f64,
    /// Seconds of the sampling loop(s).
    pub sample_s: f64,
    /// Seconds in the VAE decoder, denormalising and stitching.
    pub decode_s: f64,
}

/// The result of [`stylize`].
#[derive(Debug, Clone)]
pub struct Stylized {
    /// Raw (denormalised) HumanML3D features (T, 263), T = the content's frames.
    pub features: Array2<f32>,
    /// The settings that were used (defaults resolved), for provenance.
    pub used: UsedSettings,
    /// Counters.
    pub stats: StylizeStats,
}

/// The settings a run used after defaults were resolved.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct UsedSettings {
    /// Sampler of the denoising loop.
    pub sampler: SamplerKind,
    /// Denoising steps.
    pub steps: usize,
    /// DDIM eta (0 for inversion mode, which forces deterministic DDIM).
    pub eta: f64,
    /// Style guidance g (transfer mode; 1 in inversion mode).
    pub guidance: f32,
    /// wc and ws (inversion mode only).
    pub weights: Option<(f32, f32)>,
}

fn input(what: &str, reason: String) -> Error {
    Error::Input {
        what: what.into(),
        reason,
    }
}

/// Stylize `content` (raw HumanML3D features (T, 263) at the package's fps) with `style`.
/// `progress(done, total)` counts network steps.
pub fn stylize(
    nets: &mut dyn StyleNetworks,
    spec: &StyleConfig,
    content: ArrayView2<'_, f32>,
    style: StyleReference<'_>,
    options: &StylizeOptions,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<Stylized> {
    check_spec(spec)?;
    let frames = content.nrows();
    check_features("content", content, 1)?;
    let used = resolve(spec, options)?;
    let mut stats = StylizeStats {
        frames,
        steps: used.steps,
        ..StylizeStats::default()
    };

    let t_encode = Instant::now();
    let style_vec = style_vector(nets, spec, style)?;
    let overlap = choreo_datasets::default_overlap(spec.max_frames);
    let segments = choreo_datasets::plan_segments(frames, spec.max_frames, overlap)?;
    stats.segments = segments.len();
    let length = segments[0].len();
    let (normalised, trajectory) = normalise_content(spec, content, &segments);
    let mask = Array2::<f32>::ones((segments.len(), length));
    let latent = encode_chunked(nets, &normalised, &mask, options.chunk_segments.max(1))?;
    stats.encode_s = t_encode.elapsed().as_secs_f64();

    let t_sample = Instant::now();
    let x_t = match options.mode {
        StyleMode::Transfer => Some(initial_noise(options, &latent)?),
        StyleMode::Inversion => None,
    };
    let chunk = options.chunk_segments.max(1);
    let passes = if options.mode == StyleMode::Inversion {
        2
    } else {
        1
    };
    let total = segments.len().div_ceil(chunk) * passes * used.steps;
    let mut done = 0usize;
    let mut out = Array3::<f32>::zeros(latent.dim());
    for start in (0..segments.len()).step_by(chunk) {
        let rows = start..(start + chunk).min(segments.len());
        let batch = Batch {
            latent: latent.slice(s![rows.clone(), .., ..]),
            trajectory: trajectory.slice(s![rows.clone(), .., ..]),
            mask: mask.slice(s![rows.clone(), ..]),
            style: style_vec.view(),
        };
        let mut tick = || {
            done += 1;
            progress(done, total);
        };
        let x = match &x_t {
            Some(x_t) => transfer(
                nets,
                spec,
                &used,
                options.seed,
                start as u64,
                &batch,
                x_t.slice(s![rows.clone(), .., ..]),
                &mut stats,
                &mut tick,
            ),
            None => invert_and_denoise(nets, spec, &used, &batch, &mut stats, &mut tick),
        };
        nets.finish_batch();
        let x = x?;
        out.slice_mut(s![rows, .., ..]).assign(&x);
    }
    stats.sample_s = t_sample.elapsed().as_secs_f64();

    let t_decode = Instant::now();
    let decoded = decode_chunked(nets, &out, &mask, chunk)?;
    let mean = ArrayView1::from(&spec.mean);
    let std = ArrayView1::from(&spec.std);
    let parts: Vec<Array2<f32>> = decoded
        .outer_iter()
        .map(|seg| {
            let mut f = seg.to_owned();
            f.rows_mut().into_iter().for_each(|mut row| {
                row.zip_mut_with(&std, |v, &s| *v *= s);
                row += &mean;
            });
            f
        })
        .collect();
    let views: Vec<ArrayView2<'_, f32>> = parts.iter().map(|p| p.view()).collect();
    let features = choreo_datasets::stitch_segments(frames, &segments, &views)?;
    if let Some(i) = features.iter().position(|v| !v.is_finite()) {
        return Err(input(
            "stylized features",
            format!("value {i} is not finite: the package produced NaN or infinity"),
        ));
    }
    stats.decode_s = t_decode.elapsed().as_secs_f64();
    Ok(Stylized {
        features,
        used,
        stats,
    })
}

fn check_spec(spec: &StyleConfig) -> Result<()> {
    let dims_ok = spec.mean.len() == STYLE_FEATURE_DIM && spec.std.len() == STYLE_FEATURE_DIM;
    let std_ok = spec.std.iter().all(|s| s.is_finite() && *s > 0.0);
    if !dims_ok || !std_ok || spec.max_frames == 0 || spec.min_frames == 0 {
        return Err(Error::Schedule {
            reason: format!(
                "style-transfer package: mean/std must hold {STYLE_FEATURE_DIM} values (std \
                 > 0) and max_frames/min_frames must be > 0; got {}/{} values, max_frames {}, \
                 min_frames {}",
                spec.mean.len(),
                spec.std.len(),
                spec.max_frames,
                spec.min_frames
            ),
        });
    }
    Ok(())
}

fn check_features(what: &str, f: ArrayView2<'_, f32>, min_frames: usize) -> Result<()> {
    if f.ncols() != STYLE_FEATURE_DIM {
        return Err(input(
            what,
            format!(
                "features of shape {:?}, expected (T, {STYLE_FEATURE_DIM})",
                f.shape()
            ),
        ));
    }
    if f.nrows() < min_frames {
        return Err(input(
            what,
            format!(
                "{} frames, the package needs at least {min_frames}",
                f.nrows()
            ),
        ));
    }
    if let Some(i) = f.iter().position(|v| !v.is_finite()) {
        return Err(input(
            what,
            format!(
                "feature value at frame {}, channel {} is not finite",
                i / STYLE_FEATURE_DIM,
                i % STYLE_FEATURE_DIM
            ),
        ));
    }
    Ok(())
}

/// The settings of this run from the options and the package's defaults.
fn resolve(spec: &StyleConfig, options: &StylizeOptions) -> Result<UsedSettings> {
    let finite = |name: &str, w: f32| {
        if w.is_finite() {
            Ok(w)
        } else {
            Err(input(name, format!("{w} is not a finite number")))
        }
    };
    let used = match options.mode {
        StyleMode::Transfer => {
            let sampler = options.sampler.unwrap_or(spec.sampler.kind);
            UsedSettings {
                sampler,
                steps: options.steps.unwrap_or(spec.sampler.steps),
                eta: if sampler == SamplerKind::Ddim {
                    spec.sampler.eta
                } else {
                    0.0
                },
                guidance: finite("guidance", options.guidance.unwrap_or(spec.guidance))?,
                weights: None,
            }
        }
        StyleMode::Inversion => {
            if let Some(kind) = options.sampler.filter(|k| *k != SamplerKind::Ddim) {
                return Err(input(
                    "sampler",
                    format!(
                        "inversion mode inverts and denoises with DDIM; {} has no inverse step \
                         here (transfer mode takes the other samplers)",
                        kind.as_str()
                    ),
                ));
            }
            let wc = options.content_guidance.unwrap_or(spec.content_guidance);
            let ws = options.style_guidance.unwrap_or(spec.style_guidance);
            UsedSettings {
                sampler: SamplerKind::Ddim,
                steps: options.steps.unwrap_or(spec.inversion_steps),
                eta: 0.0,
                guidance: 1.0,
                weights: Some((
                    finite("content guidance", wc)?,
                    finite("style guidance", ws)?,
                )),
            }
        }
    };
    if used.steps == 0 || used.steps > spec.schedule.train_steps() {
        return Err(input(
            "steps",
            format!(
                "{} steps: must be 1..={} (the package's training steps)",
                used.steps,
                spec.schedule.train_steps()
            ),
        ));
    }
    Ok(used)
}

/// The style vector (1, S) from a motion (through the style encoder) or an embedding.
fn style_vector(
    nets: &mut dyn StyleNetworks,
    spec: &StyleConfig,
    style: StyleReference<'_>,
) -> Result<Array2<f32>> {
    let v = match style {
        StyleReference::Motion(f) => {
            check_features("style", f, spec.min_frames)?;
            // The style encoder's position embeddings cover at most max_frames: a longer
            // style motion is represented by its first max_frames frames.
            let used = f.nrows().min(spec.max_frames);
            let mut raw = f.slice(s![..used, ..]).to_owned();
            raw.slice_mut(s![.., ..TRAJECTORY_DIMS]).fill(0.0);
            let raw = raw.insert_axis(Axis(0));
            let mask = Array2::<f32>::ones((1, used));
            nets.style(raw.view(), mask.view())?
        }
        StyleReference::Embedding(e) => {
            if let Some(i) = e.iter().position(|v| !v.is_finite()) {
                return Err(input("style embedding", format!("value {i} is not finite")));
            }
            e.to_owned().insert_axis(Axis(0))
        }
    };
    if let Some(dim) = nets.style_dim()
        && v.dim() != (1, dim)
    {
        return Err(input(
            "style embedding",
            format!("{} values, the package's style vectors have {dim}", v.len()),
        ));
    }
    Ok(v)
}

/// Normalised content segments (n, L, 263) with dims 0..3 zeroed, and their trajectory
/// condition (n, L, 3): the normalised dims 0..3.
fn normalise_content(
    spec: &StyleConfig,
    content: ArrayView2<'_, f32>,
    segments: &[Range<usize>],
) -> (Array3<f32>, Array3<f32>) {
    let length = segments[0].len();
    let mut c = Array3::<f32>::zeros((segments.len(), length, STYLE_FEATURE_DIM));
    let mut trajectory = Array3::<f32>::zeros((segments.len(), length, TRAJECTORY_DIMS));
    for (k, seg) in segments.iter().enumerate() {
        for (i, frame) in seg.clone().enumerate() {
            for d in 0..STYLE_FEATURE_DIM {
                let v = (content[[frame, d]] - spec.mean[d]) / spec.std[d];
                if d < TRAJECTORY_DIMS {
                    trajectory[[k, i, d]] = v;
                } else {
                    c[[k, i, d]] = v;
                }
            }
        }
    }
    (c, trajectory)
}

fn encode_chunked(
    nets: &mut dyn StyleNetworks,
    features: &Array3<f32>,
    mask: &Array2<f32>,
    chunk: usize,
) -> Result<Array3<f32>> {
    let n = features.len_of(Axis(0));
    let mut parts = Vec::new();
    for start in (0..n).step_by(chunk) {
        let r = start..(start + chunk).min(n);
        let latent = nets.encode(
            features.slice(s![r.clone(), .., ..]),
            mask.slice(s![r.clone(), ..]),
        )?;
        if latent.len_of(Axis(0)) != r.len() {
            return Err(input(
                "vae_encoder output",
                format!("{} rows for {} segments", latent.len_of(Axis(0)), r.len()),
            ));
        }
        parts.push(latent);
    }
    concat_rows(&parts)
}

fn decode_chunked(
    nets: &mut dyn StyleNetworks,
    latent: &Array3<f32>,
    mask: &Array2<f32>,
    chunk: usize,
) -> Result<Array3<f32>> {
    let n = latent.len_of(Axis(0));
    let length = mask.ncols();
    let mut parts = Vec::new();
    for start in (0..n).step_by(chunk) {
        let r = start..(start + chunk).min(n);
        let f = nets.decode(
            latent.slice(s![r.clone(), .., ..]),
            mask.slice(s![r.clone(), ..]),
        )?;
        if f.dim() != (r.len(), length, STYLE_FEATURE_DIM) {
            return Err(input(
                "vae_decoder output",
                format!(
                    "shape {:?}, expected {:?}",
                    f.dim(),
                    (r.len(), length, STYLE_FEATURE_DIM)
                ),
            ));
        }
        parts.push(f);
    }
    concat_rows(&parts)
}

fn concat_rows(parts: &[Array3<f32>]) -> Result<Array3<f32>> {
    let views: Vec<ArrayView3<'_, f32>> = parts.iter().map(|p| p.view()).collect();
    ndarray::concatenate(Axis(0), &views)
        .map_err(|e| input("network outputs", format!("rows do not fit together: {e}")))
}

/// x_T for every segment: the given noise (latent shape, or with one row per segment), else
/// seeded Gaussian noise (stream 0 of the seed, drawn for all segments in order).
fn initial_noise(options: &StylizeOptions, latent: &Array3<f32>) -> Result<Array3<f32>> {
    let (n, a, b) = latent.dim();
    let Some(given) = &options.init_noise else {
        let mut x = Array3::<f32>::zeros((n, a, b));
        let mut noise = NoiseSource::new(options.seed, 0);
        noise.fill(x.as_slice_mut().expect("a new array is contiguous"));
        return Ok(x);
    };
    let per_segment = a * b;
    let fits = given.len() == per_segment || given.len() == n * per_segment;
    if !fits || given.iter().any(|v| !v.is_finite()) {
        return Err(input(
            "initial noise",
            format!(
                "need {per_segment} finite values (the latent's shape [{a}, {b}]){}, got \
                 shape {:?}",
                if n > 1 {
                    format!(
                        " or {} (one [{a}, {b}] per segment, {n} segments)",
                        n * per_segment
                    )
                } else {
                    String::new()
                },
                given.shape()
            ),
        ));
    }
    let flat: Vec<f32> = given.iter().copied().collect();
    let x = if given.len() == per_segment {
        let one = ArrayViewD::from_shape(vec![1, a, b], &flat)
            .map_err(|e| input("initial noise", e.to_string()))?;
        one.broadcast(vec![n, a, b])
            .ok_or_else(|| input("initial noise", "cannot broadcast".into()))?
            .to_owned()
    } else {
        ndarray::ArrayD::from_shape_vec(vec![n, a, b], flat)
            .map_err(|e| input("initial noise", e.to_string()))?
    };
    x.into_dimensionality()
        .map_err(|e| input("initial noise", e.to_string()))
}
