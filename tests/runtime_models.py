"""A tiny, genuine correlation tracker written as a dadiff-format model folder (test helper).

Template graph: the 127 crop is pooled, at several scales s, into 7×7 cells of 8 pixels of colour around
the centre (as the target would look s times larger in the search crop); each kernel is made zero-mean
and unit-norm (kcls0). kloc0 holds, per scale, the (l, t, r, b) half sizes of the target scaled by s.
Search graph: the 255 crop is pooled into 31×31 cells; normalised cross-correlation with every kernel
gives 16×25×25 maps; cls is a logistic of the best correlation over scales, and loc the half sizes of the
best scale. So it finds the target, estimates its scale, and its score drops when the target is gone.
Written with onnx.helper (IR 10, opset 17); never imported by dadiff.runtime.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

EXEMPLAR, INSTANCE, STRIDE, SCORE, CELLS = 127, 255, 8, 25, 7
SCALES = tuple(1.1**k for k in range(-10, 6))
# Search window for point j covers crop pixels [8j, 8j + 56): centre 8j + 28 − 127.5 from the crop centre.
POINT_ORIGIN = CELLS * STRIDE / 2 - INSTANCE / 2
PRESETS = {
    "UAVDark70": {"lr": 0.473, "penalty_k": 0.088, "window_influence": 0.401},
    "NUT_L": {"lr": 0.473, "penalty_k": 0.088, "window_influence": 0.403},
    "NAT": {"lr": 0.45, "penalty_k": 0.14, "window_influence": 0.30},
    "NAT_L": {"lr": 0.466, "penalty_k": 0.083, "window_influence": 0.404},
}


def _cell_weights(scale: float) -> np.ndarray:
    """(7, 127): average of template pixels under each cell of the 56-pixel search window at `scale`."""
    centre = EXEMPLAR / 2
    weights = np.zeros((CELLS, EXEMPLAR), np.float64)
    edges = np.arange(EXEMPLAR + 1, dtype=np.float64)
    for u in range(CELLS):
        a = centre + (STRIDE * u - CELLS * STRIDE / 2) / scale
        b = a + STRIDE / scale
        overlap = np.clip(np.minimum(edges[1:], b) - np.maximum(edges[:-1], a), 0.0, None)
        weights[u] = overlap / overlap.sum()
    return weights


def target_half_size(aspect: float, context: float = 0.5) -> tuple[float, float]:
    """Half width and height, in crop pixels, of a target of this w/h aspect (released context crop)."""
    w, h = aspect, 1.0
    pad = context * (w + h)
    scale = EXEMPLAR / math.sqrt((w + pad) * (h + pad))
    return w * scale / 2, h * scale / 2


def _const(name: str, array: np.ndarray) -> onnx.NodeProto:
    return helper.make_node("Constant", [], [name], value=numpy_helper.from_array(array, name))


def _f32(values: Iterable[float] | float) -> np.ndarray:
    return np.asarray(values, dtype=np.float32)


def _template_graph(aspect: float) -> onnx.GraphProto:
    rows = np.stack([_cell_weights(s) for s in SCALES])[:, None].astype(np.float32)  # (NS, 1, 7, 127)
    hw, hh = target_half_size(aspect)
    table = np.array([[hw * s, hh * s, hw * s, hh * s] for s in SCALES], np.float32)
    nodes = [
        _const("inv255", _f32(1 / 255)),
        _const("rows", rows),
        _const("cols", np.ascontiguousarray(rows.transpose(0, 1, 3, 2))),
        _const("eps", _f32(1e-6)),
        _const("sum_axes", np.array([1, 2, 3], np.int64)),
        _const("kloc0", table),
        helper.make_node("Mul", ["z", "inv255"], ["zn"]),
        helper.make_node(
            "AveragePool", ["zn"], ["zf0"], kernel_shape=[STRIDE, STRIDE], strides=[STRIDE, STRIDE]
        ),
        helper.make_node("MatMul", ["rows", "zn"], ["k_rows"]),
        helper.make_node("MatMul", ["k_rows", "cols"], ["k_raw"]),
        helper.make_node("ReduceMean", ["k_raw"], ["k_mean"], axes=[2, 3], keepdims=1),
        helper.make_node("Sub", ["k_raw", "k_mean"], ["k_zero"]),
        helper.make_node("Mul", ["k_zero", "k_zero"], ["k_sq"]),
        helper.make_node("ReduceSum", ["k_sq", "sum_axes"], ["k_energy"], keepdims=1),
        helper.make_node("Add", ["k_energy", "eps"], ["k_energy_eps"]),
        helper.make_node("Sqrt", ["k_energy_eps"], ["k_norm"]),
        helper.make_node("Div", ["k_zero", "k_norm"], ["kcls0"]),
    ]
    ns = len(SCALES)
    return helper.make_graph(
        nodes,
        "template",
        [helper.make_tensor_value_info("z", TensorProto.FLOAT, [1, 3, EXEMPLAR, EXEMPLAR])],
        [
            helper.make_tensor_value_info("zf0", TensorProto.FLOAT, [1, 3, 15, 15]),
            helper.make_tensor_value_info("kcls0", TensorProto.FLOAT, [ns, 3, CELLS, CELLS]),
            helper.make_tensor_value_info("kloc0", TensorProto.FLOAT, [ns, 4]),
        ],
    )


def _search_graph(gain: float, bias: float) -> onnx.GraphProto:
    n = float(CELLS * CELLS)
    nodes = [
        _const("inv255", _f32(1 / 255)),
        _const("ones", np.ones((3, 1, CELLS, CELLS), np.float32)),
        _const("inv_n", _f32(1 / n)),
        _const("eps", _f32(1e-4)),
        _const("chan_axis", np.array([1], np.int64)),
        _const("bias", _f32(bias)),
        _const("half_gain", _f32(gain / 2)),
        _const("neg_half_gain", _f32(-gain / 2)),
        helper.make_node("Mul", ["x", "inv255"], ["xn"]),
        helper.make_node(
            "AveragePool", ["xn"], ["xf"], kernel_shape=[STRIDE, STRIDE], strides=[STRIDE, STRIDE]
        ),
        helper.make_node("Conv", ["xf", "kcls0"], ["corr"]),
        helper.make_node("Conv", ["xf", "ones"], ["s1"], group=3),
        helper.make_node("Mul", ["xf", "xf"], ["xf_sq"]),
        helper.make_node("Conv", ["xf_sq", "ones"], ["s2"], group=3),
        helper.make_node("Mul", ["s1", "s1"], ["s1_sq"]),
        helper.make_node("Mul", ["s1_sq", "inv_n"], ["s1_sq_n"]),
        helper.make_node("Sub", ["s2", "s1_sq_n"], ["var_c"]),
        helper.make_node("ReduceSum", ["var_c", "chan_axis"], ["var"], keepdims=1),
        helper.make_node("Max", ["var", "eps"], ["var_eps"]),
        helper.make_node("Sqrt", ["var_eps"], ["std"]),
        helper.make_node("Div", ["corr", "std"], ["ncc"]),
        helper.make_node("ReduceMax", ["ncc"], ["best"], axes=[1], keepdims=1),
        helper.make_node("Sub", ["best", "bias"], ["margin"]),
        helper.make_node("Mul", ["margin", "neg_half_gain"], ["bg"]),
        helper.make_node("Mul", ["margin", "half_gain"], ["fg"]),
        helper.make_node("Concat", ["bg", "fg"], ["cls"], axis=1),
        helper.make_node("ArgMax", ["ncc"], ["which"], axis=1, keepdims=0),
        helper.make_node("Gather", ["kloc0", "which"], ["loc_nhwc"], axis=0),
        helper.make_node("Transpose", ["loc_nhwc"], ["loc"], perm=[0, 3, 1, 2]),
    ]
    ns = len(SCALES)
    return helper.make_graph(
        nodes,
        "search",
        [
            helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 3, INSTANCE, INSTANCE]),
            helper.make_tensor_value_info("kcls0", TensorProto.FLOAT, [ns, 3, CELLS, CELLS]),
            helper.make_tensor_value_info("kloc0", TensorProto.FLOAT, [ns, 4]),
        ],
        [
            helper.make_tensor_value_info("cls", TensorProto.FLOAT, [1, 2, SCORE, SCORE]),
            helper.make_tensor_value_info("loc", TensorProto.FLOAT, [1, 4, SCORE, SCORE]),
        ],
    )


def metadata(graph: str) -> dict[str, str]:
    """Full dadiff-format metadata for one of the two graphs."""
    hp = PRESETS["UAVDark70"]
    return {
        "dadiff_format": "1",
        "graph": graph,
        "name": "corr-test",
        "family": "test-correlation",
        "dadiff_version": "0.1.0",
        "source_sha256": "0" * 64,
        "opset": "17",
        "levels": "1",
        "exemplar_size": str(EXEMPLAR),
        "instance_size": str(INSTANCE),
        "stride": str(STRIDE),
        "score_size": str(SCORE),
        "point_origin": str(POINT_ORIGIN),
        "context_amount": "0.5",
        "min_size": "10",
        "penalty_k": str(hp["penalty_k"]),
        "window_influence": str(hp["window_influence"]),
        "lr": str(hp["lr"]),
        "hp_presets": json.dumps(PRESETS),
        "default_preset": "UAVDark70",
        "channel_order": "BGR",
        "pixel_range": "0-255",
        "pixel_mean": "[0, 0, 0]",
        "pixel_std": "[1, 1, 1]",
        "ddim_steps": "0",
        "ddim_timesteps": "[]",
        "ddim_start_t": "0",
        "template_outputs": json.dumps(["zf0", "kcls0", "kloc0"]),
        "search_inputs": json.dumps(["x", "kcls0", "kloc0"]),
    }


def _model(graph: onnx.GraphProto, meta: Mapping[str, str]) -> onnx.ModelProto:
    model = helper.make_model(
        graph, opset_imports=[helper.make_opsetid("", 17)], producer_name="dadiff-tests"
    )
    model.ir_version = 10
    helper.set_model_props(model, dict(meta))
    onnx.checker.check_model(model)
    return model


def write_corr_model(
    folder: Path,
    *,
    aspect: float = 1.0,
    gain: float = 12.0,
    bias: float = 0.6,
    meta: Mapping[str, str | None] | None = None,
) -> Path:
    """Write template.onnx and search.onnx into `folder`; `meta` adds keys (value None removes one)."""
    folder.mkdir(parents=True, exist_ok=True)
    for name, graph in (("template", _template_graph(aspect)), ("search", _search_graph(gain, bias))):
        props = metadata(name)
        for key, value in (meta or {}).items():
            if value is None:
                props.pop(key, None)
            else:
                props[key] = value
        onnx.save(_model(graph, props), str(folder / f"{name}.onnx"))
    return folder


# The geometry and released hyper-parameters of a stride-8 model, as metadata strings (fake backends).
STRIDE8_META = {
    "dadiff_format": "1",
    "exemplar_size": "127",
    "instance_size": "255",
    "stride": "8",
    "score_size": "25",
    "point_origin": "-96",
    "context_amount": "0.5",
    "min_size": "10",
    "penalty_k": "0.088",
    "window_influence": "0.401",
    "lr": "0.473",
}
