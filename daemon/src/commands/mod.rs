//! One module per verb; each turns its arguments into library calls.

pub mod beats;
pub mod check_config;
pub mod convert;
pub mod dance;
pub mod eval;
pub mod features;
pub mod live;
pub mod mel;
pub mod models;
pub mod prep;
pub mod read_motion;
pub mod render;
pub mod serve;
pub mod stylize;
mod version;
pub mod view;

use std::io::Write;

use anyhow::Context;

use crate::cli::{Cli, Command};

/// Write `text` to stdout at once; a reader that closed the pipe (`choreod beats song | head -1`)
/// is not an error, while `println!` would panic and exit 101 as an internal error.
pub(crate) fn print_stdout(text: &str) -> anyhow::Result<()> {
    let mut out = std::io::stdout().lock();
    match out.write_all(text.as_bytes()).and_then(|()| out.flush()) {
        Err(e) if e.kind() != std::io::ErrorKind::BrokenPipe => Err(e).context("writing to stdout"),
        _ => Ok(()),
    }
}

/// Refuse an output (given by `flag`) whose folder is missing or unwritable before a long job
/// rather than after it; the folder is named, as the user wrote it.
pub(crate) fn check_output_folder(path: &std::path::Path, flag: &str) -> anyhow::Result<()> {
    choreo_dsp::atomic::probe_writable(path).with_context(|| {
        format!(
            "cannot create {flag} {} in the folder {}",
            path.display(),
            choreo_dsp::atomic::parent_dir(path).display()
        )
    })
}

/// Refuse an output (given by `flag`) that is one of `inputs` (each named by its flag) — the
/// same file by any path, symbolic or hard link: writing it would replace the input. Compared
/// by device and inode, so `./a.h5`, `a.h5` and a link to it are one file.
pub(crate) fn refuse_output_over_input(
    output: &std::path::Path,
    flag: &str,
    inputs: &[(&str, &std::path::Path)],
) -> anyhow::Result<()> {
    use std::os::unix::fs::MetadataExt;
    // An output that does not exist yet cannot be an input.
    let Ok(out) = std::fs::metadata(output) else {
        return Ok(());
    };
    for (input_flag, input) in inputs {
        if let Ok(m) = std::fs::metadata(input)
            && (m.dev(), m.ino()) == (out.dev(), out.ino())
        {
            return Err(crate::exit::Usage(format!(
                "{flag} {} is the same file as {input_flag} {}: writing it would replace the \
                 input; choose another output",
                output.display(),
                input.display()
            ))
            .into());
        }
    }
    Ok(())
}

/// Run the verb the user asked for.
pub fn run(cli: Cli) -> anyhow::Result<()> {
    if cli.global.version {
        return version::run(&cli.global);
    }
    match cli.command {
        Some(Command::IsolatedReadMotion(args)) => read_motion::run(args),
        Some(Command::CheckConfig(args)) => check_config::run(args),
        Some(Command::Dance(args)) => dance::run(args, &cli.global),
        Some(Command::Stylize(args)) => stylize::run(args, &cli.global),
        Some(Command::Convert(args)) => convert::run(args, &cli.global),
        Some(Command::Render(args)) => render::run(args, &cli.global),
        Some(Command::Mel(args)) => mel::run(args, &cli.global),
        Some(Command::Beats(args)) => beats::run(args, &cli.global),
        Some(Command::Features(args)) => features::run(args, &cli.global),
        Some(Command::Eval(args)) => eval::run(args, &cli.global),
        Some(Command::Prep(args)) => prep::run(args, &cli.global),
        Some(Command::Models(args)) => models::run(args, &cli.global),
        Some(Command::Serve(args)) => serve::run(args, &cli.global),
        Some(Command::Live(args)) => live::run(args, &cli.global),
        Some(Command::View(args)) => view::run(args, &cli.global),
        // arg_required_else_help makes clap print help when no verb is given.
        None => Ok(()),
    }
}
