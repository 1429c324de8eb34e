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
    /// The music's beat times (seconds) stored with the motion: a prep shard sequence's `beats`
    /// ([`ShardSequence`]); `None` for motion files.
    pub beat_times_s: Option<Vec<f64>>,
}

/// One sequence of a `choreod prep` shard as eval reads it.
#[derive(Debug, Clone, PartialEq)]
pub struct ShardSequence {
    /// Its joints as a motion: AIST++ `joints60` (SMPL-24, 60 fps) or HumanML3D `joints`
    /// (t2m-22, 20 fps).
    pub motion: MotionFile,
    /// The music's beat times in seconds, from its `beats` (frame indices at the shard's root
    /// `fps`, README "choreod prep"); `None` when it has none (HumanML3D has no music). Checked
    /// by [`check_shard_beats`].
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
    let sequence = match crate::isolated::installed() {
        Some(reader) => reader.read_shard_sequence(path, name)?,
        None => shard_sequence(path, name)?,
    };
    Ok(EvalMotion {
        name: format!("{}:{name}", path.display()),
        path: path.to_path_buf(),
        beat_times_s: sequence.beat_times_s,
        motion: sequence.motion,
    })
}

/// One sequence of a prep shard, read in this process.
pub(crate) fn shard_sequence(path: &Path, name: &str) -> Result<ShardSequence> {
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
    let motion = MotionFile::from_joints(fps, skeleton, joints);
    let beat_times_s = shard_beats(path, &file, &group, name, &motion)?;
    Ok(ShardSequence {
        motion,
        beat_times_s,
    })
}

/// A shard sequence's `beats` (frame indices at the shard's root `fps`) as seconds, checked
/// against its `motion`; `None` when it has none.
fn shard_beats(
    path: &Path,
    file: &hdf5::File,
    group: &hdf5::Group,
    name: &str,
    motion: &MotionFile,
) -> Result<Option<Vec<f64>>> {
    if !group.link_exists("beats") {
        return Ok(None);
    }
    let bad = |reason: String| bad_beats(path, name, reason);
    let fps = file
        .attr("fps")
        .and_then(|a| a.read_scalar::<f32>())
        .map_err(|_| bad("the shard has no root fps attribute to time them".into()))?;
    crate::limits::check_fps(fps).map_err(|r| bad(format!("the shard's fps: {r}")))?;
    let ds = group
        .dataset("beats")
        .map_err(|_| bad("not a dataset".into()))?;
    let shape = ds.shape();
    let frames = motion.joints.shape()[0];
    if shape.len() != 1 || shape[0] > frames {
        return Err(bad(format!(
            "shape {shape:?}, expected (B ≤ {frames}): at most one beat per frame"
        )));
    }
    check_readable(path, &ds)?;
    let beats: Vec<i32> = ds.read_raw::<i32>().map_err(h5_err(path))?;
    let seconds: Vec<f64> = beats
        .iter()
        .map(|b| f64::from(*b) / f64::from(fps))
        .collect();
    check_shard_beats(path, name, &seconds, motion)?;
    Ok(Some(seconds))
}

/// Check a shard sequence's beat times (seconds) against its motion, as read here and as a
/// reader child sends them: at most one per frame, finite, non-decreasing, within
/// `0..=frames / fps` (prep keeps only beats on the sequence's frames).
pub(crate) fn check_shard_beats(
    path: &Path,
    name: &str,
    beat_times_s: &[f64],
    motion: &MotionFile,
) -> Result<()> {
    let frames = motion.joints.shape()[0];
    if beat_times_s.len() > frames {
        return Err(bad_beats(
            path,
            name,
            format!(
                "{} of them for {frames} frames: at most one beat per frame",
                beat_times_s.len()
            ),
        ));
    }
    let duration_s = frames as f64 / f64::from(motion.fps);
    let mut previous = 0.0;
    for (i, &t) in beat_times_s.iter().enumerate() {
        let reason = if !t.is_finite() {
            "is not finite"
        } else if t < 0.0 {
            "is before the start"
        } else if t > duration_s {
            "is after the end"
        } else if t < previous {
            "is before the beat before it"
        } else {
            previous = t;
            continue;
        };
        return Err(bad_beats(
            path,
            name,
            format!("beat {i} at {t} s {reason} (the sequence is {duration_s:.3} s)"),
        ));
    }
    Ok(())
}

fn bad_beats(path: &Path, name: &str, reason: String) -> Error {
    Error::invalid(
        path,
        format!("sequence {}: beats: {reason}", choreo_dsp::quote(name)),
    )
}

#[cfg(test)]
mod tests {
    use ndarray::{Array1, Array2};

    use super::*;

    /// A shard of one AIST++ sequence `seq`, 120 frames at 60 fps (2 s), root `fps` attribute
    /// `fps` when given, and what `beats` writes into the sequence's group.
    fn shard(dir: &Path, fps: Option<f32>, beats: impl FnOnce(&hdf5::Group)) -> PathBuf {
        let path = dir.join("shard.h5");
        // Written without an HDF5 lock: a child another test forks in this process inherits
        // the descriptor until its exec, and with it the write lock the read below would meet.
        let file = hdf5::File::with_options()
            .with_fapl(|p| p.file_locking(false))
            .create(&path)
            .unwrap();
        if let Some(fps) = fps {
            let attr = file.new_attr::<f32>().create("fps").unwrap();
            attr.write_scalar(&fps).unwrap();
        }
        let g = file.create_group("seq").unwrap();
        let joints = Array3::<f32>::from_shape_fn((120, 24, 3), |(t, j, c)| {
            (t as f32).sin() * 0.1 + j as f32 * 0.01 + c as f32
        });
        g.new_dataset_builder()
            .with_data(&joints)
            .create("joints60")
            .unwrap();
        beats(&g);
        path
    }

    fn frames(g: &hdf5::Group, beats: &[i32]) {
        g.new_dataset_builder()
            .with_data(&Array1::from(beats.to_vec()))
            .create("beats")
            .unwrap();
    }

    #[test]
    fn a_shards_beats_are_seconds_at_its_root_fps() {
        let dir = tempfile::tempdir().unwrap();
        let path = shard(dir.path(), Some(30.0), |g| frames(g, &[0, 15, 31, 60]));
        let s = shard_sequence(&path, "seq").unwrap();
        assert_eq!(s.motion.joints.shape(), &[120, 24, 3]);
        assert_eq!(s.motion.fps, 60.0);
        // Frame 60 at 30 fps is the end of the 2 s sequence: still on it.
        assert_eq!(
            s.beat_times_s,
            Some(vec![0.0, 0.5, 31.0 / 30.0, 2.0]),
            "frame indices over the shard's fps, not the motion's"
        );
        let path = shard(dir.path(), Some(30.0), |_| ());
        assert_eq!(shard_sequence(&path, "seq").unwrap().beat_times_s, None);
    }

    /// What a case writes into a sequence's group.
    type Writer = Box<dyn Fn(&hdf5::Group)>;

    #[test]
    fn a_shards_bad_beats_are_one_line_naming_the_sequence() {
        let dir = tempfile::tempdir().unwrap();
        let cases: Vec<(Option<f32>, Writer, &str)> = vec![
            (
                Some(30.0),
                Box::new(|g| frames(g, &[-1, 3])),
                "beat 0 at -0.0333",
            ),
            (
                Some(30.0),
                Box::new(|g| frames(g, &[3, 61])),
                "is after the end",
            ),
            (
                Some(30.0),
                Box::new(|g| frames(g, &[10, 5])),
                "beat 1 at 0.1666",
            ),
            (
                Some(30.0),
                Box::new(|g| frames(g, &[i32::MAX])),
                "is after the end",
            ),
            (
                Some(30.0),
                Box::new(|g| frames(g, &[0; 121])),
                "shape [121], expected (B ≤ 120)",
            ),
            (
                Some(30.0),
                Box::new(|g| {
                    g.new_dataset_builder()
                        .with_data(&Array2::<i32>::zeros((2, 2)))
                        .create("beats")
                        .unwrap();
                }),
                "shape [2, 2]",
            ),
            (None, Box::new(|g| frames(g, &[3])), "no root fps attribute"),
            (
                Some(0.0),
                Box::new(|g| frames(g, &[3])),
                "the shard's fps: 0 fps is outside",
            ),
            (
                Some(f32::NAN),
                Box::new(|g| frames(g, &[3])),
                "the shard's fps: NaN fps",
            ),
        ];
        for (fps, beats, want) in cases {
            let path = shard(dir.path(), fps, beats);
            let e = shard_sequence(&path, "seq").unwrap_err().to_string();
            assert!(
                e.contains("shard.h5") && e.contains("sequence 'seq': beats: ") && e.contains(want),
                "{want}: {e}"
            );
            assert!(!e.contains('\n'), "{e}");
        }
    }

    #[test]
    fn beat_times_are_checked_finite_in_order_and_on_the_motion() {
        let motion =
            MotionFile::from_joints(60.0, SkeletonKind::Smpl24, Array3::zeros((120, 24, 3)));
        let check = |beats: &[f64]| check_shard_beats(Path::new("s.h5"), "q", beats, &motion);
        assert!(check(&[]).is_ok());
        assert!(check(&[0.0, 0.5, 0.5, 2.0]).is_ok(), "equal neighbours");
        for (beats, want) in [
            (vec![f64::NAN], "beat 0 at NaN s is not finite"),
            (vec![0.5, f64::INFINITY], "beat 1 at inf s is not finite"),
            (vec![-1e-9], "is before the start"),
            (
                vec![2.0 + 1e-9],
                "is after the end (the sequence is 2.000 s)",
            ),
            (
                vec![1.0, 0.999],
                "beat 1 at 0.999 s is before the beat before it",
            ),
            (vec![0.0; 121], "121 of them for 120 frames"),
        ] {
            let e = check(&beats).unwrap_err().to_string();
            assert!(
                e.starts_with("s.h5") && e.contains("sequence 'q': beats: "),
                "{e}"
            );
            assert!(e.contains(want), "{want}: {e}");
        }
    }
}
