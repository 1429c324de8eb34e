//! The runtime layer: the ONNX Runtime library (where it is, loading it once, its version) and
//! [`component::Component`], one checked session per ONNX file.

pub(crate) mod component;
pub(crate) mod contract;
pub(crate) mod deadline;
mod hoist;
pub(crate) mod onnx_info;
mod proto;

use std::path::{Path, PathBuf};

use crate::error::{Error, Result};

/// ONNX Runtime, loaded and ready to create sessions.
#[derive(Debug)]
pub struct OrtRuntime {
    library: PathBuf,
    version: String,
    environment: ort::environment::Environment,
}

impl OrtRuntime {
    /// Load ONNX Runtime from `library` (see [`locate_library`]). Must run before any other ONNX
    /// Runtime use in the process; a second call with the same library is cheap.
    ///
    /// Errors ([`Error::OrtLibrary`]) are not recoverable: nothing that needs a model can run.
    pub fn load(library: &Path) -> Result<Self> {
        let fail = |reason: String| Error::OrtLibrary {
            path: library.to_path_buf(),
            reason,
        };
        if !library.exists() {
            return Err(fail("no such file".into()));
        }
        let builder = ort::init_from(library).map_err(|e| fail(e.to_string()))?;
        // Microsoft's builds (the PyPI wheel among them) send usage telemetry by default: off,
        // choreod talks to no one (ONNX Runtime's DisableTelemetryEvents). The uploader itself
        // starts when the library loads unless ORT_DISABLE_TELEMETRY=1 (set by choreod's main).
        let environment = builder
            .with_name("choreod")
            .with_logger(std::sync::Arc::new(ort_log))
            .with_telemetry(false)
            .build()
            .map_err(|e| Error::Ort(e.to_string()))?;
        // ONNX Runtime formats every message at or above this level for the logger: its
        // verbose and info chatter (hundreds of lines per session) is not worth that.
        environment.set_log_level(ort::logging::LogLevel::Warning);
        let version = library_version(library).unwrap_or_else(|| "unknown".to_string());
        Ok(Self {
            library: library.to_path_buf(),
            version,
            environment,
        })
    }

    /// The library file that was loaded.
    pub fn library(&self) -> &Path {
        &self.library
    }

    /// The environment sessions are created in.
    pub fn environment(&self) -> &ort::environment::Environment {
        &self.environment
    }

    /// The ONNX Runtime version, e.g. `1.31.1`.
    pub fn version(&self) -> &str {
        &self.version
    }
}

/// ONNX Runtime's own log messages, as `tracing` events of target `onnxruntime` at debug level,
/// one line each. Its errors also come back as the failing call's error, which choreod reports
/// in its one error line; printed by ONNX Runtime itself they were coloured duplicates on
/// stderr before that line. `--log-level onnxruntime=debug` shows them.
fn ort_log(
    level: ort::logging::LogLevel,
    category: &str,
    _id: &str,
    location: &str,
    message: &str,
) {
    let message = message.replace(['\n', '\r'], " ");
    tracing::debug!(target: "onnxruntime", ?level, category, location, "{message}");
}

/// Find the ONNX Runtime library: `configured` (a flag or `runtime.ort_library`) first, then the
/// `ORT_DYLIB_PATH` environment variable, then `.venv/libonnxruntime.so` in a directory above the
/// running executable (the checkout that `scripts/setup` prepared).
pub fn locate_library(configured: Option<&Path>) -> PathBuf {
    if let Some(p) = configured {
        return p.to_path_buf();
    }
    if let Some(p) = std::env::var_os("ORT_DYLIB_PATH").filter(|p| !p.is_empty()) {
        return PathBuf::from(p);
    }
    let exe = std::env::current_exe().ok();
    exe.iter()
        .flat_map(|e| e.ancestors().skip(1))
        .map(|dir| dir.join(".venv").join("libonnxruntime.so"))
        .find(|candidate| candidate.exists())
        .unwrap_or_else(|| PathBuf::from("libonnxruntime.so"))
}

/// The library's own version string (`OrtGetApiBase()->GetVersionString()`, e.g. `1.31.1`).
///
/// `ort` checks this version when loading but does not expose it, and the build-info string of
/// the PyPI wheel says `git-branch=HEAD`, so it is read here through the C API.
#[allow(unsafe_code)] // FFI: the one call that gives ONNX Runtime's version.
fn library_version(library: &Path) -> Option<String> {
    type GetApiBase = unsafe extern "C" fn() -> *const ort::sys::OrtApiBase;
    // SAFETY: the library was loaded successfully by `ort::init_from` just before, so opening it
    // again only bumps its reference count and runs no initialisers; `OrtGetApiBase` has this
    // signature in every ONNX Runtime release and returns a pointer to a static struct whose
    // `GetVersionString` returns a static NUL-terminated string.
    unsafe {
        let lib = libloading::Library::new(library).ok()?;
        let get_api_base: libloading::Symbol<GetApiBase> = lib.get(b"OrtGetApiBase").ok()?;
        let base = get_api_base();
        if base.is_null() {
            return None;
        }
        let text = ((*base).GetVersionString)();
        if text.is_null() {
            return None;
        }
        Some(
            std::ffi::CStr::from_ptr(text)
                .to_string_lossy()
                .into_owned(),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_missing_library_is_one_actionable_error() {
        let e = OrtRuntime::load(Path::new("/nonexistent/libonnxruntime.so")).unwrap_err();
        let msg = e.to_string();
        assert!(msg.contains("/nonexistent/libonnxruntime.so") && msg.contains("scripts/setup"));
    }
}
