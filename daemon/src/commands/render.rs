//! `choreod render IN -o OUT.gif|OUT.png`

use std::path::PathBuf;

use anyhow::{Context, bail};
use clap::Args;

use crate::cli::GlobalArgs;
use crate::commands::convert::{LimitArgs, report_assumed_fps};

/// Arguments of `render`.
#[derive(Debug, Args)]
#[command(after_help = "\
Examples:
  choreod render dance.h5 -o dance.gif    animated skeleton, 3/4 view, ground grid
  choreod render dance.h5 -o dance.png    contact sheet of 12 frames
  choreod render joints.npy --fps 60 -o dance.gif   a .npy records no frame rate
Left limbs are blue, right limbs red; green discs mark feet in contact with the floor.")]
pub struct RenderArgs {
    /// Motion to draw: .h5 motion file (also .pkl, .bvh, .npy joints or 263 features).
    pub input: PathBuf,
    /// Output: .gif (animation) or .png (contact sheet).
    #[arg(short, long, value_name = "OUT")]
    pub output: PathBuf,
    /// Width of the GIF, or of one contact-sheet tile, in pixels.
    #[arg(long, default_value_t = choreo_datasets::RenderOptions::default().width)]
    pub width: u32,
    /// Height of the GIF, or of one contact-sheet tile, in pixels.
    #[arg(long, default_value_t = choreo_datasets::RenderOptions::default().height)]
    pub height: u32,
    /// Frame rate of a .npy input, 1..=1000 (a .npy records none; else 20 fps for 22 joints
    /// and 263 features, 30 fps otherwise is assumed, and said).
    #[arg(long, value_name = "FPS", value_parser = crate::cli::fps)]
    pub fps: Option<f32>,
    #[command(flatten)]
    pub limits: LimitArgs,
}

pub fn run(args: RenderArgs, _global: &GlobalArgs) -> anyhow::Result<()> {
    super::refuse_output_over_input(&args.output, "-o", &[("the input", &args.input)])?;
    // Reading errors name the input file already.
    args.limits.apply();
    let loaded = choreo_datasets::load_motion(&args.input, args.fps)?;
    let motion = loaded.motion;
    let mut opts = choreo_datasets::RenderOptions::default();
    opts.width = args.width;
    opts.height = args.height;
    let ext = args
        .output
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase());
    match ext.as_deref() {
        Some("gif") => choreo_datasets::render_gif(&motion, &args.output, &opts),
        Some("png") => choreo_datasets::render_contact_sheet(&motion, &args.output, &opts),
        _ => bail!("{}: output must end in .gif or .png", args.output.display()),
    }
    .with_context(|| format!("rendering {}", args.input.display()))?;
    report_assumed_fps(&args.input, loaded.fps_assumed, motion.fps);
    println!(
        "{}: {} frames at {} fps drawn{}",
        args.output.display(),
        motion.joints.shape()[0],
        motion.fps,
        if loaded.fps_assumed {
            " (input frame rate assumed: pass --fps)"
        } else {
            ""
        }
    );
    Ok(())
}
