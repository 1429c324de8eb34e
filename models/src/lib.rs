//! ONNX Runtime sessions, model packages, diffusion samplers and the music-to-dance pipeline.
//!
//! - [`OrtRuntime`] loads the ONNX Runtime shared library (found by [`locate_library`]) once
//!   per process and reports its version.
//! - Definition: [`NoiseSchedule`] (betas, alphas_cumprod, [`leading_timesteps`]).
//! - Pipeline: [`Sampler`] runs DDPM/DDIM with guidance, in-painting ([`Known`]) and EDGE's
//!   window overlap over any [`Denoiser`]; [`ExemplarDenoiser`] is a closed-form one in pure Rust.

mod error;
mod exemplar;
mod manifest;
mod noise;
mod package;
mod pipeline;
mod runtime;
mod sampler;
mod schedule;
mod session;
#[cfg(test)]
mod test_support;

pub use error::{Error, Result};
pub use exemplar::ExemplarDenoiser;
pub use manifest::{
    AudioSpec, ComponentSpec, DType, DiffusionSpec, Dim, FORMAT, FORMAT_VERSION, MANIFEST_FILE,
    Manifest, MotionSpec, SamplerSpec, Task, TensorSpec,
};
pub use noise::NoiseSource;
pub use package::ModelPackage;
pub use pipeline::{
    Dance, DanceOptions, DanceStats, decode_features, generate_dance, generate_dance_with,
    generate_window,
};
pub use runtime::{OrtRuntime, locate_library};
pub use sampler::{
    Denoiser, Guidance, Known, Prediction, SampleRequest, SampleStats, Sampler, SamplerKind,
    SamplerOptions,
};
pub use schedule::{BetaSchedule, NoiseSchedule, leading_timesteps};
pub use session::{ComponentSession, RuntimeOptions, sha256_file};
