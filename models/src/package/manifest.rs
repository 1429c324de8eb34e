//! The model package manifest `choreod-model.toml` (package layer): parsed with serde, unknown
//! keys refused, then validated for its [`Task`]: each task checks the sections and components
//! ([`Role`]s) it runs and refuses the other tasks' keys. Every error names the package
//! directory and the key.
//!
//! The schema is the package contract (models/packages/README.md, DESIGN.md "Model packages").

use std::collections::BTreeMap;
use std::path::{Component, Path, PathBuf};

use serde::Deserialize;

use crate::diffusion::sampler::{Guidance, Sampler, SamplerKind, SamplerOptions};
use crate::diffusion::schedule::{BetaSchedule, NoiseSchedule};
use crate::diffusion::scheduler::Prediction;
use crate::diffusion::scheduler::TimestepSpacing;
use crate::error::{Error, Result};
use crate::runtime::component::read_regular_file;
pub(crate) use crate::runtime::contract::shape_text;
pub use crate::runtime::contract::{ComponentSpec, DType, Dim, TensorSpec};

/// A semantic check that failed: the manifest key and what is wrong with its value.
#[derive(Debug)]
struct KeyError {
    key: String,
    reason: String,
}

impl KeyError {
    fn new(key: impl Into<String>, reason: String) -> Self {
        Self {
            key: key.into(),
            reason,
        }
    }
}

/// The manifest's file name inside a package directory.
pub const MANIFEST_FILE: &str = "choreod-model.toml";
/// The `format` value this crate reads.
pub const FORMAT: &str = "choreod-model";
/// The newest `format_version` this crate reads.
pub const FORMAT_VERSION: u32 = 1;
/// Manifests are a few KB (mean/std of a few hundred floats); refuse anything absurd unread.
const MAX_MANIFEST_BYTES: u64 = 4 << 20;

/// The representation decoded by the music-to-dance pipeline: root xyz then joints 1..23 minus
/// the root, SMPL order, metres, y-up (contract: `smpl24-rootpos-rootrel`, D = 3 + 23·3 = 72).
pub const REPR_SMPL24_ROOTREL: &str = "smpl24-rootpos-rootrel";

/// What a package does.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
#[non_exhaustive]
pub enum Task {
    /// Music in, dance out (component `denoiser`; sections `[audio]`, motion windows).
    MusicToDance,
    /// Motion style transfer (components `vae_encoder`, `vae_decoder`, `style_encoder`,
    /// `denoiser`; motion `max_frames`/`min_frames`, sampler guidance weights).
    StyleTransfer,
    /// LODGE's two-stage music to dance (components `global_music`, `global_denoiser`,
    /// `local_music`, `local_denoiser`; sections `[license]`, `[lodge]`, fact35 `[audio]`,
    /// `motion.rest_joints`, `[motion.normalizer]`: models/export/README.md).
    Lodge,
}

impl Task {
    /// The manifest spelling.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::MusicToDance => "music-to-dance",
            Self::StyleTransfer => "style-transfer",
            Self::Lodge => "lodge",
        }
    }

    /// The components a package of this task has, no more and no fewer.
    pub fn roles(self) -> &'static [Role] {
        match self {
            Self::MusicToDance => &[Role::Denoiser],
            Self::StyleTransfer => &[
                Role::VaeEncoder,
                Role::VaeDecoder,
                Role::StyleEncoder,
                Role::Denoiser,
            ],
            Self::Lodge => &[
                Role::GlobalMusic,
                Role::GlobalDenoiser,
                Role::LocalMusic,
                Role::LocalDenoiser,
            ],
        }
    }

    /// The inputs of `role` that change from one diffusion step to the next; every other input
    /// is constant across the steps of a batch, so what the graph computes from those alone can
    /// be hoisted out of the step loop. None: the component is not run in a step loop.
    ///
    /// Both tasks' contracts (models/packages/README.md): the denoiser's `x_t` and `t` vary;
    /// `music`/`cond` (music-to-dance) and `content`/`trajectory`/`mask`/`style` (style
    /// transfer) do not. LODGE's denoisers are not hoisted: their music branch is a component
    /// of its own already, and the local one's style noise changes at every call.
    pub fn step_inputs(self, role: Role) -> Option<&'static [&'static str]> {
        match role {
            Role::Denoiser => Some(&["x_t", "t"]),
            _ => None,
        }
    }
}

impl std::fmt::Display for Task {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// What a component does in its package: the key of `[components.<role>]`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Deserialize)]
#[serde(rename_all = "snake_case")]
#[non_exhaustive]
pub enum Role {
    /// Predicts noise (or x0) from x_t, t and the task's conditions.
    Denoiser,
    /// Motion features to latent (style transfer).
    VaeEncoder,
    /// Latent to motion features (style transfer).
    VaeDecoder,
    /// Motion features to a style vector (style transfer).
    StyleEncoder,
    /// Audio features to a music embedding (no task uses one yet; reserved spelling).
    MusicEncoder,
    /// LODGE: 1024 frames of fact35 music to the Global network's conditioning.
    GlobalMusic,
    /// LODGE: the Global network (keyframes of 1024 frames).
    GlobalDenoiser,
    /// LODGE: 256 frames of fact35 music to the Local network's conditioning.
    LocalMusic,
    /// LODGE: the Local network (one 256-frame window with its genre and style noise).
    LocalDenoiser,
}

impl Role {
    /// The manifest spelling.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Denoiser => "denoiser",
            Self::VaeEncoder => "vae_encoder",
            Self::VaeDecoder => "vae_decoder",
            Self::StyleEncoder => "style_encoder",
            Self::MusicEncoder => "music_encoder",
            Self::GlobalMusic => "global_music",
            Self::GlobalDenoiser => "global_denoiser",
            Self::LocalMusic => "local_music",
            Self::LocalDenoiser => "local_denoiser",
        }
    }
}

impl std::fmt::Display for Role {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// A parsed and validated manifest.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
#[non_exhaustive]
pub struct Manifest {
    /// The package directory (for messages); not a manifest key.
    #[serde(skip)]
    dir: PathBuf,
    /// Always `"choreod-model"`.
    pub format: String,
    /// Schema version; this crate reads 1.
    pub format_version: u32,
    /// Short package name, e.g. `exemplar`.
    pub name: String,
    /// One line for humans.
    #[serde(default)]
    pub description: String,
    /// What the package does.
    pub task: Task,
    /// The motion the package produces.
    pub motion: MotionSpec,
    /// The terms of the weights (`[license]`): shown by `models check` and `dance` and written
    /// into the provenance. Required for `lodge` packages, optional for the others.
    #[serde(default)]
    pub license: Option<LicenseSpec>,
    /// The music features it expects (must equal what `choreo_dsp` computes): log-mel for
    /// music-to-dance ([`Manifest::dance_spec`]), fact35 for lodge ([`Manifest::lodge_spec`]).
    #[serde(default)]
    pub audio: Option<AudioSection>,
    /// The training noise schedule.
    pub diffusion: DiffusionSpec,
    /// Sampler defaults (CLI flags override).
    pub sampler: SamplerSpec,
    /// ONNX components by role: exactly [`Task::roles`].
    pub components: BTreeMap<Role, ComponentSpec>,
    /// `[lodge]`: genres and the two stages' sizes (lodge only).
    #[serde(default)]
    pub lodge: Option<LodgeSection>,
    /// Present when the package is an int8 copy of a float32 one (`models/packages/quantize.py`).
    #[serde(default)]
    pub quantization: Option<QuantizationSpec>,
    /// `[library]` (music-to-dance): the dance clips the package's motion comes from, indexed
    /// by the denoiser's optional [`SOURCE_OUTPUT`], and their attribution.
    #[serde(default)]
    pub library: Option<LibrarySection>,
}

/// The optional second output of a music-to-dance denoiser: per row, the `[library].clips`
/// index of the clip its prediction comes from (float32 [N, 1]); read once after sampling.
pub const SOURCE_OUTPUT: &str = "source";

/// `[library]`: the clips a library package plays, and the attribution they travel with.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
#[non_exhaustive]
pub struct LibrarySection {
    /// Clip names, in the order the `source` output indexes them.
    pub clips: Vec<String>,
    /// Each clip's style (same order), e.g. "salsa".
    #[serde(default)]
    pub styles: Vec<String>,
    /// The acknowledgement and attribution every motion made from the clips carries.
    pub attribution: String,
}

/// `[quantization]`: how an int8 package was made from its float32 source, and what it cost.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
#[non_exhaustive]
pub struct QuantizationSpec {
    /// One line: what was quantised and how (weights per channel, activations per tensor).
    pub scheme: String,
    /// The float32 source package's name.
    pub source: String,
    /// Largest output difference on the quantiser's test inputs over the largest output value.
    pub max_relative_error: f64,
    /// RMS of the output difference over the output's RMS, on the same inputs.
    pub rms_relative_error: f64,
    /// Each source component's sha256: what `models check --against` compares against.
    pub source_sha256: BTreeMap<Role, String>,
    /// Nodes left in float32 because their error dominated, per component.
    #[serde(default)]
    pub fp32_nodes: BTreeMap<Role, Vec<String>>,
}

/// `[motion]`
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
#[non_exhaustive]
pub struct MotionSpec {
    /// Frames per second of the network's motion.
    pub fps: f64,
    /// Skeleton of the decoded joints, e.g. `smpl24` ((T, 24, 3) joints).
    pub skeleton: String,
    /// Feature layout of one frame, e.g. `smpl24-rootpos-rootrel`.
    pub representation: String,
    /// Features per frame D.
    pub dim: usize,
    /// Frames per generated window T (EDGE: 150 = 5 s at 30 fps); music-to-dance only.
    #[serde(default)]
    pub window_frames: Option<usize>,
    /// Frames between consecutive window starts (EDGE: 75 = half a window); at least half a
    /// window, so the overlap copy regions of consecutive windows are disjoint; music-to-dance
    /// only.
    #[serde(default)]
    pub stride_frames: Option<usize>,
    /// Longest content segment the networks take; style transfer only.
    #[serde(default)]
    pub max_frames: Option<usize>,
    /// Shortest style motion the style encoder accepts; style transfer only.
    #[serde(default)]
    pub min_frames: Option<usize>,
    /// Normalisation mean: x_norm = (x - mean) / std, D values (not in lodge packages).
    #[serde(default)]
    pub mean: Vec<f32>,
    /// Normalisation standard deviation, D positive values (not in lodge packages).
    #[serde(default)]
    pub std: Vec<f32>,
    /// SMPL-X rest joints, J × 3 metres flattened (lodge only).
    #[serde(default)]
    pub rest_joints: Option<Vec<f64>>,
    /// `[motion.normalizer]`: LODGE's min-max normaliser (lodge only).
    #[serde(default)]
    pub normalizer: Option<MinMaxNormalizer>,
}

/// `[audio]`: the log-mel parameters the network was trained with.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
#[non_exhaustive]
pub struct AudioSpec {
    /// Sample rate of the analysed signal in Hz (MoFusion: 16000).
    pub sample_rate: u32,
    /// FFT size (2048).
    pub n_fft: usize,
    /// Hop in samples between mel frames (512, so 31.25 frames/s at 16 kHz).
    pub hop: usize,
    /// Mel bands (80).
    pub n_mels: usize,
    /// Lowest mel frequency in Hz (0).
    pub fmin: f64,
    /// Highest mel frequency in Hz (8000).
    pub fmax: f64,
    /// Dynamic range of `power_to_db` in dB (80).
    pub top_db: f64,
    /// Mel frames per window given to the network, ceil(window_s · sr / hop) (157 for 5 s).
    pub music_frames: usize,
}

impl AudioSpec {
    /// Mel frames per second.
    pub fn frame_rate(&self) -> f64 {
        f64::from(self.sample_rate) / self.hop as f64
    }
}

/// `[diffusion]`: how the network was trained.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
#[non_exhaustive]
pub struct DiffusionSpec {
    /// Training steps (`num_train_timesteps`).
    pub train_steps: usize,
    /// `linear`, `scaled_linear` or `cosine` (`beta_schedule`).
    pub beta_schedule: BetaSchedule,
    /// First beta of the linear schedules. Default 0.0001.
    #[serde(default = "default_beta_start")]
    pub beta_start: f64,
    /// Last beta of the linear schedules. Default 0.02.
    #[serde(default = "default_beta_end")]
    pub beta_end: f64,
    /// `epsilon` or `x0` (`prediction_type`; diffusers' "sample" is `x0`).
    pub prediction: Prediction,
    /// Clamp x0 estimates to [-1, 1] (`clip_sample`). Default false.
    #[serde(default)]
    pub clip_sample: bool,
    /// The cosine schedule's offset s (Nichol & Dhariwal); only 0.008 is computed.
    #[serde(default)]
    pub cosine_s: Option<f64>,
    /// The cosine schedule's beta cap; only 0.999 is computed.
    #[serde(default)]
    pub max_beta: Option<f64>,
    /// The precision the training code multiplied the alphas in: `float32` (LODGE casts the
    /// betas to float32 first, diffusion.py:82-86) or `float64` (the default).
    #[serde(default)]
    pub cumprod_dtype: Option<CumprodDtype>,
}

/// `diffusion.cumprod_dtype`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CumprodDtype {
    /// Betas rounded to float32, products stored in float32.
    Float32,
    /// Everything in float64.
    Float64,
}

fn default_beta_start() -> f64 {
    1e-4
}
fn default_beta_end() -> f64 {
    0.02
}

/// `[sampler]`: defaults for generation.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
#[non_exhaustive]
pub struct SamplerSpec {
    /// `ddim`, `ddpm` or `dpmsolver++`.
    pub kind: SamplerKind,
    /// Denoising steps.
    pub steps: usize,
    /// DDIM eta. Default 0.
    #[serde(default)]
    pub eta: f64,
    /// diffusers `steps_offset`. Default 0.
    #[serde(default)]
    pub steps_offset: usize,
    /// diffusers `set_alpha_to_one` (DDIM). Default false.
    #[serde(default)]
    pub set_alpha_to_one: bool,
    /// diffusers `timestep_spacing` (`leading`, `trailing`, `linspace`). Default: the
    /// scheduler's own (leading for DDPM/DDIM, linspace for DPM-Solver++).
    #[serde(default)]
    pub timestep_spacing: Option<TimestepSpacing>,
    /// Classifier-free guidance scale (on the music; on the style in transfer mode); 1.0 = off.
    /// Default 1.0.
    #[serde(default = "default_guidance")]
    pub guidance: f32,
    /// Content weight wc of two-weight guidance (style transfer, inversion mode).
    #[serde(default)]
    pub content_guidance: Option<f32>,
    /// Style weight ws of two-weight guidance (style transfer, inversion mode).
    #[serde(default)]
    pub style_guidance: Option<f32>,
    /// DDIM inversion steps of the content latent (style transfer, inversion mode).
    #[serde(default)]
    pub inversion_steps: Option<usize>,
    /// The training code's own timesteps, first to last (lodge: `steps` values, decreasing).
    #[serde(default)]
    pub timesteps: Option<Vec<i64>>,
}

/// What a music-to-dance package adds to the common sections, validated
/// ([`Manifest::dance_spec`]).
#[derive(Debug, Clone, Copy)]
#[non_exhaustive]
pub struct DanceSpec<'a> {
    /// `[audio]`: the log-mel the network was trained on.
    pub audio: &'a AudioSpec,
    /// `motion.window_frames`: frames per generated window.
    pub window_frames: usize,
    /// `motion.stride_frames`: frames between consecutive window starts.
    pub stride_frames: usize,
}

impl DanceSpec<'_> {
    /// Frames shared by consecutive windows.
    pub fn overlap_frames(&self) -> usize {
        self.window_frames - self.stride_frames
    }
}

/// What a style-transfer package adds to the common sections, validated and with the
/// contract's defaults filled in ([`Manifest::style_spec`]).
#[derive(Debug, Clone, Copy, PartialEq)]
#[non_exhaustive]
pub struct StyleSpec {
    /// `motion.max_frames`: longest content segment.
    pub max_frames: usize,
    /// `motion.min_frames`: shortest style motion.
    pub min_frames: usize,
    /// `sampler.content_guidance` (wc), default 1.0.
    pub content_guidance: f32,
    /// `sampler.style_guidance` (ws), default 2.5.
    pub style_guidance: f32,
    /// `sampler.inversion_steps`, default 30.
    pub inversion_steps: usize,
}

/// The style-transfer contract's defaults (models/packages/README.md, "the contract").
const DEFAULT_CONTENT_GUIDANCE: f32 = 1.0;
const DEFAULT_STYLE_GUIDANCE: f32 = 2.5;
const DEFAULT_INVERSION_STEPS: usize = 30;

/// The representation style-transfer packages work in: HumanML3D's 263 features per frame on
/// the t2m 22-joint skeleton.
pub const REPR_HUMANML3D263: &str = "humanml3d263";

fn default_guidance() -> f32 {
    1.0
}

impl AudioSpec {
    /// The log-mel the package was trained on, as `choreo_dsp` computes it.
    pub fn mel_options(&self) -> choreo_dsp::MelOptions {
        let mut o = choreo_dsp::MelOptions::default();
        o.sample_rate = self.sample_rate;
        o.n_fft = self.n_fft;
        o.hop_length = self.hop;
        o.n_mels = self.n_mels;
        o.fmin = self.fmin;
        o.fmax = self.fmax;
        o.top_db = Some(self.top_db as f32);
        o
    }
}

impl MotionSpec {
    /// The motion file's skeleton for this package's `skeleton` name, if it has a layout.
    pub fn skeleton_kind(&self) -> Option<choreo_datasets::SkeletonKind> {
        match self.skeleton.as_str() {
            "smpl24" => Some(choreo_datasets::SkeletonKind::Smpl24),
            "t2m22" => Some(choreo_datasets::SkeletonKind::T2m22),
            _ => None,
        }
    }
}

impl Manifest {
    /// Read and validate `DIR/choreod-model.toml`.
    pub fn load(dir: &Path) -> Result<Self> {
        let path = dir.join(MANIFEST_FILE);
        let fail = |reason: String| Error::Manifest {
            package: dir.to_path_buf(),
            key: "(file)".into(),
            reason,
        };
        let bytes = read_regular_file(&path, MAX_MANIFEST_BYTES)
            .map_err(|e| fail(format!("cannot read {}: {e}", path.display())))?;
        let text = String::from_utf8(bytes)
            .map_err(|_| fail(format!("{} is not UTF-8 text", path.display())))?;
        Self::parse(dir, &text)
    }

    /// Parse and validate manifest text; `dir` is only used in messages.
    pub fn parse(dir: &Path, text: &str) -> Result<Self> {
        let err = |key: &str, reason: String| Error::Manifest {
            package: dir.to_path_buf(),
            key: key.to_string(),
            reason,
        };
        // Check the format first, so a newer manifest says "newer" rather than "unknown field".
        let table: toml::Table = toml::from_str(text)
            .map_err(|e| err(&toml_location(text, &e), toml_reason(text, &e)))?;
        match table.get("format").and_then(toml::Value::as_str) {
            Some(FORMAT) => {}
            Some(other) => {
                let other = choreo_dsp::quote(other);
                return Err(err("format", format!("is {other}, expected {FORMAT:?}")));
            }
            None => {
                return Err(err(
                    "format",
                    format!("missing; expected format = {FORMAT:?}"),
                ));
            }
        }
        match table
            .get("format_version")
            .and_then(toml::Value::as_integer)
        {
            Some(v) if v == i64::from(FORMAT_VERSION) => {}
            Some(v) if v > i64::from(FORMAT_VERSION) => {
                return Err(err(
                    "format_version",
                    format!(
                        "is {v}, newer than {FORMAT_VERSION} which this choreod reads: upgrade choreod"
                    ),
                ));
            }
            Some(v) => {
                return Err(err(
                    "format_version",
                    format!("is {v}, expected {FORMAT_VERSION}"),
                ));
            }
            None => return Err(err("format_version", "missing or not an integer".into())),
        }
        let mut manifest: Self = toml::from_str(text)
            .map_err(|e| err(&toml_location(text, &e), toml_reason(text, &e)))?;
        manifest.dir = dir.to_path_buf();
        manifest.validate().map_err(|e| err(&e.key, e.reason))?;
        Ok(manifest)
    }

    /// The training noise schedule.
    pub fn schedule(&self) -> Result<NoiseSchedule> {
        let d = &self.diffusion;
        NoiseSchedule::new(d.beta_schedule, d.train_steps, d.beta_start, d.beta_end)
    }

    /// Sampler options from the manifest's defaults.
    pub fn sampler_options(&self) -> SamplerOptions {
        let s = &self.sampler;
        SamplerOptions {
            kind: s.kind,
            steps: s.steps,
            eta: s.eta,
            steps_offset: s.steps_offset,
            spacing: s.timestep_spacing,
            set_alpha_to_one: s.set_alpha_to_one,
            prediction: self.diffusion.prediction,
            clip_sample: self.diffusion.clip_sample,
            guidance: Guidance::from_scale(s.guidance),
            batch_guidance: true,
        }
    }

    /// The package directory this manifest was read from.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The music-to-dance sections, or an error naming the task when this package is not a
    /// music-to-dance package (its presence is validated at parse).
    pub fn dance_spec(&self) -> Result<DanceSpec<'_>> {
        match (
            self.task,
            &self.audio,
            self.motion.window_frames,
            self.motion.stride_frames,
        ) {
            (
                Task::MusicToDance,
                Some(AudioSection::LogMel(audio)),
                Some(window_frames),
                Some(stride_frames),
            ) => Ok(DanceSpec {
                audio,
                window_frames,
                stride_frames,
            }),
            _ => Err(self.wrong_task(Task::MusicToDance)),
        }
    }

    /// The style-transfer sections with the contract's defaults, or an error naming the task
    /// when this package is not a style-transfer package.
    pub fn style_spec(&self) -> Result<StyleSpec> {
        let (m, s) = (&self.motion, &self.sampler);
        match (self.task, m.max_frames, m.min_frames) {
            (Task::StyleTransfer, Some(max_frames), Some(min_frames)) => Ok(StyleSpec {
                max_frames,
                min_frames,
                content_guidance: s.content_guidance.unwrap_or(DEFAULT_CONTENT_GUIDANCE),
                style_guidance: s.style_guidance.unwrap_or(DEFAULT_STYLE_GUIDANCE),
                inversion_steps: s.inversion_steps.unwrap_or(DEFAULT_INVERSION_STEPS),
            }),
            _ => Err(self.wrong_task(Task::StyleTransfer)),
        }
    }

    fn wrong_task(&self, needed: Task) -> Error {
        Error::Manifest {
            package: self.dir.clone(),
            key: "task".into(),
            reason: format!("is {}, this needs a {needed} package", self.task),
        }
    }

    /// Semantic checks; the error names the key.
    fn validate(&self) -> std::result::Result<(), KeyError> {
        let fail = |key: &str, reason: String| Err(KeyError::new(key, reason));
        if self.name.trim().is_empty() {
            return fail("name", "must not be empty".into());
        }
        let m = &self.motion;
        // The range every motion reader accepts: a package's motion must be one choreod can
        // write and read back.
        let fps_range = choreo_datasets::limits::FPS_RANGE;
        if !(f64::from(*fps_range.start())..=f64::from(*fps_range.end())).contains(&m.fps) {
            return fail(
                "motion.fps",
                format!(
                    "must be in {}..={} frames per second, got {:?}",
                    fps_range.start(),
                    fps_range.end(),
                    m.fps
                ),
            );
        }
        if m.dim == 0 || m.dim > 100_000 {
            return fail(
                "motion.dim",
                format!("must be in 1..=100000, got {}", m.dim),
            );
        }
        let mean_std: &[(&str, &Vec<f32>)] = match self.task {
            Task::Lodge => &[],
            _ => &[("motion.mean", &m.mean), ("motion.std", &m.std)],
        };
        for &(key, values) in mean_std {
            if values.len() != m.dim {
                return fail(
                    key,
                    format!("has {} values, motion.dim is {}", values.len(), m.dim),
                );
            }
            if let Some(i) = values.iter().position(|v| !v.is_finite()) {
                return fail(key, format!("value {i} is not finite"));
            }
        }
        if let Some(i) = m.std.iter().position(|v| *v <= 0.0) {
            return fail(
                "motion.std",
                format!("value {i} is {}, must be > 0", m.std[i]),
            );
        }
        let d = &self.diffusion;
        if d.train_steps > 100_000 {
            return fail(
                "diffusion.train_steps",
                format!("{} is more than 100000", d.train_steps),
            );
        }
        let schedule = self
            .schedule()
            .map_err(|e| KeyError::new("diffusion", e.to_string()))?;
        let s = &self.sampler;
        Sampler::new(schedule, self.sampler_options())
            .map_err(|e| KeyError::new("sampler.steps", e.to_string()))?;
        if !ETA_RANGE.contains(&s.eta) {
            return fail(
                "sampler.eta",
                format!(
                    "must be in {}..={}, got {}",
                    ETA_RANGE.start(),
                    ETA_RANGE.end(),
                    s.eta
                ),
            );
        }
        check_weight("sampler.guidance", Some(s.guidance))?;
        self.validate_components()?;
        if let Some(q) = &self.quantization {
            self.validate_quantization(q)?;
        }
        // Each task's own sections; keys of another task are refused, not silently ignored.
        let (own, foreign) = match self.task {
            Task::MusicToDance => (
                self.validate_music_to_dance(),
                [&self.style_keys()[..], &self.lodge_keys()].concat(),
            ),
            Task::StyleTransfer => (
                self.validate_style_transfer(),
                [&self.dance_keys()[..], &self.lodge_keys()].concat(),
            ),
            Task::Lodge => (
                self.validate_lodge(),
                [&self.dance_keys()[1..], &self.style_keys()].concat(),
            ),
        };
        own?;
        if let Some(key) = foreign.iter().find_map(|(key, set)| set.then_some(key)) {
            return fail(key, format!("is not a key of {} packages", self.task));
        }
        Ok(())
    }

    /// Music-to-dance keys, and whether each is set.
    fn dance_keys(&self) -> [(&'static str, bool); 4] {
        [
            ("audio", self.audio.is_some()),
            ("motion.window_frames", self.motion.window_frames.is_some()),
            ("motion.stride_frames", self.motion.stride_frames.is_some()),
            ("library", self.library.is_some()),
        ]
    }

    /// LODGE keys (beside `[audio]` and `[license]`), and whether each is set.
    fn lodge_keys(&self) -> [(&'static str, bool); 3] {
        let m = &self.motion;
        [
            ("lodge", self.lodge.is_some()),
            ("motion.rest_joints", m.rest_joints.is_some()),
            ("motion.normalizer", m.normalizer.is_some()),
        ]
    }

    /// Style-transfer keys, and whether each is set.
    fn style_keys(&self) -> [(&'static str, bool); 5] {
        let (m, s) = (&self.motion, &self.sampler);
        [
            ("motion.max_frames", m.max_frames.is_some()),
            ("motion.min_frames", m.min_frames.is_some()),
            ("sampler.content_guidance", s.content_guidance.is_some()),
            ("sampler.style_guidance", s.style_guidance.is_some()),
            ("sampler.inversion_steps", s.inversion_steps.is_some()),
        ]
    }

    /// The `[quantization]` section names a source for exactly this package's components, with
    /// well-formed digests and finite errors.
    fn validate_quantization(&self, q: &QuantizationSpec) -> std::result::Result<(), KeyError> {
        let fail = |key: &str, reason: String| Err(KeyError::new(key, reason));
        for (key, value) in [
            ("quantization.max_relative_error", q.max_relative_error),
            ("quantization.rms_relative_error", q.rms_relative_error),
        ] {
            if !(value.is_finite() && value >= 0.0) {
                return fail(key, format!("must be a finite number >= 0, got {value}"));
            }
        }
        if !q.source_sha256.keys().eq(self.components.keys()) {
            return fail(
                "quantization.source_sha256",
                "must name the same components as [components]".into(),
            );
        }
        for (role, digest) in &q.source_sha256 {
            if digest.len() != 64 || !digest.bytes().all(|b| b.is_ascii_hexdigit()) {
                return fail(
                    &format!("quantization.source_sha256.{role}"),
                    "must be 64 hexadecimal digits".into(),
                );
            }
        }
        if let Some(role) = q
            .fp32_nodes
            .keys()
            .find(|r| !self.components.contains_key(r))
        {
            return fail(
                &format!("quantization.fp32_nodes.{role}"),
                "names a component the package does not have".into(),
            );
        }
        Ok(())
    }

    /// Every component: a file inside the package, a sha256, named tensors with sane shapes;
    /// and exactly the task's roles.
    fn validate_components(&self) -> std::result::Result<(), KeyError> {
        let fail = |key: &str, reason: String| Err(KeyError::new(key, reason));
        for role in self.task.roles() {
            if !self.components.contains_key(role) {
                return fail(
                    &format!("components.{role}"),
                    format!("missing ({} needs it)", self.task),
                );
            }
        }
        for (role, c) in &self.components {
            let key = |k: &str| format!("components.{role}.{k}");
            if !self.task.roles().contains(role) {
                return fail(
                    &format!("components.{role}"),
                    format!(
                        "{} packages have no {role} component (they have {})",
                        self.task,
                        role_list(self.task.roles())
                    ),
                );
            }
            check_relative(&c.file).map_err(|r| KeyError::new(key("file"), r))?;
            if c.sha256.len() != 64
                || !c
                    .sha256
                    .bytes()
                    .all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
            {
                return fail(
                    &key("sha256"),
                    format!(
                        "must be 64 lower-case hex digits, got {}",
                        choreo_dsp::quote(&c.sha256)
                    ),
                );
            }
            for (list, specs) in [("inputs", &c.inputs), ("outputs", &c.outputs)] {
                if specs.is_empty() {
                    return fail(&key(list), "must name at least one tensor".into());
                }
                for (i, t) in specs.iter().enumerate() {
                    if specs[..i].iter().any(|o| o.name == t.name) {
                        let name = choreo_dsp::quote(&t.name);
                        return fail(&key(list), format!("tensor {name} listed twice"));
                    }
                    if let Some(bad) = t
                        .shape
                        .iter()
                        .find(|d| matches!(d, Dim::Fixed(n) if *n < 1))
                    {
                        return fail(
                            &key(list),
                            format!("tensor {}: dimension {bad} must be >= 1", t.name),
                        );
                    }
                }
            }
        }
        Ok(())
    }

    /// `[audio]`, the motion windows, and the denoiser's interface as the contract says, with
    /// this manifest's sizes.
    fn validate_music_to_dance(&self) -> std::result::Result<(), KeyError> {
        let fail = |key: &str, reason: String| Err(KeyError::new(key, reason));
        let m = &self.motion;
        let needed =
            |key: &str| KeyError::new(key, "missing (music-to-dance needs it)".to_string());
        let window_frames = m
            .window_frames
            .ok_or_else(|| needed("motion.window_frames"))?;
        let stride_frames = m
            .stride_frames
            .ok_or_else(|| needed("motion.stride_frames"))?;
        let a = match self.audio.as_ref().ok_or_else(|| needed("audio"))? {
            AudioSection::LogMel(a) => a,
            AudioSection::Fact35(_) => {
                return fail(
                    "audio.features",
                    "is fact35, which lodge packages read; music-to-dance packages take log-mel"
                        .into(),
                );
            }
        };
        if !(2..=100_000).contains(&window_frames) {
            return fail(
                "motion.window_frames",
                format!("must be in 2..=100000, got {window_frames}"),
            );
        }
        if stride_frames == 0 || stride_frames > window_frames || 2 * stride_frames < window_frames
        {
            return fail(
                "motion.stride_frames",
                format!(
                    "must be between half the window and the window ({}..={window_frames}), \
                     got {stride_frames}",
                    window_frames.div_ceil(2),
                ),
            );
        }
        // The ranges the mel front end accepts (sample rate up to 768 kHz, n_fft up to 65536,
        // ...): a package outside them could load but fail every song at decode.
        if let Err(choreo_dsp::Error::BadOption {
            name,
            value,
            reason,
        }) = a.mel_options().validate()
        {
            let key = match name {
                "hop_length" => "hop",
                "fmin/fmax" => "fmax",
                other => other,
            };
            return fail(&format!("audio.{key}"), format!("{value}: {reason}"));
        }
        if !(a.top_db.is_finite() && a.top_db > 0.0) {
            return fail("audio.top_db", format!("must be > 0, got {}", a.top_db));
        }
        if a.music_frames == 0 || a.music_frames > 1_000_000 {
            return fail(
                "audio.music_frames",
                format!("must be in 1..=1000000, got {}", a.music_frames),
            );
        }
        if m.representation != REPR_SMPL24_ROOTREL {
            return fail(
                "motion.representation",
                format!(
                    "{} cannot be decoded to joints; supported: {REPR_SMPL24_ROOTREL:?}",
                    choreo_dsp::quote(&m.representation)
                ),
            );
        }
        if m.skeleton != "smpl24" || m.dim != 72 {
            return fail(
                "motion",
                format!(
                    "{REPR_SMPL24_ROOTREL} needs skeleton \"smpl24\" and dim 72, got {} and {}",
                    choreo_dsp::quote(&m.skeleton),
                    m.dim
                ),
            );
        }
        let motion = vec![batch(), fixed(window_frames), fixed(m.dim)];
        let music = vec![batch(), fixed(a.music_frames), fixed(a.n_mels)];
        let source = vec![batch(), fixed(1)];
        let mut outputs: Vec<(&str, DType, &[Dim])> = vec![("pred", DType::Float32, &motion)];
        if self.declares_source() {
            if self.library.is_none() {
                return fail(
                    "library",
                    format!("missing (the denoiser's {SOURCE_OUTPUT:?} output indexes its clips)"),
                );
            }
            outputs.push((SOURCE_OUTPUT, DType::Float32, &source));
        }
        self.check_contract(
            Role::Denoiser,
            &[
                ("x_t", DType::Float32, &motion),
                ("t", DType::Int64, &[batch()]),
                ("music", DType::Float32, &music),
                ("cond", DType::Float32, &[batch()]),
            ],
            &outputs,
        )
    }

    /// Whether the music-to-dance denoiser declares the optional [`SOURCE_OUTPUT`].
    pub fn declares_source(&self) -> bool {
        self.components
            .get(&Role::Denoiser)
            .is_some_and(|c| c.outputs.iter().any(|o| o.name == SOURCE_OUTPUT))
    }

    /// The provenance line of a dance made from the library clips `used` (indices into
    /// `[library].clips`, as the `source` output gives them): the clips by name and the
    /// attribution; `None` for a package without `[library]`.
    pub fn library_line(&self, used: &[usize]) -> Option<String> {
        let lib = self.library.as_ref()?;
        let mut names: Vec<&str> = used
            .iter()
            .filter_map(|&k| lib.clips.get(k).map(String::as_str))
            .collect();
        names.sort_unstable();
        names.dedup();
        let clips = if names.is_empty() {
            "clips used: not identified".to_string()
        } else {
            format!("clips used: {}", names.join(", "))
        };
        Some(format!("{clips}; attribution: {}", lib.attribution))
    }

    /// The motion lengths, the guidance weights, and the four components' interfaces as the
    /// contract says (models/packages/README.md, "Style transfer packages: the contract"): the
    /// latent's shape is the package's own (the VAE encoder's output), the same everywhere.
    fn validate_style_transfer(&self) -> std::result::Result<(), KeyError> {
        let fail = |key: &str, reason: String| Err(KeyError::new(key, reason));
        let m = &self.motion;
        let needed =
            |key: &str| KeyError::new(key, "missing (style-transfer needs it)".to_string());
        let max_frames = m.max_frames.ok_or_else(|| needed("motion.max_frames"))?;
        let min_frames = m.min_frames.ok_or_else(|| needed("motion.min_frames"))?;
        if !(1..=100_000).contains(&max_frames) {
            return fail(
                "motion.max_frames",
                format!("must be in 1..=100000, got {max_frames}"),
            );
        }
        if min_frames == 0 || min_frames > max_frames {
            return fail(
                "motion.min_frames",
                format!("must be in 1..=max_frames ({max_frames}), got {min_frames}"),
            );
        }
        if m.representation != REPR_HUMANML3D263 || m.skeleton != "t2m22" || m.dim != 263 {
            return fail(
                "motion",
                format!(
                    "style transfer needs representation {REPR_HUMANML3D263:?}, skeleton \
                     \"t2m22\" and dim 263, got {}, {} and {}",
                    choreo_dsp::quote(&m.representation),
                    choreo_dsp::quote(&m.skeleton),
                    m.dim
                ),
            );
        }
        let s = &self.sampler;
        check_weight("sampler.content_guidance", s.content_guidance)?;
        check_weight("sampler.style_guidance", s.style_guidance)?;
        if let Some(steps) = s.inversion_steps
            && !(1..=self.diffusion.train_steps).contains(&steps)
        {
            return fail(
                "sampler.inversion_steps",
                format!(
                    "must be in 1..={} (diffusion.train_steps), got {steps}",
                    self.diffusion.train_steps
                ),
            );
        }
        let frames = vec![batch(), symbol("T"), fixed(m.dim)];
        let mask = vec![batch(), symbol("T")];
        let latent = self.batched_output(Role::VaeEncoder, "latent")?;
        let style = self.batched_output(Role::StyleEncoder, "style")?;
        let f32 = DType::Float32;
        self.check_contract(
            Role::VaeEncoder,
            &[("features", f32, &frames), ("mask", f32, &mask)],
            &[("latent", f32, &latent)],
        )?;
        self.check_contract(
            Role::VaeDecoder,
            &[("latent", f32, &latent), ("mask", f32, &mask)],
            &[("features", f32, &frames)],
        )?;
        self.check_contract(
            Role::StyleEncoder,
            &[("features", f32, &frames), ("mask", f32, &mask)],
            &[("style", f32, &style)],
        )?;
        self.check_contract(
            Role::Denoiser,
            &[
                ("x_t", f32, &latent),
                ("t", DType::Int64, &[batch()]),
                ("content", f32, &latent),
                ("trajectory", f32, &[batch(), symbol("T"), fixed(3)]),
                ("mask", f32, &mask),
                ("style", f32, &style),
            ],
            &[("pred", f32, &latent)],
        )
    }

    /// The shape of a float32 output whose shape is the package's choice, as long as its first
    /// axis is the dynamic batch and it has another axis.
    fn batched_output(&self, role: Role, name: &str) -> std::result::Result<Vec<Dim>, KeyError> {
        let key = format!("components.{role}.outputs");
        let t = self.components[&role]
            .outputs
            .iter()
            .find(|t| t.name == name)
            .ok_or_else(|| KeyError::new(key.clone(), format!("no tensor named {name:?}")))?;
        if t.shape.len() < 2 || !matches!(t.shape[0], Dim::Symbol(_)) {
            return Err(KeyError::new(
                key,
                format!(
                    "tensor {name} is {}, expected a dynamic batch axis first and at least \
                     one more axis",
                    shape_text(&t.shape)
                ),
            ));
        }
        Ok(t.shape.clone())
    }

    /// The component of `role` has exactly these inputs and outputs (any symbol matches any
    /// symbol: sizes bind at run time).
    fn check_contract(
        &self,
        role: Role,
        inputs: &[(&str, DType, &[Dim])],
        outputs: &[(&str, DType, &[Dim])],
    ) -> std::result::Result<(), KeyError> {
        let c = &self.components[&role];
        for (list, specs, expected) in [
            ("inputs", &c.inputs, inputs),
            ("outputs", &c.outputs, outputs),
        ] {
            let key = format!("components.{role}.{list}");
            let contract = || {
                expected
                    .iter()
                    .map(|(name, dtype, shape)| {
                        format!("{name} {} {}", dtype.as_str(), shape_text(shape))
                    })
                    .collect::<Vec<_>>()
                    .join(", ")
            };
            if let Some(extra) = specs
                .iter()
                .find(|t| !expected.iter().any(|e| e.0 == t.name))
            {
                return Err(KeyError::new(
                    key,
                    format!(
                        "tensor {} is not in the {} contract ({})",
                        choreo_dsp::quote(&extra.name),
                        self.task,
                        contract()
                    ),
                ));
            }
            for (name, dtype, shape) in expected {
                let Some(t) = specs.iter().find(|t| t.name == *name) else {
                    return Err(KeyError::new(
                        key,
                        format!(
                            "no tensor named {name:?} (contract: {name} {} {})",
                            dtype.as_str(),
                            shape_text(shape)
                        ),
                    ));
                };
                let same = t.dtype == *dtype
                    && t.shape.len() == shape.len()
                    && t.shape
                        .iter()
                        .zip(shape.iter())
                        .all(|(got, want)| match (got, want) {
                            (Dim::Symbol(_), Dim::Symbol(_)) => true,
                            _ => got == want,
                        });
                if !same {
                    return Err(KeyError::new(
                        key,
                        format!(
                            "tensor {name} is {} {}, expected {} {} (symbolic axes dynamic)",
                            t.dtype.as_str(),
                            shape_text(&t.shape),
                            dtype.as_str(),
                            shape_text(shape)
                        ),
                    ));
                }
            }
        }
        Ok(())
    }
}

fn batch() -> Dim {
    symbol("N")
}

fn symbol(name: &str) -> Dim {
    Dim::Symbol(name.to_string())
}

fn fixed(size: usize) -> Dim {
    Dim::Fixed(size as i64)
}

/// Guidance weights accepted, in the manifest and on the command line: 0 (unconditional) to
/// 100, far above what papers use (MCM-LDM 2.5, EDGE 2, Stable Diffusion 7.5); beyond it one
/// step moves the sample by more than f32 holds.
pub const GUIDANCE_RANGE: std::ops::RangeInclusive<f32> = 0.0..=100.0;

/// DDIM eta accepted, in the manifest and on the command line: 0 (deterministic DDIM) to 1
/// (DDPM's variance), the range of Song et al.'s sigma_t interpolation.
pub const ETA_RANGE: std::ops::RangeInclusive<f64> = 0.0..=1.0;

/// A guidance weight, when given, lies in [`GUIDANCE_RANGE`].
fn check_weight(key: &str, weight: Option<f32>) -> std::result::Result<(), KeyError> {
    match weight {
        Some(w) if !GUIDANCE_RANGE.contains(&w) => Err(KeyError::new(
            key.to_string(),
            format!(
                "must be in {}..={}, got {w}",
                GUIDANCE_RANGE.start(),
                GUIDANCE_RANGE.end()
            ),
        )),
        _ => Ok(()),
    }
}

fn role_list(roles: &[Role]) -> String {
    roles
        .iter()
        .map(|r| r.as_str())
        .collect::<Vec<_>>()
        .join(", ")
}

/// Component files stay inside the package: relative, no `..`.
fn check_relative(file: &str) -> std::result::Result<(), String> {
    let p = Path::new(file);
    if file.is_empty()
        || !p
            .components()
            .all(|c| matches!(c, Component::Normal(_) | Component::CurDir))
    {
        return Err(format!(
            "{} must be a relative path inside the package (no '..', not absolute)",
            choreo_dsp::quote(file)
        ));
    }
    Ok(())
}

/// "line N" for a TOML error.
fn toml_location(text: &str, e: &toml::de::Error) -> String {
    match e.span() {
        Some(span) => format!(
            "line {}",
            text[..span.start.min(text.len())].matches('\n').count() + 1
        ),
        None => "(toml)".into(),
    }
}

/// TOML's message, one line, the file's text it quotes cut short (`choreo_dsp::quote_inside`).
fn toml_reason(text: &str, e: &toml::de::Error) -> String {
    let found = e
        .span()
        .and_then(|span| text.get(span.start.min(text.len())..span.end.min(text.len())))
        .unwrap_or_default();
    choreo_dsp::quote_inside(&e.message().trim().replace('\n', " "), found)
}

#[path = "lodge_manifest.rs"]
mod lodge;
pub use lodge::{
    AudioSection, Fact35Spec, LicenseSpec, LodgeSection, LodgeSpec, MinMaxNormalizer, StageLayout,
};

#[cfg(test)]
#[path = "manifest_tests.rs"]
mod tests;
