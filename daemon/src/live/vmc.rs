//! VMC protocol output: OSC over UDP, one bundle per motion frame, as a VMC "Performer" sends
//! to a "Marionette" (VSeeFace, Warudo, EVMC4U; default port 39539). Messages (VMC protocol
//! specification, sh-akira/VirtualMotionCaptureProtocol:docs/english.markdown, "Marionette"):
//!
//! - `/VMC/Ext/OK (int){loaded}` — 1: a model is loaded.
//! - `/VMC/Ext/T (float){time}` — the sender's relative time.
//! - `/VMC/Ext/Root/Pos (string){"root"} p.xyz q.xyzw` — the model root.
//! - `/VMC/Ext/Bone/Pos (string){name} p.xyz q.xyzw` — name is a Unity `HumanBodyBones` name;
//!   p and q are the bone's local position and rotation.
//!
//! Rotations are each bone's rotation relative to its parent, relative to the SMPL rest pose
//! (close to the humanoid T-pose): the local rotations of the session's rigid fit
//! ([`choreo_datasets::RigidPose`], the same rotations a BVH export carries), and the bone
//! positions are its fixed offsets; each quaternion takes the sign nearer the previous frame's,
//! so a receiver interpolating them never turns the long way round. Unity is left-handed (x right, y up, z forward); choreod's frame is
//! right-handed with the body facing +z, so vectors map as (x, y, z) → (-x, y, z) and
//! quaternions (x, y, z, w) → (x, -y, -z, w) (a reflection of the x axis).
//!
//! OSC 1.0 encoding (opensoundcontrol.org spec 1.0): strings NUL-terminated and padded to 4
//! bytes, big-endian int32/float32, bundles `#bundle` + time tag + size-prefixed elements.

use choreo_datasets::RigidPose;
use choreo_datasets::rotation::{Quat, Vec3, mat_to_quat};
use choreo_datasets::skeleton::SMPL24_PARENTS;

/// SMPL-24 joint → Unity `HumanBodyBones` name (SMPL order; the two hand tips have none).
pub const SMPL24_TO_HUMAN_BONES: [Option<&str>; 24] = [
    Some("Hips"),
    Some("LeftUpperLeg"),
    Some("RightUpperLeg"),
    Some("Spine"),
    Some("LeftLowerLeg"),
    Some("RightLowerLeg"),
    Some("Chest"),
    Some("LeftFoot"),
    Some("RightFoot"),
    Some("UpperChest"),
    Some("LeftToes"),
    Some("RightToes"),
    Some("Neck"),
    Some("LeftShoulder"),
    Some("RightShoulder"),
    Some("Head"),
    Some("LeftUpperArm"),
    Some("RightUpperArm"),
    Some("LeftLowerArm"),
    Some("RightLowerArm"),
    Some("LeftHand"),
    Some("RightHand"),
    None,
    None,
];

/// Turns frames of a rigid SMPL-24 pose into VMC bundles, keeping the previous quaternions for
/// sign continuity.
#[derive(Debug)]
pub struct VmcEncoder {
    previous: Vec<Option<Quat>>,
}

impl Default for VmcEncoder {
    fn default() -> Self {
        Self::new()
    }
}

impl VmcEncoder {
    pub fn new() -> Self {
        Self {
            previous: vec![None; 24],
        }
    }

    /// Local rotations (w, x, y, z, choreod's axes) of `frame` of a 24-joint `pose`,
    /// sign-continuous with the previous call.
    pub fn rotations(&mut self, pose: &RigidPose, frame: usize) -> Vec<Quat> {
        let mut out = Vec::with_capacity(24);
        for k in 0..24 {
            let mut q = mat_to_quat(&pose.local_rotation(&SMPL24_PARENTS, frame, k));
            if let Some(p) = self.previous[k]
                && q.iter().zip(p.iter()).map(|(a, b)| a * b).sum::<f32>() < 0.0
            {
                q = q.map(|c| -c);
            }
            self.previous[k] = Some(q);
            out.push(q);
        }
        out
    }

    /// One OSC bundle with the VMC messages of `frame` of `pose` at `time` seconds.
    pub fn bundle(&mut self, pose: &RigidPose, frame: usize, time: f32) -> Vec<u8> {
        let rotations = self.rotations(pose, frame);
        let j = &pose.joints;
        let root = [j[[frame, 0, 0]], j[[frame, 0, 1]], j[[frame, 0, 2]]];
        let mut messages = Vec::with_capacity(26);
        messages.push(message("/VMC/Ext/OK", &[Arg::Int(1)]));
        messages.push(message("/VMC/Ext/T", &[Arg::Float(time)]));
        // The root sits on the floor under the hips; the hips carry the height.
        messages.push(message(
            "/VMC/Ext/Root/Pos",
            &pose_args("root", [-root[0], 0.0, root[2]], [0.0, 0.0, 0.0, 1.0]),
        ));
        for (k, name) in SMPL24_TO_HUMAN_BONES.iter().enumerate() {
            let Some(name) = name else { continue };
            let pos = if k == 0 {
                [0.0, root[1], 0.0]
            } else {
                let o = pose.offsets[k];
                [-o[0], o[1], o[2]]
            };
            let [w, x, y, z] = rotations[k];
            messages.push(message(
                "/VMC/Ext/Bone/Pos",
                &pose_args(name, pos, [x, -y, -z, w]),
            ));
        }
        bundle(&messages)
    }
}

/// An OSC argument.
#[derive(Debug, Clone, Copy)]
enum Arg<'a> {
    Int(i32),
    Float(f32),
    Str(&'a str),
}

fn pose_args(name: &str, p: Vec3, q: [f32; 4]) -> Vec<Arg<'_>> {
    let mut a = vec![Arg::Str(name)];
    a.extend(p.iter().chain(q.iter()).map(|v| Arg::Float(*v)));
    a
}

fn push_padded_str(out: &mut Vec<u8>, s: &str) {
    out.extend_from_slice(s.as_bytes());
    out.push(0);
    while !out.len().is_multiple_of(4) {
        out.push(0);
    }
}

/// One OSC message.
fn message(address: &str, args: &[Arg<'_>]) -> Vec<u8> {
    let mut out = Vec::with_capacity(64);
    push_padded_str(&mut out, address);
    let tags: String = std::iter::once(',')
        .chain(args.iter().map(|a| match a {
            Arg::Int(_) => 'i',
            Arg::Float(_) => 'f',
            Arg::Str(_) => 's',
        }))
        .collect();
    push_padded_str(&mut out, &tags);
    for a in args {
        match a {
            Arg::Int(v) => out.extend_from_slice(&v.to_be_bytes()),
            Arg::Float(v) => out.extend_from_slice(&v.to_be_bytes()),
            Arg::Str(s) => push_padded_str(&mut out, s),
        }
    }
    out
}

/// An OSC bundle with time tag 1 ("immediately").
fn bundle(messages: &[Vec<u8>]) -> Vec<u8> {
    let mut out = Vec::with_capacity(16 + messages.iter().map(|m| m.len() + 4).sum::<usize>());
    push_padded_str(&mut out, "#bundle");
    out.extend_from_slice(&1u64.to_be_bytes());
    for m in messages {
        out.extend_from_slice(&(m.len() as i32).to_be_bytes());
        out.extend_from_slice(m);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use choreo_datasets::rotation::{qrot, quat_to_mat};
    use choreo_datasets::skeleton::SMPL24_OFFSETS;
    use choreo_datasets::{RigidFitter, SkeletonKind};
    use ndarray::Array3;

    fn rest_pose() -> Vec<Vec3> {
        let mut p = vec![[0.0, 0.9, 0.0]; 24];
        for k in 1..24 {
            let parent = SMPL24_PARENTS[k] as usize;
            let o = SMPL24_OFFSETS[k];
            p[k] = [
                p[parent][0] + o[0],
                p[parent][1] + o[1],
                p[parent][2] + o[2],
            ];
        }
        p
    }

    fn frame(p: &[Vec3]) -> Array3<f32> {
        Array3::from_shape_fn((1, 24, 3), |(_, k, c)| p[k][c])
    }

    /// A fitter whose rest offsets are SMPL's (fitted to the rest pose itself).
    fn fitter() -> RigidFitter {
        RigidFitter::from_motion(&SkeletonKind::Smpl24, frame(&rest_pose()).view()).unwrap()
    }

    /// The rigid pose of one frame.
    fn fit(fitter: &mut RigidFitter, p: &[Vec3]) -> RigidPose {
        fitter.fit(frame(p).view()).unwrap()
    }

    #[test]
    fn osc_message_bytes_follow_the_spec() {
        // Worked example of OSC 1.0: "/oscillator/4/frequency" ,f 440.0.
        let m = message("/oscillator/4/frequency", &[Arg::Float(440.0)]);
        let mut want = b"/oscillator/4/frequency\0,f\0\0".to_vec();
        want.extend_from_slice(&[0x43, 0xdc, 0x00, 0x00]);
        assert_eq!(m, want);
        // A string whose length is a multiple of 4 still gets its NUL (and 3 more bytes).
        assert_eq!(message("/abc", &[]), b"/abc\0\0\0\0,\0\0\0".to_vec());
        let b = bundle(std::slice::from_ref(&m));
        assert_eq!(&b[..8], b"#bundle\0");
        assert_eq!(&b[8..16], &[0, 0, 0, 0, 0, 0, 0, 1]);
        assert_eq!(&b[16..20], &(m.len() as i32).to_be_bytes());
    }

    #[test]
    fn rest_pose_gives_identity_rotations() {
        let mut e = VmcEncoder::new();
        let mut f = fitter();
        for (k, o) in f.offsets().iter().enumerate() {
            let d = (0..3)
                .map(|c| (o[c] - SMPL24_OFFSETS[k][c]).abs())
                .fold(0.0, f32::max);
            assert!(d < 1e-6, "joint {k}: {o:?}");
        }
        for q in e.rotations(&fit(&mut f, &rest_pose()), 0) {
            assert!((q[0].abs() - 1.0).abs() < 1e-5, "{q:?}");
        }
    }

    #[test]
    fn a_turned_forearm_rotates_the_elbow_only_and_stays_continuous() {
        let mut e = VmcEncoder::new();
        let mut f = fitter();
        let rest = rest_pose();
        // Swing the left forearm (elbow 18 → wrist 20, hand 22) by a growing angle about y, up
        // to 166°: a swing is undefined when the bone points exactly opposite its rest
        // direction, so continuity is only promised away from that.
        let mut previous: Option<Quat> = None;
        for step in 0..30 {
            let angle = step as f32 * 0.1;
            let q: Quat = [(angle / 2.0).cos(), 0.0, (angle / 2.0).sin(), 0.0];
            let mut p = rest.clone();
            for k in [20usize, 22] {
                let d = [
                    rest[k][0] - rest[18][0],
                    rest[k][1] - rest[18][1],
                    rest[k][2] - rest[18][2],
                ];
                let r = qrot(q, d);
                p[k] = [rest[18][0] + r[0], rest[18][1] + r[1], rest[18][2] + r[2]];
            }
            let rots = e.rotations(&fit(&mut f, &p), 0);
            // Elbow: its local rotation turns the rest forearm onto the measured one.
            let m = quat_to_mat(rots[18]);
            let o = SMPL24_OFFSETS[20];
            let got = choreo_datasets::rotation::mat_vec(&m, o);
            let want = [
                p[20][0] - p[18][0],
                p[20][1] - p[18][1],
                p[20][2] - p[18][2],
            ];
            for c in 0..3 {
                assert!(
                    (got[c] - want[c]).abs() < 1e-4,
                    "step {step}: {got:?} vs {want:?}"
                );
            }
            // Other bones keep the rest pose.
            assert!((rots[16][0].abs() - 1.0).abs() < 1e-5);
            // Continuity: consecutive quaternions are on the same side.
            if let Some(prev) = previous {
                let d: f32 = prev.iter().zip(rots[18].iter()).map(|(a, b)| a * b).sum();
                assert!(d > 0.9, "step {step}: jump {d}");
            }
            previous = Some(rots[18]);
        }
    }

    #[test]
    fn a_full_spin_turns_the_hips_only_and_stays_continuous() {
        // A dancer turning round 1.1 times about the vertical: the hips' rotation passes 180°,
        // where the unsigned quaternion of a matrix flips sign.
        let mut e = VmcEncoder::new();
        let mut f = fitter();
        let rest = rest_pose();
        let mut previous: Option<Quat> = None;
        for step in 0..70 {
            let angle = step as f32 * 0.1;
            let q: Quat = [(angle / 2.0).cos(), 0.0, (angle / 2.0).sin(), 0.0];
            let p: Vec<Vec3> = rest
                .iter()
                .map(|j| {
                    let r = qrot(q, [j[0], j[1] - 0.9, j[2]]);
                    [r[0], r[1] + 0.9, r[2]]
                })
                .collect();
            let rots = e.rotations(&fit(&mut f, &p), 0);
            // The whole body turns with the hips: every other bone keeps its rest rotation
            // relative to its parent.
            for (k, q) in rots.iter().enumerate().skip(1) {
                assert!(
                    (q[0].abs() - 1.0).abs() < 1e-4,
                    "step {step}, joint {k}: {q:?}"
                );
            }
            let hips = rots[0];
            if let Some(prev) = previous {
                let d: f32 = prev.iter().zip(hips.iter()).map(|(a, b)| a * b).sum();
                assert!(d > 0.99, "step {step}: jump {d}");
            }
            previous = Some(hips);
        }
    }

    #[test]
    fn a_bundle_holds_the_vmc_messages_of_a_frame() {
        let mut e = VmcEncoder::new();
        let b = e.bundle(&fit(&mut fitter(), &rest_pose()), 0, 1.5);
        let text = String::from_utf8_lossy(&b);
        assert_eq!(text.matches("/VMC/Ext/Bone/Pos").count(), 22);
        for name in [
            "Hips",
            "Spine",
            "Chest",
            "UpperChest",
            "Neck",
            "Head",
            "LeftUpperLeg",
            "RightHand",
        ] {
            assert!(text.contains(name), "{name}");
        }
        assert!(text.contains("/VMC/Ext/Root/Pos") && text.contains("/VMC/Ext/OK"));
        assert_eq!(b.len() % 4, 0);
    }
}
