#!/usr/bin/env python3
"""Writes recover_from_ric.npz: the official `recover_from_ric` on seeded, motion-like features.

    python models/export/tests/make_ric_fixture.py --repo PATH_TO_MCM-LDM_CLONE

The output of MCM-LDM's own function (mld/data/humanml/scripts/motion_process.py:420, torch,
float32) on inputs made here, so the numpy port in mcm_ldm.py is checked against the reference
implementation, not against itself. Needs torch; the test that reads the file does not.
"""

import argparse
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def features(rng: np.random.Generator, frames: int) -> np.ndarray:
    """Motion-like HumanML3D features: yaw velocity ~0.1 rad/frame, root speed ~5 cm/frame,
    root height ~0.9 m, joints within ~0.5 m; the remaining dims do not enter recover_from_ric."""
    f = rng.standard_normal((frames, 263)).astype(np.float32) * 0.5
    f[:, 0] = 0.1 * rng.standard_normal(frames)
    f[:, 1:3] = 0.05 * rng.standard_normal((frames, 2))
    f[:, 3] = 0.9 + 0.05 * rng.standard_normal(frames)
    return f


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repo", type=Path, required=True)
    a = ap.parse_args()
    sys.path.insert(0, str(a.repo))
    import torch
    from mld.data.humanml.scripts.motion_process import recover_from_ric

    f = features(np.random.default_rng(15), 24)
    joints = recover_from_ric(torch.from_numpy(f), 22).numpy()
    np.savez(HERE / "recover_from_ric.npz", features=f, joints=joints)
    print(f"wrote {HERE / 'recover_from_ric.npz'}: features {f.shape}, joints {joints.shape}")


if __name__ == "__main__":
    main()
