//! The model package manifest `choreod-model.toml` (definition): parsed with serde, unknown keys
//! refused, then validated; every error names the package directory and the key.
//!
//! The schema is the package contract (briefs/model-contract.md, DESIGN.md "Model packages").

use std::collections::BTreeMap;
use std::path::{Component, Path, PathBuf};

use serde::Deserialize;

use crate::diffusion::sampler::{Guidance, Prediction, Sampler, SamplerKind, SamplerOptions};
use crate::diffusion::schedule::{BetaSchedule, NoiseSchedule};
use crate::diffusion::scheduler::TimestepSpacing;
use crate::error::{Error, Result};
use crate::session::read_regular_file;

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
    /// Music in, dance out (component `denoiser`).
    MusicToDance,
    /// Motion style transfer (runtime support comes with the stylize verb).
    StyleTransfer,
}

impl Task {
    /// The manifest spelling.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::MusicToDance => "music-to-dance",
            Self::StyleTransfer => "style-transfer",
        }
    }
}

/// A parsed and validated manifest.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
#[non_exhaustive]
pub struct Manifest {
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
    /// The music features it expects (must equal what `choreo_dsp` computes).
    pub audio: AudioSpec,
    /// The training noise schedule.
    pub diffusion: DiffusionSpec,
    /// Sampler defaults (CLI flags override).
    pub sampler: SamplerSpec,
    /// ONNX components by role name (`denoiser`, ...).
    pub components: BTreeMap<String, ComponentSpec>,
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
    /// Frames per generated window T (EDGE: 150 = 5 s at 30 fps).
    pub window_frames: usize,
    /// Frames between consecutive window starts (EDGE: 75 = half a window); at least half a
    /// window, so the overlap copy regions of consecutive windows are disjoint.
    pub stride_frames: usize,
    /// Normalisation mean: x_norm = (x - mean) / std, D values.
    pub mean: Vec<f32>,
    /// Normalisation standard deviation, D positive values.
    pub std: Vec<f32>,
}

impl MotionSpec {
    /// Frames shared by consecutive windows.
    pub fn overlap_frames(&self) -> usize {
        self.window_frames - self.stride_frames
    }
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
    /// Classifier-free guidance scale on the music; 1.0 = off. Default 1.0.
    #[serde(default = "default_guidance")]
    pub guidance: f32,
}

fn default_guidance() -> f32 {
    1.0
}

/// `[components.NAME]`: one ONNX graph.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
#[non_exhaustive]
pub struct ComponentSpec {
    /// ONNX file, relative to the package directory (no `..`).
    pub file: String,
    /// Lower-case hex sha256 of the file, checked at load.
    pub sha256: String,
    /// Graph inputs, by name.
    pub inputs: Vec<TensorSpec>,
    /// Graph outputs, by name.
    pub outputs: Vec<TensorSpec>,
}

/// One graph input or output.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
#[non_exhaustive]
pub struct TensorSpec {
    /// Tensor name in the graph.
    pub name: String,
    /// Element type.
    pub dtype: DType,
    /// Dimensions: numbers are fixed, strings name dynamic axes (e.g. `"N"`).
    pub shape: Vec<Dim>,
}

/// Element types used by packages.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
#[non_exhaustive]
pub enum DType {
    /// 32-bit float.
    Float32,
    /// 64-bit signed integer.
    Int64,
}

impl DType {
    /// The manifest spelling.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Float32 => "float32",
            Self::Int64 => "int64",
        }
    }
}

/// One dimension of a tensor shape.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
#[serde(untagged)]
pub enum Dim {
    /// A fixed size.
    Fixed(i64),
    /// A dynamic axis, by symbol.
    Symbol(String),
}

impl std::fmt::Display for Dim {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Fixed(n) => write!(f, "{n}"),
            Self::Symbol(s) => f.write_str(s),
        }
    }
}

/// `[a, b, c]` for messages.
pub(crate) fn shape_text(shape: &[Dim]) -> String {
    let parts: Vec<String> = shape.iter().map(ToString::to_string).collect();
    format!("[{}]", parts.join(", "))
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
            .map_err(|e| err(&toml_location(text, &e), e.message().to_string()))?;
        match table.get("format").and_then(toml::Value::as_str) {
            Some(FORMAT) => {}
            Some(other) => return Err(err("format", format!("is {other:?}, expected {FORMAT:?}"))),
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
        let manifest: Self = toml::from_str(text)
            .map_err(|e| err(&toml_location(text, &e), e.message().to_string()))?;
        manifest
            .validate()
            .map_err(|(key, reason)| err(&key, reason))?;
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

    /// Semantic checks; the error is (key, reason).
    fn validate(&self) -> std::result::Result<(), (String, String)> {
        let fail = |key: &str, reason: String| Err((key.to_string(), reason));
        if self.name.trim().is_empty() {
            return fail("name", "must not be empty".into());
        }
        let m = &self.motion;
        if !(m.fps.is_finite() && m.fps > 0.0 && m.fps <= 1000.0) {
            return fail("motion.fps", format!("must be in (0, 1000], got {}", m.fps));
        }
        if m.dim == 0 || m.dim > 100_000 {
            return fail(
                "motion.dim",
                format!("must be in 1..=100000, got {}", m.dim),
            );
        }
        if m.window_frames < 2 || m.window_frames > 100_000 {
            return fail(
                "motion.window_frames",
                format!("must be in 2..=100000, got {}", m.window_frames),
            );
        }
        if m.stride_frames == 0
            || m.stride_frames > m.window_frames
            || 2 * m.stride_frames < m.window_frames
        {
            return fail(
                "motion.stride_frames",
                format!(
                    "must be between half the window and the window ({}..={}), got {}",
                    m.window_frames.div_ceil(2),
                    m.window_frames,
                    m.stride_frames
                ),
            );
        }
        for (key, values) in [("motion.mean", &m.mean), ("motion.std", &m.std)] {
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
        let a = &self.audio;
        if a.sample_rate == 0 || a.hop == 0 || a.n_fft < a.hop || a.n_mels == 0 {
            return fail(
                "audio",
                format!(
                    "need sample_rate > 0, hop > 0, n_fft >= hop, n_mels > 0; got {} {} {} {}",
                    a.sample_rate, a.hop, a.n_fft, a.n_mels
                ),
            );
        }
        if !(a.fmin >= 0.0 && a.fmax > a.fmin && a.fmax <= f64::from(a.sample_rate) / 2.0) {
            return fail(
                "audio.fmax",
                format!(
                    "need 0 <= fmin < fmax <= sample_rate/2, got {} and {}",
                    a.fmin, a.fmax
                ),
            );
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
        let d = &self.diffusion;
        if d.train_steps > 100_000 {
            return fail(
                "diffusion.train_steps",
                format!("{} is more than 100000", d.train_steps),
            );
        }
        let schedule = self
            .schedule()
            .map_err(|e| ("diffusion".to_string(), e.to_string()))?;
        let s = &self.sampler;
        Sampler::new(schedule, self.sampler_options())
            .map_err(|e| ("sampler.steps".to_string(), e.to_string()))?;
        if !(s.eta.is_finite() && s.eta >= 0.0) {
            return fail("sampler.eta", format!("must be >= 0, got {}", s.eta));
        }
        if !(s.guidance.is_finite() && s.guidance >= 0.0) {
            return fail(
                "sampler.guidance",
                format!("must be >= 0, got {}", s.guidance),
            );
        }
        if self.components.is_empty() {
            return fail("components", "no components".into());
        }
        for (name, c) in &self.components {
            let key = |k: &str| format!("components.{name}.{k}");
            check_relative(&c.file).map_err(|r| (key("file"), r))?;
            if c.sha256.len() != 64
                || !c
                    .sha256
                    .bytes()
                    .all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
            {
                return fail(
                    &key("sha256"),
                    format!("must be 64 lower-case hex digits, got {:?}", c.sha256),
                );
            }
            for (list, specs) in [("inputs", &c.inputs), ("outputs", &c.outputs)] {
                if specs.is_empty() {
                    return fail(&key(list), "must name at least one tensor".into());
                }
                for (i, t) in specs.iter().enumerate() {
                    if specs[..i].iter().any(|o| o.name == t.name) {
                        return fail(&key(list), format!("tensor {:?} listed twice", t.name));
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
        if self.task == Task::MusicToDance {
            self.validate_music_to_dance()?;
        }
        Ok(())
    }

    /// The denoiser's interface must be the contract's, with this manifest's sizes.
    fn validate_music_to_dance(&self) -> std::result::Result<(), (String, String)> {
        let m = &self.motion;
        if m.representation != REPR_SMPL24_ROOTREL {
            return Err((
                "motion.representation".into(),
                format!(
                    "{:?} cannot be decoded to joints; supported: {REPR_SMPL24_ROOTREL:?}",
                    m.representation
                ),
            ));
        }
        if m.skeleton != "smpl24" || m.dim != 72 {
            return Err((
                "motion".into(),
                format!(
                    "{REPR_SMPL24_ROOTREL} needs skeleton \"smpl24\" and dim 72, got {:?} and {}",
                    m.skeleton, m.dim
                ),
            ));
        }
        let Some(c) = self.components.get("denoiser") else {
            return Err((
                "components.denoiser".into(),
                "missing (music-to-dance needs it)".into(),
            ));
        };
        let n = Dim::Symbol("N".into());
        let fixed = |v: usize| Dim::Fixed(v as i64);
        let motion_shape = vec![n.clone(), fixed(m.window_frames), fixed(m.dim)];
        let expected_inputs = [
            ("x_t", DType::Float32, motion_shape.clone()),
            ("t", DType::Int64, vec![n.clone()]),
            (
                "music",
                DType::Float32,
                vec![
                    n.clone(),
                    fixed(self.audio.music_frames),
                    fixed(self.audio.n_mels),
                ],
            ),
            ("cond", DType::Float32, vec![n.clone()]),
        ];
        let expected_outputs = [("pred", DType::Float32, motion_shape)];
        for (list, specs, expected) in [
            ("inputs", &c.inputs, &expected_inputs[..]),
            ("outputs", &c.outputs, &expected_outputs[..]),
        ] {
            let key = format!("components.denoiser.{list}");
            for (name, dtype, shape) in expected {
                let Some(t) = specs.iter().find(|t| t.name == *name) else {
                    return Err((
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
                    return Err((
                        key,
                        format!(
                            "tensor {name} is {} {}, expected {} {} (batch axis dynamic)",
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

    /// The absolute path of a component's file.
    pub fn component_path(&self, dir: &Path, component: &ComponentSpec) -> PathBuf {
        dir.join(&component.file)
    }
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
            "{file:?} must be a relative path inside the package (no '..', not absolute)"
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

#[cfg(test)]
#[path = "manifest_tests.rs"]
mod tests;
