"""The torch half of the LODGE exporter: the official networks, the ONNX wrappers, the checks.

Imported only by `lodge.py` (export, --verify), `lodge_loop_torch.py` and
`make_lodge_test_checkpoints.py`; needs torch and einops (the user's environment, never
choreod's). Every weight runs through the official modules imported from the user's LODGE
clone; the wrappers only re-order the official `forward`
(model.py:485-532 `DanceDecoder`, 906-993 `Refine_DanceDecoder`) so that

- the music branch, which depends on neither x_t nor t, is its own graph (`*_music`), run once per
  window instead of twice per step, and hands every decoder layer's cross-attention keys and
  values of the music tokens to the denoiser, which projects only the time (and style) tokens
  per step (the official forward projects all of them at every step: model.py:523-529);
- the guidance drop (`cond_drop_prob` 0 or 1, turned into a mask by `prob_mask_like`, utils.py:52)
  is the input `keep` (1 keeps the music, 0 uses the learned null embeddings);
- the style noise the local network draws inside `forward` (model.py:947
  `torch.randn(x.shape[0], 256)`, one draw per call, so two per guided step: unconditional first,
  diffusion.py:170 -> model.py:870-871) is the input `style_noise`, and the genre head is picked
  with a gather instead of Python indexing (MappingNet, model.py:256-263);
- the local network's "refine" branch is kept as it really computes: its decoder stack is empty
  (the constructor appends the refine layer to the *main* stack, model.py:850-862), so the branch
  is `out + refine_final_layer1(refine_input_projection1(out))`, live, while its FK conditioning
  (`get_rcond`, model.py:876-904) feeds nothing and is left out.
"""

from __future__ import annotations

import contextlib
import importlib
import io
import logging
import sys
import types
import warnings
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

import lodge as E
import mcm_ldm as M
from mcm_ldm_torch import strip_metadata

# Modules LODGE's network files import for rendering and data handling only (smplfk.py:1-24):
# when absent they are replaced by placeholders that fail if anything calls them.
RENDER_ONLY = ("librosa", "soundfile", "matplotlib", "matplotlib.animation", "matplotlib.pyplot",
               "matplotlib.cm", "matplotlib.colors", "mpl_toolkits", "mpl_toolkits.mplot3d", "p_tqdm", "tqdm")
# pytorch3d: only the local network's dead FK branch (and --verify's official forward) uses it.
PYTORCH3D = ("pytorch3d", "pytorch3d.transforms")


class _Placeholder(types.ModuleType):
    def __getattr__(self, name: str):
        if name.startswith("__"):
            raise AttributeError(name)

        def missing(*_args, **_kwargs):
            raise RuntimeError(f"{self.__name__}.{name} is not installed (not needed to export LODGE)")
        return missing


def _install_placeholders(names) -> list[str]:
    added = []
    for name in names:
        top = name.split(".")[0]
        try:
            if top not in added:
                importlib.import_module(name)
                continue
        except ImportError:
            pass
        sys.modules[name] = _Placeholder(name)
        added.append(top)
    return sorted(set(added))


def import_official(repo: Path, need_pytorch3d: bool = False):
    """LODGE's `dld.models.architectures.model` and `dld.data.render_joints.smplfk` from the clone."""
    sys.path.insert(0, str(repo.resolve()))
    if "pickle5" not in sys.modules:
        try:
            importlib.import_module("pickle5")
        except ImportError:
            import pickle
            sys.modules["pickle5"] = pickle  # the backport of the stdlib module (smplfk.py:22)
    missing = _install_placeholders(RENDER_ONLY)
    try:
        importlib.import_module("pytorch3d.transforms")
        has_p3d = True
    except ImportError:
        if need_pytorch3d:
            raise E.ExportError("--verify runs the official forward, whose FK branch needs pytorch3d "
                                "(a release from 0.6.2 on, as LODGE's code imports matrix_to_axis_angle)") from None
        missing += _install_placeholders(PYTORCH3D)
        has_p3d = False
    if missing:
        print(f"note: not installed, replaced by placeholders (unused by the networks): {', '.join(missing)}",
              file=sys.stderr)
    try:
        model = importlib.import_module("dld.models.architectures.model")
        smplfk = importlib.import_module("dld.data.render_joints.smplfk")
        importlib.import_module("dld.data.utils.preprocess")
    except ImportError as e:
        raise E.ExportError(f"{repo}: cannot import LODGE's networks ({e}): install it beside torch") from None
    finally:
        # LODGE's modules keep what they imported; other libraries (torch.export probes
        # installed modules) must not see the placeholders.
        for name in [n for n, m in sys.modules.items() if isinstance(m, _Placeholder)]:
            del sys.modules[name]
    return model, smplfk, has_p3d


def _standins():
    """Attribute-only stand-ins for LODGE's Normalizer and MinMaxScaler (preprocess.py:113, 180),
    under their pickled names, for torch's weights-only unpickler: nothing of LODGE runs."""
    made = []
    for name in ("Normalizer", "MinMaxScaler"):
        cls = type(name, (), {"__module__": "dld.data.utils.preprocess"})
        made.append(cls)
    return made


class Official:
    """Both official networks with the checkpoints' weights."""

    def __init__(self, repo: Path, allow_pickle: bool = False, need_pytorch3d: bool = False):
        self.repo = repo
        self.allow_pickle = allow_pickle
        self.model, self.smplfk, self.has_pytorch3d = import_official(repo, need_pytorch3d)
        self.nets: dict[str, torch.nn.Module] = {}
        self.sizes: dict[str, dict] = {}

    def build(self, kind: str, sizes: dict, heads: int) -> torch.nn.Module:
        common = dict(nfeats=sizes["nfeats"], seq_len=sizes["seq_len"], latent_dim=sizes["latent_dim"],
                      ff_size=sizes["ff_size"], num_layers=sizes["num_layers"], num_heads=heads, dropout=0.1,
                      cond_feature_dim=sizes["cond_feature_dim"], activation="gelu",
                      use_rotary=sizes["use_rotary"])
        if kind == "global":
            return self.model.DanceDecoder(**common)
        rest = E.check_repo(self.repo)
        skeleton = self.smplfk.SMPLX_Skeleton(Jpath=str(rest)) if self.has_pytorch3d else None
        # normalizer=None: it only feeds get_rcond's FK, whose result no layer reads (see above).
        return self.model.Refine_DanceDecoder(smplx_model=skeleton, normalizer=None,
                                              genre_num=sizes["genre_num"], **common)

    def load(self, global_ckpt: Path, local_ckpt: Path, heads: int) -> None:
        for kind, path in (("global", global_ckpt), ("local", local_ckpt)):
            state = M.load_checkpoint(path, self.allow_pickle)
            weights, notes = E.split_state(state, path.name)
            for note in notes:
                print(f"note: {note}", file=sys.stderr)
            sizes = E.infer_sizes({k: tuple(v.shape) for k, v in weights.items()}, kind, path.name)
            net = self.build(kind, sizes, heads)
            try:
                net.load_state_dict(weights, strict=True)
            except RuntimeError as e:
                raise E.ExportError(f"{path}: the weights do not fit LODGE's {kind} network of the sizes "
                                    f"their shapes give ({M.first_line(e)})") from None
            if kind == "local" and len(net.refine_seqTransDecoder1.stack) != 0:
                raise E.ExportError(f"{self.repo}: Refine_DanceDecoder's refine stack is not empty: a "
                                    f"different LODGE than the one this exporter was checked with")
            self.nets[kind] = net.eval()
            self.sizes[kind] = sizes

    def load_normalizer(self, path: Path) -> tuple[np.ndarray, np.ndarray]:
        E.check_pickle_globals(path)
        try:
            with torch.serialization.safe_globals(_standins()):
                obj = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as e:  # torch raises UnpicklingError, RuntimeError, ... on a bad file
            raise E.ExportError(f"{path}: not a readable Normalizer ({M.first_line(e)})") from None
        scaler = getattr(obj, "scaler", None)
        for attr in ("scale_", "min_"):
            v = getattr(scaler, attr, None)
            if isinstance(v, torch.Tensor):
                setattr(scaler, attr, v.numpy())
        return E.normalizer_arrays(obj, path)


def _attention(layer: torch.nn.Module) -> torch.nn.MultiheadAttention:
    """A decoder layer's cross-attention, checked to be the plain kind whose packed in_proj the
    wrappers slice (q, k, v rows in that order: torch's F._in_projection_packed)."""
    attn = layer.multihead_attn
    if not (layer.norm_first and attn.batch_first and attn._qkv_same_embed_dim and attn.bias_k is None
            and not attn.add_zero_attn and attn.in_proj_bias is not None):
        raise E.ExportError("a decoder layer's cross-attention is not the layout this exporter was checked with")
    return attn


def _rows(attn: torch.nn.MultiheadAttention, part: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Weight and bias of the in-projection's q (0), k (1) or v (2) rows."""
    e = attn.embed_dim
    return attn.in_proj_weight[part * e:(part + 1) * e], attn.in_proj_bias[part * e:(part + 1) * e]


def _film(x: torch.Tensor, scale_shift: tuple) -> torch.Tensor:
    """featurewise_affine (model.py:35-37)."""
    scale, shift = scale_shift
    return (scale + 1) * x + shift


class Music(torch.nn.Module):
    """The step-invariant music branch (model.py:496-509 and 519-520; 917-931 and 941-942), and
    the part of every decoder layer's cross-attention that depends on the music tokens alone.

    The official memory is norm_cond(concat(music tokens, time tokens[, style token]))
    (model.py:523-529, 950-957), rotated (keys only) by position and projected per token in each
    layer's `_mha_block` (model.py:219-230). LayerNorm, the rotary embedding (position p of the
    memory -> angle p * freqs, rotary_embedding_torch.py:116-139) and the in-projection act on
    each token by itself, so the music tokens' keys and values are the same at every step."""

    def __init__(self, net: torch.nn.Module):
        super().__init__()
        self.net = net

    def forward(self, music: torch.Tensor, keep: torch.Tensor):
        n = self.net
        tokens = n.cond_encoder(n.abs_pos_encoding(n.cond_projection(music)))
        k = keep > 0.5
        tokens = torch.where(k[:, None, None], tokens, n.null_cond_embed.to(tokens.dtype))
        hidden = n.non_attn_cond_projection(tokens.mean(dim=-2))
        hidden = torch.where(k[:, None], hidden, n.null_cond_hidden.to(hidden.dtype))
        mem = n.norm_cond(tokens)
        keys, values = [], []
        for layer in n.seqTransDecoder.stack:
            attn = _attention(layer)
            rotated = layer.rotary.rotate_queries_or_keys(mem) if layer.use_rotary else mem
            keys.append(F.linear(rotated, *_rows(attn, 1)))
            values.append(F.linear(mem, *_rows(attn, 2)))
        return hidden, torch.stack(keys, dim=1), torch.stack(values, dim=1)


class Denoiser(torch.nn.Module):
    """One network call given the music branch's outputs: x0 from x_t and t.

    Each decoder layer runs as FiLMTransformerDecoderLayer.forward with norm_first
    (model.py:165-176) through the official sub-modules, except that the cross-attention
    (`_mha_block`, model.py:219-230, nn.MultiheadAttention with need_weights=False) is spelled
    out: the keys and values of the music tokens come in (`Music`), those of the time (and
    style) tokens, which sit after them in the memory, are projected here with the same rows of
    in_proj, and attention runs per head with scaled_dot_product_attention as torch's
    multi_head_attention_forward does (dropout is off in eval)."""

    def __init__(self, net: torch.nn.Module, local: bool):
        super().__init__()
        self.net = net
        self.local = local
        # apply_rotary_emb of the module the network's rotary embedding comes from
        # (rotary_embedding_torch.py:45-57).
        self.rotate = sys.modules[type(net.rotary).__module__].apply_rotary_emb if net.rotary is not None else None

    def forward(self, x_t, t, cond_hidden, cross_k, cross_v, genre=None, style_noise=None):
        n = self.net
        x = n.abs_pos_encoding(n.input_projection(x_t))
        # SinusoidalPosEmb multiplies the long timesteps by float32 (utils.py:46): cast first.
        t_hidden = n.time_mlp(t.to(torch.float32))
        t_cond = n.to_time_cond(t_hidden) + cond_hidden
        tail = n.to_time_tokens(t_hidden)
        if self.local:
            heads = torch.stack([head(n.mapping.shared(style_noise)) for head in n.mapping.unshared], dim=1)
            style = torch.gather(heads, 1, genre[:, None, None].expand(-1, 1, heads.shape[-1]))
            tail = torch.cat((tail, style), dim=1)
        tail = n.norm_cond(tail)
        music_len = cross_k.shape[2]
        for i, layer in enumerate(n.seqTransDecoder.stack):
            x = x + _film(layer._sa_block(layer.norm1(x), None, None), layer.film1(t_cond))
            cross = self.cross_attention(layer, layer.norm2(x), tail, cross_k[:, i], cross_v[:, i], music_len)
            x = x + _film(layer.dropout2(cross), layer.film2(t_cond))
            x = x + _film(layer._ff_block(layer.norm3(x)), layer.film3(t_cond))
        out = n.final_layer(x)
        if self.local:
            # The refine stack is empty: it passes refine_input_projection1(out) through unchanged.
            refined = n.refine_seqTransDecoder1(n.refine_input_projection1(out), None, t_cond)
            out = out + n.refine_final_layer1(refined)
        return out

    def cross_attention(self, layer, x, tail, music_k, music_v, music_len: int):
        attn = _attention(layer)
        q_in, k_in = x, tail
        if layer.use_rotary:
            q_in = layer.rotary.rotate_queries_or_keys(x)
            # The tail's positions in the official memory follow the music tokens'.
            positions = torch.arange(music_len, music_len + tail.shape[1])
            k_in = self.rotate(layer.rotary(positions), tail)
        k = torch.cat((music_k, F.linear(k_in, *_rows(attn, 1))), dim=1)
        v = torch.cat((music_v, F.linear(tail, *_rows(attn, 2))), dim=1)
        q = F.linear(q_in, *_rows(attn, 0))
        heads = [a.unflatten(-1, (attn.num_heads, -1)).transpose(1, 2) for a in (q, k, v)]
        out = F.scaled_dot_product_attention(*heads).transpose(1, 2).flatten(-2)
        return attn.out_proj(out)


def example_inputs(official: Official, role: str, n: int = 2, seed: int = 0) -> dict:
    """Named example inputs of `role`, from `lodge.components` (random values, real shapes)."""
    g = torch.Generator().manual_seed(seed)
    _, inputs, _ = E.components(official.sizes)[role]
    feeds = {}
    for name, dtype, shape in inputs:
        dims = [n if isinstance(d, str) else d for d in shape]
        if name == "t":
            feeds[name] = torch.randint(0, E.TRAIN_STEPS, dims, generator=g)
        elif name == "genre":
            feeds[name] = torch.randint(0, len(E.GENRES), dims, generator=g)
        elif name == "keep":
            feeds[name] = torch.tensor([1.0, 0.0] * (n // 2) + [1.0] * (n % 2))
        else:
            feeds[name] = torch.randn(dims, generator=g)
    return feeds


def wrappers(official: Official) -> dict:
    g, loc = official.nets["global"], official.nets["local"]
    return {"global_music": Music(g), "global_denoiser": Denoiser(g, local=False),
            "local_music": Music(loc), "local_denoiser": Denoiser(loc, local=True)}


def export(official: Official, out_dir: Path) -> None:
    """One ONNX file per role (opset 18, dynamic batch N; window lengths fixed by the networks'
    null embeddings), named as in `lodge.components`."""
    optimiser_log = logging.getLogger("onnxscript")
    level = optimiser_log.level
    optimiser_log.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="# The axis name")
            # The rotary embedding caches its angles per length in a dict (computed in-graph).
            warnings.filterwarnings("ignore", message=".*was assigned during export")
            warnings.filterwarnings("ignore", message=".*were assigned during export")
            for role, module in wrappers(official).items():
                export_one(official, role, module, out_dir)
    finally:
        optimiser_log.setLevel(level)


def export_one(official: Official, role: str, module: torch.nn.Module, out_dir: Path) -> None:
    file, inputs, outputs = E.components(official.sizes)[role]
    batch = torch.export.Dim("N", max=4096)
    dynamic = {name: {0: batch} for name, _, _ in inputs}
    feeds = example_inputs(official, role)
    log = io.StringIO()
    try:
        with torch.no_grad(), contextlib.redirect_stdout(log):
            torch.onnx.export(module.eval(), (), str(out_dir / file), kwargs=feeds,
                              input_names=[n for n, _, _ in inputs], output_names=[n for n, _, _ in outputs],
                              dynamic_shapes=dynamic, opset_version=E.OPSET, dynamo=True,
                              external_data=False, verbose=False)
    except Exception:
        sys.stdout.write(log.getvalue())
        raise
    strip_metadata(out_dir / file)


# --- --verify: each network call against the official forward --------------------------------

def official_call(official: Official, kind: str, feeds: dict, keep: bool) -> np.ndarray:
    """The official `forward` with cond_drop_prob 0 (keep) or 1 (drop). The local network draws its
    style noise with torch.randn inside: the generator is seeded so that the draw equals
    feeds["style_noise"] (drawn from the same seed by `seeded_noise`)."""
    net = official.nets[kind]
    drop = 0.0 if keep else 1.0
    with torch.no_grad():
        if kind == "local":
            torch.manual_seed(feeds["seed"])
            out = net.forward(feeds["x_t"], feeds["music"], feeds["genre"], feeds["t"], cond_drop_prob=drop)
        else:
            out = net.forward(feeds["x_t"], feeds["music"], None, feeds["t"], cond_drop_prob=drop)
    return out.numpy()


def seeded_noise(seed: int, n: int, draws: int = 1) -> list[torch.Tensor]:
    torch.manual_seed(seed)
    return [torch.randn(n, E.STYLE_NOISE) for _ in range(draws)]


def verify_calls(official: Official, pkg: Path) -> list[tuple[str, float, float]]:
    """(label, max abs difference, relative to the reference's largest magnitude) per call."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    comps = E.components(official.sizes)
    sess = {role: ort.InferenceSession(str(pkg / file), opts, providers=["CPUExecutionProvider"])
            for role, (file, _, _) in comps.items()}
    rows = []

    def onnx_call(kind: str, feeds: dict, keep: float, noise: torch.Tensor | None) -> np.ndarray:
        n = feeds["x_t"].shape[0]
        music = sess[f"{kind}_music"]
        cond = music.run(None, {"music": feeds["music"].numpy(), "keep": np.full(n, keep, np.float32)})
        den = dict(zip([o.name for o in music.get_outputs()], cond))
        den.update(x_t=feeds["x_t"].numpy(), t=feeds["t"].numpy())
        if kind == "local":
            den.update(genre=feeds["genre"].numpy(), style_noise=noise.numpy())
        (x0,) = sess[f"{kind}_denoiser"].run(None, den)
        return x0

    for kind in ("global", "local"):
        frames = E.GLOBAL_KEYFRAMES if kind == "global" else E.LOCAL_FRAMES
        music_frames = official.sizes[kind]["seq_len"]
        for n, times in ((2, (999, 18)), (1, (500,)), (2, (0, 38))):
            g = torch.Generator().manual_seed(100 + n + times[0])
            feeds = {"x_t": torch.randn(n, frames, E.NFEATS, generator=g),
                     "music": torch.randn(n, music_frames, E.MUSIC_DIM, generator=g),
                     "t": torch.tensor(times, dtype=torch.long),
                     "genre": torch.tensor([3, 15][:n], dtype=torch.long), "seed": 7 + times[0]}
            for keep in (True, False):
                ref = official_call(official, kind, feeds, keep)
                noise = seeded_noise(feeds["seed"], n)[0] if kind == "local" else None
                got = onnx_call(kind, feeds, 1.0 if keep else 0.0, noise)
                d, r = M.relative(got, ref)
                rows.append((f"{kind} N={n} t={list(times)} {'music' if keep else 'guidance drop'}", d, r))
        if kind == "local":
            # guided_forward (model.py:869-873): the unconditional call draws first.
            w = 1.3
            with torch.no_grad():
                torch.manual_seed(feeds["seed"])
                ref = official.nets["local"].guided_forward(feeds["x_t"], feeds["music"], feeds["genre"],
                                                            feeds["t"], w).numpy()
            unc_noise, cond_noise = seeded_noise(feeds["seed"], feeds["x_t"].shape[0], 2)
            unc = onnx_call(kind, feeds, 0.0, unc_noise)
            cond = onnx_call(kind, feeds, 1.0, cond_noise)
            d, r = M.relative(unc + (cond - unc) * w, ref)
            rows.append((f"local guided_forward w={w} (noise: unc, then cond)", d, r))
    return rows
