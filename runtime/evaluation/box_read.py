"""The network's own box where the target is known: `dadiff-eval box-read`.

Each frame's search crop is cut around the true box at its true size (its centre moved by a shift in crop
pixels), the search graph runs once, and the box is read before the tracker smooths, bounds or holds it
(`Tracker.look`). Tracking mixes the network's box error with its own history; this reads the first alone.
With a stride-16 score map a target falls anywhere between two grid points, so the read is taken at several
shifts (by default every quarter of the stride) and their mean is what tracking meets on average. The
stride is the metadata's, the points' spacing; `--shifts` sets other shifts.
Reported per shift: the median log ratio of the box's width and height to the truth, over all frames and by
thirds of the true width (frame pixels); and where the box's centre lands: its median offset from the true
centre along the shift, in true widths (0: the network found the target; positive: it stayed towards the
crop's centre, as a tracker that lags a fast target does), and the share of reads whose centre falls outside
the true box (at a large shift: the target moved that far in one frame and the tracker lost it).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from ..datamaking.datasets import Dataset, read_frame
from ..errors import InputError
from ..tracker import Tracker, check_box
from .evaluate import EvalError, check_first_box


@dataclass(frozen=True)
class BoxRead:
    """Median log(w / true w) and log(h / true h) at one shift, over all frames and per width third; the
    centre's median offset along the shift (true widths) and the share of centres outside the true box."""

    shift: float
    width: float
    height: float
    thirds: tuple[tuple[float, float, float, float], ...]  # (low px, high px, width, height)
    frames: int
    centre: float  # median offset of the box's centre along the shift, in true widths
    off: float  # share of reads whose centre is outside the true box


def marks_a_target(box: np.ndarray) -> bool:
    """Finite and over a pixel a side: OTB/UAV123 mark a target out of view with NaN or zero rows."""
    return bool(np.isfinite(box).all() and box[2] > 1 and box[3] > 1)


def in_frame(box: np.ndarray, width: int, height: int) -> bool:
    """Whether a later true box names a target in this frame, as the tracker checks a box it is given
    (`check_box`). Others are skipped and counted: one such box never stops the whole run."""
    if not marks_a_target(box):
        return False
    try:
        check_box(box, width, height)
    except InputError:
        return False
    return True


def frames_after_first(dataset: Dataset) -> int:
    """Frames 2..N of every sequence, skipped ones included."""
    return sum(max(0, min(len(s.frames), len(s.boxes)) - 1) for s in dataset.sequences)


def frames_with_targets(tracker: Tracker, dataset: Dataset) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """(frame, true box) for every frame after the first whose box names a target in it, the tracker
    initialised on each sequence's first frame before its frames are given: what every read starts from."""
    if not frames_after_first(dataset):
        raise EvalError(f"{dataset.path}: no frames after the first in {len(dataset.sequences)} sequences; "
                        "nothing to read")
    for seq in dataset.sequences:
        check_first_box(seq.name, seq.boxes[0])
        tracker.init(read_frame(seq.frames[0]), tuple(seq.boxes[0]))
        for path, box in zip(seq.frames[1:], seq.boxes[1:], strict=False):
            if not marks_a_target(box):
                continue  # no need to decode the frame
            frame = read_frame(path)
            if in_frame(box, frame.shape[1], frame.shape[0]):
                yield frame, box


def read_ratios(tracker: Tracker, dataset: Dataset, shifts: Sequence[float]) -> list[np.ndarray]:
    """Per shift: (true width, log width ratio, log height ratio, centre offset along the shift in true
    widths, 1 where the centre is outside the true box) per frame after the first of every sequence. Each
    frame is decoded once and read at every shift."""
    rows: list[list[tuple[float, float, float, float, float]]] = [[] for _ in shifts]
    for frame, box in frames_with_targets(tracker, dataset):
        for kept, shift in zip(rows, shifts, strict=True):
            x, y, w, h = tracker.look(frame, tuple(box), (shift, 0.0))
            dx = (x + w / 2) - (box[0] + (box[2] - 1) / 2)  # the true centre as the tracker places crops
            dy = (y + h / 2) - (box[1] + (box[3] - 1) / 2)
            outside = abs(dx) > box[2] / 2 or abs(dy) > box[3] / 2
            kept.append((box[2], np.log(w / box[2]), np.log(h / box[3]), dx / box[2], float(outside)))
    if not rows[0]:
        raise EvalError(f"{dataset.path}: all {frames_after_first(dataset)} frames after the first were skipped "
                        "(no true box inside the frame); nothing to read")
    return [np.asarray(r, dtype=np.float64).reshape(-1, 5) for r in rows]


def summarise(shift: float, rows: np.ndarray) -> BoxRead:
    edges = np.quantile(rows[:, 0], [0, 1 / 3, 2 / 3, 1]) if len(rows) else np.zeros(4)
    thirds = []
    for i, (low, high) in enumerate(zip(edges[:-1], edges[1:], strict=True)):
        inside = (rows[:, 0] >= low) & ((rows[:, 0] < high) if i < 2 else (rows[:, 0] <= high))
        thirds.append((float(low), float(high), *_medians(rows[inside])))
    centre = float(np.median(rows[:, 3])) if len(rows) else float("nan")
    off = float(np.mean(rows[:, 4])) if len(rows) else float("nan")
    return BoxRead(shift, *_medians(rows), tuple(thirds), len(rows), centre, off)


def _medians(rows: np.ndarray) -> tuple[float, float]:
    if not len(rows):
        return float("nan"), float("nan")
    return float(np.median(rows[:, 1])), float(np.median(rows[:, 2]))


def box_read(tracker: Tracker, dataset: Dataset, shifts: Sequence[float]) -> list[BoxRead]:
    return [summarise(shift, rows) for shift, rows in zip(shifts, read_ratios(tracker, dataset, shifts), strict=True)]


def format_box_read(dataset: Dataset, reads: Sequence[BoxRead]) -> str:
    """A table: one row per shift and, for several shifts, their mean (what tracking meets on average)."""
    first = reads[0]
    heads = [f"{low:.0f}-{high:.0f} px w / h" for low, high, _, _ in first.thirds]
    skipped = frames_after_first(dataset) - first.frames
    counted = f"{first.frames} frames" + (f", {skipped} skipped: no true box inside the frame" if skipped else "")
    lines = [f"{dataset.name}: the network's box read around the true box, median log(box / true) ({counted})",
             f"{'shift (crop px)':<16} {'width':>7} {'height':>7} {'centre':>7} {'off':>6}   "
             + "   ".join(f"{h:>20}" for h in heads)]

    def row(label: str, width: float, height: float, centre: float, off: float,
            thirds: Sequence[tuple[float, float]]) -> str:
        cells = "   ".join(f"{_pair(w, h):>20}" for w, h in thirds)
        return f"{label:<16} {width:>+7.3f} {height:>+7.3f} {centre:>+7.3f} {off:>6.1%}   {cells}"

    for r in reads:
        lines.append(row(f"{r.shift:g}", r.width, r.height, r.centre, r.off, [(w, h) for _, _, w, h in r.thirds]))
    if len(reads) > 1:
        thirds = [(np.mean([r.thirds[i][2] for r in reads]), np.mean([r.thirds[i][3] for r in reads]))
                  for i in range(len(first.thirds))]
        lines.append(row("mean", *(float(np.mean([getattr(r, k) for r in reads]))
                                   for k in ("width", "height", "centre", "off")), thirds))
    return "\n".join(lines)


def _pair(width: float, height: float) -> str:
    """A width-third's cell; '-' where the third holds no frame (a handful of frames, many of one width)."""
    return f"{width:+.3f} / {height:+.3f}" if np.isfinite(width) else "-"
