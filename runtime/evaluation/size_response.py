"""How far the network's box follows the size it is given: `dadiff-eval box-read --sizes`.

Each frame's search crop is cut around the true centre as if the tracker held the true box scaled by a
factor f, and the box is read once (`Tracker.look`). A network that reads the target repeats the true size
whatever f is (slope 0); one that leans on the crop's scale repeats the size it was given (slope 1). The
tracker blends each read into the size it holds, so it settles where the read equals what it holds: the
resting size, found between the factors read (with a read of log(box / true) = a + b log f it is
exp(a / (1 - b)) times the truth). A slope near 1 makes a small error at f = 1 a large one at rest, reached
over tens of frames: the slow size drift that tracking shows and one read at the true size hides.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..datamaking.datasets import Dataset
from ..tracker import Tracker
from .box_read import frames_after_first, frames_with_targets, in_frame
from .evaluate import EvalError


@dataclass(frozen=True)
class SizeResponse:
    """Median log(w / true w) and log(h / true h) per factor, the fitted slope of each against log f, and
    the resting size (read = held) as a ratio to the truth: inf where every read is larger than the size
    given (the box grows past the largest factor), 0 where every read is smaller."""

    sizes: tuple[float, ...]
    width: tuple[float, ...]
    height: tuple[float, ...]
    slope: tuple[float, float]
    rest: tuple[float, float]
    frames: int


def scaled_box(box: Sequence[float], factor: float) -> tuple[float, float, float, float]:
    """The box scaled about its centre, in the tracker's convention (centre x + (w - 1) / 2)."""
    x, y, w, h = (float(v) for v in box)
    cx, cy = x + (w - 1) / 2, y + (h - 1) / 2
    sw, sh = w * factor, h * factor
    return cx - (sw - 1) / 2, cy - (sh - 1) / 2, sw, sh


def read_sizes(tracker: Tracker, dataset: Dataset, sizes: Sequence[float]) -> np.ndarray:
    """(frames, sizes, 2): log(w / true w), log(h / true h) of each frame's read at each factor. A frame is
    kept only where every scaled box names a target in it, so each factor reads the same frames."""
    rows = []
    for frame, box in frames_with_targets(tracker, dataset):
        boxes = [scaled_box(box, f) for f in sizes]
        if all(in_frame(np.asarray(b), frame.shape[1], frame.shape[0]) for b in boxes):
            reads = [tracker.look(frame, b) for b in boxes]
            rows.append([(np.log(w / box[2]), np.log(h / box[3])) for _, _, w, h in reads])
    if not rows:
        raise EvalError(f"{dataset.path}: all {frames_after_first(dataset)} frames after the first were skipped "
                        "(a scaled box outside the frame); nothing to read")
    return np.asarray(rows, dtype=np.float64)


def summarise_sizes(sizes: Sequence[float], reads: np.ndarray) -> SizeResponse:
    medians = np.median(reads, axis=0)  # (sizes, 2)
    order = np.argsort(sizes)
    logs = np.log(np.asarray(sizes, dtype=np.float64)[order])
    slopes, rests = [], []
    for side in (0, 1):
        read = medians[order, side]
        slopes.append(float(np.polyfit(logs, read, 1)[0]) if len(logs) > 1 else float("nan"))
        rests.append(resting_size(logs, read))
    return SizeResponse(tuple(float(f) for f in sizes), tuple(medians[:, 0].tolist()), tuple(medians[:, 1].tolist()),
                        (slopes[0], slopes[1]), (rests[0], rests[1]), len(reads))


def resting_size(logs: np.ndarray, read: np.ndarray) -> float:
    """Where the read equals the size held (log f ascending), interpolated between the factors read: the
    first crossing from growing to shrinking, where a tracker settles."""
    gap = read - logs  # > 0: the read is larger than the size held, so the held size grows
    for i in range(len(gap) - 1):
        if gap[i] >= 0 >= gap[i + 1] and gap[i] != gap[i + 1]:
            return float(np.exp(logs[i] + (logs[i + 1] - logs[i]) * gap[i] / (gap[i] - gap[i + 1])))
    return float("inf") if (gap > 0).all() else 0.0 if (gap < 0).all() else float("nan")


def size_response(tracker: Tracker, dataset: Dataset, sizes: Sequence[float]) -> SizeResponse:
    return summarise_sizes(sizes, read_sizes(tracker, dataset, sizes))


def format_size_response(dataset: Dataset, response: SizeResponse) -> str:
    skipped = frames_after_first(dataset) - response.frames
    counted = f"{response.frames} frames" + (f", {skipped} skipped: a scaled box outside the frame" if skipped else "")
    lines = [f"{dataset.name}: the network's box read with the crop cut for the true box x f, median log(box / true) "
             f"({counted})",
             f"{'f':<8}" + "".join(f"{f:>8.2f}" for f in response.sizes),
             f"{'width':<8}" + "".join(f"{v:>+8.3f}" for v in response.width),
             f"{'height':<8}" + "".join(f"{v:>+8.3f}" for v in response.height),
             f"slope (0: reads the target, 1: repeats the size given): width {response.slope[0]:.2f}, "
             f"height {response.slope[1]:.2f}",
             f"resting size (where the read equals the size held), x the truth: width {_ratio(response.rest[0])}, "
             f"height {_ratio(response.rest[1])}"]
    return "\n".join(lines)


def _ratio(value: float) -> str:
    if value == float("inf"):
        return "above the largest f (every read larger than the size given)"
    if value == 0.0:
        return "below the smallest f (every read smaller than the size given)"
    return f"{value:.2f}" if np.isfinite(value) else "none (the read crosses the size given only upwards)"
