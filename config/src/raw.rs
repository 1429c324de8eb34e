//! The configuration file as written: every key optional, unknown keys rejected.

use serde::Deserialize;

use crate::error::{ConfigError, ConfigErrors, Result};

/// The TOML file as parsed, before validation. See `config/choreod.example.toml`.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawConfig {
    #[serde(default)]
    pub paths: RawPaths,
    #[serde(default)]
    pub serve: RawServe,
    #[serde(default)]
    pub runtime: RawRuntime,
    #[serde(default)]
    pub limits: RawLimits,
    #[serde(default)]
    pub metrics: RawMetrics,
    #[serde(default)]
    pub log: RawLog,
    #[serde(default)]
    pub job: RawJob,
    #[serde(default)]
    pub live: RawLive,
    #[serde(default)]
    pub style: RawStyle,
}

/// `[paths]`
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawPaths {
    pub inbox: Option<String>,
    pub output: Option<String>,
    pub state: Option<String>,
}

/// `[serve]` — integers are read signed so that a negative value gets a message naming the key
/// rather than a type error.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawServe {
    pub workers: Option<i64>,
    pub queue_capacity: Option<i64>,
    pub settle_ms: Option<i64>,
    pub max_attempts: Option<i64>,
    pub shutdown_timeout_s: Option<f64>,
}

/// `[runtime]`
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawRuntime {
    pub ort_library: Option<String>,
    pub ort_intra_threads: Option<i64>,
    pub ort_inter_threads: Option<i64>,
    pub default_model: Option<String>,
}

/// `[limits]`
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawLimits {
    pub max_file_mb: Option<f64>,
    pub max_audio_seconds: Option<f64>,
    pub min_audio_seconds: Option<f64>,
    pub min_free_disk_mb: Option<f64>,
    pub fail_truncated_audio: Option<bool>,
}

/// `[metrics]`
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawMetrics {
    pub enabled: Option<bool>,
    pub bind: Option<String>,
}

/// `[job]` — how each song is danced.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawJob {
    pub seed: Option<i64>,
    pub steps: Option<i64>,
    pub guidance: Option<f64>,
    pub chunk_windows: Option<i64>,
    pub time_limit_s: Option<f64>,
}

/// `[live]` — a live audio source beside the watch folder (the `choreod live` flags).
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawLive {
    pub enabled: Option<bool>,
    pub device: Option<String>,
    pub model: Option<String>,
    pub hop_s: Option<f64>,
    pub steps: Option<i64>,
    pub min_steps: Option<i64>,
    pub latency_budget_s: Option<f64>,
    pub sampler: Option<String>,
    pub seed: Option<i64>,
    pub intra_threads: Option<i64>,
    pub output: Option<String>,
    pub viewer: Option<String>,
    pub osc: Option<String>,
    pub nice: Option<i64>,
}

/// `[style]` — a second watch folder whose motion files are stylized (the `choreod stylize`
/// options).
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawStyle {
    pub enabled: Option<bool>,
    pub inbox: Option<String>,
    pub style: Option<String>,
    pub model: Option<String>,
    pub mode: Option<String>,
    pub guidance: Option<f64>,
    pub steps: Option<i64>,
}

/// `[log]`
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RawLog {
    pub format: Option<String>,
    pub level: Option<String>,
}

impl RawConfig {
    /// Parse TOML text. Errors are one line: `line N, key `table.key`: what is wrong`.
    pub fn parse(text: &str) -> Result<Self> {
        toml::from_str(text).map_err(|e| ConfigErrors::single(parse_error(text, &e)))
    }
}

/// toml's multi-line, caret-drawing error as its parts: the line, the key on it, the message
/// and the text it points at.
fn parse_error(text: &str, e: &toml::de::Error) -> ConfigError {
    let message = e.message().trim().replace('\n', " ");
    let Some(span) = e.span() else {
        return ConfigError::Parse {
            line: None,
            key: None,
            message,
            found: None,
        };
    };
    let start = span.start.min(text.len());
    let found = text
        .get(start..span.end.min(text.len()))
        .map(str::to_string);
    let line_no = text[..start].matches('\n').count() + 1;
    let line = text.lines().nth(line_no - 1).unwrap_or("").trim();
    // The nearest `[table]` header above the error gives the key's table.
    let table = text[..start]
        .lines()
        .rev()
        .map(str::trim)
        .find(|l| l.starts_with('[') && l.ends_with(']'))
        .map(|l| l.trim_matches(|c| c == '[' || c == ']').trim().to_string());
    let key = line
        .split('=')
        .next()
        .map(str::trim)
        .filter(|k| !k.is_empty() && !k.starts_with('['));
    ConfigError::Parse {
        line: Some(line_no),
        key: key.map(|k| match table {
            Some(t) => format!("{t}.{k}"),
            None => k.to_string(),
        }),
        message,
        found,
    }
}
