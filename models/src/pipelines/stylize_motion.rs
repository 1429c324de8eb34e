//! A content motion and a style to a stylized motion file, end to end (pipeline), the mirror of
//! [`crate::dance_song`]: both motion files, in any format choreod reads, → HumanML3D features at
//! the package's rate (datasets) → [`stylize_package`] → the joints recovered from the stylized
//! features → the motion file (joints, `/motion/features`, provenance naming both inputs with
//! their sha256). The style is read and encoded apart ([`encode_style`]), so a caller with one
//! style for many contents (`choreod serve`'s style inbox) runs the style encoder once. What
//! `choreod stylize` runs once and `choreod serve` runs per style-inbox file; the caller writes
//! the returned [`MotionFile`].

use std::path::{Path, PathBuf};
use std::time::Instant;

use choreo_datasets::{
    Features, MAX_INPUT_FRAMES, MotionFile, MotionInputOptions, Provenance, RigidFitter,
    SkeletonKind, StyleProvenance,
};
use ndarray::{Array2, Array3, ArrayView2};

use crate::error::{Error, Result};
use crate::package::ModelPackage;
use crate::package::manifest::MANIFEST_FILE;
use crate::pipelines::song::file_name;
use crate::pipelines::stylize::{
    StyleReference, StylizeOptions, StylizeStats, encode_style_package, style_config,
    stylize_package,
};

/// A motion file to read.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub struct MotionSource {
    /// The file, in any format choreod reads.
    pub path: PathBuf,
    /// Frame rate of a `.npy` (which carries none); `None`: as `choreod convert` assumes.
    /// Default: None.
    pub npy_fps: Option<f32>,
}

impl MotionSource {
    /// The motion in `path`, frame rate from the file.
    pub fn new(path: impl Into<PathBuf>) -> Self {
        Self {
            path: path.into(),
            npy_fps: None,
        }
    }
}

/// Where the style comes from.
#[derive(Debug, Clone, PartialEq)]
pub enum StyleSource {
    /// A motion file, through the package's style encoder.
    Motion(MotionSource),
    /// A precomputed style vector, float32 `.npy` of shape (S) or (1, S).
    Embedding(PathBuf),
}

impl StyleSource {
    /// The file the style is read from.
    pub fn path(&self) -> &Path {
        match self {
            Self::Motion(m) => &m.path,
            Self::Embedding(p) => p,
        }
    }
}

/// A style reference read and, for a motion, encoded: all a stylize run needs of its style.
/// Computed once by [`encode_style`], it serves any number of runs (the daemon's style inbox
/// keeps one per style file while the file is unchanged).
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub struct EncodedStyle {
    /// Where the style came from.
    pub source: StyleSource,
    /// SHA-256 of the file, the same before and after it was read (the provenance names it).
    pub sha256: String,
    /// The package it was encoded with (a style vector belongs to one style encoder).
    pub model: PathBuf,
    /// The style vector (1, S): the style encoder's output, or the embedding file's vector.
    pub vector: Array2<f32>,
    /// Seconds reading the file (formats, retargeting, features).
    pub read_s: f64,
    /// Seconds in the style encoder (0 for an embedding).
    pub encode_s: f64,
}

/// Read `style` and, for a motion, run it through the package's style encoder (the raw
/// features with the trajectory dims zeroed, at most `max_frames` of them, as [`stylize`]
/// does). Errors: a file that cannot be read or converted is [`Error::StyleFile`] (an embedding
/// file: [`Error::Datasets`] or [`Error::StyleEmbedding`]), naming it; the encoder's and a file
/// that changed while it was read are [`Error::StyleEncoding`].
///
/// [`stylize`]: crate::stylize
pub fn encode_style(package: &mut ModelPackage, style: &StyleSource) -> Result<EncodedStyle> {
    let path = style.path();
    let t0 = Instant::now();
    let sha256 = choreo_datasets::sha256_file(path).map_err(Error::StyleFile)?;
    let spec = style_config(package)?;
    let (vector, read_s, encode_s) = match style {
        StyleSource::Motion(source) => {
            let mut o = MotionInputOptions::new(spec.fps as f32);
            o.max_frames = MAX_INPUT_FRAMES;
            o.npy_fps = source.npy_fps;
            o.min_frames = spec.min_frames;
            let input =
                choreo_datasets::load_motion_input(&source.path, &o).map_err(Error::StyleFile)?;
            tracing::info!(style = %source.path.display(), format = input.origin.format,
                rig = ?input.origin.rig, frames = input.features.nrows(), "style read");
            let read_s = t0.elapsed().as_secs_f64();
            let t_encode = Instant::now();
            let vector = encode_style_package(package, input.features.view()).map_err(|e| {
                Error::StyleEncoding {
                    style: path.to_path_buf(),
                    source: Box::new(e),
                }
            })?;
            (vector, read_s, t_encode.elapsed().as_secs_f64())
        }
        StyleSource::Embedding(path) => (read_embedding(path)?, t0.elapsed().as_secs_f64(), 0.0),
    };
    // A file replaced while it was read would pair one file's vector with another's hash.
    if choreo_datasets::sha256_file(path).map_err(Error::StyleFile)? != sha256 {
        return Err(Error::StyleEncoding {
            style: path.to_path_buf(),
            source: Box::new(Error::Input {
                what: "style file".into(),
                reason: "it changed while it was read; try again".into(),
            }),
        });
    }
    Ok(EncodedStyle {
        source: style.clone(),
        sha256,
        model: package.dir().to_path_buf(),
        vector,
        read_s,
        encode_s,
    })
}

/// Where the time went and what was made.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
#[non_exhaustive]
pub struct StylizedReport {
    /// Seconds reading the content (formats, retargeting, features).
    pub read_s: f64,
    /// Seconds of style transfer (VAE encoder, sampling, decoder) and recovering the joints.
    pub stylize_s: f64,
    /// Frame rate of the output (its frames are `stats.frames`, the content's).
    pub fps: f64,
    /// Counters of the loop.
    #[serde(flatten)]
    pub stats: StylizeStats,
}

/// A stylized motion.
#[derive(Debug, Clone)]
#[non_exhaustive]
pub struct StylizedMotion {
    /// The motion file to write: t2m-22 joints, the features, provenance.
    pub motion: MotionFile,
    /// Timings and counters.
    pub report: StylizedReport,
}

/// `content` in the style `style` ([`encode_style`]) with the style-transfer `package`.
/// `init_noise_sha256` names the file `options.init_noise` came from in the provenance ("" without
/// one). Errors: a content file that cannot be read or converted is [`Error::Datasets`], naming
/// it; everything else ([`Error::StyleEmbedding`], the package, the inputs' shapes,
/// [`stylize_package`]'s) is [`Error::Stylize`] naming both inputs. `progress(done, total)`
/// counts network steps.
pub fn stylize_motion(
    package: &mut ModelPackage,
    content: &MotionSource,
    style: &EncodedStyle,
    options: &StylizeOptions,
    init_noise_sha256: &str,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<StylizedMotion> {
    stylize_files(
        package,
        content,
        style,
        options,
        init_noise_sha256,
        progress,
    )
    .map_err(|e| {
        match e {
            // A reader's error names its file already.
            Error::Datasets(_) => e,
            other => Error::Stylize {
                content: content.path.clone(),
                style: style.source.path().to_path_buf(),
                source: Box::new(other),
            },
        }
    })
}

fn stylize_files(
    package: &mut ModelPackage,
    content: &MotionSource,
    style: &EncodedStyle,
    options: &StylizeOptions,
    init_noise_sha256: &str,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<StylizedMotion> {
    let started_utc = choreo_datasets::now_utc();
    let t0 = Instant::now();
    let spec = style_config(package)?;
    let fps = spec.fps as f32;
    if style.model != package.dir() {
        return Err(Error::Input {
            what: "style".into(),
            reason: format!(
                "encoded with the package {}, not this one",
                style.model.display()
            ),
        });
    }

    let mut input_options = MotionInputOptions::new(fps);
    input_options.npy_fps = content.npy_fps;
    input_options.max_frames = MAX_INPUT_FRAMES;
    let content_input = choreo_datasets::load_motion_input(&content.path, &input_options)?;
    tracing::info!(content = %content.path.display(), format = content_input.origin.format,
        rig = ?content_input.origin.rig, frames = content_input.features.nrows(), "content read");
    let read_s = t0.elapsed().as_secs_f64();

    let t_stylize = Instant::now();
    let stylized = stylize_package(
        package,
        content_input.features.view(),
        StyleReference::Embedding(style.vector.row(0)),
        options,
        progress,
    )?;
    let joints = rigid_on_content(content_input.features.view(), stylized.features.view())?;
    let mut motion = MotionFile::from_joints(fps, SkeletonKind::T2m22, joints);
    motion.features = Some(Features {
        data: stylized.features,
        representation: "humanml3d263".into(),
        normalized: false,
    });
    let used = stylized.used;
    motion.provenance = Some(Provenance {
        source_name: file_name(&content.path),
        source_sha256: choreo_datasets::sha256_file(&content.path)?,
        model_name: package.manifest().name.clone(),
        model_sha256: choreo_datasets::sha256_file(&package.dir().join(MANIFEST_FILE))?,
        sampler: used.sampler.as_str().to_string(),
        steps: used.steps as u32,
        eta: used.eta,
        guidance: used.guidance,
        content_guidance: used.weights.map(|(wc, _)| wc),
        style_guidance: used.weights.map(|(_, ws)| ws),
        seed: options.seed,
        chunk_windows: options.chunk_segments.max(1) as u32,
        init_noise_sha256: init_noise_sha256.to_string(),
        started_utc,
        finished_utc: choreo_datasets::now_utc(),
        style: Some(StyleProvenance {
            mode: options.mode.as_str().into(),
            name: file_name(style.source.path()),
            sha256: style.sha256.clone(),
        }),
        license: package.manifest().license_line(),
        source_damage: None,
        source_kind: None,
        source_beat: None,
        library: None,
    });
    Ok(StylizedMotion {
        motion,
        report: StylizedReport {
            read_s,
            stylize_s: t_stylize.elapsed().as_secs_f64(),
            fps: spec.fps,
            stats: stylized.stats,
        },
    })
}

/// The joints of the stylized features as one rigid skeleton with the content's body: the bone
/// lengths and sibling spans of the content's joints (a rigid content keeps its own), the
/// stylized root path, and the pelvis turned with the legs
/// ([`RigidFitter::legs_first`]), so legs and feet the style left alone stay the content's.
/// Joints recovered from stylized features are not one skeleton (a restyled spine and collars
/// change the spans between siblings: neck to collar by centimetres), which no BVH or armature
/// can reproduce; fitted, the file's joints and its BVH are one motion.
fn rigid_on_content(
    content: ArrayView2<'_, f32>,
    stylized: ArrayView2<'_, f32>,
) -> Result<Array3<f32>> {
    let body = choreo_datasets::recover_from_ric(content)?;
    let joints = choreo_datasets::recover_from_ric(stylized)?;
    let fitted = RigidFitter::from_motion(&SkeletonKind::T2m22, body.view())
        .and_then(|fitter| fitter.legs_first().fit(joints.view()))
        .map_err(|source| Error::GeneratedJoints { source })?;
    Ok(fitted.joints)
}

/// A style vector from `.npy`: shape (S) or (1, S), returned as (1, S).
fn read_embedding(path: &Path) -> Result<Array2<f32>> {
    let a = choreo_datasets::read_npy(path)?;
    let shape = a.shape().to_vec();
    let bad = || Error::StyleEmbedding {
        path: path.to_path_buf(),
        shape: shape.clone(),
    };
    let s = match shape.as_slice() {
        [s] | [1, s] if *s > 0 => *s,
        _ => return Err(bad()),
    };
    a.into_shape_with_order((1, s)).map_err(|_| bad())
}
