//! One content motion + one style → one stylized motion file: the job of `choreod stylize` and
//! of the daemon's style inbox. The style pipeline (models: the style read and encoded, the
//! content read, the transfer, the joints, the motion file) → the file written atomically
//! (datasets); here: the output check before any work, the style kept from job to job while its
//! file is unchanged ([`StyleCache`]), the write's time.

use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Instant;

use choreo_models::{
    EncodedStyle, ModelPackage, MotionSource, StyleSource, StylizeOptions, StylizedReport,
};

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

/// What was made and where the time went: the pipeline's report, the style's and the write.
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct StylizeReport {
    #[serde(flatten)]
    pub stylized: StylizedReport,
    /// Seconds reading the style reference for this job (0 when it was reused).
    pub style_read_s: f64,
    /// Seconds in the style encoder for this job (0 when the style was reused or is an
    /// embedding).
    pub style_encode_s: f64,
    /// The style was encoded for an earlier job and reused.
    pub style_reused: bool,
    /// Seconds writing the output.
    pub write_s: f64,
    pub total_s: f64,
}

/// The last style reference encoded, reused by every job whose style is the same file with the
/// same content (SHA-256) and package: the style inbox runs its one configured style through
/// the style encoder once, and again only when the file changes. Shared by the workers; a
/// worker that needs it while another encodes it waits for that result.
#[derive(Debug, Default)]
pub struct StyleCache {
    last: Mutex<Option<Arc<EncodedStyle>>>,
    encodings: AtomicU64,
}

impl StyleCache {
    /// `source` encoded with `package`, and whether this call encoded it (else it was reused).
    /// Hashing the file is all a reuse costs.
    pub fn get(
        &self,
        package: &mut ModelPackage,
        source: &StyleSource,
    ) -> choreo_models::Result<(Arc<EncodedStyle>, bool)> {
        let sha256 =
            choreo_datasets::sha256_file(source.path()).map_err(choreo_models::Error::StyleFile)?;
        let mut last = self.last.lock().unwrap_or_else(PoisonError::into_inner);
        if let Some(style) = last.as_ref().filter(|s| {
            s.source == *source && s.sha256 == sha256 && s.model.as_path() == package.dir()
        }) {
            return Ok((Arc::clone(style), false));
        }
        let style = Arc::new(choreo_models::encode_style(package, source)?);
        let count = self.encodings.fetch_add(1, Ordering::Relaxed) + 1;
        tracing::info!(style = %source.path().display(), sha256 = style.sha256,
            read_s = style.read_s, encode_s = style.encode_s, encodings = count,
            "style encoded");
        *last = Some(Arc::clone(&style));
        Ok((style, true))
    }

    /// Style references encoded so far (`choreod_style_encodings_total`).
    pub fn encodings(&self) -> u64 {
        self.encodings.load(Ordering::Relaxed)
    }
}

/// Stylize `job.content` with `job.style` (from `styles`, encoded there if it is not yet) and
/// write `job.output`.
pub fn stylize_file(
    package: &mut ModelPackage,
    job: &StylizeJob,
    styles: &StyleCache,
    options: &StylizeOptions,
    progress: &mut dyn FnMut(usize, usize),
) -> anyhow::Result<StylizeReport> {
    let t0 = Instant::now();
    choreo_datasets::check_output(&job.output, &job.export)?;
    let (style, encoded) = styles.get(package, &job.style)?;
    let stylized = choreo_models::stylize_motion(
        package,
        &job.content,
        &style,
        options,
        &job.init_noise_sha256,
        progress,
    )?;
    let t_write = Instant::now();
    choreo_datasets::write_motion_as(&job.output, &stylized.motion, &job.export)?;
    let this_job = |s: f64| if encoded { s } else { 0.0 };
    Ok(StylizeReport {
        stylized: stylized.report,
        style_read_s: this_job(style.read_s),
        style_encode_s: this_job(style.encode_s),
        style_reused: !encoded,
        write_s: t_write.elapsed().as_secs_f64(),
        total_s: t0.elapsed().as_secs_f64(),
    })
}
