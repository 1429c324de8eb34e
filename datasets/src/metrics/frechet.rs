//! Set statistics on feature vectors: z-scoring with the reference set's statistics, the
//! Fréchet distance and the average pairwise distance, as lisiyao21/Bailando
//! `utils/metrics_new.py` (commit cc90b98) computes FID_k / FID_g and Div_k / Div_g.

/// Rows z-scored with the mean and population std of `reference` (+1e-10 on the std):
/// metrics_new.py:9-13 `normalize(gt, pred)`. Returns (reference, other).
pub fn zscore_with_reference(
    reference: &[Vec<f64>],
    other: &[Vec<f64>],
) -> (Vec<Vec<f64>>, Vec<Vec<f64>>) {
    let dim = reference.first().map_or(0, Vec::len);
    let mean = column_mean(reference, dim);
    let std = column_std(reference, &mean);
    let z = |rows: &[Vec<f64>]| -> Vec<Vec<f64>> {
        rows.iter()
            .map(|r| {
                (0..dim)
                    .map(|c| (r[c] - mean[c]) / (std[c] + 1e-10))
                    .collect()
            })
            .collect()
    };
    (z(reference), z(other))
}

/// Columns constant in `reference` (population std below [`CONSTANT_STD`]) on which some row of
/// `other` departs from it by more than [`DEPARTURE`]: there the z-score divides by little more
/// than the reference's 1e-10, so that row's value becomes enormous and FID measures those
/// columns alone (e.g. 6.6e27 when every reference motion holds a joint still).
pub fn constant_columns(reference: &[Vec<f64>], other: &[Vec<f64>]) -> usize {
    let dim = reference.first().map_or(0, Vec::len);
    let mean = column_mean(reference, dim);
    column_std(reference, &mean)
        .iter()
        .enumerate()
        .filter(|(c, s)| {
            **s < CONSTANT_STD && other.iter().any(|r| (r[*c] - mean[*c]).abs() > DEPARTURE)
        })
        .count()
}

/// A std this small makes the reference's +1e-10 at least a tenth of the divisor.
pub const CONSTANT_STD: f64 = 1e-9;
/// A departure this large from a constant column z-scores to at least 1e-6 / 1.1e-9 ≈ 900.
pub const DEPARTURE: f64 = 1e-6;

/// Population std (numpy's default, ddof = 0) of each column.
fn column_std(rows: &[Vec<f64>], mean: &[f64]) -> Vec<f64> {
    let n = rows.len() as f64;
    mean.iter()
        .enumerate()
        .map(|(c, m)| (rows.iter().map(|r| (r[c] - m).powi(2)).sum::<f64>() / n).sqrt())
        .collect()
}

/// The Fréchet distance between Gaussians fitted to two sets of rows
/// (metrics_new.py:93-129): `‖μ1−μ2‖² + tr Σ1 + tr Σ2 − 2 tr √(Σ1Σ2)`, with `np.cov`
/// (ddof = 1). Both sets need at least 2 rows.
///
/// `tr √(Σ1Σ2)` is computed as Σ √λ over the eigenvalues of the symmetric `√Σ1 Σ2 √Σ1`
/// (similar to Σ1Σ2), negative round-off eigenvalues clamped to 0. The reference uses
/// `scipy.linalg.sqrtm`, whose result can carry an imaginary part that it drops
/// (metrics_new.py:120-124 keeps `.real`); the clamp is the same choice: the square roots of
/// the tiny negative eigenvalues are the imaginary part, and only the real trace is kept.
pub fn frechet_distance(a: &[Vec<f64>], b: &[Vec<f64>]) -> f64 {
    let dim = a.first().map_or(0, Vec::len);
    let (mu1, s1) = mean_cov(a, dim);
    let (mu2, s2) = mean_cov(b, dim);
    let diff: f64 = mu1.iter().zip(&mu2).map(|(x, y)| (x - y).powi(2)).sum();
    let trace = |m: &[f64]| (0..dim).map(|i| m[i * dim + i]).sum::<f64>();
    let root1 = sym_sqrt(&s1, dim);
    let inner = matmul(&matmul(&root1, &s2, dim), &root1, dim);
    let tr_covmean: f64 = sym_eigenvalues(&inner, dim)
        .iter()
        .map(|&l| l.max(0.0).sqrt())
        .sum();
    diff + trace(&s1) + trace(&s2) - 2.0 * tr_covmean
}

/// Mean L2 distance over all pairs of rows (metrics_new.py:138-149
/// `calculate_avg_distance`). Needs at least 2 rows.
pub fn average_pairwise_distance(rows: &[Vec<f64>]) -> f64 {
    let n = rows.len();
    let mut total = 0.0;
    for i in 0..n {
        for j in i + 1..n {
            total += rows[i]
                .iter()
                .zip(&rows[j])
                .map(|(x, y)| (x - y).powi(2))
                .sum::<f64>()
                .sqrt();
        }
    }
    total / ((n * n - n) as f64 / 2.0)
}

fn column_mean(rows: &[Vec<f64>], dim: usize) -> Vec<f64> {
    let n = rows.len() as f64;
    (0..dim)
        .map(|c| rows.iter().map(|r| r[c]).sum::<f64>() / n)
        .collect()
}

/// Mean and row-major covariance (ddof = 1).
fn mean_cov(rows: &[Vec<f64>], dim: usize) -> (Vec<f64>, Vec<f64>) {
    let mean = column_mean(rows, dim);
    let mut cov = vec![0.0; dim * dim];
    for r in rows {
        for i in 0..dim {
            let di = r[i] - mean[i];
            for j in i..dim {
                cov[i * dim + j] += di * (r[j] - mean[j]);
            }
        }
    }
    let denom = rows.len() as f64 - 1.0;
    for i in 0..dim {
        for j in i..dim {
            let v = cov[i * dim + j] / denom;
            cov[i * dim + j] = v;
            cov[j * dim + i] = v;
        }
    }
    (mean, cov)
}

fn matmul(a: &[f64], b: &[f64], n: usize) -> Vec<f64> {
    let mut out = vec![0.0; n * n];
    for i in 0..n {
        for k in 0..n {
            let aik = a[i * n + k];
            for j in 0..n {
                out[i * n + j] += aik * b[k * n + j];
            }
        }
    }
    out
}

/// √M of a symmetric positive semi-definite matrix: V diag(√max(λ, 0)) Vᵀ.
fn sym_sqrt(m: &[f64], n: usize) -> Vec<f64> {
    let (values, vectors) = jacobi_eigen(m, n);
    let mut out = vec![0.0; n * n];
    for (k, &l) in values.iter().enumerate() {
        let s = l.max(0.0).sqrt();
        for i in 0..n {
            let vik = vectors[i * n + k] * s;
            for j in 0..n {
                out[i * n + j] += vik * vectors[j * n + k];
            }
        }
    }
    out
}

fn sym_eigenvalues(m: &[f64], n: usize) -> Vec<f64> {
    jacobi_eigen(m, n).0
}

/// Eigenvalues and column eigenvectors of a symmetric matrix by cyclic Jacobi rotations
/// (Golub & Van Loan, Matrix Computations 4th ed., §8.5.2): accurate to round-off for the
/// ≤ 72×72 covariances here, where it takes a few ms.
fn jacobi_eigen(m: &[f64], n: usize) -> (Vec<f64>, Vec<f64>) {
    let mut a = m.to_vec();
    let mut v = vec![0.0; n * n];
    for i in 0..n {
        v[i * n + i] = 1.0;
    }
    let frob: f64 = a.iter().map(|x| x * x).sum::<f64>().sqrt();
    for _sweep in 0..100 {
        let off: f64 = (0..n)
            .flat_map(|i| (0..n).filter(move |&j| j != i).map(move |j| (i, j)))
            .map(|(i, j)| a[i * n + j].powi(2))
            .sum::<f64>()
            .sqrt();
        if off <= f64::EPSILON * frob || frob == 0.0 {
            break;
        }
        for p in 0..n {
            for q in p + 1..n {
                let apq = a[p * n + q];
                if apq == 0.0 {
                    continue;
                }
                let theta = (a[q * n + q] - a[p * n + p]) / (2.0 * apq);
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let t = if theta == 0.0 { 1.0 } else { t };
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                for k in 0..n {
                    let (akp, akq) = (a[k * n + p], a[k * n + q]);
                    a[k * n + p] = c * akp - s * akq;
                    a[k * n + q] = s * akp + c * akq;
                }
                for k in 0..n {
                    let (apk, aqk) = (a[p * n + k], a[q * n + k]);
                    a[p * n + k] = c * apk - s * aqk;
                    a[q * n + k] = s * apk + c * aqk;
                }
                for k in 0..n {
                    let (vkp, vkq) = (v[k * n + p], v[k * n + q]);
                    v[k * n + p] = c * vkp - s * vkq;
                    v[k * n + q] = s * vkp + c * vkq;
                }
            }
        }
    }
    ((0..n).map(|i| a[i * n + i]).collect(), v)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn jacobi_reconstructs_a_symmetric_matrix() {
        // A known spectrum: Q diag(4, 1, 0) Qᵀ with a rotation Q; eigenvalues must come back.
        let m = [2.5, 1.5, 0.0, 1.5, 2.5, 0.0, 0.0, 0.0, 0.0];
        let mut l = sym_eigenvalues(&m, 3);
        l.sort_by(f64::total_cmp);
        for (got, want) in l.iter().zip([0.0, 1.0, 4.0]) {
            assert!((got - want).abs() < 1e-12, "{l:?}");
        }
        let r = sym_sqrt(&m, 3);
        let back = matmul(&r, &r, 3);
        for (x, y) in back.iter().zip(m) {
            assert!((x - y).abs() < 1e-12);
        }
    }

    #[test]
    fn frechet_of_a_set_with_itself_is_zero_and_shift_adds_its_square() {
        let a: Vec<Vec<f64>> = (0..6)
            .map(|i| vec![i as f64, (i * i) as f64 * 0.1, (i % 3) as f64])
            .collect();
        assert!(frechet_distance(&a, &a).abs() < 1e-9);
        let b: Vec<Vec<f64>> = a.iter().map(|r| vec![r[0] + 2.0, r[1], r[2]]).collect();
        assert!((frechet_distance(&a, &b) - 4.0).abs() < 1e-9);
    }
}
