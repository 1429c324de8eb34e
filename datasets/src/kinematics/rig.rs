//! One rig mapping for every verb: a skeleton read from a file (a BVH of any rig, a custom
//! skeleton in a motion file) placed on t2m-22 by its joint names, so `convert --to features`,
//! `eval`, `render` and `stylize` accept the same files.

use std::path::Path;

use ndarray::Array3;

use crate::error::{Error, Result};
use crate::formats::motion_file::MotionFile;
use crate::humanml3d::JOINTS;
use crate::skeleton::{SkeletonKind, T2M22_JOINT_NAMES};
use crate::smplx::{
    BODY_JOINTS, LODGE_REPRESENTATION, SMPLX_BODY_PARENTS, SMPLX22_SKELETON, decode_frame,
    smpl_hands,
};

/// Where one t2m-22 joint comes from in a named rig.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RigJoint {
    /// The joint of this name.
    Named(&'static str),
    /// The midpoint of two named joints, for a rig with fewer spine or collar joints than t2m:
    /// a midpoint keeps every t2m bone's direction that of the source (a t2m joint placed on
    /// an existing one would leave a zero-length bone whose direction is undefined).
    Between(&'static str, &'static str),
}

/// A joint-name convention and where each t2m-22 joint (in [`T2M22_JOINT_NAMES`] order) is in
/// it. Names are compared after [`normalise_name`]: case, `_`, `-`, spaces and a namespace
/// prefix (`mixamorig:`) do not matter.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Rig {
    /// Shown in messages, e.g. `"CMU"`.
    pub name: &'static str,
    /// One source per t2m-22 joint.
    pub joints: [RigJoint; JOINTS],
}

use RigJoint::{Between, Named};

/// The rigs tried, in order; the first whose names are all present is used.
pub const RIGS: [Rig; 7] = [
    // Mixamo (Adobe's auto-rigger; `mixamorig:` prefix): one joint per t2m joint.
    Rig {
        name: "Mixamo",
        joints: [
            Named("Hips"),
            Named("LeftUpLeg"),
            Named("RightUpLeg"),
            Named("Spine"),
            Named("LeftLeg"),
            Named("RightLeg"),
            Named("Spine1"),
            Named("LeftFoot"),
            Named("RightFoot"),
            Named("Spine2"),
            Named("LeftToeBase"),
            Named("RightToeBase"),
            Named("Neck"),
            Named("LeftShoulder"),
            Named("RightShoulder"),
            Named("Head"),
            Named("LeftArm"),
            Named("RightArm"),
            Named("LeftForeArm"),
            Named("RightForeArm"),
            Named("LeftHand"),
            Named("RightHand"),
        ],
    },
    // CMU mocap as converted to BVH (cgspeed; ../shared/fixtures/motion/cmu_01_01.bvh):
    // LowerBack, Neck and the shoulders sit at zero offset on their parents, the hip sockets
    // are the UpLeg joints, so t2m's spine2 and collars are midpoints.
    Rig {
        name: "CMU",
        joints: [
            Named("Hips"),
            Named("LeftUpLeg"),
            Named("RightUpLeg"),
            Named("Spine"),
            Named("LeftLeg"),
            Named("RightLeg"),
            Between("Spine", "Spine1"),
            Named("LeftFoot"),
            Named("RightFoot"),
            Named("Spine1"),
            Named("LeftToeBase"),
            Named("RightToeBase"),
            Named("Neck1"),
            Between("LeftShoulder", "LeftArm"),
            Between("RightShoulder", "RightArm"),
            Named("Head"),
            Named("LeftArm"),
            Named("RightArm"),
            Named("LeftForeArm"),
            Named("RightForeArm"),
            Named("LeftHand"),
            Named("RightHand"),
        ],
    },
    // SMPL / SMPL-X exports (`L_Hip`, `Spine1`, `L_Collar`, ...), and t2m's own names.
    Rig {
        name: "SMPL",
        joints: [
            Named("Pelvis"),
            Named("L_Hip"),
            Named("R_Hip"),
            Named("Spine1"),
            Named("L_Knee"),
            Named("R_Knee"),
            Named("Spine2"),
            Named("L_Ankle"),
            Named("R_Ankle"),
            Named("Spine3"),
            Named("L_Foot"),
            Named("R_Foot"),
            Named("Neck"),
            Named("L_Collar"),
            Named("R_Collar"),
            Named("Head"),
            Named("L_Shoulder"),
            Named("R_Shoulder"),
            Named("L_Elbow"),
            Named("R_Elbow"),
            Named("L_Wrist"),
            Named("R_Wrist"),
        ],
    },
    // SMPL as EDGE names it (Stanford-TML/EDGE vis.py `smpl_joints`; our SMPL-24 BVH export).
    Rig {
        name: "SMPL (EDGE names)",
        joints: [
            Named("root"),
            Named("lhip"),
            Named("rhip"),
            Named("belly"),
            Named("lknee"),
            Named("rknee"),
            Named("spine"),
            Named("lankle"),
            Named("rankle"),
            Named("chest"),
            Named("ltoes"),
            Named("rtoes"),
            Named("neck"),
            Named("linshoulder"),
            Named("rinshoulder"),
            Named("head"),
            Named("lshoulder"),
            Named("rshoulder"),
            Named("lelbow"),
            Named("relbow"),
            Named("lwrist"),
            Named("rwrist"),
        ],
    },
    // CMU salsa as converted with Poser/DAZ names (hip, abdomen, lShldr; the dance library's
    // 60_xx / 61_xx): no toe joint, so t2m's feet are the foot's End Site (kept by
    // `BvhMotion`, not by its motion file); spine2 is the midpoint of abdomen and chest.
    Rig {
        name: "Poser",
        joints: [
            Named("hip"),
            Named("lThigh"),
            Named("rThigh"),
            Named("abdomen"),
            Named("lShin"),
            Named("rShin"),
            Between("abdomen", "chest"),
            Named("lFoot"),
            Named("rFoot"),
            Named("chest"),
            Named("lFoot_end"),
            Named("rFoot_end"),
            Named("neck"),
            Named("lCollar"),
            Named("rCollar"),
            Named("head"),
            Named("lShldr"),
            Named("rShldr"),
            Named("lForeArm"),
            Named("rForeArm"),
            Named("lHand"),
            Named("rHand"),
        ],
    },
    // Reallusion Character Creator (`CC_Base_`; CMU 05_xx retargeted in iClone).
    Rig {
        name: "Reallusion CC_Base",
        joints: [
            Named("CC_Base_Hip"),
            Named("CC_Base_L_Thigh"),
            Named("CC_Base_R_Thigh"),
            Named("CC_Base_Waist"),
            Named("CC_Base_L_Calf"),
            Named("CC_Base_R_Calf"),
            Named("CC_Base_Spine01"),
            Named("CC_Base_L_Foot"),
            Named("CC_Base_R_Foot"),
            Named("CC_Base_Spine02"),
            Named("CC_Base_L_ToeBase"),
            Named("CC_Base_R_ToeBase"),
            Named("CC_Base_NeckTwist01"),
            Named("CC_Base_L_Clavicle"),
            Named("CC_Base_R_Clavicle"),
            Named("CC_Base_Head"),
            Named("CC_Base_L_Upperarm"),
            Named("CC_Base_R_Upperarm"),
            Named("CC_Base_L_Forearm"),
            Named("CC_Base_R_Forearm"),
            Named("CC_Base_L_Hand"),
            Named("CC_Base_R_Hand"),
        ],
    },
    // keijiro's "Neo" humanoid (CMUMocap; CMU 85_xx): Mixamo's names behind a `Neo_` prefix.
    Rig {
        name: "Neo",
        joints: [
            Named("Neo_Hips"),
            Named("Neo_LeftUpLeg"),
            Named("Neo_RightUpLeg"),
            Named("Neo_Spine"),
            Named("Neo_LeftLeg"),
            Named("Neo_RightLeg"),
            Named("Neo_Spine1"),
            Named("Neo_LeftFoot"),
            Named("Neo_RightFoot"),
            Named("Neo_Spine2"),
            Named("Neo_LeftToeBase"),
            Named("Neo_RightToeBase"),
            Named("Neo_Neck"),
            Named("Neo_LeftShoulder"),
            Named("Neo_RightShoulder"),
            Named("Neo_Head"),
            Named("Neo_LeftArm"),
            Named("Neo_RightArm"),
            Named("Neo_LeftForeArm"),
            Named("Neo_RightForeArm"),
            Named("Neo_LeftHand"),
            Named("Neo_RightHand"),
        ],
    },
];

/// A joint name as rigs compare it: the part after the last `:` (FBX/Mixamo namespaces),
/// lower case, without `_`, `-`, `.` and spaces; `left`/`right` prefixes become `l`/`r`, so
/// `L_Hip`, `left_hip` and `LeftHip` compare equal.
pub fn normalise_name(name: &str) -> String {
    let base = name.rsplit(':').next().unwrap_or(name);
    let flat: String = base
        .chars()
        .filter(|c| !matches!(c, '_' | '-' | '.' | ' '))
        .flat_map(char::to_lowercase)
        .collect();
    for (long, short) in [("left", "l"), ("right", "r")] {
        if let Some(rest) = flat.strip_prefix(long) {
            return format!("{short}{rest}");
        }
    }
    flat
}

/// How a LODGE dance's SMPL-X joints become SMPL-24 (reports and provenance say it).
pub const LODGE_ON_SMPL24: &str = "SMPL-X's 22 body joints as SMPL-24's first 22; SMPL's hands \
                                   = each wrist + SMPL's rest wrist-to-hand bone turned by the \
                                   danced wrist rotation";

/// A LODGE dance (skeleton [`SMPLX22_SKELETON`] with its raw `lodge-smplx139` features) on
/// SMPL-24: SMPL's first 22 joints are SMPL-X's first 22 in the same order (smplx
/// `joint_names.py`: `JOINT_NAMES[:22]` and `JOINT_NAMES_DICT['smpl'][:22]` are one list), so
/// they are copied; the hands are [`smpl_hands`] of each frame. `None` for any other motion.
pub fn lodge_smpl24_joints(path: &Path, m: &MotionFile) -> Result<Option<Array3<f32>>> {
    let features = match (&m.skeleton, &m.features) {
        (SkeletonKind::Custom { name, parents, .. }, Some(f))
            if name == SMPLX22_SKELETON
                && parents.as_slice() == SMPLX_BODY_PARENTS
                && f.representation == LODGE_REPRESENTATION
                && !f.normalized
                && f.data.nrows() == m.joints.shape()[0] =>
        {
            f
        }
        _ => return Ok(None),
    };
    let frames = m.joints.shape()[0];
    let mut out = Array3::zeros((frames, 24, 3));
    out.slice_mut(ndarray::s![.., ..BODY_JOINTS, ..])
        .assign(&m.joints);
    for (t, row) in features.data.outer_iter().enumerate() {
        let frame = row.to_vec();
        let pose = decode_frame(&frame).map_err(|e| e.with_path(path))?;
        let wrist = |j: usize| [0, 1, 2].map(|k| m.joints[[t, j, k]]);
        let hands = smpl_hands(&pose, [wrist(20), wrist(21)]);
        for (h, p) in hands.iter().enumerate() {
            for k in 0..3 {
                out[[t, BODY_JOINTS + h, k]] = p[k];
            }
        }
    }
    Ok(Some(out))
}

/// The motion's joints on the t2m-22 skeleton (SMPL-24's first 22 joints are t2m's; a LODGE
/// dance's SMPL-X body joints are too, [`lodge_smpl24_joints`]; another custom skeleton is
/// placed by [`retarget_t2m`]), and the rig used for a custom skeleton. `path` names the file
/// in the error.
pub fn t2m_joints(path: &Path, m: &MotionFile) -> Result<(Array3<f32>, Option<&'static str>)> {
    if let Some(j) = lodge_smpl24_joints(path, m)? {
        return Ok((j.slice(ndarray::s![.., ..JOINTS, ..]).to_owned(), None));
    }
    match &m.skeleton {
        SkeletonKind::T2m22 => Ok((m.joints.clone(), None)),
        SkeletonKind::Smpl24 => Ok((
            m.joints.slice(ndarray::s![.., ..JOINTS, ..]).to_owned(),
            None,
        )),
        SkeletonKind::Custom { joint_names, .. } => {
            let (joints, rig) =
                retarget_t2m(joint_names, &m.joints).map_err(|u| Error::MissingJoints {
                    path: path.to_path_buf(),
                    rig: u.rig,
                    missing: u.missing,
                    wanted: u.wanted,
                })?;
            Ok((joints, Some(rig)))
        }
    }
}

/// The motion on a skeleton the metrics and HumanML3D features know: SMPL-24 and t2m-22 as
/// they are, a LODGE dance on SMPL-24 ([`lodge_smpl24_joints`]), another custom skeleton
/// placed on t2m-22 by [`t2m_joints`] (same frame rate, no features or mel: they belonged to
/// the other skeleton).
pub fn on_standard_skeleton(path: &Path, m: MotionFile) -> Result<MotionFile> {
    if m.skeleton.skeleton().is_some() {
        return Ok(m);
    }
    let (skeleton, joints) = match lodge_smpl24_joints(path, &m)? {
        Some(j) => {
            tracing::info!(file = %path.display(), "LODGE dance on SMPL-24: {LODGE_ON_SMPL24}");
            (SkeletonKind::Smpl24, j)
        }
        None => {
            let (joints, rig) = t2m_joints(path, &m)?;
            tracing::debug!(file = %path.display(), rig, "skeleton placed on t2m-22");
            (SkeletonKind::T2m22, joints)
        }
    };
    let mut out = MotionFile::from_joints(m.fps, skeleton, joints);
    out.provenance = m.provenance;
    out.generator = m.generator;
    Ok(out)
}

/// Why a skeleton cannot be placed on t2m-22: the rig that came closest, the t2m joints it
/// cannot place and the names it looked for.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Unmapped {
    /// The closest rig's name.
    pub rig: &'static str,
    /// t2m-22 joints left without a source.
    pub missing: Vec<&'static str>,
    /// The closest rig's names for them, absent from the skeleton.
    pub wanted: Vec<&'static str>,
}

/// t2m-22 joints (T, 22, 3) of a skeleton whose joints (T, J, 3) are named `names`, placed by
/// the first of [`RIGS`] that finds every name it needs, and that rig's name.
pub fn retarget_t2m(
    names: &[String],
    joints: &Array3<f32>,
) -> std::result::Result<(Array3<f32>, &'static str), Unmapped> {
    let rig = find_rig(names)?;
    Ok((retarget_by_name(&rig, names, joints), rig.name))
}

/// t2m joints a rig cannot place: (t2m index, the rig's names for it that are absent).
type Unplaced = Vec<(usize, Vec<&'static str>)>;

/// The first of [`RIGS`] whose names are all among `names`; else the closest rig and what it
/// cannot place.
fn find_rig(names: &[String]) -> std::result::Result<Rig, Unmapped> {
    let have: Vec<String> = names.iter().map(|n| normalise_name(n)).collect();
    let found = |n: &str| have.contains(&normalise_name(n));
    let missing = |rig: &Rig| -> Unplaced {
        rig.joints
            .iter()
            .enumerate()
            .filter_map(|(k, src)| {
                let absent: Vec<&'static str> = match *src {
                    Named(a) => vec![a],
                    Between(a, b) => vec![a, b],
                }
                .into_iter()
                .filter(|n| !found(n))
                .collect();
                (!absent.is_empty()).then_some((k, absent))
            })
            .collect()
    };
    // RIGS is not empty, so the first rig is a candidate.
    let mut best: (&Rig, Unplaced) = (&RIGS[0], missing(&RIGS[0]));
    for rig in &RIGS {
        let miss = missing(rig);
        if miss.is_empty() {
            return Ok(*rig);
        }
        if miss.len() < best.1.len() {
            best = (rig, miss);
        }
    }
    let (rig, miss) = best;
    let mut wanted: Vec<&'static str> = miss.iter().flat_map(|(_, n)| n.iter().copied()).collect();
    wanted.dedup();
    Err(Unmapped {
        rig: rig.name,
        missing: miss.iter().map(|(k, _)| T2M22_JOINT_NAMES[*k]).collect(),
        wanted,
    })
}

/// (T, 22, 3) t2m joints picked (or interpolated) from a named skeleton's joints by `rig`.
fn retarget_by_name(rig: &Rig, names: &[String], joints: &Array3<f32>) -> Array3<f32> {
    let have: Vec<String> = names.iter().map(|n| normalise_name(n)).collect();
    // `find_rig` checked that every name exists.
    let index = |n: &str| {
        let n = normalise_name(n);
        have.iter().position(|h| *h == n).unwrap_or(0)
    };
    let sources: Vec<(usize, usize)> = rig
        .joints
        .iter()
        .map(|src| match *src {
            Named(a) => (index(a), index(a)),
            Between(a, b) => (index(a), index(b)),
        })
        .collect();
    Array3::from_shape_fn((joints.shape()[0], JOINTS, 3), |(t, j, c)| {
        let (a, b) = sources[j];
        0.5 * (joints[[t, a, c]] + joints[[t, b, c]])
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rigs_are_found_by_normalised_names() {
        let mixamo: Vec<String> = [
            "Hips",
            "Spine",
            "Spine1",
            "Spine2",
            "Neck",
            "Head",
            "LeftShoulder",
            "LeftArm",
            "LeftForeArm",
            "LeftHand",
            "RightShoulder",
            "RightArm",
            "RightForeArm",
            "RightHand",
            "LeftUpLeg",
            "LeftLeg",
            "LeftFoot",
            "LeftToeBase",
            "RightUpLeg",
            "RightLeg",
            "RightFoot",
            "RightToeBase",
        ]
        .iter()
        .map(|n| format!("mixamorig:{n}"))
        .collect();
        assert_eq!(find_rig(&mixamo).unwrap().name, "Mixamo");
        // t2m's own names (e.g. in a custom-skeleton motion file) are SMPL-style ones.
        let t2m: Vec<String> = T2M22_JOINT_NAMES.iter().map(|n| n.to_string()).collect();
        let rig = find_rig(&t2m).unwrap();
        assert_eq!(rig.name, "SMPL");
        for (k, src) in rig.joints.iter().enumerate() {
            let Named(n) = src else { panic!("{src:?}") };
            assert_eq!(normalise_name(n), normalise_name(T2M22_JOINT_NAMES[k]));
        }
        assert_eq!(normalise_name("L_Hip"), normalise_name("left_hip"));
        assert_eq!(normalise_name("mixamorig:LeftUpLeg"), "lupleg");
    }
}
