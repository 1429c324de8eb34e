//! Noise schedules: betas and `alphas_cumprod`, in f64.
//!
//! The formulas are diffusers' (huggingface/diffusers:src/diffusers/schedulers/scheduling_ddpm.py
//! and scheduling_ddim.py), so a package trained with diffusers' schedulers samples here with the
//! same numbers. f64 throughout: `alphas_cumprod` is a running product over 1000 terms, and f32
//! would drift in the 6th digit, which shows at high noise levels where it is divided by.

use crate::error::{Error, Result};

/// How betas grow over the training steps (`beta_schedule` in diffusers).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
#[non_exhaustive]
pub enum BetaSchedule {
    /// `linspace(beta_start, beta_end, N)` (DDPM, MoFusion).
    Linear,
    /// `linspace(sqrt(beta_start), sqrt(beta_end), N)^2` (Stable Diffusion, MLD/MCM-LDM).
    ScaledLinear,
    /// diffusers `squaredcos_cap_v2`: Nichol & Dhariwal's cosine schedule with `max_beta` 0.999
    /// (EDGE). `beta_start`/`beta_end` are ignored.
    Cosine,
}

impl BetaSchedule {
    /// The manifest spelling.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Linear => "linear",
            Self::ScaledLinear => "scaled_linear",
            Self::Cosine => "cosine",
        }
    }
}

/// diffusers `betas_for_alpha_bar(max_beta=0.999)` (scheduling_ddpm.py): caps betas near t = T,
/// where the cosine alpha_bar reaches 0.
pub(crate) const COSINE_MAX_BETA: f64 = 0.999;
/// The cosine schedule's offset s = 0.008 (Nichol & Dhariwal 2021, eq. 17; diffusers
/// `alpha_bar_fn`: `cos((t + 0.008) / 1.008 * pi / 2) ** 2`).
pub(crate) const COSINE_S: f64 = 0.008;

/// A training noise schedule: betas and their cumulative products.
#[derive(Debug, Clone, PartialEq)]
pub struct NoiseSchedule {
    betas: Vec<f64>,
    alphas_cumprod: Vec<f64>,
}

impl NoiseSchedule {
    /// Build the schedule of `train_steps` steps. `beta_start`/`beta_end` are used by the linear
    /// schedules only.
    pub fn new(
        kind: BetaSchedule,
        train_steps: usize,
        beta_start: f64,
        beta_end: f64,
    ) -> Result<Self> {
        let bad = |reason: String| Error::Schedule { reason };
        if train_steps < 2 {
            return Err(bad(format!(
                "train_steps must be at least 2, got {train_steps}"
            )));
        }
        if matches!(kind, BetaSchedule::Linear | BetaSchedule::ScaledLinear)
            && !(beta_start > 0.0 && beta_start <= beta_end && beta_end < 1.0)
        {
            return Err(bad(format!(
                "betas must satisfy 0 < beta_start <= beta_end < 1, got {beta_start} and {beta_end}"
            )));
        }
        let n = train_steps;
        let linspace = |a: f64, b: f64, i: usize| a + (b - a) * i as f64 / (n - 1) as f64;
        let betas: Vec<f64> = match kind {
            BetaSchedule::Linear => (0..n).map(|i| linspace(beta_start, beta_end, i)).collect(),
            BetaSchedule::ScaledLinear => (0..n)
                .map(|i| linspace(beta_start.sqrt(), beta_end.sqrt(), i).powi(2))
                .collect(),
            BetaSchedule::Cosine => {
                let alpha_bar = |t: f64| {
                    ((t + COSINE_S) / (1.0 + COSINE_S) * std::f64::consts::FRAC_PI_2)
                        .cos()
                        .powi(2)
                };
                (0..n)
                    .map(|i| {
                        let t1 = i as f64 / n as f64;
                        let t2 = (i + 1) as f64 / n as f64;
                        (1.0 - alpha_bar(t2) / alpha_bar(t1)).min(COSINE_MAX_BETA)
                    })
                    .collect()
            }
        };
        let mut alphas_cumprod = Vec::with_capacity(n);
        let mut acc = 1.0f64;
        for b in &betas {
            acc *= 1.0 - b;
            alphas_cumprod.push(acc);
        }
        Ok(Self {
            betas,
            alphas_cumprod,
        })
    }

    /// Number of training steps.
    pub fn train_steps(&self) -> usize {
        self.betas.len()
    }

    /// beta_t for t in 0..train_steps.
    pub fn betas(&self) -> &[f64] {
        &self.betas
    }

    /// alpha_bar_t = prod_{s<=t} (1 - beta_s) for t in 0..train_steps.
    pub fn alphas_cumprod(&self) -> &[f64] {
        &self.alphas_cumprod
    }

    /// alpha_bar at a timestep; negative timesteps (past the end of sampling) use `final_alpha`.
    pub fn alpha_bar(&self, t: i64, final_alpha: f64) -> f64 {
        usize::try_from(t)
            .ok()
            .and_then(|i| self.alphas_cumprod.get(i))
            .copied()
            .unwrap_or(final_alpha)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64, rel: f64) -> bool {
        (a - b).abs() <= rel * b.abs().max(1e-300)
    }

    #[test]
    fn linear_alphas_cumprod_match_closed_form() {
        let s = NoiseSchedule::new(BetaSchedule::Linear, 1000, 1e-4, 0.02).unwrap();
        // beta_t = 1e-4 + (0.02 - 1e-4) t / 999, by hand.
        assert_eq!(s.betas()[0], 1e-4);
        assert!(close(s.betas()[999], 0.02, 1e-15));
        assert!(close(s.alphas_cumprod()[0], 0.9999, 1e-15));
        assert!(close(
            s.alphas_cumprod()[1],
            0.9999 * (1.0 - (1e-4 + 0.0199 / 999.0)),
            1e-15
        ));
        // log alpha_bar_999 = sum log(1 - beta_t): evaluate the sum independently with ln_1p.
        let log_sum: f64 = (0..1000)
            .map(|t| (-(1e-4 + 0.0199 * t as f64 / 999.0)).ln_1p())
            .sum();
        assert!(close(s.alphas_cumprod()[999], log_sum.exp(), 1e-12));
        // The well-known DDPM value: alpha_bar_T ~= 4.04e-5.
        assert!((s.alphas_cumprod()[999] - 4.035e-5).abs() < 0.01e-5);
    }

    #[test]
    fn scaled_linear_alphas_cumprod_match_closed_form() {
        let s = NoiseSchedule::new(BetaSchedule::ScaledLinear, 1000, 0.00085, 0.012).unwrap();
        assert!(close(s.betas()[0], 0.00085, 1e-14));
        assert!(close(s.betas()[999], 0.012, 1e-14));
        // Midpoint t: sqrt-beta halfway between the ends, squared.
        let mid =
            (0.00085f64.sqrt() + (0.012f64.sqrt() - 0.00085f64.sqrt()) * 500.0 / 999.0).powi(2);
        assert!(close(s.betas()[500], mid, 1e-14));
        // Stable Diffusion's published final alpha_bar: 0.0047 (to 2 significant digits).
        assert!((s.alphas_cumprod()[999] - 0.0047).abs() < 0.00005);
        assert!(close(s.alphas_cumprod()[0], 1.0 - 0.00085, 1e-14));
    }

    #[test]
    fn cosine_alphas_cumprod_follow_the_cosine_until_the_cap() {
        let s = NoiseSchedule::new(BetaSchedule::Cosine, 1000, 0.0, 0.0).unwrap();
        let f = |t: f64| {
            ((t / 1000.0 + 0.008) / 1.008 * std::f64::consts::FRAC_PI_2)
                .cos()
                .powi(2)
        };
        // Without the cap, alpha_bar_t telescopes to f(t + 1) / f(0).
        for t in [0usize, 1, 10, 250, 500, 900, 990] {
            assert!(
                close(s.alphas_cumprod()[t], f(t as f64 + 1.0) / f(0.0), 1e-12),
                "t = {t}"
            );
        }
        // f(1000) = cos(pi/2)^2 = 0: the last beta is capped at 0.999.
        assert_eq!(s.betas()[999], 0.999);
        assert!(s.betas().iter().all(|&b| b > 0.0 && b <= 0.999));
    }

    #[test]
    fn bad_schedules_are_errors() {
        assert!(NoiseSchedule::new(BetaSchedule::Linear, 1, 1e-4, 0.02).is_err());
        assert!(NoiseSchedule::new(BetaSchedule::Linear, 1000, 0.02, 1e-4).is_err());
    }
}
