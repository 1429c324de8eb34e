//! One song → one dance file: the job that `choreod dance` runs once and `choreod serve` runs per
//! inbox file. Decode + log-mel (dsp) → the dance pipeline and its motion file (models) → the
//! HDF5 file written atomically (datasets); here: limits, stages, timings and the report.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use choreo_models::{DanceOptions, DanceSource, DanceStats, ModelPackage};

/// Limits on the input, checked before reading it whole.
#[derive(Debug, Clone, Copy)]
pub struct InputLimits {
    pub max_file_bytes: u64,
    pub max_audio_seconds: f64,
    /// Shorter songs are refused; `None`: one motion window of the model
    /// ([`min_audio_seconds`]).
    pub min_audio_seconds: Option<f64>,
}

impl Default for InputLimits {
    /// The daemon config's defaults (config/choreod.example.toml).
    fn default() -> Self {
        Self {
            max_file_bytes: 512 * 1024 * 1024,
            max_audio_seconds: 1200.0,
            min_audio_seconds: None,
        }
    }
}

/// Where the time went and what was made.
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct DanceReport {
    pub decode_s: f64,
    pub resample_s: f64,
    pub mel_s: f64,
    pub features_total_s: f64,
    pub generate_s: f64,
    pub ort_s: f64,
    pub write_s: f64,
    pub total_s: f64,
    pub audio_s: f64,
    pub frames: usize,
    pub fps: f64,
    pub windows: usize,
    pub network_evaluations: usize,
    pub batch_rows: usize,
    pub steps: usize,
    /// Runs of the denoiser's hoisted prologue (0: the whole graph ran at every step).
    pub prologue_runs: usize,
    /// Seconds of music per second of work.
    pub realtime_factor: f64,
}

/// The stage a job failed in, for error reports (`<name>.error.json`) and metrics.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Stage {
    Decode,
    Generate,
    Write,
}

/// A failed job: the stage and the error.
#[derive(Debug)]
pub struct JobError {
    pub stage: Stage,
    pub error: anyhow::Error,
}

impl std::fmt::Display for JobError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{:#}", self.error)
    }
}

impl std::error::Error for JobError {
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        self.error.source()
    }
}

/// What `choreod dance` adds to a job: where the initial noise came from, where to save the
/// sampler's windows.
#[derive(Debug, Clone, Default)]
pub struct DanceExtras {
    /// sha256 of the `--init-noise` file ("" when the noise comes from the seed).
    pub init_noise_sha256: String,
    /// Write the sampler's final windows (normalised, before stitching) here as `.npy`.
    pub save_windows: Option<PathBuf>,
    /// Bone names and mesh of a `.bvh` / `.glb` / `.gltf` output (the output's extension picks
    /// the format: [`choreo_datasets::write_motion_as`]).
    pub export: choreo_datasets::ExportOptions,
}

/// A refusal of too long a song names the user's knob (`knob`: a flag, a config key), which the
/// decoder, knowing only the value, cannot; other decode errors pass through unchanged.
pub fn name_duration_limit(err: choreo_dsp::Error, knob: &str) -> anyhow::Error {
    match err {
        choreo_dsp::Error::TooLong { .. } => anyhow::anyhow!("{err} ({knob})"),
        other => other.into(),
    }
}

/// The shortest song a job accepts, and why: `configured` seconds, else one motion window of
/// the model (`window_frames / fps`: every window the model makes is this long, so a shorter song
/// is mostly padding; EDGE's inference, too, slices a song into whole 5 s windows and gets none
/// from a shorter one: Stanford-TML/EDGE `data/slice.py` `slice_audio`, line 18, `while
/// start_idx <= len(audio) - window`). Never below one analysis window of the model's features
/// (`n_fft` samples): shorter, every mel frame is padding.
pub fn min_audio_seconds(
    manifest: &choreo_models::Manifest,
    spec: &choreo_models::DanceSpec<'_>,
    configured: Option<f64>,
) -> (f64, String) {
    let (fps, a) = (manifest.motion.fps, spec.audio);
    let analysis_s = a.n_fft as f64 / f64::from(a.sample_rate);
    let (wanted, why) = match configured {
        Some(s) => (s, "limits.min_audio_seconds / --min-duration".to_string()),
        None => (
            spec.window_frames as f64 / fps,
            format!(
                "one motion window of model {}: {} frames at {fps} fps",
                manifest.name, spec.window_frames
            ),
        ),
    };
    if wanted.is_nan() || wanted < analysis_s {
        let why = format!(
            "one {}-sample analysis window at {} Hz",
            a.n_fft, a.sample_rate
        );
        return (analysis_s, why);
    }
    (wanted, why)
}

/// Farthest a body's joint gets from its root joint, metres: a person with arms raised reaches
/// about 1.3 m from the pelvis (SMPL's rest pose: wrist 0.85 m to the side, head 0.6 m up);
/// well past that the model made no body.
const MAX_BODY_REACH_M: f64 = 3.0;

/// The largest distance of any joint from joint 0 (the root) in any frame, metres.
fn largest_reach_m(joints: &ndarray::Array3<f32>) -> f64 {
    joints
        .outer_iter()
        .flat_map(|frame| {
            let root = frame.row(0).to_owned();
            frame
                .outer_iter()
                .map(|j| {
                    (0..3)
                        .map(|c| (f64::from(j[c]) - f64::from(root[c])).powi(2))
                        .sum::<f64>()
                        .sqrt()
                })
                .collect::<Vec<_>>()
        })
        .fold(0.0, f64::max)
}

/// Make a dance for `audio` with `package` and write it to `output` (atomically).
pub fn dance_file(
    package: &mut ModelPackage,
    audio: &Path,
    output: &Path,
    options: &DanceOptions,
    limits: InputLimits,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<DanceReport, JobError> {
    let extras = DanceExtras::default();
    dance_file_with(package, audio, output, options, limits, &extras, progress)
}

/// [`dance_file`] with the extras of `choreod dance`.
pub fn dance_file_with(
    package: &mut ModelPackage,
    audio: &Path,
    output: &Path,
    options: &DanceOptions,
    limits: InputLimits,
    extras: &DanceExtras,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<DanceReport, JobError> {
    let started_utc = choreo_datasets::now_utc();
    let t0 = Instant::now();
    let manifest = package.manifest().clone();
    let spec = manifest.dance_spec().map_err(|e| JobError {
        stage: Stage::Generate,
        error: e.into(),
    })?;
    let mel_options = spec.audio.mel_options();
    let mut decode_options = choreo_dsp::DecodeOptions::default();
    decode_options.max_file_bytes = limits.max_file_bytes;
    decode_options.max_duration_s = limits.max_audio_seconds;

    let decode = |e: anyhow::Error| JobError {
        stage: Stage::Decode,
        error: e,
    };
    // dsp errors name the file already.
    let (mel, audio_stats) = choreo_dsp::load_log_mel(audio, &decode_options, &mel_options)
        .map_err(|e| {
            decode(name_duration_limit(
                e,
                "--max-duration / limits.max_audio_seconds",
            ))
        })?;
    let (min_audio_s, why) = min_audio_seconds(&manifest, &spec, limits.min_audio_seconds);
    if audio_stats.duration_s < min_audio_s {
        return Err(decode(anyhow::anyhow!(
            "{}: {:.3} s of audio, shorter than the minimum of {min_audio_s:.3} s ({why}): a \
             truncated file or too short a clip",
            audio.display(),
            audio_stats.duration_s,
        )));
    }
    // After decoding, which has checked the file size against the limit.
    let source_sha256 = choreo_datasets::sha256_file(audio)
        .with_context(|| format!("reading {}", audio.display()))
        .map_err(decode)?;

    let generate = |e: anyhow::Error| JobError {
        stage: Stage::Generate,
        error: e,
    };
    let t_generate = Instant::now();
    let mut options = options.clone();
    if options.duration_s.is_none() {
        options.duration_s = Some(audio_stats.duration_s);
    }
    let dance = choreo_models::generate_dance(package, mel.view(), &options, progress)
        .with_context(|| format!("generating a dance for {}", audio.display()))
        .map_err(generate)?;
    let generate_s = t_generate.elapsed().as_secs_f64();
    let reach = largest_reach_m(&dance.joints);
    if reach > MAX_BODY_REACH_M {
        tracing::warn!(
            output = %output.display(),
            "the dance is not a body: a joint is {reach:.3e} m from the root (a person reaches \
             under {MAX_BODY_REACH_M} m); the model package is untrained or broken \
             (models/packages/mofusion-ref has random weights), and `choreod render` refuses \
             motions over 1 km wide"
        );
    }

    let write = |e: anyhow::Error| JobError {
        stage: Stage::Write,
        error: e,
    };
    let t_write = Instant::now();
    if let (Some(path), Some(windows)) = (&extras.save_windows, &dance.windows) {
        choreo_datasets::write_npy(path, windows.view().into_dyn())
            .with_context(|| format!("writing the windows to {}", path.display()))
            .map_err(write)?;
    }
    let model_sha256 =
        choreo_datasets::sha256_file(&package.dir().join(choreo_models::MANIFEST_FILE))
            .with_context(|| format!("reading the manifest of {}", package.dir().display()))
            .map_err(write)?;
    let mut source = DanceSource::default();
    source.name = file_name(audio);
    source.sha256 = source_sha256;
    source.model_sha256 = model_sha256;
    source.init_noise_sha256 = extras.init_noise_sha256.clone();
    source.started_utc = started_utc;
    let (stats, fps) = (dance.stats, dance.fps);
    let motion = choreo_models::dance_motion_file(&manifest, &options, dance, mel.view(), source)
        .map_err(|e| write(e.into()))?;
    choreo_datasets::write_motion_as(output, &motion, &extras.export)
        .with_context(|| format!("writing {}", output.display()))
        .map_err(write)?;
    let write_s = t_write.elapsed().as_secs_f64();
    let total_s = t0.elapsed().as_secs_f64();
    Ok(report(
        &audio_stats,
        &stats,
        generate_s,
        write_s,
        total_s,
        fps,
    ))
}

fn report(
    audio: &choreo_dsp::Stats,
    stats: &DanceStats,
    generate_s: f64,
    write_s: f64,
    total_s: f64,
    fps: f64,
) -> DanceReport {
    DanceReport {
        decode_s: audio.decode_s,
        resample_s: audio.resample_s,
        mel_s: audio.mel_s,
        features_total_s: audio.total_s,
        generate_s,
        ort_s: stats.ort_seconds,
        write_s,
        total_s,
        audio_s: audio.duration_s,
        frames: stats.frames,
        fps,
        windows: stats.windows,
        network_evaluations: stats.evaluations,
        batch_rows: stats.rows,
        steps: stats.steps,
        prologue_runs: stats.prologue_runs,
        realtime_factor: if total_s > 0.0 {
            audio.duration_s / total_s
        } else {
            0.0
        },
    }
}

pub(crate) fn file_name(path: &Path) -> String {
    path.file_name().map_or_else(
        || path.display().to_string(),
        |n| n.to_string_lossy().into_owned(),
    )
}

/// The bundled default package: `models/packages/exemplar` in a directory above the executable
/// (the checkout it was built in), unless `CHOREOD_MODEL` names another.
pub fn default_model_dir() -> PathBuf {
    if let Some(dir) = std::env::var_os("CHOREOD_MODEL").filter(|d| !d.is_empty()) {
        return PathBuf::from(dir);
    }
    bundled_package_dir("exemplar")
}

/// `models/packages/<name>` in the nearest directory above the executable that has it (the
/// checkout it was built in), else that relative path.
pub fn bundled_package_dir(name: &str) -> PathBuf {
    let relative = Path::new("models").join("packages").join(name);
    std::env::current_exe()
        .ok()
        .iter()
        .flat_map(|e| e.ancestors().skip(1))
        .map(|dir| dir.join(&relative))
        .find(|candidate| candidate.join(choreo_models::MANIFEST_FILE).exists())
        .unwrap_or(relative)
}
