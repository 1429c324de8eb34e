#!/usr/bin/env python3
"""Official-format MCM-LDM checkpoints with seeded random weights, for testing the exporter.

    python models/export/make_test_checkpoints.py --repo PATH_TO_MCM-LDM_CLONE -o DIR [--seed 0]

No released weights are reachable from every machine; the official modules randomly initialised
have the same architecture, key names and export hazards. Writes, in the layouts the official
code reads (reference-facts §1 "Checkpoint layouts"):
- DIR/denoiser.ckpt    Lightning {"state_dict": vae.*, denoiser.*, motionclip.encoder.*, plus keys
                       inference ignores: t2m_* and motionclip.clip_model.*}, epoch, global_step
- DIR/vae7.ckpt        Lightning {"state_dict": vae.*}
- DIR/motionclip.pth.tar  plain {encoder.*}
- DIR/Mean.npy, DIR/Std.npy  per-feature mean and standard deviation (> 0) of the clone's demo
                       HumanML3D features (plausible scales; the real ones come from HumanML3D)
Needs torch (the user's environment, never choreod's).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import mcm_ldm as E  # noqa: E402

# Floor of the demo-derived std: features constant over the demo clips (e.g. a foot contact
# that never changes) would otherwise get std 0, which HumanML3D's Std.npy never has.
STD_FLOOR = 0.01


def demo_stats(repo: Path) -> tuple[np.ndarray, np.ndarray]:
    frames = np.concatenate([E.load_features(p) for p in sorted((repo / "demo").glob("*/*.npy"))])
    return frames.mean(0).astype(np.float32), np.maximum(frames.std(0), STD_FLOOR).astype(np.float32)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repo", type=Path, required=True)
    ap.add_argument("-o", "--out", type=Path, required=True)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    E.check_repo(a.repo)

    import torch

    import mcm_ldm_torch as T

    torch.manual_seed(a.seed)
    official = T.Official(a.repo)
    sd = official.state_dicts()
    a.out.mkdir(parents=True, exist_ok=True)

    def prefixed(prefix: str, state: dict) -> dict:
        return {prefix + k: v for k, v in state.items()}

    lightning = {"epoch": 0, "global_step": 0, "pytorch-lightning_version": "1.8.6"}
    full = {**prefixed("vae.", sd["vae"]), **prefixed("denoiser.", sd["denoiser"]),
            **prefixed("motionclip.encoder.", sd["motionclip_encoder"]),
            "motionclip.clip_model.logit_scale": torch.tensor(4.6052),
            "t2m_textencoder.input_emb.weight": torch.zeros(4, 4)}
    torch.save({**lightning, "state_dict": full}, a.out / "denoiser.ckpt")
    torch.save({**lightning, "state_dict": prefixed("vae.", sd["vae"])}, a.out / "vae7.ckpt")
    torch.save(prefixed("encoder.", sd["motionclip_encoder"]), a.out / "motionclip.pth.tar")
    mean, std = demo_stats(a.repo)
    np.save(a.out / "Mean.npy", mean)
    np.save(a.out / "Std.npy", std)
    print(f"wrote {a.out}: denoiser.ckpt, vae7.ckpt, motionclip.pth.tar, Mean.npy, Std.npy (seed {a.seed})")


if __name__ == "__main__":
    main()
