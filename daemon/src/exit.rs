//! Exit codes and the one-line error report.
//!
//! | code | meaning |
//! |---|---|
//! | 0 | success |
//! | 1 | the work failed: bad or unsupported input, a failed job, a write error |
//! | 2 | usage error: unknown verb or flag, missing argument (from clap) |
//! | 3 | invalid configuration file |
//! | 4 | environment not ready: ONNX Runtime library missing or too old, model package unusable |
//! | 101 | internal error (a bug in choreod): please report it |

use std::process::ExitCode;

/// Work failed (bad input, failed job).
pub const FAILURE: u8 = 1;
/// Invalid configuration file.
pub const CONFIG: u8 = 3;
/// ONNX Runtime or a model package is not usable.
pub const ENVIRONMENT: u8 = 4;
/// A panic: a bug, never the user's fault.
const INTERNAL: u8 = 101;

/// Print `err` as one line on stderr and pick its exit code from what caused it.
pub fn report(err: &anyhow::Error) -> ExitCode {
    let line = format!("{err:#}").replace('\n', " ");
    eprintln!("choreod: error: {line}");
    ExitCode::from(code_for(err))
}

fn code_for(err: &anyhow::Error) -> u8 {
    for cause in err.chain() {
        if cause
            .downcast_ref::<choreo_config::ConfigErrors>()
            .is_some()
        {
            return CONFIG;
        }
        if let Some(e) = cause.downcast_ref::<choreo_models::Error>()
            && e.is_environment()
        {
            return ENVIRONMENT;
        }
    }
    FAILURE
}

/// A panic is a bug; say so in one line instead of printing a backtrace at the user.
pub fn install_panic_hook() {
    std::panic::set_hook(Box::new(|info| {
        let location = info
            .location()
            .map(|l| format!(" at {}:{}", l.file(), l.line()));
        let message = info
            .payload()
            .downcast_ref::<&str>()
            .map(|s| (*s).to_string())
            .or_else(|| info.payload().downcast_ref::<String>().cloned())
            .unwrap_or_default()
            .replace('\n', " ");
        eprintln!(
            "choreod: internal error (a bug, please report it): {message}{}",
            location.unwrap_or_default()
        );
        std::process::exit(i32::from(INTERNAL));
    }));
}
