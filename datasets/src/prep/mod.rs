//! Dataset preparation: AIST++ and HumanML3D to training-ready HDF5 shards (`choreod prep`).
//!
//! - [`prepare_aistpp`]: the official AIST++ layout + a music folder → per-split shards of
//!   sequences with SMPL joints at 60 and 30 fps and music features aligned to the 30 fps frames.
//! - [`prepare_humanml3d`]: HumanML3D joints + texts + split lists → per-split shards of 263-dim
//!   features (optionally with mirrored `M` copies), `Mean.npy` / `Std.npy`.
//! - [`merge`]: join the partial outputs of `--shard I/N` runs (and recompute Mean/Std exactly
//!   from the per-shard f64 sums).
//!
//! How a run is organised (all in `plan.rs`):
//! - the input is listed and filtered by cheap checks (ignore list, splits, music present), the
//!   surviving candidates are sorted by name per split and cut into shards of
//!   [`PrepOptions::sequences_per_shard`] by index — so the shard of a sequence never depends on
//!   which other sequences fail later;
//! - `--shard I/N` ([`Part`]) gives machine `I` every output shard whose global number
//!   (counted over all splits, in split order train, val, test) is `≡ I (mod N)`. Shards are the
//!   unit, not sequences, so N partial runs merged are byte-identical to one full run;
//! - each shard is written under a temporary name, fsynced and renamed, then its sidecar JSON
//!   (sequences, skips, sha256) is written the same way. A shard counts as finished only when
//!   its sidecar exists, matches the run's parameters and the file size: a rerun skips it;
//! - shard files hold no times (HDF5 time tracking is off), so the same input gives the same
//!   bytes; times are in the manifest only.
//!
//! The HDF5 layouts and the manifest are documented in `README-section.md` beside this file.

mod aistpp;
mod humanml3d;
mod merge;
mod plan;

pub use aistpp::{
    AISTPP_MAX_SECONDS, AISTPP_MIN_SECONDS, MusicFeatures, bpm_from_music_id, prepare_aistpp,
};
pub use humanml3d::{
    HUMANML3D_MAX_FRAMES, HUMANML3D_MIN_FRAMES, prepare_humanml3d, swap_left_right,
};
pub use merge::merge;
pub use plan::{
    MANIFEST_FORMAT, MANIFEST_VERSION, Manifest, MeanStdEntry, Part, PrepOptions, PrepReport,
    Progress, SHARD_FORMAT, SHARD_VERSION, ShardEntry, Skip, SkipReason, SplitCounts,
};
