"""Synthetic tracking sequences for the runtime tests: a textured object over a different texture."""

from __future__ import annotations

import math

import cv2
import numpy as np
import skimage.data

FRAME_W, FRAME_H = 480, 360


def _background() -> np.ndarray:
    grass = cv2.resize(skimage.data.grass(), (FRAME_W, FRAME_H), interpolation=cv2.INTER_AREA)
    bricks = cv2.resize(skimage.data.brick(), (FRAME_W, FRAME_H), interpolation=cv2.INTER_AREA)
    return np.dstack([grass, (grass // 2 + bricks // 2), bricks]).astype(np.uint8)


def _object_texture() -> np.ndarray:
    """A colourful patch (the mission badge on the orange suit), BGR."""
    rgb = skimage.data.astronaut()[330:450, 120:240]
    return np.ascontiguousarray(rgb[:, :, ::-1])


def _occluder(w: int, h: int) -> np.ndarray:
    gravel = cv2.resize(skimage.data.gravel(), (w, h), interpolation=cv2.INTER_AREA)
    return cv2.cvtColor(gravel, cv2.COLOR_GRAY2BGR)


def iou(a: tuple[float, ...], b: tuple[float, ...]) -> float:
    """Intersection over union of two (x, y, w, h) boxes."""
    ix = max(0.0, min(a[0] + a[2], b[0] + b[2]) - max(a[0], b[0]))
    iy = max(0.0, min(a[1] + a[3], b[1] + b[3]) - max(a[1], b[1]))
    inter = ix * iy
    return inter / (a[2] * a[3] + b[2] * b[3] - inter)


def _paste(frame: np.ndarray, patch: np.ndarray, x: int, y: int) -> None:
    h, w = patch.shape[:2]
    frame[y : y + h, x : x + w] = patch


def moving_sequence(n: int = 60) -> tuple[list[np.ndarray], list[tuple[int, int, int, int]]]:
    """Object moving on a loop and scaling 1.0 → 1.45 → 1.15; returns frames and ground-truth boxes."""
    bg, tex = _background(), _object_texture()
    frames, boxes = [], []
    for k in range(n):
        t = k / max(1, n - 1)
        size = round(40 * (1.0 + 0.45 * math.sin(math.pi * min(1.0, 1.4 * t)) + 0.15 * t))
        cx = FRAME_W / 2 + 120 * math.sin(2 * math.pi * t)
        cy = FRAME_H / 2 + 70 * math.sin(4 * math.pi * t)
        x, y = round(cx - size / 2), round(cy - size / 2)
        frame = bg.copy()
        _paste(frame, cv2.resize(tex, (size, size), interpolation=cv2.INTER_AREA), x, y)
        frames.append(frame)
        boxes.append((x, y, size, size))
    return frames, boxes


def occlusion_sequence(
    before: int = 20, hidden: int = 10, after: int = 20, jump: int = 40, size: int = 24
) -> tuple[list[np.ndarray], list[tuple[int, int, int, int] | None]]:
    """Object moves right, hides behind an occluder for `hidden` frames, reappears `jump` px further on.

    Ground truth is None while the object is hidden.
    """
    bg, tex = _background(), cv2.resize(_object_texture(), (size, size), interpolation=cv2.INTER_AREA)
    occ_w, occ_h = 3 * size, 3 * size
    frames: list[np.ndarray] = []
    boxes: list[tuple[int, int, int, int] | None] = []
    x, y = 150, 160
    for _ in range(before):
        frame = bg.copy()
        _paste(frame, tex, x, y)
        frames.append(frame)
        boxes.append((x, y, size, size))
        x += 2
    occ_x, occ_y = x + size // 2 - occ_w // 2, y + size // 2 - occ_h // 2
    occluder = _occluder(occ_w, occ_h)
    for _ in range(hidden):
        frame = bg.copy()
        _paste(frame, occluder, occ_x, occ_y)
        frames.append(frame)
        boxes.append(None)
    x += jump
    for _ in range(after):
        frame = bg.copy()
        _paste(frame, occluder, occ_x, occ_y)
        _paste(frame, tex, x, y)
        frames.append(frame)
        boxes.append((x, y, size, size))
        x += 1
    return frames, boxes
