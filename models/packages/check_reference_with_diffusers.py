#!/usr/bin/env python3
"""LOCAL cross-check, never in CI: stylize_reference.py's written-out DDIM formulas against
diffusers' own DDIMScheduler / DDIMInverseScheduler, on a style-transfer package.

Needs torch + diffusers (a Python with torch from PyPI); stylize_reference.py itself needs
neither. Runs the same loop twice — once stepping with diffusers, once with
stylize_reference.stylize — from the same x_T and prints the largest difference.

    python models/packages/check_reference_with_diffusers.py \
        --model models/packages/mcm-ldm-ref --mode transfer --guidance 2.5
    python models/packages/check_reference_with_diffusers.py \
        --model models/packages/style-gaussian-oracle --mode inversion --content-guidance 1.5 --style-guidance 2
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
from diffusers import DDIMInverseScheduler, DDIMScheduler

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import pkg_style_gaussian as G  # noqa: E402
import stylize_reference as R  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--model", type=Path, required=True)
    ap.add_argument("--mode", choices=["transfer", "inversion"], default="transfer")
    ap.add_argument("--steps", type=int)
    ap.add_argument("--guidance", type=float, default=2.5)
    ap.add_argument("--content-guidance", type=float, default=1.5)
    ap.add_argument("--style-guidance", type=float, default=2.0)
    a = ap.parse_args()
    p = R.Package(a.model, 2)
    sm, dm = p.m["sampler"], p.m["diffusion"]
    steps = a.steps or (sm["steps"] if a.mode == "transfer" else sm["inversion_steps"])
    cfg = dict(num_train_timesteps=dm["train_steps"], beta_start=dm["beta_start"], beta_end=dm["beta_end"],
               beta_schedule=dm["beta_schedule"], clip_sample=False, set_alpha_to_one=sm["set_alpha_to_one"],
               steps_offset=sm["steps_offset"], prediction_type="epsilon")
    content = G.joints_like_features(np.random.default_rng(0), 1, 120)[0]
    style = G.joints_like_features(np.random.default_rng(9), 1, 90, swing=1.0)[0]

    # The conditions, exactly as stylize() prepares them.
    c = (content - p.mean) / p.std
    traj = c[None, :, :3].astype(np.float32)
    c[:, :3] = 0
    mask = np.ones((1, len(c)), np.float32)
    lat = p.run("vae_encoder", {"features": c[None].astype(np.float32), "mask": mask})
    s = style.copy()
    s[:, :3] = 0
    sv = p.run("style_encoder", {"features": s[None], "mask": np.ones((1, len(s)), np.float32)})
    null_s, null_c = np.zeros_like(sv), np.zeros_like(lat)

    def eps(x, t, rows):
        return [torch.tensor(e) for e in p.eps(x.numpy(), int(t), rows, traj, mask)]

    noise = np.random.default_rng(3).standard_normal(lat.shape[1:]).astype(np.float32)
    sch = DDIMScheduler(**cfg)
    sch.set_timesteps(steps)
    if a.mode == "transfer":
        x = torch.tensor(noise[None], dtype=torch.float64)
        for t in sch.timesteps:
            e_s, e_n = eps(x, t, [(lat, sv), (lat, null_s)])
            x = sch.step(e_n + a.guidance * (e_s - e_n), t, x, eta=0.0).prev_sample
    else:
        inv = DDIMInverseScheduler(**cfg)
        inv.set_timesteps(steps)
        x = torch.tensor(lat, dtype=torch.float64)
        for t in inv.timesteps:
            (e,) = eps(x, t, [(lat, null_s)])
            x = inv.step(e, t, x).prev_sample
        for t in sch.timesteps:
            e_u, e_c, e_cs = eps(x, t, [(null_c, null_s), (lat, null_s), (lat, sv)])
            x = sch.step(e_u + a.content_guidance * (e_c - e_u) + a.style_guidance * (e_cs - e_c), t, x,
                         eta=0.0).prev_sample
    ours_diffusers = p.run("vae_decoder", {"latent": x.numpy().astype(np.float32), "mask": mask})[0] * p.std + p.mean
    ours = R.stylize(p, content, style, a.mode, a.guidance, a.content_guidance, a.style_guidance, steps, noise, 0)
    err = float(np.abs(ours - ours_diffusers).max())
    print(f"{a.model} {a.mode} {steps} steps: max |stylize_reference - diffusers| = {err:.2e} "
          f"(output scale {np.abs(ours_diffusers).max():.2f})")


if __name__ == "__main__":
    main()
