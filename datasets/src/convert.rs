//! `choreod convert`: one function that turns any supported motion file into another: the input
//! read as [`crate::formats`] probes it, the output picked by its extension (and
//! `ConvertTarget` where the output could be either).

use std::path::Path;

use ndarray::Array3;

use crate::checksum::sha256_file;
use crate::error::Result;
use crate::export::{ExportOptions, ExportRig, OutputFormat, check_output, write_motion_as};
use crate::formats::aistpp::AistppMotion;
use crate::formats::bvh::read_bvh;
use crate::formats::motion_file::{MotionFile, Provenance, check_values, write_motion_file};
use crate::formats::npy::write_npy;
use crate::formats::{LoadedMotion, MotionFormat, extension, load_motion, probe};
use crate::kinematics::rig::{
    LODGE_ON_SMPL24, lodge_smpl24_joints, retarget_smpl24, smpl24_joints, t2m_joints,
};
use crate::skeleton::SkeletonKind;
use crate::utc::now_utc;

/// What `convert` should produce when the input allows several.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ConvertTarget {
    /// World joint positions.
    Joints,
    /// HumanML3D 263-dim features.
    Features,
    /// SMPL-24 joint positions: a BVH (or motion file) of any rig the rig table knows placed on
    /// SMPL-24 by its joint names ([`crate::retarget_smpl24`]; a BVH's End Sites count).
    Smpl24,
}

/// How to convert.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ConvertOptions {
    /// What to produce when the output could hold either.
    pub target: Option<ConvertTarget>,
    /// Frame rate of a `.npy` input (which records none); `None` assumes [`npy_default_fps`].
    pub npy_fps: Option<f32>,
    /// The command line that asked for the conversion, recorded in an `.h5` output's
    /// `/provenance` (e.g. `"choreod convert --to features"`).
    pub command: String,
    /// Bone names and mesh of `.bvh` / `.glb` / `.gltf` outputs.
    pub export: ExportOptions,
}

/// What a conversion did, for the one-line report.
#[derive(Debug, Clone, PartialEq)]
pub struct ConvertSummary {
    /// e.g. `"AIST++ motion → joints"`.
    pub what: String,
    /// Output array shape.
    pub shape: Vec<usize>,
    /// Frames per second of the output.
    pub fps: f32,
    /// Whether the input's frame rate was assumed (a `.npy` read without a given rate).
    pub fps_assumed: bool,
}

fn features_of(input: &Path, m: &MotionFile) -> Result<crate::humanml3d::FeatureExtraction> {
    let j = to_t2m(input, m)?;
    let f =
        crate::humanml3d::extract_features(j.view(), &crate::humanml3d::FeatureOptions::default())
            .map_err(|e| e.with_path(input))?;
    // Finite joints can still overflow to infinite velocities (coordinates near f32::MAX).
    check_values(input, "HumanML3D features", f.features.iter())?;
    Ok(f)
}

/// Convert `input` to `output` (see `choreod convert --help` for the pairs). The input is
/// validated like every verb's ([`load_motion`]); an `.h5` output records the conversion in
/// `/provenance`.
pub fn convert(input: &Path, output: &Path, opts: &ConvertOptions) -> Result<ConvertSummary> {
    let started = now_utc();
    let format = check_output(output, &opts.export)?;
    let (loaded, what) = if opts.target == Some(ConvertTarget::Smpl24) {
        load_smpl24(input, opts.npy_fps)?
    } else {
        let loaded = load_motion(input, opts.npy_fps)?;
        let what = loaded.what().to_owned();
        (loaded, what)
    };
    let fps_assumed = loaded.fps_assumed;
    let m = loaded.motion;
    let want_features = opts.target == Some(ConvertTarget::Features)
        || (opts.target.is_none()
            && loaded.format == MotionFormat::Npy
            && !loaded.from_features
            && m.skeleton == SkeletonKind::T2m22
            && extension(output) == "npy");
    // A LODGE dance asked for as joints (a `.npy`, or `--to joints`) is SMPL-24, which every
    // joints reader and the metrics know; to BVH / glTF or copied as a motion file it keeps its
    // SMPL-X joints and rotations.
    let as_joints = match format {
        OutputFormat::Npy => !want_features,
        OutputFormat::MotionFile => matches!(
            opts.target,
            Some(ConvertTarget::Joints | ConvertTarget::Smpl24)
        ),
        OutputFormat::Bvh | OutputFormat::Gltf { .. } => false,
    };
    let (m, what) = match as_joints
        .then(|| lodge_smpl24_joints(input, &m))
        .transpose()?
        .flatten()
    {
        Some(j) => {
            let mut smpl = MotionFile::from_joints(m.fps, SkeletonKind::Smpl24, j);
            smpl.provenance = m.provenance;
            (smpl, format!("LODGE dance on SMPL-24 ({LODGE_ON_SMPL24})"))
        }
        None => (m, what),
    };
    let summary = |what: String, shape: &[usize], fps: f32| ConvertSummary {
        what,
        shape: shape.to_vec(),
        fps,
        fps_assumed,
    };
    match format {
        OutputFormat::Npy if want_features => {
            let f = features_of(input, &m)?;
            write_npy(output, f.features.view().into_dyn())?;
            Ok(summary(
                format!("{} → HumanML3D features", what),
                f.features.shape(),
                20.0,
            ))
        }
        OutputFormat::Npy => {
            write_npy(output, m.joints.view().into_dyn())?;
            Ok(summary(
                format!("{} → joints", what),
                m.joints.shape(),
                m.fps,
            ))
        }
        OutputFormat::MotionFile => {
            let mut out = m.clone();
            if want_features {
                let f = features_of(input, &m)?;
                out = MotionFile::from_joints(20.0, SkeletonKind::T2m22, f.recovered_joints()?);
                out.features = Some(crate::formats::motion_file::Features {
                    data: f.features,
                    representation: "humanml3d263".into(),
                    normalized: false,
                });
            }
            out.validate(output)?;
            let what = format!("{what} → motion file");
            out.provenance = Some(conversion_provenance(input, &what, opts, started)?);
            write_motion_file(output, &out)?;
            Ok(summary(what, out.joints.shape(), out.fps))
        }
        OutputFormat::Bvh
            if opts.export.rig == ExportRig::Native
                && loaded.format == MotionFormat::AistppPickle =>
        {
            // Keep AIST++'s own rotations (twist included) instead of re-deriving them.
            crate::formats::bvh::write_bvh_smpl(output, &AistppMotion::read(input)?)?;
            Ok(summary(
                "AIST++ motion → BVH (SMPL rotations)".into(),
                m.joints.shape(),
                m.fps,
            ))
        }
        OutputFormat::Bvh | OutputFormat::Gltf { .. } => {
            write_motion_as(output, &m, &opts.export)?;
            let kind = if format == OutputFormat::Bvh {
                "BVH"
            } else {
                "glTF"
            };
            Ok(summary(
                format!("{} → {kind}", what),
                m.joints.shape(),
                m.fps,
            ))
        }
    }
}

/// The input on SMPL-24 ([`ConvertTarget::Smpl24`]) and what it was, for the report. A BVH is
/// read here rather than by [`load_motion`], which drops End Sites: a rig may need them (the
/// Poser rig's toes, the Neo rig's hands).
fn load_smpl24(input: &Path, npy_fps: Option<f32>) -> Result<(LoadedMotion, String)> {
    let format = probe(input)?;
    let (loaded, placed) = if format == MotionFormat::Bvh {
        if npy_fps.is_some() {
            return Err(crate::Error::FpsNotApplicable {
                path: input.to_path_buf(),
                format,
            });
        }
        let bvh = read_bvh(input).map_err(|e| e.in_format(format))?;
        let motion = bvh.to_motion_file();
        // A SMPL-24 hierarchy comes back as SMPL-24; any other is placed with its End Sites.
        let placed = match motion.skeleton {
            SkeletonKind::Custom { .. } => {
                let (j, rig) =
                    retarget_smpl24(&bvh.names, &bvh.joints).map_err(|u| u.into_error(input))?;
                Some((j, Some(rig)))
            }
            _ => None,
        };
        let loaded = LoadedMotion {
            motion,
            format,
            from_features: false,
            fps_assumed: false,
        };
        (loaded, placed)
    } else {
        (load_motion(input, npy_fps)?, None)
    };
    let (joints, rig) = match placed {
        Some(p) => p,
        None => smpl24_joints(input, &loaded.motion)?,
    };
    let what = match rig {
        Some(rig) => format!("{} ({rig} rig) on SMPL-24", loaded.what()),
        None => format!("{} on SMPL-24", loaded.what()),
    };
    let mut motion = MotionFile::from_joints(loaded.motion.fps, SkeletonKind::Smpl24, joints);
    motion.provenance = loaded.motion.provenance.clone();
    motion.validate(input).map_err(|e| e.in_format(format))?;
    Ok((LoadedMotion { motion, ..loaded }, what))
}

/// `/provenance` of a converted file: the source's name and sha256, and the conversion as the
/// producer (`model_name` = `"choreod convert"`, `sampler` = what was converted and the
/// command; no model, so no model hash, steps, guidance or seed).
fn conversion_provenance(
    input: &Path,
    what: &str,
    opts: &ConvertOptions,
    started_utc: String,
) -> Result<Provenance> {
    let command = if opts.command.is_empty() {
        String::new()
    } else {
        format!(" ({})", opts.command)
    };
    Ok(Provenance {
        source_name: input
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default(),
        source_sha256: sha256_file(input)?,
        model_name: "choreod convert".into(),
        sampler: format!("{what}{command}"),
        started_utc,
        finished_utc: now_utc(),
        ..Provenance::default()
    })
}

/// The t2m-22 joints at 20 fps that HumanML3D features are computed from (a custom skeleton
/// placed by the one rig mapping, [`t2m_joints`]).
fn to_t2m(input: &Path, m: &MotionFile) -> Result<Array3<f32>> {
    let (j, _rig) = t2m_joints(input, m)?;
    if (m.fps - 20.0).abs() > 1e-3 {
        return crate::formats::aistpp::resample_joints(&j, m.fps, 20.0)
            .map_err(|e| e.with_path(input));
    }
    Ok(j)
}
