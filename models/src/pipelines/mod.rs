//! The pipelines layer: one pipeline per task, built on the package and diffusion layers.
//!
//! - [`dance`]: music to dance — song-long windows with EDGE's overlap, chunk seams, stitching
//!   and the rigid fit; the motion file a dance becomes (joints, log-mel, provenance).
//! - [`window`]: the window stepper — one window given the previous tail as seed frames (live
//!   input).
//! - [`stylize`]: style transfer — MCM-LDM's latent transfer or MulSMo's DDIM inversion, long
//!   content in overlapping segments, cross-faded.

pub(crate) mod dance;
pub(crate) mod stylize;
pub(crate) mod window;
