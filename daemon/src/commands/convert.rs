//! `choreod convert IN -o OUT [--to joints|features]`

use std::path::PathBuf;

use clap::{Args, ValueEnum};

use crate::cli::GlobalArgs;

/// Arguments of `convert`.
#[derive(Debug, Args)]
#[command(after_help = "\
Pairs (picked by file extension):
  AIST++ .pkl          -> joints (T,24,3) as .npy, .h5 or .bvh
  .npy (T,22,3) joints -> HumanML3D features (T-1,263) .npy (or --to joints for .h5/.bvh)
  .npy (T,263)         -> joints (T,22,3)
  .bvh                 -> joints .npy / .h5;  joints -> .bvh (rotations, imports into Blender)
  .h5 motion file      -> .npy joints or .bvh

Examples:
  choreod convert gBR_sBM_cAll_d04_mBR0_ch01.pkl -o dance.h5
  choreod convert joints22.npy -o features.npy
  choreod convert dance.h5 -o dance.bvh")]
pub struct ConvertArgs {
    /// Input motion: .pkl (AIST++), .npy, .bvh or .h5.
    pub input: PathBuf,
    /// Output file: .npy, .h5 or .bvh (written atomically).
    #[arg(short, long, value_name = "OUT")]
    pub output: PathBuf,
    /// What to produce when the output could hold either joints or HumanML3D features.
    #[arg(long, value_enum)]
    pub to: Option<ToArg>,
}

/// `--to` values.
#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum ToArg {
    /// World joint positions.
    Joints,
    /// HumanML3D 263-dim features.
    Features,
}

pub fn run(args: ConvertArgs, _global: &GlobalArgs) -> anyhow::Result<()> {
    let target = args.to.map(|t| match t {
        ToArg::Joints => choreo_datasets::ConvertTarget::Joints,
        ToArg::Features => choreo_datasets::ConvertTarget::Features,
    });
    // Library errors name the offending file (input or output) already.
    let summary = choreo_datasets::convert(&args.input, &args.output, target)?;
    tracing::info!(input = %args.input.display(), output = %args.output.display(), shape = ?summary.shape, "converted");
    println!(
        "{}: {} {:?} at {} fps",
        args.output.display(),
        summary.what,
        summary.shape,
        summary.fps
    );
    Ok(())
}
