//! A package component (runtime): one ONNX Runtime session per ONNX file, its interface checked
//! against the manifest at load, and one [`Component::run`] taking and returning named tensors,
//! checked at every call; step-invariant work hoisted out of loops ([`Hoisting`]).

use std::borrow::Cow;
use std::collections::HashMap;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::time::Instant;

use ndarray::{ArrayD, ArrayView, ArrayViewD, Dimension as NdDimension};
use ort::session::builder::GraphOptimizationLevel;
use ort::session::{RunOptions, Session, SessionInputValue};
use ort::value::{DynValue, TensorElementType, TensorRef, ValueType};
use sha2::{Digest, Sha256};

use crate::error::{Error, Result};
use crate::runtime::OrtRuntime;
use crate::runtime::contract::{ComponentSpec, DType, Dim, TensorSpec, shape_text};
use crate::runtime::deadline::{self, Deadline};
use crate::runtime::hoist::{Dimension, FrontierType, HoistPlan};
use crate::runtime::onnx_info::OnnxInfo;

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
    /// Split each looped component's graph (the denoisers) so that what it computes from the
    /// step-invariant inputs alone (music and condition; content, trajectory, mask and style)
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

/// Prologue results kept at once: one per guidance row group when the groups run as separate
/// calls (conditional, unconditional, style); a batched call needs one.
const CACHED_BATCHES: usize = 3;

/// How a component's step-invariant work was hoisted out of the step loop.
///
/// The graph is split into a prologue, run once per batch of constant inputs, and a step graph
/// that takes the prologue's results (the frontier tensors) as inputs. For MoFusion-style
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
    /// Prologue runs since load (one per batch of constant inputs).
    pub prologue_runs: usize,
}

/// One input tensor of [`Component::run`]: a float32 or int64 array view of any rank.
#[derive(Debug, Clone)]
pub enum TensorView<'a> {
    /// `float32` data.
    F32(ArrayViewD<'a, f32>),
    /// `int64` data.
    I64(ArrayViewD<'a, i64>),
}

impl TensorView<'_> {
    /// The element type.
    pub fn dtype(&self) -> DType {
        match self {
            Self::F32(_) => DType::Float32,
            Self::I64(_) => DType::Int64,
        }
    }

    /// The shape.
    pub fn shape(&self) -> &[usize] {
        match self {
            Self::F32(a) => a.shape(),
            Self::I64(a) => a.shape(),
        }
    }

    /// The values' bit patterns, widened to 64 bits: equal bits, equal results.
    fn bits(&self) -> Vec<u64> {
        match self {
            Self::F32(a) => a.iter().map(|v| u64::from(v.to_bits())).collect(),
            Self::I64(a) => a.iter().map(|v| *v as u64).collect(),
        }
    }

    fn session_value(&self) -> ort::Result<SessionInputValue<'_>> {
        Ok(match self {
            Self::F32(a) => TensorRef::from_array_view(a.view())?.into(),
            Self::I64(a) => TensorRef::from_array_view(a.view())?.into(),
        })
    }
}

impl<'a, D: NdDimension> From<ArrayView<'a, f32, D>> for TensorView<'a> {
    fn from(view: ArrayView<'a, f32, D>) -> Self {
        Self::F32(view.into_dyn())
    }
}

impl<'a, D: NdDimension> From<ArrayView<'a, i64, D>> for TensorView<'a> {
    fn from(view: ArrayView<'a, i64, D>) -> Self {
        Self::I64(view.into_dyn())
    }
}

/// The outputs of one [`Component::run`], by name (every output the manifest declares; all
/// float32 in every task's contract).
#[derive(Debug)]
pub struct NamedTensors {
    package: PathBuf,
    component: String,
    tensors: Vec<(String, ArrayD<f32>)>,
}

impl NamedTensors {
    /// The output `name`, moved out.
    pub fn take(&mut self, name: &str) -> Result<ArrayD<f32>> {
        match self.tensors.iter().position(|(n, _)| n == name) {
            Some(k) => Ok(self.tensors.swap_remove(k).1),
            None => Err(Error::Tensor {
                package: self.package.clone(),
                component: self.component.clone(),
                tensor: name.to_string(),
                reason: format!(
                    "no output of this name (left: {:?})",
                    self.tensors.iter().map(|(n, _)| n).collect::<Vec<_>>()
                ),
            }),
        }
    }

    /// The output `name`, borrowed.
    pub fn get(&self, name: &str) -> Option<ArrayViewD<'_, f32>> {
        self.tensors
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, a)| a.view())
    }
}

/// The prologue session and its results for the latest batches.
#[derive(Debug)]
struct Hoisted {
    prologue: Session,
    /// The inputs that change from step to step; the others are the cache key.
    step_inputs: Vec<String>,
    frontier: Vec<String>,
    summary: Hoisting,
    /// Seconds in the prologue's runs (part of the component's `ort_seconds`).
    prologue_seconds: f64,
    /// Most recently used last.
    cache: Vec<CachedBatch>,
}

/// Prologue results for one batch, keyed by the exact constant inputs it was run on.
#[derive(Debug)]
struct CachedBatch {
    /// Shape and bit patterns of each constant input, in the call's order.
    key: Vec<(Vec<usize>, Vec<u64>)>,
    values: Vec<DynValue>,
}

impl CachedBatch {
    fn matches(&self, constant: &[&(&str, TensorView<'_>)]) -> bool {
        self.key.len() == constant.len()
            && self
                .key
                .iter()
                .zip(constant)
                .all(|((shape, bits), (_, t))| {
                    shape.as_slice() == t.shape()
                        && match t {
                            TensorView::F32(a) => bits
                                .iter()
                                .copied()
                                .eq(a.iter().map(|v| u64::from(v.to_bits()))),
                            TensorView::I64(a) => {
                                bits.iter().copied().eq(a.iter().map(|v| *v as u64))
                            }
                        }
                })
    }
}

/// One ONNX file of a package: its ONNX Runtime session, its interface checked against the
/// manifest, and run counters. [`Component::run`] takes and returns named tensors.
#[derive(Debug)]
pub struct Component {
    package: PathBuf,
    /// The component's name in its package (its role), for messages.
    name: &'static str,
    spec: ComponentSpec,
    /// The whole graph, or the step graph when `hoisted` is set.
    session: Session,
    hoisted: Option<Hoisted>,
    /// Given to every run, so the watchdog can stop it at the deadline.
    run_options: deadline::RunHandle,
    deadline: Option<Deadline>,
    file_bytes: u64,
    sha256: String,
    onnx: Option<OnnxInfo>,
    ort_seconds: f64,
    runs: usize,
}

impl Component {
    /// Read, checksum and load `spec.file` of the package in `package`, then check the graph's
    /// inputs and outputs against `spec`. `step_inputs` names the inputs that change from one
    /// step of a loop to the next (e.g. `x_t`, `t`); with [`RuntimeOptions::hoist_invariants`],
    /// what the graph computes from the other inputs alone is split off into a prologue run
    /// once per batch of them ([`Hoisting`]). None: the component is not run in a loop.
    ///
    /// Errors are not recoverable for this package: missing or unreadable file, checksum
    /// mismatch, ONNX Runtime refusing the file (corrupt, unsupported opset), interface mismatch.
    pub fn load(
        ort: &OrtRuntime,
        package: &Path,
        name: &'static str,
        spec: &ComponentSpec,
        step_inputs: Option<&[&str]>,
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
        let split = match step_inputs {
            Some(step_inputs) if options.hoist_invariants => hoist(&bytes, step_inputs, &make_session).map_err(|why| {
                tracing::debug!(package = %package.display(), component = name, "step-invariant work not hoisted: {why}");
            }).ok(),
            _ => None,
        };
        let (session, hoisted) = match split {
            Some((step, hoisted)) => (step, Some(hoisted)),
            None => (make_session(&bytes).map_err(load_err)?, None),
        };
        let run_options = deadline::RunHandle::new().map_err(|e| load_err(e.to_string()))?;
        let me = Self {
            package: package.to_path_buf(),
            name,
            spec: spec.clone(),
            session,
            hoisted,
            run_options,
            deadline: None,
            file_bytes: bytes.len() as u64,
            sha256,
            onnx: crate::runtime::onnx_info::inspect(&bytes),
            ort_seconds: 0.0,
            runs: 0,
        };
        me.check_interface()?;
        Ok(me)
    }

    pub(crate) fn tensor_err(&self, tensor: &str, reason: String) -> Error {
        Error::Tensor {
            package: self.package.clone(),
            component: self.name.to_string(),
            tensor: tensor.to_string(),
            reason,
        }
    }

    fn time_limit_err(&self, deadline: Deadline) -> Error {
        Error::TimeLimit {
            package: self.package.clone(),
            component: self.name.to_string(),
            limit: deadline.limit(),
        }
    }

    fn run_err(&self, reason: String) -> Error {
        Error::Run {
            package: self.package.clone(),
            component: self.name.to_string(),
            reason: reason.replace('\n', " "),
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
                self.check_graph_tensor(spec, outlet.dtype())?;
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

    fn check_graph_tensor(&self, spec: &TensorSpec, graph: &ValueType) -> Result<()> {
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

    /// What this component does in its package.
    pub fn name(&self) -> &'static str {
        self.name
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
    /// every call (no step inputs named, hoisting off, or nothing to hoist).
    pub fn hoisting(&self) -> Option<Hoisting> {
        self.hoisted.as_ref().map(|h| h.summary)
    }

    /// Seconds spent in `Session::run` since load (prologue runs included).
    pub fn ort_seconds(&self) -> f64 {
        self.ort_seconds
    }

    /// Of [`Self::ort_seconds`], the seconds in the hoisted prologue's runs (0 without one).
    pub fn prologue_seconds(&self) -> f64 {
        self.hoisted.as_ref().map_or(0.0, |h| h.prologue_seconds)
    }

    /// Calls of `Session::run` since load.
    pub fn runs(&self) -> usize {
        self.runs
    }

    /// Stop every run still going at `deadline` ([`Error::TimeLimit`]); None: no limit. Runs
    /// started after it has passed fail at once.
    pub fn set_deadline(&mut self, deadline: Option<Deadline>) {
        self.deadline = deadline;
    }

    /// The deadline runs are held to.
    pub fn deadline(&self) -> Option<Deadline> {
        self.deadline
    }

    /// The loop is done with this batch of constant inputs: drop the prologue results kept
    /// for it.
    pub fn finish_batch(&mut self) {
        if let Some(hoisted) = &mut self.hoisted {
            hoisted.cache.clear();
        }
    }

    /// Run the graph on named inputs; returns every output the manifest declares.
    ///
    /// Each input is checked against the manifest before ONNX Runtime sees it: every declared
    /// input given exactly once and nothing else, the declared dtype and rank, fixed axes of
    /// their size, and each symbolic axis (`N`, `T`, ...) of one size across all inputs of this
    /// call. Outputs are checked the same way (symbols bound by the inputs) and must be finite.
    /// Errors name the tensor: [`Error::Tensor`] for a bad input or output shape,
    /// [`Error::NonFinite`] for NaN/Inf, [`Error::Run`] when ONNX Runtime fails,
    /// [`Error::TimeLimit`] when the run was stopped at the deadline ([`Self::set_deadline`]).
    pub fn run(&mut self, inputs: &[(&str, TensorView<'_>)]) -> Result<NamedTensors> {
        let mut sizes = HashMap::new();
        self.check_inputs(inputs, &mut sizes)?;
        let started = Instant::now();
        let result = self.run_session(inputs);
        self.ort_seconds += started.elapsed().as_secs_f64();
        self.runs += 1;
        let tensors = result?;
        for (spec, value) in self.spec.outputs.iter().zip(&tensors) {
            self.check_shape(spec, value.shape(), &mut sizes)?;
            let bad = value.iter().filter(|v| !v.is_finite()).count();
            if bad > 0 {
                return Err(Error::NonFinite {
                    package: self.package.clone(),
                    component: self.name.to_string(),
                    tensor: spec.name.clone(),
                    count: bad,
                    timestep: None,
                });
            }
        }
        Ok(NamedTensors {
            package: self.package.clone(),
            component: self.name.to_string(),
            tensors: self
                .spec
                .outputs
                .iter()
                .map(|s| s.name.clone())
                .zip(tensors)
                .collect(),
        })
    }

    fn check_inputs(
        &self,
        inputs: &[(&str, TensorView<'_>)],
        sizes: &mut HashMap<String, usize>,
    ) -> Result<()> {
        for (k, (name, _)) in inputs.iter().enumerate() {
            if !self.spec.inputs.iter().any(|s| s.name == *name) {
                return Err(self.tensor_err(
                    name,
                    format!(
                        "not an input of this component (its inputs: {:?})",
                        self.spec.inputs.iter().map(|s| &s.name).collect::<Vec<_>>()
                    ),
                ));
            }
            if inputs[..k].iter().any(|(other, _)| other == name) {
                return Err(self.tensor_err(name, "given twice".into()));
            }
        }
        for spec in &self.spec.inputs {
            let Some((_, value)) = inputs.iter().find(|(name, _)| *name == spec.name) else {
                return Err(self.tensor_err(&spec.name, "input missing".into()));
            };
            if value.dtype() != spec.dtype {
                return Err(self.tensor_err(
                    &spec.name,
                    format!(
                        "is {}, the manifest says {}",
                        value.dtype().as_str(),
                        spec.dtype.as_str()
                    ),
                ));
            }
            self.check_shape(spec, value.shape(), sizes)?;
        }
        Ok(())
    }

    /// `shape` fits `spec`: same rank, fixed axes equal, each symbol one size (bound in `sizes`
    /// by the first tensor that has it).
    fn check_shape(
        &self,
        spec: &TensorSpec,
        shape: &[usize],
        sizes: &mut HashMap<String, usize>,
    ) -> Result<()> {
        let wrong = |why: String| {
            self.tensor_err(
                &spec.name,
                format!(
                    "shape {shape:?} does not fit the manifest's {}: {why}",
                    shape_text(&spec.shape)
                ),
            )
        };
        if shape.len() != spec.shape.len() {
            return Err(wrong(format!(
                "rank {}, expected {}",
                shape.len(),
                spec.shape.len()
            )));
        }
        for (axis, (&size, dim)) in shape.iter().zip(&spec.shape).enumerate() {
            match dim {
                Dim::Fixed(n) if size as i64 != *n => {
                    return Err(wrong(format!("axis {axis} is {size}, expected {n}")));
                }
                Dim::Symbol(symbol) => match sizes.get(symbol) {
                    Some(&bound) if bound != size => {
                        return Err(wrong(format!(
                            "axis {axis} ({symbol}) is {size}, but {symbol} is {bound} in \
                             another tensor of this call"
                        )));
                    }
                    Some(_) => {}
                    None => {
                        sizes.insert(symbol.clone(), size);
                    }
                },
                Dim::Fixed(_) => {}
            }
        }
        Ok(())
    }

    /// The session run itself: inputs (and hoisted prologue results) in, declared outputs out.
    fn run_session(&mut self, inputs: &[(&str, TensorView<'_>)]) -> Result<Vec<ArrayD<f32>>> {
        let ort_err = |me: &Self, what: &str, e: ort::Error| Error::Run {
            package: me.package.clone(),
            component: format!("{}{what}", me.name),
            reason: e.to_string().replace('\n', " "),
        };
        let mut feed = Vec::with_capacity(inputs.len());
        for (name, value) in inputs {
            let value = value.session_value().map_err(|e| ort_err(self, "", e))?;
            feed.push((Cow::from(*name), value));
        }
        let _watching = match self.deadline {
            Some(deadline) if deadline.passed() => return Err(self.time_limit_err(deadline)),
            Some(deadline) => Some(
                deadline::watch(deadline, &self.run_options)
                    .map_err(|e| self.run_err(format!("cannot watch the time limit: {e}")))?,
            ),
            None => None,
        };
        if let Some(hoisted) = &mut self.hoisted {
            let k = hoisted.prologue_results(inputs, self.run_options.options());
            let k = k.map_err(|e| match self.deadline.filter(Deadline::passed) {
                Some(deadline) => Error::TimeLimit {
                    package: self.package.clone(),
                    component: self.name.to_string(),
                    limit: deadline.limit(),
                },
                None => Error::Run {
                    package: self.package.clone(),
                    component: format!("{} (prologue)", self.name),
                    reason: e.to_string().replace('\n', " "),
                },
            })?;
            for (tensor, value) in hoisted.frontier.iter().zip(&hoisted.cache[k].values) {
                feed.push((Cow::from(tensor.as_str()), SessionInputValue::from(value)));
            }
        }
        let run = run_graph(
            &mut self.session,
            feed,
            self.run_options.options(),
            &self.spec.outputs,
        );
        run.map_err(
            |failure| match (failure, self.deadline.filter(Deadline::passed)) {
                (RunFailure::Ort(_), Some(deadline)) => self.time_limit_err(deadline),
                (RunFailure::Ort(reason) | RunFailure::Outputs(reason), _) => self.run_err(reason),
            },
        )
    }
}

/// Why [`run_graph`] failed.
enum RunFailure {
    /// ONNX Runtime's run failed (or was stopped).
    Ort(String),
    /// The outputs are not what the manifest declares.
    Outputs(String),
}

/// Run `session` on `feed` and copy out the declared `outputs` as float32 arrays.
fn run_graph(
    session: &mut Session,
    feed: Vec<(Cow<'_, str>, SessionInputValue<'_>)>,
    run_options: &RunOptions,
    outputs: &[TensorSpec],
) -> std::result::Result<Vec<ArrayD<f32>>, RunFailure> {
    let values = session
        .run_with_options(feed, run_options)
        .map_err(|e| RunFailure::Ort(e.to_string()))?;
    outputs
        .iter()
        .map(|spec| {
            values
                .get(spec.name.as_str())
                .ok_or_else(|| format!("no output named {}", spec.name))
                .and_then(|v| {
                    v.try_extract_array::<f32>()
                        .map(|a| a.to_owned())
                        .map_err(|e| format!("output {}: {e}", spec.name))
                })
        })
        .collect::<std::result::Result<Vec<_>, String>>()
        .map_err(RunFailure::Outputs)
}

impl Hoisted {
    /// The prologue's results for this call's constant inputs, cached or computed now: their
    /// index in `cache`.
    fn prologue_results(
        &mut self,
        inputs: &[(&str, TensorView<'_>)],
        run_options: &RunOptions,
    ) -> ort::Result<usize> {
        let constant: Vec<&(&str, TensorView<'_>)> = inputs
            .iter()
            .filter(|(name, _)| !self.step_inputs.iter().any(|s| s == name))
            .collect();
        if let Some(k) = self.cache.iter().position(|b| b.matches(&constant)) {
            let hit = self.cache.remove(k);
            self.cache.push(hit);
        } else {
            let mut feed = Vec::new();
            for outlet in self.prologue.inputs() {
                let Some((_, value)) = constant.iter().find(|(name, _)| *name == outlet.name())
                else {
                    return Err(ort::Error::new(format!(
                        "the prologue needs input {:?}, which is not step-invariant",
                        outlet.name()
                    )));
                };
                feed.push((Cow::from(outlet.name().to_string()), value.session_value()?));
            }
            let started = Instant::now();
            let outputs = self.prologue.run_with_options(feed, run_options);
            self.prologue_seconds += started.elapsed().as_secs_f64();
            let mut outputs = outputs?;
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
                key: constant
                    .iter()
                    .map(|(_, t)| (t.shape().to_vec(), t.bits()))
                    .collect(),
                values,
            });
        }
        Ok(self.cache.len() - 1)
    }
}

/// Split `model` into prologue and step sessions ([`HoistPlan`]) around `step_inputs`; `Err`
/// says why it was not split (the caller then loads the whole graph).
fn hoist(
    model: &[u8],
    step_inputs: &[&str],
    make_session: &dyn Fn(&[u8]) -> std::result::Result<Session, String>,
) -> std::result::Result<(Session, Hoisted), String> {
    let plan = HoistPlan::new(model, step_inputs)?;
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
        step_inputs: step_inputs.iter().map(|s| s.to_string()).collect(),
        frontier: plan.frontier().iter().map(|f| f.to_string()).collect(),
        summary: Hoisting {
            hoisted_nodes: plan.hoisted_nodes(),
            total_nodes: plan.total_nodes(),
            frontier_tensors: plan.frontier().len(),
            prologue_runs: 0,
        },
        prologue_seconds: 0.0,
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
