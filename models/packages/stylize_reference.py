#!/usr/bin/env python3
"""Reference style-transfer loop for choreod's style-transfer packages (numpy + onnxruntime).

    stylize_reference.py --model DIR --content C.npy --style S.npy -o OUT.npy
        [--mode transfer|inversion] [--guidance G] [--content-guidance WC] [--style-guidance WS]
        [--steps N] [--init-noise X_T.npy | --seed N] [--threads K]

Inputs are raw (not normalised) HumanML3D features (T, 263) float32 at the package's fps; the
output is the stylised features (T_content, 263) float32, denormalised. One JSON line with
timings goes to stdout. This is what choreod's `stylize` tests compare against; it imports
neither torch nor diffusers — the DDIM formulas of diffusers' DDIMScheduler.step and
DDIMInverseScheduler.step (huggingface/diffusers src/diffusers/schedulers/scheduling_ddim.py,
scheduling_ddim_inverse.py; eta = 0, epsilon prediction) are written out below.

transfer (MCM-LDM, XingliangJin/MCM-LDM mld/models/modeltype/mld.py `forward`,
`_diffusion_reverse`): c = (content - mean) / std; trajectory = c[:, 0:3]; c[:, 0:3] = 0;
latent = vae_encoder(c) (the posterior mean); style = style_encoder(raw style with dims 0:3
zeroed); x_T = init noise; DDIM over `steps` leading timesteps (step ratio 1000 // steps, +
steps_offset) with classifier-free guidance on the style only, in ONE batched call per step
(rows: style, null style = zeros): eps = e_null + g (e_style - e_null); decode at the content's
length; denormalise.

inversion (MulSMo, Li et al. 2024, arXiv 2412.09901: deterministic DDIM inversion of the content
latent, then guided denoising): x = latent; for t in the ascending timesteps (1, 1 + r, ...,
r = 1000 // inversion_steps): eps = denoiser(x, t, content, trajectory, null style);
x0 = (x - sqrt(1 - a) eps) / sqrt(a) with a = alphas_cumprod[t - r] (the initial alpha —
1 with set_alpha_to_one, else alphas_cumprod[0] — when t - r < 0); x = sqrt(a_t) x0 +
sqrt(1 - a_t) eps (DDIMInverseScheduler.step). Then DDIM down the same timesteps with two-weight
guidance (the SMooDi/MulSMo form, as models/src/sampler.rs `Guidance::Double`):
eps = e_u + wc (e_c - e_u) + ws (e_cs - e_c), rows u = no content and no style (content latent
and style zeros; the trajectory is kept, as MCM-LDM keeps it in both guidance rows),
c = content only, cs = content and style, in ONE batched call per step.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import tomllib
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import pkg_style_common as S  # noqa: E402


class Package:
    def __init__(self, pkg: Path, threads: int):
        with open(pkg / "choreod-model.toml", "rb") as f:
            self.m = tomllib.load(f)
        if self.m.get("task") != "style-transfer":
            raise SystemExit(f"{pkg}: task {self.m.get('task')!r}, expected 'style-transfer'")
        import onnxruntime as ort

        self.sess = {}
        for role, comp in self.m["components"].items():
            opts = ort.SessionOptions()
            opts.intra_op_num_threads = threads
            self.sess[role] = ort.InferenceSession(str(pkg / comp["file"]), opts,
                                                   providers=["CPUExecutionProvider"])
        self.mean = np.asarray(self.m["motion"]["mean"], np.float32)
        self.std = np.asarray(self.m["motion"]["std"], np.float32)
        self.ab = S.alphas_cumprod()
        sampler = self.m["sampler"]
        self.final_alpha = 1.0 if sampler["set_alpha_to_one"] else float(self.ab[0])
        self.ort_s = 0.0
        self.evals = 0

    def run(self, role: str, feeds: dict) -> np.ndarray:
        t0 = time.perf_counter()
        (out,) = self.sess[role].run(None, feeds)
        self.ort_s += time.perf_counter() - t0
        if role == "denoiser":
            self.evals += feeds["x_t"].shape[0]
        return out

    def eps(self, x: np.ndarray, t: int, rows: list[tuple[np.ndarray, np.ndarray]], traj, mask) -> list:
        """One batched denoiser call: one row per (content, style) pair; returns eps per row."""
        n = len(rows)
        feeds = {"x_t": np.repeat(x, n, axis=0).astype(np.float32), "t": np.full(n, t, np.int64),
                 "content": np.concatenate([c for c, _ in rows]).astype(np.float32),
                 "trajectory": np.repeat(traj, n, axis=0), "mask": np.repeat(mask, n, axis=0),
                 "style": np.concatenate([s for _, s in rows]).astype(np.float32)}
        out = self.run("denoiser", feeds).astype(np.float64)
        return [out[i:i + 1] for i in range(n)]


def leading_timesteps(steps: int, offset: int, train_steps: int) -> tuple[list[int], int]:
    """diffusers DDIMScheduler.set_timesteps, timestep_spacing 'leading' (descending)."""
    ratio = train_steps // steps
    return [int(i * ratio + offset) for i in range(steps)][::-1], ratio


def ddim_step(p: Package, x: np.ndarray, eps: np.ndarray, t: int, ratio: int) -> np.ndarray:
    """DDIMScheduler.step, eta 0, epsilon prediction (float64 state)."""
    a = p.ab[t]
    prev = t - ratio
    a_prev = p.ab[prev] if prev >= 0 else p.final_alpha
    x0 = (x - np.sqrt(1.0 - a) * eps) / np.sqrt(a)
    return np.sqrt(a_prev) * x0 + np.sqrt(1.0 - a_prev) * eps


def ddim_inverse_step(p: Package, x: np.ndarray, eps: np.ndarray, t: int, ratio: int) -> np.ndarray:
    """DDIMInverseScheduler.step: from the level of t - ratio (initial alpha below 0) up to t."""
    cur = min(t - ratio, len(p.ab) - 1)
    a = p.ab[cur] if cur >= 0 else p.final_alpha
    a_next = p.ab[t]
    x0 = (x - np.sqrt(1.0 - a) * eps) / np.sqrt(a)
    return np.sqrt(a_next) * x0 + np.sqrt(1.0 - a_next) * eps


def stylize(p: Package, content: np.ndarray, style: np.ndarray, mode: str, guidance: float,
            wc: float, ws: float, steps: int, init_noise: np.ndarray | None, seed: int,
            one_segment: bool = False) -> np.ndarray:
    mo = p.m["motion"]
    if not (mo["min_frames"] <= style.shape[0]):
        raise SystemExit(f"style has {style.shape[0]} frames, the package needs at least {mo['min_frames']}")
    if content.shape[0] > mo["max_frames"] and not one_segment:
        raise SystemExit(f"content has {content.shape[0]} frames, the package takes at most {mo['max_frames']} "
                         f"per segment (choreod cuts longer content into segments; this loop does not)")
    c = (content.astype(np.float32) - p.mean) / p.std
    traj = c[None, :, :S.TRAJ_DIMS].copy()
    c[:, :S.TRAJ_DIMS] = 0.0
    mask = np.ones((1, c.shape[0]), np.float32)
    latent = p.run("vae_encoder", {"features": c[None], "mask": mask})
    s = style.astype(np.float32).copy()
    s[:, :S.TRAJ_DIMS] = 0.0
    style_vec = p.run("style_encoder", {"features": s[None], "mask": np.ones((1, s.shape[0]), np.float32)})
    null_style = np.zeros_like(style_vec)
    sampler = p.m["sampler"]
    train_steps = p.m["diffusion"]["train_steps"]
    if mode == "transfer":
        if init_noise is None:
            init_noise = np.random.default_rng(seed).standard_normal(latent.shape[1:])
        if np.size(init_noise) != latent.size or not np.isfinite(init_noise).all():
            raise SystemExit(f"--init-noise: need {latent.size} finite values (latent shape "
                             f"{list(latent.shape[1:])}), got shape {list(np.shape(init_noise))}")
        x = np.asarray(init_noise, np.float64).reshape(latent.shape)
        ts, ratio = leading_timesteps(steps, sampler["steps_offset"], train_steps)
        for t in ts:
            if guidance == 1.0:
                (eps,) = p.eps(x, t, [(latent, style_vec)], traj, mask)
            else:
                e_s, e_null = p.eps(x, t, [(latent, style_vec), (latent, null_style)], traj, mask)
                eps = e_null + guidance * (e_s - e_null)
            x = ddim_step(p, x, eps, t, ratio)
    else:
        ts, ratio = leading_timesteps(steps, sampler["steps_offset"], train_steps)
        x = latent.astype(np.float64)
        for t in ts[::-1]:
            (eps,) = p.eps(x, t, [(latent, null_style)], traj, mask)
            x = ddim_inverse_step(p, x, eps, t, ratio)
        null_content = np.zeros_like(latent)
        for t in ts:
            e_u, e_c, e_cs = p.eps(x, t, [(null_content, null_style), (latent, null_style), (latent, style_vec)],
                                   traj, mask)
            eps = e_u + wc * (e_c - e_u) + ws * (e_cs - e_c)
            x = ddim_step(p, x, eps, t, ratio)
    out = p.run("vae_decoder", {"latent": x.astype(np.float32), "mask": mask})[0]
    return out * p.std + p.mean


def load_features(path: Path, what: str) -> np.ndarray:
    a = np.load(path, allow_pickle=False)
    if a.ndim != 2 or a.shape[1] != S.DIM or not np.isfinite(a).all():
        raise SystemExit(f"{path}: {what} must be finite HumanML3D features (T, {S.DIM}), got {a.shape}")
    return a


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", type=Path, required=True)
    ap.add_argument("--content", type=Path, required=True)
    ap.add_argument("--style", type=Path, required=True)
    ap.add_argument("-o", "--out", type=Path, required=True)
    ap.add_argument("--mode", choices=["transfer", "inversion"], default="transfer")
    ap.add_argument("--guidance", type=float, help="style CFG scale (transfer; default: manifest)")
    ap.add_argument("--content-guidance", type=float, help="wc (inversion; default: manifest)")
    ap.add_argument("--style-guidance", type=float, help="ws (inversion; default: manifest)")
    ap.add_argument("--steps", type=int, help="DDIM steps (default: manifest steps / inversion_steps)")
    ap.add_argument("--init-noise", type=Path,
                    help="x_T for transfer mode: float32 .npy of the latent's shape without N "
                         "([7, d] for mcm-ldm-ref, [T, 284] for style-gaussian; a leading 1 is accepted)")
    ap.add_argument("--seed", type=int, default=0, help="numpy seed for x_T without --init-noise")
    ap.add_argument("--threads", type=int, default=2, help="ORT intra-op threads (choreod's default 2)")
    ap.add_argument("--one-segment", action="store_true",
                    help="run content longer than the manifest's max_frames as one segment (benchmarks; "
                         "mcm-ldm-ref's networks accept up to 486 frames)")
    a = ap.parse_args()
    t_start = time.perf_counter()
    p = Package(a.model, a.threads)
    sm = p.m["sampler"]
    steps = a.steps or (sm["steps"] if a.mode == "transfer" else sm["inversion_steps"])
    noise = np.load(a.init_noise, allow_pickle=False) if a.init_noise else None
    t_stylize = time.perf_counter()
    out = stylize(p, load_features(a.content, "content"), load_features(a.style, "style"), a.mode,
                  sm["guidance"] if a.guidance is None else a.guidance,
                  sm["content_guidance"] if a.content_guidance is None else a.content_guidance,
                  sm["style_guidance"] if a.style_guidance is None else a.style_guidance,
                  steps, noise, a.seed, a.one_segment)
    stylize_s = time.perf_counter() - t_stylize
    np.save(a.out, out.astype(np.float32))
    total = time.perf_counter() - t_start
    print(json.dumps({"total_s": round(total, 4), "stylize_s": round(stylize_s, 4), "ort_s": round(p.ort_s, 4), "network_evals": p.evals,
                      "frames": int(out.shape[0]), "mode": a.mode, "steps": steps}))


if __name__ == "__main__":
    main()
