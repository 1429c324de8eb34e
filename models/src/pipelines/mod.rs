//! The pipelines layer: one pipeline per task, built on the package and diffusion layers.
//!
//! - [`dance`]: music to dance — song-long windows with EDGE's overlap, chunk seams, stitching
//!   and the rigid fit; the motion file a dance becomes (joints, log-mel, provenance).
//! - [`lodge`]: LODGE's two stages — Global keyframes, the Local windows' constraints and
//!   in-painting, the official quirks or their fixes.
//! - [`song`]: a song file to its motion file — decode, log-mel, the package's shortest song,
//!   [`dance`], provenance with the files' sha256.
//! - [`window`]: the window plan both share — where a window's music starts, its silence floor —
//!   and the window stepper, one window given the frames before it as seed.
//! - [`live`]: live input — log-mel frames in as they are heard, the newest window every hop,
//!   new frames fitted to the session's skeleton out.
//! - [`stylize`]: style transfer — MCM-LDM's latent transfer or MulSMo's DDIM inversion, long
//!   content in overlapping segments, cross-faded.
//! - [`stylize_motion`]: two motion files to a stylized motion file — both read as features,
//!   [`stylize`], the joints recovered, provenance naming both inputs.

pub(crate) mod dance;
pub(crate) mod live;
pub(crate) mod lodge;
pub(crate) mod song;
pub(crate) mod stylize;
pub(crate) mod stylize_motion;
pub(crate) mod window;
