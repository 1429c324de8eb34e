//! AIST++ motion: the `.pkl` reader and SMPL forward kinematics to world joint positions.

use std::path::Path;

use ndarray::{Array2, Array3, Array4, s};

use crate::error::{Error, Result};
use crate::pickle::{NdArray, Value, read_pickle};
use crate::rotation::{Mat3, add, axis_angle_to_mat, mat_mul, mat_vec};
use crate::skeleton::{SMPL24_OFFSETS, SMPL24_PARENTS};

/// Frame rate of AIST++ motion (google/aistplusplus_api:aist_plusplus/utils.py "constructed
/// under exact 60 fps").
pub const AISTPP_FPS: f32 = 60.0;
/// More frames than this (≈ 4.6 h at 60 fps) is treated as a hostile file.
pub const MAX_FRAMES: usize = 1_000_000;

/// One AIST++ motion as stored: SMPL axis-angle poses, translation and scale.
#[derive(Debug, Clone)]
pub struct AistppMotion {
    /// Axis-angle per joint, radians: (N, 24, 3).
    pub poses: Array3<f32>,
    /// Root translation in the capture's units: (N, 3).
    pub trans: Array2<f32>,
    /// Capture scale; `trans / scaling` is metres.
    pub scaling: f32,
    /// Frames per second (60).
    pub fps: f32,
}

fn array<'a>(path: &Path, root: &'a Value, key: &str) -> Result<&'a NdArray> {
    match root.get(key) {
        Some(Value::Array(a)) => Ok(a),
        Some(_) => Err(Error::invalid(
            path,
            format!("'{key}' is not a numpy array"),
        )),
        None => Err(Error::invalid(
            path,
            format!("missing key '{key}' (not an AIST++ motion?)"),
        )),
    }
}

fn finite(path: &Path, key: &str, a: &NdArray) -> Result<()> {
    if let Some(index) = a.data.iter().position(|v| !v.is_finite()) {
        return Err(Error::NonFinite {
            path: path.to_path_buf(),
            what: format!("'{key}'"),
            index,
        });
    }
    Ok(())
}

impl AistppMotion {
    /// Read an AIST++ motion pickle (keys `smpl_poses` (N,72) or (N,24,3), `smpl_trans` (N,3),
    /// `smpl_scaling` (1,) or scalar).
    pub fn read(path: &Path) -> Result<Self> {
        let root = read_pickle(path)?;
        if !matches!(root, Value::Dict(..)) {
            return Err(Error::invalid(
                path,
                "pickle does not hold a dict (not an AIST++ motion?)",
            ));
        }
        let poses = array(path, &root, "smpl_poses")?;
        let trans = array(path, &root, "smpl_trans")?;
        let scaling = match root.get("smpl_scaling") {
            Some(Value::Array(a)) if a.data.len() == 1 => a.data[0],
            Some(Value::Float(f)) => *f,
            Some(Value::Int(i)) => *i as f64,
            Some(_) => {
                return Err(Error::invalid(
                    path,
                    "'smpl_scaling' is not a single number",
                ));
            }
            None => return Err(Error::invalid(path, "missing key 'smpl_scaling'")),
        };
        let n = poses.shape.first().copied().unwrap_or(0);
        let per_frame: usize = poses.shape.iter().skip(1).product();
        if poses.shape.len() < 2 || per_frame != 72 {
            return Err(Error::invalid(
                path,
                format!(
                    "'smpl_poses' has shape {:?}, expected (N, 72) or (N, 24, 3)",
                    poses.shape
                ),
            ));
        }
        if n == 0 || n > MAX_FRAMES {
            return Err(Error::invalid(
                path,
                format!("{n} frames (accepted: 1..={MAX_FRAMES})"),
            ));
        }
        if trans.shape != [n, 3] {
            return Err(Error::invalid(
                path,
                format!(
                    "'smpl_trans' has shape {:?}, expected ({n}, 3)",
                    trans.shape
                ),
            ));
        }
        finite(path, "smpl_poses", poses)?;
        finite(path, "smpl_trans", trans)?;
        if !(scaling.is_finite() && scaling > 0.0) {
            return Err(Error::invalid(
                path,
                format!("'smpl_scaling' is {scaling}, must be > 0"),
            ));
        }
        let poses = Array3::from_shape_fn((n, 24, 3), |(t, j, k)| {
            poses.data[t * 72 + j * 3 + k] as f32
        });
        let trans = Array2::from_shape_fn((n, 3), |(t, k)| trans.data[t * 3 + k] as f32);
        Ok(AistppMotion {
            poses,
            trans,
            scaling: scaling as f32,
            fps: AISTPP_FPS,
        })
    }

    /// Number of frames.
    pub fn len(&self) -> usize {
        self.poses.shape()[0]
    }

    /// Whether there are no frames.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Root positions in metres: `trans / scaling` (google/aistplusplus_api
    /// demos/extract_motion_feats.py).
    pub fn root_positions(&self) -> Array2<f32> {
        &self.trans / self.scaling
    }

    /// SMPL forward kinematics: world joint positions (N, 24, 3), metres, y-up.
    pub fn joints(&self) -> Array3<f32> {
        smpl_forward_kinematics(&self.poses, &self.root_positions()).0
    }
}

/// SMPL forward kinematics with the neutral rest offsets of [`SMPL24_OFFSETS`]: local axis-angle
/// rotations (N, 24, 3) and root positions (N, 3) → world joints (N, 24, 3) and each joint's
/// global rotation (N, 24, 3, 3). Same recursion as Stanford-TML/EDGE:vis.py `SMPLSkeleton.forward`:
/// `p_j = p_parent + G_parent · offset_j`, `G_j = G_parent · R_j`.
pub fn smpl_forward_kinematics(
    poses: &Array3<f32>,
    root: &Array2<f32>,
) -> (Array3<f32>, Array4<f32>) {
    let n = poses.shape()[0].min(root.shape()[0]);
    let mut joints = Array3::<f32>::zeros((n, 24, 3));
    let mut globals = Array4::<f32>::zeros((n, 24, 3, 3));
    let mut g: [Mat3; 24] = [[[0.0; 3]; 3]; 24];
    let mut p = [[0.0f32; 3]; 24];
    for t in 0..n {
        for j in 0..24 {
            let local = axis_angle_to_mat([poses[[t, j, 0]], poses[[t, j, 1]], poses[[t, j, 2]]]);
            let parent = SMPL24_PARENTS[j];
            if parent < 0 {
                g[j] = local;
                p[j] = [root[[t, 0]], root[[t, 1]], root[[t, 2]]];
            } else {
                let pj = parent as usize;
                p[j] = add(p[pj], mat_vec(&g[pj], SMPL24_OFFSETS[j]));
                g[j] = mat_mul(&g[pj], &local);
            }
            for k in 0..3 {
                joints[[t, j, k]] = p[j][k];
                for l in 0..3 {
                    globals[[t, j, k, l]] = g[j][k][l];
                }
            }
        }
    }
    (joints, globals)
}

/// Change the frame rate of joint positions (T, J, 3). Integer ratios (60 → 30, 60 → 20) keep
/// every k-th frame, as EDGE does (`data/slice.py` stride 2); other ratios interpolate linearly.
/// Both rates must lie in [`crate::limits::FPS_RANGE`], and the result is refused before it is
/// allocated when it would hold more values than the element cap.
pub fn resample_joints(joints: &Array3<f32>, from_fps: f32, to_fps: f32) -> Result<Array3<f32>> {
    for fps in [from_fps, to_fps] {
        crate::limits::check_fps(fps).map_err(|why| {
            Error::motion(format!(
                "cannot resample {from_fps} fps to {to_fps} fps: {why}"
            ))
        })?;
    }
    let n = joints.shape()[0];
    let out_n = crate::limits::resampled_frames(
        n,
        joints.shape()[1] * joints.shape()[2],
        from_fps,
        to_fps,
    )?;
    let ratio = f64::from(from_fps) / f64::from(to_fps);
    if (ratio - ratio.round()).abs() < 1e-9 && ratio >= 1.0 {
        let k = ratio.round() as usize;
        return Ok(joints.slice(s![..;k, .., ..]).to_owned());
    }
    if n == 0 {
        return Ok(joints.clone());
    }
    // f64 time so long takes do not drift.
    let (jn, d) = (joints.shape()[1], joints.shape()[2]);
    let mut out = Array3::<f32>::zeros((out_n, jn, d));
    for i in 0..out_n {
        let src = i as f64 * ratio;
        let a = (src.floor() as usize).min(n - 1);
        let b = (a + 1).min(n - 1);
        let w = (src - a as f64) as f32;
        let frame = &joints.slice(s![a, .., ..]) * (1.0 - w) + &joints.slice(s![b, .., ..]) * w;
        out.slice_mut(s![i, .., ..]).assign(&frame);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rotation::norm;

    fn fixture() -> std::path::PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../shared/fixtures/motion/aistpp_gBR_sBM_cAll_d04_mBR0_ch01.pkl")
    }

    #[test]
    fn fk_bone_lengths_are_constant_and_equal_rest_offsets() {
        let m = AistppMotion::read(&fixture()).unwrap();
        let j = m.joints();
        assert_eq!(j.shape(), &[720, 24, 3]);
        let mut worst = 0.0f32;
        for t in 0..j.shape()[0] {
            for (c, p) in SMPL24_PARENTS.iter().enumerate().skip(1) {
                let p = *p as usize;
                let bone = [
                    j[[t, c, 0]] - j[[t, p, 0]],
                    j[[t, c, 1]] - j[[t, p, 1]],
                    j[[t, c, 2]] - j[[t, p, 2]],
                ];
                worst = worst.max((norm(bone) - norm(SMPL24_OFFSETS[c])).abs());
            }
        }
        // f32 rotations of < 0.5 m bones: error ~ 1e-7 m, far inside the 1e-5 m requirement.
        assert!(worst < 1e-5, "worst bone length error {worst}");
    }

    #[test]
    fn root_path_is_trans_over_scaling() {
        let m = AistppMotion::read(&fixture()).unwrap();
        let j = m.joints();
        for t in [0, 100, 719] {
            for k in 0..3 {
                let expect = m.trans[[t, k]] / m.scaling;
                assert!((j[[t, 0, k]] - expect).abs() < 1e-6);
            }
        }
    }

    #[test]
    fn feet_touch_the_floor_in_contact_frames() {
        let m = AistppMotion::read(&fixture()).unwrap();
        let j = m.joints();
        let n = j.shape()[0];
        // Floor = lowest foot joint over the take. A foot is in contact when it moves < 1 cm per
        // frame at 30 fps (EDGE vis.py), i.e. < 5 mm per frame at 60 fps.
        let feet = [7usize, 8, 10, 11];
        let floor = feet
            .iter()
            .flat_map(|f| (0..n).map(move |t| (t, *f)))
            .map(|(t, f)| j[[t, f, 1]])
            .fold(f32::MAX, f32::min);
        let mut contact_frames = 0;
        let mut grounded = 0;
        for t in 0..n - 1 {
            let lowest = feet.iter().map(|f| j[[t, *f, 1]]).fold(f32::MAX, f32::min);
            let still = feet.iter().any(|f| {
                let d = [
                    j[[t + 1, *f, 0]] - j[[t, *f, 0]],
                    j[[t + 1, *f, 1]] - j[[t, *f, 1]],
                    j[[t + 1, *f, 2]] - j[[t, *f, 2]],
                ];
                norm(d) < 0.005
            });
            if still {
                contact_frames += 1;
                // 8 cm: ankles sit ~7 cm above the sole in SMPL; toes within a few cm.
                if lowest - floor < 0.08 {
                    grounded += 1;
                }
            }
        }
        assert!(
            contact_frames > n / 4,
            "only {contact_frames} contact frames"
        );
        // A dancer can stand still with a lifted foot, so allow a few percent of exceptions.
        assert!(
            grounded as f32 >= 0.95 * contact_frames as f32,
            "{grounded}/{contact_frames}"
        );
    }

    /// Pickles written by the venv python (`$CHOREOD_PYTHON`, else `<workspace>/.venv`).
    fn python_pickle(dir: &Path, name: &str, code: &str) -> std::path::PathBuf {
        let py = std::env::var_os("CHOREOD_PYTHON")
            .map(std::path::PathBuf::from)
            .unwrap_or_else(|| Path::new(env!("CARGO_MANIFEST_DIR")).join("../.venv/bin/python"));
        let out = dir.join(name);
        let script = format!("import sys, pickle, numpy as np\n{code}\n");
        let st = std::process::Command::new(py)
            .arg("-c")
            .arg(script)
            .arg(&out)
            .status()
            .unwrap();
        assert!(st.success());
        out
    }

    #[test]
    fn other_layouts_protocols_and_bad_values() {
        let d = tempfile::tempdir().unwrap();
        // Protocol 2 stores bytes through _codecs.encode; poses (N, 24, 3) float64; scalar scaling.
        let p = python_pickle(
            d.path(),
            "p2.pkl",
            "rng = np.random.default_rng(0)\n\
             d = {'smpl_poses': rng.normal(0, 0.3, (5, 24, 3)), 'smpl_trans': rng.normal(0, 50, (5, 3)).astype(np.float32), 'smpl_scaling': 100.0}\n\
             pickle.dump(d, open(sys.argv[1], 'wb'), protocol=2)",
        );
        let m = AistppMotion::read(&p).unwrap();
        assert_eq!(m.poses.shape(), &[5, 24, 3]);
        assert_eq!(m.scaling, 100.0);
        let j = m.joints();
        assert!((j[[4, 0, 1]] - m.trans[[4, 1]] / 100.0).abs() < 1e-6);
        // NaN in the poses (protocol 5).
        let p = python_pickle(
            d.path(),
            "nan.pkl",
            "x = np.zeros((3, 72), np.float32); x[1, 5] = np.nan\n\
             pickle.dump({'smpl_poses': x, 'smpl_trans': np.zeros((3, 3), np.float32), 'smpl_scaling': np.ones(1, np.float32)}, open(sys.argv[1], 'wb'), protocol=5)",
        );
        let e = AistppMotion::read(&p).unwrap_err().to_string();
        assert!(e.contains("nan.pkl") && e.contains("non-finite"), "{e}");
        // Wrong types and shapes.
        for (name, code, want) in [
            (
                "type.pkl",
                "d = {'smpl_poses': [1, 2], 'smpl_trans': np.zeros((1, 3)), 'smpl_scaling': 1.0}",
                "not a numpy array",
            ),
            (
                "shape.pkl",
                "d = {'smpl_poses': np.zeros((4, 70)), 'smpl_trans': np.zeros((4, 3)), 'smpl_scaling': 1.0}",
                "(N, 72)",
            ),
            (
                "trans.pkl",
                "d = {'smpl_poses': np.zeros((4, 72)), 'smpl_trans': np.zeros((3, 3)), 'smpl_scaling': 1.0}",
                "smpl_trans",
            ),
            (
                "scale.pkl",
                "d = {'smpl_poses': np.zeros((4, 72)), 'smpl_trans': np.zeros((4, 3)), 'smpl_scaling': 0.0}",
                "must be > 0",
            ),
            ("list.pkl", "d = [1, 2, 3]", "not hold a dict"),
        ] {
            let p = python_pickle(
                d.path(),
                name,
                &format!("{code}\npickle.dump(d, open(sys.argv[1], 'wb'), protocol=4)"),
            );
            let e = AistppMotion::read(&p).unwrap_err().to_string();
            assert!(e.contains(name) && e.contains(want), "{name}: {e}");
        }
    }

    #[test]
    fn resampling_60_to_30_and_20() {
        let m = AistppMotion::read(&fixture()).unwrap();
        let j = m.joints();
        let j30 = resample_joints(&j, 60.0, 30.0).unwrap();
        let j20 = resample_joints(&j, 60.0, 20.0).unwrap();
        assert_eq!(j30.shape()[0], 360);
        assert_eq!(j20.shape()[0], 240);
        assert_eq!(j30[[5, 3, 1]], j[[10, 3, 1]]);
        assert_eq!(j20[[5, 3, 1]], j[[15, 3, 1]]);
        let j45 = resample_joints(&j, 60.0, 45.0).unwrap();
        // frame 1 at 45 fps is source frame 4/3: 2/3 of frame 1 + 1/3 of frame 2.
        let e = j[[1, 0, 0]] * (2.0 / 3.0) + j[[2, 0, 0]] / 3.0;
        assert!((j45[[1, 0, 0]] - e).abs() < 1e-5);
    }
}
