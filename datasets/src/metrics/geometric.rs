//! Geometric ("manual") features: 32 boolean pose/motion relations (Müller et al.) averaged
//! over frames, as google/aistplusplus_api `aist_plusplus/features/manual.py` (commit 2dd7b3e,
//! the bug-fixed version; == lisiyao21/Bailando `utils/features/manual_new.py`) with the
//! helpers of `aist_plusplus/features/utils.py`.
//!
//! Uses SMPL joints 0-21 (t2m-22 shares them) and `y_min` over every joint of the frame.

use ndarray::ArrayView3;

/// Number of geometric features.
pub const GEOMETRIC_DIM: usize = 32;

type V3 = [f64; 3];

/// Joint indices in SMPL order (manual.py:36-47).
mod j {
    pub const ROOT: usize = 0;
    pub const LHIP: usize = 1;
    pub const RHIP: usize = 2;
    pub const BELLY: usize = 3;
    pub const LKNEE: usize = 4;
    pub const RKNEE: usize = 5;
    pub const LANKLE: usize = 7;
    pub const RANKLE: usize = 8;
    pub const CHEST: usize = 9;
    pub const LTOES: usize = 10;
    pub const RTOES: usize = 11;
    pub const NECK: usize = 12;
    pub const LSHOULDER: usize = 16;
    pub const RSHOULDER: usize = 17;
    pub const LELBOW: usize = 18;
    pub const RELBOW: usize = 19;
    pub const LWRIST: usize = 20;
    pub const RWRIST: usize = 21;
}

/// A point of the frame: a joint or one of manual.py's fixed points (manual.py:175-189).
#[derive(Clone, Copy)]
enum P {
    J(usize),
    Zero,
    YUnit,
    MinusYUnit,
    /// `[0, min_joints(y), 0]` of the current frame.
    YMin,
}

/// One relation of manual.py:56-143, with the helper it calls.
#[derive(Clone, Copy)]
enum Rel {
    /// `f_move(j1, j2, j3, _)`: velocity of j3 relative to j1 along j1→j2 (utils.py:66-78).
    /// manual.py:199-208 passes j3 as the moving point and ignores j4.
    Move(usize, usize, usize, f64),
    /// `f_nmove(j1, j2, j3, j4)`: velocity of j4 relative to j1 along the normal of the plane
    /// (j1, j2, j3) (utils.py:81-95).
    NMove(usize, usize, usize, usize, f64),
    /// `f_plane`: signed distance of p from the plane through a, b, c (utils.py:38-44).
    Plane(P, P, P, P, f64),
    /// `f_nplane`: distance of p from the plane through a with normal n1→n2 (utils.py:47-50).
    NPlane(P, P, P, P, f64),
    /// `f_angle`: angle between j1→j2 and k1→k2 strictly inside (lo, hi) degrees (utils.py:53-63).
    Angle(P, P, P, P, f64, f64),
    /// `f_fast`: speed of a joint above a threshold (utils.py:98-100).
    Fast(usize, f64),
}

/// Body lengths in metres from the reference's hard-coded SMPL rest joints (manual.py:156-170).
fn body_lengths() -> (f64, f64, f64) {
    let lshoulder = [1.99113488e-01, 2.36807942e-01, -1.80702247e-02];
    let lelbow = [4.54445392e-01, 2.21158922e-01, -4.10167128e-02];
    let rshoulder = [-1.91692337e-01, 2.36928746e-01, -1.23055102e-02];
    let lhip = [5.64076714e-02, -3.23069185e-01, 1.09197125e-02];
    let rhip = [-6.24834076e-02, -3.31302464e-01, 1.50412619e-02];
    (
        norm(sub(lshoulder, lelbow)),
        norm(sub(lshoulder, rshoulder)),
        norm(sub(lhip, rhip)),
    )
}

/// The 32 relations in the reference's order (manual.py:56-143); thresholds in humerus
/// lengths `hl`, shoulder widths `sw`, hip widths `hw`.
fn relations() -> [Rel; GEOMETRIC_DIM] {
    use P::{J, MinusYUnit, YMin, YUnit, Zero};
    use Rel::{Angle, Fast, Move, NMove, NPlane, Plane};
    use j::*;
    let (hl, sw, hw) = body_lengths();
    [
        NMove(NECK, RHIP, LHIP, RWRIST, 1.8 * hl),
        NMove(NECK, LHIP, RHIP, LWRIST, 1.8 * hl),
        NPlane(J(CHEST), J(NECK), J(NECK), J(RWRIST), 0.2 * hl),
        NPlane(J(CHEST), J(NECK), J(NECK), J(LWRIST), 0.2 * hl),
        Move(BELLY, CHEST, CHEST, 1.8 * hl),
        Move(BELLY, CHEST, CHEST, 1.8 * hl),
        Angle(J(RELBOW), J(RSHOULDER), J(RELBOW), J(RWRIST), 0.0, 110.0),
        Angle(J(LELBOW), J(LSHOULDER), J(LELBOW), J(LWRIST), 0.0, 110.0),
        NPlane(J(LSHOULDER), J(RSHOULDER), J(LWRIST), J(RWRIST), 2.5 * sw),
        Move(LWRIST, RWRIST, RWRIST, 1.4 * hl),
        Move(RWRIST, ROOT, LWRIST, 1.4 * hl),
        Move(LWRIST, ROOT, RWRIST, 1.4 * hl),
        Fast(RWRIST, 2.5 * hl),
        Fast(LWRIST, 2.5 * hl),
        Plane(J(ROOT), J(LHIP), J(LTOES), J(RANKLE), 0.38 * hl),
        Plane(J(ROOT), J(RHIP), J(RTOES), J(LANKLE), 0.38 * hl),
        NPlane(Zero, YUnit, YMin, J(RANKLE), 1.2 * hl),
        NPlane(Zero, YUnit, YMin, J(LANKLE), 1.2 * hl),
        NPlane(J(LHIP), J(RHIP), J(LANKLE), J(RANKLE), 2.1 * hw),
        Angle(J(RKNEE), J(RHIP), J(RKNEE), J(RANKLE), 0.0, 110.0),
        Angle(J(LKNEE), J(LHIP), J(LKNEE), J(LANKLE), 0.0, 110.0),
        Fast(RANKLE, 2.5 * hl),
        Fast(LANKLE, 2.5 * hl),
        Angle(J(NECK), J(ROOT), J(RSHOULDER), J(RELBOW), 25.0, 180.0),
        Angle(J(NECK), J(ROOT), J(LSHOULDER), J(LELBOW), 25.0, 180.0),
        Angle(J(NECK), J(ROOT), J(RHIP), J(RKNEE), 50.0, 180.0),
        Angle(J(NECK), J(ROOT), J(LHIP), J(LKNEE), 50.0, 180.0),
        Plane(J(RANKLE), J(NECK), J(LANKLE), J(ROOT), 0.5 * hl),
        Angle(J(NECK), J(ROOT), Zero, YUnit, 70.0, 110.0),
        NPlane(Zero, MinusYUnit, YMin, J(RWRIST), -1.2 * hl),
        NPlane(Zero, MinusYUnit, YMin, J(LWRIST), -1.2 * hl),
        Fast(ROOT, 2.3 * hl),
    ]
}

/// Geometric features of `joints` (T, J ≥ 22, 3), y-up. `time_per_frame` is the seconds per
/// frame the velocity relations divide by: the reference leaves the helpers' default 1/120
/// (utils.py:67, 82, 98) on 60 fps motion. Needs at least 2 frames.
pub fn geometric_features(joints: ArrayView3<f32>, time_per_frame: f64) -> [f64; GEOMETRIC_DIM] {
    let rels = relations();
    let (t, nj) = (joints.shape()[0], joints.shape()[1]);
    let points: Vec<V3> = joints
        .outer_iter()
        .flat_map(|frame| {
            frame
                .outer_iter()
                .map(|q| [f64::from(q[0]), f64::from(q[1]), f64::from(q[2])])
                .collect::<Vec<_>>()
        })
        .collect();
    let mut sums = [0u32; GEOMETRIC_DIM];
    for f in 1..t {
        let at = |k: usize, frame: usize| -> V3 { points[frame * nj + k] };
        let y_min = points[f * nj..(f + 1) * nj]
            .iter()
            .fold(f64::INFINITY, |m, q| m.min(q[1]));
        let point = |p: P| -> V3 {
            match p {
                P::J(k) => at(k, f),
                P::Zero => [0.0; 3],
                P::YUnit => [0.0, 1.0, 0.0],
                P::MinusYUnit => [0.0, -1.0, 0.0],
                P::YMin => [0.0, y_min, 0.0],
            }
        };
        // (p - j1) - (p_prev - j1_prev), utils.py:69-71.
        let rel_velocity =
            |j1: usize, p: usize| sub(sub(at(p, f), at(j1, f)), sub(at(p, f - 1), at(j1, f - 1)));
        for (s, rel) in sums.iter_mut().zip(rels.iter()) {
            let hit = match *rel {
                Rel::Move(j1, j2, p, th) => {
                    let dir = sub(at(j2, f), at(j1, f));
                    dot(rel_velocity(j1, p), dir) / norm(dir) / time_per_frame > th
                }
                Rel::NMove(j1, j2, j3, p, th) => {
                    let dir = cross(sub(at(j3, f), at(j1, f)), sub(at(j2, f), at(j1, f)));
                    dot(rel_velocity(j1, p), dir) / norm(dir) / time_per_frame > th
                }
                Rel::Plane(a, b, c, p, th) => {
                    let a = point(a);
                    let n = cross(sub(point(c), a), sub(point(b), a));
                    dot(n, sub(point(p), a)) / norm(n) > th
                }
                Rel::NPlane(n1, n2, a, p, th) => {
                    let n = sub(point(n2), point(n1));
                    dot(n, sub(point(p), point(a))) / norm(n) > th
                }
                Rel::Angle(j1, j2, k1, k2, lo, hi) => {
                    let (u, v) = (sub(point(j2), point(j1)), sub(point(k2), point(k1)));
                    let deg = (dot(u, v) / (norm(u) * norm(v))).acos().to_degrees();
                    deg > lo && deg < hi
                }
                Rel::Fast(k, th) => norm(sub(at(k, f), at(k, f - 1))) / time_per_frame > th,
            };
            *s += u32::from(hit);
        }
    }
    // np.array(features, dtype=np.float32).mean(axis=0) (manual.py:146): a float32 mean of
    // 0/1 values.
    sums.map(|s| f64::from((f64::from(s) / (t - 1) as f64) as f32))
}

fn sub(a: V3, b: V3) -> V3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn dot(a: V3, b: V3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn cross(a: V3, b: V3) -> V3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn norm(a: V3) -> f64 {
    dot(a, a).sqrt()
}
