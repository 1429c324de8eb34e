//! One module per verb; each turns its arguments into library calls.

pub mod check_config;
mod version;

use crate::cli::{Cli, Command};

/// Run the verb the user asked for.
pub fn run(cli: Cli) -> anyhow::Result<()> {
    if cli.global.version {
        return version::run(&cli.global);
    }
    match cli.command {
        Some(Command::CheckConfig(args)) => check_config::run(args),
        // arg_required_else_help makes clap print help when no verb is given.
        None => Ok(()),
    }
}
