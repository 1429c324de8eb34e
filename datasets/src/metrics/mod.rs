//! `choreod eval`: the field's dance and style metrics, each equal to the reference code that
//! defines it (cited per function), with the known slips of that code reproduced by default
//! and a corrected variant beside them.
//!
//! - [`kinetic`]: the 72 kinetic features (FID_k) — [`kinetic_features`] with
//!   [`Acceleration::ReferenceSlip`] or [`Acceleration::Fixed`].
//! - [`geometric`]: the 32 geometric features (FID_g) — [`geometric_features`].
//! - [`frechet`]: z-scoring with the reference set, Fréchet distance, average pairwise distance.
//! - [`beats`]: Beat Alignment Score over motion beats (AIST++ / mint) and over music beats
//!   (Bailando, MoFusion).
//! - [`foot`]: EDGE's PFC, GMD's skating ratio, foot sliding (FSF) and trajectory distance (TSI).
//! - [`evaluate`] runs all of them on a generated set (and a reference set) and returns an
//!   [`EvalReport`]; for sets too large to hold, [`eval_sources`] lists files, directories and
//!   prep shards, [`score_motion`] / [`reference_features`] take one motion at a time and
//!   [`summarize`] makes the set metrics.

pub mod beats;
pub mod foot;
pub mod frechet;
pub mod geometric;
pub(crate) mod inputs;
pub mod kinetic;

use std::collections::BTreeMap;

use ndarray::{Array3, ArrayView3, s};
use serde::Serialize;

pub use geometric::{GEOMETRIC_DIM, geometric_features};
pub use inputs::{EvalMotion, EvalSource, ShardSequence, eval_sources};
pub use kinetic::{Acceleration, kinetic_features};

use crate::error::{Error, Result};
use crate::formats::aistpp::resample_joints;
use crate::skeleton::SkeletonKind;

/// Frame rate the research code assumes for every motion (kinetic.py:55 `frame_time=1./60`).
const LEGACY_FPS: f64 = 60.0;
/// Features are computed on the first 20 s: Bailando takes `[:1200]` frames of 60 fps motion
/// (utils/metrics_new.py:164).
const FEATURE_SECONDS: f64 = 20.0;

/// Options of [`evaluate`].
#[derive(Debug, Clone)]
#[non_exhaustive]
pub struct EvalOptions {
    /// Use the research code's hard-coded 60 fps frame time (kinetic 1/60 s, geometric 1/120 s)
    /// whatever the file's rate. Default: false (frame time from the file's fps).
    pub legacy_60fps: bool,
    /// Frame rate the BAS is scored at (σ = 3 frames at this rate). Default: 60, as the
    /// papers' AIST++ numbers.
    pub bas_fps: f32,
}

impl Default for EvalOptions {
    fn default() -> Self {
        EvalOptions {
            legacy_60fps: false,
            bas_fps: 60.0,
        }
    }
}

/// A motion with what it is scored against.
#[derive(Debug, Clone)]
pub struct EvalInput {
    /// The motion.
    pub motion: EvalMotion,
    /// Music beat times in seconds, when known.
    pub beat_times_s: Option<Vec<f64>>,
    /// Generations of the same song share a group (for multimodality).
    pub song: Option<String>,
}

/// Feature vectors of one motion (written by `--features-out`).
#[derive(Debug, Clone, Serialize)]
pub struct FeatureVectors {
    /// Kinetic features with the reference's acceleration slip.
    pub kinetic: Vec<f64>,
    /// Kinetic features with the corrected acceleration.
    pub kinetic_fixed_accel: Vec<f64>,
    /// Geometric features.
    pub geometric: Vec<f64>,
}

/// Metrics of one motion.
#[derive(Debug, Clone, Serialize)]
pub struct FileMetrics {
    /// The motion's name.
    pub name: String,
    /// Frames and fps as read.
    pub frames: usize,
    /// Frames per second as read.
    pub fps: f32,
    /// Kinematic beats found (mint's rule, at the BAS rate).
    pub motion_beats: usize,
    /// AIST++ / mint BAS (mean over motion beats); `None` without music beats.
    pub bas_motion_beats: Option<f64>,
    /// Bailando BAS (mean over music beats); `None` without music or kinematic beats.
    pub bas_music_beats: Option<f64>,
    /// EDGE PFC (× 10⁴), at 30 fps.
    pub pfc: f64,
    /// GMD foot-skating ratio, at 20 fps.
    pub skate_ratio: f64,
    /// Foot sliding (FSF), metres per contact frame step at 20 fps.
    pub foot_sliding_m: f64,
    /// Trajectory distance to the content motion (TSI), metres; only with a content motion.
    pub tsi_m: Option<f64>,
    /// The feature vectors.
    #[serde(skip)]
    pub features: FeatureVectors,
}

/// A set-level metric, or why it is undefined.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(untagged)]
pub enum SetValue {
    /// The value.
    Value(f64),
    /// Why it cannot be computed, e.g. "the reference set has 1 motion; FID needs at least 2".
    Undefined {
        /// The reason.
        undefined: String,
    },
}

/// Metrics of a set of motions.
#[derive(Debug, Clone, Serialize)]
pub struct SetMetrics {
    /// FID_k with the reference's acceleration slip (comparable to published numbers).
    pub fid_k: Option<SetValue>,
    /// FID_k with the corrected acceleration.
    pub fid_k_fixed_accel: Option<SetValue>,
    /// FID_g.
    pub fid_g: Option<SetValue>,
    /// Div_k of the generated set.
    pub div_k: SetValue,
    /// Div_g of the generated set.
    pub div_g: SetValue,
    /// Div_k of the reference set.
    pub div_k_reference: Option<SetValue>,
    /// Div_g of the reference set.
    pub div_g_reference: Option<SetValue>,
    /// Mean BAS over motions that have one.
    pub bas_motion_beats: Option<f64>,
    /// Mean BAS over motions that have one.
    pub bas_music_beats: Option<f64>,
    /// Mean PFC.
    pub pfc: f64,
    /// Mean skating ratio.
    pub skate_ratio: f64,
    /// Mean foot sliding.
    pub foot_sliding_m: f64,
    /// Mean TSI.
    pub tsi_m: Option<f64>,
    /// Multimodality: mean over songs with several generations of their Div_k.
    pub multimodality_k: Option<f64>,
}

/// What every number means (printed with the numbers).
#[derive(Debug, Clone, Serialize)]
pub struct Conventions {
    /// Frame time of the features.
    pub feature_frame_time: String,
    /// How the BAS is scored.
    pub bas: String,
    /// The acceleration variants.
    pub kinetic_acceleration: String,
    /// The Fréchet square root.
    pub fid_sqrtm: String,
    /// Whose statistics z-score the features.
    pub zscore: String,
}

/// Everything `choreod eval` reports.
#[derive(Debug, Clone, Serialize)]
pub struct EvalReport {
    /// The conventions used.
    pub conventions: Conventions,
    /// Per generated motion.
    pub generated: Vec<FileMetrics>,
    /// The generated set.
    pub set: SetMetrics,
    /// Number of reference motions.
    pub reference_count: usize,
    /// Numbers above that are computed but misleading, each said in one sentence.
    pub warnings: Vec<String>,
}

/// Check a motion can be scored: SMPL-24 or t2m-22 joints, ≥ 3 frames, finite, positive fps.
fn check(m: &EvalMotion) -> Result<()> {
    let motion = &m.motion;
    let bad = |reason: String| Err(Error::invalid(&m.name, reason));
    if !matches!(motion.skeleton, SkeletonKind::Smpl24 | SkeletonKind::T2m22) {
        return bad(format!(
            "skeleton {}: the metrics need SMPL-24 or t2m-22 joints",
            choreo_dsp::quote(motion.skeleton.name())
        ));
    }
    if !(motion.fps.is_finite() && motion.fps > 0.0) {
        return bad(format!("frame rate {} fps", motion.fps));
    }
    let t = motion.joints.shape()[0];
    if t < 3 {
        return bad(format!(
            "{t} frame(s): velocities and accelerations need at least 3 frames"
        ));
    }
    if let Some(i) = motion.joints.iter().position(|v| !v.is_finite()) {
        let j = motion.joints.shape()[1];
        return bad(format!(
            "non-finite joint position at frame {}, joint {}",
            i / (j * 3),
            (i / 3) % j
        ));
    }
    Ok(())
}

/// The joints features are computed on: the first 20 s, translated so frame 0's root is at the
/// origin (Bailando utils/metrics_new.py:164-168 — it matters because the acceleration slip
/// depends on absolute position).
fn feature_joints(m: &EvalMotion) -> Array3<f32> {
    let j = &m.motion.joints;
    let n = ((FEATURE_SECONDS * f64::from(m.motion.fps)).round() as usize).min(j.shape()[0]);
    let mut out = j.slice(s![..n, .., ..]).to_owned();
    let root0 = j.slice(s![0, 0, ..]).to_owned();
    for mut frame in out.outer_iter_mut() {
        for mut joint in frame.outer_iter_mut() {
            joint -= &root0;
        }
    }
    out
}

fn feature_vectors(m: &EvalMotion, opts: &EvalOptions) -> FeatureVectors {
    let fps = if opts.legacy_60fps {
        LEGACY_FPS
    } else {
        f64::from(m.motion.fps)
    };
    let joints = feature_joints(m);
    FeatureVectors {
        kinetic: kinetic_features(joints.view(), 1.0 / fps, Acceleration::ReferenceSlip),
        kinetic_fixed_accel: kinetic_features(joints.view(), 1.0 / fps, Acceleration::Fixed),
        // The helpers' 1/120 s at 60 fps (utils.py:67): half a frame, kept at other rates.
        geometric: geometric_features(joints.view(), 0.5 / fps).to_vec(),
    }
}

fn resampled(m: &EvalMotion, fps: f32) -> Result<Array3<f32>> {
    if (m.motion.fps - fps).abs() < 1e-3 {
        return Ok(m.motion.joints.clone());
    }
    resample_joints(&m.motion.joints, m.motion.fps, fps)
        .map_err(|e| e.with_path(std::path::Path::new(&m.name)))
}

/// Per-motion metrics of one generated motion (`content`: the [`content_trajectory`] for TSI).
pub fn score_motion(
    input: &EvalInput,
    content: Option<ArrayView3<f32>>,
    opts: &EvalOptions,
) -> Result<FileMetrics> {
    let m = &input.motion;
    check(m)?;
    let at_bas = resampled(m, opts.bas_fps)?;
    let t = at_bas.shape()[0];
    let mint_beats = beats::mint_motion_beats(at_bas.view());
    let bailando_beats = beats::bailando_motion_beats(at_bas.view());
    let fps = f64::from(opts.bas_fps);
    let (bas_motion, bas_music) = match &input.beat_times_s {
        Some(times) => (
            // mint truncates the music beats to the motion's frames (calculate_beat_scores.py:175),
            // Bailando to the envelope's T−1 (beat_align_score.py:68-69).
            beats::bas_motion_beats(&beats::beat_frames(times, fps, t), &mint_beats),
            beats::bas_music_beats(&beats::beat_frames(times, fps, t - 1), &bailando_beats),
        ),
        None => (None, None),
    };
    let at_pfc = resampled(m, foot::PFC_FPS)?;
    let at_skate = resampled(m, foot::SKATE_FPS)?;
    let long_enough = |a: &Array3<f32>, n: usize, what: &str| {
        if a.shape()[0] < n {
            Err(Error::invalid(
                &m.name,
                format!(
                    "too short for {what}: {} frames after resampling, need {n}",
                    a.shape()[0]
                ),
            ))
        } else {
            Ok(())
        }
    };
    long_enough(&at_pfc, 3, "PFC at 30 fps")?;
    long_enough(&at_skate, 2, "foot skating at 20 fps")?;
    let tsi = content.map(|c| foot::trajectory_distance(at_skate.view(), c));
    Ok(FileMetrics {
        name: m.name.clone(),
        frames: m.motion.joints.shape()[0],
        fps: m.motion.fps,
        motion_beats: mint_beats.len(),
        bas_motion_beats: bas_motion,
        bas_music_beats: bas_music,
        pfc: foot::pfc(at_pfc.view()),
        skate_ratio: foot::skate_ratio(at_skate.view()),
        foot_sliding_m: foot::foot_sliding(at_skate.view()),
        tsi_m: tsi,
        features: feature_vectors(m, opts),
    })
}

fn mean(values: impl Iterator<Item = f64>) -> Option<f64> {
    let (sum, n) = values.fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
    (n > 0).then(|| sum / n as f64)
}

fn need_two(n: usize, which: &str, what: &str) -> Option<SetValue> {
    (n < 2).then(|| SetValue::Undefined {
        undefined: format!("the {which} set has {n} motion(s); {what} needs at least 2"),
    })
}

/// Score `generated` (against `reference` when given; TSI against `content` when given): the
/// composition of [`content_trajectory`], [`score_motion`], [`reference_features`] and
/// [`summarize`] for motions already in memory.
pub fn evaluate(
    generated: &[EvalInput],
    reference: &[EvalMotion],
    content: Option<&EvalMotion>,
    opts: &EvalOptions,
) -> Result<EvalReport> {
    let content = content.map(content_trajectory).transpose()?;
    let files = generated
        .iter()
        .map(|g| score_motion(g, content.as_ref().map(|c| c.view()), opts))
        .collect::<Result<Vec<_>>>()?;
    let songs: Vec<Option<String>> = generated.iter().map(|g| g.song.clone()).collect();
    let reference = reference
        .iter()
        .map(|r| reference_features(r, opts))
        .collect::<Result<Vec<_>>>()?;
    summarize(files, &songs, &reference, opts)
}

/// The content motion of a style transfer, as [`score_motion`] compares trajectories (20 fps).
pub fn content_trajectory(content: &EvalMotion) -> Result<Array3<f32>> {
    check(content)?;
    resampled(content, foot::SKATE_FPS)
}

/// A reference motion's feature vectors, named.
pub fn reference_features(m: &EvalMotion, opts: &EvalOptions) -> Result<(String, FeatureVectors)> {
    check(m)?;
    Ok((m.name.clone(), feature_vectors(m, opts)))
}

/// Set metrics from per-motion results (`songs[i]` groups generation `i` for multimodality).
/// Motions that cannot be scored were errors naming them already; set metrics that are
/// undefined (FID with fewer than 2 motions on a side) are [`SetValue::Undefined`] with the
/// reason.
pub fn summarize(
    files: Vec<FileMetrics>,
    songs: &[Option<String>],
    reference: &[(String, FeatureVectors)],
    opts: &EvalOptions,
) -> Result<EvalReport> {
    if files.is_empty() {
        return Err(Error::motion("no generated motions to evaluate"));
    }
    let dims = |f: &FeatureVectors| f.kinetic.len();
    let k0 = dims(&files[0].features);
    for (name, d) in files
        .iter()
        .map(|f| (&f.name, dims(&f.features)))
        .chain(reference.iter().map(|(n, f)| (n, dims(f))))
    {
        if d != k0 {
            return Err(Error::invalid(
                name,
                format!(
                    "{} joints, other motions have {}: sets must share one skeleton",
                    d / 3,
                    k0 / 3
                ),
            ));
        }
    }
    let column = |pick: fn(&FeatureVectors) -> &Vec<f64>,
                  src: &mut dyn Iterator<Item = &FeatureVectors>|
     -> Vec<Vec<f64>> { src.map(|f| pick(f).clone()).collect() };
    type Pick = fn(&FeatureVectors) -> &Vec<f64>;
    let picks: [Pick; 3] = [|f| &f.kinetic, |f| &f.kinetic_fixed_accel, |f| &f.geometric];
    let gen_sets: Vec<Vec<Vec<f64>>> = picks
        .iter()
        .map(|p| column(*p, &mut files.iter().map(|f| &f.features)))
        .collect();
    let ref_sets: Vec<Vec<Vec<f64>>> = picks
        .iter()
        .map(|p| column(*p, &mut reference.iter().map(|(_, f)| f)))
        .collect();
    let n_gen = files.len();
    let n_ref = reference.len();
    // Features are z-scored with the reference set's statistics (metrics_new.py:58-59); with
    // fewer than 2 reference motions those are degenerate (std 0), so the generated set's own
    // statistics scale the diversity instead.
    let stats_from_reference = n_ref >= 2;
    // A set z-scored with its own statistics needs 3 motions for a diversity: two motions
    // z-scored by their own mean and std sit at ±1 on every feature that differs, so their
    // distance is 2·√(features that differ) whatever the motions are.
    let div = |rows: &[Vec<f64>], which: &str, own_stats: bool| {
        let needed = if own_stats { 3 } else { 2 };
        if rows.len() < needed {
            let why = if own_stats {
                ", as it is z-scored with its own statistics (two such motions are always 2·√(features that differ) apart)"
            } else {
                ""
            };
            SetValue::Undefined {
                undefined: format!(
                    "the {which} set has {} motion(s); diversity needs at least {needed}{why}",
                    rows.len()
                ),
            }
        } else {
            SetValue::Value(frechet::average_pairwise_distance(rows))
        }
    };
    let mut warnings = Vec::new();
    if stats_from_reference {
        for (name, i) in [("kinetic", 0), ("geometric", 2)] {
            let constant = frechet::constant_columns(&ref_sets[i], &gen_sets[i]);
            if constant > 0 {
                warnings.push(format!(
                    "{constant} of {} {name} features are the same in all {n_ref} reference motions but not in the generated ones; z-scoring divides by ~1e-10 there, so fid and div of the {name} features measure those features alone (use more varied reference motions)",
                    ref_sets[i][0].len()
                ));
            }
        }
    }
    let mut fid = Vec::new();
    let mut z_gen = Vec::new();
    let mut z_ref = Vec::new();
    for (g, r) in gen_sets.iter().zip(&ref_sets) {
        let (r_z, g_z) = if stats_from_reference {
            frechet::zscore_with_reference(r, g)
        } else {
            let (g_z, r_z) = frechet::zscore_with_reference(g, r);
            (r_z, g_z)
        };
        fid.push(
            need_two(n_ref, "reference", "FID")
                .or_else(|| need_two(n_gen, "generated", "FID"))
                .unwrap_or_else(|| SetValue::Value(frechet::frechet_distance(&g_z, &r_z))),
        );
        z_gen.push(g_z);
        z_ref.push(r_z);
    }
    let has_reference = !reference.is_empty();
    let own = !stats_from_reference;
    let div_gen = [
        div(&z_gen[0], "generated", own),
        div(&z_gen[2], "generated", own),
    ];
    let div_ref = has_reference.then(|| {
        [
            div(&z_ref[0], "reference", stats_from_reference),
            div(&z_ref[2], "reference", stats_from_reference),
        ]
    });
    let fid = has_reference.then_some(fid);
    // Multimodality (MoFusion §4): Div_k within each song's generations, averaged over songs.
    let mut by_song: BTreeMap<&str, Vec<usize>> = BTreeMap::new();
    for (i, song) in songs.iter().enumerate() {
        if let Some(song) = song {
            by_song.entry(song).or_default().push(i);
        }
    }
    let z_kinetic = &z_gen[0];
    let multimodality = mean(by_song.values().filter(|v| v.len() >= 2).map(|idx| {
        let rows: Vec<Vec<f64>> = idx.iter().map(|&i| z_kinetic[i].clone()).collect();
        frechet::average_pairwise_distance(&rows)
    }));
    let [div_k, div_g] = div_gen;
    let set = SetMetrics {
        fid_k: fid.as_ref().map(|f| f[0].clone()),
        fid_k_fixed_accel: fid.as_ref().map(|f| f[1].clone()),
        fid_g: fid.as_ref().map(|f| f[2].clone()),
        div_k,
        div_g,
        div_k_reference: div_ref.as_ref().map(|d| d[0].clone()),
        div_g_reference: div_ref.as_ref().map(|d| d[1].clone()),
        bas_motion_beats: mean(files.iter().filter_map(|f| f.bas_motion_beats)),
        bas_music_beats: mean(files.iter().filter_map(|f| f.bas_music_beats)),
        pfc: mean(files.iter().map(|f| f.pfc)).unwrap_or(0.0),
        skate_ratio: mean(files.iter().map(|f| f.skate_ratio)).unwrap_or(0.0),
        foot_sliding_m: mean(files.iter().map(|f| f.foot_sliding_m)).unwrap_or(0.0),
        tsi_m: mean(files.iter().filter_map(|f| f.tsi_m)),
        multimodality_k: multimodality,
    };
    Ok(EvalReport {
        conventions: conventions(opts, stats_from_reference),
        generated: files,
        set,
        reference_count: n_ref,
        warnings,
    })
}

/// Write each generated motion's feature vectors into `dir` as float32 `.npy` (the reference
/// saves float32, Bailando utils/metrics_new.py:174-175):
/// `NNNNN_<name>.{kinetic,kinetic_fixed_accel,geometric}.npy`, NNNNN the motion's position.
pub fn write_feature_vectors(dir: &std::path::Path, report: &EvalReport) -> Result<()> {
    for (i, f) in report.generated.iter().enumerate() {
        let stem: String = std::path::Path::new(&f.name)
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default()
            .chars()
            .map(|c| {
                if c.is_alphanumeric() || "-_.".contains(c) {
                    c
                } else {
                    '_'
                }
            })
            .collect();
        for (what, values) in [
            ("kinetic", &f.features.kinetic),
            ("kinetic_fixed_accel", &f.features.kinetic_fixed_accel),
            ("geometric", &f.features.geometric),
        ] {
            let a = ndarray::Array1::from_iter(values.iter().map(|&v| v as f32));
            crate::formats::npy::write_npy(
                &dir.join(format!("{i:05}_{stem}.{what}.npy")),
                a.view().into_dyn(),
            )?;
        }
    }
    Ok(())
}

fn conventions(opts: &EvalOptions, stats_from_reference: bool) -> Conventions {
    Conventions {
        feature_frame_time: if opts.legacy_60fps {
            "legacy: 1/60 s (kinetic) and 1/120 s (geometric) whatever the file's fps, as the research code".into()
        } else {
            "from each file's fps: 1/fps (kinetic), 0.5/fps (geometric; 1/120 s at 60 fps as the research code)".into()
        },
        bas: format!(
            "scored at {} fps (motion resampled), sigma = 3 frames = {:.0} ms; bas_motion_beats = AIST++/mint (mean over motion beats), bas_music_beats = Bailando/MoFusion (mean over music beats)",
            opts.bas_fps,
            3000.0 / f64::from(opts.bas_fps)
        ),
        kinetic_acceleration: "fid_k reproduces aistplusplus_api's precedence slip v1 = p[k] - p[k-1]/dt (comparable to published numbers); fid_k_fixed_accel uses (p[k] - p[k-1])/dt".into(),
        fid_sqrtm: "tr sqrtm(S1 S2) real part only, as scipy.linalg.sqrtm(...).real in Bailando (imaginary round-off dropped)".into(),
        zscore: if stats_from_reference {
            "features z-scored with the reference set's mean and std (+1e-10), as Bailando".into()
        } else {
            "features z-scored with the generated set's own mean and std (fewer than 2 reference motions)".into()
        },
    }
}
