//! Diffusion: the training noise schedule, the schedulers (one step down, DDIM inversion one
//! step up, forward noising), guidance, in-painting masks, the noise source, and the sampling
//! loop that drives any network through a scheduler.
//!
//! - [`schedule`]: [`NoiseSchedule`] (betas, `alphas_cumprod`, f64) and [`BetaSchedule`].
//! - [`scheduler`]: the [`Scheduler`] trait with [`Ddpm`], [`Ddim`] and [`DpmSolverPlusPlus`],
//!   and the diffusers timestep spacings ([`TimestepSpacing`]).
//! - [`sampler`]: [`Sampler`] runs a batch through a scheduler with classifier-free
//!   [`Guidance`] (one weight or two), in-painting ([`Known`]) and EDGE's window overlap over
//!   any [`Denoiser`].
//! - [`noise`]: [`NoiseSource`], seeded Gaussian noise that is the same on every platform.

pub mod noise;
pub mod sampler;
pub mod schedule;
pub mod scheduler;

pub use noise::NoiseSource;
pub use sampler::{
    Denoiser, Guidance, Known, SampleRequest, SampleStats, Sampler, SamplerKind, SamplerOptions,
};
pub use schedule::{BetaSchedule, NoiseSchedule};
pub use scheduler::{
    Ddim, Ddpm, DpmSolverPlusPlus, Prediction, Scheduler, SchedulerConfig, TimestepSpacing,
    ddim_timesteps, dpm_timesteps,
};
