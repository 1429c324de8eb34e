//! Music to dance (pipeline): log-mel → overlapping windows → batched denoising with EDGE's
//! overlap consistency → stitched, de-normalised, decoded joints → the motion file
//! ([`dance_motion_file`]: joints, the song's log-mel and the provenance).
//!
//! Windows (EDGE `long_ddim_sample`, Stanford-TML/EDGE:model/diffusion.py): window w covers
//! motion frames `[w·stride, w·stride + window)`. Its music is the mel frames from
//! `round(start_s · sr / hop)` for `music_frames` frames; past the song's end they are the song's
//! silence floor, i.e. its minimum dB value (librosa's `power_to_db(top_db=80)` clips the song at
//! max - 80 dB, so the minimum is what silence looks like in this song).
//!
//! Long songs are denoised in chunks of `chunk_windows` windows, all windows of a chunk in one
//! batch. Inside a chunk, after every step but the last, the first `overlap` frames of window i+1
//! are set to the last `overlap` frames of window i (EDGE). Across a chunk border the first window
//! of chunk k is in-painted: its first `overlap` frames are known, equal to the last `overlap`
//! frames of the final sample of chunk k-1's last window, and are replaced by their
//! forward-diffused values at every step (MoFusion seed conditioning). So memory is bounded by
//! one chunk and consecutive windows agree on their shared frames everywhere. Each chunk draws its
//! noise from its own ChaCha stream (stream = chunk index), so the result depends on the seed and
//! on `chunk_windows`, and not on anything else.
//!
//! Stitching: each window is decoded to joints; over each overlap the output follows window i to
//! a switch frame, then window i+1 carrying its difference from window i there (per bone a
//! rotation, for the root a displacement), faded out linearly by the overlap's end — where EDGE
//! (`render_sample(mode="long")`) cross-fades the two windows with weights `linspace(0, 1,
//! overlap)`. Unlike a per-frame slerp between two windows that disagree, this turns no bone
//! faster than its windows do plus at most 180° over the fade ([`Stitcher`]).

use std::time::Instant;

use ndarray::{Array2, Array3, ArrayD, ArrayView1, ArrayView2, ArrayView3, Axis, Ix3, s};

use crate::diffusion::noise::NoiseSource;
use crate::diffusion::sampler::{
    Denoiser, Guidance, Known, SampleRequest, Sampler, SamplerKind, SamplerOptions,
};
use crate::diffusion::scheduler::TimestepSpacing;
use choreo_datasets::rotation::{
    QUAT_IDENTITY, Quat, Vec3, cross, dot, fit_rotation, mat_to_quat, norm, qbetween_safe, qpow,
    qrot,
};
use choreo_datasets::skeleton::SMPL24_PARENTS;
use choreo_datasets::{MelAttachment, MotionFile, Provenance};

use crate::error::{Error, Result};
use crate::package::ModelPackage;
use crate::package::manifest::{DanceSpec, Manifest, Role, SOURCE_OUTPUT};
use crate::pipelines::window::{cut_music, mel_frame_at};
use crate::runtime::component::Component;

/// Longest song accepted: 3 hours (bounds every allocation below; 20 min is the design target).
const MAX_DURATION_S: f64 = 3.0 * 3600.0;

/// Options of one generation; `None` takes the package manifest's default.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub struct DanceOptions {
    /// Seed of all noise: same seed, package and mel → identical joints. Default: 0.
    pub seed: u64,
    /// Denoising steps. Default: None (manifest `sampler.steps`).
    pub steps: Option<usize>,
    /// Guidance scale on the music, 1 = off. Default: None (manifest `sampler.guidance`).
    pub guidance: Option<f32>,
    /// DDIM or DDPM. Default: None (manifest `sampler.kind`).
    pub sampler: Option<SamplerKind>,
    /// DDIM eta. Default: None (manifest `sampler.eta`).
    pub eta: Option<f64>,
    /// Timestep spacing. Default: None (manifest `sampler.timestep_spacing`, else the
    /// scheduler's own).
    pub spacing: Option<TimestepSpacing>,
    /// Windows denoised together in one batch; bounds memory (32 windows of 150×72 are
    /// ~1.4 MB per buffer); 0 is taken as 1. Default: 32.
    pub chunk_windows: usize,
    /// Guidance rows in one batched network call (true) or one call per row group (false, to
    /// measure what batching gains). Default: true.
    pub batch_guidance: bool,
    /// x_T of every window, (windows, T, D), or (T, D) for the same x_T in every window, in
    /// the model's normalised space; with a deterministic sampler the dance is then a function
    /// of song, model and this array alone. Default: None (noise from `seed`).
    pub init_noise: Option<ArrayD<f32>>,
    /// Keep the sampler's final windows (normalised, before decoding and stitching) in
    /// [`Dance::windows`]. Default: false.
    pub keep_windows: bool,
    /// Fit the stitched joints to one rigid skeleton (constant bones and sibling spans, as BVH
    /// files and Blender need; `choreo_datasets::fit_rigid_pose`), planted feet locked first
    /// (`choreo_datasets::lock_feet`). Default: true.
    pub rigid_fit: bool,
    /// Song length in seconds; output frames = round(duration_s · fps). Default: None, i.e.
    /// `(mel frames - 1) · hop / sample_rate` (librosa has 1 + floor(samples / hop) frames, so
    /// this is within one hop below the true length; pass the decoded length when known).
    pub duration_s: Option<f64>,
}

impl Default for DanceOptions {
    fn default() -> Self {
        Self {
            seed: 0,
            steps: None,
            guidance: None,
            sampler: None,
            eta: None,
            spacing: None,
            chunk_windows: 32,
            batch_guidance: true,
            init_noise: None,
            keep_windows: false,
            rigid_fit: true,
            duration_s: None,
        }
    }
}

/// Counters of one generation.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
#[non_exhaustive]
pub struct DanceStats {
    /// Output frames.
    pub frames: usize,
    /// Windows generated.
    pub windows: usize,
    /// Chunks (batches) the windows were split into.
    pub chunks: usize,
    /// Denoising steps per chunk.
    pub steps: usize,
    /// Network evaluations (batched calls).
    pub evaluations: usize,
    /// Batch rows evaluated (windows × steps × guidance rows).
    pub rows: usize,
    /// Seconds inside ONNX Runtime (or the denoiser, for non-ONNX denoisers).
    pub ort_seconds: f64,
    /// Runs of the denoiser's hoisted prologue (the work that depends on the music alone; 0
    /// when the whole graph runs at every step), see [`crate::Hoisting`].
    pub prologue_runs: usize,
    /// Seconds for the whole generation.
    pub total_seconds: f64,
}

/// A generated dance.
#[derive(Debug, Clone)]
#[non_exhaustive]
pub struct Dance {
    /// World joint positions (T, 24, 3), metres, y-up.
    pub joints: Array3<f32>,
    /// Frames per second of `joints`.
    pub fps: f64,
    /// The sampler's final windows (windows, T, D), normalised, when
    /// [`DanceOptions::keep_windows`].
    pub windows: Option<Array3<f32>>,
    /// Per window, the `[library]` clip it was played from (the package's `source` output);
    /// empty for packages without one.
    pub sources: Vec<usize>,
    /// Counters.
    pub stats: DanceStats,
}

/// A music-to-dance package's denoiser [`Component`] as a [`Denoiser`]: the task's named
/// tensors (x_t, t, music, cond → pred; models/packages/README.md) through [`Component::run`],
/// a non-finite output naming the timestep of the call.
#[derive(Debug)]
pub struct DanceDenoiser<'a>(&'a mut Component);

impl<'a> DanceDenoiser<'a> {
    /// The denoiser `component` of a music-to-dance package.
    pub fn new(component: &'a mut Component) -> Self {
        Self(component)
    }
}

impl Denoiser for DanceDenoiser<'_> {
    fn predict(
        &mut self,
        x_t: ArrayView3<'_, f32>,
        t: &[i64],
        music: ArrayView3<'_, f32>,
        cond: &[f32],
    ) -> Result<Array3<f32>> {
        let outputs = self.0.run(&[
            ("x_t", x_t.into()),
            ("t", ArrayView1::from(t).into()),
            ("music", music.into()),
            ("cond", ArrayView1::from(cond).into()),
        ]);
        let pred = match outputs {
            Ok(mut outputs) => outputs.take("pred")?,
            Err(Error::NonFinite {
                package,
                component,
                tensor,
                count,
                timestep: None,
            }) => {
                return Err(Error::NonFinite {
                    package,
                    component,
                    tensor,
                    count,
                    timestep: t.first().copied(),
                });
            }
            Err(e) => return Err(e),
        };
        pred.into_dimensionality::<Ix3>()
            .map_err(|_| self.0.tensor_err("pred", "not 3-D".into()))
    }

    fn finish_batch(&mut self) {
        self.0.finish_batch();
    }

    /// The package's optional `source` output for the finished windows, run once at t = 0
    /// with the music (where the posterior is the window itself).
    fn sources(
        &mut self,
        x0: ArrayView3<'_, f32>,
        music: ArrayView3<'_, f32>,
    ) -> Result<Option<Vec<usize>>> {
        if !self
            .0
            .spec()
            .outputs
            .iter()
            .any(|o| o.name == SOURCE_OUTPUT)
        {
            return Ok(None);
        }
        let n = x0.dim().0;
        let (t, cond) = (vec![0i64; n], vec![1.0f32; n]);
        let mut outputs = self.0.run(&[
            ("x_t", x0.into()),
            ("t", ArrayView1::from(&t).into()),
            ("music", music.into()),
            ("cond", ArrayView1::from(&cond).into()),
        ])?;
        self.0.finish_batch();
        let source = outputs.take(SOURCE_OUTPUT)?;
        // Clip indices are small whole numbers in float32; anything else is not an index.
        source
            .iter()
            .map(|&v| {
                (v >= 0.0 && v.fract() == 0.0 && v < 1e6)
                    .then_some(v as usize)
                    .ok_or_else(|| {
                        self.0
                            .tensor_err(SOURCE_OUTPUT, format!("{v} is not a clip index"))
                    })
            })
            .collect::<Result<Vec<_>>>()
            .map(Some)
    }
}

/// Generate a dance for a whole song with the package's denoiser. `mel` is (n_mels, F) in dB,
/// librosa layout, at the manifest's audio parameters. `progress(done, total)` counts steps over
/// all chunks.
pub fn generate_dance(
    package: &mut ModelPackage,
    mel: ArrayView2<'_, f32>,
    options: &DanceOptions,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<Dance> {
    let manifest = package.manifest().clone();
    let ort_before = package.ort_seconds();
    let prologue_runs = |p: &mut ModelPackage| -> Result<usize> {
        Ok(p.component(Role::Denoiser)?
            .hoisting()
            .map_or(0, |h| h.prologue_runs))
    };
    let runs_before = prologue_runs(package)?;
    let mut denoiser = DanceDenoiser::new(package.component(Role::Denoiser)?);
    let mut dance = generate_dance_with(&mut denoiser, &manifest, mel, options, progress)?;
    dance.stats.ort_seconds = package.ort_seconds() - ort_before;
    dance.stats.prologue_runs = prologue_runs(package)? - runs_before;
    Ok(dance)
}

/// [`generate_dance`] with any [`Denoiser`] (e.g. [`crate::ExemplarDenoiser`]).
pub fn generate_dance_with(
    denoiser: &mut dyn Denoiser,
    manifest: &Manifest,
    mel: ArrayView2<'_, f32>,
    options: &DanceOptions,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<Dance> {
    let started = Instant::now();
    let dance = manifest.dance_spec()?;
    let plan = WindowPlan::new(manifest, mel, options)?;
    let sampler = make_sampler(manifest, options)?;
    let (w, d) = (dance.window_frames, manifest.motion.dim);
    let overlap = dance.overlap_frames();
    let chunk = options.chunk_windows.max(1);
    let n_chunks = plan.windows.div_ceil(chunk);
    let steps = sampler.timesteps().len();
    let mut stitched = Stitcher::new(plan.frames, w, dance.stride_frames);
    let mut stats = DanceStats {
        frames: plan.frames,
        windows: plan.windows,
        chunks: n_chunks,
        steps,
        ..Default::default()
    };
    let init_noise = options
        .init_noise
        .as_ref()
        .map(|a| init_noise(a, plan.windows, w, d))
        .transpose()?;
    let mut windows = options
        .keep_windows
        .then(|| Array3::<f32>::zeros((plan.windows, w, d)));
    let mut previous_tail: Option<Array2<f32>> = None;
    let mut sources = Vec::new();
    for k in 0..n_chunks {
        let first = k * chunk;
        let count = chunk.min(plan.windows - first);
        let music = plan.music_batch(dance, manifest.motion.fps, mel, first, count);
        // Chunk border: the previous window's tail is known for this chunk's first window.
        let mut values = Array3::<f32>::zeros((count, w, d));
        let mut mask = Array3::from_elem((count, w, d), false);
        if let Some(tail) = &previous_tail {
            values.slice_mut(s![0, ..overlap, ..]).assign(tail);
            mask.slice_mut(s![0, ..overlap, ..]).fill(true);
        }
        let init = init_noise.as_ref().map(|a| match a.dim().0 {
            1 => Array3::from_shape_fn((count, w, d), |(_, f, c)| a[[0, f, c]]),
            _ => a.slice(s![first..first + count, .., ..]).to_owned(),
        });
        let request = SampleRequest {
            music: music.view(),
            window: (w, d),
            known: previous_tail.as_ref().map(|_| Known {
                values: values.view(),
                mask: mask.view(),
                // Guided, not pasted: a window that does not continue the previous tail exactly
                // would otherwise jump where the pasted frames end; the stitcher joins them.
                exact: false,
            }),
            chain_overlap: overlap,
            init: init.as_ref().map(|a| a.view()),
        };
        let mut noise = NoiseSource::new(options.seed, k as u64);
        let done_before = k * steps;
        let total = n_chunks * steps;
        let (x, s) = sampler.sample(denoiser, &request, &mut noise, &mut |done, _| {
            progress(done_before + done, total)
        })?;
        stats.evaluations += s.calls;
        stats.rows += s.rows;
        stats.ort_seconds += s.denoiser_seconds;
        if overlap > 0 {
            previous_tail = Some(x.slice(s![count - 1, w - overlap.., ..]).to_owned());
        }
        if let Some(used) = denoiser.sources(x.view(), music.view())? {
            sources.extend(used);
        }
        for (i, window) in x.outer_iter().enumerate() {
            let joints = decode_features(manifest, window)?;
            stitched.add(first + i, plan.windows, joints.view());
        }
        if let Some(all) = &mut windows {
            all.slice_mut(s![first..first + count, .., ..]).assign(&x);
        }
    }
    // Stitching turns each bone's direction on its own, which bends sibling spans (collar,
    // hip) by millimetres; a rigid fit makes every frame a pose of one skeleton, which BVH
    // files and Blender can reproduce (issue 12 item 15).
    let joints = match manifest.motion.skeleton_kind() {
        Some(kind) if options.rigid_fit => rigid_dance(&kind, stitched.out, manifest.motion.fps)?,
        _ => stitched.out,
    };
    stats.total_seconds = started.elapsed().as_secs_f64();
    Ok(Dance {
        joints,
        fps: manifest.motion.fps,
        windows,
        sources,
        stats,
    })
}

/// The stitched `joints` (frames, joints, 3) with planted feet locked (`choreo_datasets::lock_feet`)
/// and fitted to one rigid skeleton (`choreo_datasets::fit_rigid_pose`), each frame then lifted,
/// if need be, so that its lowest joint is no lower than the stitched frame's. The fit restores
/// every bone's length, and a frame mixed from several poses (a package's x0 is a weighted mean
/// of candidates; a transition turns legs part of the way) has shorter legs than the skeleton:
/// restored from the hips down they reach below the floor (issue 24: toes 3.5 mm below it on a
/// 153 s song, stitched frames and raw windows never below it). The stitcher keeps every frame
/// no lower than its windows, so with the lift every frame is at least as high as what the model
/// made. A vertical move keeps the frame rigid and every bone's direction, so no bone turns.
fn rigid_dance(
    kind: &choreo_datasets::SkeletonKind,
    mut joints: Array3<f32>,
    fps: f64,
) -> Result<Array3<f32>> {
    let stitched_low: Vec<f32> = joints.outer_iter().map(lowest_joint).collect();
    choreo_datasets::lock_feet(&mut joints, fps);
    let mut fitted = choreo_datasets::fit_rigid_pose(kind, joints.view())
        .map_err(|source| Error::GeneratedJoints { source })?
        .joints;
    for (mut pose, low) in fitted.outer_iter_mut().zip(stitched_low) {
        let lift = low - lowest_joint(pose.view());
        if lift > 0.0 {
            pose.column_mut(1).mapv_inplace(|y| y + lift);
        }
    }
    Ok(fitted)
}

/// The height (y) of a pose's (joints, 3) lowest joint.
fn lowest_joint(pose: ArrayView2<'_, f32>) -> f32 {
    pose.column(1).fold(f32::INFINITY, |m, &y| m.min(y))
}

/// Where a dance came from, beyond the song's mel and the options: what the pipeline cannot
/// know itself, recorded in the motion file's provenance.
#[derive(Debug, Clone, Default)]
#[non_exhaustive]
pub struct DanceSource {
    /// The song's file name.
    pub name: String,
    /// sha256 of the song file (hex).
    pub sha256: String,
    /// sha256 of the package's manifest (hex).
    pub model_sha256: String,
    /// sha256 of the initial-noise file (hex); "" when the noise came from the seed.
    pub init_noise_sha256: String,
    /// When the job started (ISO-8601 UTC).
    pub started_utc: String,
    /// What was wrong with the song when only part of it decoded (provenance
    /// `source_damage`); `None` when it decoded whole.
    pub damage: Option<String>,
    /// Why the song had no beat to follow and what was danced instead (provenance
    /// `source_beat`); `None` when it had one.
    pub beat: Option<String>,
}

/// The motion file of `dance`: its joints on the package's skeleton, the song's log-mel `mel`
/// ((n_mels, F), dB, as generated from) under `/audio/mel` with the manifest's feature
/// parameters, and a provenance naming everything the dance depends on — the sampler and its
/// settings resolved against the manifest's defaults as generation resolved them, the seed,
/// the chunk size and `source`. `finished_utc` is now.
pub fn dance_motion_file(
    manifest: &Manifest,
    options: &DanceOptions,
    dance: Dance,
    mel: ArrayView2<'_, f32>,
    source: DanceSource,
) -> Result<MotionFile> {
    let a = manifest.dance_spec()?.audio;
    let Some(skeleton) = manifest.motion.skeleton_kind() else {
        return Err(Error::Manifest {
            package: manifest.dir().to_path_buf(),
            key: "motion.skeleton".into(),
            reason: format!("{:?} has no motion-file layout", manifest.motion.skeleton),
        });
    };
    let sampler = sampler_options(manifest, options)?;
    let mut motion = MotionFile::from_joints(dance.fps as f32, skeleton, dance.joints);
    motion.mel = Some(MelAttachment {
        data: mel.t().as_standard_layout().to_owned(),
        sample_rate: a.sample_rate,
        n_fft: a.n_fft as u32,
        hop: a.hop as u32,
        fmin: a.fmin as f32,
        fmax: a.fmax as f32,
    });
    motion.provenance = Some(Provenance {
        source_name: source.name,
        source_sha256: source.sha256,
        model_name: manifest.name.clone(),
        model_sha256: source.model_sha256,
        sampler: sampler.kind.as_str().to_string(),
        steps: dance.stats.steps as u32,
        // eta only moves DDIM.
        eta: match sampler.kind {
            SamplerKind::Ddim => sampler.eta,
            _ => 0.0,
        },
        guidance: options.guidance.unwrap_or(manifest.sampler.guidance),
        content_guidance: None,
        style_guidance: None,
        seed: options.seed,
        chunk_windows: options.chunk_windows.max(1) as u32,
        init_noise_sha256: source.init_noise_sha256,
        started_utc: source.started_utc,
        finished_utc: choreo_datasets::now_utc(),
        style: None,
        license: manifest.license_line(),
        source_damage: source.damage,
        source_kind: None,
        source_beat: source.beat,
        library: manifest.library_line(&dance.sources),
    });
    Ok(motion)
}

/// The initial noise as (windows, T, D) or (1, T, D), checked against the song's windows.
fn init_noise(a: &ArrayD<f32>, windows: usize, w: usize, d: usize) -> Result<Array3<f32>> {
    let bad = |reason: String| Error::Input {
        what: "initial noise".into(),
        reason,
    };
    let shaped = match *a.shape() {
        [t, dim] if t == w && dim == d => a.to_shape((1, w, d)).map(|v| v.to_owned()),
        [n, t, dim] if (n == windows || n == 1) && t == w && dim == d => {
            a.to_shape((n, w, d)).map(|v| v.to_owned())
        }
        _ => {
            let dims: Vec<String> = a.shape().iter().map(usize::to_string).collect();
            return Err(bad(format!(
                "shape ({}); this song and package need ({windows}, {w}, {d}) or ({w}, {d})",
                dims.join(", ")
            )));
        }
    }
    .map_err(|e| bad(e.to_string()))?;
    if shaped.iter().any(|v| !v.is_finite()) {
        return Err(bad("contains NaN or infinite values".into()));
    }
    Ok(shaped)
}

/// Normalised `smpl24-rootpos-rootrel` features (T, 72) → world joints (T, 24, 3):
/// de-normalise (x · std + mean), then joint 0 = root, joint j = root + offset j.
pub fn decode_features(manifest: &Manifest, features: ArrayView2<'_, f32>) -> Result<Array3<f32>> {
    let m = &manifest.motion;
    if features.ncols() != m.dim || m.dim != 72 {
        return Err(Error::Input {
            what: "features".into(),
            reason: format!(
                "{} columns; smpl24-rootpos-rootrel has 72",
                features.ncols()
            ),
        });
    }
    let frames = features.nrows();
    let mut joints = Array3::<f32>::zeros((frames, 24, 3));
    for (f, row) in features.outer_iter().enumerate() {
        let v = |i: usize| row[i] * m.std[i] + m.mean[i];
        let root = [v(0), v(1), v(2)];
        for j in 0..24 {
            for c in 0..3 {
                joints[[f, j, c]] = if j == 0 {
                    root[c]
                } else {
                    root[c] + v(3 + 3 * (j - 1) + c)
                };
            }
        }
    }
    Ok(joints)
}

pub(super) fn make_sampler(manifest: &Manifest, options: &DanceOptions) -> Result<Sampler> {
    let o = sampler_options(manifest, options)?;
    // The manifest's own values were validated at load, so a failure here comes from the
    // caller's overrides (e.g. --steps above train_steps): an input error, not a broken package.
    Sampler::new(manifest.schedule()?, o).map_err(|e| match e {
        Error::Schedule { reason } => Error::Input {
            what: "sampler options".into(),
            reason,
        },
        other => other,
    })
}

/// The manifest's sampler defaults with the caller's overrides.
fn sampler_options(manifest: &Manifest, options: &DanceOptions) -> Result<SamplerOptions> {
    let mut o = manifest.sampler_options();
    if let Some(kind) = options.sampler {
        o.kind = kind;
    }
    if let Some(steps) = options.steps {
        o.steps = steps;
    }
    if let Some(eta) = options.eta {
        o.eta = eta;
    }
    if options.spacing.is_some() {
        o.spacing = options.spacing;
    }
    if let Some(g) = options.guidance {
        if !(g.is_finite() && g >= 0.0) {
            return Err(Error::Input {
                what: "guidance".into(),
                reason: format!("must be >= 0, got {g}"),
            });
        }
        o.guidance = Guidance::from_scale(g);
    }
    o.batch_guidance = options.batch_guidance;
    Ok(o)
}

/// Where the windows of a song are (their music: [`mel_frame_at`], [`cut_music`], shared with
/// live input).
#[derive(Debug)]
struct WindowPlan {
    frames: usize,
    windows: usize,
    stride: usize,
    floor_db: f32,
}

impl WindowPlan {
    fn new(manifest: &Manifest, mel: ArrayView2<'_, f32>, options: &DanceOptions) -> Result<Self> {
        let dance = manifest.dance_spec()?;
        let a = dance.audio;
        let m = &manifest.motion;
        let bad = |reason: String| {
            Err(Error::Input {
                what: "mel".into(),
                reason,
            })
        };
        if mel.nrows() != a.n_mels {
            return bad(format!(
                "has {} bands, the package needs {} (shape (n_mels, frames))",
                mel.nrows(),
                a.n_mels
            ));
        }
        if mel.ncols() == 0 {
            return bad("has no frames".into());
        }
        if mel.iter().any(|v| !v.is_finite()) {
            return bad("contains NaN or infinite values".into());
        }
        let duration = options
            .duration_s
            .unwrap_or((mel.ncols() - 1) as f64 / a.frame_rate());
        if !(duration.is_finite() && duration > 0.0 && duration <= MAX_DURATION_S) {
            return bad(format!(
                "duration {duration:.3} s is outside (0, {MAX_DURATION_S}] s"
            ));
        }
        let frames = ((duration * m.fps).round() as usize).max(1);
        let (w, stride) = (dance.window_frames, dance.stride_frames);
        let windows = if frames <= w {
            1
        } else {
            (frames - w).div_ceil(stride) + 1
        };
        let floor_db = mel.iter().copied().fold(f32::INFINITY, f32::min);
        Ok(Self {
            frames,
            windows,
            stride,
            floor_db,
        })
    }

    /// Music of windows `first..first + count`, (count, music_frames, n_mels) time-major.
    fn music_batch(
        &self,
        dance: DanceSpec<'_>,
        fps: f64,
        mel: ArrayView2<'_, f32>,
        first: usize,
        count: usize,
    ) -> Array3<f32> {
        let a = dance.audio;
        let mut out = Array3::<f32>::zeros((count, a.music_frames, a.n_mels));
        for (i, music) in out.outer_iter_mut().enumerate() {
            let start = mel_frame_at((first + i) * self.stride, fps, a);
            cut_music(music, mel.t(), 0, start, self.floor_db);
        }
        out
    }
}

/// Parent of SMPL joint `j` >= 1 (the one table: `choreo_datasets::skeleton`); every parent
/// index is below its child's.
fn smpl_parent(j: usize) -> usize {
    SMPL24_PARENTS[j] as usize
}

/// Joins decoded windows into one motion (EDGE `render_sample(mode="long")` joins them by
/// cross-fading each overlap). Over the overlap of windows i and i+1 the output follows window i
/// up to a switch frame, then window i+1 carrying the difference it had from window i there —
/// per bone the rotation taking i+1's bone onto i's, for the root its height — faded out
/// linearly to nothing at the overlap's last frame (an inertialization: D. Bollo, "Inertialization:
/// High-Performance Animation Transitions in Gears of War", GDC 2018).
///
/// Where the body is and which way it faces are not faded but kept: window i+1 is turned about
/// the vertical and moved as a whole so that, at the switch frame, its root meets window i's and
/// its hips face the same way. Fading a displacement would slide the whole body, planted feet
/// included, across the floor (issue 24: the library's windows, each where and facing where its
/// clip was danced, skated in 0.1 % of their frame steps on their own and in 3.7 % once faded);
/// fading a turn of the whole body bone by bone bends the pelvis out of shape, and the rigid fit
/// of such a pelvis can spin it by 70° in one frame.
///
/// Each bone's correction is a rotation about a fixed axis (for the pelvis's and the chest's
/// bones, the one they share with their siblings followed by their own), shrinking by equal
/// steps, so a bone turns between two frames by at most what its window turns plus the
/// correction's angles over the fade's frames: with EDGE's 75-frame overlap at most
/// 180° / 74 = 2.4° for a limb, twice that for a bone with siblings. A per-frame
/// slerp between the two windows, as this did before, cannot promise that: between two nearly
/// opposite bones the great circle is decided by the small part where they differ, which flips
/// side from one frame to the next and swings the half-way bone by up to 180° (issue 24: a
/// forearm turning 115° in 1/30 s where two windows disagreed by 170°).
struct Stitcher {
    out: Array3<f32>,
    window: usize,
    stride: usize,
    /// The previous window's last `overlap` frames, waiting for the next window.
    pending: Option<Array3<f32>>,
}

impl Stitcher {
    fn new(frames: usize, window: usize, stride: usize) -> Self {
        Self {
            out: Array3::zeros((frames, 24, 3)),
            window,
            stride,
            pending: None,
        }
    }

    /// Add window `i` of `windows`, as joints (window, 24, 3); windows come in order.
    fn add(&mut self, i: usize, windows: usize, joints: ArrayView3<'_, f32>) {
        let overlap = self.window - self.stride;
        let start = i * self.stride;
        let frames = self.out.dim().0;
        let mut joints = joints.to_owned();
        if let Some(prev) = self.pending.take() {
            let n = overlap.min(frames.saturating_sub(start));
            if n > 0 {
                let (from, to) = (prev.slice(s![..n, .., ..]), joints.slice(s![..n, .., ..]));
                let switch = switch_frame(from, to);
                Placement::onto(
                    from.index_axis(Axis(0), switch),
                    to.index_axis(Axis(0), switch),
                )
                .place(&mut joints);
                let joined = transition(
                    prev.slice(s![..n, .., ..]),
                    joints.slice(s![..n, .., ..]),
                    switch,
                );
                self.out
                    .slice_mut(s![start..start + n, .., ..])
                    .assign(&joined);
            }
        }
        let lo = if i > 0 { overlap } else { 0 };
        let hi = if i + 1 < windows {
            self.stride
        } else {
            self.window
        };
        for j in lo..hi {
            if start + j >= frames {
                break;
            }
            self.out
                .index_axis_mut(Axis(0), start + j)
                .assign(&joints.index_axis(Axis(0), j));
        }
        if i + 1 < windows && overlap > 0 {
            self.pending = Some(joints.slice(s![self.stride.., .., ..]).to_owned());
        }
    }
}

/// The overlap of two windows, `from` (n, 24, 3) handing over to `to` (same frames): `from`
/// up to `switch` (from [`switch_frame`]), then `to` with the difference at the switch faded out
/// linearly by the last frame (which is `to`'s own), never lower than both windows. A single
/// shared frame is `from`'s (EDGE's `linspace(0, 1, 1)` gives it weight 0).
fn transition(from: ArrayView3<'_, f32>, to: ArrayView3<'_, f32>, switch: usize) -> Array3<f32> {
    let n = from.dim().0;
    let mut out = from.to_owned();
    if n < 2 {
        return out;
    }
    let offset = PoseOffset::between(
        from.index_axis(Axis(0), switch),
        to.index_axis(Axis(0), switch),
    );
    let steps = (n - 1 - switch) as f32;
    for f in switch..n {
        let keep = 1.0 - (f - switch) as f32 / steps;
        let mut pose = offset.apply(to.index_axis(Axis(0), f), keep);
        // Legs turned part of the way between two stances can reach below both (3 cm on issue
        // 24's song): lift the pose so it goes no lower than the lower of the two windows.
        let floor =
            lowest_joint(from.index_axis(Axis(0), f)).min(lowest_joint(to.index_axis(Axis(0), f)));
        let lift = (floor - lowest_joint(pose.view())).max(0.0);
        pose.column_mut(1).mapv_inplace(|y| y + lift);
        out.index_axis_mut(Axis(0), f).assign(&pose);
    }
    out
}

/// A live window's new frames `fresh` (n, 24, 3) carried on from `shown`, the last pose shown:
/// the frame before them (extrapolated back from their first two) is placed onto `shown`'s root
/// and facing, and the pose difference left there is faded out by their last frame — the
/// hand-over between two offline windows ([`Stitcher`]) over the hop instead of the overlap, so
/// a bone turns between two frames by at most what the window turns plus its correction's
/// angles over n (the rotation shared with its siblings, then its own: at most 2 x 180° / n,
/// 24° at the default hop of 15 frames). Live, a
/// window's seed frames are its exact start, so where its new frames do not continue them (the
/// `library` package plays whichever candidate fits its first half best) they would jump: up to
/// 160° a frame at every 0.5 s hop before this.
pub(super) fn carry_on(shown: ArrayView2<'_, f32>, fresh: ArrayView3<'_, f32>) -> Array3<f32> {
    let n = fresh.dim().0;
    let mut to = Array3::<f32>::zeros((n + 1, 24, 3));
    to.slice_mut(s![1.., .., ..]).assign(&fresh);
    let before = if n >= 2 {
        &fresh.index_axis(Axis(0), 0) * 2.0 - fresh.index_axis(Axis(0), 1)
    } else {
        fresh.index_axis(Axis(0), 0).to_owned()
    };
    to.index_axis_mut(Axis(0), 0).assign(&before);
    Placement::onto(shown, before.view()).place(&mut to);
    let from = shown.broadcast((n + 1, 24, 3)).expect("a (24, 3) pose");
    transition(from, to.view(), 0).slice_move(s![1.., .., ..])
}

/// A turn about the vertical and a horizontal move placing one pose's root and facing onto
/// another's.
struct Placement {
    /// Cosine and sine of the turn.
    turn: (f32, f32),
    /// The placed pose's root (x, z), and where it goes.
    pivot: [f32; 2],
    target: [f32; 2],
}

impl Placement {
    /// The placement taking `to`'s root onto `from`'s and its facing onto `from`'s.
    fn onto(from: ArrayView2<'_, f32>, to: ArrayView2<'_, f32>) -> Self {
        let turn = match (facing(from), facing(to)) {
            (Some(a), Some(b)) => (b - a).sin_cos(),
            _ => (0.0, 1.0),
        };
        Self {
            turn: (turn.1, turn.0),
            pivot: [to[[0, 0]], to[[0, 2]]],
            target: [from[[0, 0]], from[[0, 2]]],
        }
    }

    /// Turn and move every point of `joints` (frames, joints, 3).
    fn place(&self, joints: &mut Array3<f32>) {
        for mut point in joints.lanes_mut(Axis(2)) {
            let [x, z] = self.apply([point[0], point[2]]);
            point[0] = x;
            point[2] = z;
        }
    }

    /// Where a point's (x, z) goes: turned about the pivot by `turn` (x' = c x + s z,
    /// z' = -s x + c z: about +y), then moved with the pivot onto the target.
    fn apply(&self, [x, z]: [f32; 2]) -> [f32; 2] {
        let (c, s) = self.turn;
        let (dx, dz) = (x - self.pivot[0], z - self.pivot[1]);
        [
            self.target[0] + c * dx + s * dz,
            self.target[1] - s * dx + c * dz,
        ]
    }
}

/// The heading of a pose's hips (left hip minus right hip, SMPL joints 1 and 2) in the
/// horizontal plane, radians from +x toward +z; none when the hips are nearly vertical (lying
/// on one side), where a heading means nothing.
fn facing(pose: ArrayView2<'_, f32>) -> Option<f32> {
    let (x, z) = (pose[[1, 0]] - pose[[2, 0]], pose[[1, 2]] - pose[[2, 2]]);
    (x.hypot(z) > 0.02).then(|| z.atan2(x))
}

/// Where in an overlap of n frames to hand over: among the first half (so the correction fades
/// over at least half the overlap), the frame where the correction adds the least turn per
/// frame — the largest angle between the two windows' bones there, once `to` is turned to
/// `from`'s facing, over the frames left to fade it — the earliest on ties. At frame 0 that is at most
/// 180° / (n - 1), so the choice never does worse than handing over at once; windows that agree
/// exactly somewhere hand over there with no correction at all.
fn switch_frame(from: ArrayView3<'_, f32>, to: ArrayView3<'_, f32>) -> usize {
    let n = from.dim().0;
    if n < 2 {
        return 0;
    }
    let mut best = (f32::INFINITY, 0);
    for f in 0..=(n - 1) / 2 {
        let (a, b) = (from.index_axis(Axis(0), f), to.index_axis(Axis(0), f));
        let place = Placement::onto(a, b);
        let turned = |v: Vec3| {
            let [x, z] = place.apply([v[0] + place.pivot[0], v[2] + place.pivot[1]]);
            [x - place.target[0], v[1], z - place.target[1]]
        };
        let worst = (1..24)
            .map(|j| angle_between(bone(a, j), turned(bone(b, j))))
            .fold(0f32, f32::max);
        let rate = worst / (n - 1 - f) as f32;
        if rate < best.0 {
            best = (rate, f);
        }
    }
    best.1
}

/// Bone `j` of a pose (24, 3): joint minus parent.
fn bone(pose: ArrayView2<'_, f32>, j: usize) -> Vec3 {
    let p = smpl_parent(j);
    [0, 1, 2].map(|c| pose[[j, c]] - pose[[p, c]])
}

/// Angle between two vectors, radians; atan2 of |cross| and dot is accurate near 0 and π alike.
fn angle_between(u: Vec3, v: Vec3) -> f32 {
    norm(cross(u, v)).atan2(dot(u, v))
}

/// What one pose differs from another by: the root's displacement, and per bone the rotation
/// taking the other's bone direction onto this one's and the difference in length.
struct PoseOffset {
    root: Vec3,
    /// Per bone, the rotation it shares with its siblings (identity for an only child).
    shared: [Quat; 24],
    turns: [Quat; 24],
    lengths: [f32; 24],
}

impl PoseOffset {
    /// The offset that [`PoseOffset::apply`] with `keep = 1` turns `to` into `from`. Bones
    /// that share a parent (the pelvis's hips and spine, the chest's neck and collars) turn
    /// together, by the rotation that best takes `to`'s onto `from`'s: turned one by one
    /// towards two differently leaning bodies, they would bend the pelvis out of shape half-way,
    /// and the rigid fit of such a pelvis moves the hips, and the legs hanging from them, by
    /// centimetres (issue 24: toes 6 cm below the floor).
    /// Each bone's turn is that shared rotation followed by what is left to its own direction
    /// (nothing when the two bodies' shapes are congruent, as poses of one skeleton are).
    fn between(from: ArrayView2<'_, f32>, to: ArrayView2<'_, f32>) -> Self {
        let mut shared = [QUAT_IDENTITY; 24];
        for parent in 0..24 {
            let siblings: Vec<usize> = (1..24).filter(|&j| smpl_parent(j) == parent).collect();
            if siblings.len() >= 2 {
                let ours: Vec<Vec3> = siblings.iter().map(|&j| bone(to, j)).collect();
                let theirs: Vec<Vec3> = siblings.iter().map(|&j| bone(from, j)).collect();
                let together = mat_to_quat(&fit_rotation(&ours, &theirs));
                for &j in &siblings {
                    shared[j] = together;
                }
            }
        }
        let mut turns = [QUAT_IDENTITY; 24];
        let mut lengths = [0f32; 24];
        for j in 1..24 {
            let (a, b) = (bone(from, j), bone(to, j));
            turns[j] = qbetween_safe(qrot(shared[j], b), a);
            lengths[j] = norm(a) - norm(b);
        }
        Self {
            root: [0, 1, 2].map(|c| from[[0, c]] - to[[0, c]]),
            shared,
            turns,
            lengths,
        }
    }

    /// `pose` with the fraction `keep` of the offset: the root displaced by `keep` of it, each
    /// bone turned by `keep` of its rotation's angle about the same axis and lengthened by
    /// `keep` of its difference, joints rebuilt from the root outward.
    fn apply(&self, pose: ArrayView2<'_, f32>, keep: f32) -> Array2<f32> {
        let mut out = Array2::<f32>::zeros((24, 3));
        for c in 0..3 {
            out[[0, c]] = pose[[0, c]] + keep * self.root[c];
        }
        for j in 1..24 {
            let b = bone(pose, j);
            let length = norm(b);
            let turned = qrot(
                qpow(self.turns[j], keep),
                qrot(qpow(self.shared[j], keep), b),
            );
            let scale = if length > 0.0 {
                (length + keep * self.lengths[j]) / length
            } else {
                1.0
            };
            let p = smpl_parent(j);
            for c in 0..3 {
                out[[j, c]] = out[[p, c]] + turned[c] * scale;
            }
        }
        out
    }
}

#[cfg(test)]
#[path = "dance_tests.rs"]
mod tests;
