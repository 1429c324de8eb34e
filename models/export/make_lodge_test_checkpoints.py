#!/usr/bin/env python3
"""LODGE-layout checkpoints with seeded random weights, for testing the exporter.

    python models/export/make_lodge_test_checkpoints.py --repo PATH_TO_LODGE_CLONE -o DIR [--seed 0]

The released FineDance checkpoints cannot be fetched everywhere; LODGE's own network classes,
built from the clone with the released sizes and randomly initialised, have the same
architecture, key names and export hazards. Sizes: both networks latent 512, feed-forward
1024, 8 heads, 8 decoder layers (the local one 9: its refine layer lands in the main stack);
music windows 1024 (global) and 256 (local); 16 genres — 47.46 M and 60.77 M parameters, the
released networks' counts (47.5 M and 60.8 M). Writes, as Lightning would:

- DIR/global.ckpt  {"state_dict": DanceDecoder.*, diffusion.model.* (the same tensors),
                   diffusion.master_model.* (an EMA copy, here perturbed: inference does not use
                   it)}, epoch, global_step
- DIR/local.ckpt   the same for Refine_DanceDecoder
- DIR/Normalizer.pth  LODGE's own Normalizer class fitted on random frames of plausible scale
                   (torch.save, as dld/data/pre/FineDance_normalizer.py does)

Needs torch and einops (the user's environment, never choreod's).
"""

from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

import lodge as E  # noqa: E402
import lodge_torch as T  # noqa: E402

RELEASED = {
    "global": dict(nfeats=E.NFEATS, seq_len=E.GLOBAL_MUSIC_FRAMES, latent_dim=512, ff_size=1024, num_layers=8,
                   cond_feature_dim=E.MUSIC_DIM, use_rotary=True),
    "local": dict(nfeats=E.NFEATS, seq_len=E.LOCAL_FRAMES, latent_dim=512, ff_size=1024, num_layers=8,
                  cond_feature_dim=E.MUSIC_DIM, use_rotary=True, genre_num=len(E.GENRES)),
}


def lightning(net: torch.nn.Module, seed: int) -> dict:
    g = torch.Generator().manual_seed(seed)
    weights = net.state_dict()
    state = {}
    for k, v in weights.items():
        state["DanceDecoder." + k] = v
        state["diffusion.model." + k] = v
        ema = v + 1e-3 * torch.randn(v.shape, generator=g) if v.is_floating_point() else v
        state["diffusion.master_model." + k] = ema
    return {"state_dict": state, "epoch": 0, "global_step": 0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repo", type=Path, required=True)
    ap.add_argument("-o", "--out", type=Path, required=True)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(a.seed)
    official = T.Official(a.repo)
    for kind, sizes in RELEASED.items():
        net = official.build(kind, sizes, E.HEADS)
        torch.save(lightning(net, a.seed + 1), a.out / f"{kind}.ckpt")
        print(f"{a.out / f'{kind}.ckpt'}: {sum(p.numel() for p in net.parameters()) / 1e6:.2f} M parameters")
    # Frames of plausible scale: contacts in {0, 1}, transl within a few metres, 6D in [-1, 1].
    frames = torch.rand(4096, E.NFEATS, dtype=torch.float32) * 2 - 1
    frames[:, :4] = (frames[:, :4] > 0).float()
    frames[:, 4:7] *= 3
    preprocess = importlib.import_module("dld.data.utils.preprocess")
    torch.save(preprocess.Normalizer(frames), a.out / "Normalizer.pth")
    print(f"{a.out / 'Normalizer.pth'}: LODGE's Normalizer fitted on {len(frames)} random frames")


if __name__ == "__main__":
    main()
