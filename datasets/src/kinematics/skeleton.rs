//! Skeleton definitions: SMPL-24 (AIST++, EDGE) and HumanML3D's t2m-22, plus skeletons read
//! from BVH files.

use crate::rotation::Vec3;

/// Joint counts above this are not a body (every reader refuses them: BVH, motion file).
pub const MAX_JOINTS: usize = 1024;

/// SMPL joint names in SMPL order, spelled as in Stanford-TML/EDGE:vis.py `smpl_joints`.
pub const SMPL24_JOINT_NAMES: [&str; 24] = [
    "root",
    "lhip",
    "rhip",
    "belly",
    "lknee",
    "rknee",
    "spine",
    "lankle",
    "rankle",
    "chest",
    "ltoes",
    "rtoes",
    "neck",
    "linshoulder",
    "rinshoulder",
    "head",
    "lshoulder",
    "rshoulder",
    "lelbow",
    "relbow",
    "lwrist",
    "rwrist",
    "lhand",
    "rhand",
];

/// SMPL parents (Stanford-TML/EDGE:vis.py `smpl_parents`).
pub const SMPL24_PARENTS: [i32; 24] = [
    -1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21,
];

/// SMPL neutral rest offsets from each joint's parent, metres, y-up, facing +z
/// (Stanford-TML/EDGE:vis.py `smpl_offsets`). The root's offset is zero: AIST++ places the root
/// at `smpl_trans / smpl_scaling`.
// Digits kept exactly as published so the table can be diffed against the source.
#[allow(clippy::excessive_precision)]
pub const SMPL24_OFFSETS: [Vec3; 24] = [
    [0.0, 0.0, 0.0],
    [0.05858135, -0.08228004, -0.01766408],
    [-0.06030973, -0.09051332, -0.01354254],
    [0.00443945, 0.12440352, -0.03838522],
    [0.04345142, -0.38646945, 0.008037],
    [-0.04325663, -0.38368791, -0.00484304],
    [0.00448844, 0.1379564, 0.02682033],
    [-0.01479032, -0.42687458, -0.037428],
    [0.01905555, -0.4200455, -0.03456167],
    [-0.00226458, 0.05603239, 0.00285505],
    [0.04105436, -0.06028581, 0.12204243],
    [-0.03483987, -0.06210566, 0.13032329],
    [-0.0133902, 0.21163553, -0.03346758],
    [0.07170245, 0.11399969, -0.01889817],
    [-0.08295366, 0.11247234, -0.02370739],
    [0.01011321, 0.08893734, 0.05040987],
    [0.12292141, 0.04520509, -0.019046],
    [-0.11322832, 0.04685326, -0.00847207],
    [0.2553319, -0.01564902, -0.02294649],
    [-0.26012748, -0.01436928, -0.03126873],
    [0.26570925, 0.01269811, -0.00737473],
    [-0.26910836, 0.00679372, -0.00602676],
    [0.08669055, -0.01063603, -0.01559429],
    [-0.0887537, -0.00865157, -0.01010708],
];

/// HumanML3D joint names. The t2m skeleton is the first 22 SMPL joints (pelvis … wrists), in SMPL
/// order (EricGuo5513/HumanML3D:paramUtil.py comments, raw_pose_processing.ipynb `[:, :22]`).
pub const T2M22_JOINT_NAMES: [&str; 22] = [
    "pelvis",
    "left_hip",
    "right_hip",
    "spine1",
    "left_knee",
    "right_knee",
    "spine2",
    "left_ankle",
    "right_ankle",
    "spine3",
    "left_foot",
    "right_foot",
    "neck",
    "left_collar",
    "right_collar",
    "head",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
];

/// t2m kinematic chains (EricGuo5513/HumanML3D:paramUtil.py `t2m_kinematic_chain`): right leg,
/// left leg, spine to head, right arm, left arm. The arm chains start at joint 9 (spine3).
pub const T2M22_KINEMATIC_CHAIN: [&[usize]; 5] = [
    &[0, 2, 5, 8, 11],
    &[0, 1, 4, 7, 10],
    &[0, 3, 6, 9, 12, 15],
    &[9, 14, 17, 19, 21],
    &[9, 13, 16, 18, 20],
];

/// t2m parents, derived from [`T2M22_KINEMATIC_CHAIN`] (equal to the SMPL parents of joints 0..22).
pub const T2M22_PARENTS: [i32; 22] = [
    -1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19,
];

/// t2m raw offsets: unit directions of each bone in the rest pose
/// (EricGuo5513/HumanML3D:paramUtil.py `t2m_raw_offsets`).
pub const T2M22_RAW_OFFSETS: [Vec3; 22] = [
    [0.0, 0.0, 0.0],
    [1.0, 0.0, 0.0],
    [-1.0, 0.0, 0.0],
    [0.0, 1.0, 0.0],
    [0.0, -1.0, 0.0],
    [0.0, -1.0, 0.0],
    [0.0, 1.0, 0.0],
    [0.0, -1.0, 0.0],
    [0.0, -1.0, 0.0],
    [0.0, 1.0, 0.0],
    [0.0, 0.0, 1.0],
    [0.0, 0.0, 1.0],
    [0.0, 1.0, 0.0],
    [1.0, 0.0, 0.0],
    [-1.0, 0.0, 0.0],
    [0.0, 0.0, 1.0],
    [0.0, -1.0, 0.0],
    [0.0, -1.0, 0.0],
    [0.0, -1.0, 0.0],
    [0.0, -1.0, 0.0],
    [0.0, -1.0, 0.0],
    [0.0, -1.0, 0.0],
];

/// Left joints of SMPL, paired index by index with [`SMPL_RIGHT`]
/// (HumanML3D raw_pose_processing.ipynb mirror chains, extended by the SMPL hands 22/23).
pub const SMPL_LEFT: [usize; 9] = [1, 4, 7, 10, 13, 16, 18, 20, 22];
/// Right joints of SMPL (see [`SMPL_LEFT`]).
pub const SMPL_RIGHT: [usize; 9] = [2, 5, 8, 11, 14, 17, 19, 21, 23];

/// A built-in skeleton's constants.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Skeleton {
    /// `"smpl24"` or `"t2m22"` (the motion file's `skeleton` attribute).
    pub name: &'static str,
    /// One name per joint.
    pub joint_names: &'static [&'static str],
    /// Parent per joint, -1 for the root; parents precede children.
    pub parents: &'static [i32],
    /// Rest offset of each joint from its parent: metres for SMPL-24 (EDGE vis.py); unit
    /// directions for t2m-22 (paramUtil.py raw offsets; lengths in
    /// [`T2M22_TARGET_BONE_LENGTHS`]).
    pub offsets: &'static [Vec3],
    /// Kinematic chains (t2m only; empty for SMPL-24).
    pub kinematic_chain: &'static [&'static [usize]],
}

impl Skeleton {
    /// SMPL-24.
    pub const SMPL24: Skeleton = Skeleton {
        name: "smpl24",
        joint_names: &SMPL24_JOINT_NAMES,
        parents: &SMPL24_PARENTS,
        offsets: &SMPL24_OFFSETS,
        kinematic_chain: &[],
    };
    /// HumanML3D t2m-22.
    pub const T2M22: Skeleton = Skeleton {
        name: "t2m22",
        joint_names: &T2M22_JOINT_NAMES,
        parents: &T2M22_PARENTS,
        offsets: &T2M22_RAW_OFFSETS,
        kinematic_chain: &T2M22_KINEMATIC_CHAIN,
    };

    /// Joint count.
    pub fn num_joints(&self) -> usize {
        self.parents.len()
    }
}

/// Which skeleton a motion uses.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum SkeletonKind {
    /// SMPL's 24 joints (AIST++, EDGE, MoFusion).
    Smpl24,
    /// HumanML3D's 22 joints (MCM-LDM, MLD).
    T2m22,
    /// Any other hierarchy, e.g. from a BVH file.
    Custom {
        /// Name stored in the motion file's `skeleton` attribute.
        name: String,
        /// One name per joint.
        joint_names: Vec<String>,
        /// Parent index per joint, -1 for roots.
        parents: Vec<i32>,
    },
}

impl SkeletonKind {
    /// The name in the motion file (`"smpl24"`, `"t2m22"`, or the custom name).
    pub fn name(&self) -> &str {
        match self {
            SkeletonKind::Smpl24 => "smpl24",
            SkeletonKind::T2m22 => "t2m22",
            SkeletonKind::Custom { name, .. } => name,
        }
    }

    /// Joint count.
    pub fn num_joints(&self) -> usize {
        self.parents().len()
    }

    /// Check that names and parents agree (1..=[`MAX_JOINTS`] joints) and every parent
    /// precedes its child.
    pub fn validate(&self) -> std::result::Result<(), String> {
        let parents = self.parents();
        let names = self.joint_names().len();
        if names != parents.len() || parents.is_empty() || parents.len() > MAX_JOINTS {
            return Err(format!(
                "skeleton {} has {names} joint names and {} parents (must match, 1..={MAX_JOINTS})",
                choreo_dsp::quote(self.name()),
                parents.len()
            ));
        }
        for (c, p) in parents.iter().enumerate() {
            if *p >= c as i32 || *p < -1 {
                return Err(format!(
                    "skeleton {}: joint {c} has parent {p} (parents must precede children)",
                    choreo_dsp::quote(self.name())
                ));
            }
        }
        Ok(())
    }

    /// The constants of a built-in skeleton (`None` for custom ones).
    pub fn skeleton(&self) -> Option<&'static Skeleton> {
        match self {
            SkeletonKind::Smpl24 => Some(&Skeleton::SMPL24),
            SkeletonKind::T2m22 => Some(&Skeleton::T2M22),
            SkeletonKind::Custom { .. } => None,
        }
    }

    /// Joint names.
    pub fn joint_names(&self) -> Vec<String> {
        match self {
            SkeletonKind::Smpl24 => SMPL24_JOINT_NAMES.iter().map(|s| (*s).to_owned()).collect(),
            SkeletonKind::T2m22 => T2M22_JOINT_NAMES.iter().map(|s| (*s).to_owned()).collect(),
            SkeletonKind::Custom { joint_names, .. } => joint_names.clone(),
        }
    }

    /// Parent per joint (-1 for a root).
    pub fn parents(&self) -> &[i32] {
        match self {
            SkeletonKind::Smpl24 => &SMPL24_PARENTS,
            SkeletonKind::T2m22 => &T2M22_PARENTS,
            SkeletonKind::Custom { parents, .. } => parents,
        }
    }

    /// Indices of the foot joints used for contact marks (ankles and toes), if known.
    pub fn foot_joints(&self) -> Vec<usize> {
        match self {
            // ankles 7, 8 and toes 10, 11 (EDGE vis.py `feet = poses[:, (7, 8, 10, 11)]`).
            SkeletonKind::Smpl24 | SkeletonKind::T2m22 => vec![7, 8, 10, 11],
            SkeletonKind::Custom { joint_names, .. } => joint_names
                .iter()
                .enumerate()
                .filter(|(_, n)| {
                    let n = n.to_ascii_lowercase();
                    n.contains("foot") || n.contains("toe") || n.contains("ankle")
                })
                .map(|(i, _)| i)
                .collect(),
        }
    }

    /// Whether joint `j` is on the left side (for colouring), by name.
    pub fn is_left(&self, j: usize) -> bool {
        match self {
            SkeletonKind::Smpl24 | SkeletonKind::T2m22 => SMPL_LEFT.contains(&j),
            SkeletonKind::Custom { joint_names, .. } => {
                joint_names.get(j).is_some_and(|n| side_prefix(n, "left"))
            }
        }
    }

    /// Whether joint `j` is on the right side (for colouring), by name.
    pub fn is_right(&self, j: usize) -> bool {
        match self {
            SkeletonKind::Smpl24 | SkeletonKind::T2m22 => SMPL_RIGHT.contains(&j),
            SkeletonKind::Custom { joint_names, .. } => {
                joint_names.get(j).is_some_and(|n| side_prefix(n, "right"))
            }
        }
    }

    /// The kind for a stored name and hierarchy: the built-in skeletons when name, names and
    /// parents match, else a custom one.
    pub fn from_parts(name: &str, joint_names: Vec<String>, parents: Vec<i32>) -> Self {
        for builtin in [SkeletonKind::Smpl24, SkeletonKind::T2m22] {
            if builtin.name() == name && builtin.parents() == parents.as_slice() {
                return builtin;
            }
        }
        SkeletonKind::Custom {
            name: name.to_owned(),
            joint_names,
            parents,
        }
    }

    /// Left/right joint pairs for mirroring (empty for custom skeletons).
    pub fn mirror_pairs(&self) -> Vec<(usize, usize)> {
        let n = self.num_joints();
        match self {
            SkeletonKind::Smpl24 | SkeletonKind::T2m22 => SMPL_LEFT
                .iter()
                .zip(SMPL_RIGHT.iter())
                .filter(|(l, r)| **l < n && **r < n)
                .map(|(l, r)| (*l, *r))
                .collect(),
            SkeletonKind::Custom { .. } => Vec::new(),
        }
    }
}

/// Whether a joint name marks a side: "LeftArm", "left_knee", "LHipJoint", "l_hip" (but not
/// "LowerBack").
fn side_prefix(name: &str, side: &str) -> bool {
    // A namespace before the bone's own name (Mixamo's `mixamorig:LeftArm`, Blender's
    // `Armature|LeftArm`) says nothing about the side.
    let name = name.rsplit([':', '|']).next().unwrap_or(name);
    let lower = name.to_ascii_lowercase();
    if lower.starts_with(side) {
        return true;
    }
    let mut chars = name.chars();
    let first = chars.next().map(|c| c.to_ascii_lowercase());
    let second = chars.next();
    first == side.chars().next()
        && second.is_some_and(|c| c.is_ascii_uppercase() || c == '_' || c == '.')
}

/// Bone lengths of HumanML3D's target skeleton, metres, each joint to its parent (0 for the
/// root). `motion_representation.ipynb` retargets every motion to the first frame of example
/// `000021` (`tgt_offsets = tgt_skel.get_offsets_joints(example_data[0])`); that file is not
/// distributed, but the lengths are a dataset constant, identical in every released processed
/// file (issue 12 item 18 lists them as measured; not symmetrised).
pub const T2M22_TARGET_BONE_LENGTHS: [f32; 22] = [
    0.0, 0.103074, 0.109883, 0.131568, 0.393623, 0.390188, 0.143190, 0.432433, 0.425643, 0.057365,
    0.143382, 0.149419, 0.219360, 0.137487, 0.143383, 0.103039, 0.131614, 0.122984, 0.256840,
    0.263092, 0.266012, 0.269876,
];

/// The default HumanML3D target skeleton, as the notebook builds it (`get_offsets_joints`): the
/// t2m raw directions scaled by [`T2M22_TARGET_BONE_LENGTHS`]. Pass your own offsets to
/// [`crate::FeatureOptions`] to use another target.
pub fn t2m_default_target_offsets() -> [Vec3; 22] {
    std::array::from_fn(|j| T2M22_RAW_OFFSETS[j].map(|d| d * T2M22_TARGET_BONE_LENGTHS[j]))
}

/// The largest angle (degrees) any bone — joint minus parent, `parents[j] < 0` for the root —
/// turns between two consecutive frames of `joints` (frames, joints, 3): how abruptly a motion
/// moves a limb (issue 24's bar: 60° at 30 fps). atan2 of |cross| and dot, exact near 0° and
/// 180° alike; 0 for fewer than two frames.
pub fn largest_bone_turn_deg(joints: ndarray::ArrayView3<'_, f32>, parents: &[i32]) -> f64 {
    let bone = |f: usize, j: usize, p: usize| -> Vec3 {
        [0, 1, 2].map(|c| joints[[f, j, c]] - joints[[f, p, c]])
    };
    let mut worst = 0f64;
    for f in 1..joints.dim().0 {
        for (j, &p) in parents.iter().enumerate() {
            let Ok(p) = usize::try_from(p) else { continue };
            let (u, v) = (
                bone(f - 1, j, p).map(f64::from),
                bone(f, j, p).map(f64::from),
            );
            let cross = [
                u[1] * v[2] - u[2] * v[1],
                u[2] * v[0] - u[0] * v[2],
                u[0] * v[1] - u[1] * v[0],
            ];
            let sin = (cross[0].powi(2) + cross[1].powi(2) + cross[2].powi(2)).sqrt();
            let cos = u[0] * v[0] + u[1] * v[1] + u[2] * v[2];
            worst = worst.max(sin.atan2(cos).to_degrees());
        }
    }
    worst
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rotation::norm;

    #[test]
    fn the_largest_bone_turn_is_the_angle_between_a_bone_in_two_frames() {
        // Two joints, the bone along +x, then +y (90°), then 190° from +x (100° from +y).
        let frames = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-0.985, -0.174, 0.0]];
        let joints = ndarray::Array3::from_shape_fn((3, 2, 3), |(f, j, c)| {
            if j == 0 { 5.0 } else { 5.0 + frames[f][c] }
        });
        let turn = largest_bone_turn_deg(joints.view(), &[-1, 0]);
        assert!((turn - 100.0).abs() < 0.1, "{turn}");
        assert_eq!(
            largest_bone_turn_deg(joints.slice(ndarray::s![..1, .., ..]), &[-1, 0]),
            0.0
        );
    }

    #[test]
    fn parents_come_before_children() {
        for parents in [&SMPL24_PARENTS[..], &T2M22_PARENTS[..]] {
            for (j, p) in parents.iter().enumerate() {
                assert!(*p < j as i32, "joint {j} parent {p}");
            }
        }
    }

    #[test]
    fn t2m_parents_match_chains_and_smpl() {
        for chain in T2M22_KINEMATIC_CHAIN {
            for w in chain.windows(2) {
                assert_eq!(T2M22_PARENTS[w[1]], w[0] as i32);
            }
        }
        assert_eq!(&SMPL24_PARENTS[..22], &T2M22_PARENTS[..]);
    }

    #[test]
    fn custom_sides_from_names() {
        let k = SkeletonKind::Custom {
            name: "bvh".into(),
            joint_names: [
                "Hips",
                "LowerBack",
                "LeftArm",
                "RHipJoint",
                "l_wrist",
                "rightFoot",
            ]
            .map(String::from)
            .to_vec(),
            parents: vec![-1, 0, 1, 0, 2, 3],
        };
        let left: Vec<bool> = (0..6).map(|j| k.is_left(j)).collect();
        let right: Vec<bool> = (0..6).map(|j| k.is_right(j)).collect();
        assert_eq!(left, [false, false, true, false, true, false]);
        assert_eq!(right, [false, false, false, true, false, true]);
    }

    #[test]
    fn namespaced_bone_names_keep_their_sides() {
        // Issue 23 item 10: Mixamo's rig was drawn without left/right colours.
        let names = [
            "mixamorig:Hips",
            "mixamorig:LeftArm",
            "mixamorig:RightUpLeg",
            "Armature|LeftHand",
            "mixamorig1:Spine",
        ];
        let k = SkeletonKind::Custom {
            name: "bvh".into(),
            joint_names: names.map(String::from).to_vec(),
            parents: vec![-1, 0, 0, 1, 0],
        };
        let left: Vec<bool> = (0..5).map(|j| k.is_left(j)).collect();
        let right: Vec<bool> = (0..5).map(|j| k.is_right(j)).collect();
        assert_eq!(left, [false, true, false, true, false]);
        assert_eq!(right, [false, false, true, false, false]);
    }

    #[test]
    fn default_target_is_humanml3d_example_000021() {
        let t = t2m_default_target_offsets();
        // Spot values straight from the table, along paramUtil's raw directions.
        assert_eq!(t[4], [0.0, -0.393623, 0.0]); // left knee: down
        assert_eq!(t[2], [-0.109883, 0.0, 0.0]); // right hip: -x
        assert_eq!(t[15], [0.0, 0.0, 0.103039]); // head: +z
        for j in 1..22 {
            assert!((norm(t[j]) - T2M22_TARGET_BONE_LENGTHS[j]).abs() < 1e-7);
        }
    }
}
