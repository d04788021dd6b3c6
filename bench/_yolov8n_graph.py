"""A YOLOv8n-architecture ONNX graph with random weights, for timing inference.

No trained weights can be downloaded here, but inference time depends only on the graph, so
this builds the exact YOLOv8n topology (width 0.25, depth 0.33) as the Ultralytics exporter
writes it: Conv layers with batch norm folded into their bias and SiLU as ``x * sigmoid(x)``,
C2f blocks, SPPF, the PAN neck, the decoupled detection head, DFL and the box decoding, giving
``[1, 4 + nc, N]``. At 640x640 with 80 classes it has ~3.2 M parameters and ~8.7 GFLOPs, as
the published model; at 320x320, a quarter of the FLOPs.

Benchmark-only: product code never ships random weights.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

REG_MAX = 16


class _GraphBuilder:
    def __init__(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)
        self.nodes: list[onnx.NodeProto] = []
        self.inits: list[onnx.TensorProto] = []
        self.n = 0
        self.params = 0
        self.flops = 0.0
        self.hw: dict[str, tuple[int, int]] = {}

    def _name(self, prefix: str) -> str:
        self.n += 1
        return f"{prefix}_{self.n}"

    def const(self, arr: np.ndarray, prefix: str = "c") -> str:
        name = self._name(prefix)
        self.inits.append(numpy_helper.from_array(arr, name))
        return name

    def conv(self, x: str, c1: int, c2: int, k: int = 1, s: int = 1, act: bool = True) -> str:
        """Conv2d (+ folded BN bias) (+ SiLU); tracks spatial size, parameters and FLOPs."""
        w = (self.rng.standard_normal((c2, c1, k, k)) * np.sqrt(1.0 / (c1 * k * k))).astype(np.float32)
        b = (self.rng.standard_normal(c2) * 0.01).astype(np.float32)
        wn, bn = self.const(w, "w"), self.const(b, "b")
        y = self._name("conv")
        self.nodes.append(helper.make_node("Conv", [x, wn, bn], [y], kernel_shape=[k, k],
                                           strides=[s, s], pads=[k // 2] * 4))
        h, wd = self.hw[x]
        ho, wo = (h + 2 * (k // 2) - k) // s + 1, (wd + 2 * (k // 2) - k) // s + 1
        self.hw[y] = (ho, wo)
        self.params += w.size + b.size
        self.flops += 2.0 * c1 * c2 * k * k * ho * wo
        if not act:
            return y
        sig, out = self._name("sig"), self._name("silu")
        self.nodes.append(helper.make_node("Sigmoid", [y], [sig]))
        self.nodes.append(helper.make_node("Mul", [y, sig], [out]))
        self.hw[out] = self.hw[y]
        return out

    def op(self, op_type: str, inputs: list[str], hw: tuple[int, int] | None = None, n_out: int = 1,
           **attrs: object) -> list[str]:
        outs = [self._name(op_type.lower()) for _ in range(n_out)]
        self.nodes.append(helper.make_node(op_type, inputs, outs, **attrs))
        for o in outs:
            self.hw[o] = hw if hw is not None else self.hw.get(inputs[0], (0, 0))
        return outs

    def c2f(self, x: str, c1: int, c2: int, n: int, shortcut: bool) -> str:
        c = c2 // 2
        y = self.conv(x, c1, 2 * c, 1)
        split = self.const(np.array([c, c], np.int64), "split")
        a, b = self.op("Split", [y, split], n_out=2, axis=1)
        parts = [a, b]
        cur = b
        for _ in range(n):
            t = self.conv(self.conv(cur, c, c, 3), c, c, 3)
            cur = self.op("Add", [cur, t])[0] if shortcut else t
            parts.append(cur)
        cat = self.op("Concat", parts, axis=1)[0]
        return self.conv(cat, (2 + n) * c, c2, 1)

    def sppf(self, x: str, c1: int, c2: int) -> str:
        c = c1 // 2
        y = self.conv(x, c1, c, 1)
        p1 = self.op("MaxPool", [y], kernel_shape=[5, 5], strides=[1, 1], pads=[2, 2, 2, 2])[0]
        p2 = self.op("MaxPool", [p1], kernel_shape=[5, 5], strides=[1, 1], pads=[2, 2, 2, 2])[0]
        p3 = self.op("MaxPool", [p2], kernel_shape=[5, 5], strides=[1, 1], pads=[2, 2, 2, 2])[0]
        return self.conv(self.op("Concat", [y, p1, p2, p3], axis=1)[0], 4 * c, c2, 1)

    def upsample(self, x: str) -> str:
        h, w = self.hw[x]
        scales = self.const(np.array([1.0, 1.0, 2.0, 2.0], np.float32), "scales")
        return self.op("Resize", [x, "", scales], hw=(2 * h, 2 * w), mode="nearest")[0]


def build_yolov8n(path: str | Path, input_size_px: int = 320, num_classes: int = 6, seed: int = 0) -> dict[str, float]:
    """Write a YOLOv8n-architecture model to ``path``; returns its parameter count and GFLOPs."""
    g = _GraphBuilder(seed)
    s = input_size_px
    g.hw["images"] = (s, s)
    # Backbone.
    x = g.conv("images", 3, 16, 3, 2)
    x = g.conv(x, 16, 32, 3, 2)
    x = g.c2f(x, 32, 32, 1, True)
    x = g.conv(x, 32, 64, 3, 2)
    p3 = g.c2f(x, 64, 64, 2, True)
    x = g.conv(p3, 64, 128, 3, 2)
    p4 = g.c2f(x, 128, 128, 2, True)
    x = g.conv(p4, 128, 256, 3, 2)
    x = g.c2f(x, 256, 256, 1, True)
    p5 = g.sppf(x, 256, 256)
    # PAN neck.
    x = g.op("Concat", [g.upsample(p5), p4], axis=1)[0]
    n4 = g.c2f(x, 384, 128, 1, False)
    x = g.op("Concat", [g.upsample(n4), p3], axis=1)[0]
    o3 = g.c2f(x, 192, 64, 1, False)
    x = g.op("Concat", [g.conv(o3, 64, 64, 3, 2), n4], axis=1)[0]
    o4 = g.c2f(x, 192, 128, 1, False)
    x = g.op("Concat", [g.conv(o4, 128, 128, 3, 2), p5], axis=1)[0]
    o5 = g.c2f(x, 384, 256, 1, False)
    # Decoupled head.
    c2, c3 = max(16, 64 // 4, REG_MAX * 4), max(64, min(num_classes, 100))
    levels = []
    anchors, strides = [], []
    for feat, ch, stride in ((o3, 64, 8), (o4, 128, 16), (o5, 256, 32)):
        box = g.conv(g.conv(g.conv(feat, ch, c2, 3), c2, c2, 3), c2, 4 * REG_MAX, 1, act=False)
        cls = g.conv(g.conv(g.conv(feat, ch, c3, 3), c3, c3, 3), c3, num_classes, 1, act=False)
        cat = g.op("Concat", [box, cls], axis=1)[0]
        shape = g.const(np.array([1, 4 * REG_MAX + num_classes, -1], np.int64), "shape")
        levels.append(g.op("Reshape", [cat, shape])[0])
        h, w = g.hw[feat]
        yv, xv = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
        anchors.append(np.stack([xv.ravel(), yv.ravel()]))
        strides.append(np.full(h * w, stride))
    n = sum(a.shape[1] for a in anchors)
    allp = g.op("Concat", levels, axis=2, hw=(1, n))[0]
    split = g.const(np.array([4 * REG_MAX, num_classes], np.int64), "split")
    box, cls = g.op("Split", [allp, split], n_out=2, axis=1)
    # DFL: softmax over 16 bins per side, expectation by a fixed 1x1 conv.
    box = g.op("Reshape", [box, g.const(np.array([1, 4, REG_MAX, n], np.int64), "shape")])[0]
    box = g.op("Transpose", [box], perm=[0, 2, 1, 3])[0]
    box = g.op("Softmax", [box], axis=1)[0]
    dfl_w = g.const(np.arange(REG_MAX, dtype=np.float32).reshape(1, REG_MAX, 1, 1), "dfl")
    dist = g.op("Conv", [box, dfl_w])[0]
    dist = g.op("Reshape", [dist, g.const(np.array([1, 4, n], np.int64), "shape")])[0]
    lt, rb = g.op("Split", [dist, g.const(np.array([2, 2], np.int64), "split")], n_out=2, axis=1)
    anc = g.const(np.concatenate(anchors, axis=1)[None].astype(np.float32), "anchors")
    x1y1 = g.op("Sub", [anc, lt])[0]
    x2y2 = g.op("Add", [anc, rb])[0]
    cxy = g.op("Mul", [g.op("Add", [x1y1, x2y2])[0], g.const(np.array(0.5, np.float32))])[0]
    wh = g.op("Sub", [x2y2, x1y1])[0]
    dbox = g.op("Concat", [cxy, wh], axis=1)[0]
    stride_t = g.const(np.concatenate(strides)[None, None].astype(np.float32), "strides")
    dbox = g.op("Mul", [dbox, stride_t])[0]
    out = g.op("Sigmoid", [cls])[0]
    g.nodes.append(helper.make_node("Concat", [dbox, out], ["output0"], axis=1))

    inp = helper.make_tensor_value_info("images", TensorProto.FLOAT, [1, 3, s, s])
    outp = helper.make_tensor_value_info("output0", TensorProto.FLOAT, [1, 4 + num_classes, n])
    graph = helper.make_graph(g.nodes, "yolov8n_random", [inp], [outp], g.inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    names = ["chair", "coffee_table", "conference_table", "sofa", "whiteboard", "desk"]
    helper.set_model_props(model, {"names": str(dict(enumerate((names + [f"c{i}" for i in range(num_classes)])[:num_classes])))})
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return {"params": float(g.params), "gflops": g.flops / 1e9, "anchors": float(n)}
