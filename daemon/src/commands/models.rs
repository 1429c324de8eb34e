//! `choreod models check DIR`: load a model package and validate it against its manifest.

use std::path::PathBuf;
use std::time::Instant;

use clap::{Args, Subcommand};

use crate::cli::GlobalArgs;

/// Arguments of `models`.
#[derive(Debug, Args)]
pub struct ModelsArgs {
    #[command(subcommand)]
    pub command: ModelsCommand,
}

/// What to do with model packages.
#[derive(Debug, Subcommand)]
pub enum ModelsCommand {
    /// Load a package and validate it: manifest keys and values for its task (music-to-dance or
    /// style-transfer), every component's file and sha256, that ONNX Runtime loads it, that its
    /// inputs and outputs match the manifest (names, dtypes, shapes), and one test run of every
    /// component on small inputs with finite outputs of the declared shapes. Prints a summary.
    ///
    /// Exit code 4 when the package is unusable, with one line naming the package, the
    /// component and what is wrong.
    #[command(
        after_help = "Examples:\n  choreod models check models/packages/exemplar\n  \
                            choreod models check models/packages/style-gaussian\n  \
                            choreod models check ~/my-export --no-run\n  \
                            choreod models check pkg-int8 --against pkg   # int8 vs its float32 source"
    )]
    Check(CheckArgs),
}

/// Arguments of `models check`.
#[derive(Debug, Args)]
pub struct CheckArgs {
    /// The package directory (holds choreod-model.toml and the ONNX files).
    pub dir: PathBuf,
    /// Skip the test evaluation (only load and compare interfaces).
    #[arg(long)]
    pub no_run: bool,
    /// Seconds the test evaluation may take, every component and the hoisting comparison
    /// together (0.1..=86400): a graph still running then (one that loops for ever) fails the
    /// check. The shipped packages need under a second.
    #[arg(long, value_name = "SECONDS", value_parser = crate::cli::max_seconds,
          default_value_t = CHECK_TIME_LIMIT_S)]
    pub time_limit: f64,
    /// The float32 package an int8 package was made from: run both on the test inputs and
    /// print how far the int8 outputs are from the float32 ones.
    #[arg(long, value_name = "SOURCE_DIR", conflicts_with = "no_run")]
    pub against: Option<PathBuf>,
}

/// Default `models check --time-limit`: the shipped packages' test runs take well under a
/// second (the check prints the time); 30 s leaves room for far larger packages without
/// letting a graph that loops for ever hang the check.
const CHECK_TIME_LIMIT_S: f64 = 30.0;

pub fn run(args: ModelsArgs, global: &GlobalArgs) -> anyhow::Result<()> {
    match args.command {
        ModelsCommand::Check(check) => run_check(check, global),
    }
}

fn run_check(args: CheckArgs, global: &GlobalArgs) -> anyhow::Result<()> {
    let ort = crate::settings::ort(global.ort_library.as_deref())?;
    let options = choreo_models::RuntimeOptions::default();
    let mut package = crate::settings::load_package(&args.dir, &options, &ort)?;
    print!("{package}");
    if !args.no_run {
        let started = Instant::now();
        package.set_deadline(Some(crate::settings::deadline(args.time_limit)));
        // A test run stopped at the limit: the package is unusable (exit 4), as when it fails.
        let unusable = |e: choreo_models::Error| match e {
            choreo_models::Error::TimeLimit { .. } => {
                anyhow::Error::new(crate::exit::NotReady(format!("{e} (--time-limit)")))
            }
            other => other.into(),
        };
        package.smoke_test().map_err(unusable)?;
        println!(
            "test run    ok: every component ran on small inputs; outputs finite, of the declared shapes ({:.1} ms)",
            started.elapsed().as_secs_f64() * 1e3
        );
        if let Some(source) = &args.against {
            let mut source = crate::settings::load_package(source, &options, &ort)?;
            source.set_deadline(Some(crate::settings::deadline(args.time_limit)));
            let d = package.deviation_from(&mut source).map_err(unusable)?;
            println!(
                "against     {}: max {:.3e}, rms {:.3e} of the float32 outputs (relative)",
                source.dir().display(),
                d.max_relative,
                d.rms_relative
            );
        }
        if let Some(gap) = package.verify_hoisting(&ort).map_err(unusable)? {
            println!(
                "hoisting    ok: the split denoiser gives what the whole graph gives (largest gap {gap:.1e} of the output scale)"
            );
        }
    }
    println!(
        "{}: valid (onnxruntime {})",
        args.dir.display(),
        ort.version()
    );
    Ok(())
}
