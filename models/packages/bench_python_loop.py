#!/usr/bin/env python3
"""The music-to-dance generation choreod runs, as a plain Python loop (numpy + onnxruntime).

For BENCHMARKS.md: run it next to `choreod dance SONG --model DIR --stats` on the same song and
compare seconds. It mirrors choreod's pipeline after the mel stage:

  mel (80, F) from `choreod mel SONG -o mel.npy`  ->  windows of 150 motion frames (5 s) at a
  stride of 75 (2.5 s), each with its 157 mel frames (time-major)  ->  all windows denoised as
  ONE batch with DDIM (manifest sampler defaults, e.g. 50 steps, eta, steps_offset 1,
  set_alpha_to_one), classifier-free guidance batched (cond and uncond rows in one call)
  when guidance != 1, and EDGE's overlap consistency after every step
  (Stanford-TML/EDGE:model/diffusion.py long_ddim_sample: x[1:, :half] = x[:-1, half:])
  ->  stitched (linear cross-fade over each 75-frame overlap)  ->  joints (T, 24, 3).

    .venv/bin/python models/packages/bench_python_loop.py --model target/bench/mofusion-paper \\
        --mel song.mel.npy [--seconds 180] [--guidance 2.0] [--two-calls] [--threads 2]

Prints one JSON line: seconds total / in ORT / outside ORT, windows, network evaluations,
real-time factor. `--seconds S` tiles (or crops) the mel to S seconds, to time a 30 s or 3 min
song from one clip. Not chunked: a 3 min song is 71 windows, one batch (choreod chunks long
songs to bound memory; at these lengths it runs a single chunk too).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import tomllib
from pathlib import Path

import numpy as np
import onnxruntime as ort

sys.path.insert(0, str(Path(__file__).resolve().parent))
import pkg_common as C  # noqa: E402


def alphas_cumprod(d: dict) -> np.ndarray:
    if d["beta_schedule"] != "linear":
        raise SystemExit(f"this driver implements the linear schedule only, got {d['beta_schedule']}")
    return C.alphas_cumprod(d["train_steps"], d["beta_start"], d["beta_end"])


def ddim_timesteps(train_steps: int, steps: int, offset: int) -> np.ndarray:
    # diffusers DDIMScheduler "leading" spacing: arange(steps) * (train // steps), reversed, + offset
    ratio = train_steps // steps
    return (np.arange(steps) * ratio)[::-1].astype(np.int64) + offset


def windows_of(mel: np.ndarray, m: dict) -> tuple[np.ndarray, int]:
    """(80, F) mel -> (n_windows, 157, 80) time-major music windows and the song's motion frames."""
    mo, au = m["motion"], m["audio"]
    fps, w, s = mo["fps"], mo["window_frames"], mo["stride_frames"]
    mel_rate = au["sample_rate"] / au["hop"]
    f_win = au["music_frames"]
    seconds = mel.shape[1] / mel_rate
    total = max(1, int(math.floor(seconds * fps)))
    n_win = 1 if total <= w else math.ceil((total - w) / s) + 1
    floor_db = float(mel.min())  # pad past the end with the song's quietest value (silence)
    out = np.full((n_win, f_win, mel.shape[0]), floor_db, dtype=np.float32)
    for i in range(n_win):
        start = int(round(i * s / fps * mel_rate))
        seg = mel[:, start:start + f_win].T
        out[i, :seg.shape[0]] = seg
    return out, total


def stitch(x: np.ndarray, stride: int) -> np.ndarray:
    """(n, W, D) windows overlapping by W - stride = stride frames -> (W + stride (n-1), D)."""
    n, w, d = x.shape
    out = np.zeros((w + stride * (n - 1), d), dtype=np.float64)
    acc = np.zeros((out.shape[0], 1))
    ramp = (np.arange(stride) + 0.5) / stride
    for i in range(n):
        wt = np.ones(w)
        if i > 0:
            wt[:stride] = ramp
        if i < n - 1:
            wt[w - stride:] = 1.0 - ramp
        out[i * stride:i * stride + w] += wt[:, None] * x[i]
        acc[i * stride:i * stride + w] += wt[:, None]
    return out / acc


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", type=Path, required=True, help="package directory (choreod-model.toml)")
    ap.add_argument("--mel", type=Path, required=True, help="float32 (80, F) log-mel .npy (`choreod mel`)")
    ap.add_argument("--seconds", type=float, help="tile/crop the mel to this many seconds")
    ap.add_argument("--steps", type=int, help="DDIM steps (default: manifest)")
    ap.add_argument("--guidance", type=float, help="CFG scale (default: manifest; 1 = off)")
    ap.add_argument("--eta", type=float, help="DDIM eta (default: manifest)")
    ap.add_argument("--two-calls", action="store_true", help="CFG as two calls instead of one batch")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=2, help="ORT intra-op threads (choreod default 2)")
    ap.add_argument("--out", type=Path, help="write joints (T, 24, 3) float32 .npy")
    a = ap.parse_args()

    t_start = time.perf_counter()
    with open(a.model / "choreod-model.toml", "rb") as f:
        m = tomllib.load(f)
    comp = m["components"]["denoiser"]
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = a.threads
    opts.inter_op_num_threads = 1
    sess = ort.InferenceSession(str(a.model / comp["file"]), opts, providers=["CPUExecutionProvider"])
    t_loaded = time.perf_counter()

    mel = np.load(a.mel, allow_pickle=False).astype(np.float32)
    if mel.ndim != 2 or mel.shape[0] != m["audio"]["n_mels"]:
        raise SystemExit(f"{a.mel}: expected a (80, F) log-mel, got {mel.shape}")
    if a.seconds:
        want = int(round(a.seconds * m["audio"]["sample_rate"] / m["audio"]["hop"]))
        mel = np.tile(mel, (1, math.ceil(want / mel.shape[1])))[:, :want]
    music, total = windows_of(mel, m)
    n = music.shape[0]
    mo, dif, smp = m["motion"], m["diffusion"], m["sampler"]
    if dif["prediction"] != "epsilon":
        raise SystemExit("this driver implements epsilon prediction only")
    eta = smp.get("eta", 0.0) if a.eta is None else a.eta
    steps = a.steps or smp["steps"]
    g = smp["guidance"] if a.guidance is None else a.guidance
    ab = alphas_cumprod(dif)
    ts = ddim_timesteps(dif["train_steps"], steps, smp["steps_offset"])
    ratio = dif["train_steps"] // steps
    half = mo["stride_frames"]

    rng = np.random.default_rng(a.seed)
    x = rng.standard_normal((n, mo["window_frames"], mo["dim"])).astype(np.float32)
    cond1 = np.ones(n, np.float32)
    ort_s = 0.0
    evals = 0
    if g != 1.0 and not a.two_calls:
        music_b = np.concatenate([music, music])
        cond_b = np.concatenate([cond1, np.zeros(n, np.float32)])

    def run(xx, tt, mus, cnd):
        nonlocal ort_s, evals
        t0 = time.perf_counter()
        (p,) = sess.run(["pred"], {"x_t": xx, "t": tt, "music": mus, "cond": cnd})
        ort_s += time.perf_counter() - t0
        evals += xx.shape[0]
        return p

    for k, t in enumerate(ts):
        tt = np.full(n, t, np.int64)
        if g == 1.0:
            eps = run(x, tt, music, cond1)
        elif a.two_calls:
            e_c = run(x, tt, music, cond1)
            e_u = run(x, tt, music, np.zeros(n, np.float32))
            eps = e_u + g * (e_c - e_u)
        else:
            both = run(np.concatenate([x, x]), np.concatenate([tt, tt]), music_b, cond_b)
            eps = both[n:] + g * (both[:n] - both[n:])
        a_t = ab[t]
        prev = t - ratio
        a_prev = ab[prev] if prev >= 0 else (1.0 if smp["set_alpha_to_one"] else ab[0])
        x0 = (x - math.sqrt(1.0 - a_t) * eps) / math.sqrt(a_t)
        # DDIM (Song et al. 2021 eq. 12; diffusers DDIMScheduler.step): sigma from eta
        sigma = eta * math.sqrt((1.0 - a_prev) / (1.0 - a_t)) * math.sqrt(1.0 - a_t / a_prev)
        x = math.sqrt(a_prev) * x0 + math.sqrt(max(1.0 - a_prev - sigma**2, 0.0)) * eps
        if sigma > 0.0:
            x = x + sigma * rng.standard_normal(x.shape)
        x = x.astype(np.float32)
        if k < len(ts) - 1 and n > 1:
            x[1:, :half] = x[:-1, half:]  # EDGE long_ddim_sample overlap consistency

    feats = stitch(x.astype(np.float64), half)[:total]
    feats = feats * np.asarray(mo["std"]) + np.asarray(mo["mean"])
    joints = C.features_to_joints(feats).astype(np.float32)
    t_end = time.perf_counter()
    if a.out:
        np.save(a.out, joints)
    total_s = t_end - t_start
    song_s = total / mo["fps"]
    print(json.dumps({
        "driver": "python", "model": m["name"], "windows": n, "steps": steps, "guidance": g,
        "cfg": "two-calls" if a.two_calls and g != 1.0 else ("batched" if g != 1.0 else "off"),
        "network_evals": evals, "frames": int(joints.shape[0]), "song_s": round(song_s, 3),
        "load_s": round(t_loaded - t_start, 4), "ort_s": round(ort_s, 4),
        "outside_ort_s": round(total_s - ort_s, 4), "total_s": round(total_s, 4),
        "ort_share": round(ort_s / total_s, 4), "rtf": round(total_s / song_s, 4),
    }))


if __name__ == "__main__":
    main()
