//! Beat Alignment Score in its two incompatible published conventions.
//!
//! - [`bas_motion_beats`]: AIST++ / FACT, google-research/mint `tools/calculate_beat_scores.py`
//!   (commit 83d64b9): averaged over *motion* beats.
//! - [`bas_music_beats`]: lisiyao21/Bailando `utils/beat_align_score.py` (commit cc90b98),
//!   used by MoFusion's Table 1: averaged over *music* beats.
//!
//! Both take beats as frame indices at the motion's rate; σ is 3 *frames* in both, so the
//! tolerance in seconds depends on the frame rate the motion is scored at (50 ms at 60 fps).

use ndarray::ArrayView3;

/// σ of the Gaussian score, frames (calculate_beat_scores.py:114 `sigma=3`;
/// beat_align_score.py:54 `/ 2 / 9`).
pub const BEAT_SIGMA_FRAMES: f64 = 3.0;
/// Neighbourhood of a kinematic beat in mint, frames (calculate_beat_scores.py:103
/// `order=10  # 10 for 60FPS`).
const MINT_ORDER: usize = 10;
/// σ of Bailando's smoothing of the kinematic envelope, frames (beat_align_score.py:46 `G(·, 5)`).
const BAILANDO_SMOOTH_SIGMA: f64 = 5.0;

/// Kinematic beats as mint finds them: local minima (order 10) of Σ_joints ‖p_t − p_{t−1}‖ with
/// velocity 0 at frame 0 (calculate_beat_scores.py:89-111). Indices in `0..T`.
pub fn mint_motion_beats(joints: ArrayView3<f32>) -> Vec<usize> {
    let t = joints.shape()[0];
    let mut env = vec![0.0f32; t];
    for (i, e) in env.iter_mut().enumerate().skip(1) {
        // f32 as the reference's `np.zeros_like(joints, dtype=np.float32)`.
        *e = (0..joints.shape()[1])
            .map(|j| {
                let d = |c: usize| joints[[i, j, c]] - joints[[i - 1, j, c]];
                (d(0) * d(0) + d(1) * d(1) + d(2) * d(2)).sqrt()
            })
            .sum();
    }
    local_minima(&env, MINT_ORDER)
}

/// Kinematic beats as Bailando finds them: local minima (order 1) of the Gaussian-smoothed
/// (σ 5 frames) mean over joints of ‖p_{t+1} − p_t‖ (beat_align_score.py:43-48). Indices in
/// `0..T−1`.
pub fn bailando_motion_beats(joints: ArrayView3<f32>) -> Vec<usize> {
    let (t, nj) = (joints.shape()[0], joints.shape()[1]);
    let env: Vec<f64> = (1..t)
        .map(|i| {
            (0..nj)
                .map(|j| {
                    let d =
                        |c: usize| f64::from(joints[[i, j, c]]) - f64::from(joints[[i - 1, j, c]]);
                    (d(0) * d(0) + d(1) * d(1) + d(2) * d(2)).sqrt()
                })
                .sum::<f64>()
                / nj as f64
        })
        .collect();
    local_minima(&gaussian_filter(&env, BAILANDO_SMOOTH_SIGMA), 1)
}

/// mint's `alignment_score`: mean over motion beats of exp(−d²/2σ²), d the distance to the
/// nearest music beat (calculate_beat_scores.py:114-126); 0 when there are no motion beats
/// (line 116). `None` when there are motion beats but no music beat (the reference's
/// `argmin` of an empty array raises).
pub fn bas_motion_beats(music: &[usize], motion: &[usize]) -> Option<f64> {
    if motion.is_empty() {
        return Some(0.0);
    }
    nearest_score_mean(motion, music)
}

/// Bailando's `BA`: mean over music beats of exp(−d²/2σ²), d the distance to the nearest
/// motion beat (beat_align_score.py:51-55). `None` when either list is empty (the reference
/// raises or divides by zero).
pub fn bas_music_beats(music: &[usize], motion: &[usize]) -> Option<f64> {
    nearest_score_mean(music, motion)
}

fn nearest_score_mean(over: &[usize], to: &[usize]) -> Option<f64> {
    if over.is_empty() || to.is_empty() {
        return None;
    }
    let sum: f64 = over
        .iter()
        .map(|&a| {
            let d = to.iter().map(|&b| a.abs_diff(b)).min().unwrap_or(0) as f64;
            (-d * d / (2.0 * BEAT_SIGMA_FRAMES * BEAT_SIGMA_FRAMES)).exp()
        })
        .sum();
    Some(sum / over.len() as f64)
}

/// `scipy.signal.argrelextrema(x, np.less, order)`: indices strictly below every neighbour
/// within `order`, neighbours past the ends clipped to the end value (mode 'clip'), so the
/// first and last samples are never minima.
fn local_minima<T: PartialOrd + Copy>(x: &[T], order: usize) -> Vec<usize> {
    let n = x.len();
    (0..n)
        .filter(|&i| {
            (1..=order).all(|s| x[i] < x[(i + s).min(n - 1)] && x[i] < x[i.saturating_sub(s)])
        })
        .collect()
}

/// `scipy.ndimage.gaussian_filter1d(x, sigma)` with its defaults: truncate 4.0 (radius
/// ⌊4σ + 0.5⌋), mode 'reflect' (…c b a | a b c…, period 2n).
fn gaussian_filter(x: &[f64], sigma: f64) -> Vec<f64> {
    let n = x.len();
    if n == 0 {
        return Vec::new();
    }
    let radius = (4.0 * sigma + 0.5) as i64;
    let mut w: Vec<f64> = (-radius..=radius)
        .map(|k| (-0.5 * (k as f64 / sigma).powi(2)).exp())
        .collect();
    let total: f64 = w.iter().sum();
    w.iter_mut().for_each(|v| *v /= total);
    let period = 2 * n as i64;
    let reflect = |i: i64| -> usize {
        let m = i.rem_euclid(period);
        (if m >= n as i64 { period - 1 - m } else { m }) as usize
    };
    (0..n as i64)
        .map(|i| {
            (-radius..=radius)
                .zip(&w)
                .map(|(k, wk)| wk * x[reflect(i + k)])
                .sum()
        })
        .collect()
}

/// Beat times in seconds → frame indices at `fps` (nearest frame), kept below `frames`.
pub fn beat_frames(times_s: &[f64], fps: f64, frames: usize) -> Vec<usize> {
    let mut out: Vec<usize> = times_s
        .iter()
        .filter(|t| t.is_finite() && **t >= 0.0)
        .map(|t| (t * fps).round() as usize)
        .filter(|&f| f < frames)
        .collect();
    out.dedup();
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn argrelextrema_semantics() {
        // Plateaus are not minima (strict), ends never are, order widens the neighbourhood.
        let x = [3.0, 1.0, 2.0, 2.0, 2.0, 0.5, 4.0, 0.4, 5.0];
        assert_eq!(local_minima(&x, 1), vec![1, 5, 7]);
        assert_eq!(local_minima(&x, 2), vec![1, 7]);
        assert_eq!(local_minima(&[1.0, 1.0, 1.0], 1), Vec::<usize>::new());
    }

    #[test]
    fn mint_order_is_ten_frames() {
        // A lower dip exactly 10 frames away suppresses a minimum (mint's order=10); 11 away
        // does not.
        let mut x = [1.0f32; 40];
        x[5] = 0.5;
        x[15] = 0.2;
        x[27] = 0.4;
        assert_eq!(local_minima(&x, MINT_ORDER), vec![15, 27]);
    }

    #[test]
    fn gaussian_filter_preserves_constants_and_reflects() {
        let y = gaussian_filter(&[2.0; 7], 5.0);
        assert!(y.iter().all(|v| (v - 2.0).abs() < 1e-12));
        // scipy 1.x: gaussian_filter1d([0, 0, 1, 0, 0], 1.0) printed to 8 decimals (reflect
        // mode folds the tails back in), so 1e-8 is the print precision.
        let y = gaussian_filter(&[0.0, 0.0, 1.0, 0.0, 0.0], 1.0);
        let want = [0.05842299, 0.24210528, 0.39894347, 0.24210528, 0.05842299];
        for (g, w) in y.iter().zip(want) {
            assert!((g - w).abs() < 1e-8, "{y:?}");
        }
    }

    #[test]
    fn the_two_conventions_average_over_different_beats() {
        // One motion beat on a music beat, three music beats: mint scores 1, Bailando 1/3 + tails.
        let music = [30, 60, 90];
        let motion = [60];
        assert_eq!(bas_motion_beats(&music, &motion), Some(1.0));
        let tail = (-900.0f64 / 18.0).exp();
        assert!(
            (bas_music_beats(&music, &motion).unwrap_or(0.0) - (1.0 + 2.0 * tail) / 3.0).abs()
                < 1e-12
        );
        assert_eq!(bas_motion_beats(&music, &[]), Some(0.0));
        assert_eq!(bas_music_beats(&[], &motion), None);
    }
}
