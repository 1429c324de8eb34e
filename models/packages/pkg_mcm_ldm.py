"""The `mcm-ldm-ref` package: MCM-LDM's four networks with seeded random weights.

Every module follows XingliangJin/MCM-LDM (HEAD db292c9) with the widths of its configs
(`paper`) or shrunk widths and the same structure (`tiny`):

- vae_encoder / vae_decoder: mld/models/architectures/mld_vae.py `MldVae` (arch
  encoder_decoder, configs/modules/motion_vae.yaml): skel_embedding Linear(263, d);
  `global_motion_token` = 14 learned tokens (latent_size 7 x 2: rows 0..7 are mu, 7..14 logvar
  — the issue's "14 query tokens" and the facts' "7 x 256 latent" are both right) prepended to
  the frames; learned position embedding (mld/models/operator/position_encoding.py
  PositionEmbeddingLearned1D, max_len 500: x + pe[:L]); SkipTransformerEncoder
  (mld/models/operator/cross_attention.py: (L-1)/2 input layers, a middle layer, (L-1)/2 output
  layers each after Linear(2d, d) over [x, skip], final LayerNorm) of DETR post-norm layers
  (self-attention, add, LayerNorm, FFN with exact GELU, add, LayerNorm); key-padding masks from
  `mask` instead of Python length lists; the encoder returns mu (the posterior mean, not a
  sample). The decoder's queries are zeros + learned PE, decoded by a SkipTransformerDecoder
  (post-norm layers: self-attention with the frame mask, cross-attention to the 7 latent tokens,
  FFN) with final LayerNorm, then final_layer Linear(d, 263); padded frames are zeroed.
- style_encoder: mld/models/motionclip_263/models/architectures/transformer.py
  `Encoder_TRANSFORMER` (configs/motionclip_config/motionclip_params_263.yaml: latent 512,
  9 layers, ff 1024, 4 heads, GELU): skelEmbedding Linear(263, d_s), muQuery and sigmaQuery
  prepended, sinusoidal PE (sin on even, cos on odd channels, computed in the graph), the same
  SkipTransformerEncoder; output = final[0] (mu), [N, d_s].
- denoiser: mld/models/architectures/mld_denoiser.py `MldDenoiser` (configs/modules/
  denoiser.yaml: 9 layers, 4 heads): timestep = diffusers Timesteps(d, flip_sin_to_cos=True,
  shift 0) -> TimestepEmbedding (Linear, SiLU, Linear); content ("style remover") =
  InstanceNorm1d(d, affine) over the 7 tokens + time -> learned PE -> 1-layer
  nn.TransformerEncoder (ReLU, ff 2048, post-norm) -> Linear(7d, 6d) -> 6 tokens, concatenated
  before the 7 sample tokens (+ learned PE over the 13); style = ReLU -> Linear(d_s, d) + time;
  trajectory = `TransEncoder`: ReLU -> Linear(3, d), a learned global token + frames, learned PE,
  2-layer nn.TransformerEncoder (ReLU, ff 2048) with the frame mask, token 0 + time; 9 `DiTBlock`s
  (LayerNorm without affine, eps 1e-6; adaLN_modulation(style) -> shift/scale/gate of the
  attention half, adaLN_modulation_trans(trajectory) -> those of the MLP half; timm Attention
  with qkv bias; Mlp with tanh GELU, ratio 4); output = the last 7 tokens. No final layer (as
  in the source).

Weights: numpy default_rng(seed), normal with std 1/sqrt(fan_in); LayerNorm/InstanceNorm
scale 1, bias 0; learned tokens and position embeddings N(0, 0.02). The DiT adaLN layers are
NOT zero-initialised (DiT's initialize_weights is not called in MldDenoiser either), so style
and trajectory visibly change the output of a random network.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper

import pkg_common as C
import pkg_style_common as S
from pkg_mofusion import Builder

SIZES = {
    # paper: configs/modules/motion_vae.yaml (latent [7, 256], ff 1024, 9 layers, 4 heads),
    # denoiser.yaml (9 layers, 4 heads; ff 2048 = torch's default in the content/trajectory
    # encoders), motionclip_params_263.yaml (latent 512, ff 1024, 9 layers).
    "paper": {"d": 256, "ff": 1024, "ff_torch": 2048, "d_style": 512, "ff_style": 1024, "heads": 4, "layers": 9},
    # tiny: the same structure (layers, tokens, heads, masks) at toy widths, committed (< 2 MB).
    "tiny": {"d": 16, "ff": 32, "ff_torch": 32, "d_style": 32, "ff_style": 32, "heads": 4, "layers": 9},
}
LATENT_TOKENS = 7  # configs/modules/motion_vae.yaml latent_dim [7, 256] (vae7.ckpt)
CONTENT_TOKENS = 6  # mld_denoiser.py `self.linear = nn.Linear(7*256, 6*256)`
MAX_LEN = 500  # PositionEmbeddingLearned1D max_len: T + 14 <= 500 in the VAE encoder
T_REF = 196  # FLOPs are counted at T = 196 frames (HumanML3D's longest clip, configs/base.yaml MAX_LEN)
NEG = -1e9  # additive attention bias of a padded key


class M(Builder):
    """Transformer pieces in batch-first layout [N, L, d]. MACs are counted at N = 1."""

    def small(self, base: str, shape) -> str:
        return self.const(base, (0.02 * self.rng.standard_normal(shape)).astype(np.float32))

    def f32(self, v) -> str:
        return self.const("c", np.asarray(v, np.float32), False)

    def layer_norm(self, x: str, d: int, eps: float = 1e-5, affine: bool = True) -> str:
        scale = self.const("ln_s", np.ones(d, np.float32), affine)
        bias = self.const("ln_b", np.zeros(d, np.float32), affine)
        return self.op("LayerNormalization", [x, scale, bias], axis=-1, epsilon=eps)

    def gelu(self, x: str) -> str:
        """Exact GELU (torch default): 0.5 x (1 + erf(x / sqrt 2)); opset 18 has no Gelu op."""
        e = self.op("Erf", [self.op("Mul", [x, self.f32(1.0 / math.sqrt(2.0))])])
        return self.op("Mul", [self.op("Mul", [x, self.f32(0.5)]), self.op("Add", [e, self.f32(1.0)])])

    def gelu_tanh(self, x: str) -> str:
        """GELU(approximate='tanh') (DiT's Mlp)."""
        x3 = self.op("Mul", [self.op("Mul", [x, x]), x])
        inner = self.op("Mul", [self.op("Add", [x, self.op("Mul", [x3, self.f32(0.044715)])]),
                                self.f32(math.sqrt(2.0 / math.pi))])
        return self.op("Mul", [self.op("Mul", [x, self.f32(0.5)]),
                               self.op("Add", [self.op("Tanh", [inner]), self.f32(1.0)])])

    def act(self, x: str, kind: str) -> str:
        return {"gelu": self.gelu, "relu": lambda v: self.op("Relu", [v]), "gelu_tanh": self.gelu_tanh}[kind](x)

    def silu(self, x: str) -> str:
        return self.op("Mul", [x, self.op("Sigmoid", [x])])

    def attention(self, q_in: str, kv_in: str, d: int, heads: int, lq: int, lk: int, bias: str | None) -> str:
        """torch MultiheadAttention / timm Attention: in-projections with bias, softmax(QK^T /
        sqrt(dh) + key bias) V, out-projection."""
        dh = d // heads
        q = self.linear(q_in, d, d, lq)
        k = self.linear(kv_in, d, d, lk)
        v = self.linear(kv_in, d, d, lk)
        split = self.ints([0, 0, heads, dh])
        q = self.op("Transpose", [self.op("Reshape", [q, split])], perm=[0, 2, 1, 3])
        k = self.op("Transpose", [self.op("Reshape", [k, split])], perm=[0, 2, 3, 1])
        v = self.op("Transpose", [self.op("Reshape", [v, split])], perm=[0, 2, 1, 3])
        s = self.op("Mul", [self.op("MatMul", [q, k]), self.f32(1.0 / math.sqrt(dh))])
        if bias is not None:
            s = self.op("Add", [s, bias])
        o = self.op("MatMul", [self.op("Softmax", [s], axis=-1), v])
        self.macs += 2 * lq * lk * d
        o = self.op("Reshape", [self.op("Transpose", [o], perm=[0, 2, 1, 3]), self.ints([0, 0, d])])
        return self.linear(o, d, d, lq)

    def ffn(self, x: str, d: int, ff: int, rows: int, act: str) -> str:
        return self.linear(self.act(self.linear(x, d, ff, rows), act), ff, d, rows)

    def encoder_layer(self, x: str, d: int, ff: int, heads: int, rows: int, bias, act: str) -> str:
        """Post-norm encoder layer (DETR TransformerEncoderLayer normalize_before=False, and
        torch nn.TransformerEncoderLayer with its defaults)."""
        x = self.layer_norm(self.op("Add", [x, self.attention(x, x, d, heads, rows, rows, bias)]), d)
        return self.layer_norm(self.op("Add", [x, self.ffn(x, d, ff, rows, act)]), d)

    def decoder_layer(self, x: str, mem: str, d: int, ff: int, heads: int, rows: int, mem_rows: int, bias) -> str:
        """Post-norm DETR TransformerDecoderLayer: self-attention (frame mask), cross-attention
        to the latent tokens (no mask), FFN (exact GELU)."""
        x = self.layer_norm(self.op("Add", [x, self.attention(x, x, d, heads, rows, rows, bias)]), d)
        x = self.layer_norm(self.op("Add", [x, self.attention(x, mem, d, heads, rows, mem_rows, None)]), d)
        return self.layer_norm(self.op("Add", [x, self.ffn(x, d, ff, rows, "gelu")]), d)

    def skip_stack(self, x: str, layers: int, layer) -> str:
        """SkipTransformerEncoder/Decoder: input blocks, middle, output blocks after
        Linear(2d, d) over [x, skip]; the final LayerNorm is the caller's."""
        skips = []
        for _ in range((layers - 1) // 2):
            x = layer(x)
            skips.append(x)
        x = layer(x)
        for _ in range((layers - 1) // 2):
            x = self.op("Concat", [x, skips.pop()], axis=-1)
            x = layer(self.linear(x, 2 * self.width, self.width, self.rows))
        return x

    def batch_tokens(self, like: str, table: str, n_tok: int, d: int) -> str:
        """A learned [n_tok, d] table repeated over the batch of `like` ([N, ...])."""
        shape = self.op("Concat", [self.op("Slice", [self.op("Shape", [like]), self.ints([0]), self.ints([1])]),
                                   self.ints([n_tok, d])], axis=0)
        return self.op("Expand", [self.op("Unsqueeze", [table, self.ints([0])]), shape])

    def key_bias(self, mask: str, prepend: int) -> str:
        """[N, T] mask (1 valid) -> [N, 1, 1, prepend + T] additive bias (0 or -1e9)."""
        b = self.op("Mul", [self.op("Sub", [mask, self.f32(1.0)]), self.f32(-NEG)])
        if prepend:
            zeros = self.op("Tile", [self.op("Mul", [self.op("Slice", [mask, self.ints([0]), self.ints([1]),
                                                                       self.ints([1])]), self.f32(0.0)]),
                                     self.ints([1, prepend])])
            b = self.op("Concat", [zeros, b], axis=1)
        return self.op("Unsqueeze", [b, self.ints([1, 2])])

    def learned_pe(self, x: str, d: int) -> str:
        """x + pe[:L] (PositionEmbeddingLearned1D, max_len 500)."""
        pe = self.small("pe", (MAX_LEN, d))
        length = self.op("Slice", [self.op("Shape", [x]), self.ints([1]), self.ints([2])])
        return self.op("Add", [x, self.op("Slice", [pe, self.ints([0]), length, self.ints([0])])])

    def sinusoidal_pe(self, x: str, d: int) -> str:
        """MotionCLIP PositionalEncoding: pe[p, 2i] = sin(p w_i), pe[p, 2i+1] = cos(p w_i),
        w_i = exp(-2i ln(10000) / d); computed for the sequence's length."""
        length = self.op("Squeeze", [self.op("Slice", [self.op("Shape", [x]), self.ints([1]), self.ints([2])])])
        pos = self.op("Cast", [self.op("Range", [self.const("zero", np.array(0, np.int64), False), length,
                                                  self.const("one", np.array(1, np.int64), False)])],
                      to=TensorProto.FLOAT)
        w = np.exp(np.arange(0, d, 2, dtype=np.float64) * (-math.log(10000.0) / d)).astype(np.float32)
        arg = self.op("Mul", [self.op("Unsqueeze", [pos, self.ints([1])]), self.f32(w[None, :])])
        pe = self.op("Concat", [self.op("Unsqueeze", [self.op("Sin", [arg]), self.ints([2])]),
                                self.op("Unsqueeze", [self.op("Cos", [arg]), self.ints([2])])], axis=2)
        return self.op("Add", [x, self.op("Reshape", [pe, self.ints([-1, d])])])


def io(name: str, shape, int64: bool = False):
    return helper.make_tensor_value_info(name, TensorProto.INT64 if int64 else TensorProto.FLOAT, shape)


def finish(b: M, name: str, out: str, out_name: str, inputs, out_shape, doc: str) -> onnx.ModelProto:
    b.nodes.append(helper.make_node("Identity", [out], [out_name], name=out_name))
    graph = helper.make_graph(b.nodes, name, inputs=inputs, outputs=[io(out_name, out_shape)], initializer=b.inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", C.OPSET)])
    model.ir_version = 10
    model.doc_string = doc
    return model


def vae_encoder(cfg: dict, seed: int) -> M:
    d, ff, h, layers = cfg["d"], cfg["ff"], cfg["heads"], cfg["layers"]
    b = M(seed)
    b.width, b.rows = d, 2 * LATENT_TOKENS + T_REF
    x = b.linear("features", S.DIM, d, T_REF)
    x = b.op("Concat", [b.batch_tokens(x, b.small("global_motion_token", (2 * LATENT_TOKENS, d)),
                                       2 * LATENT_TOKENS, d), x], axis=1)
    x = b.learned_pe(x, d)
    bias = b.key_bias("mask", 2 * LATENT_TOKENS)
    x = b.skip_stack(x, layers, lambda v: b.encoder_layer(v, d, ff, h, b.rows, bias, "gelu"))
    x = b.layer_norm(x, d)
    b.out = b.op("Slice", [x, b.ints([0]), b.ints([LATENT_TOKENS]), b.ints([1])])  # mu
    return b


def vae_decoder(cfg: dict, seed: int) -> M:
    d, ff, h, layers = cfg["d"], cfg["ff"], cfg["heads"], cfg["layers"]
    b = M(seed)
    b.width, b.rows = d, T_REF
    # queries = zeros [N, T, d] + pe[:T]: shaped from the mask
    zeros = b.op("Mul", [b.op("Unsqueeze", ["mask", b.ints([2])]), b.f32(np.zeros(d, np.float32))])
    x = b.learned_pe(zeros, d)
    bias = b.key_bias("mask", 0)
    x = b.skip_stack(x, layers, lambda v: b.decoder_layer(v, "latent", d, ff, h, T_REF, LATENT_TOKENS, bias))
    x = b.linear(b.layer_norm(x, d), d, S.DIM, T_REF)
    b.out = b.op("Mul", [x, b.op("Unsqueeze", ["mask", b.ints([2])])])
    return b


def style_encoder(cfg: dict, seed: int) -> M:
    d, ff, h, layers = cfg["d_style"], cfg["ff_style"], cfg["heads"], cfg["layers"]
    b = M(seed)
    b.width, b.rows = d, 2 + T_REF
    x = b.linear("features", S.DIM, d, T_REF)
    queries = b.op("Concat", [b.small("muQuery", (1, d)), b.small("sigmaQuery", (1, d))], axis=0)
    x = b.op("Concat", [b.batch_tokens(x, queries, 2, d), x], axis=1)
    x = b.sinusoidal_pe(x, d)
    bias = b.key_bias("mask", 2)
    x = b.skip_stack(x, layers, lambda v: b.encoder_layer(v, d, ff, h, b.rows, bias, "gelu"))
    x = b.layer_norm(x, d)
    b.out = b.op("Squeeze", [b.op("Slice", [x, b.ints([0]), b.ints([1]), b.ints([1])]), b.ints([1])])
    return b


def denoiser(cfg: dict, seed: int) -> M:
    d, h, layers, ff_t, ds = cfg["d"], cfg["heads"], cfg["layers"], cfg["ff_torch"], cfg["d_style"]
    b = M(seed)
    # timestep: diffusers get_timestep_embedding(t, d, flip_sin_to_cos=True, downscale_freq_shift=0)
    half = d // 2
    freqs = np.exp(-math.log(10000.0) * np.arange(half, dtype=np.float64) / half).astype(np.float32)
    arg = b.op("Mul", [b.op("Unsqueeze", [b.op("Cast", ["t"], to=TensorProto.FLOAT), b.ints([1])]),
                       b.f32(freqs[None, :])])
    temb = b.op("Concat", [b.op("Cos", [arg]), b.op("Sin", [arg])], axis=1)
    temb = b.linear(b.silu(b.linear(temb, d, d, 1)), d, d, 1)                        # [N, d]
    temb3 = b.op("Unsqueeze", [temb, b.ints([1])])
    # content: instance norm over the 7 tokens per channel (the "style remover")
    c = b.op("Transpose", ["content"], perm=[0, 2, 1])
    c = b.op("InstanceNormalization", [c, b.const("in_s", np.ones(d, np.float32)),
                                       b.const("in_b", np.zeros(d, np.float32))], epsilon=1e-5)
    c = b.op("Add", [b.op("Transpose", [c], perm=[0, 2, 1]), temb3])
    c = b.learned_pe(c, d)
    c = b.encoder_layer(c, d, ff_t, h, LATENT_TOKENS, None, "relu")
    c = b.linear(b.op("Reshape", [c, b.ints([0, LATENT_TOKENS * d])]), LATENT_TOKENS * d, CONTENT_TOKENS * d, 1)
    c = b.op("Reshape", [c, b.ints([0, CONTENT_TOKENS, d])])
    tokens = CONTENT_TOKENS + LATENT_TOKENS
    x = b.learned_pe(b.op("Concat", [c, "x_t"], axis=1), d)
    # style: ReLU -> Linear(d_s, d) + time
    style = b.op("Add", [b.linear(b.op("Relu", ["style"]), ds, d, 1), temb])
    # trajectory encoder: ReLU -> Linear(3, d), global token, learned PE, 2 ReLU layers, token 0
    macs_before_traj = b.macs
    tr = b.linear(b.op("Relu", ["trajectory"]), S.TRAJ_DIMS, d, T_REF)
    tr = b.op("Concat", [b.batch_tokens(tr, b.small("traj_token", (1, d)), 1, d), tr], axis=1)
    tr = b.learned_pe(tr, d)
    bias = b.key_bias("mask", 1)
    for _ in range(2):
        tr = b.encoder_layer(tr, d, ff_t, h, 1 + T_REF, bias, "relu")
    b.invariant_macs = b.macs - macs_before_traj  # depends on trajectory and mask only
    traj = b.op("Add", [b.op("Squeeze", [b.op("Slice", [tr, b.ints([0]), b.ints([1]), b.ints([1])]), b.ints([1])]),
                        temb])
    # 9 DiT blocks with adaLN-Zero: style modulates attention, trajectory the MLP
    for _ in range(layers):
        mods = []
        for cond in (style, traj):
            m = b.linear(b.silu(cond), d, 3 * d, 1)
            mods.append([b.op("Unsqueeze", [b.op("Slice", [m, b.ints([i * d]), b.ints([(i + 1) * d]), b.ints([1])]),
                                            b.ints([1])]) for i in range(3)])
        for (shift, scale, gate), half_fn in zip(mods, ("attn", "mlp")):
            y = b.layer_norm(x, d, eps=1e-6, affine=False)
            y = b.op("Add", [b.op("Mul", [y, b.op("Add", [scale, b.f32(1.0)])]), shift])
            y = b.attention(y, y, d, h, tokens, tokens, None) if half_fn == "attn" else b.ffn(y, d, 4 * d, tokens, "gelu_tanh")
            x = b.op("Add", [x, b.op("Mul", [gate, y])])
    b.out = b.op("Slice", [x, b.ints([CONTENT_TOKENS]), b.ints([tokens]), b.ints([1])])
    return b


def build_models(size: str, seed: int) -> dict:
    cfg = SIZES[size]
    d, ds = cfg["d"], cfg["d_style"]
    lat = ["N", LATENT_TOKENS, d]
    feat, mask = ["N", "T", S.DIM], ["N", "T"]
    specs = {
        "vae_encoder": (vae_encoder, [("features", feat), ("mask", mask)], ("latent", lat)),
        "vae_decoder": (vae_decoder, [("latent", lat), ("mask", mask)], ("features", feat)),
        "style_encoder": (style_encoder, [("features", feat), ("mask", mask)], ("style", ["N", ds])),
        "denoiser": (denoiser, [("x_t", lat), ("t", ["N"]), ("content", lat), ("trajectory", ["N", "T", S.TRAJ_DIMS]),
                                ("mask", mask), ("style", ["N", ds])], ("pred", lat)),
    }
    out = {}
    for i, (role, (fn, ins, (oname, oshape))) in enumerate(specs.items()):
        b = fn(cfg, seed + i)
        model = finish(b, f"mcm_ldm_ref_{size}_{role}", b.out, oname,
                       [io(n, s, int64=(n == "t")) for n, s in ins], oshape,
                       f"MCM-LDM {role}, size {size}, SEEDED RANDOM WEIGHTS (seed {seed + i})")
        out[role] = (model, ins, [(oname, oshape)], b.params, 2 * b.macs, 2 * getattr(b, "invariant_macs", 0))
    return out


def build(out_dir: Path, size: str, seed: int) -> dict:
    out_dir.mkdir(parents=True, exist_ok=True)
    models = build_models(size, seed)
    comps, stats = {}, {}
    for role, (model, ins, outs, params, flops, _) in models.items():
        sha = C.save_model(model, out_dir / f"{role}.onnx")
        comps[role] = (f"{role}.onnx", sha, ins, outs)
        stats[role] = (params, flops)
    total = sum(p for p, _ in stats.values())
    desc = (f"MCM-LDM architecture (MLD VAE with 7 latent tokens, DiT denoiser with content/style/"
            f"trajectory conditions, MotionCLIP-263 style encoder), size '{size}', SEEDED RANDOM WEIGHTS "
            f"(seed {seed}): {total:,} parameters, denoiser {stats['denoiser'][1] / 1e9:.3f} GFLOPs per "
            f"evaluation. Its output is not a style transfer: it measures speed and exercises the contract.")
    S.write_manifest(out_dir, name="mcm-ldm-ref", description=desc, max_frames=S.TRAINED_MAX_FRAMES,
                     mean=np.zeros(S.DIM), std=np.ones(S.DIM),
                     sampler={"set_alpha_to_one": False, "guidance": 2.5, "content_guidance": 1.0,
                              "style_guidance": 2.5},
                     components=comps)
    (out_dir / "README.md").write_text(readme_text(size, seed), encoding="utf-8")
    return {"parameters": total, "denoiser_gflops": round(stats["denoiser"][1] / 1e9, 4),
            "step_invariant_gflops": round(models["denoiser"][5] / 1e9, 4)}


def check(pkg: Path, m: dict, sess: dict) -> None:
    """Each condition reaches the output; padded frames are ignored (the masks work)."""
    rng = np.random.default_rng(11)
    lat_shape = [1] + list(m["components"]["denoiser"]["inputs"][0]["shape"][1:])
    ds = m["components"]["style_encoder"]["outputs"][0]["shape"][1]
    t_len = 40
    base = {"x_t": rng.standard_normal(lat_shape).astype(np.float32), "t": np.array([500], np.int64),
            "content": rng.standard_normal(lat_shape).astype(np.float32),
            "trajectory": rng.standard_normal((1, t_len, S.TRAJ_DIMS)).astype(np.float32),
            "mask": np.ones((1, t_len), np.float32), "style": rng.standard_normal((1, ds)).astype(np.float32)}
    (ref,) = sess["denoiser"].run(None, base)
    for k in ("x_t", "t", "content", "trajectory", "style"):
        alt = dict(base)
        alt[k] = (base[k] + 1) if k == "t" else rng.standard_normal(base[k].shape).astype(np.float32)
        (p,) = sess["denoiser"].run(None, alt)
        if np.abs(p - ref).max() < 1e-6:
            S.fail(f"denoiser ignores {k}")
    # A padded trajectory frame must not matter; a valid one must.
    mask = base["mask"].copy()
    mask[0, -10:] = 0
    tr = base["trajectory"].copy()
    (a,) = sess["denoiser"].run(None, dict(base, mask=mask))
    tr[0, -10:] += 5.0
    (b,) = sess["denoiser"].run(None, dict(base, mask=mask, trajectory=tr))
    # 1e-5: softmax weights of masked keys are exp(-1e9) = 0 exactly; only summation order moves.
    if np.abs(a - b).max() > 1e-5 * (np.abs(a).max() + 1):
        S.fail("denoiser: padded trajectory frames change the output")
    feats = S.random_motion(rng, 1, t_len)
    (lat,) = sess["vae_encoder"].run(None, {"features": feats, "mask": mask})
    f2 = feats.copy()
    f2[0, -10:] += 5.0
    (lat2,) = sess["vae_encoder"].run(None, {"features": f2, "mask": mask})
    if np.abs(lat - lat2).max() > 1e-5 * (np.abs(lat).max() + 1):
        S.fail("vae_encoder: padded frames change the latent")
    (dec,) = sess["vae_decoder"].run(None, {"latent": lat, "mask": mask})
    if np.any(dec[0, -10:] != 0):
        S.fail("vae_decoder: padded frames are not zero")
    print(f"ok  {pkg}: x_t, t, content, trajectory and style all change pred; padded frames ignored "
          f"(trajectory encoder, VAE encoder) and zeroed (VAE decoder)")


def readme_text(size: str, seed: int) -> str:
    rows = []
    for s in SIZES:
        models = build_models(s, seed)
        cells = " | ".join(f"{models[r][3]:,} / {models[r][4] / 1e9:.3f}" for r in
                           ("vae_encoder", "vae_decoder", "style_encoder", "denoiser"))
        total = sum(models[r][3] for r in models)
        cfg = SIZES[s]
        rows.append(f"| {s} | {cfg['d']} / {cfg['d_style']} | {cells} | {total:,} |")
        if s == "paper":
            inv, den = models["denoiser"][5] / 1e9, models["denoiser"][4] / 1e9
    table = "\n".join(rows)
    return f"""# `mcm-ldm-ref` — MCM-LDM's architecture with seeded random weights (size `{size}`)

Built by `models/packages/build.py mcm-ldm-ref --size {size} --seed {seed}`. **The weights are
random**: the output is not a style transfer. The package exists to run choreod's `stylize`
pipeline on networks of exactly MCM-LDM's structure (Song et al., CVPR 2024; code
XingliangJin/MCM-LDM) — tensor names, shapes, masks and cost — and to measure speed. The
`tiny` size is committed; build `paper` on demand:

    .venv/bin/python models/packages/build.py mcm-ldm-ref --size paper --out target/bench/mcm-ldm-paper --check

| size | d / d_style | vae_encoder | vae_decoder | style_encoder | denoiser | parameters |
|---|---|---|---|---|---|---|
{table}

Cells: parameters / GFLOPs for one call at N = 1 and T = {T_REF} frames (FLOPs = 2 x the
multiply-accumulates of every linear layer and attention product; norms and element-wise ops
not counted). A transfer costs one VAE encode, one style encode, `steps` denoiser calls (x2
rows with guidance) and one VAE decode. Only the denoiser's trajectory encoder sees the
frames, and it depends on `trajectory` and `mask` alone (the timestep is added after it): at
the paper size and T = {T_REF} it is {inv:.3f} of the denoiser's {den:.3f} GFLOPs ({inv / den:.0%}), work a
sampler can do once per sequence instead of at every step (the contract keeps content,
trajectory, mask and style constant across steps).

## Components (the style-transfer contract, models/packages/README.md)

| role | inputs | output |
|---|---|---|
| vae_encoder | `features` [N,T,263] normalised, dims 0..3 zeroed; `mask` [N,T] | `latent` [N,7,d]: the posterior mean |
| vae_decoder | `latent` [N,7,d]; `mask` [N,T] | `features` [N,T,263] normalised, padded frames 0 |
| style_encoder | `features` [N,T,263] raw scale, dims 0..3 zeroed; `mask` | `style` [N,d_style] (MotionCLIP mu) |
| denoiser | `x_t`, `content` [N,7,d]; `t` int64 [N]; `trajectory` [N,T,3]; `mask`; `style` (zeros = null) | `pred` [N,7,d] (epsilon) |

Lengths: T + 14 <= 500 in the VAE encoder and T <= 500 in the decoder (learned position
embeddings of 500 rows), T + 1 <= 500 in the trajectory encoder; the manifest's `max_frames` is
196 (the longest clip MCM-LDM trained on, configs/base.yaml) and `min_frames` 40 (the shortest).
Manifest mean/std are the identity (nothing was trained).

## Architecture (what each graph computes, after the official source)

- **VAE** (`mld/models/architectures/mld_vae.py`, arch `encoder_decoder`): skel_embedding
  Linear(263, d); 14 learned `global_motion_token`s (7 mu + 7 logvar: the latent is the first
  7) before the frames; learned PE (max 500); SkipTransformerEncoder of 9 post-norm layers
  (4 heads, ff = 4d, exact GELU): 4 layers, a middle one, 4 layers each after Linear(2d, d) on
  [x, skip]; final LayerNorm. Decoder: zero queries + learned PE, SkipTransformerDecoder (self-
  attention with the frame mask, cross-attention to the 7 tokens, FFN), final LayerNorm,
  Linear(d, 263), padded frames zeroed. Deterministic: mu, never a sample.
- **MotionCLIP-263 encoder** (`mld/models/motionclip_263/models/architectures/transformer.py`):
  Linear(263, d_style), muQuery + sigmaQuery, sinusoidal PE, the same 9-layer skip encoder; mu.
- **Denoiser** (`mld/models/architectures/mld_denoiser.py`): timestep embedding (cos first,
  Linear-SiLU-Linear); content: InstanceNorm over the 7 tokens + time, learned PE, 1 ReLU
  transformer layer (ff {SIZES[size]['ff_torch']}), Linear(7d, 6d) -> 6 tokens before the 7 noisy tokens
  (learned PE over 13); style: ReLU, Linear(d_style, d) + time; trajectory: ReLU, Linear(3, d),
  a global token, learned PE, 2 ReLU layers with the frame mask, token 0 + time; 9 DiT blocks,
  adaLN from the style on the attention half and from the trajectory on the MLP half (tanh-GELU
  MLP, ratio 4); the output is the last 7 tokens.
- **Checked against the official modules**: `check_mcm_ldm_against_official.py` (local only:
  torch, timm and a checkout of the official repository) builds MldDenoiser, MldVae and
  MotionCLIP's Encoder_TRANSFORMER at the paper's widths, copies their random weights into these
  builders and runs both on the same batch (lengths 50 and 38): largest differences 9.5e-7
  (denoiser), 2.5e-6 (VAE encoder mu), 2.1e-6 (VAE decoder), 2.4e-6 (MotionCLIP mu), at output
  scales of 2-4 (float32 summation order).
- Export notes: key-padding masks come from the `mask` input (the source builds them from
  Python length lists); `.squeeze()` calls of the source are explicit axes here, so N = 1 works;
  dropout is off (inference).
"""
