//! Skeletons and what moves them: the skeleton constants, the one rig mapping of named
//! skeletons onto t2m-22, rigid poses fitted to joint positions, foot-contact cleanup and the
//! rotation helpers they share. (SMPL forward kinematics lives with the AIST++ reader it
//! serves, `formats::aistpp`.)

pub mod foot_lock;
pub mod rig;
pub mod rigid;
pub mod rotation;
pub mod skeleton;
pub mod smplx;
