"""Where a tracker loses its frames: how often it keeps the target's centre, how good its box is there, and
both against how visible the target is (the mean grey level inside the true box); and, where the run saved
each frame's state, whether that state told the truth.

Success (the area under the IoU curve) mixes the two ways a tracker can fail: losing the target and drawing
a poor box around it. At night they have different causes: most lost frames are frames where the target
cannot be seen at all, which a better box cannot mend. Frames are pooled over the sequences; the first
frame (the given box) is left out.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from ..datamaking.datasets import Dataset
from ..datamaking.datasets import Sequence as Clip
from .evaluate import EvalError
from .metrics import centre_errors, iou

CENTRED = 0.5  # centre error below this share of the target's size sqrt(w * h)
GREY_EDGES = (0, 8, 15, 30, 60, 256)  # bins of the mean grey level (0-255) inside the true box


@dataclass(frozen=True)
class Anatomy:
    """One tracker's frames: `centred` share, mean IoU where centred, centred share per grey-level bin."""

    name: str
    centred: float
    iou_centred: float
    centred_by_grey: tuple[float, ...]  # NaN where a bin holds no frame


@dataclass(frozen=True)
class Honesty:
    """How a tracker's reported state matches its frames: what a follow controller or a pilot is told.

    `tracking_off`: of the frames reported 'tracking', the share not centred (a confident wrong lock);
    `off_flagged`: of the frames not centred, the share reported 'uncertain' or 'lost' (a loss that shows);
    `centred_flagged`: of the centred frames, the share reported 'uncertain' or 'lost' (a false alarm).
    """

    name: str
    tracking: float
    tracking_off: float
    off_flagged: float
    centred_flagged: float


def known_frames(gt: np.ndarray) -> np.ndarray:
    """True where the true box is finite with a positive size: UAV123 marks a target out of view with a NaN
    row, which names no frame to measure (skipped, as `box-read` skips it), not a lost one."""
    with np.errstate(invalid="ignore"):
        return np.isfinite(gt).all(axis=1) & (gt[:, 2] > 0) & (gt[:, 3] > 0)


def _pooled(gts: Sequence[np.ndarray], values: Sequence[np.ndarray]) -> np.ndarray:
    """Frames 2..N with a known true box of every sequence, in one array (frame 1 is the given box)."""
    return np.concatenate([np.asarray(v)[1:][known_frames(g)[1:]] for g, v in zip(gts, values, strict=True)])


def check_frames(dataset: Dataset) -> None:
    """Refuse a selection with no known frame after the first: its tables would be all NaN."""
    if not _pooled([s.boxes for s in dataset.sequences], [s.boxes for s in dataset.sequences]).size:
        raise EvalError(f"{dataset.path}: no frames after the first with a known target box in "
                        f"{len(dataset.sequences)} sequences; nothing to measure")


def _pooled_centred(gts: Sequence[np.ndarray], preds: Sequence[np.ndarray]) -> np.ndarray:
    """`centred_frames` of frames 2..N of every sequence, in one array (frame 1 is the given box)."""
    return _pooled(gts, [centred_frames(g, p) for g, p in zip(gts, preds, strict=True)])


def _share(mask: np.ndarray) -> float:
    return float(mask.mean()) if mask.size else float("nan")


def honesty(
    name: str, gts: Sequence[np.ndarray], preds: Sequence[np.ndarray], states: Sequence[Sequence[str]]
) -> Honesty:
    """Pool frames 2..N of every sequence (`states` as `read_states` gives them, one list per sequence)."""
    ok = _pooled_centred(gts, preds)
    tracking = _pooled(gts, [np.asarray(s) == "tracking" for s in states])
    return Honesty(name, _share(tracking), _share(~ok[tracking]), _share(~tracking[~ok]), _share(~tracking[ok]))


def target_grey(clip: Clip) -> np.ndarray:
    """Mean grey level inside the true box in each frame; NaN where the box holds no whole pixel or is not
    known (a NaN or inf row: int() of it raised)."""
    out = np.full(len(clip), np.nan)
    for k, (path, (x, y, w, h)) in enumerate(zip(clip.frames, clip.boxes, strict=False)):
        if not np.isfinite((x, y, w, h)).all():
            continue
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if image is None:
            continue
        x0, y0 = max(0, int(np.ceil(x))), max(0, int(np.ceil(y)))
        x1, y1 = min(image.shape[1], int(x + w)), min(image.shape[0], int(y + h))
        if x1 > x0 and y1 > y0:
            out[k] = float(image[y0:y1, x0:x1].mean())
    return out


def centred_frames(gt: np.ndarray, pred: np.ndarray) -> np.ndarray:
    """True where the predicted centre lies within CENTRED of the target's size from the true centre."""
    size = np.sqrt(np.clip(gt[:, 2] * gt[:, 3], 1e-12, None))
    error = centre_errors(gt, pred)
    return (error >= 0) & (error < CENTRED * size)


def grey_bin(grey: np.ndarray) -> np.ndarray:
    """Bin index of each grey level in GREY_EDGES; -1 for NaN."""
    index = np.digitize(grey, GREY_EDGES[1:-1])
    return np.where(np.isnan(grey), -1, index)


def anatomy(name: str, gts: Sequence[np.ndarray], preds: Sequence[np.ndarray], bins: Sequence[np.ndarray]) -> Anatomy:
    """Pool frames 2..N of every sequence (`bins` from `grey_bin`, one array per sequence)."""
    ok = _pooled_centred(gts, preds)
    overlap = _pooled(gts, [iou(g, p) for g, p in zip(gts, preds, strict=True)])
    where = _pooled(gts, bins)
    by_grey = tuple(float(ok[where == k].mean()) if (where == k).any() else float("nan")
                    for k in range(len(GREY_EDGES) - 1))
    return Anatomy(name, float(ok.mean()), float(overlap[ok].mean()) if ok.any() else float("nan"), by_grey)


def grey_bins(dataset: Dataset) -> list[np.ndarray]:
    """`grey_bin` of every frame of every sequence (reads each frame once)."""
    return [grey_bin(target_grey(clip)) for clip in dataset.sequences]


def format_anatomy(dataset: Dataset, rows: Sequence[Anatomy], bins: Sequence[np.ndarray]) -> str:
    where = _pooled([s.boxes for s in dataset.sequences], bins)
    labels = [f"{lo}-{hi}" if hi < 256 else f">={lo}" for lo, hi in zip(GREY_EDGES[:-1], GREY_EDGES[1:], strict=True)]
    shares = [f"{label} ({(where == k).mean():.0%})" for k, label in enumerate(labels)]
    width = max(8, *(len(r.name) for r in rows))
    lines = [f"{dataset.name}: {len(dataset.sequences)} sequences, {where.size} frames after the first",
             f"centred: centre within {CENTRED:g} of the target's size; by the mean grey level in the true box:",
             f"{'Tracker':<{width}}  centred  IoU there  " + "  ".join(f"{s:>{max(12, len(s))}}" for s in shares)]
    for r in rows:
        cells = "  ".join(f"{_cell(v, '.3f'):>{max(12, len(s))}}"
                          for v, s in zip(r.centred_by_grey, shares, strict=True))
        lines.append(f"{r.name:<{width}}  {_cell(r.centred, '7.3f')}  {_cell(r.iou_centred, '9.3f')}  {cells}")
    return "\n".join(lines)


def _cell(value: float, spec: str) -> str:
    """A table cell; '-' where nothing was measured (no frame in a grey bin, no centred frame), not nan."""
    return format(value, spec) if np.isfinite(value) else format("-", ">" + spec.split(".")[0])


def format_honesty(rows: Sequence[Honesty]) -> str:
    width = max(8, *(len(r.name) for r in rows))
    lines = ["reported state against the truth (off: not centred; flagged: 'uncertain' or 'lost'):",
             f"{'Tracker':<{width}}  tracking  tracking but off  off but flagged  centred but flagged"]
    lines += [f"{r.name:<{width}}  {r.tracking:8.3f}  {r.tracking_off:15.3f}  {r.off_flagged:15.3f}  "
              f"{r.centred_flagged:19.3f}" for r in rows]
    return "\n".join(lines)
