"""Night-scene benchmark generator: small objects over real photographs, by day and at night, exact boxes.

A `Scene` is a camera moving and zooming over a photograph (the background), a small object (a textured
patch cut from another photograph of the same split, inside an irregular blob outline) that moves, scales
and turns, and sometimes an occluder passing over the object or a look-alike distractor. Everything is a
closed-form function of the frame index, so `render(i)` is random-access and deterministic. The ground
truth box is computed from the geometry (object outline minus occluder), not from pixels, and is tight
around the visible part of the object.

`render_night` turns a day frame into a night frame with a simple camera model: linear light, optical
blur, ambient light pools and lamp glows, Poisson shot noise and Gaussian read noise, low gain, gamma and a
colour cast. Photos come from scikit-image's bundled images only (no download), split once and for all
into `PHOTO_SPLITS` so that a test benchmark never shows a training photo.

Attributes (per sequence, from the geometry): SV, ARC, OCC, FM, CM, LR, IV, SOB; night versions add LAI.
"""

from __future__ import annotations

import ctypes
import functools
import json
import math
import multiprocessing
import os
import statistics
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

PHOTO_SPLITS: dict[str, tuple[str, ...]] = {
    "train": (
        "astronaut",
        "brick",
        "camera",
        "coffee",
        "grass",
        "hubble_deep_field",
        "immunohistochemistry",
        "moon",
        "retina",
    ),
    "test": ("chelsea", "coins", "gravel", "motorcycle", "rocket"),
}
# skimage.data function (and index into its tuple result) for names that differ from the function name.
_PHOTO_LOADERS = {"motorcycle": ("stereo_motorcycle", 0)}

# Attribute rules, applied to the exact boxes and the scene parameters.
SV_RATIO = 1.5  # SV: sqrt(area) of some frame vs frame 0 outside [1/1.5, 1.5] (occlusion not counted)
ARC_RATIO = 1.5  # ARC: aspect ratio of some frame vs frame 0 outside [1/1.5, 1.5] (occlusion not counted)
FM_PIXELS = 20.0  # FM: the box centre moves more than 20 px between two frames (OTB / UAV123 rule)
LR_AREA = 25 * 25  # LR: box area below 25 x 25 px (NUT-LR's definition) in at least half of the frames
OCC_FRACTION = 0.25  # OCC: at least a quarter of the object hidden in some frame
CM_PIXELS = 1.0  # CM: the background moves more than 1 px per frame on average
IV_RATIO = 1.5  # IV: global brightness max / min above 1.5
ATTRIBUTE_ORDER = ("SV", "ARC", "OCC", "FM", "CM", "LR", "IV", "SOB", "LAI")

_SS = 4  # supersampling of object masks
_VERTICES = 48  # blob outline vertices
_MIN_VISIBLE = 0.3  # an occluder never hides more than 70 % of the object


class SceneError(ValueError):
    """Bad generator input or a missing photo source (one-line message)."""


# --------------------------------------------------------------------------------------------- photos


@functools.lru_cache(maxsize=4)
def _photos(split: str) -> tuple[tuple[str, np.ndarray], ...]:
    try:
        import skimage.data
    except ImportError:
        raise SceneError("scikit-image is needed for the scene photos: pip install scikit-image") from None
    out = []
    for name in PHOTO_SPLITS[split]:
        func, index = _PHOTO_LOADERS.get(name, (name, None))
        try:
            image = getattr(skimage.data, func)()
        except Exception as exc:  # a missing bundled file surfaces as many different errors
            raise SceneError(f"scikit-image's bundled image '{func}' cannot be loaded ({exc})") from None
        image = np.asarray(image if index is None else image[index])
        if image.ndim == 2:
            image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        else:
            image = cv2.cvtColor(image[:, :, :3], cv2.COLOR_RGB2BGR)
        image = np.ascontiguousarray(image, dtype=np.uint8)
        image.flags.writeable = False
        out.append((name, image))
    return tuple(out)


def load_photos(split: str) -> dict[str, np.ndarray]:
    """The photographs of one split ('train' or 'test') as read-only BGR uint8 arrays, by name."""
    if split not in PHOTO_SPLITS:
        raise SceneError(f"unknown photo split '{split}'; expected one of {', '.join(PHOTO_SPLITS)}")
    return dict(_photos(split))


# ------------------------------------------------------------------------------------------ geometry


def _rotation(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s], [s, c]])


def _blob(rng: np.random.Generator, aspect: float) -> np.ndarray:
    """Irregular closed outline (K, 2), long axis along x, bounding box long side exactly 1."""
    phi = np.linspace(0, 2 * np.pi, _VERTICES, endpoint=False)
    radius = np.ones_like(phi)
    for k in (2, 3, 4, 5):
        radius += rng.uniform(0, 0.12 / (k - 1)) * np.cos(k * phi + rng.uniform(0, 2 * np.pi))
    pts = np.stack([radius * np.cos(phi), radius * np.sin(phi) / aspect], axis=1)
    pts -= (pts.max(0) + pts.min(0)) / 2
    return pts / np.ptp(pts[:, 0])


def _ellipse(aspect: float, vertices: int = 24) -> np.ndarray:
    phi = np.linspace(0, 2 * np.pi, vertices, endpoint=False)
    return np.stack([0.5 * np.cos(phi), 0.5 * np.sin(phi) / aspect], axis=1)


def _rectangle(aspect: float) -> np.ndarray:
    h = 0.5 / aspect
    return np.array([[-0.5, -h], [0.5, -h], [0.5, h], [-0.5, h]])


def _place(shape: np.ndarray, centre: np.ndarray, size: float, angle: float) -> np.ndarray:
    return centre + size * shape @ _rotation(angle).T


def _area(poly: np.ndarray) -> float:
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


def _hidden_fraction(target: np.ndarray, occluder: np.ndarray) -> float:
    return _area(_clip_convex(target, occluder)) / max(_area(target), 1e-9)


# ------------------------------------------------------------------------------------------- motion


def _wave(
    rng: np.random.Generator, n: int, amplitude: float, periods: tuple[float, float], terms: int = 3
) -> np.ndarray:
    """Smooth random signal over n frames, 0 at frame 0, of roughly `amplitude` peak deviation."""
    t = np.arange(n, dtype=np.float64)
    out = np.zeros(n)
    for _ in range(terms):
        period, phase = rng.uniform(*periods), rng.uniform(0, 2 * np.pi)
        out += rng.uniform(0.4, 1.0) * (np.sin(2 * np.pi * t / period + phase) - math.sin(phase))
    return out * (amplitude / terms)


def _fold(values: np.ndarray, low: float, high: float) -> np.ndarray:
    """Reflect values into [low, high] (a bounce at each border)."""
    span = max(high - low, 1e-6)
    m = np.mod(values - low, 2 * span)
    return low + np.where(m > span, 2 * span - m, m)


def _smoothstep(u: np.ndarray) -> np.ndarray:
    u = np.clip(u, 0, 1)
    return u * u * (3 - 2 * u)


# ---------------------------------------------------------------------------------------- textures


def _texture_patch(rng: np.random.Generator, photo: np.ndarray, side: int = 128) -> np.ndarray:
    """The most contrasted of a few random square crops of `photo`, resized to side x side."""
    h, w = photo.shape[:2]
    best, best_std = None, -1.0
    for _ in range(6):
        crop = int(rng.uniform(0.15, 0.4) * min(h, w))
        y, x = int(rng.integers(0, h - crop + 1)), int(rng.integers(0, w - crop + 1))
        patch = photo[y : y + crop, x : x + crop]
        std = float(patch.std())
        if std > best_std:
            best, best_std = patch, std
    return cv2.resize(best, (side, side), interpolation=cv2.INTER_AREA)


def _pyramid(patch: np.ndarray) -> list[np.ndarray]:
    levels = [patch]
    while levels[-1].shape[0] > 8:
        levels.append(cv2.pyrDown(levels[-1]))
    return levels


def _paste(frame: np.ndarray, poly: np.ndarray, pyramid: list[np.ndarray], centre, size: float, angle: float):
    """Composite the texture, scaled to `size` and turned by `angle`, inside outline `poly` (anti-aliased)."""
    h, w = frame.shape[:2]
    x0, y0 = np.maximum(np.floor(poly.min(0)).astype(int) - 1, 0)
    x1, y1 = np.minimum(np.ceil(poly.max(0)).astype(int) + 1, (w, h))
    if x1 <= x0 or y1 <= y0:
        return
    rw, rh = int(x1 - x0), int(y1 - y0)
    big = np.zeros((rh * _SS, rw * _SS), np.uint8)
    pts = np.rint(((poly - (x0, y0)) * _SS - 0.5) * 16).astype(np.int32)
    cv2.fillPoly(big, [pts], 255, cv2.LINE_8, 4)
    alpha = cv2.resize(big, (rw, rh), interpolation=cv2.INTER_AREA).astype(np.float32)[..., None] / 255
    level = next((p for p in reversed(pyramid) if p.shape[0] >= size), pyramid[0])
    side = level.shape[0]
    rot = _rotation(angle) * (size / side)
    offset = np.asarray(centre) - (x0, y0) - 0.5 + rot @ np.full(2, 0.5 - side / 2)
    matrix = np.hstack([rot, offset[:, None]])
    texture = cv2.warpAffine(level, matrix, (rw, rh), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
    roi = frame[y0:y1, x0:x1]
    roi[:] = np.rint(roi * (1 - alpha) + texture * alpha).astype(np.uint8)


# ------------------------------------------------------------------------------------------- lights


@dataclass(frozen=True)
class Light:
    """A street light: a pool of light on the scene (multiplies ambient light) and a glowing lamp (adds)."""

    x: float
    y: float
    pool_sigma: float
    pool_gain: float
    glow_sigma: float
    glow_gain: float
    colour: tuple[float, float, float]  # BGR


_LAMP_COLOURS = ((0.35, 0.7, 1.0), (1.0, 1.0, 1.0), (0.6, 0.85, 1.0), (1.0, 0.92, 0.8))


def _random_lights(rng: np.random.Generator, width: int, height: int, scale: float = 1.0) -> tuple[Light, ...]:
    lights = []
    for _ in range(int(rng.integers(3, 11))):
        colour = _LAMP_COLOURS[int(rng.integers(len(_LAMP_COLOURS)))]
        lights.append(
            Light(
                x=float(rng.uniform(0, width)),
                y=float(rng.uniform(0, height)),
                pool_sigma=float(rng.uniform(0.04, 0.12) * min(width, height)),
                pool_gain=float(rng.uniform(1.5, 6)),
                glow_sigma=float(rng.uniform(1.2, 3.0) * scale),
                glow_gain=float(rng.uniform(1.2, 3.0)),
                colour=colour,
            )
        )
    return tuple(lights)


def light_maps(lights: tuple[Light, ...], width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """(pool, glow) float32 H x W x 3 maps: extra ambient-light factor, and lamp light in output units."""
    pool = np.zeros((height, width, 3), np.float32)
    glow = np.zeros((height, width, 3), np.float32)
    for light in lights:
        colour = np.asarray(light.colour, np.float32)
        for target, sigma, gain, reach, halo in (
            (pool, light.pool_sigma, light.pool_gain, 3.0, 0.0),
            (glow, light.glow_sigma, light.glow_gain, 16.0, 0.25),
        ):
            r = reach * sigma
            x0, x1 = max(int(light.x - r), 0), min(int(light.x + r) + 1, width)
            y0, y1 = max(int(light.y - r), 0), min(int(light.y + r) + 1, height)
            if x1 <= x0 or y1 <= y0:
                continue
            xs = (np.arange(x0, x1, dtype=np.float32) + 0.5 - light.x) ** 2
            ys = (np.arange(y0, y1, dtype=np.float32) + 0.5 - light.y) ** 2
            d2 = ys[:, None] + xs[None, :]
            value = np.exp(-d2 / (2 * sigma**2))
            if halo:
                value += halo * np.exp(-d2 / (2 * (5 * sigma) ** 2))
            target[y0:y1, x0:x1] += (gain * value)[..., None] * colour
    return pool, glow


# ------------------------------------------------------------------------------------ night camera

_LAMBDA_LEVELS = 16  # Poisson table rows at sqrt(lambda) steps of 1/16 (1 MB: stays in cache)
_LAMBDA_TABLE_MAX = 1024.0
_QUANTILES = 1024
_DITHER_BITS = 10
_DITHER = 1 << _DITHER_BITS


@functools.lru_cache(maxsize=1)
def _poisson_table() -> np.ndarray:
    """Inverse CDF of Poisson(lambda) at (j + 0.5)/1024 for lambda = (l/16)^2 up to 1024 (uint16)."""
    levels = int(math.sqrt(_LAMBDA_TABLE_MAX) * _LAMBDA_LEVELS) + 1
    lam = (np.arange(levels) / _LAMBDA_LEVELS) ** 2
    kmax = int(_LAMBDA_TABLE_MAX + 8 * math.sqrt(_LAMBDA_TABLE_MAX) + 16)
    k = np.arange(kmax)
    log_fact = np.concatenate([[0.0], np.cumsum(np.log(np.arange(1, kmax)))])
    u = (np.arange(_QUANTILES) + 0.5) / _QUANTILES
    table = np.zeros((levels, _QUANTILES), np.uint16)
    for row, value in enumerate(lam):
        if value == 0:
            continue
        cdf = np.cumsum(np.exp(-value + k * math.log(value) - log_fact))
        table[row] = np.minimum(np.searchsorted(cdf, u), kmax - 1)
    return table


@functools.lru_cache(maxsize=1)
def _normal_table() -> np.ndarray:
    dist = statistics.NormalDist()
    return np.array([dist.inv_cdf((j + 0.5) / _QUANTILES) for j in range(_QUANTILES)], np.float32)


def _normal(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    return _normal_table()[rng.integers(0, _QUANTILES, shape, dtype=np.int32)]


def poisson(lam: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Poisson samples for a float32 mean image (table inverse CDF; normal approximation above 1024)."""
    table = _poisson_table()
    flat = np.maximum(lam.reshape(-1), 0)
    bits = rng.integers(0, _QUANTILES * _DITHER, flat.size, dtype=np.int32)
    # Row = sqrt(lambda) * 16, randomly rounded up or down so that the mean stays lambda (within 0.001).
    level = np.sqrt(flat)
    level *= _LAMBDA_LEVELS
    level += (bits & (_DITHER - 1)).astype(np.float32) * (1 / _DITHER)
    np.minimum(level, table.shape[0] - 1, out=level)
    index = level.astype(np.int32)
    index *= _QUANTILES
    index += bits >> _DITHER_BITS
    out = np.take(table.reshape(-1), index).astype(np.float32)
    big = np.flatnonzero(flat > _LAMBDA_TABLE_MAX)
    if big.size:
        out[big] = flat[big] + np.sqrt(flat[big]) * _normal(rng, (big.size,))
    return out.reshape(lam.shape)


_TO_LINEAR = ((np.arange(256, dtype=np.float32) / 255) ** 2.2).reshape(1, 256)
_CASTS = ((0.75, 0.9, 1.2), (1.2, 1.0, 0.75), (0.9, 1.1, 0.85), (1.0, 1.0, 1.0))


@dataclass(frozen=True)
class NightStyle:
    """One night camera: how much light reaches the sensor, its noise, gain, tone curve and colour."""

    white_photons: float  # photons a white day pixel yields at ambient light (sets the shot noise)
    brightness: float  # output level of a white day pixel (low gain keeps the image dark)
    read_noise: float  # read noise, in photons
    black_level: float
    gamma: float
    blur: float  # optical blur sigma (px), before noise
    smear: float  # smoothing after noise (the camera's own denoising), sigma px
    colour: np.ndarray = field(repr=False)  # 3 x 3 linear BGR matrix: desaturation and colour cast

    @classmethod
    def random(cls, rng: np.random.Generator, darkness: float | None = None) -> NightStyle:
        """A random night camera; `darkness` in [0, 1] (None: drawn from [0.5, 0.95])."""
        if darkness is None:
            darkness = float(rng.uniform(0.5, 0.95))
        if not 0 <= darkness <= 1:
            raise SceneError(f"darkness must be in [0, 1], got {darkness}")
        saturation = rng.uniform(0.3, 0.8)
        grey = np.full((3, 3), 1 / 3)
        cast = np.asarray(_CASTS[int(rng.integers(len(_CASTS)))]) ** rng.uniform(0.3, 1.0)
        colour = np.diag(cast) @ (saturation * np.eye(3) + (1 - saturation) * grey)
        return cls(
            white_photons=float(10 ** (3 - 1.6 * darkness) * rng.uniform(0.7, 1.4)),
            brightness=float(rng.uniform(0.06, 0.3) * (1 - 0.5 * darkness)),
            read_noise=float(rng.uniform(0.5, 3.0)),
            black_level=float(rng.uniform(0, 0.004)),
            gamma=float(rng.uniform(1.8, 2.6)),
            blur=float(rng.choice([0.0, rng.uniform(0.4, 1.2)])),
            smear=float(rng.choice([0.0, rng.uniform(0.3, 0.7)])),
            colour=colour.astype(np.float32),
        )

    def apply(
        self,
        frame: np.ndarray,
        rng: np.random.Generator,
        lights: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> np.ndarray:
        """Night version of a BGR uint8 day frame; `lights` = (pool, glow) maps of the frame's size."""
        linear = cv2.LUT(frame, _TO_LINEAR)
        if self.blur:
            linear = cv2.GaussianBlur(linear, (0, 0), self.blur)
        linear = cv2.transform(linear, self.colour)
        if lights is not None:
            pool, glow = lights
            linear *= 1 + pool
            linear += glow / self.brightness
        photons = poisson(linear * self.white_photons, rng)
        photons += self.read_noise * _normal(rng, photons.shape)
        out = photons * (self.brightness / self.white_photons) + self.black_level
        if self.smear:
            out = cv2.GaussianBlur(out, (0, 0), self.smear)
        encode = np.rint(255 * (np.arange(4096) / 4095) ** (1 / self.gamma)).astype(np.uint8)
        return encode[np.clip(out * 4095, 0, 4095).astype(np.uint16)]


def render_night(frame: np.ndarray, rng: np.random.Generator, darkness: float | None = None) -> np.ndarray:
    """A night version of one BGR uint8 frame: a random night camera and a few random street lights."""
    if not isinstance(frame, np.ndarray) or frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[2] != 3:
        raise SceneError(f"render_night needs an H x W x 3 uint8 BGR frame, got {getattr(frame, 'shape', frame)}")
    style = NightStyle.random(rng, darkness)
    h, w = frame.shape[:2]
    return style.apply(frame, rng, light_maps(_random_lights(rng, w, h), w, h))


# --------------------------------------------------------------------------------------------- scene


@dataclass
class _Layer:
    """A textured shape over the frames: outline (unit size), per-frame centre, size and angle."""

    shape: np.ndarray
    pyramid: list[np.ndarray]
    centre: np.ndarray  # (N, 2)
    size: np.ndarray  # (N,)
    angle: np.ndarray  # (N,)
    active: np.ndarray  # (N,) bool

    def outline(self, i: int) -> np.ndarray:
        return _place(self.shape, self.centre[i], self.size[i], self.angle[i])

    def draw(self, frame: np.ndarray, i: int) -> None:
        if self.active[i]:
            _paste(frame, self.outline(i), self.pyramid, self.centre[i], self.size[i], self.angle[i])


class Scene:
    """A generated sequence before rendering: camera path, object, occluder, distractor, lights.

    `boxes` (N, 4) holds the exact ground truth of every frame; `attributes` the tags it earns.
    """

    def __init__(
        self,
        size: tuple[int, int],
        background: np.ndarray,
        cameras: np.ndarray,
        target: _Layer,
        occluder: _Layer | None,
        distractor: _Layer | None,
        brightness: np.ndarray,
        lights: tuple[Light, ...],
    ) -> None:
        self.size = size
        self.frames = len(cameras)
        self.background = background
        self.cameras = cameras
        self.target, self.occluder, self.distractor = target, occluder, distractor
        self.brightness = brightness
        self.lights = lights
        width, height = size
        self.boxes = np.array(
            [visible_box(target.outline(i), self._occluder_at(i), width, height) for i in range(self.frames)]
        )
        self.attributes = self._attributes()

    @classmethod
    def random(
        cls,
        rng: np.random.Generator,
        photos: dict[str, np.ndarray],
        size: tuple[int, int] = (640, 360),
        frames: int = 120,
    ) -> Scene:
        """A random scene; the same generator state and photos always give the same scene."""
        width, height = (int(v) for v in size)
        if width < 64 or height < 64:
            raise SceneError(f"frame size must be at least 64 x 64, got {width} x {height}")
        if frames < 1:
            raise SceneError(f"frames must be at least 1, got {frames}")
        names = sorted(photos)
        if len(names) < 2:
            raise SceneError("a scene needs at least two photos (background and object)")
        order = [names[i] for i in rng.permutation(len(names))]
        bg_name, obj_name, occ_name = order[0], order[1], order[2 % len(order)]
        background = _prepare_background(rng, photos[bg_name], width, height)
        cameras, zoom = _camera_path(rng, background.shape, width, height, frames)
        target = _target(rng, photos[obj_name], zoom, width, height, frames)
        occluder = _occluder(rng, photos[occ_name], target, frames)
        distractor = _distractor(rng, target, width, height, frames) if rng.random() < 0.25 else None
        varying_light = rng.random() < 0.3  # IV
        brightness = (
            np.exp(_wave(rng, frames, rng.uniform(0.25, 0.45), (50, 140), 2)) if varying_light else np.ones(frames)
        )
        lights = _random_lights(rng, background.shape[1], background.shape[0], scale=1 / float(zoom[0]))
        return cls((width, height), background, cameras, target, occluder, distractor, brightness, lights)

    def _occluder_at(self, i: int) -> np.ndarray | None:
        if self.occluder is None or not self.occluder.active[i]:
            return None
        return self.occluder.outline(i)

    def render(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Frame i by day (BGR uint8) and its exact box (x, y, w, h) as a float array."""
        if not 0 <= i < self.frames:
            raise IndexError(f"frame {i} out of range 0..{self.frames - 1}")
        width, height = self.size
        frame = cv2.warpAffine(
            self.background, self.cameras[i], (width, height), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101
        )
        for layer in (self.distractor, self.target, self.occluder):
            if layer is not None:
                layer.draw(frame, i)
        if self.brightness[i] != 1:
            frame = cv2.convertScaleAbs(frame, alpha=float(self.brightness[i]))
        return frame, self.boxes[i].copy()

    @functools.cached_property
    def _world_lights(self) -> tuple[np.ndarray, np.ndarray]:
        h, w = self.background.shape[:2]
        return light_maps(self.lights, w, h)

    def lights_at(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """The (pool, glow) light maps seen in frame i (the lamps stay fixed on the ground)."""
        width, height = self.size
        return tuple(
            cv2.warpAffine(m, self.cameras[i], (width, height), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
            for m in self._world_lights
        )

    def _attributes(self) -> tuple[str, ...]:
        width, height = self.size
        full = np.array([visible_box(self.target.outline(i), None, width, height) for i in range(self.frames)])
        tags = set()
        root = np.sqrt(full[:, 2] * full[:, 3])
        if np.any((root / root[0] > SV_RATIO) | (root / root[0] < 1 / SV_RATIO)):
            tags.add("SV")
        aspect = full[:, 2] / full[:, 3]
        if np.any((aspect / aspect[0] > ARC_RATIO) | (aspect / aspect[0] < 1 / ARC_RATIO)):
            tags.add("ARC")
        if self.occluder is not None:
            hidden = [
                _hidden_fraction(self.target.outline(i), self.occluder.outline(i))
                for i in np.flatnonzero(self.occluder.active)
            ]
            if max(hidden, default=0) >= OCC_FRACTION:
                tags.add("OCC")
        centre = full[:, :2] + full[:, 2:] / 2
        if self.frames > 1 and np.max(np.hypot(*np.diff(centre, axis=0).T)) > FM_PIXELS:
            tags.add("FM")
        if self.frames > 1 and _background_motion(self.cameras, width, height) > CM_PIXELS:
            tags.add("CM")
        if np.mean(self.boxes[:, 2] * self.boxes[:, 3] < LR_AREA) >= 0.5:
            tags.add("LR")
        if self.brightness.max() / self.brightness.min() > IV_RATIO:
            tags.add("IV")
        if self.distractor is not None:
            tags.add("SOB")
        return tuple(a for a in ATTRIBUTE_ORDER if a in tags)


def _prepare_background(rng: np.random.Generator, photo: np.ndarray, width: int, height: int) -> np.ndarray:
    """The photo scaled so that it covers the frame at zoom >= 1 with room to pan."""
    scale = max(1.3 * width / photo.shape[1], 1.3 * height / photo.shape[0]) * rng.uniform(1.0, 1.5)
    size = (max(width, round(photo.shape[1] * scale)), max(height, round(photo.shape[0] * scale)))
    interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_CUBIC
    image = cv2.resize(np.asarray(photo), size, interpolation=interp)
    return image[:, ::-1].copy() if rng.random() < 0.5 else image


def _camera_path(rng: np.random.Generator, shape, width: int, height: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """World-to-frame affine matrices (N, 2, 3) and zoom per frame."""
    bh, bw = shape[:2]
    still = rng.random() < 0.25
    zoom = np.exp(_wave(rng, n, 0.0 if still else rng.uniform(0.05, 0.3), (80, 300), 2))
    zoom = zoom / zoom.min() * rng.uniform(1.0, 1.2)
    angle = rng.uniform(-0.2, 0.2) + _wave(rng, n, 0.0 if still else rng.uniform(0, 0.08), (100, 300), 2)
    half_w, half_h = width / (2 * zoom.min()), height / (2 * zoom.min())
    speed = 0.0 if still else rng.uniform(40, 160)
    cx = _fold(rng.uniform(half_w, bw - half_w) + _wave(rng, n, speed, (60, 240)), half_w, bw - half_w)
    cy = _fold(rng.uniform(half_h, bh - half_h) + _wave(rng, n, speed * 0.6, (60, 240)), half_h, bh - half_h)
    cameras = np.zeros((n, 2, 3))
    for i in range(n):
        rot = zoom[i] * _rotation(angle[i])
        cameras[i, :, :2] = rot
        cameras[i, :, 2] = (width / 2, height / 2) - rot @ (cx[i], cy[i])
    return cameras, zoom


def _background_motion(cameras: np.ndarray, width: int, height: int) -> float:
    """Mean per-frame displacement (px) of the frame's corners and centre on the background."""
    pts = np.array([[0, 0], [width, 0], [0, height], [width, height], [width / 2, height / 2]], np.float64)
    moves = []
    for a, b in zip(cameras[:-1], cameras[1:], strict=True):
        world = np.linalg.solve(a[:, :2], (pts - a[:, 2]).T).T
        moves.append(np.max(np.hypot(*((world @ b[:, :2].T + b[:, 2]) - pts).T)))
    return float(np.mean(moves))


def _object_size(rng: np.random.Generator) -> float:
    """Long side in px: mostly low resolution (< 25 px, NUT-LR), sometimes up to 60 px."""
    return float(rng.uniform(8, 24) if rng.random() < 0.75 else rng.uniform(24, 60))


def _target(rng: np.random.Generator, photo: np.ndarray, zoom: np.ndarray, width: int, height: int, n: int) -> _Layer:
    aspect = rng.uniform(1.0, 2.4)
    shape = _blob(rng, aspect)
    size0 = _object_size(rng)
    sv = rng.random() < 0.35
    own = np.exp(_wave(rng, n, rng.uniform(0.35, 0.6) if sv else rng.uniform(0, 0.12), (60, 200), 2))
    size = np.clip(size0 * zoom / zoom[0] * own, 5, 90)
    turns = rng.random() < 0.4
    angle = rng.uniform(0, np.pi) + _wave(rng, n, rng.uniform(0.6, 1.6) if turns else 0.1, (120, 400), 1)
    margin = 0.6 * size.max() + 4
    speed = rng.uniform(15, 120)
    start = rng.uniform((margin, margin), (width - margin, height - margin))
    path = np.stack([start[0] + _wave(rng, n, speed, (40, 200)), start[1] + _wave(rng, n, speed * 0.7, (40, 200))], 1)
    if n > 12 and rng.random() < 0.3:  # a dash: FM
        i0, length = int(rng.integers(n // 5, n - 6)), int(rng.integers(3, 6))
        towards = np.array([width / 2, height / 2]) - path[i0]
        towards /= max(np.linalg.norm(towards), 1e-6)
        distance = rng.uniform(24, 40) * length / 1.5
        path += distance * towards * _smoothstep((np.arange(n) - i0) / length)[:, None]
    centre = np.stack([_fold(path[:, 0], margin, width - margin), _fold(path[:, 1], margin, height - margin)], 1)
    texture = _pyramid(_texture_patch(rng, photo))
    return _Layer(shape, texture, centre, size, angle, np.ones(n, bool))


def _occluder(rng: np.random.Generator, photo: np.ndarray, target: _Layer, n: int) -> _Layer | None:
    """An occluder sweeping across the target for a few frames, never hiding more than 70 % of it."""
    if n < 12 or rng.random() >= 0.5:
        return None
    length = int(rng.integers(5, min(15, n - 3) + 1))
    i0 = int(rng.integers(2, n - length))
    frames = np.arange(i0, i0 + length)
    aspect = rng.uniform(1.5, 4.0)
    shape = _rectangle(aspect) if rng.random() < 0.5 else _ellipse(aspect)
    occ_size = float(target.size[i0] * rng.uniform(1.2, 2.5))
    direction = rng.uniform(0, 2 * np.pi)
    along = np.array([math.cos(direction), math.sin(direction)])
    across = np.array([-along[1], along[0]])
    reach = 0.55 * (target.size[frames].max() + occ_size / aspect)
    sweep = np.linspace(-1, 1, length)[:, None] * reach * along
    offset = rng.uniform(0.0, 0.3) * occ_size
    centre = np.zeros((n, 2))
    active = np.zeros(n, bool)
    active[frames] = True
    angle = np.full(n, direction + np.pi / 2)  # the long side lies across the sweep
    size = np.full(n, occ_size)
    texture = _pyramid(_texture_patch(rng, photo))
    for _ in range(16):
        centre[frames] = target.centre[frames] + sweep + offset * across
        layer = _Layer(shape, texture, centre.copy(), size, angle, active)
        hidden = max(_hidden_fraction(target.outline(i), layer.outline(i)) for i in frames)
        if hidden <= 1 - _MIN_VISIBLE:
            return layer
        offset = offset * 1.25 + 0.1 * occ_size
    return None


def _distractor(rng: np.random.Generator, target: _Layer, width: int, height: int, n: int) -> _Layer:
    """A look-alike (same texture, own outline and path) that starts away from the target."""
    size = target.size * rng.uniform(0.8, 1.2)
    margin = 0.6 * size.max() + 4
    start = target.centre[0]
    for _ in range(20):
        start = rng.uniform((margin, margin), (width - margin, height - margin))
        if np.linalg.norm(start - target.centre[0]) > 3 * target.size[0] + 10:
            break
    speed = rng.uniform(15, 100)
    path = np.stack([start[0] + _wave(rng, n, speed, (40, 200)), start[1] + _wave(rng, n, speed * 0.7, (40, 200))], 1)
    centre = np.stack([_fold(path[:, 0], margin, width - margin), _fold(path[:, 1], margin, height - margin)], 1)
    angle = rng.uniform(0, np.pi) + _wave(rng, n, 0.3, (120, 400), 1)
    return _Layer(_blob(rng, rng.uniform(1.0, 2.4)), target.pyramid, centre, size, angle, np.ones(n, bool))


# ------------------------------------------------------------------------------------------ sequences


@dataclass(frozen=True)
class SceneSequence:
    """A rendered sequence: day and night frames (BGR uint8), exact boxes (N, 4), attributes of the day
    version (`night_attributes` adds LAI)."""

    name: str
    day: list[np.ndarray]
    night: list[np.ndarray]
    boxes: np.ndarray
    attributes: tuple[str, ...]

    @property
    def night_attributes(self) -> tuple[str, ...]:
        return (*self.attributes, "LAI")


def _check_split(split: str) -> None:
    if split not in PHOTO_SPLITS:
        raise SceneError(f"unknown photo split '{split}'; expected one of {', '.join(PHOTO_SPLITS)}")


def _scene_and_style(entropy: list[int], split: str, frames: int, size: tuple[int, int]) -> tuple[Scene, NightStyle]:
    rng = np.random.default_rng(entropy)
    scene = Scene.random(rng, load_photos(split), size=size, frames=frames)
    return scene, NightStyle.random(rng)


def _night_rng(entropy: list[int], i: int) -> np.random.Generator:
    return np.random.default_rng([*entropy, 1_000_003, i])


def make_sequence(
    seed: int, split: str = "test", frames: int = 120, size: tuple[int, int] = (640, 360)
) -> SceneSequence:
    """One sequence rendered by day and at night, deterministic from `seed`."""
    _check_split(split)
    entropy = [int(seed)]
    scene, style = _scene_and_style(entropy, split, frames, size)
    day, night = [], []
    for i in range(frames):
        frame, _ = scene.render(i)
        day.append(frame)
        night.append(style.apply(frame, _night_rng(entropy, i), scene.lights_at(i)))
    return SceneSequence(f"scene{seed}", day, night, scene.boxes.copy(), scene.attributes)


def _write_boxes(path: Path, boxes: np.ndarray) -> None:
    path.write_text("".join(",".join(f"{v:.3f}" for v in row) + "\n" for row in boxes))


def _tune_worker() -> None:
    """Set up a generator worker process: one OpenCV thread each, and glibc told to keep freed memory.

    Each frame allocates and frees some 50 MB of temporaries; by default glibc hands that back to the
    system and takes the page faults again on the next frame (a third of the CPU time). Only ever called
    in the worker processes that `write_benchmark` starts.
    """
    cv2.setNumThreads(1)
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(-1, 1 << 30)  # M_TRIM_THRESHOLD
        libc.mallopt(-3, 32 << 20)  # M_MMAP_THRESHOLD (glibc's maximum)
    except (OSError, AttributeError):
        pass  # not glibc: only slower


def _write_sequence(job: tuple[Path, str, list[int], str, int, tuple[int, int]]) -> tuple[str, tuple[str, ...]]:
    root, name, entropy, split, frames, size = job
    scene, style = _scene_and_style(entropy, split, frames, size)
    folders = {kind: root / f"{name}_{kind}" for kind in ("day", "night")}
    for folder in folders.values():
        (folder / "img").mkdir(parents=True, exist_ok=True)
    params = [cv2.IMWRITE_JPEG_QUALITY, 92]
    for i in range(frames):
        day, _ = scene.render(i)
        night = style.apply(day, _night_rng(entropy, i), scene.lights_at(i))
        for kind, image in (("day", day), ("night", night)):
            if not cv2.imwrite(str(folders[kind] / "img" / f"{i + 1:04d}.jpg"), image, params):
                raise SceneError(f"{folders[kind] / 'img'}: cannot write frames")
    for folder in folders.values():
        _write_boxes(folder / "groundtruth_rect.txt", scene.boxes)
    return name, scene.attributes


def write_benchmark(
    root: str | Path,
    sequences: int,
    frames: int,
    seed: int,
    split: str = "test",
    *,
    size: tuple[int, int] = (640, 360),
    workers: int | None = None,
) -> Path:
    """Write an OTB-layout benchmark: `<root>/seqNNN_day/img/0001.jpg...`, `groundtruth_rect.txt`, the same
    for `_night`, and `attributes.json`. Sequence k uses seed entropy [seed, k]. Returns `root`."""
    _check_split(split)
    if sequences < 1 or frames < 1:
        raise SceneError(f"need at least one sequence and one frame, got {sequences} x {frames}")
    root = Path(root).expanduser()
    if root.exists() and (not root.is_dir() or any(root.iterdir())):
        raise SceneError(f"{root}: exists and is not an empty folder; choose a new --out")
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SceneError(f"{root}: cannot create ({exc.strerror or exc})") from None
    load_photos(split)  # fail early, before any worker starts
    workers = max(1, min(workers or os.cpu_count() or 1, sequences))
    jobs = [(root, f"seq{k + 1:03d}", [int(seed), k], split, frames, tuple(size)) for k in range(sequences)]
    if workers == 1:
        results = [_write_sequence(job) for job in jobs]
    else:
        spawn = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(workers, mp_context=spawn, initializer=_tune_worker) as pool:
            results = list(pool.map(_write_sequence, jobs))
    table: dict[str, list[str]] = {}
    for name, attributes in results:
        table[f"{name}_day"] = list(attributes)
        table[f"{name}_night"] = [*attributes, "LAI"]
    lines = ",\n".join(f" {json.dumps(k)}: {json.dumps(v)}" for k, v in table.items())
    (root / "attributes.json").write_text("{\n" + lines + "\n}\n")
    info = {
        "generator": "dadiff.runtime.scenes",
        "seed": seed,
        "split": split,
        "sequences": sequences,
        "frames": frames,
    }
    (root / "benchmark.json").write_text(json.dumps({**info, "size": list(size)}, indent=1) + "\n")
    return root
