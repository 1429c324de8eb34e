//! Foot-contact cleanup: planted feet stay put.
//!
//! Generated and cross-faded motion lets a foot that rests on the floor drift sideways (a
//! cross-fade between two windows whose roots disagree moves the whole body, planted feet
//! included). [`lock_feet`] finds each toe's contacts — below the foot-skating metric's contact
//! height above the motion's floor ([`crate::metrics::foot`]'s GMD rule) and slower than
//! [`PLANTED_SPEED`] — pins the toe's horizontal position to its mean over the contact, moves the
//! ankle with it, and re-solves the knee so that thigh and shin keep their lengths (two-bone
//! inverse kinematics, the knee staying in the plane of hip, ankle and its original position).
//! Around each contact the correction fades in and out over [`EASE_FRAMES`] frames.

use ndarray::Array3;

use crate::metrics::foot::{CONTACT_HEIGHT_M, floor};
use crate::rotation::{Vec3, dot, norm, sub};

/// A toe moving faster than this (m/s) near the floor is stepping or sweeping, not planted:
/// twice the speed above which GMD's metric counts a contact as skating
/// (korrawe/guided-motion-diffusion `data_loaders/humanml/utils/metrics.py:207`,
/// `thresh_vel = 0.50`), so drift up to that speed is removed while floor footwork is kept.
pub const PLANTED_SPEED: f64 = 1.0;
/// Frames over which the correction fades in before a contact and out after it (5 frames =
/// 0.17 s at 30 fps: while the foot is in the air, short enough to finish between steps).
pub const EASE_FRAMES: usize = 5;

/// (hip, knee, ankle, toe) of the left and right leg, SMPL-24 / t2m-22 numbering (both share
/// joints 0-21: Stanford-TML/EDGE `vis.py` `smpl_joints`).
const LEGS: [[usize; 4]; 2] = [[1, 4, 7, 10], [2, 5, 8, 11]];

/// Lock planted feet of `joints` (frames, joints, 3; metres, y-up) sampled at `fps`, in place.
/// Motions with fewer than 12 joints or 2 frames are left as they are.
pub fn lock_feet(joints: &mut Array3<f32>, fps: f64) {
    let (frames, n_joints, _) = joints.dim();
    if frames < 2 || n_joints < 12 || fps.is_nan() || fps <= 0.0 {
        return;
    }
    let floor = floor(joints.view());
    for leg in LEGS {
        let shifts = toe_shifts(joints, leg[3], floor, fps);
        for (f, shift) in shifts.iter().enumerate() {
            if shift[0] != 0.0 || shift[2] != 0.0 {
                solve_leg(joints, f, leg, *shift);
            }
        }
    }
}

/// Per frame, the horizontal shift (x, 0, z) that pins `toe` during its contacts, faded in
/// and out around them.
fn toe_shifts(joints: &Array3<f32>, toe: usize, floor: f64, fps: f64) -> Vec<Vec3> {
    let frames = joints.dim().0;
    let xz = |f: usize| [joints[[f, toe, 0]], joints[[f, toe, 2]]];
    let speed = |a: usize, b: usize| {
        let (p, q) = (xz(a), xz(b));
        f64::from((q[0] - p[0]).hypot(q[1] - p[1])) * fps
    };
    let planted: Vec<bool> = (0..frames)
        .map(|f| {
            let low = f64::from(joints[[f, toe, 1]]) - floor < CONTACT_HEIGHT_M;
            let v = if f + 1 < frames {
                speed(f, f + 1)
            } else {
                speed(f - 1, f)
            };
            low && v < PLANTED_SPEED
        })
        .collect();
    let mut shift = vec![[0f32; 3]; frames];
    let mut weight = vec![0f32; frames];
    let mut f = 0;
    while f < frames {
        if !planted[f] {
            f += 1;
            continue;
        }
        let start = f;
        while f < frames && planted[f] {
            f += 1;
        }
        // A single planted frame has nothing to drift against.
        if f - start < 2 {
            continue;
        }
        let n = (f - start) as f64;
        let anchor =
            [0, 1].map(|c| ((start..f).map(|g| f64::from(xz(g)[c])).sum::<f64>() / n) as f32);
        let pin = |g: usize| {
            let p = xz(g);
            [anchor[0] - p[0], 0.0, anchor[1] - p[1]]
        };
        for g in start..f {
            shift[g] = pin(g);
            weight[g] = 1.0;
        }
        // Fade: the shift at the contact's edge, scaled down linearly away from it; where two
        // fades meet, the nearer contact's wins.
        for e in 1..=EASE_FRAMES {
            let w = 1.0 - e as f32 / (EASE_FRAMES + 1) as f32;
            for (g, edge) in [(start.checked_sub(e), start), (Some(f - 1 + e), f - 1)] {
                if let Some(g) = g.filter(|&g| g < frames && weight[g] < w) {
                    let s = pin(edge);
                    shift[g] = s.map(|v| v * w);
                    weight[g] = w;
                }
            }
        }
    }
    shift
}

/// Move ankle and toe of `leg` at frame `f` by `shift` and put the knee where thigh and shin
/// keep their lengths; an ankle the leg cannot reach is pulled back along the hip–ankle line.
fn solve_leg(joints: &mut Array3<f32>, f: usize, [hip, knee, ankle, toe]: [usize; 4], shift: Vec3) {
    let get = |j: &Array3<f32>, i: usize| [0, 1, 2].map(|c| j[[f, i, c]]);
    let (h, k, a, t) = (
        get(joints, hip),
        get(joints, knee),
        get(joints, ankle),
        get(joints, toe),
    );
    let (thigh, shin) = (norm(sub(k, h)), norm(sub(a, k)));
    let target = [0, 1, 2].map(|c| a[c] + shift[c]);
    let reach = sub(target, h);
    let d = norm(reach);
    if d < 1e-6 || thigh < 1e-6 || shin < 1e-6 {
        return;
    }
    let axis = reach.map(|v| v / d);
    // Keep a hair inside the reachable band so the knee's sine stays real.
    let dist = d.clamp((thigh - shin).abs() + 1e-4, thigh + shin - 1e-4);
    let new_ankle = [0, 1, 2].map(|c| h[c] + axis[c] * dist);
    // The knee bends toward where it was: its offset from the hip with the axis part removed.
    let hk = sub(k, h);
    let along = dot(hk, axis);
    let side = [0, 1, 2].map(|c| hk[c] - along * axis[c]);
    let side_len = norm(side);
    if side_len < 1e-6 {
        return;
    }
    let x = (thigh * thigh - shin * shin + dist * dist) / (2.0 * dist);
    let y = (thigh * thigh - x * x).max(0.0).sqrt();
    let new_knee = [0, 1, 2].map(|c| h[c] + axis[c] * x + side[c] / side_len * y);
    let new_toe = [0, 1, 2].map(|c| new_ankle[c] + t[c] - a[c]);
    for (i, p) in [(knee, new_knee), (ankle, new_ankle), (toe, new_toe)] {
        for c in 0..3 {
            joints[[f, i, c]] = p[c];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array3;

    /// A standing pose (24 joints) at 30 fps whose whole body drifts +x at `speed` m/s, the
    /// left toe resting on the floor and the right foot lifted 0.3 m.
    fn drifting(frames: usize, speed: f32) -> Array3<f32> {
        let mut j = Array3::<f32>::zeros((frames, 24, 3));
        for f in 0..frames {
            let dx = speed * f as f32 / 30.0;
            let mut put = |i: usize, p: [f32; 3]| {
                for c in 0..3 {
                    j[[f, i, c]] = p[c] + if c == 0 { dx } else { 0.0 };
                }
            };
            put(0, [0.0, 0.9, 0.0]);
            put(1, [0.1, 0.85, 0.0]);
            put(2, [-0.1, 0.85, 0.0]);
            put(4, [0.1, 0.47, 0.15]);
            put(5, [-0.1, 0.77, 0.2]);
            put(7, [0.1, 0.08, 0.0]);
            put(8, [-0.1, 0.38, 0.1]);
            put(10, [0.1, 0.0, 0.12]);
            put(11, [-0.1, 0.3, 0.22]);
            for i in [3, 6, 9, 12, 13, 14, 15, 16, 17, 18, 19, 20, 21, 22, 23] {
                put(i, [0.0, 1.0 + 0.02 * i as f32, 0.0]);
            }
        }
        j
    }

    fn dist(j: &Array3<f32>, f: usize, a: usize, b: usize) -> f32 {
        norm(sub(
            [0, 1, 2].map(|c| j[[f, a, c]]),
            [0, 1, 2].map(|c| j[[f, b, c]]),
        ))
    }

    #[test]
    fn a_drifting_planted_toe_is_pinned_with_leg_lengths_kept() {
        let before = drifting(30, 0.3);
        let mut after = before.clone();
        lock_feet(&mut after, 30.0);
        // Pinned to the mean of its drift: every frame at x = 0.1 + 0.3 * 14.5 / 30.
        let anchor = 0.1 + 0.3 * 14.5 / 30.0;
        for f in 0..30 {
            // f32 joint coordinates of order 1 m: 1e-5 m is a few ulps after the IK's sqrt.
            assert!((after[[f, 10, 0]] - anchor).abs() < 1e-5, "frame {f}");
            assert!((after[[f, 10, 2]] - 0.12).abs() < 1e-5);
            assert!((after[[f, 10, 1]] - before[[f, 10, 1]]).abs() < 1e-5);
            for (a, b) in [(1, 4), (4, 7), (7, 10)] {
                assert!((dist(&after, f, a, b) - dist(&before, f, a, b)).abs() < 1e-5);
            }
            // The hip, the lifted right leg and the rest of the body are untouched.
            for i in [0, 1, 2, 5, 8, 11, 15] {
                for c in 0..3 {
                    assert_eq!(after[[f, i, c]], before[[f, i, c]]);
                }
            }
        }
        // At 0.6 m/s GMD's skating ratio counts most steps as skating; after the lock, none.
        let skate = |j: &Array3<f32>| {
            let at20 = crate::resample_joints(j, 30.0, crate::metrics::foot::SKATE_FPS).unwrap();
            crate::metrics::foot::skate_ratio(at20.view())
        };
        let mut fast = drifting(30, 0.6);
        let skated = skate(&fast);
        lock_feet(&mut fast, 30.0);
        assert!(skated > 0.5, "{skated}");
        assert_eq!(skate(&fast), 0.0);
    }

    #[test]
    fn the_floor_is_the_motions_lowest_point_and_an_overstretched_leg_keeps_its_foot() {
        // Lifted 1 m, the same motion is locked the same way: contact is measured from the
        // motion's own floor (as the skating metric measures it), not from y = 0.
        let mut lifted = drifting(30, 0.3);
        lifted
            .slice_mut(ndarray::s![.., .., 1])
            .mapv_inplace(|y| y + 1.0);
        let mut on_floor = drifting(30, 0.3);
        lock_feet(&mut lifted, 30.0);
        lock_feet(&mut on_floor, 30.0);
        for f in 0..30 {
            assert!((lifted[[f, 10, 0]] - on_floor[[f, 10, 0]]).abs() < 1e-5);
        }
        assert_ne!(on_floor, drifting(30, 0.3));
        // A nearly straight leg cannot reach the pinned spot at the ends of a 0.3 m drift: the
        // ankle stops at full reach and the toe stays on the ankle, every bone its length.
        let mut straight = drifting(30, 0.3);
        straight.slice_mut(ndarray::s![.., 4, 2]).fill(0.05);
        let before = straight.clone();
        lock_feet(&mut straight, 30.0);
        let anchor = 0.1 + 0.3 * 14.5 / 30.0;
        assert!(
            (straight[[0, 10, 0]] - anchor).abs() > 1e-3,
            "the test must clamp"
        );
        for f in 0..30 {
            for (a, b) in [(1, 4), (4, 7), (7, 10)] {
                assert!((dist(&straight, f, a, b) - dist(&before, f, a, b)).abs() < 1e-5);
            }
        }
    }

    #[test]
    fn the_correction_fades_over_the_ease_frames_around_a_contact() {
        // The left toe touches down for frames 10-19 only (lifted 0.3 m before and after).
        let mut before = drifting(30, 0.3);
        for f in (0..10).chain(20..30) {
            before[[f, 10, 1]] = 0.3;
        }
        let mut after = before.clone();
        lock_feet(&mut after, 30.0);
        let anchor = 0.1 + 0.3 * 14.5 / 30.0;
        let x = |j: &Array3<f32>, f: usize| j[[f, 10, 0]];
        for e in 1..=EASE_FRAMES {
            let w = 1.0 - e as f32 / (EASE_FRAMES + 1) as f32;
            let (lead, trail) = (10 - e, 19 + e);
            let want_lead = x(&before, lead) + w * (anchor - x(&before, 10));
            let want_trail = x(&before, trail) + w * (anchor - x(&before, 19));
            assert!((x(&after, lead) - want_lead).abs() < 1e-5, "frame {lead}");
            assert!(
                (x(&after, trail) - want_trail).abs() < 1e-5,
                "frame {trail}"
            );
        }
        for f in (0..10 - EASE_FRAMES - 1).chain(20 + EASE_FRAMES..30) {
            assert_eq!(x(&after, f), x(&before, f), "frame {f}");
        }
    }

    #[test]
    fn stepping_and_short_or_tiny_motions_are_left_alone() {
        // 1.5 m/s is a step, not a planted foot.
        let before = drifting(30, 1.5);
        let mut after = before.clone();
        lock_feet(&mut after, 30.0);
        assert_eq!(after, before);
        for mut m in [Array3::<f32>::zeros((1, 24, 3)), Array3::zeros((10, 5, 3))] {
            let copy = m.clone();
            lock_feet(&mut m, 30.0);
            assert_eq!(m, copy);
        }
    }
}
