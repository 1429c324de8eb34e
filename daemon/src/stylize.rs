//! One content motion + one style → one stylized motion file: the job of `choreod stylize` and
//! of the daemon's style inbox. The style pipeline (models: both inputs read, the transfer, the
//! joints, the motion file) → the file written atomically (datasets); here: the output check
//! before any work, the write's time.

use std::path::PathBuf;
use std::time::Instant;

use choreo_models::{ModelPackage, MotionSource, StyleSource, StylizeOptions, StylizedReport};

/// One stylize job.
#[derive(Debug, Clone)]
pub struct StylizeJob {
    /// The content motion (timing, path, legs).
    pub content: MotionSource,
    /// The style reference.
    pub style: StyleSource,
    /// The output, in the format its extension names ([`choreo_datasets::write_motion_as`]).
    pub output: PathBuf,
    /// Bone names and mesh of a `.bvh` / `.glb` / `.gltf` output.
    pub export: choreo_datasets::ExportOptions,
    /// sha256 of the `--init-noise` file ("" without one), for the provenance.
    pub init_noise_sha256: String,
}

/// What was made and where the time went: the pipeline's report and the write.
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct StylizeReport {
    #[serde(flatten)]
    pub stylized: StylizedReport,
    /// Seconds writing the output.
    pub write_s: f64,
    pub total_s: f64,
}

/// Stylize `job.content` with `job.style` and write `job.output`.
pub fn stylize_file(
    package: &mut ModelPackage,
    job: &StylizeJob,
    options: &StylizeOptions,
    progress: &mut dyn FnMut(usize, usize),
) -> anyhow::Result<StylizeReport> {
    let t0 = Instant::now();
    choreo_datasets::check_output(&job.output, &job.export)?;
    let stylized = choreo_models::stylize_motion(
        package,
        &job.content,
        &job.style,
        options,
        &job.init_noise_sha256,
        progress,
    )?;
    let t_write = Instant::now();
    choreo_datasets::write_motion_as(&job.output, &stylized.motion, &job.export)?;
    Ok(StylizeReport {
        stylized: stylized.report,
        write_s: t_write.elapsed().as_secs_f64(),
        total_s: t0.elapsed().as_secs_f64(),
    })
}
