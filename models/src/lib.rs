//! Diffusion models as a toolkit, in four layers (as candle and diffusers layer them).
//!
//! Where things are:
//! - **Runtime** ([`runtime`]): the tensor contract of a component ([`ComponentSpec`],
//!   [`TensorSpec`]: names, dtypes, fixed and symbolic axes); [`OrtRuntime`] loads the ONNX
//!   Runtime library once (found by [`locate_library`]). A [`Component`] is one ONNX file of a package: loaded with
//!   [`RuntimeOptions`] (a regular file, read bounded by its size, sha256 checked), its graph's
//!   inputs and outputs compared with the manifest, and one [`Component::run`] taking named
//!   [`TensorView`]s (f32 or i64) and returning [`NamedTensors`], checked by name, dtype and
//!   shape (symbolic axes bound consistently) with finite outputs. What a looped component
//!   computes from its step-invariant inputs alone is split off into a prologue run once per
//!   batch ([`Hoisting`]). A [`Deadline`] stops a run still going when it passes (a watchdog
//!   sets ONNX Runtime's terminate flag). [`inspect_onnx`] reads IR version, opsets and weight
//!   count.
//! - **Package** ([`package`]): the [`Manifest`] (`choreod-model.toml`) with its [`Task`]
//!   (`music-to-dance`, `style-transfer`); each task validates the sections and components
//!   ([`Role`]: denoiser, vae_encoder, ...) it needs — [`Manifest::dance_spec`] (audio, windows)
//!   and [`Manifest::style_spec`] (segment lengths, guidance weights) give them validated.
//!   [`ModelPackage`] loads one [`Component`] per role ([`ModelPackage::component`]) and runs
//!   every component once for `choreod models check` ([`ModelPackage::smoke_test`]).
//! - **Diffusion** ([`diffusion`]): [`NoiseSchedule`] (betas and `alphas_cumprod`, f64); the
//!   [`Scheduler`] trait — `set_timesteps`, `step`, `inverse_step` (DDIM inversion),
//!   `add_noise` — with [`Ddpm`], [`Ddim`] and [`DpmSolverPlusPlus`] as diffusers computes them,
//!   and diffusers' [`TimestepSpacing`]s; [`Sampler`] runs a batch through a scheduler with
//!   classifier-free [`Guidance`] (one weight or two), in-painting ([`Known`]) and EDGE's window
//!   overlap over any [`Denoiser`], from given x_T or deterministic [`NoiseSource`] noise.
//! - **Pipelines** ([`pipelines`]): one per task. Music to dance: [`generate_dance`] turns a
//!   log-mel into joints ([`Dance`]) window by window, in chunks, with EDGE's overlap, stitching
//!   and the rigid fit (over a denoiser [`Component`] or the closed-form [`ExemplarDenoiser`]
//!   in pure Rust, [`generate_dance_with`]); [`dance_motion_file`] makes the motion file of a
//!   dance (joints, the song's log-mel, the provenance, with the song's [`DanceSource`]). The
//!   window stepper [`generate_window`] is one window on its own, seeded by the frames before
//!   it; [`LiveDance`] is live input on the same window plan, fed log-mel frames as they are
//!   heard and returning new frames fitted to the session's skeleton ([`LiveStep`]), through
//!   [`DanceDenoiser`] (the task's tensor names). End to end, [`dance_song`] turns a song file
//!   into its motion file ([`SongOptions`]: the generation and the input limits; the shortest
//!   song is the package's, [`minimum_length`]) with a [`SongReport`]. Style transfer: [`stylize`] runs MCM-LDM's transfer or
//!   MulSMo's inversion ([`StyleMode`]) over any [`StyleNetworks`] (a package's components via
//!   [`stylize_package`]) with a package's [`StyleConfig`], cutting long content into segments;
//!   end to end, [`encode_style`] reads a style reference ([`StyleSource`]) into its style
//!   vector once ([`EncodedStyle`]) and [`stylize_motion`] turns a content motion file
//!   ([`MotionSource`]) and it into the stylized motion file, joints and provenance included.
//!
//! Files: `runtime/` (`mod.rs` the library, `contract.rs`, `component.rs`, `hoist.rs`, `onnx_info.rs`),
//! `package/` (`mod.rs` the loaded package, `manifest.rs`), `diffusion/` (`schedule.rs`,
//! `scheduler.rs`, `sampler.rs`, `noise.rs`), `pipelines/` (`dance.rs`, `song.rs`, `window.rs`, `live.rs`, `stylize.rs`, `stylize_motion.rs`), and
//! `exemplar.rs` (the bundled package's denoiser in Rust).
//!
//! Errors: one [`Error`]; [`Error::is_environment`] tells a package/setup problem (refuse to
//! start, exit 4) from a problem with one input.

pub mod diffusion;
mod error;
mod exemplar;
pub mod package;
pub mod pipelines;
pub mod runtime;
#[cfg(test)]
mod test_support;

pub use diffusion::{
    BetaSchedule, Ddim, Ddpm, Denoiser, DpmSolverPlusPlus, Guidance, Known, NoiseSchedule,
    NoiseSource, Prediction, SampleRequest, SampleStats, Sampler, SamplerKind, SamplerOptions,
    Scheduler, SchedulerConfig, TimestepSpacing,
};
pub use error::{Error, MinimumLength, Result};
pub use exemplar::ExemplarDenoiser;
pub use package::manifest::{
    AudioSection, AudioSpec, ComponentSpec, DType, DanceSpec, DiffusionSpec, Dim, ETA_RANGE,
    FORMAT, FORMAT_VERSION, Fact35Spec, GUIDANCE_RANGE, LibrarySection, LicenseSpec, LodgeSpec,
    MANIFEST_FILE, Manifest, MotionSpec, QuantizationSpec, REPR_HUMANML3D263, REPR_SMPL24_ROOTREL,
    Role, SOURCE_OUTPUT, SamplerSpec, StyleSpec, Task, TensorSpec,
};
pub use package::{ComponentTime, Deviation, ModelPackage};
pub use pipelines::dance::{
    Dance, DanceDenoiser, DanceOptions, DanceSource, DanceStats, dance_motion_file,
    decode_features, generate_dance, generate_dance_with,
};
pub use pipelines::live::{LiveDance, LiveFrames, LiveStep, LiveWindow};
pub use pipelines::lodge::{
    FIXES as LODGE_FIXES, LodgeCompat, LodgeConstraints, LodgeDance, LodgeNoise, LodgeOptions,
    LodgeStage, LodgeStats, LodgeWindows, generate_lodge,
};
pub use pipelines::song::{SongDance, SongOptions, SongReport, dance_song, minimum_length};
pub use pipelines::stylize::{
    STYLE_FEATURE_DIM, StyleConfig, StyleDenoiserInputs, StyleMode, StyleNetworks, StyleReference,
    StylizeOptions, StylizeStats, Stylized, UsedSettings, encode_style_package, style_config,
    stylize, stylize_package,
};
pub use pipelines::stylize_motion::{
    EncodedStyle, MotionSource, StyleSource, StylizedMotion, StylizedReport, encode_style,
    stylize_motion,
};
pub use pipelines::window::generate_window;
pub use runtime::component::{Component, Hoisting, NamedTensors, RuntimeOptions, TensorView};
pub use runtime::deadline::Deadline;
pub use runtime::onnx_info::{OnnxInfo, inspect as inspect_onnx};
pub use runtime::{OrtRuntime, locate_library};
