"""Shared pieces of the style-transfer package builders: contract constants, the scaled-linear
schedule, the manifest writer and the onnxruntime checks every style-transfer package passes.

The contract (task "style-transfer", components by role) is documented in models/packages/README.md
("Style-transfer packages"); facts on MCM-LDM in ../shared/notes/reference-facts.md section 1.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

import pkg_common as C

FPS = 20.0  # HumanML3D frame rate (EricGuo5513/HumanML3D raw_pose_processing.ipynb: downsample to 20 fps)
DIM = 263  # HumanML3D feature width (motion_representation.ipynb: 4 + 63 + 126 + 66 + 4)
TRAJ_DIMS = 3  # trajectory condition = normalised dims 0..3 (MCM-LDM mld/models/modeltype/mld.py forward)
# Motion lengths MCM-LDM trained on: XingliangJin/MCM-LDM configs/base.yaml DATASET.SAMPLER
# MIN_LEN 40 (2 s, the shortest style the encoders ever saw) and MAX_LEN 196.
MIN_STYLE_FRAMES = 40
TRAINED_MAX_FRAMES = 196

# MCM-LDM configs/modules/scheduler.yaml (identical in ChenFengYe/motion-latent-diffusion):
# DDIM, 1000 train steps, scaled_linear 0.00085 -> 0.012, steps_offset 1, set_alpha_to_one false.
TRAIN_STEPS = 1000
BETA_START = 0.00085
BETA_END = 0.012


def alphas_cumprod() -> np.ndarray:
    """diffusers `scaled_linear`: betas = linspace(sqrt(beta_start), sqrt(beta_end), T) ** 2.

    float64 here; diffusers computes in float32 (relative difference ~1e-7, far below every
    tolerance that uses this)."""
    betas = np.linspace(BETA_START ** 0.5, BETA_END ** 0.5, TRAIN_STEPS, dtype=np.float64) ** 2
    return np.cumprod(1.0 - betas)


def tensor_row(name: str, shape) -> str:
    dims = ", ".join(f'"{d}"' if isinstance(d, str) else str(d) for d in shape)
    return f'{{ name = "{name}", dtype = "{"int64" if name == "t" else "float32"}", shape = [{dims}] }}'


def write_manifest(out_dir: Path, *, name: str, description: str, max_frames: int,
                   mean: np.ndarray, std: np.ndarray, sampler: dict, components: dict,
                   extra_comment: str = "") -> Path:
    """Write a style-transfer `choreod-model.toml`.

    `components` maps role -> (file, sha256, [(input, shape)], [(output, shape)]) in the
    contract's order: vae_encoder, vae_decoder, style_encoder, denoiser.
    `sampler` holds the [sampler] values (guidance, content_guidance, style_guidance,
    set_alpha_to_one; the rest are MCM-LDM's)."""
    comp_text = ""
    for role, (file, sha, ins, outs) in components.items():
        ins_t = "\n".join(f"  {tensor_row(n, s)}," for n, s in ins)
        outs_t = ", ".join(tensor_row(n, s) for n, s in outs)
        comp_text += f"""
[components.{role}]
file = {C.toml_str(file)}
sha256 = "{sha}"
inputs = [
{ins_t}
]
outputs = [ {outs_t} ]
"""
    text = f"""# choreod model package manifest (written by models/packages/build.py; do not edit by hand:
# rebuild instead, the sha256 values below must match the ONNX files).
{extra_comment}format = "choreod-model"
format_version = 1
name = {C.toml_str(name)}
description = {C.toml_str(description)}
task = "style-transfer"

[motion]
fps = {C.fmt_float(FPS)}
skeleton = "t2m22"
representation = "humanml3d263"
dim = {DIM}
max_frames = {max_frames}
min_frames = {MIN_STYLE_FRAMES}
mean = {C.float_list(mean)}
std = {C.float_list(std)}

[diffusion]
train_steps = {TRAIN_STEPS}
beta_schedule = "scaled_linear"
beta_start = {BETA_START!r}
beta_end = {BETA_END!r}
prediction = "epsilon"
clip_sample = false

[sampler]
kind = "ddim"
steps = 50
eta = 0.0
steps_offset = 1
set_alpha_to_one = {str(sampler["set_alpha_to_one"]).lower()}
guidance = {C.fmt_float(sampler["guidance"])}
content_guidance = {C.fmt_float(sampler["content_guidance"])}
style_guidance = {C.fmt_float(sampler["style_guidance"])}
inversion_steps = 30
{comp_text}"""
    path = out_dir / "choreod-model.toml"
    path.write_text(text, encoding="utf-8")
    return path


# --- checks (build.py check DIR) ------------------------------------------------------------

def fail(msg: str) -> None:
    raise SystemExit(f"check failed: {msg}")


def sessions(pkg: Path, manifest: dict) -> dict:
    """One onnxruntime session per component, after checking each file's sha256."""
    import onnxruntime as ort

    out = {}
    for role, comp in manifest["components"].items():
        data = (pkg / comp["file"]).read_bytes()
        got = hashlib.sha256(data).hexdigest()
        if got != comp["sha256"]:
            fail(f"{pkg / comp['file']}: sha256 {got} does not match the manifest's {comp['sha256']}")
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = 2
        out[role] = ort.InferenceSession(data, opts, providers=["CPUExecutionProvider"])
    return out


def random_motion(rng: np.random.Generator, n: int, t: int) -> np.ndarray:
    """Feature-shaped input with a smooth, motion-like time course (random walk, unit scale)."""
    x = np.cumsum(rng.standard_normal((n, t, DIM)), axis=1) / np.sqrt(t)
    return x.astype(np.float32)


def check_contract(pkg: Path, m: dict, sess: dict, lengths=(60, 33)) -> None:
    """Names and dtypes against the manifest; N=1 and N=3 runs; rows independent; finite;
    padded frames (mask 0) never change the valid frames' outputs."""
    if m.get("format") != "choreod-model" or m.get("format_version") != 1 or m.get("task") != "style-transfer":
        fail(f"{pkg}: format/format_version/task")
    if set(m["components"]) != {"vae_encoder", "vae_decoder", "style_encoder", "denoiser"}:
        fail(f"components {sorted(m['components'])}")
    dt = {"float32": "tensor(float)", "int64": "tensor(int64)"}
    for role, s in sess.items():
        comp = m["components"][role]
        for got, want in (([(i.name, i.type) for i in s.get_inputs()], [(i["name"], dt[i["dtype"]]) for i in comp["inputs"]]),
                          ([(o.name, o.type) for o in s.get_outputs()], [(o["name"], dt[o["dtype"]]) for o in comp["outputs"]])):
            if got != want:
                fail(f"{role}: {got} != manifest {want}")
    rng = np.random.default_rng(1234)
    t_len = lengths[0]
    n = 3
    feats = random_motion(rng, n, t_len)
    feats[..., :TRAJ_DIMS] = 0.0
    mask = np.ones((n, t_len), np.float32)
    mask[1, lengths[1]:] = 0.0  # row 1 is shorter: padded frames
    (latent,) = sess["vae_encoder"].run(None, {"features": feats, "mask": mask})
    (style,) = sess["style_encoder"].run(None, {"features": feats, "mask": mask})
    traj = random_motion(rng, n, t_len)[..., :TRAJ_DIMS]
    feeds = {"x_t": rng.standard_normal(latent.shape).astype(np.float32),
             "t": np.array([1, 500, 981], np.int64), "content": latent, "trajectory": traj,
             "mask": mask, "style": style}
    (pred,) = sess["denoiser"].run(None, feeds)
    (dec,) = sess["vae_decoder"].run(None, {"latent": latent, "mask": mask})
    outs = {"latent": latent, "style": style, "pred": pred, "features": dec}
    for k, v in outs.items():
        if v.dtype != np.float32 or v.shape[0] != n or not np.isfinite(v).all():
            fail(f"N={n} {k}: {v.shape} {v.dtype} finite={np.isfinite(v).all()}")
    if pred.shape != latent.shape or dec.shape != feats.shape:
        fail(f"pred {pred.shape} / latent {latent.shape}; decoded {dec.shape} / features {feats.shape}")
    # Rows independent: each row alone equals its row of the batch. 1e-4 relative to the output
    # scale: batched MatMul kernels may sum in another order (float32).
    runs = (("vae_encoder", {"features": feats, "mask": mask}, latent),
            ("style_encoder", {"features": feats, "mask": mask}, style),
            ("denoiser", feeds, pred),
            ("vae_decoder", {"latent": latent, "mask": mask}, dec))
    for role, f, full in runs:
        scale = float(np.abs(full).max()) + 1e-6
        for i in range(n):
            (one,) = sess[role].run(None, {k: v[i:i + 1] for k, v in f.items()})
            err = float(np.abs(one[0] - full[i]).max())
            if err > 1e-4 * scale:
                fail(f"{role}: row {i} alone differs from the batch by {err} (scale {scale})")
    # Padding is ignored: garbage in row 1's padded frames changes nothing in its valid frames.
    f2 = feats.copy()
    f2[1, lengths[1]:] = 1e3 * rng.standard_normal((t_len - lengths[1], DIM))
    f2[1, lengths[1]:, :TRAJ_DIMS] = 0.0
    (style2,) = sess["style_encoder"].run(None, {"features": f2, "mask": mask})
    if np.abs(style2[1] - style[1]).max() > 1e-4 * (np.abs(style[1]).max() + 1e-6):
        fail("style_encoder: padded frames change the style")
    print(f"ok  {pkg}: 4 components, names/dtypes match the manifest; N=1 and N={n}, finite, rows "
          f"independent; padded style frames ignored; latent {list(latent.shape)}, style {list(style.shape)}")
