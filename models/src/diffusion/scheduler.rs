//! Schedulers: one reverse step (and its inverse) of DDPM, DDIM and DPM-Solver++ (2M).
//!
//! Formulas and conventions are diffusers' 0.42 (huggingface/diffusers:src/diffusers/schedulers/):
//! `DDPMScheduler.step` with `variance_type="fixed_small"` (scheduling_ddpm.py), `DDIMScheduler.step`
//! (scheduling_ddim.py, "1. get previous step value" .. "7."), `DDIMInverseScheduler.step`
//! (scheduling_ddim_inverse.py) and `DPMSolverMultistepScheduler` with
//! `algorithm_type="dpmsolver++"`, `solver_order=2`, `solver_type="midpoint"`,
//! `lower_order_final=True`, `final_sigmas_type="zero"` (scheduling_dpmsolver_multistep.py:
//! `set_timesteps` l. 367-490, `dpm_solver_first_order_update` l. 847,
//! `multistep_dpm_solver_second_order_update` l. 921, `step` l. 1196). Coefficients are f64;
//! samples are f32 slices of any shape (windows, latents), updated elementwise in f64.

use crate::diffusion::schedule::NoiseSchedule;
use crate::error::{Error, Result};

/// What the network predicts (`prediction_type` in diffusers).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
#[non_exhaustive]
pub enum Prediction {
    /// The added noise (DDPM, MoFusion, MLD).
    Epsilon,
    /// The clean sample (EDGE's `predict_epsilon=False`); diffusers calls it "sample".
    X0,
}

impl Prediction {
    /// The manifest spelling.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Epsilon => "epsilon",
            Self::X0 => "x0",
        }
    }
}

/// How inference timesteps are spread over the training steps (`timestep_spacing`; Lin et al.
/// 2023, "Common Diffusion Noise Schedules and Sample Steps are Flawed", table 2).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
#[non_exhaustive]
pub enum TimestepSpacing {
    /// `arange(0, n) * (N // n)` reversed, plus `steps_offset` (DDIM/DDPM default).
    Leading,
    /// `round(arange(N, 0, -N / n)) - 1`: the first step is at the last training step.
    Trailing,
    /// `round(linspace(0, N - 1, n))` reversed (DDIM), or `round(linspace(0, N - 1, n + 1))`
    /// reversed without its final 0 (DPM-Solver, whose last step goes to sigma 0).
    Linspace,
}

impl TimestepSpacing {
    /// The manifest and diffusers spelling.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Leading => "leading",
            Self::Trailing => "trailing",
            Self::Linspace => "linspace",
        }
    }
}

/// DDIM/DDPM inference timesteps, largest first (`DDIMScheduler.set_timesteps`).
pub fn ddim_timesteps(
    train_steps: usize,
    steps: usize,
    spacing: TimestepSpacing,
    steps_offset: usize,
) -> Result<Vec<i64>> {
    check_steps(train_steps, steps)?;
    let n = train_steps as f64;
    let timesteps: Vec<i64> = match spacing {
        TimestepSpacing::Leading => {
            let ratio = train_steps / steps;
            (0..steps)
                .rev()
                .map(|i| (i * ratio + steps_offset) as i64)
                .collect()
        }
        TimestepSpacing::Trailing => {
            // np.arange(N, 0, -N / n): n values N - k N / n, k = 0..n (exact for k < n here).
            let ratio = n / steps as f64;
            (0..steps)
                .map(|k| round_half_even(n - k as f64 * ratio) as i64 - 1)
                .collect()
        }
        TimestepSpacing::Linspace => linspace_rounded(n - 1.0, steps, steps),
    };
    if let Some(&t0) = timesteps.first()
        && t0 >= train_steps as i64
    {
        return Err(Error::Schedule {
            reason: format!(
                "steps_offset {steps_offset} puts the first timestep at {t0}, past train_steps {train_steps}"
            ),
        });
    }
    Ok(timesteps)
}

/// DPM-Solver++ inference timesteps, largest first (`DPMSolverMultistepScheduler.set_timesteps`
/// with `lambda_min_clipped=-inf`, so `last_timestep = N`).
pub fn dpm_timesteps(
    train_steps: usize,
    steps: usize,
    spacing: TimestepSpacing,
    steps_offset: usize,
) -> Result<Vec<i64>> {
    check_steps(train_steps, steps)?;
    let timesteps = match spacing {
        TimestepSpacing::Linspace => linspace_rounded((train_steps - 1) as f64, steps + 1, steps),
        TimestepSpacing::Leading => {
            // step_ratio = N // (n + 1); arange(0, n + 1) * ratio reversed, last dropped.
            let ratio = train_steps / (steps + 1);
            (1..=steps)
                .rev()
                .map(|i| (i * ratio + steps_offset) as i64)
                .collect()
        }
        TimestepSpacing::Trailing => ddim_timesteps(train_steps, steps, spacing, 0)?,
    };
    if timesteps.iter().any(|&t| t >= train_steps as i64) {
        return Err(Error::Schedule {
            reason: format!("steps_offset {steps_offset} puts a timestep past {train_steps}"),
        });
    }
    Ok(timesteps)
}

fn check_steps(train_steps: usize, steps: usize) -> Result<()> {
    if steps == 0 || steps > train_steps {
        return Err(Error::Schedule {
            reason: format!("sampling steps must be in 1..={train_steps}, got {steps}"),
        });
    }
    Ok(())
}

/// `np.linspace(0, end, points).round()[::-1]`, first `keep` values.
fn linspace_rounded(end: f64, points: usize, keep: usize) -> Vec<i64> {
    let at = |i: usize| {
        if points == 1 {
            0.0
        } else {
            // numpy: start + i * (end - start) / (points - 1), the last point exactly `end`.
            if i == points - 1 {
                end
            } else {
                i as f64 * (end / (points - 1) as f64)
            }
        }
    };
    (0..points)
        .rev()
        .take(keep)
        .map(|i| round_half_even(at(i)) as i64)
        .collect()
}

/// numpy's `round`: halves go to the even neighbour.
fn round_half_even(x: f64) -> f64 {
    let r = x.round();
    if (x - x.trunc()).abs() == 0.5 && r % 2.0 != 0.0 {
        r - x.signum()
    } else {
        r
    }
}

/// One reverse (and inverse) diffusion step over f32 samples of any shape.
///
/// Use: [`Scheduler::set_timesteps`] once, then for each of [`Scheduler::timesteps`] in order
/// evaluate the network at (x, t) and call [`Scheduler::step`]. Stochastic steps take their noise
/// explicitly (diffusers' `variance_noise`), a standard normal value per element, when
/// [`Scheduler::needs_noise`] says so.
pub trait Scheduler: std::fmt::Debug + Send {
    /// Choose `steps` inference timesteps; resets any multistep history.
    fn set_timesteps(&mut self, steps: usize) -> Result<()>;

    /// The inference timesteps, largest first.
    fn timesteps(&self) -> &[i64];

    /// The training schedule.
    fn schedule(&self) -> &NoiseSchedule;

    /// What the network predicts.
    fn prediction(&self) -> Prediction;

    /// alpha_bar of the clean end of the chain (negative timesteps): 1, or DDIM's
    /// `alphas_cumprod[0]` without `set_alpha_to_one`.
    fn final_alpha_bar(&self) -> f64 {
        1.0
    }

    /// Whether the step at `index` of [`Scheduler::timesteps`] adds noise.
    fn needs_noise(&self, index: usize) -> bool;

    /// alpha_bar of the noise level the step at `index` arrives at (in-painting re-noises known
    /// frames to it).
    fn alpha_bar_after(&self, index: usize) -> f64;

    /// x_t → x_prev in place for the step at `index` of [`Scheduler::timesteps`]; `noise` (one
    /// value per element) is required when [`Scheduler::needs_noise`].
    fn step(
        &mut self,
        x: &mut [f32],
        model_output: &[f32],
        index: usize,
        noise: Option<&[f32]>,
    ) -> Result<()>;

    /// Deterministic DDIM inversion, x at level `t` → level `t_next` > t in place
    /// (`DDIMInverseScheduler.step`; t < 0 is the clean level, [`Scheduler::final_alpha_bar`],
    /// diffusers' `initial_alpha_cumprod`): the network output
    /// at x gives x0 and epsilon (split at level `t`), which are re-noised to `t_next`. diffusers'
    /// inversion pipelines evaluate the network at `t_next` (at the clean level there is no
    /// noise to predict); that choice is the caller's.
    fn inverse_step(&self, x: &mut [f32], model_output: &[f32], t: i64, t_next: i64) -> Result<()> {
        check_lengths(x.len(), model_output.len(), None)?;
        let s = self.schedule();
        let ab_t = s.alpha_bar(t, self.final_alpha_bar());
        let ab_next = s.alpha_bar(t_next, self.final_alpha_bar());
        let (c0, c1) = (ab_next.sqrt(), (1.0 - ab_next).sqrt());
        let split = Split::new(ab_t, self.prediction(), false);
        for (x, &out) in x.iter_mut().zip(model_output) {
            let (x0, eps) = split.apply(*x, out);
            *x = (c0 * x0 + c1 * eps) as f32;
        }
        Ok(())
    }

    /// Forward diffusion q(x_t | x_0) in place: `sqrt(ab_t) x0 + sqrt(1 - ab_t) noise`
    /// (`add_noise`).
    fn add_noise(&self, x0: &mut [f32], noise: &[f32], t: i64) -> Result<()> {
        check_lengths(x0.len(), noise.len(), None)?;
        let ab = self.schedule().alpha_bar(t, 1.0);
        let (a, b) = (ab.sqrt(), (1.0 - ab).sqrt());
        for (x, &z) in x0.iter_mut().zip(noise) {
            *x = (a * f64::from(*x) + b * f64::from(z)) as f32;
        }
        Ok(())
    }
}

fn check_lengths(x: usize, out: usize, noise: Option<usize>) -> Result<()> {
    if out != x || noise.is_some_and(|n| n != x) {
        return Err(Error::Input {
            what: "scheduler step".into(),
            reason: format!(
                "sample has {x} values, model output {out}, noise {noise:?}: they must match"
            ),
        });
    }
    Ok(())
}

fn unknown_index(index: usize, steps: usize) -> Error {
    Error::Input {
        what: "scheduler step".into(),
        reason: format!("step index {index} outside the {steps} timesteps"),
    }
}

/// x0 and epsilon from the network output at a noise level (diffusers `step()`, "3. compute
/// predicted original sample", "4. clip").
#[derive(Debug, Clone, Copy)]
struct Split {
    sa: f64,
    sb: f64,
    prediction: Prediction,
    clip: bool,
}

impl Split {
    fn new(ab_t: f64, prediction: Prediction, clip: bool) -> Self {
        Self {
            sa: ab_t.sqrt(),
            sb: (1.0 - ab_t).sqrt(),
            prediction,
            clip,
        }
    }

    #[inline]
    fn apply(&self, x: f32, out: f32) -> (f64, f64) {
        let (x, out) = (f64::from(x), f64::from(out));
        let (x0, eps) = match self.prediction {
            Prediction::Epsilon => ((x - self.sb * out) / self.sa, out),
            Prediction::X0 => (out, (x - self.sa * out) / self.sb),
        };
        let x0 = if self.clip { x0.clamp(-1.0, 1.0) } else { x0 };
        (x0, eps)
    }
}

/// Settings shared by the schedulers (diffusers config names in parentheses).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SchedulerConfig {
    /// What the network predicts (`prediction_type`).
    pub prediction: Prediction,
    /// Clamp the x0 estimate to [-1, 1] (`clip_sample`; DDPM and DDIM only).
    pub clip_sample: bool,
    /// Timestep spacing (`timestep_spacing`).
    pub spacing: TimestepSpacing,
    /// Added to every "leading" timestep (`steps_offset`).
    pub steps_offset: usize,
    /// DDIM: alpha_bar after the last step is 1 (true) or `alphas_cumprod[0]` (false)
    /// (`set_alpha_to_one`).
    pub set_alpha_to_one: bool,
}

/// DDIM (Song et al. 2021), `eta` 0 deterministic; prev_t = t - N // n whatever the spacing,
/// as diffusers does.
#[derive(Debug, Clone)]
pub struct Ddim {
    schedule: NoiseSchedule,
    config: SchedulerConfig,
    eta: f64,
    timesteps: Vec<i64>,
    ratio: i64,
}

impl Ddim {
    /// A DDIM scheduler; call [`Scheduler::set_timesteps`] before stepping.
    pub fn new(schedule: NoiseSchedule, config: SchedulerConfig, eta: f64) -> Self {
        Self {
            schedule,
            config,
            eta,
            timesteps: Vec::new(),
            ratio: 1,
        }
    }
}

impl Scheduler for Ddim {
    fn set_timesteps(&mut self, steps: usize) -> Result<()> {
        let n = self.schedule.train_steps();
        let c = &self.config;
        self.timesteps = ddim_timesteps(n, steps, c.spacing, c.steps_offset)?;
        self.ratio = (n / steps) as i64;
        Ok(())
    }

    fn timesteps(&self) -> &[i64] {
        &self.timesteps
    }

    fn schedule(&self) -> &NoiseSchedule {
        &self.schedule
    }

    fn prediction(&self) -> Prediction {
        self.config.prediction
    }

    fn final_alpha_bar(&self) -> f64 {
        if self.config.set_alpha_to_one {
            1.0
        } else {
            self.schedule.alphas_cumprod()[0]
        }
    }

    fn needs_noise(&self, _index: usize) -> bool {
        self.eta > 0.0
    }

    fn alpha_bar_after(&self, index: usize) -> f64 {
        let t = self.timesteps.get(index).copied().unwrap_or(-1);
        self.schedule
            .alpha_bar(t - self.ratio, self.final_alpha_bar())
    }

    fn step(
        &mut self,
        x: &mut [f32],
        model_output: &[f32],
        index: usize,
        noise: Option<&[f32]>,
    ) -> Result<()> {
        let t = *self
            .timesteps
            .get(index)
            .ok_or_else(|| unknown_index(index, self.timesteps.len()))?;
        check_lengths(x.len(), model_output.len(), noise.map(<[f32]>::len))?;
        let ab_t = self.schedule.alpha_bar(t, 1.0);
        let ab_prev = self.alpha_bar_after(index);
        let split = Split::new(ab_t, self.config.prediction, self.config.clip_sample);
        // sigma_t = eta sqrt((1 - ab_prev)/(1 - ab_t)) sqrt(1 - ab_t/ab_prev)
        // (DDIM paper eq. 16; diffusers `_get_variance`).
        let variance = (1.0 - ab_prev) / (1.0 - ab_t) * (1.0 - ab_t / ab_prev);
        let std_dev = self.eta * variance.max(0.0).sqrt();
        let dir = (1.0 - ab_prev - std_dev * std_dev).max(0.0).sqrt();
        let c0 = ab_prev.sqrt();
        match (self.eta > 0.0, noise) {
            (true, Some(z)) => {
                for ((x, &out), &z) in x.iter_mut().zip(model_output).zip(z) {
                    let (x0, eps) = split.apply(*x, out);
                    *x = (c0 * x0 + dir * eps + std_dev * f64::from(z)) as f32;
                }
            }
            (true, None) => return Err(missing_noise("DDIM with eta > 0")),
            (false, _) => {
                for (x, &out) in x.iter_mut().zip(model_output) {
                    let (x0, eps) = split.apply(*x, out);
                    *x = (c0 * x0 + dir * eps) as f32;
                }
            }
        }
        Ok(())
    }
}

fn missing_noise(what: &str) -> Error {
    Error::Input {
        what: "scheduler step".into(),
        reason: format!("{what} needs step noise"),
    }
}

/// Ancestral DDPM (Ho et al. 2020) with the "fixed_small" posterior variance. Each step goes to
/// the next listed timestep (`previous_timestep`; t - N // n for "leading" spacing); after the
/// last step alpha_bar is 1 (diffusers `self.one`).
#[derive(Debug, Clone)]
pub struct Ddpm {
    schedule: NoiseSchedule,
    config: SchedulerConfig,
    timesteps: Vec<i64>,
}

impl Ddpm {
    /// A DDPM scheduler; call [`Scheduler::set_timesteps`] before stepping.
    pub fn new(schedule: NoiseSchedule, config: SchedulerConfig) -> Self {
        Self {
            schedule,
            config,
            timesteps: Vec::new(),
        }
    }
}

impl Scheduler for Ddpm {
    fn set_timesteps(&mut self, steps: usize) -> Result<()> {
        let n = self.schedule.train_steps();
        let c = &self.config;
        self.timesteps = ddim_timesteps(n, steps, c.spacing, c.steps_offset)?;
        Ok(())
    }

    fn timesteps(&self) -> &[i64] {
        &self.timesteps
    }

    fn schedule(&self) -> &NoiseSchedule {
        &self.schedule
    }

    fn prediction(&self) -> Prediction {
        self.config.prediction
    }

    fn needs_noise(&self, index: usize) -> bool {
        self.timesteps.get(index).is_some_and(|&t| t > 0)
    }

    fn alpha_bar_after(&self, index: usize) -> f64 {
        let next = self.timesteps.get(index + 1).copied().unwrap_or(-1);
        self.schedule.alpha_bar(next, 1.0)
    }

    fn step(
        &mut self,
        x: &mut [f32],
        model_output: &[f32],
        index: usize,
        noise: Option<&[f32]>,
    ) -> Result<()> {
        let t = *self
            .timesteps
            .get(index)
            .ok_or_else(|| unknown_index(index, self.timesteps.len()))?;
        check_lengths(x.len(), model_output.len(), noise.map(<[f32]>::len))?;
        let ab_t = self.schedule.alpha_bar(t, 1.0);
        let ab_prev = self.alpha_bar_after(index);
        let split = Split::new(ab_t, self.config.prediction, self.config.clip_sample);
        let cur_alpha = ab_t / ab_prev;
        let cur_beta = 1.0 - cur_alpha;
        // Posterior mean coefficients (DDPM eq. 7; diffusers "4."/"5.").
        let c0 = ab_prev.sqrt() * cur_beta / (1.0 - ab_t);
        let c1 = cur_alpha.sqrt() * (1.0 - ab_prev) / (1.0 - ab_t);
        // "fixed_small": beta~_t, clamped at 1e-20 as diffusers does.
        let std_dev = ((1.0 - ab_prev) / (1.0 - ab_t) * cur_beta)
            .max(1e-20)
            .sqrt();
        match (t > 0, noise) {
            (true, Some(z)) => {
                for ((x, &out), &z) in x.iter_mut().zip(model_output).zip(z) {
                    let (x0, _) = split.apply(*x, out);
                    *x = (c0 * x0 + c1 * f64::from(*x) + std_dev * f64::from(z)) as f32;
                }
            }
            (true, None) => return Err(missing_noise("DDPM before t = 0")),
            (false, _) => {
                for (x, &out) in x.iter_mut().zip(model_output) {
                    let (x0, _) = split.apply(*x, out);
                    *x = (c0 * x0 + c1 * f64::from(*x)) as f32;
                }
            }
        }
        Ok(())
    }
}

/// DPM-Solver++ (2M) (Lu et al. 2022, "DPM-Solver++", algorithm 2, midpoint form): a
/// deterministic multistep solver of the probability-flow ODE in the data-prediction form;
/// first order at the first step (no history) and at the last (to sigma 0).
#[derive(Debug, Clone)]
pub struct DpmSolverPlusPlus {
    schedule: NoiseSchedule,
    config: SchedulerConfig,
    timesteps: Vec<i64>,
    /// sigma = sqrt((1 - ab) / ab) at each timestep, then 0 (`final_sigmas_type="zero"`).
    sigmas: Vec<f64>,
    /// The previous step's index and x0 estimate (`model_outputs[-2]`).
    previous: Option<(usize, Vec<f64>)>,
}

impl DpmSolverPlusPlus {
    /// A DPM-Solver++ (2M) scheduler; call [`Scheduler::set_timesteps`] before stepping.
    pub fn new(schedule: NoiseSchedule, config: SchedulerConfig) -> Self {
        Self {
            schedule,
            config,
            timesteps: Vec::new(),
            sigmas: Vec::new(),
            previous: None,
        }
    }
}

/// (alpha_t, sigma_t, lambda_t) of a sigma (`_sigma_to_alpha_sigma_t`; lambda = log alpha -
/// log sigma, -inf at sigma 0).
fn alpha_sigma_lambda(sigma: f64) -> (f64, f64, f64) {
    let alpha = 1.0 / (sigma * sigma + 1.0).sqrt();
    let sigma_t = sigma * alpha;
    (alpha, sigma_t, alpha.ln() - sigma_t.ln())
}

impl Scheduler for DpmSolverPlusPlus {
    fn set_timesteps(&mut self, steps: usize) -> Result<()> {
        let c = &self.config;
        self.timesteps = dpm_timesteps(
            self.schedule.train_steps(),
            steps,
            c.spacing,
            c.steps_offset,
        )?;
        self.sigmas = self
            .timesteps
            .iter()
            .map(|&t| {
                let ab = self.schedule.alpha_bar(t, 1.0);
                ((1.0 - ab) / ab).sqrt()
            })
            .chain(std::iter::once(0.0))
            .collect();
        self.previous = None;
        Ok(())
    }

    fn timesteps(&self) -> &[i64] {
        &self.timesteps
    }

    fn schedule(&self) -> &NoiseSchedule {
        &self.schedule
    }

    fn prediction(&self) -> Prediction {
        self.config.prediction
    }

    fn needs_noise(&self, _index: usize) -> bool {
        false
    }

    fn alpha_bar_after(&self, index: usize) -> f64 {
        let sigma = self.sigmas.get(index + 1).copied().unwrap_or(0.0);
        1.0 / (1.0 + sigma * sigma)
    }

    fn step(
        &mut self,
        x: &mut [f32],
        model_output: &[f32],
        index: usize,
        _noise: Option<&[f32]>,
    ) -> Result<()> {
        let last = self.timesteps.len().saturating_sub(1);
        if index > last || self.sigmas.len() != self.timesteps.len() + 1 {
            return Err(unknown_index(index, self.timesteps.len()));
        }
        check_lengths(x.len(), model_output.len(), None)?;
        let (alpha_s0, sigma_s0, lambda_s0) = alpha_sigma_lambda(self.sigmas[index]);
        let (alpha_t, sigma_t, lambda_t) = alpha_sigma_lambda(self.sigmas[index + 1]);
        // convert_model_output: the data prediction x0 at this step.
        let split = Split::new(alpha_s0 * alpha_s0, self.config.prediction, false);
        let x0: Vec<f64> = x
            .iter()
            .zip(model_output)
            .map(|(&x, &out)| split.apply(x, out).0)
            .collect();
        let h = lambda_t - lambda_s0;
        let ratio = sigma_t / sigma_s0;
        let phi = alpha_t * ((-h).exp() - 1.0);
        let history = self
            .previous
            .take()
            .filter(|(i, _)| index > 0 && *i + 1 == index && index < last);
        match history {
            Some((_, m1)) => {
                let (_, _, lambda_s1) = alpha_sigma_lambda(self.sigmas[index - 1]);
                let r0 = (lambda_s0 - lambda_s1) / h;
                for ((x, &m0), &m1) in x.iter_mut().zip(&x0).zip(&m1) {
                    let d1 = (1.0 / r0) * (m0 - m1);
                    *x = (ratio * f64::from(*x) - phi * m0 - 0.5 * phi * d1) as f32;
                }
            }
            None => {
                for (x, &m0) in x.iter_mut().zip(&x0) {
                    *x = (ratio * f64::from(*x) - phi * m0) as f32;
                }
            }
        }
        self.previous = Some((index, x0));
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn timesteps_match_diffusers_spacings() {
        // Printed by diffusers 0.42 (DDIMScheduler / DPMSolverMultistepScheduler.set_timesteps,
        // num_train_timesteps=1000) for the spacings and step counts below.
        let leading = ddim_timesteps(1000, 10, TimestepSpacing::Leading, 1).unwrap();
        assert_eq!(leading, [901, 801, 701, 601, 501, 401, 301, 201, 101, 1]);
        let trailing = ddim_timesteps(1000, 10, TimestepSpacing::Trailing, 0).unwrap();
        assert_eq!(trailing, [999, 899, 799, 699, 599, 499, 399, 299, 199, 99]);
        let linspace = ddim_timesteps(1000, 10, TimestepSpacing::Linspace, 0).unwrap();
        assert_eq!(linspace, [999, 888, 777, 666, 555, 444, 333, 222, 111, 0]);
        let dpm = dpm_timesteps(1000, 10, TimestepSpacing::Linspace, 0).unwrap();
        assert_eq!(dpm, [999, 899, 799, 699, 599, 500, 400, 300, 200, 100]);
        let dpm7 = dpm_timesteps(1000, 7, TimestepSpacing::Linspace, 0).unwrap();
        assert_eq!(dpm7, [999, 856, 714, 571, 428, 285, 143]);
        assert!(ddim_timesteps(1000, 0, TimestepSpacing::Leading, 1).is_err());
        assert!(dpm_timesteps(1000, 1001, TimestepSpacing::Linspace, 0).is_err());
        assert!(ddim_timesteps(1000, 1000, TimestepSpacing::Leading, 1).is_err());
    }
}
