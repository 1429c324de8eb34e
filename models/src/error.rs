use std::path::PathBuf;

/// Everything that can go wrong loading ONNX Runtime, a model package, or running a model.
///
/// Package errors name the package directory and the manifest key or component (and tensor), so
/// one line tells the user which file to fix.
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
    /// An ONNX Runtime call failed outside any package (e.g. creating the environment).
    #[error("ONNX Runtime: {0}")]
    Ort(String),
    /// The manifest is missing, unreadable, not TOML, or a key has a bad value.
    #[error("model package {}: choreod-model.toml: {key}: {reason}", package.display())]
    Manifest {
        package: PathBuf,
        key: String,
        reason: String,
    },
    /// A component's ONNX file is missing or unreadable.
    #[error("model package {}: component {component}: {}: {reason}", package.display(), path.display())]
    ComponentFile {
        package: PathBuf,
        component: String,
        path: PathBuf,
        reason: String,
    },
    /// A component's file does not have the sha256 the manifest declares.
    #[error(
        "model package {}: component {component}: {} has sha256 {got}, the manifest says {expected} \
         (file changed or corrupt; rebuild the package or update the manifest)",
        package.display(), path.display()
    )]
    Checksum {
        package: PathBuf,
        component: String,
        path: PathBuf,
        expected: String,
        got: String,
    },
    /// ONNX Runtime could not create a session from the file (corrupt ONNX, unsupported opset, ...).
    #[error("model package {}: component {component}: ONNX Runtime cannot load it: {reason}", package.display())]
    SessionLoad {
        package: PathBuf,
        component: String,
        reason: String,
    },
    /// A graph input/output differs from the manifest (name, dtype, rank or a fixed dimension).
    #[error("model package {}: component {component}: tensor {tensor}: {reason}", package.display())]
    Tensor {
        package: PathBuf,
        component: String,
        tensor: String,
        reason: String,
    },
    /// A network output contains NaN or infinity.
    #[error(
        "model package {}: component {component}: output {tensor} has {count} non-finite values \
         (NaN/Inf){}",
        package.display(), timestep.map_or(String::new(), |t| format!(" at timestep {t}"))
    )]
    NonFinite {
        package: PathBuf,
        component: String,
        tensor: String,
        count: usize,
        /// The diffusion timestep of the call, when the component is a denoiser.
        timestep: Option<i64>,
    },
    /// Running a component failed.
    #[error("model package {}: component {component}: run failed: {reason}", package.display())]
    Run {
        package: PathBuf,
        component: String,
        reason: String,
    },
    /// The diffusion schedule or sampler settings are inconsistent.
    #[error("diffusion schedule: {reason}")]
    Schedule { reason: String },
    /// An input to generation (mel, seed frames, options) has the wrong shape or value.
    #[error("{what}: {reason}")]
    Input { what: String, reason: String },
}

impl Error {
    /// True when the error is about this machine's setup (library, package), not about one input:
    /// the daemon refuses to start, `choreod models check` exits 4. A component that fails to
    /// run or emits NaN on validated inputs counts: the package is broken, not the song.
    pub fn is_environment(&self) -> bool {
        matches!(
            self,
            Self::OrtLibrary { .. }
                | Self::Manifest { .. }
                | Self::ComponentFile { .. }
                | Self::Checksum { .. }
                | Self::SessionLoad { .. }
                | Self::Tensor { .. }
                | Self::NonFinite { .. }
                | Self::Run { .. }
                | Self::Schedule { .. }
        )
    }
}

/// Result of the models crate.
pub type Result<T> = std::result::Result<T, Error>;
