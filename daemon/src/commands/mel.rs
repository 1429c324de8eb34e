//! `choreod mel AUDIO -o OUT.npy [--stats]`: librosa-exact log-mel features as float32 `.npy`.

use std::path::PathBuf;

use anyhow::Context;
use clap::Args;

use crate::cli::GlobalArgs;
use crate::dance::name_duration_limit;

/// Arguments of `mel`.
#[derive(Debug, Args)]
#[command(after_help = "\
Examples:
  choreod mel song.ogg -o song.mel.npy               (80, T) float32, T = 1 + samples // 512
  choreod mel song.flac -o m.npy --stats             also print one JSON line of per-stage seconds
  choreod mel song.wav -o m.npy --n-mels 128 --fmax 11025 --sr 22050

Numerics follow librosa 0.11: load(sr) with channel mean, melspectrogram(n_fft 2048, hop 512,
periodic Hann, centred zero padding, power 2, Slaney scale and norm), power_to_db(ref 1,
amin 1e-10, top_db 80). Load in Python with numpy.load(OUT).")]
pub struct MelArgs {
    /// Audio file: WAV, FLAC, MP3, Ogg Vorbis, AAC/ALAC in MP4/M4A, AIFF (not Opus).
    pub audio: PathBuf,
    /// Output `.npy` (written atomically: temporary name, then rename).
    #[arg(short = 'o', long = "output", value_name = "OUT.npy")]
    pub output: PathBuf,
    /// Print one JSON line on stdout: decode_s, resample_s, mel_s, total_s, frames.
    #[arg(long)]
    pub stats: bool,
    /// Analysis sample rate, Hz.
    #[arg(long, default_value_t = choreo_dsp::MelOptions::default().sample_rate)]
    pub sr: u32,
    /// Mel bands.
    #[arg(long, default_value_t = choreo_dsp::MelOptions::default().n_mels)]
    pub n_mels: usize,
    /// FFT size and window length, samples.
    #[arg(long, default_value_t = choreo_dsp::MelOptions::default().n_fft)]
    pub n_fft: usize,
    /// Hop between frames, samples.
    #[arg(long, default_value_t = choreo_dsp::MelOptions::default().hop_length)]
    pub hop: usize,
    /// Lowest band edge, Hz.
    #[arg(long, default_value_t = choreo_dsp::MelOptions::default().fmin)]
    pub fmin: f64,
    /// Highest band edge, Hz (default: 8000, or sr/2 if lower).
    #[arg(long)]
    pub fmax: Option<f64>,
    /// Dynamic range kept below the loudest value, dB (librosa top_db).
    #[arg(long, default_value_t = mel_default_top_db(), conflicts_with = "no_top_db")]
    pub top_db: f32,
    /// Do not clamp the dynamic range.
    #[arg(long)]
    pub no_top_db: bool,
    /// Refuse audio longer than this many seconds (0.1..=86400).
    #[arg(long, default_value_t = choreo_dsp::DecodeOptions::default().max_duration_s,
          value_name = "SECONDS", value_parser = crate::cli::max_seconds)]
    pub max_duration: f64,
}

impl MelArgs {
    /// The analysis options these flags describe.
    pub fn mel_options(&self) -> choreo_dsp::MelOptions {
        let mut o = choreo_dsp::MelOptions::default();
        o.sample_rate = self.sr;
        o.n_mels = self.n_mels;
        o.n_fft = self.n_fft;
        o.hop_length = self.hop;
        o.fmin = self.fmin;
        o.fmax = self
            .fmax
            .unwrap_or_else(|| o.fmax.min(f64::from(self.sr) / 2.0));
        o.top_db = (!self.no_top_db).then_some(self.top_db);
        o
    }
}

pub fn run(args: MelArgs, _global: &GlobalArgs) -> anyhow::Result<()> {
    super::refuse_output_over_input(&args.output, "-o", &[("the audio", &args.audio)])?;
    let mel = args.mel_options();
    mel.validate().context("invalid mel options")?;
    let mut decode = choreo_dsp::DecodeOptions::default();
    decode.max_duration_s = args.max_duration;
    // dsp errors name the file already.
    let (features, stats) = choreo_dsp::load_log_mel(&args.audio, &decode, &mel)
        .map_err(|e| name_duration_limit(e, "--max-duration"))?;
    let (n_mels, frames) = features.dim();
    let data = features.as_standard_layout();
    let slice = data.as_slice().context("log-mel array is not contiguous")?;
    choreo_dsp::write_npy_f32(&args.output, &[n_mels, frames], slice)?;
    tracing::info!(audio = %args.audio.display(), output = %args.output.display(), frames, "log-mel written");
    if args.stats {
        let line = serde_json::json!({
            "decode_s": stats.decode_s,
            "resample_s": stats.resample_s,
            "mel_s": stats.mel_s,
            "total_s": stats.total_s,
            "frames": stats.frames,
            "source_rate": stats.source_rate,
            "source_channels": stats.source_channels,
            "duration_s": stats.duration_s,
        });
        println!("{line}");
    }
    Ok(())
}

/// `--top-db`'s default: the library's (librosa's 80 dB).
fn mel_default_top_db() -> f32 {
    choreo_dsp::MelOptions::default()
        .top_db
        .expect("the mel's default keeps a top_db")
}
