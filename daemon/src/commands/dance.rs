//! `choreod dance AUDIO -o OUT.h5`

use std::io::IsTerminal;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::Context;
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};

use crate::cli::{self, GlobalArgs, ModelArgs, OutputArgs, SamplerArgs, at_least_one};
use crate::cli::{SamplerArg, SpacingArg, TimeLimitArg};
use crate::dance::{DanceExtras, dance_file};
use crate::settings::{self, PackageKind};

/// `-o` of `dance`: its .h5 holds the song's mel too.
const OUTPUT_HELP: &str = "The dance to write, in the format its extension names: .h5 (the \
motion file, format choreod-motion v2, with provenance and mel), .bvh, .glb / .gltf (skinned \
mannequin) or .npy (joints). Written under a temporary name and renamed into place only when \
complete";

/// Arguments of `dance`.
#[derive(Debug, Args)]
#[command(mut_arg("output", |a| a.help(OUTPUT_HELP)))]
#[command(after_help = "\
Examples:
  choreod dance song.ogg -o song.h5                     bundled default model (library)
  choreod dance song.flac -o song.h5 --seed 7 --steps 50 --stats
  choreod dance song.mp3 -o song.h5 --model models/packages/mofusion-ref
  choreod dance song.ogg -o song.h5 --sampler dpmsolver++ --steps 15
  choreod dance song.ogg -o song.h5 --init-noise xT.npy --save-windows windows.npy
  choreod dance song.ogg -o song.glb                    skinned mannequin (glTF 2.0)
  choreod dance song.ogg -o song.bvh --rig mixamo       Mixamo bone names
  choreod dance song.wav -o song.h5 --model lodge-pkg --genre Popping   LODGE
  choreod dance --features song.npy -o song.h5 --model lodge-pkg --init-noise noise.npz \\
      --eta 0 --lodge-compat official                   the official code's run
Then look at it: choreod view song.h5 (in a browser, with the song), or
choreod render song.h5 -o song.gif")]
pub struct DanceArgs {
    /// The song: WAV, FLAC, MP3, Ogg Vorbis, AAC/ALAC in M4A, AIFF.
    #[arg(required_unless_present = "features", conflicts_with = "features")]
    pub audio: Option<PathBuf>,
    /// LODGE packages: the song's fact35 features, float .npy (T, 35) at the package's rate
    /// (`choreod features`), danced instead of a song.
    #[arg(long, value_name = "FILE.npy")]
    pub features: Option<PathBuf>,
    /// LODGE packages: the genre by name (any case), alias or id. Default: by the song's tempo
    /// (beats of the features): under 100 BPM Chinese, under 125 Jazz, else Popping.
    #[arg(long, value_name = "NAME|ID")]
    pub genre: Option<String>,
    /// LODGE packages: `fixed` (default) mends the official code's window bugs (the tail,
    /// the last windows' music, root restarts, short songs; README "LODGE"); `official`
    /// reproduces its output, quirks included.
    #[arg(long, value_enum, default_value_t = LodgeCompatArg::Fixed)]
    pub lodge_compat: LodgeCompatArg,
    /// Classifier-free guidance scale on the music (0..=100); 1 turns it off. Default: the
    /// package's.
    #[arg(long, value_parser = cli::guidance)]
    pub guidance: Option<f32>,
    /// x_T of every window: float32 .npy in the model's normalised space, shaped
    /// (windows, T, D), or (T, D) for the same x_T in every window. With a deterministic
    /// sampler (ddim with eta 0, dpmsolver++) the dance is then a function of song, model and
    /// this file; its sha256 goes into the provenance. LODGE packages: an .npz with
    /// global_xT (G, 104, 139), local_xT (L, 256, 139) and local_style (steps, 2, L, 256)
    /// (per step the unconditional then the conditional call's style noise).
    #[arg(long, value_name = "FILE.npy|npz")]
    pub init_noise: Option<PathBuf>,
    /// Also write the sampler's final windows, before decoding and stitching, normalised:
    /// float32 .npy (windows, T, D). LODGE packages: .npz with global_windows,
    /// local_windows and each Local window's in-painting, local_constraint_value and
    /// local_constraint_mask (L, 256, 139).
    #[arg(long, value_name = "FILE.npy|npz")]
    pub save_windows: Option<PathBuf>,
    /// DDIM eta, 0..=1 (0 = deterministic DDIM, 1 = DDPM-like noise); refused with another
    /// sampler. Default: the package's.
    #[arg(long, value_parser = cli::eta)]
    pub eta: Option<f64>,
    /// Timestep spacing (diffusers' `timestep_spacing`): leading, trailing or linspace.
    /// Default: the package's, else leading for ddim/ddpm and linspace for dpmsolver++.
    /// 1000 DDIM steps need trailing or linspace (leading with steps_offset 1 passes t = 999).
    #[arg(long, value_enum)]
    pub timestep_spacing: Option<SpacingArg>,
    /// With guidance: evaluate the conditional and unconditional rows in two network calls per
    /// step instead of one batched call (for benchmarks; on 2 cores neither is consistently
    /// faster: BENCHMARKS.md, "Music to dance").
    #[arg(long)]
    pub unbatched_guidance: bool,
    /// Run the whole denoiser graph at every step instead of computing what depends on the
    /// music alone once per batch (the default: see `choreod models check`). For benchmarks, or
    /// to rule the optimisation out.
    #[arg(long)]
    pub no_hoist: bool,
    /// Windows denoised together in one batch (bounds memory on long songs).
    #[arg(long, value_parser = at_least_one,
          default_value_t = choreo_models::DanceOptions::default().chunk_windows)]
    pub chunk_windows: usize,
    /// Refuse songs longer than this many seconds (0.1..=86400).
    #[arg(long, default_value_t = choreo_models::SongOptions::default().max_audio_seconds, value_parser = cli::max_seconds)]
    pub max_duration: f64,
    /// Refuse songs shorter than this many seconds (0..=86400). Default: one motion window of
    /// the model (5 s for the shipped packages); never below one analysis window (n_fft
    /// samples).
    #[arg(long, value_parser = cli::min_seconds)]
    pub min_duration: Option<f64>,
    #[command(flatten)]
    pub time_limit: TimeLimitArg,
    /// Print one JSON line on stdout with seconds per stage, network evaluations, ORT seconds
    /// and `components`: per network its runs and ORT seconds (hoisted prologue apart).
    #[arg(long)]
    pub stats: bool,
    // The shared groups last: each starts a help heading that would also take the flags after it.
    #[command(flatten)]
    pub out: OutputArgs,
    #[command(flatten)]
    pub model: ModelArgs,
    #[command(flatten)]
    pub sampler: SamplerArgs,
}

/// `--lodge-compat`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum LodgeCompatArg {
    /// The official output with its bugs mended.
    Fixed,
    /// The official output, quirks included.
    Official,
}

pub fn run(args: DanceArgs, global: &GlobalArgs) -> anyhow::Result<()> {
    let source = args
        .features
        .clone()
        .or_else(|| args.audio.clone())
        .context("give the song (or --features)")?;
    let output = &args.out.output;
    let mut inputs = vec![("the song", source.as_path())];
    inputs.extend(args.init_noise.as_deref().map(|p| ("--init-noise", p)));
    let export = args.out.check(&inputs)?;
    if let Some(path) = &args.save_windows {
        inputs.push(("-o", output));
        super::refuse_output_over_input(path, "--save-windows", &inputs)?;
        super::check_output_folder(path, "--save-windows")?;
    }
    let ort = settings::ort(global.ort_library.as_deref())?;
    let mut runtime = args.model.runtime();
    runtime.hoist_invariants = !args.no_hoist;
    let mut package = args.model.load(PackageKind::Dance, &runtime, &ort)?;
    let lodge = package.manifest().task == choreo_models::Task::Lodge;
    check_lodge_flags(&args, lodge, &package.manifest().name)?;
    if let Some(license) = &package.manifest().license {
        eprintln!("{}", license.line());
    }
    let sampler = args
        .sampler
        .sampler
        .map_or(package.manifest().sampler.kind, SamplerArg::kind);
    // eta only moves DDIM: with another sampler it is refused rather than silently ignored.
    anyhow::ensure!(
        args.eta.is_none() || sampler == choreo_models::SamplerKind::Ddim,
        "--eta applies to the ddim sampler only; this run samples with {}",
        sampler.as_str()
    );

    let mut song = choreo_models::SongOptions::default();
    song.dance = args.sampler.dance_options();
    let options = &mut song.dance;
    options.guidance = args.guidance;
    options.eta = args.eta;
    options.spacing = args.timestep_spacing.map(SpacingArg::spacing);
    options.chunk_windows = args.chunk_windows;
    options.batch_guidance = !args.unbatched_guidance;
    // The pipeline checks the noise's shape against the song and the package.
    if let Some(path) = &args.init_noise {
        let reading = || format!("reading the initial noise {}", path.display());
        if lodge {
            song.lodge.init_noise = Some(read_lodge_noise(path).with_context(reading)?);
        } else {
            options.init_noise = Some(choreo_datasets::read_npy(path).with_context(reading)?);
        }
        song.init_noise_sha256 = choreo_datasets::sha256_file(path).with_context(reading)?;
    }
    if let Some(path) = &args.features {
        let reading = || format!("reading the features {}", path.display());
        let f = choreo_datasets::read_npy(path).with_context(reading)?;
        let f = f
            .into_dimensionality::<ndarray::Ix2>()
            .map_err(|_| anyhow::anyhow!("{}: features must be (T, 35)", path.display()))?;
        song.features = Some(f);
    }
    song.lodge.genre = args.genre.clone();
    song.lodge.chunk_windows = args.chunk_windows;
    song.lodge.compat = match args.lodge_compat {
        LodgeCompatArg::Fixed => choreo_models::LodgeCompat::Fixed,
        LodgeCompatArg::Official => choreo_models::LodgeCompat::Official,
    };
    if lodge && song.lodge.compat == choreo_models::LodgeCompat::Fixed {
        eprintln!(
            "LODGE default mode: {} fixes of the official code (tail danced, each window's own \
             music, root continued, mirror normalised, short songs); --lodge-compat official \
             reproduces it",
            choreo_models::LODGE_FIXES.len()
        );
    }
    song.dance.keep_windows = args.save_windows.is_some();
    song.max_audio_seconds = args.max_duration;
    song.min_audio_seconds = args.min_duration;

    let bar = ProgressBar::new(0).with_style(
        ProgressStyle::with_template("{msg} [{bar:30}] {pos}/{len} steps, {elapsed} (eta {eta})")
            .context("progress bar template")?
            .progress_chars("=> "),
    );
    bar.set_message(format!("dancing to {}", source.display()));
    // The bar draws only on a terminal; a redirected stderr (a log, CI) gets plain lines.
    let mut plain = PlainProgress::new(
        !std::io::stderr().is_terminal(),
        format!("dancing to {}", source.display()),
    );
    let extras = DanceExtras {
        save_windows: args.save_windows.clone(),
        export,
    };
    package.set_deadline(Some(args.time_limit.deadline()));
    let report = dance_file(
        &mut package,
        &source,
        output,
        &song,
        &extras,
        &mut |done, total| {
            bar.set_length(total as u64);
            bar.set_position(done as u64);
            plain.update(done, total);
        },
    );
    bar.finish_and_clear();
    let report = report.map_err(|e| {
        tracing::debug!(stage = ?e.stage, "dance failed");
        e.error
    })?;
    tracing::info!(
        audio = %source.display(),
        output = %output.display(),
        frames = report.song.frames,
        seconds = report.total_s,
        "dance written"
    );
    if args.stats {
        let stats = crate::commands::StatsLine {
            report: &report,
            components: package.ort_profile(),
        };
        println!("{}", serde_json::to_string(&stats)?);
    }
    eprintln!(
        "wrote {} ({} frames, {:.1} s at {} fps, model {})",
        output.display(),
        report.song.frames,
        report.song.frames as f64 / report.song.fps,
        report.song.fps,
        package.manifest().name
    );
    if matches!(
        choreo_datasets::OutputFormat::from_path(output),
        Ok(choreo_datasets::OutputFormat::Gltf { .. })
    ) {
        eprintln!(
            "look at it: open {} in Blender (File > Import > glTF 2.0) or any glTF viewer",
            shell_word(output)
        );
    } else {
        eprintln!(
            "look at it: choreod view {}{}",
            shell_word(output),
            args.audio
                .as_ref()
                .map(|a| format!(" --audio {}", shell_word(a)))
                .unwrap_or_default()
        );
    }
    Ok(())
}

/// LODGE's flags only with a LODGE package, and the other packages' sampler flags not with one.
fn check_lodge_flags(args: &DanceArgs, lodge: bool, model: &str) -> anyhow::Result<()> {
    let lodge_only = [
        ("--features", args.features.is_some()),
        ("--genre", args.genre.is_some()),
        (
            "--lodge-compat official",
            args.lodge_compat == LodgeCompatArg::Official,
        ),
    ];
    let not_lodge = [
        ("--guidance", args.guidance.is_some()),
        (
            "--sampler other than ddim",
            args.sampler
                .sampler
                .is_some_and(|s| !matches!(s, SamplerArg::Ddim)),
        ),
        ("--timestep-spacing", args.timestep_spacing.is_some()),
        ("--unbatched-guidance", args.unbatched_guidance),
    ];
    if !lodge && let Some((flag, _)) = lodge_only.iter().find(|(_, set)| *set) {
        anyhow::bail!("{flag} applies to LODGE packages; {model} is not one");
    }
    if lodge && let Some((flag, _)) = not_lodge.iter().find(|(_, set)| *set) {
        anyhow::bail!(
            "{flag} does not apply to LODGE packages ({model} samples DDIM with its own guidance)"
        );
    }
    Ok(())
}

/// `--init-noise` of a LODGE package: an `.npz` with `global_xT`, `local_xT`, `local_style`.
fn read_lodge_noise(path: &std::path::Path) -> anyhow::Result<choreo_models::LodgeNoise> {
    let mut arrays = choreo_datasets::read_npz(path)?;
    let mut take = |name: &str, rank: usize| -> anyhow::Result<ndarray::ArrayD<f32>> {
        let a = arrays
            .remove(name)
            .with_context(|| format!("no array {name} (needs global_xT, local_xT, local_style)"))?;
        anyhow::ensure!(
            a.ndim() == rank,
            "{name} has {} axes, needs {rank}",
            a.ndim()
        );
        anyhow::ensure!(
            a.iter().all(|v| v.is_finite()),
            "{name} holds NaN or infinite values"
        );
        Ok(a)
    };
    let dims = |e: ndarray::ShapeError| anyhow::anyhow!("{e}");
    Ok(choreo_models::LodgeNoise {
        global_x: take("global_xT", 3)?.into_dimensionality().map_err(dims)?,
        local_x: take("local_xT", 3)?.into_dimensionality().map_err(dims)?,
        local_style: take("local_style", 4)?
            .into_dimensionality()
            .map_err(dims)?,
    })
}

/// Progress as a line every [`PlainProgress::EVERY`] (and when generation starts) where no bar
/// is drawn: a 10-minute song takes half a minute or more.
struct PlainProgress {
    enabled: bool,
    what: String,
    started: Instant,
    last: Option<Instant>,
}

impl PlainProgress {
    const EVERY: Duration = Duration::from_secs(10);

    fn new(enabled: bool, what: String) -> Self {
        Self {
            enabled,
            what,
            started: Instant::now(),
            last: None,
        }
    }

    fn update(&mut self, done: usize, total: usize) {
        if !self.enabled || self.last.is_some_and(|t| t.elapsed() < Self::EVERY) {
            return;
        }
        self.last = Some(Instant::now());
        eprintln!(
            "{}: {done}/{total} steps, {:.0} s",
            self.what,
            self.started.elapsed().as_secs_f64()
        );
    }
}

/// `path` as one word a POSIX shell reads back as that path (quoted when it has spaces,
/// quotes or other special characters), for hints the user pastes.
pub(crate) fn shell_word(path: &std::path::Path) -> String {
    let text = path.to_string_lossy();
    // try_quote refuses only a NUL byte, which no path holds.
    shlex::try_quote(&text).map_or_else(|_| text.to_string(), |q| q.into_owned())
}
