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
//! - `.bvh`: any hierarchy whose joint names one of the [`crate::RIGS`] maps onto t2m-22 (CMU,
//!   Mixamo, SMPL-style names), else one error naming the t2m joints left unmapped;
//! - `.h5`: our motion file, with any of the skeletons above.
//!
//! Joints are resampled to the target rate with [`resample_joints`]; frame counts are bounded
//! before features are computed, and non-finite values are refused.

use std::path::Path;

use ndarray::Array2;

use crate::error::{Error, FrameBound, Result};
use crate::formats::aistpp::resample_joints;
use crate::formats::motion_file::{MotionFile, check_values};
use crate::formats::{MotionFormat, NpyMotion, probe, read_motion, read_npy_motion};
use crate::humanml3d::{FEATURE_DIM, FeatureOptions, extract_features};
use crate::kinematics::rig::t2m_joints;

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
    let format = probe(path)?;
    // HumanML3D features in a .npy are the model's input as they are: not through joints.
    if format == MotionFormat::Npy
        && let Some(features) = npy_features(path, opts)?
    {
        return finish(
            path,
            features,
            opts,
            origin("HumanML3D features", None, opts.fps),
        );
    }
    let loaded = read_motion(path, format, opts.npy_fps)?;
    let format = loaded.what();
    let motion = loaded.motion;
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

/// The HumanML3D features of a `.npy` that holds them (`None` for joints), at the model's rate:
/// features cannot be resampled.
fn npy_features(path: &Path, opts: &MotionInputOptions) -> Result<Option<Array2<f32>>> {
    let NpyMotion::Features(f) =
        read_npy_motion(path, opts.npy_fps).map_err(|e| e.in_format(MotionFormat::Npy))?
    else {
        return Ok(None);
    };
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
    Ok(Some(f))
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

fn check_frames(path: &Path, frames: usize, opts: &MotionInputOptions) -> Result<()> {
    let bound = if frames < opts.min_frames {
        FrameBound::AtLeast {
            frames: opts.min_frames,
            fps: opts.fps,
        }
    } else if frames > opts.max_frames {
        FrameBound::AtMost {
            frames: opts.max_frames,
            fps: opts.fps,
        }
    } else {
        return Ok(());
    };
    Err(Error::FrameCount {
        path: path.to_path_buf(),
        frames,
        fps: opts.fps,
        bound,
    })
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
    use crate::formats::aistpp::AistppMotion;
    use crate::formats::motion_file::{Features, write_motion_file};
    use crate::formats::npy::{read_npy, write_npy};
    use crate::skeleton::SkeletonKind;
    use ndarray::Ix2;

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
        let motion = crate::formats::load_motion(&path, None).unwrap().motion;
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
