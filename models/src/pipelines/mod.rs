//! The pipelines layer: one pipeline per task, built on the package and diffusion layers.
//!
//! - [`dance`]: music to dance — song-long windows with EDGE's overlap, chunk seams, stitching
//!   and the rigid fit; the motion file a dance becomes (joints, log-mel, provenance).
//! - [`window`]: the window stepper — one window given the previous tail as seed frames (live
//!   input).

pub(crate) mod dance;
pub(crate) mod window;
