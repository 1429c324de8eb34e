//! The package layer: a model package on disk — its [`Manifest`] (task, sections, components
//! by [`Role`]) and, loaded, one runtime [`Component`] per role ([`ModelPackage`]).

pub(crate) mod manifest;

use std::collections::BTreeMap;
use std::fmt;
use std::path::{Path, PathBuf};

use ndarray::{Array2, Array3, ArrayD, Axis};

use crate::diffusion::schedule::{BetaSchedule, COSINE_MAX_BETA, COSINE_S};
use crate::error::{Error, Result};
use crate::runtime::OrtRuntime;
use crate::runtime::component::{Component, RuntimeOptions, TensorView};
use manifest::{Manifest, Role, Task, shape_text};

/// One component's share of ONNX Runtime's time ([`ModelPackage::ort_profile`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
#[non_exhaustive]
pub struct ComponentTime {
    /// The component's role in the manifest (`denoiser`, `global_music`, ...).
    pub role: &'static str,
    /// Calls of the component since load.
    pub runs: usize,
    /// Seconds in ONNX Runtime, its hoisted prologue included.
    pub seconds: f64,
    /// Runs of the hoisted step-invariant prologue (once per batch of constant inputs).
    pub prologue_runs: usize,
    /// Of `seconds`, the prologue's.
    pub prologue_seconds: f64,
}

/// A model package ready to run.
#[derive(Debug)]
pub struct ModelPackage {
    dir: PathBuf,
    manifest: Manifest,
    components: BTreeMap<Role, Component>,
    options: RuntimeOptions,
}

impl ModelPackage {
    /// Load `dir`: parse and validate the manifest, then check and load every component (the
    /// denoiser with its step-invariant work hoisted, [`Task::step_inputs`]).
    ///
    /// Errors are environment errors ([`Error::is_environment`]): the package cannot be used.
    pub fn load(dir: &Path, options: &RuntimeOptions, ort: &OrtRuntime) -> Result<Self> {
        let manifest = Manifest::load(dir)?;
        let mut components = BTreeMap::new();
        for (&role, spec) in &manifest.components {
            let step_inputs = manifest.task.step_inputs(role);
            let component = Component::load(ort, dir, role.as_str(), spec, step_inputs, options)?;
            tracing::debug!(package = %dir.display(), component = %role, bytes = component.file_bytes(), "component loaded");
            components.insert(role, component);
        }
        Ok(Self {
            dir: dir.to_path_buf(),
            manifest,
            components,
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

    /// Loaded components, in role order.
    pub fn components(&self) -> impl Iterator<Item = &Component> {
        self.components.values()
    }

    /// The component of `role`; an error naming the key when the package's task has none.
    pub fn component(&mut self, role: Role) -> Result<&mut Component> {
        self.components
            .get_mut(&role)
            .ok_or_else(|| Error::Manifest {
                package: self.dir.clone(),
                key: format!("components.{role}"),
                reason: format!("missing ({} packages have none)", self.manifest.task),
            })
    }

    /// Hold every component's runs to `deadline` ([`crate::Deadline`]); None: no limit.
    pub fn set_deadline(&mut self, deadline: Option<crate::Deadline>) {
        for component in self.components.values_mut() {
            component.set_deadline(deadline);
        }
    }

    /// Seconds all components spent in ONNX Runtime since load.
    pub fn ort_seconds(&self) -> f64 {
        self.components.values().map(Component::ort_seconds).sum()
    }

    /// Where ONNX Runtime's time went since load, per component (in role order): what `--stats`
    /// prints so a user can see which network to quantise or hoist.
    pub fn ort_profile(&self) -> Vec<ComponentTime> {
        self.components
            .iter()
            .map(|(role, c)| ComponentTime {
                role: role.as_str(),
                runs: c.runs(),
                seconds: c.ort_seconds(),
                prologue_runs: c.hoisting().map_or(0, |h| h.prologue_runs),
                prologue_seconds: c.prologue_seconds(),
            })
            .collect()
    }

    /// Run every component once on small inputs: catches graphs that fail at run time, give
    /// shapes other than the manifest's, or emit NaN/Inf. Returns the denoiser's predictions
    /// at the noisiest and the cleanest timestep (rows with and without conditioning), e.g. to
    /// compare two loads.
    pub fn smoke_test(&mut self) -> Result<Vec<ArrayD<f32>>> {
        match self.manifest.task {
            Task::MusicToDance => self.smoke_test_dance(),
            Task::StyleTransfer => self.smoke_test_style(),
            Task::Lodge => self.smoke_test_lodge(),
        }
    }

    /// Both LODGE stages on their own test inputs: each music branch with the music kept and
    /// dropped, each denoiser at the first and last timestep (the local one with genre 0 and
    /// 1 and fixed style noise).
    fn smoke_test_lodge(&mut self) -> Result<Vec<ArrayD<f32>>> {
        let m = self.manifest.clone();
        let spec = m.lodge_spec()?;
        let l = spec.section;
        let t = [
            spec.timesteps[0],
            *spec.timesteps.last().expect("validated"),
        ];
        let mut outputs = Vec::new();
        for manifest::StageLayout {
            music: music_role,
            denoiser: denoiser_role,
            music_frames,
            frames,
        } in l.stages()
        {
            // Features in -0.5..0.5 that differ per frame and column.
            let music = Array3::<f32>::from_shape_fn((2, music_frames, 35), |(_, f, c)| {
                0.01 * ((f * 7 + c * 3) % 101) as f32 - 0.5
            });
            let mut cond = self.component(music_role)?.run(&[
                ("music", music.view().into()),
                ("keep", ndarray::aview1(&[1.0f32, 0.0]).into()),
            ])?;
            // The music outputs by name: the denoiser takes them all (validated at load); all but
            // cond_hidden (the tokens, or the keys and values) are returned too.
            let music_out: Vec<(String, ArrayD<f32>)> = m.components[&music_role]
                .outputs
                .iter()
                .map(|spec| Ok((spec.name.clone(), cond.take(&spec.name)?)))
                .collect::<Result<_>>()?;
            let x = Array3::<f32>::from_shape_fn((2, frames, m.motion.dim), |(n, f, c)| {
                0.01 * ((f * 5 + c * 3 + n * 11) % 61) as f32 - 0.3
            });
            let style = Array2::<f32>::from_shape_fn((2, l.local.style_noise), |(n, i)| {
                0.1 * ((i * 7 + n * 3) % 21) as f32 - 1.0
            });
            let denoiser = self.component(denoiser_role)?;
            let mut inputs: Vec<(&str, TensorView<'_>)> =
                vec![("x_t", x.view().into()), ("t", ndarray::aview1(&t).into())];
            inputs.extend(
                music_out
                    .iter()
                    .map(|(name, v)| (name.as_str(), v.view().into())),
            );
            let genre = [0i64, 1];
            if denoiser_role == Role::LocalDenoiser {
                inputs.push(("genre", ndarray::aview1(&genre).into()));
                inputs.push(("style_noise", style.view().into()));
            }
            outputs.push(denoiser.run(&inputs)?.take("x0")?);
            outputs.extend(
                music_out
                    .into_iter()
                    .filter(|(name, _)| name != "cond_hidden")
                    .map(|(_, v)| v),
            );
        }
        Ok(outputs)
    }

    fn smoke_test_dance(&mut self) -> Result<Vec<ArrayD<f32>>> {
        let m = &self.manifest;
        let dance = m.dance_spec()?;
        let (frames, dim) = (dance.window_frames, m.motion.dim);
        let (music_frames, mels) = (dance.audio.music_frames, dance.audio.n_mels);
        let last = m.diffusion.train_steps as i64 - 1;
        let x = Array3::<f32>::zeros((2, frames, dim));
        // A ramp over -80..-20 dB: mid-range log-mel values that differ per frame and band.
        let music = Array3::<f32>::from_shape_fn((2, music_frames, mels), |(_, f, b)| {
            -80.0 + ((f * 7 + b * 3) % 61) as f32
        });
        let denoiser = self.component(Role::Denoiser)?;
        let outputs = [last, 0]
            .into_iter()
            .map(|t| {
                denoiser
                    .run(&[
                        ("x_t", x.view().into()),
                        ("t", ndarray::aview1(&[t, t]).into()),
                        ("music", music.view().into()),
                        ("cond", ndarray::aview1(&[1.0f32, 0.0]).into()),
                    ])?
                    .take("pred")
            })
            .collect::<Result<Vec<_>>>()?;
        denoiser.finish_batch();
        Ok(outputs)
    }

    /// Two motions of `min_frames` frames through the VAE and the style encoder, then the
    /// denoiser on the encoded latent with a style row and a null-style row.
    fn smoke_test_style(&mut self) -> Result<Vec<ArrayD<f32>>> {
        let m = &self.manifest;
        let (frames, dim) = (m.style_spec()?.min_frames, m.motion.dim);
        let last = m.diffusion.train_steps as i64 - 1;
        // Features in -0.3..0.3 that differ per frame and channel, with dims 0..3 (root
        // velocity and height, which the contract zeroes) at 0.
        let features = Array3::<f32>::from_shape_fn((2, frames, dim), |(n, f, c)| {
            if c < 4 {
                0.0
            } else {
                0.01 * ((f * 7 + c * 3 + n * 11) % 61) as f32 - 0.3
            }
        });
        let mask = Array2::<f32>::ones((2, frames));
        let trajectory = Array3::<f32>::from_shape_fn((2, frames, 3), |(_, f, c)| {
            if c == 1 { 0.9 } else { 0.02 * f as f32 }
        });
        let latent = self
            .component(Role::VaeEncoder)?
            .run(&[
                ("features", features.view().into()),
                ("mask", mask.view().into()),
            ])?
            .take("latent")?;
        let decoded = self
            .component(Role::VaeDecoder)?
            .run(&[
                ("latent", latent.view().into()),
                ("mask", mask.view().into()),
            ])?
            .take("features")?;
        let mut style = self
            .component(Role::StyleEncoder)?
            .run(&[
                ("features", decoded.view().into()),
                ("mask", mask.view().into()),
            ])?
            .take("style")?;
        // Row 1 is the null style (all zeros) of classifier-free guidance.
        style.index_axis_mut(Axis(0), 1).fill(0.0);
        let x_t = ArrayD::<f32>::zeros(latent.shape());
        let denoiser = self.component(Role::Denoiser)?;
        let outputs = [last, 0]
            .into_iter()
            .map(|t| {
                denoiser
                    .run(&[
                        ("x_t", x_t.view().into()),
                        ("t", ndarray::aview1(&[t, t]).into()),
                        ("content", latent.view().into()),
                        ("trajectory", trajectory.view().into()),
                        ("mask", mask.view().into()),
                        ("style", style.view().into()),
                    ])?
                    .take("pred")
            })
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
        if self
            .components
            .get(&Role::Denoiser)
            .is_none_or(|c| c.hoisting().is_none())
        {
            return Ok(None);
        }
        let split = self.smoke_test()?;
        let mut options = self.options.clone();
        options.hoist_invariants = false;
        let mut whole = Self::load(&self.dir, &options, ort)?;
        whole.set_deadline(self.component(Role::Denoiser)?.deadline());
        let whole = whole.smoke_test()?;
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
                     scale; please report this, and run with hoisting off meanwhile"
                ),
            });
        }
        Ok(Some(gap))
    }
}

/// How far one package's outputs are from another's on the same inputs ([`ModelPackage::deviation_from`]).
#[derive(Debug, Clone, Copy, PartialEq)]
#[non_exhaustive]
pub struct Deviation {
    /// Largest |difference| over the largest |reference value|.
    pub max_relative: f64,
    /// RMS of the difference over the reference's RMS.
    pub rms_relative: f64,
}

impl ModelPackage {
    /// Run [`Self::smoke_test`] on this package and on `source` and measure this package's
    /// outputs against the source's — for an int8 package, against the float32 package it was
    /// quantised from. An error when `source` is not that package (its component sha256s differ
    /// from the `[quantization]` section's) or the two packages' outputs differ in shape.
    pub fn deviation_from(&mut self, source: &mut ModelPackage) -> Result<Deviation> {
        if let Some(q) = &self.manifest.quantization {
            for (role, digest) in &q.source_sha256 {
                let got = source.component(*role)?.sha256().to_string();
                if &got != digest {
                    return Err(Error::Manifest {
                        package: self.dir.clone(),
                        key: format!("quantization.source_sha256.{role}"),
                        reason: format!(
                            "{} is not this package's source: its {role} has sha256 {got}",
                            source.dir.display()
                        ),
                    });
                }
            }
        }
        let (got, want) = (self.smoke_test()?, source.smoke_test()?);
        let (mut diff_max, mut ref_max, mut diff_sq, mut ref_sq, mut n) =
            (0.0f64, 0.0f64, 0.0f64, 0.0f64, 0usize);
        if got.len() != want.len() {
            return Err(Error::Run {
                package: self.dir.clone(),
                component: "test run".into(),
                reason: format!(
                    "gives {} outputs where {} gives {}",
                    got.len(),
                    source.dir.display(),
                    want.len()
                ),
            });
        }
        for (i, (g, w)) in got.iter().zip(&want).enumerate() {
            if g.shape() != w.shape() {
                // The test run's outputs are in a fixed order per task, not named by component.
                return Err(Error::Run {
                    package: self.dir.clone(),
                    component: format!("test run output {}", i + 1),
                    reason: format!(
                        "gives shape {:?} where {} gives {:?}",
                        g.shape(),
                        source.dir.display(),
                        w.shape()
                    ),
                });
            }
            for (&a, &b) in g.iter().zip(w) {
                let (a, b) = (f64::from(a), f64::from(b));
                diff_max = diff_max.max((a - b).abs());
                ref_max = ref_max.max(b.abs());
                diff_sq += (a - b) * (a - b);
                ref_sq += b * b;
                n += 1;
            }
        }
        let n = n.max(1) as f64;
        Ok(Deviation {
            max_relative: diff_max / ref_max.max(f64::MIN_POSITIVE),
            rms_relative: (diff_sq / n).sqrt() / (ref_sq / n).sqrt().max(f64::MIN_POSITIVE),
        })
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
        if let Some(license) = &m.license {
            writeln!(f, "{}", license.line())?;
            if !license.summary.is_empty() {
                writeln!(f, "  {}", license.summary)?;
            }
        }
        let mo = &m.motion;
        writeln!(
            f,
            "motion      {} fps, skeleton {}, representation {} (D = {})",
            mo.fps, mo.skeleton, mo.representation, mo.dim
        )?;
        if let Ok(dance) = m.dance_spec() {
            writeln!(
                f,
                "window      {} frames ({:.2} s), stride {} frames, overlap {}",
                dance.window_frames,
                dance.window_frames as f64 / mo.fps,
                dance.stride_frames,
                dance.overlap_frames()
            )?;
            let a = dance.audio;
            writeln!(
                f,
                "audio       {} Hz, n_fft {}, hop {}, {} mels {}-{} Hz, top_db {}, {} frames per window",
                a.sample_rate, a.n_fft, a.hop, a.n_mels, a.fmin, a.fmax, a.top_db, a.music_frames
            )?;
        }
        if let Ok(style) = m.style_spec() {
            writeln!(
                f,
                "segments    content up to {} frames ({:.2} s), style at least {} frames; \
                 inversion {} steps, guidance wc {} ws {}",
                style.max_frames,
                style.max_frames as f64 / mo.fps,
                style.min_frames,
                style.inversion_steps,
                style.content_guidance,
                style.style_guidance
            )?;
        }
        if let Ok(lodge) = m.lodge_spec() {
            let l = lodge.section;
            writeln!(
                f,
                "audio       fact35 at {} fps as librosa {} computes it",
                lodge.audio.fps,
                lodge.audio.librosa_str()
            )?;
            writeln!(
                f,
                "lodge       global {} music frames -> {} keyframes (guidance {}), local {} \
                 frames (guidance ramp {}..{} capped at {}), {} genres: {}",
                l.global.music_frames,
                l.global.keyframes,
                l.global.guidance,
                l.local.frames,
                l.local.guidance_ramp[0],
                l.local.guidance_ramp[1],
                l.local.guidance,
                l.genres.len(),
                l.genres.join(", ")
            )?;
        }
        let d = &m.diffusion;
        // The cosine schedule ignores beta_start/beta_end: show what it computes instead.
        let betas = match d.beta_schedule {
            BetaSchedule::Cosine => {
                format!("cosine betas (s {COSINE_S}, capped at {COSINE_MAX_BETA})")
            }
            other => format!("{} betas {}..{}", other.as_str(), d.beta_start, d.beta_end),
        };
        writeln!(
            f,
            "schedule    {} steps, {betas}{}, predicts {}{}",
            d.train_steps,
            if d.cumprod_dtype == Some(manifest::CumprodDtype::Float32) {
                ", alphas multiplied in float32"
            } else {
                ""
            },
            d.prediction.as_str(),
            if d.clip_sample { ", clip_sample" } else { "" }
        )?;
        let s = &m.sampler;
        match m.lodge_spec() {
            // LODGE samples at the package's timesteps; its guidance is the lodge line's.
            Ok(lodge) => writeln!(
                f,
                "sampler     {} {} steps at timesteps {}, eta {}",
                s.kind.as_str(),
                s.steps,
                timestep_text(lodge.timesteps),
                s.eta
            )?,
            Err(_) => writeln!(
                f,
                "sampler     {} {} steps, eta {}, steps_offset {}, set_alpha_to_one {}, guidance {}",
                s.kind.as_str(),
                s.steps,
                s.eta,
                s.steps_offset,
                s.set_alpha_to_one,
                s.guidance
            )?,
        }
        if let Some(q) = &m.quantization {
            let kept: usize = q.fp32_nodes.values().map(Vec::len).sum();
            writeln!(
                f,
                "quantized   from {} ({}); {kept} nodes left float32; deviation on the quantiser's \
                 test inputs: max {:.3e}, rms {:.3e} (relative)",
                q.source, q.scheme, q.max_relative_error, q.rms_relative_error
            )?;
        }
        for c in self.components.values() {
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
                    "  hoisted {} of {} nodes out of the step loop: {} {} computed once per batch",
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
                        "  {dir} {:<10} {:<8} {}",
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

/// A timestep list as `first, second, ..., last` (the whole list when it is short).
fn timestep_text(t: &[i64]) -> String {
    match t {
        [a, b, .., z] if t.len() > 4 => format!("{a}, {b}, ..., {z}"),
        _ => t.iter().map(i64::to_string).collect::<Vec<_>>().join(", "),
    }
}
