//! `tracing` output on stderr: human-readable by default, JSON lines with `--log-format json`.

use std::io::IsTerminal;

use tracing_subscriber::EnvFilter;

use crate::cli::{Cli, Command, LogFormatArg};

/// Install the global subscriber. Precedence: `RUST_LOG`, then the flags, then (for `serve`)
/// the config file's `[log]` section, then `info` for `serve` and `live`, `warn` / human for the
/// rest.
pub fn init(cli: &Cli) {
    let (mut level, mut format) = (None, None);
    if let Some(Command::Serve(args)) = &cli.command {
        // A config that fails to load is reported by `serve` itself, after logging is up.
        let path = crate::commands::serve::config_path(args);
        if let Ok(config) = choreo_config::load(&path) {
            level = Some(config.log_level);
            format = Some(match config.log_format {
                choreo_config::LogFormat::Json => LogFormatArg::Json,
                choreo_config::LogFormat::Human => LogFormatArg::Human,
            });
        }
        level = level.or_else(|| Some("info".to_string()));
    }
    // A live session runs in the foreground for as long as the show: its periodic latency line
    // and what happens to the input are info.
    if let Some(Command::Live(_)) = &cli.command {
        level = Some("info".to_string());
    }
    let mut level = cli
        .global
        .log_level
        .clone()
        .or(level)
        .unwrap_or_else(|| "warn".into());
    // symphonia logs a failed probe as ERROR before returning the error we report in one line
    // ourselves; keep it quiet unless a filter asks for it by name.
    if !level.contains("symphonia") {
        level.push_str(",symphonia=off");
    }
    let format = cli
        .global
        .log_format
        .or(format)
        .unwrap_or(LogFormatArg::Human);
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new(level));
    // Colour codes only on a terminal: in a file or the journal they are noise.
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_ansi(std::io::stderr().is_terminal())
        .with_writer(std::io::stderr);
    match format {
        LogFormatArg::Human => builder.with_target(false).init(),
        LogFormatArg::Json => builder.json().flatten_event(true).init(),
    }
}
