//! The tensor contract of an ONNX component, as a package manifest declares it and the runtime
//! checks it: the file and its sha256, and each graph input and output by name, element type
//! and shape (fixed sizes and named dynamic axes).

use serde::Deserialize;

/// One ONNX graph (a manifest's `[components.NAME]`).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
#[non_exhaustive]
pub struct ComponentSpec {
    /// ONNX file, relative to the package directory (no `..`).
    pub file: String,
    /// Lower-case hex sha256 of the file, checked at load.
    pub sha256: String,
    /// Graph inputs, by name.
    pub inputs: Vec<TensorSpec>,
    /// Graph outputs, by name.
    pub outputs: Vec<TensorSpec>,
}

/// One graph input or output.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
#[non_exhaustive]
pub struct TensorSpec {
    /// Tensor name in the graph.
    pub name: String,
    /// Element type.
    pub dtype: DType,
    /// Dimensions: numbers are fixed, strings name dynamic axes (e.g. `"N"`).
    pub shape: Vec<Dim>,
}

/// Element types used by packages.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
#[non_exhaustive]
pub enum DType {
    /// 32-bit float.
    Float32,
    /// 64-bit signed integer.
    Int64,
}

impl DType {
    /// The manifest spelling.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Float32 => "float32",
            Self::Int64 => "int64",
        }
    }
}

/// One dimension of a tensor shape.
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
#[serde(untagged)]
pub enum Dim {
    /// A fixed size.
    Fixed(i64),
    /// A dynamic axis, by symbol.
    Symbol(String),
}

impl std::fmt::Display for Dim {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Fixed(n) => write!(f, "{n}"),
            Self::Symbol(s) => f.write_str(s),
        }
    }
}

/// `[a, b, c]` for messages.
pub(crate) fn shape_text(shape: &[Dim]) -> String {
    let parts: Vec<String> = shape.iter().map(ToString::to_string).collect();
    format!("[{}]", parts.join(", "))
}
