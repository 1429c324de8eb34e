//! The command line: verbs and flags (a contract, see DESIGN.md). Parsing only checks syntax;
//! each verb turns its arguments into library options once.

use std::path::PathBuf;

use clap::{Args, Parser, Subcommand, ValueEnum};

use crate::commands;

const ABOUT: &str = "Music to 3D dance, and dance/motion dataset preparation, with diffusion \
models exported to ONNX.";

const AFTER_HELP: &str = "\
Examples:
  choreod dance song.ogg -o song.h5                a dance for a song (bundled model)
  choreod render song.h5 -o song.gif               look at it
  choreod stylize --content walk.bvh --style dance.pkl -o styled.h5   motion style transfer
  choreod convert song.h5 -o song.bvh              for Blender
  choreod mel song.ogg -o song.mel.npy --stats     librosa-exact 80-band log-mel
  choreod features song.ogg -o f.npy --set fact35  LODGE/FineDance/EDGE's 35 music features
  choreod serve --config config/choreod.example.toml   the watch-folder daemon
  choreod live -o take.h5 --viewer 127.0.0.1:8080      dance to the sound card, live
  choreod view song.h5                             look at a motion in the browser
  choreod prep aistpp ~/data/aistpp -o ~/prep/aistpp   training-ready shards

Exit codes: 0 ok, 1 the work failed (bad input), 2 usage error, 3 invalid config,
4 ONNX Runtime or model package not usable, 101 internal error (a bug).
ONNX Runtime is loaded from --ort-library, else $ORT_DYLIB_PATH, else the checkout's
.venv/libonnxruntime.so (made by scripts/setup).";

/// `choreod`
#[derive(Debug, Parser)]
#[command(name = "choreod", about = ABOUT, after_help = AFTER_HELP, disable_version_flag = true)]
#[command(arg_required_else_help = true, propagate_version = false)]
pub struct Cli {
    #[command(flatten)]
    pub global: GlobalArgs,
    #[command(subcommand)]
    pub command: Option<Command>,
}

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

/// The verbs.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Make a dance for a song: an HDF5 motion file with joints, the song's log-mel and provenance.
    ///
    /// Decodes the song, computes its log-mel, denoises overlapping windows of the whole song in
    /// batches with the model package's sampler, stitches them, and writes the file atomically.
    Dance(commands::dance::DanceArgs),
    /// Motion style transfer: a content motion in the style of another (MCM-LDM latent
    /// diffusion, or MulSMo inversion), from any motion format, to an HDF5 motion file or BVH.
    ///
    /// Reads both motions as HumanML3D features at the model's rate, runs the model package's
    /// networks (default: the bundled closed-form style-gaussian, no download), recovers the
    /// joints and writes the file atomically with provenance naming both inputs.
    Stylize(commands::stylize::StylizeArgs),
    /// Convert motion between AIST++ .pkl, joint/feature .npy, BVH and the HDF5 motion file.
    ///
    /// The pair is picked by file extensions; `--to features` asks for HumanML3D 263-dim features.
    /// Writes atomically; bad input is one error line naming the file.
    Convert(commands::convert::ConvertArgs),
    /// Draw a motion: an animated GIF of the skeleton or a PNG contact sheet of frames.
    Render(commands::render::RenderArgs),
    /// Compute librosa-exact log-mel features of an audio file and write them as float32 `.npy` (n_mels, T).
    Mel(commands::mel::MelArgs),
    /// Compute the dance field's music features (`--set fact35`: FACT / EDGE / LODGE / FineDance's
    /// 35 librosa columns, exact to librosa 0.7.2) and write them as float32 `.npy` (T, 35).
    Features(commands::features::FeaturesArgs),
    /// Estimate the tempo and beat times of an audio file (librosa's onset envelope and beat tracker).
    Beats(commands::beats::BeatsArgs),
    /// Score motions with the field's metrics: FID_k/g, Div, BAS (both conventions), PFC, foot
    /// skating, TSI/FSF — each equal to the reference code that defines it, conventions printed.
    Eval(commands::eval::EvalArgs),
    /// Prepare AIST++ or HumanML3D as training-ready HDF5 shards: parallel, resumable, shardable across machines.
    Prep(commands::prep::PrepArgs),
    /// Model packages: `choreod models check DIR` loads one and validates it (exit 4 if unusable).
    Models(commands::models::ModelsArgs),
    /// Run the watch-folder daemon: every song dropped into the inbox becomes one dance file.
    ///
    /// Crash-safe: a `kill -9` at any moment loses no input and leaves no partial output; on
    /// restart unfinished jobs resume. Each input gets exactly one outcome: `<song>.h5` in the
    /// output folder, or the input moved to the state folder's `failed/` with an `.error.json`.
    /// SIGTERM finishes jobs in flight; `/healthz` and `/metrics` on `metrics.bind`.
    Serve(commands::serve::ServeArgs),
    /// Live input: dance to a sound card in real time, with a browser viewer, an HDF5 file and
    /// VMC (OSC) output for VTuber apps.
    ///
    /// Every hop (0.5 s) the newest window is generated with the motion already emitted as its
    /// seed frames, and only the new frames are emitted; under load the step count drops.
    Live(commands::live::LiveArgs),
    /// Play a motion file in the browser viewer: serves the page on loopback and prints its URL.
    View(commands::view::ViewArgs),
    /// Validate a daemon configuration file and the directories it names.
    ///
    /// Reports every problem at once, each naming its key; prints the effective configuration
    /// (defaults filled in) when it is valid. Exit code 3 when invalid.
    CheckConfig(commands::check_config::CheckConfigArgs),
    /// The child process reading one untrusted motion file for its parent (internal).
    #[command(name = commands::read_motion::VERB, hide = true)]
    IsolatedReadMotion(commands::read_motion::ReadMotionArgs),
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
