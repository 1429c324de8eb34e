//! The HDF5 motion file (format `choreod-motion`, version 2; layout in DESIGN.md):
//!
//! ```text
//! /                  attrs: format, format_version, generator, created_utc
//! /motion            attrs: fps, skeleton, joint_names, parents, up_axis="y", units="m"
//! /motion/joints     float32 (T, J, 3), chunked, extendable along T
//! /motion/features   float32 (T', D) optional; attrs: representation, normalized
//! /audio/mel         float32 (F, 80) optional; attrs: sample_rate, n_fft, hop, fmin, fmax
//! /provenance        attrs: source_name, source_sha256, model_name, model_sha256, sampler,
//!                    steps, eta, guidance [, content_guidance, style_guidance], seed,
//!                    chunk_windows, init_noise_sha256, started_utc, finished_utc
//!                    [, style_mode, style_name, style_sha256] [, source_damage]
//!                    [, source_kind] [, source_beat]
//! ```
//!
//! Version 2 added the provenance attributes `eta`, `chunk_windows`, `init_noise_sha256` and
//! the optional two guidance weights; version 1 files are still read (those read as 0, "" and
//! absent). The optional style attributes (style transfer: its mode and the style reference)
//! are absent from other files. `source_damage` says what was wrong with an input that was used
//! in part (a song that ends mid-stream); absent when the input read whole. `source_kind`
//! says what the source file is when it is not the song or motion itself (`dance --features`:
//! precomputed features); absent otherwise. `source_beat` says that a dance's song had no steady
//! beat to follow (speech, noise, a drone) and what was danced instead; absent when it had one.
//!
//! Files are written under a temporary name in the target directory, fsynced, renamed into
//! place and the directory fsynced, so a reader never sees a partial file under the final name.

use std::path::{Path, PathBuf};

use choreo_dsp::atomic::{commit_atomic, temp_path};
use choreo_dsp::quote;

use hdf5::types::VarLenUnicode;
use ndarray::{Array2, Array3, ArrayView2, ArrayView3, s};

use crate::error::{Error, Result, h5_err, io_err};
use crate::formats::h5::{check_readable, h5_writer, open_checked, put, put_str, vlu};
use crate::skeleton::SkeletonKind;

/// The `format` attribute of every motion file.
pub const MOTION_FORMAT: &str = "choreod-motion";
/// The `format_version` this build writes and the highest it reads (it reads 1 too).
pub const MOTION_FORMAT_VERSION: i64 = 2;
/// Frames per HDF5 chunk of `/motion/joints` (64 frames ≈ 2 s at 30 fps: small enough for live
/// appends, large enough to keep chunk overhead low).
const CHUNK_FRAMES: usize = 64;

/// Motion features stored beside the joints.
#[derive(Debug, Clone, PartialEq)]
pub struct Features {
    /// (T', D) values.
    pub data: Array2<f32>,
    /// e.g. `"humanml3d263"`.
    pub representation: String,
    /// Whether `data` is (x − mean) / std.
    pub normalized: bool,
}

/// The log-mel the motion was generated from, time-major.
#[derive(Debug, Clone, PartialEq)]
pub struct MelAttachment {
    /// (F, 80) log-mel frames.
    pub data: Array2<f32>,
    /// Hz.
    pub sample_rate: u32,
    /// FFT size, samples.
    pub n_fft: u32,
    /// Hop, samples.
    pub hop: u32,
    /// Lowest mel band edge, Hz.
    pub fmin: f32,
    /// Highest mel band edge, Hz.
    pub fmax: f32,
}

/// Where a generated motion came from.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Provenance {
    /// Input file name (audio or content motion).
    pub source_name: String,
    /// SHA-256 of the input, hex.
    pub source_sha256: String,
    /// Model package name.
    pub model_name: String,
    /// SHA-256 of the model package manifest, hex.
    pub model_sha256: String,
    /// e.g. `"ddim"`.
    pub sampler: String,
    /// Sampling steps.
    pub steps: u32,
    /// DDIM eta (0 for deterministic samplers). Version 1 files: 0.
    pub eta: f64,
    /// Guidance scale (one weight; 1 = off).
    pub guidance: f32,
    /// Two-weight guidance (style transfer): content weight wc, when used.
    pub content_guidance: Option<f32>,
    /// Two-weight guidance: style weight ws, when used.
    pub style_guidance: Option<f32>,
    /// Random seed.
    pub seed: u64,
    /// Windows denoised per batch (the result depends on it). Version 1 files: 0.
    pub chunk_windows: u32,
    /// SHA-256 of the initial-noise file, hex; "" when the noise came from `seed`.
    pub init_noise_sha256: String,
    /// ISO-8601 UTC start time.
    pub started_utc: String,
    /// ISO-8601 UTC end time.
    pub finished_utc: String,
    /// Style transfer: the mode and the style reference (`source_*` name the content).
    pub style: Option<StyleProvenance>,
    /// The model's licence line (`[license]` of its package), "" when it has none.
    pub license: String,
    /// What was wrong with the input when only part of it was used, e.g. "the file ends
    /// mid-stream: 12.026 s of audio decoded"; `None` when it was read whole.
    #[serde(default)]
    pub source_damage: Option<String>,
    /// What the source file is when it is not the song or motion itself, e.g. "fact35
    /// features (T, 35)" for a dance of precomputed features; `None` otherwise.
    pub source_kind: Option<String>,
    /// Why the song had no beat to follow and what the dance did instead, e.g. "no steady beat
    /// (...): danced anyway, ..."; `None` when a beat was found (or not looked for).
    #[serde(default)]
    pub source_beat: Option<String>,
    /// A library package's dance: the library clips it was played from and their attribution
    /// (`[library]` of the package); `None` for other models.
    #[serde(default)]
    pub library: Option<String>,
}

/// The style half of a style transfer's provenance.
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct StyleProvenance {
    /// `"transfer"` or `"inversion"`.
    pub mode: String,
    /// File name of the style motion (or of the style embedding).
    pub name: String,
    /// SHA-256 of that file, hex.
    pub sha256: String,
}

/// A motion file's content.
#[derive(Debug, Clone, PartialEq)]
pub struct MotionFile {
    /// Frames per second.
    pub fps: f32,
    /// The skeleton of `joints`.
    pub skeleton: SkeletonKind,
    /// (T, J, 3) world positions, metres, y-up.
    pub joints: Array3<f32>,
    /// Optional features.
    pub features: Option<Features>,
    /// Optional log-mel.
    pub mel: Option<MelAttachment>,
    /// Optional provenance.
    pub provenance: Option<Provenance>,
    /// Program that wrote the file, e.g. `"choreod 0.1.0"`.
    pub generator: String,
}

impl MotionFile {
    /// A motion with only joints (no features, mel or provenance) and this crate as generator.
    pub fn from_joints(fps: f32, skeleton: SkeletonKind, joints: Array3<f32>) -> Self {
        MotionFile {
            fps,
            skeleton,
            joints,
            features: None,
            mel: None,
            provenance: None,
            generator: format!("choreod {}", env!("CARGO_PKG_VERSION")),
        }
    }

    /// The one rule every verb applies to motion it reads or writes: shapes that match the
    /// skeleton, a frame rate in [`crate::limits::FPS_RANGE`], at least one frame, and only
    /// finite joint positions and features within ±[`MAX_MOTION_VALUE`]. `path` is the file the
    /// motion came from or goes to, for the message.
    pub fn validate(&self, path: &Path) -> Result<()> {
        self.check().map_err(|r| Error::invalid(path, r))?;
        if self.joints.shape()[0] == 0 {
            return Err(Error::NoFrames {
                path: path.to_path_buf(),
            });
        }
        check_values(path, "joint positions", self.joints.iter())?;
        if let Some(f) = &self.features {
            check_values(path, "features", f.data.iter())?;
        }
        Ok(())
    }

    fn check(&self) -> std::result::Result<(), String> {
        let j = self.skeleton.num_joints();
        let sh = self.joints.shape();
        if sh[1] != j || sh[2] != 3 {
            return Err(format!(
                "joints have shape {sh:?}, skeleton {} needs (T, {j}, 3)",
                quote(self.skeleton.name())
            ));
        }
        self.skeleton.validate()?;
        crate::limits::check_fps(self.fps)?;
        if let Some(m) = &self.mel
            && m.data.shape()[1] != 80
        {
            return Err(format!(
                "mel has shape {:?}, expected (F, 80)",
                m.data.shape()
            ));
        }
        Ok(())
    }
}

/// Write `bytes` to `path` atomically (`choreo_dsp::atomic`), errors naming `path`.
pub(crate) fn write_atomic_bytes(path: &Path, bytes: &[u8]) -> Result<()> {
    choreo_dsp::atomic::write_atomic(path, bytes).map_err(io_err(path))
}

/// Largest magnitude of a joint coordinate (metres) or HumanML3D feature accepted: 1e8 (100,000
/// km; `render` still draws a dance moved 30,000 km away). A finite but huge value (3e38 in a
/// BVH) would pass every NaN check and overflow later, inside a network, where it would look
/// like a broken model.
pub const MAX_MOTION_VALUE: f32 = 1e8;

/// Refuse the first value of `values` (flat index) that is NaN or infinite ([`Error::NonFinite`])
/// or beyond ±[`MAX_MOTION_VALUE`] ([`Error::Invalid`]).
pub(crate) fn check_values<'a>(
    path: &Path,
    what: &str,
    values: impl IntoIterator<Item = &'a f32>,
) -> Result<()> {
    match values
        .into_iter()
        .enumerate()
        .find(|(_, v)| v.is_nan() || v.abs() > MAX_MOTION_VALUE)
    {
        Some((index, v)) if v.is_finite() => Err(Error::invalid(
            path,
            format!(
                "{what} holds {v:e} at index {index}, beyond ±{MAX_MOTION_VALUE:e} (corrupt, or \
                 not in metres)"
            ),
        )),
        Some((index, _)) => Err(Error::NonFinite {
            path: path.to_path_buf(),
            what: what.to_owned(),
            index,
        }),
        None => Ok(()),
    }
}

/// Create the groups, attributes and datasets of `m` in an open file; returns `/motion/joints`.
fn write_layout(
    path: &Path,
    file: &hdf5::File,
    m: &MotionFile,
    provenance: Option<&Provenance>,
) -> Result<hdf5::Dataset> {
    m.check().map_err(|r| Error::invalid(path, r))?;
    let e = h5_err(path);
    put_str(path, file, "format", MOTION_FORMAT)?;
    put(path, file, "format_version", MOTION_FORMAT_VERSION)?;
    put_str(path, file, "generator", &m.generator)?;
    put_str(path, file, "created_utc", &crate::utc::now_utc())?;

    let motion = file.create_group("motion").map_err(h5_err(path))?;
    put(path, &motion, "fps", m.fps)?;
    put_str(path, &motion, "skeleton", m.skeleton.name())?;
    let names = m
        .skeleton
        .joint_names()
        .iter()
        .map(|n| vlu(path, n))
        .collect::<Result<Vec<_>>>()?;
    motion
        .new_attr::<VarLenUnicode>()
        .shape(names.len())
        .create("joint_names")
        .and_then(|a| a.write_raw(&names))
        .map_err(h5_err(path))?;
    let parents = m.skeleton.parents().to_vec();
    motion
        .new_attr::<i32>()
        .shape(parents.len())
        .create("parents")
        .and_then(|a| a.write_raw(&parents))
        .map_err(h5_err(path))?;
    put_str(path, &motion, "up_axis", "y")?;
    put_str(path, &motion, "units", "m")?;

    let (t, j) = (m.joints.shape()[0], m.joints.shape()[1]);
    let joints = motion
        .new_dataset::<f32>()
        .chunk((CHUNK_FRAMES, j, 3))
        .shape(((t, None::<usize>), j, 3usize))
        .create("joints")
        .map_err(h5_err(path))?;
    if t > 0 {
        joints.write(m.joints.view()).map_err(h5_err(path))?;
    }

    if let Some(f) = &m.features {
        let ds = motion
            .new_dataset_builder()
            .with_data(f.data.view())
            .create("features")
            .map_err(h5_err(path))?;
        put_str(path, &ds, "representation", &f.representation)?;
        put(path, &ds, "normalized", f.normalized)?;
    }
    if let Some(mel) = &m.mel {
        let audio = file.create_group("audio").map_err(h5_err(path))?;
        // Chunked and extendable along time like the joints, so live sessions append to it.
        let (f, n_mels) = mel.data.dim();
        let ds = audio
            .new_dataset::<f32>()
            .chunk((CHUNK_FRAMES, n_mels.max(1)))
            .shape(((f, None::<usize>), n_mels))
            .create("mel")
            .map_err(h5_err(path))?;
        if f > 0 {
            ds.write(mel.data.view()).map_err(h5_err(path))?;
        }
        put(path, &ds, "sample_rate", mel.sample_rate)?;
        put(path, &ds, "n_fft", mel.n_fft)?;
        put(path, &ds, "hop", mel.hop)?;
        put(path, &ds, "fmin", mel.fmin)?;
        put(path, &ds, "fmax", mel.fmax)?;
    }
    if let Some(p) = provenance {
        write_provenance(path, file, p)?;
    }
    let _ = e;
    Ok(joints)
}

fn write_provenance(path: &Path, file: &hdf5::File, p: &Provenance) -> Result<()> {
    let g = file.create_group("provenance").map_err(h5_err(path))?;
    put_str(path, &g, "source_name", &p.source_name)?;
    put_str(path, &g, "source_sha256", &p.source_sha256)?;
    put_str(path, &g, "model_name", &p.model_name)?;
    put_str(path, &g, "model_sha256", &p.model_sha256)?;
    put_str(path, &g, "sampler", &p.sampler)?;
    put(path, &g, "steps", p.steps)?;
    put(path, &g, "eta", p.eta)?;
    put(path, &g, "guidance", p.guidance)?;
    if let Some(wc) = p.content_guidance {
        put(path, &g, "content_guidance", wc)?;
    }
    if let Some(ws) = p.style_guidance {
        put(path, &g, "style_guidance", ws)?;
    }
    put(path, &g, "seed", p.seed)?;
    put(path, &g, "chunk_windows", p.chunk_windows)?;
    put_str(path, &g, "init_noise_sha256", &p.init_noise_sha256)?;
    put_str(path, &g, "started_utc", &p.started_utc)?;
    put_str(path, &g, "finished_utc", &p.finished_utc)?;
    if let Some(style) = &p.style {
        put_str(path, &g, "style_mode", &style.mode)?;
        put_str(path, &g, "style_name", &style.name)?;
        put_str(path, &g, "style_sha256", &style.sha256)?;
    }
    if !p.license.is_empty() {
        put_str(path, &g, "license", &p.license)?;
    }
    if let Some(damage) = &p.source_damage {
        put_str(path, &g, "source_damage", damage)?;
    }
    if let Some(kind) = &p.source_kind {
        put_str(path, &g, "source_kind", kind)?;
    }
    if let Some(beat) = &p.source_beat {
        put_str(path, &g, "source_beat", beat)?;
    }
    if let Some(library) = &p.library {
        put_str(path, &g, "library", library)?;
    }
    Ok(())
}

/// Write a motion file atomically: temporary name in the same directory, fsync, rename, fsync
/// the directory.
pub fn write_motion_file(path: &Path, m: &MotionFile) -> Result<()> {
    let tmp = temp_path(path);
    let res = (|| {
        {
            let file = h5_writer().create(&tmp).map_err(h5_err(path))?;
            write_layout(path, &file, m, m.provenance.as_ref())?;
            file.flush().map_err(h5_err(path))?;
            // Handles close here, before the rename.
        }
        commit_atomic(&tmp, path).map_err(io_err(path))
    })();
    if res.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    res
}

fn get_str(path: &Path, loc: &hdf5::Location, name: &str) -> Result<String> {
    let a = loc.attr(name).map_err(|_| {
        Error::invalid(
            path,
            format!("attribute '{name}' missing on {}", loc.name()),
        )
    })?;
    let v: VarLenUnicode = a.read_scalar().map_err(|_| {
        Error::invalid(
            path,
            format!("attribute '{name}' on {} is not a string", loc.name()),
        )
    })?;
    Ok(v.as_str().to_owned())
}

fn get<T: hdf5::H5Type>(path: &Path, loc: &hdf5::Location, name: &str) -> Result<T> {
    let a = loc.attr(name).map_err(|_| {
        Error::invalid(
            path,
            format!("attribute '{name}' missing on {}", loc.name()),
        )
    })?;
    a.read_scalar().map_err(|e| {
        Error::invalid(
            path,
            format!(
                "attribute '{name}' on {} has the wrong type: {e}",
                loc.name()
            ),
        )
    })
}

/// Read a motion file, checking format, version and shapes. In a program that called
/// [`crate::isolated::isolate_motion_reads`], the file is read by a child process.
pub fn read_motion_file(path: &Path) -> Result<MotionFile> {
    if let Some(reader) = crate::isolated::installed() {
        return reader.read(path);
    }
    let file = open_checked(path)?;
    let format = file
        .attr("format")
        .ok()
        .and_then(|a| a.read_scalar::<VarLenUnicode>().ok());
    match format {
        Some(f) if f.as_str() == MOTION_FORMAT => {}
        Some(f) => {
            return Err(Error::invalid(
                path,
                format!(
                    "HDF5 file of format {}, not a choreod motion file",
                    quote(f.as_str())
                ),
            ));
        }
        None => {
            return Err(Error::invalid(
                path,
                "HDF5 file without format=\"choreod-motion\": not a choreod motion file",
            ));
        }
    }
    let version: i64 = get(path, &file, "format_version")?;
    if version > MOTION_FORMAT_VERSION {
        return Err(Error::UnsupportedVersion {
            path: path.to_path_buf(),
            found: version,
            supported: MOTION_FORMAT_VERSION,
        });
    }
    if version < 1 {
        return Err(Error::invalid(
            path,
            format!("format_version {version} is not valid"),
        ));
    }
    let generator = get_str(path, &file, "generator")?;
    let motion = file
        .group("motion")
        .map_err(|_| Error::invalid(path, "group /motion missing"))?;
    let fps: f32 = get(path, &motion, "fps")?;
    crate::limits::check_fps(fps)
        .map_err(|why| Error::invalid(path, format!("/motion fps: {why}")))?;
    let skel_name = get_str(path, &motion, "skeleton")?;
    let names_attr = motion
        .attr("joint_names")
        .map_err(|_| Error::invalid(path, "attribute joint_names missing on /motion"))?;
    let names: Vec<VarLenUnicode> = names_attr
        .read_raw()
        .map_err(|_| Error::invalid(path, "/motion joint_names is not a list of strings"))?;
    let parents: Vec<i32> = motion
        .attr("parents")
        .and_then(|a| a.read_raw())
        .map_err(|_| Error::invalid(path, "/motion parents missing or not integers"))?;
    let j = parents.len();
    let skeleton = SkeletonKind::from_parts(
        &skel_name,
        names.iter().map(|n| n.as_str().to_owned()).collect(),
        parents,
    );
    // The one hierarchy check (the isolated reader's parent side runs it again on the answer).
    skeleton
        .validate()
        .map_err(|reason| Error::invalid(path, format!("/motion: {reason}")))?;

    let ds = motion
        .dataset("joints")
        .map_err(|_| Error::invalid(path, "dataset /motion/joints missing"))?;
    let shape = ds.shape();
    if shape.len() != 3 || shape[1] != j || shape[2] != 3 {
        return Err(Error::invalid(
            path,
            format!("/motion/joints has shape {shape:?}, expected (T, {j}, 3)"),
        ));
    }
    check_readable(path, &ds)?;
    let joints: Array3<f32> = ds.read().map_err(h5_err(path))?;

    let features = match motion.dataset("features") {
        Ok(ds) => {
            let sh = ds.shape();
            if sh.len() != 2 {
                return Err(Error::invalid(
                    path,
                    format!("/motion/features has shape {sh:?}, expected (T', D)"),
                ));
            }
            check_readable(path, &ds)?;
            Some(Features {
                data: ds.read_2d().map_err(h5_err(path))?,
                representation: get_str(path, &ds, "representation")?,
                normalized: get(path, &ds, "normalized")?,
            })
        }
        Err(_) => None,
    };
    let mel = match file.dataset("audio/mel") {
        Ok(ds) => {
            let sh = ds.shape();
            if sh.len() != 2 || sh[1] != 80 {
                return Err(Error::invalid(
                    path,
                    format!("/audio/mel has shape {sh:?}, expected (F, 80)"),
                ));
            }
            check_readable(path, &ds)?;
            Some(MelAttachment {
                data: ds.read_2d().map_err(h5_err(path))?,
                sample_rate: get(path, &ds, "sample_rate")?,
                n_fft: get(path, &ds, "n_fft")?,
                hop: get(path, &ds, "hop")?,
                fmin: get(path, &ds, "fmin")?,
                fmax: get(path, &ds, "fmax")?,
            })
        }
        Err(_) => None,
    };
    let provenance = match file.group("provenance") {
        Ok(g) => {
            let v2 = version >= 2;
            let optional = |name: &str| -> Result<Option<f32>> {
                match g.attr(name) {
                    Ok(_) => get(path, &g, name).map(Some),
                    Err(_) => Ok(None),
                }
            };
            Some(Provenance {
                source_name: get_str(path, &g, "source_name")?,
                source_sha256: get_str(path, &g, "source_sha256")?,
                model_name: get_str(path, &g, "model_name")?,
                model_sha256: get_str(path, &g, "model_sha256")?,
                sampler: get_str(path, &g, "sampler")?,
                steps: get(path, &g, "steps")?,
                eta: if v2 { get(path, &g, "eta")? } else { 0.0 },
                guidance: get(path, &g, "guidance")?,
                content_guidance: optional("content_guidance")?,
                style_guidance: optional("style_guidance")?,
                seed: get(path, &g, "seed")?,
                chunk_windows: if v2 {
                    get(path, &g, "chunk_windows")?
                } else {
                    0
                },
                init_noise_sha256: if v2 {
                    get_str(path, &g, "init_noise_sha256")?
                } else {
                    String::new()
                },
                started_utc: get_str(path, &g, "started_utc")?,
                finished_utc: get_str(path, &g, "finished_utc")?,
                style: match g.attr("style_mode") {
                    Ok(_) => Some(StyleProvenance {
                        mode: get_str(path, &g, "style_mode")?,
                        name: get_str(path, &g, "style_name")?,
                        sha256: get_str(path, &g, "style_sha256")?,
                    }),
                    Err(_) => None,
                },
                license: match g.attr("license") {
                    Ok(_) => get_str(path, &g, "license")?,
                    Err(_) => String::new(),
                },
                source_damage: match g.attr("source_damage") {
                    Ok(_) => Some(get_str(path, &g, "source_damage")?),
                    Err(_) => None,
                },
                source_kind: match g.attr("source_kind") {
                    Ok(_) => Some(get_str(path, &g, "source_kind")?),
                    Err(_) => None,
                },
                source_beat: match g.attr("source_beat") {
                    Ok(_) => Some(get_str(path, &g, "source_beat")?),
                    Err(_) => None,
                },
                library: match g.attr("library") {
                    Ok(_) => Some(get_str(path, &g, "library")?),
                    Err(_) => None,
                },
            })
        }
        Err(_) => None,
    };
    Ok(MotionFile {
        fps,
        skeleton,
        joints,
        features,
        mel,
        provenance,
        generator,
    })
}

/// Writes a motion file frame by frame for live use. The file lives under a temporary name in
/// the target directory until [`MotionAppender::finish`] renames it into place; dropping an
/// unfinished appender deletes the temporary file.
#[derive(Debug)]
pub struct MotionAppender {
    path: PathBuf,
    tmp: PathBuf,
    file: Option<hdf5::File>,
    joints: Option<hdf5::Dataset>,
    frames: usize,
    num_joints: usize,
    /// `/audio/mel` when the header had a mel, and its rows so far.
    mel: Option<hdf5::Dataset>,
    mel_frames: usize,
}

impl MotionAppender {
    /// Start a file at `path` (written as a temporary file) with the header, features and mel
    /// of `header`; its `joints` (possibly zero frames) are the first frames. Provenance is
    /// written by [`MotionAppender::finish`].
    pub fn create(path: &Path, header: &MotionFile) -> Result<Self> {
        let tmp = temp_path(path);
        let file = h5_writer().create(&tmp).map_err(h5_err(path))?;
        let joints = match write_layout(path, &file, header, None) {
            Ok(j) => j,
            Err(e) => {
                drop(file);
                let _ = std::fs::remove_file(&tmp);
                return Err(e);
            }
        };
        let mel = match &header.mel {
            Some(_) => Some(file.dataset("audio/mel").map_err(h5_err(path))?),
            None => None,
        };
        Ok(MotionAppender {
            path: path.to_path_buf(),
            tmp,
            file: Some(file),
            joints: Some(joints),
            frames: header.joints.shape()[0],
            num_joints: header.skeleton.num_joints(),
            mel,
            mel_frames: header.mel.as_ref().map_or(0, |m| m.data.nrows()),
        })
    }

    /// Frames written so far.
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// Append frames (n, J, 3).
    pub fn append(&mut self, frames: ArrayView3<'_, f32>) -> Result<()> {
        let sh = frames.shape();
        if sh[1] != self.num_joints || sh[2] != 3 {
            return Err(Error::invalid(
                &self.path,
                format!(
                    "appended frames have shape {sh:?}, expected (n, {}, 3)",
                    self.num_joints
                ),
            ));
        }
        let Some(ds) = &self.joints else {
            return Err(Error::invalid(&self.path, "appender already finished"));
        };
        let n = sh[0];
        if n == 0 {
            return Ok(());
        }
        let end = self.frames + n;
        ds.resize((end, self.num_joints, 3))
            .map_err(h5_err(&self.path))?;
        ds.write_slice(frames, s![self.frames..end, .., ..])
            .map_err(h5_err(&self.path))?;
        self.frames = end;
        Ok(())
    }

    /// Append log-mel frames (n, n_mels) to `/audio/mel` (the header must have had a mel).
    pub fn append_mel(&mut self, frames: ArrayView2<'_, f32>) -> Result<()> {
        let Some(ds) = &self.mel else {
            return Err(Error::invalid(
                &self.path,
                "motion file was started without a mel",
            ));
        };
        let n_mels = ds.shape().get(1).copied().unwrap_or(0);
        let (n, cols) = frames.dim();
        if cols != n_mels {
            return Err(Error::invalid(
                &self.path,
                format!("appended mel has {cols} bands, the file has {n_mels}"),
            ));
        }
        if n == 0 {
            return Ok(());
        }
        let end = self.mel_frames + n;
        ds.resize((end, n_mels)).map_err(h5_err(&self.path))?;
        ds.write_slice(frames, s![self.mel_frames..end, ..])
            .map_err(h5_err(&self.path))?;
        self.mel_frames = end;
        Ok(())
    }

    /// The temporary file the frames go to until [`MotionAppender::finish`] (what a crash
    /// leaves behind, readable up to the last [`MotionAppender::flush`]).
    pub fn temp_path(&self) -> &Path {
        &self.tmp
    }

    /// Push written frames to the OS (call periodically; a crash loses at most the frames since).
    pub fn flush(&self) -> Result<()> {
        match &self.file {
            Some(f) => f.flush().map_err(h5_err(&self.path)),
            None => Ok(()),
        }
    }

    /// Write provenance (if any), close, fsync and rename into place. If that fails, the
    /// temporary file (flushed up to the last [`flush`](Self::flush)) is kept, and the error
    /// names it: it holds a recording that cannot be made again.
    pub fn finish(mut self, provenance: Option<&Provenance>) -> Result<()> {
        let res = (|| {
            if let Some(file) = &self.file {
                if let Some(p) = provenance {
                    write_provenance(&self.path, file, p)?;
                }
                file.flush().map_err(h5_err(&self.path))?;
            }
            self.joints = None;
            self.mel = None;
            self.file = None;
            commit_atomic(&self.tmp, &self.path).map_err(io_err(&self.path))
        })();
        let kept = std::mem::take(&mut self.tmp);
        res.map_err(|e| {
            self.joints = None;
            self.mel = None;
            self.file = None;
            Error::Unfinished {
                path: self.path.clone(),
                kept,
                source: Box::new(e),
            }
        })
    }
}

impl Drop for MotionAppender {
    fn drop(&mut self) {
        self.joints = None;
        self.mel = None;
        self.file = None;
        if !self.tmp.as_os_str().is_empty() {
            let _ = std::fs::remove_file(&self.tmp);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array;

    fn sample() -> MotionFile {
        let joints =
            Array::from_shape_fn((10, 24, 3), |(t, j, k)| (t * 100 + j * 3 + k) as f32 * 0.01);
        let mut m = MotionFile::from_joints(30.0, SkeletonKind::Smpl24, joints);
        m.features = Some(Features {
            data: Array2::from_shape_fn((9, 263), |(t, d)| (t + d) as f32),
            representation: "humanml3d263".into(),
            normalized: false,
        });
        m.mel = Some(MelAttachment {
            data: Array2::from_shape_fn((11, 80), |(t, d)| -(t as f32) - d as f32),
            sample_rate: 16000,
            n_fft: 2048,
            hop: 512,
            fmin: 0.0,
            fmax: 8000.0,
        });
        m.provenance = Some(Provenance {
            source_name: "song.ogg".into(),
            source_sha256: "ab".repeat(32),
            model_name: "mofusion-tiny".into(),
            model_sha256: "cd".repeat(32),
            sampler: "ddim".into(),
            steps: 50,
            eta: 0.25,
            guidance: 2.5,
            content_guidance: Some(1.5),
            style_guidance: Some(3.0),
            seed: u64::MAX - 1,
            chunk_windows: 32,
            init_noise_sha256: "ef".repeat(32),
            started_utc: "2026-11-22T01:00:00Z".into(),
            finished_utc: "2026-11-22T01:00:05Z".into(),
            style: Some(StyleProvenance {
                mode: "inversion".into(),
                name: "dancer.bvh".into(),
                sha256: "01".repeat(32),
            }),
            license: "licence: test (commercial use not allowed)".into(),
            source_damage: Some("the file ends mid-stream: 12.026 s of audio decoded".into()),
            source_kind: Some("fact35 features (T, 35)".into()),
            source_beat: Some("no steady beat (periodicity 0.19): danced anyway".into()),
            library: Some("clips used: a, b; attribution: test".into()),
        });
        m
    }

    #[test]
    fn write_read_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.h5");
        let m = sample();
        write_motion_file(&p, &m).unwrap();
        let back = read_motion_file(&p).unwrap();
        assert_eq!(back, m);
        // Only the final file remains: no temporary left behind.
        let names: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(names, vec![std::ffi::OsString::from("a.h5")]);
    }

    #[test]
    fn appender_extends_and_renames_only_on_finish() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("live.h5");
        let full = sample();
        let mut header = MotionFile::from_joints(
            30.0,
            SkeletonKind::Smpl24,
            full.joints.slice(s![..3, .., ..]).to_owned(),
        );
        header.generator = full.generator.clone();
        let mel = full.mel.clone().unwrap();
        header.mel = Some(MelAttachment {
            data: mel.data.slice(s![..0, ..]).to_owned(),
            ..mel.clone()
        });
        let mut app = MotionAppender::create(&p, &header).unwrap();
        app.append_mel(mel.data.slice(s![..4, ..])).unwrap();
        app.append(full.joints.slice(s![3..7, .., ..])).unwrap();
        app.append_mel(mel.data.slice(s![4.., ..])).unwrap();
        assert!(app.append_mel(mel.data.slice(s![.., ..3])).is_err());
        app.flush().unwrap();
        assert!(!p.exists(), "final name visible before finish");
        app.append(full.joints.slice(s![7.., .., ..])).unwrap();
        assert_eq!(app.frames(), 10);
        app.finish(full.provenance.as_ref()).unwrap();
        let back = read_motion_file(&p).unwrap();
        assert_eq!(back.joints, full.joints);
        assert_eq!(back.mel, Some(mel));
        assert_eq!(back.provenance, full.provenance);
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn a_recording_that_cannot_be_renamed_is_kept_and_named() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("take.h5");
        let mut app = MotionAppender::create(&p, &sample()).unwrap();
        app.append(sample().joints.view()).unwrap();
        let tmp = app.temp_path().to_path_buf();
        // A non-empty directory at the final name: the rename fails.
        std::fs::create_dir_all(p.join("occupied")).unwrap();
        let e = app.finish(None).unwrap_err().to_string();
        assert!(e.contains(&tmp.display().to_string()), "{e}");
        let kept = read_motion_file(&tmp).unwrap();
        assert_eq!(kept.joints.dim().0, 2 * sample().joints.dim().0);
    }

    #[test]
    fn dropped_appender_leaves_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("x.h5");
        let app = MotionAppender::create(&p, &sample()).unwrap();
        drop(app);
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }

    #[test]
    fn foreign_and_newer_files_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        // Not HDF5 at all.
        let p = dir.path().join("text.h5");
        std::fs::write(&p, b"hello").unwrap();
        let e = read_motion_file(&p).unwrap_err().to_string();
        assert!(
            e.contains("text.h5") && e.contains("not an HDF5 file"),
            "{e}"
        );
        // HDF5 but not ours.
        let p = dir.path().join("other.h5");
        {
            let f = hdf5::File::create(&p).unwrap();
            f.new_dataset::<f32>().shape((2, 2)).create("x").unwrap();
        }
        let e = read_motion_file(&p).unwrap_err().to_string();
        assert!(e.contains("not a choreod motion file"), "{e}");
        // Ours, but from the future.
        let p = dir.path().join("new.h5");
        write_motion_file(&p, &sample()).unwrap();
        set_format_version(&hdf5::File::append(&p).unwrap(), 3);
        let e = read_motion_file(&p).unwrap_err();
        assert!(
            matches!(e, Error::UnsupportedVersion { found: 3, .. }),
            "{e}"
        );
    }

    /// Rewrite the file's `format_version` attribute (files of other versions).
    fn set_format_version(f: &hdf5::File, version: i64) {
        f.delete_attr("format_version").unwrap();
        f.new_attr::<i64>()
            .create("format_version")
            .unwrap()
            .write_scalar(&version)
            .unwrap();
    }

    #[test]
    fn version_1_files_are_still_read() {
        // A version-1 file: the version-2 writer's output with version 1 and without the
        // provenance attributes version 2 added.
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("v1.h5");
        write_motion_file(&p, &sample()).unwrap();
        {
            let f = hdf5::File::append(&p).unwrap();
            set_format_version(&f, 1);
            let g = f.group("provenance").unwrap();
            for name in [
                "eta",
                "content_guidance",
                "style_guidance",
                "chunk_windows",
                "init_noise_sha256",
            ] {
                g.delete_attr(name).unwrap();
            }
        }
        let back = read_motion_file(&p).unwrap();
        let mut want = sample().provenance.unwrap();
        want.eta = 0.0;
        want.content_guidance = None;
        want.style_guidance = None;
        want.chunk_windows = 0;
        want.init_noise_sha256 = String::new();
        assert_eq!(back.provenance, Some(want));
        assert_eq!(back.joints, sample().joints);
        // A version-2 file without them is damaged, not old.
        let p2 = dir.path().join("v2.h5");
        write_motion_file(&p2, &sample()).unwrap();
        hdf5::File::append(&p2)
            .unwrap()
            .group("provenance")
            .unwrap()
            .delete_attr("chunk_windows")
            .unwrap();
        let e = read_motion_file(&p2).unwrap_err().to_string();
        assert!(e.contains("chunk_windows"), "{e}");
    }

    #[test]
    fn a_missing_file_is_named_with_the_systems_reason() {
        // Issue 23 item 10: the reader said "entity not found" (an io::ErrorKind's text).
        let dir = tempfile::tempdir().unwrap();
        let e = read_motion_file(&dir.path().join("gone.h5")).unwrap_err();
        let why = std::error::Error::source(&e).map(ToString::to_string);
        assert!(e.to_string().contains("gone.h5"), "{e}");
        assert!(
            why.as_deref()
                .is_some_and(|w| w.contains("No such file or directory")),
            "{why:?}"
        );
    }

    #[test]
    fn h5py_sees_the_documented_layout() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("layout.h5");
        write_motion_file(&p, &sample()).unwrap();
        let script = r#"
import sys, h5py, numpy as np
f = h5py.File(sys.argv[1], "r")
a = f.attrs
assert a["format"] == "choreod-motion", a["format"]
assert int(a["format_version"]) == 2
assert a["generator"].startswith("choreod ")
assert len(a["created_utc"]) == 20 and a["created_utc"].endswith("Z")
m = f["motion"]
assert abs(float(m.attrs["fps"]) - 30.0) < 1e-6
assert m.attrs["skeleton"] == "smpl24"
assert list(m.attrs["joint_names"])[:3] == ["root", "lhip", "rhip"], m.attrs["joint_names"]
assert list(m.attrs["parents"])[:4] == [-1, 0, 0, 0]
assert m.attrs["up_axis"] == "y" and m.attrs["units"] == "m"
j = m["joints"]
assert j.dtype == np.float32 and j.shape == (10, 24, 3), (j.dtype, j.shape)
assert j.chunks is not None and j.maxshape == (None, 24, 3), (j.chunks, j.maxshape)
assert abs(j[9, 23, 2] - (900 + 69 + 2) * 0.01) < 1e-4
ft = m["features"]
assert ft.dtype == np.float32 and ft.shape == (9, 263)
assert ft.attrs["representation"] == "humanml3d263" and not bool(ft.attrs["normalized"])
mel = f["audio/mel"]
assert mel.shape == (11, 80) and mel.dtype == np.float32
assert int(mel.attrs["sample_rate"]) == 16000 and int(mel.attrs["hop"]) == 512
assert int(mel.attrs["n_fft"]) == 2048 and float(mel.attrs["fmax"]) == 8000.0 and float(mel.attrs["fmin"]) == 0.0
p = f["provenance"].attrs
for k in ["source_name", "source_sha256", "model_name", "model_sha256", "sampler", "started_utc", "finished_utc"]:
    assert isinstance(p[k], str), k
assert int(p["steps"]) == 50 and abs(float(p["guidance"]) - 2.5) < 1e-6 and int(p["seed"]) == 2**64 - 2
assert float(p["eta"]) == 0.25 and int(p["chunk_windows"]) == 32 and p["init_noise_sha256"] == "ef" * 32
assert float(p["content_guidance"]) == 1.5 and float(p["style_guidance"]) == 3.0
print("ok")
"#;
        let out = std::process::Command::new(crate::formats::h5::venv_python())
            .arg("-c")
            .arg(script)
            .arg(&p)
            .output()
            .expect("run the venv python (set CHOREOD_PYTHON)");
        assert!(
            out.status.success() && String::from_utf8_lossy(&out.stdout).trim() == "ok",
            "h5py check failed: {}",
            String::from_utf8_lossy(&out.stderr)
        );
    }

    #[test]
    fn mismatched_joint_shape_is_refused_on_write() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("bad.h5");
        let m = MotionFile::from_joints(30.0, SkeletonKind::T2m22, Array3::zeros((4, 24, 3)));
        let e = write_motion_file(&p, &m).unwrap_err().to_string();
        assert!(e.contains("(T, 22, 3)"), "{e}");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }
}
