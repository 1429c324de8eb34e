#!/usr/bin/env python3
"""Synthetic AIST++ / HumanML3D datasets in the official layouts, for `choreod prep` tests and
the benchmark. Made from the one real AIST++ motion fixture (with variations: heading rotation,
translation, pose noise, forward/backward tiling to other lengths, crops) and the fixture music.

  prep_synthetic.py aistpp ROOT --pkl FIXTURE.pkl --audio-dir DIR [--count N] [--min-s A --max-s B]
                    [--corrupt] [--music-ids K] [--seed S]
  prep_synthetic.py humanml3d ROOT --smpl-joints J.npy [--count N] [--corrupt] [--seed S]

`--smpl-joints` is the fixture's SMPL joints (T, 24, 3) at 60 fps (`choreod convert X.pkl -o J.npy`);
its first 22 joints are the t2m skeleton (HumanML3D paramUtil.py: t2m = SMPL joints 0..21).
With `--corrupt` a handful of bad members is added, named so tests can find them:
truncated / wrong-type files, NaN, too short, missing or undecodable music, ignored, in no split.
Deterministic for a given seed.
"""
import argparse
import os
import pickle
import subprocess
import sys

import numpy as np

GENRES = ["BR", "PO", "LO", "MH", "LH", "HO", "WA", "KR", "JS", "JB"]


def aa_to_mat(aa):
    th = np.linalg.norm(aa, axis=-1, keepdims=True)
    k = aa / np.maximum(th, 1e-12)
    kx, ky, kz = k[..., 0], k[..., 1], k[..., 2]
    z = np.zeros_like(kx)
    K = np.stack([z, -kz, ky, kz, z, -kx, -ky, kx, z], -1).reshape(aa.shape[:-1] + (3, 3))
    th = th[..., None]
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * (K @ K)


def mat_to_aa(R):
    cos = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1) / 2, -1, 1)
    th = np.arccos(cos)
    v = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    s = np.sin(th)[..., None]
    return np.where(s > 1e-6, v / np.maximum(2 * s, 1e-12) * th[..., None], v / 2)


def roty(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def tile(x, n):
    """Forward, backward, forward ... (continuous at the joins) to n frames."""
    parts, k = [], 0
    while sum(len(p) for p in parts) < n:
        parts.append(x if k % 2 == 0 else x[::-1])
        k += 1
    return np.concatenate(parts)[:n]


def aistpp(a):
    rng = np.random.default_rng(a.seed)
    with open(a.pkl, "rb") as f:
        base = pickle.load(f)
    poses = base["smpl_poses"].reshape(-1, 24, 3).astype(np.float64)
    trans = base["smpl_trans"].astype(np.float64)
    scale = float(np.asarray(base["smpl_scaling"]).reshape(-1)[0])
    os.makedirs(os.path.join(a.root, "motions"), exist_ok=True)
    os.makedirs(os.path.join(a.root, "splits"), exist_ok=True)
    os.makedirs(os.path.join(a.root, "music"), exist_ok=True)
    music_ids = [f"m{GENRES[i % 10]}{i // 10 % 6}" for i in range(a.music_ids)]
    names = []
    for i in range(a.count):
        mid = music_ids[i % len(music_ids)]
        names.append(f"g{mid[1:3]}_sBM_cAll_d{i % 30 + 1:02d}_{mid}_ch{i:04d}")

    def write(name, p, t, nan=False):
        obj = {"smpl_loss": 0.0, "smpl_poses": p.reshape(len(p), 72).astype(np.float32),
               "smpl_scaling": np.array([scale], np.float32), "smpl_trans": t.astype(np.float32)}
        if nan:
            obj["smpl_poses"][len(p) // 2, 5] = np.nan
        with open(os.path.join(a.root, "motions", name + ".pkl"), "wb") as f:
            pickle.dump(obj, f, protocol=4)

    for name in names:
        n = int(rng.uniform(a.min_s, a.max_s) * 60)
        off = int(rng.integers(0, len(poses)))
        p = tile(np.roll(poses, -off, axis=0), n) + rng.normal(0, 0.01, (n, 24, 3))
        t = tile(np.roll(trans, -off, axis=0), n)
        R = roty(rng.uniform(-np.pi, np.pi))
        p[:, 0] = mat_to_aa(R @ aa_to_mat(p[:, 0]))
        t = (t - t[0]) @ R.T + t[0] + np.array([rng.uniform(-50, 50), 0, rng.uniform(-50, 50)])
        write(name, p, t)

    split = {"train": names[: int(len(names) * 0.8)], "val": names[int(len(names) * 0.8): int(len(names) * 0.9)],
             "test": names[int(len(names) * 0.9):]}
    ignore = []
    if a.corrupt:
        bad = {
            "gBR_sBM_cAll_d01_mBR0_ch9001": "truncated",
            "gBR_sBM_cAll_d01_mBR0_ch9002": "nan",
            "gBR_sBM_cAll_d01_mBR0_ch9003": "short",
            "gBR_sBM_cAll_d01_mBR5_ch9004": "nomusic",
            "gBR_sBM_cAll_d01_mBR0_ch9005": "ignored",
            "gBR_sBM_cAll_d01_mBR0_ch9006": "nosplit",
            "gBR_sBM_cAll_d01_mBR0_ch9007": "wrongtype",
            "gKR_sBM_cAll_d01_mKR5_ch9008": "badmusic",
        }
        for name, kind in bad.items():
            if kind == "truncated":
                write(name, poses, trans)
                path = os.path.join(a.root, "motions", name + ".pkl")
                data = open(path, "rb").read()
                open(path, "wb").write(data[: len(data) // 2])
            elif kind == "wrongtype":
                with open(os.path.join(a.root, "motions", name + ".pkl"), "wb") as f:
                    pickle.dump([1, 2, 3], f, protocol=4)
            else:
                n = 120 if kind == "short" else len(poses)
                write(name, poses[:n], trans[:n], nan=(kind == "nan"))
            if kind == "badmusic":
                with open(os.path.join(a.root, "music", "mKR5.wav"), "wb") as f:
                    f.write(b"RIFF\x10\x00\x00\x00WAVEjunk" + bytes(64))  # a WAV header and no audio
            if kind == "ignored":
                ignore.append(name)
            if kind != "nosplit":
                split["train"].append(name)
    for s, lst in split.items():
        with open(os.path.join(a.root, "splits", f"crossmodal_{s}.txt"), "w") as f:
            f.write("\n".join(sorted(lst)) + "\n")
    with open(os.path.join(a.root, "ignore_list.txt"), "w") as f:
        f.write("\n".join(ignore) + "\n")
    oggs = sorted(os.path.join(a.audio_dir, x) for x in os.listdir(a.audio_dir) if x.endswith(".ogg"))
    for k, mid in enumerate(music_ids):
        out = os.path.join(a.root, "music", mid + ".wav")
        if not os.path.exists(out):
            subprocess.run(["ffmpeg", "-v", "error", "-y", "-i", oggs[k % len(oggs)], "-ac", "1", "-ar", "22050",
                            out], check=True)
    print(f"aistpp: {len(names)} sequences, {len(music_ids)} music ids -> {a.root}")


def humanml3d(a):
    rng = np.random.default_rng(a.seed)
    j60 = np.load(a.smpl_joints)[:, :22].astype(np.float64)
    j20 = j60[::3]  # 60 -> 20 fps, raw_pose_processing.ipynb `int(fps / 20)` stride
    jd = os.path.join(a.root, "new_joints")
    td = os.path.join(a.root, "texts")
    os.makedirs(jd, exist_ok=True)
    os.makedirs(td, exist_ok=True)
    ids = [f"{i:06d}" for i in range(a.count)]
    for i in ids:
        n = int(rng.uniform(a.min_s, a.max_s) * 20)
        off = int(rng.integers(0, len(j20)))
        x = tile(np.roll(j20, -off, axis=0), n)
        R = roty(rng.uniform(-np.pi, np.pi))
        x = (x - x[:1, :1]) @ R.T + np.array([rng.uniform(-2, 2), 0, rng.uniform(-2, 2)]) + x[:1, :1] * [0, 1, 0]
        np.save(os.path.join(jd, i + ".npy"), x.astype(np.float32))
        with open(os.path.join(td, i + ".txt"), "w") as f:
            f.write("a person raises the left hand#a/DET person/NOUN raise/VERB the/DET left/ADJ hand/NOUN#0.0#0.0\n")
            f.write(f"someone dances then turns right#someone/PRON dance/VERB then/ADV turn/VERB right/ADV#0.0#{n / 40:.1f}\n")
    split = {"train": ids[: int(len(ids) * 0.8)], "val": ids[int(len(ids) * 0.8): int(len(ids) * 0.9)],
             "test": ids[int(len(ids) * 0.9):]}
    if a.corrupt:
        bad = ["900001", "900002", "900003", "900004", "900005", "900006"]
        np.save(os.path.join(jd, "900001.npy"), j20[:100].astype(np.float32))
        p = os.path.join(jd, "900001.npy")
        data = open(p, "rb").read()
        open(p, "wb").write(data[: len(data) // 2])  # truncated
        x = j20[:100].astype(np.float32).copy()
        x[50, 3, 1] = np.nan
        np.save(os.path.join(jd, "900002.npy"), x)  # NaN
        np.save(os.path.join(jd, "900003.npy"), j20[:20].astype(np.float32))  # too short
        np.save(os.path.join(jd, "900004.npy"), np.zeros((100, 10, 3), np.float32))  # wrong shape
        np.save(os.path.join(jd, "900005.npy"), j20[:100].astype(np.float32))  # no caption file
        np.save(os.path.join(jd, "900006.npy"), j20[:100].astype(np.float32))  # in no split
        split["train"] += bad[:5]
        # Listed with no motion file (a skip), and an M id that --mirror makes from 000000.
        split["train"] += ["900007", "M000000"]
    for s, lst in split.items():
        with open(os.path.join(a.root, f"{s}.txt"), "w") as f:
            f.write("\n".join(sorted(lst)) + "\n")
    print(f"humanml3d: {len(ids)} sequences -> {a.root}")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("kind", choices=["aistpp", "humanml3d"])
    ap.add_argument("root")
    ap.add_argument("--pkl")
    ap.add_argument("--audio-dir")
    ap.add_argument("--smpl-joints")
    ap.add_argument("--count", type=int, default=30)
    ap.add_argument("--music-ids", type=int, default=6)
    ap.add_argument("--min-s", type=float, default=None)
    ap.add_argument("--max-s", type=float, default=None)
    ap.add_argument("--corrupt", action="store_true")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    if a.kind == "aistpp":
        a.min_s = 6.0 if a.min_s is None else a.min_s
        a.max_s = 14.0 if a.max_s is None else a.max_s
        if not (a.pkl and a.audio_dir):
            sys.exit("aistpp needs --pkl and --audio-dir")
        aistpp(a)
    else:
        a.min_s = 2.0 if a.min_s is None else a.min_s
        a.max_s = 10.0 if a.max_s is None else a.max_s
        if not a.smpl_joints:
            sys.exit("humanml3d needs --smpl-joints")
        humanml3d(a)


if __name__ == "__main__":
    main()
