#!/usr/bin/env python3
"""Time LODGE's official sampling loop on the CPU, for scripts/bench-lodge (not a test).

    python models/export/lodge_time_official.py --repo LODGE_CLONE --global CKPT --local CKPT \\
        --frames T [--steps K] [--threads 2] [--json OUT]

Runs the official networks (imported from the user's clone by lodge_torch.py; nothing of LODGE
is in choreod) at the batch sizes the official `infer_lodge.py` loop gives a song of T feature
frames, and times the first and K more of its 50 DDIM steps per stage, then scales to 50:

- Global: `count` = 1 copy of each of ceil(L/4) windows (infer_lodge.py:161, 213-235), one
  `guided_forward` per step (two `forward`s, guidance 2; diffusion.py:168-170, 262-294).
- Local: L = T // 256 windows (infer_lodge.py:211-212: the tail is dropped), one
  `guided_forward` per step with the ramp weight (diffusion.py:491-545); the `forward` includes
  the dead refine branch's SMPL-X FK (model.py:876-904, 963-967), as the official code runs it.

A step's DDIM arithmetic and in-painting are elementwise on (L, 256, 139) and are included (the
official formulas, in torch). Model loading is timed separately. Every step costs the same (the
networks do not depend on t's value for their work), so the first step (torch's warm-up) plus K
more scaled by 49/K is the loop's sampling time; the output says so.
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import lodge as E  # noqa: E402


def ddim_step(x, x0, alphas, t, t_next, eta=1.0):
    """diffusion.py:280-293 (x0 prediction, clamped) with eta 1."""
    x0 = x0.clamp(-1, 1)
    a, an = alphas[t], alphas[t_next]
    pred_noise = ((1 / a).sqrt() * x - x0) / (1 / a - 1).sqrt()
    sigma = eta * ((1 - a / an) * (1 - an) / (1 - a)).sqrt()
    c = (1 - an - sigma**2).sqrt()
    return x0 * an.sqrt() + c * pred_noise + sigma * x.new_empty(x.shape).normal_()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repo", type=Path, required=True, help="the LODGE clone")
    ap.add_argument("--global", dest="global_ckpt", type=Path, required=True)
    ap.add_argument("--local", dest="local_ckpt", type=Path, required=True)
    ap.add_argument("--frames", type=int, required=True, help="feature frames of the song (30 fps)")
    ap.add_argument("--steps", type=int, default=3, help="DDIM steps timed per stage after the first (1..49), scaled to 49")
    ap.add_argument("--threads", type=int, default=2, help="torch intra-op threads")
    ap.add_argument("--heads", type=int, default=E.HEADS)
    ap.add_argument("--allow-pickle", action="store_true")
    ap.add_argument("--json", type=Path, help="also write the result here")
    args = ap.parse_args(argv)
    if not 1 <= args.steps < E.STEPS:
        ap.error(f"--steps must be in 1..{E.STEPS - 1}")
    globals_, locals_ = E.official_windows(args.frames)
    if locals_ < 2 * (E.GLOBAL_MUSIC_FRAMES // E.LOCAL_FRAMES):
        ap.error(f"{args.frames} frames: the official loop needs at least two Global windows' worth")
    import torch  # the user's torch environment, never choreod's

    import lodge_torch as T

    torch.set_num_threads(args.threads)

    started = time.perf_counter()
    official = T.Official(args.repo, allow_pickle=args.allow_pickle, need_pytorch3d=True)
    official.load(args.global_ckpt, args.local_ckpt, args.heads)
    load_s = time.perf_counter() - started

    # The official schedule (diffusion.py:82-86), from the clone's own utils.py.
    make_beta_schedule = importlib.import_module("dld.models.architectures.utils").make_beta_schedule
    betas = torch.Tensor(make_beta_schedule(schedule="cosine", n_timestep=E.TRAIN_STEPS))
    alphas = torch.cumprod(1 - betas, 0)
    times = list(reversed(torch.linspace(-1, E.TRAIN_STEPS - 1, steps=E.STEPS + 1).int().tolist()))
    weights = [min(2.0, 4.0 * i / (E.STEPS - 1)) for i in range(E.STEPS)]
    g = torch.Generator().manual_seed(0)
    stages = {}
    with torch.no_grad():
        for kind, n, frames, music_frames in (
            ("global", globals_, E.GLOBAL_KEYFRAMES, E.GLOBAL_MUSIC_FRAMES),
            ("local", locals_, E.LOCAL_FRAMES, E.LOCAL_FRAMES),
        ):
            net = official.nets[kind]
            x = torch.randn(n, frames, E.NFEATS, generator=g)
            music = torch.randn(n, music_frames, E.MUSIC_DIM, generator=g)
            genre = torch.zeros(n, dtype=torch.long) if kind == "local" else None
            value, mask = torch.zeros_like(x), (torch.rand(x.shape, generator=g) > 0.9).float()
            per_step = []
            # The first step pays torch's one-time warm-up (allocations, rotary caches): timed
            # once, then `--steps` more, scaled to the other 49.
            for i in range(args.steps + 1):
                t, t_next = times[i], times[i + 1]
                t0 = time.perf_counter()
                tt = torch.full((n,), t, dtype=torch.long)
                w = 2.0 if kind == "global" else weights[i]
                x0 = net.guided_forward(x, music, genre, tt, w)
                x = ddim_step(x, x0, alphas, t, t_next)
                if kind == "local":
                    x = value * mask + (1.0 - mask) * x
                per_step.append(time.perf_counter() - t0)
            stages[kind] = {"windows": n, "rows_per_call": n, "calls_per_step": 2,
                            "timed_steps": args.steps + 1, "step_s": per_step,
                            "scaled_s": per_step[0] + sum(per_step[1:]) * (E.STEPS - 1) / args.steps}
    result = {"frames": args.frames, "threads": args.threads, "load_s": load_s, "stages": stages,
              "sampling_s": sum(s["scaled_s"] for s in stages.values()),
              "note": f"per stage the first step (warm-up) and {args.steps} more of {E.STEPS} timed, "
                      f"those {args.steps} scaled to {E.STEPS - 1}"}
    text = json.dumps(result)
    print(text)
    if args.json:
        args.json.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
