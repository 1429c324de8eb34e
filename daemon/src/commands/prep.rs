//! `choreod prep aistpp|humanml3d|merge`: training-ready HDF5 shards from the public datasets.

use std::path::PathBuf;
use std::sync::Mutex;

use anyhow::Context;
use choreo_datasets::prep::{self, Part, PrepOptions, PrepReport, Progress};
use clap::{Args, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};

use crate::cli::{FeatureSet, GlobalArgs, LibrosaArg};

/// Arguments of `prep`.
#[derive(Debug, Args)]
#[command(after_help = "\
Examples:
  choreod prep aistpp ~/data/aistpp -o ~/prep/aistpp --music ~/data/aist_music --jobs 8
  choreod prep humanml3d ~/data/HumanML3D -o ~/prep/hml3d --mirror
  # across 4 machines (each writes the shards whose number is I mod 4), then join:
  choreod prep humanml3d ROOT -o OUT --shard 2/4
  choreod prep merge OUT -o OUT

A rerun with the same input and output skips finished shards (interrupted runs resume).
The output: <split>-<NNNNN>.h5 shards with a .json sidecar each, manifest.json (counts,
parameters, sha256 of every shard, every skipped sequence with its reason), and for
HumanML3D Mean.npy / Std.npy.")]
pub struct PrepArgs {
    #[command(subcommand)]
    pub dataset: PrepCommand,
}

/// `prep` verbs.
#[derive(Debug, Subcommand)]
pub enum PrepCommand {
    /// AIST++: motions/*.pkl + splits/crossmodal_*.txt + ignore_list.txt + music WAVs → shards
    /// with SMPL joints at 60 and 30 fps, log-mel, onset envelope and beats aligned to 30 fps.
    Aistpp(AistppArgs),
    /// HumanML3D: new_joints/ (or joints/) + texts/ + train/val/test.txt → shards of 263-dim
    /// features with captions, Mean.npy and Std.npy (grouped std).
    Humanml3d(Humanml3dArgs),
    /// Join the outputs of `--shard I/N` runs (checks every shard's sha256; HumanML3D Mean/Std
    /// are recomputed exactly from the per-shard sums).
    Merge(MergeArgs),
}

/// Flags shared by the two datasets.
#[derive(Debug, Args)]
pub struct CommonArgs {
    /// Dataset root in the official layout.
    pub root: PathBuf,
    /// Output directory (created; a rerun into it resumes).
    #[arg(short, long, value_name = "DIR")]
    pub output: PathBuf,
    /// Worker threads (0 = one per core).
    #[arg(long, default_value_t = 0, value_name = "N")]
    pub jobs: usize,
    /// Do part I of N: the output shards whose number is I mod N (0-based).
    #[arg(long, value_name = "I/N")]
    pub shard: Option<String>,
    /// Sequences per shard file (0 = dataset default: AIST++ 64, HumanML3D 256).
    #[arg(long, default_value_t = 0, value_name = "N")]
    pub per_shard: usize,
    /// Stop after writing this many shards (a budgeted run; run again to continue).
    #[arg(long, value_name = "N")]
    pub max_shards: Option<usize>,
    #[command(flatten)]
    pub limits: crate::commands::convert::LimitArgs,
}

/// Arguments of `prep aistpp`.
#[derive(Debug, Args)]
pub struct AistppArgs {
    #[command(flatten)]
    pub common: CommonArgs,
    /// Folder of music WAVs named by music id (mBR0.wav ...). Default: ROOT/music.
    #[arg(long, value_name = "DIR")]
    pub music: Option<PathBuf>,
    /// Also write these music features of every sequence (`fact35`: (T, 35) at 30 fps, as
    /// `choreod features --set fact35` computes them with the music id's BPM as --start-bpm).
    #[arg(long, value_enum, value_name = "SET")]
    pub features: Option<FeatureSet>,
    /// The librosa whose numbers --features reproduces.
    #[arg(long, value_enum, default_value = "0.7", requires = "features")]
    pub librosa: LibrosaArg,
}

/// Arguments of `prep humanml3d`.
#[derive(Debug, Args)]
pub struct Humanml3dArgs {
    #[command(flatten)]
    pub common: CommonArgs,
    /// Also write the mirrored copy M<id> of every sequence (captions with left/right swapped).
    #[arg(long)]
    pub mirror: bool,
}

/// Arguments of `prep merge`.
#[derive(Debug, Args)]
pub struct MergeArgs {
    /// Output directories of the parts (each holds manifest.part-I-of-N.json or manifest.json).
    #[arg(required = true)]
    pub inputs: Vec<PathBuf>,
    /// Merged output directory (may be one of the inputs).
    #[arg(short, long, value_name = "DIR")]
    pub output: PathBuf,
}

fn options(c: &CommonArgs) -> anyhow::Result<PrepOptions> {
    let mut o = PrepOptions::default();
    o.jobs = c.jobs;
    o.sequences_per_shard = c.per_shard;
    o.max_shards = c.max_shards;
    if let Some(s) = &c.shard {
        o.part = s
            .parse::<Part>()
            .map_err(anyhow::Error::msg)
            .context("--shard")?;
    }
    Ok(o)
}

/// A bar per stage, with rate and ETA; hidden when stderr is not a terminal.
struct Bar {
    bar: ProgressBar,
    stage: Mutex<&'static str>,
}

impl Bar {
    fn new() -> anyhow::Result<Self> {
        let bar = ProgressBar::new(0).with_style(
            ProgressStyle::with_template(
                "{msg:9} [{bar:30}] {pos}/{len} {per_sec} {elapsed} (eta {eta})",
            )
            .context("progress bar template")?
            .progress_chars("=> "),
        );
        Ok(Bar {
            bar,
            stage: Mutex::new(""),
        })
    }

    fn update(&self, p: Progress) {
        if let Ok(mut s) = self.stage.lock()
            && *s != p.stage
        {
            *s = p.stage;
            self.bar.reset();
            self.bar.set_message(p.stage);
        }
        self.bar.set_length(p.total as u64);
        // Workers report out of order; the bar only moves forward within a stage.
        if p.done as u64 > self.bar.position() || p.done == 0 {
            self.bar.set_position(p.done as u64);
        }
    }
}

/// Print the validation report; a closed stdout (`| head`) is not an error.
fn print_report(what: &str, r: &PrepReport) -> anyhow::Result<()> {
    use std::fmt::Write as _;
    let m = &r.manifest;
    let sequences: usize = m.shards.iter().map(|s| s.sequences).sum();
    let mut o = String::new();
    writeln!(
        o,
        "{what}: {} motion files, {sequences} sequences in {} shards ({} written now, {} kept), {} skipped",
        m.files_found,
        m.shards.len(),
        r.shards_written,
        r.shards_reused,
        m.skips.len()
    )?;
    for (split, c) in &m.splits {
        writeln!(
            o,
            "  {split}: {} sequences, {} frames, {}/{} shards",
            c.sequences, c.frames, c.shards, c.planned_shards
        )?;
    }
    let mut by_reason: std::collections::BTreeMap<String, usize> = Default::default();
    for s in &m.skips {
        *by_reason.entry(s.reason.to_string()).or_default() += 1;
    }
    if !by_reason.is_empty() {
        let parts: Vec<String> = by_reason.iter().map(|(r, n)| format!("{n} {r}")).collect();
        writeln!(o, "  skipped: {}", parts.join(", "))?;
    }
    for s in &m.skips {
        writeln!(o, "  skipped {}: {} ({})", s.name, s.reason, s.detail)?;
    }
    for n in &m.notes {
        writeln!(o, "  note: {n}")?;
    }
    if let Some(ms) = &m.mean_std {
        writeln!(
            o,
            "  {} / {} from {} frames",
            ms.mean_file, ms.std_file, ms.frames
        )?;
    }
    if !m.complete {
        writeln!(o, "  incomplete: run the same command again to continue")?;
    }
    writeln!(o, "manifest: {}", r.manifest_path.display())?;
    super::print_stdout(&o)
}

pub fn run(args: PrepArgs, _global: &GlobalArgs) -> anyhow::Result<()> {
    match args.dataset {
        PrepCommand::Aistpp(a) => {
            a.common.limits.apply();
            let mut o = options(&a.common)?;
            o.music_dir = a.music;
            o.fact35 = a.features.map(|FeatureSet::Fact35| a.librosa.version());
            let bar = Bar::new()?;
            let r = prep::prepare_aistpp(&a.common.root, &a.common.output, &o, &|p| bar.update(p))
                .with_context(|| format!("preparing AIST++ from {}", a.common.root.display()));
            bar.bar.finish_and_clear();
            print_report("aistpp", &r?)?;
        }
        PrepCommand::Humanml3d(a) => {
            a.common.limits.apply();
            let mut o = options(&a.common)?;
            o.mirror = a.mirror;
            let bar = Bar::new()?;
            let r =
                prep::prepare_humanml3d(&a.common.root, &a.common.output, &o, &|p| bar.update(p))
                    .with_context(|| {
                        format!("preparing HumanML3D from {}", a.common.root.display())
                    });
            bar.bar.finish_and_clear();
            print_report("humanml3d", &r?)?;
        }
        PrepCommand::Merge(a) => {
            let r = prep::merge(&a.inputs, &a.output)
                .with_context(|| format!("merging into {}", a.output.display()))?;
            print_report("merge", &r)?;
        }
    }
    Ok(())
}
