use std::path::PathBuf;

/// Everything that can go wrong loading ONNX Runtime, a model package, or running a model.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// The ONNX Runtime shared library could not be found, opened, or is too old.
    #[error(
        "cannot load ONNX Runtime from {}: {reason}. Fix: run scripts/setup (it installs \
         onnxruntime 1.31.1 into .venv), or set ORT_DYLIB_PATH to libonnxruntime.so 1.31 or newer",
        path.display()
    )]
    OrtLibrary { path: PathBuf, reason: String },
    /// An ONNX Runtime call failed.
    #[error("ONNX Runtime: {0}")]
    Ort(String),
}

impl Error {
    /// True when the error is about this machine's setup (library, package), not about one input.
    pub fn is_environment(&self) -> bool {
        matches!(self, Self::OrtLibrary { .. })
    }
}

/// Result of the models crate.
pub type Result<T> = std::result::Result<T, Error>;
