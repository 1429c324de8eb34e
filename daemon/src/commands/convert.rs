//! `choreod convert IN -o OUT [--to joints|features|smpl24] [--rig native|mixamo] [--no-mesh]`

use std::path::PathBuf;

use clap::{Args, ValueEnum};

use crate::cli::GlobalArgs;

/// Arguments of `convert`.
#[derive(Debug, Args)]
#[command(after_help = "\
Pairs (the input is read by its content, else its extension; the output by its extension):
  AIST++ .pkl          -> joints (T,24,3) as .npy, .h5 or .bvh
  .npy (T,22,3) joints -> HumanML3D features (T-1,263) .npy (or --to joints for .h5/.bvh)
  .npy (T,263)         -> joints (T,22,3)
  .bvh                 -> joints .npy / .h5;  joints -> .bvh (rotations, imports into Blender)
                          --to features: a BVH of any rig stylize reads (CMU, Mixamo, ...)
                          placed on t2m-22 by its joint names
                          --to smpl24: SMPL-24 joints (T,24,3) .npy / .h5, placed by the
                          same rig table; each hand at SMPL's rest length (8.8 cm) from the
                          wrist towards the rig's hand joint (End Sites count)
  .h5 motion file      -> .npy joints or .bvh
  any of the above     -> .glb / .gltf: glTF 2.0 with a skinned mannequin, the skeleton
                          (joint names, rest pose) and one animation at the motion's frame
                          times; --no-mesh for the skeleton alone
--rig mixamo names the bones of a .bvh / .glb / .gltf as Mixamo does (mixamorig:Hips, ...;
SMPL-24 and t2m-22 motion), so a Mixamo character retargets by matching names.

A .npy records no frame rate: pass --fps (else 20 fps is assumed for 22 joints and
263 features, 30 fps otherwise, and said). Inputs with no frames or with NaN/infinite
values are refused, as by every verb. An .h5 output records the source's name and
sha256 and the conversion in /provenance.

Examples:
  choreod convert gBR_sBM_cAll_d04_mBR0_ch01.pkl -o dance.h5
  choreod convert joints22.npy -o features.npy
  choreod convert 60_01.bvh --to smpl24 -o salsa.npy  any known rig -> SMPL-24 joints
  choreod convert aistpp_joints.npy --fps 60 -o dance.bvh
  choreod convert dance.h5 -o dance.bvh
  choreod convert dance.h5 -o dance.glb               open in Blender, three.js, Godot...
  choreod convert dance.h5 -o dance.glb --rig mixamo  Mixamo bone names and axes")]
pub struct ConvertArgs {
    /// Input motion: .pkl (AIST++), .npy, .bvh or .h5.
    pub input: PathBuf,
    /// Output file: .npy, .h5, .bvh, .glb or .gltf (written atomically).
    #[arg(short, long, value_name = "OUT")]
    pub output: PathBuf,
    #[command(flatten)]
    pub export: ExportArgs,
    /// What to produce when the output could hold either joints or HumanML3D features, or
    /// `smpl24` for the input placed on SMPL-24.
    #[arg(long, value_enum)]
    pub to: Option<ToArg>,
    /// Frame rate of a .npy input, 1..=1000 (a .npy records none).
    #[arg(long, value_name = "FPS", value_parser = crate::cli::fps)]
    pub fps: Option<f32>,
    #[command(flatten)]
    pub limits: LimitArgs,
}

/// Bone names and mesh of `.bvh` / `.glb` / `.gltf` outputs, shared by every verb that writes
/// motion.
#[derive(Debug, Args)]
pub struct ExportArgs {
    /// Bone names of a .bvh / .glb / .gltf output: native (the motion's joint names) or mixamo
    /// (Mixamo's, `mixamorig:` prefix, with Mixamo's bone axes in glTF; README: "glTF and
    /// Mixamo").
    #[arg(long, value_enum, default_value_t = RigArg::Native)]
    pub rig: RigArg,
    /// A .glb / .gltf output without the mannequin: a plain animated skeleton.
    #[arg(long)]
    pub no_mesh: bool,
}

impl ExportArgs {
    /// As the library takes them.
    pub fn options(&self) -> choreo_datasets::ExportOptions {
        choreo_datasets::ExportOptions {
            rig: match self.rig {
                RigArg::Native => choreo_datasets::ExportRig::Native,
                RigArg::Mixamo => choreo_datasets::ExportRig::Mixamo,
            },
            no_mesh: self.no_mesh,
        }
    }
}

/// `--rig` values.
#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum RigArg {
    /// The motion's own joint names.
    Native,
    /// Mixamo's bone names (SMPL-24 and t2m-22 motion).
    Mixamo,
}

/// The reader limit shared by every verb that reads motion files.
#[derive(Debug, Args)]
pub struct LimitArgs {
    /// Refuse input files that would need more than N values in memory (README: Reader limits).
    #[arg(long, value_name = "N", default_value_t = choreo_datasets::limits::DEFAULT_MAX_ELEMENTS)]
    pub max_elements: usize,
}

impl LimitArgs {
    /// Make every reader of this process obey the limit.
    pub fn apply(&self) {
        choreo_datasets::limits::set_max_elements(self.max_elements);
    }
}

/// Say when a `.npy`'s frame rate was assumed rather than given.
pub fn report_assumed_fps(input: &std::path::Path, fps_assumed: bool, fps: f32) {
    if fps_assumed {
        tracing::warn!(input = %input.display(), fps, "no --fps given for a .npy: frame rate assumed");
    }
}

/// `--to` values.
#[derive(Debug, Clone, Copy, ValueEnum)]
pub enum ToArg {
    /// World joint positions.
    Joints,
    /// HumanML3D 263-dim features.
    Features,
    /// SMPL-24 joint positions (T,24,3): a BVH of any known rig placed by its joint names,
    /// the hands along the rig's hand bones at SMPL's rest hand length.
    Smpl24,
}

pub fn run(args: ConvertArgs, _global: &GlobalArgs) -> anyhow::Result<()> {
    super::refuse_output_over_input(&args.output, "-o", &[("the input", &args.input)])?;
    args.limits.apply();
    let target = args.to.map(|t| match t {
        ToArg::Joints => choreo_datasets::ConvertTarget::Joints,
        ToArg::Features => choreo_datasets::ConvertTarget::Features,
        ToArg::Smpl24 => choreo_datasets::ConvertTarget::Smpl24,
    });
    let mut command = String::from("choreod convert");
    if let Some(t) = target {
        command.push_str(match t {
            choreo_datasets::ConvertTarget::Joints => " --to joints",
            choreo_datasets::ConvertTarget::Features => " --to features",
            choreo_datasets::ConvertTarget::Smpl24 => " --to smpl24",
        });
    }
    if let Some(fps) = args.fps {
        command.push_str(&format!(" --fps {fps}"));
    }
    let export = args.export.options();
    if export.rig == choreo_datasets::ExportRig::Mixamo {
        command.push_str(" --rig mixamo");
    }
    if export.no_mesh {
        command.push_str(" --no-mesh");
    }
    let opts = choreo_datasets::ConvertOptions {
        target,
        npy_fps: args.fps,
        command,
        export,
    };
    // Library errors name the offending file (input or output) already.
    let summary = choreo_datasets::convert(&args.input, &args.output, &opts)?;
    report_assumed_fps(&args.input, summary.fps_assumed, summary.fps);
    tracing::info!(input = %args.input.display(), output = %args.output.display(), shape = ?summary.shape, "converted");
    println!(
        "{}: {} {:?} at {} fps{}",
        args.output.display(),
        summary.what,
        summary.shape,
        summary.fps,
        if summary.fps_assumed {
            " (input frame rate assumed: pass --fps)"
        } else {
            ""
        }
    );
    Ok(())
}
