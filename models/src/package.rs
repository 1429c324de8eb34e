//! A loaded model package: its manifest and one session per component.

use std::collections::BTreeMap;
use std::fmt;
use std::path::{Path, PathBuf};

use ndarray::Array3;

use crate::diffusion::sampler::Denoiser;
use crate::error::{Error, Result};
use crate::manifest::{Manifest, Task, shape_text};
use crate::runtime::OrtRuntime;
use crate::session::{ComponentSession, RuntimeOptions};

/// A model package ready to run.
#[derive(Debug)]
pub struct ModelPackage {
    dir: PathBuf,
    manifest: Manifest,
    sessions: BTreeMap<String, ComponentSession>,
    options: RuntimeOptions,
}

impl ModelPackage {
    /// Load `dir`: parse and validate the manifest, then check and load every component.
    ///
    /// Errors are environment errors ([`Error::is_environment`]): the package cannot be used.
    pub fn load(dir: &Path, options: &RuntimeOptions, ort: &OrtRuntime) -> Result<Self> {
        let manifest = Manifest::load(dir)?;
        let mut sessions = BTreeMap::new();
        for (name, spec) in &manifest.components {
            let session = ComponentSession::load(ort, dir, name, spec, options)?;
            tracing::debug!(package = %dir.display(), component = %name, bytes = session.file_bytes(), "component loaded");
            sessions.insert(name.clone(), session);
        }
        Ok(Self {
            dir: dir.to_path_buf(),
            manifest,
            sessions,
            options: options.clone(),
        })
    }

    /// The package directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The validated manifest.
    pub fn manifest(&self) -> &Manifest {
        &self.manifest
    }

    /// Loaded components by name.
    pub fn components(&self) -> impl Iterator<Item = &ComponentSession> {
        self.sessions.values()
    }

    /// The `denoiser` component (music-to-dance packages always have one).
    pub fn denoiser(&mut self) -> Result<&mut ComponentSession> {
        let dir = self.dir.clone();
        self.sessions.get_mut("denoiser").ok_or(Error::Manifest {
            package: dir,
            key: "components.denoiser".into(),
            reason: "missing".into(),
        })
    }

    /// Seconds all components spent in ONNX Runtime since load.
    pub fn ort_seconds(&self) -> f64 {
        self.sessions
            .values()
            .map(ComponentSession::ort_seconds)
            .sum()
    }

    /// Run the denoiser on a zero window at the noisiest and the cleanest timestep, with and
    /// without conditioning: catches graphs that fail at run time or emit NaN/Inf. Returns the
    /// two predictions (empty for tasks without a denoiser), e.g. to compare two loads.
    pub fn smoke_test(&mut self) -> Result<Vec<Array3<f32>>> {
        if self.manifest.task != Task::MusicToDance {
            return Ok(Vec::new());
        }
        let m = &self.manifest;
        let (frames, dim) = (m.motion.window_frames, m.motion.dim);
        let (music_frames, mels) = (m.audio.music_frames, m.audio.n_mels);
        let last = m.diffusion.train_steps as i64 - 1;
        let x = Array3::<f32>::zeros((2, frames, dim));
        // A ramp over -80..-20 dB: mid-range log-mel values that differ per frame and band.
        let music = Array3::<f32>::from_shape_fn((2, music_frames, mels), |(_, f, b)| {
            -80.0 + ((f * 7 + b * 3) % 61) as f32
        });
        let denoiser = self.denoiser()?;
        let outputs = [last, 0]
            .into_iter()
            .map(|t| denoiser.predict(x.view(), &[t, t], music.view(), &[1.0, 0.0]))
            .collect::<Result<Vec<_>>>()?;
        denoiser.finish_batch();
        Ok(outputs)
    }

    /// For a package whose denoiser was split ([`crate::Hoisting`]): load the whole graph as
    /// well, run [`Self::smoke_test`] on both and return the largest difference relative to the
    /// output scale. None when nothing was hoisted. An error when the difference exceeds 1e-5 of
    /// the scale (ONNX Runtime may fuse operators differently on either side of the split, which
    /// moves float32 results by a few ulps; a wrong split moves them by O(1)).
    pub fn verify_hoisting(&mut self, ort: &OrtRuntime) -> Result<Option<f32>> {
        if self.denoiser()?.hoisting().is_none() {
            return Ok(None);
        }
        let split = self.smoke_test()?;
        let mut options = self.options.clone();
        options.hoist_invariants = false;
        let whole = Self::load(&self.dir, &options, ort)?.smoke_test()?;
        let gap = split.iter().zip(&whole).fold(0.0f32, |gap, (a, b)| {
            let scale = b.iter().fold(1.0f32, |m, v| m.max(v.abs()));
            let diff = a
                .iter()
                .zip(b)
                .fold(0.0f32, |m, (x, y)| m.max((x - y).abs()));
            gap.max(diff / scale)
        });
        if gap > 1e-5 {
            return Err(Error::Run {
                package: self.dir.clone(),
                component: "denoiser".into(),
                reason: format!(
                    "the hoisted denoiser differs from the whole graph by {gap:e} of the output \
                     scale; please report this, and run with hoisting off meanwhile \
                     (`choreod dance --no-hoist`)"
                ),
            });
        }
        Ok(Some(gap))
    }
}

/// A human summary (for `choreod models check`).
impl fmt::Display for ModelPackage {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let m = &self.manifest;
        writeln!(f, "package     {} ({})", m.name, self.dir.display())?;
        if !m.description.is_empty() {
            writeln!(f, "description {}", m.description)?;
        }
        writeln!(f, "task        {}", m.task.as_str())?;
        let mo = &m.motion;
        writeln!(
            f,
            "motion      {} fps, skeleton {}, representation {} (D = {})",
            mo.fps, mo.skeleton, mo.representation, mo.dim
        )?;
        writeln!(
            f,
            "window      {} frames ({:.2} s), stride {} frames, overlap {}",
            mo.window_frames,
            mo.window_frames as f64 / mo.fps,
            mo.stride_frames,
            mo.overlap_frames()
        )?;
        let a = &m.audio;
        writeln!(
            f,
            "audio       {} Hz, n_fft {}, hop {}, {} mels {}-{} Hz, top_db {}, {} frames per window",
            a.sample_rate, a.n_fft, a.hop, a.n_mels, a.fmin, a.fmax, a.top_db, a.music_frames
        )?;
        let d = &m.diffusion;
        writeln!(
            f,
            "schedule    {} steps, {} betas {}..{}, predicts {}{}",
            d.train_steps,
            d.beta_schedule.as_str(),
            d.beta_start,
            d.beta_end,
            d.prediction.as_str(),
            if d.clip_sample { ", clip_sample" } else { "" }
        )?;
        let s = &m.sampler;
        writeln!(
            f,
            "sampler     {} {} steps, eta {}, steps_offset {}, set_alpha_to_one {}, guidance {}",
            s.kind.as_str(),
            s.steps,
            s.eta,
            s.steps_offset,
            s.set_alpha_to_one,
            s.guidance
        )?;
        for c in self.sessions.values() {
            writeln!(
                f,
                "component   {}: {} ({} bytes, sha256 {})",
                c.name(),
                c.spec().file,
                c.file_bytes(),
                c.sha256()
            )?;
            if let Some(info) = c.onnx_info() {
                let opsets: Vec<String> = info
                    .opsets
                    .iter()
                    .map(|(d, v)| {
                        if d.is_empty() {
                            v.to_string()
                        } else {
                            format!("{d}:{v}")
                        }
                    })
                    .collect();
                writeln!(
                    f,
                    "  onnx ir {}, opset {}, {} stored weight values (initializers and constants)",
                    info.ir_version,
                    opsets.join(" "),
                    info.stored_values
                )?;
            }
            if let Some(h) = c.hoisting() {
                writeln!(
                    f,
                    "  hoisted {} of {} nodes out of the step loop: {} {} computed once per batch of music",
                    h.hoisted_nodes,
                    h.total_nodes,
                    h.frontier_tensors,
                    if h.frontier_tensors == 1 {
                        "tensor"
                    } else {
                        "tensors"
                    }
                )?;
            }
            for (dir, list) in [("in ", &c.spec().inputs), ("out", &c.spec().outputs)] {
                for t in list {
                    writeln!(
                        f,
                        "  {dir} {:<8} {:<8} {}",
                        t.name,
                        t.dtype.as_str(),
                        shape_text(&t.shape)
                    )?;
                }
            }
        }
        Ok(())
    }
}
