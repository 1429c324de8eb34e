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
//! - [`load_log_mel`]: one call from a file to features, decoding on a second thread.
//! - [`write_npy_f32`]: atomic float32 `.npy` output; [`atomic`]: the atomic file writer every
//!   crate of choreod uses (temporary name, fsync, rename, fsync of the directory).
//! - [`quote`]: input text (a token, key or name read from a file) in a message, cut short, as
//!   every reader of choreod quotes it.
#![forbid(unsafe_code)]

pub mod atomic;
mod beats;
mod decode;
mod error;
mod mel;
mod mp4;
mod npy;
mod onset;
mod pipeline;
mod quote;
mod resample;
mod stream;

pub use beats::{BeatOptions, Beats, track_beats, track_beats_from_onsets};
pub use decode::{
    AudioFileReader, Chunk, DecodeOptions, DecodeSummary, DecodedAudio, MAX_SAMPLE_RATE,
    decode_file, decode_file_with, mix_to_mono,
};
pub use error::{Error, Result};
pub use mel::{
    FrameAnalyzer, MelFilterbank, MelOptions, clamp_top_db, hz_to_mel, log_mel, mel_to_hz,
};
pub use npy::write_npy_f32;
pub use onset::{OnsetOptions, onset_strength};
pub use pipeline::{Stats, load_log_mel};
pub use quote::{QUOTE_CHARS, quote};
pub use resample::{OUTPUT_BLOCK, StreamResampler, resample_to};
pub use stream::{FeatureStream, LogMelStream};
