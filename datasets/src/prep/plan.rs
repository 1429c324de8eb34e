//! The machinery both preparations share: options, the shard plan, atomic shard files with
//! sidecars (resume), the manifest, progress and skip records.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

use choreo_dsp::atomic::{commit_atomic, temp_path, write_atomic};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::checksum::{hex, sha256_file};
use crate::error::{Error, Result, h5_err, io_err};
use crate::formats::h5::{put, put_str};

/// `format` attribute at the root of every shard file.
pub const SHARD_FORMAT: &str = "choreod-prep-shard";
/// Version of the shard layout.
pub const SHARD_VERSION: i32 = 1;
/// `format` field of the manifest.
pub const MANIFEST_FORMAT: &str = "choreod-prep-manifest";
/// Version of the manifest layout.
pub const MANIFEST_VERSION: u32 = 1;
/// Splits in plan order.
pub(crate) const SPLITS: [&str; 3] = ["train", "val", "test"];
/// Longest split/ignore list accepted (the real ones are < 1 MB).
pub(crate) const MAX_LIST_BYTES: u64 = 64 * 1024 * 1024;

/// Which part of the work one machine does: output shards whose global number is
/// `≡ index (mod count)`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Part {
    /// This machine's number, `0..count`.
    pub index: usize,
    /// Number of machines.
    pub count: usize,
}

impl Default for Part {
    fn default() -> Self {
        Part { index: 0, count: 1 }
    }
}

impl Part {
    /// A part, checked: `count ≥ 1` and `index < count`; the error says why not.
    pub fn new(index: usize, count: usize) -> std::result::Result<Self, String> {
        if count == 0 || index >= count {
            return Err(format!("{index}/{count}: need 0 <= I < N and N >= 1"));
        }
        Ok(Part { index, count })
    }

    /// Whether this part is the whole job.
    pub fn is_whole(&self) -> bool {
        self.count == 1
    }

    /// Whether this part writes the shard with global number `global`.
    pub fn owns(&self, global: usize) -> bool {
        global % self.count == self.index
    }

    /// The manifest file name of this part.
    pub fn manifest_name(&self) -> String {
        if self.is_whole() {
            "manifest.json".to_string()
        } else {
            format!("manifest.part-{}-of-{}.json", self.index, self.count)
        }
    }
}

/// Parse `I/N` (as in `--shard 3/8`).
impl std::str::FromStr for Part {
    type Err = String;

    fn from_str(s: &str) -> std::result::Result<Self, String> {
        let bad = || format!("{s:?}: expected I/N, e.g. 0/4");
        let (i, n) = s.split_once('/').ok_or_else(bad)?;
        let i = i.trim().parse().map_err(|_| bad())?;
        let n = n.trim().parse().map_err(|_| bad())?;
        Part::new(i, n)
    }
}

impl std::fmt::Display for Part {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}", self.index, self.count)
    }
}

/// Knobs of a preparation run.
#[derive(Debug, Clone, Default)]
#[non_exhaustive]
pub struct PrepOptions {
    /// Worker threads; 0 = one per core. Default: 0.
    pub jobs: usize,
    /// The part of the work this machine does (`--shard I/N`). Default: 0/1 (everything).
    pub part: Part,
    /// Sequences per shard file; 0 = the dataset's default (AIST++ 64, HumanML3D 256).
    /// Default: 0.
    pub sequences_per_shard: usize,
    /// AIST++ only: folder of `<music id>.wav`; `None` = `ROOT/music`. Default: None.
    pub music_dir: Option<PathBuf>,
    /// HumanML3D only: also write the mirrored `M<id>` copy of each sequence. Default: false.
    pub mirror: bool,
    /// Stop after writing this many shards (a budgeted run; a rerun continues). Default: None.
    pub max_shards: Option<usize>,
    /// AIST++ only: also write each sequence's fact35 music features (`choreo_dsp`'s 35
    /// librosa columns) as this librosa computes them. Default: None.
    pub fact35: Option<choreo_dsp::LibrosaVersion>,
}

/// A progress report: `done` of `total` units of `stage` ("music", "sequences").
#[derive(Debug, Clone, Copy)]
#[non_exhaustive]
pub struct Progress {
    /// What is being counted.
    pub stage: &'static str,
    /// Units finished.
    pub done: usize,
    /// Units in this stage.
    pub total: usize,
}

/// Why a sequence was left out.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
#[non_exhaustive]
pub enum SkipReason {
    /// Listed in the dataset's ignore list.
    Ignored,
    /// In none of the split lists.
    NotInSplit,
    /// The name does not follow the dataset's naming scheme.
    BadName,
    /// No music file for the sequence's music id.
    MissingMusic,
    /// Listed in a split list, but its motion file is not there.
    MissingMotion,
    /// The music file exists but cannot be decoded.
    MusicUnreadable,
    /// The motion file cannot be read (truncated, wrong type or shape).
    Corrupt,
    /// Fewer frames than the minimum.
    TooShort,
    /// More frames than any take of the dataset has (a hostile or mislabelled file); bounds the
    /// memory a shard needs.
    TooLong,
    /// NaN or infinity in the motion.
    NonFinite,
}

impl std::fmt::Display for SkipReason {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            SkipReason::Ignored => "in the ignore list",
            SkipReason::NotInSplit => "in no split list",
            SkipReason::BadName => "bad name",
            SkipReason::MissingMusic => "missing music",
            SkipReason::MissingMotion => "missing motion file",
            SkipReason::MusicUnreadable => "music unreadable",
            SkipReason::Corrupt => "corrupt file",
            SkipReason::TooShort => "too short",
            SkipReason::TooLong => "too long",
            SkipReason::NonFinite => "NaN or infinity",
        })
    }
}

/// One sequence left out, and why.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize)]
pub struct Skip {
    /// Sequence name.
    pub name: String,
    /// The reason class.
    pub reason: SkipReason,
    /// Specifics (the error message, the frame count...).
    pub detail: String,
}

impl Skip {
    pub(crate) fn new(name: &str, reason: SkipReason, detail: impl Into<String>) -> Self {
        Skip {
            name: name.to_string(),
            reason,
            detail: detail.into(),
        }
    }
}

/// One finished shard file.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ShardEntry {
    /// File name inside the output directory (`train-00003.h5`).
    pub file: String,
    /// Split.
    pub split: String,
    /// Number within the split.
    pub index: usize,
    /// Number over all splits (the unit `--shard I/N` distributes).
    pub global: usize,
    /// Sequences stored.
    pub sequences: usize,
    /// Frames stored (30 fps frames for AIST++, feature frames for HumanML3D).
    pub frames: u64,
    /// File size.
    pub bytes: u64,
    /// sha256 of the file, lowercase hex.
    pub sha256: String,
}

/// The sidecar `<shard>.json` written after the shard: the proof it is complete.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub(crate) struct Sidecar {
    pub parameters_sha256: String,
    pub shard: ShardEntry,
    pub names: Vec<String>,
    pub skips: Vec<Skip>,
}

/// Counts of one split.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct SplitCounts {
    /// Shards in the whole plan (over all parts).
    pub planned_shards: usize,
    /// Shards in this manifest.
    pub shards: usize,
    /// Sequences in this manifest's shards.
    pub sequences: usize,
    /// Frames in this manifest's shards.
    pub frames: u64,
}

/// Mean/Std files of a HumanML3D preparation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MeanStdEntry {
    /// `Mean.npy`.
    pub mean_file: String,
    /// `Std.npy`.
    pub std_file: String,
    /// Feature frames they were computed from.
    pub frames: u64,
    /// sha256 of `Mean.npy`.
    pub mean_sha256: String,
    /// sha256 of `Std.npy`.
    pub std_sha256: String,
}

/// The manifest (`manifest.json`, or `manifest.part-I-of-N.json` for a part).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Manifest {
    /// [`MANIFEST_FORMAT`].
    pub format: String,
    /// [`MANIFEST_VERSION`].
    pub format_version: u32,
    /// `aistpp` or `humanml3d`.
    pub dataset: String,
    /// choreod version that wrote it.
    pub tool_version: String,
    /// Everything that determines the shard contents (options, feature parameters, input list).
    pub parameters: serde_json::Value,
    /// sha256 of `parameters` as compact JSON: runs (and parts) with equal values are compatible.
    pub parameters_sha256: String,
    /// The part this manifest covers.
    pub part: Part,
    /// Whether every shard of `part` is present.
    pub complete: bool,
    /// UTC start of the run (or merge).
    pub started_utc: String,
    /// UTC end.
    pub finished_utc: String,
    /// Motion files found in the input.
    pub files_found: usize,
    /// Per split counts.
    pub splits: BTreeMap<String, SplitCounts>,
    /// The shard files, in plan order.
    pub shards: Vec<ShardEntry>,
    /// Every sequence left out, sorted by name.
    pub skips: Vec<Skip>,
    /// Warnings that did not skip anything (missing captions, split entries without a file).
    pub notes: Vec<String>,
    /// HumanML3D: Mean.npy / Std.npy (absent for a part: `merge` writes them).
    pub mean_std: Option<MeanStdEntry>,
}

/// What a preparation run did.
#[derive(Debug, Clone)]
#[non_exhaustive]
pub struct PrepReport {
    /// Where the manifest was written.
    pub manifest_path: PathBuf,
    /// The manifest.
    pub manifest: Manifest,
    /// Shards written by this run.
    pub shards_written: usize,
    /// Finished shards found from an earlier run and kept.
    pub shards_reused: usize,
}

/// One input sequence planned into a shard.
#[derive(Debug, Clone)]
pub(crate) struct Candidate<T> {
    pub name: String,
    pub item: T,
}

/// One shard of the plan.
#[derive(Debug)]
pub(crate) struct PlannedShard<T> {
    pub split: &'static str,
    pub index: usize,
    pub global: usize,
    pub items: Vec<Candidate<T>>,
}

impl<T> PlannedShard<T> {
    pub fn file_name(&self) -> String {
        format!("{}-{:05}.h5", self.split, self.index)
    }
}

/// The shard plan of a run: `opts.sequences_per_shard` (0 = the dataset's `default_per_shard`),
/// the shards, and the sha256 of the input listing (split and name of every candidate, in plan
/// order) that goes into the run's parameters.
pub(crate) fn plan_run<T>(
    by_split: BTreeMap<&'static str, Vec<Candidate<T>>>,
    opts: &PrepOptions,
    default_per_shard: usize,
) -> (usize, Vec<PlannedShard<T>>, String) {
    let per_shard = match opts.sequences_per_shard {
        0 => default_per_shard,
        n => n,
    };
    let listing: Vec<String> = by_split
        .iter()
        .flat_map(|(s, v)| v.iter().map(move |c| format!("{s}\t{}", c.name)))
        .collect();
    (
        per_shard,
        make_plan(by_split, per_shard),
        lines_sha256(&listing),
    )
}

/// Cut sorted candidates per split into shards of `per_shard`, numbered over all splits.
pub(crate) fn make_plan<T>(
    mut by_split: BTreeMap<&'static str, Vec<Candidate<T>>>,
    per_shard: usize,
) -> Vec<PlannedShard<T>> {
    let per_shard = per_shard.max(1);
    let mut out = Vec::new();
    for split in SPLITS {
        let mut items = by_split.remove(split).unwrap_or_default();
        items.sort_by(|a, b| a.name.cmp(&b.name));
        let mut index = 0;
        while !items.is_empty() {
            let rest = items.split_off(per_shard.min(items.len()));
            let global = out.len();
            out.push(PlannedShard {
                split,
                index,
                global,
                items,
            });
            items = rest;
            index += 1;
        }
    }
    out
}

/// sha256 of compact JSON, hex.
pub(crate) fn json_sha256(v: &serde_json::Value) -> String {
    hex(&Sha256::digest(v.to_string().as_bytes()))
}

/// sha256 of lines (each followed by a newline), hex.
pub(crate) fn lines_sha256(lines: &[String]) -> String {
    let mut h = Sha256::new();
    for l in lines {
        h.update(l.as_bytes());
        h.update(b"\n");
    }
    hex(&h.finalize())
}

/// Read a small text file (split list, ignore list, captions), bounded.
pub(crate) fn read_text(path: &Path) -> Result<String> {
    let len = std::fs::metadata(path).map_err(io_err(path))?.len();
    if len > MAX_LIST_BYTES {
        return Err(Error::invalid(
            path,
            format!("{len} bytes: larger than the {MAX_LIST_BYTES} accepted for a text list"),
        ));
    }
    let bytes = std::fs::read(path).map_err(io_err(path))?;
    String::from_utf8(bytes).map_err(|e| Error::invalid(path, format!("not UTF-8: {e}")))
}

/// Names in a list file, one per line (blank lines and surrounding spaces ignored).
pub(crate) fn read_name_list(path: &Path) -> Result<Vec<String>> {
    Ok(read_text(path)?
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty())
        .map(str::to_string)
        .collect())
}

/// Create a group without modification times (they would make equal inputs give different bytes).
pub(crate) fn group(path: &Path, parent: &hdf5::Group, name: &str) -> Result<hdf5::Group> {
    parent
        .create_group_builder()
        .obj_track_times(false)
        .create(name)
        .map_err(h5_err(path))
}

/// Dataset-specific half of a run: turn one candidate into stored data, and store a shard.
pub(crate) trait ShardJob: Sync {
    type Item: Sync;
    type Output: Send;
    /// Read and compute one sequence; `Err` is a skip, not a failure of the run.
    fn process(&self, c: &Candidate<Self::Item>) -> std::result::Result<Self::Output, Skip>;
    /// Write the sequences of one shard into `file`; returns the frames stored.
    fn write(
        &self,
        path: &Path,
        file: &hdf5::File,
        outputs: &[(String, Self::Output)],
    ) -> Result<u64>;
}

/// What [`run_plan`] did.
#[derive(Debug, Default)]
pub(crate) struct RunOutcome {
    pub entries: Vec<ShardEntry>,
    pub skips: Vec<Skip>,
    pub written: usize,
    pub reused: usize,
    pub complete: bool,
}

/// The sidecar of a finished shard, if it is there and valid for these parameters.
/// A sidecar for other parameters is a fatal error: mixing runs would corrupt the dataset.
pub(crate) fn finished(out_dir: &Path, file: &str, params_sha: &str) -> Result<Option<Sidecar>> {
    let side = out_dir.join(format!("{file}.json"));
    if !side.exists() {
        return Ok(None);
    }
    let text = read_text(&side)?;
    let Ok(sc) = serde_json::from_str::<Sidecar>(&text) else {
        // A damaged sidecar means an unfinished shard: redo it.
        return Ok(None);
    };
    if sc.parameters_sha256 != params_sha {
        return Err(Error::invalid(
            &side,
            "written with different parameters or inputs; use a new output directory",
        ));
    }
    let shard = out_dir.join(file);
    match std::fs::metadata(&shard) {
        Ok(m) if m.len() == sc.shard.bytes => Ok(Some(sc)),
        _ => Ok(None),
    }
}

/// Remove this process's (or a killed earlier run's) temporaries of a shard we are about to write.
fn remove_stale_temps(out_dir: &Path, file: &str) {
    let prefix = format!(".{file}.tmp-");
    let side_prefix = format!(".{file}.json.tmp-");
    if let Ok(rd) = std::fs::read_dir(out_dir) {
        for e in rd.flatten() {
            let n = e.file_name().to_string_lossy().into_owned();
            if n.starts_with(&prefix) || n.starts_with(&side_prefix) {
                let _ = std::fs::remove_file(e.path());
            }
        }
    }
}

/// Run the plan: skip finished shards, process and write the rest in parallel.
pub(crate) fn run_plan<J: ShardJob>(
    job: &J,
    shards: &[PlannedShard<J::Item>],
    out_dir: &Path,
    params_sha: &str,
    opts: &PrepOptions,
    progress: &(dyn Fn(Progress) + Sync),
) -> Result<RunOutcome> {
    let mine: Vec<&PlannedShard<J::Item>> =
        shards.iter().filter(|s| opts.part.owns(s.global)).collect();
    let mut done: Vec<Option<Sidecar>> = Vec::with_capacity(mine.len());
    for s in &mine {
        done.push(finished(out_dir, &s.file_name(), params_sha)?);
    }
    let pending: Vec<&PlannedShard<J::Item>> = mine
        .iter()
        .zip(&done)
        .filter(|(_, d)| d.is_none())
        .map(|(s, _)| *s)
        .collect();
    let total: usize = pending.iter().map(|s| s.items.len()).sum();
    let counter = AtomicUsize::new(0);
    let started = AtomicUsize::new(0);
    progress(Progress {
        stage: "sequences",
        done: 0,
        total,
    });
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(opts.jobs)
        .build()
        .map_err(|source| Error::ThreadPool {
            threads: opts.jobs,
            source,
        })?;
    let written: Vec<Option<Sidecar>> = pool.install(|| {
        pending
            .par_iter()
            .map(|s| -> Result<Option<Sidecar>> {
                if let Some(max) = opts.max_shards
                    && started.fetch_add(1, Ordering::SeqCst) >= max
                {
                    return Ok(None);
                }
                let file = s.file_name();
                remove_stale_temps(out_dir, &file);
                let results: Vec<std::result::Result<J::Output, Skip>> = s
                    .items
                    .par_iter()
                    .map(|c| {
                        let r = job.process(c);
                        let d = counter.fetch_add(1, Ordering::Relaxed) + 1;
                        progress(Progress {
                            stage: "sequences",
                            done: d,
                            total,
                        });
                        r
                    })
                    .collect();
                let mut outputs = Vec::new();
                let mut skips = Vec::new();
                for (c, r) in s.items.iter().zip(results) {
                    match r {
                        Ok(o) => outputs.push((c.name.clone(), o)),
                        Err(k) => {
                            // info, not warn: the end-of-run report lists every skip anyway.
                            tracing::info!(sequence = %k.name, reason = %k.reason, detail = %k.detail, "skipped");
                            skips.push(k);
                        }
                    }
                }
                let entry = write_shard(job, out_dir, s, &outputs)?;
                tracing::info!(shard = %entry.file, sequences = entry.sequences, frames = entry.frames, "shard written");
                let sc = Sidecar {
                    parameters_sha256: params_sha.to_string(),
                    shard: entry,
                    names: outputs.iter().map(|(n, _)| n.clone()).collect(),
                    skips,
                };
                let side = out_dir.join(format!("{file}.json"));
                let text = serde_json::to_string_pretty(&sc)
                    .map_err(|e| Error::invalid(&side, format!("serialising: {e}")))?;
                write_atomic(&side, text.as_bytes()).map_err(io_err(&side))?;
                Ok(Some(sc))
            })
            .collect::<Result<Vec<_>>>()
    })?;
    let mut out = RunOutcome {
        complete: true,
        ..RunOutcome::default()
    };
    let mut fresh = pending.iter().zip(written);
    for (s, d) in mine.iter().zip(done) {
        let sc = match d {
            Some(sc) => {
                out.reused += 1;
                Some(sc)
            }
            None => {
                let (p, w) = fresh
                    .next()
                    .ok_or_else(|| Error::motion("internal: shard bookkeeping out of step"))?;
                debug_assert_eq!(p.global, s.global);
                if w.is_some() {
                    out.written += 1;
                }
                w
            }
        };
        match sc {
            Some(sc) => {
                out.entries.push(sc.shard);
                out.skips.extend(sc.skips);
            }
            None => out.complete = false,
        }
    }
    Ok(out)
}

fn write_shard<J: ShardJob>(
    job: &J,
    out_dir: &Path,
    s: &PlannedShard<J::Item>,
    outputs: &[(String, J::Output)],
) -> Result<ShardEntry> {
    let file_name = s.file_name();
    let path = out_dir.join(&file_name);
    let tmp = temp_path(&path);
    let res = (|| {
        let frames = {
            let file = crate::formats::h5::h5_writer()
                .with_fcpl(|p| p.obj_track_times(false))
                .create(&tmp)
                .map_err(h5_err(&tmp))?;
            put_str(&path, &file, "format", SHARD_FORMAT)?;
            put(&path, &file, "format_version", SHARD_VERSION)?;
            put_str(&path, &file, "split", s.split)?;
            put(&path, &file, "shard_index", s.index as u64)?;
            put(&path, &file, "shard_global", s.global as u64)?;
            put(&path, &file, "sequences", outputs.len() as u64)?;
            let frames = job.write(&path, &file, outputs)?;
            file.flush().map_err(h5_err(&tmp))?;
            frames
        };
        commit_atomic(&tmp, &path).map_err(io_err(&path))?;
        Ok(frames)
    })();
    let frames = match res {
        Ok(f) => f,
        Err(e) => {
            let _ = std::fs::remove_file(&tmp);
            return Err(e);
        }
    };
    let bytes = std::fs::metadata(&path).map_err(io_err(&path))?.len();
    Ok(ShardEntry {
        file: file_name,
        split: s.split.to_string(),
        index: s.index,
        global: s.global,
        sequences: outputs.len(),
        frames,
        bytes,
        sha256: sha256_file(&path)?,
    })
}

/// Per-split counts of a manifest's shards, with the planned totals.
pub(crate) fn split_counts(
    entries: &[ShardEntry],
    planned: &BTreeMap<String, usize>,
) -> BTreeMap<String, SplitCounts> {
    let mut out: BTreeMap<String, SplitCounts> = BTreeMap::new();
    for (split, n) in planned {
        out.entry(split.clone()).or_default().planned_shards = *n;
    }
    for e in entries {
        let c = out.entry(e.split.clone()).or_default();
        c.shards += 1;
        c.sequences += e.sequences;
        c.frames += e.frames;
    }
    out
}

/// Planned shards per split.
pub(crate) fn planned_per_split<T>(shards: &[PlannedShard<T>]) -> BTreeMap<String, usize> {
    let mut m = BTreeMap::new();
    for s in shards {
        *m.entry(s.split.to_string()).or_insert(0) += 1;
    }
    m
}

/// What a dataset run knows about itself besides its shards, for the manifest.
pub(crate) struct RunHeader {
    /// `aistpp` or `humanml3d`.
    pub dataset: &'static str,
    pub parameters: serde_json::Value,
    pub parameters_sha256: String,
    pub started_utc: String,
    pub files_found: usize,
    pub notes: Vec<String>,
}

/// Write the manifest of a run (complete or not) and report it. `skips` are the sequences left
/// out before the shards ran; the shards' own skips come from `outcome`.
pub(crate) fn finish_run<T>(
    out_dir: &Path,
    part: Part,
    header: RunHeader,
    plan: &[PlannedShard<T>],
    outcome: RunOutcome,
    mut skips: Vec<Skip>,
    mean_std: Option<MeanStdEntry>,
) -> Result<PrepReport> {
    skips.extend(outcome.skips);
    skips.sort();
    let planned = planned_per_split(plan);
    let manifest = Manifest {
        format: MANIFEST_FORMAT.to_string(),
        format_version: MANIFEST_VERSION,
        dataset: header.dataset.to_string(),
        tool_version: env!("CARGO_PKG_VERSION").to_string(),
        parameters: header.parameters,
        parameters_sha256: header.parameters_sha256,
        part,
        complete: outcome.complete,
        started_utc: header.started_utc,
        finished_utc: crate::utc::now_utc(),
        files_found: header.files_found,
        splits: split_counts(&outcome.entries, &planned),
        shards: outcome.entries,
        skips,
        notes: header.notes,
        mean_std,
    };
    let manifest_path = write_manifest(out_dir, &manifest)?;
    let stored: usize = manifest.shards.iter().map(|s| s.sequences).sum();
    if part.is_whole() && manifest.complete && stored == 0 {
        return Err(Error::invalid(
            &manifest_path,
            format!(
                "no sequence survived: {} skipped ({}), each listed under \"skips\" here",
                manifest.skips.len(),
                skip_summary(&manifest.skips)
            ),
        ));
    }
    Ok(PrepReport {
        manifest_path,
        manifest,
        shards_written: outcome.written,
        shards_reused: outcome.reused,
    })
}

/// How many skips of each reason, most first: `2 too short, 1 missing motion file`.
fn skip_summary(skips: &[Skip]) -> String {
    let mut by_reason: BTreeMap<SkipReason, usize> = BTreeMap::new();
    for s in skips {
        *by_reason.entry(s.reason).or_default() += 1;
    }
    let mut counts: Vec<(SkipReason, usize)> = by_reason.into_iter().collect();
    counts.sort_by_key(|c| std::cmp::Reverse(c.1));
    let parts: Vec<String> = counts.iter().map(|(r, n)| format!("{n} {r}")).collect();
    if parts.is_empty() {
        "no input sequence found".to_string()
    } else {
        parts.join(", ")
    }
}

/// Write the manifest of `part` into `out_dir`.
pub(crate) fn write_manifest(out_dir: &Path, m: &Manifest) -> Result<PathBuf> {
    let path = out_dir.join(m.part.manifest_name());
    let text = serde_json::to_string_pretty(m)
        .map_err(|e| Error::invalid(&path, format!("serialising: {e}")))?;
    write_atomic(&path, text.as_bytes()).map_err(io_err(&path))?;
    Ok(path)
}

/// Create the output directory.
pub(crate) fn ensure_dir(dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(io_err(dir))
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array1;

    /// Items are numbers; negative ones are skipped, the rest stored as a small dataset.
    struct Fake;

    impl ShardJob for Fake {
        type Item = i32;
        type Output = Array1<f32>;

        fn process(&self, c: &Candidate<i32>) -> std::result::Result<Array1<f32>, Skip> {
            if c.item < 0 {
                return Err(Skip::new(&c.name, SkipReason::TooShort, "negative"));
            }
            Ok(Array1::from_shape_fn(c.item as usize + 1, |i| {
                i as f32 * 0.5
            }))
        }

        fn write(
            &self,
            path: &Path,
            file: &hdf5::File,
            outputs: &[(String, Array1<f32>)],
        ) -> Result<u64> {
            let mut frames = 0;
            for (name, a) in outputs {
                let g = group(path, file, name)?;
                put_str(path, &g, "name", name)?;
                g.new_dataset_builder()
                    .with_data(a)
                    .create("x")
                    .map_err(h5_err(path))?;
                frames += a.len() as u64;
            }
            Ok(frames)
        }
    }

    fn fake_plan() -> Vec<PlannedShard<i32>> {
        let mut m = BTreeMap::new();
        let items = (0..11)
            .map(|i| Candidate {
                name: format!("s{i:02}"),
                item: if i == 4 { -1 } else { i },
            })
            .collect();
        m.insert("train", items);
        m.insert(
            "val",
            vec![Candidate {
                name: "v".to_string(),
                item: 3,
            }],
        );
        make_plan(m, 3)
    }

    fn run(dir: &Path, opts: &PrepOptions, params: &str) -> Result<RunOutcome> {
        run_plan(&Fake, &fake_plan(), dir, params, opts, &|_| {})
    }

    #[test]
    fn runs_are_byte_identical_resumable_and_refuse_other_parameters() {
        let a = tempfile::tempdir().unwrap();
        let b = tempfile::tempdir().unwrap();
        let full = run(a.path(), &PrepOptions::default(), "p1").unwrap();
        assert!(full.complete);
        assert_eq!((full.written, full.reused, full.entries.len()), (5, 0, 5));
        assert_eq!(full.skips.len(), 1);
        assert_eq!(full.skips[0].name, "s04");
        assert_eq!(
            full.entries[1].sequences, 2,
            "the skipped s04 leaves shard 1 with 2"
        );
        assert_eq!(full.entries[4].file, "val-00000.h5");
        assert_eq!(full.entries[4].global, 4);

        // A budgeted run stops early, then a rerun finishes; same bytes as the single run.
        let opts = PrepOptions {
            jobs: 1,
            max_shards: Some(2),
            ..PrepOptions::default()
        };
        let first = run(b.path(), &opts, "p1").unwrap();
        assert!(!first.complete);
        assert_eq!(first.written, 2);
        let rest = run(b.path(), &PrepOptions::default(), "p1").unwrap();
        assert!(rest.complete);
        assert_eq!((rest.written, rest.reused), (3, 2));
        assert_eq!(rest.entries, full.entries, "sha256, sizes and counts equal");
        for e in &full.entries {
            assert_eq!(sha256_file(&b.path().join(&e.file)).unwrap(), e.sha256);
        }

        // A shard whose sidecar is damaged is redone, to the same bytes.
        std::fs::write(b.path().join("train-00002.h5.json"), b"{").unwrap();
        let again = run(b.path(), &PrepOptions::default(), "p1").unwrap();
        assert_eq!((again.written, again.reused), (1, 4));
        assert_eq!(again.entries, full.entries);

        // Other parameters: refused, naming the sidecar.
        let err = run(b.path(), &PrepOptions::default(), "p2")
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("train-00000.h5.json") && err.contains("different parameters"),
            "{err}"
        );
    }

    #[test]
    fn parts_split_shards_round_robin_and_together_equal_the_whole() {
        let whole = tempfile::tempdir().unwrap();
        let parts = tempfile::tempdir().unwrap();
        let full = run(whole.path(), &PrepOptions::default(), "p").unwrap();
        let mut got = Vec::new();
        for i in 0..2 {
            let o = PrepOptions {
                part: Part::new(i, 2).unwrap(),
                ..PrepOptions::default()
            };
            let r = run(parts.path(), &o, "p").unwrap();
            assert!(r.entries.iter().all(|e| e.global % 2 == i));
            got.extend(r.entries);
        }
        got.sort_by_key(|e| e.global);
        assert_eq!(got, full.entries);
    }

    #[test]
    fn part_parse_and_ownership() {
        let p: Part = "1/3".parse().unwrap();
        assert_eq!(p, Part { index: 1, count: 3 });
        assert!(p.owns(1) && p.owns(4) && !p.owns(0) && !p.owns(2));
        assert!("3/3".parse::<Part>().unwrap_err().contains("3/3"));
        assert!("0/0".parse::<Part>().is_err());
        assert!("x".parse::<Part>().is_err());
        assert_eq!(p.to_string(), "1/3");
        assert_eq!(p.manifest_name(), "manifest.part-1-of-3.json");
        assert_eq!(Part::default().manifest_name(), "manifest.json");
    }

    #[test]
    fn plan_is_sorted_cut_by_index_and_numbered_over_splits() {
        let mut m = BTreeMap::new();
        let c = |n: &str| Candidate {
            name: n.to_string(),
            item: (),
        };
        m.insert("test", vec![c("t1")]);
        m.insert("train", vec![c("e"), c("a"), c("c"), c("b"), c("d")]);
        let plan = make_plan(m, 2);
        let names: Vec<Vec<&str>> = plan
            .iter()
            .map(|s| s.items.iter().map(|c| c.name.as_str()).collect())
            .collect();
        assert_eq!(
            names,
            vec![vec!["a", "b"], vec!["c", "d"], vec!["e"], vec!["t1"]]
        );
        assert_eq!(plan[3].split, "test");
        assert_eq!(plan[3].index, 0);
        assert_eq!(plan[3].global, 3);
        assert_eq!(plan[1].file_name(), "train-00001.h5");
    }
}
