//! Rigid skeleton poses from joint positions.
//!
//! Generated and stitched motion is not rigid: bone lengths and the spans between sibling joints
//! (left–right shoulder, left–right hip) drift by millimetres from frame to frame, so no
//! rotation-animated armature (BVH, a rig in Blender) reproduces it. [`fit_rigid_pose`] turns
//! per-frame positions into one rigid skeleton: a fixed rest offset per bone and, per frame, a
//! global rotation per joint; forward kinematics of those gives [`RigidPose::joints`], in which
//! every distance between a joint and its children, and between siblings, is constant.
//! [`RigidFitter`] is the same fit a chunk at a time with the offsets fixed from the first chunk
//! (live output); its rotations also drive BVH channels and VMC bones.
//!
//! Rotations are continuous from frame to frame, which is what an animation tool interpolates:
//! - a joint with two or more children takes the best-fit rotation of its rest child offsets onto
//!   the measured ones (Wahba's problem, [`fit_rotation`]);
//! - a joint with one child has a free twist about that bone. It follows the twist that is
//!   smallest relative to the parent (the swing of the rest offset onto the bone in the parent's
//!   frame), but its twist relative to the parent moves toward that by at most
//!   [`MAX_TWIST_STEP`] per frame, so the twist cannot flip where that swing is undefined (bone
//!   opposite its rest direction); a parent's own turn (a spin of the whole body) is carried
//!   along at once;
//! - a leaf joint keeps its parent's rotation.

use ndarray::{Array3, ArrayView3};

use crate::error::{Error, Result};
use crate::rotation::{
    MAT3_IDENTITY, Mat3, Vec3, dot, fit_rotation, mat_mul, mat_to_quat, mat_transpose, mat_vec,
    norm, qbetween_safe, qinv, qmul, qnormalize, qrot, quat_to_mat, sub,
};
use crate::skeleton::{SMPL24_OFFSETS, SkeletonKind, T2M22_RAW_OFFSETS};

/// Largest change of a single-child joint's twist about its bone, relative to its parent,
/// between two frames, radians (3°). Away from the swing singularity the minimal-twist target moves by about as much as the
/// bone swings, well under this at 20–60 fps, so it is followed exactly; at the singularity it
/// can spin by up to 180° in one frame, and this caps what an animation tool would interpolate.
pub const MAX_TWIST_STEP: f32 = 3.0 * std::f32::consts::PI / 180.0;

/// A motion as a rigid skeleton: rest offsets, per-frame global rotations, and the joints they
/// place.
#[derive(Debug, Clone)]
pub struct RigidPose {
    /// Rest offset of each joint from its parent, metres (zero for roots). Directions follow the
    /// skeleton's rest pose (SMPL-24: EDGE's T-pose; t2m-22: HumanML3D's raw directions; custom:
    /// the first frame); lengths and sibling spans are the medians of the frames they were
    /// estimated from.
    pub offsets: Vec<Vec3>,
    /// Global rotation of every joint, frame-major: `rotations[frame * joints + joint]`.
    pub rotations: Vec<Mat3>,
    /// (T, J, 3) forward kinematics of the rotations and offsets from the measured root.
    pub joints: Array3<f32>,
}

impl RigidPose {
    /// Global rotation of `joint` at `frame`.
    pub fn rotation(&self, frame: usize, joint: usize) -> &Mat3 {
        &self.rotations[frame * self.offsets.len() + joint]
    }

    /// Rotation of `joint` at `frame` relative to its parent's (a root's is its global one):
    /// what a BVH channel or a VMC bone message carries.
    pub fn local_rotation(&self, parents: &[i32], frame: usize, joint: usize) -> Mat3 {
        match parents[joint] {
            p if p < 0 => *self.rotation(frame, joint),
            p => mat_mul(
                &mat_transpose(self.rotation(frame, p as usize)),
                self.rotation(frame, joint),
            ),
        }
    }
}

/// Fit a rigid skeleton to joint positions (T, J, 3) of `skeleton`; see the module docs. The root
/// keeps its measured path. Rest offsets are estimated from the motion itself (median bone
/// lengths, median sibling shapes in the joint's fitted frame) rather than taken from a table:
/// generated motion has no body of its own to look up, and the median moves the joints least
/// (an already rigid motion, e.g. SMPL forward kinematics, comes back unchanged).
pub fn fit_rigid_pose(skeleton: &SkeletonKind, joints: ArrayView3<'_, f32>) -> Result<RigidPose> {
    RigidFitter::from_motion(skeleton, joints)?.fit(joints)
}

/// Fits frames to one fixed rigid skeleton, a chunk at a time: the offline fit
/// ([`fit_rigid_pose`]) hands it the whole motion; live output estimates the offsets from its
/// first chunk and fits every later chunk to them, so bone lengths and sibling spans stay the
/// same for the whole session. Rotations continue from the previous chunk's last frame.
#[derive(Debug, Clone)]
pub struct RigidFitter {
    skeleton: SkeletonKind,
    children: Vec<Vec<usize>>,
    offsets: Vec<Vec3>,
    /// Global rotations of the last frame fitted.
    previous: Option<Vec<Mat3>>,
    /// The root's rotation follows its leg children ([`RigidFitter::legs_first`]).
    legs_first: bool,
}

/// Weight of a root's other children beside its legs under [`RigidFitter::legs_first`]: enough
/// to set the one turn the two hips leave open (about the line through them, when they sit on
/// it), too little to move the hips (a 0.3 rad disagreement moves them by ~3e-5 m).
const LEGS_FIRST_WEIGHT: f32 = 1e-3;

impl RigidFitter {
    /// Rest offsets from the frames `joints` (T, J, 3) of `skeleton`: median bone lengths along
    /// the skeleton's rest directions, median sibling shapes.
    pub fn from_motion(skeleton: &SkeletonKind, joints: ArrayView3<'_, f32>) -> Result<Self> {
        check_joints(skeleton, joints)?;
        let pos = |f: usize, k: usize| -> Vec3 {
            [joints[[f, k, 0]], joints[[f, k, 1]], joints[[f, k, 2]]]
        };
        let children = children_of(skeleton.parents());
        let dirs = rest_directions(skeleton, &pos);
        let offsets = rest_offsets(&children, &dirs, &pos, joints.shape()[0]);
        Ok(Self {
            skeleton: skeleton.clone(),
            children,
            offsets,
            previous: None,
            legs_first: false,
        })
    }

    /// Fit the root's rotation to its two hips, the other children (the spine) only breaking
    /// the tie a straight hip line leaves: where the motion's spine leans on its pelvis
    /// differently from the rest shape (a restyled upper body on a content's legs), the legs
    /// and feet stay where they are and the spine's base moves instead. The default (false)
    /// fits all the root's children alike. Only for SMPL-24 and t2m-22 (hips are joints 1, 2);
    /// other skeletons are fitted alike.
    pub fn legs_first(mut self) -> Self {
        self.legs_first = matches!(self.skeleton, SkeletonKind::Smpl24 | SkeletonKind::T2m22);
        self
    }

    /// The fixed rest offsets (see [`RigidPose::offsets`]).
    pub fn offsets(&self) -> &[Vec3] {
        &self.offsets
    }

    /// The rigid pose of the frames `joints` (T, J, 3), continuing the previous call's rotations.
    pub fn fit(&mut self, joints: ArrayView3<'_, f32>) -> Result<RigidPose> {
        check_joints(&self.skeleton, joints)?;
        let parents = self.skeleton.parents();
        let (t, nj) = (joints.shape()[0], joints.shape()[1]);
        let pos = |f: usize, k: usize| -> Vec3 {
            [joints[[f, k, 0]], joints[[f, k, 1]], joints[[f, k, 2]]]
        };
        let offsets = &self.offsets;
        let mut rotations = vec![MAT3_IDENTITY; t * nj];
        let mut out = Array3::<f32>::zeros((t, nj, 3));
        let mut placed = vec![[0.0f64; 3]; nj];
        for f in 0..t {
            for k in 0..nj {
                let inherit = match parents[k] {
                    p if p < 0 => MAT3_IDENTITY,
                    p => rotations[f * nj + p as usize],
                };
                // This joint's and its parent's rotations in the previous frame.
                let prev_frame = match f {
                    0 => self.previous.as_deref(),
                    _ => Some(&rotations[(f - 1) * nj..f * nj]),
                };
                let prev = prev_frame.map(|r| {
                    let parent = match parents[k] {
                        p if p < 0 => MAT3_IDENTITY,
                        p => r[p as usize],
                    };
                    (parent, r[k])
                });
                rotations[f * nj + k] = match self.children[k].as_slice() {
                    [] => inherit,
                    [c] => single_child_rotation(
                        &inherit,
                        prev,
                        offsets[*c],
                        sub(pos(f, *c), pos(f, k)),
                    ),
                    many => {
                        let weight = |c: usize| match parents[k] < 0 && self.legs_first {
                            true if ![1, 2].contains(&c) => LEGS_FIRST_WEIGHT,
                            _ => 1.0,
                        };
                        let rest: Vec<Vec3> = many
                            .iter()
                            .map(|c| offsets[*c].map(|v| v * weight(*c)))
                            .collect();
                        let cur: Vec<Vec3> =
                            many.iter().map(|c| sub(pos(f, *c), pos(f, k))).collect();
                        fit_rotation(&rest, &cur)
                    }
                };
            }
            // Forward kinematics accumulates in f64: in f32 each of up to 9 steps along a chain
            // rounds at the magnitude of the coordinates, which for a body far from the origin
            // is many times the bone's own rounding; this way each joint is rounded once.
            for k in 0..nj {
                placed[k] = match parents[k] {
                    p if p < 0 => pos(f, k).map(f64::from),
                    p => {
                        let p = p as usize;
                        let r = &rotations[f * nj + p];
                        let o = offsets[k];
                        std::array::from_fn(|i| {
                            placed[p][i]
                                + (0..3)
                                    .map(|c| f64::from(r[i][c]) * f64::from(o[c]))
                                    .sum::<f64>()
                        })
                    }
                };
                for (c, v) in placed[k].iter().enumerate() {
                    out[[f, k, c]] = *v as f32;
                }
            }
        }
        if t > 0 {
            self.previous = Some(rotations[(t - 1) * nj..].to_vec());
        }
        Ok(RigidPose {
            offsets: offsets.clone(),
            rotations,
            joints: out,
        })
    }
}

/// Joints (T ≥ 1, J, 3) of `skeleton`, finite.
fn check_joints(skeleton: &SkeletonKind, joints: ArrayView3<'_, f32>) -> Result<()> {
    let sh = joints.shape();
    let nj = skeleton.parents().len();
    if sh[0] == 0 || sh[2] != 3 || sh[1] != nj {
        return Err(Error::motion(format!(
            "joints of shape {sh:?} do not fit skeleton {} ({nj} joints)",
            choreo_dsp::quote(skeleton.name()),
        )));
    }
    skeleton.validate().map_err(Error::motion)?;
    if joints.iter().any(|v| !v.is_finite()) {
        return Err(Error::motion("joint positions contain NaN or infinity"));
    }
    Ok(())
}

/// Children of every joint, in joint order.
pub(crate) fn children_of(parents: &[i32]) -> Vec<Vec<usize>> {
    let mut out = vec![Vec::new(); parents.len()];
    for (c, p) in parents.iter().enumerate() {
        if *p >= 0 {
            out[*p as usize].push(c);
        }
    }
    out
}

/// The rest direction of every bone: the built-in skeletons' T-poses, else the first frame.
fn rest_directions(skeleton: &SkeletonKind, pos: &impl Fn(usize, usize) -> Vec3) -> Vec<Vec3> {
    match skeleton {
        SkeletonKind::Smpl24 => SMPL24_OFFSETS.to_vec(),
        SkeletonKind::T2m22 => T2M22_RAW_OFFSETS.to_vec(),
        SkeletonKind::Custom { parents, .. } => parents
            .iter()
            .enumerate()
            .map(|(k, p)| {
                if *p < 0 {
                    [0.0; 3]
                } else {
                    sub(pos(0, k), pos(0, *p as usize))
                }
            })
            .collect(),
    }
}

/// `v` scaled to `len`, or `fallback` scaled to `len` when `v` has no direction.
fn with_length(v: Vec3, fallback: Vec3, len: f32) -> Vec3 {
    let n = norm(v);
    if n > 1e-9 {
        v.map(|c| c / n * len)
    } else {
        let n = norm(fallback);
        if n > 1e-9 {
            fallback.map(|c| c / n * len)
        } else {
            [0.0, len, 0.0]
        }
    }
}

/// The median of `values` (the upper middle for an even count); `values` is reordered.
fn median(values: &mut [f32]) -> f32 {
    let mid = values.len() / 2;
    *values.select_nth_unstable_by(mid, f32::total_cmp).1
}

/// Rest offsets: for a single child, its median length along the rest direction; for siblings,
/// their median shape in the frame that best fits each frame onto the first, then turned as a
/// whole to best match the rest directions.
fn rest_offsets(
    children: &[Vec<usize>],
    dirs: &[Vec3],
    pos: &impl Fn(usize, usize) -> Vec3,
    t: usize,
) -> Vec<Vec3> {
    let mut offsets = vec![[0.0f32; 3]; children.len()];
    for (k, cs) in children.iter().enumerate() {
        let vectors =
            |f: usize| -> Vec<Vec3> { cs.iter().map(|c| sub(pos(f, *c), pos(f, k))).collect() };
        match cs.as_slice() {
            [] => {}
            [c] => {
                let mut lens: Vec<f32> = (0..t).map(|f| norm(sub(pos(f, *c), pos(f, k)))).collect();
                offsets[*c] = with_length(dirs[*c], vectors(0)[0], median(&mut lens));
            }
            _ => {
                let first = vectors(0);
                let local: Vec<Vec<Vec3>> = (0..t)
                    .map(|f| {
                        let cur = vectors(f);
                        let back = mat_transpose(&fit_rotation(&first, &cur));
                        cur.iter().map(|v| mat_vec(&back, *v)).collect()
                    })
                    .collect();
                // The median shape, each vector at its bone's median length: a component-wise
                // median of vectors that turn a little against each other is shorter than any
                // of them, and bone lengths are the medians the module promises.
                let shape: Vec<Vec3> = (0..cs.len())
                    .map(|i| {
                        let s = [0, 1, 2].map(|a| {
                            let mut comp: Vec<f32> = local.iter().map(|l| l[i][a]).collect();
                            median(&mut comp)
                        });
                        let mut lens: Vec<f32> = local.iter().map(|l| norm(l[i])).collect();
                        with_length(s, first[i], median(&mut lens))
                    })
                    .collect();
                let goal: Vec<Vec3> = cs
                    .iter()
                    .zip(&shape)
                    .map(|(c, s)| with_length(dirs[*c], *s, norm(*s)))
                    .collect();
                let turn = fit_rotation(&shape, &goal);
                for (c, s) in cs.iter().zip(&shape) {
                    offsets[*c] = mat_vec(&turn, *s);
                }
            }
        }
    }
    offsets
}

/// Global rotation of a joint with one child whose rest offset is `rest` and whose measured bone
/// is `cur`: the twist smallest relative to the parent's rotation `inherit`, approached from the
/// previous frame's twist relative to the parent by at most [`MAX_TWIST_STEP`]. `prev`: the
/// parent's and this joint's rotations in the previous frame. Works in the parent's frame, so
/// the parent's own turn never counts as twist.
fn single_child_rotation(
    inherit: &Mat3,
    prev: Option<(Mat3, Mat3)>,
    rest: Vec3,
    cur: Vec3,
) -> Mat3 {
    // Local rotations as unit quaternions: the previous frame's is re-normalised here, so f32
    // rounding cannot build up from frame to frame.
    let prev_local =
        prev.map(|(parent, own)| qnormalize(mat_to_quat(&mat_mul(&mat_transpose(&parent), &own))));
    let len = norm(cur);
    if len < 1e-9 || norm(rest) < 1e-9 {
        return mat_mul(
            inherit,
            &quat_to_mat(prev_local.unwrap_or([1.0, 0.0, 0.0, 0.0])),
        );
    }
    let cur = mat_vec(&mat_transpose(inherit), cur);
    let target = qbetween_safe(rest, cur);
    let Some(prev) = prev_local else {
        return mat_mul(inherit, &quat_to_mat(target));
    };
    // The previous local rotation carried along the bone's swing: no twist about the bone.
    let carried = qnormalize(qmul(qbetween_safe(qrot(prev, rest), cur), prev));
    // Both map `rest` onto `cur`, so they differ by a rotation about the bone axis d.
    let d = cur.map(|c| c / len);
    let q = qmul(target, qinv(carried));
    let mut theta = 2.0 * dot([q[1], q[2], q[3]], d).atan2(q[0]);
    if theta > std::f32::consts::PI {
        theta -= 2.0 * std::f32::consts::PI;
    } else if theta < -std::f32::consts::PI {
        theta += 2.0 * std::f32::consts::PI;
    }
    let half = 0.5 * theta.clamp(-MAX_TWIST_STEP, MAX_TWIST_STEP);
    let (s, c) = half.sin_cos();
    let local = qnormalize(qmul([c, d[0] * s, d[1] * s, d[2] * s], carried));
    mat_mul(inherit, &quat_to_mat(local))
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::AistppMotion;
    use ndarray::{Array2, Axis};

    fn fixture() -> AistppMotion {
        let p = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../shared/fixtures/motion/aistpp_gBR_sBM_cAll_d04_mBR0_ch01.pkl");
        AistppMotion::read(&p).unwrap()
    }

    /// Rotation angle of `b · aᵀ`, degrees.
    fn angle_between(a: &Mat3, b: &Mat3) -> f32 {
        let m = mat_mul(b, &mat_transpose(a));
        let c = ((m[0][0] + m[1][1] + m[2][2] - 1.0) * 0.5).clamp(-1.0, 1.0);
        c.acos().to_degrees()
    }

    /// Largest frame-to-frame rotation of each joint, degrees.
    fn max_steps(t: usize, nj: usize, rot: impl Fn(usize, usize) -> Mat3) -> Vec<f32> {
        (0..nj)
            .map(|k| {
                (1..t)
                    .map(|f| angle_between(&rot(f - 1, k), &rot(f, k)))
                    .fold(0.0, f32::max)
            })
            .collect()
    }

    fn max_abs_diff(a: &Array3<f32>, b: &Array3<f32>) -> f32 {
        a.iter()
            .zip(b.iter())
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max)
    }

    /// Largest change over the frames of the distance between joints `a` and `b`, metres.
    fn span_variation(j: &Array3<f32>, a: usize, b: usize) -> f32 {
        let d: Vec<f32> = j
            .axis_iter(Axis(0))
            .map(|f| {
                norm(sub(
                    [f[[a, 0]], f[[a, 1]], f[[a, 2]]],
                    [f[[b, 0]], f[[b, 1]], f[[b, 2]]],
                ))
            })
            .collect();
        d.iter().fold(f32::MIN, |m, v| m.max(*v)) - d.iter().fold(f32::MAX, |m, v| m.min(*v))
    }

    /// Every joint–child and sibling–sibling pair of SMPL-24.
    fn rigid_pairs() -> Vec<(usize, usize)> {
        let children = children_of(&crate::skeleton::SMPL24_PARENTS);
        let mut pairs = Vec::new();
        for (k, cs) in children.iter().enumerate() {
            for (i, a) in cs.iter().enumerate() {
                pairs.push((k, *a));
                pairs.extend(cs[i + 1..].iter().map(|b| (*a, *b)));
            }
        }
        pairs
    }

    #[test]
    fn rigid_motion_comes_back_unchanged() {
        let a = fixture();
        let j = a.joints();
        let fit = fit_rigid_pose(&SkeletonKind::Smpl24, j.view()).unwrap();
        // f32 rotations along chains of up to 9 bones of < 0.5 m: a few 1e-7 m per step.
        let d = max_abs_diff(&fit.joints, &j);
        assert!(d < 1e-5, "moved by {d} m");
        for (k, o) in fit.offsets.iter().enumerate() {
            let e = norm(sub(*o, SMPL24_OFFSETS[k]));
            assert!(
                e < 1e-5,
                "joint {k}: offset {o:?} vs {:?}",
                SMPL24_OFFSETS[k]
            );
        }
    }

    #[test]
    fn non_rigid_spans_become_constant() {
        let j = fixture().joints();
        // Shoulders and hips drift apart and together by ±6.5 mm along the line joining them
        // (13 mm spans, as stitched dances do): whole limbs slide, so their own bones stay intact.
        let across = |f: usize, l: usize, r: usize| -> Vec3 {
            let d = sub(
                [j[[f, r, 0]], j[[f, r, 1]], j[[f, r, 2]]],
                [j[[f, l, 0]], j[[f, l, 1]], j[[f, l, 2]]],
            );
            d.map(|c| c / norm(d))
        };
        let left_arm = [16, 18, 20, 22];
        let right_arm = [17, 19, 21, 23];
        let left_leg = [1, 4, 7, 10];
        let mut wobbly = j.clone();
        let mut biggest = 0.0f32;
        for f in 0..j.shape()[0] {
            let d = 0.0065 * (0.37 * f as f32).cos();
            let e = 0.0065 * (0.23 * f as f32 + 1.0).cos();
            biggest = biggest.max(d.abs()).max(e.abs());
            let (arms, hips) = (across(f, 16, 17), across(f, 1, 2));
            for c in 0..3 {
                left_arm
                    .iter()
                    .for_each(|k| wobbly[[f, *k, c]] -= d * arms[c]);
                right_arm
                    .iter()
                    .for_each(|k| wobbly[[f, *k, c]] += d * arms[c]);
                left_leg
                    .iter()
                    .for_each(|k| wobbly[[f, *k, c]] -= e * hips[c]);
            }
        }
        assert!(span_variation(&wobbly, 16, 17) > 0.012 && span_variation(&wobbly, 1, 2) > 0.006);
        let fit = fit_rigid_pose(&SkeletonKind::Smpl24, wobbly.view()).unwrap();
        for (a, b) in rigid_pairs() {
            // f32 forward kinematics: 1e-5 m, three orders below the perturbation.
            let v = span_variation(&fit.joints, a, b);
            assert!(v < 1e-5, "span {a}-{b} varies by {v} m");
        }
        // The slides swing evenly about zero, so the median rest offsets are the true ones
        // (measured 0.08 mm off; frame 0 alone, slid by 6.5 mm, gives 5.9 mm): 0.5 mm.
        let off = (0..24)
            .map(|k| norm(sub(fit.offsets[k], SMPL24_OFFSETS[k])))
            .fold(0.0f32, f32::max);
        assert!(off < 5e-4, "rest offsets {off} m from the truth");
        // Sliding a limb back moves each of its joints by at most the slide, so the rigid pose
        // stays within the perturbation of the true motion (1e-4 m for the median lengths).
        let d = max_abs_diff(&fit.joints, &j);
        assert!(
            d <= biggest + 1e-4,
            "moved {d} m from the truth, perturbation {biggest} m"
        );
    }

    /// A smooth synthetic dance through SMPL forward kinematics, sampled at frames `f + shift`:
    /// every joint swings by up to ±2.5 rad about all three axes, so forearms and hands pass
    /// through the directions opposite their rest pose where a shortest-arc swing flips.
    pub(crate) fn swinging_motion(shift: f32) -> (Array3<f32>, ndarray::Array4<f32>) {
        let t = 600;
        let poses = Array3::from_shape_fn((t, 24, 3), |(f, k, c)| {
            let amp = if k == 0 { 0.5 } else { 2.5 };
            let time = f as f32 + shift;
            amp * (0.01 * time * (1.0 + 0.13 * k as f32) + 0.7 * c as f32 + 0.3 * k as f32).sin()
        });
        let root = Array2::from_shape_fn((t, 3), |(f, c)| {
            if c == 1 {
                0.9
            } else {
                0.001 * (f as f32 + shift)
            }
        });
        smpl_fk(&poses, &root)
    }

    fn smpl_fk(poses: &Array3<f32>, root: &Array2<f32>) -> (Array3<f32>, ndarray::Array4<f32>) {
        crate::smpl_forward_kinematics(poses, root)
    }

    /// Largest frame-to-frame rotation of each SMPL-24 joint the fit may make, given the true
    /// motion's (`real`, degrees). Ours differs from the truth by a twist relative to the parent
    /// at the joint and at each single-child joint above it, each changing by at most
    /// MAX_TWIST_STEP per frame; 1° more for the bone axes turning under them.
    fn continuity_bounds(real: &[f32]) -> Vec<f32> {
        let parents = crate::skeleton::SMPL24_PARENTS;
        let children = children_of(&parents);
        (0..24)
            .map(|k| {
                let mut twisted = 0;
                let mut j = k as i32;
                while j >= 0 {
                    twisted += usize::from(children[j as usize].len() == 1);
                    j = parents[j as usize];
                }
                real[k] + twisted as f32 * MAX_TWIST_STEP.to_degrees() + 1.0
            })
            .collect()
    }

    #[test]
    fn rotations_stay_continuous() {
        let (j, truth) = swinging_motion(0.0);
        let (t, nj) = (j.shape()[0], j.shape()[1]);
        let fit = fit_rigid_pose(&SkeletonKind::Smpl24, j.view()).unwrap();
        assert!(max_abs_diff(&fit.joints, &j) < 1e-4);
        let true_mat = |f: usize, k: usize| -> Mat3 {
            std::array::from_fn(|r| std::array::from_fn(|c| truth[[f, k, r, c]]))
        };
        let ours = max_steps(t, nj, |f, k| *fit.rotation(f, k));
        let real = max_steps(t, nj, true_mat);
        let bounds = continuity_bounds(&real);
        for k in 0..nj {
            let bound = bounds[k];
            assert!(
                ours[k] <= bound,
                "joint {k}: {}° per frame, bound {bound}°",
                ours[k]
            );
        }
        // The fixture: real dancing at 60 fps.
        let a = fixture();
        let (j, truth) = smpl_fk(&a.poses, &a.root_positions());
        let fit = fit_rigid_pose(&SkeletonKind::Smpl24, j.view()).unwrap();
        let true_mat = |f: usize, k: usize| -> Mat3 {
            std::array::from_fn(|r| std::array::from_fn(|c| truth[[f, k, r, c]]))
        };
        let ours = max_steps(j.shape()[0], nj, |f, k| *fit.rotation(f, k));
        let real = max_steps(j.shape()[0], nj, true_mat);
        let bounds = continuity_bounds(&real);
        for k in 0..nj {
            let bound = bounds[k];
            assert!(
                ours[k] <= bound,
                "fixture joint {k}: {}° per frame, bound {bound}°",
                ours[k]
            );
        }
    }

    #[test]
    fn chunks_fitted_one_by_one_equal_one_fit_with_the_same_offsets() {
        // The swinging motion passes forearms through the twist singularity, where only the
        // carried rotation of the previous frame keeps the twist continuous: a chunk that forgot
        // the previous chunk's last frame would start from the raw swing and differ.
        let (j, _) = swinging_motion(0.0);
        let first = j.slice(ndarray::s![..15, .., ..]);
        let mut whole = RigidFitter::from_motion(&SkeletonKind::Smpl24, first).unwrap();
        let mut chunked = whole.clone();
        let all = whole.fit(j.view()).unwrap();
        let mut frames = 0;
        for chunk in j.axis_chunks_iter(Axis(0), 15) {
            let part = chunked.fit(chunk).unwrap();
            let want = all
                .joints
                .slice(ndarray::s![frames..frames + chunk.shape()[0], .., ..]);
            let d = part
                .joints
                .iter()
                .zip(want.iter())
                .map(|(a, b)| (a - b).abs())
                .fold(0.0f32, f32::max);
            // Same arithmetic in the same order: identical.
            assert_eq!(d, 0.0, "chunk at frame {frames}");
            frames += chunk.shape()[0];
        }
    }

    #[test]
    fn offsets_fixed_from_the_first_chunk_hold_for_the_whole_motion() {
        // Bones that stretch by up to ±1 cm over the motion (generated output drifts like this):
        // every bone of the fit keeps the first chunk's length.
        let (j, _) = swinging_motion(0.0);
        let mut stretched = j.clone();
        let parents = crate::skeleton::SMPL24_PARENTS;
        for f in 0..j.shape()[0] {
            for k in 1..24 {
                // Scale each joint's offset from its parent, outward from the root: a child
                // moves with its parent's shift plus its own bone's stretch.
                let p = parents[k] as usize;
                let scale = 1.0 + 0.04 * (0.05 * f as f32 + k as f32).sin();
                for c in 0..3 {
                    let bone = j[[f, k, c]] - j[[f, p, c]];
                    stretched[[f, k, c]] = stretched[[f, p, c]] + bone * scale;
                }
            }
        }
        let bone_len = |m: &Array3<f32>, f: usize, k: usize| {
            let p = parents[k] as usize;
            norm(sub(
                [m[[f, k, 0]], m[[f, k, 1]], m[[f, k, 2]]],
                [m[[f, p, 0]], m[[f, p, 1]], m[[f, p, 2]]],
            ))
        };
        let spread = (1..24)
            .map(|k| span_variation(&stretched, parents[k] as usize, k))
            .fold(0.0f32, f32::max);
        assert!(spread > 0.01, "the input stretches: {spread} m");
        let mut fitter = RigidFitter::from_motion(
            &SkeletonKind::Smpl24,
            stretched.slice(ndarray::s![..15, .., ..]),
        )
        .unwrap();
        let lengths: Vec<f32> = fitter.offsets().iter().map(|o| norm(*o)).collect();
        for chunk in stretched.axis_chunks_iter(Axis(0), 15) {
            let fit = fitter.fit(chunk).unwrap();
            for f in 0..chunk.shape()[0] {
                for (k, len) in lengths.iter().enumerate().skip(1) {
                    let d = (bone_len(&fit.joints, f, k) - len).abs();
                    // f32 forward kinematics: a few 1e-7 m.
                    assert!(d < 1e-5, "bone {k} off its fixed length by {d} m");
                }
            }
        }
        // One chunk with another body (every bone 10 % longer) is still fitted, not refused.
        let longer = stretched.slice(ndarray::s![..15, .., ..]).mapv(|v| v * 1.1);
        let fit = fitter.fit(longer.view()).unwrap();
        assert!((bone_len(&fit.joints, 0, 18) - lengths[18]).abs() < 1e-5);
    }

    #[test]
    fn bad_input_is_an_error() {
        let z = Array3::<f32>::zeros((3, 22, 3));
        assert!(fit_rigid_pose(&SkeletonKind::Smpl24, z.view()).is_err());
        assert!(fit_rigid_pose(&SkeletonKind::T2m22, Array3::zeros((0, 22, 3)).view()).is_err());
        let mut n = Array3::<f32>::zeros((3, 22, 3));
        n[[1, 3, 2]] = f32::INFINITY;
        assert!(fit_rigid_pose(&SkeletonKind::T2m22, n.view()).is_err());
        // Degenerate but finite (every joint at one point): a pose, not a panic.
        assert!(fit_rigid_pose(&SkeletonKind::T2m22, z.view()).is_ok());
    }
}
