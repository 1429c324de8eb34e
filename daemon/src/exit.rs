//! Exit codes and the one-line error report.
//!
//! | code | meaning |
//! |---|---|
//! | 0 | success |
//! | 1 | the work failed: bad or unsupported input, a failed job, a write error |
//! | 2 | usage error: unknown verb or flag, missing argument, a value the flag does not accept (printed by clap, several lines); an output that is one of the inputs ([`Usage`], one line) |
//! | 3 | invalid configuration: the file, or the folders it names (missing, overlapping, inbox and state on different filesystems, no model package) |
//! | 4 | environment not ready: ONNX Runtime library missing or too old, model package unusable, metrics port taken, state or output folder locked by another daemon |
//! | 101 | internal error (a bug in choreod): please report it |
//!
//! The libraries name no flags; a motion error the user can change with a flag of the verb
//! they ran gets that flag appended to its line ([`flag_hint`]), e.g. an array over the
//! element cap ends in `(--max-elements)`.

use std::cell::{Cell, RefCell};
use std::process::ExitCode;

/// Work failed (bad input, failed job).
pub const FAILURE: u8 = 1;
/// The command line asks for something impossible that the parser cannot see.
const USAGE: u8 = 2;
/// Invalid configuration file.
pub const CONFIG: u8 = 3;
/// ONNX Runtime or a model package is not usable.
pub const ENVIRONMENT: u8 = 4;
/// A panic: a bug, never the user's fault.
const INTERNAL: u8 = 101;

/// Print `err` as one line on stderr and pick its exit code from what caused it.
pub fn report(err: &anyhow::Error) -> ExitCode {
    let mut line = match err.downcast_ref::<choreo_config::ConfigErrors>() {
        // The config crate hands its input text over raw; it is cut here.
        Some(config) if err.chain().count() == 1 => config.describe(&choreo_dsp::quote_inside),
        _ => format!("{err:#}"),
    }
    .replace('\n', " ");
    if let Some((flag, hint)) = flag_hint(err)
        && verb_has_flag(std::env::args_os(), flag)
    {
        line.push_str(&format!(" ({hint})"));
    }
    // The line names files: their names may hold anything.
    let line = crate::logging::escape_controls(&line, false);
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
        if cause.downcast_ref::<NotReady>().is_some() {
            return ENVIRONMENT;
        }
        if cause.downcast_ref::<Usage>().is_some() {
            return USAGE;
        }
    }
    FAILURE
}

/// The flag (long name) that changes the outcome of a motion error or a model's time limit,
/// and the hint to append.
fn flag_hint(err: &anyhow::Error) -> Option<(&'static str, &'static str)> {
    use choreo_datasets::{Error, ExportRefusal};
    use choreo_models::Error as Models;
    if stopped_at_time_limit(err) {
        return Some(("time-limit", "--time-limit"));
    }
    // A datasets error is in the chain itself, or inside a models error that shows it as its
    // own (transparent: not a separate link of the chain).
    let (e, of_style) = err.chain().find_map(|c| match c.downcast_ref::<Models>() {
        Some(Models::Datasets(e)) => Some((e, false)),
        Some(Models::StyleFile(e)) => Some((e, true)),
        _ => c.downcast_ref::<Error>().map(|e| (e, false)),
    })?;
    Some(match e {
        Error::FpsNotApplicable { .. } | Error::FpsOutOfRange { .. } if of_style => {
            ("style-fps", "--style-fps")
        }
        Error::TooLarge { .. } | Error::ResampleTooLarge { .. } => {
            ("max-elements", "--max-elements")
        }
        Error::FpsNotApplicable { .. } | Error::FpsOutOfRange { .. } => ("fps", "--fps"),
        Error::Export { option, .. } => match option {
            ExportRefusal::MixamoNames { .. } => {
                ("rig", "--rig mixamo; export it with --rig native")
            }
            ExportRefusal::RigWithoutBones => ("rig", "--rig"),
            ExportRefusal::NoMeshWithoutMesh => ("no-mesh", "--no-mesh"),
            _ => return None,
        },
        Error::ThreadPool { .. } => ("jobs", "--jobs"),
        _ => return None,
    })
}

/// Whether the work failed because a model was stopped at its time limit.
pub fn stopped_at_time_limit(err: &anyhow::Error) -> bool {
    err.chain().any(|cause| {
        matches!(
            cause.downcast_ref::<choreo_models::Error>(),
            Some(choreo_models::Error::TimeLimit { .. })
        )
    })
}

/// Whether the verb this process runs (e.g. `convert`, `prep aistpp`) has the flag `--long`:
/// a hint names only a flag the user can pass to what they ran.
fn verb_has_flag(args: impl IntoIterator<Item = std::ffi::OsString>, long: &str) -> bool {
    let mut command = <crate::commands::Cli as clap::CommandFactory>::command();
    // Parsing succeeded once already; this only finds which (sub)command ran.
    let Ok(mut matches) = command.clone().try_get_matches_from(args) else {
        return false;
    };
    while let Some((name, sub_matches)) = matches.subcommand() {
        let Some(sub) = command.find_subcommand(name).cloned() else {
            return false;
        };
        command = sub;
        matches = sub_matches.clone();
    }
    command.get_arguments().any(|a| a.get_long() == Some(long))
}

/// The machine is not ready for the daemon (another process holds its port or its folders).
#[derive(Debug)]
pub struct NotReady(pub String);

impl std::fmt::Display for NotReady {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for NotReady {}

/// A usage error found after parsing (e.g. `-o` naming an input): exit 2, as the parser's.
#[derive(Debug)]
pub struct Usage(pub String);

impl std::fmt::Display for Usage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for Usage {}

thread_local! {
    /// Inside [`catch_panic`] on this thread: a panic fails the work, not the process.
    static CATCHING: Cell<bool> = const { Cell::new(false) };
    /// The caught panic's one-line description, left by the hook for [`catch_panic`].
    static CAUGHT: RefCell<Option<String>> = const { RefCell::new(None) };
}

/// Run `work`, turning a panic inside it into `Err(one line: message and location)` instead of
/// ending the process. A daemon job runs in here, so a bug hit by one input fails that job only.
pub fn catch_panic<T>(work: impl FnOnce() -> T) -> Result<T, String> {
    let was = CATCHING.replace(true);
    let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(work));
    CATCHING.set(was);
    result.map_err(|_| {
        CAUGHT
            .take()
            .unwrap_or_else(|| "panicked (no message)".to_string())
    })
}

/// A panic is a bug; say so in one line instead of printing a backtrace at the user. Inside
/// [`catch_panic`] the hook only records the message: the caller fails that piece of work.
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
        let what = format!("{message}{}", location.unwrap_or_default());
        if CATCHING.get() {
            CAUGHT.set(Some(what));
            return;
        }
        let what = crate::logging::escape_controls(&what, false);
        eprintln!("choreod: internal error (a bug, please report it): {what}");
        std::process::exit(i32::from(INTERNAL));
    }));
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_panic_on_a_worker_thread_fails_the_work_not_the_process() {
        install_panic_hook();
        // Were the hook to exit, this test binary would die here instead of failing politely.
        let caught = std::thread::spawn(|| catch_panic(|| -> u32 { panic!("bad input {}", 7) }))
            .join()
            .expect("the thread itself survives");
        let message = caught.unwrap_err();
        assert!(
            message.starts_with("bad input 7 at ") && message.contains("exit.rs"),
            "{message}"
        );
        assert_eq!(catch_panic(|| 5), Ok(5));
        let _ = std::panic::take_hook();
    }

    #[test]
    fn motion_errors_name_the_flag_of_the_verb_that_changes_them() {
        let too_large = anyhow::Error::new(choreo_datasets::Error::TooLarge {
            path: "x.npy".into(),
            what: "array of shape [9, 9]".into(),
            limit: 10,
        })
        .context("reading");
        assert_eq!(
            flag_hint(&too_large),
            Some(("max-elements", "--max-elements"))
        );
        let rate = anyhow::Error::new(choreo_datasets::Error::FpsNotApplicable {
            path: "x.bvh".into(),
            format: choreo_datasets::MotionFormat::Bvh,
        });
        assert_eq!(flag_hint(&rate), Some(("fps", "--fps")));
        // The same refusal for the style reference names the style's flag.
        let style_rate = anyhow::Error::new(choreo_models::Error::StyleFile(
            choreo_datasets::Error::FpsNotApplicable {
                path: "style.bvh".into(),
                format: choreo_datasets::MotionFormat::Bvh,
            },
        ));
        assert_eq!(flag_hint(&style_rate), Some(("style-fps", "--style-fps")));
        let content_rate = anyhow::Error::new(choreo_models::Error::Datasets(
            choreo_datasets::Error::FpsNotApplicable {
                path: "content.bvh".into(),
                format: choreo_datasets::MotionFormat::Bvh,
            },
        ));
        assert_eq!(flag_hint(&content_rate), Some(("fps", "--fps")));
        assert_eq!(flag_hint(&anyhow::anyhow!("a job failed")), None);
        let args = |line: &str| {
            line.split(' ')
                .map(std::ffi::OsString::from)
                .collect::<Vec<_>>()
        };
        assert!(verb_has_flag(args("choreod eval a.h5"), "max-elements"));
        assert!(verb_has_flag(args("choreod convert a.bvh -o b.npy"), "fps"));
        // `dance` has no element cap to raise: no hint naming one.
        assert!(!verb_has_flag(
            args("choreod dance a.ogg -o b.h5"),
            "max-elements"
        ));
        assert!(verb_has_flag(
            args("choreod prep aistpp root -o out"),
            "jobs"
        ));
    }

    #[test]
    fn startup_refusals_map_to_the_documented_codes() {
        let busy = anyhow::Error::new(NotReady("port taken".into())).context("starting");
        assert_eq!(code_for(&busy), ENVIRONMENT);
        assert_eq!(code_for(&anyhow::anyhow!("a job failed")), FAILURE);
        assert_eq!(
            code_for(&anyhow::Error::new(Usage("-o is the input".into()))),
            USAGE
        );
    }
}
