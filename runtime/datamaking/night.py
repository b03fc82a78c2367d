"""Night versions of day frames, in two styles, with their street lights and noise.

"real" (`RealNight`, the default of `render_night`) matches the statistics measured on real night drone video:
mostly near black, sodium-orange or white-LED pools of light (`NightLights`), saturating lamps and headlights,
the camera's denoising smear and JPEG blocking, motion blur when the camera moves fast. "classic" (`NightStyle`)
is the original camera model (linear light, optical blur, ambient light pools and lamp glows (`Light`), Poisson
shot noise and Gaussian read noise from inverse-CDF tables, low gain, gamma and a colour cast), kept unchanged:
the seeded benchmark s2026 (`dadiff-eval generate --seed 2026`, docs/evaluation.md) is made with it and stays
bit for bit.
"""

from __future__ import annotations

import functools
import math
import statistics
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from .scene_error import SceneError

NIGHT_STYLES = ("classic", "real")
NIGHT_KINDS = ("sodium", "led", "mixed")  # the street lighting of a "real" night
_TO_LINEAR = ((np.arange(256, dtype=np.float32) / 255) ** 2.2).reshape(1, 256)  # uint8 to linear light (cv2.LUT)


def check_night_style(style: str) -> None:
    """SceneError unless `style` is one of `NIGHT_STYLES`."""
    if style not in NIGHT_STYLES:
        raise SceneError(f"unknown night style '{style}'; expected one of {', '.join(NIGHT_STYLES)}")


def _check_kind(kind: str) -> None:
    if kind not in NIGHT_KINDS:
        raise SceneError(f"unknown night lighting '{kind}'; expected one of {', '.join(NIGHT_KINDS)}")


def _check_darkness(darkness: float) -> None:
    if not 0 <= darkness <= 1:
        raise SceneError(f"darkness must be in [0, 1], got {darkness}")


# ---------------------------------------------------------------------------------- classic: lights


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


def random_lights(rng: np.random.Generator, width: int, height: int, scale: float = 1.0) -> tuple[Light, ...]:
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


# --------------------------------------------------------------------------- classic: night camera

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


@functools.lru_cache(maxsize=2)
def _normal_quantiles(count: int) -> np.ndarray:
    """The standard normal's quantiles at (j + 0.5) / count for j < count (float32)."""
    dist = statistics.NormalDist()
    return np.array([dist.inv_cdf((j + 0.5) / count) for j in range(count)], np.float32)


def _normal(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    return _normal_quantiles(_QUANTILES)[rng.integers(0, _QUANTILES, shape, dtype=np.int32)]


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
        _check_darkness(darkness)
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


# ------------------------------------------------------------------------------ real: night camera
#
# What real night drone video looks like (measured: /work/shared/notes/real-night-footage.md, UAVDark135 and
# DarkTrack2021): mean luma 11-24, 60-80 % of the pixels below 20, light concentrated in pools and lamps, a few
# saturated lamp pixels, red ~2.7x blue under sodium light, and *little* visible grain (1.3-2.2 in the dark
# areas): night cameras denoise and compress, so detail is lost to smearing and blocking rather than buried in
# noise. The "real" style renders that: a dim sky glow, pools of sodium-orange or white-LED light, lamps and
# headlights that saturate, an auto-exposure towards a low mean level, a square-root tone curve (the one that
# makes shot noise uniform) with a little luma noise, the camera's denoising blur, crushed blacks, the encoder's
# 8x8 blocks (a JPEG round trip at low quality) and motion blur along the camera's motion.

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
    table = _normal_quantiles(256)
    return (table / table.std()).reshape(1, 256)


@dataclass(frozen=True, eq=False)
class FrameLights:
    """The real-style lights seen in one frame: `pools` (ceil(H/8), ceil(W/8), 3) float32 illumination added to
    the sky glow (1 = a street light's pool centre), `lamps` (L, 7): x, y, radius, gain, B, G, R (light sources
    added after exposure; gain >= 1 saturates the centre)."""

    pools: np.ndarray
    lamps: np.ndarray


def _pool_colour(rng: np.random.Generator, kind: str) -> tuple[float, float, float]:
    """The colour of one street light's pool: sodium, LED, or (kind "mixed") either, at even odds."""
    return _SODIUM if kind == "sodium" or (kind == "mixed" and rng.random() < 0.5) else _LED


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
        _check_kind(kind)
        unit = float(unit or min(width, height))
        frames_area = width * height / (unit * unit * 16 / 9)
        pools, lamps = [], []
        for _ in range(max(1, int(rng.poisson(rng.uniform(2, 6) * frames_area)))):
            colour = _pool_colour(rng, kind)
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
        colour = _pool_colour(rng, kind)
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

    def with_lamp_at(
        self, rng: np.random.Generator, kind: str, x: float, y: float, unit: float, pool: bool
    ) -> NightLights:
        """The same lights and one more saturating lamp head at (x, y), with its pool of light under it when
        `pool` (a street light beside the target's path: the distractor a night tracker most often locks on)."""
        colour = _pool_colour(rng, kind)
        lamp = (x, y, rng.uniform(0.004, 0.008) * unit, rng.uniform(4, 40), *colour)
        lights = replace(self, lamps=np.vstack([self.lamps, lamp]))
        if not pool:
            return lights
        sigma = rng.uniform(0.05, 0.12) * unit
        spot = (x, y, sigma, sigma * rng.uniform(0.6, 1.0), rng.uniform(0, np.pi), rng.uniform(0.4, 1.2), *colour)
        return replace(lights, pools=np.vstack([self.pools, spot]))

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
        _check_darkness(darkness)
        if kind is None:
            kind = NIGHT_KINDS[int(rng.choice(3, p=(0.45, 0.3, 0.25)))]
        else:
            _check_kind(kind)
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
        return classic.apply(frame, rng, light_maps(random_lights(rng, w, h), w, h))
    check_night_style(style)
    camera = RealNight.random(rng, darkness)
    lights = NightLights.random(rng, camera.kind, w, h).at(None, 0, w, h)
    return camera.apply(frame, rng, lights, _random_motion(rng))
