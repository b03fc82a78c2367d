"""`dadiff-run --demo`: track one generated night sequence and write an annotated video.

Needs no data: the sequence comes from the night-scene generator (test photos), so the demo also shows
how well the model does (success and precision against the exact ground truth).
"""

from __future__ import annotations

import time
from pathlib import Path

import cv2
import numpy as np

from ..datamaking.scenes import make_sequence
from ..evaluation.evaluate import protocol_box
from ..evaluation.metrics import SequenceCurves, summarise
from ..outputs import Record, draw_overlay, open_mp4
from ..tracker import Tracker

_GT_COLOUR = (255, 255, 255)


def _draw_truth(image: np.ndarray, box: np.ndarray) -> None:
    if np.all(np.isfinite(box)):
        x, y, w, h = box
        cv2.rectangle(image, (round(x), round(y)), (round(x + w), round(y + h)), _GT_COLOUR, 1, cv2.LINE_AA)


def _caption(image: np.ndarray, text: str) -> None:
    """White text on a black band at the bottom (an outline drawn with a thicker stroke shifts in OpenCV 5)."""
    h = image.shape[0]
    image[h - 24 :] //= 3
    cv2.putText(image, text, (8, h - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)


def run_demo(model: str | None, out_dir: Path, seed: int = 0, *, frames: int = 120) -> dict:
    """Generate night sequence `seed`, track it with `model` (None: the shipped default), write
    `<out_dir>/demo-night-<seed>.mp4`, print one summary line and return the numbers.

    Raises ModelError when the model cannot be loaded (also when no default model ships yet).
    Returns {"video", "sequence", "attributes", "frames", "fps", "success", "precision", "norm_precision"}.
    """
    tracker = Tracker.load(model)
    sequence = make_sequence(seed, split="test", frames=frames)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    video = out_dir / f"demo-night-{seed}.mp4"
    height, width = sequence.night[0].shape[:2]
    writer = open_mp4(video, (width, height))
    first = protocol_box(sequence.boxes[0])
    boxes = [first]
    seconds, fps = 0.0, None
    try:
        tracker.init(sequence.night[0], first)
        for i, frame in enumerate(sequence.night):
            if i == 0:
                record = Record(first, 1.0, "init")
            else:
                start = time.perf_counter()
                result = tracker.update(frame)
                took = time.perf_counter() - start
                seconds += took
                fps = 1 / took if fps is None else 0.9 * fps + 0.1 / max(took, 1e-9)
                boxes.append(result.box)
                record = Record(result.box, result.score, result.state, fps)
            image = frame.copy()
            _draw_truth(image, sequence.boxes[i])
            draw_overlay(image, record)
            _caption(image, f"{sequence.name} night  frame {i + 1}/{len(sequence.night)}  white: ground truth")
            writer.write(image)
    finally:
        writer.close()
    scores = summarise([SequenceCurves.from_boxes(sequence.boxes, boxes)])
    mean_fps = (len(boxes) - 1) / seconds if seconds > 0 else float("nan")
    print(
        f"demo: {sequence.name} at night ({', '.join(sequence.night_attributes)}), {len(boxes)} frames, "
        f"tracker {mean_fps:.1f} FPS, success {scores.success:.3f}, precision {scores.precision:.3f} -> {video}"
    )
    return {
        "video": video,
        "sequence": sequence.name,
        "attributes": list(sequence.night_attributes),
        "frames": len(boxes),
        "fps": mean_fps,
        "success": scores.success,
        "precision": scores.precision,
        "norm_precision": scores.norm_precision,
    }
