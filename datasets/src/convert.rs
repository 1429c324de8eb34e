//! `choreod convert`: one function that turns any supported motion file into another, picked
//! by file extensions (and `ConvertTarget` where the output could be either).

use std::path::Path;

use ndarray::{Array3, Ix2, Ix3};

use crate::aistpp::{AISTPP_FPS, AistppMotion};
use crate::checksum::sha256_file;
use crate::error::{Error, Result};
use crate::export::{ExportOptions, ExportRig, OutputFormat, check_output, write_motion_as};
use crate::motion_file::{
    MotionFile, Provenance, check_values, read_motion_file, write_motion_file,
};
use crate::npy::{read_npy, write_npy};
use crate::skeleton::SkeletonKind;
use crate::utc::now_utc;

/// What `convert` should produce when the input allows several.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ConvertTarget {
    /// World joint positions.
    Joints,
    /// HumanML3D 263-dim features.
    Features,
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
    /// Whether the input's frame rate was assumed (a `.npy` read without `--fps`).
    pub fps_assumed: bool,
}

/// Motion loaded from any supported input, validated ([`MotionFile::validate`]).
#[derive(Debug, Clone)]
pub struct LoadedMotion {
    /// The motion.
    pub motion: MotionFile,
    /// What the input was, e.g. `"AIST++ motion"`.
    pub what: &'static str,
    /// Whether `motion.fps` was assumed (a `.npy` read without a frame rate).
    pub fps_assumed: bool,
}

/// The extension that decides `p`'s format. A temporary file choreod writes under
/// (`.NAME.EXT.tmp-PID-N`, [`choreo_dsp::atomic::temp_path`]; what `kill -9` leaves of a live
/// take) reads as `NAME.EXT`, so it can be read in place before it is renamed.
fn ext(p: &Path) -> String {
    let name = p
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let name = name
        .strip_prefix('.')
        .and_then(|n| n.rsplit_once(".tmp-"))
        .map_or(name.as_str(), |(original, _)| original);
    Path::new(name)
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default()
}

/// Frame rate assumed for a `.npy` read without one: HumanML3D's 20 fps for 22 joints and 263
/// features, else AIST++ / EDGE's 30 fps.
pub fn npy_default_fps(joints: usize) -> f32 {
    if joints == 22 { 20.0 } else { 30.0 }
}

fn skeleton_for(path: &Path, j: usize) -> Result<SkeletonKind> {
    match j {
        24 => Ok(SkeletonKind::Smpl24),
        22 => Ok(SkeletonKind::T2m22),
        _ => Err(Error::invalid(
            path,
            format!(
                "{j} joints per frame: only SMPL-24 and t2m-22 joint arrays can be converted from .npy"
            ),
        )),
    }
}

fn load_any(input: &Path, npy_fps: Option<f32>) -> Result<LoadedMotion> {
    let kind = ext(input);
    if let Some(fps) = npy_fps {
        if kind != "npy" {
            return Err(Error::invalid(
                input,
                "--fps applies to .npy input only (this file records its frame rate)",
            ));
        }
        crate::limits::check_fps(fps)
            .map_err(|why| Error::invalid(input, format!("--fps: {why}")))?;
    }
    let loaded = |motion, what| LoadedMotion {
        motion,
        what,
        fps_assumed: false,
    };
    match kind.as_str() {
        "pkl" | "pickle" => {
            let m = AistppMotion::read(input)?;
            Ok(loaded(
                MotionFile::from_joints(AISTPP_FPS, SkeletonKind::Smpl24, m.joints()),
                "AIST++ motion",
            ))
        }
        "h5" | "hdf5" => Ok(loaded(read_motion_file(input)?, "motion file")),
        "bvh" => Ok(loaded(crate::bvh::read_bvh(input)?.to_motion_file(), "BVH")),
        "npy" => {
            let a = read_npy(input)?;
            let (motion, what) = match a.ndim() {
                3 if a.shape()[2] == 3 => {
                    let j = a
                        .into_dimensionality::<Ix3>()
                        .map_err(|e| Error::invalid(input, e.to_string()))?;
                    let skel = skeleton_for(input, j.shape()[1])?;
                    let fps = npy_fps.unwrap_or(npy_default_fps(j.shape()[1]));
                    (MotionFile::from_joints(fps, skel, j), "joints")
                }
                2 if a.shape()[1] == crate::humanml3d::FEATURE_DIM => {
                    let f = a
                        .into_dimensionality::<Ix2>()
                        .map_err(|e| Error::invalid(input, e.to_string()))?;
                    check_values(input, "features", f.iter())?;
                    let j = crate::humanml3d::recover_from_ric(f.view())
                        .map_err(|e| e.with_path(input))?;
                    let fps = npy_fps.unwrap_or(npy_default_fps(22));
                    (
                        MotionFile::from_joints(fps, SkeletonKind::T2m22, j),
                        "HumanML3D features",
                    )
                }
                _ => {
                    return Err(Error::invalid(
                        input,
                        format!(
                            "array of shape {:?}: expected joints (T, J, 3) or HumanML3D features (T, 263)",
                            a.shape()
                        ),
                    ));
                }
            };
            Ok(LoadedMotion {
                motion,
                what,
                fps_assumed: npy_fps.is_none(),
            })
        }
        other => Err(Error::invalid(
            input,
            format!("unsupported input type '.{other}' (pkl, npy, bvh, h5)"),
        )),
    }
}

/// Load any supported motion input (`.pkl`, `.h5`, `.bvh`, `.npy` joints or 263 features) and
/// validate it ([`MotionFile::validate`]: frames, finite values, shapes), so every verb refuses
/// the same inputs. `npy_fps` is the frame rate of a `.npy` input (refused for other inputs,
/// which record theirs); without it [`npy_default_fps`] is assumed and reported.
pub fn load_motion(input: &Path, npy_fps: Option<f32>) -> Result<LoadedMotion> {
    let loaded = load_any(input, npy_fps)?;
    loaded.motion.validate(input)?;
    Ok(loaded)
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
    let loaded = load_motion(input, opts.npy_fps)?;
    let fps_assumed = loaded.fps_assumed;
    let m = loaded.motion;
    let want_features = opts.target == Some(ConvertTarget::Features)
        || (opts.target.is_none()
            && loaded.what == "joints"
            && m.skeleton == SkeletonKind::T2m22
            && ext(output) == "npy");
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
                format!("{} → HumanML3D features", loaded.what),
                f.features.shape(),
                20.0,
            ))
        }
        OutputFormat::Npy => {
            write_npy(output, m.joints.view().into_dyn())?;
            Ok(summary(
                format!("{} → joints", loaded.what),
                m.joints.shape(),
                m.fps,
            ))
        }
        OutputFormat::MotionFile => {
            let mut out = m.clone();
            if want_features {
                let f = features_of(input, &m)?;
                out = MotionFile::from_joints(20.0, SkeletonKind::T2m22, f.recovered_joints()?);
                out.features = Some(crate::motion_file::Features {
                    data: f.features,
                    representation: "humanml3d263".into(),
                    normalized: false,
                });
            }
            out.validate(output)?;
            let what = format!("{} → motion file", loaded.what);
            out.provenance = Some(conversion_provenance(input, &what, opts, started)?);
            write_motion_file(output, &out)?;
            Ok(summary(what, out.joints.shape(), out.fps))
        }
        OutputFormat::Bvh
            if opts.export.rig == ExportRig::Native
                && matches!(ext(input).as_str(), "pkl" | "pickle") =>
        {
            // Keep AIST++'s own rotations (twist included) instead of re-deriving them.
            crate::bvh::write_bvh_smpl(output, &AistppMotion::read(input)?)?;
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
                format!("{} → {kind}", loaded.what),
                m.joints.shape(),
                m.fps,
            ))
        }
    }
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

/// The t2m-22 joints at 20 fps that HumanML3D features are computed from.
fn to_t2m(input: &Path, m: &MotionFile) -> Result<Array3<f32>> {
    let j = match m.skeleton {
        SkeletonKind::Smpl24 => m.joints.slice(ndarray::s![.., ..22, ..]).to_owned(),
        SkeletonKind::T2m22 => m.joints.clone(),
        SkeletonKind::Custom { .. } => {
            return Err(Error::invalid(
                input,
                "HumanML3D features need SMPL-24 or t2m-22 joints",
            ));
        }
    };
    if (m.fps - 20.0).abs() > 1e-3 {
        return crate::aistpp::resample_joints(&j, m.fps, 20.0).map_err(|e| e.with_path(input));
    }
    Ok(j)
}
