//! Live dance (pipeline): log-mel frames in as they are heard, new motion frames out, one window
//! per hop, on the offline dance's window plan ([`super::window`]).
//!
//! Every hop the newest window is generated: it ends at motion frame `E = N + hop` (N = frames
//! emitted so far) and starts at `S = max(0, E - W)`. The frames already emitted in `[S, N)` are
//! its in-painted seed (known at every step), so only `[N, E)` is new and only those are
//! emitted. Before the first full window (E < W) the window starts at 0 and its music past the
//! newest heard frame is the silence floor. The window's music is the mel frames from
//! `round(S / fps · sr / hop)` on, as in the offline pipeline ([`mel_frame_at`], [`cut_music`]).
//! New frames are decoded, carried on from the last pose shown ([`carry_on`]: placed onto its
//! root and facing, the difference faded out over the new frames, so a window that does not
//! continue its seed does not jump) and fitted to the session's rigid skeleton (bone lengths
//! fixed from the first frames, [`RigidFitter`]).

use std::time::{Duration, Instant};

use ndarray::{Array2, Array3, ArrayView2, Axis, s};

use choreo_datasets::{RigidFitter, RigidPose, SkeletonKind};

use crate::diffusion::sampler::Denoiser;
use crate::error::{Error, Result};
use crate::package::ModelPackage;
use crate::package::manifest::{Manifest, Role};
use crate::pipelines::dance::{DanceDenoiser, DanceOptions, carry_on, decode_features};
use crate::pipelines::window::{cut_music, generate_window, mel_frame_at};

/// A live dance: fed log-mel frames ([`LiveDance::push_mel`]), it generates the newest window
/// whenever the music for it has been heard ([`LiveDance::step`]).
#[derive(Debug)]
pub struct LiveDance {
    manifest: Manifest,
    /// New frames per window when generation keeps up.
    hop: usize,
    mel: HeardMel,
    emitted: EmittedFeatures,
    skeleton: SkeletonKind,
    /// Made from the first frames emitted; every later frame is fitted to its bone lengths.
    fitter: Option<RigidFitter>,
    /// Windows generated (each draws its noise from its own stream).
    windows: u64,
    /// The last pose shown (joints (24, 3), before the rigid fit): held frames repeat it, new
    /// frames carry on from it.
    shown: Option<Array2<f32>>,
}

/// Where one live window is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub struct LiveWindow {
    /// First motion frame of the window.
    pub start: usize,
    /// One past the last new frame (`start + window` once the first full window is reached).
    pub end: usize,
    /// First mel frame of the window's music.
    pub mel_start: usize,
    /// Mel frames that must have been heard before the window can be generated: the newest
    /// motion frame's own mel frame, or the window's whole music if that comes first.
    pub mel_needed: usize,
}

/// Motion frames `first..first + pose.joints.len()`, fitted to the session's skeleton.
#[derive(Debug, Clone)]
#[non_exhaustive]
pub struct LiveFrames {
    pub first: usize,
    pub pose: RigidPose,
}

/// What one [`LiveDance::step`] made.
#[derive(Debug, Clone)]
#[non_exhaustive]
pub struct LiveStep {
    /// Generation fell behind the music by more than a window can catch up: these frames hold
    /// the last pose (they are late by definition).
    pub held: Option<LiveFrames>,
    /// The window's new frames.
    pub fresh: LiveFrames,
    /// The window they came from.
    pub window: LiveWindow,
    /// Time spent denoising the window.
    pub denoise: Duration,
}

impl LiveDance {
    /// A live dance on `manifest`'s package with `hop` new frames per window (1 to half a
    /// window, so half of every window stays seed).
    pub fn new(manifest: &Manifest, hop: usize) -> Result<Self> {
        let dance = manifest.dance_spec()?;
        let window = dance.window_frames;
        if hop == 0 || hop > window / 2 {
            return Err(Error::Input {
                what: "live hop".into(),
                reason: format!("{hop} frames; 1 to half the package's {window}-frame window"),
            });
        }
        let Some(skeleton) = manifest.motion.skeleton_kind() else {
            return Err(Error::Manifest {
                package: manifest.dir().to_path_buf(),
                key: "motion.skeleton".into(),
                reason: format!("{:?} has no motion-file layout", manifest.motion.skeleton),
            });
        };
        Ok(Self {
            manifest: manifest.clone(),
            hop,
            mel: HeardMel::new(dance.audio.n_mels, dance.audio.top_db as f32),
            emitted: EmittedFeatures::new(manifest.motion.dim, window),
            skeleton,
            fitter: None,
            windows: 0,
            shown: None,
        })
    }

    /// Log-mel frames heard next, time-major (n_mels values per frame), in dB before the
    /// `top_db` clamp.
    pub fn push_mel(&mut self, frames: &[f32]) -> Result<()> {
        let n_mels = self.mel.n_mels();
        let whole = ArrayView2::from_shape((frames.len() / n_mels, n_mels), frames)
            .ok()
            .filter(|_| frames.len().is_multiple_of(n_mels));
        let Some(frames) = whole else {
            return Err(Error::Input {
                what: "live mel".into(),
                reason: format!(
                    "{} values are not whole frames of {n_mels} bands",
                    frames.len()
                ),
            });
        };
        self.mel.push(frames)
    }

    /// Mel frames heard so far.
    pub fn mel_heard(&self) -> usize {
        self.mel.len()
    }

    /// Motion frames made so far (held frames included).
    pub fn frames(&self) -> usize {
        self.emitted.len()
    }

    /// Generate the newest window with the package's denoiser; `None` (nothing done) until its
    /// music has been heard.
    pub fn step(
        &mut self,
        package: &mut ModelPackage,
        options: &DanceOptions,
    ) -> Result<Option<LiveStep>> {
        let mut denoiser = DanceDenoiser::new(package.component(Role::Denoiser)?);
        self.step_with(&mut denoiser, options)
    }

    /// [`LiveDance::step`] with any [`Denoiser`].
    pub fn step_with(
        &mut self,
        denoiser: &mut dyn Denoiser,
        options: &DanceOptions,
    ) -> Result<Option<LiveStep>> {
        let spec = self.manifest.dance_spec()?;
        let (fps, window) = (self.manifest.motion.fps, spec.window_frames);
        let (mel_rate, music_frames) = (spec.audio.frame_rate(), spec.audio.music_frames);
        let n = self.emitted.len();
        if self.mel.len() < self.plan(n, self.hop)?.mel_needed {
            return Ok(None);
        }
        // Behind? The newest frame whose mel was heard.
        let heard_end = (((self.mel.len() - 1) as f64 / mel_rate) * fps).floor() as usize;
        let behind = heard_end.saturating_sub(n + self.hop);
        let mut new = self.hop;
        let mut held = None;
        if behind > 0 {
            // Catch up inside one window while at least half of it stays seed; frames beyond
            // that are skipped (the last pose held) rather than queued.
            let catch_up = behind.min(window / 2 - self.hop);
            new += catch_up;
            let skip = behind - catch_up;
            if skip > 0 {
                let frames = self.emitted.hold(skip);
                let joints = match &self.shown {
                    Some(last) => last
                        .broadcast((skip, 24, 3))
                        .expect("a (24, 3) pose")
                        .to_owned(),
                    None => decode_features(&self.manifest, frames.view())?,
                };
                held = Some(self.show(joints, n)?);
            }
        }
        let n = self.emitted.len();
        let plan = self.plan(n, new)?;
        let music = self.mel.window(plan.mel_start, music_frames);
        let seed = self
            .emitted
            .since(plan.start)
            .filter(|s| s.nrows() > 0)
            .map(|s| s.to_owned());
        let started = Instant::now();
        let features = generate_window(
            denoiser,
            &self.manifest,
            music.view(),
            seed.as_ref().map(|s| s.view()),
            options,
            self.windows,
        )?;
        let denoise = started.elapsed();
        self.windows += 1;
        let fresh = features.slice(s![n - plan.start..plan.end - plan.start, ..]);
        self.emitted.push(fresh);
        let mut joints = decode_features(&self.manifest, fresh)?;
        if let Some(last) = &self.shown {
            joints = carry_on(last.view(), joints.view());
        }
        let fresh = self.show(joints, n)?;
        // Later windows start at or after this one's start.
        self.mel.discard_before(plan.mel_start);
        Ok(Some(LiveStep {
            held,
            fresh,
            window: plan,
            denoise,
        }))
    }

    /// The window whose new frames are `[emitted, emitted + new)`.
    fn plan(&self, emitted: usize, new: usize) -> Result<LiveWindow> {
        let spec = self.manifest.dance_spec()?;
        let fps = self.manifest.motion.fps;
        let end = emitted + new;
        let start = end.saturating_sub(spec.window_frames);
        let mel_start = mel_frame_at(start, fps, spec.audio);
        // The newest motion frame's own mel frame must be heard; beyond it is the window's tail.
        let mel_needed =
            (mel_frame_at(end, fps, spec.audio) + 1).min(mel_start + spec.audio.music_frames);
        Ok(LiveWindow {
            start,
            end,
            mel_start,
            mel_needed,
        })
    }

    /// Show joint frames (frames, 24, 3) starting at frame `first`: fitted to the session's
    /// skeleton, the last one kept as the pose shown.
    fn show(&mut self, joints: Array3<f32>, first: usize) -> Result<LiveFrames> {
        if let Some(last) = joints.outer_iter().last() {
            self.shown = Some(last.to_owned());
        }
        let fitted = match &mut self.fitter {
            Some(f) => f.fit(joints.view()),
            None => RigidFitter::from_motion(&self.skeleton, joints.view())
                .and_then(|f| self.fitter.insert(f).fit(joints.view())),
        };
        let pose = fitted.map_err(|source| Error::GeneratedJoints { source })?;
        Ok(LiveFrames { first, pose })
    }
}

/// Log-mel frames heard so far, time-major, clamped like the offline path: librosa's
/// `power_to_db(top_db)` floors every value at `max - top_db` over the whole song; live, the
/// maximum is the running maximum of what was heard.
#[derive(Debug)]
struct HeardMel {
    top_db: f32,
    /// Unclamped frames `first..`, (frames, n_mels).
    frames: Array2<f32>,
    first: usize,
    max_db: f32,
}

impl HeardMel {
    fn new(n_mels: usize, top_db: f32) -> Self {
        Self {
            top_db,
            frames: Array2::zeros((0, n_mels)),
            first: 0,
            max_db: f32::NEG_INFINITY,
        }
    }

    fn n_mels(&self) -> usize {
        self.frames.ncols()
    }

    /// Append frames (k, n_mels).
    fn push(&mut self, frames: ArrayView2<'_, f32>) -> Result<()> {
        self.max_db = frames.iter().copied().fold(self.max_db, f32::max);
        self.frames
            .append(Axis(0), frames)
            .map_err(|e| Error::Input {
                what: "live mel".into(),
                reason: e.to_string(),
            })
    }

    /// Frames heard so far (including discarded ones).
    fn len(&self) -> usize {
        self.first + self.frames.nrows()
    }

    /// Forget frames before `frame` (no later window starts before it): memory stays bounded
    /// however long the session runs.
    fn discard_before(&mut self, frame: usize) {
        let drop = frame.saturating_sub(self.first).min(self.frames.nrows());
        if drop > 0 {
            self.frames = self.frames.slice(s![drop.., ..]).to_owned();
            self.first += drop;
        }
    }

    /// The silence floor: what a clamped frame of silence holds.
    fn floor(&self) -> f32 {
        if self.max_db.is_finite() {
            self.max_db - self.top_db
        } else {
            // Nothing heard yet: librosa's power_to_db of zero power with amin = 1e-10.
            -100.0
        }
    }

    /// Frames `start..start + n` (time-major, clamped at the floor); frames not heard yet (or
    /// discarded) are the floor.
    fn window(&self, start: usize, n: usize) -> Array2<f32> {
        let mut out = Array2::zeros((n, self.n_mels()));
        cut_music(
            out.view_mut(),
            self.frames.view(),
            self.first,
            start,
            self.floor(),
        );
        out
    }
}

/// Normalised feature frames emitted so far (the seeds of later windows). Only the last window
/// is kept.
#[derive(Debug)]
struct EmittedFeatures {
    dim: usize,
    keep: usize,
    /// Frames `first..first + rows` of the emitted features.
    first: usize,
    rows: Vec<f32>,
}

impl EmittedFeatures {
    fn new(dim: usize, keep: usize) -> Self {
        Self {
            dim,
            keep,
            first: 0,
            rows: Vec::new(),
        }
    }

    /// Frames emitted so far.
    fn len(&self) -> usize {
        self.first + self.rows.len() / self.dim
    }

    fn push(&mut self, frames: ArrayView2<'_, f32>) {
        self.rows.extend(frames.iter());
        let held = self.rows.len() / self.dim;
        if held > self.keep {
            let drop = held - self.keep;
            self.rows.drain(..drop * self.dim);
            self.first += drop;
        }
    }

    /// Repeat the last frame `n` times (frames skipped when generation fell behind).
    fn hold(&mut self, n: usize) -> Array2<f32> {
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
    fn since(&self, start: usize) -> Option<ArrayView2<'_, f32>> {
        if start < self.first || start > self.len() {
            return None;
        }
        let all =
            ArrayView2::from_shape((self.rows.len() / self.dim, self.dim), &self.rows).ok()?;
        Some(all.slice_move(s![start - self.first.., ..]))
    }
}

#[cfg(test)]
#[path = "live_tests.rs"]
mod tests;
