"""Plots are drawn with OpenCV: files exist, have the expected size, and show each tracker's colour."""

from __future__ import annotations

import cv2
import numpy as np

from dadiff.runtime.evaluation.metrics import SequenceCurves, summarise
from dadiff.runtime.evaluation.plots import PALETTE, Curve, draw_plot, write_plots


def _scores(shift: float):
    gt = np.tile([50.0, 50.0, 20.0, 20.0], (30, 1))
    pred = gt + np.linspace(0, shift, 30)[:, None] * [1, 1, 0, 0]
    return summarise([SequenceCurves.from_boxes(gt, pred)])


def _has_colour(image: np.ndarray, bgr) -> bool:
    return bool(np.any(np.all(np.abs(image.astype(int) - bgr) <= 12, axis=2)))


def test_write_plots_makes_three_pngs_per_subject(tmp_path):
    scores = {"good": _scores(4), "bad": _scores(40), "worse": _scores(80)}
    paths = write_plots(scores, tmp_path / "plots", "bench")
    paths += write_plots(scores, tmp_path / "plots", "bench", attribute="LR")
    names = sorted(p.name for p in paths)
    assert names == sorted(f"{k}_{a}.png" for k in ("success", "precision", "norm_precision") for a in ("ALL", "LR"))
    image = cv2.imread(str(paths[0]))
    assert image.shape == (560, 620, 3)
    for colour in PALETTE[:3]:
        assert _has_colour(image, colour)
    assert not _has_colour(image, PALETTE[3])


def test_best_tracker_gets_the_first_colour():
    x = np.linspace(0, 1, 21)
    curves = [Curve("low", x, np.full(21, 0.2), 0.2), Curve("high", x, np.full(21, 0.8), 0.8)]
    image = draw_plot(curves, title="t", xlabel="x", ylabel="y", x_max=1.0, x_step=0.1)
    # The first palette colour is drawn on the upper line (y = 0.8 of a 0..0.9 axis).
    rows = np.nonzero(np.all(np.abs(image.astype(int) - PALETTE[0]) <= 12, axis=2))[0]
    rows_second = np.nonzero(np.all(np.abs(image.astype(int) - PALETTE[1]) <= 12, axis=2))[0]
    assert np.median(rows) < np.median(rows_second)
