"""Smooth random motion over the frames of a scene: signals (waves, folds, smooth steps) and the camera paths
built from them (a panning, zooming camera over a photo; a drone camera looking down)."""

from __future__ import annotations

import math

import numpy as np

from .geometry import rotation


def wave(
    rng: np.random.Generator, n: int, amplitude: float, periods: tuple[float, float], terms: int = 3
) -> np.ndarray:
    """Smooth random signal over n frames, 0 at frame 0, of roughly `amplitude` peak deviation."""
    t = np.arange(n, dtype=np.float64)
    out = np.zeros(n)
    for _ in range(terms):
        period, phase = rng.uniform(*periods), rng.uniform(0, 2 * np.pi)
        out += rng.uniform(0.4, 1.0) * (np.sin(2 * np.pi * t / period + phase) - math.sin(phase))
    return out * (amplitude / terms)


def fold(values: np.ndarray, low: float, high: float) -> np.ndarray:
    """Reflect values into [low, high] (a bounce at each border)."""
    span = max(high - low, 1e-6)
    m = np.mod(values - low, 2 * span)
    return low + np.where(m > span, 2 * span - m, m)


def smoothstep(u: np.ndarray) -> np.ndarray:
    u = np.clip(u, 0, 1)
    return u * u * (3 - 2 * u)


def _cameras(zoom, angle, cx, cy, width: int, height: int) -> np.ndarray:
    """World-to-frame affine matrices (N, 2, 3) of a camera zoomed by `zoom`, turned by `angle`, centred on the
    world point (cx, cy) in each frame."""
    cameras = np.zeros((len(zoom), 2, 3))
    for i in range(len(zoom)):
        rot = zoom[i] * rotation(angle[i])
        cameras[i, :, :2] = rot
        cameras[i, :, 2] = (width / 2, height / 2) - rot @ (cx[i], cy[i])
    return cameras


def camera_path(rng: np.random.Generator, shape, width: int, height: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """World-to-frame affine matrices (N, 2, 3) and zoom per frame."""
    bh, bw = shape[:2]
    still = rng.random() < 0.25
    zoom = np.exp(wave(rng, n, 0.0 if still else rng.uniform(0.05, 0.3), (80, 300), 2))
    zoom = zoom / zoom.min() * rng.uniform(1.0, 1.2)
    angle = rng.uniform(-0.2, 0.2) + wave(rng, n, 0.0 if still else rng.uniform(0, 0.08), (100, 300), 2)
    half_w, half_h = width / (2 * zoom.min()), height / (2 * zoom.min())
    speed = 0.0 if still else rng.uniform(40, 160)
    cx = fold(rng.uniform(half_w, bw - half_w) + wave(rng, n, speed, (60, 240)), half_w, bw - half_w)
    cy = fold(rng.uniform(half_h, bh - half_h) + wave(rng, n, speed * 0.6, (60, 240)), half_h, bh - half_h)
    return _cameras(zoom, angle, cx, cy, width, height), zoom


def background_motion(cameras: np.ndarray, width: int, height: int) -> float:
    """Mean per-frame displacement (px) of the frame's corners and centre on the background."""
    pts = np.array([[0, 0], [width, 0], [0, height], [width, height], [width / 2, height / 2]], np.float64)
    moves = []
    for a, b in zip(cameras[:-1], cameras[1:], strict=True):
        world = np.linalg.solve(a[:, :2], (pts - a[:, 2]).T).T
        moves.append(np.max(np.hypot(*((world @ b[:, :2].T + b[:, 2]) - pts).T)))
    return float(np.mean(moves))


def drone_path(rng: np.random.Generator, shape, width: int, height: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """World-to-frame matrices (N, 2, 3) and zoom of a drone camera looking down: it hovers (a slow sway),
    often drifts, sometimes turns (yaw) and sometimes climbs or descends (zoom)."""
    bh, bw = shape[:2]
    t = np.arange(n, dtype=np.float64)

    def ramp(total: float) -> np.ndarray:  # a manoeuvre: 0 before, `total` after, smooth in between
        start = rng.uniform(0, 0.5) * n
        return total * smoothstep((t - start) / max(rng.uniform(0.3, 0.8) * n, 1))

    climbs = rng.random() < 0.4
    log_zoom = wave(rng, n, 0.03, (60, 200), 2)
    if climbs:
        log_zoom += ramp(rng.choice([-1, 1]) * math.log(rng.uniform(1.4, 2.2)))
    zoom = np.exp(log_zoom)
    zoom = zoom / zoom.min() * rng.uniform(1.0, 1.2)
    angle = rng.uniform(0, 2 * np.pi) + wave(rng, n, 0.03, (60, 200), 2)
    if rng.random() < 0.5:
        angle += ramp(rng.choice([-1, 1]) * rng.uniform(0.3, 1.5))
    half = math.hypot(width, height) / (2 * zoom.min())  # the frame stays on the background whatever the yaw
    sway = rng.uniform(2, 10)
    cx = rng.uniform(half, bw - half) + wave(rng, n, sway, (30, 120))
    cy = rng.uniform(half, bh - half) + wave(rng, n, sway, (30, 120))
    if rng.random() < 0.6:  # drifting (world px per frame at zoom 1)
        speed, heading = rng.uniform(0.5, 6.0), rng.uniform(0, 2 * np.pi)
        cx, cy = cx + speed * math.cos(heading) * t, cy + speed * math.sin(heading) * t
    cx, cy = fold(cx, half, bw - half), fold(cy, half, bh - half)
    return _cameras(zoom, angle, cx, cy, width, height), zoom
