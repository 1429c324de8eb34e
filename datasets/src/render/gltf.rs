//! glTF 2.0 output (`.glb`, or `.gltf` with its buffer embedded as a data URI): the motion as a
//! skeleton of nodes named like its joints, the [`mannequin`](crate::render::mannequin) skinned to it
//! (unless `no_mesh`), and one animation: every joint's rotation and each root's translation at
//! the motion's frame times (`frame / fps` seconds), linearly interpolated.
//!
//! The pose is the rigid fit of the joints ([`fit_rigid_pose`], as for BVH): rest offsets of
//! median bone lengths, so a rigid motion (SMPL forward kinematics, a BVH) comes back to within
//! float precision and generated motion as its nearest rigid pose. glTF is y-up, metres, facing
//! +z: the motion file's own frame, so no axis change is made.
//!
//! The JSON is built with `gltf-json` (the types of the glTF 2.0 schema), not by hand.

use std::collections::BTreeMap;
use std::path::Path;

use gltf_json as json;
use json::validation::Checked::Valid;
use json::validation::USize64;

use crate::error::{Error, Result};
use crate::export::ExportOptions;
use crate::formats::motion_file::{MotionFile, write_atomic_bytes};
use crate::kinematics::rigid::fit_rigid_pose;
use crate::render::mannequin::{Side, mannequin};
use crate::rotation::{Mat3, Quat, Vec3, add, mat_mul, mat_to_quat, mat_transpose, mat_vec};
use crate::skeleton::{SMPL24_OFFSETS, SkeletonKind, t2m_default_target_offsets};
use ndarray::Array3;

/// Rest position of every joint: each root at `root`, each child at its parent's plus its
/// offset (parents listed before children).
pub(crate) fn rest_positions(parents: &[i32], offsets: &[Vec3], root: Vec3) -> Vec<Vec3> {
    let mut rest = vec![root; parents.len()];
    for (k, &p) in parents.iter().enumerate() {
        if p >= 0 {
            rest[k] = add(rest[p as usize], offsets[k]);
        }
    }
    rest
}

/// Base colours (linear RGBA) of the left, right and centre parts: blue, red and light grey,
/// as the viewer and `choreod render` colour the sides.
const COLOURS: [[f32; 4]; 3] = [
    [0.11, 0.21, 0.42, 1.0],
    [0.52, 0.12, 0.14, 1.0],
    [0.78, 0.80, 0.83, 1.0],
];

/// Write `m` as glTF to `path` (binary `.glb` when `binary`), atomically.
pub fn write_gltf(path: &Path, m: &MotionFile, opts: &ExportOptions, binary: bool) -> Result<()> {
    write_atomic_bytes(path, &document(path, m, opts, binary)?)
}

/// `m` as the bytes of a `.glb` (what the viewer serves).
pub fn gltf_bytes(m: &MotionFile, opts: &ExportOptions) -> Result<Vec<u8>> {
    document(Path::new("motion.glb"), m, opts, true).map_err(|e| match e {
        Error::Invalid { reason, .. } => Error::motion(reason),
        other => other,
    })
}

/// The mannequin of a built-in skeleton in its rest pose, with the skeleton's table offsets
/// (SMPL-24: EDGE's T-pose; t2m-22: HumanML3D's default target body) and a one-frame
/// animation: what the live viewer loads and then poses from the rotations it receives.
pub fn rest_mannequin_glb(skeleton: &SkeletonKind) -> Result<Vec<u8>> {
    let offsets: Vec<Vec3> = match skeleton {
        SkeletonKind::Smpl24 => SMPL24_OFFSETS.to_vec(),
        SkeletonKind::T2m22 => t2m_default_target_offsets().to_vec(),
        SkeletonKind::Custom { name, .. } => {
            return Err(Error::motion(format!(
                "skeleton {} has no rest pose table for a mannequin",
                choreo_dsp::quote(name)
            )));
        }
    };
    let rest = rest_positions(skeleton.parents(), &offsets, [0.0; 3]);
    let joints = Array3::from_shape_fn((1, rest.len(), 3), |(_, k, c)| rest[k][c]);
    // One frame: the frame rate only names the single key's time (0 s).
    let m = MotionFile::from_joints(30.0, skeleton.clone(), joints);
    gltf_bytes(&m, &ExportOptions::default())
}

/// What a player needs to know about a glTF file's skeleton: its joints (the first skin's, or
/// else every node the first animation turns, in node order), their parents among themselves,
/// and the animation's key rate and length.
#[derive(Debug, Clone, PartialEq)]
pub struct GltfSkeleton {
    /// Node index of every joint.
    pub nodes: Vec<usize>,
    pub joint_names: Vec<String>,
    /// Parent of every joint as an index into `nodes`, -1 for roots.
    pub parents: Vec<i32>,
    /// Keys per second of the first animation (its first sampler's input: count − 1 over the
    /// span between its min and max).
    pub fps: f64,
    /// Keys of that sampler.
    pub frames: usize,
}

/// Read the skeleton of a `.glb` or `.gltf` file's bytes (JSON only; the binary buffer is not
/// read). A `.gltf` whose buffers or images are other files is refused: a player is given one
/// file and reads nothing beside it.
pub fn read_gltf_skeleton(path: &Path, bytes: &[u8]) -> Result<GltfSkeleton> {
    let bad = |reason: String| Error::invalid(path, reason);
    let text = if bytes.starts_with(b"glTF") {
        glb_json_chunk(bytes).map_err(|r| bad(format!("not a GLB file: {r}")))?
    } else {
        bytes
    };
    let root = json::Root::from_slice(text).map_err(|e| bad(format!("not glTF 2.0 JSON: {e}")))?;
    let uris = root
        .buffers
        .iter()
        .filter_map(|b| b.uri.as_deref())
        .chain(root.images.iter().filter_map(|i| i.uri.as_deref()));
    for uri in uris {
        if !uri.starts_with("data:") {
            return Err(bad(format!(
                "refers to the file {}; give a .glb or a .gltf with its buffers embedded \
                 (`choreod convert -o X.glb` writes one)",
                choreo_dsp::quote(uri)
            )));
        }
    }
    let animation = root
        .animations
        .first()
        .ok_or_else(|| bad("has no animation".into()))?;
    let nodes: Vec<usize> = match root.skins.first() {
        Some(skin) => skin.joints.iter().map(|j| j.value()).collect(),
        None => {
            let mut turned: Vec<usize> = animation
                .channels
                .iter()
                .filter(|c| c.target.path == Valid(json::animation::Property::Rotation))
                .map(|c| c.target.node.value())
                .collect();
            turned.sort_unstable();
            turned.dedup();
            turned
        }
    };
    if nodes.is_empty() || nodes.iter().any(|&n| n >= root.nodes.len()) {
        return Err(bad(
            "has no skeleton (no skin joints or turned nodes)".into()
        ));
    }
    let mut parents = vec![-1i32; nodes.len()];
    for (k, &n) in nodes.iter().enumerate() {
        for child in root.nodes[n].children.iter().flatten() {
            if let Some(c) = nodes.iter().position(|&m| m == child.value()) {
                parents[c] = k as i32;
            }
        }
    }
    let joint_names = nodes
        .iter()
        .map(|&n| {
            root.nodes[n]
                .name
                .clone()
                .unwrap_or_else(|| format!("node{n}"))
        })
        .collect();
    let input = animation
        .samplers
        .first()
        .and_then(|s| root.accessors.get(s.input.value()))
        .ok_or_else(|| bad("has an animation without keys".into()))?;
    let frames = input.count.0 as usize;
    let bound = |v: &Option<json::Value>| {
        v.as_ref()
            .and_then(|v| v.get(0))
            .and_then(json::Value::as_f64)
    };
    let span = match (bound(&input.min), bound(&input.max)) {
        (Some(lo), Some(hi)) => hi - lo,
        _ => {
            return Err(bad(
                "an animation input has no min/max (glTF requires them)".into(),
            ));
        }
    };
    // Key times are f32 (relative error 6e-8 each), so the estimate is off by ~1e-5 fps at
    // most: rounded to 1e-4, a file written at 60 fps reads as 60, not 59.99999.
    let fps = if frames > 1 && span > 0.0 {
        ((frames - 1) as f64 / span * 1e4).round() / 1e4
    } else {
        0.0
    };
    Ok(GltfSkeleton {
        nodes,
        joint_names,
        parents,
        fps,
        frames,
    })
}

/// The JSON chunk of a GLB: header `glTF`, version 2, total length, then a chunk of type JSON.
fn glb_json_chunk(bytes: &[u8]) -> std::result::Result<&[u8], String> {
    let word = |at: usize| -> Option<u32> {
        Some(u32::from_le_bytes(bytes.get(at..at + 4)?.try_into().ok()?))
    };
    let (version, total, len, kind) = match (word(4), word(8), word(12), bytes.get(16..20)) {
        (Some(v), Some(t), Some(l), Some(k)) => (v, t as usize, l as usize, k),
        _ => return Err(format!("{} bytes, shorter than a GLB header", bytes.len())),
    };
    if version != 2 {
        return Err(format!("GLB version {version}, not 2"));
    }
    if total != bytes.len() {
        return Err(format!(
            "header says {total} bytes, the file has {}",
            bytes.len()
        ));
    }
    if kind != b"JSON" {
        return Err("the first chunk is not JSON".into());
    }
    bytes
        .get(20..20 + len)
        .ok_or_else(|| format!("JSON chunk of {len} bytes runs past the end"))
}

/// The glTF document of `m`; errors name `path`.
fn document(path: &Path, m: &MotionFile, opts: &ExportOptions, binary: bool) -> Result<Vec<u8>> {
    let names = opts.rig.joint_names(path, &m.skeleton)?;
    let parents = m.skeleton.parents().to_vec();
    if parents.iter().enumerate().any(|(k, &p)| p >= k as i32) {
        return Err(Error::invalid(
            path,
            "glTF export needs every joint's parent listed before it",
        ));
    }
    let (t, nj) = (m.joints.shape()[0], m.joints.shape()[1]);
    if t == 0 {
        return Err(Error::invalid(path, "the motion has no frames"));
    }
    let rigid = fit_rigid_pose(&m.skeleton, m.joints.view()).map_err(|e| e.with_path(path))?;
    let root_at = |f: usize, k: usize| -> Vec3 {
        [
            m.joints[[f, k, 0]],
            m.joints[[f, k, 1]],
            m.joints[[f, k, 2]],
        ]
    };
    // Rest pose: every root where it starts.
    let mut rest = rest_positions(&parents, &rigid.offsets, [0.0; 3]);
    for k in 0..nj {
        if parents[k] < 0 {
            let at = root_at(0, k);
            let shift = crate::rotation::sub(at, rest[k]);
            for (j, at) in rest.iter_mut().enumerate().skip(k) {
                if descends_from(&parents, j, k) {
                    *at = add(*at, shift);
                }
            }
        }
    }
    let frames = opts.rig.rest_frames(&parents, &rest);

    let mut g = Builder::new();
    // Nodes: joint k is node k.
    for k in 0..nj {
        let (translation, rotation) = match parents[k] {
            p if p < 0 => (rest[k], frames[k]),
            p => {
                let parent = &frames[p as usize];
                (
                    mat_vec(&mat_transpose(parent), rigid.offsets[k]),
                    mat_mul(&mat_transpose(parent), &frames[k]),
                )
            }
        };
        let children: Vec<json::Index<json::Node>> = (0..nj)
            .filter(|&c| parents[c] == k as i32)
            .map(|c| json::Index::new(c as u32))
            .collect();
        g.root.push(json::Node {
            name: Some(names[k].clone()),
            translation: Some(translation),
            rotation: Some(json::scene::UnitQuaternion(to_xyzw(mat_to_quat(&rotation)))),
            children: (!children.is_empty()).then_some(children),
            ..Default::default()
        });
    }
    let roots: Vec<json::Index<json::Node>> = (0..nj)
        .filter(|&k| parents[k] < 0)
        .map(|k| json::Index::new(k as u32))
        .collect();
    let mut scene_nodes = roots.clone();

    if !opts.no_mesh {
        let body = mannequin(&rest, &parents, |j| {
            if m.skeleton.is_left(j) {
                Side::Left
            } else if m.skeleton.is_right(j) {
                Side::Right
            } else {
                Side::Centre
            }
        });
        let mesh_node = g.skinned_mesh(&body, &rest, &frames, nj, &roots)?;
        scene_nodes.push(mesh_node);
    }
    g.animation(m, &rigid, &parents, &frames, t);
    let scene = g.root.push(json::Scene {
        extensions: None,
        extras: Default::default(),
        name: Some("choreod".into()),
        nodes: scene_nodes,
    });
    g.root.scene = Some(scene);
    g.finish(binary)
}

fn descends_from(parents: &[i32], mut j: usize, root: usize) -> bool {
    loop {
        if j == root {
            return true;
        }
        match parents[j] {
            p if p < 0 => return false,
            p => j = p as usize,
        }
    }
}

/// `[w, x, y, z]` as glTF's `[x, y, z, w]`.
fn to_xyzw(q: Quat) -> [f32; 4] {
    [q[1], q[2], q[3], q[0]]
}

/// The document and its binary buffer as they grow.
struct Builder {
    root: json::Root,
    bin: Vec<u8>,
    buffer: json::Index<json::Buffer>,
}

impl Builder {
    fn new() -> Self {
        let mut root = json::Root {
            asset: json::Asset {
                generator: Some(format!("choreod {}", env!("CARGO_PKG_VERSION"))),
                ..Default::default()
            },
            ..Default::default()
        };
        let buffer = root.push(json::Buffer {
            byte_length: USize64(0),
            extensions: None,
            extras: Default::default(),
            name: None,
            uri: None,
        });
        Self {
            root,
            bin: Vec::new(),
            buffer,
        }
    }

    /// Append `bytes` as a buffer view (4-byte aligned, as every accessor here needs).
    fn view(
        &mut self,
        bytes: &[u8],
        target: Option<json::buffer::Target>,
    ) -> json::Index<json::buffer::View> {
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        let offset = self.bin.len();
        self.bin.extend_from_slice(bytes);
        self.root.push(json::buffer::View {
            buffer: self.buffer,
            byte_length: USize64::from(bytes.len()),
            byte_offset: Some(USize64::from(offset)),
            byte_stride: None,
            name: None,
            target: target.map(Valid),
            extensions: None,
            extras: Default::default(),
        })
    }

    /// An accessor over a new view holding `bytes`: `count` elements of `type_`.
    fn accessor(
        &mut self,
        bytes: &[u8],
        count: usize,
        component: json::accessor::ComponentType,
        type_: json::accessor::Type,
        target: Option<json::buffer::Target>,
        bounds: Option<(Vec<f32>, Vec<f32>)>,
    ) -> json::Index<json::Accessor> {
        let view = self.view(bytes, target);
        let (min, max) = match bounds {
            Some((lo, hi)) => (Some(json::Value::from(lo)), Some(json::Value::from(hi))),
            None => (None, None),
        };
        self.root.push(json::Accessor {
            buffer_view: Some(view),
            byte_offset: None,
            count: USize64::from(count),
            component_type: Valid(json::accessor::GenericComponentType(component)),
            extensions: None,
            extras: Default::default(),
            type_: Valid(type_),
            min,
            max,
            name: None,
            normalized: false,
            sparse: None,
        })
    }

    /// Float vectors of `width` components; `bounds` adds min/max (positions, times).
    fn floats(
        &mut self,
        values: &[f32],
        width: usize,
        target: Option<json::buffer::Target>,
        bounds: bool,
    ) -> json::Index<json::Accessor> {
        use json::accessor::Type;
        let type_ = match width {
            1 => Type::Scalar,
            3 => Type::Vec3,
            4 => Type::Vec4,
            _ => Type::Mat4,
        };
        let bounds = bounds.then(|| {
            let mut lo = vec![f32::INFINITY; width];
            let mut hi = vec![f32::NEG_INFINITY; width];
            for v in values.chunks(width) {
                for c in 0..width {
                    lo[c] = lo[c].min(v[c]);
                    hi[c] = hi[c].max(v[c]);
                }
            }
            (lo, hi)
        });
        let bytes: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
        self.accessor(
            &bytes,
            values.len() / width,
            json::accessor::ComponentType::F32,
            type_,
            target,
            bounds,
        )
    }

    /// The mannequin as a mesh skinned to joints `0..nj`; returns its node.
    fn skinned_mesh(
        &mut self,
        body: &crate::render::mannequin::Mannequin,
        rest: &[Vec3],
        frames: &[Mat3],
        nj: usize,
        roots: &[json::Index<json::Node>],
    ) -> Result<json::Index<json::Node>> {
        use json::accessor::{ComponentType, Type};
        use json::buffer::Target::{ArrayBuffer, ElementArrayBuffer};
        let positions: Vec<f32> = body.positions.iter().flatten().copied().collect();
        let normals: Vec<f32> = body.normals.iter().flatten().copied().collect();
        let count = body.positions.len();
        let position = self.floats(&positions, 3, Some(ArrayBuffer), true);
        let normal = self.floats(&normals, 3, Some(ArrayBuffer), false);
        // One joint per vertex, weight 1: JOINTS_0 = (j, 0, 0, 0), WEIGHTS_0 = (1, 0, 0, 0).
        let (joint_bytes, joint_type) = if nj <= 256 {
            let b: Vec<u8> = body
                .joints
                .iter()
                .flat_map(|&j| [j as u8, 0, 0, 0])
                .collect();
            (b, ComponentType::U8)
        } else {
            let b: Vec<u8> = body
                .joints
                .iter()
                .flat_map(|&j| [j, 0, 0, 0])
                .flat_map(u16::to_le_bytes)
                .collect();
            (b, ComponentType::U16)
        };
        let joints = self.accessor(
            &joint_bytes,
            count,
            joint_type,
            Type::Vec4,
            Some(ArrayBuffer),
            None,
        );
        let weights: Vec<f32> = (0..count).flat_map(|_| [1.0, 0.0, 0.0, 0.0]).collect();
        let weights = self.floats(&weights, 4, Some(ArrayBuffer), false);
        let mut attributes = BTreeMap::new();
        attributes.insert(Valid(json::mesh::Semantic::Positions), position);
        attributes.insert(Valid(json::mesh::Semantic::Normals), normal);
        attributes.insert(Valid(json::mesh::Semantic::Joints(0)), joints);
        attributes.insert(Valid(json::mesh::Semantic::Weights(0)), weights);
        let mut primitives = Vec::new();
        for (side, tris) in body.triangles.iter().enumerate() {
            if tris.is_empty() {
                continue;
            }
            let material = self.root.push(json::Material {
                name: Some(["left", "right", "centre"][side].into()),
                pbr_metallic_roughness: json::material::PbrMetallicRoughness {
                    base_color_factor: json::material::PbrBaseColorFactor(COLOURS[side]),
                    metallic_factor: json::material::StrengthFactor(0.0),
                    roughness_factor: json::material::StrengthFactor(0.7),
                    ..Default::default()
                },
                ..Default::default()
            });
            let (bytes, component) = if count <= usize::from(u16::MAX) {
                let b: Vec<u8> = tris
                    .iter()
                    .flat_map(|&i| (i as u16).to_le_bytes())
                    .collect();
                (b, ComponentType::U16)
            } else {
                let b: Vec<u8> = tris.iter().flat_map(|&i| i.to_le_bytes()).collect();
                (b, ComponentType::U32)
            };
            let indices = self.accessor(
                &bytes,
                tris.len(),
                component,
                Type::Scalar,
                Some(ElementArrayBuffer),
                None,
            );
            primitives.push(json::mesh::Primitive {
                attributes: attributes.clone(),
                extensions: None,
                extras: Default::default(),
                indices: Some(indices),
                material: Some(material),
                mode: Valid(json::mesh::Mode::Triangles),
                targets: None,
            });
        }
        if primitives.is_empty() {
            return Err(Error::motion(
                "the skeleton has no bone long enough for a mannequin",
            ));
        }
        // Inverse bind matrices: the inverse of each joint's rest transform (rotation `frames`,
        // position `rest`), column-major.
        let mut ibm = Vec::with_capacity(16 * nj);
        for k in 0..nj {
            let inv = mat_transpose(&frames[k]);
            let t = mat_vec(&inv, rest[k]);
            // Column c of the inverse (the transpose) is row c of the rest frame.
            for row in &frames[k] {
                ibm.extend([row[0], row[1], row[2], 0.0]);
            }
            ibm.extend([-t[0], -t[1], -t[2], 1.0]);
        }
        let ibm = self.floats(&ibm, 16, None, false);
        let skin = self.root.push(json::Skin {
            extensions: None,
            extras: Default::default(),
            inverse_bind_matrices: Some(ibm),
            joints: (0..nj).map(|k| json::Index::new(k as u32)).collect(),
            name: Some("skeleton".into()),
            skeleton: (roots.len() == 1).then(|| roots[0]),
        });
        let mesh = self.root.push(json::Mesh {
            extensions: None,
            extras: Default::default(),
            name: Some("mannequin".into()),
            primitives,
            weights: None,
        });
        Ok(self.root.push(json::Node {
            name: Some("mannequin".into()),
            mesh: Some(mesh),
            skin: Some(skin),
            ..Default::default()
        }))
    }

    /// One animation: per joint its local rotation (the rig's rest frames turned by the rigid
    /// fit's rotations), per root its measured path.
    fn animation(
        &mut self,
        m: &MotionFile,
        rigid: &crate::RigidPose,
        parents: &[i32],
        frames: &[Mat3],
        t: usize,
    ) {
        use json::animation::{Channel, Interpolation, Property, Sampler, Target};
        let nj = parents.len();
        let times: Vec<f32> = (0..t)
            .map(|f| (f as f64 / f64::from(m.fps)) as f32)
            .collect();
        let input = self.floats(&times, 1, None, true);
        // World frame of joint k at frame f: the fit's rotation of the rest frame.
        let world = |f: usize, k: usize| mat_mul(rigid.rotation(f, k), &frames[k]);
        let mut samplers = Vec::new();
        let mut channels = Vec::new();
        let mut channel = |samplers: &mut Vec<Sampler>, output, node: usize, path: Property| {
            samplers.push(Sampler {
                extensions: None,
                extras: Default::default(),
                input,
                interpolation: Valid(Interpolation::Linear),
                output,
            });
            channels.push(Channel {
                sampler: json::Index::new(samplers.len() as u32 - 1),
                target: Target {
                    extensions: None,
                    extras: Default::default(),
                    node: json::Index::new(node as u32),
                    path: Valid(path),
                },
                extensions: None,
                extras: Default::default(),
            });
        };
        for (k, &parent) in parents.iter().enumerate().take(nj) {
            let mut values = Vec::with_capacity(4 * t);
            let mut previous: Option<Quat> = None;
            for f in 0..t {
                let local = match parent {
                    p if p < 0 => world(f, k),
                    p => mat_mul(&mat_transpose(&world(f, p as usize)), &world(f, k)),
                };
                let mut q = mat_to_quat(&local);
                // q and -q are one rotation; keep neighbours on one side so that tools which
                // interpolate components (Blender) take the short way.
                if let Some(p) = previous
                    && (0..4).map(|i| p[i] * q[i]).sum::<f32>() < 0.0
                {
                    q = q.map(|c| -c);
                }
                previous = Some(q);
                values.extend(to_xyzw(q));
            }
            let output = self.floats(&values, 4, None, false);
            channel(&mut samplers, output, k, Property::Rotation);
            if parent < 0 {
                let path: Vec<f32> = (0..t)
                    .flat_map(|f| {
                        [
                            m.joints[[f, k, 0]],
                            m.joints[[f, k, 1]],
                            m.joints[[f, k, 2]],
                        ]
                    })
                    .collect();
                let output = self.floats(&path, 3, None, false);
                channel(&mut samplers, output, k, Property::Translation);
            }
        }
        self.root.push(json::Animation {
            extensions: None,
            extras: Default::default(),
            channels,
            name: Some("dance".into()),
            samplers,
        });
    }

    /// The file's bytes: GLB (header, JSON chunk, BIN chunk), or JSON with the buffer as a
    /// base64 data URI.
    fn finish(mut self, binary: bool) -> Result<Vec<u8>> {
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        let buffer = &mut self.root.buffers[self.buffer.value()];
        buffer.byte_length = USize64::from(self.bin.len());
        if !binary {
            use base64::Engine;
            buffer.uri = Some(format!(
                "data:application/octet-stream;base64,{}",
                base64::engine::general_purpose::STANDARD.encode(&self.bin)
            ));
            return self
                .root
                .to_vec()
                .map_err(|e| Error::motion(format!("glTF JSON: {e}")));
        }
        let mut text = self
            .root
            .to_vec()
            .map_err(|e| Error::motion(format!("glTF JSON: {e}")))?;
        // GLB 2.0: chunks 4-byte aligned, JSON padded with spaces, BIN with zeros.
        while !text.len().is_multiple_of(4) {
            text.push(b' ');
        }
        let total = 12 + 8 + text.len() + 8 + self.bin.len();
        let total = u32::try_from(total)
            .map_err(|_| Error::motion(format!("{total} bytes exceed GLB's 4 GiB")))?;
        let mut out = Vec::with_capacity(total as usize);
        out.extend(b"glTF");
        out.extend(2u32.to_le_bytes());
        out.extend(total.to_le_bytes());
        out.extend((text.len() as u32).to_le_bytes());
        out.extend(b"JSON");
        out.extend(text);
        out.extend((self.bin.len() as u32).to_le_bytes());
        out.extend(b"BIN\0");
        out.extend(self.bin);
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::SkeletonKind;
    use crate::export::ExportRig;

    /// The parts of a GLB a player uses, read back with serde_json and byte offsets (not with
    /// the writer's types).
    struct Glb {
        json: serde_json::Value,
        bin: Vec<u8>,
    }

    impl Glb {
        fn parse(bytes: &[u8]) -> Glb {
            let word = |at: usize| u32::from_le_bytes(bytes[at..at + 4].try_into().unwrap());
            assert_eq!(&bytes[..4], b"glTF");
            assert_eq!(word(4), 2);
            assert_eq!(word(8) as usize, bytes.len());
            let json_len = word(12) as usize;
            assert_eq!(&bytes[16..20], b"JSON");
            let json = serde_json::from_slice(&bytes[20..20 + json_len]).unwrap();
            let at = 20 + json_len;
            let bin_len = word(at) as usize;
            assert_eq!(&bytes[at + 4..at + 8], b"BIN\0");
            Glb {
                json,
                bin: bytes[at + 8..at + 8 + bin_len].to_vec(),
            }
        }

        /// Accessor `i` as f32 values.
        fn floats(&self, i: u64) -> Vec<f32> {
            let a = &self.json["accessors"][i as usize];
            let v = &self.json["bufferViews"][a["bufferView"].as_u64().unwrap() as usize];
            let start = v["byteOffset"].as_u64().unwrap_or(0) as usize;
            let len = v["byteLength"].as_u64().unwrap() as usize;
            assert_eq!(a["componentType"], 5126);
            self.bin[start..start + len]
                .chunks(4)
                .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
                .collect()
        }
    }

    /// `q` (x, y, z, w) applied to `v`.
    fn rotate(q: &[f32], v: [f64; 3]) -> [f64; 3] {
        let (x, y, z, w) = (q[0] as f64, q[1] as f64, q[2] as f64, q[3] as f64);
        let (vx, vy, vz) = (v[0], v[1], v[2]);
        // v + 2w (q × v) + 2 q × (q × v)
        let c = [y * vz - z * vy, z * vx - x * vz, x * vy - y * vx];
        let cc = [
            y * c[2] - z * c[1],
            z * c[0] - x * c[2],
            x * c[1] - y * c[0],
        ];
        [0, 1, 2].map(|i| v[i] + 2.0 * w * c[i] + 2.0 * cc[i])
    }

    fn qmul_xyzw(a: &[f32], b: &[f32]) -> [f32; 4] {
        let (ax, ay, az, aw) = (a[0], a[1], a[2], a[3]);
        let (bx, by, bz, bw) = (b[0], b[1], b[2], b[3]);
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ]
    }

    /// World joint positions at key `f`: each node's translation and rotation (animated ones
    /// from the animation's key `f`) composed down the node tree.
    fn forward_kinematics(g: &Glb, nj: usize, f: usize) -> Vec<[f64; 3]> {
        let nodes = g.json["nodes"].as_array().unwrap();
        let mut trs: Vec<([f64; 3], [f32; 4])> = (0..nj)
            .map(|k| {
                let t = &nodes[k]["translation"];
                let r = &nodes[k]["rotation"];
                (
                    [0, 1, 2].map(|i| t[i].as_f64().unwrap()),
                    [0, 1, 2, 3].map(|i| r[i].as_f64().unwrap() as f32),
                )
            })
            .collect();
        let anim = &g.json["animations"][0];
        for ch in anim["channels"].as_array().unwrap() {
            let s = &anim["samplers"][ch["sampler"].as_u64().unwrap() as usize];
            let values = g.floats(s["output"].as_u64().unwrap());
            let node = ch["target"]["node"].as_u64().unwrap() as usize;
            match ch["target"]["path"].as_str().unwrap() {
                "rotation" => trs[node].1.copy_from_slice(&values[4 * f..4 * f + 4]),
                "translation" => {
                    trs[node].0 = [0, 1, 2].map(|i| f64::from(values[3 * f + i]));
                }
                other => panic!("{other}"),
            }
        }
        let mut world: Vec<([f64; 3], [f32; 4])> = vec![([0.0; 3], [0.0, 0.0, 0.0, 1.0]); nj];
        let mut done = vec![false; nj];
        // Parents from the node tree.
        let mut parent = vec![None; nj];
        for (k, n) in nodes.iter().enumerate().take(nj) {
            for c in n["children"].as_array().into_iter().flatten() {
                parent[c.as_u64().unwrap() as usize] = Some(k);
            }
        }
        for k in 0..nj {
            assert!(parent[k].is_none_or(|p| done[p]), "parent after child");
            world[k] = match parent[k] {
                None => trs[k],
                Some(p) => {
                    let (pt, pr) = world[p];
                    let d = rotate(&pr, trs[k].0);
                    ([0, 1, 2].map(|i| pt[i] + d[i]), qmul_xyzw(&pr, &trs[k].1))
                }
            };
            done[k] = true;
        }
        world.iter().map(|w| w.0).collect()
    }

    fn aist() -> MotionFile {
        let pkl = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../daemon/assets/motion/aistpp_gBR_sBM_cAll_d04_mBR0_ch01.pkl");
        let a = crate::AistppMotion::read(&pkl).unwrap();
        MotionFile::from_joints(60.0, SkeletonKind::Smpl24, a.joints())
    }

    #[test]
    fn the_nodes_and_animation_place_every_joint_where_the_motion_has_it() {
        let m = aist();
        for rig in [ExportRig::Native, ExportRig::Mixamo] {
            let opts = ExportOptions {
                rig,
                no_mesh: false,
            };
            let g = Glb::parse(&gltf_bytes(&m, &opts).unwrap());
            let anim = &g.json["animations"][0];
            let times = g.floats(anim["samplers"][0]["input"].as_u64().unwrap());
            assert_eq!(times.len(), 720);
            for f in [0, 1, 359, 719] {
                assert!((f64::from(times[f]) - f as f64 / 60.0).abs() < 1e-6);
                let placed = forward_kinematics(&g, 24, f);
                for (k, p) in placed.iter().enumerate() {
                    for (c, &at) in p.iter().enumerate() {
                        let d = (at - f64::from(m.joints[[f, k, c]])).abs();
                        // SMPL FK is rigid: the fit reproduces it to float precision (a few
                        // micrometres over chains of 1-2 m of bones in f32).
                        assert!(d < 2e-5, "{rig:?} frame {f} joint {k}: off by {d} m");
                    }
                }
            }
            assert_keys_on_one_side(&g, &format!("{rig:?}"));
        }
    }

    /// Neighbouring rotation keys on one side of the quaternion double cover, for tools that
    /// interpolate components (Blender): a key and its negation are one rotation, but halfway
    /// between them is no rotation at all.
    fn assert_keys_on_one_side(g: &Glb, label: &str) {
        let anim = &g.json["animations"][0];
        for ch in anim["channels"].as_array().unwrap() {
            if ch["target"]["path"] != "rotation" {
                continue;
            }
            let s = &anim["samplers"][ch["sampler"].as_u64().unwrap() as usize];
            let q = g.floats(s["output"].as_u64().unwrap());
            for f in 1..q.len() / 4 {
                let dot: f32 = (0..4).map(|i| q[4 * f + i] * q[4 * f - 4 + i]).sum();
                assert!(dot > 0.0, "{label} {ch}: frame {f}");
            }
        }
    }

    #[test]
    fn keys_stay_on_one_side_of_the_double_cover_through_a_full_turn() {
        // The clip turned about the vertical by a whole turn over its frames: the root's
        // rotation passes 240°, where the matrix-to-quaternion conversion's own sign choice
        // flips (w > 0 again), so only the sign continuity keeps neighbouring keys together.
        let mut m = aist();
        let t = m.joints.shape()[0];
        for f in 0..t {
            let a = std::f64::consts::TAU * f as f64 / t as f64;
            let (sin, cos) = a.sin_cos();
            for k in 0..24 {
                let (x, z) = (
                    f64::from(m.joints[[f, k, 0]]),
                    f64::from(m.joints[[f, k, 2]]),
                );
                m.joints[[f, k, 0]] = (cos * x + sin * z) as f32;
                m.joints[[f, k, 2]] = (cos * z - sin * x) as f32;
            }
        }
        let g = Glb::parse(&gltf_bytes(&m, &ExportOptions::default()).unwrap());
        assert_keys_on_one_side(&g, "turning clip");
        for f in [0, 480, 719] {
            for (k, p) in forward_kinematics(&g, 24, f).iter().enumerate() {
                for (c, &at) in p.iter().enumerate() {
                    let d = (at - f64::from(m.joints[[f, k, c]])).abs();
                    assert!(d < 2e-5, "frame {f} joint {k}: off by {d} m");
                }
            }
        }
    }

    #[test]
    fn a_players_skeleton_is_read_from_the_json_alone() {
        let m = aist();
        let path = Path::new("aist.glb");
        for no_mesh in [false, true] {
            let opts = ExportOptions {
                rig: ExportRig::Native,
                no_mesh,
            };
            let s = read_gltf_skeleton(path, &gltf_bytes(&m, &opts).unwrap()).unwrap();
            assert_eq!(s.nodes, (0..24).collect::<Vec<_>>(), "no_mesh {no_mesh}");
            assert_eq!(s.joint_names, SkeletonKind::Smpl24.joint_names());
            assert_eq!(s.parents, crate::skeleton::SMPL24_PARENTS);
            assert_eq!((s.fps, s.frames), (60.0, 720));
        }
        let glb = gltf_bytes(&m, &ExportOptions::default()).unwrap();
        let err = |bytes: &[u8]| read_gltf_skeleton(path, bytes).unwrap_err().to_string();
        assert!(err(&glb[..glb.len() / 2]).contains("the file has"));
        assert!(err(&glb[..10]).contains("shorter than a GLB header"));
        assert!(err(b"{").contains("not glTF 2.0 JSON"));
        let text = br#"{"asset": {"version": "2.0"}, "buffers": [{"uri": "../secret.bin", "byteLength": 4}]}"#;
        assert!(err(text).contains("refers to the file"), "{}", err(text));
    }

    #[test]
    fn the_rest_mannequin_stands_in_the_skeleton_tables_rest_pose() {
        for (kind, offsets) in [
            (SkeletonKind::Smpl24, SMPL24_OFFSETS.to_vec()),
            (SkeletonKind::T2m22, t2m_default_target_offsets().to_vec()),
        ] {
            let g = Glb::parse(&rest_mannequin_glb(&kind).unwrap());
            let nj = offsets.len();
            let want = rest_positions(kind.parents(), &offsets, [0.0; 3]);
            for (k, p) in forward_kinematics(&g, nj, 0).iter().enumerate() {
                for c in 0..3 {
                    let d = (p[c] - f64::from(want[k][c])).abs();
                    assert!(d < 1e-6, "{} joint {k}: off by {d} m", kind.name());
                }
            }
            assert_eq!(g.json["skins"][0]["joints"].as_array().unwrap().len(), nj);
        }
        assert!(
            rest_mannequin_glb(&SkeletonKind::from_parts("bvh", vec!["a".into()], vec![-1]))
                .is_err()
        );
    }

    #[test]
    fn the_skin_binds_each_joint_at_its_rest_pose() {
        let m = aist();
        for rig in [ExportRig::Native, ExportRig::Mixamo] {
            let g = Glb::parse(
                &gltf_bytes(
                    &m,
                    &ExportOptions {
                        rig,
                        no_mesh: false,
                    },
                )
                .unwrap(),
            );
            let skin = &g.json["skins"][0];
            let ibm = g.floats(skin["inverseBindMatrices"].as_u64().unwrap());
            // The rest pose: node transforms without the animation.
            let nodes = g.json["nodes"].as_array().unwrap();
            let mut world: Vec<([f64; 3], [f32; 4])> = Vec::new();
            for (k, node) in nodes.iter().enumerate().take(24) {
                let t = [0, 1, 2].map(|i| node["translation"][i].as_f64().unwrap());
                let r = [0, 1, 2, 3].map(|i| node["rotation"][i].as_f64().unwrap() as f32);
                let p = crate::skeleton::SMPL24_PARENTS[k];
                world.push(if p < 0 {
                    (t, r)
                } else {
                    let (pt, pr) = world[p as usize];
                    let d = rotate(&pr, t);
                    ([0, 1, 2].map(|i| pt[i] + d[i]), qmul_xyzw(&pr, &r))
                });
            }
            for (k, (t, r)) in world.iter().enumerate() {
                let inv = &ibm[16 * k..16 * k + 16];
                // inverse(bind) · bind = identity: check on the joint's origin and axes.
                for v in [
                    [0.0, 0.0, 0.0],
                    [1.0, 0.0, 0.0],
                    [0.0, 1.0, 0.0],
                    [0.0, 0.0, 1.0],
                ] {
                    let rv = rotate(r, v);
                    let w = [0, 1, 2].map(|i| t[i] + rv[i]);
                    let back: [f64; 3] = [0, 1, 2].map(|row| {
                        (0..3)
                            .map(|c| f64::from(inv[4 * c + row]) * w[c])
                            .sum::<f64>()
                            + f64::from(inv[12 + row])
                    });
                    for i in 0..3 {
                        assert!(
                            (back[i] - v[i]).abs() < 1e-5,
                            "{rig:?} joint {k}: {back:?} vs {v:?}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn gltf_text_embeds_the_same_buffer() {
        let m = aist();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.gltf");
        write_gltf(&path, &m, &ExportOptions::default(), false).unwrap();
        let text: serde_json::Value =
            serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
        let uri = text["buffers"][0]["uri"].as_str().unwrap();
        use base64::Engine;
        let bin = base64::engine::general_purpose::STANDARD
            .decode(
                uri.strip_prefix("data:application/octet-stream;base64,")
                    .unwrap(),
            )
            .unwrap();
        let glb = Glb::parse(&gltf_bytes(&m, &ExportOptions::default()).unwrap());
        assert_eq!(bin, glb.bin);
        assert_eq!(text["nodes"], glb.json["nodes"]);
    }
}
