#!/usr/bin/env python3
"""A model package whose denoiser never finishes, for the tests of choreod's time limits on
ONNX Runtime runs (issue 20, item 9):

  hostile_onnx.py endless-loop PKG   PKG (a copy of models/packages/exemplar) gets a
                                     denoiser.onnx of the same interface (x_t, t, music, cond
                                     in; pred out) whose pred = x_t + 0 * (an ONNX Loop of
                                     2**62 iterations counting from sum(x_t)), and the
                                     manifest's sha256 of it. A valid model: onnx.checker
                                     accepts it and ONNX Runtime loads it in milliseconds; a
                                     run would take centuries. The loop starts from x_t, a
                                     step input, so it stays in the step graph.
"""
import hashlib
import os
import sys

import numpy as np
import onnx
from onnx import TensorProto as T
from onnx import helper, numpy_helper


def endless_loop(pkg):
    def io(name, dtype, shape):
        return helper.make_tensor_value_info(name, dtype, shape)

    body = helper.make_graph(
        [
            helper.make_node("Identity", ["keep_in"], ["keep_out"]),
            helper.make_node("Add", ["count_in", "one"], ["count_out"]),
        ],
        "count",
        [io("i", T.INT64, []), io("keep_in", T.BOOL, []), io("count_in", T.FLOAT, [])],
        [io("keep_out", T.BOOL, []), io("count_out", T.FLOAT, [])],
        [numpy_helper.from_array(np.array(1.0, np.float32), "one")],
    )
    graph = helper.make_graph(
        [
            helper.make_node("ReduceSum", ["x_t"], ["start"], keepdims=0),
            helper.make_node("Loop", ["trips", "keep", "start"], ["count"], body=body),
            helper.make_node("Mul", ["count", "zero"], ["nothing"]),
            helper.make_node("Add", ["x_t", "nothing"], ["pred"]),
        ],
        "endless",
        [
            io("x_t", T.FLOAT, ["N", 150, 72]),
            io("t", T.INT64, ["N"]),
            io("music", T.FLOAT, ["N", 157, 80]),
            io("cond", T.FLOAT, ["N"]),
        ],
        [io("pred", T.FLOAT, ["N", 150, 72])],
        [
            numpy_helper.from_array(np.array(2**62, np.int64), "trips"),
            numpy_helper.from_array(np.array(True), "keep"),
            numpy_helper.from_array(np.array(0.0, np.float32), "zero"),
        ],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    model.ir_version = 10
    onnx.checker.check_model(model)
    onnx_path = os.path.join(pkg, "denoiser.onnx")
    onnx.save(model, onnx_path)
    manifest = os.path.join(pkg, "choreod-model.toml")
    text = open(manifest).read()
    old = text.split('sha256 = "')[1].split('"')[0]
    new = hashlib.sha256(open(onnx_path, "rb").read()).hexdigest()
    open(manifest, "w").write(text.replace(old, new))


if __name__ == "__main__":
    if sys.argv[1:2] == ["endless-loop"] and len(sys.argv) == 3:
        endless_loop(sys.argv[2])
    else:
        sys.exit(__doc__)
