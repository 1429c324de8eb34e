#!/usr/bin/env python3
"""Single-process numpy/librosa port of `choreod prep` (benchmarking only): the same steps per
sequence, on a subset, timed; optionally compared with the Rust shards.

  prep_numpy.py aistpp ROOT RUST_OUT N        first N candidate sequences (sorted, as the plan)
  prep_numpy.py humanml3d ROOT RUST_OUT N

AIST++ per sequence: pickle load, SMPL FK (EDGE vis.py recursion, rest offsets parsed from
datasets/src/skeleton.rs), 60 -> 30 fps, music per id (librosa load at 16 kHz, melspectrogram
n_fft 2048 hop 512 80 bands fmax 8000, power_to_db top_db 80, onset_strength, beat_track with the
tempo prior from the name, tightness 100), np.interp to the 30 fps frame times, h5py write.
HumanML3D per sequence: np.load, [:, :22], NaN check, `process_file` of
datasets/bench/features_numpy.py (the notebook's steps), captions, f64 sums, h5py write.
Prints one JSON line with per-sequence and per-track times.
"""
import json
import os
import pickle
import re
import sys
import tempfile
import time

import h5py
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
WS = os.path.dirname(os.path.dirname(HERE))


def smpl_tables():
    src = open(os.path.join(WS, "datasets/src/skeleton.rs")).read()
    par = re.search(r"SMPL24_PARENTS: \[i32; 24\] = \[(.*?)\];", src, re.S).group(1)
    off = re.search(r"SMPL24_OFFSETS: \[Vec3; 24\] = \[(.*?)\n\];", src, re.S).group(1)
    parents = [int(x) for x in par.replace("\n", " ").split(",") if x.strip()]
    rows = re.findall(r"\[([-0-9.e, ]+)\]", off)
    return parents, np.array([[float(v) for v in r.split(",")] for r in rows])


def rodrigues(aa):
    th = np.linalg.norm(aa, axis=-1, keepdims=True)
    k = aa / np.maximum(th, 1e-12)
    kx, ky, kz = k[..., 0], k[..., 1], k[..., 2]
    z = np.zeros_like(kx)
    K = np.stack([z, -kz, ky, kz, z, -kx, -ky, kx, z], -1).reshape(aa.shape[:-1] + (3, 3))
    th = th[..., None]
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * (K @ K)


def fk(poses, root, parents, offsets):
    R = rodrigues(poses)  # (N, 24, 3, 3)
    n = len(poses)
    G = np.zeros((n, 24, 3, 3))
    P = np.zeros((n, 24, 3))
    for j in range(24):
        p = parents[j]
        if p < 0:
            G[:, j], P[:, j] = R[:, j], root
        else:
            P[:, j] = P[:, p] + G[:, p] @ offsets[j]
            G[:, j] = G[:, p] @ R[:, j]
    return P


def bpm(mid):
    d = int(mid[3:])
    return 110 + 5 * d if mid[:3] == "mHO" else 80 + 10 * d


def aistpp(root, rust_out, n):
    import librosa

    parents, offsets = smpl_tables()
    # Warm-up outside the timing: librosa's first calls compile numba kernels.
    y = np.random.default_rng(0).normal(0, 0.1, 16000 * 3).astype(np.float32)
    e = librosa.onset.onset_strength(y=y, sr=16000, hop_length=512)
    librosa.beat.beat_track(onset_envelope=e, sr=16000, hop_length=512)
    ignore = set(open(os.path.join(root, "ignore_list.txt")).read().split())
    cands = []
    for split in ["train", "val", "test"]:
        names = open(os.path.join(root, "splits", f"crossmodal_{split}.txt")).read().split()
        cands += sorted(x for x in names if x not in ignore and os.path.exists(os.path.join(root, "motions", x + ".pkl")))
    cands = cands[:n]
    music, music_s, seq_s = {}, 0.0, 0.0
    out = h5py.File(tempfile.mktemp(suffix=".h5"), "w")
    worst = 0.0
    for name in cands:
        mid = name.split("_")[4]
        if mid not in music:
            t0 = time.perf_counter()
            try:
                y, sr = librosa.load(os.path.join(root, "music", mid + ".wav"), sr=16000)
            except Exception:  # missing or undecodable music: a skip on the Rust side
                music[mid] = None
                continue
            mel = librosa.power_to_db(librosa.feature.melspectrogram(y=y, sr=sr, n_fft=2048, hop_length=512,
                                                                     n_mels=80, fmax=8000), top_db=80).T
            env = librosa.onset.onset_strength(y=y, sr=sr, hop_length=512)
            _, beats = librosa.beat.beat_track(onset_envelope=env, sr=sr, hop_length=512, start_bpm=bpm(mid),
                                               tightness=100)
            music[mid] = (mel, env, librosa.frames_to_time(beats, sr=sr, hop_length=512), len(y) / sr)
            music_s += time.perf_counter() - t0
        if music[mid] is None:
            continue
        t0 = time.perf_counter()
        try:
            d = pickle.load(open(os.path.join(root, "motions", name + ".pkl"), "rb"))
            poses = d["smpl_poses"]
        except Exception:  # the Rust side reports these as skips
            continue
        poses = d["smpl_poses"].reshape(-1, 24, 3).astype(np.float64)
        scale = float(np.asarray(d["smpl_scaling"]).reshape(-1)[0])
        j60 = fk(poses, d["smpl_trans"] / scale, parents, offsets).astype(np.float32)
        mel, env, bt, dur = music[mid]
        n30 = min((len(j60) + 1) // 2, int(dur * 30))
        j60 = j60[: 2 * n30]
        j30 = j60[::2]
        t = np.arange(len(j30)) / 30 * (16000 / 512)
        k = np.arange(len(mel))
        m30 = np.stack([np.interp(t, k, mel[:, b]) for b in range(mel.shape[1])], 1).astype(np.float32)
        o30 = np.interp(t, np.arange(len(env)), env).astype(np.float32)
        b30 = np.unique(np.round(bt * 30).astype(np.int32))
        b30 = b30[(b30 >= 0) & (b30 < len(j30))]
        g = out.create_group(name)
        for key, v in [("joints60", j60), ("joints30", j30), ("mel", m30), ("onset", o30), ("beats", b30)]:
            g.create_dataset(key, data=v)
        seq_s += time.perf_counter() - t0
        if rust_out:
            worst = max(worst, rust_joints_diff(rust_out, name, "joints60", j60))
    return {"sequences": len(cands), "music_tracks": len(music),
            "music_s_per_track": music_s / max(1, sum(v is not None for v in music.values())),
            "seq_s_per_sequence": seq_s / max(1, len(cands)), "max_abs_joints60_diff_vs_rust_m": worst}


def rust_joints_diff(rust_out, name, key, ours):
    for fn in sorted(os.listdir(rust_out)):
        if fn.endswith(".h5"):
            with h5py.File(os.path.join(rust_out, fn), "r") as f:
                if name in f:
                    r = f[name][key][:]
                    k = min(len(r), len(ours))
                    return float(np.abs(r[:k] - ours[:k]).max())
    return 0.0


def humanml3d(root, rust_out, n):
    sys.path.insert(0, os.path.join(WS, "datasets", "bench"))
    import features_numpy as fnp

    jd = os.path.join(root, "new_joints")
    cands = []
    for split in ["train", "val", "test"]:
        cands += sorted(open(os.path.join(root, f"{split}.txt")).read().split())
    cands = [c for c in cands if os.path.exists(os.path.join(jd, c + ".npy"))][:n]
    first = np.load(os.path.join(jd, cands[0] + ".npy")).astype(np.float64)
    tgt = fnp.offsets_of(first[0]) if hasattr(fnp, "offsets_of") else None
    out = h5py.File(tempfile.mktemp(suffix=".h5"), "w")
    s = np.zeros(263)
    q = np.zeros(263)
    t0 = time.perf_counter()
    for c in cands:
        try:
            x = np.load(os.path.join(jd, c + ".npy"))[:, :22].astype(np.float64)
        except Exception:  # the Rust side reports these as skips
            continue
        if x.shape[1:] != (22, 3) or not np.isfinite(x).all() or len(x) < 40:
            continue
        f = fnp.process_file(x, tgt).astype(np.float32)
        tp = os.path.join(root, "texts", c + ".txt")
        caps = open(tp).read().splitlines() if os.path.exists(tp) else []
        g = out.create_group(c)
        g.create_dataset("features", data=f)
        g.create_dataset("captions", data=[l.split("#")[0] for l in caps], dtype=h5py.string_dtype())
        s += f.sum(0, dtype=np.float64)
        q += (f.astype(np.float64) ** 2).sum(0)
    dt = time.perf_counter() - t0
    return {"sequences": len(cands), "seq_s_per_sequence": dt / max(1, len(cands))}


def main():
    kind, root, rust_out, n = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])
    r = aistpp(root, rust_out, n) if kind == "aistpp" else humanml3d(root, rust_out, n)
    print(json.dumps(r))


if __name__ == "__main__":
    main()
