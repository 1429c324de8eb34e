//! One rig mapping for every verb: a skeleton read from a file (a BVH of any rig, a custom
//! skeleton in a motion file) placed on t2m-22 by its joint names, so `convert --to features`,
//! `eval`, `render` and `stylize` accept the same files.

use std::path::Path;

use ndarray::Array3;

use crate::error::{Error, Result};
use crate::formats::motion_file::MotionFile;
use crate::humanml3d::JOINTS;

/// SMPL-24's joint count.
const SMPL24_JOINTS: usize = 24;
use crate::rotation::{norm, sub};
use crate::skeleton::{SMPL24_JOINT_NAMES, SMPL24_OFFSETS, SkeletonKind, T2M22_JOINT_NAMES};
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
    /// (left, right): a joint past each wrist (a knuckle, a hand End Site) whose direction from
    /// the wrist is the hand's, for SMPL-24's hand joints ([`retarget_smpl24`]); t2m-22 has no
    /// hands, so placing a rig on t2m-22 does not need them.
    pub hands: [&'static str; 2],
}

use RigJoint::{Between, Named};

/// The CMU skeleton's t2m-22 placement (cgspeed's BVH conversion and MotionBuilder's export
/// share the body joints): LowerBack, Neck and the shoulders sit at zero offset on their
/// parents, the hip sockets are the UpLeg joints, so t2m's spine2 and collars are midpoints.
const RIGS_CMU_JOINTS: [RigJoint; JOINTS] = [
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
];

/// The rigs tried, in order; the first whose names are all present is used.
pub const RIGS: [Rig; 8] = [
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
        hands: ["LeftHandMiddle1", "RightHandMiddle1"],
    },
    // CMU mocap as converted to BVH (cgspeed; ../shared/fixtures/motion/cmu_01_01.bvh).
    Rig {
        name: "CMU",
        joints: RIGS_CMU_JOINTS,
        hands: ["LFingers", "RFingers"],
    },
    // CMU as exported from MotionBuilder (55_01 of the dance library, via FBX and Blender):
    // CMU's names and the same placement, but a finger chain LeftHandIndex1 instead of
    // LFingers; after "CMU" so that a t2m-22 placement of either keeps the name "CMU".
    Rig {
        name: "CMU MotionBuilder",
        joints: RIGS_CMU_JOINTS,
        hands: ["LeftHandIndex1", "RightHandIndex1"],
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
        hands: ["L_Hand", "R_Hand"],
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
        hands: ["lhand", "rhand"],
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
        hands: ["lMid1", "rMid1"],
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
        hands: ["CC_Base_L_Mid1", "CC_Base_R_Mid1"],
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
        hands: ["Neo_LeftHand_end", "Neo_RightHand_end"],
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
                retarget_t2m(joint_names, &m.joints).map_err(|u| u.into_error(path))?;
            Ok((joints, Some(rig)))
        }
    }
}

/// The motion's joints on SMPL-24 (`convert --to smpl24`): SMPL-24 as it is, a LODGE dance by
/// [`lodge_smpl24_joints`], a custom skeleton placed by [`retarget_smpl24`] (with the rig's
/// name). t2m-22 is refused: it has no hands. `path` names the file in the error.
pub fn smpl24_joints(path: &Path, m: &MotionFile) -> Result<(Array3<f32>, Option<&'static str>)> {
    if let Some(j) = lodge_smpl24_joints(path, m)? {
        return Ok((j, None));
    }
    match &m.skeleton {
        SkeletonKind::Smpl24 => Ok((m.joints.clone(), None)),
        SkeletonKind::T2m22 => Err(Error::invalid(
            path,
            "t2m-22 joints have no hands, which SMPL-24 needs: convert the source that has them \
             (e.g. the BVH)",
        )),
        SkeletonKind::Custom { joint_names, .. } => {
            let (joints, rig) =
                retarget_smpl24(joint_names, &m.joints).map_err(|u| u.into_error(path))?;
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

/// Why a skeleton cannot be placed on t2m-22 (or SMPL-24): the rig that came closest, the
/// joints it cannot place and the names it looked for.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Unmapped {
    /// The skeleton asked for: `"t2m-22"` or `"SMPL-24"`.
    pub target: &'static str,
    /// The closest rig's name.
    pub rig: &'static str,
    /// Joints of the target left without a source.
    pub missing: Vec<&'static str>,
    /// The closest rig's names for them, absent from the skeleton.
    pub wanted: Vec<&'static str>,
}

impl Unmapped {
    /// As the error every verb reports, naming `path`.
    pub fn into_error(self, path: &Path) -> Error {
        Error::MissingJoints {
            path: path.to_path_buf(),
            target: self.target,
            rig: self.rig,
            missing: self.missing,
            wanted: self.wanted,
        }
    }
}

/// t2m-22 joints (T, 22, 3) of a skeleton whose joints (T, J, 3) are named `names`, placed by
/// the first of [`RIGS`] that finds every name it needs, and that rig's name.
pub fn retarget_t2m(
    names: &[String],
    joints: &Array3<f32>,
) -> std::result::Result<(Array3<f32>, &'static str), Unmapped> {
    let rig = find_rig(names, false)?;
    Ok((retarget_by_name(&rig, names, joints), rig.name))
}

/// SMPL-24 joints (T, 24, 3) of a skeleton whose joints (T, J, 3) are named `names` (a BVH's
/// End Sites included, as `<parent>_end`), and the rig's name: SMPL-24's first 22 joints are
/// t2m-22's, placed as [`retarget_t2m`] places them by the first of [`RIGS`] that also names
/// both [`Rig::hands`]; each hand (SMPL's `lhand`, `rhand`) lies at SMPL's rest wrist-to-hand
/// length ([`SMPL24_OFFSETS`] 22 and 23: 8.8 and 8.9 cm) from the wrist towards the rig's hand
/// joint, so the hand keeps the source's direction, as the rest of the body does.
pub fn retarget_smpl24(
    names: &[String],
    joints: &Array3<f32>,
) -> std::result::Result<(Array3<f32>, &'static str), Unmapped> {
    let rig = find_rig(names, true)?;
    let body = retarget_by_name(&rig, names, joints);
    let index = name_index(names);
    let frames = joints.shape()[0];
    let mut out = Array3::zeros((frames, SMPL24_JOINTS, 3));
    out.slice_mut(ndarray::s![.., ..JOINTS, ..]).assign(&body);
    for (h, src) in rig.hands.iter().map(|n| index(n)).enumerate() {
        let (elbow, wrist, hand) = (18 + h, 20 + h, 22 + h);
        let length = norm(SMPL24_OFFSETS[hand]);
        for t in 0..frames {
            let at = |a: &Array3<f32>, j: usize| [0, 1, 2].map(|c| a[[t, j, c]]);
            let w = at(&body, wrist);
            let mut d = sub(at(joints, src), w);
            // A hand joint on the wrist has no direction: continue the forearm instead.
            if norm(d) <= f32::EPSILON {
                d = sub(w, at(&body, elbow));
            }
            let n = norm(d).max(f32::MIN_POSITIVE);
            for c in 0..3 {
                out[[t, hand, c]] = w[c] + d[c] * length / n;
            }
        }
    }
    Ok((out, rig.name))
}

/// Joints of the target a rig cannot place: (the target's joint name, the rig's names for it
/// that are absent).
type Unplaced = Vec<(&'static str, Vec<&'static str>)>;

/// The first of [`RIGS`] whose names (with its [`Rig::hands`] if `hands`) are all among
/// `names`; else the closest rig and what it cannot place.
fn find_rig(names: &[String], hands: bool) -> std::result::Result<Rig, Unmapped> {
    let have: Vec<String> = names.iter().map(|n| normalise_name(n)).collect();
    let found = |n: &str| have.contains(&normalise_name(n));
    let missing = |rig: &Rig| -> Unplaced {
        let body = rig.joints.iter().enumerate().map(|(k, src)| {
            let sources = match *src {
                Named(a) => vec![a],
                Between(a, b) => vec![a, b],
            };
            (T2M22_JOINT_NAMES[k], sources)
        });
        let hand_sources = rig
            .hands
            .iter()
            .zip(&SMPL24_JOINT_NAMES[JOINTS..])
            .map(|(src, name)| (*name, vec![*src]))
            .filter(|_| hands);
        body.chain(hand_sources)
            .filter_map(|(joint, sources)| {
                let absent: Vec<&'static str> = sources.into_iter().filter(|n| !found(n)).collect();
                (!absent.is_empty()).then_some((joint, absent))
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
        target: if hands { "SMPL-24" } else { "t2m-22" },
        rig: rig.name,
        missing: miss.iter().map(|(joint, _)| *joint).collect(),
        wanted,
    })
}

/// Position of a name among `names`, compared as [`normalise_name`] does (0 if absent:
/// callers look up names [`find_rig`] found).
fn name_index(names: &[String]) -> impl Fn(&str) -> usize {
    let have: Vec<String> = names.iter().map(|n| normalise_name(n)).collect();
    move |n: &str| {
        let n = normalise_name(n);
        have.iter().position(|h| *h == n).unwrap_or(0)
    }
}

/// (T, 22, 3) t2m joints picked (or interpolated) from a named skeleton's joints by `rig`.
fn retarget_by_name(rig: &Rig, names: &[String], joints: &Array3<f32>) -> Array3<f32> {
    let index = name_index(names);
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
    use crate::rotation::Vec3;

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
        assert_eq!(find_rig(&mixamo, false).unwrap().name, "Mixamo");
        // t2m's own names (e.g. in a custom-skeleton motion file) are SMPL-style ones.
        let t2m: Vec<String> = T2M22_JOINT_NAMES.iter().map(|n| n.to_string()).collect();
        let rig = find_rig(&t2m, false).unwrap();
        assert_eq!(rig.name, "SMPL");
        for (k, src) in rig.joints.iter().enumerate() {
            let Named(n) = src else { panic!("{src:?}") };
            assert_eq!(normalise_name(n), normalise_name(T2M22_JOINT_NAMES[k]));
        }
        assert_eq!(normalise_name("L_Hip"), normalise_name("left_hip"));
        assert_eq!(normalise_name("mixamorig:LeftUpLeg"), "lupleg");
    }

    /// Joint names of each dance-library source as the BVH reader names them (depth-first,
    /// End Sites as `<parent>_end`), copied from the files' hierarchies.
    /// ../shared/data/dance-mocap/cmu-55-dance/55_01.bvh.gz (CMU MotionBuilder).
    const CMU_55_01: &str = "Hips LHipJoint LeftUpLeg LeftLeg LeftFoot LeftToeBase LeftToeBase_end \
        LeftToeBase_end_end RHipJoint RightUpLeg RightLeg RightFoot RightToeBase \
        RightToeBase_end RightToeBase_end_end LowerBack Spine Spine1 Neck Neck1 Head Head_end \
        Head_end_end LeftShoulder LeftArm LeftForeArm LeftHand LeftFingerBase LeftHandIndex1 \
        LeftHandIndex1_end LeftHandIndex1_end_end LThumb LThumb_end LThumb_end_end \
        RightShoulder RightArm RightForeArm RightHand RightFingerBase RightHandIndex1 \
        RightHandIndex1_end RightHandIndex1_end_end RThumb RThumb_end RThumb_end_end";
    /// cmu-60-61-salsa/60_01_scaled.bvh.gz (Poser-style names).
    const SALSA_60_01: &str = "hip abdomen chest neck head leftEye leftEye_end rightEye rightEye_end rCollar rShldr \
        rForeArm rHand rThumb1 rThumb2 rThumb2_end rIndex1 rIndex2 rIndex2_end rMid1 rMid2 \
        rMid2_end rRing1 rRing2 rRing2_end rPinky1 rPinky2 rPinky2_end lCollar lShldr lForeArm \
        lHand lThumb1 lThumb2 lThumb2_end lIndex1 lIndex2 lIndex2_end lMid1 lMid2 lMid2_end \
        lRing1 lRing2 lRing2_end lPinky1 lPinky2 lPinky2_end rButtock rThigh rShin rFoot \
        rFoot_end lButtock lThigh lShin lFoot lFoot_end";
    /// cmu-85-breakdance/85_03.bvh.gz (keijiro's Neo).
    const NEO_85_03: &str = "Neo_Hips Neo_LeftUpLeg Neo_LeftLeg Neo_LeftFoot Neo_LeftToeBase Neo_LeftToeBase_end \
        Neo_RightUpLeg Neo_RightLeg Neo_RightFoot Neo_RightToeBase Neo_RightToeBase_end \
        Neo_Spine Neo_Spine1 Neo_Spine2 Neo_LeftShoulder Neo_LeftArm Neo_LeftForeArm \
        Neo_LeftHand Neo_LeftHand_end Neo_RightShoulder Neo_RightArm Neo_RightForeArm \
        Neo_RightHand Neo_RightHand_end Neo_Neck Neo_Head Neo_Head_end";
    /// cmu-05-modern/005_02.bvh.gz (Reallusion CC_Base).
    const CC_BASE_005_02: &str = "CC_Base_Hip CC_Base_Pelvis CC_Base_L_Thigh CC_Base_L_Calf CC_Base_L_Foot \
        CC_Base_L_ToeBaseShareBone CC_Base_L_ToeBaseShareBone_end CC_Base_L_ToeBase \
        CC_Base_L_PinkyToe1 CC_Base_L_PinkyToe1_end CC_Base_L_RingToe1 CC_Base_L_RingToe1_end \
        CC_Base_L_MidToe1 CC_Base_L_MidToe1_end CC_Base_L_IndexToe1 CC_Base_L_IndexToe1_end \
        CC_Base_L_BigToe1 CC_Base_L_BigToe1_end CC_Base_L_CalfTwist01 CC_Base_L_CalfTwist02 \
        CC_Base_L_CalfTwist02_end CC_Base_L_KneeShareBone CC_Base_L_KneeShareBone_end \
        CC_Base_L_ThighTwist01 CC_Base_L_ThighTwist02 CC_Base_L_ThighTwist02_end \
        CC_Base_R_Thigh CC_Base_R_ThighTwist01 CC_Base_R_ThighTwist02 \
        CC_Base_R_ThighTwist02_end CC_Base_R_Calf CC_Base_R_Foot CC_Base_R_ToeBase \
        CC_Base_R_PinkyToe1 CC_Base_R_PinkyToe1_end CC_Base_R_BigToe1 CC_Base_R_BigToe1_end \
        CC_Base_R_IndexToe1 CC_Base_R_IndexToe1_end CC_Base_R_MidToe1 CC_Base_R_MidToe1_end \
        CC_Base_R_RingToe1 CC_Base_R_RingToe1_end CC_Base_R_ToeBaseShareBone \
        CC_Base_R_ToeBaseShareBone_end CC_Base_R_KneeShareBone CC_Base_R_KneeShareBone_end \
        CC_Base_R_CalfTwist01 CC_Base_R_CalfTwist02 CC_Base_R_CalfTwist02_end CC_Base_Waist \
        CC_Base_Spine01 CC_Base_Spine02 CC_Base_NeckTwist01 CC_Base_NeckTwist02 CC_Base_Head \
        CC_Base_FacialBone CC_Base_JawRoot CC_Base_Tongue01 CC_Base_Tongue02 CC_Base_Tongue03 \
        CC_Base_Tongue03_end CC_Base_Teeth02 CC_Base_Teeth02_end CC_Base_R_Eye \
        CC_Base_R_Eye_end CC_Base_L_Eye CC_Base_L_Eye_end CC_Base_UpperJaw CC_Base_Teeth01 \
        CC_Base_Teeth01_end CC_Base_L_Clavicle CC_Base_L_Upperarm CC_Base_L_Forearm \
        CC_Base_L_ForearmTwist01 CC_Base_L_ForearmTwist02 CC_Base_L_ForearmTwist02_end \
        CC_Base_L_ElbowShareBone CC_Base_L_ElbowShareBone_end CC_Base_L_Hand CC_Base_L_Mid1 \
        CC_Base_L_Mid2 CC_Base_L_Mid3 CC_Base_L_Mid3_end CC_Base_L_Index1 CC_Base_L_Index2 \
        CC_Base_L_Index3 CC_Base_L_Index3_end CC_Base_L_Ring1 CC_Base_L_Ring2 CC_Base_L_Ring3 \
        CC_Base_L_Ring3_end CC_Base_L_Pinky1 CC_Base_L_Pinky2 CC_Base_L_Pinky3 \
        CC_Base_L_Pinky3_end CC_Base_L_Thumb1 CC_Base_L_Thumb2 CC_Base_L_Thumb3 \
        CC_Base_L_Thumb3_end CC_Base_L_UpperarmTwist01 CC_Base_L_UpperarmTwist02 \
        CC_Base_L_UpperarmTwist02_end CC_Base_R_Clavicle CC_Base_R_Upperarm \
        CC_Base_R_UpperarmTwist01 CC_Base_R_UpperarmTwist02 CC_Base_R_UpperarmTwist02_end \
        CC_Base_R_Forearm CC_Base_R_ForearmTwist01 CC_Base_R_ForearmTwist02 \
        CC_Base_R_ForearmTwist02_end CC_Base_R_ElbowShareBone CC_Base_R_ElbowShareBone_end \
        CC_Base_R_Hand CC_Base_R_Mid1 CC_Base_R_Mid2 CC_Base_R_Mid3 CC_Base_R_Mid3_end \
        CC_Base_R_Ring1 CC_Base_R_Ring2 CC_Base_R_Ring3 CC_Base_R_Ring3_end CC_Base_R_Thumb1 \
        CC_Base_R_Thumb2 CC_Base_R_Thumb3 CC_Base_R_Thumb3_end CC_Base_R_Index1 \
        CC_Base_R_Index2 CC_Base_R_Index3 CC_Base_R_Index3_end CC_Base_R_Pinky1 \
        CC_Base_R_Pinky2 CC_Base_R_Pinky3 CC_Base_R_Pinky3_end CC_Base_R_RibsTwist \
        CC_Base_R_Breast CC_Base_R_Breast_end CC_Base_L_RibsTwist CC_Base_L_Breast \
        CC_Base_L_Breast_end";

    fn names(list: &str) -> Vec<String> {
        list.split_whitespace().map(str::to_owned).collect()
    }

    /// Each dance-library rig is found by its files' real names, for t2m-22 and for SMPL-24
    /// (which also needs the hands), and the t2m-22 placement of MotionBuilder's CMU keeps the
    /// name "CMU". Without End Sites (a motion file of the salsa) the Poser rig has no toes.
    #[test]
    fn dance_library_rigs_are_found_by_their_real_names() {
        for (list, t2m, smpl24) in [
            (CMU_55_01, "CMU", "CMU MotionBuilder"),
            (SALSA_60_01, "Poser", "Poser"),
            (NEO_85_03, "Neo", "Neo"),
            (CC_BASE_005_02, "Reallusion CC_Base", "Reallusion CC_Base"),
        ] {
            let n = names(list);
            assert_eq!(find_rig(&n, false).unwrap().name, t2m, "{list}");
            assert_eq!(find_rig(&n, true).unwrap().name, smpl24, "{list}");
        }
        let no_end_sites: Vec<String> = names(SALSA_60_01)
            .into_iter()
            .filter(|n| !n.ends_with("_end"))
            .collect();
        let err = find_rig(&no_end_sites, false).unwrap_err();
        assert_eq!(err.rig, "Poser");
        assert_eq!(err.missing, ["left_foot", "right_foot"]);
        assert_eq!(err.wanted, ["lFoot_end", "rFoot_end"]);
        // The CMU fixture (cgspeed) has no LeftHandIndex1: its hands are LFingers.
        let mut cgspeed = names(CMU_55_01);
        cgspeed.retain(|n| !n.starts_with("LeftHandIndex1") && !n.starts_with("RightHandIndex1"));
        let err = find_rig(&cgspeed, true).unwrap_err();
        assert_eq!(
            (err.target, err.missing.as_slice()),
            ("SMPL-24", &["lhand", "rhand"][..])
        );
        cgspeed.extend(["LFingers".to_owned(), "RFingers".to_owned()]);
        assert_eq!(find_rig(&cgspeed, true).unwrap().name, "CMU");
    }

    /// SMPL-24 from each dance-library rig on a motion whose every joint sits somewhere else:
    /// joint k is where the rig's names say (looked up by exact name here, not by
    /// `normalise_name`), a `Between` is the midpoint, and each hand lies at SMPL's rest hand
    /// length from the wrist in the direction of the rig's hand joint (cosine 1 to 1e-6;
    /// length to 1e-6 m: f32 arithmetic on coordinates of magnitude <= 50).
    #[test]
    fn smpl24_places_each_rig_by_name_with_hands_at_smpl_length() {
        for list in [CMU_55_01, SALSA_60_01, NEO_85_03, CC_BASE_005_02] {
            let n = names(list);
            let (frames, count) = (3, n.len());
            let joints = Array3::from_shape_fn((frames, count, 3), |(t, j, c)| {
                let v = (j * 7 + c * 13 + t * 5) % 31;
                v as f32 * [0.5, -0.25, 0.75][c] + t as f32
            });
            let (got, rig_name) = retarget_smpl24(&n, &joints).unwrap();
            let rig = RIGS.iter().find(|r| r.name == rig_name).unwrap();
            assert_eq!(got.shape(), [frames, 24, 3]);
            let at = |name: &str, t: usize| -> Vec3 {
                let j = n
                    .iter()
                    .position(|x| x == name)
                    .unwrap_or_else(|| panic!("{name}"));
                [0, 1, 2].map(|c| joints[[t, j, c]])
            };
            for t in 0..frames {
                let got_at = |k: usize| [0, 1, 2].map(|c| got[[t, k, c]]);
                for (k, src) in rig.joints.iter().enumerate() {
                    let want = match *src {
                        Named(a) => at(a, t),
                        Between(a, b) => [0, 1, 2].map(|c| 0.5 * (at(a, t)[c] + at(b, t)[c])),
                    };
                    assert_eq!(got_at(k), want, "{rig_name} joint {k} frame {t}");
                }
                for h in 0..2 {
                    let wrist = got_at(20 + h);
                    let bone = sub(got_at(22 + h), wrist);
                    let towards = sub(at(rig.hands[h], t), wrist);
                    let length = norm(SMPL24_OFFSETS[22 + h]);
                    assert!((norm(bone) - length).abs() < 1e-6, "{rig_name} hand {h}");
                    let cos = (0..3).map(|c| bone[c] * towards[c]).sum::<f32>()
                        / (norm(bone) * norm(towards));
                    assert!(cos > 1.0 - 1e-6, "{rig_name} hand {h}: cosine {cos}");
                }
            }
        }
    }

    /// A hand joint on the wrist (no direction of its own) continues the forearm.
    #[test]
    fn a_hand_on_its_wrist_continues_the_forearm() {
        let n = names(NEO_85_03);
        let wrist = n.iter().position(|x| x == "Neo_LeftHand").unwrap();
        let elbow = n.iter().position(|x| x == "Neo_LeftForeArm").unwrap();
        let end = n.iter().position(|x| x == "Neo_LeftHand_end").unwrap();
        let mut joints = Array3::from_shape_fn((1, n.len(), 3), |(_, j, c)| (j + c) as f32);
        for (j, p) in [
            (elbow, [0.0, 1.0, 0.0]),
            (wrist, [0.0, 1.0, 0.3]),
            (end, [0.0, 1.0, 0.3]),
        ] {
            for c in 0..3 {
                joints[[0, j, c]] = p[c];
            }
        }
        let (got, _) = retarget_smpl24(&n, &joints).unwrap();
        let length = norm(SMPL24_OFFSETS[22]);
        let hand = [0, 1, 2].map(|c| got[[0, 22, c]]);
        let want = [0.0, 1.0, 0.3 + length];
        assert!((0..3).all(|c| (hand[c] - want[c]).abs() < 1e-6), "{hand:?}");
    }
}
