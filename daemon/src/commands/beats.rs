//! `choreod beats AUDIO [--json]`: tempo and beat times (librosa's beat tracker).

use std::path::{Path, PathBuf};

use anyhow::Context;
use clap::Args;

use crate::cli::GlobalArgs;
use crate::dance::name_duration_limit;

/// Analysis rate of the beat tracker (the rate the reference features use).
const SR: u32 = 16_000;

/// Arguments of `beats`.
#[derive(Debug, Args)]
#[command(after_help = "\
Examples:
  choreod beats song.ogg             tempo on the first line, then one beat time (s) per line
  choreod beats song.ogg --json      {\"tempo_bpm\": .., \"beat_times_s\": [..], \"beat\": \"steady\", ..}

The audio is analysed at 16 kHz with hop 512 (31.25 frames/s): librosa's onset_strength and
beat_track (start_bpm 120, tightness 100, weak leading/trailing beats trimmed). --json adds the
check `choreod dance` makes for input that is not music: beat (steady, weak, no_steady_beat,
no_onsets) and its measures on the 80-band log-mel the dance packages hear.")]
pub struct BeatsArgs {
    /// Audio file (any format `choreod mel` reads).
    pub audio: PathBuf,
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
    /// Centre of the tempo prior, BPM.
    #[arg(long, default_value_t = choreo_dsp::BeatOptions::default().start_bpm)]
    pub start_bpm: f64,
    /// Refuse audio longer than this many seconds (0.1..=86400).
    #[arg(long, default_value_t = choreo_dsp::DecodeOptions::default().max_duration_s,
          value_name = "SECONDS", value_parser = crate::cli::max_seconds)]
    pub max_duration: f64,
}

/// Decode `audio` and track its beats at 16 kHz; returns the beats and the audio's duration (s).
pub fn track(
    audio: &Path,
    start_bpm: f64,
    max_duration_s: f64,
) -> anyhow::Result<(choreo_dsp::Beats, f64)> {
    let (y, duration_s) = decode_16k(audio, max_duration_s)?;
    Ok((track_samples(audio, &y, start_bpm)?, duration_s))
}

/// `audio` decoded, mixed to mono and resampled to 16 kHz; and its duration (s).
fn decode_16k(audio: &Path, max_duration_s: f64) -> anyhow::Result<(Vec<f32>, f64)> {
    let mut decode = choreo_dsp::DecodeOptions::default();
    decode.max_duration_s = max_duration_s;
    // dsp errors name the file already; the later steps only fail on internal limits.
    let decoded = choreo_dsp::decode_file(audio, &decode)
        .map_err(|e| name_duration_limit(e, "--max-duration"))?;
    let y = choreo_dsp::resample_to(&decoded.samples, decoded.sample_rate, SR)
        .with_context(|| format!("resampling {}", audio.display()))?;
    Ok((y, decoded.duration_s))
}

fn track_samples(audio: &Path, y: &[f32], start_bpm: f64) -> anyhow::Result<choreo_dsp::Beats> {
    let mut opts = choreo_dsp::BeatOptions::default();
    opts.start_bpm = start_bpm;
    choreo_dsp::track_beats(y, SR, &opts)
        .with_context(|| format!("tracking beats of {}", audio.display()))
}

/// The beat check of `choreod dance` on `y` (16 kHz) with the dance packages' log-mel.
fn presence(y: &[f32]) -> choreo_dsp::Result<choreo_dsp::BeatPresence> {
    let mel = choreo_dsp::MelOptions::default();
    let log_mel = choreo_dsp::log_mel(y, &mel)?;
    Ok(choreo_dsp::beat_presence(
        log_mel.view(),
        f64::from(mel.sample_rate) / mel.hop_length as f64,
    ))
}

pub fn run(args: BeatsArgs, _global: &GlobalArgs) -> anyhow::Result<()> {
    anyhow::ensure!(
        args.start_bpm > 0.0 && args.start_bpm.is_finite(),
        "--start-bpm must be > 0"
    );
    let (y, duration_s) = decode_16k(&args.audio, args.max_duration)?;
    let beats = track_samples(&args.audio, &y, args.start_bpm)?;
    if args.json {
        let presence = presence(&y)
            .with_context(|| format!("checking the beat of {}", args.audio.display()))?;
        let v = serde_json::json!({
            "file": args.audio.display().to_string(),
            "tempo_bpm": beats.tempo_bpm,
            "beat_times_s": beats.beat_times_s,
            "duration_s": duration_s,
            "beat": presence.verdict.as_str(),
            "beat_periodicity": presence.periodicity,
            "onset_db": presence.onset_db,
            "loudness_fluctuation_db": presence.fluctuation_db,
        });
        super::print_stdout(&format!("{v}\n"))
    } else {
        let mut text = format!(
            "tempo {:.2} BPM, {} beats\n",
            beats.tempo_bpm,
            beats.beat_times_s.len()
        );
        for t in &beats.beat_times_s {
            text += &format!("{t:.3}\n");
        }
        super::print_stdout(&text)
    }
}
