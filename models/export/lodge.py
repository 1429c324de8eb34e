#!/usr/bin/env python3
"""Export LODGE's released FineDance checkpoints to a choreod `lodge` package.

    python models/export/lodge.py --repo PATH_TO_LODGE_CLONE \\
        --global exp/Global_Module/FineDance_Global/checkpoints/epoch=2999.ckpt \\
        --local exp/Local_Module/FineDance_FineTuneV2_Local/checkpoints/epoch=299.ckpt \\
        -o PACKAGE_DIR [--normalizer data/Normalizer.pth] [--verify] [--allow-pickle]

Imports LODGE's network classes from the clone (nothing of LODGE is copied into choreod), builds
them with the sizes the checkpoints' weight shapes say (the clone's configs disagree with the
released weights: LODGE issues #25 and #42), loads the weights strictly, exports the two
networks to ONNX — each split into its step-invariant music branch and the per-step denoiser,
with the randomness the official `forward` draws made into inputs — and writes
`choreod-model.toml`: the 35-dim music features, the 139-value SMPL-X representation with the
min-max normaliser of `data/Normalizer.pth` and the SMPL-X rest joints of the clone, the
schedule, the sampler, the 16 genres, the guidance of each stage and FineDance's licence terms.
The package appears under PACKAGE_DIR only when complete. See models/export/README.md.

--verify compares every exported network call with the official module's `forward` on the same
inputs (with and without the guidance drop), in onnxruntime on the CPU.
The whole loop, the official code against `choreod dance` on the same features and noise, is
lodge_verify_loop.py.

This file needs no torch for its own parts (checks, sizes from shapes, the pickle scan, the
manifest); the torch half is lodge_torch.py, imported only when exporting or verifying.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import pickletools
import shutil
import sys
import tempfile
import time
import zipfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "packages"))
sys.path.insert(0, str(HERE))

import mcm_ldm as M  # noqa: E402  (shared exporter helpers: errors, checkpoint loading, publishing)
import pkg_common as C  # noqa: E402

ExportError = M.ExportError

# --- facts of the official code (li-ronghui/LODGE, read at a898e59) ---------------------------

NFEATS = 139  # dld/data/render_joints/smplfk.py:95-117: 4 contacts, transl, 22 x 6D
MUSIC_DIM = 35  # dld/data/utils/audio.py `extract`: the FACT/EDGE 35-dim librosa set
FPS = 30.0  # FineDance motion and features (dld/data/utils/audio.py FPS = 30)
LIBROSA = "0.7.2"  # the version the 35-dim set is defined with (EDGE / FACT, LODGE's requirements)
STYLE_NOISE = 256  # model.py:947 `torch.randn(x.shape[0], 256)`, MappingNet(256, ...) model.py:758
# Global windows: infer_lodge.py:314 length1 = 1024 music frames; Global_Module.py:152-153 samples
# 104 keyframe frames for a 1024-frame window. Local windows: infer_lodge.py:315 length2 = 256.
GLOBAL_MUSIC_FRAMES = 1024
GLOBAL_KEYFRAMES = 104
LOCAL_FRAMES = 256
# Schedule: diffusion.py:82-86 with utils.py:78-86 (cosine, s = 0.008, betas clipped at 0.999,
# computed in float64, then cast to float32 and cumprod in float32); n_timestep 1000 (configs).
TRAIN_STEPS = 1000
COSINE_S = 0.008
MAX_BETA = 0.999
# Sampler: diffusion.py:262-294 and 491-545: DDIM, 50 steps, eta 1, timesteps
# int(linspace(-1, T - 1, steps + 1)) reversed (truncated toward zero), x0 clamped to [-1, 1].
STEPS = 50
ETA = 1.0
# torch.linspace(-1, 999, 51).int() reversed, without the final -1 (the last step returns x0):
# 999, 979, ..., 19 (checked with torch 2.15; the float32 linspace hits the integers exactly).
TIMESTEPS = list(range(TRAIN_STEPS - 1, 0, -(TRAIN_STEPS // STEPS)))
# Guidance: the configs' diffusion.params.guidance_weight 2 (coarse_finedance_fea139.yaml,
# finedance_fea139_finetune_v2.yaml); the local sampler ramps it: diffusion.py:507
# np.clip(np.linspace(0, 2 * w, steps), None, w).
GUIDANCE = 2.0
# Heads are not visible in the weights: 8 in both configs' DanceDecoder params.
HEADS = 8
# FineDance genres: dld/data/FineDance_dataset.py:48-72 `Genres_fd` (id -> first name; aliases).
GENRES = ["Breaking", "Popping", "Locking", "Hiphop", "Urban", "Jazz", "Tai", "Uighur", "Hmong",
          "HanTang", "ShenYun", "Kun", "DunHuang", "Korean", "Choreography", "Chinese"]
GENRE_ALIASES = {"jazz": 5, "Dai": 6, "Wei": 7, "Miao": 8}
# SMPL-X rest joints: the code reads data/smplx_neu_J_1.npy (Local_Module.py:108); the clone
# ships it as dld/data/utils/smplx_neu_J_1.npy.
REST_JOINTS_PATHS = ("data/smplx_neu_J_1.npy", "dld/data/utils/smplx_neu_J_1.npy")
REST_JOINTS = 55
NORMALIZER_PATH = "data/Normalizer.pth"  # configs/data/assets.yaml:22
REPO_FILES = ("dld/models/architectures/model.py", "dld/models/architectures/utils.py",
              "dld/models/architectures/rotary_embedding_torch.py", "dld/data/render_joints/smplfk.py",
              "dld/data/utils/preprocess.py")
PREFIX = "DanceDecoder."  # Global_Module / Local_Module attribute; diffusion.model.* is the same object

LICENSE = {
    "name": "FineDance (non-commercial research use)",
    "commercial_use": False,
    "redistribution": False,
    "summary": ("These weights were trained on FineDance, whose terms allow non-commercial research "
                "use only and no redistribution; LODGE's code has no licence and is not part of this "
                "package. Do not share this package or use its output commercially."),
    "url": "https://github.com/li-ronghui/FineDance",
}

OPSET = C.OPSET


def decoder_layers(kind: str, s: dict) -> int:
    """Layers of the main decoder stack: the local constructor appends its refine layer to it
    (model.py:850-862), so it holds num_layers + 1."""
    return s["num_layers"] + (1 if kind == "local" else 0)


def official_windows(frames: int) -> tuple[int, int]:
    """(Global, Local) windows the official loop makes of `frames` feature frames: the tail under
    256 frames is dropped, then one Global window per 4 Local ones, rounded up
    (infer_lodge.py:211-218)."""
    local = frames // LOCAL_FRAMES
    per_global = GLOBAL_MUSIC_FRAMES // LOCAL_FRAMES
    return -(-local // per_global), local


def components(sizes: dict) -> dict:
    """role -> (file, [(input, dtype, shape)], [(output, dtype, shape)]) for the package.

    The music branch hands the denoiser, besides the FiLM vector `cond_hidden`, every decoder
    layer's cross-attention keys and values of the music tokens (`cross_k`, `cross_v`, layer
    axis second): they depend on neither x_t nor t, so the denoiser projects only the time (and
    style) tokens per step (see lodge_torch.Denoiser)."""
    g, loc = sizes["global"], sizes["local"]

    def kv(kind: str, s: dict, frames: int) -> list:
        shape = ["N", decoder_layers(kind, s), frames, s["latent_dim"]]
        return [("cond_hidden", "float32", ["N", s["latent_dim"]]),
                ("cross_k", "float32", shape), ("cross_v", "float32", shape)]

    def music(kind: str, s: dict) -> tuple:
        return ([("music", "float32", ["N", s["seq_len"], MUSIC_DIM]), ("keep", "float32", ["N"])],
                kv(kind, s, s["seq_len"]))

    def denoiser(kind: str, s: dict, frames: int, extra: list) -> tuple:
        return ([("x_t", "float32", ["N", frames, NFEATS]), ("t", "int64", ["N"]),
                 *kv(kind, s, s["seq_len"]), *extra],
                [("x0", "float32", ["N", frames, NFEATS])])

    return {
        "global_music": ("global_music.onnx", *music("global", g)),
        "global_denoiser": ("global_denoiser.onnx", *denoiser("global", g, GLOBAL_KEYFRAMES, [])),
        "local_music": ("local_music.onnx", *music("local", loc)),
        "local_denoiser": ("local_denoiser.onnx", *denoiser(
            "local", loc, LOCAL_FRAMES,
            [("genre", "int64", ["N"]), ("style_noise", "float32", ["N", STYLE_NOISE])])),
    }


# --- pure parts (no torch) ------------------------------------------------------------------

def check_repo(repo: Path) -> Path:
    """The clone's files the exporter relies on; returns the rest-joint file."""
    missing = [f for f in REPO_FILES if not (repo / f).is_file()]
    if missing:
        raise ExportError(f"{repo}: not a LODGE clone (missing {', '.join(missing)})")
    for rel in REST_JOINTS_PATHS:
        if (repo / rel).is_file():
            return repo / rel
    raise ExportError(f"{repo}: no SMPL-X rest joints ({' or '.join(REST_JOINTS_PATHS)})")


def load_rest_joints(path: Path) -> np.ndarray:
    try:
        a = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as e:
        raise ExportError(f"{path}: not a readable .npy file ({e})") from None
    if a.shape != (REST_JOINTS, 3) or not np.issubdtype(a.dtype, np.floating) or not np.isfinite(a).all():
        raise ExportError(f"{path}: expected {REST_JOINTS} x 3 finite SMPL-X rest joints, got {a.shape} {a.dtype}")
    return a.astype(np.float64)


def _count(shapes: dict, prefix: str) -> int:
    n = 0
    while any(k.startswith(f"{prefix}{n}.") for k in shapes):
        n += 1
    return n


def infer_sizes(shapes: dict, kind: str, name: str) -> dict:
    """Constructor sizes of the official network from its state dict's shapes (no prefix).

    kind "global" is `DanceDecoder` (model.py:382-532), "local" `Refine_DanceDecoder`
    (model.py:733-993), whose constructor appends its "refine" layer to the main stack
    (model.py:850-862): the main stack holds num_layers + 1 layers."""
    def shape(key: str, rank: int) -> tuple:
        if key not in shapes:
            raise ExportError(f"{name}: no '{PREFIX}{key}' weight: not a LODGE {kind} checkpoint")
        s = tuple(shapes[key])
        if len(s) != rank:
            raise ExportError(f"{name}: '{PREFIX}{key}' has shape {s}, expected rank {rank}")
        return s

    latent, nfeats = shape("input_projection.weight", 2)
    _, cond_dim = shape("cond_projection.weight", 2)
    _, seq_len, latent2 = shape("null_cond_embed", 3)
    ff, _ = shape("cond_encoder.0.linear1.weight", 2)
    layers = _count(shapes, "seqTransDecoder.stack.")
    sizes = {"latent_dim": latent, "nfeats": nfeats, "cond_feature_dim": cond_dim, "seq_len": seq_len,
             "ff_size": ff, "num_layers": layers, "use_rotary": "rotary.freqs" in shapes}
    if nfeats != NFEATS or cond_dim != MUSIC_DIM or latent2 != latent:
        raise ExportError(f"{name}: {nfeats} motion values and {cond_dim} music features per frame (latent "
                          f"{latent}/{latent2}); LODGE's FineDance networks take {NFEATS} and {MUSIC_DIM}")
    if kind == "local":
        genres = _count(shapes, "mapping.unshared.")
        _, noise = shape("mapping.shared.0.weight", 2)
        if noise != STYLE_NOISE:
            raise ExportError(f"{name}: style mapping takes {noise} values; the official forward draws "
                              f"{STYLE_NOISE} (model.py:947)")
        if genres != len(GENRES):
            raise ExportError(f"{name}: {genres} genre heads, FineDance has {len(GENRES)}")
        if layers < 2:
            raise ExportError(f"{name}: {layers} decoder layers; the refine decoder has at least 2")
        sizes.update(genre_num=genres, num_layers=layers - 1)
        want = LOCAL_FRAMES
    else:
        want = GLOBAL_MUSIC_FRAMES
    if layers < 1:
        raise ExportError(f"{name}: no decoder layers")
    if seq_len != want:
        raise ExportError(f"{name}: music window of {seq_len} frames (null_cond_embed); LODGE's {kind} stage "
                          f"uses {want} (infer_lodge.py:314-315)")
    return sizes


def split_state(state: dict, name: str) -> tuple[dict, list[str]]:
    """The network's weights (PREFIX stripped) and notes on the copies the Lightning module also
    saves: diffusion.model.* is the same module as DanceDecoder.* (diffusion.py:68), and
    diffusion.master_model.* (the EMA copy, diffusion.py:71) is not what inference runs
    (diffusion.py:170 and 200 call self.model)."""
    weights = M.strip_prefix(state, PREFIX)
    if not weights:
        raise ExportError(f"{name}: no '{PREFIX}*' weights (expected a LODGE Lightning checkpoint)")
    notes = []
    twin = M.strip_prefix(state, "diffusion.model.")
    if twin:
        diff = M.max_abs_diff(weights, twin)
        if diff > 0:
            notes.append(f"{name}: diffusion.model.* differs from DanceDecoder.* by {diff:.3g}; "
                         f"using DanceDecoder.*, the module the official sampler calls")
    return weights, notes


# Globals a checkpoint or Normalizer.pth may name: torch's tensor rebuilding, containers, and the
# Normalizer and its scaler (dld/data/utils/preprocess.py:113 and 180), built as plain
# attribute holders, never LODGE's classes.
ALLOWED_GLOBALS = {
    ("collections", "OrderedDict"), ("torch._utils", "_rebuild_tensor_v2"),
    ("torch._utils", "_rebuild_parameter"), ("torch", "FloatStorage"), ("torch", "DoubleStorage"),
    ("torch", "LongStorage"), ("torch", "IntStorage"), ("torch", "BoolStorage"),
    ("torch", "HalfStorage"), ("torch", "BFloat16Storage"), ("torch", "ByteStorage"),
    ("torch", "float32"), ("torch", "float64"),
    ("dld.data.utils.preprocess", "Normalizer"), ("dld.data.utils.preprocess", "MinMaxScaler"),
}


def pickle_globals(data: bytes) -> list[tuple[str, str]]:
    """Every global a pickle names, found by reading its opcodes without running any of them.
    STACK_GLOBAL counts only when its two names were pushed as literal strings just before."""
    found, strings = [], []
    try:
        for op, arg, _ in pickletools.genops(io.BytesIO(data)):
            if op.name == "GLOBAL":
                module, _, name = arg.partition(" ")
                found.append((module, name))
            elif op.name == "STACK_GLOBAL":
                if len(strings) < 2:
                    found.append(("?", "STACK_GLOBAL of computed names"))
                else:
                    found.append((strings[-2], strings[-1]))
            if op.name in ("SHORT_BINUNICODE", "BINUNICODE", "UNICODE", "BINUNICODE8"):
                strings.append(arg)
            elif op.name not in ("MEMOIZE", "BINPUT", "LONG_BINPUT", "PUT"):
                strings.clear()
    except Exception as e:  # pickletools raises ValueError and others on damaged data
        raise ExportError(f"damaged pickle ({e})") from None
    return found


def check_pickle_globals(path: Path) -> None:
    """Refuse a torch zip file whose pickles name anything outside ALLOWED_GLOBALS, before
    torch ever unpickles it."""
    try:
        if not zipfile.is_zipfile(path):
            raise ExportError(f"{path}: not a PyTorch zip file (torch.save since 1.6)")
        with zipfile.ZipFile(path) as z:
            pickles = [(n, z.read(n)) for n in z.namelist() if n.endswith(".pkl")]
        if not pickles:
            raise ExportError(f"{path}: a zip file without a pickle: not a PyTorch file")
    except (OSError, zipfile.BadZipFile) as e:
        raise ExportError(f"{path}: cannot read ({e})") from None
    for member, data in pickles:
        try:
            names = pickle_globals(data)
        except ExportError as e:
            raise ExportError(f"{path} ({member}): {e}") from None
        bad = sorted({f"{m}.{n}" for m, n in names if (m, n) not in ALLOWED_GLOBALS})
        if bad:
            raise ExportError(f"{path} ({member}): refers to {', '.join(bad[:5])}: not a plain weights file; "
                              f"refusing to unpickle it")


def normalizer_arrays(obj, path: Path) -> tuple[np.ndarray, np.ndarray]:
    """`scale_` and `min_` of LODGE's Normalizer (preprocess.py:180-207: MinMaxScaler to [-1, 1],
    clip on): normalise x * scale + min, then clip; un-normalise clip(x, -1, 1), then
    (x - min) / scale. `obj` is the unpickled stand-in (attributes only)."""
    scaler = getattr(obj, "scaler", None)
    arrays = []
    for attr in ("scale_", "min_"):
        a = getattr(scaler, attr, None)
        a = None if a is None else np.asarray(a)
        if a is None or a.shape != (NFEATS,) or not np.issubdtype(a.dtype, np.floating) or not np.isfinite(a).all():
            raise ExportError(f"{path}: not LODGE's Normalizer (scaler.{attr} should be {NFEATS} finite floats)")
        arrays.append(a)
    if tuple(getattr(scaler, "feature_range", ())) != (-1, 1) or getattr(scaler, "clip", None) is not True:
        raise ExportError(f"{path}: the scaler maps to {getattr(scaler, 'feature_range', '?')} with clip "
                          f"{getattr(scaler, 'clip', '?')}; LODGE's maps to (-1, 1) with clip on")
    if (arrays[0] == 0).any():
        raise ExportError(f"{path}: scale is 0 at feature {int(np.argmin(np.abs(arrays[0])))}")
    return arrays[0], arrays[1]


def f64(v: float) -> str:
    """Shortest decimal that round-trips the float64 value (TOML float)."""
    s = repr(float(v))
    return s if ("." in s or "e" in s or "n" in s) else s + ".0"


def f64_list(values, per_line: int = 4) -> str:
    vals = [f64(v) for v in np.asarray(values, np.float64).ravel()]
    return "[\n" + "\n".join("  " + ", ".join(vals[i:i + per_line]) + "," for i in range(0, len(vals), per_line)) + "\n]"


def tensor_specs(specs: list) -> str:
    rows = []
    for name, dtype, shape in specs:
        dims = ", ".join(f'"{d}"' if isinstance(d, str) else str(d) for d in shape)
        rows.append(f'  {{ name = "{name}", dtype = "{dtype}", shape = [{dims}] }},')
    return "[\n" + "\n".join(rows) + "\n]"


def write_manifest(out_dir: Path, *, sizes: dict, scale: np.ndarray, offset: np.ndarray, rest: np.ndarray,
                   sources: dict, name: str = "lodge-finedance", license: dict = LICENSE,
                   description: str = "LODGE (Li et al., CVPR 2024) exported from the released FineDance "
                                      "checkpoints: two-stage music-to-dance, SMPL-X body at 30 fps.") -> Path:
    """`choreod-model.toml` of a `lodge` package for the ONNX files already in out_dir; `sources`
    (role -> checkpoint) go into a comment with their sha256."""
    comps = components(sizes)
    ramp_end = 2 * GUIDANCE
    lines = [
        "# choreod model package manifest (written by models/export/lodge.py; do not edit by hand:",
        "# export again instead, the sha256 below must match the ONNX files).",
        *(f"#   {role} network from {path.name} sha256 {C.sha256_file(path)}" for role, path in sources.items()),
        'format = "choreod-model"',
        "format_version = 1",
        f"name = {C.toml_str(name)}",
        f"description = {C.toml_str(description)}",
        'task = "lodge"',
        "",
        "[license]",
        f"name = {C.toml_str(license['name'])}",
        f"commercial_use = {str(license['commercial_use']).lower()}",
        f"redistribution = {str(license['redistribution']).lower()}",
        f"summary = {C.toml_str(license['summary'])}",
        f"url = {C.toml_str(license['url'])}",
        "",
        "[motion]",
        f"fps = {f64(FPS)}",
        'skeleton = "smplx22"',
        'representation = "lodge-smplx139"',
        f"dim = {NFEATS}",
        f"rest_joints = {f64_list(rest, 3)}",
        "",
        "[motion.normalizer]",
        'kind = "minmax"',
        f"dtype = \"{scale.dtype}\"",
        "clip = true",
        f"scale = {f64_list(scale)}",
        f"offset = {f64_list(offset)}",
        "",
        "[audio]",
        'features = "fact35"',
        f'librosa = "{LIBROSA}"',
        f"dim = {MUSIC_DIM}",
        f"fps = {f64(FPS)}",
        "",
        "[diffusion]",
        f"train_steps = {TRAIN_STEPS}",
        'beta_schedule = "cosine"',
        f"cosine_s = {f64(COSINE_S)}",
        f"max_beta = {f64(MAX_BETA)}",
        'cumprod_dtype = "float32"',
        'prediction = "x0"',
        "clip_sample = true",
        "",
        "[sampler]",
        'kind = "ddim"',
        f"steps = {STEPS}",
        f"eta = {f64(ETA)}",
        f"timesteps = [{', '.join(str(t) for t in TIMESTEPS)}]",
        "",
        "[lodge]",
        f"genres = [{', '.join(C.toml_str(g) for g in GENRES)}]",
        "genre_aliases = { " + ", ".join(f"{k} = {v}" for k, v in GENRE_ALIASES.items()) + " }",
        "",
        "[lodge.global]",
        f"music_frames = {sizes['global']['seq_len']}",
        f"keyframes = {GLOBAL_KEYFRAMES}",
        f"guidance = {f64(GUIDANCE)}",
        "",
        "[lodge.local]",
        f"frames = {LOCAL_FRAMES}",
        f"guidance = {f64(GUIDANCE)}",
        f"guidance_ramp = [0.0, {f64(ramp_end)}]",
        f"style_noise = {STYLE_NOISE}",
    ]
    for role, (file, inputs, outputs) in comps.items():
        lines += ["", f"[components.{role}]", f"file = {C.toml_str(file)}",
                  f'sha256 = "{C.sha256_file(out_dir / file)}"',
                  f"inputs = {tensor_specs(inputs)}", f"outputs = {tensor_specs(outputs)}"]
    path = out_dir / "choreod-model.toml"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


# --- torch parts ----------------------------------------------------------------------------

def export_package(args) -> tuple:
    import lodge_torch as T

    t0 = time.perf_counter()
    rest = load_rest_joints(check_repo(args.repo))
    official = T.Official(args.repo, allow_pickle=args.allow_pickle)
    official.load(args.global_ckpt, args.local_ckpt, heads=args.heads)
    scale, offset = official.load_normalizer(args.normalizer or args.repo / NORMALIZER_PATH)
    staging = Path(tempfile.mkdtemp(prefix=f".{args.out.name}.partial-", dir=args.out.parent))
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(staging, 0o777 & ~umask)  # mkdtemp's 0700 would make the package private
    try:
        T.export(official, staging)
        write_manifest(staging, sizes=official.sizes, scale=scale, offset=offset, rest=rest,
                       sources={"global": args.global_ckpt, "local": args.local_ckpt})
        M.publish(staging, args.out)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    print(f"exported {args.out} in {time.perf_counter() - t0:.1f} s "
          f"(global {official.sizes['global']}, local {official.sizes['local']})")
    return official


# Each network call against the official forward, relative to the reference's largest magnitude:
# float32 rounding through ~10 transformer layers gives ~1e-6; a wrong style noise, genre, drop
# flag or timestep gives >= 1e-2.
TOLERANCE = 1e-5


def verify(args, official) -> bool:
    import lodge_torch as T

    t0 = time.perf_counter()
    rows = T.verify_calls(official, args.out)
    worst = 0.0
    for label, diff, rel in rows:
        worst = max(worst, rel)
        print(f"  {label:<44} max abs {diff:.2e}  rel {rel:.2e}")
    ok = worst <= TOLERANCE
    print(json.dumps({"verify": "ok" if ok else "failed", "calls": len(rows),
                      "worst_call_rel": float(f"{worst:.3g}"), "tolerance": TOLERANCE,
                      "seconds": round(time.perf_counter() - t0, 1)}))
    return ok


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repo", type=Path, required=True, help="a clone of li-ronghui/LODGE")
    ap.add_argument("--global", dest="global_ckpt", type=Path, required=True,
                    help="exp/Global_Module/FineDance_Global/checkpoints/epoch=2999.ckpt")
    ap.add_argument("--local", dest="local_ckpt", type=Path, required=True,
                    help="exp/Local_Module/FineDance_FineTuneV2_Local/checkpoints/epoch=299.ckpt")
    ap.add_argument("--normalizer", type=Path, help=f"default: REPO/{NORMALIZER_PATH}")
    ap.add_argument("-o", "--out", type=Path, required=True, help="package directory to create")
    ap.add_argument("--heads", type=int, default=HEADS,
                    help=f"attention heads of both networks (not visible in the weights; default {HEADS}, "
                         f"as in the clone's configs)")
    ap.add_argument("--verify", action="store_true",
                    help="compare each exported network call with the official forward (onnxruntime, CPU)")
    ap.add_argument("--allow-pickle", action="store_true",
                    help="load checkpoints holding Python objects besides tensors (runs their pickle code: "
                         "only for files you trust)")
    a = ap.parse_args(argv)
    for flag, path in (("--global", a.global_ckpt), ("--local", a.local_ckpt), ("--normalizer", a.normalizer)):
        if path is not None and not path.is_file():
            ap.error(f"{flag} {path}: no such file")
    if a.heads < 1:
        ap.error("--heads must be at least 1")
    return a


def main(argv=None) -> int:
    args = parse_args(argv)
    try:
        check_repo(args.repo)
        M.check_output(args.out)
        official = export_package(args)
        if args.verify and not verify(args, official):
            print(f"lodge.py: error: {args.out}: a network call differs from the official forward by more "
                  f"than {TOLERANCE} (relative)", file=sys.stderr)
            return 1
    except ExportError as e:
        print(f"lodge.py: error: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    # Run the importable module, so lodge_torch and this code share one set of constants.
    import lodge

    sys.exit(lodge.main())
