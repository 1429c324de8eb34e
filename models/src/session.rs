//! ONNX Runtime sessions for package components (runtime): file checks, session creation with
//! the configured threads, and the graph's interface checked against the manifest at load.

use std::io::Read;
use std::path::{Path, PathBuf};
use std::time::Instant;

use ndarray::{Array3, ArrayView1, ArrayView3, Ix3};
use ort::session::Session;
use ort::session::builder::GraphOptimizationLevel;
use ort::value::{TensorElementType, TensorRef, ValueType};
use sha2::{Digest, Sha256};

use crate::error::{Error, Result};
use crate::manifest::{ComponentSpec, DType, Dim, TensorSpec, shape_text};
use crate::onnx_info::OnnxInfo;
use crate::runtime::OrtRuntime;
use crate::sampler::Denoiser;

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
}

impl Default for RuntimeOptions {
    fn default() -> Self {
        Self {
            intra_threads: 0,
            inter_threads: 0,
            verify_checksums: true,
            spin_threads: true,
        }
    }
}

/// One component's ONNX Runtime session, its checked interface and run counters.
#[derive(Debug)]
pub struct ComponentSession {
    package: PathBuf,
    name: String,
    spec: ComponentSpec,
    session: Session,
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
        let meta = std::fs::metadata(&path).map_err(|e| file_err(e.to_string()))?;
        if meta.len() > MAX_COMPONENT_BYTES {
            return Err(file_err(format!(
                "{} bytes, more than {MAX_COMPONENT_BYTES}",
                meta.len()
            )));
        }
        let mut bytes = Vec::with_capacity(meta.len() as usize);
        std::fs::File::open(&path)
            .and_then(|f| f.take(MAX_COMPONENT_BYTES).read_to_end(&mut bytes))
            .map_err(|e| file_err(e.to_string()))?;
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
        // Builder errors carry the builder back; only their message is kept.
        let builder_err = |e: ort::Error<_>| load_err(ort::Error::<()>::from(e).to_string());
        let session = Session::builder(ort.environment())
            .map_err(|e| load_err(e.to_string()))?
            .with_optimization_level(GraphOptimizationLevel::All)
            .map_err(builder_err)?
            .with_intra_threads(options.intra_threads)
            .map_err(builder_err)?
            .with_inter_threads(options.inter_threads)
            .map_err(builder_err)?
            .with_intra_op_spinning(options.spin_threads)
            .map_err(builder_err)?
            .commit_from_memory(&bytes)
            .map_err(|e| load_err(e.to_string()))?;
        let me = Self {
            package: package.to_path_buf(),
            name: name.to_string(),
            spec: spec.clone(),
            session,
            file_bytes: meta.len(),
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
        for (kind, specs, outlets) in [
            ("input", &self.spec.inputs, self.session.inputs()),
            ("output", &self.spec.outputs, self.session.outputs()),
        ] {
            let names: Vec<&str> = outlets.iter().map(|o| o.name()).collect();
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

    /// Seconds spent in `Session::run` since load.
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
        let inputs = (|| -> ort::Result<_> {
            Ok(ort::inputs![
                "x_t" => TensorRef::from_array_view(x_t)?,
                "t" => TensorRef::from_array_view(ArrayView1::from(t))?,
                "music" => TensorRef::from_array_view(music)?,
                "cond" => TensorRef::from_array_view(ArrayView1::from(cond))?,
            ])
        })()
        .map_err(|e| run_err(self, e.to_string()))?;
        let (package, name) = (&self.package, &self.name);
        let outputs = self.session.run(inputs).map_err(|e| Error::Run {
            package: package.clone(),
            component: name.clone(),
            reason: e.to_string().replace('\n', " "),
        })?;
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
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// Lower-case hex sha256 of a file, read in 1 MiB blocks (any size, bounded memory).
pub fn sha256_file(path: &Path) -> std::io::Result<String> {
    let mut file = std::fs::File::open(path)?;
    let mut hasher = Sha256::new();
    let mut buf = vec![0u8; 1 << 20];
    loop {
        let n = file.read(&mut buf)?;
        if n == 0 {
            break;
        }
        hasher.update(&buf[..n]);
    }
    Ok(hex(&hasher.finalize()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sha256_of_a_file_matches_the_fips_example() {
        // FIPS 180-2, appendix B.1: sha256("abc").
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("abc");
        std::fs::write(&path, b"abc").unwrap();
        assert_eq!(
            sha256_file(&path).unwrap(),
            "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
        );
        assert!(sha256_file(&dir.path().join("missing")).is_err());
    }
}
