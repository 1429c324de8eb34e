//! The one error type of `choreo-datasets`. Every variant that comes from a file names it.

use std::path::PathBuf;

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
    #[error("{}: {what} exceeds the limit of {limit} values (--max-elements)", path.display())]
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

    /// Attach a file name to a path-less [`Error::Motion`] (the crate boundary adds the path).
    pub fn with_path(self, path: &std::path::Path) -> Self {
        match self {
            Error::Motion { reason } => Error::Invalid {
                path: path.to_path_buf(),
                reason,
            },
            other => other,
        }
    }
}

/// Shorthand for an [`Error::Io`] mapper.
pub(crate) fn io_err(path: &std::path::Path) -> impl FnOnce(std::io::Error) -> Error + '_ {
    move |source| Error::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// Shorthand for an [`Error::Hdf5`] mapper.
pub(crate) fn h5_err(path: &std::path::Path) -> impl FnOnce(hdf5::Error) -> Error + '_ {
    move |source| Error::Hdf5 {
        path: path.to_path_buf(),
        source,
    }
}
