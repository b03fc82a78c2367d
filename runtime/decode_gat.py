"""Released SiamGAT decoding (DaDiff-GAT's `siamgat_tracker.py`): centerness, bicubic upsampling, two-stage peak.

Per frame: score = softmax(cls)[1] + 0.05; centerness min-max normalised over the map (no sigmoid); the SiamBAN
size/aspect penalty on the (l, t, r, b) map; p = penalty·score·centerness, hp = p windowed by a Hanning window.
hp, p, score and the distances are upsampled bicubically (cv2.INTER_CUBIC) to (S − 1)·stride + 1 points, one
crop pixel apart. The coarse peak is hp's argmax; a region around it, sized from the *low-resolution* distances
at the nearest coarse cell, masks p, whose argmax is the location used. The size step is weighted by a second
penalty that compares the box in frame pixels with the target in crop pixels: the release's unit mix-up
(inherited from SiamCAR), kept because its trained hyper-parameters assume it. Dtypes follow the release
(float32 maps, the window in float64). All positions are crop pixels relative to the crop centre.
"""

from __future__ import annotations

import cv2
import numpy as np

from .decode import Detection, foreground_score, hann_window, size_penalty


def template_roi(w: float, h: float, s_z: int, exemplar_size: int) -> np.ndarray:
    """The target's box in template-crop pixels, (1, 4) float32 (x1, y1, x2, y2), as the release's `init` builds
    it: centred on the crop, scaled by exemplar_size / s_z with s_z the rounded template window side."""
    scale = exemplar_size / s_z
    c = (exemplar_size - 1) / 2
    return np.array([[c - w * scale / 2, c - h * scale / 2, c + w * scale / 2, c + h * scale / 2]], np.float32)


def _upsample(a: np.ndarray, size: int) -> np.ndarray:
    return cv2.resize(a, (size, size), interpolation=cv2.INTER_CUBIC)


class GatDecoder:
    """The released SiamGAT post-processing for one score-map layout (S, stride, origin of point (0, 0))."""

    def __init__(self, score_size: int, stride: float, origin: float, exemplar_size: int,
                 region_s: float = 0.1, region_l: float = 0.44) -> None:
        self.score_size, self.origin = score_size, origin
        self.stride = int(stride)
        self.up = (score_size - 1) * self.stride + 1
        self.window = hann_window(score_size)
        self.region = (int(region_s * exemplar_size), int(region_l * exemplar_size))

    def _coarse_mask(self, hp_up: np.ndarray, lrtb: np.ndarray) -> tuple[tuple[int, int], np.ndarray]:
        """hp's peak (row, col) and the region around it, sized from the low-resolution distances there."""
        row, col = np.unravel_index(int(np.argmax(hp_up)), hp_up.shape)
        scale = self.up / (self.score_size - 1)
        last = self.score_size - 1
        cell = lrtb[:, min(max(int(round(row / scale)), 0), last), min(max(int(round(col / scale)), 0), last)]
        low, high = self.region
        left, top, right, bottom = (float(min(max(v, low), high)) for v in cell)
        left, right = int(min(col, left) / 2), int(min(self.up - col, right) / 2)
        top, bottom = int(min(row, top) / 2), int(min(self.up - row, bottom) / 2)
        mask = np.zeros(hp_up.shape, np.float32)
        mask[row - top:row + bottom + 1, col - left:col + right + 1] = 1
        return (int(row), int(col)), mask

    def __call__(self, cls: np.ndarray, loc: np.ndarray, cen: np.ndarray, target_w: float, target_h: float,
                 scale: float, penalty_k: float, window_influence: float) -> Detection:
        """The chosen point for a target of (target_w, target_h) crop pixels; `scale` is crop px per frame px."""
        s = self.score_size
        if any(tuple(m.shape[-2:]) != (s, s) for m in (cls, loc, cen)):
            raise ValueError(f"score maps are {cls.shape}, {loc.shape} and {cen.shape}, expected (1, 2|4|1, {s}, {s})")
        score = foreground_score(cls).astype(np.float32) + np.float32(0.05)
        c = np.asarray(cen, np.float32).reshape(s, s)
        spread = np.ptp(c)
        centred = (c - c.min()) / spread if spread > 0 else np.ones_like(c)  # a flat map weighs every cell alike
        lrtb = np.asarray(loc, np.float32).reshape(4, s, s)
        penalty = size_penalty(lrtb[0] + lrtb[2], lrtb[1] + lrtb[3], target_w, target_h, penalty_k)
        p_score = (penalty * score * centred).astype(np.float32)
        hp_score = p_score * (1.0 - window_influence) + self.window * window_influence
        hp_up, p_up = _upsample(hp_score, self.up), _upsample(p_score, self.up)
        score_up = _upsample(score, self.up)
        lrtb_up = _upsample(np.ascontiguousarray(lrtb.transpose(1, 2, 0)), self.up)
        coarse, mask = self._coarse_mask(hp_up, lrtb)
        best = int(np.argmax(p_up * mask))
        row, col = divmod(best, self.up)
        point = lrtb_up[row, col]
        w, h = float(point[0] + point[2]), float(point[1] + point[3])  # summed in float32, as the release
        # the box in frame pixels against the target in crop pixels: the release's unit mix-up
        step_penalty = size_penalty(w / scale, h / scale, target_w, target_h, penalty_k)
        weight = float(score_up[row, col])
        return Detection(self.origin + col, self.origin + row, w, h, min(max(weight - 0.05, 0.0), 1.0),
                         float(step_penalty), best, weight=weight, coarse=coarse[0] * self.up + coarse[1])
