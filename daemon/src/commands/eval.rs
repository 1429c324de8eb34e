//! `choreod eval GEN... [--reference REF...] [--music AUDIO | --beats FILE] [--json]`: the
//! field's dance and style metrics (the engine is `choreo_datasets::metrics`).

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::Context;
use choreo_datasets::metrics::{
    self, EvalInput, EvalMotion, EvalSource, FileMetrics, SetValue, eval_sources,
};
use choreo_datasets::{EvalOptions, EvalReport};
use clap::Args;

use crate::cli::GlobalArgs;

/// Arguments of `eval`.
#[derive(Debug, Args)]
#[command(after_help = "\
Examples:
  choreod eval out/*.h5 --reference ~/prep/aistpp/test-00000.h5 --music song.ogg
  choreod eval gen/ --reference gt/ --json > scores.json
  choreod eval styled.h5 --content content.npy          foot sliding (FSF) and TSI
  choreod eval dance.h5 --beats beats.txt --bas-fps 30   BAS at 30 fps (sigma = 100 ms)

Inputs are motion files (.h5, .pkl, .bvh, .npy joints or HumanML3D features), directories of
them, or `choreod prep` shards (every sequence). A BVH of another rig (CMU, Mixamo, ...) is
placed on t2m-22 by its joint names, as stylize does. Music beats come from --beats (seconds, one
per line), else the beat tracker on --music, else the song named in each motion file's
provenance when it is found beside the motion file. A prep shard's sequences use the beats prep
stored with them unless --music or --beats is given.

Metrics (sources in README \"choreod eval\"): FID_k (aistplusplus_api features with their
acceleration slip, comparable to papers) and fid_k_fixed_accel, FID_g, Div_k / Div_g
(Bailando), bas_motion_beats (AIST++/mint) and bas_music_beats (Bailando/MoFusion), PFC
(EDGE), skate ratio (GMD), foot sliding FSF and TSI (MCM-LDM, definitions in README),
multimodality when several generations share a song.")]
pub struct EvalArgs {
    /// Generated motions: files, directories or prep shards.
    #[arg(required = true, value_name = "GEN")]
    pub generated: Vec<PathBuf>,
    /// Reference (ground-truth) motions for FID and the z-scoring statistics.
    #[arg(long, num_args = 1.., value_name = "REF")]
    pub reference: Vec<PathBuf>,
    /// Song whose beats the BAS scores against (any format `choreod beats` reads). A motion
    /// whose provenance names another song (by sha256) is refused, naming it.
    #[arg(long, value_name = "AUDIO", conflicts_with = "beats")]
    pub music: Option<PathBuf>,
    /// Score every motion against --music even where its provenance names another song (a
    /// warning names each).
    #[arg(long, requires = "music")]
    pub any_music: bool,
    /// Music beat times, seconds, one per line.
    #[arg(long, value_name = "FILE")]
    pub beats: Option<PathBuf>,
    /// Content motion of a style transfer: adds TSI (trajectory distance) per motion.
    #[arg(long, value_name = "FILE")]
    pub content: Option<PathBuf>,
    /// Print one JSON object instead of text.
    #[arg(long)]
    pub json: bool,
    /// Write each generated motion's feature vectors here as .npy
    /// (`NNNNN_<name>.{kinetic,kinetic_fixed_accel,geometric}.npy`).
    #[arg(long, value_name = "DIR")]
    pub features_out: Option<PathBuf>,
    /// Use the research code's hard-coded 60 fps frame time whatever the file's fps.
    #[arg(long)]
    pub legacy_60fps: bool,
    /// Frame rate the BAS is scored at, 1..=1000 (sigma = 3 frames at this rate).
    #[arg(long, default_value_t = choreo_datasets::EvalOptions::default().bas_fps, value_name = "FPS", value_parser = crate::cli::fps)]
    pub bas_fps: f32,
    /// Frame rate of .npy inputs, 1..=1000 (a .npy records none; else 20 fps for 22 joints
    /// and 263 features, 30 fps otherwise is assumed).
    #[arg(long, value_name = "FPS", value_parser = crate::cli::fps)]
    pub fps: Option<f32>,
    #[command(flatten)]
    pub limits: super::convert::LimitArgs,
}

/// Longest `--beats` file read (a beat per line; a day of music at 300 BPM is 7 MB).
const MAX_BEATS_FILE_BYTES: u64 = 16 << 20;

fn read_beats_file(path: &Path) -> anyhow::Result<Vec<f64>> {
    let ctx = || format!("reading beats {}", path.display());
    let len = std::fs::metadata(path).with_context(ctx)?.len();
    anyhow::ensure!(
        len <= MAX_BEATS_FILE_BYTES,
        "{}: {len} bytes is too large for a beat list",
        path.display()
    );
    let text = std::fs::read_to_string(path).with_context(ctx)?;
    let mut out = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let t: f64 = line
            .parse()
            .ok()
            .filter(|t: &f64| t.is_finite() && *t >= 0.0)
            .with_context(|| {
                format!(
                    "{}: line {}: {} is not a time in seconds",
                    path.display(),
                    n + 1,
                    choreo_dsp::quote(line)
                )
            })?;
        out.push(t);
    }
    Ok(out)
}

/// The song a generated file's provenance names, when it sits beside the motion file (not a
/// features file a dance was made from: `source_kind`).
fn provenance_song(m: &EvalMotion) -> Option<PathBuf> {
    let p = m
        .motion
        .provenance
        .as_ref()
        .filter(|p| p.source_kind.is_none())?;
    let name = &p.source_name;
    let file_name = Path::new(name).file_name()?;
    let candidate = m.path.parent()?.join(file_name);
    candidate.is_file().then_some(candidate)
}

fn tracked(path: &Path) -> anyhow::Result<Vec<f64>> {
    // 3600 s: `choreod beats`' default limit.
    Ok(super::beats::track(path, 120.0, 3600.0)?.0.beat_times_s)
}

fn sources(paths: &[PathBuf]) -> anyhow::Result<Vec<EvalSource>> {
    let mut out = Vec::new();
    for p in paths {
        out.extend(eval_sources(p)?);
    }
    Ok(out)
}

/// Refuse (or with `--any-music` warn about) a motion made from another song than `--music`:
/// its BAS against that song would be a number about nothing.
fn check_music(
    motion: &EvalMotion,
    music: &Path,
    music_sha256: &str,
    any: bool,
) -> anyhow::Result<()> {
    let Some(p) = motion.motion.provenance.as_ref() else {
        return Ok(());
    };
    if p.source_sha256.is_empty() || p.source_sha256 == music_sha256 {
        return Ok(());
    }
    let what = format!(
        "{} was made from {} (sha256 {}…), not from --music {} (sha256 {}…)",
        motion.name,
        choreo_dsp::quote(&p.source_name),
        p.source_sha256.get(..12).unwrap_or(&p.source_sha256),
        music.display(),
        &music_sha256[..12],
    );
    anyhow::ensure!(
        any,
        "{what}; leave it out, or pass --any-music to score it anyway"
    );
    tracing::warn!("{what}: its BAS is scored against --music as --any-music asks");
    Ok(())
}

pub fn run(args: EvalArgs, _global: &GlobalArgs) -> anyhow::Result<()> {
    args.limits.apply();
    let global_beats = match (&args.beats, &args.music) {
        (Some(b), _) => Some(read_beats_file(b)?),
        (None, Some(m)) => Some(tracked(m)?),
        (None, None) => None,
    };
    let music_sha256 = args
        .music
        .as_deref()
        .map(choreo_datasets::sha256_file)
        .transpose()?;
    let mut opts = EvalOptions::default();
    opts.legacy_60fps = args.legacy_60fps;
    opts.bas_fps = args.bas_fps;
    let content = match &args.content {
        Some(c) => Some(metrics::content_trajectory(
            &EvalSource::File(c.clone()).load(args.fps)?,
        )?),
        None => None,
    };
    // One motion in memory at a time: each is scored, then only its numbers are kept.
    let mut song_beats: BTreeMap<PathBuf, Vec<f64>> = BTreeMap::new();
    let mut files = Vec::new();
    let mut songs = Vec::new();
    let mut have_beats = global_beats.is_some();
    for source in sources(&args.generated)? {
        let mut motion = source.load(args.fps)?;
        if let (Some(music), Some(sha)) = (&args.music, &music_sha256) {
            check_music(&motion, music, sha, args.any_music)?;
        }
        let song = motion
            .motion
            .provenance
            .as_ref()
            .map(|p| p.source_sha256.clone())
            .filter(|s| !s.is_empty());
        let stored = motion.beat_times_s.take();
        let beat_times_s = match (&global_beats, stored, provenance_song(&motion)) {
            (Some(b), _, _) => Some(b.clone()),
            (None, Some(b), _) => Some(b),
            (None, None, Some(path)) => {
                if !song_beats.contains_key(&path) {
                    let b = tracked(&path)?;
                    song_beats.insert(path.clone(), b);
                }
                song_beats.get(&path).cloned()
            }
            (None, None, None) => None,
        };
        have_beats |= beat_times_s.is_some();
        let input = EvalInput {
            motion,
            beat_times_s,
            song,
        };
        files.push(metrics::score_motion(
            &input,
            content.as_ref().map(|c| c.view()),
            &opts,
        )?);
        songs.push(input.song);
    }
    let mut reference = Vec::new();
    for source in sources(&args.reference)? {
        reference.push(metrics::reference_features(&source.load(args.fps)?, &opts)?);
    }
    let report = metrics::summarize(files, &songs, &reference, &opts)?;
    for w in &report.warnings {
        tracing::warn!("{w}");
    }
    if let Some(dir) = &args.features_out {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        metrics::write_feature_vectors(dir, &report)?;
    }
    let text = if args.json {
        format!("{}\n", serde_json::to_string(&report)?)
    } else {
        render_text(&report, have_beats)
    };
    super::print_stdout(&text)
}

fn show(v: Option<&SetValue>) -> String {
    match v {
        Some(SetValue::Value(x)) => format!("{x:.4}"),
        Some(SetValue::Undefined { undefined }) => format!("undefined ({undefined})"),
        None => "n/a (no --reference)".into(),
    }
}

fn opt(v: Option<f64>, why: &str) -> String {
    v.map_or_else(|| format!("n/a ({why})"), |x| format!("{x:.4}"))
}

fn render_file(out: &mut String, f: &FileMetrics, have_beats: bool) {
    let why = if have_beats {
        "no beats to score"
    } else {
        "no music beats"
    };
    let _ = writeln!(
        out,
        "{}: {} frames at {} fps, {} motion beats, bas_motion_beats {}, bas_music_beats {}, pfc {:.4}, skate_ratio {:.4}, foot_sliding {:.4} m{}",
        f.name,
        f.frames,
        f.fps,
        f.motion_beats,
        opt(f.bas_motion_beats, why),
        opt(f.bas_music_beats, why),
        f.pfc,
        f.skate_ratio,
        f.foot_sliding_m,
        f.tsi_m
            .map(|t| format!(", tsi {t:.4} m"))
            .unwrap_or_default()
    );
}

fn render_text(r: &EvalReport, have_beats: bool) -> String {
    let mut out = String::new();
    for f in &r.generated {
        render_file(&mut out, f, have_beats);
    }
    let s = &r.set;
    let why = if have_beats {
        "no motion scored"
    } else {
        "no music beats: give --music or --beats"
    };
    let _ = writeln!(
        out,
        "set: {} generated, {} reference",
        r.generated.len(),
        r.reference_count
    );
    let _ = writeln!(out, "  fid_k                {}", show(s.fid_k.as_ref()));
    let _ = writeln!(
        out,
        "  fid_k_fixed_accel    {}",
        show(s.fid_k_fixed_accel.as_ref())
    );
    let _ = writeln!(out, "  fid_g                {}", show(s.fid_g.as_ref()));
    let _ = writeln!(out, "  div_k                {}", show(Some(&s.div_k)));
    let _ = writeln!(out, "  div_g                {}", show(Some(&s.div_g)));
    let _ = writeln!(
        out,
        "  div_k_reference      {}",
        show(s.div_k_reference.as_ref())
    );
    let _ = writeln!(
        out,
        "  div_g_reference      {}",
        show(s.div_g_reference.as_ref())
    );
    let _ = writeln!(
        out,
        "  bas_motion_beats     {}",
        opt(s.bas_motion_beats, why)
    );
    let _ = writeln!(
        out,
        "  bas_music_beats      {}",
        opt(s.bas_music_beats, why)
    );
    let _ = writeln!(out, "  pfc                  {:.4}", s.pfc);
    let _ = writeln!(out, "  skate_ratio          {:.4}", s.skate_ratio);
    let _ = writeln!(out, "  foot_sliding_m       {:.4}", s.foot_sliding_m);
    if let Some(t) = s.tsi_m {
        let _ = writeln!(out, "  tsi_m                {t:.4}");
    }
    if let Some(m) = s.multimodality_k {
        let _ = writeln!(out, "  multimodality_k      {m:.4}");
    }
    let c = &r.conventions;
    let _ = writeln!(out, "conventions:");
    let _ = writeln!(out, "  features: {}", c.feature_frame_time);
    let _ = writeln!(out, "  bas: {}", c.bas);
    let _ = writeln!(out, "  fid_k: {}", c.kinetic_acceleration);
    let _ = writeln!(out, "  fid sqrtm: {}", c.fid_sqrtm);
    let _ = writeln!(out, "  z-scores: {}", c.zscore);
    out
}
