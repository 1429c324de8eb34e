//! Motion representations and files of choreod.
//!
//! - Skeletons: [`SkeletonKind`] (SMPL-24 of AIST++, HumanML3D's t2m-22, or custom from BVH) with
//!   the reference constants in [`skeleton`].
//! - AIST++: [`AistppMotion`] reads a motion `.pkl` through a safe pickle subset ([`pickle`]) and
//!   runs SMPL forward kinematics to world joints; [`resample_joints`] changes the frame rate.
//! - The HDF5 motion file (format `choreod-motion` v1): [`MotionFile`], [`write_motion_file`],
//!   [`read_motion_file`] and the live [`MotionAppender`].
//! - Pictures: [`render_gif`] and [`render_contact_sheet`] draw the skeleton over a ground grid.
//! - HumanML3D 263-dim features ([`humanml3d`]): [`extract_features`], [`recover_from_ric`],
//!   mirroring and the grouped mean/std.
//! - BVH: [`read_bvh`] (any hierarchy) and [`write_bvh_positions`] (rotations recovered from
//!   positions by [`JointRotations`], which live output's VMC bones share).
//! - [`convert`]: the engine of `choreod convert`.
//! - `.npy` files: [`read_npy`], [`write_npy`].
//! - [`rotation`]: the quaternion / matrix helpers all of the above share.
//! - [`prep`]: `choreod prep` — AIST++ and HumanML3D to training-ready HDF5 shards, parallel,
//!   resumable, shardable across machines, with a merge of partial runs.
// No `#![forbid(unsafe_code)]`: ndarray's `s!` expands to `#[allow(unsafe_code)]`, which forbid rejects;
// the workspace lint denies unsafe code instead.

mod aistpp;
mod bvh;
mod convert;
mod error;
pub mod humanml3d;
mod motion_file;
mod npy;
pub mod pickle;
pub mod prep;
mod render;
pub mod rotation;
pub mod skeleton;
mod utc;

pub use aistpp::{AISTPP_FPS, AistppMotion, resample_joints, smpl_forward_kinematics};
pub use bvh::{
    BvhMotion, CMU_UNIT_M, JointRotations, read_bvh, read_bvh_scaled, write_bvh_positions,
    write_bvh_smpl,
};
pub use convert::{ConvertSummary, ConvertTarget, convert, load_motion};
pub use error::{Error, Result};
pub use humanml3d::{
    FeatureExtraction, FeatureOptions, extract_features, mirror_features, mirror_joints,
    recover_from_ric,
};
pub use motion_file::{
    Features, MOTION_FORMAT, MOTION_FORMAT_VERSION, MelAttachment, MotionAppender, MotionFile,
    Provenance, read_motion_file, write_motion_file,
};
pub use npy::{read_npy, write_npy};
pub use render::{RenderOptions, render_contact_sheet, render_gif};
pub use skeleton::{Skeleton, SkeletonKind};
pub use utc::{format_utc, now_utc};
