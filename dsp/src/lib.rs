//! Audio front end of choreod: file → mono f32 → 16 kHz → librosa-exact log-mel, streaming
//! frames for live input, onset strength and beats.
//!
//! - [`decode_file`], [`AudioFileReader`] (pull; `Ok(None)` at the end of the stream): symphonia
//!   decoding of WAV, FLAC, MP3, Ogg Vorbis, AAC/ALAC in MP4, AIFF, mixed to mono by the channel
//!   mean ([`mix_to_mono`], shared with live capture), bounded by [`DecodeOptions`]; AAC edit
//!   lists applied (symphonia does not).
//! - [`resample_to`] / [`StreamResampler`]: rubato FFT resampling in fixed blocks
//!   (chunk-invariant), trimmed and sized like librosa's `resample`.
//! - [`MelOptions`], [`log_mel`]: librosa's `melspectrogram` + `power_to_db`, `(n_mels, T)`.
//! - [`LogMelStream`] ([`FeatureStream`]): the same frames from chunks of any size at any rate.
//! - [`onset_strength`], [`track_beats`]: librosa's onset envelope, tempo and DP beat tracker.
//! - [`beat_presence`]: whether a log-mel has a steady beat, or is speech, noise or a drone.
//! - [`load_log_mel`]: one call from a file to features, decoding on a second thread.
//! - [`write_npy_f32`]: atomic float32 `.npy` output; [`atomic`]: the atomic file writer every
//!   crate of choreod uses (temporary name, fsync, rename, fsync of the directory).
//! - [`quote`]: input text (a token, key or name read from a file) in a message, cut short, as
//!   every reader of choreod quotes it; [`quote_inside`] for input text inside another parser's
//!   sentence (TOML's messages).
// "deny", not "forbid": `soxr` calls libsoxr through its C API (the one unsafe block).
#![deny(unsafe_code)]

pub mod atomic;
mod beats;
mod beats_dp;
mod chroma;
mod decode;
mod error;
mod fact35;
mod kaiser;
mod mel;
mod mp4;
mod npy;
mod onset;
mod peaks;
mod pipeline;
mod quote;
mod resample;
mod soxr;
mod spectrum;
mod steadiness;
mod stream;

pub use beats::{BeatOptions, Beats, track_beats, track_beats_from_onsets};
pub use beats_dp::{DpBeatOptions, beat_track_dp, tempo as tempo_dp};
pub use chroma::{chroma_cens, cqt_magnitude_07, cqt_magnitude_010, estimate_tuning};
pub use decode::{
    AudioFileReader, Chunk, DecodeOptions, DecodeSummary, DecodedAudio, MAX_SAMPLE_RATE,
    decode_file, decode_file_with, mix_to_mono,
};
pub use error::{Error, Result};
pub use fact35::{
    FACT35_COLUMNS, FACT35_HOP, FACT35_MIN_SECONDS, Fact35, Fact35Options, Fact35Stats,
    LibrosaVersion, StartBpmSource, aist_start_bpm, fact35_from_samples, load_fact35,
    mfcc_from_power, onset_envelope, onset_from_power,
};
pub use kaiser::{KaiserFilter, resample_kaiser};
pub use mel::{
    FrameAnalyzer, MelFilterbank, MelOptions, clamp_top_db, hz_to_mel, log_mel, mel_to_hz,
};
pub use npy::{write_npy_f32, write_npy_to};
pub use onset::{OnsetOptions, onset_strength};
pub use peaks::{PeakNormalize, PeakWindows, onset_detect, peak_pick};
pub use pipeline::{Stats, load_log_mel};
pub use quote::{QUOTE_CHARS, quote, quote_inside};
pub use resample::{OUTPUT_BLOCK, StreamResampler, resample_to};
pub use soxr::resample_soxr_hq;
pub use spectrum::{PadMode, Stft, Window, power_to_db};
pub use steadiness::{
    BURST_ONSET_DB, BeatPresence, BeatVerdict, MIN_ONSET_DB, MIN_PERIODICITY, NOISE_FLUCTUATION_DB,
    SPARSE_ONSET_DB, beat_presence,
};
pub use stream::{FeatureStream, LogMelStream};
