//! `choreod features AUDIO -o OUT.npy --set fact35`: the dance field's 35 librosa music
//! features per frame as float32 `.npy` `(T, 35)`.

use std::path::PathBuf;

use clap::Args;

use crate::cli::{FeatureSet, GlobalArgs, LibrosaArg};
use crate::dance::name_duration_limit;

/// Arguments of `features`.
#[derive(Debug, Args)]
#[command(after_help = "\
Examples:
  choreod features song.wav -o song.fact35.npy --set fact35        (T, 35), 30 fps, librosa 0.7.2
  choreod features gBR_sBM_cAll_d04_mBR0_ch01.wav -o f.npy --set fact35 --fps 60   FACT's 60 fps
  choreod features song.flac -o f.npy --set fact35 --start-bpm 96 --stats
  choreod features song.ogg -o f.npy --set fact35 --librosa 0.10   current librosa's numbers

Columns: 0 onset strength, 1-20 MFCC, 21-32 chroma_cens (C..B), 33 onset peaks (one-hot),
34 beats (one-hot); frames 1 + floor(samples / 512) at sr = fps x 512 Hz; not normalised.
Beat tracking starts from --start-bpm, else from an AIST++ name (its fifth '_' field, e.g.
mBR0 -> 80 BPM), else from the song's tempo estimated at 22050 Hz, as LODGE and EDGE do.
Load in Python with numpy.load(OUT).")]
pub struct FeaturesArgs {
    /// Audio file: WAV, FLAC, MP3, Ogg Vorbis, AAC/ALAC in MP4/M4A, AIFF (not Opus).
    pub audio: PathBuf,
    /// Output `.npy` (written atomically: temporary name, then rename).
    #[arg(short = 'o', long = "output", value_name = "OUT.npy")]
    pub output: PathBuf,
    /// Feature set.
    #[arg(long = "set", value_enum)]
    pub set: FeatureSet,
    /// Frames per second (sr = fps x 512 Hz): 30 (LODGE, FineDance, EDGE) or 60 (FACT).
    #[arg(long, default_value_t = choreo_dsp::Fact35Options::default().fps, value_parser = parse_fps)]
    pub fps: u32,
    /// The librosa whose numbers to reproduce.
    #[arg(long, value_enum, default_value = "0.7")]
    pub librosa: LibrosaArg,
    /// Tempo prior of the beat tracker, BPM (default: the start-BPM rule above).
    #[arg(long, value_name = "BPM")]
    pub start_bpm: Option<f64>,
    /// Print one JSON line on stdout: per-stage seconds, frames, start BPM and its source,
    /// tempo, tuning.
    #[arg(long)]
    pub stats: bool,
    /// Refuse audio longer than this many seconds.
    #[arg(long, default_value_t = choreo_dsp::DecodeOptions::default().max_duration_s,
          value_name = "SECONDS")]
    pub max_duration: f64,
}

/// The two rates the field computes these features at.
fn parse_fps(s: &str) -> Result<u32, String> {
    match s {
        "30" => Ok(30),
        "60" => Ok(60),
        _ => Err("the fact35 features exist at 30 or 60 fps".to_string()),
    }
}

pub fn run(args: FeaturesArgs, _global: &GlobalArgs) -> anyhow::Result<()> {
    let FeatureSet::Fact35 = args.set;
    let opts = choreo_dsp::Fact35Options {
        fps: args.fps,
        version: args.librosa.version(),
        start_bpm: args.start_bpm,
    };
    super::check_output_folder(&args.output, "-o")?;
    let mut decode = choreo_dsp::DecodeOptions::default();
    decode.max_duration_s = args.max_duration;
    let f = choreo_dsp::load_fact35(&args.audio, &decode, &opts).map_err(|e| match e {
        // Decoding errors name the file already; analysis errors do not.
        choreo_dsp::Error::TooShort { .. } | choreo_dsp::Error::BadOption { .. } => {
            anyhow::Error::new(e).context(args.audio.display().to_string())
        }
        other => name_duration_limit(other, "--max-duration"),
    })?;
    choreo_dsp::write_npy_f32(
        &args.output,
        &[f.frames, choreo_dsp::FACT35_COLUMNS],
        &f.data,
    )?;
    tracing::info!(audio = %args.audio.display(), output = %args.output.display(), frames = f.frames,
        start_bpm = f.start_bpm, tempo = f.tempo_bpm, "fact35 features written");
    if args.stats {
        let s = &f.stats;
        let source = match f.start_bpm_source {
            choreo_dsp::StartBpmSource::Given => "given",
            choreo_dsp::StartBpmSource::FileName => "file name",
            choreo_dsp::StartBpmSource::Estimated => "estimated",
        };
        let line = serde_json::json!({
            "decode_s": s.decode_s,
            "resample_s": s.resample_s,
            "stft_s": s.stft_s,
            "mfcc_onset_s": s.mfcc_onset_s,
            "chroma_s": s.chroma_s,
            "start_bpm_s": s.start_bpm_s,
            "peaks_beats_s": s.peaks_beats_s,
            "total_s": s.total_s,
            "frames": f.frames,
            "start_bpm": f.start_bpm,
            "start_bpm_source": source,
            "tempo_bpm": f.tempo_bpm,
            "tuning": f.tuning,
        });
        super::print_stdout(&format!("{line}\n"))?;
    }
    Ok(())
}
