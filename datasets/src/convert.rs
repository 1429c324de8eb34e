//! `choreod convert`: one function that turns any supported motion file into another, picked
//! by file extensions (and `ConvertTarget` where the output could be either).

use std::path::Path;

use ndarray::{Array3, Ix2, Ix3};

use crate::aistpp::{AISTPP_FPS, AistppMotion};
use crate::error::{Error, Result};
use crate::motion_file::{MotionFile, read_motion_file, write_motion_file};
use crate::npy::{read_npy, write_npy};
use crate::skeleton::SkeletonKind;

/// What `convert` should produce when the input allows several.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ConvertTarget {
    /// World joint positions.
    Joints,
    /// HumanML3D 263-dim features.
    Features,
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
}

fn ext(p: &Path) -> String {
    p.extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default()
}

/// Frame rate assumed for `.npy` joints without metadata: HumanML3D's 20 fps for 22 joints,
/// else AIST++ / EDGE's 30 fps.
pub(crate) fn npy_fps(joints: usize) -> f32 {
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

/// Joints + skeleton + fps loaded from any joint-bearing input.
struct Loaded {
    motion: MotionFile,
    what: &'static str,
}

fn load(input: &Path) -> Result<Loaded> {
    match ext(input).as_str() {
        "pkl" | "pickle" => {
            let m = AistppMotion::read(input)?;
            Ok(Loaded {
                motion: MotionFile::from_joints(AISTPP_FPS, SkeletonKind::Smpl24, m.joints()),
                what: "AIST++ motion",
            })
        }
        "h5" | "hdf5" => Ok(Loaded {
            motion: read_motion_file(input)?,
            what: "motion file",
        }),
        "bvh" => {
            let b = crate::bvh::read_bvh(input)?;
            Ok(Loaded {
                motion: b.to_motion_file(),
                what: "BVH",
            })
        }
        "npy" => {
            let a = read_npy(input)?;
            match a.ndim() {
                3 if a.shape()[2] == 3 => {
                    let j = a
                        .into_dimensionality::<Ix3>()
                        .map_err(|e| Error::invalid(input, e.to_string()))?;
                    let skel = skeleton_for(input, j.shape()[1])?;
                    let fps = npy_fps(j.shape()[1]);
                    Ok(Loaded {
                        motion: MotionFile::from_joints(fps, skel, j),
                        what: "joints",
                    })
                }
                2 if a.shape()[1] == crate::humanml3d::FEATURE_DIM => {
                    let f = a
                        .into_dimensionality::<Ix2>()
                        .map_err(|e| Error::invalid(input, e.to_string()))?;
                    let j = crate::humanml3d::recover_from_ric(f.view())
                        .map_err(|e| e.with_path(input))?;
                    Ok(Loaded {
                        motion: MotionFile::from_joints(20.0, SkeletonKind::T2m22, j),
                        what: "HumanML3D features",
                    })
                }
                _ => Err(Error::invalid(
                    input,
                    format!(
                        "array of shape {:?}: expected joints (T, J, 3) or HumanML3D features (T, 263)",
                        a.shape()
                    ),
                )),
            }
        }
        other => Err(Error::invalid(
            input,
            format!("unsupported input type '.{other}' (pkl, npy, bvh, h5)"),
        )),
    }
}

/// Load any supported motion input (`.pkl`, `.h5`, `.bvh`, `.npy` joints or 263 features) as a
/// [`MotionFile`].
pub fn load_motion(input: &Path) -> Result<MotionFile> {
    Ok(load(input)?.motion)
}

/// Convert `input` to `output` (see `choreod convert --help` for the pairs).
pub fn convert(
    input: &Path,
    output: &Path,
    target: Option<ConvertTarget>,
) -> Result<ConvertSummary> {
    let loaded = load(input)?;
    let m = loaded.motion;
    let want_features = target == Some(ConvertTarget::Features)
        || (target.is_none()
            && loaded.what == "joints"
            && m.skeleton == SkeletonKind::T2m22
            && ext(output) == "npy");
    match ext(output).as_str() {
        "npy" if want_features => {
            let j = to_t2m(input, &m)?;
            let f = crate::humanml3d::extract_features(
                j.view(),
                &crate::humanml3d::FeatureOptions::default(),
            )
            .map_err(|e| e.with_path(input))?;
            write_npy(output, f.features.view().into_dyn())?;
            Ok(ConvertSummary {
                what: format!("{} → HumanML3D features", loaded.what),
                shape: f.features.shape().to_vec(),
                fps: 20.0,
            })
        }
        "npy" => {
            write_npy(output, m.joints.view().into_dyn())?;
            Ok(ConvertSummary {
                what: format!("{} → joints", loaded.what),
                shape: m.joints.shape().to_vec(),
                fps: m.fps,
            })
        }
        "h5" | "hdf5" => {
            let mut out = m.clone();
            if want_features {
                let j = to_t2m(input, &m)?;
                let f = crate::humanml3d::extract_features(
                    j.view(),
                    &crate::humanml3d::FeatureOptions::default(),
                )
                .map_err(|e| e.with_path(input))?;
                out = MotionFile::from_joints(20.0, SkeletonKind::T2m22, f.recovered_joints()?);
                out.features = Some(crate::motion_file::Features {
                    data: f.features,
                    representation: "humanml3d263".into(),
                    normalized: false,
                });
            }
            write_motion_file(output, &out)?;
            Ok(ConvertSummary {
                what: format!("{} → motion file", loaded.what),
                shape: out.joints.shape().to_vec(),
                fps: out.fps,
            })
        }
        "bvh" if matches!(ext(input).as_str(), "pkl" | "pickle") => {
            // Keep AIST++'s own rotations (twist included) instead of re-deriving them.
            crate::bvh::write_bvh_smpl(output, &AistppMotion::read(input)?)?;
            Ok(ConvertSummary {
                what: "AIST++ motion → BVH (SMPL rotations)".into(),
                shape: m.joints.shape().to_vec(),
                fps: m.fps,
            })
        }
        "bvh" => {
            crate::bvh::write_bvh_positions(output, &m)?;
            Ok(ConvertSummary {
                what: format!("{} → BVH", loaded.what),
                shape: m.joints.shape().to_vec(),
                fps: m.fps,
            })
        }
        other => Err(Error::invalid(
            output,
            format!("unsupported output type '.{other}' (npy, h5, bvh)"),
        )),
    }
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
