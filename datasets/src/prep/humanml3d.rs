//! `choreod prep humanml3d`: HumanML3D joints + captions → per-split shards of 263-dim features,
//! `Mean.npy` and `Std.npy`.
//!
//! Mean/Std follow `cal_mean_variance.ipynb`: over every frame of every written sequence (all
//! splits, mirrored copies included, as the notebook reads the whole `new_joint_vecs/`), std
//! averaged within [`crate::humanml3d::STD_GROUPS`]. Each shard stores its f64 sum, sum of
//! squares and frame count; Mean/Std are always computed from those, shard by shard in plan
//! order, so a resumed run, a merge of parts and a single run give the same bits.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use hdf5::types::VarLenUnicode;
use ndarray::{Array1, Array2, Array3, Axis};

use super::plan::{
    Candidate, MeanStdEntry, PrepOptions, PrepReport, Progress, RunHeader, SPLITS, ShardEntry,
    ShardJob, Skip, SkipReason, ensure_dir, finish_run, group, json_sha256, plan_run,
    read_name_list, read_text, run_plan,
};
use crate::checksum::sha256_file;
use crate::error::{Error, Result, h5_err, io_err};
use crate::formats::h5::{check_readable, open_checked, put, put_str, vlu};
use crate::humanml3d::{FEATURE_DIM, FeatureOptions, JOINTS, extract_features};
use crate::utc::now_utc;

/// Shortest sequence kept, frames at 20 fps: the t2m loaders' `min_motion_len = 40`
/// (EricGuo5513/text-to-motion `data/dataset.py`, ChenFengYe/motion-latent-diffusion
/// `mld/data/humanml/data/dataset.py`).
pub const HUMANML3D_MIN_FRAMES: usize = 40;
/// Longest sequence kept, frames: 20 minutes at 20 fps (HumanML3D clips are ≤ 10 s; raw AMASS
/// takes run to minutes), which bounds a shard's memory whatever the input.
pub const HUMANML3D_MAX_FRAMES: usize = 24_000;
/// HumanML3D frame rate (raw_pose_processing.ipynb downsamples to 20 fps).
const FPS: f32 = 20.0;
/// Sequences per shard by default: ≈ 60 MB shards for 7 s average sequences.
const DEFAULT_PER_SHARD: usize = 256;
/// Longest caption file accepted.
const MAX_TEXT_BYTES: u64 = 1 << 20;

/// Swap the words "left" and "right" (any case pattern of the first letter), as HumanML3D's
/// mirrored `M` captions do.
pub fn swap_left_right(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    let mut word = String::new();
    let flush = |word: &mut String, out: &mut String| {
        let swapped = match word.as_str() {
            "left" => "right",
            "right" => "left",
            "Left" => "Right",
            "Right" => "Left",
            "LEFT" => "RIGHT",
            "RIGHT" => "LEFT",
            w => w,
        };
        out.push_str(swapped);
        word.clear();
    };
    for ch in s.chars() {
        if ch.is_alphabetic() {
            word.push(ch);
        } else {
            flush(&mut word, &mut out);
            out.push(ch);
        }
    }
    flush(&mut word, &mut out);
    out
}

#[derive(Debug, Clone)]
struct Item {
    path: PathBuf,
    source: String,
    mirrored: bool,
    text: Option<PathBuf>,
}

#[derive(Debug)]
struct Caption {
    caption: String,
    tokens: String,
    start: f32,
    end: f32,
}

#[derive(Debug)]
struct Sequence {
    source: String,
    mirrored: bool,
    features: Array2<f32>,
    joints: Array3<f32>,
    captions: Vec<Caption>,
}

fn read_captions(path: &Path, mirrored: bool) -> Result<Vec<Caption>> {
    let len = std::fs::metadata(path).map_err(io_err(path))?.len();
    if len > MAX_TEXT_BYTES {
        return Err(Error::invalid(path, format!("{len} bytes of captions")));
    }
    let text = read_text(path)?;
    let mut out = Vec::new();
    for line in text.lines().map(str::trim).filter(|l| !l.is_empty()) {
        let f: Vec<&str> = line.split('#').collect();
        if f.len() < 4 {
            continue;
        }
        let num = |s: &str| {
            s.trim()
                .parse::<f32>()
                .ok()
                .filter(|v| v.is_finite())
                .unwrap_or(0.0)
        };
        let (caption, tokens) = if mirrored {
            (swap_left_right(f[0]), swap_left_right(f[1]))
        } else {
            (f[0].to_string(), f[1].to_string())
        };
        out.push(Caption {
            caption,
            tokens,
            start: num(f[2]),
            end: num(f[3]),
        });
    }
    Ok(out)
}

struct Job {
    features: FeatureOptions,
}

impl ShardJob for Job {
    type Item = Item;
    type Output = Sequence;

    fn process(&self, c: &Candidate<Item>) -> std::result::Result<Sequence, Skip> {
        let it = &c.item;
        let name = c.name.as_str();
        let corrupt = |e: String| Skip::new(name, SkipReason::Corrupt, e);
        let a = crate::formats::npy::read_npy(&it.path).map_err(|e| corrupt(e.to_string()))?;
        let sh = a.shape().to_vec();
        // Raw `joints/` files hold all SMPL-H joints; the notebook keeps `[:, :joints_num]`.
        if sh.len() != 3 || sh[1] < JOINTS || sh[2] != 3 {
            return Err(corrupt(format!(
                "{}: shape {sh:?}, expected (T, 22, 3)",
                it.path.display()
            )));
        }
        let joints = a
            .slice_axis(Axis(1), (0..JOINTS).into())
            .into_dimensionality::<ndarray::Ix3>()
            .map_err(|e| corrupt(e.to_string()))?
            .to_owned();
        if joints.iter().any(|v| !v.is_finite()) {
            return Err(Skip::new(
                name,
                SkipReason::NonFinite,
                it.path.display().to_string(),
            ));
        }
        if sh[0] < HUMANML3D_MIN_FRAMES {
            return Err(Skip::new(
                name,
                SkipReason::TooShort,
                format!("{} frames, need {HUMANML3D_MIN_FRAMES}", sh[0]),
            ));
        }
        if sh[0] > HUMANML3D_MAX_FRAMES {
            return Err(Skip::new(
                name,
                SkipReason::TooLong,
                format!("{} frames, more than {HUMANML3D_MAX_FRAMES}", sh[0]),
            ));
        }
        let joints = if it.mirrored {
            crate::humanml3d::mirror_joints(joints.view()).map_err(|e| corrupt(e.to_string()))?
        } else {
            joints
        };
        let fx = extract_features(joints.view(), &self.features)
            .map_err(|e| corrupt(e.with_path(&it.path).to_string()))?;
        if fx.features.iter().any(|v| !v.is_finite()) {
            return Err(Skip::new(
                name,
                SkipReason::NonFinite,
                "features contain NaN",
            ));
        }
        let captions = match &it.text {
            Some(p) => read_captions(p, it.mirrored).map_err(|e| corrupt(e.to_string()))?,
            None => Vec::new(),
        };
        Ok(Sequence {
            source: it.source.clone(),
            mirrored: it.mirrored,
            features: fx.features,
            joints: fx.global_positions,
            captions,
        })
    }

    fn write(&self, path: &Path, file: &hdf5::File, outputs: &[(String, Sequence)]) -> Result<u64> {
        put_str(path, file, "dataset", "humanml3d")?;
        put(path, file, "fps", FPS)?;
        // f64: millions of frames of squares; the merge must reproduce the single-run bits.
        let mut sum = vec![0.0f64; FEATURE_DIM];
        let mut sum_sq = vec![0.0f64; FEATURE_DIM];
        let mut frames = 0u64;
        for (name, q) in outputs {
            let g = group(path, file, name)?;
            put_str(path, &g, "name", name)?;
            put_str(path, &g, "source", &q.source)?;
            put(path, &g, "mirrored", u8::from(q.mirrored))?;
            let e = || h5_err(path);
            g.new_dataset_builder()
                .with_data(&q.features)
                .create("features")
                .map_err(e())?;
            g.new_dataset_builder()
                .with_data(&q.joints)
                .create("joints")
                .map_err(e())?;
            let caps: Vec<VarLenUnicode> = q
                .captions
                .iter()
                .map(|c| vlu(path, &c.caption))
                .collect::<Result<_>>()?;
            let toks: Vec<VarLenUnicode> = q
                .captions
                .iter()
                .map(|c| vlu(path, &c.tokens))
                .collect::<Result<_>>()?;
            let spans = Array2::from_shape_fn((q.captions.len(), 2), |(i, k)| {
                if k == 0 {
                    q.captions[i].start
                } else {
                    q.captions[i].end
                }
            });
            g.new_dataset_builder()
                .with_data(&Array1::from(caps))
                .create("captions")
                .map_err(e())?;
            g.new_dataset_builder()
                .with_data(&Array1::from(toks))
                .create("tokens")
                .map_err(e())?;
            g.new_dataset_builder()
                .with_data(&spans)
                .create("spans")
                .map_err(e())?;
            for row in q.features.axis_iter(Axis(0)) {
                for (d, v) in row.iter().enumerate() {
                    let v = f64::from(*v);
                    sum[d] += v;
                    sum_sq[d] += v * v;
                }
            }
            frames += q.features.nrows() as u64;
        }
        let st = group(path, file, "_stats")?;
        put(path, &st, "frames", frames)?;
        st.new_dataset_builder()
            .with_data(&Array1::from(sum))
            .create("sum")
            .map_err(h5_err(path))?;
        st.new_dataset_builder()
            .with_data(&Array1::from(sum_sq))
            .create("sum_sq")
            .map_err(h5_err(path))?;
        Ok(frames)
    }
}

/// Read the per-shard sums and write `Mean.npy` / `Std.npy` into `out_dir`.
pub(crate) fn write_mean_std(out_dir: &Path, entries: &[ShardEntry]) -> Result<MeanStdEntry> {
    let mut sum = vec![0.0f64; FEATURE_DIM];
    let mut sum_sq = vec![0.0f64; FEATURE_DIM];
    let mut n = 0u64;
    let mut sorted: Vec<&ShardEntry> = entries.iter().collect();
    sorted.sort_by_key(|e| e.global);
    for e in sorted {
        let path = out_dir.join(&e.file);
        let f = open_checked(&path)?;
        let st = f.group("_stats").map_err(h5_err(&path))?;
        let frames: u64 = st
            .attr("frames")
            .and_then(|a| a.read_scalar())
            .map_err(h5_err(&path))?;
        let read = |name: &str| -> Result<Array1<f64>> {
            let ds = st.dataset(name).map_err(h5_err(&path))?;
            check_readable(&path, &ds)?;
            ds.read_1d().map_err(h5_err(&path))
        };
        let (s, q) = (read("sum")?, read("sum_sq")?);
        if s.len() != FEATURE_DIM || q.len() != FEATURE_DIM {
            return Err(Error::invalid(&path, "_stats has the wrong width"));
        }
        for d in 0..FEATURE_DIM {
            sum[d] += s[d];
            sum_sq[d] += q[d];
        }
        n += frames;
    }
    let (mean, std) = crate::humanml3d::mean_std_from_sums(&sum, &sum_sq, n)?;
    let mp = out_dir.join("Mean.npy");
    let sp = out_dir.join("Std.npy");
    crate::formats::npy::write_npy(&mp, mean.view().into_dyn())?;
    crate::formats::npy::write_npy(&sp, std.view().into_dyn())?;
    Ok(MeanStdEntry {
        mean_file: "Mean.npy".to_string(),
        std_file: "Std.npy".to_string(),
        frames: n,
        mean_sha256: sha256_file(&mp)?,
        std_sha256: sha256_file(&sp)?,
    })
}

/// Prepare HumanML3D at `root` into `out_dir`; see the module docs of [`crate::prep`].
///
/// Input: `new_joints/*.npy` (or `joints/*.npy`), `texts/<id>.txt`, `train.txt` / `val.txt` /
/// `test.txt`. Fatal errors: no joints folder, unreadable split lists, an output directory of
/// other parameters, write failures.
pub fn prepare_humanml3d(
    root: &Path,
    out_dir: &Path,
    opts: &PrepOptions,
    progress: &(dyn Fn(Progress) + Sync),
) -> Result<PrepReport> {
    let started_utc = now_utc();
    let joints_dir = ["new_joints", "joints"]
        .iter()
        .map(|d| root.join(d))
        .find(|p| p.is_dir())
        .ok_or_else(|| Error::invalid(root, "neither new_joints/ nor joints/ exists"))?;
    let mut files: Vec<(String, PathBuf)> = Vec::new();
    for e in std::fs::read_dir(&joints_dir).map_err(io_err(&joints_dir))? {
        let p = e.map_err(io_err(&joints_dir))?.path();
        if p.extension().is_some_and(|x| x == "npy")
            && let Some(stem) = p.file_stem()
        {
            files.push((stem.to_string_lossy().into_owned(), p));
        }
    }
    files.sort();
    let mut split_of: BTreeMap<String, &'static str> = BTreeMap::new();
    let mut notes = Vec::new();
    for split in SPLITS {
        for n in read_name_list(&root.join(format!("{split}.txt")))? {
            if let Some(prev) = split_of.insert(n.clone(), split) {
                notes.push(format!(
                    "{n} is listed in {prev} and {split}; using {split}"
                ));
            }
        }
    }
    let have: BTreeSet<&str> = files.iter().map(|(n, _)| n.as_str()).collect();
    let texts = root.join("texts");
    let mut skips = Vec::new();
    // An id a split list names without its motion file is reported, not silently dropped; with
    // --mirror an `M` id is made from its unmirrored file.
    for (name, split) in &split_of {
        let made_by_mirror = opts.mirror
            && name
                .strip_prefix('M')
                .is_some_and(|base| have.contains(base));
        if !have.contains(name.as_str()) && !made_by_mirror {
            skips.push(Skip::new(
                name,
                SkipReason::MissingMotion,
                format!(
                    "listed in {split}.txt, no {}",
                    joints_dir.join(format!("{name}.npy")).display()
                ),
            ));
        }
    }
    let mut no_text = 0usize;
    let mut by_split: BTreeMap<&'static str, Vec<Candidate<Item>>> = BTreeMap::new();
    for (name, path) in &files {
        // `_stats` is the shard's own group; ids are digits (optionally M-prefixed).
        if name.starts_with('_') {
            skips.push(Skip::new(
                name,
                SkipReason::BadName,
                "names starting with _ are reserved",
            ));
            continue;
        }
        let Some(split) = split_of.get(name).copied() else {
            skips.push(Skip::new(
                name,
                SkipReason::NotInSplit,
                "train/val/test.txt",
            ));
            continue;
        };
        let text = texts.join(format!("{name}.txt"));
        let text = if text.is_file() {
            Some(text)
        } else {
            no_text += 1;
            None
        };
        let mut push = |n: String, mirrored: bool| {
            by_split.entry(split).or_default().push(Candidate {
                name: n,
                item: Item {
                    path: path.clone(),
                    source: name.clone(),
                    mirrored,
                    text: text.clone(),
                },
            })
        };
        push(name.clone(), false);
        // An input that already holds the M copy keeps it instead of a second mirror.
        let m = format!("M{name}");
        if opts.mirror && !name.starts_with('M') && !have.contains(m.as_str()) {
            push(m, true);
        }
    }
    if no_text > 0 {
        notes.push(format!(
            "{no_text} sequences have no texts/<id>.txt (stored without captions)"
        ));
    }
    let (per_shard, shards, inputs_sha256) = plan_run(by_split, opts, DEFAULT_PER_SHARD);
    let features = FeatureOptions::default();
    let parameters = serde_json::json!({
        "dataset": "humanml3d",
        "sequences_per_shard": per_shard,
        "fps": FPS,
        "min_frames": HUMANML3D_MIN_FRAMES,
        "max_frames": HUMANML3D_MAX_FRAMES,
        "mirror": opts.mirror,
        "joints_dir": joints_dir.file_name().map(|n| n.to_string_lossy().into_owned()),
        "features": {
            "uniform_skeleton": features.target_offsets.is_some(),
            "feet_threshold": features.feet_threshold,
            "smooth_sigma": features.smooth_sigma,
            "fix_heading_wrap": features.fix_heading_wrap,
        },
        "mean_std": "all written frames, std averaged in groups [0,1) [1,3) [3,4) [4,67) [67,193) [193,259) [259,263)",
        "inputs_sha256": inputs_sha256,
    });
    let params_sha = json_sha256(&parameters);
    ensure_dir(out_dir)?;
    let job = Job { features };
    let outcome = run_plan(&job, &shards, out_dir, &params_sha, opts, progress)?;
    // A part writes no Mean/Std: `merge` computes them from all parts' sums. A run where no
    // sequence survived has none either: `finish_run` says why.
    let stored: usize = outcome.entries.iter().map(|e| e.sequences).sum();
    let mean_std = if opts.part.is_whole() && outcome.complete && stored > 0 {
        Some(write_mean_std(out_dir, &outcome.entries)?)
    } else {
        None
    };
    let header = RunHeader {
        dataset: "humanml3d",
        parameters,
        parameters_sha256: params_sha,
        started_utc,
        files_found: files.len(),
        notes,
    };
    finish_run(
        out_dir, opts.part, header, &shards, outcome, skips, mean_std,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array2;

    #[test]
    fn left_and_right_swap_as_words_only() {
        assert_eq!(
            swap_left_right("a person turns left/VERB then Right, leftover"),
            "a person turns right/VERB then Left, leftover"
        );
    }

    #[test]
    fn finalize_matches_the_crate_mean_std() {
        let a = Array2::from_shape_fn((50, FEATURE_DIM), |(t, d)| {
            ((t * 7 + d * 3) % 11) as f32 * 0.1 + d as f32
        });
        let b = Array2::from_shape_fn((30, FEATURE_DIM), |(t, d)| ((t * 5 + d) % 13) as f32 * 0.2);
        let (m0, s0) = crate::humanml3d::mean_std([a.view(), b.view()]).unwrap();
        let mut sum = vec![0.0f64; FEATURE_DIM];
        let mut sq = vec![0.0f64; FEATURE_DIM];
        for x in [&a, &b] {
            for row in x.rows() {
                for (d, v) in row.iter().enumerate() {
                    sum[d] += f64::from(*v);
                    sq[d] += f64::from(*v) * f64::from(*v);
                }
            }
        }
        let (m1, s1) = crate::humanml3d::mean_std_from_sums(&sum, &sq, 80).unwrap();
        // Same f64 sums in the same order, so equal to the last bit.
        assert_eq!(m0, m1);
        assert_eq!(s0, s1);
        // Grouped: every dim of a group has the same std.
        assert_eq!(s1[4], s1[66]);
        assert!(crate::humanml3d::mean_std_from_sums(&sum, &sq, 0).is_err());
    }
}
