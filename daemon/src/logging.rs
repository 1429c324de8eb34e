//! `tracing` output on stderr: human-readable by default, JSON lines with `--log-format json`.
//!
//! Every line goes through [`escape_controls`]: a file name (or anything else that reaches a log
//! line) cannot start a fake line or send the terminal escape sequences.

use std::borrow::Cow;
use std::io::{IsTerminal, Write};

use tracing_subscriber::EnvFilter;

use crate::cli::LogFormatArg;
use crate::commands::{Cli, Command};

/// Install the global subscriber. Precedence: `RUST_LOG`, then the flags, then (for `serve`)
/// the config file's `[log]` section (`serve_config`), then `info` for `serve` and `live`,
/// `warn` / human for the rest.
pub fn init(cli: &Cli, serve_config: Option<&choreo_config::Config>) {
    let (mut level, mut format) = (None, None);
    if let Some(Command::Serve(_)) = &cli.command {
        // A config that fails to load is reported by `serve` itself, after logging is up.
        if let Some(config) = serve_config {
            level = Some(config.log_level.clone());
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
    let ansi = std::io::stderr().is_terminal();
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_ansi(ansi)
        .with_writer(move || EscapingStderr { keep_colours: ansi });
    match format {
        LogFormatArg::Human => builder.with_target(false).init(),
        LogFormatArg::Json => builder.json().flatten_event(true).init(),
    }
}

/// stderr for the log: each event arrives in one write (tracing-subscriber formats a whole line
/// first) and leaves with its control characters escaped, but for its final newline and, on a
/// terminal, the formatter's colour codes.
struct EscapingStderr {
    keep_colours: bool,
}

impl Write for EscapingStderr {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let text = String::from_utf8_lossy(buf);
        let (line, newline) = match text.strip_suffix('\n') {
            Some(line) => (line, "\n"),
            None => (text.as_ref(), ""),
        };
        let escaped = escape_controls(line, self.keep_colours);
        let mut err = std::io::stderr().lock();
        err.write_all(escaped.as_bytes())?;
        err.write_all(newline.as_bytes())?;
        Ok(buf.len())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        std::io::stderr().flush()
    }
}

/// `text` with every character that could end a line or steer a terminal escaped: C0 and C1
/// controls (newline, carriage return, escape …), Unicode line and paragraph separators and
/// bidirectional overrides. The escapes (`\n`, `\r`, `\t`, `\u001b`, `\u202e`) are also valid
/// inside a JSON string, so JSON log lines stay JSON. With `keep_colours`, colour codes
/// (`ESC [ digits ; ... m`, SGR) pass: they can only recolour text.
pub fn escape_controls(text: &str, keep_colours: bool) -> Cow<'_, str> {
    let unsafe_char = |c: char| {
        c.is_control()
            || matches!(c, '\u{2028}' | '\u{2029}' | '\u{200e}' | '\u{200f}')
            || ('\u{202a}'..='\u{202e}').contains(&c)
            || ('\u{2066}'..='\u{2069}').contains(&c)
    };
    if !text.chars().any(unsafe_char) {
        return Cow::Borrowed(text);
    }
    let mut out = String::with_capacity(text.len() + 16);
    let mut rest = text;
    while let Some(c) = rest.chars().next() {
        if keep_colours && c == '\x1b' {
            let sgr_len = rest[1..].strip_prefix('[').and_then(|params| {
                let end = params.find(|p: char| !(p.is_ascii_digit() || p == ';'))?;
                params[end..].starts_with('m').then_some(end + 3)
            });
            if let Some(len) = sgr_len {
                out.push_str(&rest[..len]);
                rest = &rest[len..];
                continue;
            }
        }
        match c {
            '\n' => out.push_str("\\n"),
            '\r' => out.push_str("\\r"),
            '\t' => out.push_str("\\t"),
            c if unsafe_char(c) => {
                let _ = std::fmt::Write::write_fmt(&mut out, format_args!("\\u{:04x}", c as u32));
            }
            c => out.push(c),
        }
        rest = &rest[c.len_utf8()..];
    }
    Cow::Owned(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn control_characters_are_escaped_and_colours_kept_only_when_asked() {
        let forged = "x\nchoreod: error: FORGED.wav\r\x1b[2K\x1b]0;title\x07\u{202e}vaw.exe\u{85}";
        let e = escape_controls(forged, false);
        assert_eq!(
            e,
            "x\\nchoreod: error: FORGED.wav\\r\\u001b[2K\\u001b]0;title\\u0007\\u202evaw.exe\\u0085"
        );
        assert!(!e.chars().any(char::is_control));
        // Valid JSON string escapes: a JSON log line stays JSON.
        let json: String = serde_json::from_str(&format!("\"{e}\"")).unwrap();
        assert_eq!(json, forged);
        // Colours pass on a terminal; anything else with ESC does not.
        assert_eq!(
            escape_controls("\x1b[1;31mERROR\x1b[0m a\x1b[2Kb", true),
            "\x1b[1;31mERROR\x1b[0m a\\u001b[2Kb"
        );
        assert_eq!(escape_controls("\x1b[1m", false), "\\u001b[1m");
        assert!(matches!(
            escape_controls("plain ünïcode name.wav", false),
            Cow::Borrowed(_)
        ));
    }
}
