"""Straightforward numpy port of HumanML3D's feature extraction (benchmarking only).

Follows EricGuo5513/HumanML3D motion_representation.ipynb `process_file` step by step, with
common/skeleton.py (inverse/forward kinematics) and common/quaternion.py rewritten in numpy
(the originals go through torch, which is not installable here). Used by scripts/bench-features
to (1) time the reference pipeline and (2) check the Rust features against it.

usage: features_numpy.py JOINTS.npy TARGET_OFFSETS.npy RUST_FEATURES.npy SEQS FRAMES WORKERS
"""
import json
import sys
import time
from multiprocessing import Pool

import numpy as np
from scipy.ndimage import gaussian_filter1d

# paramUtil.py
T2M_RAW_OFFSETS = np.array([
    [0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, -1, 0], [0, 1, 0], [0, -1, 0],
    [0, -1, 0], [0, 1, 0], [0, 0, 1], [0, 0, 1], [0, 1, 0], [1, 0, 0], [-1, 0, 0], [0, 0, 1],
    [0, -1, 0], [0, -1, 0], [0, -1, 0], [0, -1, 0], [0, -1, 0], [0, -1, 0]], dtype=np.float32)
CHAIN = [[0, 2, 5, 8, 11], [0, 1, 4, 7, 10], [0, 3, 6, 9, 12, 15], [9, 14, 17, 19, 21], [9, 13, 16, 18, 20]]
PARENTS = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19]
L_IDX1, L_IDX2 = 5, 8
FID_R, FID_L = [8, 11], [7, 10]
FACE = [2, 1, 17, 16]


def qinv(q):
    return q * np.array([1, -1, -1, -1], dtype=q.dtype)


def qmul(q, r):
    w = r[..., 0] * q[..., 0] - r[..., 1] * q[..., 1] - r[..., 2] * q[..., 2] - r[..., 3] * q[..., 3]
    x = r[..., 0] * q[..., 1] + r[..., 1] * q[..., 0] - r[..., 2] * q[..., 3] + r[..., 3] * q[..., 2]
    y = r[..., 0] * q[..., 2] + r[..., 1] * q[..., 3] + r[..., 2] * q[..., 0] - r[..., 3] * q[..., 1]
    z = r[..., 0] * q[..., 3] - r[..., 1] * q[..., 2] + r[..., 2] * q[..., 1] + r[..., 3] * q[..., 0]
    return np.stack((w, x, y, z), axis=-1)


def qrot(q, v):
    qvec = q[..., 1:]
    uv = np.cross(qvec, v)
    uuv = np.cross(qvec, uv)
    return v + 2 * (q[..., :1] * uv + uuv)


def qbetween(v0, v1):
    v = np.cross(v0, v1)
    w = np.sqrt((v0 ** 2).sum(-1, keepdims=True) * (v1 ** 2).sum(-1, keepdims=True)) + (v0 * v1).sum(-1, keepdims=True)
    q = np.concatenate([w, v], -1)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def quat_to_cont6d(q):
    r, i, j, k = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    two_s = 2.0 / (q * q).sum(-1)
    m = np.stack((1 - two_s * (j * j + k * k), two_s * (i * j - k * r), two_s * (i * k + j * r),
                  two_s * (i * j + k * r), 1 - two_s * (i * i + k * k), two_s * (j * k - i * r),
                  two_s * (i * k - j * r), two_s * (j * k + i * r), 1 - two_s * (i * i + j * j)), -1)
    m = m.reshape(q.shape[:-1] + (3, 3))
    return np.concatenate([m[..., 0], m[..., 1]], axis=-1)


def offsets_of(joints0):
    off = T2M_RAW_OFFSETS.copy()
    for i in range(1, 22):
        off[i] = np.linalg.norm(joints0[i] - joints0[PARENTS[i]]) * off[i]
    return off


def inverse_kinematics(joints, smooth_forward=False):
    l_hip, r_hip, sdr_r, sdr_l = FACE
    across = (joints[:, r_hip] - joints[:, l_hip]) + (joints[:, sdr_r] - joints[:, sdr_l])
    across = across / np.sqrt((across ** 2).sum(-1))[:, None]
    forward = np.cross(np.array([[0, 1, 0]]), across, axis=-1)
    if smooth_forward:
        forward = gaussian_filter1d(forward, 20, axis=0, mode="nearest")
    forward = forward / np.sqrt((forward ** 2).sum(-1))[..., None]
    root_quat = qbetween(forward, np.array([[0, 0, 1]]).repeat(len(forward), 0))
    root_quat[0] = np.array([1.0, 0.0, 0.0, 0.0])  # skeleton.py inverse_kinematics_np
    quat = np.zeros(joints.shape[:-1] + (4,))
    quat[:, 0] = root_quat
    for chain in CHAIN:
        R = root_quat
        for j in range(len(chain) - 1):
            u = T2M_RAW_OFFSETS[chain[j + 1]][None].repeat(len(joints), 0)
            v = joints[:, chain[j + 1]] - joints[:, chain[j]]
            v = v / np.sqrt((v ** 2).sum(-1))[:, None]
            R_loc = qmul(qinv(R), qbetween(u, v))
            quat[:, chain[j + 1]] = R_loc
            R = qmul(R, R_loc)
    return quat


def forward_kinematics(quat, root_pos, offsets):
    joints = np.zeros(quat.shape[:-1] + (3,))
    joints[:, 0] = root_pos
    for chain in CHAIN:
        R = quat[:, 0]
        for i in range(1, len(chain)):
            R = qmul(R, quat[:, chain[i]])
            joints[:, chain[i]] = qrot(R, offsets[None, chain[i]].repeat(len(quat), 0)) + joints[:, chain[i - 1]]
    return joints


def process_file(positions, tgt_offsets, feet_thre=0.002):
    # uniform skeleton
    src = offsets_of(positions[0])
    scale = (np.abs(tgt_offsets[L_IDX1]).max() + np.abs(tgt_offsets[L_IDX2]).max()) / (
        np.abs(src[L_IDX1]).max() + np.abs(src[L_IDX2]).max())
    quat = inverse_kinematics(positions)
    positions = forward_kinematics(quat, positions[:, 0] * scale, tgt_offsets)
    # floor, XZ origin
    positions[:, :, 1] -= positions.min(axis=0).min(axis=0)[1]
    root_pos_init = positions[0]
    positions = positions - root_pos_init[0] * np.array([1, 0, 1])
    # face Z+
    r_hip, l_hip, sdr_r, sdr_l = FACE
    across = (root_pos_init[r_hip] - root_pos_init[l_hip]) + (root_pos_init[sdr_r] - root_pos_init[sdr_l])
    across = across / np.sqrt((across ** 2).sum(-1))
    forward_init = np.cross(np.array([[0, 1, 0]]), across, axis=-1)
    forward_init = forward_init / np.sqrt((forward_init ** 2).sum(-1))[..., None]
    root_quat_init = qbetween(forward_init, np.array([[0, 0, 1]]))
    root_quat_init = np.ones(positions.shape[:-1] + (4,)) * root_quat_init
    positions = qrot(root_quat_init, positions)
    global_positions = positions.copy()
    # foot contacts
    feet_l = (((positions[1:, FID_L] - positions[:-1, FID_L]) ** 2).sum(-1) < feet_thre).astype(np.float32)
    feet_r = (((positions[1:, FID_R] - positions[:-1, FID_R]) ** 2).sum(-1) < feet_thre).astype(np.float32)
    # rotations (smoothed facing)
    quat = inverse_kinematics(positions, smooth_forward=True)
    cont6d = quat_to_cont6d(quat)
    r_rot = quat[:, 0].copy()
    velocity = qrot(r_rot[1:], positions[1:, 0] - positions[:-1, 0])
    r_velocity = qmul(r_rot[1:], qinv(r_rot[:-1]))
    # rifke
    positions[..., 0] -= positions[:, 0:1, 0]
    positions[..., 2] -= positions[:, 0:1, 2]
    positions = qrot(np.repeat(r_rot[:, None], positions.shape[1], axis=1), positions)
    root_y = positions[:, 0, 1:2]
    r_velocity = np.arcsin(r_velocity[:, 2:3])
    l_velocity = velocity[:, [0, 2]]
    root_data = np.concatenate([r_velocity, l_velocity, root_y[:-1]], axis=-1)
    rot_data = cont6d[:, 1:].reshape(len(cont6d), -1)
    ric_data = positions[:, 1:].reshape(len(positions), -1)
    local_vel = qrot(np.repeat(r_rot[:-1, None], global_positions.shape[1], axis=1),
                     global_positions[1:] - global_positions[:-1]).reshape(len(global_positions) - 1, -1)
    return np.concatenate([root_data, ric_data[:-1], rot_data[:-1], local_vel, feet_l, feet_r], axis=-1)


def windows(joints, n_seqs, frames):
    starts = max(1, len(joints) - frames + 1)
    return [joints[i % starts:i % starts + frames] for i in range(n_seqs)]


def work(args):
    path, tgt_path, n_seqs, frames = args
    joints = np.load(path).astype(np.float64)
    tgt = np.load(tgt_path).astype(np.float64)
    for w in windows(joints, n_seqs, frames):
        process_file(w.copy(), tgt)
    return n_seqs


def main():
    path, tgt_path, rust_path, n_seqs, frames, workers = sys.argv[1:7]
    n_seqs, frames, workers = int(n_seqs), int(frames), int(workers)
    joints = np.load(path).astype(np.float64)
    tgt = np.load(tgt_path).astype(np.float64)
    ours = process_file(joints[:frames].copy(), tgt)
    rust = np.load(rust_path)
    diff = np.abs(ours - rust)
    t0 = time.perf_counter()
    per = n_seqs // workers
    with Pool(workers) as pool:
        done = sum(pool.map(work, [(path, tgt_path, per, frames)] * workers))
    dt = time.perf_counter() - t0
    print(json.dumps({"python_seqs_per_s": done / dt, "seqs": done, "seconds": dt,
                      "max_abs_diff_vs_rust": float(diff.max()),
                      "max_abs_diff_excluding_contacts": float(diff[:, :259].max()),
                      "contact_mismatches": int((diff[:, 259:] > 0.5).sum())}))


if __name__ == "__main__":
    main()
