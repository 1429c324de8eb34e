//! The one writer of finished motion, picked by the output's extension: `.h5` (the motion
//! file), `.bvh`, `.glb` / `.gltf` and `.npy` (joints). Every verb that writes motion (`dance`,
//! `stylize`, `live`'s take, `convert`) goes through [`OutputFormat::from_path`] before it
//! starts and [`write_motion_as`] at the end, so an extension that names no motion format is
//! refused before any work, with one line that says what to do instead.
//!
//! [`ExportRig`] names the exported skeleton: [`ExportRig::Native`] keeps the motion's own joint
//! names; [`ExportRig::Mixamo`] gives SMPL-24 / t2m-22 joints Mixamo's bone names (`mixamorig:`
//! prefix) and, in glTF, Mixamo's rest-pose conventions (see [`MIXAMO_NAMES`]).

use std::path::Path;

use crate::error::{Error, ExportRefusal, Result};
use crate::formats::motion_file::{MotionFile, write_motion_file};
use crate::rotation::{Mat3, Vec3, cross, dot, norm};
use crate::skeleton::SkeletonKind;

/// A format finished motion can be written in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OutputFormat {
    /// `.h5` / `.hdf5`: the choreod motion file (joints, features, mel, provenance).
    MotionFile,
    /// `.bvh`: a rotation-animated armature.
    Bvh,
    /// `.glb` (binary) or `.gltf` (JSON with the buffer embedded): skinned mannequin + skeleton
    /// + one animation.
    Gltf {
        /// `.glb`.
        binary: bool,
    },
    /// `.npy`: world joints (T, J, 3), float32, no frame rate.
    Npy,
}

/// The extensions [`OutputFormat::from_path`] accepts, for messages and `--help`.
pub const OUTPUT_EXTENSIONS: &str = ".h5, .bvh, .glb, .gltf or .npy";

impl OutputFormat {
    /// The format `path`'s extension names, or one error saying what to write instead.
    pub fn from_path(path: &Path) -> Result<Self> {
        let ext = path
            .extension()
            .map(|e| e.to_string_lossy().to_ascii_lowercase())
            .unwrap_or_default();
        Ok(match ext.as_str() {
            "h5" | "hdf5" => Self::MotionFile,
            "bvh" => Self::Bvh,
            "glb" => Self::Gltf { binary: true },
            "gltf" => Self::Gltf { binary: false },
            "npy" => Self::Npy,
            "gif" | "png" => {
                let h5 = path.with_extension("h5");
                return Err(Error::invalid(
                    path,
                    format!(
                        "a .{ext} is a picture, not motion: write {} (or {OUTPUT_EXTENSIONS}), \
                         then `choreod render {} -o {}`",
                        h5.display(),
                        h5.display(),
                        path.display()
                    ),
                ));
            }
            "" => {
                return Err(Error::invalid(
                    path,
                    format!("no extension: name the format with one of {OUTPUT_EXTENSIONS}"),
                ));
            }
            other => {
                return Err(Error::invalid(
                    path,
                    format!(
                        "'.{other}' is not a motion format choreod writes: use {OUTPUT_EXTENSIONS}"
                    ),
                ));
            }
        })
    }

    /// Whether `--rig` applies (formats with bone names).
    pub fn takes_rig(self) -> bool {
        matches!(self, Self::Bvh | Self::Gltf { .. })
    }
}

/// Bone names (and, in glTF, bone orientations) of an exported skeleton.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum ExportRig {
    /// The motion's own joint names; glTF joints rest unrotated (world axes), as BVH joints do.
    #[default]
    Native,
    /// Mixamo's names with the `mixamorig:` prefix ([`MIXAMO_NAMES`]); glTF joints rest with
    /// their +Y axis along the bone and +Z toward the character's front (Mixamo's T-pose
    /// convention), so a Mixamo character's bones match by name and axis.
    Mixamo,
}

/// Mixamo's bone name for each SMPL-24 joint, in SMPL order (t2m-22 uses the first 22).
/// Mixamo's rig (Adobe's auto-rigger, as its FBX files name bones in Blender) has the same
/// chain from Hips to the hands and toes; SMPL's `hand` joint (the middle of the palm) becomes
/// the middle finger's first bone. Mixamo bones SMPL has no counterpart for (they are absent
/// from the export): `HeadTop_End`, `LeftToe_End` / `RightToe_End`, and every finger bone but
/// `HandMiddle1` (`HandThumb1-4`, `HandIndex1-4`, `HandMiddle2-4`, `HandRing1-4`,
/// `HandPinky1-4`).
pub const MIXAMO_NAMES: [&str; 24] = [
    "Hips",
    "LeftUpLeg",
    "RightUpLeg",
    "Spine",
    "LeftLeg",
    "RightLeg",
    "Spine1",
    "LeftFoot",
    "RightFoot",
    "Spine2",
    "LeftToeBase",
    "RightToeBase",
    "Neck",
    "LeftShoulder",
    "RightShoulder",
    "Head",
    "LeftArm",
    "RightArm",
    "LeftForeArm",
    "RightForeArm",
    "LeftHand",
    "RightHand",
    "LeftHandMiddle1",
    "RightHandMiddle1",
];

/// The namespace Mixamo's FBX files give every bone.
pub const MIXAMO_PREFIX: &str = "mixamorig:";

impl ExportRig {
    /// The exported joint names of `skeleton`, or why this rig cannot name it.
    pub fn joint_names(self, path: &Path, skeleton: &SkeletonKind) -> Result<Vec<String>> {
        match self {
            ExportRig::Native => Ok(skeleton.joint_names()),
            ExportRig::Mixamo => match skeleton {
                SkeletonKind::Smpl24 | SkeletonKind::T2m22 => Ok(MIXAMO_NAMES
                    [..skeleton.num_joints()]
                    .iter()
                    .map(|n| format!("{MIXAMO_PREFIX}{n}"))
                    .collect()),
                SkeletonKind::Custom { name, .. } => Err(Error::Export {
                    path: path.to_path_buf(),
                    option: ExportRefusal::MixamoNames {
                        skeleton: name.clone(),
                    },
                }),
            },
        }
    }

    /// World orientation of each joint's frame in the rest pose (columns: the joint's x, y, z
    /// axes), given rest positions `rest` and the hierarchy. Native: the world axes. Mixamo: +Y
    /// along the bone to the joint's main child ([`main_child`]), a leaf keeping its parent's;
    /// +Z as near the body's front (+Z) as that allows, or up (+Y) for a bone pointing front or
    /// back.
    pub fn rest_frames(self, parents: &[i32], rest: &[Vec3]) -> Vec<Mat3> {
        let identity = crate::rotation::MAT3_IDENTITY;
        match self {
            ExportRig::Native => vec![identity; parents.len()],
            ExportRig::Mixamo => {
                let children = crate::kinematics::rigid::children_of(parents);
                let mut frames = vec![identity; parents.len()];
                for k in 0..parents.len() {
                    let bone = main_child(&children[k], rest, k)
                        .map(|c| crate::rotation::sub(rest[c], rest[k]));
                    frames[k] = match bone {
                        Some(b) if norm(b) > 1e-6 => bone_frame(b),
                        // Parents come before children in every skeleton choreod writes.
                        _ if parents[k] >= 0 => frames[parents[k] as usize],
                        _ => identity,
                    };
                }
                frames
            }
        }
    }
}

/// The child a joint's bone points to: of several, the one most nearly straight above the joint
/// (hips → spine, chest → neck, as in Mixamo's rig); else the only child.
fn main_child(children: &[usize], rest: &[Vec3], k: usize) -> Option<usize> {
    children.iter().copied().max_by(|&a, &b| {
        let up = |c: usize| {
            let d = crate::rotation::sub(rest[c], rest[k]);
            d[1] / norm(d).max(1e-9)
        };
        up(a).total_cmp(&up(b))
    })
}

/// Rotation (columns x, y, z) whose y is along `bone` and whose z is the body's front (+Z)
/// made perpendicular to it, or up (+Y) when the bone points front or back.
fn bone_frame(bone: Vec3) -> Mat3 {
    let n = norm(bone);
    let y = [bone[0] / n, bone[1] / n, bone[2] / n];
    let pick = if y[2].abs() > 0.9 {
        [0.0, 1.0, 0.0]
    } else {
        [0.0, 0.0, 1.0]
    };
    let d = dot(pick, y);
    let z = [pick[0] - d * y[0], pick[1] - d * y[1], pick[2] - d * y[2]];
    let zn = norm(z);
    let z = [z[0] / zn, z[1] / zn, z[2] / zn];
    let x = cross(y, z);
    [[x[0], y[0], z[0]], [x[1], y[1], z[1]], [x[2], y[2], z[2]]]
}

/// How [`write_motion_as`] writes formats that have choices.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ExportOptions {
    /// Bone names (BVH, glTF).
    pub rig: ExportRig,
    /// glTF: leave out the mannequin mesh (a plain animated skeleton).
    pub no_mesh: bool,
}

/// Write `m` to `path` in the format its extension names ([`OutputFormat::from_path`]),
/// atomically. BVH and glTF carry the rigid fit of the joints
/// ([`crate::fit_rigid_pose`]); `.npy` the joints alone.
pub fn write_motion_as(path: &Path, m: &MotionFile, opts: &ExportOptions) -> Result<()> {
    match check_output(path, opts)? {
        OutputFormat::MotionFile => write_motion_file(path, m),
        OutputFormat::Bvh => {
            let names = opts.rig.joint_names(path, &m.skeleton)?;
            crate::formats::bvh::write_bvh_named(path, m, &names)
        }
        OutputFormat::Gltf { binary } => crate::render::gltf::write_gltf(path, m, opts, binary),
        OutputFormat::Npy => crate::formats::npy::write_npy(path, m.joints.view().into_dyn()),
    }
}

/// The format [`write_motion_as`] will write `path` in, or why it cannot (an extension that
/// names no motion format, or an option the format has no use for). Verbs call this before
/// they start, so a wrong name costs nothing.
pub fn check_output(path: &Path, opts: &ExportOptions) -> Result<OutputFormat> {
    let format = OutputFormat::from_path(path)?;
    if opts.rig != ExportRig::Native && !format.takes_rig() {
        return Err(Error::Export {
            path: path.to_path_buf(),
            option: ExportRefusal::RigWithoutBones,
        });
    }
    if opts.no_mesh && !matches!(format, OutputFormat::Gltf { .. }) {
        return Err(Error::Export {
            path: path.to_path_buf(),
            option: ExportRefusal::NoMeshWithoutMesh,
        });
    }
    Ok(format)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn extensions_pick_formats_and_pictures_are_refused_with_the_way_to_make_one() {
        let f = |p: &str| OutputFormat::from_path(Path::new(p));
        assert_eq!(f("a.H5").unwrap(), OutputFormat::MotionFile);
        assert_eq!(f("a.bvh").unwrap(), OutputFormat::Bvh);
        assert_eq!(f("a.glb").unwrap(), OutputFormat::Gltf { binary: true });
        assert_eq!(f("a.gltf").unwrap(), OutputFormat::Gltf { binary: false });
        assert_eq!(f("a.npy").unwrap(), OutputFormat::Npy);
        let gif = f("d/dance.gif").unwrap_err().to_string();
        assert!(
            gif.contains("choreod render d/dance.h5 -o d/dance.gif"),
            "{gif}"
        );
        assert!(f("dance.fbx").unwrap_err().to_string().contains(".glb"));
        assert!(f("dance").is_err());
    }

    #[test]
    fn mixamo_frames_point_y_along_each_bone_and_z_forward() {
        let parents = SkeletonKind::Smpl24.parents();
        let rest = crate::render::gltf::rest_positions(
            parents,
            &crate::skeleton::SMPL24_OFFSETS,
            [0.0; 3],
        );
        let frames = ExportRig::Mixamo.rest_frames(parents, &rest);
        let col = |m: &Mat3, c: usize| [m[0][c], m[1][c], m[2][c]];
        // Hips point up the spine (belly), not down a leg; the left forearm along +x.
        let to = |a: usize, b: usize| {
            let d = crate::rotation::sub(rest[b], rest[a]);
            let n = norm(d);
            [d[0] / n, d[1] / n, d[2] / n]
        };
        assert!(dot(col(&frames[0], 1), to(0, 3)) > 0.9999);
        assert!(dot(col(&frames[18], 1), to(18, 20)) > 0.9999);
        assert!(col(&frames[18], 1)[0] > 0.9, "left forearm points +x");
        // Legs point down with z still forward.
        assert!(col(&frames[4], 1)[1] < -0.99 && col(&frames[4], 2)[2] > 0.99);
        for m in &frames {
            let (x, y, z) = (col(m, 0), col(m, 1), col(m, 2));
            assert!((norm(x) - 1.0).abs() < 1e-5 && dot(x, y).abs() < 1e-5);
            // Right-handed.
            assert!(dot(cross(x, y), z) > 0.9999);
        }
    }
}
