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
//! - Rigid poses: [`fit_rigid_pose`] turns joint positions into a [`RigidPose`] (fixed bone
//!   offsets, continuous per-joint rotations, forward kinematics back to joints); a
//!   [`RigidFitter`] does it chunk by chunk with offsets fixed at the start (live output, whose
//!   rotations are also the VMC bones).
//! - Foot contact: [`lock_feet`] pins planted toes (and re-solves the knees) after stitching.
//! - BVH: [`read_bvh`] (any hierarchy) and [`write_bvh_positions`] (the rotations of
//!   [`fit_rigid_pose`]).
//! - glTF: [`write_motion_as`] writes `.glb` / `.gltf` (a skinned mannequin made here, the
//!   skeleton, one animation), and is the one writer-by-extension of finished motion (`.h5`,
//!   `.bvh`, `.glb`, `.gltf`, `.npy`); [`ExportRig::Mixamo`] exports Mixamo bone names.
//! - [`convert`]: the engine of `choreod convert`.
//! - Style-transfer inputs: [`load_motion_input`] reads any of the above as HumanML3D features
//!   at a model's frame rate ([`MotionInput`]), mapping named skeletons onto t2m-22 with a
//!   [`Rig`]; [`plan_segments`] / [`stitch_segments`] cut long content into overlapping
//!   segments and cross-fade the results.
//! - `.npy` files: [`read_npy`], [`write_npy`] (through `choreo_dsp::write_npy_f32`).
//! - Reader limits ([`limits`]): the element cap, and the HDF5 checks every `.h5` read passes
//!   (no links or storage outside the file, no declared-but-unwritten data).
//! - [`isolated`]: untrusted `.h5` files read in a child process under limits, so that a crash
//!   of libhdf5 fails the file, not the program.
//! - [`sha256_file`]: the checksum of inputs recorded in provenance and manifests.
//! - [`metrics`]: `choreod eval` — kinetic / geometric features, FID_k / FID_g, diversity, Beat
//!   Alignment Score in both conventions, PFC, foot skating, TSI / FSF ([`evaluate`] →
//!   [`EvalReport`]).
//! - [`rotation`]: the quaternion / matrix helpers all of the above share.
//! - [`smplx`]: LODGE's FineDance representation (139 values: contacts, SMPL-X `transl`, 22
//!   body joints as 6D) with pytorch3d's rotation formulas and the official SMPL-X body FK.
//! - [`prep`]: `choreod prep` — AIST++ and HumanML3D to training-ready HDF5 shards, parallel,
//!   resumable, shardable across machines, with a merge of partial runs.
// No `#![forbid(unsafe_code)]`: ndarray's `s!` expands to `#[allow(unsafe_code)]`, which forbid rejects;
// the workspace lint denies unsafe code instead.

mod aistpp;
mod bvh;
mod checksum;
mod convert;
mod error;
mod export;
mod foot_lock;
mod gltf;
mod h5;
pub mod humanml3d;
pub mod isolated;
pub mod limits;
mod mannequin;
pub mod metrics;
mod motion_file;
mod motion_input;
mod npy;
pub mod pickle;
pub mod prep;
mod render;
mod rigid;
pub mod rotation;
mod segments;
pub mod skeleton;
pub mod smplx;
mod utc;

pub use aistpp::{AISTPP_FPS, AistppMotion, resample_joints, smpl_forward_kinematics};
pub use bvh::{
    BvhMotion, CMU_UNIT_M, read_bvh, read_bvh_scaled, write_bvh_named, write_bvh_positions,
    write_bvh_smpl,
};
pub use checksum::sha256_file;
pub use convert::{
    ConvertOptions, ConvertSummary, ConvertTarget, LoadedMotion, convert, load_motion,
    npy_default_fps,
};
pub use error::{Error, Result};
pub use export::{
    ExportOptions, ExportRig, MIXAMO_NAMES, MIXAMO_PREFIX, OUTPUT_EXTENSIONS, OutputFormat,
    check_output, write_motion_as,
};
pub use foot_lock::lock_feet;
pub use gltf::gltf_bytes;
pub use humanml3d::{
    FeatureExtraction, FeatureOptions, extract_features, mirror_features, mirror_joints,
    recover_from_ric,
};
pub use metrics::{EvalOptions, EvalReport, evaluate};
pub use motion_file::{
    Features, MAX_MOTION_VALUE, MOTION_FORMAT, MOTION_FORMAT_VERSION, MelAttachment,
    MotionAppender, MotionFile, Provenance, StyleProvenance, read_motion_file, write_motion_file,
};
pub use motion_input::{
    InputOrigin, MAX_INPUT_FRAMES, MotionInput, MotionInputOptions, RIGS, Rig, RigJoint,
    load_motion_input, normalise_name, retarget_t2m,
};
pub use npy::{read_npy, write_npy};
pub use render::{RenderOptions, render_contact_sheet, render_gif};
pub use rigid::{MAX_TWIST_STEP, RigidFitter, RigidPose, fit_rigid_pose};
pub use segments::{default_overlap, plan_segments, stitch_segments};
pub use skeleton::{Skeleton, SkeletonKind};
pub use utc::{format_utc, now_utc};
