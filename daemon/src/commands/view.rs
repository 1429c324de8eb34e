//! `choreod view FILE.h5` — the viewer page playing a finished motion file.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use anyhow::Context;
use clap::Args;
use serde::Serialize;

use crate::cli::GlobalArgs;
use crate::live::viewer::{self, SkeletonInfo};

/// Arguments of `view`.
#[derive(Debug, Args)]
#[command(after_help = "\
Examples:
  choreod view song.h5                         prints the URL to open; Ctrl-C stops
  choreod view song.h5 --bind 127.0.0.1:8080")]
pub struct ViewArgs {
    /// A motion file (HDF5, choreod-motion).
    pub file: PathBuf,
    /// Loopback address to serve on (port 0 picks a free one).
    #[arg(long, value_name = "ADDR", default_value = "127.0.0.1:0")]
    pub bind: SocketAddr,
}

#[derive(Serialize)]
struct MotionJson {
    fps: f32,
    joints: Vec<Vec<[f32; 3]>>,
}

pub fn run(args: ViewArgs, _global: &GlobalArgs) -> anyhow::Result<()> {
    if !args.bind.ip().is_loopback() {
        anyhow::bail!(
            "--bind {}: the viewer listens on loopback addresses only",
            args.bind
        );
    }
    let m = choreo_datasets::read_motion_file(&args.file)?;
    if m.joints.shape()[0] == 0 {
        anyhow::bail!("{}: the motion has no frames", args.file.display());
    }
    let motion = MotionJson {
        fps: m.fps,
        joints: m
            .joints
            .outer_iter()
            .map(|f| f.outer_iter().map(|j| [j[0], j[1], j[2]]).collect())
            .collect(),
    };
    let info = SkeletonInfo {
        fps: f64::from(m.fps),
        joint_names: m.skeleton.joint_names(),
        parents: m.skeleton.parents().to_vec(),
    };
    let server = viewer::serve(
        args.bind,
        &info,
        None,
        Some(serde_json::to_string(&motion).context("motion as JSON")?),
    )?;
    // stdout: the URL alone, for scripts.
    println!("http://{}/", server.addr);
    let stop = Arc::new(AtomicBool::new(false));
    for signal in [signal_hook::consts::SIGTERM, signal_hook::consts::SIGINT] {
        signal_hook::flag::register(signal, Arc::clone(&stop))?;
    }
    while !stop.load(Ordering::SeqCst) {
        std::thread::sleep(std::time::Duration::from_millis(100));
    }
    Ok(())
}
