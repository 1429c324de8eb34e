//! The manifest sections of `task = "lodge"` packages (written by models/export/lodge.py; the
//! keys are documented in models/export/README.md) and the `[audio]` section's two feature
//! sets. Every value is bounded here, so a hostile manifest gives one line naming its key.

use std::collections::BTreeMap;

use serde::Deserialize;

use super::{
    AudioSpec, BetaSchedule, DType, Dim, GUIDANCE_RANGE, KeyError, Manifest, Prediction, Role,
    SamplerKind, Task, batch, fixed,
};
use crate::error::{Error, Result};

/// The representation LODGE packages produce: 4 foot contacts, SMPL-X `transl`, 22 × 6D
/// (`choreo_datasets::smplx`).
pub const REPR_LODGE: &str = choreo_datasets::smplx::LODGE_REPRESENTATION;
/// Longest text value shown to users (names, summaries, URLs).
const MAX_TEXT: usize = 2000;
/// Most genres a package may name.
const MAX_GENRES: usize = 256;

/// `[license]`: the terms the weights come with.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
#[non_exhaustive]
pub struct LicenseSpec {
    /// Short name, e.g. "FineDance (non-commercial research)".
    pub name: String,
    /// Whether commercial use is allowed.
    pub commercial_use: bool,
    /// Whether the weights may be passed on.
    pub redistribution: bool,
    /// The terms in a sentence or two.
    #[serde(default)]
    pub summary: String,
    /// Where the terms are.
    #[serde(default)]
    pub url: String,
}

impl LicenseSpec {
    /// One line for stderr and the provenance: name, the two permissions, the URL.
    pub fn line(&self) -> String {
        let allowed = |yes: bool| if yes { "allowed" } else { "not allowed" };
        let mut line = format!(
            "licence: {} (commercial use {}, redistribution {})",
            self.name,
            allowed(self.commercial_use),
            allowed(self.redistribution)
        );
        if !self.url.is_empty() {
            line.push_str(&format!(", {}", self.url));
        }
        line
    }
}

/// `[audio]`: which music features the package's networks take.
#[derive(Debug, Clone, Deserialize)]
#[serde(try_from = "RawAudio")]
#[non_exhaustive]
pub enum AudioSection {
    /// `features = "log-mel"` (the default when the key is absent): [`AudioSpec`].
    LogMel(AudioSpec),
    /// `features = "fact35"`: the 35-value librosa set (`choreod features`).
    Fact35(Fact35Spec),
}

impl AudioSection {
    /// The `features` name.
    pub fn features(&self) -> &'static str {
        match self {
            Self::LogMel(_) => "log-mel",
            Self::Fact35(_) => "fact35",
        }
    }
}

/// `[audio]` of a fact35 package.
#[derive(Debug, Clone, Copy, PartialEq)]
#[non_exhaustive]
pub struct Fact35Spec {
    /// The librosa whose features the network was trained on.
    pub librosa: choreo_dsp::LibrosaVersion,
    /// Frames per second (30 or 60).
    pub fps: u32,
}

impl Fact35Spec {
    /// The options `choreo_dsp::load_fact35` computes this set with.
    pub fn options(&self) -> choreo_dsp::Fact35Options {
        choreo_dsp::Fact35Options {
            fps: self.fps,
            version: self.librosa,
            start_bpm: None,
        }
    }

    /// The manifest spelling of the librosa version.
    pub fn librosa_str(&self) -> &'static str {
        match self.librosa {
            choreo_dsp::LibrosaVersion::V07 => "0.7.2",
            choreo_dsp::LibrosaVersion::V010 => "0.10.1",
        }
    }
}

/// `[audio]` as written: either set's keys, checked in [`AudioSection::try_from`].
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawAudio {
    features: Option<String>,
    librosa: Option<String>,
    dim: Option<usize>,
    fps: Option<f64>,
    sample_rate: Option<u32>,
    n_fft: Option<usize>,
    hop: Option<usize>,
    n_mels: Option<usize>,
    fmin: Option<f64>,
    fmax: Option<f64>,
    top_db: Option<f64>,
    music_frames: Option<usize>,
}

impl TryFrom<RawAudio> for AudioSection {
    type Error = String;

    fn try_from(a: RawAudio) -> std::result::Result<Self, String> {
        let features = a.features.as_deref().unwrap_or("log-mel");
        let mel_keys = [
            ("sample_rate", a.sample_rate.is_some()),
            ("n_fft", a.n_fft.is_some()),
            ("hop", a.hop.is_some()),
            ("n_mels", a.n_mels.is_some()),
            ("fmin", a.fmin.is_some()),
            ("fmax", a.fmax.is_some()),
            ("top_db", a.top_db.is_some()),
            ("music_frames", a.music_frames.is_some()),
        ];
        let fact_keys = [
            ("librosa", a.librosa.is_some()),
            ("dim", a.dim.is_some()),
            ("fps", a.fps.is_some()),
        ];
        let foreign = |keys: &[(&str, bool)]| {
            keys.iter()
                .find(|(_, set)| *set)
                .map(|(k, _)| format!("audio.{k} is not a key of {features} audio"))
        };
        match features {
            "log-mel" => {
                if let Some(e) = foreign(&fact_keys) {
                    return Err(e);
                }
                let need = |k: &str| format!("audio.{k} missing (log-mel needs it)");
                Ok(Self::LogMel(AudioSpec {
                    sample_rate: a.sample_rate.ok_or_else(|| need("sample_rate"))?,
                    n_fft: a.n_fft.ok_or_else(|| need("n_fft"))?,
                    hop: a.hop.ok_or_else(|| need("hop"))?,
                    n_mels: a.n_mels.ok_or_else(|| need("n_mels"))?,
                    fmin: a.fmin.ok_or_else(|| need("fmin"))?,
                    fmax: a.fmax.ok_or_else(|| need("fmax"))?,
                    top_db: a.top_db.ok_or_else(|| need("top_db"))?,
                    music_frames: a.music_frames.ok_or_else(|| need("music_frames"))?,
                }))
            }
            "fact35" => {
                if let Some(e) = foreign(&mel_keys) {
                    return Err(e);
                }
                let librosa = match a.librosa.as_deref() {
                    Some("0.7.2") => choreo_dsp::LibrosaVersion::V07,
                    Some("0.10.1") => choreo_dsp::LibrosaVersion::V010,
                    Some(other) => {
                        return Err(format!(
                            "audio.librosa is {}, choreod computes fact35 as librosa \"0.7.2\" \
                             or \"0.10.1\" do",
                            choreo_dsp::quote(other)
                        ));
                    }
                    None => return Err("audio.librosa missing (fact35 needs it)".into()),
                };
                if a.dim.is_some_and(|d| d != choreo_dsp::FACT35_COLUMNS) {
                    return Err(format!(
                        "audio.dim must be {} for fact35",
                        choreo_dsp::FACT35_COLUMNS
                    ));
                }
                let fps = match a.fps {
                    Some(30.0) => 30,
                    Some(60.0) => 60,
                    Some(f) => {
                        return Err(format!("audio.fps must be 30 or 60 for fact35, got {f}"));
                    }
                    None => 30,
                };
                Ok(Self::Fact35(Fact35Spec { librosa, fps }))
            }
            other => Err(format!(
                "audio.features is {}, expected \"log-mel\" or \"fact35\"",
                choreo_dsp::quote(other)
            )),
        }
    }
}

/// `[motion.normalizer]`: LODGE's min-max scaler (preprocess.py:113-207): normalise
/// `clip(x·scale + offset, -1, 1)`, un-normalise `(clip(x, -1, 1) - offset) / scale`.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
#[non_exhaustive]
pub struct MinMaxNormalizer {
    /// `minmax`.
    pub kind: String,
    /// The stored tensors' dtype (`float32` or `float64`).
    pub dtype: String,
    /// Clip to [-1, 1] (always true for LODGE).
    pub clip: bool,
    /// `scale_`, one per feature.
    pub scale: Vec<f64>,
    /// `min_`, one per feature.
    pub offset: Vec<f64>,
}

impl MinMaxNormalizer {
    /// Normalise one float32 value of feature `c` as the official in-place float32 ops do
    /// (`X *= scale_; X += min_; clip`): each product and sum rounded to float32.
    pub fn normalize(&self, c: usize, x: f32) -> f32 {
        let y = (f64::from(x) * self.scale[c]) as f32;
        ((f64::from(y) + self.offset[c]) as f32).clamp(-1.0, 1.0)
    }

    /// Un-normalise one value of feature `c` (`clip; X -= min_; X /= scale_`, float32).
    pub fn unnormalize(&self, c: usize, x: f32) -> f32 {
        let y = (f64::from(x.clamp(-1.0, 1.0)) - self.offset[c]) as f32;
        (f64::from(y) / self.scale[c]) as f32
    }
}

/// `[lodge]`.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
#[non_exhaustive]
pub struct LodgeSection {
    /// Genre names, index = the id the local network takes (FineDance_dataset.py:48-72).
    pub genres: Vec<String>,
    /// Other spellings of genres → id.
    #[serde(default)]
    pub genre_aliases: BTreeMap<String, i64>,
    /// `[lodge.global]`.
    pub global: GlobalStage,
    /// `[lodge.local]`.
    pub local: LocalStage,
}

/// One LODGE stage's two networks and its window sizes, as the manifest and the pipeline see it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub struct StageLayout {
    /// The stage's music branch (its outputs: [`Manifest::lodge_music_outputs`]).
    pub music: Role,
    /// The stage's denoiser (`x0`).
    pub denoiser: Role,
    /// Music frames per window the music branch takes.
    pub music_frames: usize,
    /// Motion frames per window the denoiser makes.
    pub frames: usize,
}

impl LodgeSection {
    /// The two stages in the order they run: Global (music windows to keyframes), then Local.
    pub fn stages(&self) -> [StageLayout; 2] {
        [
            StageLayout {
                music: Role::GlobalMusic,
                denoiser: Role::GlobalDenoiser,
                music_frames: self.global.music_frames,
                frames: self.global.keyframes,
            },
            StageLayout {
                music: Role::LocalMusic,
                denoiser: Role::LocalDenoiser,
                music_frames: self.local.frames,
                frames: self.local.frames,
            },
        ]
    }
}

/// `[lodge.global]`.
#[derive(Debug, Clone, Copy, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
#[non_exhaustive]
pub struct GlobalStage {
    /// Music frames per Global window (1024).
    pub music_frames: usize,
    /// Keyframes the Global network makes per window (104 = 13 chunks of 8).
    pub keyframes: usize,
    /// Guidance weight.
    pub guidance: f32,
}

/// `[lodge.local]`.
#[derive(Debug, Clone, Copy, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
#[non_exhaustive]
pub struct LocalStage {
    /// Frames per Local window (256).
    pub frames: usize,
    /// The largest guidance weight.
    pub guidance: f32,
    /// Step i's weight is `min(guidance, linspace(ramp[0], ramp[1], steps)[i])`
    /// (diffusion.py:507).
    pub guidance_ramp: [f32; 2],
    /// Values of style noise per window (`style_noise (N, 256)`).
    pub style_noise: usize,
}

/// LODGE's window layout, which the constraint builder follows (infer_lodge.py:214-280,
/// Local_Module.py:175-224): 1024 music frames per Global window, 104 keyframes = 13 chunks of
/// 8, 256-frame Local windows, four of them per Global window.
pub const LODGE_LAYOUT: (usize, usize, usize) = (1024, 104, 256);

/// A validated LODGE package's own sections ([`Manifest::lodge_spec`]).
#[derive(Debug, Clone, Copy)]
#[non_exhaustive]
pub struct LodgeSpec<'a> {
    /// `[license]`.
    pub license: &'a LicenseSpec,
    /// `[audio]`.
    pub audio: Fact35Spec,
    /// `[motion.normalizer]`.
    pub normalizer: &'a MinMaxNormalizer,
    /// `motion.rest_joints`, flattened J × 3.
    pub rest_joints: &'a [f64],
    /// `sampler.timesteps`.
    pub timesteps: &'a [i64],
    /// `[lodge]`.
    pub section: &'a LodgeSection,
}

impl LodgeSpec<'_> {
    /// The rest joints as points.
    pub fn rest_points(&self) -> Vec<[f32; 3]> {
        self.rest_joints
            .chunks_exact(3)
            .map(|p| [p[0] as f32, p[1] as f32, p[2] as f32])
            .collect()
    }

    /// The id of a genre given as a name (case-insensitive, aliases too) or a number.
    pub fn genre_id(&self, given: &str) -> Option<usize> {
        let s = self.section;
        if let Ok(id) = given.parse::<usize>() {
            return (id < s.genres.len()).then_some(id);
        }
        s.genres
            .iter()
            .position(|g| g.eq_ignore_ascii_case(given))
            .or_else(|| {
                s.genre_aliases
                    .iter()
                    .find(|(k, _)| k.eq_ignore_ascii_case(given))
                    .map(|(_, &v)| v as usize)
            })
    }
}

impl Manifest {
    /// The `[license]` line for provenance and stderr, "" when the package has none.
    pub fn license_line(&self) -> String {
        self.license
            .as_ref()
            .map(LicenseSpec::line)
            .unwrap_or_default()
    }

    /// The LODGE sections, or an error naming the task when this is not a lodge package (they
    /// are validated at parse).
    pub fn lodge_spec(&self) -> Result<LodgeSpec<'_>> {
        let m = &self.motion;
        match (
            self.task,
            &self.license,
            &self.audio,
            &m.normalizer,
            &m.rest_joints,
            &self.sampler.timesteps,
            &self.lodge,
        ) {
            (
                Task::Lodge,
                Some(license),
                Some(AudioSection::Fact35(audio)),
                Some(normalizer),
                Some(rest_joints),
                Some(timesteps),
                Some(section),
            ) => Ok(LodgeSpec {
                license,
                audio: *audio,
                normalizer,
                rest_joints,
                timesteps,
                section,
            }),
            _ => Err(Error::Manifest {
                package: self.dir.clone(),
                key: "task".into(),
                reason: format!("is {}, this needs a lodge package", self.task),
            }),
        }
    }

    /// Every LODGE section present and bounded, and the four components' interfaces.
    pub(super) fn validate_lodge(&self) -> std::result::Result<(), KeyError> {
        let fail = |key: &str, reason: String| Err(KeyError::new(key, reason));
        let needed = |key: &str| KeyError::new(key, "missing (lodge needs it)".to_string());
        let license = self.license.as_ref().ok_or_else(|| needed("license"))?;
        for (key, text) in [
            ("license.name", &license.name),
            ("license.summary", &license.summary),
            ("license.url", &license.url),
        ] {
            if text.len() > MAX_TEXT || text.chars().any(char::is_control) {
                return fail(key, format!("must be one line of at most {MAX_TEXT} bytes"));
            }
        }
        if license.name.trim().is_empty() {
            return fail("license.name", "must not be empty".into());
        }
        let audio = match self.audio.as_ref().ok_or_else(|| needed("audio"))? {
            AudioSection::Fact35(a) => a,
            AudioSection::LogMel(_) => {
                return fail(
                    "audio.features",
                    "is log-mel; lodge packages take fact35".into(),
                );
            }
        };
        let m = &self.motion;
        let dim = choreo_datasets::smplx::LODGE_FEATURES;
        if m.representation != REPR_LODGE
            || m.skeleton != choreo_datasets::smplx::SMPLX22_SKELETON
            || m.dim != dim
        {
            return fail(
                "motion",
                format!(
                    "lodge needs representation {REPR_LODGE:?}, skeleton \"smplx22\" and dim \
                     {dim}, got {}, {} and {}",
                    choreo_dsp::quote(&m.representation),
                    choreo_dsp::quote(&m.skeleton),
                    m.dim
                ),
            );
        }
        if m.fps != f64::from(audio.fps) {
            return fail(
                "motion.fps",
                format!("must equal audio.fps ({}), got {}", audio.fps, m.fps),
            );
        }
        let rest = m
            .rest_joints
            .as_ref()
            .ok_or_else(|| needed("motion.rest_joints"))?;
        let body = choreo_datasets::smplx::BODY_JOINTS;
        if !rest.len().is_multiple_of(3) || rest.len() < 3 * body || rest.len() > 3 * 1000 {
            return fail(
                "motion.rest_joints",
                format!(
                    "must hold J × 3 values with {body} <= J <= 1000, got {} values",
                    rest.len()
                ),
            );
        }
        if let Some(i) = rest
            .iter()
            .position(|v| !(v.is_finite() && v.abs() <= 10.0))
        {
            return fail(
                "motion.rest_joints",
                format!("value {i} is not a position within 10 m of the origin"),
            );
        }
        let n = m
            .normalizer
            .as_ref()
            .ok_or_else(|| needed("motion.normalizer"))?;
        if n.kind != "minmax" || !n.clip {
            return fail(
                "motion.normalizer",
                "must have kind = \"minmax\" and clip = true (LODGE's scaler)".into(),
            );
        }
        if n.dtype != "float32" && n.dtype != "float64" {
            return fail(
                "motion.normalizer.dtype",
                format!(
                    "must be float32 or float64, got {}",
                    choreo_dsp::quote(&n.dtype)
                ),
            );
        }
        for (key, values) in [
            ("motion.normalizer.scale", &n.scale),
            ("motion.normalizer.offset", &n.offset),
        ] {
            if values.len() != dim {
                return fail(key, format!("has {} values, needs {dim}", values.len()));
            }
            if let Some(i) = values
                .iter()
                .position(|v| !(v.is_finite() && v.abs() <= 1e12))
            {
                return fail(key, format!("value {i} is not finite or beyond 1e12"));
            }
        }
        if let Some(i) = n.scale.iter().position(|v| v.abs() < 1e-12) {
            return fail(
                "motion.normalizer.scale",
                format!("value {i} is zero (the scaler divides by it)"),
            );
        }
        let d = &self.diffusion;
        if d.beta_schedule != BetaSchedule::Cosine
            || d.prediction != Prediction::X0
            || !d.clip_sample
        {
            return fail(
                "diffusion",
                "lodge needs beta_schedule = \"cosine\", prediction = \"x0\", clip_sample = true"
                    .into(),
            );
        }
        if d.cosine_s.is_some_and(|s| s != 0.008) || d.max_beta.is_some_and(|b| b != 0.999) {
            return fail(
                "diffusion.cosine_s",
                "only the cosine schedule with s = 0.008 and max_beta = 0.999 is computed".into(),
            );
        }
        let s = &self.sampler;
        if s.kind != SamplerKind::Ddim {
            return fail("sampler.kind", "lodge samples with ddim".into());
        }
        let times = s
            .timesteps
            .as_ref()
            .ok_or_else(|| needed("sampler.timesteps"))?;
        let train = d.train_steps as i64;
        if times.len() != s.steps
            || times.windows(2).any(|w| w[1] >= w[0])
            || times.iter().any(|t| !(0..train).contains(t))
        {
            return fail(
                "sampler.timesteps",
                format!(
                    "must be sampler.steps ({}) decreasing values in 0..{train}",
                    s.steps
                ),
            );
        }
        let l = self.lodge.as_ref().ok_or_else(|| needed("lodge"))?;
        if l.genres.is_empty() || l.genres.len() > MAX_GENRES {
            return fail(
                "lodge.genres",
                format!("must name 1..={MAX_GENRES} genres, got {}", l.genres.len()),
            );
        }
        if let Some(g) = l
            .genres
            .iter()
            .chain(l.genre_aliases.keys())
            .find(|g| g.is_empty() || g.len() > 64 || g.chars().any(char::is_control))
        {
            return fail(
                "lodge.genres",
                format!(
                    "{} is not a name of 1..=64 printable bytes",
                    choreo_dsp::quote(g)
                ),
            );
        }
        if let Some((k, v)) = l
            .genre_aliases
            .iter()
            .find(|&(_, &v)| !usize::try_from(v).is_ok_and(|v| v < l.genres.len()))
        {
            return fail(
                "lodge.genre_aliases",
                format!(
                    "{} = {v} is not a genre id (0..{})",
                    choreo_dsp::quote(k),
                    l.genres.len()
                ),
            );
        }
        let (music, keys, frames) = LODGE_LAYOUT;
        if (l.global.music_frames, l.global.keyframes, l.local.frames) != (music, keys, frames) {
            return fail(
                "lodge",
                format!(
                    "this choreod runs LODGE's layout: global.music_frames = {music}, \
                     global.keyframes = {keys}, local.frames = {frames}; got {}, {} and {}",
                    l.global.music_frames, l.global.keyframes, l.local.frames
                ),
            );
        }
        for (key, w) in [
            ("lodge.global.guidance", l.global.guidance),
            ("lodge.local.guidance", l.local.guidance),
            ("lodge.local.guidance_ramp", l.local.guidance_ramp[0]),
            ("lodge.local.guidance_ramp", l.local.guidance_ramp[1]),
        ] {
            if !GUIDANCE_RANGE.contains(&w) {
                return fail(
                    key,
                    format!(
                        "must be in {}..={}, got {w}",
                        GUIDANCE_RANGE.start(),
                        GUIDANCE_RANGE.end()
                    ),
                );
            }
        }
        if !(1..=4096).contains(&l.local.style_noise) {
            return fail(
                "lodge.local.style_noise",
                format!("must be in 1..=4096, got {}", l.local.style_noise),
            );
        }
        self.validate_lodge_components()
    }

    fn validate_lodge_components(&self) -> std::result::Result<(), KeyError> {
        let l = self.lodge.as_ref().expect("checked");
        let f32 = DType::Float32;
        let cols = fixed(choreo_dsp::FACT35_COLUMNS);
        let n = [batch()];
        for stage in l.stages() {
            let (music_role, denoiser_role) = (stage.music, stage.denoiser);
            let shared = self.lodge_music_outputs(stage)?;
            let shared: Vec<(&str, DType, &[Dim])> = shared
                .iter()
                .map(|(name, shape)| (*name, f32, shape.as_slice()))
                .collect();
            self.check_contract(
                music_role,
                &[
                    (
                        "music",
                        f32,
                        &[batch(), fixed(stage.music_frames), cols.clone()],
                    ),
                    ("keep", f32, &n),
                ],
                &shared,
            )?;
            let x = [batch(), fixed(stage.frames), fixed(self.motion.dim)];
            let mut inputs: Vec<(&str, DType, &[Dim])> =
                vec![("x_t", f32, &x[..]), ("t", DType::Int64, &n[..])];
            inputs.extend(shared.iter().copied());
            let style = [batch(), fixed(l.local.style_noise)];
            if denoiser_role == Role::LocalDenoiser {
                inputs.push(("genre", DType::Int64, &n[..]));
                inputs.push(("style_noise", f32, &style[..]));
            }
            self.check_contract(denoiser_role, &inputs, &[("x0", f32, &x[..])])?;
        }
        Ok(())
    }

    /// The music branch's outputs, which the denoiser takes as they are, in one of two layouts:
    /// `cond_tokens (N, frames, D)` and `cond_hidden (N, D)`; or `cond_hidden` and every
    /// decoder layer's cross-attention keys and values of the music tokens, `cross_k` and
    /// `cross_v (N, layers, frames, D)` (models/export/lodge.py `components`).
    fn lodge_music_outputs(
        &self,
        stage: StageLayout,
    ) -> std::result::Result<Vec<(&'static str, Vec<Dim>)>, KeyError> {
        let role = stage.music;
        let frames = stage.music_frames as i64;
        let key = format!("components.{role}.outputs");
        let hidden = self.batched_output(role, "cond_hidden")?;
        let width = match hidden.as_slice() {
            [_, Dim::Fixed(w)] if (1..=65536).contains(w) => *w,
            _ => {
                return Err(KeyError::new(
                    key,
                    "cond_hidden must be (N, D) with D in 1..=65536".to_string(),
                ));
            }
        };
        let hidden = ("cond_hidden", vec![batch(), Dim::Fixed(width)]);
        let hoisted = self.components[&role]
            .outputs
            .iter()
            .any(|t| t.name == "cross_k");
        if hoisted {
            let layers = match self.batched_output(role, "cross_k")?.as_slice() {
                [_, Dim::Fixed(layers), Dim::Fixed(t), Dim::Fixed(w)]
                    if *t == frames && *w == width && (1..=256).contains(layers) =>
                {
                    *layers
                }
                _ => {
                    return Err(KeyError::new(
                        key,
                        format!(
                            "cross_k must be (N, layers, {frames}, D) with layers in 1..=256 \
                             and cond_hidden's D"
                        ),
                    ));
                }
            };
            let kv = vec![
                batch(),
                Dim::Fixed(layers),
                Dim::Fixed(frames),
                Dim::Fixed(width),
            ];
            return Ok(vec![hidden, ("cross_k", kv.clone()), ("cross_v", kv)]);
        }
        match self.batched_output(role, "cond_tokens")?.as_slice() {
            [_, Dim::Fixed(t), Dim::Fixed(w)] if *t == frames && *w == width => Ok(vec![
                (
                    "cond_tokens",
                    vec![batch(), Dim::Fixed(frames), Dim::Fixed(width)],
                ),
                hidden,
            ]),
            _ => Err(KeyError::new(
                key,
                format!("cond_tokens must be (N, {frames}, D) with cond_hidden's D"),
            )),
        }
    }
}
