//! Physical plausibility: EDGE's Physical Foot Contact score, GMD's foot-skating ratio, and the
//! style-transfer measures of MCM-LDM (§5.1) — foot sliding (FSF) and trajectory similarity
//! (TSI) — with the exact definitions chosen here. Joints are y-up metres; feet are SMPL /
//! t2m joints 7, 8 (ankles) and 10, 11 (toes).

use ndarray::ArrayView3;

/// Frame rate PFC is scored at: EDGE's motions are 30 fps (eval_pfc.py:16 `DT = 1 / 30`).
pub const PFC_FPS: f32 = 30.0;
/// Frame rate of GMD's skating ratio and of FSF / TSI: HumanML3D's 20 fps
/// (korrawe/guided-motion-diffusion `data_loaders/humanml/utils/metrics.py:206`).
pub const SKATE_FPS: f32 = 20.0;
/// A foot is in contact when it is below this height above the floor in two adjacent frames
/// (metrics.py:205 `thresh_height = 0.05`, :220).
pub const CONTACT_HEIGHT_M: f64 = 0.05;
/// Skating speed threshold, m/s (metrics.py:207 `thresh_vel = 0.50`).
const SKATE_SPEED: f64 = 0.5;
/// Moving-average window of the speed, frames (metrics.py:208 `avg_window = 5`).
const SKATE_WINDOW: usize = 5;
/// Toe joints (metrics.py:211 "10 left, 11 right foot").
const TOES: [usize; 2] = [10, 11];

/// EDGE's PFC of one motion at 30 fps (Stanford-TML/EDGE `eval/eval_pfc.py:24-45`, commit
/// 17c3428) times 10000 (line 50): mean over frames of
/// min(‖v_lankle‖, ‖v_ltoe‖) · min(‖v_rankle‖, ‖v_rtoe‖) · ‖a_root‖ / max‖a_root‖, horizontal
/// foot displacement per frame, root acceleration with its up component clamped at ≥ 0.
/// EDGE's data is z-up; here the up axis is y. A root that never accelerates scores 0 (the
/// reference divides 0 by 0). Needs at least 3 frames.
pub fn pfc(joints: ArrayView3<f32>) -> f64 {
    let t = joints.shape()[0];
    let dt = 1.0 / f64::from(PFC_FPS);
    let p = |i: usize, j: usize, c: usize| f64::from(joints[[i, j, c]]);
    let root_a: Vec<f64> = (0..t - 2)
        .map(|i| {
            let a = |c: usize| {
                ((p(i + 2, 0, c) - p(i + 1, 0, c)) / dt - (p(i + 1, 0, c) - p(i, 0, c)) / dt) / dt
            };
            let (ax, ay, az) = (a(0), a(1).max(0.0), a(2));
            (ax * ax + ay * ay + az * az).sqrt()
        })
        .collect();
    let max_a = root_a.iter().copied().fold(0.0, f64::max);
    if max_a == 0.0 {
        return 0.0;
    }
    let horiz = |i: usize, j: usize| {
        let (dx, dz) = (p(i + 1, j, 0) - p(i, j, 0), p(i + 1, j, 2) - p(i, j, 2));
        (dx * dx + dz * dz).sqrt()
    };
    // foot_v[k] uses frames k+1 → k+2 (eval_pfc.py:35-37), paired with root_a[k].
    let sum: f64 = (0..t - 2)
        .map(|k| {
            let left = horiz(k + 1, 7).min(horiz(k + 1, 10));
            let right = horiz(k + 1, 8).min(horiz(k + 1, 11));
            left * right * root_a[k] / max_a
        })
        .sum();
    sum / (t - 2) as f64 * 10000.0
}

/// The floor height: the lowest joint over the whole motion, as HumanML3D's processing places
/// the floor (EricGuo5513/HumanML3D `motion_representation.ipynb`, `floor_height =
/// positions.min(axis=0).min(axis=0)[1]`).
pub(crate) fn floor(joints: ArrayView3<f32>) -> f64 {
    joints
        .slice(ndarray::s![.., .., 1])
        .iter()
        .fold(f64::INFINITY, |m, &y| m.min(f64::from(y)))
}

/// Per toe, per frame step t → t+1: in contact (below 5 cm above the floor in both frames).
fn contacts(joints: ArrayView3<f32>) -> [Vec<bool>; 2] {
    let t = joints.shape()[0];
    let base = floor(joints);
    TOES.map(|toe| {
        (0..t - 1)
            .map(|i| {
                f64::from(joints[[i, toe, 1]]) - base < CONTACT_HEIGHT_M
                    && f64::from(joints[[i + 1, toe, 1]]) - base < CONTACT_HEIGHT_M
            })
            .collect()
    })
}

/// Horizontal displacement of a joint per frame step, metres.
fn steps(joints: ArrayView3<f32>, j: usize) -> Vec<f64> {
    (0..joints.shape()[0] - 1)
        .map(|i| {
            let dx = f64::from(joints[[i + 1, j, 0]]) - f64::from(joints[[i, j, 0]]);
            let dz = f64::from(joints[[i + 1, j, 2]]) - f64::from(joints[[i, j, 2]]);
            (dx * dx + dz * dz).sqrt()
        })
        .collect()
}

/// GMD's foot-skating ratio of one motion at 20 fps (`calculate_skating_ratio`,
/// metrics.py:204-231, commit 2f6264a): the fraction of frame steps in which either toe is in
/// contact and moves faster than 0.5 m/s both in that step and on a 5-step moving average
/// (`uniform_filter1d(size=5, mode='constant')`, zeros past the ends). Heights are measured
/// from [`floor`] (GMD's data already has its floor at 0). Needs at least 2 frames.
pub fn skate_ratio(joints: ArrayView3<f32>) -> f64 {
    let n = joints.shape()[0] - 1;
    let fps = f64::from(SKATE_FPS);
    let contact = contacts(joints);
    let mut skating = vec![false; n];
    for (k, &toe) in TOES.iter().enumerate() {
        let speed: Vec<f64> = steps(joints, toe).iter().map(|d| d * fps).collect();
        let half = (SKATE_WINDOW / 2) as i64;
        for i in 0..n {
            let avg: f64 = (i as i64 - half..=i as i64 + half)
                .filter(|&m| m >= 0 && (m as usize) < n)
                .map(|m| speed[m as usize])
                .sum::<f64>()
                / SKATE_WINDOW as f64;
            skating[i] |= contact[k][i] && speed[i] > SKATE_SPEED && avg > SKATE_SPEED;
        }
    }
    skating.iter().filter(|&&s| s).count() as f64 / n as f64
}

/// Foot sliding (FSF, MCM-LDM §5.1 "foot sliding displacement during ground contact"), as
/// defined here: at 20 fps, the mean horizontal displacement (metres) of a toe over the frame
/// steps in which it is in contact (the contact rule of [`skate_ratio`]); 0 when no foot ever
/// touches the floor.
pub fn foot_sliding(joints: ArrayView3<f32>) -> f64 {
    let contact = contacts(joints);
    let (mut sum, mut count) = (0.0, 0usize);
    for (k, &toe) in TOES.iter().enumerate() {
        for (d, &c) in steps(joints, toe).iter().zip(&contact[k]) {
            if c {
                sum += d;
                count += 1;
            }
        }
    }
    if count == 0 { 0.0 } else { sum / count as f64 }
}

/// Trajectory similarity (TSI, MCM-LDM §5.1 "Euclidean distance between the stylized and
/// content trajectories"), as defined here: at 20 fps, over the frames both motions have, the
/// mean distance (metres) between their ground-plane root positions (x, z), each trajectory
/// taken relative to its own first frame.
pub fn trajectory_distance(stylized: ArrayView3<f32>, content: ArrayView3<f32>) -> f64 {
    let t = stylized.shape()[0].min(content.shape()[0]);
    let rel =
        |m: ArrayView3<f32>, i: usize, c: usize| f64::from(m[[i, 0, c]]) - f64::from(m[[0, 0, c]]);
    let sum: f64 = (0..t)
        .map(|i| {
            let dx = rel(stylized, i, 0) - rel(content, i, 0);
            let dz = rel(stylized, i, 2) - rel(content, i, 2);
            (dx * dx + dz * dz).sqrt()
        })
        .sum();
    sum / t as f64
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array3;

    /// 21 frames of 24 joints at 1 m height, toes (10, 11) given per frame.
    fn motion(toe: impl Fn(usize) -> [f32; 3], root: impl Fn(usize) -> [f32; 3]) -> Array3<f32> {
        let mut m = Array3::<f32>::from_elem((21, 24, 3), 1.0);
        for i in 0..21 {
            for (c, v) in toe(i).iter().enumerate() {
                m[[i, 10, c]] = *v;
                m[[i, 11, c]] = *v;
            }
            for (c, v) in root(i).iter().enumerate() {
                m[[i, 0, c]] = *v;
            }
        }
        m
    }

    #[test]
    fn foot_sliding_is_the_contact_displacement_per_step() {
        // Toes on the floor sliding 1 cm per step along x: FSF 0.01 m; lifted 10 cm: 0.
        let sliding = motion(|i| [0.01 * i as f32, 0.0, 0.0], |_| [0.0, 1.0, 0.0]);
        assert!((foot_sliding(sliding.view()) - 0.01).abs() < 1e-6);
        // 1 cm per step at 20 fps is 0.2 m/s: under GMD's 0.5 m/s, not skating.
        assert_eq!(skate_ratio(sliding.view()), 0.0);
        let fast = motion(|i| [0.0375 * i as f32, 0.0, 0.0], |_| [0.0, 1.0, 0.0]);
        // 0.75 m/s: every step skates except the first and last, where the 5-step average
        // (zeros past the ends) is 3 · 0.75 / 5 = 0.45 m/s.
        assert!((skate_ratio(fast.view()) - 18.0 / 20.0).abs() < 1e-12);
        let lifted = motion(|i| [0.01 * i as f32, 0.1, 0.0], |_| [0.0, 0.0, 0.0]);
        assert_eq!(foot_sliding(lifted.view()), 0.0);
    }

    #[test]
    fn trajectory_distance_compares_paths_from_their_starts() {
        let still = motion(|_| [0.0; 3], |_| [3.0, 1.0, 4.0]);
        let walk = motion(|_| [0.0; 3], |i| [0.1 * i as f32, 1.0, 0.0]);
        assert_eq!(trajectory_distance(still.view(), still.view()), 0.0);
        // Distances 0, 0.1, ..., 2.0 m: mean 1.0 m; the start offset (3, 4) does not count.
        assert!((trajectory_distance(walk.view(), still.view()) - 1.0).abs() < 1e-6);
    }
}
