//! The command line's low layer (ripgrep's LowArgs): the flags every verb accepts, the flag
//! groups and value enums verbs share, and the value parsers. Parsing only checks syntax; the
//! verbs ([`crate::commands`]) turn arguments into library options once, through
//! [`crate::settings`].

use std::path::PathBuf;

use clap::{Args, ValueEnum};

/// Flags every verb accepts.
#[derive(Debug, Args)]
#[command(next_help_heading = "Global options")]
pub struct GlobalArgs {
    /// Print the version of choreod and of the ONNX Runtime library it loads, then exit.
    #[arg(short = 'V', long)]
    pub version: bool,
    /// Log format on stderr. Default: human (for serve: the config's `log.format`).
    #[arg(long, value_enum, global = true)]
    pub log_format: Option<LogFormatArg>,
    /// Log filter, e.g. `info`, `debug`, `choreod=debug`. Default: `warn` (for serve: the
    /// config's `log.level`, `info` by default). `RUST_LOG` overrides it.
    #[arg(long, global = true, value_name = "FILTER")]
    pub log_level: Option<String>,
    /// Path to libonnxruntime.so (overrides ORT_DYLIB_PATH and the config).
    #[arg(long, global = true, value_name = "FILE")]
    pub ort_library: Option<PathBuf>,
}

/// Log formats.
#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum LogFormatArg {
    /// Readable lines.
    Human,
    /// One JSON object per line.
    Json,
}

/// Samplers (the models crate's [`choreo_models::SamplerKind`]).
#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum SamplerArg {
    Ddim,
    Ddpm,
    #[value(name = "dpmsolver++")]
    DpmSolverPlusPlus,
}

impl SamplerArg {
    /// The models crate's sampler.
    pub fn kind(self) -> choreo_models::SamplerKind {
        match self {
            Self::Ddim => choreo_models::SamplerKind::Ddim,
            Self::Ddpm => choreo_models::SamplerKind::Ddpm,
            Self::DpmSolverPlusPlus => choreo_models::SamplerKind::DpmSolverPlusPlus,
        }
    }
}

/// Music feature sets (`features --set`, `prep aistpp --features`).
#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum FeatureSet {
    /// FACT / AIST++, EDGE's baseline, LODGE, FineDance: onset envelope, 20 MFCC, 12
    /// chroma_cens, onset peaks (one-hot), beats (one-hot).
    Fact35,
}

/// Reference librosa versions of the music features (`--librosa`).
#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum LibrosaArg {
    /// librosa 0.7.2 with resampy 0.3 (LODGE, FineDance and the models trained on them).
    #[value(name = "0.7")]
    V07,
    /// librosa 0.10.1 with python-soxr (current librosa; 36-bin-per-octave chroma, soxr
    /// resampling, zero-padded frames).
    #[value(name = "0.10")]
    V010,
}

impl LibrosaArg {
    /// The dsp crate's version.
    pub fn version(self) -> choreo_dsp::LibrosaVersion {
        match self {
            Self::V07 => choreo_dsp::LibrosaVersion::V07,
            Self::V010 => choreo_dsp::LibrosaVersion::V010,
        }
    }
}

/// Timestep spacings (diffusers' `timestep_spacing`).
#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum SpacingArg {
    Leading,
    Trailing,
    Linspace,
}

impl SpacingArg {
    /// The models crate's spacing.
    pub fn spacing(self) -> choreo_models::TimestepSpacing {
        match self {
            Self::Leading => choreo_models::TimestepSpacing::Leading,
            Self::Trailing => choreo_models::TimestepSpacing::Trailing,
            Self::Linspace => choreo_models::TimestepSpacing::Linspace,
        }
    }
}

/// Style-transfer modes (the models crate's [`choreo_models::StyleMode`]).
#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum ModeArg {
    Transfer,
    Inversion,
}

impl ModeArg {
    /// The models crate's mode.
    pub fn mode(self) -> choreo_models::StyleMode {
        match self {
            Self::Transfer => choreo_models::StyleMode::Transfer,
            Self::Inversion => choreo_models::StyleMode::Inversion,
        }
    }
}

/// The model package a verb runs and ONNX Runtime's threads (`dance`, `stylize`, `live`); a
/// verb whose default package differs words `--model` its own way (`mut_arg`).
#[derive(Debug, Args)]
#[command(next_help_heading = "Model")]
pub struct ModelArgs {
    /// Model package directory. Default: $CHOREOD_MODEL, else the bundled
    /// models/packages/library.
    #[arg(long, value_name = "DIR")]
    pub model: Option<PathBuf>,
    /// ONNX Runtime threads inside one operator, up to the CPUs this process may use; 0 (the
    /// default) takes one per such CPU (CPU affinity and cgroup quotas counted).
    #[arg(long, value_parser = intra_threads,
          default_value_t = choreo_models::RuntimeOptions::default().intra_threads)]
    pub intra_threads: usize,
}

/// The diffusion sampler of a music-to-dance run (`dance`, `live`): which sampler, how many
/// steps, which noise.
#[derive(Debug, Args)]
#[command(next_help_heading = "Sampler")]
pub struct SamplerArgs {
    /// Sampler: ddim, ddpm or dpmsolver++ (DPM-Solver++ 2M, deterministic). Default: the
    /// package's.
    #[arg(long, value_enum)]
    pub sampler: Option<SamplerArg>,
    /// Denoising steps. Default: the package's (`sampler.steps` in its manifest).
    #[arg(long)]
    pub steps: Option<usize>,
    /// Seed of all noise: the same seed, song and model give the identical dance.
    #[arg(long, default_value_t = choreo_models::DanceOptions::default().seed)]
    pub seed: u64,
}

/// The motion file a verb writes (`dance`, `stylize`): its path, whose extension names the
/// format, and the bone names and mesh of the formats that have them.
#[derive(Debug, Args)]
#[command(next_help_heading = "Output")]
pub struct OutputArgs {
    /// The motion to write, in the format its extension names: .h5 (the motion file, format
    /// choreod-motion v2, with provenance), .bvh, .glb / .gltf (skinned mannequin) or .npy
    /// (joints). Written under a temporary name and renamed into place only when complete.
    #[arg(short, long, value_name = "OUT.h5")]
    pub output: PathBuf,
    #[command(flatten)]
    pub export: crate::commands::convert::ExportArgs,
}

/// `--time-limit` of the verbs that run a model over a whole input (`dance`, `stylize`).
#[derive(Debug, Args)]
pub struct TimeLimitArg {
    /// Stop and fail after this many seconds (0.1..=86400; the config's `job.time_limit_s` for
    /// serve): a model that runs too long, or for ever, cannot hang the command.
    #[arg(long, value_name = "SECONDS", value_parser = max_seconds,
          default_value_t = choreo_config::JobConfig::DEFAULT_TIME_LIMIT_S)]
    pub time_limit: f64,
}

impl TimeLimitArg {
    /// The deadline of work starting now.
    pub fn deadline(&self) -> choreo_models::Deadline {
        crate::settings::deadline(self.time_limit)
    }
}

/// Parser of a frame rate flag (`--fps`, `--style-fps`, `--bas-fps`): the range every motion
/// reader accepts (`choreo_datasets::limits::FPS_RANGE`, 1..=1000).
pub fn fps(text: &str) -> Result<f32, String> {
    within(number(text)?, choreo_datasets::limits::FPS_RANGE)
}

/// Parser of a guidance weight (`--guidance`, `--content-guidance`, `--style-guidance`):
/// `choreo_models::GUIDANCE_RANGE`, 0..=100, as in a package's manifest.
pub fn guidance(text: &str) -> Result<f32, String> {
    within(number(text)?, choreo_models::GUIDANCE_RANGE)
}

/// Parser of `--eta`: `choreo_models::ETA_RANGE`, 0..=1.
pub fn eta(text: &str) -> Result<f64, String> {
    within(number(text)?, choreo_models::ETA_RANGE)
}

/// Longest song a duration limit may name: a day, as the config's `limits.max_audio_seconds`.
const MAX_SECONDS: f64 = 86_400.0;

/// Parser of a duration limit (`--max-duration`, `--time-limit`): 0.1..=86400 s, as the
/// config's `limits.max_audio_seconds` and `job.time_limit_s`.
pub fn max_seconds(text: &str) -> Result<f64, String> {
    within(number(text)?, 0.1..=MAX_SECONDS)
}

/// Parser of `--min-duration`: 0..=86400 s.
pub fn min_seconds(text: &str) -> Result<f64, String> {
    within(number(text)?, 0.0..=MAX_SECONDS)
}

/// Parser of `--intra-threads`: 0 (one per core) up to the CPUs this process may run on
/// (`available_parallelism`: affinity and cgroup quotas included). More threads than CPUs never
/// speed an operator up, and ONNX Runtime's spinning pool then stalls: 1024 threads on 2 CPUs
/// did not finish a 2-step dance in 5 minutes; 2000 deadlocked and 100000 crashed (issue 20).
pub fn intra_threads(text: &str) -> Result<usize, String> {
    let cpus = std::thread::available_parallelism().map_or(1, std::num::NonZero::get);
    within(number(text)?, 0..=cpus).map_err(|e| format!("{e} (the CPUs this process may use)"))
}

fn number<T: std::str::FromStr>(text: &str) -> Result<T, String>
where
    T::Err: std::fmt::Display,
{
    text.trim().parse().map_err(|e: T::Err| e.to_string())
}

/// `value` when it lies in `range` (NaN lies in none).
fn within<T: PartialOrd + std::fmt::Display>(
    value: T,
    range: std::ops::RangeInclusive<T>,
) -> Result<T, String> {
    if range.contains(&value) {
        Ok(value)
    } else {
        Err(format!("must be in {}..={}", range.start(), range.end()))
    }
}

/// Parser of a count that must be at least 1 (a batch of zero would do nothing): 0 is a usage
/// error at parse time rather than silently meaning 1.
pub fn at_least_one(text: &str) -> Result<usize, String> {
    match text.parse::<usize>() {
        Ok(0) => Err("must be at least 1".to_string()),
        Ok(n) => Ok(n),
        Err(e) => Err(e.to_string()),
    }
}
