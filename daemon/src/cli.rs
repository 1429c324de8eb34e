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

/// Parser of `--max-duration`: 0.1..=86400 s, as the config's `limits.max_audio_seconds`.
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
