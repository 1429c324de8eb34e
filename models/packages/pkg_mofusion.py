"""The `mofusion-ref` package: MoFusion's denoiser architecture with seeded random weights.

Architecture (after Dabral et al., "MoFusion", CVPR 2023: a 1D U-Net over time whose residual
blocks take a sinusoidal timestep embedding and which cross-attends to the audio features; the
exact widths below are ours, the paper's code is not public):

    x_t [N,T,72] -> transpose [N,72,T] -> Conv1d k3 -> c0
    3 down levels l = 0,1,2:  ResBlock(c_{l-1} -> c_l, temb) -> CrossAttn(music) -> skip_l
                              -> Conv1d k3 stride 2 (T: 150 -> 75 -> 38 -> 19)
    bottleneck:               ResBlock -> CrossAttn -> ResBlock
    3 up levels l = 2,1,0:    nearest Resize to len(skip_l) -> Conv1d k3 -> Concat(skip_l)
                              -> ResBlock(-> c_l, temb) -> CrossAttn(music)
    out: GroupNorm -> SiLU -> Conv1d k3 -> 72 -> transpose -> pred [N,T,72]

- ResBlock: GroupNorm -> SiLU -> Conv k3 -> + Linear(SiLU(temb)) -> GroupNorm -> SiLU -> Conv k3,
  plus a 1x1 Conv on the skip path when channels change (the DDPM/ADM residual block).
- GroupNorm: Reshape [N,G,-1] -> InstanceNormalization -> Reshape back -> per-channel affine.
  Opset 18's GroupNormalization takes per-GROUP scale/bias (redefined per-channel in opset 21),
  so it cannot express PyTorch's nn.GroupNorm; the reshape form is exact and runs everywhere.
- CrossAttn: pre-LayerNorm over channels, multi-head attention with queries from the motion
  features and keys/values from the music memory, output projection, residual add.
- Music memory: log-mel [N,157,80] -> Linear 80 -> d_music (+ bias). cond = 0 replaces it by a
  learned null embedding [157, d_music]: memory = cond * proj(music) + (1 - cond) * null.
- Timestep: sinusoidal embedding (dim c0, the DDPM/transformer formula with 10000) -> Linear ->
  SiLU -> Linear (4 c0).
- Odd lengths: no padding; the stride-2 convs round up (ceil) and each up level resizes to its
  skip's exact length, so any T works (T = 150 in the manifest).

Weights: numpy default_rng(seed), normal with std 1/sqrt(fan_in) (keeps activations O(1) so
outputs stay finite and informative); norms start at scale 1 / bias 0; biases N(0, 0.02).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

import pkg_common as C

SIZES = {
    # tiny: for tests, committed (< 1 MB); paper: MoFusion-like width for benchmarks.
    "tiny": {"channels": (16, 24, 32), "groups": 8, "heads": 2, "d_music": 32},
    "paper": {"channels": (128, 256, 512), "groups": 32, "heads": 8, "d_music": 256},
}


class Builder:
    """Tiny onnx.helper graph builder that also counts parameters and MACs (N=1, T=150, F=157)."""

    def __init__(self, seed: int):
        self.rng = np.random.default_rng(seed)
        self.nodes: list = []
        self.inits: list = []
        self.params = 0
        self.macs = 0
        self.n = 0

    def name(self, base: str) -> str:
        self.n += 1
        return f"{base}_{self.n}"

    def const(self, base: str, arr: np.ndarray, param: bool = True) -> str:
        nm = self.name(base)
        self.inits.append(numpy_helper.from_array(np.ascontiguousarray(arr), nm))
        if param:
            self.params += int(arr.size)
        return nm

    def ints(self, vals) -> str:
        return self.const("shape", np.asarray(vals, dtype=np.int64), param=False)

    def weight(self, base: str, shape, fan_in: int) -> str:
        w = self.rng.standard_normal(shape) / math.sqrt(fan_in)
        return self.const(base, w.astype(np.float32))

    def bias(self, base: str, n: int) -> str:
        return self.const(base, (0.02 * self.rng.standard_normal(n)).astype(np.float32))

    def op(self, op_type: str, inputs, base: str | None = None, **attrs) -> str:
        out = self.name(base or op_type.lower())
        self.nodes.append(helper.make_node(op_type, list(inputs), [out], name=out, **attrs))
        return out

    # --- layers (conv layout [N, C, T]) -----------------------------------------------------
    def conv(self, x: str, cin: int, cout: int, k: int, t_out: int, stride: int = 1) -> str:
        w = self.weight("conv_w", (cout, cin, k), cin * k)
        b = self.bias("conv_b", cout)
        self.macs += cout * cin * k * t_out
        return self.op("Conv", [x, w, b], "conv", kernel_shape=[k], pads=[k // 2, k // 2], strides=[stride])

    def silu(self, x: str) -> str:
        return self.op("Mul", [x, self.op("Sigmoid", [x])], "silu")

    def group_norm(self, x: str, c: int, groups: int) -> str:
        g = self.op("Reshape", [x, self.ints([0, groups, -1])])
        g = self.op("InstanceNormalization", [g, self.const("gn_one", np.ones(groups, np.float32), False),
                                              self.const("gn_zero", np.zeros(groups, np.float32), False)],
                    epsilon=1e-5)
        g = self.op("Reshape", [g, self.op("Shape", [x])])
        gamma = self.const("gn_gamma", np.ones((c, 1), np.float32))
        beta = self.const("gn_beta", np.zeros((c, 1), np.float32))
        return self.op("Add", [self.op("Mul", [g, gamma]), beta])

    def linear(self, x: str, cin: int, cout: int, rows: int) -> str:
        w = self.weight("lin_w", (cin, cout), cin)
        b = self.bias("lin_b", cout)
        self.macs += rows * cin * cout
        return self.op("Add", [self.op("MatMul", [x, w]), b], "linear")

    def res_block(self, x: str, cin: int, cout: int, temb: str, c_temb: int, t_len: int, groups: int) -> str:
        h = self.conv(self.silu(self.group_norm(x, cin, groups)), cin, cout, 3, t_len)
        emb = self.linear(self.silu(temb), c_temb, cout, 1)                # [N, cout]
        h = self.op("Add", [h, self.op("Unsqueeze", [emb, self.ints([2])])])
        h = self.conv(self.silu(self.group_norm(h, cout, groups)), cout, cout, 3, t_len)
        skip = x if cin == cout else self.conv(x, cin, cout, 1, t_len)
        return self.op("Add", [h, skip], "res")

    def cross_attn(self, x: str, c: int, mem: str, d_mem: int, heads: int, t_len: int) -> str:
        dh = c // heads
        h = self.op("Transpose", [x], perm=[0, 2, 1])                      # [N, T, C]
        ln_s = self.const("ln_s", np.ones(c, np.float32))
        ln_b = self.const("ln_b", np.zeros(c, np.float32))
        h = self.op("LayerNormalization", [h, ln_s, ln_b], axis=-1, epsilon=1e-5)
        q = self.linear(h, c, c, t_len)
        k = self.linear(mem, d_mem, c, C.MUSIC_FRAMES)
        v = self.linear(mem, d_mem, c, C.MUSIC_FRAMES)
        split = self.ints([0, 0, heads, dh])
        q = self.op("Transpose", [self.op("Reshape", [q, split])], perm=[0, 2, 1, 3])   # [N,H,T,dh]
        k = self.op("Transpose", [self.op("Reshape", [k, split])], perm=[0, 2, 3, 1])   # [N,H,dh,F]
        v = self.op("Transpose", [self.op("Reshape", [v, split])], perm=[0, 2, 1, 3])   # [N,H,F,dh]
        scale = self.const("attn_scale", np.array(1.0 / math.sqrt(dh), np.float32), False)
        s = self.op("Mul", [self.op("MatMul", [q, k]), scale])
        a = self.op("Softmax", [s], axis=-1)
        o = self.op("MatMul", [a, v])                                      # [N,H,T,dh]
        self.macs += 2 * t_len * C.MUSIC_FRAMES * c
        o = self.op("Reshape", [self.op("Transpose", [o], perm=[0, 2, 1, 3]), self.ints([0, 0, c])])
        o = self.linear(o, c, c, t_len)
        return self.op("Add", [x, self.op("Transpose", [o], perm=[0, 2, 1])], "attn_res")


def build_model(size: str, seed: int) -> tuple[onnx.ModelProto, int, int]:
    cfg = SIZES[size]
    ch, groups, heads, d_music = cfg["channels"], cfg["groups"], cfg["heads"], cfg["d_music"]
    c0 = ch[0]
    c_temb = 4 * c0
    b = Builder(seed)

    # Timestep embedding: sin/cos(t * 10000^(-i/half)) -> Linear -> SiLU -> Linear.
    half = c0 // 2
    freqs = np.exp(-math.log(10000.0) * np.arange(half, dtype=np.float64) / half).astype(np.float32)
    tf = b.op("Unsqueeze", [b.op("Cast", ["t"], to=TensorProto.FLOAT), b.ints([1])])
    arg = b.op("Mul", [tf, b.const("freqs", freqs[None, :], False)])
    temb = b.op("Concat", [b.op("Sin", [arg]), b.op("Cos", [arg])], axis=1)
    temb = b.linear(b.silu(b.linear(temb, c0, c_temb, 1)), c_temb, c_temb, 1)

    # Music memory with the null embedding for cond = 0.
    proj = b.linear("music", C.N_MELS, d_music, C.MUSIC_FRAMES)           # [N, F, d]
    null = b.const("null_music", (0.02 * b.rng.standard_normal((1, C.MUSIC_FRAMES, d_music))).astype(np.float32))
    cnd = b.op("Unsqueeze", ["cond", b.ints([1, 2])])                      # [N, 1, 1]
    one = b.const("one", np.array(1.0, np.float32), False)
    mem = b.op("Add", [b.op("Mul", [proj, cnd]), b.op("Mul", [null, b.op("Sub", [one, cnd])])])

    lens = [C.WINDOW_FRAMES]
    for _ in range(3):
        lens.append((lens[-1] + 1) // 2)                                   # 150, 75, 38, 19
    h = b.op("Transpose", ["x_t"], perm=[0, 2, 1])
    h = b.conv(h, C.DIM, c0, 3, lens[0])
    skips = []
    cin = c0
    for lvl in range(3):
        h = b.res_block(h, cin, ch[lvl], temb, c_temb, lens[lvl], groups)
        h = b.cross_attn(h, ch[lvl], mem, d_music, heads, lens[lvl])
        skips.append(h)
        h = b.conv(h, ch[lvl], ch[lvl], 3, lens[lvl + 1], stride=2)
        cin = ch[lvl]
    h = b.res_block(h, cin, ch[2], temb, c_temb, lens[3], groups)
    h = b.cross_attn(h, ch[2], mem, d_music, heads, lens[3])
    h = b.res_block(h, ch[2], ch[2], temb, c_temb, lens[3], groups)
    cin = ch[2]
    for lvl in (2, 1, 0):
        skip = skips[lvl]
        sizes = b.op("Concat", [b.op("Slice", [b.op("Shape", [h]), b.ints([0]), b.ints([2])]),
                                b.op("Slice", [b.op("Shape", [skip]), b.ints([2]), b.ints([3])])], axis=0)
        h = b.op("Resize", [h, "", "", sizes], mode="nearest", coordinate_transformation_mode="asymmetric",
                 nearest_mode="floor")
        h = b.conv(h, cin, cin, 3, lens[lvl])
        h = b.op("Concat", [h, skip], axis=1)
        h = b.res_block(h, cin + ch[lvl], ch[lvl], temb, c_temb, lens[lvl], groups)
        h = b.cross_attn(h, ch[lvl], mem, d_music, heads, lens[lvl])
        cin = ch[lvl]
    h = b.conv(b.silu(b.group_norm(h, cin, groups)), cin, C.DIM, 3, lens[0])
    out = b.op("Transpose", [h], perm=[0, 2, 1])
    b.nodes.append(helper.make_node("Identity", [out], ["pred"], name="pred"))

    f = TensorProto.FLOAT
    graph = helper.make_graph(
        b.nodes, f"mofusion_ref_{size}",
        inputs=[helper.make_tensor_value_info("x_t", f, ["N", C.WINDOW_FRAMES, C.DIM]),
                helper.make_tensor_value_info("t", TensorProto.INT64, ["N"]),
                helper.make_tensor_value_info("music", f, ["N", C.MUSIC_FRAMES, C.N_MELS]),
                helper.make_tensor_value_info("cond", f, ["N"])],
        outputs=[helper.make_tensor_value_info("pred", f, ["N", C.WINDOW_FRAMES, C.DIM])],
        initializer=b.inits,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", C.OPSET)])
    model.ir_version = 10  # what onnxscript 0.7.2 emits for opset 18; ORT 1.31 reads it
    return model, b.params, b.macs


def build(out_dir: Path, size: str, seed: int) -> dict:
    model, params, macs = build_model(size, seed)
    flops = 2 * macs
    cfg = SIZES[size]
    desc = (f"MoFusion architecture (1D U-Net, 3 down/3 up levels, residual blocks, cross-attention to "
            f"the linearly projected log-mel at every level, sinusoidal timestep embedding through a "
            f"2-layer SiLU MLP), size '{size}', channels {cfg['channels']}, SEEDED RANDOM WEIGHTS "
            f"(seed {seed}): {params:,} parameters, {flops / 1e9:.3f} GFLOPs per evaluation at N=1. "
            f"Its output is not a dance: it measures speed and exercises the package contract.")
    model.doc_string = desc
    out_dir.mkdir(parents=True, exist_ok=True)
    sha = C.save_model(model, out_dir / "denoiser.onnx")
    # Identity normalisation: random weights were trained on nothing.
    C.write_manifest(out_dir, name="mofusion-ref", description=desc, mean=np.zeros(C.DIM),
                     std=np.ones(C.DIM), onnx_file="denoiser.onnx", onnx_sha256=sha)
    (out_dir / "README.md").write_text(readme_text(size, seed, params, flops), encoding="utf-8")
    return {"params": params, "flops": flops}


def readme_text(size: str, seed: int, params: int, flops: int) -> str:
    other = {}
    for s in SIZES:
        _, p, m = build_model(s, seed) if s != size else (None, params, flops // 2)
        other[s] = (p, 2 * m)
    rows = "\n".join(f"| {s} | {SIZES[s]['channels']} | {SIZES[s]['groups']} | {SIZES[s]['heads']} | "
                     f"{SIZES[s]['d_music']} | {other[s][0]:,} | {other[s][1] / 1e9:.3f} |" for s in SIZES)
    return f"""# `mofusion-ref` — MoFusion's architecture with seeded random weights (size `{size}`)

Built by `models/packages/build.py mofusion-ref --size {size} --seed {seed}`. **The weights are
random** (numpy `default_rng({seed})`): the output is not a dance. The package exists to measure
speed (BENCHMARKS.md) and to exercise the model-package contract end to end with a network of the
right shape and cost. The `tiny` size is committed; build `paper` on demand:

    .venv/bin/python models/packages/build.py mofusion-ref --size paper --out target/bench/mofusion-paper --check

| size | channels per level | groups | heads | music dim | parameters | GFLOPs / evaluation (N=1) |
|---|---|---|---|---|---|---|
{rows}

FLOPs = 2 x multiply-accumulates of every Conv, MatMul and attention product for one window
(N = 1, T = 150 motion frames, F = 157 mel frames); element-wise ops and norms are not counted.
Cost grows linearly with N (a batch of windows, or twice that with classifier-free guidance).

## Architecture

After Dabral et al., *MoFusion: A Framework for Denoising-Diffusion-based Motion Synthesis*
(CVPR 2023): a 1D convolutional U-Net over time with three down and three up levels, residual
blocks conditioned on a sinusoidal timestep embedding passed through a two-layer MLP (SiLU), and
cross-attention from the motion features to the linearly projected log-mel spectrogram. MoFusion's
code is not public, so widths and the placement of attention (after every residual block of every
level and in the bottleneck) are our choices.

- in: `x_t` [N,150,72] -> [N,72,150] -> Conv1d k3 -> c0
- down l = 0..2: ResBlock -> CrossAttn -> (skip) -> Conv1d k3 stride 2; lengths 150 -> 75 -> 38 -> 19
- bottleneck: ResBlock -> CrossAttn -> ResBlock
- up l = 2..0: nearest Resize to the skip's length -> Conv1d k3 -> Concat skip -> ResBlock -> CrossAttn
- out: GroupNorm -> SiLU -> Conv1d k3 -> 72 -> `pred` [N,150,72]
- ResBlock: GroupNorm, SiLU, Conv k3, + Linear(SiLU(temb)), GroupNorm, SiLU, Conv k3, 1x1 skip conv
  when channels change. GroupNorm is Reshape -> InstanceNormalization -> Reshape -> per-channel affine
  (opset 18's GroupNormalization has per-group affine parameters, unlike PyTorch's GroupNorm).
- Odd lengths need no padding: stride-2 convs round up and each up level resizes to its skip.
- Music: `music` [N,157,80] log-mel dB -> Linear 80 -> music dim. `cond` = 0 swaps in a learned null
  embedding [157, music dim] (memory = cond * proj + (1 - cond) * null), so classifier-free guidance
  batches conditional and unconditional rows in one call.
- Manifest normalisation is the identity (mean 0, std 1) since nothing was trained.
"""
