//! One content motion + one style → one stylized motion file: the job of `choreod stylize`.
//! Any motion format → HumanML3D features at the package's rate (datasets) → the style-transfer
//! loop (models) → joints recovered from the features → the HDF5 motion file (with
//! `/motion/features` and provenance naming both inputs) or a BVH, written atomically.

use std::path::{Path, PathBuf};
use std::time::Instant;

use crate::dance::file_name;
use anyhow::{Context, bail};
use choreo_datasets::{
    Features, MAX_INPUT_FRAMES, MotionFile, MotionInputOptions, Provenance, SkeletonKind,
    StyleProvenance,
};
use choreo_models::{ModelPackage, StyleReference, StylizeOptions, StylizeStats};

/// Where the style comes from.
#[derive(Debug, Clone)]
pub enum StyleInput {
    /// A motion file in any format choreod reads.
    Motion(PathBuf),
    /// A precomputed style vector, float32 `.npy` of shape (S) or (1, S).
    Embedding(PathBuf),
}

impl StyleInput {
    fn path(&self) -> &Path {
        match self {
            Self::Motion(p) | Self::Embedding(p) => p,
        }
    }
}

/// One stylize job.
#[derive(Debug, Clone)]
pub struct StylizeJob {
    /// The content motion (timing, path, legs).
    pub content: PathBuf,
    /// The style reference.
    pub style: StyleInput,
    /// The output, in the format its extension names ([`choreo_datasets::write_motion_as`]).
    pub output: PathBuf,
    /// Bone names and mesh of a `.bvh` / `.glb` / `.gltf` output.
    pub export: choreo_datasets::ExportOptions,
    /// Frame rate of a `.npy` content (`None`: as `choreod convert` assumes).
    pub content_fps: Option<f32>,
    /// Frame rate of a `.npy` style motion.
    pub style_fps: Option<f32>,
    /// sha256 of the `--init-noise` file ("" without one), for the provenance.
    pub init_noise_sha256: String,
}

/// What was made and where the time went.
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct StylizeReport {
    /// Seconds reading both inputs (formats, retargeting, features).
    pub read_s: f64,
    /// Seconds of style transfer (encoders, sampling, decoder).
    pub stylize_s: f64,
    /// Seconds recovering joints and writing the output.
    pub write_s: f64,
    pub total_s: f64,
    /// Frame rate of the output (its frames are `stats.frames`, the content's).
    pub fps: f64,
    /// Counters of the loop.
    #[serde(flatten)]
    pub stats: StylizeStats,
}

/// Stylize `job.content` with `job.style` and write `job.output`.
pub fn stylize_file(
    package: &mut ModelPackage,
    job: &StylizeJob,
    options: &StylizeOptions,
    progress: &mut dyn FnMut(usize, usize),
) -> anyhow::Result<StylizeReport> {
    let started_utc = choreo_datasets::now_utc();
    let t0 = Instant::now();
    choreo_datasets::check_output(&job.output, &job.export)?;
    let spec = choreo_models::style_config(package)?;
    let fps = spec.fps as f32;

    let mut input_options = MotionInputOptions::new(fps);
    input_options.npy_fps = job.content_fps;
    input_options.max_frames = MAX_INPUT_FRAMES;
    let content = choreo_datasets::load_motion_input(&job.content, &input_options)?;
    tracing::info!(content = %job.content.display(), format = content.origin.format,
        rig = ?content.origin.rig, frames = content.features.nrows(), "content read");
    let style_data = match &job.style {
        StyleInput::Motion(path) => {
            let mut o = input_options.clone();
            o.npy_fps = job.style_fps;
            o.min_frames = spec.min_frames;
            let style = choreo_datasets::load_motion_input(path, &o)?;
            tracing::info!(style = %path.display(), format = style.origin.format,
                rig = ?style.origin.rig, frames = style.features.nrows(), "style read");
            style.features
        }
        StyleInput::Embedding(path) => read_embedding(path)?,
    };
    let style = match &job.style {
        StyleInput::Motion(_) => StyleReference::Motion(style_data.view()),
        StyleInput::Embedding(_) => StyleReference::Embedding(style_data.row(0)),
    };
    let read_s = t0.elapsed().as_secs_f64();

    let t_stylize = Instant::now();
    let stylized =
        choreo_models::stylize_package(package, content.features.view(), style, options, progress)
            .with_context(|| {
                format!(
                    "stylizing {} with {}",
                    job.content.display(),
                    job.style.path().display()
                )
            })?;
    let stylize_s = t_stylize.elapsed().as_secs_f64();

    let t_write = Instant::now();
    let joints = choreo_datasets::recover_from_ric(stylized.features.view())
        .context("recovering joints from the stylized features")?;
    let mut motion = MotionFile::from_joints(fps, SkeletonKind::T2m22, joints);
    motion.features = Some(Features {
        data: stylized.features,
        representation: "humanml3d263".into(),
        normalized: false,
    });
    let model_sha256 =
        choreo_datasets::sha256_file(&package.dir().join(choreo_models::MANIFEST_FILE))
            .with_context(|| format!("reading the manifest of {}", package.dir().display()))?;
    let sha = |p: &Path| {
        choreo_datasets::sha256_file(p).with_context(|| format!("reading {}", p.display()))
    };
    let used = stylized.used;
    motion.provenance = Some(Provenance {
        source_name: file_name(&job.content),
        source_sha256: sha(&job.content)?,
        model_name: package.manifest().name.clone(),
        model_sha256,
        sampler: used.sampler.as_str().to_string(),
        steps: used.steps as u32,
        eta: used.eta,
        guidance: used.guidance,
        content_guidance: used.weights.map(|(wc, _)| wc),
        style_guidance: used.weights.map(|(_, ws)| ws),
        seed: options.seed,
        chunk_windows: options.chunk_segments.max(1) as u32,
        init_noise_sha256: job.init_noise_sha256.clone(),
        started_utc,
        finished_utc: choreo_datasets::now_utc(),
        style: Some(StyleProvenance {
            mode: options.mode.as_str().into(),
            name: file_name(job.style.path()),
            sha256: sha(job.style.path())?,
        }),
    });
    choreo_datasets::write_motion_as(&job.output, &motion, &job.export)?;
    let write_s = t_write.elapsed().as_secs_f64();
    Ok(StylizeReport {
        read_s,
        stylize_s,
        write_s,
        total_s: t0.elapsed().as_secs_f64(),
        fps: spec.fps,
        stats: stylized.stats,
    })
}

/// A style vector from `.npy`: shape (S) or (1, S), returned as (1, S).
fn read_embedding(path: &Path) -> anyhow::Result<ndarray::Array2<f32>> {
    let a = choreo_datasets::read_npy(path)?;
    let shape = a.shape().to_vec();
    let s = match shape.as_slice() {
        [s] | [1, s] if *s > 0 => *s,
        _ => bail!(
            "{}: style embedding of shape {shape:?}: expected one vector, (S) or (1, S)",
            path.display()
        ),
    };
    a.into_shape_with_order((1, s))
        .with_context(|| format!("reading the style embedding {}", path.display()))
}
