//! Motion representations and files of choreod, by concern:
//!
//! - **Formats** (`formats`): one reader per motion format — AIST++ `.pkl` ([`AistppMotion`]
//!   through a safe [`pickle`] subset), `.npy` ([`read_npy`]), BVH of any hierarchy
//!   ([`read_bvh`]), the HDF5 motion file ([`MotionFile`], [`read_motion_file`],
//!   [`write_motion_file`], the live [`MotionAppender`]) — and the one [`probe`] that picks the
//!   reader by content, then extension ([`MotionFormat`]). [`load_motion`] is how every verb
//!   reads motion. Reader [`limits`] bound what any reader allocates; [`isolated`] reads
//!   untrusted `.h5` files in a child process, so a crash of libhdf5 fails the file, not the
//!   program.
//! - **Skeleton and kinematics** (`kinematics`): [`SkeletonKind`] (SMPL-24, t2m-22, custom)
//!   with the reference constants in [`skeleton`]; SMPL forward kinematics
//!   ([`smpl_forward_kinematics`]) and [`resample_joints`]; the one rig mapping ([`RIGS`],
//!   [`t2m_joints`], [`on_standard_skeleton`]) that places any named skeleton (a CMU or Mixamo
//!   BVH) on t2m-22 for every verb; rigid poses ([`fit_rigid_pose`], [`RigidFitter`]); foot
//!   contact cleanup ([`lock_feet`]); the [`rotation`] helpers.
//! - **Features** (`features`): HumanML3D 263-dim features ([`humanml3d`]:
//!   [`extract_features`], [`recover_from_ric`], mirroring); style-transfer inputs
//!   ([`load_motion_input`] → [`MotionInput`] at a model's rate); long content cut into
//!   overlapping segments ([`plan_segments`], [`stitch_segments`]).
//! - **Output**: [`write_motion_as`] is the one writer by extension of finished motion (`.h5`,
//!   `.bvh`, `.glb`, `.gltf`, `.npy`; [`ExportRig::Mixamo`] for Mixamo bone names), and
//!   [`convert`] the engine of `choreod convert`.
//! - **Render** (`render`): pictures ([`render_gif`], [`render_contact_sheet`]) and glTF
//!   ([`gltf_bytes`]: a skinned mannequin made here, the skeleton, one animation).
//! - [`metrics`]: `choreod eval` — kinetic / geometric features, FID_k / FID_g, diversity, Beat
//!   Alignment Score in both conventions, PFC, foot skating, TSI / FSF ([`evaluate`] →
//!   [`EvalReport`]).
//! - [`smplx`]: LODGE's FineDance representation (139 values: contacts, SMPL-X `transl`, 22
//!   body joints as 6D) with pytorch3d's rotation formulas and the official SMPL-X body FK.
//! - [`prep`]: `choreod prep` — AIST++ and HumanML3D to training-ready HDF5 shards, parallel,
//!   resumable, shardable across machines, with a merge of partial runs.
//! - [`Error`]: the crate's one error type, with the variants callers branch on;
//!   [`sha256_file`] and [`now_utc`] for provenance.
// No `#![forbid(unsafe_code)]`: ndarray's `s!` expands to `#[allow(unsafe_code)]`, which forbid rejects;
// the workspace lint denies unsafe code instead.

mod checksum;
mod convert;
mod error;
mod export;
mod features;
mod formats;
mod kinematics;
pub mod metrics;
pub mod prep;
mod render;
mod utc;

pub use features::{
    humanml3d,
    segments::{default_overlap, plan_segments, stitch_segments},
};
pub use formats::{isolated, limits, pickle};
pub use kinematics::{rotation, skeleton, smplx};

pub use checksum::sha256_file;
pub use convert::{ConvertOptions, ConvertSummary, ConvertTarget, convert};
pub use error::{Error, ExportRefusal, FrameBound, Result};
pub use export::{
    ExportOptions, ExportRig, MIXAMO_NAMES, MIXAMO_PREFIX, OUTPUT_EXTENSIONS, OutputFormat,
    check_output, write_motion_as,
};
pub use features::humanml3d::{
    FeatureExtraction, FeatureOptions, extract_features, mirror_features, mirror_joints,
    recover_from_ric,
};
pub use features::motion_input::{
    InputOrigin, MAX_INPUT_FRAMES, MotionInput, MotionInputOptions, load_motion_input,
};
pub use formats::aistpp::{AISTPP_FPS, AistppMotion, resample_joints, smpl_forward_kinematics};
pub use formats::bvh::{
    BvhMotion, CMU_UNIT_M, read_bvh, read_bvh_scaled, write_bvh_named, write_bvh_positions,
    write_bvh_smpl,
};
pub use formats::motion_file::{
    Features, MAX_MOTION_VALUE, MOTION_FORMAT, MOTION_FORMAT_VERSION, MelAttachment,
    MotionAppender, MotionFile, Provenance, StyleProvenance, read_motion_file, write_motion_file,
};
pub use formats::npy::{read_npy, read_npz, write_npy, write_npz};
pub use formats::{
    LoadedMotion, MOTION_EXTENSIONS, MotionFormat, NpyMotion, load_motion, npy_default_fps, probe,
    read_npy_motion,
};
pub use kinematics::foot_lock::lock_feet;
pub use kinematics::rig::{
    RIGS, Rig, RigJoint, Unmapped, normalise_name, on_standard_skeleton, retarget_smpl24,
    retarget_t2m, smpl24_joints, t2m_joints,
};
pub use kinematics::rigid::{MAX_TWIST_STEP, RigidFitter, RigidPose, fit_rigid_pose};
pub use kinematics::skeleton::{Skeleton, SkeletonKind};
pub use metrics::{EvalOptions, EvalReport, evaluate};
pub use render::gltf::{GltfSkeleton, gltf_bytes, read_gltf_skeleton, rest_mannequin_glb};
pub use render::picture::{RenderOptions, render_contact_sheet, render_gif};
pub use utc::{format_utc, now_utc};
