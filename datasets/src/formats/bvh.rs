//! BVH motion capture files: a reader for any hierarchy (any channel order and Euler order)
//! to world joint positions, and a writer that turns joint positions into a rotation-animated
//! armature (Blender imports it as one).
//!
//! Conventions: rotation channels compose in the order listed (`Zrotation Xrotation Yrotation`
//! means `Rz·Rx·Ry`), degrees; position channels replace the joint's offset component (as
//! Holden's `BVH.py` reads them); End Sites are kept as extra joints flagged `end_site`.

use std::path::Path;

use choreo_dsp::quote;
use ndarray::Array3;

use crate::error::{Error, Result, io_err};
use crate::formats::motion_file::{MotionFile, write_atomic_bytes};
use crate::kinematics::rigid::{children_of, fit_rigid_pose};
use crate::rotation::{
    MAT3_IDENTITY, Mat3, Vec3, add, axis_rotation, mat_mul, mat_to_euler, mat_transpose, mat_vec,
    norm, sub,
};
use crate::skeleton::{MAX_JOINTS, SMPL24_OFFSETS, SkeletonKind};

const MAX_BVH_BYTES: u64 = 512 * 1024 * 1024;
const MAX_FRAMES: usize = 1_000_000;
/// Metres per CMU BVH unit (the cgspeed conversion of the CMU database: 2.54 cm / 0.45).
pub const CMU_UNIT_M: f32 = 0.056_444;

/// One channel of a BVH joint.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Channel {
    Pos(usize),
    Rot(usize),
}

/// A BVH file read into world joint positions.
#[derive(Debug, Clone)]
pub struct BvhMotion {
    /// Joint names (End Sites are named `<parent>_end`).
    pub names: Vec<String>,
    /// Parent per joint (-1 for the root).
    pub parents: Vec<i32>,
    /// Whether each joint is an End Site.
    pub end_site: Vec<bool>,
    /// (T, J, 3) world positions in metres (after `scale`).
    pub joints: Array3<f32>,
    /// Frames per second (1 / Frame Time).
    pub fps: f32,
    /// Metres per file unit used.
    pub scale: f32,
}

impl BvhMotion {
    /// The motion without End Sites as a [`MotionFile`]; SMPL-24 / t2m-22 hierarchies written by
    /// [`write_bvh_positions`] are recognised by their joint names.
    pub fn to_motion_file(&self) -> MotionFile {
        let keep: Vec<usize> = (0..self.names.len())
            .filter(|j| !self.end_site[*j])
            .collect();
        let mut remap = vec![-1i32; self.names.len()];
        for (new, old) in keep.iter().enumerate() {
            remap[*old] = new as i32;
        }
        let names: Vec<String> = keep.iter().map(|j| self.names[*j].clone()).collect();
        let parents: Vec<i32> = keep
            .iter()
            .map(|j| {
                if self.parents[*j] < 0 {
                    -1
                } else {
                    remap[self.parents[*j] as usize]
                }
            })
            .collect();
        let t = self.joints.shape()[0];
        // Built-in skeletons come back in their canonical joint order (the file is depth-first).
        for kind in [SkeletonKind::Smpl24, SkeletonKind::T2m22] {
            let want = kind.joint_names();
            if want.len() != names.len() {
                continue;
            }
            let idx: Option<Vec<usize>> = want
                .iter()
                .map(|n| names.iter().position(|m| m == n))
                .collect();
            let Some(idx) = idx else { continue };
            let same_tree = kind.parents().iter().enumerate().all(|(k, p)| {
                let fp = parents[idx[k]];
                if *p < 0 {
                    fp < 0
                } else {
                    fp >= 0 && names[fp as usize] == want[*p as usize]
                }
            });
            if same_tree {
                let joints = Array3::from_shape_fn((t, idx.len(), 3), |(f, j, c)| {
                    self.joints[[f, keep[idx[j]], c]]
                });
                return MotionFile::from_joints(self.fps, kind, joints);
            }
        }
        let joints =
            Array3::from_shape_fn((t, keep.len(), 3), |(f, j, c)| self.joints[[f, keep[j], c]]);
        let skeleton = SkeletonKind::Custom {
            name: "bvh".into(),
            joint_names: names,
            parents,
        };
        MotionFile::from_joints(self.fps, skeleton, joints)
    }
}

struct Tokens<'a> {
    toks: Vec<(usize, &'a str)>,
    at: usize,
}

impl<'a> Tokens<'a> {
    fn next(&mut self, path: &Path) -> Result<(usize, &'a str)> {
        let t = self
            .toks
            .get(self.at)
            .copied()
            .ok_or_else(|| Error::invalid(path, "BVH ends unexpectedly"))?;
        self.at += 1;
        Ok(t)
    }

    fn expect(&mut self, path: &Path, want: &str) -> Result<()> {
        let (line, t) = self.next(path)?;
        if t != want {
            return Err(Error::invalid(
                path,
                format!("line {line}: expected '{want}', found {}", quote(t)),
            ));
        }
        Ok(())
    }

    fn number(&mut self, path: &Path) -> Result<f32> {
        let (line, t) = self.next(path)?;
        match t.parse::<f32>() {
            Ok(v) if v.is_finite() => Ok(v),
            _ => Err(Error::invalid(
                path,
                format!("line {line}: {} is not a finite number", quote(t)),
            )),
        }
    }
}

/// Read a BVH file into world joint positions. `scale` is metres per file unit; `None` guesses
/// it from the rest pose's height (centimetres, CMU units or metres).
pub fn read_bvh(path: &Path) -> Result<BvhMotion> {
    read_bvh_scaled(path, None)
}

/// [`read_bvh`] with an explicit scale (metres per file unit) or `None` to guess.
pub fn read_bvh_scaled(path: &Path, scale: Option<f32>) -> Result<BvhMotion> {
    let len = std::fs::metadata(path).map_err(io_err(path))?.len();
    if len > MAX_BVH_BYTES {
        return Err(Error::invalid(
            path,
            format!("BVH of {len} bytes exceeds {MAX_BVH_BYTES}"),
        ));
    }
    let text = std::fs::read_to_string(path)
        .map_err(|e| Error::invalid(path, format!("not a text BVH file: {e}")))?;
    let toks: Vec<(usize, &str)> = text
        .lines()
        .enumerate()
        .flat_map(|(i, l)| l.split_whitespace().map(move |w| (i + 1, w)))
        .collect();
    let mut tk = Tokens { toks, at: 0 };
    tk.expect(path, "HIERARCHY")?;
    let mut names = Vec::new();
    let mut parents = Vec::new();
    let mut offsets: Vec<Vec3> = Vec::new();
    let mut channels: Vec<Vec<Channel>> = Vec::new();
    let mut end_site = Vec::new();
    let mut stack: Vec<usize> = Vec::new();
    let (line, first) = tk.next(path)?;
    if first != "ROOT" {
        return Err(Error::invalid(
            path,
            format!("line {line}: expected 'ROOT', found {}", quote(first)),
        ));
    }
    let mut pending = Some(("ROOT", line));
    loop {
        if let Some((kind, line)) = pending.take() {
            if names.len() >= MAX_JOINTS {
                return Err(Error::invalid(
                    path,
                    format!("more than {MAX_JOINTS} joints"),
                ));
            }
            let is_end = kind == "End";
            let name = if is_end {
                tk.expect(path, "Site")?;
                let p = *stack.last().ok_or_else(|| {
                    Error::invalid(path, format!("line {line}: End Site outside a joint"))
                })?;
                format!("{}_end", names[p])
            } else {
                tk.next(path)?.1.to_owned()
            };
            tk.expect(path, "{")?;
            tk.expect(path, "OFFSET")?;
            let o = [tk.number(path)?, tk.number(path)?, tk.number(path)?];
            let mut ch = Vec::new();
            if !is_end {
                tk.expect(path, "CHANNELS")?;
                let (l, n) = tk.next(path)?;
                let n: usize = n.parse().ok().filter(|n| *n <= 6).ok_or_else(|| {
                    Error::invalid(
                        path,
                        format!("line {l}: channel count {} (0-6 allowed)", quote(n)),
                    )
                })?;
                for _ in 0..n {
                    let (l, c) = tk.next(path)?;
                    let c = match c.to_ascii_lowercase().as_str() {
                        "xposition" => Channel::Pos(0),
                        "yposition" => Channel::Pos(1),
                        "zposition" => Channel::Pos(2),
                        "xrotation" => Channel::Rot(0),
                        "yrotation" => Channel::Rot(1),
                        "zrotation" => Channel::Rot(2),
                        _ => {
                            return Err(Error::invalid(
                                path,
                                format!("line {l}: unknown channel {}", quote(c)),
                            ));
                        }
                    };
                    ch.push(c);
                }
            }
            parents.push(stack.last().map_or(-1, |p| *p as i32));
            names.push(name);
            offsets.push(o);
            channels.push(ch);
            end_site.push(is_end);
            stack.push(names.len() - 1);
            continue;
        }
        let (line, t) = tk.next(path)?;
        match t {
            "JOINT" | "End" => {
                if stack.is_empty() {
                    return Err(Error::invalid(
                        path,
                        format!("line {line}: {t} outside the ROOT block"),
                    ));
                }
                if end_site.last().copied().unwrap_or(false)
                    && stack.last() == Some(&(names.len() - 1))
                {
                    return Err(Error::invalid(
                        path,
                        format!("line {line}: End Site cannot have children"),
                    ));
                }
                pending = Some((if t == "End" { "End" } else { "JOINT" }, line));
            }
            "}" => {
                stack
                    .pop()
                    .ok_or_else(|| Error::invalid(path, format!("line {line}: unbalanced '}}'")))?;
                if stack.is_empty() {
                    break;
                }
            }
            other => {
                return Err(Error::invalid(
                    path,
                    format!("line {line}: unexpected {} in hierarchy", quote(other)),
                ));
            }
        }
    }
    tk.expect(path, "MOTION")?;
    tk.expect(path, "Frames:")?;
    let (l, nf) = tk.next(path)?;
    let frames: usize = nf
        .parse()
        .ok()
        .filter(|n| *n <= MAX_FRAMES)
        .ok_or_else(|| {
            Error::invalid(
                path,
                format!("line {l}: frame count {} (0..={MAX_FRAMES})", quote(nf)),
            )
        })?;
    tk.expect(path, "Frame")?;
    tk.expect(path, "Time:")?;
    let (l, dt_text) = tk.next(path)?;
    let fps = fps_from_frame_time(dt_text).ok_or_else(|| {
        Error::invalid(
            path,
            format!(
                "line {l}: Frame Time {} is not a positive number",
                quote(dt_text)
            ),
        )
    })?;
    crate::limits::check_fps(fps).map_err(|why| {
        Error::invalid(
            path,
            format!("line {l}: Frame Time {}: {why}", quote(dt_text)),
        )
    })?;
    let total: usize = channels.iter().map(Vec::len).sum();
    let remaining = tk.toks.len() - tk.at;
    if remaining != frames * total {
        let line = tk.toks.get(tk.at).map_or(0, |t| t.0);
        return Err(Error::invalid(
            path,
            format!(
                "from line {line}: {frames} frames × {total} channels need {} numbers, found {remaining}",
                frames * total
            ),
        ));
    }
    let j = names.len();
    // Joints without channels cost output but no input: bound the output before allocating.
    crate::limits::elements(path, "BVH joint positions", &[frames, j, 3])?;
    let rest = rest_positions(&parents, &offsets);
    let scale = scale.unwrap_or_else(|| guess_scale(&rest));
    let mut joints = Array3::<f32>::zeros((frames, j, 3));
    let mut g: Vec<Mat3> = vec![MAT3_IDENTITY; j];
    let mut p: Vec<Vec3> = vec![[0.0; 3]; j];
    for f in 0..frames {
        for k in 0..j {
            let mut off = offsets[k];
            let mut rot = MAT3_IDENTITY;
            for c in &channels[k] {
                let v = tk.number(path)?;
                match c {
                    Channel::Pos(a) => off[*a] = v,
                    Channel::Rot(a) => {
                        rot = mat_mul(&rot, &axis_rotation(*a, f64::from(v).to_radians()))
                    }
                }
            }
            if parents[k] < 0 {
                g[k] = rot;
                p[k] = off;
            } else {
                let pk = parents[k] as usize;
                p[k] = add(p[pk], mat_vec(&g[pk], off));
                g[k] = mat_mul(&g[pk], &rot);
            }
            for c in 0..3 {
                joints[[f, k, c]] = p[k][c] * scale;
            }
        }
    }
    Ok(BvhMotion {
        names,
        parents,
        end_site,
        joints,
        fps,
        scale,
    })
}

/// Frame rate from a BVH `Frame Time` token: the first rate `p/q` the printed seconds allow,
/// trying whole rates (`q` = 1), then NTSC's (`q` = 1001: 30000/1001, 24000/1001), then other
/// fractions up to `q` = 1000, else `1 / Frame Time` itself. A value printed with `d` decimals
/// can be off by half a unit of its last digit; the tolerance is that, and at least 1e-6
/// relative. So `0.0166667` and `0.01666667` both read as exactly 60 fps, `0.0083333` (CMU) as
/// 120, `0.03336667` as 30000/1001. Returns `None` for a non-number or a non-positive time.
fn fps_from_frame_time(text: &str) -> Option<f32> {
    let dt: f64 = text
        .parse()
        .ok()
        .filter(|v: &f64| v.is_finite() && *v > 0.0)?;
    let raw = 1.0 / dt;
    if !(raw.is_finite() && raw <= f64::from(f32::MAX)) {
        return None;
    }
    let decimals = text.split_once('.').map_or(0, |(_, frac)| {
        frac.chars().take_while(char::is_ascii_digit).count()
    });
    let half_unit = if text.contains(['e', 'E']) {
        0.0
    } else {
        0.5 * 10f64.powi(-(decimals as i32))
    };
    // d(1/dt) = dt_err / dt²; at least 1e-6 relative.
    let tolerance = (half_unit / (dt * dt)).max(raw * 1e-6);
    for q in [1, 1001].into_iter().chain(2..=1000u32) {
        let p = (raw * f64::from(q)).round();
        if p >= 1.0 && (p / f64::from(q) - raw).abs() <= tolerance {
            return Some((p / f64::from(q)) as f32);
        }
    }
    Some(raw as f32)
}

fn rest_positions(parents: &[i32], offsets: &[Vec3]) -> Vec<Vec3> {
    let mut out: Vec<Vec3> = Vec::with_capacity(offsets.len());
    for (k, o) in offsets.iter().enumerate() {
        let p = if parents[k] < 0 {
            [0.0; 3]
        } else {
            out[parents[k] as usize]
        };
        out.push(add(p, *o));
    }
    out
}

/// Metres per unit from the rest-pose height: a person is 1-2.2 m tall.
fn guess_scale(rest: &[Vec3]) -> f32 {
    let (lo, hi) = rest.iter().fold((f32::MAX, f32::MIN), |(lo, hi), p| {
        (lo.min(p[1]), hi.max(p[1]))
    });
    let h = hi - lo;
    if h > 60.0 {
        0.01 // centimetres
    } else if h > 5.0 {
        CMU_UNIT_M
    } else {
        1.0
    }
}

/// Write joint positions as a BVH armature animated by rotations (Blender imports it): the rigid
/// skeleton of [`fit_rigid_pose`] (median bone lengths and sibling spans, rotations continuous
/// from frame to frame), so a rigid motion is reproduced exactly and a non-rigid one by its
/// nearest rigid pose; root translation channels carry the root path. Euler order ZXY, degrees,
/// metres, each angle unwrapped to the one nearest the previous frame's.
pub fn write_bvh_positions(path: &Path, m: &MotionFile) -> Result<()> {
    write_bvh_named(path, m, &m.skeleton.joint_names())
}

/// [`write_bvh_positions`] with the joints named `names` (e.g. a rig's bone names) instead of
/// the skeleton's own.
pub fn write_bvh_named(path: &Path, m: &MotionFile, names: &[String]) -> Result<()> {
    let (t, nj) = (m.joints.shape()[0], m.joints.shape()[1]);
    let parents = m.skeleton.parents().to_vec();
    if parents.len() == nj && (parents.iter().filter(|p| **p < 0).count() != 1 || parents[0] != -1)
    {
        return Err(Error::invalid(path, "BVH needs exactly one root, joint 0"));
    }
    if names.len() != nj {
        return Err(Error::invalid(
            path,
            format!("{} joint names for {nj} joints", names.len()),
        ));
    }
    if let Some(rotations) = lodge_rotations(m) {
        return write_bvh_rotations(path, m, names, &parents, &rotations);
    }
    let rigid = fit_rigid_pose(&m.skeleton, m.joints.view()).map_err(|e| e.with_path(path))?;
    emit(
        path,
        (names, &parents, &rigid.offsets),
        t,
        m.fps,
        |f| {
            [
                m.joints[[f, 0, 0]],
                m.joints[[f, 0, 1]],
                m.joints[[f, 0, 2]],
            ]
        },
        |f, locals| {
            for (k, l) in locals.iter_mut().enumerate() {
                *l = rigid.local_rotation(&parents, f, k);
            }
        },
    )
}

/// The local rotations `(T, 22)` of a LODGE dance, when the motion file holds its raw
/// `lodge-smplx139` features beside its 22 joints: the network's own 6D, Gram–Schmidt'ed
/// (`crate::smplx::rot6d_to_mat`).
fn lodge_rotations(m: &MotionFile) -> Option<Vec<[Mat3; crate::smplx::BODY_JOINTS]>> {
    let f = m.features.as_ref()?;
    let (t, nj) = (m.joints.shape()[0], m.joints.shape()[1]);
    if f.representation != crate::smplx::LODGE_REPRESENTATION
        || f.normalized
        || nj != crate::smplx::BODY_JOINTS
        || f.data.dim() != (t, crate::smplx::LODGE_FEATURES)
    {
        return None;
    }
    f.data
        .outer_iter()
        .map(|row| {
            crate::smplx::decode_frame(row.as_slice()?)
                .ok()
                .map(|p| p.rotations)
        })
        .collect()
}

/// BVH with given local rotations (no IK): the offsets are the bones of frame 0 taken back
/// through its rotations (`R_parent_world^T (p_child - p_parent)`, the rest pose the joints were
/// made from), the root channel the root joint.
fn write_bvh_rotations(
    path: &Path,
    m: &MotionFile,
    names: &[String],
    parents: &[i32],
    rotations: &[[Mat3; crate::smplx::BODY_JOINTS]],
) -> Result<()> {
    let nj = parents.len();
    let mut world = vec![[[0.0f32; 3]; 3]; nj];
    let mut offsets = vec![[0.0f32; 3]; nj];
    let p = |j: usize| {
        [
            m.joints[[0, j, 0]],
            m.joints[[0, j, 1]],
            m.joints[[0, j, 2]],
        ]
    };
    for j in 0..nj {
        match usize::try_from(parents[j]) {
            Err(_) => world[j] = rotations[0][j],
            Ok(parent) => {
                offsets[j] = mat_vec(&mat_transpose(&world[parent]), sub(p(j), p(parent)));
                world[j] = mat_mul(&world[parent], &rotations[0][j]);
            }
        }
    }
    emit(
        path,
        (names, parents, &offsets),
        m.joints.shape()[0],
        m.fps,
        |f| {
            [
                m.joints[[f, 0, 0]],
                m.joints[[f, 0, 1]],
                m.joints[[f, 0, 2]],
            ]
        },
        |f, locals| locals.copy_from_slice(&rotations[f][..locals.len()]),
    )
}

/// Write an AIST++ motion as BVH with its own SMPL rotations (twist included) on the SMPL
/// neutral skeleton of [`SMPL24_OFFSETS`]; the root path is `trans / scaling`. Joint positions
/// read back equal [`crate::AistppMotion::joints`].
pub fn write_bvh_smpl(path: &Path, m: &crate::AistppMotion) -> Result<()> {
    let t = m.len();
    let names: Vec<String> = crate::skeleton::SMPL24_JOINT_NAMES
        .iter()
        .map(|n| (*n).to_owned())
        .collect();
    let parents = crate::skeleton::SMPL24_PARENTS.to_vec();
    let root = m.root_positions();
    emit(
        path,
        (&names, &parents, &SMPL24_OFFSETS),
        t,
        m.fps,
        |f| [root[[f, 0]], root[[f, 1]], root[[f, 2]]],
        |f, locals| {
            for (k, l) in locals.iter_mut().enumerate() {
                *l = crate::rotation::axis_angle_to_mat([
                    m.poses[[f, k, 0]],
                    m.poses[[f, k, 1]],
                    m.poses[[f, k, 2]],
                ]);
            }
        },
    )
}

/// Write the hierarchy (joint 0 the root, parents before children) and `t` frames whose local
/// rotations `locals(frame, &mut [Mat3])` fills; Euler order ZXY, degrees, 6 decimals.
fn emit(
    path: &Path,
    (names, parents, offsets): (&[String], &[i32], &[Vec3]),
    t: usize,
    fps: f32,
    root_pos: impl Fn(usize) -> Vec3,
    mut locals: impl FnMut(usize, &mut [Mat3]),
) -> Result<()> {
    let nj = parents.len();
    let children = children_of(parents);
    const ORDER: [usize; 3] = [2, 0, 1];
    let mut s = String::with_capacity(64 * nj + t * nj * 30);
    s.push_str("HIERARCHY\n");
    fn write_joint(
        s: &mut String,
        k: usize,
        depth: usize,
        names: &[String],
        offsets: &[Vec3],
        children: &[Vec<usize>],
    ) {
        let ind = "\t".repeat(depth);
        let kw = if depth == 0 { "ROOT" } else { "JOINT" };
        let o = if depth == 0 { [0.0; 3] } else { offsets[k] };
        s.push_str(&format!(
            "{ind}{kw} {}\n{ind}{{\n",
            names[k].replace(char::is_whitespace, "_")
        ));
        s.push_str(&format!(
            "{ind}\tOFFSET {:.6} {:.6} {:.6}\n",
            o[0], o[1], o[2]
        ));
        if depth == 0 {
            s.push_str(&format!(
                "{ind}\tCHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation\n"
            ));
        } else {
            s.push_str(&format!(
                "{ind}\tCHANNELS 3 Zrotation Xrotation Yrotation\n"
            ));
        }
        if children[k].is_empty() {
            // A short End Site along the bone so Blender draws the leaf bone.
            let d = offsets[k];
            let n = norm(d).max(1e-6);
            let e = [d[0] / n * 0.05, d[1] / n * 0.05, d[2] / n * 0.05];
            s.push_str(&format!(
                "{ind}\tEnd Site\n{ind}\t{{\n{ind}\t\tOFFSET {:.6} {:.6} {:.6}\n{ind}\t}}\n",
                e[0], e[1], e[2]
            ));
        }
        for c in &children[k] {
            write_joint(s, *c, depth + 1, names, offsets, children);
        }
        s.push_str(&format!("{ind}}}\n"));
    }
    write_joint(&mut s, 0, 0, names, offsets, &children);
    // Channel order of the file is depth-first order of the hierarchy.
    let mut order = Vec::with_capacity(nj);
    fn dfs(k: usize, children: &[Vec<usize>], out: &mut Vec<usize>) {
        out.push(k);
        for c in &children[k] {
            dfs(*c, children, out);
        }
    }
    dfs(0, &children, &mut order);
    s.push_str(&format!(
        "MOTION\nFrames: {t}\nFrame Time: {:.8}\n",
        1.0 / f64::from(fps)
    ));
    let mut local = vec![MAT3_IDENTITY; nj];
    let mut previous: Vec<Option<[f64; 3]>> = vec![None; nj];
    for f in 0..t {
        locals(f, &mut local);
        let mut line = String::with_capacity(nj * 36);
        for &k in &order {
            if parents[k] < 0 {
                let r = root_pos(f);
                line.push_str(&format!("{:.6} {:.6} {:.6} ", r[0], r[1], r[2]));
            }
            let mut e = mat_to_euler(&local[k], ORDER);
            if let Some(prev) = previous[k] {
                e = euler_nearest(e, prev);
            }
            previous[k] = Some(e);
            line.push_str(&format!(
                "{:.6} {:.6} {:.6} ",
                e[0].to_degrees(),
                e[1].to_degrees(),
                e[2].to_degrees()
            ));
        }
        s.push_str(line.trim_end());
        s.push('\n');
    }
    write_atomic_bytes(path, s.as_bytes())
}

/// The Euler angles equal in rotation to `e` (order of three distinct axes) nearest to `prev`:
/// either of the two solutions, `(a, b, c)` or `(a + π, π − b, c + π)`, each angle shifted by whole
/// turns. Animation tools interpolate channels linearly, so a ±180° wrap between two keys would
/// spin the bone all the way round in between.
fn euler_nearest(e: [f64; 3], prev: [f64; 3]) -> [f64; 3] {
    use std::f64::consts::{PI, TAU};
    let near = |v: f64, p: f64| v - ((v - p) / TAU).round() * TAU;
    let dist = |a: [f64; 3]| (0..3).map(|i| (a[i] - prev[i]).abs()).sum::<f64>();
    let first = [0, 1, 2].map(|i| near(e[i], prev[i]));
    let alt = [e[0] + PI, PI - e[1], e[2] + PI];
    let second = [0, 1, 2].map(|i| near(alt[i], prev[i]));
    if dist(second) < dist(first) {
        second
    } else {
        first
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::AistppMotion;

    fn fixture(name: &str) -> std::path::PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../shared/fixtures/motion")
            .join(name)
    }

    #[test]
    fn cmu_bvh_reads_with_constant_bone_lengths() {
        let b = read_bvh(&fixture("cmu_01_01.bvh")).unwrap();
        assert_eq!(b.joints.shape()[0], 2752);
        assert!((b.fps - 120.0).abs() < 0.01, "{}", b.fps);
        assert_eq!(b.scale, CMU_UNIT_M);
        let mut worst = 0.0f32;
        for k in 1..b.names.len() {
            let p = b.parents[k] as usize;
            let len = |f: usize| {
                let d = [
                    b.joints[[f, k, 0]] - b.joints[[f, p, 0]],
                    b.joints[[f, k, 1]] - b.joints[[f, p, 1]],
                    b.joints[[f, k, 2]] - b.joints[[f, p, 2]],
                ];
                norm(d)
            };
            let l0 = len(0);
            for f in 0..b.joints.shape()[0] {
                worst = worst.max((len(f) - l0).abs());
            }
        }
        // Rotations in f32 of bones < 0.5 m: 1e-5 m.
        assert!(worst < 1e-5, "bone length varies by {worst} m");
        // A person: head well above the feet, 1.4-2 m tall in the first frame.
        let m = b.to_motion_file();
        let ys: Vec<f32> = (0..m.joints.shape()[1])
            .map(|k| m.joints[[0, k, 1]])
            .collect();
        let h = ys.iter().cloned().fold(f32::MIN, f32::max)
            - ys.iter().cloned().fold(f32::MAX, f32::min);
        assert!((1.3..2.1).contains(&h), "height {h}");
    }

    #[test]
    fn smpl_write_read_round_trip() {
        let a = AistppMotion::read(&fixture("aistpp_gBR_sBM_cAll_d04_mBR0_ch01.pkl")).unwrap();
        let j = a.joints();
        let m = MotionFile::from_joints(60.0, SkeletonKind::Smpl24, j.clone());
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("smpl.bvh");
        write_bvh_positions(&p, &m).unwrap();
        let back = read_bvh_scaled(&p, Some(1.0)).unwrap().to_motion_file();
        assert_eq!(back.skeleton, SkeletonKind::Smpl24);
        assert!((back.fps - 60.0).abs() < 1e-3);
        let d = back
            .joints
            .iter()
            .zip(j.iter())
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max);
        // 6-decimal text (1e-6 m) plus f32 chains: the requirement is 1e-4 m.
        assert!(d < 1e-4, "max joint error {d} m");
    }

    /// Every pair of consecutive frames of a BVH replaced by the average of their channels: what
    /// an animation tool plays half way between two keys.
    fn half_frames(text: &str) -> String {
        let (head, body) = text.split_at(text.find("Frame Time:").unwrap());
        let (time_line, body) = body.split_once('\n').unwrap();
        let frames: Vec<Vec<f64>> = body
            .lines()
            .map(|l| l.split_whitespace().map(|v| v.parse().unwrap()).collect())
            .collect();
        let mut out = head.replace(
            &format!("Frames: {}", frames.len()),
            &format!("Frames: {}", frames.len() - 1),
        );
        out.push_str(time_line);
        out.push('\n');
        for w in frames.windows(2) {
            let mid: Vec<String> = w[0]
                .iter()
                .zip(&w[1])
                .map(|(a, b)| format!("{:.6}", 0.5 * (a + b)))
                .collect();
            out.push_str(&mid.join(" "));
            out.push('\n');
        }
        out
    }

    fn max_abs_diff(a: &Array3<f32>, b: &Array3<f32>) -> f32 {
        assert_eq!(a.shape(), b.shape());
        a.iter()
            .zip(b.iter())
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max)
    }

    /// Write `joints` (SMPL-24, 60 fps) as BVH; return the joints read back at the keys and half
    /// way between them.
    fn keys_and_in_betweens(dir: &Path, joints: &Array3<f32>) -> (Array3<f32>, Array3<f32>) {
        let p = dir.join("keys.bvh");
        let m = MotionFile::from_joints(60.0, SkeletonKind::Smpl24, joints.clone());
        write_bvh_positions(&p, &m).unwrap();
        let q = dir.join("half.bvh");
        std::fs::write(&q, half_frames(&std::fs::read_to_string(&p).unwrap())).unwrap();
        let read = |p: &Path| {
            read_bvh_scaled(p, Some(1.0))
                .unwrap()
                .to_motion_file()
                .joints
        };
        (read(&p), read(&q))
    }

    #[test]
    fn in_between_frames_follow_the_motion() {
        let dir = tempfile::tempdir().unwrap();
        // The synthetic swinging dance, whose true in-between poses are known.
        let (j, _) = crate::kinematics::rigid::tests::swinging_motion(0.0);
        let (half, _) = crate::kinematics::rigid::tests::swinging_motion(0.5);
        let (keys, between) = keys_and_in_betweens(dir.path(), &j);
        // Rigid input is reproduced at the keys: 6-decimal text, and f32 rotation matrices whose
        // Euler angles lose ~1e-4 rad near gimbal lock (middle angle ±90°): 3e-4 m.
        let d = max_abs_diff(&keys, &j);
        assert!(d < 3e-4, "keys off by {d} m");
        let n = between.shape()[0];
        let d = max_abs_diff(&between, &half.slice(ndarray::s![..n, .., ..]).to_owned());
        // Measured 6.4 mm (true rotations written the same way: 0.9 mm). A twist flip puts hands
        // decimetres off (40 cm here without the twist step limit): 1 cm.
        assert!(d < 0.01, "in-between frames off by {d} m");
        // The AIST++ fixture: against the midpoint of the keys (itself off the true path by the
        // chord of one 60 fps frame). Measured 1.9 mm: 5 mm.
        let a = AistppMotion::read(&fixture("aistpp_gBR_sBM_cAll_d04_mBR0_ch01.pkl")).unwrap();
        let j = a.joints();
        let (_, between) = keys_and_in_betweens(dir.path(), &j);
        let n = between.shape()[0];
        let chord = (&j.slice(ndarray::s![..n, .., ..]) + &j.slice(ndarray::s![1.., .., ..])) * 0.5;
        let d = max_abs_diff(&between, &chord);
        assert!(d < 0.005, "fixture in-between frames off by {d} m");
    }

    #[test]
    fn aistpp_rotations_write_read_round_trip() {
        let a = AistppMotion::read(&fixture("aistpp_gBR_sBM_cAll_d04_mBR0_ch01.pkl")).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("rot.bvh");
        write_bvh_smpl(&p, &a).unwrap();
        let back = read_bvh_scaled(&p, Some(1.0)).unwrap().to_motion_file();
        assert_eq!(back.skeleton, SkeletonKind::Smpl24);
        let j = a.joints();
        let d = back
            .joints
            .iter()
            .zip(j.iter())
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max);
        assert!(d < 1e-4, "max joint error {d} m");
    }

    #[test]
    fn t2m_write_read_round_trip() {
        let a = AistppMotion::read(&fixture("aistpp_gBR_sBM_cAll_d04_mBR0_ch01.pkl")).unwrap();
        let j = crate::resample_joints(&a.joints(), 60.0, 20.0).unwrap();
        let f = crate::extract_features(
            j.slice(ndarray::s![.., ..22, ..]),
            &crate::FeatureOptions::default(),
        )
        .unwrap();
        let rec = f.recovered_joints().unwrap();
        let m = MotionFile::from_joints(20.0, SkeletonKind::T2m22, rec.clone());
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("t2m.bvh");
        write_bvh_positions(&p, &m).unwrap();
        let back = read_bvh_scaled(&p, Some(1.0)).unwrap().to_motion_file();
        assert_eq!(back.skeleton, SkeletonKind::T2m22);
        let d = back
            .joints
            .iter()
            .zip(rec.iter())
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max);
        assert!(d < 1e-4, "max joint error {d} m");
    }

    #[test]
    fn broken_files_give_line_numbers() {
        let dir = tempfile::tempdir().unwrap();
        let good = std::fs::read_to_string(fixture("cmu_01_01.bvh")).unwrap();
        let cases = [
            (
                "channels.bvh",
                good.replacen(
                    "CHANNELS 3 Zrotation Yrotation Xrotation",
                    "CHANNELS 3 Zrotation Yrotation",
                    1,
                ),
                "line",
            ),
            (
                "count.bvh",
                good.replacen("CHANNELS 6", "CHANNELS 9", 1),
                "channel count",
            ),
            (
                "brace.bvh",
                good.replacen("MOTION", "}\nMOTION", 1),
                "expected 'MOTION'",
            ),
            (
                "frames.bvh",
                good.replacen("Frames: 2752", "Frames: 2753", 1),
                "need",
            ),
            ("nan.bvh", good.replacen("9.3722", "nan", 1), "finite"),
            ("empty.bvh", String::new(), "ends unexpectedly"),
        ];
        for (name, text, want) in cases {
            let p = dir.path().join(name);
            std::fs::write(&p, text).unwrap();
            let e = read_bvh(&p).unwrap_err().to_string();
            assert!(e.contains(name) && e.contains(want), "{name}: {e}");
        }
    }

    #[test]
    fn frame_time_reads_back_as_the_exact_rate() {
        // Rates as written with 8 decimals (our writer), 7 (CMU), 6, and plain seconds.
        for (text, want) in [
            ("0.01666667", 60.0f64),
            ("0.0166667", 60.0),
            ("0.0083333", 120.0),
            ("0.03333333", 30.0),
            ("0.05", 20.0),
            ("0.03336667", 30000.0 / 1001.0),
            ("0.04170833", 24000.0 / 1001.0),
            ("1.6666667e-2", 60.0),
        ] {
            assert_eq!(fps_from_frame_time(text), Some(want as f32), "{text}");
        }
        // A rate no simple fraction explains stays as read.
        assert_eq!(
            fps_from_frame_time("0.0123456789"),
            Some((1.0 / 0.0123456789f64) as f32)
        );
        for bad in ["0", "-0.1", "nan", "inf", "x", "1e-320"] {
            assert_eq!(fps_from_frame_time(bad), None, "{bad}");
        }
        // A file written at 60 fps reads back at exactly 60, not 59.99999.
        let j = Array3::from_shape_fn((3, 22, 3), |(t, k, c)| (t + k + c) as f32 * 0.01);
        let dir = tempfile::tempdir().unwrap();
        for fps in [60.0f32, 30000.0 / 1001.0] {
            let p = dir.path().join("rate.bvh");
            write_bvh_positions(
                &p,
                &MotionFile::from_joints(fps, SkeletonKind::T2m22, j.clone()),
            )
            .unwrap();
            assert_eq!(read_bvh(&p).unwrap().fps, fps);
        }
    }

    #[test]
    fn joints_without_channels_cannot_inflate_the_output() {
        // 41 KB declaring 1,024 joints × 10^6 frames (12 GB of positions) with no numbers: joints
        // without channels need no input, so only the element cap stops the allocation.
        let mut text = String::from("HIERARCHY\nROOT r\n{\nOFFSET 0 0 0\nCHANNELS 0\n");
        for k in 1..1024 {
            text.push_str(&format!("JOINT j{k}\n{{\nOFFSET 0 1 0\nCHANNELS 0\n}}\n"));
        }
        text.push_str("}\nMOTION\nFrames: 1000000\nFrame Time: 0.01\n");
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("wide.bvh");
        std::fs::write(&p, text).unwrap();
        let e = read_bvh(&p).unwrap_err();
        assert!(matches!(e, Error::TooLarge { .. }), "{e}");
    }
}
