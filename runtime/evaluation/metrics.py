"""One-pass evaluation (OPE) metrics, computed exactly as the pysot toolkit does (spec section 9).

Per sequence, every frame counts, frame 0 included (its result is the init box), and the curves are
divided by the number of ground-truth frames. Invalid ground truth follows the toolkit too:

- success: a frame whose GT width or height is not > 0 (NaN included) gets IoU -1, a failure at every
  threshold. A NaN in the prediction gives a NaN IoU, also a failure.
- precision: a frame whose GT centre has a coordinate <= 0 or NaN gets distance -1, a hit at every
  threshold. Normalised precision applies the same rule to the GT centre divided by the GT size.

Thresholds are built with the toolkit's own expressions (`np.arange(0, 1.05, 0.05)`, ...), floating-point
error included, because success uses a strict `>` and a value such as 0.3 sits right on a threshold.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from ..datamaking.geometry import as_boxes, iou, paired_boxes

SUCCESS_THRESHOLDS = np.arange(0, 1.05, 0.05)  # 21 IoU thresholds, strict >
PRECISION_THRESHOLDS = np.arange(0, 51, 1)  # centre error in pixels, <=
NORM_THRESHOLDS = np.arange(0, 51, 1) / 100  # centre error in GT sizes, <=
PRECISION_INDEX = 20  # 20 px, and 0.20 for the toolkit's normalised precision

_NORM_EPS = 1e-16  # the toolkit's guard against a zero GT size


def centres(boxes: object) -> np.ndarray:
    """(N, 2) centres in the toolkit's convention, (x + (w - 1)/2, y + (h - 1)/2)."""
    b = as_boxes(boxes)
    with np.errstate(over="ignore"):  # a huge box's centre is inf: a miss at every threshold
        return np.stack([b[:, 0] + (b[:, 2] - 1) / 2, b[:, 1] + (b[:, 3] - 1) / 2], axis=1)


def _distances(gt_c: np.ndarray, pred_c: np.ndarray) -> np.ndarray:
    out = np.full(len(gt_c), -1.0)
    with np.errstate(invalid="ignore"):
        valid = np.sum(gt_c > 0, axis=1) == 2
    with np.errstate(over="ignore", invalid="ignore"):  # huge boxes: an inf (or NaN) distance, a miss
        out[valid] = np.sqrt(np.sum((gt_c[valid] - pred_c[valid]) ** 2, axis=1))
    return out


def centre_errors(gt: object, pred: object) -> np.ndarray:
    """Per-frame centre distance in pixels; -1 (a hit) where a GT centre coordinate is <= 0 or NaN."""
    g, p = paired_boxes(gt, pred)
    return _distances(centres(g), centres(p))


def norm_centre_errors(gt: object, pred: object) -> np.ndarray:
    """Centre distance after dividing both centres by the GT (w, h) (+1e-16); -1 as in `centre_errors`."""
    g, p = paired_boxes(gt, pred)
    size = g[:, 2:] + _NORM_EPS
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        return _distances(centres(g) / size, centres(p) / size)


def _rate_above(values: np.ndarray, thresholds: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return np.array([np.sum(values > t) for t in thresholds], dtype=np.float64) / len(values)


def _rate_within(values: np.ndarray, thresholds: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore"):
        return np.array([np.sum(values <= t) for t in thresholds], dtype=np.float64) / len(values)


def success_curve(gt: object, pred: object) -> np.ndarray:
    """Fraction of frames with IoU > each of the 21 `SUCCESS_THRESHOLDS`."""
    return _rate_above(iou(gt, pred), SUCCESS_THRESHOLDS)


def precision_curve(gt: object, pred: object) -> np.ndarray:
    """Fraction of frames with centre error <= 0, 1, ..., 50 px."""
    return _rate_within(centre_errors(gt, pred), PRECISION_THRESHOLDS)


def norm_precision_curve(gt: object, pred: object) -> np.ndarray:
    """Fraction of frames with normalised centre error <= 0, 0.01, ..., 0.50."""
    return _rate_within(norm_centre_errors(gt, pred), NORM_THRESHOLDS)


@dataclass(frozen=True)
class SequenceCurves:
    """The three OPE curves of one sequence."""

    success: np.ndarray
    precision: np.ndarray
    norm_precision: np.ndarray

    @classmethod
    def from_boxes(cls, gt: object, pred: object) -> SequenceCurves:
        g, p = paired_boxes(gt, pred)
        return cls(success_curve(g, p), precision_curve(g, p), norm_precision_curve(g, p))


@dataclass(frozen=True)
class Scores:
    """A tracker's scores over a set of sequences, each sequence weighted equally.

    `success`: area under the success plot (the mean of the mean curve over its 21 thresholds).
    `precision`: the mean precision curve at 20 px.
    `norm_precision`: the paper's normalised precision, the area under the normalised precision plot
    over [0, 0.5] (the mean of the mean curve over its 51 thresholds).
    `norm_precision_at_20`: the toolkit's normalised precision, the mean curve at 0.20.
    """

    success: float
    precision: float
    norm_precision: float
    norm_precision_at_20: float
    success_curve: np.ndarray
    precision_curve: np.ndarray
    norm_precision_curve: np.ndarray
    sequences: int


def summarise(curves: Iterable[SequenceCurves]) -> Scores:
    """Average per-sequence curves into `Scores` (raises ValueError when there are none)."""
    items = list(curves)
    if not items:
        raise ValueError("no sequences to score")
    succ = np.mean([c.success for c in items], axis=0)
    prec = np.mean([c.precision for c in items], axis=0)
    norm = np.mean([c.norm_precision for c in items], axis=0)
    return Scores(
        success=float(np.mean(succ)),
        precision=float(prec[PRECISION_INDEX]),
        norm_precision=float(np.mean(norm)),
        norm_precision_at_20=float(norm[PRECISION_INDEX]),
        success_curve=succ,
        precision_curve=prec,
        norm_precision_curve=norm,
        sequences=len(items),
    )


@dataclass(frozen=True)
class PairedDifference:
    """Mean per-sequence difference of two trackers' success on the same sequences, with a bootstrap
    interval: how far a gap between two means can be trusted when a single sequence swings by 0.5."""

    mean: float
    low: float
    high: float
    level: float
    sequences: int


def paired_difference(
    ours: Iterable[float], theirs: Iterable[float], samples: int = 10000, level: float = 0.95, seed: int = 0
) -> PairedDifference:
    """Percentile bootstrap over sequences (resampled with replacement, the same draw for both trackers)."""
    a, b = np.asarray(list(ours), dtype=np.float64), np.asarray(list(theirs), dtype=np.float64)
    if a.shape != b.shape or a.ndim != 1 or len(a) == 0:
        raise ValueError(f"paired scores need the same non-empty sequences, got {a.shape} and {b.shape}")
    diff = a - b
    draws = np.random.default_rng(seed).integers(0, len(diff), size=(samples, len(diff)))
    means = diff[draws].mean(axis=1)
    tail = (1 - level) / 2 * 100
    low, high = np.percentile(means, [tail, 100 - tail])
    return PairedDifference(float(diff.mean()), float(low), float(high), level, len(diff))
