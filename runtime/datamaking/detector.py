"""A video's per-frame detections from an object detector exported to ONNX, written as a MOTChallenge det.txt.

The detector is any model with the TensorFlow Object Detection API's interface (what `tf2onnx` makes of its
frozen graphs, SSD-MobileNet and the like): a uint8 batch of RGB images in, `num_detections`,
`detection_scores`, `detection_boxes` (y0, x0, y1, x1, relative to the image) and `detection_classes` (COCO
ids: 1 is a person) out. Small people are lost when a wide frame is squeezed into the detector's 300 x 300
input, so besides the whole frame it also looks at overlapping tiles across the frame's long side; the linker
(`detection_tracks`) merges the duplicates.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import onnxruntime as ort

from ..onnx_backend import thread_count
from .scene_error import SceneError

OUTPUTS = ("num_detections", "detection_scores", "detection_boxes", "detection_classes")


class Detector:
    """One ONNX detector session; `detect(image)` gives (x, y, w, h, score, class) rows in image pixels."""

    def __init__(self, path: str | Path, input_size: int = 300, threads: int = 1) -> None:
        path = Path(path).expanduser()
        if not path.is_file():
            raise SceneError(f"{path}: no such detector file")
        options = ort.SessionOptions()
        options.intra_op_num_threads = thread_count(threads)  # bounded as the tracker's (thread_count)
        try:
            self.session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own types for unreadable or invalid models
            raise SceneError(f"{path}: not a readable ONNX model ({_first_line(exc)})") from None
        inputs = self.session.get_inputs()
        if len(inputs) != 1 or inputs[0].type != "tensor(uint8)" or len(inputs[0].shape) != 4:
            raise SceneError(f"{path}: expected one uint8 image input of rank 4 (TF Object Detection API), got "
                             + ", ".join(f"{i.name} {i.type} rank {len(i.shape)}" for i in inputs))
        self.input = inputs[0].name
        names = {o.name.split(":")[0]: o.name for o in self.session.get_outputs()}
        missing = [n for n in OUTPUTS if n not in names]
        if missing:
            raise SceneError(f"{path}: no output named {missing[0]} (expected {', '.join(OUTPUTS)})")
        self.outputs = [names[n] for n in OUTPUTS]
        self.input_size = input_size

    def detect(self, image: np.ndarray) -> np.ndarray:
        """Rows (x, y, w, h, score, class) for a BGR image, in its pixels."""
        height, width = image.shape[:2]
        rgb = cv2.resize(image, (self.input_size, self.input_size))[:, :, ::-1]
        try:
            count, scores, boxes, classes = self.session.run(self.outputs, {self.input: rgb[None].copy()})
            n = int(count[0])
            y0, x0, y1, x1 = (boxes[0, :n, i] for i in range(4))
            scores, classes = scores[0, :n], classes[0, :n]
        except Exception as exc:  # onnxruntime's own errors, or outputs of other shapes than the interface's
            raise SceneError(f"the detector failed on a {width} x {height} image: {_first_line(exc)}") from None
        return np.stack([x0 * width, y0 * height, (x1 - x0) * width, (y1 - y0) * height, scores, classes],
                        axis=1).astype(np.float64).reshape(-1, 6)


def _first_line(exc: Exception) -> str:
    """An exception's first line, short enough for a one-line error."""
    text = str(exc).strip()
    return text.splitlines()[0][:100] if text else type(exc).__name__


def tiles(width: int, height: int, count: int) -> list[tuple[int, int, int, int]]:
    """The whole frame, then `count` tiles (x, y, w, h) along its long side, each 2 / (count + 1) of that side
    long, so that neighbours overlap by half."""
    if count == 0:
        return [(0, 0, width, height)]
    long_side = max(width, height)
    length = round(2 * long_side / (count + 1))
    starts = [round(i * long_side / (count + 1)) for i in range(count)]
    if width >= height:
        parts = [(x, 0, length, height) for x in starts]
    else:
        parts = [(0, y, width, length) for y in starts]
    return [(0, 0, width, height), *parts]


def detect_video(frames: list[np.ndarray], detector: Detector, classes: set[int], min_score: float,
                 tile_count: int) -> list[np.ndarray]:
    """Per frame, the (x, y, w, h, score) rows of the wanted classes from the whole frame and its tiles (the
    frames share one size, as `read_video` guarantees, so the tiles are laid out once)."""
    layout = tiles(frames[0].shape[1], frames[0].shape[0], tile_count)
    wanted = sorted(classes)
    out = []
    for frame in frames:
        rows = []
        for x, y, w, h in layout:
            found = detector.detect(frame[y:y + h, x:x + w])
            found = found[(found[:, 4] >= min_score) & np.isin(found[:, 5].round(), wanted)]
            rows.append(found[:, :5] + [x, y, 0, 0, 0])
        out.append(np.concatenate(rows))
    return out


def write_det_txt(path: str | Path, detections: list[np.ndarray]) -> int:
    """The rows as a MOTChallenge det.txt (frames from 1, id -1); returns how many were written."""
    lines = [f"{t + 1},-1,{x:.2f},{y:.2f},{w:.2f},{h:.2f},{score:.4f},-1,-1,-1"
             for t, rows in enumerate(detections) for x, y, w, h, score in rows]
    Path(path).expanduser().write_text("".join(line + "\n" for line in lines))
    return len(lines)
