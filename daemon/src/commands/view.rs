//! `choreod view FILE [--audio SONG]` — the viewer page playing a finished motion: the mannequin
//! glTF `choreod convert -o X.glb` writes, drawn by three.js, with the song.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use anyhow::Context;
use clap::Args;

use crate::cli::GlobalArgs;
use crate::commands::convert::{LimitArgs, report_assumed_fps};
use crate::live::viewer::{self, SkeletonInfo, ViewFile};

/// Arguments of `view`.
#[derive(Debug, Args)]
#[command(after_help = "\
The page plays the dance on a mannequin (three.js, the same glTF `choreod convert -o X.glb`
writes) with the song: from --audio, else the file its provenance names when that file sits
beside the motion and its sha256 matches. Space plays / pauses; the slider scrubs; the readout
shows the song's time, the frame and the frame rate.

Examples:
  choreod view song.h5                         prints the URL to open; Ctrl-C stops
  choreod view song.h5 --audio song.ogg        with the song
  choreod view take.bvh --bind 127.0.0.1:8080
  choreod view dance.glb --audio song.ogg      a glTF choreod (or another tool) wrote
  choreod view joints.npy --fps 60             a .npy records no frame rate")]
pub struct ViewArgs {
    /// Motion to show: .h5 motion file (also .pkl, .bvh, .npy joints or 263 features), or a
    /// .glb / .gltf (played as it is: its own mesh and first animation).
    pub file: PathBuf,
    /// The song to play with it (any format `choreod dance` reads). Default: the song named in
    /// the file's provenance, if it is beside the file and its sha256 matches.
    #[arg(long, value_name = "FILE")]
    pub audio: Option<PathBuf>,
    /// Loopback address to serve on (port 0 picks a free one).
    #[arg(long, value_name = "ADDR", default_value = "127.0.0.1:0")]
    pub bind: SocketAddr,
    /// Frame rate of a .npy input (a .npy records none).
    #[arg(long, value_name = "FPS")]
    pub fps: Option<f32>,
    #[command(flatten)]
    pub limits: LimitArgs,
}

pub fn run(args: ViewArgs, _global: &GlobalArgs) -> anyhow::Result<()> {
    if !args.bind.ip().is_loopback() {
        anyhow::bail!(
            "--bind {}: the viewer listens on loopback addresses only",
            args.bind
        );
    }
    args.limits.apply();
    let (info, glb, provenance) = if is_gltf(&args.file) {
        let glb = std::fs::read(&args.file)
            .with_context(|| format!("cannot read {}", args.file.display()))?;
        let g = choreo_datasets::read_gltf_skeleton(&args.file, &glb)?;
        let info = SkeletonInfo {
            fps: g.fps,
            joint_names: g.joint_names,
            parents: g.parents,
            nodes: g.nodes,
        };
        (info, glb, None)
    } else {
        let loaded = choreo_datasets::load_motion(&args.file, args.fps)?;
        report_assumed_fps(&args.file, loaded.fps_assumed, loaded.motion.fps);
        let m = loaded.motion;
        let glb = choreo_datasets::gltf_bytes(&m, &choreo_datasets::ExportOptions::default())
            .with_context(|| format!("making the mannequin of {}", args.file.display()))?;
        let info = SkeletonInfo::of(f64::from(m.fps), &m.skeleton);
        (info, glb, m.provenance)
    };
    let song = match &args.audio {
        Some(path) => Ok(path.clone()),
        None => provenance_song(&args.file, provenance.as_ref()),
    };
    let audio = match &song {
        Ok(path) => Ok(wav_of(path)?),
        Err(why) => Err(why.clone()),
    };
    let server = viewer::serve(args.bind, &info, None, Some(ViewFile { glb, audio }))?;
    match &song {
        Ok(path) => eprintln!("viewer: playing with {}", path.display()),
        Err(why) => eprintln!("viewer: no song: {why}"),
    }
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

/// A glTF file (played as it is) rather than a motion file (made into one).
fn is_gltf(path: &Path) -> bool {
    path.extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case("glb") || e.eq_ignore_ascii_case("gltf"))
}

/// The song the provenance names, when it sits beside the motion and is the same file
/// (sha256); otherwise why not.
fn provenance_song(
    motion: &Path,
    provenance: Option<&choreo_datasets::Provenance>,
) -> Result<PathBuf, String> {
    const GIVE: &str = "give --audio FILE to hear one";
    let Some(p) = provenance.filter(|p| !p.source_name.is_empty() && !p.source_sha256.is_empty())
    else {
        return Err(format!("the file names no song ({GIVE})"));
    };
    // A bare file name: nothing is read from outside the motion's folder.
    let Some(name) = Path::new(&p.source_name).file_name() else {
        return Err(format!("the file names no song ({GIVE})"));
    };
    let path = motion.parent().unwrap_or(Path::new(".")).join(name);
    match choreo_datasets::sha256_file(&path) {
        Ok(sha) if sha == p.source_sha256 => Ok(path),
        Ok(_) => Err(format!(
            "{} differs from the song the dance was made from (sha256), so it is not played \
             ({GIVE})",
            path.display()
        )),
        Err(_) => Err(format!(
            "the song it was made from, {}, is not beside it ({GIVE})",
            choreo_dsp::quote(&p.source_name)
        )),
    }
}

/// The song decoded (mono, its own rate) as a 16-bit WAV the browser plays whatever the
/// source format.
fn wav_of(path: &Path) -> anyhow::Result<Vec<u8>> {
    let audio = choreo_dsp::decode_file(path, &choreo_dsp::DecodeOptions::default())
        .with_context(|| format!("reading the song {}", path.display()))?;
    let data_len = u32::try_from(audio.samples.len() * 2)
        .ok()
        .filter(|n| *n < u32::MAX - 36)
        .with_context(|| format!("{}: too long for a WAV file", path.display()))?;
    let rate = audio.sample_rate;
    let mut wav = Vec::with_capacity(44 + data_len as usize);
    wav.extend(b"RIFF");
    wav.extend((36 + data_len).to_le_bytes());
    wav.extend(b"WAVEfmt ");
    // PCM, 1 channel, rate, byte rate, block align 2, 16 bits.
    wav.extend(16u32.to_le_bytes());
    wav.extend(1u16.to_le_bytes());
    wav.extend(1u16.to_le_bytes());
    wav.extend(rate.to_le_bytes());
    wav.extend((rate * 2).to_le_bytes());
    wav.extend(2u16.to_le_bytes());
    wav.extend(16u16.to_le_bytes());
    wav.extend(b"data");
    wav.extend(data_len.to_le_bytes());
    for s in &audio.samples {
        wav.extend(((s.clamp(-1.0, 1.0) * 32767.0).round() as i16).to_le_bytes());
    }
    Ok(wav)
}
