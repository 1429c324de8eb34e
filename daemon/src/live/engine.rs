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

/// Steps that fit the time budget, from the measured seconds per step, within
/// `[floor, ceiling]`.
pub fn adapt_steps(
    per_step: Option<Duration>,
    budget: Duration,
    floor: usize,
    ceiling: usize,
) -> usize {
    let floor = floor.clamp(1, ceiling.max(1));
    match per_step {
        None => ceiling.max(floor),
        Some(d) if d.is_zero() => ceiling.max(floor),
        Some(d) => ((budget.as_secs_f64() / d.as_secs_f64()).floor() as usize)
            .clamp(floor, ceiling.max(floor)),
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
    let manifest = package.manifest().clone();
    let denoiser = package
        .component(choreo_models::Role::Denoiser)
        .context("model package has no denoiser")?;
    choreo_models::generate_window(denoiser, &manifest, music, seed, options, window_index)
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

    #[test]
    fn steps_follow_the_budget_between_floor_and_ceiling() {
        let ms = Duration::from_millis;
        assert_eq!(adapt_steps(None, ms(300), 4, 20), 20);
        assert_eq!(adapt_steps(Some(ms(10)), ms(300), 4, 20), 20);
        assert_eq!(adapt_steps(Some(ms(30)), ms(300), 4, 20), 10);
        assert_eq!(adapt_steps(Some(ms(1000)), ms(300), 4, 20), 4);
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
