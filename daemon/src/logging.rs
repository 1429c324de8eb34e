//! `tracing` output on stderr: human-readable by default, JSON lines with `--log-format json`.

use tracing_subscriber::EnvFilter;

use crate::cli::{GlobalArgs, LogFormatArg};

/// Install the global subscriber. `RUST_LOG`, when set, overrides `--log-level`.
pub fn init(global: &GlobalArgs) {
    let filter = EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| EnvFilter::new(global.log_level.as_deref().unwrap_or("warn")));
    let builder = tracing_subscriber::fmt().with_env_filter(filter).with_writer(std::io::stderr);
    match global.log_format {
        LogFormatArg::Human => builder.with_target(false).init(),
        LogFormatArg::Json => builder.json().flatten_event(true).init(),
    }
}
