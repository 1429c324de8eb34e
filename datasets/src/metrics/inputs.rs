//! What `choreod eval` reads: motion files in any format [`load_motion`] takes (a custom
//! skeleton placed on t2m-22 by the one rig mapping, [`on_standard_skeleton`]), directories of
//! them, and `choreod prep` shards (every sequence of the shard).

use std::path::{Path, PathBuf};

use ndarray::{Array3, Ix3};

use crate::error::{Error, Result, h5_err, io_err};
use crate::formats::h5::{check_readable, open_checked};
use crate::formats::motion_file::MotionFile;
use crate::formats::{MOTION_EXTENSIONS, MotionFormat, load_motion, probe};
use crate::kinematics::rig::on_standard_skeleton;
use crate::prep::SHARD_FORMAT;
use crate::skeleton::SkeletonKind;
/// Longest sequence read from a shard: 10 minutes at 60 fps is prep's own limit (README
/// "longer than 10 minutes are skipped"); twice that refuses hostile shapes before allocating.
const MAX_SHARD_FRAMES: usize = 72_000;

/// One motion to evaluate.
#[derive(Debug, Clone)]
pub struct EvalMotion {
    /// Where it came from: the file, or `shard.h5:sequence`.
    pub name: String,
    /// The file it was read from.
    pub path: PathBuf,
    /// The motion.
    pub motion: MotionFile,
    /// The music's beat times (seconds) stored with the motion; `None` for motion files and (for
    /// now) prep shards, whose `beats` are not yet read through the isolated reader.
    pub beat_times_s: Option<Vec<f64>>,
}

/// Where one motion comes from; [`EvalSource::load`] reads it (one at a time, so a thousand
/// files never sit in memory together).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum EvalSource {
    /// A motion file in any format [`load_motion`] reads.
    File(PathBuf),
    /// One sequence of a `choreod prep` shard.
    ShardSequence {
        /// The shard.
        shard: PathBuf,
        /// The sequence's group name.
        sequence: String,
    },
}

impl EvalSource {
    /// Read the motion; `npy_fps` is the frame rate of `.npy` joints (they carry none).
    pub fn load(&self, npy_fps: Option<f32>) -> Result<EvalMotion> {
        match self {
            EvalSource::File(path) => Ok(EvalMotion {
                name: path.display().to_string(),
                path: path.clone(),
                motion: on_standard_skeleton(path, load_motion(path, npy_fps)?.motion)?,
                beat_times_s: None,
            }),
            EvalSource::ShardSequence { shard, sequence } => read_shard_sequence(shard, sequence),
        }
    }
}

/// Every motion in `path`: a motion file, a prep shard (each sequence), or a directory of
/// either (sorted by name, hidden files and other extensions skipped, not recursive).
pub fn eval_sources(path: &Path) -> Result<Vec<EvalSource>> {
    if path.is_dir() {
        let mut files: Vec<PathBuf> = std::fs::read_dir(path)
            .map_err(io_err(path))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| {
                let hidden = p
                    .file_name()
                    .is_some_and(|n| n.to_string_lossy().starts_with('.'));
                let ext = p
                    .extension()
                    .map(|e| e.to_string_lossy().to_ascii_lowercase());
                p.is_file()
                    && !hidden
                    && ext.is_some_and(|e| MOTION_EXTENSIONS.contains(&e.as_str()))
            })
            .collect();
        files.sort();
        if files.is_empty() {
            return Err(Error::invalid(
                path,
                "directory holds no motion files (pkl, h5, bvh, npy)",
            ));
        }
        let mut out = Vec::new();
        for f in files {
            out.extend(file_sources(&f)?);
        }
        return Ok(out);
    }
    file_sources(path)
}

fn file_sources(path: &Path) -> Result<Vec<EvalSource>> {
    if !is_prep_shard(path)? {
        return Ok(vec![EvalSource::File(path.to_path_buf())]);
    }
    let names = match crate::isolated::installed() {
        Some(reader) => reader.read_shard_sequences(path)?,
        None => shard_sequences(path)?,
    };
    Ok(names
        .into_iter()
        .map(|sequence| EvalSource::ShardSequence {
            shard: path.to_path_buf(),
            sequence,
        })
        .collect())
}

/// The sequence names of a prep shard, sorted (`_stats` left out), read in this process.
pub(crate) fn shard_sequences(path: &Path) -> Result<Vec<String>> {
    let file = open_checked(path)?;
    let mut names = file.member_names().map_err(h5_err(path))?;
    names.sort();
    names.retain(|n| n != "_stats");
    Ok(names)
}

/// Whether `path` is a prep shard: an HDF5 file ([`probe`]) whose root `format` attribute says
/// so (read by the isolated reader when the program installed one: the attribute is where a
/// hostile file may crash libhdf5).
fn is_prep_shard(path: &Path) -> Result<bool> {
    if probe(path)? != MotionFormat::MotionFile {
        return Ok(false);
    }
    let format = match crate::isolated::installed() {
        Some(reader) => reader.read_format(path)?,
        None => crate::isolated::root_format(path),
    };
    Ok(format.as_deref() == Some(SHARD_FORMAT))
}

/// One sequence of a prep shard, read by the isolated reader when the program installed one:
/// the whole file is untrusted (`choreo_datasets::isolated`).
fn read_shard_sequence(path: &Path, name: &str) -> Result<EvalMotion> {
    let motion = match crate::isolated::installed() {
        Some(reader) => reader.read_shard_sequence(path, name)?,
        None => shard_motion(path, name)?,
    };
    Ok(EvalMotion {
        name: format!("{}:{name}", path.display()),
        path: path.to_path_buf(),
        // A shard's stored beats would be read through the isolated reader too; not yet.
        beat_times_s: None,
        motion,
    })
}

/// One sequence of a prep shard as a motion, read in this process: AIST++ `joints60`
/// (SMPL-24, 60 fps) or HumanML3D `joints` (t2m-22, 20 fps).
pub(crate) fn shard_motion(path: &Path, name: &str) -> Result<MotionFile> {
    let file = open_checked(path)?;
    let group = file.group(name).map_err(h5_err(path))?;
    let (ds_name, fps, skeleton) = if group.link_exists("joints60") {
        ("joints60", 60.0, SkeletonKind::Smpl24)
    } else {
        ("joints", 20.0, SkeletonKind::T2m22)
    };
    let ds = group.dataset(ds_name).map_err(|_| {
        Error::invalid(
            path,
            format!(
                "sequence {} has no {ds_name} dataset",
                choreo_dsp::quote(name)
            ),
        )
    })?;
    let shape = ds.shape();
    let joints_wanted = skeleton.num_joints();
    if shape.len() != 3 || shape[1] != joints_wanted || shape[2] != 3 || shape[0] > MAX_SHARD_FRAMES
    {
        return Err(Error::invalid(
            path,
            format!(
                "sequence {}: {ds_name} has shape {shape:?}, expected (T ≤ {MAX_SHARD_FRAMES}, {joints_wanted}, 3)",
                choreo_dsp::quote(name)
            ),
        ));
    }
    check_readable(path, &ds)?;
    let joints: Array3<f32> = ds.read::<f32, Ix3>().map_err(h5_err(path))?;
    Ok(MotionFile::from_joints(fps, skeleton, joints))
}
