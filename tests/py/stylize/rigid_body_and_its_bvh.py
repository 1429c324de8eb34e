"""A stylized motion is one rigid body and the BVH stylize wrote of it is its joints.

Args: the stylized .h5 and its BVH. `bvh_joints` is FK of a BVH in numpy, read from the format's
definition (not choreod's reader): each joint's rotation is the product of its rotation channels
in the order listed, a child sits at its parent's position plus the parent's global rotation times
its OFFSET; the root adds its position channels.
"""
import numpy as np
def _axis(a, deg):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    i = "XYZ".index(a)
    m = np.eye(3)
    j, k = (i + 1) % 3, (i + 2) % 3
    m[j, j], m[j, k], m[k, j], m[k, k] = c, -s, s, c
    return m
def bvh_joints(path):
    words = open(path).read().split()
    names, parents, offsets, channels, stack, i = [], [], [], [], [], 0
    while words[i] != "MOTION":
        w = words[i]
        if w in ("ROOT", "JOINT"):
            names.append(words[i + 1]); parents.append(stack[-1] if stack else -1)
            stack.append(len(names) - 1); i += 2
        elif w == "End":
            stack.append(None); i += 2
        elif w == "OFFSET":
            if stack[-1] is not None:
                offsets.append([float(x) for x in words[i + 1:i + 4]])
            i += 4
        elif w == "CHANNELS":
            n = int(words[i + 1]); channels.append(words[i + 2:i + 2 + n]); i += 2 + n
        elif w == "}":
            stack.pop(); i += 1
        else:
            i += 1
    frames = int(words[i + 2])
    values = np.array(words[i + 6:], dtype=np.float64).reshape(frames, -1)
    out = np.zeros((frames, len(names), 3))
    for f in range(frames):
        col, rot = 0, [None] * len(names)
        for k, chans in enumerate(channels):
            r, pos = np.eye(3), np.array(offsets[k], dtype=np.float64)
            for c in chans:
                v = values[f, col]; col += 1
                if c.endswith("position"):
                    pos["XYZ".index(c[0])] = v
                else:
                    r = r @ _axis(c[0], v)
            p = parents[k]
            rot[k] = r if p < 0 else rot[p] @ r
            out[f, k] = pos if p < 0 else out[f, p] + rot[p] @ offsets[k]
    return names, out

import sys, h5py
with h5py.File(sys.argv[1], "r") as f:
    j = f["motion/joints"][:].astype(np.float64)
    names = [str(n) for n in f["motion"].attrs["joint_names"]]
    parents = list(f["motion"].attrs["parents"])
lengths = np.linalg.norm(j[:, 1:] - j[:, parents[1:]], axis=-1)
spread = (lengths.max(0) - lengths.min(0)).max()
bnames, b = bvh_joints(sys.argv[2])
order = [bnames.index(n) for n in names]
gap = np.linalg.norm(b[:, order] - j, axis=-1).max()
# Lengths: float32 positions of metre scale carry ~1e-7 m; 1e-4 m is the bound (the old
# output spread by ~9 cm). BVH: 6 decimals of degrees and metres, 1 mm.
assert spread < 1e-4 and gap < 1e-3, (spread, gap)
print(f"ok bone length spread {spread:.1e} m, BVH vs h5 {gap:.1e} m")
