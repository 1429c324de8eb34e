//! Motion file formats: one reader per format, one [`probe`] that picks the reader, and one
//! loader ([`load_motion`]) every verb reads motion through, as symphonia's `probe` picks a
//! `FormatReader`.
//!
//! | format | reader | content |
//! |---|---|---|
//! | [`MotionFormat::AistppPickle`] | [`aistpp`] over [`pickle`] | SMPL poses → SMPL-24 joints, 60 fps |
//! | [`MotionFormat::Npy`] | [`npy`] | joints (T, 24 or 22, 3) or HumanML3D features (T, 263); no frame rate |
//! | [`MotionFormat::Bvh`] | [`bvh`] | any hierarchy, its own joint names |
//! | [`MotionFormat::MotionFile`] | [`motion_file`] (in a child process once [`isolated`] is installed) | our HDF5 motion file |
//!
//! **The probe's rule: content wins.** A file whose first bytes are one format's signature
//! (HDF5's `\x89HDF\r\n\x1a\n`, NumPy's `\x93NUMPY`, a pickle's `\x80` protocol opcode, BVH's
//! `HIERARCHY` keyword) is read as that format whatever its name says: an HDF5 file named
//! `.npy` is a motion file, a BVH named `.pkl` a BVH. Bytes that match no signature go to the
//! reader the extension names, which then says what is wrong in that format's terms (empty,
//! truncated, bad magic). Neither a signature nor a known extension: [`Error::UnsupportedFormat`].
//!
//! Every reader bounds what it allocates by [`limits`]; [`h5`] holds the HDF5 checks every
//! `.h5` read passes.

pub mod aistpp;
pub mod bvh;
pub mod h5;
pub mod isolated;
pub mod limits;
pub mod motion_file;
pub mod npy;
pub mod pickle;

use std::io::Read;
use std::path::Path;

use ndarray::{Array2, Ix2, Ix3};

use crate::error::{Error, Result, io_err};
use crate::humanml3d::FEATURE_DIM;
use crate::skeleton::SkeletonKind;
use aistpp::{AISTPP_FPS, AistppMotion};
use motion_file::{MotionFile, check_values};

/// A motion file format choreod reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub enum MotionFormat {
    /// An AIST++ motion `.pkl` (SMPL poses).
    AistppPickle,
    /// A NumPy `.npy` array: joints or HumanML3D features.
    Npy,
    /// A BVH motion capture file.
    Bvh,
    /// choreod's HDF5 motion file (`.h5`).
    MotionFile,
}

/// Extensions of the files [`probe`] knows by name (directories are listed by these).
pub const MOTION_EXTENSIONS: [&str; 6] = ["pkl", "pickle", "npy", "bvh", "h5", "hdf5"];

/// HDF5's format signature (at offset 0 of a file without a user block).
const HDF5_SIGNATURE: &[u8] = b"\x89HDF\r\n\x1a\n";
/// Bytes read to recognise a format: BVH's keyword may follow a byte-order mark and blank lines.
const SNIFF_BYTES: usize = 64;

impl MotionFormat {
    /// The format's name in messages, e.g. `"BVH"`.
    pub fn name(self) -> &'static str {
        match self {
            MotionFormat::AistppPickle => "AIST++ motion",
            MotionFormat::Npy => ".npy array",
            MotionFormat::Bvh => "BVH",
            MotionFormat::MotionFile => "motion file",
        }
    }

    fn from_extension(ext: &str) -> Option<Self> {
        match ext {
            "pkl" | "pickle" => Some(MotionFormat::AistppPickle),
            "npy" => Some(MotionFormat::Npy),
            "bvh" => Some(MotionFormat::Bvh),
            "h5" | "hdf5" => Some(MotionFormat::MotionFile),
            _ => None,
        }
    }

    /// The format whose signature `head` (a file's first bytes) starts with.
    fn from_signature(head: &[u8]) -> Option<Self> {
        if head.starts_with(HDF5_SIGNATURE) {
            return Some(MotionFormat::MotionFile);
        }
        if head.starts_with(b"\x93NUMPY") {
            return Some(MotionFormat::Npy);
        }
        // PROTO opcode and a protocol number: what pickle protocols 2-5 start with.
        if let [0x80, 2..=5, ..] = head {
            return Some(MotionFormat::AistppPickle);
        }
        let text = head.strip_prefix(b"\xef\xbb\xbf").unwrap_or(head);
        let start = text
            .iter()
            .position(|b| !b.is_ascii_whitespace())
            .unwrap_or(text.len());
        text[start..]
            .starts_with(b"HIERARCHY")
            .then_some(MotionFormat::Bvh)
    }
}

impl std::fmt::Display for MotionFormat {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// The lower-case extension that names `p`'s format. A temporary file choreod writes under
/// (`.NAME.EXT.tmp-PID-N`, [`choreo_dsp::atomic::temp_path`]; what `kill -9` leaves of a live
/// take) reads as `NAME.EXT`, so it can be read in place before it is renamed.
pub(crate) fn extension(p: &Path) -> String {
    let name = p
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let name = name
        .strip_prefix('.')
        .and_then(|n| n.rsplit_once(".tmp-"))
        .map_or(name.as_str(), |(original, _)| original);
    Path::new(name)
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default()
}

/// Which reader `path` is for: by its first bytes, else by its extension (the module's rule).
/// Reads at most 64 bytes in this process (never through libhdf5).
pub fn probe(path: &Path) -> Result<MotionFormat> {
    let mut head = Vec::with_capacity(SNIFF_BYTES);
    std::fs::File::open(path)
        .and_then(|f| f.take(SNIFF_BYTES as u64).read_to_end(&mut head))
        .map_err(io_err(path))?;
    let ext = extension(path);
    let by_name = MotionFormat::from_extension(&ext);
    match (MotionFormat::from_signature(&head), by_name) {
        (Some(content), named) => {
            if named.is_some_and(|n| n != content) {
                tracing::info!(file = %path.display(), extension = ext, format = %content, "read by its content, not its extension");
            }
            Ok(content)
        }
        (None, Some(named)) => Ok(named),
        (None, None) => Err(Error::UnsupportedFormat {
            path: path.to_path_buf(),
            extension: ext,
        }),
    }
}

/// Frame rate assumed for a `.npy` read without one: HumanML3D's 20 fps for 22 joints and 263
/// features, else AIST++ / EDGE's 30 fps.
pub fn npy_default_fps(joints: usize) -> f32 {
    if joints == 22 { 20.0 } else { 30.0 }
}

/// What a `.npy` holds.
#[derive(Debug, Clone)]
pub enum NpyMotion {
    /// HumanML3D 263-dim features (T, 263), finite.
    Features(Array2<f32>),
    /// SMPL-24 or t2m-22 joints, validated.
    Joints(Box<MotionFile>),
}

/// Read a `.npy` as motion: HumanML3D features (T, 263) or SMPL-24 / t2m-22 joints (T, 24 | 22,
/// 3) at `fps` (a `.npy` records none; `None`: [`npy_default_fps`]).
pub fn read_npy_motion(path: &Path, fps: Option<f32>) -> Result<NpyMotion> {
    let a = npy::read_npy(path)?;
    let shape = a.shape().to_vec();
    let corrupt = |reason: String| Error::Corrupt {
        path: path.to_path_buf(),
        format: MotionFormat::Npy,
        reason,
    };
    match shape.as_slice() {
        [_, FEATURE_DIM] => {
            let f = a
                .into_dimensionality::<Ix2>()
                .map_err(|e| corrupt(e.to_string()))?;
            check_values(path, "features", f.iter())?;
            Ok(NpyMotion::Features(f))
        }
        [_, j @ (22 | 24), 3] => {
            let skeleton = if *j == 22 {
                SkeletonKind::T2m22
            } else {
                SkeletonKind::Smpl24
            };
            let joints = a
                .into_dimensionality::<Ix3>()
                .map_err(|e| corrupt(e.to_string()))?;
            let fps = fps.unwrap_or_else(|| npy_default_fps(*j));
            let motion = MotionFile::from_joints(fps, skeleton, joints);
            motion.validate(path)?;
            Ok(NpyMotion::Joints(Box::new(motion)))
        }
        _ => Err(corrupt(format!(
            "array of shape {shape:?}: expected HumanML3D features (T, 263) or SMPL-24 / t2m-22 \
             joints (T, 24, 3) / (T, 22, 3)"
        ))),
    }
}

/// Motion loaded from any supported input, validated ([`MotionFile::validate`]).
#[derive(Debug, Clone)]
pub struct LoadedMotion {
    /// The motion (world joints; HumanML3D features are recovered to t2m-22 joints).
    pub motion: MotionFile,
    /// The file's format.
    pub format: MotionFormat,
    /// The file held HumanML3D features rather than joints (a `.npy (T, 263)`).
    pub from_features: bool,
    /// Whether `motion.fps` was assumed (a `.npy` read without a frame rate).
    pub fps_assumed: bool,
}

impl LoadedMotion {
    /// What the input was, for reports: e.g. `"AIST++ motion"`, `"joints"` (a `.npy`).
    pub fn what(&self) -> &'static str {
        match (self.format, self.from_features) {
            (MotionFormat::Npy, true) => "HumanML3D features",
            (MotionFormat::Npy, false) => "joints",
            (format, _) => format.name(),
        }
    }
}

/// Load any supported motion input ([`probe`] picks the reader) and validate it
/// ([`MotionFile::validate`]: frames, finite values, shapes), so every verb refuses the same
/// inputs. `npy_fps` is the frame rate of a `.npy` input (refused for other inputs, which
/// record theirs: [`Error::FpsNotApplicable`]); without it [`npy_default_fps`] is assumed and
/// reported. A reader's complaint about the content is [`Error::Corrupt`] naming the format.
pub fn load_motion(path: &Path, npy_fps: Option<f32>) -> Result<LoadedMotion> {
    read_motion(path, probe(path)?, npy_fps)
}

/// [`load_motion`] with the format already probed.
pub(crate) fn read_motion(
    path: &Path,
    format: MotionFormat,
    npy_fps: Option<f32>,
) -> Result<LoadedMotion> {
    if let Some(fps) = npy_fps {
        if format != MotionFormat::Npy {
            return Err(Error::FpsNotApplicable {
                path: path.to_path_buf(),
                format,
            });
        }
        if limits::check_fps(fps).is_err() {
            return Err(Error::FpsOutOfRange {
                path: path.to_path_buf(),
                fps,
            });
        }
    }
    let loaded = |motion| LoadedMotion {
        motion,
        format,
        from_features: false,
        fps_assumed: false,
    };
    let result = match format {
        MotionFormat::AistppPickle => AistppMotion::read(path).map(|m| {
            loaded(MotionFile::from_joints(
                AISTPP_FPS,
                SkeletonKind::Smpl24,
                m.joints(),
            ))
        }),
        MotionFormat::MotionFile => motion_file::read_motion_file(path).map(loaded),
        MotionFormat::Bvh => bvh::read_bvh(path).map(|b| loaded(b.to_motion_file())),
        MotionFormat::Npy => read_npy_as_joints(path, npy_fps),
    }
    .and_then(|l| l.motion.validate(path).map(|()| l));
    result.map_err(|e| e.in_format(format))
}

fn read_npy_as_joints(path: &Path, fps: Option<f32>) -> Result<LoadedMotion> {
    let (motion, from_features) = match read_npy_motion(path, fps)? {
        NpyMotion::Joints(m) => (*m, false),
        NpyMotion::Features(f) => {
            let j = crate::humanml3d::recover_from_ric(f.view()).map_err(|e| e.with_path(path))?;
            let fps = fps.unwrap_or(npy_default_fps(22));
            (MotionFile::from_joints(fps, SkeletonKind::T2m22, j), true)
        }
    };
    Ok(LoadedMotion {
        motion,
        format: MotionFormat::Npy,
        from_features,
        fps_assumed: fps.is_none(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn shared_motion(name: &str) -> std::path::PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../shared/fixtures/motion")
            .join(name)
    }

    fn bundled(name: &str) -> std::path::PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../daemon/assets/motion")
            .join(name)
    }

    /// Content wins over a lying extension: each real file, copied under every other
    /// format's extension, is still read as what it is, and gives the same motion.
    #[test]
    fn the_probe_reads_content_not_the_extension() {
        let dir = tempfile::tempdir().unwrap();
        let h5 = dir.path().join("m.h5");
        let aist = AistppMotion::read(&shared_motion("aistpp_gBR_sBM_cAll_d04_mBR0_ch01.pkl"))
            .unwrap()
            .joints();
        motion_file::write_motion_file(
            &h5,
            &MotionFile::from_joints(60.0, SkeletonKind::Smpl24, aist.clone()),
        )
        .unwrap();
        let npy_path = dir.path().join("j.npy");
        npy::write_npy(&npy_path, aist.view().into_dyn()).unwrap();
        let sources = [
            (
                shared_motion("aistpp_gBR_sBM_cAll_d04_mBR0_ch01.pkl"),
                MotionFormat::AistppPickle,
            ),
            (bundled("cmu_01_01_8s_30fps.bvh"), MotionFormat::Bvh),
            (h5, MotionFormat::MotionFile),
            (npy_path, MotionFormat::Npy),
        ];
        for (source, format) in &sources {
            let truth = load_motion(source, None).unwrap();
            assert_eq!(truth.format, *format);
            for ext in ["pkl", "npy", "bvh", "h5", "txt"] {
                let liar = dir.path().join(format!("liar.{ext}"));
                std::fs::copy(source, &liar).unwrap();
                assert_eq!(probe(&liar).unwrap(), *format, "{} as .{ext}", format);
                let read = load_motion(&liar, None).unwrap();
                assert_eq!(read.format, *format);
                assert_eq!(
                    read.motion.joints, truth.motion.joints,
                    "{format} as .{ext}"
                );
            }
        }
    }

    /// No signature: the extension's reader speaks (in its own format's terms); no signature
    /// and no known extension: unsupported, naming the extension.
    #[test]
    fn unknown_content_goes_to_the_extensions_reader() {
        let dir = tempfile::tempdir().unwrap();
        let empty_npy = dir.path().join("empty.npy");
        std::fs::write(&empty_npy, b"").unwrap();
        assert_eq!(probe(&empty_npy).unwrap(), MotionFormat::Npy);
        let e = load_motion(&empty_npy, None).unwrap_err();
        assert!(
            matches!(
                &e,
                Error::Corrupt {
                    format: MotionFormat::Npy,
                    ..
                }
            ),
            "{e:?}"
        );
        assert!(e.to_string().contains("not a .npy file"), "{e}");
        let text = dir.path().join("notes.txt");
        std::fs::write(&text, b"hello").unwrap();
        let e = load_motion(&text, None).unwrap_err();
        assert!(
            matches!(&e, Error::UnsupportedFormat { extension, .. } if extension == "txt"),
            "{e:?}"
        );
        // A frame rate for a file that records its own is refused, typed.
        let bvh = bundled("cmu_01_01_8s_30fps.bvh");
        assert!(matches!(
            load_motion(&bvh, Some(30.0)),
            Err(Error::FpsNotApplicable {
                format: MotionFormat::Bvh,
                ..
            })
        ));
    }

    #[test]
    fn signatures_are_recognised_after_a_bom_and_blank_lines() {
        assert_eq!(
            MotionFormat::from_signature(b"\xef\xbb\xbf\r\n  HIERARCHY\nROOT Hips"),
            Some(MotionFormat::Bvh)
        );
        assert_eq!(
            MotionFormat::from_signature(b"\x80\x04\x95"),
            Some(MotionFormat::AistppPickle)
        );
        assert_eq!(MotionFormat::from_signature(b"\x80\x09"), None);
        assert_eq!(MotionFormat::from_signature(b""), None);
        assert_eq!(MotionFormat::from_signature(b"HIERARCH"), None);
    }
}
