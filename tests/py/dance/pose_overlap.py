"""Pose overlap between two dances (issue 24's measure), and their provenance's `library` line.

Share of dance A's frames whose nearest pose in dance B is within 3 cm mean joint distance,
root-relative and facing-aligned (each frame turned about y so its hips' left-to-right axis is
+x). Prints one JSON line: {"overlap": ..., "library_a": ..., "library_b": ..., "frames": [a, b]}.
"""
import json, sys, h5py, numpy as np


def poses(path):
    with h5py.File(path, "r") as f:
        j = f["motion/joints"][...].astype(np.float64)
        lib = f["provenance"].attrs.get("library") if "provenance" in f else None
    j = j - j[:, :1]
    across = j[:, 1] - j[:, 2]  # SMPL: left hip (1) minus right hip (2)
    a = np.arctan2(across[:, 2], across[:, 0])  # turn by -a about y puts it on +x
    c, s = np.cos(a)[:, None], np.sin(a)[:, None]
    x, z = j[..., 0], j[..., 2]
    j = np.stack([c * x + s * z, j[..., 1], -s * x + c * z], axis=-1)
    if isinstance(lib, bytes):
        lib = lib.decode()
    return j, lib


a, lib_a = poses(sys.argv[1])
b, lib_b = poses(sys.argv[2])
near = np.empty(a.shape[0])
for i in range(0, a.shape[0], 256):
    d = np.linalg.norm(a[i:i + 256, None] - b[None], axis=-1).mean(axis=-1)
    near[i:i + 256] = d.min(axis=1)
print(json.dumps({"overlap": float((near < 0.03).mean()), "library_a": lib_a, "library_b": lib_b,
                  "frames": [a.shape[0], b.shape[0]]}))
