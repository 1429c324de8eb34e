//! `choreod isolated-read-motion` (hidden): the child process that reads one untrusted motion
//! file for its parent `choreod` (see `choreo_datasets::isolated`). Not for people.

use std::path::PathBuf;

use anyhow::Context;
use clap::Args;

/// The verb that makes this process a reader child.
pub const VERB: &str = "isolated-read-motion";

/// Arguments of the hidden reader verb.
#[derive(Debug, Args)]
pub struct ReadMotionArgs {
    /// Only the root `format` attribute (which reader the file is for).
    #[arg(long)]
    pub format_only: bool,
    /// The parent's element cap (`--max-elements`).
    #[arg(long)]
    pub max_elements: usize,
    /// The motion file.
    #[arg(last = true)]
    pub file: PathBuf,
}

/// Every `.h5` motion file the rest of this process reads is read by a child: this program,
/// re-executed from its own image (`/proc/self/exe`, so an upgrade on disk does not matter).
pub fn isolate() {
    choreo_datasets::isolated::isolate_motion_reads(
        choreo_datasets::isolated::IsolatedReader::new(
            "/proc/self/exe",
            [VERB],
            choreo_datasets::isolated::ReaderLimits::default(),
        ),
    );
}

pub fn run(args: ReadMotionArgs) -> anyhow::Result<()> {
    let mut out = std::io::stdout().lock();
    choreo_datasets::isolated::answer_isolated_read(
        &args.file,
        args.max_elements,
        args.format_only,
        &choreo_datasets::isolated::ReaderLimits::default(),
        &mut out,
    )
    .context("answering the parent")
}
