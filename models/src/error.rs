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
    /// A run of a component was stopped at its time limit (see `Deadline`): the graph runs
    /// too long for the limit, or for ever (a hostile `Loop`).
    #[error(
        "model package {}: component {component}: stopped at the time limit of {} s",
        package.display(), limit.as_secs_f64()
    )]
    TimeLimit {
        package: PathBuf,
        component: String,
        limit: std::time::Duration,
    },
    /// The diffusion schedule or sampler settings are inconsistent.
    #[error("diffusion schedule: {reason}")]
    Schedule { reason: String },
    /// An input to generation (mel, seed frames, options) has the wrong shape or value.
    #[error("{what}: {reason}")]
    Input { what: String, reason: String },
    /// The song could not be decoded or turned into features (names the file).
    #[error(transparent)]
    Audio(#[from] choreo_dsp::Error),
    /// The song is shorter than the shortest the package makes a dance of.
    #[error(
        "{}: {seconds:.3} s of audio, shorter than the minimum of {:.3} s ({minimum}): a \
         truncated file or too short a clip",
        path.display(), minimum.seconds()
    )]
    SongTooShort {
        path: PathBuf,
        /// Seconds of audio decoded.
        seconds: f64,
        /// The minimum that applied, and where it comes from.
        minimum: MinimumLength,
    },
    /// The song ends mid-stream and the options refuse a dance of part of it.
    #[error(
        "{}: the file ends mid-stream after {seconds:.3} s of audio (truncated?); refused by \
         limits.fail_truncated_audio",
        path.display()
    )]
    SongTruncated {
        path: PathBuf,
        /// Seconds of audio before the damage.
        seconds: f64,
    },
    /// A style embedding file is not one vector.
    #[error(
        "{}: style embedding of shape {shape:?}: expected one vector, (S) or (1, S)",
        path.display()
    )]
    StyleEmbedding { path: PathBuf, shape: Vec<usize> },
    /// The generated joints could not be fitted to one rigid skeleton.
    #[error("generated joints")]
    GeneratedJoints { source: choreo_datasets::Error },
    /// Reading or converting a file (a song for its sha256, a motion) failed; the source names
    /// the file.
    #[error(transparent)]
    Datasets(#[from] choreo_datasets::Error),
    /// Reading the style reference motion failed (the source names the file): apart from
    /// [`Error::Datasets`] so that a frame rate refused for it is told apart from the content's.
    #[error(transparent)]
    StyleFile(choreo_datasets::Error),
    /// Encoding the style reference failed past reading it: the package's style encoder, the
    /// style's shape, or the file changing while it was read (the source says which).
    #[error("encoding the style {}", style.display())]
    StyleEncoding { style: PathBuf, source: Box<Error> },
    /// Stylizing `content` with `style` failed past reading them: the package, the inputs'
    /// shapes or the transfer (the source says which).
    #[error("stylizing {} with {}", content.display(), style.display())]
    Stylize {
        content: PathBuf,
        style: PathBuf,
        source: Box<Error>,
    },
}

/// The shortest song a dance is made of, and where that length comes from.
#[derive(Debug, Clone, PartialEq)]
#[non_exhaustive]
pub enum MinimumLength {
    /// The caller's minimum (a config key or flag the binary names).
    Configured { seconds: f64 },
    /// One motion window of the model: every window it makes is this long.
    MotionWindow {
        model: String,
        frames: usize,
        fps: f64,
    },
    /// One analysis window of the model's features (`n_fft` samples): shorter, every mel frame
    /// is padding.
    AnalysisWindow { n_fft: usize, sample_rate: u32 },
}

impl MinimumLength {
    /// The minimum in seconds.
    pub fn seconds(&self) -> f64 {
        match self {
            Self::Configured { seconds } => *seconds,
            Self::MotionWindow { frames, fps, .. } => *frames as f64 / fps,
            Self::AnalysisWindow { n_fft, sample_rate } => *n_fft as f64 / f64::from(*sample_rate),
        }
    }
}

impl std::fmt::Display for MinimumLength {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Configured { .. } => f.write_str("the configured minimum"),
            Self::MotionWindow { model, frames, fps } => write!(
                f,
                "one motion window of model {model}: {frames} frames at {fps} fps"
            ),
            Self::AnalysisWindow { n_fft, sample_rate } => {
                write!(f, "one {n_fft}-sample analysis window at {sample_rate} Hz")
            }
        }
    }
}

impl Error {
    /// True when the error is about this machine's setup (library, package), not about one input:
    /// the daemon refuses to start, `choreod models check` exits 4. A component that fails to
    /// run or emits NaN on validated inputs counts: the package is broken, not the song.
    pub fn is_environment(&self) -> bool {
        if let Self::Stylize { source, .. } | Self::StyleEncoding { source, .. } = self {
            return source.is_environment();
        }
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
