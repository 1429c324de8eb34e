//! LODGE's SMPL-X body representation (FineDance, 139 values a frame at 30 fps) and its
//! forward kinematics, with the rotation formulas the official code really ran.
//!
//! A frame is `[4 foot contacts, SMPL-X transl (3), 22 body joints × 6D]` (LODGE
//! `dld/data/render_joints/smplfk.py:95-117` `do_smplxfk`: contacts 0..4, transl 4..7, 6D
//! 7..139). The 6D of a rotation is the first two **rows** of its matrix (pytorch3d
//! `matrix_to_rotation_6d`), and back by Gram–Schmidt (`rotation_6d_to_matrix`).
//!
//! LODGE pins pytorch3d 0.3.0, which lacks `matrix_to_axis_angle` that LODGE imports, so a
//! release from 0.6.2 on ran; 0.6.2 to 0.7.5 share one `matrix_to_quaternion` (the
//! best-conditioned of four candidates, real part not made positive: `transforms/
//! rotation_conversions.py` of v0.7.5, lines 102-161), which is what [`mat_to_quat`] computes.
//! The axis-angle of a matrix is then `quaternion_to_axis_angle` of it (same file, 525-553),
//! whose angle can exceed π when the chosen candidate has a negative real part.
//!
//! The FK is `SMPLX_Skeleton.forward` (smplfk.py:706-759): each axis-angle goes through
//! smplx's `batch_rodrigues` (smplfk.py:579-609, which adds 1e-8 to every component before
//! taking the norm), the chain runs over SMPL-X's parents (smplfk.py:292) from the rest
//! joints, and `transl` is added to every joint, so the pelvis is `transl + J0`. The rest joints
//! (SMPL-X's `smplx_neu_J_1.npy`, 55 × 3 metres, y up) are not part of choreod: a LODGE package
//! carries them, read from the user's clone.
//!
//! Computed in f64 inside and rounded to f32 at the end: the official code runs in float32, so
//! the results agree with it to float32 rounding.

use crate::error::{Error, Result};
use crate::rotation::{Mat3, Vec3, quat_to_mat};

/// The `representation` name of raw LODGE features (a motion file's `/motion/features`).
pub const LODGE_REPRESENTATION: &str = "lodge-smplx139";
/// Values per frame of LODGE's FineDance motion.
pub const LODGE_FEATURES: usize = 139;
/// Foot contacts at the start of a frame (smplfk.py `get_rcond` order: left ankle, right
/// ankle, left toe, right toe; LODGE model.py:882).
pub const LODGE_CONTACTS: usize = 4;
/// The SMPL-X body joints a LODGE frame rotates.
pub const BODY_JOINTS: usize = 22;
/// Offset of `transl` in a frame.
const TRANSL: usize = LODGE_CONTACTS;
/// Offset of the first joint's 6D in a frame.
const ROT6D: usize = LODGE_CONTACTS + 3;

/// Parent of each SMPL-X body joint, -1 for the pelvis: LODGE's `smplx_parents[:22]`
/// (smplfk.py:292), the same tree as SMPL's first 22 joints (HumanML3D's t2m-22).
pub const SMPLX_BODY_PARENTS: [i32; BODY_JOINTS] = crate::skeleton::T2M22_PARENTS;

/// SMPL-X's names of the body joints, in order: SMPL's first 22.
pub const SMPLX_BODY_NAMES: [&str; BODY_JOINTS] = crate::skeleton::T2M22_JOINT_NAMES;

type M64 = [[f64; 3]; 3];

fn to_f32(m: M64) -> Mat3 {
    m.map(|row| row.map(|v| v as f32))
}

fn to_f64(m: &Mat3) -> M64 {
    m.map(|row| row.map(f64::from))
}

/// `x / max(|x|, 1e-12)`, torch's `F.normalize` (its default eps).
fn normalize(v: [f64; 3]) -> [f64; 3] {
    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt().max(1e-12);
    [v[0] / n, v[1] / n, v[2] / n]
}

/// Rotation matrix of a 6D rotation (pytorch3d `rotation_6d_to_matrix`, v0.7.5
/// rotation_conversions.py:556-577): rows b1 = a1/|a1|, b2 = the unit part of a2 orthogonal to
/// b1, b3 = b1 × b2.
pub fn rot6d_to_mat(d6: &[f32; 6]) -> Mat3 {
    let a1 = [d6[0], d6[1], d6[2]].map(f64::from);
    let a2 = [d6[3], d6[4], d6[5]].map(f64::from);
    let b1 = normalize(a1);
    let d = b1[0] * a2[0] + b1[1] * a2[1] + b1[2] * a2[2];
    let b2 = normalize([a2[0] - d * b1[0], a2[1] - d * b1[1], a2[2] - d * b1[2]]);
    let b3 = [
        b1[1] * b2[2] - b1[2] * b2[1],
        b1[2] * b2[0] - b1[0] * b2[2],
        b1[0] * b2[1] - b1[1] * b2[0],
    ];
    to_f32([b1, b2, b3])
}

/// The 6D of a rotation matrix: its first two rows (pytorch3d `matrix_to_rotation_6d`, v0.7.5
/// rotation_conversions.py:580-596).
pub fn mat_to_rot6d(m: &Mat3) -> [f32; 6] {
    [m[0][0], m[0][1], m[0][2], m[1][0], m[1][1], m[1][2]]
}

/// `sqrt(max(0, x))` (pytorch3d `_sqrt_positive_part`).
fn sqrt_positive(x: f64) -> f64 {
    if x > 0.0 { x.sqrt() } else { 0.0 }
}

fn mat_to_quat64(m: &M64) -> [f64; 4] {
    let q_abs = [
        sqrt_positive(1.0 + m[0][0] + m[1][1] + m[2][2]),
        sqrt_positive(1.0 + m[0][0] - m[1][1] - m[2][2]),
        sqrt_positive(1.0 - m[0][0] + m[1][1] - m[2][2]),
        sqrt_positive(1.0 - m[0][0] - m[1][1] + m[2][2]),
    ];
    // The quaternion times each of r, i, j, k; the candidate with the largest |component|
    // (torch's argmax: the first of equal maxima) is divided by 2 × that component.
    #[rustfmt::skip]
    let by = [
        [q_abs[0] * q_abs[0], m[2][1] - m[1][2], m[0][2] - m[2][0], m[1][0] - m[0][1]],
        [m[2][1] - m[1][2], q_abs[1] * q_abs[1], m[1][0] + m[0][1], m[0][2] + m[2][0]],
        [m[0][2] - m[2][0], m[1][0] + m[0][1], q_abs[2] * q_abs[2], m[1][2] + m[2][1]],
        [m[1][0] - m[0][1], m[2][0] + m[0][2], m[2][1] + m[1][2], q_abs[3] * q_abs[3]],
    ];
    let mut best = 0;
    for i in 1..4 {
        if q_abs[i] > q_abs[best] {
            best = i;
        }
    }
    let denom = 2.0 * q_abs[best].max(0.1);
    by[best].map(|v| v / denom)
}

/// Quaternion `[w, x, y, z]` of a rotation matrix as pytorch3d 0.6.2–0.7.5's
/// `matrix_to_quaternion` computes it (v0.7.5 rotation_conversions.py:102-161): the
/// best-conditioned of four candidates, its real part left as it comes (it may be negative).
pub fn mat_to_quat(m: &Mat3) -> [f32; 4] {
    mat_to_quat64(&to_f64(m)).map(|v| v as f32)
}

/// `sin(θ/2) / θ`, with pytorch3d's series `1/2 - θ²/48` under |θ| < 1e-6.
fn sin_half_over_angle(angle: f64) -> f64 {
    if angle.abs() < 1e-6 {
        0.5 - angle * angle / 48.0
    } else {
        (angle / 2.0).sin() / angle
    }
}

fn quat_to_axis_angle64(q: [f64; 4]) -> [f64; 3] {
    let n = (q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    let angle = 2.0 * n.atan2(q[0]);
    let s = sin_half_over_angle(angle);
    [q[1] / s, q[2] / s, q[3] / s]
}

/// Axis-angle of a rotation matrix as the official code computed it: pytorch3d
/// `quaternion_to_axis_angle(matrix_to_quaternion(m))` (v0.7.5 rotation_conversions.py:477-553;
/// LODGE smplfk.py:51 `ax_from_6v`). The angle is `2 atan2(|xyz|, w)`, in [0, 2π).
pub fn mat_to_axis_angle(m: &Mat3) -> Vec3 {
    quat_to_axis_angle64(mat_to_quat64(&to_f64(m))).map(|v| v as f32)
}

/// Rotation matrix of an axis-angle vector as pytorch3d 0.6.2–0.7.5 computes it:
/// `quaternion_to_matrix(axis_angle_to_quaternion(a))` (v0.7.5 rotation_conversions.py:41-70,
/// 461-522; LODGE's `ax_to_6v`, used for the mirrored keyframes).
pub fn axis_angle_to_mat(a: &Vec3) -> Mat3 {
    let a = a.map(f64::from);
    let angle = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
    let s = sin_half_over_angle(angle);
    quat_to_mat([(angle / 2.0).cos(), a[0] * s, a[1] * s, a[2] * s].map(|v| v as f32))
}

/// smplx's `batch_rodrigues` (LODGE smplfk.py:579-609): the angle is `|a + 1e-8|` (1e-8 added
/// to each component), the axis `a / angle`, and `R = I + sin K + (1 - cos) K²`.
fn smplx_rodrigues(a: &Vec3) -> M64 {
    let a = a.map(f64::from);
    let angle = ((a[0] + 1e-8).powi(2) + (a[1] + 1e-8).powi(2) + (a[2] + 1e-8).powi(2)).sqrt();
    let [x, y, z] = a.map(|v| v / angle);
    let (s, c) = angle.sin_cos();
    let k = [[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]];
    let kk = mul(&k, &k);
    let mut r = [[0.0; 3]; 3];
    for (i, row) in r.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = f64::from(u8::from(i == j)) + s * k[i][j] + (1.0 - c) * kk[i][j];
        }
    }
    r
}

fn mul(a: &M64, b: &M64) -> M64 {
    let mut out = [[0.0; 3]; 3];
    for (i, row) in out.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j];
        }
    }
    out
}

/// One frame of LODGE's representation, decoded.
#[derive(Debug, Clone, PartialEq)]
pub struct LodgePose {
    /// Foot contacts as stored (left ankle, right ankle, left toe, right toe).
    pub contacts: [f32; LODGE_CONTACTS],
    /// SMPL-X `transl` (metres, y up); the pelvis is at `transl + rest[0]`.
    pub transl: Vec3,
    /// Each body joint's rotation relative to its parent (pytorch3d's `rotation_6d_to_matrix`).
    pub rotations: [Mat3; BODY_JOINTS],
}

/// Decode one raw (un-normalised) frame of 139 values.
pub fn decode_frame(frame: &[f32]) -> Result<LodgePose> {
    if frame.len() != LODGE_FEATURES {
        return Err(Error::motion(format!(
            "a LODGE frame has {LODGE_FEATURES} values, got {}",
            frame.len()
        )));
    }
    if let Some(i) = frame.iter().position(|v| !v.is_finite()) {
        return Err(Error::motion(format!(
            "LODGE frame value {i} is not finite"
        )));
    }
    let mut rotations = [[[0.0; 3]; 3]; BODY_JOINTS];
    for (j, r) in rotations.iter_mut().enumerate() {
        let at = ROT6D + 6 * j;
        let d6: [f32; 6] = frame[at..at + 6].try_into().expect("six values");
        *r = rot6d_to_mat(&d6);
    }
    Ok(LodgePose {
        contacts: frame[..LODGE_CONTACTS].try_into().expect("four values"),
        transl: [frame[TRANSL], frame[TRANSL + 1], frame[TRANSL + 2]],
        rotations,
    })
}

/// SMPL-X body rest joints checked for FK: at least the 22 body joints (a 55-joint SMPL-X
/// table is accepted; the rest is ignored), all finite.
pub fn body_rest_joints(rest: &[Vec3]) -> Result<[Vec3; BODY_JOINTS]> {
    if rest.len() < BODY_JOINTS {
        return Err(Error::motion(format!(
            "SMPL-X rest joints: need at least {BODY_JOINTS}, got {}",
            rest.len()
        )));
    }
    if let Some(j) = rest[..BODY_JOINTS]
        .iter()
        .position(|p| p.iter().any(|v| !v.is_finite()))
    {
        return Err(Error::motion(format!(
            "SMPL-X rest joint {j} is not finite"
        )));
    }
    Ok(rest[..BODY_JOINTS].try_into().expect("22 joints"))
}

/// World positions of the 22 body joints for one pose, as LODGE's FK computes them
/// (`do_smplxfk`, smplfk.py:95-117 and 706-759): each rotation goes matrix → axis-angle
/// ([`mat_to_axis_angle`]) → smplx Rodrigues, the chain starts at the pelvis's rest position,
/// each child sits at `parent + R_parent_world (rest_child - rest_parent)`, and `transl` is
/// added to all.
pub fn body_joints(pose: &LodgePose, rest: &[Vec3; BODY_JOINTS]) -> [Vec3; BODY_JOINTS] {
    let rest = rest.map(|p| p.map(f64::from));
    let mut world_rot = [[[0.0; 3]; 3]; BODY_JOINTS];
    let mut world_pos = [[0.0f64; 3]; BODY_JOINTS];
    for j in 0..BODY_JOINTS {
        // Through f32 axis-angle, as the official code hands float32 to batch_rodrigues.
        let local = smplx_rodrigues(&mat_to_axis_angle(&pose.rotations[j]));
        match usize::try_from(SMPLX_BODY_PARENTS[j]) {
            Err(_) => {
                world_rot[j] = local;
                world_pos[j] = rest[j];
            }
            Ok(p) => {
                let off = [0, 1, 2].map(|k| rest[j][k] - rest[p][k]);
                let r = &world_rot[p];
                world_pos[j] = [0, 1, 2].map(|k| {
                    world_pos[p][k] + r[k][0] * off[0] + r[k][1] * off[1] + r[k][2] * off[2]
                });
                world_rot[j] = mul(r, &local);
            }
        }
    }
    let t = pose.transl.map(f64::from);
    world_pos.map(|p| [0, 1, 2].map(|k| (p[k] + t[k]) as f32))
}

/// Body joints `(T, 22, 3)` of raw LODGE features `(T, 139)` given row-major, from the rest
/// joints of the package.
pub fn features_to_body_joints(
    features: &[f32],
    rest: &[Vec3],
) -> Result<Vec<[Vec3; BODY_JOINTS]>> {
    if !features.len().is_multiple_of(LODGE_FEATURES) {
        return Err(Error::motion(format!(
            "LODGE features: {} values is not a whole number of {LODGE_FEATURES}-value frames",
            features.len()
        )));
    }
    let rest = body_rest_joints(rest)?;
    features
        .chunks_exact(LODGE_FEATURES)
        .map(|frame| Ok(body_joints(&decode_frame(frame)?, &rest)))
        .collect()
}

/// The `skeleton` name of a LODGE dance's motion file: SMPL-X's first 22 joints.
pub const SMPLX22_SKELETON: &str = "smplx22";

/// SMPL's hand joints (22 `left_hand`, 23 `right_hand`; smplx `joint_names.py`
/// `JOINT_NAMES_DICT['smpl']` = SMPL-H's first 22 + the two hands) for a LODGE dance: SMPL-X has
/// no such joint (its joint 22 is `jaw`, its hands are finger joints LODGE never poses), so
/// each hand is placed as SMPL's FK places it: the wrist plus SMPL's own rest wrist→hand bone
/// ([`crate::skeleton::SMPL24_OFFSETS`] 22 / 23, 8.9 cm) turned by the wrist's world rotation
/// (the product of the frame's 6D rotations from the pelvis down the arm). `wrists` are the
/// frame's joints 20 and 21.
pub fn smpl_hands(pose: &LodgePose, wrists: [Vec3; 2]) -> [Vec3; 2] {
    use crate::skeleton::SMPL24_OFFSETS;
    let mut world = [[[0.0f64; 3]; 3]; BODY_JOINTS];
    for j in 0..BODY_JOINTS {
        let local = to_f64(&pose.rotations[j]);
        world[j] = match usize::try_from(SMPLX_BODY_PARENTS[j]) {
            Err(_) => local,
            Ok(p) => mul(&world[p], &local),
        };
    }
    [(20, 22), (21, 23)].map(|(wrist, hand)| {
        let r = &world[wrist];
        let off = SMPL24_OFFSETS[hand].map(f64::from);
        let w = wrists[wrist - 20].map(f64::from);
        [0, 1, 2].map(|k| (w[k] + r[k][0] * off[0] + r[k][1] * off[1] + r[k][2] * off[2]) as f32)
    })
}

#[cfg(test)]
mod tests {
    //! Against values the official code computed (tests/fixtures/lodge_smplx/make_reference.py:
    //! pytorch3d 0.7.5's rotation_conversions.py and LODGE's own `do_smplxfk`, float32, with
    //! random rest joints). Tolerances: the reference runs in float32 (eps 1.2e-7), this code in
    //! f64 rounded to f32; a handful of float32 operations on values of magnitude <= 1 stay within
    //! 2e-6, and the FK chain of up to 8 joints on positions of a few metres within 1e-5 m.
    use super::*;
    use crate::read_npy;
    use std::path::PathBuf;

    fn fixture(name: &str) -> (Vec<f32>, Vec<usize>) {
        let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
            .join("tests/fixtures/lodge_smplx")
            .join(format!("{name}.npy"));
        let a = read_npy(&path).unwrap();
        (a.iter().copied().collect(), a.shape().to_vec())
    }

    fn mats(name: &str) -> Vec<Mat3> {
        let (v, shape) = fixture(name);
        assert_eq!(&shape[1..], &[3, 3]);
        v.chunks_exact(9)
            .map(|m| [[m[0], m[1], m[2]], [m[3], m[4], m[5]], [m[6], m[7], m[8]]])
            .collect()
    }

    fn rows<const N: usize>(name: &str) -> Vec<[f32; N]> {
        let (v, shape) = fixture(name);
        assert_eq!(shape[shape.len() - 1], N);
        v.chunks_exact(N).map(|r| r.try_into().unwrap()).collect()
    }

    /// Largest absolute difference over all rows, and the row where it is.
    fn worst<const N: usize>(got: &[[f32; N]], want: &[[f32; N]]) -> (f32, usize) {
        assert_eq!(got.len(), want.len());
        let mut w = (0.0f32, 0);
        for (i, (g, r)) in got.iter().zip(want).enumerate() {
            for (a, b) in g.iter().zip(r) {
                if (a - b).abs() > w.0 {
                    w = ((a - b).abs(), i);
                }
            }
        }
        w
    }

    fn flat(m: &Mat3) -> [f32; 9] {
        [
            m[0][0], m[0][1], m[0][2], m[1][0], m[1][1], m[1][2], m[2][0], m[2][1], m[2][2],
        ]
    }

    /// |a2| / |a2 orthogonal to a1|: how much Gram–Schmidt amplifies rounding of a 6D.
    fn gram_schmidt_gain(d: &[f32; 6]) -> f64 {
        let a1 = normalize([d[0], d[1], d[2]].map(f64::from));
        let a2 = [d[3], d[4], d[5]].map(f64::from);
        let along = a1[0] * a2[0] + a1[1] * a2[1] + a1[2] * a2[2];
        let norm = |v: [f64; 3]| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        norm(a2) / norm([0, 1, 2].map(|k| a2[k] - along * a1[k]))
    }

    #[test]
    fn rot6d_to_matrix_matches_pytorch3d() {
        let d6 = rows::<6>("rot6d_in");
        let want: Vec<[f32; 9]> = mats("rot6d_mat").iter().map(flat).collect();
        // float32 Gram–Schmidt loses precision as a2 nears a1's direction: the bound scales
        // with that gain (row 79 of the fixture: gain 89, float32 eps x 89 = 1.1e-5, and it
        // differs by 1.0e-5).
        for (i, (d, w)) in d6.iter().zip(&want).enumerate() {
            let got = flat(&rot6d_to_mat(d));
            let bound = 2e-6 * gram_schmidt_gain(d).max(1.0);
            let (diff, _) = worst(&[got], &[*w]);
            assert!(
                f64::from(diff) <= bound,
                "6D -> matrix off by {diff} at row {i} (bound {bound:.2e})"
            );
        }
    }

    #[test]
    fn matrix_to_rot6d_takes_the_first_two_rows() {
        let got: Vec<[f32; 6]> = mats("rot6d_mat").iter().map(mat_to_rot6d).collect();
        assert_eq!(worst(&got, &rows::<6>("mat_rot6d")).0, 0.0);
    }

    #[test]
    fn matrix_to_quaternion_is_the_best_conditioned_candidate_unstandardised() {
        let got: Vec<[f32; 4]> = mats("rot6d_mat").iter().map(mat_to_quat).collect();
        let want = rows::<4>("mat_quat");
        assert!(want.iter().filter(|q| q[0] < 0.0).count() >= 5);
        let (d, i) = worst(&got, &want);
        assert!(
            d <= 2e-6,
            "quaternion off by {d} at row {i}: {:?} vs {:?}",
            got[i],
            want[i]
        );
    }

    #[test]
    fn matrix_to_axis_angle_matches_pytorch3d() {
        let got: Vec<[f32; 3]> = mats("rot6d_mat").iter().map(mat_to_axis_angle).collect();
        let (d, i) = worst(&got, &rows::<3>("mat_axis_angle"));
        // Axis-angle divides by sin(θ/2)/θ, which amplifies float32 rounding of the quaternion by
        // up to ~2π: 1e-5.
        assert!(d <= 1e-5, "axis-angle off by {d} at row {i}");
    }

    #[test]
    fn axis_angle_to_matrix_matches_pytorch3d() {
        let got: Vec<[f32; 9]> = rows::<3>("aa_in")
            .iter()
            .map(|a| flat(&axis_angle_to_mat(a)))
            .collect();
        let want: Vec<[f32; 9]> = mats("aa_mat").iter().map(flat).collect();
        let (d, i) = worst(&got, &want);
        assert!(d <= 2e-6, "axis-angle -> matrix off by {d} at row {i}");
    }

    #[test]
    fn body_joints_match_lodge_fk() {
        let (features, shape) = fixture("fk_features");
        assert_eq!(shape[1], LODGE_FEATURES);
        let rest: Vec<Vec3> = rows::<3>("fk_rest");
        assert_eq!(rest.len(), 55);
        let got: Vec<[f32; 3]> = features_to_body_joints(&features, &rest)
            .unwrap()
            .into_iter()
            .flatten()
            .collect();
        let want = rows::<3>("fk_joints");
        let (d, i) = worst(&got, &want);
        assert!(
            d <= 1e-5,
            "joint {} of frame {} off by {d} m",
            i % BODY_JOINTS,
            i / BODY_JOINTS
        );
        // The pelvis is transl + J0.
        for (f, frame) in features.chunks_exact(LODGE_FEATURES).enumerate() {
            for k in 0..3 {
                let pelvis = got[f * BODY_JOINTS][k];
                assert!((pelvis - (frame[TRANSL + k] + rest[0][k])).abs() <= 1e-6);
            }
        }
    }

    #[test]
    fn bad_frames_and_rest_joints_are_refused() {
        let rest = [[0.0f32; 3]; BODY_JOINTS];
        assert!(features_to_body_joints(&[0.0; LODGE_FEATURES + 1], &rest).is_err());
        let mut frame = [0.0f32; LODGE_FEATURES];
        frame[50] = f32::NAN;
        assert!(features_to_body_joints(&frame, &rest).is_err());
        assert!(features_to_body_joints(&[0.0; LODGE_FEATURES], &rest[..21]).is_err());
        let mut bad = rest;
        bad[3][1] = f32::INFINITY;
        assert!(body_rest_joints(&bad).is_err());
        // Zero 6D is degenerate but finite: the official normalisation's eps keeps it finite.
        let joints = features_to_body_joints(&[0.0; LODGE_FEATURES], &rest).unwrap();
        assert!(joints[0].iter().flatten().all(|v| v.is_finite()));
    }

    /// SMPL's hands: the wrist plus SMPL's rest wrist-to-hand bone turned by the wrist's world
    /// rotation, which the elbow's and the wrist's own rotations both move; worked out by hand
    /// here (a quarter turn about y maps (x, y, z) to (z, y, -x), about z to (-y, x, z)).
    #[test]
    fn smpl_hands_follow_the_wrists_world_rotation() {
        use crate::skeleton::SMPL24_OFFSETS;
        let identity = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        let about_y = [[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]];
        let about_z = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]];
        let mut pose = LodgePose {
            contacts: [0.0; 4],
            transl: [0.0; 3],
            rotations: [identity; BODY_JOINTS],
        };
        let wrists = [[0.7, 1.3, 0.1], [-0.7, 1.2, -0.1]];
        let near = |a: Vec3, b: [f32; 3]| a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-6);
        let (l, r) = (SMPL24_OFFSETS[22], SMPL24_OFFSETS[23]);
        let rest_l = [0, 1, 2].map(|k| wrists[0][k] + l[k]);
        let rest_r = [0, 1, 2].map(|k| wrists[1][k] + r[k]);
        let [hl, hr] = smpl_hands(&pose, wrists);
        assert!(near(hl, rest_l) && near(hr, rest_r), "{hl:?} {hr:?}");
        // The left elbow (18) a quarter turn about y: only the left hand turns.
        pose.rotations[18] = about_y;
        let [hl, hr] = smpl_hands(&pose, wrists);
        let turned = [
            wrists[0][0] + l[2],
            wrists[0][1] + l[1],
            wrists[0][2] - l[0],
        ];
        assert!(near(hl, turned) && near(hr, rest_r), "{hl:?} {hr:?}");
        // Then the left wrist (20) a quarter turn about z: world = about_y · about_z.
        pose.rotations[20] = about_z;
        let [hl, _] = smpl_hands(&pose, wrists);
        // about_z: (x, y, z) -> (-y, x, z); then about_y: (a, b, c) -> (c, b, -a).
        let (a, b, c) = (-l[1], l[0], l[2]);
        let both = [wrists[0][0] + c, wrists[0][1] + b, wrists[0][2] - a];
        assert!(near(hl, both), "{hl:?} vs {both:?}");
    }
}
