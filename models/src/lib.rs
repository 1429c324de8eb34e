//! ONNX Runtime sessions, model packages, diffusion samplers and the music-to-dance pipeline.
//!
//! - [`OrtRuntime`] loads the ONNX Runtime shared library (found by [`locate_library`]) once
//!   per process and reports its version.

mod error;
mod runtime;

pub use error::{Error, Result};
pub use runtime::{OrtRuntime, locate_library};
