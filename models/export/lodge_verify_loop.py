#!/usr/bin/env python3
"""Run LODGE's official inference loop and `choreod dance` on the same features and noise.

    PYTHONPATH=PYTORCH3D python models/export/lodge_verify_loop.py --repo LODGE \\
        --global GLOBAL.ckpt --local LOCAL.ckpt --package PKG --features F.npy \\
        [--normalizer data/Normalizer.pth] [--genre ID] [--seed N] [--choreod PATH] [--work DIR]

The whole-loop half of the exporter's check (`lodge.py --verify` checks each network call):

1. draws every random value of a deterministic run for the official window counts of F.npy
   (`(T, 35)` fact35 features, e.g. `choreod features SONG --set fact35 -o F.npy`) into
   WORK/noise.npz: `global_xT (G,104,139)`, `local_xT (L,256,139)` and `local_style
   (50, 2, L, 256)` (per step the unconditional, then the conditional call's style noise);
2. runs the official loop from the user's clone, its own code: `infer_lodge.py`'s per-song body
   (198-289, cached features), `Global_Module.render_sample_ori`, `Local_Module.render_sample`
   (158-299) and `GaussianDiffusion.render_sample`, `ddim_sample`, `inpaint_soft_ddim`
   (diffusion.py 261-294, 490-545) with `--soft 1`, every `torch.randn` answered with the file's
   draws in the order the code makes them, and eta 0 (the official samplers fix eta = 1 in a
   local: the two sampler functions are recompiled from the clone's source with that one
   literal changed);
3. runs `choreod dance --features F.npy --init-noise noise.npz --sampler ddim --eta 0
   --lodge-compat official --save-windows` with the same genre;
4. runs the official loop again up to its Local sampler, its Global sampler answering with
   choreod's Global windows: the in-painting the official code builds from the keyframes choreod
   built its own from (`Local_Module.py:170-224`); both official in-paintings go to
   WORK/official-constraints.npz;
5. prints the figures (one JSON line, then a summary): both stages' normalised x0 after 50 steps,
   the final un-normalised 139 features (official: concat_res.py's concatenation of the saved
   local windows), the 22 joints (official: smplfk.py's `do_smplxfk` with the clone's rest
   joints; choreod: the motion file's) and the in-painting of step 4 against choreod's (copied
   and mirrored rows apart; the in-loop difference, which carries the Global stage's, beside
   them). Exits 1 if a bar fails.

Nothing of LODGE is copied: its code runs from the clone. Needs torch, einops, h5py and a
pytorch3d from 0.6.2 on (as `lodge.py --verify`).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import lodge as E  # noqa: E402

# The Evidence bars of issue 25 (max absolute difference unless named otherwise).
BARS = {
    "global_x0": 1e-3,  # normalised, after 50 steps
    "local_x0": 1e-3,
    "features_max": 1e-2,  # un-normalised 139 features
    "features_p999": 1e-3,  # their 99.9th percentile
    "joints_mm": 2.0,  # Euclidean distance per joint and frame
    # The Local in-painting built from the same Global windows (normalised values where the
    # mask holds; rows copied from the keyframes, and their mirrors), and mask entries differing.
    "constraint_copied": 1e-6,
    "constraint_mirrored": 1e-5,
    "constraint_mask": 0,
}
# Rows of a 256-frame Local window holding mirrored keyframes (Local_Module.py:209, 211).
MIRRORED_ROWS = np.r_[60:68, 188:196]


def window_counts(frames: int) -> tuple[int, int]:
    """`lodge.official_windows`, refusing songs the official code crashes on."""
    if frames < E.GLOBAL_MUSIC_FRAMES:
        raise E.ExportError(f"{frames} feature frames: the official code needs at least "
                            f"{E.GLOBAL_MUSIC_FRAMES} (34.1 s)")
    return E.official_windows(frames)


def draw_noise(seed: int, frames: int, steps: int = E.STEPS) -> dict[str, np.ndarray]:
    """Every draw of a deterministic run, in `choreod dance --init-noise`'s layout."""
    g, n = window_counts(frames)
    rng = np.random.default_rng(seed)
    return {
        "global_xT": rng.standard_normal((g, E.GLOBAL_KEYFRAMES, E.NFEATS), dtype=np.float32),
        "local_xT": rng.standard_normal((n, E.LOCAL_FRAMES, E.NFEATS), dtype=np.float32),
        "local_style": rng.standard_normal((steps, 2, n, E.STYLE_NOISE), dtype=np.float32),
    }


def official_order(noise: dict[str, np.ndarray]) -> list[np.ndarray]:
    """The draws in the order the official loop makes its `torch.randn` calls: Global's x_T
    (diffusion.py:269), Local's x_T (diffusion.py:510), then per Local step the style noise of
    `guided_forward`'s unconditional call and then its conditional one (model.py:869-873, each
    `forward` drawing at model.py:947). The per-step `randn_like` of both samplers
    (diffusion.py:289, 535) is multiplied by sigma = 0 at eta 0 and is not in the file."""
    draws = [noise["global_xT"], noise["local_xT"]]
    for step in noise["local_style"]:
        draws += [step[0], step[1]]
    return draws


def constraint_differences(official: dict[str, np.ndarray], choreod: dict[str, np.ndarray]) -> dict:
    """Largest difference of the in-painting values where the official mask holds, in copied and
    in mirrored rows, and the number of mask entries that differ. Both dicts hold
    `constraint_value` and `constraint_mask` (L, 256, 139)."""
    for key in ("constraint_value", "constraint_mask"):
        if official[key].shape != choreod[key].shape:
            raise E.ExportError(f"{key}: official {official[key].shape}, choreod {choreod[key].shape}")
    held = official["constraint_mask"] == 1
    diff = np.where(held, np.abs(official["constraint_value"].astype(np.float64) - choreod["constraint_value"]), 0.0)
    diff[~np.isfinite(diff)] = np.inf
    mirrored = np.zeros(held.shape[1], bool)
    mirrored[MIRRORED_ROWS] = True
    return {"constraint_copied": float(diff[:, ~mirrored].max()),
            "constraint_mirrored": float(diff[:, mirrored].max()),
            "constraint_mask": int((official["constraint_mask"] != choreod["constraint_mask"]).sum())}


def compare(official: dict[str, np.ndarray], choreod: dict[str, np.ndarray], built: dict[str, np.ndarray]) -> dict:
    """The figures and whether each meets its bar. `official` and `choreod` hold `global_x0
    (G,104,139)`, `local_x0 (L,256,139)` normalised, `features (T,139)` raw, `joints (T,22,3)` in
    metres and the Local in-painting; `built` the in-painting the official code builds from
    choreod's Global windows (the constraint figures: the same keyframes on both sides; the
    in-loop difference, which carries the Global stage's, is reported beside them)."""
    for key in ("global_x0", "local_x0", "features", "joints"):
        if official[key].shape != choreod[key].shape:
            raise E.ExportError(f"{key}: official {official[key].shape}, choreod {choreod[key].shape}")
    diff = {k: np.abs(official[k].astype(np.float64) - choreod[k].astype(np.float64))
            for k in ("global_x0", "local_x0", "features")}
    distance = np.linalg.norm(official["joints"].astype(np.float64) - choreod["joints"], axis=-1)
    figures = {
        "global_x0": float(diff["global_x0"].max()),
        "local_x0": float(diff["local_x0"].max()),
        "features_max": float(diff["features"].max()),
        "features_p999": float(np.percentile(diff["features"], 99.9)),
        "joints_mm": float(distance.max() * 1000.0),
        **constraint_differences(built, choreod),
    }
    failed = [k for k, v in figures.items() if not v <= BARS[k]]
    in_loop = {f"{k}_in_loop": v for k, v in constraint_differences(official, choreod).items()}
    return {"figures": figures, "bars": BARS, "failed": failed, "ok": not failed, "context": in_loop}


def summary(report: dict) -> str:
    lines = []
    for key, value in report["figures"].items():
        mark = "ok" if key not in report["failed"] else "FAILED"
        lines.append(f"  {key:19s} {value:.3g}  (bar {report['bars'][key]:g})  {mark}")
    for key, value in report["context"].items():
        lines.append(f"  {key:27s} {value:.3g}  (official loop's own keyframes: carries the Global difference)")
    return "\n".join(lines)


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repo", type=Path, required=True, help="a clone of li-ronghui/LODGE")
    ap.add_argument("--global", dest="global_ckpt", type=Path, required=True, help="Global checkpoint")
    ap.add_argument("--local", dest="local_ckpt", type=Path, required=True, help="Local checkpoint")
    ap.add_argument("--normalizer", type=Path, help=f"default: REPO/{E.NORMALIZER_PATH}")
    ap.add_argument("--package", type=Path, required=True, help="the package exported from these checkpoints")
    ap.add_argument("--features", type=Path, required=True, help="(T, 35) fact35 features, T >= 1024")
    ap.add_argument("--genre", type=int, default=1, help="genre id 0-15 (default 1, Popping)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the noise file")
    ap.add_argument("--heads", type=int, default=E.HEADS, help="attention heads (not in the weights)")
    ap.add_argument("--choreod", default="choreod", help="the choreod binary")
    ap.add_argument("--work", type=Path, default=Path("lodge-verify-loop"),
                    help="directory for the noise file, both runs' outputs and the official log")
    ap.add_argument("--allow-pickle", action="store_true",
                    help="load checkpoints with full unpickling (only for files you trust)")
    return ap.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    try:
        import lodge_loop_torch as L

        features = np.load(args.features).astype(np.float32)
        if features.ndim != 2 or features.shape[1] != E.MUSIC_DIM:
            raise E.ExportError(f"{args.features}: features {features.shape}, expected (T, {E.MUSIC_DIM})")
        if not 0 <= args.genre < len(E.GENRES):
            raise E.ExportError(f"--genre {args.genre}: ids are 0-{len(E.GENRES) - 1}")
        args.work.mkdir(parents=True, exist_ok=True)
        noise = draw_noise(args.seed, len(features))
        np.savez(args.work / "noise.npz", **noise)
        official = L.run_official(args, features, official_order(noise))
        ours = L.run_choreod(args)
        built = L.run_official(args, features, [], global_x0=ours["global_x0"])
        np.savez(args.work / "official-constraints.npz", in_loop_value=official["constraint_value"],
                 in_loop_mask=official["constraint_mask"], built_value=built["constraint_value"],
                 built_mask=built["constraint_mask"])
        report = compare(official, ours, built)
    except E.ExportError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    report.update(windows={"global": int(len(official["global_x0"])), "local": int(len(official["local_x0"]))},
                  frames=int(len(official["features"])), genre=args.genre, seed=args.seed)
    print(json.dumps({"verify_loop": "ok" if report["ok"] else "failed", **report}))
    print(f"official loop vs choreod dance ({report['frames']} frames, {report['windows']['global']} Global and "
          f"{report['windows']['local']} Local windows, genre {args.genre}, seed {args.seed}, eta 0):",
          file=sys.stderr)
    print(summary(report), file=sys.stderr)
    return 0 if report["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
