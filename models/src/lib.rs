//! ONNX Runtime sessions, model packages, diffusion samplers and the music-to-dance pipeline.
//!
//! Where things are:
//! - **Diffusion** ([`diffusion`]): [`NoiseSchedule`] (betas and `alphas_cumprod`, f64); the
//!   [`Scheduler`] trait — `set_timesteps`, `step`, `inverse_step` (DDIM inversion),
//!   `add_noise` — with [`Ddpm`], [`Ddim`] and [`DpmSolverPlusPlus`] as diffusers computes them,
//!   and diffusers' [`TimestepSpacing`]s; [`Sampler`] runs a batch through a scheduler with
//!   classifier-free [`Guidance`] (one weight or two), in-painting ([`Known`]) and EDGE's window
//!   overlap over any [`Denoiser`], from given x_T or deterministic [`NoiseSource`] noise.
//! - **Package definition**: [`Manifest`] parses and validates a package's `choreod-model.toml`
//!   (its audio section gives the mel options, its motion section the skeleton).
//! - **Runtime**: [`OrtRuntime`] loads the ONNX Runtime library once (found by
//!   [`locate_library`]); [`ModelPackage::load`] checks every component's file (a regular file,
//!   read bounded by its size) and sha256 and opens one [`ComponentSession`] per component with
//!   [`RuntimeOptions`], comparing the graph's inputs and outputs with the manifest;
//!   [`inspect_onnx`] reads IR version, opsets and the stored weight count from the file. The
//!   denoiser's step-invariant work (what it computes from the music alone) is split off into a
//!   prologue run once per batch ([`Hoisting`]).
//! - **Pipeline**: [`generate_dance`] turns a log-mel into joints ([`Dance`]) window by window, in
//!   chunks (a [`ComponentSession`] or the closed-form [`ExemplarDenoiser`] in pure Rust);
//!   [`generate_window`] is one window on its own, seeded by the previous window's tail (live
//!   input).
//! - **Style transfer**: [`stylize`] runs MCM-LDM's transfer or MulSMo's inversion
//!   ([`StyleMode`]) over any [`StyleNetworks`] with a package's [`StyleConfig`], cutting long
//!   content into segments.
//!
//! Errors: one [`Error`]; [`Error::is_environment`] tells a package/setup problem (refuse to
//! start, exit 4) from a problem with one input.

pub mod diffusion;
mod error;
mod exemplar;
mod hoist;
mod manifest;
mod onnx_info;
mod package;
mod pipeline;
mod proto;
mod runtime;
mod session;
mod stylize;
#[cfg(test)]
mod test_support;

pub use diffusion::{
    BetaSchedule, Ddim, Ddpm, Denoiser, DpmSolverPlusPlus, Guidance, Known, NoiseSchedule,
    NoiseSource, Prediction, SampleRequest, SampleStats, Sampler, SamplerKind, SamplerOptions,
    Scheduler, SchedulerConfig, TimestepSpacing,
};
pub use error::{Error, Result};
pub use exemplar::ExemplarDenoiser;
pub use manifest::{
    AudioSpec, ComponentSpec, DType, DiffusionSpec, Dim, FORMAT, FORMAT_VERSION, MANIFEST_FILE,
    Manifest, MotionSpec, REPR_SMPL24_ROOTREL, SamplerSpec, Task, TensorSpec,
};
pub use onnx_info::{OnnxInfo, inspect as inspect_onnx};
pub use package::ModelPackage;
pub use pipeline::{
    Dance, DanceOptions, DanceStats, decode_features, generate_dance, generate_dance_with,
    generate_window,
};
pub use runtime::{OrtRuntime, locate_library};
pub use session::{ComponentSession, Hoisting, RuntimeOptions};
pub use stylize::{
    STYLE_FEATURE_DIM, StyleConfig, StyleDenoiserInputs, StyleMode, StyleNetworks, StyleReference,
    StylizeOptions, StylizeStats, Stylized, UsedSettings, style_config, stylize, stylize_package,
};
