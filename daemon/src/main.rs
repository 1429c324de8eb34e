//! `choreod`: the thin binary. Parse the command line, set up logging, run one verb, and turn
//! its outcome into one line on stderr and a documented exit code (see [`exit`]).

mod cli;
mod commands;
mod dance;
mod exit;
mod live;
mod logging;
#[cfg(test)]
mod readme_defaults;
mod serve;
mod settings;
mod stylize;

use std::process::ExitCode;

use clap::Parser;

fn main() -> ExitCode {
    // ONNX Runtime's telemetry uploader (on in Microsoft's builds, the PyPI wheel among them)
    // starts when the library is loaded, before `DisableTelemetryEvents` (see models::runtime)
    // can be called; this variable, read at load, keeps it from starting (README, "Privacy").
    // SAFETY: the first statement of main: no other thread exists that could read the
    // environment meanwhile.
    #[allow(unsafe_code)] // std::env::set_var is unsafe in edition 2024 for that reason.
    unsafe {
        std::env::set_var("ORT_DISABLE_TELEMETRY", "1");
    }
    exit::install_panic_hook();
    let cli = commands::Cli::parse();
    // Read once: its `[log]` section sets up logging, then the service runs with it.
    let serve_config = match &cli.command {
        Some(commands::Command::Serve(args)) => Some(settings::ServeConfig::load(
            commands::serve::config_path(args),
        )),
        _ => None,
    };
    logging::init(
        &cli,
        serve_config.as_ref().and_then(|c| c.config.as_ref().ok()),
    );
    // A crash of libhdf5 on a hostile .h5 then kills a child, not this process.
    if !matches!(cli.command, Some(commands::Command::IsolatedReadMotion(_))) {
        commands::read_motion::isolate();
    }
    match commands::run(cli, serve_config) {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => exit::report(&err),
    }
}
