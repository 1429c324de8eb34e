//! `choreod isolated-read-motion` (hidden): the child process that reads one untrusted motion
//! file for its parent `choreod` (see `choreo_datasets::isolated`). Not for people.

use std::path::PathBuf;

use anyhow::Context;
use choreo_datasets::isolated::ReadRequest;
use clap::Args;

/// The verb that makes this process a reader child.
pub const VERB: &str = "isolated-read-motion";

/// Arguments of the hidden reader verb, in the order `IsolatedReader` passes them.
#[derive(Debug, Args)]
pub struct ReadMotionArgs {
    /// What to read: `motion` (the whole file), `format` (only the root `format` attribute),
    /// `sequences` (a prep shard's sequence names) or `sequence:NAME` (one of them).
    #[arg(value_parser = request)]
    pub request: ReadRequest,
    /// The parent's element cap.
    pub max_elements: usize,
    /// The motion file.
    #[arg(last = true)]
    pub file: PathBuf,
}

fn request(arg: &str) -> Result<ReadRequest, String> {
    ReadRequest::from_arg(arg).ok_or_else(|| format!("not a read request: {arg}"))
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
        args.request,
        &choreo_datasets::isolated::ReaderLimits::default(),
        &mut out,
    )
    .context("answering the parent")
}
