"""Plane geometry of the generated scenes: object outlines, polygon area and clipping, the exact box of what
an outline shows behind a convex occluder (computed from the geometry, not from pixels), and the overlap (IoU)
of boxes: the benchmark's own definition, which the labellers (fixed camera, detection tracks, HIT-UAV) link
boxes by and the metrics score by."""

from __future__ import annotations

import math

import numpy as np

_VERTICES = 48  # blob outline vertices


def rotation(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s], [s, c]])


def blob(rng: np.random.Generator, aspect: float) -> np.ndarray:
    """Irregular closed outline (K, 2), long axis along x, bounding box long side exactly 1."""
    phi = np.linspace(0, 2 * np.pi, _VERTICES, endpoint=False)
    radius = np.ones_like(phi)
    for k in (2, 3, 4, 5):
        radius += rng.uniform(0, 0.12 / (k - 1)) * np.cos(k * phi + rng.uniform(0, 2 * np.pi))
    pts = np.stack([radius * np.cos(phi), radius * np.sin(phi) / aspect], axis=1)
    pts -= (pts.max(0) + pts.min(0)) / 2
    return pts / np.ptp(pts[:, 0])


def ellipse(aspect: float, vertices: int = 24) -> np.ndarray:
    phi = np.linspace(0, 2 * np.pi, vertices, endpoint=False)
    return np.stack([0.5 * np.cos(phi), 0.5 * np.sin(phi) / aspect], axis=1)


def rectangle(aspect: float) -> np.ndarray:
    h = 0.5 / aspect
    return np.array([[-0.5, -h], [0.5, -h], [0.5, h], [-0.5, h]])


def place(shape: np.ndarray, centre: np.ndarray, size: float, angle: float) -> np.ndarray:
    return centre + size * shape @ rotation(angle).T


def polygon_area(poly: np.ndarray) -> float:
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def _clip_convex(subject: np.ndarray, clip: np.ndarray) -> np.ndarray:
    """Sutherland-Hodgman: `subject` (any simple polygon) intersected with the convex polygon `clip`."""
    e1, e2 = clip[1] - clip[0], clip[2] - clip[1]
    orient = 1.0 if e1[0] * e2[1] - e1[1] * e2[0] >= 0 else -1.0
    out = subject
    for a, b in zip(clip, np.roll(clip, -1, axis=0), strict=True):
        if len(out) == 0:
            break
        edge = b - a
        side = orient * (edge[0] * (out[:, 1] - a[1]) - edge[1] * (out[:, 0] - a[0]))
        nxt, side_n = np.roll(out, -1, axis=0), np.roll(side, -1)
        kept = []
        for p, q, sp, sq in zip(out, nxt, side, side_n, strict=True):
            if sp >= 0:
                kept.append(p)
            if (sp >= 0) != (sq >= 0):
                kept.append(p + (q - p) * (sp / (sp - sq)))
        out = np.array(kept).reshape(-1, 2)
    return out


def _inside_convex(points: np.ndarray, poly: np.ndarray) -> np.ndarray:
    edges = np.roll(poly, -1, axis=0) - poly
    rel = points[:, None, :] - poly[None, :, :]
    cross = edges[None, :, 0] * rel[:, :, 1] - edges[None, :, 1] * rel[:, :, 0]
    return np.all(cross > 0, axis=1) | np.all(cross < 0, axis=1)


def _inside_polygon(points: np.ndarray, poly: np.ndarray) -> np.ndarray:
    a, b = poly, np.roll(poly, -1, axis=0)
    px, py = points[:, None, 0], points[:, None, 1]
    crosses = (a[None, :, 1] > py) != (b[None, :, 1] > py)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_at = a[None, :, 0] + (py - a[None, :, 1]) * (b[None, :, 0] - a[None, :, 0]) / (b[None, :, 1] - a[None, :, 1])
    return np.sum(crosses & (px < x_at), axis=1) % 2 == 1


def _edge_crossings(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """All intersection points of the edges of two closed polygons."""
    a0, a1 = p, np.roll(p, -1, axis=0)
    b0, b1 = q, np.roll(q, -1, axis=0)
    da, db = (a1 - a0)[:, None, :], (b1 - b0)[None, :, :]
    diff = b0[None, :, :] - a0[:, None, :]
    den = da[..., 0] * db[..., 1] - da[..., 1] * db[..., 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (diff[..., 0] * db[..., 1] - diff[..., 1] * db[..., 0]) / den
        u = (diff[..., 0] * da[..., 1] - diff[..., 1] * da[..., 0]) / den
    hit = (den != 0) & (t >= 0) & (t <= 1) & (u >= 0) & (u <= 1)
    rows, cols = np.nonzero(hit)
    return a0[rows] + t[rows, cols, None] * da[rows, 0]


def visible_box(target: np.ndarray, occluder: np.ndarray | None, width: int, height: int) -> np.ndarray:
    """Exact (x, y, w, h) of `target` minus the convex `occluder`, clipped to the frame; NaN if nothing shows."""
    if occluder is None:
        points = target
    else:
        points = np.concatenate(
            [
                target[~_inside_convex(target, occluder)],
                occluder[_inside_polygon(occluder, target)],
                _edge_crossings(target, occluder),
            ]
        )
    if len(points) == 0:
        return np.full(4, np.nan)
    x0, y0 = np.clip(points.min(0), 0, (width, height))
    x1, y1 = np.clip(points.max(0), 0, (width, height))
    if x1 <= x0 or y1 <= y0:
        return np.full(4, np.nan)
    return np.array([x0, y0, x1 - x0, y1 - y0])


def hidden_fraction(target: np.ndarray, occluder: np.ndarray) -> float:
    return polygon_area(_clip_convex(target, occluder)) / max(polygon_area(target), 1e-9)


def as_boxes(boxes: object, what: str = "boxes") -> np.ndarray:
    """(N, 4) float64 array of (x, y, w, h) rows; raises ValueError naming `what` otherwise."""
    array = np.asarray(boxes, dtype=np.float64)
    if array.ndim == 1 and array.size == 0:
        array = array.reshape(0, 4)
    if array.ndim != 2 or array.shape[1] != 4:
        raise ValueError(f"{what} must be an (N, 4) array of x, y, w, h rows, got shape {array.shape}")
    return array


def paired_boxes(gt: object, pred: object) -> tuple[np.ndarray, np.ndarray]:
    """Ground truth and prediction as (N, 4) arrays of one length N > 0; ValueError naming the mismatch."""
    g, p = as_boxes(gt, "ground truth"), as_boxes(pred, "prediction")
    if len(g) != len(p):
        raise ValueError(f"prediction has {len(p)} boxes, ground truth has {len(g)}")
    if len(g) == 0:
        raise ValueError("a sequence needs at least one frame")
    return g, p


def iou(gt: object, pred: object) -> np.ndarray:
    """Per-frame IoU of boxes spanning [x, x+w] x [y, y+h], clipped to [0, 1]; -1 where the GT is invalid."""
    g, p = paired_boxes(gt, pred)
    out = np.full(len(g), -1.0)
    with np.errstate(invalid="ignore"):
        valid = np.sum(g[:, 2:] > 0, axis=1) == 2
    g, p = g[valid], p[valid]
    # over: a finite but huge box (1e308) overflows to inf, giving IoU 0 or NaN (a failure) as it should
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        left = np.maximum(g[:, 0], p[:, 0])
        right = np.minimum(g[:, 0] + g[:, 2], p[:, 0] + p[:, 2])
        top = np.maximum(g[:, 1], p[:, 1])
        bottom = np.minimum(g[:, 1] + g[:, 3], p[:, 1] + p[:, 3])
        inter = np.maximum(0, right - left) * np.maximum(0, bottom - top)
        union = g[:, 2] * g[:, 3] + p[:, 2] * p[:, 3] - inter
        out[valid] = np.maximum(np.minimum(1, inter / union), 0)
    return out


def iou_with_each(box: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """IoU of one box (x, y, w, h) with each row of `boxes`: the benchmark's own IoU, one box against many."""
    return iou(np.broadcast_to(box, boxes.shape), boxes)
