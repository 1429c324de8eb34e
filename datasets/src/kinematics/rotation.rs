//! Small rotation toolbox: quaternions (w, x, y, z; Hamilton product, as in
//! EricGuo5513/HumanML3D:common/quaternion.py) and row-major 3×3 matrices.
//! f32 throughout: these run per joint per frame on the hot path.

/// A quaternion `[w, x, y, z]`.
pub type Quat = [f32; 4];
/// A row-major rotation matrix.
pub type Mat3 = [[f32; 3]; 3];
/// A 3-vector.
pub type Vec3 = [f32; 3];

/// The identity rotation.
pub const QUAT_IDENTITY: Quat = [1.0, 0.0, 0.0, 0.0];
/// The identity matrix.
pub const MAT3_IDENTITY: Mat3 = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

/// Hamilton product `q * r` (apply `r` first, then `q`).
#[inline]
pub fn qmul(q: Quat, r: Quat) -> Quat {
    [
        q[0] * r[0] - q[1] * r[1] - q[2] * r[2] - q[3] * r[3],
        q[0] * r[1] + q[1] * r[0] + q[2] * r[3] - q[3] * r[2],
        q[0] * r[2] - q[1] * r[3] + q[2] * r[0] + q[3] * r[1],
        q[0] * r[3] + q[1] * r[2] - q[2] * r[1] + q[3] * r[0],
    ]
}

/// Conjugate (the inverse of a unit quaternion).
#[inline]
pub fn qinv(q: Quat) -> Quat {
    [q[0], -q[1], -q[2], -q[3]]
}

/// Rotate `v` by unit quaternion `q` (v + 2 (w (u×v) + u×(u×v)), HumanML3D `qrot`).
#[inline]
pub fn qrot(q: Quat, v: Vec3) -> Vec3 {
    let u = [q[1], q[2], q[3]];
    let uv = cross(u, v);
    let uuv = cross(u, uv);
    [
        v[0] + 2.0 * (q[0] * uv[0] + uuv[0]),
        v[1] + 2.0 * (q[0] * uv[1] + uuv[1]),
        v[2] + 2.0 * (q[0] * uv[2] + uuv[2]),
    ]
}

/// The shortest-arc rotation taking direction `v0` to `v1` (HumanML3D `qbetween`:
/// w = |v0||v1| + v0·v1, xyz = v0×v1, normalised).
#[inline]
pub fn qbetween(v0: Vec3, v1: Vec3) -> Quat {
    let c = cross(v0, v1);
    let w = (dot(v0, v0) * dot(v1, v1)).sqrt() + dot(v0, v1);
    qnormalize([w, c[0], c[1], c[2]])
}

/// qbetween that stays finite for opposite or zero vectors (the reference gives NaN there).
pub fn qbetween_safe(u: Vec3, v: Vec3) -> Quat {
    let q = qbetween(u, v);
    if q.iter().all(|c| c.is_finite()) {
        return q;
    }
    if norm(v) < 1e-12 || norm(u) < 1e-12 {
        return [1.0, 0.0, 0.0, 0.0];
    }
    // 180°: any axis perpendicular to u.
    let axis = if u[0].abs() < 0.9 {
        cross(u, [1.0, 0.0, 0.0])
    } else {
        cross(u, [0.0, 1.0, 0.0])
    };
    let n = norm(axis);
    [0.0, axis[0] / n, axis[1] / n, axis[2] / n]
}

/// Unit-length copy of `q`.
#[inline]
pub fn qnormalize(q: Quat) -> Quat {
    let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    [q[0] / n, q[1] / n, q[2] / n, q[3] / n]
}

/// The rotation about unit quaternion `q`'s axis by `t` times its angle (`q^t`: the identity at
/// t = 0, `q` at t = 1), taking the angle in [0, π] (q and -q are one rotation).
pub fn qpow(q: Quat, t: f32) -> Quat {
    let q = if q[0] < 0.0 { q.map(|c| -c) } else { q };
    let s = (q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    if s < 1e-12 {
        return QUAT_IDENTITY;
    }
    // Half the angle by atan2: accurate near 0 and near π alike.
    let half = t * s.atan2(q[0]);
    let k = half.sin() / s;
    [half.cos(), q[1] * k, q[2] * k, q[3] * k]
}

/// Rotation matrix of a unit quaternion (HumanML3D `quaternion_to_matrix`).
#[inline]
pub fn quat_to_mat(q: Quat) -> Mat3 {
    let [r, i, j, k] = q;
    let two_s = 2.0 / (r * r + i * i + j * j + k * k);
    [
        [
            1.0 - two_s * (j * j + k * k),
            two_s * (i * j - k * r),
            two_s * (i * k + j * r),
        ],
        [
            two_s * (i * j + k * r),
            1.0 - two_s * (i * i + k * k),
            two_s * (j * k - i * r),
        ],
        [
            two_s * (i * k - j * r),
            two_s * (j * k + i * r),
            1.0 - two_s * (i * i + j * j),
        ],
    ]
}

/// Unit quaternion of a rotation matrix (Shepperd's method, robust for all angles).
pub fn mat_to_quat(m: &Mat3) -> Quat {
    let tr = m[0][0] + m[1][1] + m[2][2];
    let q = if tr > 0.0 {
        let s = (tr + 1.0).sqrt() * 2.0;
        [
            0.25 * s,
            (m[2][1] - m[1][2]) / s,
            (m[0][2] - m[2][0]) / s,
            (m[1][0] - m[0][1]) / s,
        ]
    } else if m[0][0] > m[1][1] && m[0][0] > m[2][2] {
        let s = (1.0 + m[0][0] - m[1][1] - m[2][2]).sqrt() * 2.0;
        [
            (m[2][1] - m[1][2]) / s,
            0.25 * s,
            (m[0][1] + m[1][0]) / s,
            (m[0][2] + m[2][0]) / s,
        ]
    } else if m[1][1] > m[2][2] {
        let s = (1.0 + m[1][1] - m[0][0] - m[2][2]).sqrt() * 2.0;
        [
            (m[0][2] - m[2][0]) / s,
            (m[0][1] + m[1][0]) / s,
            0.25 * s,
            (m[1][2] + m[2][1]) / s,
        ]
    } else {
        let s = (1.0 + m[2][2] - m[0][0] - m[1][1]).sqrt() * 2.0;
        [
            (m[1][0] - m[0][1]) / s,
            (m[0][2] + m[2][0]) / s,
            (m[1][2] + m[2][1]) / s,
            0.25 * s,
        ]
    };
    qnormalize(q)
}

/// Rotation matrix of an axis-angle vector (Rodrigues; the angle is the vector's norm, radians).
/// Computed in f64 so tiny angles keep full f32 precision after the cast.
pub fn axis_angle_to_mat(a: Vec3) -> Mat3 {
    let (x, y, z) = (f64::from(a[0]), f64::from(a[1]), f64::from(a[2]));
    let theta = (x * x + y * y + z * z).sqrt();
    if theta < 1e-12 {
        return MAT3_IDENTITY;
    }
    let (kx, ky, kz) = (x / theta, y / theta, z / theta);
    let (s, c) = theta.sin_cos();
    let t = 1.0 - c;
    let m = [
        [t * kx * kx + c, t * kx * ky - s * kz, t * kx * kz + s * ky],
        [t * kx * ky + s * kz, t * ky * ky + c, t * ky * kz - s * kx],
        [t * kx * kz - s * ky, t * ky * kz + s * kx, t * kz * kz + c],
    ];
    m.map(|row| row.map(|v| v as f32))
}

/// `a * b`.
#[inline]
pub fn mat_mul(a: &Mat3, b: &Mat3) -> Mat3 {
    let mut out = [[0.0f32; 3]; 3];
    for (i, row) in out.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j];
        }
    }
    out
}

/// `m * v`.
#[inline]
pub fn mat_vec(m: &Mat3, v: Vec3) -> Vec3 {
    [
        m[0][0] * v[0] + m[0][1] * v[1] + m[0][2] * v[2],
        m[1][0] * v[0] + m[1][1] * v[1] + m[1][2] * v[2],
        m[2][0] * v[0] + m[2][1] * v[1] + m[2][2] * v[2],
    ]
}

/// Transpose (the inverse of a rotation).
#[inline]
pub fn mat_transpose(m: &Mat3) -> Mat3 {
    [
        [m[0][0], m[1][0], m[2][0]],
        [m[0][1], m[1][1], m[2][1]],
        [m[0][2], m[1][2], m[2][2]],
    ]
}

/// Elementary rotation about one axis (0 = x, 1 = y, 2 = z) by `angle` radians.
pub fn axis_rotation(axis: usize, angle: f64) -> Mat3 {
    let (s, c) = angle.sin_cos();
    let (s, c) = (s as f32, c as f32);
    match axis {
        0 => [[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]],
        1 => [[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]],
        _ => [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]],
    }
}

/// Euler angles (radians) of `m = R_a0(e0) R_a1(e1) R_a2(e2)` for a proper Tait-Bryan order
/// (three distinct axes, e.g. ZXY as BVH writes them). Inverse of composing [`axis_rotation`]s.
pub fn mat_to_euler(m: &Mat3, order: [usize; 3]) -> [f64; 3] {
    let [i, j, k] = order;
    // Sign of the permutation (i, j, k): +1 for cyclic orders (xyz, yzx, zxy).
    let parity = if (j + 3 - i) % 3 == 1 { 1.0 } else { -1.0 };
    let m = |r: usize, c: usize| f64::from(m[r][c]);
    let sy = (parity * m(i, k)).clamp(-1.0, 1.0);
    let e1 = sy.asin();
    let (e0, e2) = if sy.abs() < 1.0 - 1e-9 {
        (
            (-parity * m(j, k)).atan2(m(k, k)),
            (-parity * m(i, j)).atan2(m(i, i)),
        )
    } else {
        // Gimbal lock: only e0 ± e2 is defined; put it all in e0.
        ((parity * m(k, j)).atan2(m(j, j)), 0.0)
    };
    [e0, e1, e2]
}

/// Best rotation taking each `a[i]` onto `b[i]` (Wahba's problem) (Horn's quaternion method; the 4×4 eigenproblem
/// is solved by Jacobi rotations). f64: sums of products of small offsets.
// Jacobi sweeps index rows and columns of the same matrix together; iterators obscure that.
#[allow(clippy::needless_range_loop)]
pub fn fit_rotation(a: &[Vec3], b: &[Vec3]) -> Mat3 {
    let mut s = [[0.0f64; 3]; 3];
    for (u, v) in a.iter().zip(b.iter()) {
        for i in 0..3 {
            for k in 0..3 {
                s[i][k] += f64::from(u[i]) * f64::from(v[k]);
            }
        }
    }
    let (sxx, sxy, sxz, syx, syy, syz, szx, szy, szz) = (
        s[0][0], s[0][1], s[0][2], s[1][0], s[1][1], s[1][2], s[2][0], s[2][1], s[2][2],
    );
    let mut n = [
        [sxx + syy + szz, syz - szy, szx - sxz, sxy - syx],
        [syz - szy, sxx - syy - szz, sxy + syx, szx + sxz],
        [szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy],
        [sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz],
    ];
    let mut v = [[0.0f64; 4]; 4];
    for (i, row) in v.iter_mut().enumerate() {
        row[i] = 1.0;
    }
    for _ in 0..50 {
        let mut off = 0.0;
        for p in 0..4 {
            for q in p + 1..4 {
                off += n[p][q] * n[p][q];
            }
        }
        if off < 1e-30 {
            break;
        }
        for p in 0..4 {
            for q in p + 1..4 {
                if n[p][q].abs() < 1e-300 {
                    continue;
                }
                let theta = (n[q][q] - n[p][p]) / (2.0 * n[p][q]);
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let t = if theta == 0.0 { 1.0 } else { t };
                let c = 1.0 / (t * t + 1.0).sqrt();
                let sn = t * c;
                for k in 0..4 {
                    let (nkp, nkq) = (n[k][p], n[k][q]);
                    n[k][p] = c * nkp - sn * nkq;
                    n[k][q] = sn * nkp + c * nkq;
                }
                for k in 0..4 {
                    let (npk, nqk) = (n[p][k], n[q][k]);
                    n[p][k] = c * npk - sn * nqk;
                    n[q][k] = sn * npk + c * nqk;
                }
                for row in v.iter_mut() {
                    let (vp, vq) = (row[p], row[q]);
                    row[p] = c * vp - sn * vq;
                    row[q] = sn * vp + c * vq;
                }
            }
        }
    }
    let best = (0..4)
        .max_by(|x, y| n[*x][*x].total_cmp(&n[*y][*y]))
        .unwrap_or(0);
    let q: Quat = [
        v[0][best] as f32,
        v[1][best] as f32,
        v[2][best] as f32,
        v[3][best] as f32,
    ];
    let qn = (q.iter().map(|c| c * c).sum::<f32>()).sqrt();
    if !(qn > 0.0 && qn.is_finite()) {
        return MAT3_IDENTITY;
    }
    quat_to_mat(q.map(|c| c / qn))
}

/// Cross product.
#[inline]
pub fn cross(a: Vec3, b: Vec3) -> Vec3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// Dot product.
#[inline]
pub fn dot(a: Vec3, b: Vec3) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// `a - b`.
#[inline]
pub fn sub(a: Vec3, b: Vec3) -> Vec3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// `a + b`.
#[inline]
pub fn add(a: Vec3, b: Vec3) -> Vec3 {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

/// Euclidean norm.
#[inline]
pub fn norm(a: Vec3) -> f32 {
    dot(a, a).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: &Mat3, b: &Mat3, tol: f32) -> bool {
        (0..3).all(|i| (0..3).all(|j| (a[i][j] - b[i][j]).abs() <= tol))
    }

    #[test]
    fn quaternion_and_matrix_agree() {
        let m = axis_angle_to_mat([0.3, -1.1, 0.5]);
        let q = mat_to_quat(&m);
        // f32 round trip: 1e-6 is a few ulps of values near 1.
        assert!(close(&quat_to_mat(q), &m, 1e-6));
        let v = [0.2, 0.7, -0.4];
        let a = qrot(q, v);
        let b = mat_vec(&m, v);
        assert!((0..3).all(|i| (a[i] - b[i]).abs() < 1e-6));
    }

    #[test]
    fn a_fraction_of_a_rotation_turns_by_that_fraction_of_its_angle() {
        // 170° about z, given in either hemisphere (-q is the same rotation).
        let q = mat_to_quat(&axis_rotation(2, 170f64.to_radians()));
        for q in [q, q.map(|c| -c)] {
            for t in [0.0f32, 0.25, 0.5, 1.0] {
                let v = qrot(qpow(q, t), [1.0, 0.0, 0.0]);
                let want = (170.0 * t).to_radians();
                // f32 trigonometry: 1e-6 of unit vectors.
                assert!((v[0] - want.cos()).abs() < 1e-6 && (v[1] - want.sin()).abs() < 1e-6);
                assert!(v[2].abs() < 1e-6, "{t}: {v:?}");
            }
        }
        assert_eq!(qpow(QUAT_IDENTITY, 0.5), QUAT_IDENTITY);
    }

    #[test]
    fn euler_round_trip_all_orders() {
        let orders = [
            [0, 1, 2],
            [0, 2, 1],
            [1, 0, 2],
            [1, 2, 0],
            [2, 0, 1],
            [2, 1, 0],
        ];
        for order in orders {
            let e = [0.4, -0.9, 1.3];
            let m = mat_mul(
                &mat_mul(
                    &axis_rotation(order[0], e[0]),
                    &axis_rotation(order[1], e[1]),
                ),
                &axis_rotation(order[2], e[2]),
            );
            let back = mat_to_euler(&m, order);
            for k in 0..3 {
                // f32 matrices: angles good to ~1e-6 rad away from gimbal lock.
                assert!(
                    (back[k] - e[k]).abs() < 1e-5,
                    "order {order:?}: {back:?} vs {e:?}"
                );
            }
        }
    }

    #[test]
    fn qbetween_maps_v0_onto_v1() {
        let v0 = [1.0, 0.0, 0.0];
        let v1 = [0.0, 0.6, 0.8];
        let r = qrot(qbetween(v0, v1), v0);
        assert!((0..3).all(|i| (r[i] - v1[i]).abs() < 1e-6));
    }

    #[test]
    fn fit_rotation_recovers_a_rotation() {
        let r = axis_angle_to_mat([0.4, -1.2, 2.0]);
        let a = [[0.1, 0.0, 0.0], [0.0, 0.2, 0.05], [0.0, -0.1, 0.3]];
        let b: Vec<Vec3> = a.iter().map(|v| mat_vec(&r, *v)).collect();
        let f = fit_rotation(&a, &b);
        for i in 0..3 {
            for k in 0..3 {
                assert!((f[i][k] - r[i][k]).abs() < 1e-5);
            }
        }
    }
}
