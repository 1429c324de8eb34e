"""Shared pieces of the package builders: contract constants, schedule, SMPL FK, manifest writer.

Everything here is deterministic: no clocks, no absolute paths, no unseeded randomness, so
that `build.py` produces the same bytes on every machine (checked by building twice and
comparing sha256, see README.md).
"""

from __future__ import annotations

import hashlib
import math
from pathlib import Path

import numpy as np
import onnx

# --- The contract (models/packages/README.md, DESIGN.md "Model packages") -----------------
FPS = 30.0
WINDOW_FRAMES = 150  # 5 s at 30 fps (Stanford-TML/EDGE: EDGE.py horizon 5 s, data/slice.py)
STRIDE_FRAMES = 75  # 2.5 s (Stanford-TML/EDGE: model/diffusion.py long_ddim_sample, test.py)
N_JOINTS = 24
DIM = 3 + (N_JOINTS - 1) * 3  # root xyz + 23 root-relative joints = 72
OPSET = 18

# Audio features: MoFusion defaults as our dsp computes them (DESIGN.md "MoFusion").
SAMPLE_RATE = 16000
N_FFT = 2048
HOP = 512
N_MELS = 80
FMIN = 0.0
FMAX = 8000.0
TOP_DB = 80.0
# ceil(window_s * sr / hop) = ceil(5 * 16000 / 512) = ceil(156.25) = 157 (model-contract.md)
MUSIC_FRAMES = math.ceil(WINDOW_FRAMES / FPS * SAMPLE_RATE / HOP)

# Diffusion schedule written into every shipped manifest (model-contract.md [diffusion]).
TRAIN_STEPS = 1000
BETA_START = 1e-4
BETA_END = 0.02

# SMPL kinematic tree and neutral rest offsets (metres, y-up), Stanford-TML/EDGE:vis.py
# `smpl_parents`, `smpl_offsets` (24 joints, "phone" joint commented out there too).
SMPL_PARENTS = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21]
SMPL_OFFSETS = np.array(
    [
        [0.0, 0.0, 0.0],
        [0.05858135, -0.08228004, -0.01766408],
        [-0.06030973, -0.09051332, -0.01354254],
        [0.00443945, 0.12440352, -0.03838522],
        [0.04345142, -0.38646945, 0.008037],
        [-0.04325663, -0.38368791, -0.00484304],
        [0.00448844, 0.1379564, 0.02682033],
        [-0.01479032, -0.42687458, -0.037428],
        [0.01905555, -0.4200455, -0.03456167],
        [-0.00226458, 0.05603239, 0.00285505],
        [0.04105436, -0.06028581, 0.12204243],
        [-0.03483987, -0.06210566, 0.13032329],
        [-0.0133902, 0.21163553, -0.03346758],
        [0.07170245, 0.11399969, -0.01889817],
        [-0.08295366, 0.11247234, -0.02370739],
        [0.01011321, 0.08893734, 0.05040987],
        [0.12292141, 0.04520509, -0.019046],
        [-0.11322832, 0.04685326, -0.00847207],
        [0.2553319, -0.01564902, -0.02294649],
        [-0.26012748, -0.01436928, -0.03126873],
        [0.26570925, 0.01269811, -0.00737473],
        [-0.26910836, 0.00679372, -0.00602676],
        [0.08669055, -0.01063603, -0.01559429],
        [-0.0887537, -0.00865157, -0.01010708],
    ],
    dtype=np.float64,
)


def alphas_cumprod(train_steps: int = TRAIN_STEPS, beta_start: float = BETA_START,
                   beta_end: float = BETA_END) -> np.ndarray:
    """Linear beta schedule as diffusers defines it (linspace(beta_start, beta_end, steps)).

    float64 on purpose: the cumulative product over 1000 factors drifts in float32; callers
    store the result as float32 only at the end.
    """
    betas = np.linspace(beta_start, beta_end, train_steps, dtype=np.float64)
    return np.cumprod(1.0 - betas)


def axis_angle_to_matrix(aa: np.ndarray) -> np.ndarray:
    """Rodrigues' formula, (..., 3) axis-angle -> (..., 3, 3), float64."""
    aa = np.asarray(aa, dtype=np.float64)
    theta = np.linalg.norm(aa, axis=-1, keepdims=True)
    # Small angles: the axis is undefined, but sin(theta)/theta -> 1 makes R -> I + [aa]x.
    safe = np.where(theta < 1e-12, 1.0, theta)
    k = aa / safe
    kx, ky, kz = k[..., 0], k[..., 1], k[..., 2]
    zero = np.zeros_like(kx)
    kmat = np.stack([zero, -kz, ky, kz, zero, -kx, -ky, kx, zero], axis=-1).reshape(aa.shape[:-1] + (3, 3))
    s = np.sin(theta)[..., None]
    c = np.cos(theta)[..., None]
    eye = np.eye(3)
    return eye + s * kmat + (1.0 - c) * (kmat @ kmat)


def smpl_forward_kinematics(poses: np.ndarray, root: np.ndarray) -> np.ndarray:
    """SMPL joint positions (T, 24, 3) from local axis-angle rotations (T, 24, 3) and root (T, 3).

    The same FK as Stanford-TML/EDGE:vis.py `SMPLSkeleton.forward` (world rotation of a joint =
    parent world rotation times its local rotation; position = parent position + parent world
    rotation applied to the rest offset), written with rotation matrices in float64.
    """
    local = axis_angle_to_matrix(poses)
    n = poses.shape[0]
    world_rot = np.zeros((n, N_JOINTS, 3, 3))
    pos = np.zeros((n, N_JOINTS, 3))
    for j, p in enumerate(SMPL_PARENTS):
        if p < 0:
            world_rot[:, j] = local[:, j]
            pos[:, j] = root
        else:
            world_rot[:, j] = world_rot[:, p] @ local[:, j]
            pos[:, j] = pos[:, p] + np.einsum("nab,b->na", world_rot[:, p], SMPL_OFFSETS[j])
    return pos


def joints_to_features(joints: np.ndarray) -> np.ndarray:
    """(T, 24, 3) -> (T, 72): root xyz, then joints 1..23 minus the root (contract representation)."""
    root = joints[:, 0, :]
    rel = joints[:, 1:, :] - root[:, None, :]
    return np.concatenate([root, rel.reshape(joints.shape[0], -1)], axis=1)


def features_to_joints(x: np.ndarray) -> np.ndarray:
    """(..., T, 72) -> (..., T, 24, 3), inverse of `joints_to_features`."""
    root = x[..., :3]
    rel = x[..., 3:].reshape(x.shape[:-1] + (N_JOINTS - 1, 3))
    return np.concatenate([root[..., None, :], rel + root[..., None, :]], axis=-2)


def fmt_float(v: float) -> str:
    """Shortest decimal that round-trips the float32 value (TOML float, parses back bit-exactly)."""
    s = np.format_float_positional(np.float32(v), unique=True, trim="0")
    if "e" not in s and "." not in s:
        s += ".0"
    return s


def toml_str(s: str) -> str:
    """A TOML basic string (escapes backslash, quote and control characters)."""
    out = s.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n").replace("\t", "\\t")
    return f'"{out}"'


def float_list(values) -> str:
    vals = [fmt_float(v) for v in np.asarray(values, dtype=np.float32).ravel()]
    lines = []
    for i in range(0, len(vals), 6):
        lines.append("  " + ", ".join(vals[i:i + 6]) + ",")
    return "[\n" + "\n".join(lines) + "\n]"


def write_manifest(out_dir: Path, *, name: str, description: str, mean: np.ndarray, std: np.ndarray,
                   onnx_file: str, onnx_sha256: str, guidance: float = 1.0, eta: float = 0.0, set_alpha_to_one: bool = False,
                   extra_comment: str = "", extra_outputs: str = "", extra_sections: str = "") -> Path:
    """Write `choreod-model.toml` following the contract's draft schema field by field.

    `extra_outputs`: further output tables after `pred` (e.g. `library`'s `source`);
    `extra_sections`: TOML sections placed before `[motion]` (e.g. `[license]`, `[library]`).
    """
    text = f"""# choreod model package manifest (written by models/packages/build.py; do not edit by hand:
# rebuild instead, the sha256 below must match the ONNX file).
{extra_comment}format = "choreod-model"
format_version = 1
name = {toml_str(name)}
description = {toml_str(description)}
task = "music-to-dance"
{extra_sections}
[motion]
fps = {fmt_float(FPS)}
skeleton = "smpl24"
representation = "smpl24-rootpos-rootrel"
dim = {DIM}
window_frames = {WINDOW_FRAMES}
stride_frames = {STRIDE_FRAMES}
mean = {float_list(mean)}
std = {float_list(std)}

[audio]
sample_rate = {SAMPLE_RATE}
n_fft = {N_FFT}
hop = {HOP}
n_mels = {N_MELS}
fmin = {fmt_float(FMIN)}
fmax = {fmt_float(FMAX)}
top_db = {fmt_float(TOP_DB)}
music_frames = {MUSIC_FRAMES}

[diffusion]
train_steps = {TRAIN_STEPS}
beta_schedule = "linear"
beta_start = {BETA_START!r}
beta_end = {BETA_END!r}
prediction = "epsilon"
clip_sample = false

[sampler]
kind = "ddim"
steps = 50
eta = {fmt_float(eta)}
steps_offset = 1
set_alpha_to_one = {str(set_alpha_to_one).lower()}
guidance = {fmt_float(guidance)}

[components.denoiser]
file = {toml_str(onnx_file)}
sha256 = "{onnx_sha256}"
inputs = [
  {{ name = "x_t", dtype = "float32", shape = ["N", {WINDOW_FRAMES}, {DIM}] }},
  {{ name = "t", dtype = "int64", shape = ["N"] }},
  {{ name = "music", dtype = "float32", shape = ["N", {MUSIC_FRAMES}, {N_MELS}] }},
  {{ name = "cond", dtype = "float32", shape = ["N"] }},
]
outputs = [ {{ name = "pred", dtype = "float32", shape = ["N", {WINDOW_FRAMES}, {DIM}] }}{extra_outputs} ]
"""
    path = out_dir / "choreod-model.toml"
    path.write_text(text, encoding="utf-8")
    return path


def save_model(model: onnx.ModelProto, path: Path) -> str:
    """Check the model, serialise it deterministically and return the file's sha256."""
    model.producer_name = "choreod models/packages/build.py"
    model.producer_version = "1"
    onnx.checker.check_model(model, full_check=True)
    data = model.SerializeToString(deterministic=True)
    path.write_bytes(data)
    return hashlib.sha256(data).hexdigest()


def sha256_file(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()
