//! `choreod`: the thin binary. Parse the command line, set up logging, run one verb, and turn
//! its outcome into one line on stderr and a documented exit code (see [`exit`]).

mod cli;
mod commands;
mod dance;
mod exit;
mod live;
mod logging;
mod serve;
mod stylize;

use std::process::ExitCode;

use clap::Parser;

fn main() -> ExitCode {
    exit::install_panic_hook();
    let cli = cli::Cli::parse();
    logging::init(&cli);
    match commands::run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => exit::report(&err),
    }
}
