//! A song to a dance, end to end (pipeline): the audio file → decoded and its log-mel (dsp, at
//! the package's audio parameters) → checked against the package's shortest song → the dance
//! ([`generate_dance`]) → its motion file ([`dance_motion_file`]: joints, log-mel, provenance
//! with both files' sha256). What `choreod dance` runs once and `choreod serve` runs per inbox
//! file; the caller writes the returned [`MotionFile`] (`choreo_datasets::write_motion_as`).

use std::path::Path;
use std::time::Instant;

use choreo_datasets::MotionFile;
use ndarray::{Array2, Array3};

use crate::error::{Error, MinimumLength, Result};
use crate::package::ModelPackage;
use crate::package::manifest::{DanceSpec, MANIFEST_FILE, Manifest, Task};
use crate::pipelines::dance::{DanceOptions, DanceSource, dance_motion_file, generate_dance};
use crate::pipelines::lodge::{LodgeOptions, LodgeStage, LodgeWindows, generate_lodge};

/// Options of one song: the generation's and the limits on the input, checked before it is
/// read whole.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub struct SongOptions {
    /// The generation's options; their `duration_s` is the decoded song's when `None`.
    /// Default: [`DanceOptions::default`].
    pub dance: DanceOptions,
    /// Refuse files bigger than this many bytes. Default: 512 MiB.
    pub max_file_bytes: u64,
    /// Refuse songs longer than this many seconds. Default: 1200 (20 min, the design target).
    pub max_audio_seconds: f64,
    /// Refuse songs shorter than this many seconds; `None`: one motion window of the model
    /// ([`minimum_length`]). Default: None.
    pub min_audio_seconds: Option<f64>,
    /// LODGE packages: genre, exact mode, the draws of `--init-noise`.
    pub lodge: LodgeOptions,
    /// LODGE packages: precomputed `(T, 35)` fact35 features read instead of decoding the
    /// song (`--features`); the song path then names this features file.
    pub features: Option<Array2<f32>>,
    /// sha256 of the file the initial noise came from, for the provenance ("" when the noise
    /// comes from the seed). Default: "".
    pub init_noise_sha256: String,
    /// Refuse a song whose file ends mid-stream ([`Error::SongTruncated`]) instead of dancing
    /// the audio before the damage (which the report and provenance record). Default: false.
    pub fail_truncated: bool,
}

impl Default for SongOptions {
    fn default() -> Self {
        Self {
            dance: DanceOptions::default(),
            max_file_bytes: 512 * 1024 * 1024,
            max_audio_seconds: 1200.0,
            min_audio_seconds: None,
            lodge: LodgeOptions::default(),
            features: None,
            init_noise_sha256: String::new(),
            fail_truncated: false,
        }
    }
}

/// Where the time went and what was made.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
#[non_exhaustive]
pub struct SongReport {
    /// Seconds decoding the audio.
    pub decode_s: f64,
    /// Seconds resampling it to the model's rate.
    pub resample_s: f64,
    /// Seconds computing the log-mel.
    pub mel_s: f64,
    /// Wall seconds of decode, resample and log-mel together.
    pub features_total_s: f64,
    /// Seconds generating the dance.
    pub generate_s: f64,
    /// Seconds inside ONNX Runtime (or the denoiser).
    pub ort_s: f64,
    /// Seconds of the song (decoded: of a truncated file, the audio before the damage).
    pub audio_s: f64,
    /// The file ended mid-stream: the dance is of its first `audio_s` seconds.
    pub audio_truncated: bool,
    /// Undecodable packets skipped.
    pub skipped_packets: usize,
    /// Frames of the dance.
    pub frames: usize,
    /// Its frame rate.
    pub fps: f64,
    /// Windows generated.
    pub windows: usize,
    /// Network evaluations (batched calls).
    pub network_evaluations: usize,
    /// Batch rows evaluated.
    pub batch_rows: usize,
    /// Denoising steps per chunk.
    pub steps: usize,
    /// Runs of the denoiser's hoisted prologue (0: the whole graph ran at every step).
    pub prologue_runs: usize,
    /// Whether the song has a beat to follow ([`choreo_dsp::beat_presence`] on its log-mel):
    /// `steady`, `weak`, `no_steady_beat` or `no_onsets`; "" when not checked (LODGE packages).
    pub beat: &'static str,
    /// The check's periodicity (0..1; a steady beat from [`choreo_dsp::MIN_PERIODICITY`]).
    pub beat_periodicity: f64,
    /// The check's mean onset strength, dB per frame.
    pub onset_db: f64,
    /// The check's short-time loudness fluctuation, dB.
    pub loudness_fluctuation_db: f64,
}

/// A song's dance.
#[derive(Debug, Clone)]
#[non_exhaustive]
pub struct SongDance {
    /// The motion file to write: joints, the song's log-mel, provenance.
    pub motion: MotionFile,
    /// The sampler's final windows (windows, T, D), normalised, when
    /// [`DanceOptions::keep_windows`].
    pub windows: Option<Array3<f32>>,
    /// LODGE: both stages' final normalised windows and the Local in-painting, when
    /// [`DanceOptions::keep_windows`].
    pub lodge_windows: Option<LodgeWindows>,
    /// LODGE: the genre danced and why.
    pub genre: Option<(String, String)>,
    /// Timings and counters.
    pub report: SongReport,
}

/// Farthest a body's joint gets from its root joint, metres: a person with arms raised reaches
/// about 1.3 m from the pelvis (SMPL's rest pose: wrist 0.85 m to the side, head 0.6 m up);
/// well past that the model made no body.
const MAX_BODY_REACH_M: f64 = 3.0;

/// The dance for the song in `audio` with `package`. Errors: the audio ([`Error::Audio`],
/// [`Error::SongTooShort`]) and reading the song again for its sha256 ([`Error::Datasets`])
/// fail this song; the others as [`generate_dance`]'s. `progress(done, total)` counts steps.
pub fn dance_song(
    package: &mut ModelPackage,
    audio: &Path,
    options: &SongOptions,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<SongDance> {
    let started_utc = choreo_datasets::now_utc();
    let manifest = package.manifest().clone();
    if manifest.task == Task::Lodge {
        return lodge_song(package, audio, options, progress);
    }
    let spec = manifest.dance_spec()?;
    let (mel, audio_stats) =
        choreo_dsp::load_log_mel(audio, &decode_options(options), &spec.audio.mel_options())?;
    let damage = Damage {
        seconds: audio_stats.duration_s,
        truncated: audio_stats.truncated,
        bad_packets: audio_stats.bad_packets,
    };
    damage.refuse_if_configured(audio, options)?;
    let beat = choreo_dsp::beat_presence(mel.view(), spec.audio.frame_rate());
    let minimum = minimum_length(&manifest, &spec, options.min_audio_seconds);
    if audio_stats.duration_s < minimum.seconds() {
        return Err(Error::SongTooShort {
            path: audio.to_path_buf(),
            seconds: audio_stats.duration_s,
            minimum,
        });
    }
    // After decoding, which has checked the file size against the limit.
    let source_sha256 = choreo_datasets::sha256_file(audio)?;

    let t_generate = Instant::now();
    let mut dance_options = options.dance.clone();
    if dance_options.duration_s.is_none() {
        dance_options.duration_s = Some(audio_stats.duration_s);
    }
    let no_beat = no_beat_note(&beat);
    if let Some(note) = &no_beat {
        tracing::warn!(song = %audio.display(), "{}: {note}", file_name(audio));
    }
    let mut dance = generate_dance(package, mel.view(), &dance_options, progress)?;
    let generate_s = t_generate.elapsed().as_secs_f64();
    let reach = largest_reach_m(&dance.joints);
    if reach > MAX_BODY_REACH_M {
        tracing::warn!(
            song = %audio.display(),
            "the dance is not a body: a joint is {reach:.3e} m from the root (a person reaches \
             under {MAX_BODY_REACH_M} m); the model package is untrained or broken \
             (models/packages/mofusion-ref has random weights), and `choreod render` refuses \
             motions over 1 km wide"
        );
    }
    let windows = dance.windows.take();
    let (stats, fps) = (dance.stats, dance.fps);
    let source = DanceSource {
        name: file_name(audio),
        sha256: source_sha256,
        model_sha256: choreo_datasets::sha256_file(&package.dir().join(MANIFEST_FILE))?,
        init_noise_sha256: options.init_noise_sha256.clone(),
        started_utc,
        damage: damage.describe(),
        beat: no_beat,
    };
    let motion = dance_motion_file(&manifest, &dance_options, dance, mel.view(), source)?;
    let report = SongReport {
        decode_s: audio_stats.decode_s,
        resample_s: audio_stats.resample_s,
        mel_s: audio_stats.mel_s,
        features_total_s: audio_stats.total_s,
        generate_s,
        ort_s: stats.ort_seconds,
        audio_s: audio_stats.duration_s,
        audio_truncated: audio_stats.truncated,
        skipped_packets: audio_stats.bad_packets,
        frames: stats.frames,
        fps,
        windows: stats.windows,
        network_evaluations: stats.evaluations,
        batch_rows: stats.rows,
        steps: stats.steps,
        prologue_runs: stats.prologue_runs,
        beat: beat.verdict.as_str(),
        beat_periodicity: beat.periodicity,
        onset_db: beat.onset_db,
        loudness_fluctuation_db: beat.fluctuation_db,
    };
    Ok(SongDance {
        motion,
        windows,
        lodge_windows: None,
        genre: None,
        report,
    })
}

/// A song (or its precomputed fact35 features) to a LODGE dance's motion file: the raw 139
/// features as `/motion/features`, the SMPL-X body joints by FK from the package's rest joints,
/// provenance with the licence line.
fn lodge_song(
    package: &mut ModelPackage,
    audio: &Path,
    options: &SongOptions,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<SongDance> {
    let started_utc = choreo_datasets::now_utc();
    let manifest = package.manifest().clone();
    let spec = manifest.lodge_spec()?;
    let mut report = SongReport::default();
    let t_features = Instant::now();
    // Precomputed features (`--features`) come whole; a decoded song may not.
    let mut damage = Damage::default();
    let music = match &options.features {
        Some(f) => f.clone(),
        None => {
            let f =
                choreo_dsp::load_fact35(audio, &decode_options(options), &spec.audio.options())?;
            let stats = &f.stats;
            damage = Damage {
                seconds: stats.duration_s,
                truncated: stats.truncated,
                bad_packets: stats.bad_packets,
            };
            damage.refuse_if_configured(audio, options)?;
            report.decode_s = stats.decode_s;
            report.resample_s = stats.resample_s;
            report.audio_truncated = stats.truncated;
            report.skipped_packets = stats.bad_packets;
            Array2::from_shape_vec((f.frames, choreo_dsp::FACT35_COLUMNS), f.data).map_err(|e| {
                Error::Input {
                    what: "fact35 features".into(),
                    reason: e.to_string(),
                }
            })?
        }
    };
    report.features_total_s = t_features.elapsed().as_secs_f64();
    report.audio_s = music.nrows() as f64 / f64::from(spec.audio.fps);
    let source_sha256 = choreo_datasets::sha256_file(audio)?;
    let t_generate = Instant::now();
    let ort0 = package.ort_seconds();
    let mut lodge_options = options.lodge.clone();
    lodge_options.seed = options.dance.seed;
    lodge_options.steps = options.dance.steps;
    lodge_options.eta = options.dance.eta;
    let dance = generate_lodge(
        package,
        music.view(),
        &lodge_options,
        &mut |stage, done, total| {
            // One bar over both stages: the Global stage is the first half.
            let (done, total) = match stage {
                LodgeStage::Global => (done, 2 * total),
                LodgeStage::Local => (total + done, 2 * total),
            };
            progress(done, total);
        },
    )?;
    report.generate_s = t_generate.elapsed().as_secs_f64();
    report.ort_s = package.ort_seconds() - ort0;
    report.frames = dance.features.nrows();
    report.fps = manifest.motion.fps;
    report.windows = dance.stats.local_windows;
    report.network_evaluations = dance.stats.evaluations;
    report.steps = dance.steps;

    let rest = spec.rest_points();
    let joints = choreo_datasets::smplx::features_to_body_joints(
        dance.features.as_slice().expect("standard layout"),
        &rest,
    )?;
    let joints = Array3::from_shape_fn((joints.len(), 22, 3), |(t, j, c)| joints[t][j][c]);
    let skeleton = choreo_datasets::SkeletonKind::Custom {
        name: manifest.motion.skeleton.clone(),
        joint_names: choreo_datasets::smplx::SMPLX_BODY_NAMES
            .iter()
            .map(|n| n.to_string())
            .collect(),
        parents: choreo_datasets::smplx::SMPLX_BODY_PARENTS.to_vec(),
    };
    let mut motion = MotionFile::from_joints(manifest.motion.fps as f32, skeleton, joints);
    motion.features = Some(choreo_datasets::Features {
        data: dance.features.clone(),
        representation: manifest.motion.representation.clone(),
        normalized: false,
    });
    motion.provenance = Some(choreo_datasets::Provenance {
        source_name: file_name(audio),
        source_sha256,
        model_name: manifest.name.clone(),
        model_sha256: choreo_datasets::sha256_file(&package.dir().join(MANIFEST_FILE))?,
        sampler: "ddim".into(),
        steps: dance.steps as u32,
        eta: dance.eta,
        guidance: spec.section.global.guidance,
        seed: options.dance.seed,
        chunk_windows: lodge_options.chunk_windows.max(1) as u32,
        init_noise_sha256: options.init_noise_sha256.clone(),
        started_utc,
        finished_utc: choreo_datasets::now_utc(),
        license: manifest.license_line(),
        source_damage: damage.describe(),
        source_kind: options.features.as_ref().map(|f| {
            format!(
                "fact35 features ({}, {}), danced instead of a song",
                f.nrows(),
                f.ncols()
            )
        }),
        ..Default::default()
    });
    let genre = spec
        .section
        .genres
        .get(dance.genre)
        .cloned()
        .unwrap_or_default();
    Ok(SongDance {
        motion,
        windows: None,
        lodge_windows: options.dance.keep_windows.then_some(LodgeWindows {
            global: dance.global_windows,
            local: dance.local_windows,
            constraints: dance.local_constraints,
        }),
        genre: Some((genre, dance.genre_reason)),
        report,
    })
}

/// What a dance of a song without a beat says about it (the warning and the provenance's
/// `source_beat`): the beat that is missing, the measure that found it missing, and what was
/// danced instead. The bundled package times its dance by the onsets it hears (its beat warp
/// fits a pulse to them, models/packages/exemplar/README.md), so without a beat the timing is
/// the model's guess. `None` when the song has a beat.
fn no_beat_note(beat: &choreo_dsp::BeatPresence) -> Option<String> {
    let like = beat.sounds_like()?;
    Some(match beat.verdict {
        choreo_dsp::BeatVerdict::NoOnsets => format!(
            "no beat: hardly any onsets (onset strength {:.3} dB per frame, under {}), as in \
             {like}; danced anyway, to a pulse the model guessed with nothing to follow",
            beat.onset_db,
            choreo_dsp::MIN_ONSET_DB
        ),
        _ => format!(
            "no steady beat: its onsets keep no fixed period (periodicity {:.2}; a steady beat \
             scores {} or more); it sounds like {like}; danced anyway, to a pulse the model \
             guessed from those onsets, not to a beat of the audio",
            beat.periodicity,
            choreo_dsp::MIN_PERIODICITY
        ),
    })
}

/// The decoder's limits from the song options (both the log-mel and the fact35 paths).
fn decode_options(options: &SongOptions) -> choreo_dsp::DecodeOptions {
    let mut decode = choreo_dsp::DecodeOptions::default();
    decode.max_file_bytes = options.max_file_bytes;
    decode.max_duration_s = options.max_audio_seconds;
    decode
}

/// What the decoder found wrong with a song it decoded in part.
#[derive(Debug, Clone, Copy, Default)]
struct Damage {
    /// Seconds decoded.
    seconds: f64,
    /// The file ended mid-stream.
    truncated: bool,
    /// Undecodable packets skipped.
    bad_packets: usize,
}

impl Damage {
    /// [`Error::SongTruncated`] when the file ended mid-stream and the options refuse that.
    fn refuse_if_configured(&self, audio: &Path, options: &SongOptions) -> Result<()> {
        if self.truncated && options.fail_truncated {
            return Err(Error::SongTruncated {
                path: audio.to_path_buf(),
                seconds: self.seconds,
            });
        }
        Ok(())
    }

    /// The provenance's `source_damage`; `None` when the song decoded whole.
    fn describe(&self) -> Option<String> {
        let mut parts = Vec::new();
        if self.truncated {
            parts.push(format!(
                "the file ends mid-stream: {:.3} s of audio decoded",
                self.seconds
            ));
        }
        if self.bad_packets > 0 {
            parts.push(format!("{} undecodable packets skipped", self.bad_packets));
        }
        (!parts.is_empty()).then(|| parts.join("; "))
    }
}

/// The shortest song the package accepts, and why: `configured` seconds, else one motion window
/// of the model (`window_frames / fps`: every window the model makes is this long, so a shorter
/// song is mostly padding; EDGE's inference, too, slices a song into whole 5 s windows and gets
/// none from a shorter one: Stanford-TML/EDGE `data/slice.py` `slice_audio`, line 18, `while
/// start_idx <= len(audio) - window`). Never below one analysis window of the model's features
/// (`n_fft` samples): shorter, every mel frame is padding.
pub fn minimum_length(
    manifest: &Manifest,
    spec: &DanceSpec<'_>,
    configured: Option<f64>,
) -> MinimumLength {
    let a = spec.audio;
    let wanted = match configured {
        Some(seconds) => MinimumLength::Configured { seconds },
        None => MinimumLength::MotionWindow {
            model: manifest.name.clone(),
            frames: spec.window_frames,
            fps: manifest.motion.fps,
        },
    };
    let analysis = MinimumLength::AnalysisWindow {
        n_fft: a.n_fft,
        sample_rate: a.sample_rate,
    };
    let seconds = wanted.seconds();
    if seconds.is_nan() || seconds < analysis.seconds() {
        analysis
    } else {
        wanted
    }
}

/// The largest distance of any joint from joint 0 (the root) in any frame, metres.
fn largest_reach_m(joints: &Array3<f32>) -> f64 {
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

/// The file name of `path` for a provenance (the whole path when it has none).
pub(crate) fn file_name(path: &Path) -> String {
    path.file_name().map_or_else(
        || path.display().to_string(),
        |n| n.to_string_lossy().into_owned(),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_a_song_without_a_beat_gets_a_note_naming_what_it_lacks_and_what_was_danced() {
        // A held tone: every frame the same (no onsets). A click every 16 frames: steady.
        let held = ndarray::Array2::from_elem((80, 600), -30.0f32);
        let note = no_beat_note(&choreo_dsp::beat_presence(held.view(), 31.25)).unwrap();
        assert!(
            note.starts_with("no beat: hardly any onsets")
                && note.contains("a drone, a held tone or silence")
                && note.contains("danced anyway"),
            "{note}"
        );
        let clicks =
            ndarray::Array2::from_shape_fn(
                (80, 600),
                |(_, t)| if t % 16 == 0 { -20.0 } else { -40.0 },
            );
        assert_eq!(
            no_beat_note(&choreo_dsp::beat_presence(clicks.view(), 31.25)),
            None
        );
    }
}
