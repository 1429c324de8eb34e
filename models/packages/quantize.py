#!/usr/bin/env python3
"""Make an int8 copy of a choreod model package and measure what it costs in accuracy.

    python models/packages/quantize.py SRC -o DST [--fp32-share 0.05] [--rank-nodes 16] [--seed 0]

Every component's matrix products (Conv, and MatMul / Gemm whose weight is a constant) become
int8: weights per output channel (signed), activations per tensor (unsigned), ranges calibrated on
inputs drawn from the manifest's tensor specs (below). The format is ONNX's QDQ form, which ONNX
Runtime's CPU provider fuses into integer kernels (u8 x s8: the fast path of its x86 kernels; s8
activations run 2-4x slower there, measured). Measured first, on each node alone: how far
quantising only that node moves the component's output. The nodes whose error dominates stay
float32, most harmful first, while their share of the component's weights stays within
`--fp32-share` (a node too big to fit is passed over). Each measurement builds and runs the whole
component once, so only `--rank-nodes N` candidates are measured (default 16; 0: none, every node
int8): the nodes small enough to fit the share, N of them spread evenly through the graph when
there are more (every depth represented). The paper-size mcm-ldm-ref has 59-95 quantisable
nodes per component, 308 in all: measuring all of them took over 15 minutes on 2 cores.

The manifest is copied with new sha256s, a `-int8` name and a `[quantization]` section: the
scheme, the source package's name and component sha256s, the nodes left in float32, and the
measured error on the test inputs (max and RMS, relative to the largest output value / the
output's RMS). `choreod models check DST --against SRC` repeats that comparison in Rust.

Calibration inputs (two rows each, 8 draws): timesteps spread over the schedule; guidance flags
(`cond`, `keep`) both 0 and 1; `mask` all ones; `genre` ids over the package's genres; log-mel
`music` in -80..+20 dB; everything else standard normal (noisy motion, latents, style noise).
With trained weights, real inputs calibrate better: pass `--calibration FILE.npz` with one array
per input name (rows on axis 0) recorded from real runs.

A random-weight package is a poor judge of accuracy: its networks are chaotic (a 1e-4 relative
perturbation of every weight moves the paper-size mofusion-ref's output by 1 %), so its measured
deviation is a sanity bound only. With trained weights, compare the int8 package's dances with the
float32 package's on your own songs (`choreod dance` both with one seed; `choreod eval`).

Run with the project venv (onnx, onnxruntime with its quantization tools, numpy). No torch.
"""

from __future__ import annotations

import argparse
import hashlib
import logging
import re
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

# The package builder beside this file reads manifests the same way.
from build import load_manifest

SCHEME = "int8-qdq-static: weights s8 per channel, activations u8 per tensor (onnxruntime.quantization)"
CALIBRATION_DRAWS = 8
QUANTISED_OPS = ("Conv", "MatMul", "Gemm")


def fail(msg: str) -> None:
    raise SystemExit(f"quantize: {msg}")


def concrete_shape(shape: list, rows: int, frames: int) -> tuple:
    """The manifest's shape with its batch dimension ("N") set to `rows` and any other symbolic
    dimension (a sequence length, "T") to `frames`."""
    return tuple(rows if d == "N" else d if isinstance(d, int) else frames for d in shape)


def draw_inputs(manifest: dict, inputs: list, rng: np.random.Generator, rows: int) -> dict:
    train_steps = int(manifest.get("diffusion", {}).get("train_steps", 1000))
    genres = len(manifest.get("lodge", {}).get("genres", [])) or 1
    log_mel = "n_mels" in manifest.get("audio", {})
    motion = manifest.get("motion", {})
    frames = int(motion.get("max_frames", motion.get("window_frames", 64)))
    feeds = {}
    for spec in inputs:
        name, shape = spec["name"], concrete_shape(spec["shape"], rows, frames)
        if spec["dtype"] == "int64":
            high = genres if name == "genre" else train_steps
            feeds[name] = rng.integers(0, high, size=shape).astype(np.int64)
        elif name in ("cond", "keep"):
            feeds[name] = (np.arange(np.prod(shape)) % 2).reshape(shape).astype(np.float32)
        elif name == "mask":
            feeds[name] = np.ones(shape, np.float32)
        elif name == "music" and log_mel:
            feeds[name] = rng.uniform(-80.0, 20.0, size=shape).astype(np.float32)
        else:
            feeds[name] = rng.standard_normal(shape).astype(np.float32)
    return feeds


def quantisable_nodes(model) -> list:
    weights = {i.name for i in model.graph.initializer}
    return [n for n in model.graph.node
            if n.op_type in QUANTISED_OPS and len(n.input) > 1 and n.input[1] in weights]


def weight_counts(model, nodes: list) -> dict:
    sizes = {i.name: int(np.prod(i.dims)) for i in model.graph.initializer}
    return {n.name: sizes[n.input[1]] for n in nodes}


class Reader:
    """onnxruntime's CalibrationDataReader protocol over a list of feeds."""

    def __init__(self, feeds: list):
        self.feeds = iter(feeds)

    def get_next(self):
        return next(self.feeds, None)


def quantise(src: Path, dst: Path, calibration: list, nodes: list) -> None:
    from onnxruntime.quantization import QuantFormat, QuantType, quantize_static

    quantize_static(str(src), str(dst), Reader(calibration), quant_format=QuantFormat.QDQ,
                    per_channel=True, weight_type=QuantType.QInt8,
                    activation_type=QuantType.QUInt8, nodes_to_quantize=nodes)


def run(path: Path, feeds: list) -> list:
    return run_model(str(path), feeds)


def run_model(model, feeds: list) -> list:
    """Run a model (a path or a ModelProto) on each feed with ONNX Runtime's CPU provider."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 2
    source = model if isinstance(model, str) else model.SerializeToString()
    sess = ort.InferenceSession(source, opts, providers=["CPUExecutionProvider"])
    return [sess.run(None, f) for f in feeds]


def with_int8_weight(model, node):
    """A copy of `model` whose `node` weight went through a symmetric per-output-channel int8
    round trip: the weight's share of the quantisation error, measured without a calibration
    pass (activation error is common to every node and not what ranks them)."""
    import onnx
    from onnx import numpy_helper

    copy = onnx.ModelProto()
    copy.CopyFrom(model)
    init = next(i for i in copy.graph.initializer if i.name == node.input[1])
    w = numpy_helper.to_array(init).astype(np.float32)
    # Output channels: Conv weight (out, in, k...) axis 0; MatMul (in, out) axis 1; Gemm by transB.
    trans_b = any(a.name == "transB" and a.i == 1 for a in node.attribute)
    axis = 0 if node.op_type == "Conv" or (node.op_type == "Gemm" and trans_b) else w.ndim - 1
    reduce = tuple(d for d in range(w.ndim) if d != axis)
    scale = np.maximum(np.abs(w).max(axis=reduce, keepdims=True), 1e-30) / 127.0
    init.CopyFrom(numpy_helper.from_array((np.round(w / scale) * scale).astype(np.float32), init.name))
    return copy


def rank_candidates(fitting: list, limit: int) -> list:
    """At most `limit` of the nodes that fit the float32 share, evenly spaced in graph order."""
    if len(fitting) <= limit:
        return fitting
    if limit == 0:
        return []
    picks = np.linspace(0, len(fitting) - 1, limit).round().astype(int)
    return [fitting[i] for i in sorted(set(picks.tolist()))]


def deviation(got: list, want: list) -> tuple:
    """Largest |difference| over the largest |reference value|, and the RMS of the difference over
    the reference's RMS, across every output of every test call."""
    diff = np.concatenate([(g - w).ravel() for gs, ws in zip(got, want) for g, w in zip(gs, ws)])
    ref = np.concatenate([w.ravel() for ws in want for w in ws])
    scale = max(float(np.abs(ref).max()), 1e-30)
    rms = max(float(np.sqrt(np.mean(ref.astype(np.float64) ** 2))), 1e-30)
    return float(np.abs(diff).max()) / scale, float(np.sqrt(np.mean(diff.astype(np.float64) ** 2))) / rms


def quantise_component(src_pkg: Path, dst_pkg: Path, manifest: dict, role: str, comp: dict,
                       args, rng: np.random.Generator, tmp: Path) -> dict:
    import onnx
    from onnxruntime.quantization.shape_inference import quant_pre_process

    src = src_pkg / comp["file"]
    pre = tmp / f"{role}.pre.onnx"
    # Constant folding and shape inference first, as onnxruntime's quantiser asks.
    quant_pre_process(str(src), str(pre), skip_symbolic_shape=True)
    model = onnx.load(str(pre))
    nodes = quantisable_nodes(model)
    if not nodes:
        print(f"{role}: no Conv / MatMul with constant weights; copied as float32", file=sys.stderr)
        shutil.copyfile(src, dst_pkg / comp["file"])
        return {"nodes": 0, "fp32": [], "error": (0.0, 0.0)}
    if args.calibration is not None:
        data = np.load(args.calibration)
        names = [i["name"] for i in comp["inputs"]]
        missing = [n for n in names if n not in data]
        if missing:
            fail(f"{args.calibration}: no array for {role}'s inputs {missing}")
        count = min(len(data[n]) for n in names)
        calibration = [{n: data[n][i:i + 2] for n in names} for i in range(0, count, 2)]
    else:
        calibration = [draw_inputs(manifest, comp["inputs"], rng, 2) for _ in range(CALIBRATION_DRAWS)]
    tests = [draw_inputs(manifest, comp["inputs"], rng, 2) for _ in range(4)]
    reference = run(pre, tests)

    counts = weight_counts(model, nodes)
    total = sum(counts.values())
    budget = args.fp32_share * total
    candidates = rank_candidates([n for n in nodes if counts[n.name] <= budget], args.rank_nodes)
    single = {}
    for i, node in enumerate(candidates):
        single[node.name] = deviation(run_model(with_int8_weight(model, node), tests), reference)[1]
        if sys.stderr.isatty():
            print(f"\r{role}: measuring node {i + 1}/{len(candidates)}", end="", file=sys.stderr, flush=True)
    if sys.stderr.isatty():
        print(file=sys.stderr)
    keep, kept = [], 0
    for name in sorted(single, key=single.get, reverse=True):
        if kept + counts[name] <= budget:
            keep.append(name)
            kept += counts[name]
    out = dst_pkg / comp["file"]
    quantise(pre, out, calibration, [n.name for n in nodes if n.name not in keep])
    error = deviation(run(out, tests), reference)
    print(f"{role}: {len(nodes) - len(keep)} of {len(nodes)} nodes int8 ({len(keep)} float32, "
          f"{kept / total:.1%} of the weights; {len(candidates)} nodes ranked); deviation max "
          f"{error[0]:.3e} rms {error[1]:.3e}", file=sys.stderr)
    return {"nodes": len(nodes), "fp32": keep, "error": error}


def toml_str(s: str) -> str:
    out = s.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n").replace("\t", "\\t")
    return f'"{out}"'


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="example: python models/packages/quantize.py "
                                       "target/bench/mofusion-paper -o target/bench/mofusion-paper-int8")
    p.add_argument("src", type=Path, help="the float32 package directory")
    p.add_argument("-o", "--out", type=Path, required=True, help="the int8 package directory to write")
    p.add_argument("--fp32-share", type=float, default=0.05,
                   help="largest share of a component's weights kept in float32 (default 0.05)")
    p.add_argument("--rank-nodes", type=int, default=16, metavar="N",
                   help="nodes measured to choose the float32 ones, spread through the graph "
                        "(default 16; 0: none, all int8); each costs one run of the component")
    p.add_argument("--calibration", type=Path, help="an .npz of real inputs, one array per input name")
    p.add_argument("--seed", type=int, default=0, help="seed of the drawn calibration and test inputs")
    args = p.parse_args()
    # onnxruntime's quantiser logs advice at WARNING on every call (pre-processing is done here).
    logging.getLogger().setLevel(logging.ERROR)
    if not 0.0 <= args.fp32_share < 1.0:
        fail("--fp32-share must be in [0, 1)")
    if args.rank_nodes < 0:
        fail("--rank-nodes must be 0 or more")
    manifest = load_manifest(args.src)
    if "quantization" in manifest:
        fail(f"{args.src} is already quantised")
    if args.out.exists() and any(args.out.iterdir()):
        fail(f"{args.out} exists and is not empty")
    args.out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(args.seed)
    text = (args.src / "choreod-model.toml").read_text(encoding="utf-8")
    sources, fp32, worst = {}, {}, (0.0, 0.0)
    with tempfile.TemporaryDirectory() as tmp:
        for role, comp in manifest["components"].items():
            digest = hashlib.sha256((args.src / comp["file"]).read_bytes()).hexdigest()
            if digest != comp["sha256"]:
                fail(f"{args.src / comp['file']}: sha256 does not match the manifest")
            result = quantise_component(args.src, args.out, manifest, role, comp, args, rng, Path(tmp))
            new = hashlib.sha256((args.out / comp["file"]).read_bytes()).hexdigest()
            text = text.replace(f'sha256 = "{digest}"', f'sha256 = "{new}"')
            sources[role], fp32[role] = digest, result["fp32"]
            worst = (max(worst[0], result["error"][0]), max(worst[1], result["error"][1]))
    name = manifest["name"]
    text = re.sub(r'^name = .*$', f"name = {toml_str(name + '-int8')}", text, count=1, flags=re.M)
    section = ["", "[quantization]", f"scheme = {toml_str(SCHEME)}", f"source = {toml_str(name)}",
               f"max_relative_error = {worst[0]:.6e}", f"rms_relative_error = {worst[1]:.6e}"]
    section.append("[quantization.source_sha256]")
    section += [f"{role} = \"{digest}\"" for role, digest in sources.items()]
    section.append("[quantization.fp32_nodes]")
    section += [f"{role} = [{', '.join(toml_str(n) for n in nodes)}]" for role, nodes in fp32.items()]
    (args.out / "choreod-model.toml").write_text(text.rstrip("\n") + "\n" + "\n".join(section) + "\n",
                                                 encoding="utf-8")
    for extra in args.src.iterdir():
        if extra.suffix not in (".onnx",) and extra.name != "choreod-model.toml" and extra.is_file():
            shutil.copyfile(extra, args.out / extra.name)
    with open(args.out / "README.md", "a", encoding="utf-8") as readme:
        readme.write(f"\n## This copy is int8\n\nMade from `{name}` by `models/packages/quantize.py "
                     f"--fp32-share {args.fp32_share} --rank-nodes {args.rank_nodes} --seed {args.seed}`; the manifest's "
                     "`[quantization]` section records the scheme, the source's sha256s, the nodes "
                     "left float32 and the measured deviation. Check it against its source with "
                     f"`choreod models check THIS_DIR --against {name.split('/')[-1]}-DIR`.\n")
    print(f"wrote {args.out}: worst deviation on the test inputs max {worst[0]:.3e}, rms {worst[1]:.3e} "
          f"(relative; a random-weight package's deviation is a sanity bound only)")


if __name__ == "__main__":
    main()
