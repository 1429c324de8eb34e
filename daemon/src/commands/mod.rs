//! The command line's verbs ([`Cli`], [`Command`]) and one module per verb; each turns its
//! arguments into library options through [`crate::settings`] and runs them.

pub mod beats;
pub mod check_config;
pub mod convert;
pub mod dance;
pub mod eval;
pub mod features;
pub mod live;
pub mod mel;
pub mod models;
pub mod prep;
pub mod read_motion;
pub mod render;
pub mod serve;
pub mod stylize;
mod version;
pub mod view;

use std::io::Write;

use anyhow::Context;
use clap::{Parser, Subcommand};

use crate::cli::GlobalArgs;

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

/// The verbs.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Make a dance for a song: an HDF5 motion file with joints, the song's log-mel and provenance.
    ///
    /// Decodes the song, computes its log-mel, denoises overlapping windows of the whole song in
    /// batches with the model package's sampler, stitches them, and writes the file atomically.
    Dance(dance::DanceArgs),
    /// Motion style transfer: a content motion in the style of another (MCM-LDM latent
    /// diffusion, or MulSMo inversion), from any motion format, to an HDF5 motion file or BVH.
    ///
    /// Reads both motions as HumanML3D features at the model's rate, runs the model package's
    /// networks (default: the bundled closed-form style-gaussian, no download), recovers the
    /// joints and writes the file atomically with provenance naming both inputs.
    Stylize(stylize::StylizeArgs),
    /// Convert motion between AIST++ .pkl, joint/feature .npy, BVH and the HDF5 motion file.
    ///
    /// The pair is picked by file extensions; `--to features` asks for HumanML3D 263-dim features.
    /// Writes atomically; bad input is one error line naming the file.
    Convert(convert::ConvertArgs),
    /// Draw a motion: an animated GIF of the skeleton or a PNG contact sheet of frames.
    Render(render::RenderArgs),
    /// Compute librosa-exact log-mel features of an audio file and write them as float32 `.npy` (n_mels, T).
    Mel(mel::MelArgs),
    /// Compute the dance field's music features (`--set fact35`: FACT / EDGE / LODGE / FineDance's
    /// 35 librosa columns, exact to librosa 0.7.2) and write them as float32 `.npy` (T, 35).
    Features(features::FeaturesArgs),
    /// Estimate the tempo and beat times of an audio file (librosa's onset envelope and beat tracker).
    Beats(beats::BeatsArgs),
    /// Score motions with the field's metrics: FID_k/g, Div, BAS (both conventions), PFC, foot
    /// skating, TSI/FSF — each equal to the reference code that defines it, conventions printed.
    Eval(eval::EvalArgs),
    /// Prepare AIST++ or HumanML3D as training-ready HDF5 shards: parallel, resumable, shardable across machines.
    Prep(prep::PrepArgs),
    /// Model packages: `choreod models check DIR` loads one and validates it (exit 4 if unusable).
    Models(models::ModelsArgs),
    /// Run the watch-folder daemon: every song dropped into the inbox becomes one dance file.
    ///
    /// Crash-safe: a `kill -9` at any moment loses no input and leaves no partial output; on
    /// restart unfinished jobs resume. Each input gets exactly one outcome: `<song>.h5` in the
    /// output folder, or the input moved to the state folder's `failed/` with an `.error.json`.
    /// SIGTERM finishes jobs in flight; `/healthz` and `/metrics` on `metrics.bind`.
    Serve(serve::ServeArgs),
    /// Live input: dance to a sound card in real time, with a browser viewer, an HDF5 file and
    /// VMC (OSC) output for VTuber apps.
    ///
    /// Every hop (0.5 s) the newest window is generated with the motion already emitted as its
    /// seed frames, and only the new frames are emitted; under load the step count drops.
    Live(live::LiveArgs),
    /// Play a motion file in the browser viewer: serves the page on loopback and prints its URL.
    View(view::ViewArgs),
    /// Validate a daemon configuration file and the directories it names.
    ///
    /// Reports every problem at once, each naming its key; prints the effective configuration
    /// (defaults filled in) when it is valid. Exit code 3 when invalid.
    CheckConfig(check_config::CheckConfigArgs),
    /// The child process reading one untrusted motion file for its parent (internal).
    #[command(name = read_motion::VERB, hide = true)]
    IsolatedReadMotion(read_motion::ReadMotionArgs),
}

/// Write `text` to stdout at once; a reader that closed the pipe (`choreod beats song | head -1`)
/// is not an error, while `println!` would panic and exit 101 as an internal error.
/// The `--stats` line of `dance` and `stylize`: the run's report, its fields in their order
/// (scripts read the line by its first key), then `components`, where ONNX Runtime's time went.
#[derive(serde::Serialize)]
pub(crate) struct StatsLine<'a, R: serde::Serialize> {
    #[serde(flatten)]
    pub report: &'a R,
    pub components: Vec<choreo_models::ComponentTime>,
}

pub(crate) fn print_stdout(text: &str) -> anyhow::Result<()> {
    let mut out = std::io::stdout().lock();
    match out.write_all(text.as_bytes()).and_then(|()| out.flush()) {
        Err(e) if e.kind() != std::io::ErrorKind::BrokenPipe => Err(e).context("writing to stdout"),
        _ => Ok(()),
    }
}

/// Refuse an output (given by `flag`) whose folder is missing or unwritable before a long job
/// rather than after it; the folder is named, as the user wrote it.
pub(crate) fn check_output_folder(path: &std::path::Path, flag: &str) -> anyhow::Result<()> {
    choreo_dsp::atomic::probe_writable(path).with_context(|| {
        format!(
            "cannot create {flag} {} in the folder {}",
            path.display(),
            choreo_dsp::atomic::parent_dir(path).display()
        )
    })
}

/// Refuse an output (given by `flag`) that is one of `inputs` (each named by its flag) — the
/// same file by any path, symbolic or hard link: writing it would replace the input. Compared
/// by device and inode, so `./a.h5`, `a.h5` and a link to it are one file.
pub(crate) fn refuse_output_over_input(
    output: &std::path::Path,
    flag: &str,
    inputs: &[(&str, &std::path::Path)],
) -> anyhow::Result<()> {
    use std::os::unix::fs::MetadataExt;
    // An output that does not exist yet cannot be an input.
    let Ok(out) = std::fs::metadata(output) else {
        return Ok(());
    };
    for (input_flag, input) in inputs {
        if let Ok(m) = std::fs::metadata(input)
            && (m.dev(), m.ino()) == (out.dev(), out.ino())
        {
            return Err(crate::exit::Usage(format!(
                "{flag} {} is the same file as {input_flag} {}: writing it would replace the \
                 input; choose another output",
                output.display(),
                input.display()
            ))
            .into());
        }
    }
    Ok(())
}

/// Run the verb the user asked for (`serve` with its config file, loaded by `main`).
pub fn run(cli: Cli, serve_config: Option<crate::settings::ServeConfig>) -> anyhow::Result<()> {
    if cli.global.version {
        return version::run(&cli.global);
    }
    match cli.command {
        Some(Command::IsolatedReadMotion(args)) => read_motion::run(args),
        Some(Command::CheckConfig(args)) => check_config::run(args),
        Some(Command::Dance(args)) => dance::run(args, &cli.global),
        Some(Command::Stylize(args)) => stylize::run(args, &cli.global),
        Some(Command::Convert(args)) => convert::run(args, &cli.global),
        Some(Command::Render(args)) => render::run(args, &cli.global),
        Some(Command::Mel(args)) => mel::run(args, &cli.global),
        Some(Command::Beats(args)) => beats::run(args, &cli.global),
        Some(Command::Features(args)) => features::run(args, &cli.global),
        Some(Command::Eval(args)) => eval::run(args, &cli.global),
        Some(Command::Prep(args)) => prep::run(args, &cli.global),
        Some(Command::Models(args)) => models::run(args, &cli.global),
        Some(Command::Serve(args)) => {
            let path = serve::config_path(&args);
            let config = serve_config.unwrap_or_else(|| crate::settings::ServeConfig::load(path));
            serve::run(args, config, &cli.global)
        }
        Some(Command::Live(args)) => live::run(args, &cli.global),
        Some(Command::View(args)) => view::run(args, &cli.global),
        // arg_required_else_help makes clap print help when no verb is given.
        None => Ok(()),
    }
}
