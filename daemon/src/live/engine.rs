//! How many denoising steps of a live window ([`choreo_models::LiveDance`]) fit in the time
//! budget.

use std::time::Duration;

/// Steps per window, within `[floor, ceiling]`, held under two limits:
/// - the hop: a window's denoising must fit its share of the hop (`hop_budget`), or generation
///   falls behind; from the measured time per step;
/// - the latency: the emit latency of recent windows must stay under `latency_budget`. A window
///   over [`LATENCY_HIGH`] of it cuts the steps at once, by as many as bring it back to
///   [`LATENCY_AIM`]; only [`CALM_WINDOWS`] windows in a row under [`LATENCY_LOW`] of it add
///   steps back, half the headroom at a time. Between the two the steps hold (hysteresis: one
///   noisy window neither raises nor lowers them twice).
#[derive(Debug, Clone)]
pub struct StepController {
    floor: usize,
    ceiling: usize,
    hop_budget: Duration,
    latency_budget: Duration,
    /// Exponential average of the seconds per step.
    per_step: Option<Duration>,
    /// The latency limit on the steps.
    latency_cap: usize,
    /// Windows in a row under [`LATENCY_LOW`] of the budget.
    calm: usize,
}

/// Share of the latency budget above which the steps are cut: under load the latency of a
/// window varies by about a quarter between neighbours, so cutting at 0.8 keeps the p99 under
/// the budget.
pub const LATENCY_HIGH: f64 = 0.8;
/// Where a cut aims the next window's latency.
pub const LATENCY_AIM: f64 = 0.6;
/// Share of the budget below which windows count as calm.
pub const LATENCY_LOW: f64 = 0.5;
/// Calm windows in a row before steps are added (2 s at the default hop).
pub const CALM_WINDOWS: usize = 4;

impl StepController {
    pub fn new(
        floor: usize,
        ceiling: usize,
        hop_budget: Duration,
        latency_budget: Duration,
    ) -> Self {
        let ceiling = ceiling.max(1);
        let floor = floor.clamp(1, ceiling);
        Self {
            floor,
            ceiling,
            hop_budget,
            latency_budget,
            per_step: None,
            latency_cap: ceiling,
            calm: 0,
        }
    }

    /// The fewest steps a window runs.
    pub fn floor(&self) -> usize {
        self.floor
    }

    /// The most steps a window runs.
    pub fn ceiling(&self) -> usize {
        self.ceiling
    }

    /// Steps for the next window.
    pub fn steps(&self) -> usize {
        let hop_cap = match self.per_step {
            Some(d) if !d.is_zero() => {
                (self.hop_budget.as_secs_f64() / d.as_secs_f64()).floor() as usize
            }
            _ => self.ceiling,
        };
        hop_cap
            .min(self.latency_cap)
            .clamp(self.floor, self.ceiling)
    }

    /// Start from a window of `steps` steps timed before the session (`took`): the time per
    /// step is known, and the latency limit is the steps whose window time lands at
    /// [`LATENCY_AIM`] of the budget. Without it the first window runs the ceiling, which on a
    /// slow package came out 0.5-1.3 s late (BENCHMARKS.md, "Live input").
    pub fn calibrate(&mut self, steps: usize, took: Duration) {
        let per_step = took / steps.max(1) as u32;
        self.per_step = Some(per_step);
        let aim = LATENCY_AIM * self.latency_budget.as_secs_f64();
        let fits = (aim / per_step.as_secs_f64().max(1e-9) + 1e-6).floor() as usize;
        self.latency_cap = fits.clamp(self.floor, self.ceiling);
        self.calm = 0;
    }

    /// A window ran `steps` steps in `took` and its frames were emitted `latency` after the
    /// newest sample it used arrived.
    pub fn observe(&mut self, steps: usize, took: Duration, latency: Duration) {
        let this_step = took / steps.max(1) as u32;
        let per_step = match self.per_step {
            // Reacts within a few windows, ignores one slow window.
            Some(p) => p.mul_f64(0.7) + this_step.mul_f64(0.3),
            None => this_step,
        };
        self.per_step = Some(per_step);
        let budget = self.latency_budget.as_secs_f64();
        let latency = latency.as_secs_f64();
        let step_s = per_step.as_secs_f64().max(1e-9);
        // Seconds as steps; the 1e-6 step keeps a whole number of steps whole through the
        // float rounding of the shares above.
        let in_steps = |seconds: f64| seconds / step_s;
        if latency > LATENCY_HIGH * budget {
            let excess = (in_steps(latency - LATENCY_AIM * budget) - 1e-6).ceil() as usize;
            self.latency_cap = steps.saturating_sub(excess.max(1)).max(self.floor);
            self.calm = 0;
        } else if latency < LATENCY_LOW * budget {
            self.calm += 1;
            if self.calm >= CALM_WINDOWS {
                let room = (in_steps(LATENCY_AIM * budget - latency) / 2.0 + 1e-6).floor() as usize;
                self.latency_cap = (self.latency_cap + room.max(1)).min(self.ceiling);
                self.calm = 0;
            }
        } else {
            self.calm = 0;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn controller(latency_budget_ms: u64) -> StepController {
        // Hop budget 300 ms: at 10 ms a step the hop allows 30 of the 50.
        StepController::new(
            4,
            50,
            Duration::from_millis(300),
            Duration::from_millis(latency_budget_ms),
        )
    }

    #[test]
    fn steps_follow_the_hop_budget_between_floor_and_ceiling() {
        let ms = Duration::from_millis;
        let mut c = controller(10_000);
        assert_eq!(c.steps(), 50, "nothing measured yet: the ceiling");
        c.observe(50, ms(500), ms(500));
        assert_eq!(c.steps(), 30);
        let mut c = controller(10_000);
        c.observe(10, ms(10_000), ms(100));
        assert_eq!(c.steps(), 4, "never under the floor");
        let mut c = controller(10_000);
        c.observe(20, ms(20), ms(30));
        assert_eq!(c.steps(), 50, "never over the ceiling");
    }

    #[test]
    fn a_calibrated_controller_starts_at_the_steps_the_budget_fits() {
        let ms = Duration::from_millis;
        let mut c = controller(250);
        // 4 steps in 40 ms: 10 ms a step; 0.6 x 250 ms = 150 ms fit 15 steps (the hop 30).
        c.calibrate(4, ms(40));
        assert_eq!(c.steps(), 15);
        // A fast package: the hop's 300 ms / 2 ms = 150 steps, capped at the ceiling.
        c.calibrate(4, ms(8));
        assert_eq!(c.steps(), 50);
        // Slower than the budget allows even at the floor: the floor.
        c.calibrate(4, ms(800));
        assert_eq!(c.steps(), 4);
    }

    #[test]
    fn a_slow_window_cuts_steps_to_aim_under_the_latency_budget() {
        let ms = Duration::from_millis;
        // 20 steps of 5 ms; the window's latency 222 ms > 0.8 × 250: cut to aim at 150 ms,
        // i.e. ⌈(222 - 150) / 5⌉ = 15 steps fewer.
        let mut c = controller(250);
        c.observe(20, ms(100), ms(222));
        assert_eq!(c.steps(), 5);
        // Just over the threshold: at least one step fewer, never more steps.
        let mut c = controller(250);
        c.observe(20, ms(100), ms(201));
        assert!(c.steps() < 20 && c.steps() >= 4, "{}", c.steps());
        // A latency the floor cannot meet: the floor.
        let mut c = controller(250);
        c.observe(20, ms(100), ms(2_000));
        assert_eq!(c.steps(), 4);
    }

    #[test]
    fn steps_come_back_only_after_calm_windows_and_hold_in_between() {
        let ms = Duration::from_millis;
        let mut c = controller(250);
        c.observe(20, ms(100), ms(222));
        assert_eq!(c.steps(), 5);
        // Between 0.5 and 0.8 of the budget: hold.
        for _ in 0..10 {
            c.observe(5, ms(25), ms(150));
            assert_eq!(c.steps(), 5);
        }
        // Calm windows: nothing changes until 4 (CALM_WINDOWS) in a row...
        for _ in 0..3 {
            c.observe(5, ms(25), ms(50));
            assert_eq!(c.steps(), 5);
        }
        // ...and a window in the middle band restarts the count.
        c.observe(5, ms(25), ms(150));
        for _ in 0..3 {
            c.observe(5, ms(25), ms(50));
            assert_eq!(c.steps(), 5);
        }
        c.observe(5, ms(25), ms(50));
        // Headroom (150 - 50) ms at 5 ms a step = 20 steps; half of it is added.
        assert_eq!(c.steps(), 15);
        // Calm for long: back to the ceiling (the hop would allow 300 ms / 5 ms = 60 steps).
        for _ in 0..100 {
            c.observe(c.steps(), ms(5) * c.steps() as u32, ms(50));
        }
        assert_eq!(c.steps(), 50);
    }
}
