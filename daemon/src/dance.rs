//! One song → one dance file: the job that `choreod dance` runs once and `choreod serve` runs per
//! inbox file. The song pipeline (models: decode, log-mel, dance, motion file) → the file written
//! atomically (datasets); here: the stage a failure belongs to, the knobs a refusal names, the
//! write's time.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use choreo_models::{MinimumLength, ModelPackage, SongOptions, SongReport};

/// Where the time went and what was made: the pipeline's report and the write.
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct DanceReport {
    #[serde(flatten)]
    pub song: SongReport,
    pub write_s: f64,
    pub total_s: f64,
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

impl Stage {
    /// The stage of a pipeline error: the song's own problems are the decode stage's.
    fn of(error: &choreo_models::Error) -> Self {
        match error {
            choreo_models::Error::Audio(_)
            | choreo_models::Error::SongTooShort { .. }
            | choreo_models::Error::SongTruncated { .. }
            | choreo_models::Error::Datasets(_) => Self::Decode,
            _ => Self::Generate,
        }
    }

    /// The name in error reports and metrics.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Decode => "decode",
            Self::Generate => "generate",
            Self::Write => "write",
        }
    }
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

/// What `choreod dance` adds to a job: where to save the sampler's windows, and the export.
#[derive(Debug, Clone, Default)]
pub struct DanceExtras {
    /// Write the sampler's final windows (normalised, before stitching) here as `.npy` (LODGE:
    /// both stages' windows as `.npz`).
    pub save_windows: Option<PathBuf>,
    /// Bone names and mesh of a `.bvh` / `.glb` / `.gltf` output (the output's extension picks
    /// the format: [`choreo_datasets::write_motion_as`]).
    pub export: choreo_datasets::ExportOptions,
}

/// The flags and config keys that set the song limits, named in refusals (the library knows
/// only the values).
const MAX_DURATION_KNOB: &str = "--max-duration / limits.max_audio_seconds";
const MIN_DURATION_KNOB: &str = "limits.min_audio_seconds / --min-duration";

/// A refusal of too long a song names the user's knob (`knob`: a flag, a config key), which the
/// decoder, knowing only the value, cannot; other decode errors pass through unchanged.
pub fn name_duration_limit(err: choreo_dsp::Error, knob: &str) -> anyhow::Error {
    match err {
        choreo_dsp::Error::TooLong { .. } => anyhow::anyhow!("{err} ({knob})"),
        other => other.into(),
    }
}

/// A song pipeline's error, with the user's knob named where one set the limit it hit.
fn name_song_limit(err: choreo_models::Error) -> anyhow::Error {
    match err {
        choreo_models::Error::Audio(e) => name_duration_limit(e, MAX_DURATION_KNOB),
        e @ choreo_models::Error::SongTooShort {
            minimum: MinimumLength::Configured { .. },
            ..
        } => anyhow::anyhow!("{e} ({MIN_DURATION_KNOB})"),
        other => other.into(),
    }
}

/// Make a dance for `audio` with `package` and write it to `output` (atomically).
pub fn dance_file(
    package: &mut ModelPackage,
    audio: &Path,
    output: &Path,
    options: &SongOptions,
    extras: &DanceExtras,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<DanceReport, JobError> {
    let t0 = Instant::now();
    let dance = choreo_models::dance_song(package, audio, options, progress).map_err(|e| {
        let stage = Stage::of(&e);
        let error = match stage {
            Stage::Generate => {
                anyhow::Error::new(e).context(format!("generating a dance for {}", audio.display()))
            }
            _ => name_song_limit(e),
        };
        JobError { stage, error }
    })?;
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
    if let (Some(path), Some(w)) = (&extras.save_windows, &dance.lodge_windows) {
        choreo_datasets::write_npz(
            path,
            &[
                ("global_windows", w.global.view().into_dyn()),
                ("local_windows", w.local.view().into_dyn()),
                (
                    "local_constraint_value",
                    w.constraints.value.view().into_dyn(),
                ),
                (
                    "local_constraint_mask",
                    w.constraints.mask.view().into_dyn(),
                ),
            ],
        )
        .with_context(|| format!("writing the windows to {}", path.display()))
        .map_err(write)?;
    }
    choreo_datasets::write_motion_as(output, &dance.motion, &extras.export)
        .with_context(|| format!("writing {}", output.display()))
        .map_err(write)?;
    let write_s = t_write.elapsed().as_secs_f64();
    let total_s = t0.elapsed().as_secs_f64();
    if let Some((genre, why)) = &dance.genre {
        tracing::info!(genre = %genre, reason = %why, "genre");
    }
    Ok(DanceReport {
        song: dance.report,
        write_s,
        total_s,
        realtime_factor: if total_s > 0.0 {
            dance.report.audio_s / total_s
        } else {
            0.0
        },
    })
}
