#!/usr/bin/env python3
"""A tiny `lodge` package with seeded random weights, made without LODGE's code, for CI tests.

    python models/export/make_lodge_fixture_package.py -o models/packages/lodge-tiny-random-kv \\
        [--seed 0] [--check-repo PATH_TO_LODGE_CLONE]

The two networks are written here from the architecture's facts (layer order, names and shapes
as in LODGE's dld/models/architectures/model.py: `DanceDecoder` 382-532, `Refine_DanceDecoder`
733-993, FiLM decoder layers 111-227, pre-norm encoder layers 40-108, rotary embeddings, the
genre mapping 241-263), with the state-dict layout of the official modules, at tiny sizes
(latent 16, feed-forward 32, 2 heads, 2 decoder layers; music windows 1024 and 256 as LODGE's).
They are exported through the exporter's own wrappers (lodge_torch.Music / Denoiser) and the
package is written by lodge.write_manifest with random normaliser values and random rest joints
(not SMPL-X's), so the package has the released package's interface and none of its content.

--check-repo builds LODGE's own modules from a clone with the same sizes, loads these weights
into them strictly (same layout) and runs the exporter's --verify comparison on the package.
Needs torch and einops (never in CI); the package it writes is committed.
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

sys.path.insert(0, str(Path(__file__).resolve().parent))

import lodge as E  # noqa: E402
import lodge_torch as T  # noqa: E402
import mcm_ldm as M  # noqa: E402

TINY = dict(latent_dim=16, ff_size=32, num_layers=2, heads=2)
LICENSE = {
    "name": "choreod test fixture (random weights)",
    "commercial_use": True,
    "redistribution": True,
    "summary": "Seeded random weights of LODGE's layout at tiny sizes, made by "
               "models/export/make_lodge_fixture_package.py; no FineDance data, no LODGE code. "
               "Its output is not a dance.",
    "url": "",
}


class Rotary(nn.Module):
    """Rotary position embedding of interleaved pairs (rotary_embedding_torch, 'lang' freqs)."""

    def __init__(self, dim: int):
        super().__init__()
        self.register_buffer("freqs", 1.0 / 10000 ** (torch.arange(0, dim, 2)[: dim // 2].float() / dim))

    def forward(self, positions: torch.Tensor) -> torch.Tensor:
        """The angle of each position and feature."""
        return (positions.to(self.freqs.dtype)[:, None] * self.freqs).repeat_interleave(2, dim=-1)

    def rotate_queries_or_keys(self, t: torch.Tensor) -> torch.Tensor:
        return apply_rotary_emb(self(torch.arange(t.shape[-2])), t)


def apply_rotary_emb(angles: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Each interleaved pair of t rotated by its angle (lodge_torch.Denoiser calls this by name)."""
    pairs = t.unflatten(-1, (-1, 2))
    rotated = torch.stack((-pairs[..., 1], pairs[..., 0]), dim=-1).flatten(-2)
    return t * angles.cos() + rotated * angles.sin()


class EncoderLayer(nn.Module):
    def __init__(self, d: int, heads: int, ff: int, rotary: Rotary):
        super().__init__()
        self.self_attn = nn.MultiheadAttention(d, heads, dropout=0.1, batch_first=True)
        self.linear1, self.linear2 = nn.Linear(d, ff), nn.Linear(ff, d)
        self.norm1, self.norm2 = nn.LayerNorm(d), nn.LayerNorm(d)
        self.rotary = rotary

    def forward(self, x):
        h = self.norm1(x)
        qk = self.rotary.rotate_queries_or_keys(h)
        x = x + self.self_attn(qk, qk, h, need_weights=False)[0]
        return x + self.linear2(F.gelu(self.linear1(self.norm2(x))))


class Film(nn.Module):
    """Scale and shift from t (DenseFiLM)."""

    def __init__(self, d: int):
        super().__init__()
        self.block = nn.Sequential(nn.Mish(), nn.Linear(d, 2 * d))

    def forward(self, t):
        return self.block(t)[:, None].chunk(2, dim=-1)


class DecoderLayer(nn.Module):
    """A pre-norm FiLM decoder layer's parts, by the names lodge_torch.Denoiser runs them."""

    norm_first = True
    use_rotary = True

    def __init__(self, d: int, heads: int, ff: int, rotary: Rotary):
        super().__init__()
        self.self_attn = nn.MultiheadAttention(d, heads, dropout=0.1, batch_first=True)
        self.multihead_attn = nn.MultiheadAttention(d, heads, dropout=0.1, batch_first=True)
        self.linear1, self.linear2 = nn.Linear(d, ff), nn.Linear(ff, d)
        self.norm1, self.norm2, self.norm3 = nn.LayerNorm(d), nn.LayerNorm(d), nn.LayerNorm(d)
        self.film1, self.film2, self.film3 = Film(d), Film(d), Film(d)
        self.dropout2 = nn.Dropout(0.1)
        self.rotary = rotary

    def _sa_block(self, x, attn_mask, key_padding_mask):
        qk = self.rotary.rotate_queries_or_keys(x)
        return self.self_attn(qk, qk, x, attn_mask=attn_mask, key_padding_mask=key_padding_mask,
                              need_weights=False)[0]

    def _ff_block(self, x):
        return self.linear2(F.gelu(self.linear1(x)))


class Stack(nn.Module):
    def __init__(self, layers):
        super().__init__()
        self.stack = nn.ModuleList(layers)

    def forward(self, x, cond, t):
        for layer in self.stack:
            x = layer(x, cond, t)
        return x


class SinusoidalTime(nn.Module):
    def __init__(self, dim: int):
        super().__init__()
        self.dim = dim

    def forward(self, t):
        half = self.dim // 2
        freqs = torch.exp(torch.arange(half) * -(math.log(10000) / (half - 1)))
        angles = t[:, None] * freqs[None]
        return torch.cat((angles.sin(), angles.cos()), dim=-1)


class TimeTokens(nn.Module):
    def __init__(self, d: int):
        super().__init__()
        self.linear = nn.Linear(4 * d, 2 * d)

    def forward(self, h):
        return self.linear(h).unflatten(-1, (2, -1))


class Network(nn.Module):
    """The attributes and weights the exporter's wrappers use, in the official layout."""

    def __init__(self, seq_len: int, local: bool, latent_dim: int, ff_size: int, num_layers: int, heads: int):
        super().__init__()
        d = latent_dim
        self.rotary = Rotary(d)
        self.abs_pos_encoding = nn.Identity()
        self.time_mlp = nn.Sequential(SinusoidalTime(d), nn.Linear(d, 4 * d), nn.Mish())
        self.to_time_cond = nn.Sequential(nn.Linear(4 * d, d))
        self.to_time_tokens = TimeTokens(d)
        self.null_cond_embed = nn.Parameter(torch.randn(1, seq_len, d))
        self.null_cond_hidden = nn.Parameter(torch.randn(1, d))
        self.norm_cond = nn.LayerNorm(d)
        self.input_projection = nn.Linear(E.NFEATS, d)
        self.cond_encoder = nn.Sequential(*[EncoderLayer(d, heads, ff_size, self.rotary) for _ in range(2)])
        self.cond_projection = nn.Linear(E.MUSIC_DIM, d)
        self.non_attn_cond_projection = nn.Sequential(nn.LayerNorm(d), nn.Linear(d, d), nn.SiLU(), nn.Linear(d, d))
        layers = num_layers + (1 if local else 0)
        self.seqTransDecoder = Stack([DecoderLayer(d, heads, ff_size, self.rotary) for _ in range(layers)])
        self.final_layer = nn.Linear(d, E.NFEATS)
        if local:
            self.mapping = nn.Module()
            self.mapping.shared = nn.Sequential(nn.Linear(E.STYLE_NOISE, d), nn.GELU(), nn.Linear(d, d), nn.GELU())
            self.mapping.unshared = nn.ModuleList(
                [nn.Sequential(nn.Linear(d, d), nn.GELU(), nn.Linear(d, d)) for _ in E.GENRES])
            self.refine_norm_cond1 = nn.LayerNorm(d)
            self.refine_final_layer1 = nn.Linear(d, E.NFEATS)
            self.refine_input_projection1 = nn.Linear(E.NFEATS, d)
            self.refine_cond_projection1 = nn.Linear(48, d)
            self.refine_seqTransDecoder1 = Stack([])


def official_state(net: Network) -> dict:
    """State dict under the official key names (the time-token Linear sits at index 0 of a
    Sequential whose index 1 is an einops Rearrange)."""
    return {k.replace("to_time_tokens.linear.", "to_time_tokens.0."): v for k, v in net.state_dict().items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-o", "--out", type=Path, required=True)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--check-repo", type=Path, help="a LODGE clone to check the package against")
    a = ap.parse_args()
    M.check_output(a.out)
    torch.manual_seed(a.seed)
    torch.set_num_threads(1)
    nets = {"global": Network(E.GLOBAL_MUSIC_FRAMES, False, **TINY).eval(),
            "local": Network(E.LOCAL_FRAMES, True, **TINY).eval()}
    official = types_namespace(nets)
    rng = np.random.default_rng(a.seed)
    scale, offset = rng.uniform(0.2, 2.0, E.NFEATS), rng.uniform(-1.0, 1.0, E.NFEATS)
    rest = rng.standard_normal((E.REST_JOINTS, 3)) * 0.15
    staging = Path(tempfile.mkdtemp(prefix=f".{a.out.name}.partial-", dir=a.out.parent))
    os.chmod(staging, 0o755)
    try:
        T.export(official, staging)
        E.write_manifest(staging, sizes=official.sizes, scale=scale, offset=offset, rest=rest, sources={},
                         name=a.out.name, license=LICENSE,
                         description="LODGE's two networks at tiny sizes (latent 16, ff 32, 2 heads, 2 layers) "
                                     "with SEEDED RANDOM WEIGHTS, random normaliser and random rest joints: "
                                     "the released package's interface for tests; its output is not a dance.")
        (staging / "README.md").write_text(
            f"# {a.out.name}\n\nA test fixture: LODGE's network layout at tiny sizes with seeded random "
            "weights, made without LODGE's code by\n\n    python models/export/make_lodge_fixture_package.py "
            f"-o models/packages/{a.out.name} --seed {a.seed}\n\n(torch; see models/export/README.md). "
            "Not a dance model.\n", encoding="utf-8")
        M.publish(staging, a.out)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    print(f"wrote {a.out}: {sum(p.stat().st_size for p in a.out.iterdir()) / 1e6:.2f} MB")
    if a.check_repo:
        check(a.check_repo, nets, a.out)


def types_namespace(nets: dict):
    """What lodge_torch.export and verify_calls read of an `Official`: the networks and sizes."""
    import types
    sizes = {k: E.infer_sizes({n: tuple(v.shape) for n, v in official_state(net).items()}, k, f"{k} network")
             for k, net in nets.items()}
    return types.SimpleNamespace(nets=nets, sizes=sizes)


def check(repo: Path, nets: dict, pkg: Path) -> None:
    """LODGE's own modules with these weights (strict load) against the package's ONNX calls."""
    official = T.Official(repo, need_pytorch3d=True)
    for kind, net in nets.items():
        sizes = E.infer_sizes({n: tuple(v.shape) for n, v in official_state(net).items()}, kind, kind)
        ref = official.build(kind, sizes, TINY["heads"])
        ref.load_state_dict(official_state(net), strict=True)
        official.nets[kind], official.sizes[kind] = ref.eval(), sizes
    worst = 0.0
    for label, diff, rel in T.verify_calls(official, pkg):
        worst = max(worst, rel)
        print(f"  {label:<44} max abs {diff:.2e}  rel {rel:.2e}")
    print(f"worst relative difference to LODGE's own modules: {worst:.2e} (tolerance {E.TOLERANCE})")
    if worst > E.TOLERANCE:
        sys.exit(1)


if __name__ == "__main__":
    main()
