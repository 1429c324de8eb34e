//! Kinetic features (72 = 24 joints × [horizontal KE, vertical KE, energy expenditure]) as
//! google/aistplusplus_api computes them (`aist_plusplus/features/kinetic.py`,
//! `aist_plusplus/features/utils.py`, commit 2dd7b3e; identical in lisiyao21/Bailando
//! `utils/features/`).
//!
//! Arithmetic follows the reference's dtypes: joint differences in f32 (numpy keeps the
//! float32 positions' dtype), sums in f64 (the reference accumulates into `np.zeros`, f64).

use ndarray::ArrayView3;

/// Frames either side averaged by the velocity and acceleration estimates
/// (kinetic.py:55 `sliding_window=2`).
const SLIDING_WINDOW: usize = 2;

/// Which acceleration formula the energy-expenditure feature uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Acceleration {
    /// As published (utils.py:127-130): `v1 = p[k] - p[k-1] / frame_time`, an operator-precedence
    /// slip that makes the feature depend on absolute position. Kept for comparability.
    ReferenceSlip,
    /// The intended `v1 = (p[k] - p[k-1]) / frame_time`.
    Fixed,
}

/// Kinetic features of `joints` (T, J, 3), y-up: `3 J` values, joint-major
/// (kinetic.py:40-48). `frame_time` is seconds per frame (the reference hard-codes 1/60,
/// kinetic.py:55). Needs at least 3 frames (with fewer the reference divides by zero).
pub fn kinetic_features(joints: ArrayView3<f32>, frame_time: f64, accel: Acceleration) -> Vec<f64> {
    let (t, nj) = (joints.shape()[0], joints.shape()[1]);
    let mut out = Vec::with_capacity(3 * nj);
    let ft32 = frame_time as f32;
    // Logical (T, J, 3) order in one flat buffer: plain indexing in the inner loops.
    let flat: Vec<f32> = joints.iter().copied().collect();
    for j in 0..nj {
        let p = |i: usize, c: usize| flat[(i * nj + j) * 3 + c];
        let (mut ke_h, mut ke_v, mut energy) = (0.0f64, 0.0f64, 0.0f64);
        for i in 1..t {
            // calc_average_velocity_*: frames k = i+w, w in -2..=2, with k-1 >= 0 and k < T
            // (utils.py:141-147).
            let lo = i.saturating_sub(SLIDING_WINDOW).max(1);
            let hi = (i + SLIDING_WINDOW).min(t - 1);
            let mut v = [0.0f64; 3];
            for k in lo..=hi {
                for (c, vc) in v.iter_mut().enumerate() {
                    *vc += f64::from(p(k, c) - p(k - 1, c));
                }
            }
            let scale = (hi - lo + 1) as f64 * frame_time;
            // y-up: horizontal = (x, z), vertical = y (utils.py:148-151, 173-176).
            let h = ((v[0] / scale).powi(2) + (v[2] / scale).powi(2)).sqrt();
            ke_h += h * h;
            let vy = (v[1] / scale).abs();
            ke_v += vy * vy;
            // calc_average_acceleration: k-1 >= 0 and k+1 < T (utils.py:121-133).
            let hi_a = (i + SLIDING_WINDOW).min(t.saturating_sub(2));
            let mut a = [0.0f64; 3];
            let mut n = 0usize;
            for k in lo..=hi_a {
                for (c, ac) in a.iter_mut().enumerate() {
                    let v2 = (p(k + 1, c) - p(k, c)) / ft32;
                    let v1 = match accel {
                        Acceleration::ReferenceSlip => p(k, c) - p(k - 1, c) / ft32,
                        Acceleration::Fixed => (p(k, c) - p(k - 1, c)) / ft32,
                    };
                    *ac += f64::from((v2 - v1) / ft32);
                }
                n += 1;
            }
            let n = n as f64;
            energy += ((a[0] / n).powi(2) + (a[1] / n).powi(2) + (a[2] / n).powi(2)).sqrt();
        }
        let frames = (t - 1) as f64;
        // The reference returns float32 (kinetic.py:49); round the same way.
        out.extend([ke_h / frames, ke_v / frames, energy / frames].map(|v| f64::from(v as f32)));
    }
    out
}
