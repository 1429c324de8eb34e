//! `choreod check-config FILE`

use std::path::PathBuf;

use clap::Args;

/// Arguments of `check-config`.
#[derive(Debug, Args)]
#[command(after_help = "\
Examples:
  choreod check-config config/choreod.example.toml   each problem named (exit 3), or the config
  choreod check-config /etc/choreod/choreod.toml && systemctl restart choreod")]
pub struct CheckConfigArgs {
    /// The TOML file (see config/choreod.example.toml for every key).
    pub file: PathBuf,
}

pub fn run(args: CheckConfigArgs) -> anyhow::Result<()> {
    let config = choreo_config::load(&args.file)?;
    config.preflight().map_err(|e| e.with_path(&args.file))?;
    tracing::info!(file = %args.file.display(), "configuration valid, directories usable");
    println!("{}: valid", args.file.display());
    println!("{config}");
    Ok(())
}
