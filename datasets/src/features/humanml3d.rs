//! HumanML3D's 263-dim motion features, step by step as in EricGuo5513/HumanML3D
//! `motion_representation.ipynb` (`process_file`, `recover_from_ric`), with the skeleton and
//! quaternion helpers of `common/skeleton.py` / `common/quaternion.py`, plus mirroring and the
//! grouped mean/std of `cal_mean_variance.ipynb`.
//!
//! Feature layout per frame (T−1 frames from T joints):
//! `[rot_vel(1), lin_vel_xz(2), root_y(1), ric(21×3), rot6d(21×6), local_vel(22×3), feet_l(2), feet_r(2)]`.

use ndarray::{Array1, Array2, Array3, ArrayView2, ArrayView3, Axis};

use crate::error::{Error, Result};
use crate::rotation::{
    Quat, Vec3, cross, dot, norm, qbetween_safe, qinv, qmul, qrot, quat_to_mat, sub,
};
use crate::skeleton::{
    SMPL_LEFT, SMPL_RIGHT, T2M22_KINEMATIC_CHAIN, T2M22_PARENTS, T2M22_RAW_OFFSETS,
    t2m_default_target_offsets,
};

/// Feature width.
pub const FEATURE_DIM: usize = 263;
/// Joints of the t2m skeleton.
pub const JOINTS: usize = 22;
/// Right/left foot joints (notebook `fid_r, fid_l = [8, 11], [7, 10]`).
const FID_R: [usize; 2] = [8, 11];
const FID_L: [usize; 2] = [7, 10];
/// Face direction joints (notebook `face_joint_indx = [2, 1, 17, 16]`).
const FACE_JOINT_INDX: [usize; 4] = [2, 1, 17, 16];
/// Lower-leg joints used for the uniform-skeleton scale (notebook `l_idx1, l_idx2 = 5, 8`).
const L_IDX1: usize = 5;
const L_IDX2: usize = 8;
/// Groups of `cal_mean_variance.ipynb` whose std is averaged: root rot vel, root lin vel,
/// root y, ric, rot6d, local vel, foot contacts.
pub const STD_GROUPS: [(usize, usize); 7] = [
    (0, 1),
    (1, 3),
    (3, 4),
    (4, 67),
    (67, 193),
    (193, 259),
    (259, 263),
];
/// Longest sequence accepted (≈ 14 h at 20 fps).
const MAX_FRAMES: usize = 1_000_000;

/// Knobs of feature extraction.
#[derive(Debug, Clone)]
#[non_exhaustive]
pub struct FeatureOptions {
    /// Target skeleton offsets for the "uniform skeleton" retargeting, or `None` to skip that
    /// step (use when the joints already have the target proportions). The notebook takes them
    /// from AMASS example 000021, which is not available here.
    /// Default: [`t2m_default_target_offsets`] (t2m raw directions × SMPL neutral bone lengths).
    pub target_offsets: Option<[Vec3; JOINTS]>,
    /// Foot contact threshold on the squared per-frame displacement, m² (notebook `feet_thre`).
    /// Default: 0.002.
    pub feet_threshold: f32,
    /// Gaussian sigma (frames) smoothing the facing direction for rotations (skeleton.py
    /// `gaussian_filter1d(forward, 20, ...)`). Default: 20.
    pub smooth_sigma: f32,
    /// Flip the root-velocity quaternion to w ≥ 0 before taking arcsin of its y. The notebook
    /// does not, so a turn through ±180° of the smoothed heading yields a wrong-signed step and
    /// `recover_from_ric` drifts by that angle. Default: false (numerically as the reference).
    pub fix_heading_wrap: bool,
}

impl Default for FeatureOptions {
    fn default() -> Self {
        FeatureOptions {
            target_offsets: Some(t2m_default_target_offsets()),
            feet_threshold: 0.002,
            smooth_sigma: 20.0,
            fix_heading_wrap: false,
        }
    }
}

/// The result of [`extract_features`].
#[derive(Debug, Clone)]
pub struct FeatureExtraction {
    /// (T−1, 263) features.
    pub features: Array2<f32>,
    /// (T, 22, 3) processed joints (retargeted, on the floor, origin, facing +z): the notebook's
    /// `global_positions`.
    pub global_positions: Array3<f32>,
    /// The smoothed root rotation of frame 0 (`r_rot[0]`); `recover_from_ric(features)` equals
    /// `global_positions` rotated by it.
    pub root_rot0: Quat,
}

impl FeatureExtraction {
    /// `recover_from_ric` of the features: (T−1, 22, 3).
    pub fn recovered_joints(&self) -> Result<Array3<f32>> {
        recover_from_ric(self.features.view())
    }
}

fn get(a: &ArrayView3<'_, f32>, t: usize, j: usize) -> Vec3 {
    [a[[t, j, 0]], a[[t, j, 1]], a[[t, j, 2]]]
}

/// Forward direction per frame (skeleton.py `inverse_kinematics_np`): across = (j[r_hip] −
/// j[l_hip]) + (j[sdr_r] − j[sdr_l]) with `l_hip, r_hip, sdr_r, sdr_l = face_joint_idx`;
/// forward = y × across, normalised after optional smoothing.
fn forward_dirs(pos: &[[Vec3; JOINTS]], sigma: Option<f32>) -> Vec<Vec3> {
    let [l_hip, r_hip, sdr_r, sdr_l] = FACE_JOINT_INDX;
    let mut fwd: Vec<Vec3> = pos
        .iter()
        .map(|p| {
            let a1 = sub(p[r_hip], p[l_hip]);
            let a2 = sub(p[sdr_r], p[sdr_l]);
            let a = [a1[0] + a2[0], a1[1] + a2[1], a1[2] + a2[2]];
            let n = norm(a).max(1e-12);
            cross([0.0, 1.0, 0.0], [a[0] / n, a[1] / n, a[2] / n])
        })
        .collect();
    if let Some(sigma) = sigma {
        fwd = gaussian_filter1d(&fwd, sigma);
    }
    fwd.iter()
        .map(|f| {
            let n = norm(*f).max(1e-12);
            [f[0] / n, f[1] / n, f[2] / n]
        })
        .collect()
}

/// scipy `gaussian_filter1d(x, sigma, axis=0, mode='nearest')` (truncate 4.0).
fn gaussian_filter1d(x: &[Vec3], sigma: f32) -> Vec<Vec3> {
    let radius = (4.0 * sigma + 0.5) as usize;
    // Weights and sums in f64: 161 taps per output for sigma 20.
    let mut w: Vec<f64> = (0..=2 * radius)
        .map(|k| {
            let d = k as f64 - radius as f64;
            (-0.5 * d * d / f64::from(sigma * sigma)).exp()
        })
        .collect();
    let total: f64 = w.iter().sum();
    w.iter_mut().for_each(|v| *v /= total);
    // 'nearest' = edge values repeated; pad once instead of clamping every tap.
    let (first, last) = (x[0], x[x.len() - 1]);
    let padded: Vec<[f64; 3]> = std::iter::repeat_n(first, radius)
        .chain(x.iter().copied())
        .chain(std::iter::repeat_n(last, radius))
        .map(|v| v.map(f64::from))
        .collect();
    padded
        .windows(2 * radius + 1)
        .map(|win| {
            // Four partial sums per component so the adds pipeline instead of chaining.
            let mut acc = [[0.0f64; 3]; 4];
            let mut chunks = win.chunks_exact(4).zip(w.chunks_exact(4));
            for (p, wk) in &mut chunks {
                for l in 0..4 {
                    acc[l][0] += wk[l] * p[l][0];
                    acc[l][1] += wk[l] * p[l][1];
                    acc[l][2] += wk[l] * p[l][2];
                }
            }
            let tail = win.len() / 4 * 4;
            for (p, wk) in win[tail..].iter().zip(w[tail..].iter()) {
                acc[0][0] += wk * p[0];
                acc[0][1] += wk * p[1];
                acc[0][2] += wk * p[2];
            }
            [0, 1, 2].map(|c| (acc[0][c] + acc[1][c] + acc[2][c] + acc[3][c]) as f32)
        })
        .collect()
}

/// qbetween of two unit vectors: for |u| = |v| = 1 the norm of [1 + u·v, u×v] is
/// sqrt(2 (1 + u·v)), so one square root does (same value as [`qbetween`] up to rounding).
#[inline]
fn qbetween_unit(u: Vec3, v: Vec3) -> Quat {
    let w = 1.0 + dot(u, v);
    if w > 1e-6 {
        let c = cross(u, v);
        let s = 1.0 / (2.0 * w).sqrt();
        [w * s, c[0] * s, c[1] * s, c[2] * s]
    } else {
        qbetween_safe(u, v)
    }
}

/// skeleton.py `inverse_kinematics_np`: per-joint local quaternions (T, 22), root = rotation
/// taking the forward direction to +z.
fn inverse_kinematics(pos: &[[Vec3; JOINTS]], smooth: Option<f32>) -> Vec<[Quat; JOINTS]> {
    let fwd = forward_dirs(pos, smooth);
    pos.iter()
        .zip(fwd.iter())
        .enumerate()
        .map(|(frame, (p, f))| {
            // The reference sets frame 0's root rotation to the identity (skeleton.py
            // `root_quat[0] = np.array([[1.0, 0.0, 0.0, 0.0]])`): process_file has already
            // turned frame 0 to face +z with its unsmoothed facing.
            let root = if frame == 0 {
                [1.0, 0.0, 0.0, 0.0]
            } else {
                qbetween_safe(*f, [0.0, 0.0, 1.0])
            };
            let mut q = [[1.0f32, 0.0, 0.0, 0.0]; JOINTS];
            q[0] = root;
            for chain in T2M22_KINEMATIC_CHAIN {
                // Every chain restarts from the root rotation, also the arm chains that start
                // at joint 9 (as in the reference).
                let mut r = root;
                for w in chain.windows(2) {
                    let u = T2M22_RAW_OFFSETS[w[1]];
                    let d = sub(p[w[1]], p[w[0]]);
                    let n = norm(d);
                    let v = if n > 1e-12 {
                        [d[0] / n, d[1] / n, d[2] / n]
                    } else {
                        u
                    };
                    let between = qbetween_unit(u, v);
                    q[w[1]] = qmul(qinv(r), between);
                    // The reference updates r = r · r_loc = r · r⁻¹ · between, which is
                    // `between` up to rounding (~1e-7); taking it directly removes a serial
                    // quaternion product per joint.
                    r = between;
                }
            }
            q
        })
        .collect()
}

/// skeleton.py `forward_kinematics_np` with fixed offsets (the reference [`retarget`] is
/// checked against).
#[cfg(test)]
fn forward_kinematics(
    quats: &[[Quat; JOINTS]],
    root: &[Vec3],
    offsets: &[Vec3; JOINTS],
) -> Vec<[Vec3; JOINTS]> {
    quats
        .iter()
        .zip(root.iter())
        .map(|(q, r0)| {
            let mut p = [[0.0f32; 3]; JOINTS];
            p[0] = *r0;
            for chain in T2M22_KINEMATIC_CHAIN {
                let mut r = q[0];
                for w in chain.windows(2) {
                    r = qmul(r, q[w[1]]);
                    let o = qrot(r, offsets[w[1]]);
                    p[w[1]] = [o[0] + p[w[0]][0], o[1] + p[w[0]][1], o[2] + p[w[0]][2]];
                }
            }
            p
        })
        .collect()
}

/// The notebook's `uniform_skeleton` (IK on the source, FK with the target offsets) in closed
/// form. In its FK the accumulated rotation of joint j is R·R⁻¹·qbetween(u_j, v_j) = the
/// rotation taking the raw direction u_j onto the source bone direction v_j, so FK places
/// `p_j = p_parent + |target_j| · v_j` with the root at `scale · root`: bone directions kept,
/// lengths replaced. Equal to [`forward_kinematics`]∘[`inverse_kinematics`] up to rounding
/// (tested), at a fraction of the cost.
fn retarget(pos: &[[Vec3; JOINTS]], tgt: &[Vec3; JOINTS], scale: f32) -> Vec<[Vec3; JOINTS]> {
    let lens: [f32; JOINTS] = std::array::from_fn(|j| norm(tgt[j]));
    pos.iter()
        .map(|p| {
            let mut out = [[0.0f32; 3]; JOINTS];
            out[0] = [p[0][0] * scale, p[0][1] * scale, p[0][2] * scale];
            // Parents precede children in SMPL order.
            for j in 1..JOINTS {
                let parent = T2M22_PARENTS[j] as usize;
                let d = sub(p[j], p[parent]);
                let n = norm(d);
                let v = if n > 1e-12 {
                    [d[0] / n, d[1] / n, d[2] / n]
                } else {
                    T2M22_RAW_OFFSETS[j]
                };
                let l = lens[j];
                out[j] = [
                    out[parent][0] + v[0] * l,
                    out[parent][1] + v[1] * l,
                    out[parent][2] + v[2] * l,
                ];
            }
            out
        })
        .collect()
}

/// skeleton.py `get_offsets_joints`: raw directions × bone lengths of one frame.
fn offsets_of(p: &[Vec3; JOINTS]) -> [Vec3; JOINTS] {
    let mut o = [[0.0f32; 3]; JOINTS];
    for j in 1..JOINTS {
        let len = norm(sub(p[j], p[T2M22_PARENTS[j] as usize]));
        let d = T2M22_RAW_OFFSETS[j];
        o[j] = [d[0] * len, d[1] * len, d[2] * len];
    }
    o
}

fn max_abs(v: Vec3) -> f32 {
    v[0].abs().max(v[1].abs()).max(v[2].abs())
}

fn check_joints(j: &ArrayView3<'_, f32>) -> Result<()> {
    let sh = j.shape();
    if sh[1] != JOINTS || sh[2] != 3 {
        return Err(Error::motion(format!(
            "joints have shape {sh:?}, HumanML3D features need (T, 22, 3)"
        )));
    }
    if sh[0] < 2 || sh[0] > MAX_FRAMES {
        return Err(Error::motion(format!(
            "{} frames: HumanML3D features need 2..={MAX_FRAMES}",
            sh[0]
        )));
    }
    if j.iter().any(|v| !v.is_finite()) {
        return Err(Error::motion("joint positions contain NaN or infinity"));
    }
    Ok(())
}

/// Joints (T, 22, 3) in metres, y-up → HumanML3D features (T−1, 263), following
/// `process_file` of motion_representation.ipynb.
pub fn extract_features(
    joints: ArrayView3<'_, f32>,
    opts: &FeatureOptions,
) -> Result<FeatureExtraction> {
    check_joints(&joints)?;
    let t = joints.shape()[0];
    let mut pos: Vec<[Vec3; JOINTS]> = (0..t)
        .map(|f| std::array::from_fn(|j| get(&joints, f, j)))
        .collect();

    // Uniform skeleton: IK on the source, FK on the target, root scaled by the leg ratio.
    if let Some(tgt) = &opts.target_offsets {
        let src = offsets_of(&pos[0]);
        let src_leg = max_abs(src[L_IDX1]) + max_abs(src[L_IDX2]);
        let tgt_leg = max_abs(tgt[L_IDX1]) + max_abs(tgt[L_IDX2]);
        if src_leg <= 1e-9 {
            return Err(Error::motion("the first frame has zero-length legs"));
        }
        pos = retarget(&pos, tgt, tgt_leg / src_leg);
    }

    // Put on floor.
    let floor = pos
        .iter()
        .flat_map(|p| p.iter().map(|v| v[1]))
        .fold(f32::MAX, f32::min);
    // XZ of the first root at the origin.
    let (ox, oz) = (pos[0][0][0], pos[0][0][2]);
    for p in pos.iter_mut() {
        for v in p.iter_mut() {
            v[0] -= ox;
            v[1] -= floor;
            v[2] -= oz;
        }
    }
    // All initially face +z (unsmoothed first-frame facing; notebook names r_hip, l_hip, sdr_r, sdr_l).
    let [r_hip, l_hip, sdr_r, sdr_l] = FACE_JOINT_INDX;
    let p0 = pos[0];
    let a1 = sub(p0[r_hip], p0[l_hip]);
    let a2 = sub(p0[sdr_r], p0[sdr_l]);
    let across = [a1[0] + a2[0], a1[1] + a2[1], a1[2] + a2[2]];
    let an = norm(across).max(1e-12);
    let f0 = cross(
        [0.0, 1.0, 0.0],
        [across[0] / an, across[1] / an, across[2] / an],
    );
    let fnorm = norm(f0).max(1e-12);
    let q_init = qbetween_safe(
        [f0[0] / fnorm, f0[1] / fnorm, f0[2] / fnorm],
        [0.0, 0.0, 1.0],
    );
    for p in pos.iter_mut() {
        for v in p.iter_mut() {
            *v = qrot(q_init, *v);
        }
    }
    let global = pos;

    // Foot contacts: squared displacement below the threshold.
    let contacts = |fid: [usize; 2], f: usize| -> [f32; 2] {
        fid.map(|j| {
            let d = sub(global[f + 1][j], global[f][j]);
            if d[0] * d[0] + d[1] * d[1] + d[2] * d[2] < opts.feet_threshold {
                1.0
            } else {
                0.0
            }
        })
    };

    // Rotations with the smoothed facing (get_cont6d_params).
    let quats = inverse_kinematics(&global, Some(opts.smooth_sigma));
    let r_rot: Vec<Quat> = quats.iter().map(|q| q[0]).collect();

    // Rows are filled through plain slices (no ndarray index checks on the hot path).
    let mut buf = vec![0.0f32; (t - 1) * FEATURE_DIM];
    for (f, row) in buf.chunks_exact_mut(FEATURE_DIM).enumerate() {
        // Root angular velocity about y: arcsin of the y of r_rot[f+1] · r_rot[f]⁻¹.
        let mut rv = qmul(r_rot[f + 1], qinv(r_rot[f]));
        if opts.fix_heading_wrap && rv[0] < 0.0 {
            rv = rv.map(|c| -c);
        }
        row[0] = rv[2].clamp(-1.0, 1.0).asin();
        // Root linear velocity in the root frame of the next frame.
        let vel = qrot(r_rot[f + 1], sub(global[f + 1][0], global[f][0]));
        row[1] = vel[0];
        row[2] = vel[2];
        row[3] = global[f][0][1];
        // ric: root-relative xz, rotated to face +z.
        for j in 1..JOINTS {
            let p = global[f][j];
            let local = qrot(
                r_rot[f],
                [p[0] - global[f][0][0], p[1], p[2] - global[f][0][2]],
            );
            for c in 0..3 {
                row[4 + (j - 1) * 3 + c] = local[c];
            }
        }
        // rot6d: first two columns of each local rotation matrix.
        for (j, q) in quats[f].iter().enumerate().skip(1) {
            let m = quat_to_mat(*q);
            let base = 67 + (j - 1) * 6;
            for r in 0..3 {
                row[base + r] = m[r][0];
                row[base + 3 + r] = m[r][1];
            }
        }
        // Local velocity of every joint, in the root frame of this frame.
        for j in 0..JOINTS {
            let v = qrot(r_rot[f], sub(global[f + 1][j], global[f][j]));
            for c in 0..3 {
                row[193 + j * 3 + c] = v[c];
            }
        }
        let [l0, l1] = contacts(FID_L, f);
        let [r0, r1] = contacts(FID_R, f);
        row[259] = l0;
        row[260] = l1;
        row[261] = r0;
        row[262] = r1;
    }
    let out = Array2::from_shape_vec((t - 1, FEATURE_DIM), buf)
        .map_err(|e| Error::motion(e.to_string()))?;
    let global_positions = Array3::from_shape_fn((t, JOINTS, 3), |(f, j, c)| global[f][j][c]);
    Ok(FeatureExtraction {
        features: out,
        global_positions,
        root_rot0: r_rot[0],
    })
}

/// HumanML3D features (T, 263) → joints (T, 22, 3) (notebook `recover_from_ric`).
/// Root heading and position are integrated in f64 so long sequences do not drift.
pub fn recover_from_ric(data: ArrayView2<'_, f32>) -> Result<Array3<f32>> {
    let sh = data.shape();
    if sh[1] != FEATURE_DIM {
        return Err(Error::motion(format!(
            "features have shape {sh:?}, expected (T, 263)"
        )));
    }
    if sh[0] > MAX_FRAMES {
        return Err(Error::motion(format!(
            "{} frames is more than {MAX_FRAMES}",
            sh[0]
        )));
    }
    if data.iter().any(|v| !v.is_finite()) {
        return Err(Error::motion("features contain NaN or infinity"));
    }
    let t = sh[0];
    let mut out = Array3::<f32>::zeros((t, JOINTS, 3));
    let (mut ang, mut px, mut pz) = (0.0f64, 0.0f64, 0.0f64);
    for f in 0..t {
        if f > 0 {
            ang += f64::from(data[[f - 1, 0]]);
        }
        let q: Quat = [ang.cos() as f32, 0.0, ang.sin() as f32, 0.0];
        let qi = qinv(q);
        if f > 0 {
            let d = qrot(qi, [data[[f - 1, 1]], 0.0, data[[f - 1, 2]]]);
            px += f64::from(d[0]);
            pz += f64::from(d[2]);
        }
        let (rx, rz) = (px as f32, pz as f32);
        out[[f, 0, 0]] = rx;
        out[[f, 0, 1]] = data[[f, 3]];
        out[[f, 0, 2]] = rz;
        for j in 1..JOINTS {
            let b = 4 + (j - 1) * 3;
            let p = qrot(qi, [data[[f, b]], data[[f, b + 1]], data[[f, b + 2]]]);
            out[[f, j, 0]] = p[0] + rx;
            out[[f, j, 1]] = p[1];
            out[[f, j, 2]] = p[2] + rz;
        }
    }
    Ok(out)
}

fn mirror_index(j: usize) -> usize {
    if let Some(k) = SMPL_LEFT.iter().position(|&l| l == j) {
        SMPL_RIGHT[k]
    } else if let Some(k) = SMPL_RIGHT.iter().position(|&r| r == j) {
        SMPL_LEFT[k]
    } else {
        j
    }
}

/// Mirror joints (T, J, 3) of SMPL-24 or t2m-22 across the x = 0 plane: negate x and swap left
/// and right joints (HumanML3D raw_pose_processing.ipynb `swap_left_right`).
pub fn mirror_joints(joints: ArrayView3<'_, f32>) -> Result<Array3<f32>> {
    let sh = joints.shape();
    if !(sh[1] == 22 || sh[1] == 24) || sh[2] != 3 {
        return Err(Error::motion(format!(
            "cannot mirror joints of shape {sh:?} (SMPL-24 or t2m-22)"
        )));
    }
    Ok(Array3::from_shape_fn((sh[0], sh[1], 3), |(f, j, c)| {
        let v = joints[[f, mirror_index(j), c]];
        if c == 0 { -v } else { v }
    }))
}

/// The mirror in feature space: the features of the mirrored motion, computed from the
/// features alone (every dimension is defined: rotation velocity and x components change sign,
/// left/right joints swap, the 6D rotations become M·R·M with M = diag(−1, 1, 1)).
pub fn mirror_features(data: ArrayView2<'_, f32>) -> Result<Array2<f32>> {
    let sh = data.shape();
    if sh[1] != FEATURE_DIM {
        return Err(Error::motion(format!(
            "features have shape {sh:?}, expected (T, 263)"
        )));
    }
    let mut out = data.to_owned();
    for (f, mut row) in out.outer_iter_mut().enumerate() {
        let src = data.row(f);
        row[0] = -src[0];
        row[1] = -src[1];
        for j in 1..JOINTS {
            let m = mirror_index(j);
            for c in 0..3 {
                let v = src[4 + (m - 1) * 3 + c];
                row[4 + (j - 1) * 3 + c] = if c == 0 { -v } else { v };
            }
            // column 0 = (R00, R10, R20) → (R00, −R10, −R20); column 1 → (−R01, R11, R21).
            let sign = [1.0, -1.0, -1.0, -1.0, 1.0, 1.0];
            for (k, s) in sign.iter().enumerate() {
                row[67 + (j - 1) * 6 + k] = s * src[67 + (m - 1) * 6 + k];
            }
        }
        for j in 0..JOINTS {
            let m = mirror_index(j);
            for c in 0..3 {
                let v = src[193 + m * 3 + c];
                row[193 + j * 3 + c] = if c == 0 { -v } else { v };
            }
        }
        row[259] = src[261];
        row[260] = src[262];
        row[261] = src[259];
        row[262] = src[260];
    }
    Ok(out)
}

/// Mean and std over all frames of many feature arrays, with the std averaged inside each of
/// [`STD_GROUPS`] (HumanML3D cal_mean_variance.py: every group's mean std divided by 1.0, i.e.
/// unchanged). Population std (numpy `std`, ddof 0). Accumulated in f64: millions of frames.
pub fn mean_std<'a>(
    sequences: impl IntoIterator<Item = ArrayView2<'a, f32>>,
) -> Result<(Array1<f32>, Array1<f32>)> {
    let mut sum = vec![0.0f64; FEATURE_DIM];
    let mut sq = vec![0.0f64; FEATURE_DIM];
    let mut n = 0usize;
    for s in sequences {
        if s.shape()[1] != FEATURE_DIM {
            return Err(Error::motion(format!(
                "features have shape {:?}, expected (T, 263)",
                s.shape()
            )));
        }
        for row in s.axis_iter(Axis(0)) {
            for (d, v) in row.iter().enumerate() {
                let v = f64::from(*v);
                sum[d] += v;
                sq[d] += v * v;
            }
            n += 1;
        }
    }
    mean_std_from_sums(&sum, &sq, n as u64)
}

/// Mean and grouped std from f64 per-dimension sums and sums of squares over `n` frames (the
/// part of [`mean_std`] that `choreod prep` runs on per-shard sums).
pub fn mean_std_from_sums(
    sum: &[f64],
    sum_sq: &[f64],
    n: u64,
) -> Result<(Array1<f32>, Array1<f32>)> {
    if n == 0 || sum.len() != FEATURE_DIM || sum_sq.len() != FEATURE_DIM {
        return Err(Error::motion(format!(
            "no frames or wrong width for mean/std ({n} frames, {} dims)",
            sum.len()
        )));
    }
    let nf = n as f64;
    let mean: Vec<f64> = sum.iter().map(|s| s / nf).collect();
    let std: Vec<f64> = sum_sq
        .iter()
        .zip(&mean)
        .map(|(q, m)| (q / nf - m * m).max(0.0).sqrt())
        .collect();
    let mut grouped = vec![0.0f32; FEATURE_DIM];
    for (a, b) in STD_GROUPS {
        let avg = std[a..b].iter().sum::<f64>() / (b - a) as f64;
        grouped[a..b].fill(avg as f32);
    }
    Ok((
        mean.iter().map(|m| *m as f32).collect(),
        Array1::from(grouped),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::AistppMotion;
    use ndarray::s;

    /// AIST++ fixture → t2m-22 joints at 20 fps.
    fn fixture_t2m() -> Array3<f32> {
        let p = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../shared/fixtures/motion/aistpp_gBR_sBM_cAll_d04_mBR0_ch01.pkl");
        let j = AistppMotion::read(&p).unwrap().joints();
        let j = crate::resample_joints(&j, 60.0, 20.0).unwrap();
        j.slice(s![.., ..22, ..]).to_owned()
    }

    #[test]
    fn closed_form_retarget_equals_ik_then_fk() {
        let j = fixture_t2m();
        let pos: Vec<[Vec3; JOINTS]> = (0..j.shape()[0])
            .map(|f| std::array::from_fn(|k| get(&j.view(), f, k)))
            .collect();
        let tgt = t2m_default_target_offsets();
        let scale = 0.93;
        let root: Vec<Vec3> = pos.iter().map(|p| p[0].map(|v| v * scale)).collect();
        let slow = forward_kinematics(&inverse_kinematics(&pos, None), &root, &tgt);
        let fast = retarget(&pos, &tgt, scale);
        let d = slow
            .iter()
            .zip(fast.iter())
            .flat_map(|(a, b)| {
                a.iter()
                    .zip(b.iter())
                    .flat_map(|(x, y)| (0..3).map(move |c| (x[c] - y[c]).abs()))
            })
            .fold(0.0f32, f32::max);
        // f32 quaternion chains of up to 6 joints: a few 1e-7 m.
        assert!(d < 1e-5, "max difference {d} m");
    }

    /// The features agree with the numpy port of the notebook (datasets/bench/features_numpy.py,
    /// float64, scipy's gaussian_filter1d) on the fixture.
    #[test]
    fn matches_the_numpy_port_of_the_notebook() {
        let dir = tempfile::tempdir().unwrap();
        let j = fixture_t2m();
        let opts = FeatureOptions::default();
        let tgt = opts.target_offsets.unwrap();
        let f = extract_features(j.view(), &opts).unwrap().features;
        let (jp, tp, fp) = (
            dir.path().join("j.npy"),
            dir.path().join("t.npy"),
            dir.path().join("f.npy"),
        );
        crate::write_npy(&jp, j.view().into_dyn()).unwrap();
        crate::write_npy(
            &tp,
            Array2::from_shape_fn((22, 3), |(a, b)| tgt[a][b])
                .view()
                .into_dyn(),
        )
        .unwrap();
        crate::write_npy(&fp, f.view().into_dyn()).unwrap();
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
        let py = std::env::var_os("CHOREOD_PYTHON")
            .map(std::path::PathBuf::from)
            .unwrap_or_else(|| root.join("../.venv/bin/python"));
        let frames = j.shape()[0].to_string();
        let out = std::process::Command::new(py)
            .arg(root.join("bench/features_numpy.py"))
            .args([&jp, &tp, &fp])
            .args(["1", frames.as_str(), "1"])
            .output()
            .unwrap();
        let text = String::from_utf8_lossy(&out.stdout);
        assert!(
            out.status.success(),
            "{text}{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let field = |k: &str| -> f64 {
            let at = text.find(k).unwrap() + k.len() + 3;
            text[at..]
                .split([',', '}'])
                .next()
                .unwrap()
                .trim()
                .parse()
                .unwrap()
        };
        // f32 (ours) against float64 (numpy) over 240 frames: a few 1e-6.
        assert!(field("max_abs_diff_vs_rust") < 1e-4, "{text}");
        assert_eq!(field("contact_mismatches"), 0.0, "{text}");
    }

    /// Max |a − b| over the elements of two equally shaped arrays.
    fn max_abs_diff(a: &ndarray::ArrayD<f32>, b: &ndarray::ArrayD<f32>) -> f32 {
        assert_eq!(a.shape(), b.shape());
        a.iter()
            .zip(b.iter())
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max)
    }

    /// The features and processed joints equal those of HumanML3D's own `process_file`, run
    /// with torch on the notebook's code by tests/fixtures/humanml3d_official/make_reference.py
    /// (the AIST++ fixture as choreod converts it, a larger body turning, a non-rigid wobble).
    #[test]
    fn matches_the_official_process_file() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("tests/fixtures/humanml3d_official");
        let load = |name: &str| crate::read_npy(&dir.join(name)).unwrap();
        // The AIST++ case's input is exactly what choreod feeds the extractor.
        let ours = fixture_t2m().slice(s![..120, .., ..]).to_owned().into_dyn();
        assert_eq!(load("aistpp_joints.npy"), ours);
        for case in ["aistpp", "synthetic_turn", "synthetic_wobble"] {
            let joints = load(&format!("{case}_joints.npy"))
                .into_dimensionality::<ndarray::Ix3>()
                .unwrap();
            let f = extract_features(joints.view(), &FeatureOptions::default()).unwrap();
            let want = load(&format!("{case}_features.npy"));
            let got = f.features.into_dyn();
            // Both pipelines run in float32 (the notebook's quaternion helpers cast to torch
            // float); values are O(1) m or rad, so a few ulps of chained rotations, 1e-5.
            let root = max_abs_diff(
                &got.slice(s![.., ..4]).to_owned().into_dyn(),
                &want.slice(s![.., ..4]).to_owned().into_dyn(),
            );
            let all = max_abs_diff(&got, &want);
            assert!(root < 1e-5 && all < 1e-5, "{case}: root {root}, all {all}");
            let pos = max_abs_diff(
                &f.global_positions.into_dyn(),
                &load(&format!("{case}_positions.npy")),
            );
            assert!(pos < 1e-5, "{case}: positions differ by {pos} m");
        }
    }

    #[test]
    fn shape_and_contacts_are_binary() {
        let f = extract_features(fixture_t2m().view(), &FeatureOptions::default()).unwrap();
        assert_eq!(f.features.shape(), &[239, 263]);
        assert!(
            f.features
                .slice(s![.., 259..])
                .iter()
                .all(|v| *v == 0.0 || *v == 1.0)
        );
        // Processed joints stand on the floor and start at the XZ origin.
        let g = &f.global_positions;
        assert!(
            g.iter()
                .skip(1)
                .step_by(3)
                .fold(f32::MAX, |a, b| a.min(*b))
                .abs()
                < 1e-6
        );
        assert!(g[[0, 0, 0]].abs() < 1e-5 && g[[0, 0, 2]].abs() < 1e-5);
    }

    /// max |recover_from_ric(features) − R(root_rot0)·processed joints| in metres.
    fn round_trip_error(joints: &Array3<f32>, opts: &FeatureOptions) -> f32 {
        let f = extract_features(joints.view(), opts).unwrap();
        let rec = f.recovered_joints().unwrap();
        let t = rec.shape()[0];
        let mut worst = 0.0f32;
        for fr in 0..t {
            for j in 0..JOINTS {
                let g = f.global_positions.slice(s![fr, j, ..]);
                let e = qrot(f.root_rot0, [g[0], g[1], g[2]]);
                for c in 0..3 {
                    worst = worst.max((rec[[fr, j, c]] - e[c]).abs());
                }
            }
        }
        worst
    }

    #[test]
    fn round_trip_reproduces_processed_joints() {
        let j = fixture_t2m();
        // f32 quaternion chains over 240 frames: ~1e-6 m; the requirement is 1e-4 m. The fixture
        // never turns through ±180° of its initial heading, so the reference formula suffices.
        for fix in [false, true] {
            let opts = FeatureOptions {
                fix_heading_wrap: fix,
                ..FeatureOptions::default()
            };
            let d = round_trip_error(&j, &opts);
            assert!(d < 1e-4, "fix_heading_wrap={fix}: max joint error {d} m");
        }
    }

    #[test]
    fn a_full_turn_needs_the_heading_fix() {
        // One pose of the fixture spun about y by 4° per frame: 1.5 turns in 135 frames.
        let j0 = fixture_t2m();
        let j = Array3::from_shape_fn((135, JOINTS, 3), |(f, k, c)| {
            let a = (4.0f32 * f as f32).to_radians();
            let q = [(a / 2.0).cos(), 0.0, (a / 2.0).sin(), 0.0];
            qrot(q, [j0[[0, k, 0]], j0[[0, k, 1]], j0[[0, k, 2]]])[c]
        });
        let faithful = round_trip_error(&j, &FeatureOptions::default());
        let fixed = round_trip_error(
            &j,
            &FeatureOptions {
                fix_heading_wrap: true,
                ..FeatureOptions::default()
            },
        );
        // The reference's arcsin(q_y) takes a wrong-signed step at the ±180° crossing: the
        // recovered heading is then off by about twice the per-frame turn, decimetres at the hands.
        assert!(faithful > 0.01, "reference formula error only {faithful} m");
        assert!(fixed < 1e-4, "fixed formula error {fixed} m");
    }

    #[test]
    fn mirror_twice_is_identity() {
        let j = fixture_t2m();
        let back = mirror_joints(mirror_joints(j.view()).unwrap().view()).unwrap();
        assert_eq!(back, j);
        let f = extract_features(j.view(), &FeatureOptions::default())
            .unwrap()
            .features;
        let back = mirror_features(mirror_features(f.view()).unwrap().view()).unwrap();
        assert_eq!(back, f);
    }

    #[test]
    fn features_of_mirror_equal_mirror_of_features() {
        // Retarget first so both sides share the (symmetric) target skeleton; the leg-ratio
        // scale of the uniform-skeleton step uses the right leg only and would differ.
        let g = extract_features(fixture_t2m().view(), &FeatureOptions::default())
            .unwrap()
            .global_positions;
        let opts = FeatureOptions {
            target_offsets: None,
            ..FeatureOptions::default()
        };
        let a = extract_features(mirror_joints(g.view()).unwrap().view(), &opts)
            .unwrap()
            .features;
        let b =
            mirror_features(extract_features(g.view(), &opts).unwrap().features.view()).unwrap();
        let d = a
            .iter()
            .zip(b.iter())
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max);
        // f32 rounding differs between the two paths (different summation order): 1e-4.
        assert!(d < 1e-4, "max feature difference {d}");
    }

    #[test]
    fn grouped_std_is_constant_within_groups() {
        let f = extract_features(fixture_t2m().view(), &FeatureOptions::default())
            .unwrap()
            .features;
        let (mean, std) = mean_std([f.view()]).unwrap();
        assert!((mean[3] - f.column(3).mean().unwrap()).abs() < 1e-5);
        for (a, b) in STD_GROUPS {
            assert!(std.slice(s![a..b]).iter().all(|v| *v == std[a]));
        }
        assert!(std[4] > 0.0);
    }

    #[test]
    fn bad_shapes_and_nan_are_errors() {
        assert!(
            extract_features(Array3::zeros((1, 22, 3)).view(), &FeatureOptions::default()).is_err()
        );
        assert!(
            extract_features(Array3::zeros((5, 24, 3)).view(), &FeatureOptions::default()).is_err()
        );
        let mut j = fixture_t2m();
        j[[3, 4, 1]] = f32::NAN;
        assert!(
            extract_features(j.view(), &FeatureOptions::default())
                .unwrap_err()
                .to_string()
                .contains("NaN")
        );
        assert!(recover_from_ric(Array2::zeros((3, 262)).view()).is_err());
    }
}
