//! The one error type of `choreo-dsp`.

use std::path::PathBuf;

/// Everything that can go wrong in the audio front end. Variants carry the file and the values
/// involved so that one line tells the user what to fix.
#[non_exhaustive]
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The file could not be opened or read.
    #[error("{}: {io}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The OS error (in the message, not chained, so it is printed once).
        io: std::io::Error,
    },
    /// The file is empty (0 bytes).
    #[error("{}: the file is empty", path.display())]
    EmptyFile {
        /// The file.
        path: PathBuf,
    },
    /// The file is larger than `DecodeOptions::max_file_bytes`.
    #[error("{}: file is {bytes} bytes, more than the limit of {limit} bytes", path.display())]
    FileTooLarge {
        /// The file.
        path: PathBuf,
        /// Its size.
        bytes: u64,
        /// The configured limit.
        limit: u64,
    },
    /// No demuxer recognised the file.
    #[error("{}: not a recognised audio file ({reason})", path.display())]
    UnrecognisedFormat {
        /// The file.
        path: PathBuf,
        /// What symphonia said.
        reason: String,
    },
    /// The container ends before its headers are complete (a truncated or damaged file).
    #[error("{}: truncated or damaged file (unexpected end of file while opening the container)", path.display())]
    Truncated {
        /// The file.
        path: PathBuf,
    },
    /// The container holds no audio track.
    #[error("{}: no audio track", path.display())]
    NoAudioTrack {
        /// The file.
        path: PathBuf,
    },
    /// Opus: symphonia has no Opus decoder.
    #[error(
        "{}: Opus is not supported by symphonia; convert it first, e.g. `ffmpeg -i {} {}`",
        path.display(),
        path.display(),
        path.with_extension("flac").display()
    )]
    OpusUnsupported {
        /// The file.
        path: PathBuf,
    },
    /// A codec symphonia cannot decode.
    #[error("{}: unsupported codec ({reason})", path.display())]
    UnsupportedCodec {
        /// The file.
        path: PathBuf,
        /// What symphonia said.
        reason: String,
    },
    /// The stream is malformed beyond the bad-packet budget, or the demuxer failed.
    #[error("{}: corrupt audio stream: {reason}", path.display())]
    Corrupt {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        reason: String,
    },
    /// More undecodable packets than `DecodeOptions::max_bad_packets`.
    #[error("{}: {count} undecodable packets, more than the limit of {limit} (last: {last})", path.display())]
    TooManyBadPackets {
        /// The file.
        path: PathBuf,
        /// Bad packets seen.
        count: usize,
        /// The configured limit.
        limit: usize,
        /// The last decoder error.
        last: String,
    },
    /// The decoded audio is longer than `DecodeOptions::max_duration_s`.
    #[error("{}: audio is longer than the limit of {limit_s} s", path.display())]
    TooLong {
        /// The file.
        path: PathBuf,
        /// The configured limit in seconds.
        limit_s: f64,
    },
    /// The file decodes to zero samples.
    #[error("{}: the file contains no audio samples", path.display())]
    NoSamples {
        /// The file.
        path: PathBuf,
    },
    /// A sample was NaN or infinite (e.g. a corrupt float WAV).
    #[error("{}: sample {index} is not finite ({value}); the file is corrupt", path.display())]
    NonFiniteSample {
        /// The file.
        path: PathBuf,
        /// Index of the first bad sample (mono, after mixing).
        index: u64,
        /// The value.
        value: f32,
    },
    /// The sample rate of the stream changed mid-stream or between `accept_waveform` calls.
    #[error("sample rate changed from {expected} Hz to {got} Hz mid-stream")]
    SampleRateChanged {
        /// The first rate.
        expected: u32,
        /// The new rate.
        got: u32,
    },
    /// A sample rate of zero or beyond what we accept.
    #[error("unsupported sample rate {rate} Hz (accepted: 1..={max} Hz)")]
    BadSampleRate {
        /// The rate.
        rate: u32,
        /// The largest accepted rate.
        max: u32,
    },
    /// Samples were given after `input_finished`.
    #[error("samples given after input_finished")]
    InputAfterFinish,
    /// Invalid analysis options.
    #[error("invalid option {name} = {value}: {reason}")]
    BadOption {
        /// The option name.
        name: &'static str,
        /// Its value.
        value: String,
        /// Why it is rejected.
        reason: &'static str,
    },
    /// The resampler could not be built or failed.
    #[error("resampling {from} Hz -> {to} Hz: {reason}")]
    Resample {
        /// Input rate.
        from: u32,
        /// Output rate.
        to: u32,
        /// rubato's message.
        reason: String,
    },
    /// `frames(start, n)` asked for frames that are not (or no longer) held.
    #[error("frames {start}..{end} requested, but only frames {held_from}..{ready} are held")]
    FramesOutOfRange {
        /// First frame asked for.
        start: usize,
        /// One past the last frame asked for.
        end: usize,
        /// First frame still held (earlier ones were discarded).
        held_from: usize,
        /// Frames ready so far.
        ready: usize,
    },
    /// The consumer of a decode stopped early (internal; never shown for a finished job).
    #[error("{}: decoding cancelled by its consumer", path.display())]
    Cancelled {
        /// The file.
        path: PathBuf,
    },
    /// Writing an `.npy` file failed.
    #[error("writing {}: {io}", path.display())]
    Write {
        /// The file.
        path: PathBuf,
        /// The OS error (in the message, not chained, so it is printed once).
        io: std::io::Error,
    },
    /// Shape and data length disagree (npy writer).
    #[error("npy shape {shape:?} holds {expected} values but {got} were given")]
    ShapeMismatch {
        /// The shape.
        shape: Vec<usize>,
        /// Product of the shape.
        expected: usize,
        /// Values given.
        got: usize,
    },
    /// The audio is shorter than an analysis needs.
    #[error("audio is {seconds:.3} s long; {what} need at least {min_s} s")]
    TooShort {
        /// Its duration.
        seconds: f64,
        /// The minimum.
        min_s: f64,
        /// What needs it.
        what: &'static str,
    },
    /// A worker thread of an analysis panicked (a bug; the input is not to blame).
    #[error("internal error: the {stage} worker panicked")]
    WorkerPanicked {
        /// The stage it ran.
        stage: &'static str,
    },
}

/// `Result` with [`Error`].
pub type Result<T> = std::result::Result<T, Error>;
