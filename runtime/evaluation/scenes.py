"""Night-scene benchmark generator: small objects over real photographs, by day and at night, exact boxes.

A `Scene` is a camera moving and zooming over a photograph (the background), a small object (a textured
patch cut from another photograph of the same split, inside an irregular blob outline) that moves, scales
and turns, and sometimes an occluder passing over the object or a look-alike distractor. Everything is a
closed-form function of the frame index, so `render(i)` is random-access and deterministic. The ground
truth box is computed from the geometry (object outline minus occluder), not from pixels, and is tight
around the visible part of the object.

Two night styles. "real" (`RealNight`, the default of `render_night`) matches the statistics measured on
real night drone video: mostly near black, sodium-orange or white-LED pools of light, saturating lamps and
headlights, the camera's denoising smear and JPEG blocking, motion blur when the camera moves fast.
"classic" (`NightStyle`) is the original camera model (linear light, optical blur, ambient light pools and
lamp glows, Poisson shot noise and Gaussian read noise, low gain, gamma and a colour cast), kept unchanged:
the seeded benchmark in README (`dadiff-eval generate --seed 2026`) is made with it and stays bit for bit.

Two picture sources. "skimage": scikit-image's bundled images only (no download), split once and for all
into `PHOTO_SPLITS` so that a test benchmark never shows a training photo. "library": the real-photo
library (`dadiff-eval data fetch`, runtime/evaluation/library.py): real cut-outs (pasted with their alpha,
boxed from the alpha's outline) over aerial textures and photos seen by a hovering, drifting, turning and
climbing drone camera (`random_library_scene`), with the library's own train/test split.

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
from dataclasses import dataclass, field, replace
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


# ------------------------------------------------------------------------------- real night camera
#
# What real night drone video looks like (measured: /work/shared/notes/real-night-footage.md, UAVDark135 and
# DarkTrack2021): mean luma 11-24, 60-80 % of the pixels below 20, light concentrated in pools and lamps, a few
# saturated lamp pixels, red ~2.7x blue under sodium light, and *little* visible grain (1.3-2.2 in the dark
# areas): night cameras denoise and compress, so detail is lost to smearing and blocking rather than buried in
# noise. The "real" style renders that: a dim sky glow, pools of sodium-orange or white-LED light, lamps and
# headlights that saturate, an auto-exposure towards a low mean level, a square-root tone curve (the one that
# makes shot noise uniform) with a little luma noise, the camera's denoising blur, crushed blacks, the encoder's
# 8x8 blocks (a JPEG round trip at low quality) and motion blur along the camera's motion.

NIGHT_STYLES = ("classic", "real")
NIGHT_KINDS = ("sodium", "led", "mixed")  # the street lighting of a "real" night
_SODIUM = (0.16, 0.5, 1.0)  # linear BGR of high-pressure sodium light
_LED = (1.0, 0.97, 0.9)  # linear BGR of a white LED street light
_HEADLIGHT = (0.9, 0.95, 1.0)
_TAIL_LIGHT = (0.05, 0.08, 1.0)
_SATURATION = {"sodium": (0.15, 0.5), "led": (0.4, 0.8), "mixed": (0.3, 0.7)}  # sodium light is near-monochrome
_SKY_GLOW = {"sodium": (0.28, 0.55, 1.0), "led": (1.0, 0.97, 0.92), "mixed": (0.5, 0.7, 1.0)}
_MAP_STEP = 8  # light-pool maps are computed at 1/8 resolution (they are smooth) and upsampled
_MAX_BLUR_TAPS = 10  # motion blur: line kernels of at most 10 px, longer blurs as sums of shifted copies
_LUMA = np.array([0.114, 0.587, 0.299], np.float32)  # BGR weights of OpenCV's BGR2GRAY


@functools.lru_cache(maxsize=1)
def _normal_bytes() -> np.ndarray:
    """256 normal quantiles (1 x 256 float32): a uint8 random image through cv2.LUT is a cheap normal image."""
    dist = statistics.NormalDist()
    table = np.array([dist.inv_cdf((j + 0.5) / 256) for j in range(256)], np.float32)
    return (table / table.std()).reshape(1, 256)


@dataclass(frozen=True, eq=False)
class FrameLights:
    """The real-style lights seen in one frame: `pools` (ceil(H/8), ceil(W/8), 3) float32 illumination added to
    the sky glow (1 = a street light's pool centre), `lamps` (L, 7): x, y, radius, gain, B, G, R (light sources
    added after exposure; gain >= 1 saturates the centre)."""

    pools: np.ndarray
    lamps: np.ndarray


def _gaussians(centres: np.ndarray, out: np.ndarray, step: float) -> None:
    """Add gain * colour * exp(-d^2 / 2 sigma^2) (elliptic when sigma_y given) for each row of `centres`
    (x, y, sigma_x, sigma_y, angle, gain, B, G, R) to the low-resolution map `out` (cell k at (k + 0.5) * step)."""
    gh, gw = out.shape[:2]
    for x, y, sx, sy, angle, gain, *colour in centres:
        reach = 3 * max(sx, sy)
        i0, i1 = max(int((y - reach) / step), 0), min(int((y + reach) / step) + 1, gh)
        j0, j1 = max(int((x - reach) / step), 0), min(int((x + reach) / step) + 1, gw)
        if i1 <= i0 or j1 <= j0:
            continue
        dx = ((np.arange(j0, j1, dtype=np.float32) + 0.5) * step - x)[None, :]
        dy = ((np.arange(i0, i1, dtype=np.float32) + 0.5) * step - y)[:, None]
        c, s = math.cos(angle), math.sin(angle)
        u, v = dx * c + dy * s, dy * c - dx * s
        value = gain * np.exp(-0.5 * ((u / sx) ** 2 + (v / sy) ** 2))
        out[i0:i1, j0:j1] += value[..., None] * np.asarray(colour, np.float32)


@dataclass(frozen=True, eq=False)
class NightLights:
    """The street lights of a "real" night, in the pixel coordinates of one image (a scene's background, fixed
    on the ground, or a single frame): pools of light, lamps, and cars (a pair of headlights with their beam,
    or tail lights) driving at (vx, vy) px per frame."""

    pools: np.ndarray  # (P, 9): x, y, sigma_x, sigma_y, angle, gain, B, G, R
    lamps: np.ndarray  # (L, 7): x, y, radius, gain, B, G, R
    cars: np.ndarray  # (C, 6): x, y, vx, vy, spacing, beam (0: tail lights only)
    width: int
    height: int

    @classmethod
    def random(
        cls, rng: np.random.Generator, kind: str, width: int, height: int, unit: float | None = None
    ) -> NightLights:
        """Random lights of one `kind` (NIGHT_KINDS) over a width x height image; `unit` = the frame's short
        side in this image's pixels (the lights are sized for the frame; default: min(width, height))."""
        if kind not in NIGHT_KINDS:
            raise SceneError(f"unknown night lighting '{kind}'; expected one of {', '.join(NIGHT_KINDS)}")
        unit = float(unit or min(width, height))
        frames_area = width * height / (unit * unit * 16 / 9)
        pools, lamps = [], []
        for _ in range(max(1, int(rng.poisson(rng.uniform(2, 6) * frames_area)))):
            colour = _SODIUM if kind == "sodium" or (kind == "mixed" and rng.random() < 0.5) else _LED
            x, y = rng.uniform(0, width), rng.uniform(0, height)
            sigma = rng.uniform(0.05, 0.14) * unit
            pools.append(
                (x, y, sigma, sigma * rng.uniform(0.6, 1.0), rng.uniform(0, np.pi), rng.uniform(0.4, 1.3), *colour)
            )
            if rng.random() < 0.6:  # the lamp head above the pool
                lamps.append((x, y, rng.uniform(0.004, 0.008) * unit, rng.uniform(2, 40), *colour))
        for _ in range(int(rng.poisson(3 * frames_area))):  # windows, distant lamps, signs
            colour = _SODIUM if kind == "sodium" or rng.random() < 0.3 else _LED
            lamps.append(
                (
                    rng.uniform(0, width),
                    rng.uniform(0, height),
                    rng.uniform(0.002, 0.006) * unit,
                    rng.uniform(0.3, 6),
                    *colour,
                )
            )
        cars = []
        for _ in range(int(rng.poisson(0.8 * frames_area))):
            heading, speed = rng.uniform(0, 2 * np.pi), rng.uniform(0.003, 0.015) * unit
            cars.append(
                (
                    rng.uniform(0, width),
                    rng.uniform(0, height),
                    speed * math.cos(heading),
                    speed * math.sin(heading),
                    rng.uniform(0.012, 0.025) * unit,
                    float(rng.random() < 0.6),
                )
            )
        return cls(
            np.array(pools, np.float64).reshape(-1, 9),
            np.array(lamps, np.float64).reshape(-1, 7),
            np.array(cars, np.float64).reshape(-1, 6),
            int(width),
            int(height),
        )

    def with_pool_at(self, rng: np.random.Generator, kind: str, x: float, y: float, unit: float) -> NightLights:
        """The same lights and one more pool centred near (x, y) (a street light above the target's start)."""
        colour = _SODIUM if kind == "sodium" or (kind == "mixed" and rng.random() < 0.5) else _LED
        sigma = rng.uniform(0.07, 0.14) * unit
        pool = (
            x + rng.normal(0, 0.3 * sigma),
            y + rng.normal(0, 0.3 * sigma),
            sigma,
            sigma,
            0.0,
            rng.uniform(0.6, 1.2),
            *colour,
        )
        return replace(self, pools=np.vstack([self.pools, pool]))

    @functools.cached_property
    def _ground(self) -> np.ndarray:
        out = np.zeros((-(-self.height // _MAP_STEP), -(-self.width // _MAP_STEP), 3), np.float32)
        _gaussians(self.pools, out, _MAP_STEP)
        return out

    def at(self, camera: np.ndarray | None, i: int, width: int, height: int) -> FrameLights:
        """The lights seen in frame i of a width x height camera; `camera` (2 x 3, image to frame, as for
        cv2.warpAffine) or None when this image is the frame."""
        gw, gh = -(-width // _MAP_STEP), -(-height // _MAP_STEP)
        same = camera is None and self._ground.shape[:2] == (gh, gw)
        camera = np.eye(2, 3) if camera is None else camera
        linear = camera[:, :2]
        zoom = math.sqrt(abs(np.linalg.det(linear)))
        if same:
            pools = self._ground.copy()
        else:  # the ground map seen by the camera, at 1/8 resolution both sides
            low = np.hstack([linear, (camera[:, 2] / _MAP_STEP + linear @ (0.5, 0.5) - 0.5)[:, None]])
            pools = cv2.warpAffine(self._ground, low, (gw, gh), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        lamps, beams = [self.lamps], []
        for x, y, vx, vy, spacing, beam in self.cars:
            heading = np.array([vx, vy]) / max(math.hypot(vx, vy), 1e-9)
            across = np.array([-heading[1], heading[0]]) * spacing / 2
            centre = np.array([x, y]) + i * np.array([vx, vy])
            if beam:  # coming: headlights and the road they light
                at, radius, gain, colour = centre + heading * spacing, 0.18, 30.0, _HEADLIGHT
                ahead = at + heading * 2.5 * spacing
                angle = math.atan2(heading[1], heading[0])
                beams.append((*ahead, 2.5 * spacing, 0.9 * spacing, angle, 1.5, *_HEADLIGHT))
            else:  # going: tail lights
                at, radius, gain, colour = centre - heading * spacing, 0.12, 3.0, _TAIL_LIGHT
            lamps.append(np.array([[*(at + side), spacing * radius, gain, *colour] for side in (across, -across)]))
        lamps = np.concatenate(lamps) if len(lamps) > 1 else self.lamps.copy()
        if len(lamps):
            lamps[:, :2] = lamps[:, :2] @ linear.T + camera[:, 2]
            lamps[:, 2] *= zoom
        if beams:
            beams = np.array(beams)
            beams[:, :2] = beams[:, :2] @ linear.T + camera[:, 2]
            beams[:, 2:4] *= zoom
            beams[:, 4] += math.atan2(linear[1, 0], linear[0, 0])
            _gaussians(beams, pools, _MAP_STEP)
        return FrameLights(pools, lamps)


def _add_lamps(image: np.ndarray, lamps: np.ndarray) -> None:
    """Add each lamp (a bright core of `radius` and a wide dim glare) to a linear, exposed image in place."""
    h, w = image.shape[:2]
    for x, y, radius, gain, *colour in lamps:
        radius = max(radius, 0.6)
        reach = 9 * radius + 3
        x0, x1 = max(int(x - reach), 0), min(int(x + reach) + 1, w)
        y0, y1 = max(int(y - reach), 0), min(int(y + reach) + 1, h)
        if x1 <= x0 or y1 <= y0:
            continue
        xs = (np.arange(x0, x1, dtype=np.float32) + 0.5 - x) ** 2
        ys = (np.arange(y0, y1, dtype=np.float32) + 0.5 - y) ** 2
        d2 = ys[:, None] + xs[None, :]
        value = gain * (np.exp(-d2 / (2 * radius**2)) + 0.02 * np.exp(-d2 / (2 * (3 * radius) ** 2)))
        image[y0:y1, x0:x1] += value[..., None] * np.asarray(colour, np.float32)


def _line_kernel(dx: float, dy: float) -> np.ndarray:
    """Normalised anti-aliased line kernel from -(dx, dy)/2 to +(dx, dy)/2."""
    r = int(math.ceil(max(abs(dx), abs(dy)) / 2)) + 1
    kernel = np.zeros((2 * r + 1, 2 * r + 1), np.float32)
    steps = max(int(math.ceil(2 * math.hypot(dx, dy))), 1) + 1
    for t in np.linspace(-0.5, 0.5, steps):
        x, y = r + t * dx, r + t * dy
        x0, y0 = int(math.floor(x)), int(math.floor(y))
        fx, fy = x - x0, y - y0
        kernel[y0, x0] += (1 - fx) * (1 - fy)
        kernel[y0, x0 + 1] += fx * (1 - fy)
        kernel[y0 + 1, x0] += (1 - fx) * fy
        kernel[y0 + 1, x0 + 1] += fx * fy
    return kernel / kernel.sum()


def motion_blur(image: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """Blur along the motion (dx, dy) px during the exposure (a line kernel; long ones in <= 10 px pieces)."""
    length = math.hypot(dx, dy)
    if length < 1.0:
        return image
    pieces = int(math.ceil(length / _MAX_BLUR_TAPS))
    out = cv2.filter2D(image, -1, _line_kernel(dx / pieces, dy / pieces), borderType=cv2.BORDER_REPLICATE)
    if pieces == 1:
        return out
    shifts = [
        (round((k - (pieces - 1) / 2) * dx / pieces), round((k - (pieces - 1) / 2) * dy / pieces))
        for k in range(pieces)
    ]
    pad = max(max(abs(sx), abs(sy)) for sx, sy in shifts)
    padded = cv2.copyMakeBorder(out, pad, pad, pad, pad, cv2.BORDER_REPLICATE)
    h, w = image.shape[:2]
    total = np.zeros_like(out)
    for sx, sy in shifts:
        total += padded[pad - sy : pad - sy + h, pad - sx : pad - sx + w]
    total *= 1 / pieces
    return total


@dataclass(frozen=True)
class RealNight:
    """A night camera as measured on real night drone video: dark, lit in pools, denoised and compressed."""

    kind: str  # NIGHT_KINDS: the street lighting
    luma: float  # auto-exposure target: mean output luma (real night video: 11-24)
    sky: float  # sky glow (ambient light) relative to a street light pool's centre
    saturation: float  # colour left in the scene (night cameras see little colour)
    noise: float  # luma noise std (output levels) before the camera's denoising
    smear: float  # the camera's denoising blur sigma (px)
    crush: float  # output levels crushed to black by the tone curve
    contrast: float  # tone curve exponent after the square root
    quality: int  # the encoder's JPEG quality (blocking)
    shutter: float  # exposure time over frame interval: motion blur length per px of motion

    @classmethod
    def random(cls, rng: np.random.Generator, darkness: float | None = None, kind: str | None = None) -> RealNight:
        """A random real-style night camera; `darkness` in [0, 1] sets the exposure (None: drawn from
        [0.25, 1]: mean luma ~9-30)."""
        if darkness is None:
            darkness = float(rng.uniform(0.25, 1.0))
        if not 0 <= darkness <= 1:
            raise SceneError(f"darkness must be in [0, 1], got {darkness}")
        if kind is None:
            kind = NIGHT_KINDS[int(rng.choice(3, p=(0.45, 0.3, 0.25)))]
        elif kind not in NIGHT_KINDS:
            raise SceneError(f"unknown night lighting '{kind}'; expected one of {', '.join(NIGHT_KINDS)}")
        return cls(
            kind=kind,
            luma=float(44 * (9 / 44) ** darkness * rng.uniform(0.9, 1.1)),
            sky=float(rng.uniform(0.01, 0.05)),
            saturation=float(rng.uniform(*_SATURATION[kind])),
            noise=float(rng.uniform(3.5, 7.0)),
            smear=float(rng.uniform(0.3, 0.8)),
            crush=float(rng.uniform(0, 3)),
            contrast=float(rng.uniform(0.95, 1.2)),
            quality=int(rng.integers(30, 71)),
            shutter=float(rng.uniform(0.4, 1.0)),
        )

    @functools.cached_property
    def _desaturate(self) -> np.ndarray:
        return (self.saturation * np.eye(3) + (1 - self.saturation) * _LUMA[None, :]).astype(np.float32)

    @functools.cached_property
    def _tone(self) -> np.ndarray:
        v = np.clip((np.arange(256) - self.crush) / (255 - self.crush), 0, 1) ** self.contrast
        return np.rint(255 * v).astype(np.uint8)

    def _illumination(self, lights: FrameLights | None, width: int, height: int) -> np.ndarray:
        sky = self.sky * np.asarray(_SKY_GLOW[self.kind], np.float32)
        if lights is None:
            return np.broadcast_to(sky, (-(-height // _MAP_STEP), -(-width // _MAP_STEP), 3)).copy()
        return lights.pools + sky

    def exposure(self, frame: np.ndarray, lights: FrameLights | None = None) -> float:
        """Auto-exposure: the gain that brings this frame's mean output luma to `luma` (within the gain range
        of the camera: a black scene stays dark)."""
        h, w = frame.shape[:2]
        illumination = self._illumination(lights, w, h)
        gh, gw = illumination.shape[:2]
        small = cv2.LUT(cv2.resize(frame, (gw, gh), interpolation=cv2.INTER_AREA), _TO_LINEAR)
        level = 255 * float((np.sqrt(small * illumination) @ _LUMA).mean())
        grey = 255 * math.sqrt(0.01 * float(illumination.mean()))  # the darkest scene the exposure compensates
        target = self.crush + (255 - self.crush) * (self.luma / 255) ** (1 / self.contrast)  # before the tone curve
        return (target / max(level, grey)) ** 2

    def apply(
        self,
        frame: np.ndarray,
        rng: np.random.Generator,
        lights: FrameLights | None = None,
        motion: tuple[float, float] = (0.0, 0.0),
        gain: float | None = None,
    ) -> np.ndarray:
        """Night version of a BGR uint8 day frame. `lights`: what `NightLights.at` gives for this frame;
        `motion`: how far the scene moves in the frame during one frame interval (px); `gain`: the exposure
        (default: auto-exposure on this frame)."""
        h, w = frame.shape[:2]
        illumination = self._illumination(lights, w, h)
        if gain is None:
            gain = self.exposure(frame, lights)
        linear = cv2.LUT(cv2.transform(frame, self._desaturate), _TO_LINEAR)
        linear *= cv2.resize(illumination * np.float32(gain), (w, h), interpolation=cv2.INTER_LINEAR)
        if lights is not None and len(lights.lamps):
            _add_lamps(linear, lights.lamps)
        linear = motion_blur(linear, motion[0] * self.shutter, motion[1] * self.shutter)
        encoded = cv2.sqrt(linear)
        noise = cv2.LUT(rng.integers(0, 256, (h, w), dtype=np.uint8), _normal_bytes())
        encoded = cv2.scaleAdd(cv2.cvtColor(noise, cv2.COLOR_GRAY2BGR), self.noise / 255, encoded)
        image = cv2.convertScaleAbs(cv2.max(encoded, 0.0), alpha=255)
        if self.smear:
            image = cv2.GaussianBlur(image, (0, 0), self.smear)
        image = cv2.LUT(image, self._tone)
        _, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, self.quality])
        return cv2.imdecode(data, cv2.IMREAD_COLOR)


def _random_motion(rng: np.random.Generator) -> tuple[float, float]:
    """A camera shake for a lone frame: none most of the time, sometimes a fast pan (2-24 px per frame)."""
    if rng.random() >= 0.25:
        return 0.0, 0.0
    length, angle = rng.uniform(2, 24), rng.uniform(0, 2 * np.pi)
    return length * math.cos(angle), length * math.sin(angle)


def render_night(
    frame: np.ndarray, rng: np.random.Generator, darkness: float | None = None, style: str = "real"
) -> np.ndarray:
    """A night version of one BGR uint8 frame with a random night camera and random street lights.

    style "real" (default): as real night drone video looks (`RealNight`: dark, lit in pools, saturating lamps,
    denoised and JPEG-blocked, sometimes motion-blurred); "classic": the original camera model (`NightStyle`),
    unchanged, that the seed-2026 benchmark was made with."""
    if not isinstance(frame, np.ndarray) or frame.dtype != np.uint8 or frame.ndim != 3 or frame.shape[2] != 3:
        raise SceneError(f"render_night needs an H x W x 3 uint8 BGR frame, got {getattr(frame, 'shape', frame)}")
    h, w = frame.shape[:2]
    if style == "classic":
        classic = NightStyle.random(rng, darkness)
        return classic.apply(frame, rng, light_maps(_random_lights(rng, w, h), w, h))
    if style != "real":
        raise SceneError(f"unknown night style '{style}'; expected one of {', '.join(NIGHT_STYLES)}")
    camera = RealNight.random(rng, darkness)
    lights = NightLights.random(rng, camera.kind, w, h).at(None, 0, w, h)
    return camera.apply(frame, rng, lights, _random_motion(rng))


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

    def visible_box(self, i: int, occluder: np.ndarray | None, width: int, height: int) -> np.ndarray:
        """Exact (x, y, w, h) of frame i minus the convex `occluder` (see `visible_box`)."""
        return visible_box(self.outline(i), occluder, width, height)


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
        self.boxes = np.array([target.visible_box(i, self._occluder_at(i), width, height) for i in range(self.frames)])
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

    def motion(self, i: int) -> tuple[float, float]:
        """How far (px) the ground under the frame centre moves in the frame from frame i - 1 to frame i
        (frame 0: as from 0 to 1); the "real" night blurs along it."""
        if self.frames < 2:
            return 0.0, 0.0
        a, b = (i - 1, i) if i > 0 else (0, 1)
        centre = np.array(self.size, np.float64) / 2
        world = np.linalg.solve(self.cameras[b][:, :2], centre - self.cameras[b][:, 2])
        before = self.cameras[a][:, :2] @ world + self.cameras[a][:, 2]
        return float(centre[0] - before[0]), float(centre[1] - before[1])

    def night_lights(self, rng: np.random.Generator, kind: str) -> NightLights:
        """Street lights of a "real" night over this scene: fixed on the ground (the background), sized for
        the frame, and most of the time one pool lighting the target where it starts."""
        h, w = self.background.shape[:2]
        linear = self.cameras[0][:, :2]
        unit = min(self.size) / math.sqrt(abs(np.linalg.det(linear)))
        lights = NightLights.random(rng, kind, w, h, unit)
        if rng.random() < 0.6:
            x, y = np.linalg.solve(linear, self.target.centre[0] - self.cameras[0][:, 2])
            lights = lights.with_pool_at(rng, kind, float(x), float(y), unit)
        return lights

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


# ------------------------------------------------------------------------------------- library scenes
#
# Scenes over the real-photo library (runtime/evaluation/library.py, fetched by `dadiff-eval data fetch`): a
# drone camera hovering over an aerial texture or photo, drifting, turning and climbing; the target is a real
# cut-out (BGRA) pasted with its alpha, walking away or coming closer (strong scale change); distractors are
# other cut-outs of the same split. The box is computed from the alpha's outline (alpha > 0.5), as exactly as
# for the blobs (behind an occluder: leaving out slivers under half a pixel thick).

_CUTOUT_SIDE = 400  # cut-outs are kept at most this long (they are drawn up to ~250 px)
_BACKGROUND_SIDE = 1600  # and backgrounds at most this long (a 640 x 360 scene uses ~950-1450 px)
_OUTLINE_SS = 4  # the alpha = 0.5 outline is traced on the alpha upsampled 4x
_LIBRARY_CACHE: dict[tuple, object] = {}  # least recently used first
_LIBRARY_CACHE_BYTES = 256 << 20  # per process (each training data worker has its own)


@dataclass(frozen=True, eq=False)
class _Cutout:
    """A prepared cut-out: premultiplied BGRA pyramid, and the alpha > 0.5 outline in level-0 pixel coordinates
    (pixel (x, y) covers [x, x + 1] x [y, y + 1])."""

    pyramid: tuple[np.ndarray, ...]
    outline: np.ndarray  # (K, 2)

    @property
    def shape(self) -> np.ndarray:
        """The outline centred on its bounding box, long side 1 (as `_Layer.shape`)."""
        low, high = self.outline.min(0), self.outline.max(0)
        return (self.outline - (low + high) / 2) / float(np.max(high - low))

    def flipped(self) -> _Cutout:
        width = self.pyramid[0].shape[1]
        outline = self.outline.copy()
        outline[:, 0] = width - outline[:, 0]
        return _Cutout(tuple(level[:, ::-1].copy() for level in self.pyramid), outline[::-1].copy())


def _prepare_cutout(bgra: np.ndarray) -> _Cutout:
    bgra = np.asarray(bgra)
    if bgra.dtype != np.uint8 or bgra.ndim != 3 or bgra.shape[2] != 4:
        raise SceneError(f"a library target must be an H x W x 4 uint8 BGRA image, got {bgra.dtype} {bgra.shape}")
    scale = _CUTOUT_SIDE / max(bgra.shape[:2])
    premultiplied = bgra.astype(np.float32)
    premultiplied[..., :3] *= premultiplied[..., 3:] / 255
    if scale < 1:
        size = (max(1, round(bgra.shape[1] * scale)), max(1, round(bgra.shape[0] * scale)))
        premultiplied = cv2.resize(premultiplied, size, interpolation=cv2.INTER_AREA)
    alpha = premultiplied[..., 3]
    count, labels, stats, _ = cv2.connectedComponentsWithStats((alpha > 127.5).astype(np.uint8), connectivity=8)
    if count < 2:
        raise SceneError("a library target has no opaque pixel (alpha > 0.5)")
    keep = (labels == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))).astype(np.uint8)
    keep = cv2.dilate(keep, np.ones((5, 5), np.uint8)).astype(np.float32)  # the largest part and its soft edge
    premultiplied *= keep[..., None]
    ys, xs = np.nonzero(premultiplied[..., 3] > 0)
    y0, y1 = max(ys.min() - 2, 0), min(ys.max() + 3, alpha.shape[0])
    x0, x1 = max(xs.min() - 2, 0), min(xs.max() + 3, alpha.shape[1])
    image = np.rint(premultiplied[y0:y1, x0:x1]).astype(np.uint8)
    # Bilinear alpha crosses 0.5 between pixel centres: trace it on a 4x upsampled alpha.
    h, w = image.shape[:2]
    fine = cv2.resize(image[..., 3], (w * _OUTLINE_SS, h * _OUTLINE_SS), interpolation=cv2.INTER_LINEAR)
    fine = cv2.copyMakeBorder((fine > 127).astype(np.uint8), 1, 1, 1, 1, cv2.BORDER_CONSTANT, value=0)
    contours, _ = cv2.findContours(fine, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    contour = max(contours, key=cv2.contourArea)
    contour = cv2.approxPolyDP(contour, 0.7, True).reshape(-1, 2).astype(np.float64) - 1
    outline = (contour + 0.5) / _OUTLINE_SS
    if len(outline) < 3 or _area(outline) <= 0:
        raise SceneError("a library target's opaque part is too thin to outline")
    levels = [image]
    while max(levels[-1].shape[:2]) > 8:
        levels.append(cv2.pyrDown(levels[-1]))
    for level in levels:
        level.flags.writeable = False
    return _Cutout(tuple(levels), outline)


def _nbytes(item) -> int:
    if isinstance(item, _Cutout):
        return sum(level.nbytes for level in item.pyramid)
    return len(item) if isinstance(item, str) else item.nbytes


def _read_library_image(image, role: str) -> _Cutout | np.ndarray:
    try:
        pixels = image.load()
    except ValueError as exc:  # LibraryError: an unreadable file, named
        raise SceneError(str(exc)) from None
    if role == "target":
        return _prepare_cutout(pixels)
    pixels = np.asarray(pixels)
    if pixels.dtype != np.uint8 or pixels.ndim != 3 or pixels.shape[2] != 3:
        raise SceneError(f"a library background must be an H x W x 3 uint8 BGR image, got {pixels.shape}")
    scale = _BACKGROUND_SIDE / max(pixels.shape[:2])
    if scale < 1:
        size = (round(pixels.shape[1] * scale), round(pixels.shape[0] * scale))
        pixels = cv2.resize(pixels, size, interpolation=cv2.INTER_AREA)
    pixels = np.ascontiguousarray(pixels)
    pixels.flags.writeable = False
    return pixels


def _library_load(image, role: str) -> _Cutout | np.ndarray:
    """A library image loaded once (cut-outs prepared, backgrounds at most 1600 px), kept in a small cache
    (an unusable image too: its error)."""
    key = (role, getattr(image, "path", None), image.package, image.source, image.width, image.height)
    cached = _LIBRARY_CACHE.pop(key, None)
    if cached is None:
        try:
            cached = _read_library_image(image, role)
        except SceneError as exc:
            cached = str(exc)
        while _LIBRARY_CACHE and sum(map(_nbytes, _LIBRARY_CACHE.values())) + _nbytes(cached) > _LIBRARY_CACHE_BYTES:
            _LIBRARY_CACHE.pop(next(iter(_LIBRARY_CACHE)))
    _LIBRARY_CACHE[key] = cached
    if isinstance(cached, str):
        raise SceneError(cached)
    return cached


class _CutoutLayer(_Layer):
    """A `_Layer` drawn from a cut-out with its own alpha (outline: the cut-out's alpha > 0.5 outline).

    Its box behind an occluder leaves out slivers thinner than half a pixel (a cut-out's outline is ragged:
    feet or fingers showing by a hair past the occluder would stretch the box far from the visible part)."""

    def visible_box(self, i: int, occluder: np.ndarray | None, width: int, height: int) -> np.ndarray:
        outline = self.outline(i)
        if occluder is None:
            return visible_box(outline, None, width, height)
        x0, y0 = np.maximum(np.floor(outline.min(0)).astype(int), 0)
        x1, y1 = np.minimum(np.ceil(outline.max(0)).astype(int), (width, height))
        if x1 <= x0 or y1 <= y0:
            return np.full(4, np.nan)
        ss = _SS  # rasterised at 1/4 px, opened by 1/2 px
        shown = np.zeros(((y1 - y0) * ss, (x1 - x0) * ss), np.uint8)
        hidden = np.zeros_like(shown)
        for mask, poly in ((shown, outline), (hidden, occluder)):
            cv2.fillPoly(mask, [np.rint(((poly - (x0, y0)) * ss - 0.5) * 16).astype(np.int32)], 255, cv2.LINE_8, 4)
        shown = cv2.morphologyEx(cv2.subtract(shown, hidden), cv2.MORPH_OPEN, np.ones((2, 2), np.uint8))
        ys, xs = np.nonzero(shown)
        if len(xs) == 0:
            return np.full(4, np.nan)
        left, top = x0 + xs.min() / ss, y0 + ys.min() / ss
        return np.array([left, top, x0 + (xs.max() + 1) / ss - left, y0 + (ys.max() + 1) / ss - top])

    def __init__(self, cutout: _Cutout, centre: np.ndarray, size: np.ndarray, angle: np.ndarray) -> None:
        super().__init__(cutout.shape, list(cutout.pyramid), centre, size, angle, np.ones(len(size), bool))
        self.cutout = cutout

    def draw(self, frame: np.ndarray, i: int) -> None:
        if not self.active[i]:
            return
        h, w = frame.shape[:2]
        poly = self.outline(i)
        x0, y0 = np.maximum(np.floor(poly.min(0)).astype(int) - 2, 0)
        x1, y1 = np.minimum(np.ceil(poly.max(0)).astype(int) + 2, (w, h))
        if x1 <= x0 or y1 <= y0:
            return
        base = self.cutout.outline
        long_side = float(np.max(np.ptp(base, axis=0)))
        scale = self.size[i] / long_side  # level-0 px -> frame px
        full = self.pyramid[0].shape
        # The coarsest level whose pixels are no larger than the frame's (as `_paste` does).
        level = next((p for p in reversed(self.pyramid) if max(p.shape[:2]) >= max(full[:2]) * scale), self.pyramid[0])
        steps = np.array([full[1] / level.shape[1], full[0] / level.shape[0]])  # level px -> level-0 px
        rot = scale * _rotation(self.angle[i])
        middle = (base.min(0) + base.max(0)) / 2
        linear = rot * steps[None, :]
        offset = self.centre[i] - (x0, y0) - 0.5 + rot @ (steps * 0.5 - middle)
        warped = cv2.warpAffine(
            level,
            np.hstack([linear, offset[:, None]]),
            (int(x1 - x0), int(y1 - y0)),
            flags=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0,
        )
        warped = warped.astype(np.float32)
        roi = frame[y0:y1, x0:x1]
        roi[:] = np.clip(np.rint(roi * (1 - warped[..., 3:] / 255) + warped[..., :3]), 0, 255).astype(np.uint8)


def _drone_path(rng: np.random.Generator, shape, width: int, height: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """World-to-frame matrices (N, 2, 3) and zoom of a drone camera looking down: it hovers (a slow sway),
    often drifts, sometimes turns (yaw) and sometimes climbs or descends (zoom)."""
    bh, bw = shape[:2]
    t = np.arange(n, dtype=np.float64)

    def ramp(total: float) -> np.ndarray:  # a manoeuvre: 0 before, `total` after, smooth in between
        start = rng.uniform(0, 0.5) * n
        return total * _smoothstep((t - start) / max(rng.uniform(0.3, 0.8) * n, 1))

    climbs = rng.random() < 0.4
    log_zoom = _wave(rng, n, 0.03, (60, 200), 2)
    if climbs:
        log_zoom += ramp(rng.choice([-1, 1]) * math.log(rng.uniform(1.4, 2.2)))
    zoom = np.exp(log_zoom)
    zoom = zoom / zoom.min() * rng.uniform(1.0, 1.2)
    angle = rng.uniform(0, 2 * np.pi) + _wave(rng, n, 0.03, (60, 200), 2)
    if rng.random() < 0.5:
        angle += ramp(rng.choice([-1, 1]) * rng.uniform(0.3, 1.5))
    half = math.hypot(width, height) / (2 * zoom.min())  # the frame stays on the background whatever the yaw
    sway = rng.uniform(2, 10)
    cx = rng.uniform(half, bw - half) + _wave(rng, n, sway, (30, 120))
    cy = rng.uniform(half, bh - half) + _wave(rng, n, sway, (30, 120))
    if rng.random() < 0.6:  # drifting (world px per frame at zoom 1)
        speed, heading = rng.uniform(0.5, 6.0), rng.uniform(0, 2 * np.pi)
        cx, cy = cx + speed * math.cos(heading) * t, cy + speed * math.sin(heading) * t
    cx, cy = _fold(cx, half, bw - half), _fold(cy, half, bh - half)
    cameras = np.zeros((n, 2, 3))
    for i in range(n):
        rot = zoom[i] * _rotation(angle[i])
        cameras[i, :, :2] = rot
        cameras[i, :, 2] = (width / 2, height / 2) - rot @ (cx[i], cy[i])
    return cameras, zoom


def _walk_sizes(rng: np.random.Generator, zoom: np.ndarray, height: int, n: int) -> np.ndarray:
    """Long side (px) over the frames: small (10-40 px) or medium to large (40-200 px); half of the time the
    object walks away or comes closer (x2-x4.5 over the sequence: size ~ 1 / distance), else a mild change."""
    t = np.arange(n, dtype=np.float64)
    near = rng.uniform(10, 40) if rng.random() < 0.5 else rng.uniform(40, 200)
    if n > 1 and rng.random() < 0.5:
        ratio = math.exp(rng.uniform(math.log(2.0), math.log(4.5)))
        far = max(near / ratio, 6.0)
        near = far * ratio
        start, end = (near, far) if rng.random() < 0.5 else (far, near)
        t0, t1 = rng.uniform(0, 0.25) * n, rng.uniform(0.75, 1.0) * n
        progress = np.clip((t - t0) / max(t1 - t0, 1), 0, 1)
        size = 1 / (1 / start + (1 / end - 1 / start) * progress)
    else:
        size = near * np.exp(_wave(rng, n, rng.uniform(0.05, 0.25), (60, 200), 2))
    return np.clip(size * zoom / zoom[0], 5, 0.9 * height)


def _cutout_layer(
    rng: np.random.Generator, cutout: _Cutout, size: np.ndarray, width: int, height: int, n: int
) -> _CutoutLayer:
    """The cut-out moving about the frame (upright, slightly tilting), kept inside it whatever its size."""
    if rng.random() < 0.5:
        cutout = cutout.flipped()
    speed = rng.uniform(0.02, 0.2)
    ux = _fold(rng.uniform(0, 1) + _wave(rng, n, speed, (40, 200)), 0, 1)
    uy = _fold(rng.uniform(0, 1) + _wave(rng, n, speed * 0.7, (40, 200)), 0, 1)
    margin = 0.6 * size + 4
    centre = np.stack(
        [margin + ux * np.maximum(width - 2 * margin, 0), margin + uy * np.maximum(height - 2 * margin, 0)], 1
    )
    angle = rng.uniform(-0.15, 0.15) + _wave(rng, n, rng.uniform(0, 0.1), (60, 200), 1)
    return _CutoutLayer(cutout, centre, size, angle)


def _usable(images: list, role: str, rng: np.random.Generator):
    """The library's images of one role, prepared, in a random order, skipping unusable ones (unreadable, no
    opaque part)."""
    usable = 0
    for k in rng.permutation(len(images)):
        try:
            yield _library_load(images[int(k)], role)
            usable += 1
        except SceneError:
            continue
    if not usable:
        raise SceneError(f"none of the real-photo library's {role} images can be used")


def random_library_scene(
    rng: np.random.Generator,
    library,
    split: str = "train",
    frames: int = 120,
    size: tuple[int, int] = (640, 360),
) -> Scene:
    """A random scene over the real-photo library: one of its backgrounds of `split` seen by a drone camera,
    a cut-out target of `split` (alpha-pasted, exact box), sometimes an occluder and a look-alike distractor
    (another cut-out of `split`). `library`: what `library.open_library()` returns. Deterministic from the
    generator state and the library's contents."""
    _check_split(split)
    width, height = (int(v) for v in size)
    if width < 64 or height < 64:
        raise SceneError(f"frame size must be at least 64 x 64, got {width} x {height}")
    if frames < 1:
        raise SceneError(f"frames must be at least 1, got {frames}")
    backgrounds, targets = library.images("background", split), library.images("target", split)
    for role, images in (("background", backgrounds), ("target", targets)):
        if not images:
            raise SceneError(f"the real-photo library has no {role} images in split '{split}'")
    photos = _usable(backgrounds, "background", rng)
    photo = next(photos)
    diagonal = math.ceil(math.hypot(width, height))
    background = _prepare_background(rng, photo, diagonal, diagonal)
    cameras, zoom = _drone_path(rng, background.shape, width, height, frames)
    cutouts = _usable(targets, "target", rng)
    target = _cutout_layer(rng, next(cutouts), _walk_sizes(rng, zoom, height, frames), width, height, frames)
    occluder = _occluder(rng, next(photos, photo), target, frames)  # textured by another background
    distractor = None
    look_alike = next(cutouts, None) if len(targets) > 1 and rng.random() < 0.3 else None
    if look_alike is not None:
        sizes = target.size * rng.uniform(0.7, 1.3) * np.exp(_wave(rng, frames, 0.2, (60, 200), 1))
        distractor = _cutout_layer(rng, look_alike, np.clip(sizes, 5, 0.9 * height), width, height, frames)
    varying_light = rng.random() < 0.3  # IV
    brightness = np.exp(_wave(rng, frames, rng.uniform(0.25, 0.45), (50, 140), 2)) if varying_light else np.ones(frames)
    lights = _random_lights(rng, background.shape[1], background.shape[0], scale=1 / float(zoom[0]))
    return Scene((width, height), background, cameras, target, occluder, distractor, brightness, lights)


def open_scene_library():
    """The real-photo library (`library.open_library()`), or SceneError when it was never fetched."""
    try:
        from .library import LibraryError, open_library
    except ImportError as exc:
        raise SceneError(f"the real-photo library code cannot be imported ({exc})") from None
    try:
        library = open_library()
    except LibraryError as exc:
        raise SceneError(str(exc).splitlines()[0] if str(exc) else "the real-photo library cannot be read") from None
    if library is None:
        raise SceneError("no real-photo library here: run dadiff-eval data fetch first")
    return library


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


SOURCES = ("skimage", "library")  # where scenes take their pictures from


def _source_and_night(source: str, night: str | None) -> str:
    """Check `source` and `night`; the night style (None: classic for skimage, real for library)."""
    if source not in SOURCES:
        raise SceneError(f"unknown scene source '{source}'; expected one of {', '.join(SOURCES)}")
    if night is None:
        return "classic" if source == "skimage" else "real"
    if night not in NIGHT_STYLES:
        raise SceneError(f"unknown night style '{night}'; expected one of {', '.join(NIGHT_STYLES)}")
    return night


def _night_rng(entropy: list[int], i: int) -> np.random.Generator:
    return np.random.default_rng([*entropy, 1_000_003, i])


class SceneNight:
    """The night over one scene, the same in all its frames: one night camera and, for style "real", street
    lights fixed on the ground and an exposure locked on frame 0. `night(day, i, rng)` is frame i at night
    (`rng`: that frame's noise); random access. `classic`: the classic camera (default: drawn from `rng`)."""

    def __init__(
        self, scene: Scene, rng: np.random.Generator, style: str = "real", classic: NightStyle | None = None
    ) -> None:
        if style not in NIGHT_STYLES:
            raise SceneError(f"unknown night style '{style}'; expected one of {', '.join(NIGHT_STYLES)}")
        self.scene, self.style = scene, style
        if style == "classic":
            self.classic = classic or NightStyle.random(rng)
        else:
            self.real = RealNight.random(rng)
            self.lights = scene.night_lights(rng, self.real.kind)
            self.gain = self.real.exposure(scene.render(0)[0], self._lights(0))

    def _lights(self, i: int) -> FrameLights:
        return self.lights.at(self.scene.cameras[i], i, *self.scene.size)

    def __call__(self, day: np.ndarray, i: int, rng: np.random.Generator) -> np.ndarray:
        if self.style == "classic":
            return self.classic.apply(day, rng, self.scene.lights_at(i))
        return self.real.apply(day, rng, self._lights(i), self.scene.motion(i), self.gain)


def _scene_and_night(
    entropy: list[int], split: str, frames: int, size: tuple[int, int], source: str, night: str, library
) -> tuple[Scene, SceneNight]:
    rng = np.random.default_rng(entropy)
    if source == "skimage":
        scene = Scene.random(rng, load_photos(split), size=size, frames=frames)
    else:
        scene = random_library_scene(rng, library or open_scene_library(), split, frames, size)
    classic = NightStyle.random(rng)  # drawn whatever the style: the seeded sequences stay as they were
    return scene, SceneNight(scene, np.random.default_rng([*entropy, 2_000_003]), night, classic)


def make_sequence(
    seed: int,
    split: str = "test",
    frames: int = 120,
    size: tuple[int, int] = (640, 360),
    *,
    source: str = "skimage",
    night: str | None = None,
    library=None,
) -> SceneSequence:
    """One sequence rendered by day and at night, deterministic from `seed`.

    `source`: "skimage" (blobs textured from scikit-image photos) or "library" (the real-photo library:
    `library`, default `open_scene_library()`); `night`: "classic" or "real" (None: classic for skimage, so
    that seeded sequences stay as they always were, real for library)."""
    _check_split(split)
    style = _source_and_night(source, night)
    entropy = [int(seed)]
    scene, camera = _scene_and_night(entropy, split, frames, size, source, style, library)
    day, nights = [], []
    for i in range(frames):
        frame, _ = scene.render(i)
        day.append(frame)
        nights.append(camera(frame, i, _night_rng(entropy, i)))
    return SceneSequence(f"scene{seed}", day, nights, scene.boxes.copy(), scene.attributes)


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


def _write_sequence(job: tuple) -> tuple[str, tuple[str, ...]]:
    root, name, entropy, split, frames, size, source, night, library = job
    scene, camera = _scene_and_night(entropy, split, frames, size, source, night, library)
    folders = {kind: root / f"{name}_{kind}" for kind in ("day", "night")}
    for folder in folders.values():
        (folder / "img").mkdir(parents=True, exist_ok=True)
    params = [cv2.IMWRITE_JPEG_QUALITY, 92]
    for i in range(frames):
        day, _ = scene.render(i)
        night = camera(day, i, _night_rng(entropy, i))
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
    source: str = "skimage",
    night: str | None = None,
    library=None,
) -> Path:
    """Write an OTB-layout benchmark: `<root>/seqNNN_day/img/0001.jpg...`, `groundtruth_rect.txt`, the same
    for `_night`, `attributes.json` and `benchmark.json`. Sequence k uses seed entropy [seed, k]. `source`,
    `night` and `library` as for `make_sequence`. Returns `root`."""
    _check_split(split)
    night = _source_and_night(source, night)
    if sequences < 1 or frames < 1:
        raise SceneError(f"need at least one sequence and one frame, got {sequences} x {frames}")
    root = Path(root).expanduser()
    if root.exists() and (not root.is_dir() or any(root.iterdir())):
        raise SceneError(f"{root}: exists and is not an empty folder; choose a new --out")
    if source == "library":  # fail early, before anything is written (the workers open their own)
        for role in ("background", "target"):
            if not (library or open_scene_library()).images(role, split):
                raise SceneError(f"the real-photo library has no {role} images in split '{split}'")
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SceneError(f"{root}: cannot create ({exc.strerror or exc})") from None
    if source == "skimage":  # fail early, before any worker starts
        load_photos(split)
    workers = max(1, min(workers or os.cpu_count() or 1, sequences))
    jobs = [
        (root, f"seq{k + 1:03d}", [int(seed), k], split, frames, tuple(size), source, night, library)
        for k in range(sequences)
    ]
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
        "source": source,
        "night": night,
        "sequences": sequences,
        "frames": frames,
    }
    (root / "benchmark.json").write_text(json.dumps({**info, "size": list(size)}, indent=1) + "\n")
    return root
