"""Tiny denoiser graphs for the package error tests (run by models/tests/packages.rs).

usage: make_graphs.py OUT_DIR
Writes good.onnx (pred = 0.5 * x_t, the contract's interface with T=8, D=72, F=6, 80 mels),
renamed.onnx (input `xt` instead of `x_t`), nan.onnx (pred = x_t * NaN), fixed_batch.onnx
(batch axis fixed to 1), future_opset.onnx (opset 99) and corrupt.onnx (not protobuf).
"""
import sys
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper


def graph(name, x_name="x_t", factor=0.5, batch="N", opset=18, check=True):
    f32, i64 = TensorProto.FLOAT, TensorProto.INT64
    inputs = [
        helper.make_tensor_value_info(x_name, f32, [batch, 8, 72]),
        helper.make_tensor_value_info("t", i64, [batch]),
        helper.make_tensor_value_info("music", f32, [batch, 6, 80]),
        helper.make_tensor_value_info("cond", f32, [batch]),
    ]
    out = helper.make_tensor_value_info("pred", f32, [batch, 8, 72])
    k = helper.make_tensor("k", f32, [], [factor])
    node = helper.make_node("Mul", [x_name, "k"], ["pred"])
    g = helper.make_graph([node], name, inputs, [out], initializer=[k])
    m = helper.make_model(g, opset_imports=[helper.make_opsetid("", opset)], producer_name="choreod-tests")
    m.ir_version = 9
    if check:
        onnx.checker.check_model(m)
    return m.SerializeToString(deterministic=True)


def main():
    out = Path(sys.argv[1])
    out.mkdir(parents=True, exist_ok=True)
    (out / "good.onnx").write_bytes(graph("good"))
    (out / "renamed.onnx").write_bytes(graph("renamed", x_name="xt"))
    (out / "nan.onnx").write_bytes(graph("nan", factor=float("nan")))
    (out / "fixed_batch.onnx").write_bytes(graph("fixed", batch=1))
    # An opset from the future: ONNX Runtime 1.31 must refuse it at load.
    (out / "future_opset.onnx").write_bytes(graph("future", opset=99, check=False))
    (out / "corrupt.onnx").write_bytes(b"\x08\x07this is not an ONNX protobuf" * 8)


if __name__ == "__main__":
    main()
