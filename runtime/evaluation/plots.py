"""Success, precision and normalised-precision plots (PNG) drawn with OpenCV, in the style of OPE papers.

One line per tracker, legend entries "[value] name" sorted best first: the success plot's legend holds
the AUC, the precision plot's the value at 20 px, the normalised plot's the area over [0, 0.5].
OpenCV is the only drawing dependency; OpenCV 5's TrueType font is used when present, Hershey otherwise.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from .metrics import NORM_THRESHOLDS, PRECISION_THRESHOLDS, SUCCESS_THRESHOLDS, Scores

# BGR; distinct in colour and, past the first eight, also in dash pattern.
PALETTE = (
    (40, 40, 220),
    (200, 110, 0),
    (40, 160, 40),
    (180, 60, 180),
    (0, 140, 255),
    (160, 160, 0),
    (40, 40, 40),
    (120, 120, 120),
)
_SCALE = 2  # drawn at twice the size, then reduced, for smooth lines and text


@dataclass(frozen=True)
class Curve:
    """One tracker's line: x and y values, and the number shown in the legend."""

    label: str
    x: np.ndarray
    y: np.ndarray
    value: float


class _Text:
    """Text drawing with OpenCV 5's sans font when available, else Hershey simplex."""

    def __init__(self) -> None:
        face = getattr(cv2, "FontFace", None)
        self._face = face("sans") if face is not None else None

    def size(self, text: str, px: int, bold: bool = False) -> tuple[int, int]:
        if self._face is not None:
            _, _, w, h = cv2.getTextSize((0, 0), text, (0, 0), self._face, px, 700 if bold else 400)
            return w, px
        scale = px / 30
        (w, _), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 2 if bold else 1)
        return w, px

    def draw(self, img: np.ndarray, text: str, x: float, y: float, px: int, bold: bool = False, anchor: str = "lb"):
        """Draw with the anchor at (x, y): 'l'/'c'/'r' horizontally, 'b' baseline or 'm' middle vertically."""
        w, h = self.size(text, px, bold)
        x -= {"l": 0, "c": w / 2, "r": w}[anchor[0]]
        y += {"b": 0, "m": 0.36 * h}[anchor[1]]
        org = (round(x), round(y))
        if self._face is not None:
            cv2.putText(img, text, org, (0, 0, 0), self._face, px, 700 if bold else 400)
        else:
            thick = max(1, round(px / 14)) + (1 if bold else 0)
            cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, px / 30, (0, 0, 0), thick, cv2.LINE_AA)


def _polyline(img: np.ndarray, pts: np.ndarray, colour, thickness: int, dash: int) -> None:
    if not dash:
        cv2.polylines(img, [np.rint(pts * 16).astype(np.int32)], False, colour, thickness, cv2.LINE_AA, 4)
        return
    seg = np.hypot(*np.diff(pts, axis=0).T)
    run = np.concatenate([[0], np.cumsum(seg)])
    for start in np.arange(0, run[-1], 2 * dash):
        s = np.linspace(start, min(start + dash, run[-1]), 8)
        part = np.stack([np.interp(s, run, pts[:, 0]), np.interp(s, run, pts[:, 1])], axis=1)
        cv2.polylines(img, [np.rint(part * 16).astype(np.int32)], False, colour, thickness, cv2.LINE_AA, 4)


def draw_plot(
    curves: list[Curve],
    *,
    title: str,
    xlabel: str,
    ylabel: str,
    x_max: float,
    x_step: float,
    legend: str = "lower left",
    size: tuple[int, int] = (620, 560),
) -> np.ndarray:
    """A BGR image of the curves, best legend value first; y runs from 0 to just above the highest point."""
    s = _SCALE
    width, height = size[0] * s, size[1] * s
    img = np.full((height, width, 3), 255, np.uint8)
    text = _Text()
    left, right, top, bottom = 78 * s, 22 * s, 46 * s, 62 * s
    pw, ph = width - left - right, height - top - bottom
    top_value = max([float(np.nanmax(c.y)) for c in curves if np.isfinite(c.y).any()] + [0.0])
    y_max = min(1.0, math.ceil((top_value + 0.03) * 10) / 10) or 0.1

    def to_px(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return np.stack([left + x / x_max * pw, top + ph - y / y_max * ph], axis=1)

    grid = (225, 225, 225)
    for gx in np.arange(0, x_max + 1e-9, x_step):
        px = left + gx / x_max * pw
        cv2.line(img, (round(px), top), (round(px), top + ph), grid, s)
        label = f"{gx:g}" if x_step >= 1 else f"{gx:.{2 if round(x_step * 10) != x_step * 10 else 1}f}"
        text.draw(img, label, px, top + ph + 22 * s, 15 * s, anchor="cb")
    for gy in np.arange(0, y_max + 1e-9, 0.1):
        py = top + ph - gy / y_max * ph
        cv2.line(img, (left, round(py)), (left + pw, round(py)), grid, s)
        text.draw(img, f"{gy:.1f}", left - 8 * s, py, 15 * s, anchor="rm")
    cv2.rectangle(img, (left, top), (left + pw, top + ph), (0, 0, 0), s)
    text.draw(img, title, left + pw / 2, top - 16 * s, 18 * s, bold=True, anchor="cb")
    text.draw(img, xlabel, left + pw / 2, height - 14 * s, 16 * s, anchor="cb")
    label = np.full((30 * s, ph, 3), 255, np.uint8)
    text.draw(label, ylabel, ph / 2, 15 * s, 16 * s, anchor="cm")
    img[top : top + ph, 14 * s : 44 * s] = np.minimum(img[top : top + ph, 14 * s : 44 * s], np.rot90(label))

    ordered = sorted(curves, key=lambda c: -c.value if np.isfinite(c.value) else math.inf)
    for k, curve in reversed(list(enumerate(ordered))):  # best drawn last, on top
        colour = PALETTE[k % len(PALETTE)]
        dash = 0 if k < len(PALETTE) else (10 + 6 * (k // len(PALETTE) % 2)) * s
        _polyline(img, to_px(curve.x, np.nan_to_num(curve.y)), colour, 2 * s, dash)

    entries = [f"[{c.value:.3f}] {c.label}" for c in ordered]
    if entries:
        row, px = 22 * s, 15 * s
        box_w = max(text.size(e, px)[0] for e in entries) + 52 * s
        box_h = row * len(entries) + 10 * s
        x0 = left + 10 * s if legend.endswith("left") else left + pw - 10 * s - box_w
        y0 = top + ph - 10 * s - box_h if legend.startswith("lower") else top + 10 * s
        cv2.rectangle(img, (x0, y0), (x0 + box_w, y0 + box_h), (255, 255, 255), -1)
        cv2.rectangle(img, (x0, y0), (x0 + box_w, y0 + box_h), (160, 160, 160), s)
        for k, entry in enumerate(entries):
            cy = y0 + 5 * s + row * k + row / 2
            colour = PALETTE[k % len(PALETTE)]
            dash = 0 if k < len(PALETTE) else (6 + 3 * (k // len(PALETTE) % 2)) * s
            _polyline(img, np.array([[x0 + 8 * s, cy], [x0 + 38 * s, cy]], float), colour, 2 * s, dash)
            text.draw(img, entry, x0 + 44 * s, cy, px, anchor="lm")
    return cv2.resize(img, size, interpolation=cv2.INTER_AREA)


def _curves(scores: Mapping[str, Scores], kind: str) -> list[Curve]:
    if kind == "success":
        return [Curve(n, SUCCESS_THRESHOLDS, s.success_curve, s.success) for n, s in scores.items()]
    if kind == "precision":
        return [Curve(n, PRECISION_THRESHOLDS.astype(float), s.precision_curve, s.precision) for n, s in scores.items()]
    return [Curve(n, NORM_THRESHOLDS, s.norm_precision_curve, s.norm_precision) for n, s in scores.items()]


_PLOTS = {
    "success": ("Success plots of OPE", "Overlap threshold", "Success rate", 1.0, 0.1, "lower left"),
    "precision": ("Precision plots of OPE", "Location error threshold", "Precision", 50.0, 5.0, "lower right"),
    "norm_precision": (
        "Normalized precision plots of OPE",
        "Normalized location error threshold",
        "Normalized precision",
        0.5,
        0.05,
        "lower right",
    ),
}


def plot(scores: Mapping[str, Scores], kind: str, subject: str) -> np.ndarray:
    """One plot ('success', 'precision' or 'norm_precision') of every tracker in `scores`."""
    title, xlabel, ylabel, x_max, x_step, legend = _PLOTS[kind]
    return draw_plot(
        _curves(scores, kind),
        title=f"{title} {subject}",
        xlabel=xlabel,
        ylabel=ylabel,
        x_max=x_max,
        x_step=x_step,
        legend=legend,
    )


def write_plots(scores: Mapping[str, Scores], folder: Path, dataset: str, attribute: str | None = None) -> list[Path]:
    """Write success, precision and normalised-precision PNGs for `dataset` (or one attribute of it)."""
    folder.mkdir(parents=True, exist_ok=True)
    subject = f"on {dataset}" if attribute is None else f"- {attribute} ({dataset})"
    stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", attribute or "ALL")
    paths = []
    for kind in _PLOTS:
        path = folder / f"{kind}_{stem}.png"
        if not cv2.imwrite(str(path), plot(scores, kind, subject)):
            raise OSError(f"{path}: cannot write PNG")
        paths.append(path)
    return paths
