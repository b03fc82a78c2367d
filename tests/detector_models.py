"""A stand-in object detector with the TensorFlow Object Detection API's interface (test helper).

Whatever the image, it reports fixed relative boxes (y0, x0, y1, x1), scores and classes; the image still
flows into the graph (its mean, times zero, is added to the scores) so that the input is used. Written with
onnx.helper; never imported by dadiff.runtime.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper


def write_fake_detector(path: Path, boxes: list[list[float]], scores: list[float], classes: list[float],
                        input_type: int = TensorProto.UINT8, box_shape: list[int] | None = None) -> Path:
    """Write the stand-in detector to `path` (`box_shape` other than (1, n, 4) breaks the interface)."""
    n = len(boxes)
    consts = [
        helper.make_tensor("boxes", TensorProto.FLOAT, box_shape or [1, n, 4], np.array(boxes, np.float32).ravel()),
        helper.make_tensor("scores", TensorProto.FLOAT, [1, n], scores),
        helper.make_tensor("classes", TensorProto.FLOAT, [1, n], classes),
        helper.make_tensor("count", TensorProto.FLOAT, [1], [float(n)]),
        helper.make_tensor("zero", TensorProto.FLOAT, [1], [0.0]),
    ]
    nodes = [
        helper.make_node("Cast", ["image_tensor:0"], ["image_f"], to=TensorProto.FLOAT),
        helper.make_node("ReduceMean", ["image_f"], ["mean"], keepdims=0),
        helper.make_node("Mul", ["mean", "zero"], ["nothing"]),
        helper.make_node("Add", ["scores", "nothing"], ["detection_scores:0"]),
        helper.make_node("Identity", ["boxes"], ["detection_boxes:0"]),
        helper.make_node("Identity", ["classes"], ["detection_classes:0"]),
        helper.make_node("Identity", ["count"], ["num_detections:0"]),
    ]
    graph = helper.make_graph(
        nodes, "fake_ssd",
        [helper.make_tensor_value_info("image_tensor:0", input_type, [1, None, None, 3])],
        [helper.make_tensor_value_info(name, TensorProto.FLOAT, None)
         for name in ("num_detections:0", "detection_scores:0", "detection_boxes:0", "detection_classes:0")],
        initializer=consts)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    onnx.save(model, str(path))
    return path
