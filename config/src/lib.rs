//! Typed configuration of the `choreod` daemon.
//!
//! The daemon's TOML file is read in two steps, as vector does:
//!
//! 1. [`RawConfig`] mirrors the file (serde, unknown keys rejected, every field optional so that a
//!    missing key gets its documented default or a clear "missing key" error);
//! 2. [`RawConfig::validate`] is pure (no filesystem access) and turns it into a [`Config`] whose
//!    values are checked, collecting *every* problem as a [`ConfigError`] that names the key.
//!
//! [`Config::preflight`] then checks the environment the config points at (directories exist and
//! are writable) before anything starts. [`load`] runs parse + validate for a path and resolves
//! relative paths against the config file's directory.
//!
//! `config/choreod.example.toml` in the repository documents every key; a test keeps it valid.

mod error;
mod raw;
mod validated;

pub use error::{ConfigError, ConfigErrors, Quote, Result};
pub use raw::RawConfig;
pub use validated::{
    Config, JobConfig, LimitsConfig, LiveConfig, LogFormat, MetricsConfig, PathsConfig,
    RuntimeConfig, Sampler, ServeConfig, StyleConfig, StyleMode, available_cpus, serve_threads,
};

use std::path::Path;

/// Read, parse and validate the config file at `path`.
///
/// Relative paths inside the file are resolved against the directory holding it, so a config
/// works the same whatever the daemon's working directory is.
pub fn load(path: &Path) -> Result<Config> {
    let text = std::fs::read_to_string(path).map_err(|source| {
        ConfigErrors::single(ConfigError::Read {
            path: path.to_path_buf(),
            source,
        })
    })?;
    let raw = RawConfig::parse(&text).map_err(|e| e.with_path(path))?;
    let base = path.parent().map(Path::to_path_buf).unwrap_or_default();
    raw.validate(&base).map_err(|e| e.with_path(path))
}
