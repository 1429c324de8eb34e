//! `choreod prep merge`: join the outputs of `--shard I/N` runs into one directory with one
//! manifest (and, for HumanML3D, Mean/Std from the per-shard sums).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use super::humanml3d::write_mean_std;
use super::plan::{
    MANIFEST_FORMAT, Manifest, Part, PrepReport, ShardEntry, ensure_dir, read_text, split_counts,
};
use crate::checksum::sha256_file;
use crate::error::{Error, Result, io_err};
use crate::utc::now_utc;

/// Manifests (`manifest.json`, `manifest.part-*.json`) in `dir`, sorted by file name.
fn manifests_in(dir: &Path) -> Result<Vec<(PathBuf, Manifest)>> {
    let mut paths = Vec::new();
    for e in std::fs::read_dir(dir).map_err(io_err(dir))? {
        let p = e.map_err(io_err(dir))?.path();
        let n = p
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        if n == "manifest.json" || (n.starts_with("manifest.part-") && n.ends_with(".json")) {
            paths.push(p);
        }
    }
    paths.sort();
    let mut out = Vec::new();
    for p in paths {
        let m: Manifest = serde_json::from_str(&read_text(&p)?)
            .map_err(|e| Error::invalid(&p, format!("not a prep manifest: {e}")))?;
        if m.format != MANIFEST_FORMAT {
            return Err(Error::invalid(
                &p,
                format!("format {:?}, expected {MANIFEST_FORMAT:?}", m.format),
            ));
        }
        out.push((p, m));
    }
    Ok(out)
}

/// Copy `src` to `dst` through a temporary name unless `dst` already is that file.
fn copy_into(src: &Path, dst: &Path) -> Result<bool> {
    if let (Ok(a), Ok(b)) = (src.canonicalize(), dst.canonicalize())
        && a == b
    {
        return Ok(false);
    }
    // Streamed (shards are large), under a temporary name so a killed merge leaves no torn copy.
    let tmp = choreo_dsp::atomic::temp_path(dst);
    let res = std::fs::copy(src, &tmp)
        .map_err(io_err(src))
        .and_then(|_| choreo_dsp::atomic::commit_atomic(&tmp, dst).map_err(io_err(dst)));
    if res.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    res.map(|()| true)
}

/// Merge the manifests found in `inputs` (each a `choreod prep` output directory) into
/// `out_dir`: shard files and sidecars are copied there (unless already there) and checked
/// against their sha256; the result must cover every planned shard.
pub fn merge(inputs: &[PathBuf], out_dir: &Path) -> Result<PrepReport> {
    let started_utc = now_utc();
    let mut found: Vec<(PathBuf, Manifest)> = Vec::new();
    for d in inputs {
        let ms = manifests_in(d)?;
        if ms.is_empty() {
            return Err(Error::invalid(
                d,
                "no manifest.json or manifest.part-*.json",
            ));
        }
        found.extend(ms);
    }
    let Some((first_path, first)) = found.first().cloned() else {
        return Err(Error::motion("merge needs at least one input directory"));
    };
    // shard global number → (entry, source directory)
    let mut shards: BTreeMap<usize, (ShardEntry, PathBuf)> = BTreeMap::new();
    let mut skips = Vec::new();
    let mut notes = Vec::new();
    let mut files_found = 0;
    for (p, m) in &found {
        if m.dataset != first.dataset || m.parameters_sha256 != first.parameters_sha256 {
            return Err(Error::invalid(
                p,
                format!(
                    "dataset {} / parameters {} differ from {} ({} / {})",
                    m.dataset,
                    &m.parameters_sha256[..12.min(m.parameters_sha256.len())],
                    first_path.display(),
                    first.dataset,
                    &first.parameters_sha256[..12.min(first.parameters_sha256.len())]
                ),
            ));
        }
        let dir = p.parent().map(Path::to_path_buf).unwrap_or_default();
        for e in &m.shards {
            if let Some((prev, _)) = shards.get(&e.global) {
                if prev.sha256 != e.sha256 {
                    return Err(Error::invalid(
                        p,
                        format!("{} differs from another part's copy", e.file),
                    ));
                }
                continue;
            }
            shards.insert(e.global, (e.clone(), dir.clone()));
        }
        skips.extend(m.skips.iter().cloned());
        notes.extend(m.notes.iter().cloned());
        files_found = files_found.max(m.files_found);
    }
    let planned: BTreeMap<String, usize> = first
        .splits
        .iter()
        .map(|(k, v)| (k.clone(), v.planned_shards))
        .collect();
    let total: usize = planned.values().sum();
    let missing: Vec<usize> = (0..total).filter(|g| !shards.contains_key(g)).collect();
    if !missing.is_empty() {
        return Err(Error::invalid(
            &first_path,
            format!(
                "{} of {total} planned shards are in no input (global numbers {:?}...); run the missing parts first",
                missing.len(),
                &missing[..missing.len().min(8)]
            ),
        ));
    }
    ensure_dir(out_dir)?;
    let (mut copied, mut kept) = (0, 0);
    let mut entries = Vec::new();
    // Check every source against its manifest before copying anything, so a damaged part
    // leaves the output untouched and the error names the bad file where it is.
    for (e, dir) in shards.values() {
        let src = dir.join(&e.file);
        let sha = sha256_file(&src)?;
        if sha != e.sha256 {
            return Err(Error::invalid(
                &src,
                format!("sha256 {sha} but its manifest says {}", e.sha256),
            ));
        }
    }
    for (e, dir) in shards.into_values() {
        if copy_into(&dir.join(&e.file), &out_dir.join(&e.file))? {
            copied += 1;
        } else {
            kept += 1;
        }
        let side = format!("{}.json", e.file);
        copy_into(&dir.join(&side), &out_dir.join(&side))?;
        entries.push(e);
    }
    // Every part lists the skips found while listing the input; details may name paths that
    // differ between machines, so one entry per (sequence, reason).
    skips.sort();
    skips.dedup_by(|a, b| a.name == b.name && a.reason == b.reason);
    notes.sort();
    notes.dedup();
    let mean_std = if first.dataset == "humanml3d" {
        Some(write_mean_std(out_dir, &entries)?)
    } else {
        None
    };
    let manifest = Manifest {
        part: Part::default(),
        complete: true,
        started_utc,
        finished_utc: now_utc(),
        files_found,
        splits: split_counts(&entries, &planned),
        shards: entries,
        skips,
        notes,
        mean_std,
        ..first
    };
    let manifest_path = out_dir.join(manifest.part.manifest_name());
    let text = serde_json::to_string_pretty(&manifest)
        .map_err(|e| Error::invalid(&manifest_path, format!("serialising: {e}")))?;
    choreo_dsp::atomic::write_atomic(&manifest_path, text.as_bytes())
        .map_err(io_err(&manifest_path))?;
    Ok(PrepReport {
        manifest_path,
        manifest,
        shards_written: copied,
        shards_reused: kept,
    })
}
