"""Released SiamBAN decoding (spec 8.3 steps 2-5), vectorised over the score map.

All quantities are in instance-crop pixels relative to the crop centre; the tracker converts to frame pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def foreground_score(cls: np.ndarray) -> np.ndarray:
    """Softmax over the 2 channels of a (1, 2, S, S) map, channel 1, as an (S, S) array.

    Written as 0.5 + 0.5·tanh((c1 − c0)/2), which equals the 2-way softmax without overflow warnings.
    """
    c = np.asarray(cls, dtype=np.float64).reshape(2, *cls.shape[-2:])
    return 0.5 + 0.5 * np.tanh(0.5 * (c[1] - c[0]))


def point_grid(score_size: int, stride: float, origin: float) -> tuple[np.ndarray, np.ndarray]:
    """(px, py) of every cell: cell (i, j) sits at (origin + stride·j, origin + stride·i)."""
    line = origin + stride * np.arange(score_size, dtype=np.float64)
    return np.meshgrid(line, line)


def hann_window(score_size: int) -> np.ndarray:
    """outer(h, h) with h[n] = 0.5 − 0.5·cos(2πn/(N−1)) (endpoints 0), as the released tracker."""
    h = np.hanning(score_size)
    return np.outer(h, h)


def decode_boxes(loc: np.ndarray, px: np.ndarray, py: np.ndarray) -> tuple[np.ndarray, ...]:
    """(cx, cy, w, h) per cell from (1, 4, S, S) distances (l, t, r, b) to the cell's point."""
    left, top, right, bottom = np.asarray(loc, dtype=np.float64).reshape(4, *loc.shape[-2:])
    x1, y1, x2, y2 = px - left, py - top, px + right, py + bottom
    return (x1 + x2) / 2, (y1 + y2) / 2, x2 - x1, y2 - y1


def _context_size(w: np.ndarray | float, h: np.ndarray | float) -> np.ndarray | float:
    pad = (w + h) * 0.5
    return np.sqrt((w + pad) * (h + pad))


def _change(r: np.ndarray | float) -> np.ndarray | float:
    return np.maximum(r, 1.0 / r)


def size_penalty(
    w: np.ndarray, h: np.ndarray, target_w: float, target_h: float, penalty_k: float
) -> np.ndarray:
    """exp(−(r_c·s_c − 1)·k): penalises change of scale and aspect against the current target (crop px)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        s_c = _change(_context_size(w, h) / _context_size(target_w, target_h))
        r_c = _change((target_w / target_h) / (w / h))
        penalty = np.exp(-(r_c * s_c - 1.0) * penalty_k)
    return np.nan_to_num(penalty, nan=0.0)


@dataclass(frozen=True)
class Detection:
    """The chosen cell: offset and size in crop pixels, its raw score and its penalty.

    `weight`: the score that scales the size step when it is not `score` (SiamGAT: the upsampled score + 0.05);
    `coarse`: SiamGAT's first-stage peak (flat index on the upsampled map), -1 for SiamBAN.
    """

    dx: float
    dy: float
    w: float
    h: float
    score: float
    penalty: float
    index: int
    weight: float | None = None
    coarse: int = -1

    @property
    def step_score(self) -> float:
        return self.score if self.weight is None else self.weight


class Decoder:
    """Holds the point grid and cosine window of one score-map layout."""

    def __init__(self, score_size: int, stride: float, origin: float) -> None:
        self.score_size = score_size
        self.px, self.py = point_grid(score_size, stride, origin)
        self.window = hann_window(score_size)

    def __call__(
        self,
        cls: np.ndarray,
        loc: np.ndarray,
        target_w: float,
        target_h: float,
        penalty_k: float,
        window_influence: float,
        prior: np.ndarray | None = None,
    ) -> Detection:
        """Pick the best cell (first argmax of penalised, windowed score) for a target of this crop size;
        `prior` (S×S) weights each cell's score in that choice only (runtime/colour_prior.py)."""
        expected = (self.score_size, self.score_size)
        if tuple(cls.shape[-2:]) != expected or tuple(loc.shape[-2:]) != expected:
            raise ValueError(f"score maps are {cls.shape} and {loc.shape}, expected (1, 2|4, {expected})")
        score = foreground_score(cls)
        cx, cy, w, h = decode_boxes(loc, self.px, self.py)
        penalty = size_penalty(w, h, target_w, target_h, penalty_k)
        weighted = score if prior is None else score * prior
        pscore = penalty * weighted * (1.0 - window_influence) + self.window * window_influence
        best = int(np.argmax(pscore))
        i, j = divmod(best, self.score_size)
        return Detection(
            float(cx[i, j]),
            float(cy[i, j]),
            float(w[i, j]),
            float(h[i, j]),
            float(score[i, j]),
            float(penalty[i, j]),
            best,
        )
