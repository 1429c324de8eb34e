//! A mannequin for any skeleton, made here (no third-party asset): one capsule per bone, each
//! bound rigidly to the bone's parent joint, in the skeleton's rest pose.
//!
//! Radii follow the body's shape without knowing joint names: bones along the spine (the path
//! from the root to the highest joint) are the torso, 11 cm, except the top two (neck and head
//! base), 5 cm; bones from a torso joint to a side branch (hip sockets, collars) 7.5 cm; limbs
//! 16 % of their length, between 3 and 6.5 cm. The highest joint gets a 10 cm head above it;
//! other leaves (hands, toes) a 6 cm stub along their bone. Bones shorter than 1 mm (joints
//! placed on their parent, as CMU's BVH has) get no capsule.

use crate::rotation::{Vec3, add, cross, norm, sub};

/// Triangles of one side, for colouring (left, right, centre).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Side {
    /// Joints the skeleton calls left.
    Left,
    /// Joints the skeleton calls right.
    Right,
    /// Everything else.
    Centre,
}

/// A skinned triangle mesh: every vertex bound to one joint with weight 1.
#[derive(Debug, Clone, Default)]
pub struct Mannequin {
    /// Rest-pose vertex positions, metres.
    pub positions: Vec<Vec3>,
    /// Unit normals.
    pub normals: Vec<Vec3>,
    /// The joint each vertex follows.
    pub joints: Vec<u16>,
    /// Triangle vertex indices of the left, right and centre parts.
    pub triangles: [Vec<u32>; 3],
}

/// Segments around a capsule, and rings per hemisphere.
const AROUND: usize = 12;
const RINGS: usize = 3;

/// Build the mannequin for a skeleton in its rest pose: joint positions `rest`, parents, and
/// each joint's side.
pub fn mannequin(rest: &[Vec3], parents: &[i32], side: impl Fn(usize) -> Side) -> Mannequin {
    let n = parents.len();
    let children = crate::kinematics::rigid::children_of(parents);
    // The spine: the path from the root to the highest joint.
    let top = (0..n)
        .max_by(|&a, &b| rest[a][1].total_cmp(&rest[b][1]))
        .unwrap_or(0);
    let mut spine = vec![false; n];
    let mut depth_from_top = vec![usize::MAX; n];
    let (mut k, mut d) = (top as i32, 0);
    while k >= 0 {
        spine[k as usize] = true;
        depth_from_top[k as usize] = d;
        d += 1;
        k = parents[k as usize];
    }
    let mut out = Mannequin::default();
    for (k, &p) in parents.iter().enumerate() {
        if p < 0 {
            continue;
        }
        let p = p as usize;
        let length = norm(sub(rest[k], rest[p]));
        let radius = if spine[k] {
            if depth_from_top[k] < 2 { 0.05 } else { 0.11 }
        } else if spine[p] {
            0.075
        } else {
            (0.16 * length).clamp(0.03, 0.065)
        };
        let bone_side = side(k);
        if length > 1e-3 {
            out.capsule(rest[p], rest[k], radius, p, bone_side);
        }
        if children[k].is_empty() && length > 1e-3 {
            let dir = sub(rest[k], rest[p]);
            let (tip, r) = if k == top {
                ([rest[k][0], rest[k][1] + 0.12, rest[k][2]], 0.1)
            } else {
                (add(rest[k], scale(dir, 0.06 / length)), radius * 0.9)
            };
            out.capsule(rest[k], tip, r, k, bone_side);
        }
    }
    out
}

fn scale(v: Vec3, s: f32) -> Vec3 {
    [v[0] * s, v[1] * s, v[2] * s]
}

fn unit(v: Vec3) -> Vec3 {
    scale(v, 1.0 / norm(v))
}

impl Mannequin {
    /// A capsule from `a` to `b` of `radius`, bound to `joint`: two hemispheres of `RINGS`
    /// rings joined by the cylinder between their equators, and one vertex at each pole.
    fn capsule(&mut self, a: Vec3, b: Vec3, radius: f32, joint: usize, side: Side) {
        let axis = unit(sub(b, a));
        // Any direction not along the axis gives the ring's plane.
        let seed = if axis[0].abs() < 0.9 {
            [1.0, 0.0, 0.0]
        } else {
            [0.0, 1.0, 0.0]
        };
        let u = unit(cross(axis, seed));
        let v = cross(axis, u);
        let first = self.positions.len() as u32;
        let mut push = |centre: Vec3, normal: Vec3| {
            self.positions.push(add(centre, scale(normal, radius)));
            self.normals.push(normal);
            self.joints.push(joint as u16);
        };
        push(a, scale(axis, -1.0));
        // Latitudes from the bottom pole (exclusive) to the top pole (exclusive); the two
        // equators are separate rings around `a` and `b`.
        let step = std::f32::consts::FRAC_PI_2 / RINGS as f32;
        let below = (1..=RINGS).map(|i| (a, -std::f32::consts::FRAC_PI_2 + step * i as f32));
        let above = (0..RINGS).map(|i| (b, step * i as f32));
        for (centre, lat) in below.chain(above) {
            {
                for s in 0..AROUND {
                    let t = std::f32::consts::TAU * s as f32 / AROUND as f32;
                    let radial = add(scale(u, t.cos()), scale(v, t.sin()));
                    let normal = add(scale(radial, lat.cos()), scale(axis, lat.sin()));
                    push(centre, normal);
                }
            }
        }
        push(b, axis);
        let rings = 2 * RINGS;
        let ring = |r: usize, s: usize| first + 1 + (r * AROUND + s % AROUND) as u32;
        let last = first + 1 + (rings * AROUND) as u32;
        let tris = &mut self.triangles[side as usize];
        for s in 0..AROUND {
            // Counter-clockwise seen from outside.
            tris.extend([first, ring(0, s + 1), ring(0, s)]);
            for r in 0..rings - 1 {
                tris.extend([ring(r, s), ring(r, s + 1), ring(r + 1, s + 1)]);
                tris.extend([ring(r, s), ring(r + 1, s + 1), ring(r + 1, s)]);
            }
            tris.extend([last, ring(rings - 1, s), ring(rings - 1, s + 1)]);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rotation::dot;

    /// Signed volume of a closed triangle mesh (divergence theorem): positive when every
    /// triangle faces outward.
    fn volume(m: &Mannequin, tris: &[u32]) -> f32 {
        tris.chunks(3)
            .map(|t| {
                let [a, b, c] = [0, 1, 2].map(|i| m.positions[t[i] as usize]);
                dot(a, cross(b, c)) / 6.0
            })
            .sum()
    }

    #[test]
    fn a_capsule_is_closed_faces_outward_and_has_the_capsule_volume() {
        let mut m = Mannequin::default();
        let (r, l) = (0.05f32, 0.3f32);
        m.capsule([0.1, 0.2, 0.3], [0.1, 0.2 + l, 0.3], r, 4, Side::Left);
        let tris = &m.triangles[Side::Left as usize];
        // Closed: every edge is used once in each direction.
        let mut edges = std::collections::HashMap::new();
        for t in tris.chunks(3) {
            for i in 0..3 {
                *edges.entry((t[i], t[(i + 1) % 3])).or_insert(0) += 1;
            }
        }
        for (&(a, b), &count) in &edges {
            assert_eq!(count, 1);
            assert_eq!(edges.get(&(b, a)), Some(&1), "edge {a}-{b} has no twin");
        }
        // A polygonal capsule is inside the true one: its volume is within 10 % below
        // pi r^2 l + 4/3 pi r^3 (12 segments keep 95.5 % of a circle's area).
        let exact = std::f32::consts::PI * r * r * (l + 4.0 / 3.0 * r);
        let v = volume(&m, tris);
        assert!(v < exact && v > 0.9 * exact, "volume {v} vs {exact}");
        assert!(m.joints.iter().all(|&j| j == 4));
        for (p, n) in m.positions.iter().zip(&m.normals) {
            assert!((norm(*n) - 1.0).abs() < 1e-5);
            // Every vertex lies at the radius from the axis segment.
            let y = p[1].clamp(0.2, 0.2 + l);
            let d = norm(sub(*p, [0.1, y, 0.3]));
            assert!((d - r).abs() < 1e-5, "{p:?}");
        }
    }

    #[test]
    fn the_smpl_mannequin_covers_every_bone_and_colours_its_sides() {
        let parents = crate::skeleton::SMPL24_PARENTS;
        let rest = crate::render::gltf::rest_positions(
            &parents,
            &crate::skeleton::SMPL24_OFFSETS,
            [0.0; 3],
        );
        let kind = crate::SkeletonKind::Smpl24;
        let m = mannequin(&rest, &parents, |j| {
            if kind.is_left(j) {
                Side::Left
            } else if kind.is_right(j) {
                Side::Right
            } else {
                Side::Centre
            }
        });
        // 23 bones + the head and 4 leaf stubs (hands, toes).
        let per_capsule = 2 + 2 * RINGS * AROUND;
        assert_eq!(m.positions.len(), 28 * per_capsule);
        // Left triangles are bound to left joints or the torso joints their bones start at.
        for t in &m.triangles[Side::Left as usize] {
            let j = m.joints[*t as usize] as usize;
            assert!(kind.is_left(j) || [0, 9].contains(&j), "joint {j}");
        }
        let total: f32 = (0..3).map(|s| volume(&m, &m.triangles[s])).sum();
        // A body of 60-110 litres would be a person; capsules overlap, so this counts some
        // volume twice: the bound is loose on purpose, it catches inside-out or missing parts.
        assert!((0.03..0.12).contains(&total), "volume {total} m^3");
    }
}
