#!/usr/bin/env python3
"""Export MCM-LDM's official checkpoints to a choreod style-transfer package.

    python models/export/mcm_ldm.py --repo PATH_TO_MCM-LDM_CLONE --vae vae7.ckpt \\
        --denoiser denoiser.ckpt --motionclip motionclip.pth.tar --mean Mean.npy --std Std.npy \\
        -o PACKAGE_DIR [--verify] [--pair CONTENT.npy STYLE.npy ...] [--allow-pickle]

Imports the official modules from the clone (nothing of it is copied into choreod), loads the
checkpoints, exports the four components of the style-transfer contract to ONNX (opset 18,
dynamic batch N and length T) and writes `choreod-model.toml` with each file's sha256 and the
HumanML3D Mean/Std inline. The package appears under PACKAGE_DIR only when complete.

Weights: the official demo (demo_transfer.py) loads *every* weight from denoiser.ckpt
(`model.load_state_dict(state_dict, strict=True)`), which holds `vae.*`, `denoiser.*` and
`motionclip.encoder.*`; the exporter does the same. vae7.ckpt and motionclip.pth.tar are the
fall-back for a denoiser.ckpt without those keys, and are compared with it otherwise.

--verify runs the official PyTorch inference (the official modules, diffusers' DDIMScheduler
configured by the clone's configs/modules/scheduler.yaml, the official classifier-free guidance)
on content/style pairs with a fixed x_T, and compares with (a) each exported component run by
onnxruntime on the same inputs, (b) the whole loop run on the exported package by
models/packages/stylize_reference.py and (c) `choreod stylize --init-noise` on the package, both
with the same x_T. It prints the largest differences in normalised features and in joints. See
models/export/README.md.

This file needs no torch for its own parts (argument checks, weight selection, manifest); the
torch half is mcm_ldm_torch.py, imported only when exporting or verifying.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
PACKAGES = HERE.parent / "packages"
sys.path.insert(0, str(PACKAGES))
sys.path.insert(0, str(HERE))

import pkg_common as C  # noqa: E402
import pkg_style_common as S  # noqa: E402

DIM = S.DIM
TRAJ_DIMS = S.TRAJ_DIMS
JOINTS = 22  # t2m skeleton (HumanML3D paramUtil.py t2m_kinematic_chain)
STYLE_DIM = 512  # MotionCLIP latent_dim (configs/motionclip_config/motionclip_params_263.yaml)
OPSET = C.OPSET
# Content frames: the VAE encoder adds its 14 query tokens (latent_size * 2, mld_vae.py
# `global_motion_token`) before the learned positional table of 500 rows
# (mld/models/operator/position_encoding.py PositionEmbeddingLearned1D max_len=500): 500 - 14.
MAX_FRAMES = 500 - 14
# README.md demo command: `--scale 2.5` (classifier-free guidance on the style).
GUIDANCE = 2.5
# Inversion mode (MulSMo-style, not part of MCM-LDM): content weight 1 keeps the content
# condition as trained; the style weight is MCM-LDM's own style scale.
CONTENT_GUIDANCE = 1.0
STYLE_GUIDANCE = GUIDANCE

# Files of the official clone the exporter relies on (XingliangJin/MCM-LDM 701cc96).
MAIN_CONFIG = "configs/config_mld_humanml3d.yaml"
VAE_CONFIG = "configs/modules/motion_vae.yaml"
DENOISER_CONFIG = "configs/modules/denoiser.yaml"
SCHEDULER_CONFIG = "configs/modules/scheduler.yaml"
MOTIONCLIP_CONFIG = "configs/motionclip_config/motionclip_params_263.yaml"
REPO_FILES = (MAIN_CONFIG, VAE_CONFIG, DENOISER_CONFIG, SCHEDULER_CONFIG, MOTIONCLIP_CONFIG,
              "mld/models/architectures/mld_vae.py", "mld/models/architectures/mld_denoiser.py",
              "mld/models/motionclip_263/models/architectures/transformer.py",
              "mld/data/humanml/scripts/motion_process.py")

# The style-transfer contract (models/packages/README.md): role -> (file, inputs, outputs).
COMPONENTS = {
    "vae_encoder": ("vae_encoder.onnx", [("features", ["N", "T", DIM]), ("mask", ["N", "T"])],
                    [("latent", ["N", 7, 256])]),
    "vae_decoder": ("vae_decoder.onnx", [("latent", ["N", 7, 256]), ("mask", ["N", "T"])],
                    [("features", ["N", "T", DIM])]),
    "style_encoder": ("style_encoder.onnx", [("features", ["N", "T", DIM]), ("mask", ["N", "T"])],
                      [("style", ["N", STYLE_DIM])]),
    "denoiser": ("denoiser.onnx", [("x_t", ["N", 7, 256]), ("t", ["N"]), ("content", ["N", 7, 256]),
                                   ("trajectory", ["N", "T", TRAJ_DIMS]), ("mask", ["N", "T"]),
                                   ("style", ["N", STYLE_DIM])],
                 [("pred", ["N", 7, 256])]),
}

# Where each official module's weights live: (checkpoint argument, key prefix). The first
# source holding the prefix wins; denoiser.ckpt first, as demo_transfer.py loads it last and
# strictly. Keys under other prefixes (t2m_* evaluators, motionclip.decoder, clip_model) are
# not needed for inference and are ignored.
WEIGHT_SOURCES = {
    "vae": (("denoiser", "vae."), ("vae", "vae.")),
    "denoiser": (("denoiser", "denoiser."),),
    "motionclip_encoder": (("denoiser", "motionclip.encoder."), ("motionclip", "encoder.")),
}
# Two sources of the same module may differ by float noise only (frozen during diffusion
# training: mld.py sets requires_grad False on the VAE and MotionCLIP).
SAME_WEIGHTS_ATOL = 1e-6


class ExportError(Exception):
    """A bad input of the exporter; main() prints it as one line and exits 1."""


# --- pure parts (no torch) ------------------------------------------------------------------

def check_repo(repo: Path) -> None:
    missing = [f for f in REPO_FILES if not (repo / f).is_file()]
    if missing:
        raise ExportError(f"{repo}: not an MCM-LDM clone (missing {', '.join(missing)})")


def check_output(out: Path) -> None:
    if out.exists():
        raise ExportError(f"{out}: already exists; choose a new package directory")
    if not out.parent.is_dir():
        raise ExportError(f"{out.parent}: no such directory")


def load_stats(mean_path: Path, std_path: Path) -> tuple[np.ndarray, np.ndarray]:
    """HumanML3D Mean.npy / Std.npy: (263,) finite, std > 0 (the content is divided by it)."""
    out = []
    for path, what in ((mean_path, "mean"), (std_path, "std")):
        try:
            a = np.load(path, allow_pickle=False)
        except (OSError, ValueError, EOFError) as e:
            raise ExportError(f"{path}: not a readable .npy file ({e})") from None
        if a.shape != (DIM,) or not np.issubdtype(a.dtype, np.floating) or not np.isfinite(a).all():
            raise ExportError(f"{path}: {what} must be {DIM} finite floats, got shape {a.shape} {a.dtype}")
        out.append(a.astype(np.float32))
    if (out[1] <= 0).any():
        raise ExportError(f"{std_path}: std must be > 0 everywhere (dimension {int(np.argmin(out[1]))} "
                          f"is {out[1].min()})")
    return out[0], out[1]


def strip_prefix(state: dict, prefix: str) -> dict:
    return {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}


def max_abs_diff(a: dict, b: dict) -> float:
    """Largest absolute difference between two weight dicts; inf if their keys or shapes differ."""
    if a.keys() != b.keys():
        return float("inf")
    worst = 0.0
    for k in a:
        x, y = np.asarray(a[k], np.float64), np.asarray(b[k], np.float64)
        if x.shape != y.shape:
            return float("inf")
        worst = max(worst, float(np.abs(x - y).max(initial=0.0)))
    return worst


def select_weights(checkpoints: dict[str, dict], names: dict[str, str]) -> tuple[dict, list[str]]:
    """Weights of each official module from the checkpoints' state dicts.

    `checkpoints` maps argument name ("denoiser", "vae", "motionclip") to its state dict and
    `names` to the file name used in messages. Returns ({module: weights}, notes): a note for
    each module taken from a fall-back file, and for each pair of sources that disagree."""
    chosen, notes = {}, []
    for module, sources in WEIGHT_SOURCES.items():
        found = [(arg, prefix, strip_prefix(checkpoints[arg], prefix)) for arg, prefix in sources]
        found = [f for f in found if f[2]]
        if not found:
            where = " or ".join(f"'{p}*' in {names[a]}" for a, p in sources)
            raise ExportError(f"no weights for the {module}: expected keys {where}")
        arg, prefix, weights = found[0]
        chosen[module] = weights
        if arg != sources[0][0]:
            notes.append(f"{module}: weights from {names[arg]} ({names[sources[0][0]]} has no '{sources[0][1]}*' keys)")
        for other, other_prefix, other_weights in found[1:]:
            diff = max_abs_diff(weights, other_weights)
            if diff > SAME_WEIGHTS_ATOL:
                notes.append(f"{module}: {names[other]} ('{other_prefix}*') differs from {names[arg]} "
                             f"('{prefix}*') by up to {diff:.3g}; using {names[arg]}, as the official demo does")
    return chosen, notes


def write_package_manifest(out_dir: Path, mean: np.ndarray, std: np.ndarray, sources: dict[str, Path]) -> Path:
    """The style-transfer manifest for the ONNX files in out_dir (sha256 of each)."""
    components = {role: (file, C.sha256_file(out_dir / file), inputs, outputs)
                  for role, (file, inputs, outputs) in COMPONENTS.items()}
    comment = "# Exported by models/export/mcm_ldm.py from the official MCM-LDM checkpoints:\n" + "".join(
        f"#   {path.name} sha256 {C.sha256_file(path)}\n" for path in sources.values())
    return S.write_manifest(
        out_dir, name="mcm-ldm",
        description="MCM-LDM (Song et al., CVPR 2024) exported from the official checkpoints "
                    "(XingliangJin/MCM-LDM): arbitrary motion style transfer on HumanML3D features.",
        max_frames=MAX_FRAMES, mean=mean, std=std,
        sampler={"set_alpha_to_one": False, "guidance": GUIDANCE, "content_guidance": CONTENT_GUIDANCE,
                 "style_guidance": STYLE_GUIDANCE},
        components=components, extra_comment=comment)


def fsync_path(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def publish(staging: Path, out: Path) -> None:
    """Make a complete package visible under its final name: fsync files, rename, fsync parent."""
    for f in staging.iterdir():
        fsync_path(f)
    fsync_path(staging)
    os.rename(staging, out)
    fsync_path(out.parent)


def recover_from_ric(features: np.ndarray) -> np.ndarray:
    """Joints (T, 22, 3) from denormalised HumanML3D features (T, 263), in float64.

    HumanML3D's `recover_from_ric` (MCM-LDM mld/data/humanml/scripts/motion_process.py:420, with
    `recover_root_rot_pos` at :367; the same in EricGuo5513/HumanML3D): root yaw = cumulative
    sum of dim 0 (shifted by one frame), root xz = cumulative sum of the yaw-rotated dims 1..2,
    root height = dim 3, joints 1..21 = dims 4..66 rotated by the root yaw and shifted by the
    root xz. The root quaternion (cos a, 0, sin a, 0) is a rotation by 2a about y; here as
    matrices."""
    f = np.asarray(features, np.float64)
    angle = np.concatenate([[0.0], np.cumsum(f[:-1, 0])])
    c, s = np.cos(2 * angle), np.sin(2 * angle)
    # inverse of the root rotation: about y by -2a, applied to (x, z)
    vx, vz = np.zeros(len(f)), np.zeros(len(f))
    vx[1:], vz[1:] = f[:-1, 1], f[:-1, 2]
    root = np.stack([np.cumsum(c * vx - s * vz), f[:, 3], np.cumsum(s * vx + c * vz)], axis=-1)
    local = f[:, 4:4 + (JOINTS - 1) * 3].reshape(len(f), JOINTS - 1, 3)
    x = c[:, None] * local[..., 0] - s[:, None] * local[..., 2] + root[:, None, 0]
    z = s[:, None] * local[..., 0] + c[:, None] * local[..., 2] + root[:, None, 2]
    joints = np.stack([x, local[..., 1], z], axis=-1)
    return np.concatenate([root[:, None], joints], axis=1)


def relative(got: np.ndarray, ref: np.ndarray) -> tuple[float, float]:
    """(max abs difference, that divided by the reference's max magnitude)."""
    diff = float(np.abs(np.asarray(got, np.float64) - np.asarray(ref, np.float64)).max())
    return diff, diff / max(float(np.abs(ref).max()), 1e-12)


# --- torch parts ----------------------------------------------------------------------------

def first_line(e: Exception) -> str:
    return (str(e).strip().splitlines() or [type(e).__name__])[0]


def load_checkpoint(path: Path, allow_pickle: bool) -> dict:
    """The state dict of a Lightning .ckpt ({"state_dict": ...}) or a plain dict of tensors."""
    import pickle

    import torch

    try:
        obj = torch.load(path, map_location="cpu", weights_only=not allow_pickle)
    except pickle.UnpicklingError:
        raise ExportError(f"{path}: holds Python objects besides tensors; if you trust this file, "
                          f"re-run with --allow-pickle") from None
    except (OSError, RuntimeError, EOFError, ValueError) as e:
        raise ExportError(f"{path}: not a readable PyTorch checkpoint ({first_line(e)})") from None
    state = obj.get("state_dict", obj) if isinstance(obj, dict) else None
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise ExportError(f"{path}: no state dict of tensors (neither a Lightning checkpoint nor a weights dict)")
    return state


def build(args) -> tuple:
    """Official modules with the checkpoints' weights, and the Mean/Std."""
    import mcm_ldm_torch as T

    mean, std = load_stats(args.mean, args.std)
    paths = {"denoiser": args.denoiser, "vae": args.vae, "motionclip": args.motionclip}
    states = {k: load_checkpoint(p, args.allow_pickle) for k, p in paths.items()}
    weights, notes = select_weights(states, {k: p.name for k, p in paths.items()})
    for note in notes:
        print(f"note: {note}", file=sys.stderr)
    official = T.Official(args.repo)
    official.load(weights)
    return official, mean, std, paths


def export_package(args) -> tuple:
    import mcm_ldm_torch as T

    t0 = time.perf_counter()
    official, mean, std, paths = build(args)
    staging = Path(tempfile.mkdtemp(prefix=f".{args.out.name}.partial-", dir=args.out.parent))
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(staging, 0o777 & ~umask)  # mkdtemp's 0700 would make the package private
    try:
        T.export(official, staging)
        write_package_manifest(staging, mean, std, paths)
        publish(staging, args.out)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    print(f"exported {args.out} in {time.perf_counter() - t0:.1f} s")
    return official, mean, std


# --- --verify --------------------------------------------------------------------------------

# Pairs from the clone's demo folders: a 6-frame content (the shortest demo content, the
# batch-1 and short-length edge case), a 38-frame and a 161-frame one; styles of 59 and 199 frames.
DEFAULT_PAIRS = (("demo/content_test_feats/003790-5.npy", "demo/style_motion/old.npy"),
                 ("demo/content_motion/jump.npy", "demo/style_test_feats/1_001666-0.npy"),
                 ("demo/content_motion/walk_and_turn.npy", "demo/style_motion/hands_high.npy"))
# The target for the whole loop (features, relative to their largest magnitude), also
# applied to each component's output: float32 rounding in ~10 transformer layers gives ~1e-6,
# while a wrong mask, a sample instead of the mean or a wrong guidance weight give >= 1e-2.
TOLERANCE = 1e-4


def load_features(path: Path) -> np.ndarray:
    try:
        a = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as e:
        raise ExportError(f"{path}: not a readable .npy file ({e})") from None
    if a.ndim != 2 or a.shape[1] != DIM or not np.isfinite(a).all():
        raise ExportError(f"{path}: expected finite HumanML3D features (T, {DIM}), got {a.shape}")
    return a.astype(np.float32)


def verify_components(official, pkg: Path, content: np.ndarray, style: np.ndarray, mean, std) -> tuple[list, float]:
    """Each ONNX component against the official module on the pair's own inputs: at N = 1, and at
    N = 2 with the second row shorter (padding masked), at three timesteps for the denoiser.
    Returns the printed lines and the largest relative difference."""
    import onnxruntime as ort

    import mcm_ldm_torch as T

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    sess = {role: ort.InferenceSession(str(pkg / file), opts, providers=["CPUExecutionProvider"])
            for role, (file, _, _) in COMPONENTS.items()}
    c = (content - mean) / std
    traj = c[:, :TRAJ_DIMS].copy()
    c[:, :TRAJ_DIMS] = 0
    s = style.copy()
    s[:, :TRAJ_DIMS] = 0
    rng = np.random.default_rng(7)

    def batch2(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rows: the sequence, and its first 2/3 padded with noise (which the mask must hide)."""
        short = max(1, 2 * len(a) // 3)
        second = a.copy()
        second[short:] = rng.standard_normal(second[short:].shape)
        mask = np.ones((2, len(a)), np.float32)
        mask[1, short:] = 0
        return np.stack([a, second]).astype(np.float32), mask

    lines, worst = [], [0.0]

    def compare(role: str, feeds: dict, valid: np.ndarray | None = None) -> None:
        (got,) = sess[role].run(None, feeds)
        ref = T.official_components(official, role, feeds)
        if valid is not None:  # padded frames: the official decoder zeroes them, compare valid ones
            got, ref = got[valid], ref[valid]
        d, r = relative(got, ref)
        worst[0] = max(worst[0], r)
        n = feeds[next(iter(feeds))].shape[0]
        lines.append(f"  {role:<13} N={n}  max abs {d:.2e}  rel {r:.2e}")

    ones = np.ones((1, len(c)), np.float32)
    compare("vae_encoder", {"features": c[None], "mask": ones})
    feats2, mask2 = batch2(c)
    compare("vae_encoder", {"features": feats2, "mask": mask2})
    compare("style_encoder", {"features": s[None], "mask": np.ones((1, len(s)), np.float32)})
    sfeats2, smask2 = batch2(s)
    compare("style_encoder", {"features": sfeats2, "mask": smask2})
    (latent,) = sess["vae_encoder"].run(None, {"features": c[None], "mask": ones})
    (style_vec,) = sess["style_encoder"].run(None, {"features": s[None], "mask": np.ones((1, len(s)), np.float32)})
    compare("vae_decoder", {"latent": latent, "mask": ones})
    compare("vae_decoder", {"latent": np.concatenate([latent, latent]), "mask": mask2}, valid=mask2 > 0.5)
    x_t = rng.standard_normal(latent.shape).astype(np.float32)
    traj2, _ = batch2(traj)
    for t in (981, 501, 1):
        # N = 2: the official denoiser cannot run N = 1 (its .squeeze()); rows are independent,
        # so N = 1 is checked against the official batch's first row.
        feeds = {"x_t": np.concatenate([x_t, x_t]), "t": np.array([t, t], np.int64),
                 "content": np.concatenate([latent, latent]), "trajectory": traj2, "mask": mask2,
                 "style": np.concatenate([style_vec, np.zeros_like(style_vec)])}
        compare("denoiser", feeds)
        ref = T.official_components(official, "denoiser", feeds)[:1]
        (got,) = sess["denoiser"].run(None, {k: v[:1] for k, v in feeds.items()})
        d, r = relative(got, ref)
        worst[0] = max(worst[0], r)
        lines.append(f"  denoiser      N=1  max abs {d:.2e}  rel {r:.2e}  (t={t})")
    return lines, worst[0]


def run_reference_loop(args, stem: Path, content: Path, style: Path, x_t: Path) -> np.ndarray:
    """The package's numpy + onnxruntime loop (models/packages/stylize_reference.py): raw features."""
    out = stem.with_suffix(".npy")
    subprocess.run([sys.executable, str(PACKAGES / "stylize_reference.py"), "--model", str(args.out),
                    "--content", str(content), "--style", str(style), "-o", str(out),
                    "--init-noise", str(x_t), "--guidance", str(GUIDANCE), "--threads", "1"],
                   check=True, stdout=subprocess.DEVNULL)
    return np.load(out)


def run_choreod(args, stem: Path, content: Path, style: Path, x_t: Path) -> np.ndarray:
    """`choreod stylize --init-noise` on the package: the denormalised features it writes to
    /motion/features of its HDF5 motion file."""
    import h5py

    out = stem.with_suffix(".h5")
    done = subprocess.run([args.choreod, "stylize", "--model", str(args.out), "--content", str(content),
                           "--style", str(style), "--init-noise", str(x_t), "--guidance", str(GUIDANCE),
                           "--intra-threads", "1", "-o", str(out)],
                          stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    if done.returncode != 0:
        raise ExportError(f"{args.choreod} stylize failed (exit {done.returncode}): {done.stderr.strip()}")
    with h5py.File(out, "r") as f:
        return f["motion/features"][()]


def verify(args, official, mean: np.ndarray, std: np.ndarray) -> bool:
    import mcm_ldm_torch as T

    pairs = [tuple(Path(p) for p in pair) for pair in args.pair] if args.pair else \
        [(args.repo / c, args.repo / s) for c, s in DEFAULT_PAIRS]
    worst, worst_component = 0.0, 0.0
    with tempfile.TemporaryDirectory(prefix="mcm-ldm-verify-") as tmp:
        for i, (content_path, style_path) in enumerate(pairs):
            content, style = load_features(content_path), load_features(style_path)
            if not len(content) <= MAX_FRAMES:
                raise ExportError(f"{content_path}: {len(content)} frames, the exported VAE takes at most {MAX_FRAMES}")
            if len(style) < S.MIN_STYLE_FRAMES:
                raise ExportError(f"{style_path}: {len(style)} frames, a style needs at least {S.MIN_STYLE_FRAMES}")
            print(f"pair {i + 1}: content {content_path.name} ({len(content)} frames), "
                  f"style {style_path.name} ({len(style)} frames)")
            lines, component_rel = verify_components(official, args.out, content, style, mean, std)
            print("\n".join(lines))
            worst_component = max(worst_component, component_rel)
            x_t = np.random.default_rng(1000 + i).standard_normal((1, 7, 256)).astype(np.float32)
            xt_path = Path(tmp) / f"x_t_{i}.npy"
            np.save(xt_path, x_t)
            t0 = time.perf_counter()
            ref_feats, ref_joints = T.official_transfer(official, mean, std, content, style, x_t, GUIDANCE)
            torch_s = time.perf_counter() - t0
            print(f"  whole loop (DDIM 50, guidance {GUIDANCE}), official torch {torch_s:.1f} s:")
            for label, run in (("package reference loop", run_reference_loop),
                               ("choreod stylize", run_choreod)):
                t0 = time.perf_counter()
                ours = run(args, Path(tmp) / f"ours_{i}", content_path, style_path, xt_path)
                seconds = time.perf_counter() - t0
                feats_diff, feats_rel = relative((ours - mean) / std, ref_feats)
                joints_diff, joints_rel = relative(recover_from_ric(ours), ref_joints)
                worst = max(worst, feats_rel)
                print(f"    {label:<22} normalised features max abs {feats_diff:.2e} rel {feats_rel:.2e}; "
                      f"joints max abs {joints_diff:.2e} m rel {joints_rel:.2e} ({seconds:.1f} s)")
    ok = worst <= TOLERANCE and worst_component <= TOLERANCE
    print(json.dumps({"verify": "ok" if ok else "failed", "pairs": len(pairs),
                      "worst_component_rel": float(f"{worst_component:.3g}"),
                      "worst_features_rel": float(f"{worst:.3g}"), "tolerance": TOLERANCE}))
    return ok


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repo", type=Path, required=True, help="a clone of XingliangJin/MCM-LDM")
    ap.add_argument("--vae", type=Path, required=True, help="checkpoints/vae_checkpoint/vae7.ckpt")
    ap.add_argument("--denoiser", type=Path, required=True, help="checkpoints/denoiser_checkpoint/denoiser.ckpt")
    ap.add_argument("--motionclip", type=Path, required=True,
                    help="checkpoints/motionclip_checkpoint/motionclip.pth.tar")
    ap.add_argument("--mean", type=Path, required=True, help="HumanML3D Mean.npy (263,)")
    ap.add_argument("--std", type=Path, required=True, help="HumanML3D Std.npy (263,)")
    ap.add_argument("-o", "--out", type=Path, required=True, help="package directory to create")
    ap.add_argument("--verify", action="store_true", help="compare the package with the official PyTorch loop")
    ap.add_argument("--pair", nargs=2, action="append", metavar=("CONTENT", "STYLE"),
                    help="raw HumanML3D .npy content/style pair for --verify (repeatable; default: "
                         "three of the clone's demo pairs)")
    ap.add_argument("--choreod", metavar="BIN", default=shutil.which("choreod"),
                    help="the choreod binary --verify runs (`stylize --init-noise`); default: choreod on PATH")
    ap.add_argument("--allow-pickle", action="store_true",
                    help="load checkpoints holding Python objects besides tensors (runs their pickle code: "
                         "only for files you trust)")
    a = ap.parse_args(argv)
    for name in ("vae", "denoiser", "motionclip", "mean", "std"):
        path = getattr(a, name)
        if not path.is_file():
            ap.error(f"--{name} {path}: no such file")
    for pair in a.pair or []:
        for p in pair:
            if not Path(p).is_file():
                ap.error(f"--pair {p}: no such file")
    if a.pair and not a.verify:
        ap.error("--pair needs --verify")
    if a.verify and (a.choreod is None or shutil.which(a.choreod) is None):
        ap.error(f"--verify runs `choreod stylize`: {a.choreod or 'choreod'} is not an executable "
                 "(put choreod on PATH or pass --choreod BIN)")
    return a


def main(argv=None) -> int:
    args = parse_args(argv)
    try:
        check_repo(args.repo)
        check_output(args.out)
        official, mean, std = export_package(args)
        if args.verify and not verify(args, official, mean, std):
            print(f"mcm_ldm.py: error: {args.out}: the package differs from the official modules or loop by more "
                  f"than {TOLERANCE} (relative)", file=sys.stderr)
            return 1
    except ExportError as e:
        print(f"mcm_ldm.py: error: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    # Run the importable module, not __main__, so mcm_ldm_torch and this code share one
    # ExportError class and one set of constants.
    import mcm_ldm

    sys.exit(mcm_ldm.main())
