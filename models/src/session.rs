//! ONNX Runtime sessions for package components (runtime): file checks, session creation with
//! the configured threads, and the graph's interface checked against the manifest at load.

use std::borrow::Cow;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::time::Instant;

use ndarray::{Array3, ArrayView1, ArrayView3, Ix3};
use ort::session::builder::GraphOptimizationLevel;
use ort::session::{Session, SessionInputValue};
use ort::value::{DynValue, TensorElementType, TensorRef, ValueType};
use sha2::{Digest, Sha256};

use crate::diffusion::sampler::Denoiser;
use crate::error::{Error, Result};
use crate::hoist::{Dimension, FrontierType, HoistPlan};
use crate::manifest::{ComponentSpec, DType, Dim, TensorSpec, shape_text};
use crate::onnx_info::OnnxInfo;
use crate::runtime::OrtRuntime;

/// Component files larger than this are refused before reading (the paper-size MoFusion is
/// ~100 MB; 4 GiB is beyond what a single-file ONNX model may hold anyway: protobuf's 2 GiB).
const MAX_COMPONENT_BYTES: u64 = 4 << 30;

/// How sessions are created.
#[derive(Debug, Clone, PartialEq, Eq)]
#[non_exhaustive]
pub struct RuntimeOptions {
    /// Threads inside one operator (ORT intra-op); 0 lets ONNX Runtime choose (one per core).
    /// Default: 0.
    pub intra_threads: usize,
    /// Threads across independent operators (ORT inter-op); 0 lets ONNX Runtime choose.
    /// Default: 0.
    pub inter_threads: usize,
    /// Check every component's sha256 against the manifest at load. Default: true.
    pub verify_checksums: bool,
    /// Let ONNX Runtime's intra-op threads spin-wait for work between operators and runs (as
    /// onnxruntime's Python default does). Faster when one generation owns the cores (measured
    /// 7-15 % on `mofusion-ref` paper and `exemplar`, see BENCHMARKS.md); turn it off when
    /// several sessions run at once (the daemon with more than one worker), where spinning
    /// threads take cores from each other. Default: true.
    pub spin_threads: bool,
    /// Split the denoiser graph so that what it computes from the music and condition alone
    /// runs once per batch instead of at every step (see [`Hoisting`]). Default: true.
    pub hoist_invariants: bool,
}

impl Default for RuntimeOptions {
    fn default() -> Self {
        Self {
            intra_threads: 0,
            inter_threads: 0,
            verify_checksums: true,
            spin_threads: true,
            hoist_invariants: true,
        }
    }
}

/// The denoiser contract's inputs that change from step to step; `music` and `cond` do not.
const DENOISER_STEP_INPUTS: [&str; 2] = ["x_t", "t"];

/// Prologue results kept at once: one per guidance row group when the groups run as separate
/// calls (conditional, unconditional, style); a batched call needs one.
const CACHED_BATCHES: usize = 3;

/// How the denoiser's step-invariant work was hoisted out of the denoising loop.
///
/// The graph is split into a prologue, run once per batch of music and condition, and a step
/// graph that takes the prologue's results (the frontier tensors) as inputs. For MoFusion-style
/// networks the prologue holds the music projection and every cross-attention's keys and values.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[non_exhaustive]
pub struct Hoisting {
    /// Nodes that left the step graph.
    pub hoisted_nodes: usize,
    /// Nodes of the whole graph.
    pub total_nodes: usize,
    /// Tensors the prologue hands to the step graph.
    pub frontier_tensors: usize,
    /// Prologue runs since load (one per batch of music and condition).
    pub prologue_runs: usize,
}

/// The prologue session and its results for the latest batches.
#[derive(Debug)]
struct Hoisted {
    prologue: Session,
    frontier: Vec<String>,
    summary: Hoisting,
    /// Most recently used last.
    cache: Vec<CachedBatch>,
}

/// Prologue results for one batch, keyed by the exact music and condition it was run on.
#[derive(Debug)]
struct CachedBatch {
    music_dim: (usize, usize, usize),
    music: Vec<u32>,
    cond: Vec<u32>,
    values: Vec<DynValue>,
}

impl CachedBatch {
    fn matches(&self, music: &ArrayView3<'_, f32>, cond: &[f32]) -> bool {
        // Bit patterns: the same bits give the same prologue results.
        self.music_dim == music.dim()
            && self
                .cond
                .iter()
                .copied()
                .eq(cond.iter().map(|c| c.to_bits()))
            && self
                .music
                .iter()
                .copied()
                .eq(music.iter().map(|m| m.to_bits()))
    }
}

/// One component's ONNX Runtime session, its checked interface and run counters.
#[derive(Debug)]
pub struct ComponentSession {
    package: PathBuf,
    name: String,
    spec: ComponentSpec,
    /// The whole graph, or the step graph when `hoisted` is set.
    session: Session,
    hoisted: Option<Hoisted>,
    file_bytes: u64,
    sha256: String,
    onnx: Option<OnnxInfo>,
    ort_seconds: f64,
    runs: usize,
}

impl ComponentSession {
    /// Read, checksum and load `spec.file` of the package in `package`, then check the graph's
    /// inputs and outputs against `spec`.
    ///
    /// Errors are not recoverable for this package: missing or unreadable file, checksum
    /// mismatch, ONNX Runtime refusing the file (corrupt, unsupported opset), interface mismatch.
    pub fn load(
        ort: &OrtRuntime,
        package: &Path,
        name: &str,
        spec: &ComponentSpec,
        options: &RuntimeOptions,
    ) -> Result<Self> {
        let path = package.join(&spec.file);
        let file_err = |reason: String| Error::ComponentFile {
            package: package.to_path_buf(),
            component: name.to_string(),
            path: path.clone(),
            reason,
        };
        let bytes =
            read_regular_file(&path, MAX_COMPONENT_BYTES).map_err(|e| file_err(e.to_string()))?;
        let sha256 = hex(&Sha256::digest(&bytes));
        if options.verify_checksums && sha256 != spec.sha256 {
            return Err(Error::Checksum {
                package: package.to_path_buf(),
                component: name.to_string(),
                path,
                expected: spec.sha256.clone(),
                got: sha256,
            });
        }
        let load_err = |reason: String| Error::SessionLoad {
            package: package.to_path_buf(),
            component: name.to_string(),
            reason: reason.replace('\n', " "),
        };
        let make_session = |model: &[u8]| -> std::result::Result<Session, String> {
            // Builder errors carry the builder back; only their message is kept.
            let builder_err = |e: ort::Error<_>| ort::Error::<()>::from(e).to_string();
            Session::builder(ort.environment())
                .map_err(|e| e.to_string())?
                .with_optimization_level(GraphOptimizationLevel::All)
                .map_err(builder_err)?
                .with_intra_threads(options.intra_threads)
                .map_err(builder_err)?
                .with_inter_threads(options.inter_threads)
                .map_err(builder_err)?
                .with_intra_op_spinning(options.spin_threads)
                .map_err(builder_err)?
                .commit_from_memory(model)
                .map_err(|e| e.to_string())
        };
        let split = if options.hoist_invariants && name == "denoiser" {
            hoist(&bytes, &make_session).map_err(|why| {
                tracing::debug!(package = %package.display(), component = name, "step-invariant work not hoisted: {why}");
            }).ok()
        } else {
            None
        };
        let (session, hoisted) = match split {
            Some((step, hoisted)) => (step, Some(hoisted)),
            None => (make_session(&bytes).map_err(load_err)?, None),
        };
        let me = Self {
            package: package.to_path_buf(),
            name: name.to_string(),
            spec: spec.clone(),
            session,
            hoisted,
            file_bytes: bytes.len() as u64,
            sha256,
            onnx: crate::onnx_info::inspect(&bytes),
            ort_seconds: 0.0,
            runs: 0,
        };
        me.check_interface()?;
        Ok(me)
    }

    fn tensor_err(&self, tensor: &str, reason: String) -> Error {
        Error::Tensor {
            package: self.package.clone(),
            component: self.name.clone(),
            tensor: tensor.to_string(),
            reason,
        }
    }

    /// Every manifest tensor exists in the graph with the same dtype, rank and fixed sizes, and
    /// the graph needs no input the manifest does not declare.
    fn check_interface(&self) -> Result<()> {
        let frontier: &[String] = self.hoisted.as_ref().map_or(&[], |h| &h.frontier);
        for (kind, specs, outlets) in [
            ("input", &self.spec.inputs, self.session.inputs()),
            ("output", &self.spec.outputs, self.session.outputs()),
        ] {
            let names: Vec<&str> = outlets
                .iter()
                .map(|o| o.name())
                .filter(|n| !frontier.iter().any(|f| f == n))
                .collect();
            for spec in specs {
                let Some(outlet) = outlets.iter().find(|o| o.name() == spec.name) else {
                    return Err(self.tensor_err(
                        &spec.name,
                        format!(
                            "the graph has no {kind} named {:?}; its {kind}s are {names:?}",
                            spec.name
                        ),
                    ));
                };
                self.check_tensor(spec, outlet.dtype())?;
            }
            if kind == "input"
                && let Some(extra) = names.iter().find(|n| !specs.iter().any(|s| s.name == **n))
            {
                return Err(self.tensor_err(
                    extra,
                    "the graph needs this input but the manifest does not declare it".into(),
                ));
            }
        }
        Ok(())
    }

    fn check_tensor(&self, spec: &TensorSpec, graph: &ValueType) -> Result<()> {
        let ValueType::Tensor { ty, shape, .. } = graph else {
            return Err(self.tensor_err(
                &spec.name,
                format!("the graph's value is not a tensor: {graph}"),
            ));
        };
        let want = match spec.dtype {
            DType::Float32 => TensorElementType::Float32,
            DType::Int64 => TensorElementType::Int64,
        };
        let graph_shape: Vec<String> = shape
            .iter()
            .map(|d| {
                if *d < 0 {
                    "?".to_string()
                } else {
                    d.to_string()
                }
            })
            .collect();
        let mismatch = |what: &str| {
            self.tensor_err(
                &spec.name,
                format!(
                    "{what}: the graph has {ty} [{}], the manifest says {} {}",
                    graph_shape.join(", "),
                    spec.dtype.as_str(),
                    shape_text(&spec.shape)
                ),
            )
        };
        if *ty != want {
            return Err(mismatch("dtype differs"));
        }
        if shape.len() != spec.shape.len() {
            return Err(mismatch("rank differs"));
        }
        for (g, m) in shape.iter().zip(&spec.shape) {
            match m {
                // A dynamic graph axis accepts the manifest's fixed size.
                Dim::Fixed(n) if *g >= 0 && g != n => return Err(mismatch("fixed size differs")),
                Dim::Symbol(_) if *g >= 0 => {
                    return Err(mismatch(
                        "the graph fixes an axis the manifest declares dynamic",
                    ));
                }
                _ => {}
            }
        }
        Ok(())
    }

    /// Component name (`denoiser`, ...).
    pub fn name(&self) -> &str {
        &self.name
    }

    /// The manifest's description of this component.
    pub fn spec(&self) -> &ComponentSpec {
        &self.spec
    }

    /// Size of the ONNX file in bytes.
    pub fn file_bytes(&self) -> u64 {
        self.file_bytes
    }

    /// The file's sha256 (lower-case hex).
    pub fn sha256(&self) -> &str {
        &self.sha256
    }

    /// IR version, opsets and stored weight count read from the file (None if unreadable).
    pub fn onnx_info(&self) -> Option<&OnnxInfo> {
        self.onnx.as_ref()
    }

    /// How step-invariant work was hoisted out of the loop; None when the whole graph runs at
    /// every step (not the denoiser, hoisting off, or nothing to hoist).
    pub fn hoisting(&self) -> Option<Hoisting> {
        self.hoisted.as_ref().map(|h| h.summary)
    }

    /// Seconds spent in `Session::run` since load (prologue runs included).
    pub fn ort_seconds(&self) -> f64 {
        self.ort_seconds
    }

    /// Calls of `Session::run` since load.
    pub fn runs(&self) -> usize {
        self.runs
    }

    /// Run the music-to-dance denoiser contract (x_t, t, music, cond → pred), checking the
    /// output's shape and that every value is finite.
    fn run_denoiser(
        &mut self,
        x_t: ArrayView3<'_, f32>,
        t: &[i64],
        music: ArrayView3<'_, f32>,
        cond: &[f32],
    ) -> Result<Array3<f32>> {
        let run_err = |me: &Self, reason: String| Error::Run {
            package: me.package.clone(),
            component: me.name.clone(),
            reason: reason.replace('\n', " "),
        };
        let n = x_t.dim().0;
        if t.len() != n || cond.len() != n || music.dim().0 != n {
            return Err(run_err(
                self,
                format!(
                    "batch sizes differ: x_t {n}, t {}, music {}, cond {}",
                    t.len(),
                    music.dim().0,
                    cond.len()
                ),
            ));
        }
        let started = Instant::now();
        let mut inputs = (|| -> ort::Result<_> {
            Ok(ort::inputs![
                "x_t" => TensorRef::from_array_view(x_t)?,
                "t" => TensorRef::from_array_view(ArrayView1::from(t))?,
                "music" => TensorRef::from_array_view(music)?,
                "cond" => TensorRef::from_array_view(ArrayView1::from(cond))?,
            ])
        })()
        .map_err(|e| run_err(self, e.to_string()))?;
        let (package, name) = (&self.package, &self.name);
        let ort_err = |what: &str, e: ort::Error| Error::Run {
            package: package.clone(),
            component: format!("{name}{what}"),
            reason: e.to_string().replace('\n', " "),
        };
        if let Some(hoisted) = &mut self.hoisted {
            let k = hoisted
                .prologue_results(music, cond)
                .map_err(|e| ort_err(" (prologue)", e))?;
            for (tensor, value) in hoisted.frontier.iter().zip(&hoisted.cache[k].values) {
                inputs.push((Cow::from(tensor.as_str()), SessionInputValue::from(value)));
            }
        }
        let outputs = self.session.run(inputs).map_err(|e| ort_err("", e))?;
        let pred = outputs
            .get("pred")
            .ok_or_else(|| "no output named pred".to_string())
            .and_then(|v| v.try_extract_array::<f32>().map_err(|e| e.to_string()))
            .and_then(|a| {
                a.into_dimensionality::<Ix3>()
                    .map(|a| a.to_owned())
                    .map_err(|_| "output pred is not 3-D".to_string())
            });
        drop(outputs);
        self.ort_seconds += started.elapsed().as_secs_f64();
        self.runs += 1;
        let pred = pred.map_err(|reason| run_err(self, reason))?;
        if pred.dim() != x_t.dim() {
            return Err(self.tensor_err(
                "pred",
                format!("shape {:?}, expected {:?} like x_t", pred.dim(), x_t.dim()),
            ));
        }
        let bad = pred.iter().filter(|v| !v.is_finite()).count();
        if bad > 0 {
            return Err(Error::NonFinite {
                package: self.package.clone(),
                component: self.name.clone(),
                tensor: "pred".into(),
                count: bad,
                timestep: t.first().copied().unwrap_or(-1),
            });
        }
        Ok(pred)
    }
}

impl Hoisted {
    /// The prologue's results for this music and condition, cached or computed now: their index
    /// in `cache`.
    fn prologue_results(&mut self, music: ArrayView3<'_, f32>, cond: &[f32]) -> ort::Result<usize> {
        if let Some(k) = self.cache.iter().position(|b| b.matches(&music, cond)) {
            let hit = self.cache.remove(k);
            self.cache.push(hit);
        } else {
            let mut inputs = Vec::new();
            for outlet in self.prologue.inputs() {
                let value: SessionInputValue<'_> = match outlet.name() {
                    "music" => TensorRef::from_array_view(music)?.into(),
                    "cond" => TensorRef::from_array_view(ArrayView1::from(cond))?.into(),
                    other => {
                        return Err(ort::Error::new(format!(
                            "the prologue needs input {other:?}, which is not step-invariant"
                        )));
                    }
                };
                inputs.push((Cow::from(outlet.name().to_string()), value));
            }
            let mut outputs = self.prologue.run(inputs)?;
            let values = self
                .frontier
                .iter()
                .map(|f| {
                    outputs.remove(f.as_str()).ok_or_else(|| {
                        ort::Error::new(format!("the prologue did not return {f:?}"))
                    })
                })
                .collect::<ort::Result<Vec<_>>>()?;
            drop(outputs);
            self.summary.prologue_runs += 1;
            if self.cache.len() == CACHED_BATCHES {
                self.cache.remove(0);
            }
            self.cache.push(CachedBatch {
                music_dim: music.dim(),
                music: music.iter().map(|m| m.to_bits()).collect(),
                cond: cond.iter().map(|c| c.to_bits()).collect(),
                values,
            });
        }
        Ok(self.cache.len() - 1)
    }
}

/// Split the denoiser `model` into prologue and step sessions ([`HoistPlan`]); `Err` says why
/// it was not split (the caller then loads the whole graph).
fn hoist(
    model: &[u8],
    make_session: &dyn Fn(&[u8]) -> std::result::Result<Session, String>,
) -> std::result::Result<(Session, Hoisted), String> {
    let plan = HoistPlan::new(model, &DENOISER_STEP_INPUTS)?;
    let prologue = make_session(&plan.prologue_model()).map_err(|e| format!("prologue: {e}"))?;
    let types = plan
        .frontier()
        .iter()
        .map(|name| {
            let outlet = prologue
                .outputs()
                .iter()
                .find(|o| o.name() == *name)
                .ok_or_else(|| format!("the prologue has no output {name:?}"))?;
            frontier_type(outlet.dtype())
                .ok_or_else(|| format!("{name:?} has type {}", outlet.dtype()))
        })
        .collect::<std::result::Result<Vec<_>, String>>()?;
    let step = make_session(&plan.step_model(&types)).map_err(|e| format!("step graph: {e}"))?;
    let hoisted = Hoisted {
        prologue,
        frontier: plan.frontier().iter().map(|f| f.to_string()).collect(),
        summary: Hoisting {
            hoisted_nodes: plan.hoisted_nodes(),
            total_nodes: plan.total_nodes(),
            frontier_tensors: plan.frontier().len(),
            prologue_runs: 0,
        },
        cache: Vec::new(),
    };
    Ok((step, hoisted))
}

/// ONNX's declaration of a tensor ONNX Runtime inferred; None for non-tensors and exotic types.
fn frontier_type(value: &ValueType) -> Option<FrontierType> {
    let ValueType::Tensor {
        ty,
        shape,
        dimension_symbols,
    } = value
    else {
        return None;
    };
    // onnx/onnx:onnx/onnx.proto TensorProto.DataType.
    let elem_type = match ty {
        TensorElementType::Float32 => 1,
        TensorElementType::Uint8 => 2,
        TensorElementType::Int8 => 3,
        TensorElementType::Uint16 => 4,
        TensorElementType::Int16 => 5,
        TensorElementType::Int32 => 6,
        TensorElementType::Int64 => 7,
        TensorElementType::Bool => 9,
        TensorElementType::Float16 => 10,
        TensorElementType::Float64 => 11,
        TensorElementType::Uint32 => 12,
        TensorElementType::Uint64 => 13,
        TensorElementType::Bfloat16 => 16,
        _ => return None,
    };
    let dims = shape
        .iter()
        .enumerate()
        .map(|(k, &d)| match dimension_symbols.get(k) {
            _ if d >= 0 => Dimension::Fixed(d),
            Some(symbol) if !symbol.is_empty() => Dimension::Symbol(symbol.clone()),
            _ => Dimension::Unknown,
        })
        .collect();
    Some(FrontierType { elem_type, dims })
}

/// A [`ComponentSession`] that follows the denoiser contract is a [`Denoiser`].
impl Denoiser for ComponentSession {
    fn predict(
        &mut self,
        x_t: ArrayView3<'_, f32>,
        t: &[i64],
        music: ArrayView3<'_, f32>,
        cond: &[f32],
    ) -> Result<Array3<f32>> {
        self.run_denoiser(x_t, t, music, cond)
    }

    fn finish_batch(&mut self) {
        if let Some(hoisted) = &mut self.hoisted {
            hoisted.cache.clear();
        }
    }
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// The whole content of a regular file of at most `max_bytes`. Anything else is refused before
/// it is read: FIFOs (reading would block), devices (`/dev/zero` never ends), directories —
/// also behind a symlink, whose target is what is checked. The read is bounded by the size the
/// open file reports, so a file that grows or is swapped meanwhile cannot make it larger.
pub(crate) fn read_regular_file(path: &Path, max_bytes: u64) -> std::io::Result<Vec<u8>> {
    let not_regular = |what: &str| {
        std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            format!("not a regular file ({what})"),
        )
    };
    let kind = |m: &std::fs::Metadata| {
        let t = m.file_type();
        if t.is_dir() {
            "a directory"
        } else if t.is_symlink() {
            "a symlink"
        } else {
            "a FIFO, socket or device"
        }
    };
    let before = std::fs::metadata(path)?;
    if !before.is_file() {
        return Err(not_regular(kind(&before)));
    }
    let file = std::fs::File::open(path)?;
    let meta = file.metadata()?;
    if !meta.is_file() {
        return Err(not_regular(kind(&meta)));
    }
    if meta.len() > max_bytes {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            format!("{} bytes, more than {max_bytes}", meta.len()),
        ));
    }
    let mut bytes = Vec::with_capacity(meta.len() as usize);
    file.take(meta.len()).read_to_end(&mut bytes)?;
    Ok(bytes)
}
