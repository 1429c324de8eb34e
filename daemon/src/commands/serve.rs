//! `choreod serve [--config FILE]`

use std::path::PathBuf;

use clap::Args;

use crate::cli::GlobalArgs;
use crate::settings::{self, PackageKind, ServeConfig};

/// Arguments of `serve`.
#[derive(Debug, Args)]
#[command(after_help = "\
Examples:
  choreod serve --config config/choreod.example.toml --log-level info
  systemctl start choreod          (see daemon/systemd/choreod.service)
Drop songs into paths.inbox; each becomes paths.output/<song>.h5, or
paths.state/failed/<id>__<song> with <id>__<song>.error.json. With [style] enabled, motion
files (.bvh, .pkl, .npy, .h5) dropped into style.inbox are stylized with style.style the same
way. Stop with SIGTERM or Ctrl-C.
Health and metrics: curl http://127.0.0.1:9464/healthz, .../metrics (metrics.bind).
With [live] enabled, live sessions run beside the watch folder: the viewer at live.viewer, one
live-<UTC time>.h5 per session in live.output, finished on SIGTERM.")]
pub struct ServeArgs {
    /// The daemon's TOML configuration (every key: config/choreod.example.toml).
    /// Default: $CHOREOD_CONFIG, else /etc/choreod/choreod.toml.
    #[arg(long, short, value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// Model package directory. Default: runtime.default_model of the config, else
    /// $CHOREOD_MODEL, else the bundled models/packages/library.
    #[arg(long, value_name = "DIR")]
    pub model: Option<PathBuf>,
}

/// The config file serve reads: `--config`, else `$CHOREOD_CONFIG`, else the system path.
pub fn config_path(args: &ServeArgs) -> PathBuf {
    args.config
        .clone()
        .or_else(|| {
            std::env::var_os("CHOREOD_CONFIG")
                .filter(|v| !v.is_empty())
                .map(PathBuf::from)
        })
        .unwrap_or_else(|| PathBuf::from("/etc/choreod/choreod.toml"))
}

/// Run the service with `config`, the file [`config_path`] names, loaded once before logging
/// started.
pub fn run(args: ServeArgs, config: ServeConfig, global: &GlobalArgs) -> anyhow::Result<()> {
    let shutdown = crate::serve::install_signal_handlers()?;
    let (path, config) = config.into_config()?;
    config.preflight().map_err(|e| e.with_path(&path))?;
    tracing::info!(file = %path.display(), "configuration valid");
    for line in config.to_string().lines() {
        tracing::info!("{line}");
    }
    let configured = global
        .ort_library
        .as_deref()
        .or(config.runtime.ort_library.as_deref());
    let ort = settings::ort(configured)?;
    let model_dir = PackageKind::Dance.dir(
        args.model
            .or_else(|| config.runtime.default_model.clone())
            .as_deref(),
    );
    crate::serve::run(&config, &ort, &model_dir, shutdown)
}
