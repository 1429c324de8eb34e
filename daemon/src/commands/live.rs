//! `choreod live` — a sound card in, dance out in real time.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::time::Duration;

use anyhow::Context;
use clap::Args;

use choreo_config::LiveConfig;

use crate::cli::{GlobalArgs, ModelArgs, SamplerArgs};
use crate::commands::convert::ExportArgs;
use crate::live::{LiveMetrics, LiveOptions, LiveViewer, capture, run_session};
use crate::settings::{self, PackageKind};

/// Arguments of `live`: the sampler's steps are the most per window, and the seed is not a
/// promise of the same dance (that depends on when audio arrives).
#[derive(Debug, Args)]
#[command(mut_arg("model", |a| a.help("Model package directory. Default: $CHOREOD_MODEL, else the bundled library")))]
#[command(mut_arg("steps", |a| a.help("Most denoising steps per window. Default: the package's")))]
#[command(mut_arg("sampler", |a| a.help("Sampler. Default: the package's")))]
#[command(mut_arg("seed", |a| a.help("Seed of all noise")))]
#[command(after_help = "\
Examples:
  choreod live --list-devices                          the input devices and their formats
  choreod live -o session.h5 --viewer 127.0.0.1:8080   dance to the default input; open the URL
  choreod live --device pulse --osc 127.0.0.1:39539    drive a VTuber app (VMC protocol)
  choreod live -o take.h5 --duration 60 --stats        one minute of audio, then a JSON line
  choreod live -o take.h5 --max-wall-time 300          stop after 5 minutes, audio or not
  choreod live -o take.glb                             the take as a mannequin glTF at the end
Stop with Ctrl-C: the motion file is finished and renamed into place (with its provenance).
A take that made no motion (no audio arrived) writes no file and exits with an error.
Frames leave one frame period apart, hop + latency budget after their audio; frames of a
window over the budget are skipped (logged), never sent in a burst. Every 10 s a latency
line is logged. After `kill -9` the frames flushed so far are in a hidden file next to the
output (.NAME.tmp-*): rename it to recover the take.")]
pub struct LiveArgs {
    /// Print the input devices (name, channels, rate, sample format) and exit.
    #[arg(long)]
    pub list_devices: bool,
    /// Input device, as `--list-devices` prints it: its id (`alsa:pulse`), the id without the
    /// host (`pulse`) or its description. Default: the system's default input.
    #[arg(long, value_name = "NAME")]
    pub device: Option<String>,
    /// Motion file to write (HDF5): appended and flushed every 0.5 s under a hidden temporary
    /// name, renamed to this name when the session ends. Another extension (.bvh, .glb, .gltf,
    /// .npy) records the take as HDF5 beside it and writes that format when the session ends.
    #[arg(short, long, value_name = "OUT.h5")]
    pub output: Option<PathBuf>,
    #[command(flatten)]
    pub export: ExportArgs,
    /// Stop after this many seconds of audio heard (default: run until Ctrl-C / SIGTERM). Time
    /// with no audio arriving does not count: see --max-wall-time.
    #[arg(long, value_name = "S")]
    pub duration: Option<f64>,
    /// Stop after this many seconds on the clock, whether audio arrived or not.
    #[arg(long, value_name = "S")]
    pub max_wall_time: Option<f64>,
    /// Seconds between windows: each window emits this much new motion.
    #[arg(long, value_name = "S", default_value_t = LiveConfig::DEFAULT_HOP_S)]
    pub hop: f64,
    /// Fewest steps per window: when a window takes too long the step count drops to this.
    #[arg(long, default_value_t = LiveConfig::DEFAULT_MIN_STEPS)]
    pub min_steps: usize,
    /// Latency to hold, in seconds from audio in to motion out: a window slower than 0.8 of it
    /// gets fewer steps (down to --min-steps); steps come back when windows are fast again.
    #[arg(long, value_name = "S", default_value_t = LiveConfig::DEFAULT_LATENCY_BUDGET_S)]
    pub latency_budget: f64,
    /// Serve the viewer page and the live WebSocket on this address (loopback, e.g.
    /// 127.0.0.1:8080; port 0 picks one). The URL is printed on stderr.
    #[arg(long, value_name = "ADDR")]
    pub viewer: Option<SocketAddr>,
    /// Send VMC protocol bone messages (OSC over UDP) to this address, e.g. 127.0.0.1:39539.
    #[arg(long, value_name = "ADDR")]
    pub osc: Option<SocketAddr>,
    /// Nice value of the generation and capture threads, -20 (highest priority) to 19; 0
    /// leaves them as they are. Needs CAP_SYS_NICE or an RLIMIT_NICE allowing it (root has
    /// it); otherwise one warning and the session runs at normal priority.
    #[arg(long, value_name = "N", default_value_t = LiveConfig::DEFAULT_NICE, allow_negative_numbers = true,
          value_parser = clap::value_parser!(i32).range(-20..=19))]
    pub nice: i32,
    /// Print one JSON line on stdout at the end: latency percentiles, steps, overruns,
    /// reconnects, frames skipped late, seconds waited for audio, real-time factor, CPU share,
    /// whether the output was written.
    #[arg(long)]
    pub stats: bool,
    // The shared groups last: each starts a help heading that would also take the flags after it.
    #[command(flatten)]
    pub model: ModelArgs,
    #[command(flatten)]
    pub sampler: SamplerArgs,
}

pub fn run(args: LiveArgs, global: &GlobalArgs) -> anyhow::Result<()> {
    let max_wall = args
        .max_wall_time
        .map(|s| positive_seconds("--max-wall-time", s))
        .transpose()?;
    if args.list_devices {
        let lines: String = capture::list_devices()?
            .iter()
            .map(|line| format!("{line}\n"))
            .collect();
        return super::print_stdout(&lines);
    }
    // This thread generates: raised before the package loads, so that ONNX Runtime's worker
    // threads, started with it, inherit the priority.
    let export = args.export.options();
    let take = match &args.output {
        Some(out) => Some(take_path(out, &export)?),
        None => None,
    };
    crate::live::priority::raise_current_thread(args.nice);
    let ort = settings::ort(global.ort_library.as_deref())?;
    let mut package = args
        .model
        .load(PackageKind::Dance, &args.model.runtime(), &ort)?;

    let options = LiveOptions {
        device: args.device,
        hop_s: args.hop,
        steps: args.sampler.steps,
        min_steps: args.min_steps,
        latency_budget: positive_seconds("--latency-budget", args.latency_budget)?,
        dance: args.sampler.dance_options(),
        duration_s: args.duration,
        max_wall,
        output: take.clone(),
        osc: args.osc,
        nice: args.nice,
    };
    crate::live::check_options(package.manifest(), &options)?;
    let viewer = match args.viewer {
        Some(bind) => {
            let v = LiveViewer::start(bind, package.manifest(), args.nice)
                .with_context(|| format!("--viewer {bind}"))?;
            eprintln!("viewer: http://{}/", v.addr());
            Some(v)
        }
        None => None,
    };
    let stop = Arc::new(AtomicBool::new(false));
    for signal in [signal_hook::consts::SIGTERM, signal_hook::consts::SIGINT] {
        signal_hook::flag::register(signal, Arc::clone(&stop))?;
    }
    let stats = run_session(
        &mut package,
        &options,
        viewer.as_ref(),
        &LiveMetrics::default(),
        stop,
    )?;
    if args.stats {
        println!("{}", serde_json::to_string(&stats)?);
    }
    if let Some(out) = &args.output {
        if !stats.output_written {
            anyhow::bail!(
                "no motion was made ({:.1} s of audio heard, {:.0} s waited for audio): {} was not written",
                stats.audio_s,
                stats.waiting_s,
                out.display()
            );
        }
        if let Some(take) = take.as_ref().filter(|take| *take != out) {
            finish_take(take, out, &export)?;
        }
        eprintln!(
            "wrote {} ({} frames, {:.1} s of audio, {} overruns, {} reconnects)",
            out.display(),
            stats.frames,
            stats.audio_s,
            stats.overruns,
            stats.reconnects
        );
    }
    Ok(())
}

/// Where the take is recorded: `out` itself for HDF5, else a hidden `.NAME.take.h5` beside it
/// that [`finish_take`] turns into `out`'s format.
fn take_path(out: &Path, export: &choreo_datasets::ExportOptions) -> anyhow::Result<PathBuf> {
    if choreo_datasets::check_output(out, export)? == choreo_datasets::OutputFormat::MotionFile {
        return Ok(out.to_path_buf());
    }
    let name = out
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    Ok(out.with_file_name(format!(".{name}.take.h5")))
}

/// Write the recorded take in `out`'s format; the HDF5 take is removed once `out` is in place,
/// and kept (and named) if that fails.
fn finish_take(
    take: &Path,
    out: &Path,
    export: &choreo_datasets::ExportOptions,
) -> anyhow::Result<()> {
    let keep = || format!("the take is kept as {}", take.display());
    let motion = choreo_datasets::read_motion_file(take).with_context(keep)?;
    choreo_datasets::write_motion_as(out, &motion, export).with_context(keep)?;
    std::fs::remove_file(take).with_context(|| format!("removing {}", take.display()))
}

/// A positive number of seconds given as `flag`, as a duration.
fn positive_seconds(flag: &str, seconds: f64) -> anyhow::Result<Duration> {
    Duration::try_from_secs_f64(seconds)
        .ok()
        .filter(|d| !d.is_zero())
        .ok_or_else(|| anyhow::anyhow!("{flag} must be > 0 seconds, got {seconds}"))
}
