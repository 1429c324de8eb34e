//! `choreod stylize --content C --style S -o OUT.h5`

use std::path::PathBuf;

use anyhow::{Context, bail};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};

use crate::cli::{self, GlobalArgs, ModelArgs, OutputArgs, at_least_one};
use crate::cli::{ModeArg, SamplerArg, TimeLimitArg};
use crate::commands::convert::LimitArgs;
use crate::settings::{self, PackageKind};
use crate::stylize::{StyleCache, StylizeJob, stylize_file};
use choreo_models::{MotionSource, StyleSource};

/// `-o` of `stylize`: its .h5 holds the features too.
const OUTPUT_HELP: &str = "Output, in the format its extension names: .h5 (motion file with \
joints, /motion/features and provenance), .bvh, .glb / .gltf (skinned mannequin) or .npy \
(joints). Written under a temporary name and renamed into place when complete";

/// `--model` of `stylize`: a style-transfer package.
const MODEL_HELP: &str =
    "Style-transfer package directory. Default: the bundled models/packages/style-gaussian";

/// Arguments of `stylize`.
#[derive(Debug, Args)]
#[command(mut_arg("output", |a| a.help(OUTPUT_HELP)), mut_arg("model", |a| a.help(MODEL_HELP)))]
#[command(after_help = "\
Inputs: any motion choreod reads - HumanML3D features .npy (T,263), t2m-22 / SMPL-24
joints .npy (T,22,3) / (T,24,3), BVH (CMU, Mixamo, SMPL joint names; mapped onto the
t2m-22 skeleton, else an error naming the joints it cannot place), AIST++ .pkl, and
choreod's .h5. They are resampled to the model's frame rate (20 fps). Content longer than
the model's max_frames is cut into overlapping segments and cross-faded back.

Modes:
  transfer   (MCM-LDM) denoise from noise, conditioned on the content's latent and root
             trajectory, with classifier-free guidance on the style (--guidance g):
             e_null + g (e_style - e_null).
  inversion  (MulSMo) invert the content's latent to noise with deterministic DDIM
             (--steps, default the package's inversion_steps), then denoise with content
             and style weights: e_u + wc (e_c - e_u) + ws (e_cs - e_c).

The default model, style-gaussian, needs no download: it gives the content the style's
upper-body posture and arm movement amplitude (per-channel statistics), and keeps the
content's root path, timing, legs, feet and bone lengths. It cannot transfer rhythm, gait
or anything temporal (README: Style transfer).

Examples:
  choreod stylize --content daemon/assets/motion/cmu_01_01_8s_30fps.bvh \\
      --style daemon/assets/motion/aistpp_gBR_sBM_cAll_d04_mBR0_ch01.pkl -o styled.h5
  choreod stylize --content walk.bvh --style dance.h5 -o styled.bvh \\
      --mode inversion --style-guidance 0.5
  choreod stylize --content c.npy --style s.npy -o out.h5 --model models/packages/mcm-ldm-ref \\
      --guidance 2.5 --steps 50 --init-noise xT.npy
  choreod stylize --content c.bvh --style-embedding clip_text.npy -o out.h5 --model MY_PACKAGE
Then look at it: choreod render styled.h5 -o styled.gif")]
pub struct StylizeArgs {
    /// The content motion: its timing, root path and (with style-gaussian) legs are kept.
    #[arg(long, value_name = "FILE")]
    pub content: PathBuf,
    /// The style motion (at least the model's min_frames, 2 s for the shipped models; only
    /// its first max_frames frames are used).
    #[arg(long, value_name = "FILE", required_unless_present = "style_embedding")]
    pub style: Option<PathBuf>,
    /// A precomputed style vector instead of a style motion: float32 .npy of shape (S) or
    /// (1, S), S = the model's style size (e.g. from your own text or image encoder).
    #[arg(long, value_name = "FILE.npy", conflicts_with = "style")]
    pub style_embedding: Option<PathBuf>,
    /// transfer (MCM-LDM) or inversion (MulSMo).
    #[arg(long, value_enum, default_value_t = ModeArg::Transfer)]
    pub mode: ModeArg,
    /// Style guidance of transfer mode (0..=100); 1 turns the unconditional pass off.
    /// Default: the package's.
    #[arg(long, value_parser = cli::guidance)]
    pub guidance: Option<f32>,
    /// Content weight wc of inversion mode (0..=100). Default: the package's.
    #[arg(long, value_name = "WC", value_parser = cli::guidance)]
    pub content_guidance: Option<f32>,
    /// Style weight ws of inversion mode (0..=100). Default: the package's.
    #[arg(long, value_name = "WS", value_parser = cli::guidance)]
    pub style_guidance: Option<f32>,
    /// Steps. Transfer: denoising steps (default: the package's sampler.steps); inversion:
    /// inversion steps, then as many denoising steps (default: sampler.inversion_steps).
    #[arg(long)]
    pub steps: Option<usize>,
    /// Sampler of transfer mode: ddim, ddpm or dpmsolver++ (inversion is always DDIM).
    #[arg(long, value_enum)]
    pub sampler: Option<SamplerArg>,
    /// Seed of x_T (transfer mode). Default: 0.
    #[arg(long)]
    pub seed: Option<u64>,
    /// x_T of transfer mode: float32 .npy of the latent's shape (e.g. (7, 256) for MCM-LDM),
    /// the same for every segment, or with one row per segment. Its sha256 goes into the
    /// provenance.
    #[arg(long, value_name = "FILE.npy")]
    pub init_noise: Option<PathBuf>,
    /// Frame rate of a .npy content, 1..=1000 (a .npy records none; default 20 fps for 22
    /// joints and for features, 30 fps for 24 joints). Features must already be at the
    /// model's rate.
    #[arg(long, value_name = "FPS", value_parser = cli::fps)]
    pub fps: Option<f32>,
    /// Frame rate of a .npy style motion (as --fps).
    #[arg(long, value_name = "FPS", value_parser = cli::fps)]
    pub style_fps: Option<f32>,
    /// Content segments denoised together in one batch (bounds memory on long content).
    #[arg(long, value_parser = at_least_one,
          default_value_t = choreo_models::StylizeOptions::default().chunk_segments)]
    pub chunk_segments: usize,
    /// Print one JSON line on stdout with seconds per stage, network evaluations and
    /// `components`: per network its runs and ONNX Runtime seconds.
    #[arg(long)]
    pub stats: bool,
    #[command(flatten)]
    pub limits: LimitArgs,
    #[command(flatten)]
    pub time_limit: TimeLimitArg,
    // The shared groups last: each starts a help heading that would also take the flags after it.
    #[command(flatten)]
    pub out: OutputArgs,
    #[command(flatten)]
    pub model: ModelArgs,
}

pub fn run(args: StylizeArgs, global: &GlobalArgs) -> anyhow::Result<()> {
    args.limits.apply();
    let mode = args.mode.mode();
    check_flags(&args, mode)?;
    let mut inputs = vec![("--content", args.content.as_path())];
    for (flag, path) in [
        ("--style", &args.style),
        ("--style-embedding", &args.style_embedding),
        ("--init-noise", &args.init_noise),
    ] {
        inputs.extend(path.as_deref().map(|p| (flag, p)));
    }
    let export = args.out.check(&inputs)?;
    let ort = settings::ort(global.ort_library.as_deref())?;
    let mut package = args
        .model
        .load(PackageKind::Style, &args.model.runtime(), &ort)?;

    let mut options = choreo_models::StylizeOptions::new(mode);
    options.guidance = args.guidance;
    options.content_guidance = args.content_guidance;
    options.style_guidance = args.style_guidance;
    options.steps = args.steps;
    options.sampler = args.sampler.map(SamplerArg::kind);
    if let Some(seed) = args.seed {
        options.seed = seed;
    }
    options.chunk_segments = args.chunk_segments;
    let init_noise_sha256 = match &args.init_noise {
        Some(path) => {
            let reading = || format!("reading the initial noise {}", path.display());
            options.init_noise = Some(choreo_datasets::read_npy(path).with_context(reading)?);
            choreo_datasets::sha256_file(path).with_context(reading)?
        }
        None => String::new(),
    };
    let style = match (&args.style, &args.style_embedding) {
        (_, Some(e)) => StyleSource::Embedding(e.clone()),
        (Some(s), None) => {
            let mut source = MotionSource::new(s);
            source.npy_fps = args.style_fps;
            StyleSource::Motion(source)
        }
        (None, None) => bail!("give --style FILE or --style-embedding FILE.npy"),
    };
    let mut content = MotionSource::new(&args.content);
    content.npy_fps = args.fps;
    let job = StylizeJob {
        content,
        style,
        output: args.out.output.clone(),
        export,
        init_noise_sha256,
    };

    let bar = ProgressBar::new(0).with_style(
        ProgressStyle::with_template("{msg} [{bar:30}] {pos}/{len} steps, {elapsed} (eta {eta})")
            .context("progress bar template")?
            .progress_chars("=> "),
    );
    bar.set_message(format!("stylizing {}", args.content.display()));
    package.set_deadline(Some(args.time_limit.deadline()));
    let styles = StyleCache::default();
    let report = stylize_file(&mut package, &job, &styles, &options, &mut |done, total| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    });
    bar.finish_and_clear();
    let report = report?;
    if args.stats {
        let stats = crate::commands::StatsLine {
            report: &report,
            components: package.ort_profile(),
        };
        println!("{}", serde_json::to_string(&stats)?);
    }
    eprintln!(
        "wrote {} ({} frames, {:.1} s at {} fps, {} mode, model {})",
        args.out.output.display(),
        report.stylized.stats.frames,
        report.stylized.stats.frames as f64 / report.stylized.fps,
        report.stylized.fps,
        mode.as_str(),
        package.manifest().name
    );
    Ok(())
}

/// Flags that belong to the other mode are refused rather than silently ignored.
fn check_flags(args: &StylizeArgs, mode: choreo_models::StyleMode) -> anyhow::Result<()> {
    use choreo_models::StyleMode::{Inversion, Transfer};
    match mode {
        Transfer if args.content_guidance.is_some() || args.style_guidance.is_some() => bail!(
            "--content-guidance and --style-guidance weight the inversion mode; transfer mode \
             takes --guidance (or add --mode inversion)"
        ),
        Inversion if args.guidance.is_some() => bail!(
            "--guidance is transfer mode's style guidance; inversion mode takes \
             --content-guidance WC and --style-guidance WS"
        ),
        Inversion if args.init_noise.is_some() || args.seed.is_some() => bail!(
            "--init-noise and --seed give x_T of transfer mode; inversion mode computes x_T from \
             the content"
        ),
        _ => Ok(()),
    }
}
