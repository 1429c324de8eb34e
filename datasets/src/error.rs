//! The one error type of `choreo-datasets`. Every variant that comes from a file names it.

use std::path::{Path, PathBuf};

use crate::formats::MotionFormat;

/// Errors from reading, writing and converting motion.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// The operating system refused a read, write, rename or sync.
    // The cause is the error's source, printed after it by `{:#}` / anyhow chains.
    #[error("cannot access {}", path.display())]
    Io {
        /// The file or directory involved.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// The HDF5 library reported an error.
    #[error("{}: HDF5 error", path.display())]
    Hdf5 {
        /// The HDF5 file.
        path: PathBuf,
        /// The underlying error.
        source: hdf5::Error,
    },
    /// The file's content is not what its format requires (truncated, hostile, wrong type or shape).
    #[error("{}: {reason}", path.display())]
    Invalid {
        /// The offending file.
        path: PathBuf,
        /// What is wrong, with the values found.
        reason: String,
    },
    /// A recording (the live appender's temporary file) could not be put in place; it is kept.
    #[error("{}: not finished ({source}); what was recorded is kept in {}", path.display(), kept.display())]
    Unfinished {
        /// The final name it was to get.
        path: PathBuf,
        /// The temporary file, left as it was (readable up to its last flush).
        kept: PathBuf,
        /// Why finishing failed.
        source: Box<Error>,
    },
    /// An image encoder (GIF, PNG) failed.
    #[error("{}: encoding image: {reason}", path.display())]
    Encode {
        /// The output file.
        path: PathBuf,
        /// The encoder's message.
        reason: String,
    },
    /// A motion file written by a newer choreod.
    #[error("{}: format_version {found} is newer than the supported {supported}", path.display())]
    UnsupportedVersion {
        /// The motion file.
        path: PathBuf,
        /// Version in the file.
        found: i64,
        /// Highest version this build reads.
        supported: i64,
    },
    /// A file declares more values than the reader accepts (see `limits`), or more than the file
    /// can hold.
    #[error("{}: {what} exceeds the limit of {limit} values", path.display())]
    TooLarge {
        /// The file.
        path: PathBuf,
        /// The array and its declared shape.
        what: String,
        /// The element cap in force.
        limit: usize,
    },
    /// An HDF5 file uses a feature that would make the reader leave the file or read what was
    /// never written: external, soft or user-defined links, external storage, virtual datasets,
    /// declared but unwritten data.
    #[error("{}: {}: {feature} is not accepted", path.display(), choreo_dsp::quote(object))]
    Hdf5Refused {
        /// The HDF5 file.
        path: PathBuf,
        /// The link or dataset, e.g. `/motion/joints`.
        object: String,
        /// What was found.
        feature: String,
    },
    /// Motion values that are NaN or infinite.
    #[error("{}: {what} holds a non-finite value (NaN or infinity) at index {index}", path.display())]
    NonFinite {
        /// The file read or written.
        path: PathBuf,
        /// Which array.
        what: String,
        /// Flat index of the first bad value.
        index: usize,
    },
    /// A motion without frames.
    #[error("{}: the motion has no frames", path.display())]
    NoFrames {
        /// The file read or written.
        path: PathBuf,
    },
    /// The child process that reads an untrusted HDF5 file ([`crate::isolated`]) died, overran
    /// its limits or answered nonsense: whatever libhdf5 did, only the child suffered it.
    #[error("{}: the HDF5 reader {what} — the file is corrupt or hostile", path.display())]
    ReaderDied {
        /// The HDF5 file.
        path: PathBuf,
        /// What happened, e.g. `crashed (signal 11 SIGSEGV)`.
        what: String,
    },
    /// The child process that reads an HDF5 file exited with an error of its own (e.g. it
    /// could not set its limits): not the file's fault; its last line on stderr, relayed.
    #[error("{}: the HDF5 reader failed (exit status {status}): {message}", path.display())]
    ReaderFailed {
        /// The HDF5 file.
        path: PathBuf,
        /// The child's exit status.
        status: i32,
        /// Its last stderr line (bounded, control characters escaped).
        message: String,
    },
    /// The child process that read an HDF5 file refused it: its one-line message, as it said it
    /// (it names the file).
    #[error("{message}")]
    ReadInChild {
        /// The file.
        path: PathBuf,
        /// The reader's message.
        message: String,
    },
    /// An error of the audio crate (decoding music, writing `.npy`); it names its file.
    #[error(transparent)]
    Dsp(#[from] choreo_dsp::Error),
    /// In-memory motion data that cannot be processed (wrong shape, non-finite values, too short).
    #[error("invalid motion: {reason}")]
    Motion {
        /// What is wrong, with the values found.
        reason: String,
    },
    /// No reader for this file: its first bytes are no format's signature and its extension
    /// names none (see [`crate::formats`]).
    #[error("{}: unsupported input type '.{extension}' (pkl, npy, bvh, h5)", path.display())]
    UnsupportedFormat {
        /// The file.
        path: PathBuf,
        /// Its extension, lower case (empty without one).
        extension: String,
    },
    /// A reader refused the file's content: truncated, hostile, wrong type or shape for the
    /// format.
    #[error("{}: {reason}", path.display())]
    Corrupt {
        /// The file.
        path: PathBuf,
        /// The format it was read as.
        format: MotionFormat,
        /// What is wrong, with the values found.
        reason: String,
    },
    /// A skeleton that no rig places on t2m-22 (or SMPL-24) ([`crate::RIGS`]).
    #[error(
        "{}: cannot map the skeleton to {target}: no joint for {} (closest rig: {rig}, which names them {})",
        path.display(), missing.join(", "), wanted.join(", ")
    )]
    MissingJoints {
        /// The file.
        path: PathBuf,
        /// The skeleton asked for: `"t2m-22"` or `"SMPL-24"`.
        target: &'static str,
        /// The rig that came closest.
        rig: &'static str,
        /// The target's joints left without a source.
        missing: Vec<&'static str>,
        /// The closest rig's names for them.
        wanted: Vec<&'static str>,
    },
    /// A frame rate was given for a file that records its own (only a `.npy` takes one).
    #[error("{}: a given frame rate applies to .npy input only (a {format} records its own)", path.display())]
    FpsNotApplicable {
        /// The file.
        path: PathBuf,
        /// Its format.
        format: MotionFormat,
    },
    /// A frame rate given for a file lies outside [`crate::limits::FPS_RANGE`].
    #[error(
        "{}: {fps} fps is outside the accepted {}..={} fps",
        path.display(), crate::limits::FPS_RANGE.start(), crate::limits::FPS_RANGE.end()
    )]
    FpsOutOfRange {
        /// The file the rate was for.
        path: PathBuf,
        /// The rate given.
        fps: f32,
    },
    /// Resampling would make more values than the element cap ([`crate::limits`]); refused
    /// before anything is allocated.
    #[error(
        "{}resampling {frames} frames from {from_fps} fps to {to_fps} fps would make {resampled} frames of {values_per_frame} values, over the limit of {limit} values",
        path.as_deref().map(|p| format!("{}: ", p.display())).unwrap_or_default()
    )]
    ResampleTooLarge {
        /// The file, once known ([`Error::with_path`]).
        path: Option<PathBuf>,
        /// Frames before.
        frames: usize,
        /// Rate before.
        from_fps: f32,
        /// Rate asked for.
        to_fps: f32,
        /// Frames it would make.
        resampled: u64,
        /// Values per frame.
        values_per_frame: usize,
        /// The element cap in force.
        limit: usize,
    },
    /// A motion input with fewer or more frames than the model takes.
    #[error("{}: {frames} frames at {fps} fps ({:.2} s): {bound}", path.display(), *frames as f32 / fps)]
    FrameCount {
        /// The file.
        path: PathBuf,
        /// Frames it has (at `fps`).
        frames: usize,
        /// The model's frame rate.
        fps: f32,
        /// The bound it breaks.
        bound: FrameBound,
    },
    /// An export option the output format has no use for, or cannot apply to this motion.
    #[error("{}: {option}", path.display())]
    Export {
        /// The output file.
        path: PathBuf,
        /// What cannot be done.
        option: ExportRefusal,
    },
    /// The worker threads of a parallel job could not be started.
    #[error("cannot start {threads} worker threads")]
    ThreadPool {
        /// Threads asked for.
        threads: usize,
        /// The thread pool's error.
        source: rayon::ThreadPoolBuildError,
    },
}

/// The frame bound a motion input breaks ([`Error::FrameCount`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum FrameBound {
    /// The model needs at least this many frames.
    AtLeast {
        /// Fewest frames.
        frames: usize,
        /// At the model's rate.
        fps: f32,
    },
    /// At most this many are accepted.
    AtMost {
        /// Most frames.
        frames: usize,
        /// At the model's rate.
        fps: f32,
    },
}

impl std::fmt::Display for FrameBound {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match *self {
            FrameBound::AtLeast { frames, fps } => write!(
                f,
                "the model needs at least {frames} ({:.2} s)",
                frames as f32 / fps
            ),
            FrameBound::AtMost { frames, fps } => write!(
                f,
                "at most {frames} ({:.0} s) are accepted",
                frames as f32 / fps
            ),
        }
    }
}

/// What an export cannot do ([`Error::Export`]).
#[derive(Debug, Clone, PartialEq, Eq)]
#[non_exhaustive]
pub enum ExportRefusal {
    /// Mixamo bone names for a skeleton other than SMPL-24 / t2m-22.
    MixamoNames {
        /// The motion's skeleton.
        skeleton: String,
    },
    /// Bone names asked of an output that has none (not `.bvh`, `.glb`, `.gltf`).
    RigWithoutBones,
    /// No mesh asked of an output that has none (not `.glb`, `.gltf`).
    NoMeshWithoutMesh,
}

impl std::fmt::Display for ExportRefusal {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ExportRefusal::MixamoNames { skeleton } => write!(
                f,
                "Mixamo bone names map the SMPL-24 and t2m-22 skeletons; this motion's skeleton \
                 is '{skeleton}' (export it with its own names)"
            ),
            ExportRefusal::RigWithoutBones => {
                f.write_str("bone names apply to .bvh, .glb and .gltf outputs")
            }
            ExportRefusal::NoMeshWithoutMesh => {
                f.write_str("a motion without a mesh applies to .glb and .gltf outputs")
            }
        }
    }
}

/// Result with [`Error`].
pub type Result<T> = std::result::Result<T, Error>;

impl Error {
    /// An [`Error::Invalid`] for `path`.
    pub(crate) fn invalid(path: impl Into<PathBuf>, reason: impl Into<String>) -> Self {
        Error::Invalid {
            path: path.into(),
            reason: reason.into(),
        }
    }

    /// An [`Error::Motion`].
    pub(crate) fn motion(reason: impl Into<String>) -> Self {
        Error::Motion {
            reason: reason.into(),
        }
    }

    /// Attach a file name to a path-less error ([`Error::Motion`], [`Error::ResampleTooLarge`]):
    /// the crate boundary adds the path.
    pub fn with_path(self, path: &Path) -> Self {
        match self {
            Error::Motion { reason } => Error::Invalid {
                path: path.to_path_buf(),
                reason,
            },
            Error::ResampleTooLarge { path: None, .. } => {
                let mut e = self;
                if let Error::ResampleTooLarge { path: slot, .. } = &mut e {
                    *slot = Some(path.to_path_buf());
                }
                e
            }
            other => other,
        }
    }

    /// A reader's [`Error::Invalid`] as [`Error::Corrupt`] in `format` (the probe's boundary).
    pub(crate) fn in_format(self, format: MotionFormat) -> Self {
        match self {
            Error::Invalid { path, reason } => Error::Corrupt {
                path,
                format,
                reason,
            },
            other => other,
        }
    }
}

/// Shorthand for an [`Error::Io`] mapper.
pub(crate) fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> Error + '_ {
    move |source| Error::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Shorthand for an [`Error::Hdf5`] mapper.
pub(crate) fn h5_err(path: &Path) -> impl FnOnce(hdf5::Error) -> Error + '_ {
    move |source| Error::Hdf5 {
        path: path.to_path_buf(),
        source,
    }
}
