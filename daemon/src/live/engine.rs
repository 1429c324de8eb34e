//! The live loop's arithmetic: which window to generate next, its music, its seed frames, and
//! how many denoising steps fit in the time budget.
//!
//! Every hop the newest window is generated: it ends at motion frame `E = N + hop` (N = frames
//! emitted so far) and starts at `S = max(0, E - W)`. The frames already emitted in `[S, N)` are
//! its in-painted seed (known at every step), so only `[N, E)` is new and only those are
//! emitted. Before the first full window (E < W) the window starts at 0 and its music past the
//! newest heard frame is the silence floor. The window's music is the mel frames from
//! `round(S / fps · sr / hop)` on, as in the offline pipeline (`choreo_models` `WindowPlan`).

use std::time::Duration;

use anyhow::Context;
use ndarray::{Array2, ArrayView2, s};

use choreo_models::{DanceOptions, Manifest, ModelPackage};

/// Log-mel frames heard so far, time-major, clamped like the offline path: librosa's
/// `power_to_db(top_db)` floors every value at `max - top_db` over the whole song; live, the
/// maximum is the running maximum of what was heard.
#[derive(Debug)]
pub struct HeardMel {
    n_mels: usize,
    top_db: f32,
    /// Unclamped frames `first..`, time-major (n_mels per frame).
    frames: Vec<f32>,
    first: usize,
    max_db: f32,
}

impl HeardMel {
    pub fn new(n_mels: usize, top_db: f32) -> Self {
        Self {
            n_mels,
            top_db,
            frames: Vec::new(),
            first: 0,
            max_db: f32::NEG_INFINITY,
        }
    }

    pub fn push(&mut self, frames: &[f32]) {
        self.max_db = frames.iter().copied().fold(self.max_db, f32::max);
        self.frames.extend_from_slice(frames);
    }

    /// Frames heard so far (including discarded ones).
    pub fn len(&self) -> usize {
        self.first + self.frames.len() / self.n_mels
    }

    /// Forget frames before `frame` (no later window starts before it): memory stays bounded
    /// however long the session runs.
    pub fn discard_before(&mut self, frame: usize) {
        let drop = frame
            .saturating_sub(self.first)
            .min(self.frames.len() / self.n_mels);
        self.frames.drain(..drop * self.n_mels);
        self.first += drop;
    }

    /// The silence floor: what a clamped frame of silence holds.
    pub fn floor(&self) -> f32 {
        if self.max_db.is_finite() {
            self.max_db - self.top_db
        } else {
            // Nothing heard yet: librosa's power_to_db of zero power with amin = 1e-10.
            -100.0
        }
    }

    /// Frames `start..start + n` (time-major, clamped at the floor); frames not heard yet (or
    /// discarded) are the floor.
    pub fn window(&self, start: usize, n: usize) -> Array2<f32> {
        let floor = self.floor();
        let mut out = Array2::from_elem((n, self.n_mels), floor);
        for i in 0..n {
            let f = start + i;
            if f >= self.len() {
                break;
            }
            if f < self.first {
                continue;
            }
            let k = f - self.first;
            let src = &self.frames[k * self.n_mels..(k + 1) * self.n_mels];
            for (o, v) in out.row_mut(i).iter_mut().zip(src) {
                *o = v.max(floor);
            }
        }
        out
    }
}

/// The next window to generate.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct WindowPlan {
    /// First motion frame of the window.
    pub start: usize,
    /// One past the last new frame (`start + window` once the first full window is reached).
    pub end: usize,
    /// First mel frame of the window's music.
    pub mel_start: usize,
    /// Mel frames that must have been heard before the window can be generated.
    pub mel_needed: usize,
}

/// Plan the window whose new frames are `[emitted, emitted + new)`.
pub fn plan_window(manifest: &Manifest, emitted: usize, new: usize) -> anyhow::Result<WindowPlan> {
    let m = &manifest.motion;
    let dance = manifest.dance_spec()?;
    let a = dance.audio;
    let end = emitted + new;
    let start = end.saturating_sub(dance.window_frames);
    let mel_rate = a.frame_rate();
    let mel_at = |frame: usize| (frame as f64 / m.fps * mel_rate).round() as usize;
    let mel_start = mel_at(start);
    // The newest motion frame's own mel frame must be heard; beyond it is the window's tail.
    let mel_needed = (mel_at(end) + 1).min(mel_start + a.music_frames);
    Ok(WindowPlan {
        start,
        end,
        mel_start,
        mel_needed,
    })
}

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

/// The one call into the models crate: denoise one window with its seed frames in-painted.
/// (The toolkit's window stepper replaces this call at merge.)
pub fn denoise_window(
    package: &mut ModelPackage,
    music: ArrayView2<'_, f32>,
    seed: Option<ArrayView2<'_, f32>>,
    options: &DanceOptions,
    window_index: u64,
) -> anyhow::Result<Array2<f32>> {
    choreo_models::generate_package_window(package, music, seed, options, window_index)
        .context("generating a live window")
}

/// Normalised feature frames emitted so far (the seeds of later windows). Only the last window
/// is kept.
#[derive(Debug)]
pub struct EmittedFeatures {
    dim: usize,
    keep: usize,
    /// Frames `first..first + rows` of the emitted features.
    first: usize,
    rows: Vec<f32>,
}

impl EmittedFeatures {
    pub fn new(dim: usize, keep: usize) -> Self {
        Self {
            dim,
            keep,
            first: 0,
            rows: Vec::new(),
        }
    }

    /// Frames emitted so far.
    pub fn len(&self) -> usize {
        self.first + self.rows.len() / self.dim
    }

    pub fn push(&mut self, frames: ArrayView2<'_, f32>) {
        self.rows.extend(frames.iter());
        let held = self.rows.len() / self.dim;
        if held > self.keep {
            let drop = held - self.keep;
            self.rows.drain(..drop * self.dim);
            self.first += drop;
        }
    }

    /// Repeat the last frame `n` times (frames skipped when generation fell behind).
    pub fn hold(&mut self, n: usize) -> Array2<f32> {
        let last = if self.rows.is_empty() {
            vec![0.0; self.dim]
        } else {
            self.rows[self.rows.len() - self.dim..].to_vec()
        };
        let out = Array2::from_shape_fn((n, self.dim), |(_, d)| last[d]);
        self.push(out.view());
        out
    }

    /// Frames `[start, len())` (must still be held).
    pub fn since(&self, start: usize) -> Option<ArrayView2<'_, f32>> {
        if start < self.first || start > self.len() {
            return None;
        }
        let all =
            ArrayView2::from_shape((self.rows.len() / self.dim, self.dim), &self.rows).ok()?;
        Some(all.slice_move(s![start - self.first.., ..]))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn manifest() -> Manifest {
        let dir =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../models/packages/exemplar");
        Manifest::load(&dir).unwrap()
    }

    #[test]
    fn windows_end_at_the_newest_frame_and_seed_with_the_rest() {
        let m = manifest();
        // Warm-up: the window starts at 0 and ends at the newest frame.
        let p = plan_window(&m, 0, 15).unwrap();
        assert_eq!((p.start, p.end, p.mel_start), (0, 15, 0));
        // 15 frames at 30 fps = 0.5 s = 15.625 mel frames at 31.25 frames/s: frame 16 is the
        // newest frame's own (round(15.625) = 16), so 17 must be heard.
        assert_eq!(p.mel_needed, 17);
        // Steady state: W = 150 frames, new = 15, seed = the 135 emitted before.
        let p = plan_window(&m, 300, 15).unwrap();
        assert_eq!((p.start, p.end), (165, 315));
        assert_eq!(p.mel_start, (165.0f64 / 30.0 * 31.25).round() as usize);
        // The music window never asks for more than music_frames.
        assert!(p.mel_needed <= p.mel_start + m.dance_spec().unwrap().audio.music_frames);
        assert_eq!(p.mel_needed, (315.0f64 / 30.0 * 31.25).round() as usize + 1);
    }

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

    #[test]
    fn heard_mel_is_clamped_at_the_running_floor() {
        let mut h = HeardMel::new(2, 80.0);
        h.push(&[-10.0, -95.0, -20.0, -30.0]);
        assert_eq!(h.floor(), -90.0);
        let w = h.window(1, 3);
        assert_eq!(w.row(0).to_vec(), vec![-20.0, -30.0]);
        // Not heard yet: the floor.
        assert_eq!(w.row(1).to_vec(), vec![-90.0, -90.0]);
        let w = h.window(0, 1);
        assert_eq!(w.row(0).to_vec(), vec![-10.0, -90.0]);
        // Discarded frames no longer count against memory; later ones keep their indices.
        h.discard_before(1);
        assert_eq!(h.len(), 2);
        assert_eq!(h.window(1, 1).row(0).to_vec(), vec![-20.0, -30.0]);
        assert_eq!(h.floor(), -90.0);
    }

    #[test]
    fn emitted_features_keep_the_last_window() {
        let mut e = EmittedFeatures::new(2, 3);
        let a = Array2::from_shape_fn((4, 2), |(t, d)| (t * 10 + d) as f32);
        e.push(a.view());
        assert_eq!(e.len(), 4);
        assert!(e.since(0).is_none());
        assert_eq!(e.since(2).unwrap().row(0).to_vec(), vec![20.0, 21.0]);
        let held = e.hold(2);
        assert_eq!(held.row(1).to_vec(), vec![30.0, 31.0]);
        assert_eq!(e.len(), 6);
        assert_eq!(e.since(5).unwrap().row(0).to_vec(), vec![30.0, 31.0]);
    }
}
