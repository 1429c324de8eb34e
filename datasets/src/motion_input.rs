//! Motion inputs of `choreod stylize`: any motion file choreod reads, as HumanML3D 263-dim
//! features on the t2m-22 skeleton at a model's frame rate.
//!
//! Every format goes through world joints on the t2m-22 skeleton, then [`extract_features`] with
//! its default options, except HumanML3D features themselves (`.npy (T, 263)`, or the raw
//! `/motion/features` of our `.h5` at the target rate), which are taken as they are:
//! - `.npy (T, 22, 3)` / `(T, 24, 3)`: t2m-22 or SMPL-24 joints (SMPL's first 22 joints are
//!   t2m's); a `.npy` has no frame rate, so [`MotionInputOptions::npy_fps`] gives it (default as
//!   `choreod convert`);
//! - `.pkl`: AIST++ (SMPL-24 at 60 fps);
//! - `.bvh`: any hierarchy whose joint names one of the [`RIGS`] maps onto t2m-22 (CMU,
//!   Mixamo, SMPL-style names), else one error naming the t2m joints left unmapped;
//! - `.h5`: our motion file, with any of the skeletons above.
//!
//! Joints are resampled to the target rate with [`resample_joints`]; frame counts are bounded
//! before features are computed, and non-finite values are refused.

use std::path::Path;

use ndarray::{Array2, Array3, Ix2, Ix3};

use crate::aistpp::resample_joints;
use crate::convert::{load_motion, npy_default_fps};
use crate::error::{Error, Result};
use crate::humanml3d::{FEATURE_DIM, FeatureOptions, JOINTS, extract_features};
use crate::motion_file::{MotionFile, check_values};
use crate::npy::read_npy;
use crate::skeleton::{SkeletonKind, T2M22_JOINT_NAMES};

/// Where one t2m-22 joint comes from in a named rig.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RigJoint {
    /// The joint of this name.
    Named(&'static str),
    /// The midpoint of two named joints, for a rig with fewer spine or collar joints than t2m:
    /// a midpoint keeps every t2m bone's direction that of the source (a t2m joint placed on
    /// an existing one would leave a zero-length bone whose direction is undefined).
    Between(&'static str, &'static str),
}

/// A joint-name convention and where each t2m-22 joint (in [`T2M22_JOINT_NAMES`] order) is in
/// it. Names are compared after [`normalise_name`]: case, `_`, `-`, spaces and a namespace
/// prefix (`mixamorig:`) do not matter.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Rig {
    /// Shown in messages, e.g. `"CMU"`.
    pub name: &'static str,
    /// One source per t2m-22 joint.
    pub joints: [RigJoint; JOINTS],
}

use RigJoint::{Between, Named};

/// The rigs tried, in order; the first whose names are all present is used.
pub const RIGS: [Rig; 7] = [
    // Mixamo (Adobe's auto-rigger; `mixamorig:` prefix): one joint per t2m joint.
    Rig {
        name: "Mixamo",
        joints: [
            Named("Hips"),
            Named("LeftUpLeg"),
            Named("RightUpLeg"),
            Named("Spine"),
            Named("LeftLeg"),
            Named("RightLeg"),
            Named("Spine1"),
            Named("LeftFoot"),
            Named("RightFoot"),
            Named("Spine2"),
            Named("LeftToeBase"),
            Named("RightToeBase"),
            Named("Neck"),
            Named("LeftShoulder"),
            Named("RightShoulder"),
            Named("Head"),
            Named("LeftArm"),
            Named("RightArm"),
            Named("LeftForeArm"),
            Named("RightForeArm"),
            Named("LeftHand"),
            Named("RightHand"),
        ],
    },
    // CMU mocap as converted to BVH (cgspeed; ../shared/fixtures/motion/cmu_01_01.bvh):
    // LowerBack, Neck and the shoulders sit at zero offset on their parents, the hip sockets
    // are the UpLeg joints, so t2m's spine2 and collars are midpoints.
    Rig {
        name: "CMU",
        joints: [
            Named("Hips"),
            Named("LeftUpLeg"),
            Named("RightUpLeg"),
            Named("Spine"),
            Named("LeftLeg"),
            Named("RightLeg"),
            Between("Spine", "Spine1"),
            Named("LeftFoot"),
            Named("RightFoot"),
            Named("Spine1"),
            Named("LeftToeBase"),
            Named("RightToeBase"),
            Named("Neck1"),
            Between("LeftShoulder", "LeftArm"),
            Between("RightShoulder", "RightArm"),
            Named("Head"),
            Named("LeftArm"),
            Named("RightArm"),
            Named("LeftForeArm"),
            Named("RightForeArm"),
            Named("LeftHand"),
            Named("RightHand"),
        ],
    },
    // SMPL / SMPL-X exports (`L_Hip`, `Spine1`, `L_Collar`, ...), and t2m's own names.
    Rig {
        name: "SMPL",
        joints: [
            Named("Pelvis"),
            Named("L_Hip"),
            Named("R_Hip"),
            Named("Spine1"),
            Named("L_Knee"),
            Named("R_Knee"),
            Named("Spine2"),
            Named("L_Ankle"),
            Named("R_Ankle"),
            Named("Spine3"),
            Named("L_Foot"),
            Named("R_Foot"),
            Named("Neck"),
            Named("L_Collar"),
            Named("R_Collar"),
            Named("Head"),
            Named("L_Shoulder"),
            Named("R_Shoulder"),
            Named("L_Elbow"),
            Named("R_Elbow"),
            Named("L_Wrist"),
            Named("R_Wrist"),
        ],
    },
    // SMPL as EDGE names it (Stanford-TML/EDGE vis.py `smpl_joints`; our SMPL-24 BVH export).
    Rig {
        name: "SMPL (EDGE names)",
        joints: [
            Named("root"),
            Named("lhip"),
            Named("rhip"),
            Named("belly"),
            Named("lknee"),
            Named("rknee"),
            Named("spine"),
            Named("lankle"),
            Named("rankle"),
            Named("chest"),
            Named("ltoes"),
            Named("rtoes"),
            Named("neck"),
            Named("linshoulder"),
            Named("rinshoulder"),
            Named("head"),
            Named("lshoulder"),
            Named("rshoulder"),
            Named("lelbow"),
            Named("relbow"),
            Named("lwrist"),
            Named("rwrist"),
        ],
    },
    // CMU salsa as converted with Poser/DAZ names (hip, abdomen, lShldr; the dance library's
    // 60_xx / 61_xx): no toe joint, so t2m's feet are the foot's End Site (kept by
    // `BvhMotion`, not by its motion file); spine2 is the midpoint of abdomen and chest.
    Rig {
        name: "Poser",
        joints: [
            Named("hip"),
            Named("lThigh"),
            Named("rThigh"),
            Named("abdomen"),
            Named("lShin"),
            Named("rShin"),
            Between("abdomen", "chest"),
            Named("lFoot"),
            Named("rFoot"),
            Named("chest"),
            Named("lFoot_end"),
            Named("rFoot_end"),
            Named("neck"),
            Named("lCollar"),
            Named("rCollar"),
            Named("head"),
            Named("lShldr"),
            Named("rShldr"),
            Named("lForeArm"),
            Named("rForeArm"),
            Named("lHand"),
            Named("rHand"),
        ],
    },
    // Reallusion Character Creator (`CC_Base_`; CMU 05_xx retargeted in iClone).
    Rig {
        name: "Reallusion CC_Base",
        joints: [
            Named("CC_Base_Hip"),
            Named("CC_Base_L_Thigh"),
            Named("CC_Base_R_Thigh"),
            Named("CC_Base_Waist"),
            Named("CC_Base_L_Calf"),
            Named("CC_Base_R_Calf"),
            Named("CC_Base_Spine01"),
            Named("CC_Base_L_Foot"),
            Named("CC_Base_R_Foot"),
            Named("CC_Base_Spine02"),
            Named("CC_Base_L_ToeBase"),
            Named("CC_Base_R_ToeBase"),
            Named("CC_Base_NeckTwist01"),
            Named("CC_Base_L_Clavicle"),
            Named("CC_Base_R_Clavicle"),
            Named("CC_Base_Head"),
            Named("CC_Base_L_Upperarm"),
            Named("CC_Base_R_Upperarm"),
            Named("CC_Base_L_Forearm"),
            Named("CC_Base_R_Forearm"),
            Named("CC_Base_L_Hand"),
            Named("CC_Base_R_Hand"),
        ],
    },
    // keijiro's "Neo" humanoid (CMUMocap; CMU 85_xx): Mixamo's names behind a `Neo_` prefix.
    Rig {
        name: "Neo",
        joints: [
            Named("Neo_Hips"),
            Named("Neo_LeftUpLeg"),
            Named("Neo_RightUpLeg"),
            Named("Neo_Spine"),
            Named("Neo_LeftLeg"),
            Named("Neo_RightLeg"),
            Named("Neo_Spine1"),
            Named("Neo_LeftFoot"),
            Named("Neo_RightFoot"),
            Named("Neo_Spine2"),
            Named("Neo_LeftToeBase"),
            Named("Neo_RightToeBase"),
            Named("Neo_Neck"),
            Named("Neo_LeftShoulder"),
            Named("Neo_RightShoulder"),
            Named("Neo_Head"),
            Named("Neo_LeftArm"),
            Named("Neo_RightArm"),
            Named("Neo_LeftForeArm"),
            Named("Neo_RightForeArm"),
            Named("Neo_LeftHand"),
            Named("Neo_RightHand"),
        ],
    },
];

/// A joint name as rigs compare it: the part after the last `:` (FBX/Mixamo namespaces),
/// lower case, without `_`, `-`, `.` and spaces; `left`/`right` prefixes become `l`/`r`, so
/// `L_Hip`, `left_hip` and `LeftHip` compare equal.
pub fn normalise_name(name: &str) -> String {
    let base = name.rsplit(':').next().unwrap_or(name);
    let flat: String = base
        .chars()
        .filter(|c| !matches!(c, '_' | '-' | '.' | ' '))
        .flat_map(char::to_lowercase)
        .collect();
    for (long, short) in [("left", "l"), ("right", "r")] {
        if let Some(rest) = flat.strip_prefix(long) {
            return format!("{short}{rest}");
        }
    }
    flat
}

/// Knobs of [`load_motion_input`].
#[derive(Debug, Clone)]
pub struct MotionInputOptions {
    /// Frame rate of the features (the model's `motion.fps`).
    pub fps: f32,
    /// Frame rate of `.npy` joints, which carry none; `None`: as `choreod convert` assumes
    /// (20 fps for 22 joints, HumanML3D's `new_joints`; 30 fps for 24).
    pub npy_fps: Option<f32>,
    /// Fewest feature frames accepted (e.g. the style encoder's `min_frames`).
    pub min_frames: usize,
    /// Most feature frames accepted, checked before features are computed.
    pub max_frames: usize,
}

/// Longest input accepted by default: one hour at HumanML3D's 20 fps.
pub const MAX_INPUT_FRAMES: usize = 72_000;

impl MotionInputOptions {
    /// Options for a model running at `fps`, with no lower bound and [`MAX_INPUT_FRAMES`].
    pub fn new(fps: f32) -> Self {
        MotionInputOptions {
            fps,
            npy_fps: None,
            min_frames: 1,
            max_frames: MAX_INPUT_FRAMES,
        }
    }
}

/// How an input was read, for logs and provenance.
#[derive(Debug, Clone, PartialEq)]
pub struct InputOrigin {
    /// e.g. `"BVH"`, `"AIST++ motion"`, `"HumanML3D features"`.
    pub format: &'static str,
    /// The rig that mapped a custom skeleton onto t2m-22, if one was needed.
    pub rig: Option<&'static str>,
    /// Frame rate of the file.
    pub fps: f32,
}

/// A motion input ready for a style-transfer model.
#[derive(Debug, Clone)]
pub struct MotionInput {
    /// (T, 263) raw (not normalised) HumanML3D features at the requested fps.
    pub features: Array2<f32>,
    /// What the file was.
    pub origin: InputOrigin,
}

/// Read `path` (any format in the module docs) as HumanML3D features at `opts.fps`.
pub fn load_motion_input(path: &Path, opts: &MotionInputOptions) -> Result<MotionInput> {
    if !(opts.fps.is_finite() && opts.fps > 0.0) {
        return Err(Error::motion(format!("target frame rate {} fps", opts.fps)));
    }
    let is_npy = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("npy"));
    let (motion, format) = if is_npy {
        match read_npy_motion(path, opts)? {
            NpyMotion::Features(features) => {
                return finish(
                    path,
                    features,
                    opts,
                    origin("HumanML3D features", None, opts.fps),
                );
            }
            NpyMotion::Joints(m) => (*m, "joints"),
        }
    } else {
        let m = load_motion(path, opts.npy_fps)?.motion;
        let format = match path
            .extension()
            .map(|e| e.to_string_lossy().to_ascii_lowercase())
            .as_deref()
        {
            Some("bvh") => "BVH",
            Some("pkl" | "pickle") => "AIST++ motion",
            _ => "motion file",
        };
        (m, format)
    };
    if let Some(features) = raw_features_at(&motion, opts.fps) {
        return finish(path, features, opts, origin(format, None, motion.fps));
    }
    let (joints, rig) = t2m_joints(path, &motion)?;
    let joints = if (motion.fps - opts.fps).abs() > 1e-3 {
        resample_joints(&joints, motion.fps, opts.fps).map_err(|e| e.with_path(path))?
    } else {
        joints
    };
    // Features have one frame fewer than joints (velocities).
    let frames = joints.shape()[0].saturating_sub(1);
    check_frames(path, frames, opts)?;
    let features = extract_features(joints.view(), &FeatureOptions::default())
        .map_err(|e| e.with_path(path))?
        .features;
    finish(path, features, opts, origin(format, rig, motion.fps))
}

fn origin(format: &'static str, rig: Option<&'static str>, fps: f32) -> InputOrigin {
    InputOrigin { format, rig, fps }
}

enum NpyMotion {
    Features(Array2<f32>),
    Joints(Box<MotionFile>),
}

fn read_npy_motion(path: &Path, opts: &MotionInputOptions) -> Result<NpyMotion> {
    let a = read_npy(path)?;
    let shape = a.shape().to_vec();
    match shape.as_slice() {
        [_, FEATURE_DIM] => {
            if let Some(fps) = opts.npy_fps.filter(|f| (f - opts.fps).abs() > 1e-3) {
                return Err(Error::invalid(
                    path,
                    format!(
                        "HumanML3D features at {fps} fps: the model needs {} fps, and features \
                         cannot be resampled (convert the joints instead)",
                        opts.fps
                    ),
                ));
            }
            let f = a
                .into_dimensionality::<Ix2>()
                .map_err(|e| Error::invalid(path, e.to_string()))?;
            Ok(NpyMotion::Features(f))
        }
        [_, j @ (22 | 24), 3] => {
            let fps = opts.npy_fps.unwrap_or_else(|| npy_default_fps(*j));
            let skeleton = if *j == JOINTS {
                SkeletonKind::T2m22
            } else {
                SkeletonKind::Smpl24
            };
            let joints = a
                .into_dimensionality::<Ix3>()
                .map_err(|e| Error::invalid(path, e.to_string()))?;
            let motion = MotionFile::from_joints(fps, skeleton, joints);
            motion.validate(path)?;
            Ok(NpyMotion::Joints(Box::new(motion)))
        }
        _ => Err(Error::invalid(
            path,
            format!(
                "array of shape {shape:?}: expected HumanML3D features (T, 263) or t2m-22 / \
                 SMPL-24 joints (T, 22, 3) / (T, 24, 3)"
            ),
        )),
    }
}

/// The file's own raw HumanML3D features, when it has them at the wanted rate.
fn raw_features_at(m: &MotionFile, fps: f32) -> Option<Array2<f32>> {
    let f = m.features.as_ref()?;
    let usable = f.representation == "humanml3d263"
        && !f.normalized
        && f.data.shape()[1] == FEATURE_DIM
        && (m.fps - fps).abs() <= 1e-3;
    usable.then(|| f.data.clone())
}

/// The motion's joints on the t2m-22 skeleton, and the rig used for a custom skeleton.
fn t2m_joints(path: &Path, m: &MotionFile) -> Result<(Array3<f32>, Option<&'static str>)> {
    match &m.skeleton {
        SkeletonKind::T2m22 => Ok((m.joints.clone(), None)),
        SkeletonKind::Smpl24 => Ok((
            m.joints.slice(ndarray::s![.., ..JOINTS, ..]).to_owned(),
            None,
        )),
        SkeletonKind::Custom { joint_names, .. } => {
            let (joints, rig) = retarget_t2m(joint_names, &m.joints)
                .map_err(|reason| Error::invalid(path, reason))?;
            Ok((joints, Some(rig)))
        }
    }
}

/// t2m-22 joints (T, 22, 3) of a skeleton whose joints (T, J, 3) are named `names`, placed by
/// the first of [`RIGS`] that finds every name it needs, and that rig's name; else a message
/// naming the t2m joints left unplaced.
pub fn retarget_t2m(
    names: &[String],
    joints: &Array3<f32>,
) -> std::result::Result<(Array3<f32>, &'static str), String> {
    let rig = find_rig(names)?;
    Ok((retarget_by_name(&rig, names, joints), rig.name))
}

/// t2m joints a rig cannot place: (t2m index, the rig's names for it that are absent).
type Unplaced = Vec<(usize, Vec<&'static str>)>;

/// The first of [`RIGS`] whose names are all among `names`; else a message naming the t2m
/// joints the closest rig cannot place and the names it looked for.
fn find_rig(names: &[String]) -> std::result::Result<Rig, String> {
    let have: Vec<String> = names.iter().map(|n| normalise_name(n)).collect();
    let found = |n: &str| have.contains(&normalise_name(n));
    let missing = |rig: &Rig| -> Unplaced {
        rig.joints
            .iter()
            .enumerate()
            .filter_map(|(k, src)| {
                let absent: Vec<&'static str> = match *src {
                    Named(a) => vec![a],
                    Between(a, b) => vec![a, b],
                }
                .into_iter()
                .filter(|n| !found(n))
                .collect();
                (!absent.is_empty()).then_some((k, absent))
            })
            .collect()
    };
    let mut best: Option<(&Rig, Unplaced)> = None;
    for rig in &RIGS {
        let miss = missing(rig);
        if miss.is_empty() {
            return Ok(*rig);
        }
        if best.as_ref().is_none_or(|(_, b)| miss.len() < b.len()) {
            best = Some((rig, miss));
        }
    }
    let Some((rig, miss)) = best else {
        return Err("no rig to map joint names with".into());
    };
    let joints: Vec<&str> = miss.iter().map(|(k, _)| T2M22_JOINT_NAMES[*k]).collect();
    let mut wanted: Vec<&str> = miss.iter().flat_map(|(_, n)| n.iter().copied()).collect();
    wanted.dedup();
    Err(format!(
        "cannot map the skeleton to t2m-22: no joint for {} (closest rig: {}, which names them {})",
        joints.join(", "),
        rig.name,
        wanted.join(", ")
    ))
}

/// (T, 22, 3) t2m joints picked (or interpolated) from a named skeleton's joints by `rig`.
fn retarget_by_name(rig: &Rig, names: &[String], joints: &Array3<f32>) -> Array3<f32> {
    let have: Vec<String> = names.iter().map(|n| normalise_name(n)).collect();
    // `find_rig` checked that every name exists.
    let index = |n: &str| {
        let n = normalise_name(n);
        have.iter().position(|h| *h == n).unwrap_or(0)
    };
    let sources: Vec<(usize, usize)> = rig
        .joints
        .iter()
        .map(|src| match *src {
            Named(a) => (index(a), index(a)),
            Between(a, b) => (index(a), index(b)),
        })
        .collect();
    Array3::from_shape_fn((joints.shape()[0], JOINTS, 3), |(t, j, c)| {
        let (a, b) = sources[j];
        0.5 * (joints[[t, a, c]] + joints[[t, b, c]])
    })
}

fn check_frames(path: &Path, frames: usize, opts: &MotionInputOptions) -> Result<()> {
    let seconds = |n: usize| n as f32 / opts.fps;
    if frames < opts.min_frames {
        return Err(Error::invalid(
            path,
            format!(
                "{frames} frames at {} fps ({:.2} s): the model needs at least {} ({:.2} s)",
                opts.fps,
                seconds(frames),
                opts.min_frames,
                seconds(opts.min_frames)
            ),
        ));
    }
    if frames > opts.max_frames {
        return Err(Error::invalid(
            path,
            format!(
                "{frames} frames at {} fps ({:.0} s): at most {} ({:.0} s) are accepted",
                opts.fps,
                seconds(frames),
                opts.max_frames,
                seconds(opts.max_frames)
            ),
        ));
    }
    Ok(())
}

fn finish(
    path: &Path,
    features: Array2<f32>,
    opts: &MotionInputOptions,
    origin: InputOrigin,
) -> Result<MotionInput> {
    check_frames(path, features.shape()[0], opts)?;
    check_values(path, "HumanML3D features", features.iter())?;
    Ok(MotionInput { features, origin })
}

#[cfg(test)]
mod tests {
    use std::path::PathBuf;

    use super::*;
    use crate::aistpp::AistppMotion;
    use crate::motion_file::{Features, write_motion_file};
    use crate::npy::write_npy;

    fn shared_motion(name: &str) -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../shared/fixtures/motion")
            .join(name)
    }

    fn bundled(name: &str) -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../daemon/assets/motion")
            .join(name)
    }

    const PKL: &str = "aistpp_gBR_sBM_cAll_d04_mBR0_ch01.pkl";
    const CMU: &str = "cmu_01_01_8s_30fps.bvh";

    fn at_20() -> MotionInputOptions {
        MotionInputOptions::new(20.0)
    }

    fn max_abs_diff(a: &Array2<f32>, b: &Array2<f32>) -> f32 {
        assert_eq!(a.shape(), b.shape());
        (a - b).mapv(f32::abs).fold(0.0f32, |x, y| x.max(*y))
    }

    fn message(r: Result<MotionInput>) -> String {
        match r {
            Ok(m) => panic!("accepted: {:?}", m.origin),
            Err(e) => e.to_string(),
        }
    }

    #[test]
    fn aistpp_pkl_becomes_features_at_20_fps() {
        let m = load_motion_input(&shared_motion(PKL), &at_20()).unwrap();
        // 720 frames at 60 fps → every 3rd → 240 joints → 239 velocity frames.
        assert_eq!(m.features.shape(), &[239, 263]);
        assert_eq!(m.origin.format, "AIST++ motion");
        assert_eq!(m.origin.fps, 60.0);
        // The same file through `choreod convert --to features` (its own SMPL → t2m path).
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("f.npy");
        let opts = crate::ConvertOptions {
            target: Some(crate::ConvertTarget::Features),
            ..Default::default()
        };
        crate::convert(&shared_motion(PKL), &out, &opts).unwrap();
        let converted = read_npy(&out)
            .unwrap()
            .into_dimensionality::<Ix2>()
            .unwrap();
        // Identical joints and code path after the SMPL → t2m cut: equal to the last bit.
        assert_eq!(max_abs_diff(&m.features, &converted), 0.0);
    }

    #[test]
    fn joint_npy_uses_the_given_frame_rate() {
        let pkl = load_motion_input(&shared_motion(PKL), &at_20()).unwrap();
        let joints = AistppMotion::read(&shared_motion(PKL)).unwrap().joints();
        let dir = tempfile::tempdir().unwrap();
        let smpl = dir.path().join("smpl.npy");
        write_npy(&smpl, joints.view().into_dyn()).unwrap();
        let t2m = dir.path().join("t2m.npy");
        let j22 = joints.slice(ndarray::s![.., ..22, ..]).to_owned();
        write_npy(&t2m, j22.view().into_dyn()).unwrap();
        let opts = MotionInputOptions {
            npy_fps: Some(60.0),
            ..at_20()
        };
        for path in [&smpl, &t2m] {
            let m = load_motion_input(path, &opts).unwrap();
            assert_eq!(m.origin.format, "joints");
            assert_eq!(max_abs_diff(&m.features, &pkl.features), 0.0, "{path:?}");
        }
        // Without --fps a 22-joint array is HumanML3D's 20 fps: 720 frames stay 720.
        let m = load_motion_input(&t2m, &at_20()).unwrap();
        assert_eq!(m.features.shape()[0], 719);
    }

    #[test]
    fn feature_npy_is_taken_as_is_and_checked() {
        let pkl = load_motion_input(&shared_motion(PKL), &at_20()).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("f.npy");
        write_npy(&path, pkl.features.view().into_dyn()).unwrap();
        let m = load_motion_input(&path, &at_20()).unwrap();
        assert_eq!(m.origin.format, "HumanML3D features");
        assert_eq!(m.features, pkl.features);

        let wrong_rate = MotionInputOptions {
            npy_fps: Some(30.0),
            ..at_20()
        };
        assert!(message(load_motion_input(&path, &wrong_rate)).contains("cannot be resampled"));

        let mut bad = pkl.features.clone();
        bad[[17, 200]] = f32::NAN;
        write_npy(&path, bad.view().into_dyn()).unwrap();
        let msg = message(load_motion_input(&path, &at_20()));
        assert!(
            msg.contains("f.npy") && msg.contains(&format!("at index {}", 17 * 263 + 200)),
            "{msg}"
        );
    }

    #[test]
    fn non_finite_joints_are_one_error_naming_the_file() {
        let mut joints = AistppMotion::read(&shared_motion(PKL)).unwrap().joints();
        joints[[5, 3, 1]] = f32::INFINITY;
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("nan.npy");
        write_npy(&path, joints.view().into_dyn()).unwrap();
        let msg = message(load_motion_input(&path, &at_20()));
        assert!(
            msg.contains("nan.npy") && msg.contains("NaN or infinity"),
            "{msg}"
        );
    }

    #[test]
    fn other_npy_shapes_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("x.npy");
        write_npy(&path, Array2::<f32>::zeros((10, 72)).view().into_dyn()).unwrap();
        let msg = message(load_motion_input(&path, &at_20()));
        assert!(
            msg.contains("[10, 72]") && msg.contains("(T, 263)"),
            "{msg}"
        );
    }

    #[test]
    fn frame_bounds_are_clear_errors() {
        let path = shared_motion(PKL);
        let short = MotionInputOptions {
            min_frames: 240,
            ..at_20()
        };
        let msg = message(load_motion_input(&path, &short));
        assert!(
            msg.contains("239 frames") && msg.contains("at least 240"),
            "{msg}"
        );
        let long = MotionInputOptions {
            max_frames: 238,
            ..at_20()
        };
        let msg = message(load_motion_input(&path, &long));
        assert!(
            msg.contains("239 frames") && msg.contains("at most 238"),
            "{msg}"
        );
    }

    #[test]
    fn cmu_bvh_maps_by_name_onto_t2m() {
        let path = bundled(CMU);
        let motion = load_motion(&path, None).unwrap().motion;
        let names = motion.skeleton.joint_names();
        let (t2m, rig) = t2m_joints(&path, &motion).unwrap();
        assert_eq!(rig, Some("CMU"));
        let at = |n: &str| names.iter().position(|m| m == n).unwrap();
        for t in [0, 100, 239] {
            for c in 0..3 {
                let src = |n: &str| motion.joints[[t, at(n), c]];
                // left_knee = LeftLeg, head = Head, spine2 = midpoint of Spine and Spine1,
                // right_collar = midpoint of RightShoulder and RightArm.
                assert_eq!(t2m[[t, 4, c]], src("LeftLeg"));
                assert_eq!(t2m[[t, 15, c]], src("Head"));
                assert_eq!(t2m[[t, 6, c]], 0.5 * (src("Spine") + src("Spine1")));
                assert_eq!(
                    t2m[[t, 14, c]],
                    0.5 * (src("RightShoulder") + src("RightArm"))
                );
            }
        }
        // 240 frames at 30 fps → 160 at 20 fps → 159 feature frames.
        let m = load_motion_input(&path, &at_20()).unwrap();
        assert_eq!(m.features.shape(), &[159, 263]);
        assert_eq!((m.origin.format, m.origin.rig), ("BVH", Some("CMU")));
    }

    #[test]
    fn bvh_with_unmappable_joints_names_them() {
        let text = std::fs::read_to_string(bundled(CMU)).unwrap();
        let renamed = text
            .replace("JOINT LeftLeg", "JOINT LeftShin")
            .replace("JOINT Head", "JOINT Skull");
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("odd.bvh");
        std::fs::write(&path, renamed).unwrap();
        let msg = message(load_motion_input(&path, &at_20()));
        assert!(
            msg.contains("odd.bvh")
                && msg.contains("no joint for left_knee, head")
                && msg.contains("closest rig: CMU, which names them LeftLeg, Head"),
            "{msg}"
        );
    }

    #[test]
    fn rigs_are_found_by_normalised_names() {
        let mixamo: Vec<String> = [
            "Hips",
            "Spine",
            "Spine1",
            "Spine2",
            "Neck",
            "Head",
            "LeftShoulder",
            "LeftArm",
            "LeftForeArm",
            "LeftHand",
            "RightShoulder",
            "RightArm",
            "RightForeArm",
            "RightHand",
            "LeftUpLeg",
            "LeftLeg",
            "LeftFoot",
            "LeftToeBase",
            "RightUpLeg",
            "RightLeg",
            "RightFoot",
            "RightToeBase",
        ]
        .iter()
        .map(|n| format!("mixamorig:{n}"))
        .collect();
        assert_eq!(find_rig(&mixamo).unwrap().name, "Mixamo");
        // t2m's own names (e.g. in a custom-skeleton motion file) are SMPL-style ones.
        let t2m: Vec<String> = T2M22_JOINT_NAMES.iter().map(|n| n.to_string()).collect();
        let rig = find_rig(&t2m).unwrap();
        assert_eq!(rig.name, "SMPL");
        for (k, src) in rig.joints.iter().enumerate() {
            let Named(n) = src else { panic!("{src:?}") };
            assert_eq!(normalise_name(n), normalise_name(T2M22_JOINT_NAMES[k]));
        }
        assert_eq!(normalise_name("L_Hip"), normalise_name("left_hip"));
        assert_eq!(normalise_name("mixamorig:LeftUpLeg"), "lupleg");
    }

    #[test]
    fn motion_files_give_joints_or_their_own_raw_features() {
        let pkl = load_motion_input(&shared_motion(PKL), &at_20()).unwrap();
        let aist = AistppMotion::read(&shared_motion(PKL)).unwrap().joints();
        let marked = Features {
            data: pkl.features.mapv(|v| v + 1.0),
            representation: "humanml3d263".into(),
            normalized: false,
        };
        let t2m_20 = aist.slice(ndarray::s![..;3, ..22, ..]).to_owned();
        let dir = tempfile::tempdir().unwrap();
        let file = |name: &str, m: &MotionFile| {
            let path = dir.path().join(name);
            write_motion_file(&path, m).unwrap();
            load_motion_input(&path, &at_20()).unwrap()
        };
        let joints_only = MotionFile::from_joints(60.0, SkeletonKind::Smpl24, aist.clone());
        let got = file("j.h5", &joints_only);
        assert_eq!(got.origin.format, "motion file");
        assert_eq!(max_abs_diff(&got.features, &pkl.features), 0.0);

        // Features at another rate, or normalised ones, are not the model's input: the joints are.
        let mut other_rate = joints_only;
        other_rate.features = Some(marked.clone());
        assert_eq!(file("r.h5", &other_rate).features, pkl.features);
        let mut normalised = MotionFile::from_joints(20.0, SkeletonKind::T2m22, t2m_20.clone());
        normalised.features = Some(Features {
            normalized: true,
            ..marked.clone()
        });
        assert_eq!(file("n.h5", &normalised).features, pkl.features);

        // Raw features at the model's rate (as `stylize` writes them): those, not re-extracted.
        let mut own = MotionFile::from_joints(20.0, SkeletonKind::T2m22, t2m_20);
        own.features = Some(marked.clone());
        assert_eq!(file("f.h5", &own).features, marked.data);
    }
}
