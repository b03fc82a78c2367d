"""One generated scene, by day, with exact boxes: a camera moving and zooming over a photograph (the
background), a small object (a textured patch cut from another photograph, inside an irregular blob outline)
that moves, scales and turns, and sometimes an occluder passing over the object or a look-alike distractor.

Everything is a closed-form function of the frame index, so `Scene.render(i)` is random-access and
deterministic. The ground truth box is computed from the geometry (object outline minus occluder), not from
pixels, and is tight around the visible part of the object. A scene also carries what its night needs: the
classic night's lights fixed on the ground (`lights_at`), the real night's (`night_lights`) and the camera's
motion (`motion`). Library scenes (library_scenes.py) are `Scene`s too, with cut-out layers.

Attributes (per scene, from the geometry): SV, ARC, OCC, FM, CM, LR, IV, SOB; night versions add LAI.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np

from .geometry import blob, ellipse, hidden_fraction, place, rectangle, rotation, visible_box
from .night import Light, NightLights, light_maps, random_lights
from .paths import background_motion, camera_path, fold, smoothstep, wave
from .scene_error import SceneError

# Attribute rules, applied to the exact boxes and the scene parameters.
SV_RATIO = 1.5  # SV: sqrt(area) of some frame vs frame 0 outside [1/1.5, 1.5] (occlusion not counted)
ARC_RATIO = 1.5  # ARC: aspect ratio of some frame vs frame 0 outside [1/1.5, 1.5] (occlusion not counted)
FM_PIXELS = 20.0  # FM: the box centre moves more than 20 px between two frames (OTB / UAV123 rule)
LR_AREA = 25 * 25  # LR: box area below 25 x 25 px (NUT-LR's definition) in at least half of the frames
OCC_FRACTION = 0.25  # OCC: at least a quarter of the object hidden in some frame
CM_PIXELS = 1.0  # CM: the background moves more than 1 px per frame on average
IV_RATIO = 1.5  # IV: global brightness max / min above 1.5
ATTRIBUTE_ORDER = ("SV", "ARC", "OCC", "FM", "CM", "LR", "IV", "SOB", "LAI")

MAX_SIDE = 4096  # largest frame side: a 4096 x 4096 frame is 48 MiB; 100000 x 100000 failed in OpenCV
SUPERSAMPLE = 4  # supersampling of object masks
_MIN_VISIBLE = 0.3  # an occluder never hides more than 70 % of the object


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


def texture_pyramid(patch: np.ndarray) -> list[np.ndarray]:
    """`patch` and its halvings (cv2.pyrDown) down to a long side of at most 8 px."""
    levels = [patch]
    while max(levels[-1].shape[:2]) > 8:
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
    big = np.zeros((rh * SUPERSAMPLE, rw * SUPERSAMPLE), np.uint8)
    pts = np.rint(((poly - (x0, y0)) * SUPERSAMPLE - 0.5) * 16).astype(np.int32)
    cv2.fillPoly(big, [pts], 255, cv2.LINE_8, 4)
    alpha = cv2.resize(big, (rw, rh), interpolation=cv2.INTER_AREA).astype(np.float32)[..., None] / 255
    level = next((p for p in reversed(pyramid) if p.shape[0] >= size), pyramid[0])
    side = level.shape[0]
    rot = rotation(angle) * (size / side)
    offset = np.asarray(centre) - (x0, y0) - 0.5 + rot @ np.full(2, 0.5 - side / 2)
    matrix = np.hstack([rot, offset[:, None]])
    texture = cv2.warpAffine(level, matrix, (rw, rh), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
    roi = frame[y0:y1, x0:x1]
    roi[:] = np.rint(roi * (1 - alpha) + texture * alpha).astype(np.uint8)


# --------------------------------------------------------------------------------------------- scene


@dataclass
class Layer:
    """A textured shape over the frames: outline (unit size), per-frame centre, size and angle."""

    shape: np.ndarray
    pyramid: list[np.ndarray]
    centre: np.ndarray  # (N, 2)
    size: np.ndarray  # (N,)
    angle: np.ndarray  # (N,)
    active: np.ndarray  # (N,) bool

    def outline(self, i: int) -> np.ndarray:
        return place(self.shape, self.centre[i], self.size[i], self.angle[i])

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
        target: Layer,
        occluder: Layer | None,
        distractor: Layer | None,
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
        width, height = frame_size(size, frames)
        names = sorted(photos)
        if len(names) < 2:
            raise SceneError("a scene needs at least two photos (background and object)")
        order = [names[i] for i in rng.permutation(len(names))]
        bg_name, obj_name, occ_name = order[0], order[1], order[2 % len(order)]
        background = prepare_background(rng, photos[bg_name], width, height)
        cameras, zoom = camera_path(rng, background.shape, width, height, frames)
        target = _target(rng, photos[obj_name], zoom, width, height, frames)
        occluder = random_occluder(rng, photos[occ_name], target, frames)
        distractor = _distractor(rng, target, width, height, frames) if rng.random() < 0.25 else None
        brightness, lights = random_lighting(rng, background, zoom, frames)
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
        world = self.on_ground(b, centre)
        before = self.cameras[a][:, :2] @ world + self.cameras[a][:, 2]
        return float(centre[0] - before[0]), float(centre[1] - before[1])

    def on_ground(self, i: int, point: np.ndarray) -> np.ndarray:
        """A point of frame i (x, y) in the background's pixel coordinates (the ground the camera films)."""
        camera = self.cameras[i]
        return np.linalg.solve(camera[:, :2], point - camera[:, 2])

    def ground_unit(self, i: int) -> float:
        """Frame i's short side in background pixels: what lights on the ground are sized by."""
        return min(self.size) / math.sqrt(abs(np.linalg.det(self.cameras[i][:, :2])))

    def night_lights(self, rng: np.random.Generator, kind: str) -> NightLights:
        """Street lights of a "real" night over this scene: fixed on the ground (the background), sized for
        the frame, and most of the time one pool lighting the target where it starts."""
        h, w = self.background.shape[:2]
        unit = self.ground_unit(0)
        lights = NightLights.random(rng, kind, w, h, unit)
        if rng.random() < 0.6:
            x, y = self.on_ground(0, self.target.centre[0])
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
                hidden_fraction(self.target.outline(i), self.occluder.outline(i))
                for i in np.flatnonzero(self.occluder.active)
            ]
            if max(hidden, default=0) >= OCC_FRACTION:
                tags.add("OCC")
        centre = full[:, :2] + full[:, 2:] / 2
        if self.frames > 1 and np.max(np.hypot(*np.diff(centre, axis=0).T)) > FM_PIXELS:
            tags.add("FM")
        if self.frames > 1 and background_motion(self.cameras, width, height) > CM_PIXELS:
            tags.add("CM")
        if np.mean(self.boxes[:, 2] * self.boxes[:, 3] < LR_AREA) >= 0.5:
            tags.add("LR")
        if self.brightness.max() / self.brightness.min() > IV_RATIO:
            tags.add("IV")
        if self.distractor is not None:
            tags.add("SOB")
        return tuple(a for a in ATTRIBUTE_ORDER if a in tags)


def frame_size(size: tuple[int, int], frames: int) -> tuple[int, int]:
    """(width, height) of a scene's frames as ints; SceneError when the size is outside 64..MAX_SIDE a side (checked
    before OpenCV is asked to allocate the frame) or the frame count is below 1."""
    width, height = (int(v) for v in size)
    if width < 64 or height < 64:
        raise SceneError(f"frame size must be at least 64 x 64, got {width} x {height}")
    if width > MAX_SIDE or height > MAX_SIDE:
        raise SceneError(f"frame size must be at most {MAX_SIDE} x {MAX_SIDE}, got {width} x {height}")
    if frames < 1:
        raise SceneError(f"frames must be at least 1, got {frames}")
    return width, height


def random_lighting(
    rng: np.random.Generator, background: np.ndarray, zoom: np.ndarray, frames: int
) -> tuple[np.ndarray, tuple[Light, ...]]:
    """Brightness per frame (varying in 30 % of the scenes: IV) and the classic night's lights on the ground."""
    varying_light = rng.random() < 0.3  # IV
    brightness = np.exp(wave(rng, frames, rng.uniform(0.25, 0.45), (50, 140), 2)) if varying_light else np.ones(frames)
    lights = random_lights(rng, background.shape[1], background.shape[0], scale=1 / float(zoom[0]))
    return brightness, lights


def prepare_background(rng: np.random.Generator, photo: np.ndarray, width: int, height: int) -> np.ndarray:
    """The photo scaled so that it covers the frame at zoom >= 1 with room to pan."""
    scale = max(1.3 * width / photo.shape[1], 1.3 * height / photo.shape[0]) * rng.uniform(1.0, 1.5)
    size = (max(width, round(photo.shape[1] * scale)), max(height, round(photo.shape[0] * scale)))
    interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_CUBIC
    image = cv2.resize(np.asarray(photo), size, interpolation=interp)
    return image[:, ::-1].copy() if rng.random() < 0.5 else image


def _wander(rng: np.random.Generator, start: np.ndarray, speed: float, n: int) -> np.ndarray:
    """An object's free path (N, 2) from `start`: smooth waves, slower along y."""
    return np.stack([start[0] + wave(rng, n, speed, (40, 200)), start[1] + wave(rng, n, speed * 0.7, (40, 200))], 1)


def _fold_inside(path: np.ndarray, margin: float, width: int, height: int) -> np.ndarray:
    """`path` bounced back into the frame, `margin` px from its borders."""
    return np.stack([fold(path[:, 0], margin, width - margin), fold(path[:, 1], margin, height - margin)], 1)


def _object_size(rng: np.random.Generator) -> float:
    """Long side in px: mostly low resolution (< 25 px, NUT-LR), sometimes up to 60 px."""
    return float(rng.uniform(8, 24) if rng.random() < 0.75 else rng.uniform(24, 60))


def _target(rng: np.random.Generator, photo: np.ndarray, zoom: np.ndarray, width: int, height: int, n: int) -> Layer:
    aspect = rng.uniform(1.0, 2.4)
    shape = blob(rng, aspect)
    size0 = _object_size(rng)
    sv = rng.random() < 0.35
    own = np.exp(wave(rng, n, rng.uniform(0.35, 0.6) if sv else rng.uniform(0, 0.12), (60, 200), 2))
    size = np.clip(size0 * zoom / zoom[0] * own, 5, 90)
    turns = rng.random() < 0.4
    angle = rng.uniform(0, np.pi) + wave(rng, n, rng.uniform(0.6, 1.6) if turns else 0.1, (120, 400), 1)
    margin = 0.6 * size.max() + 4
    speed = rng.uniform(15, 120)
    start = rng.uniform((margin, margin), (width - margin, height - margin))
    path = _wander(rng, start, speed, n)
    if n > 12 and rng.random() < 0.3:  # a dash: FM
        i0, length = int(rng.integers(n // 5, n - 6)), int(rng.integers(3, 6))
        towards = np.array([width / 2, height / 2]) - path[i0]
        towards /= max(np.linalg.norm(towards), 1e-6)
        distance = rng.uniform(24, 40) * length / 1.5
        path += distance * towards * smoothstep((np.arange(n) - i0) / length)[:, None]
    centre = _fold_inside(path, margin, width, height)
    texture = texture_pyramid(_texture_patch(rng, photo))
    return Layer(shape, texture, centre, size, angle, np.ones(n, bool))


def random_occluder(rng: np.random.Generator, photo: np.ndarray, target: Layer, n: int) -> Layer | None:
    """An occluder sweeping across the target for a few frames, never hiding more than 70 % of it."""
    if n < 12 or rng.random() >= 0.5:
        return None
    length = int(rng.integers(5, min(15, n - 3) + 1))
    i0 = int(rng.integers(2, n - length))
    frames = np.arange(i0, i0 + length)
    aspect = rng.uniform(1.5, 4.0)
    shape = rectangle(aspect) if rng.random() < 0.5 else ellipse(aspect)
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
    texture = texture_pyramid(_texture_patch(rng, photo))
    for _ in range(16):
        centre[frames] = target.centre[frames] + sweep + offset * across
        layer = Layer(shape, texture, centre.copy(), size, angle, active)
        hidden = max(hidden_fraction(target.outline(i), layer.outline(i)) for i in frames)
        if hidden <= 1 - _MIN_VISIBLE:
            return layer
        offset = offset * 1.25 + 0.1 * occ_size
    return None


def _distractor(rng: np.random.Generator, target: Layer, width: int, height: int, n: int) -> Layer:
    """A look-alike (same texture, own outline and path) that starts away from the target."""
    size = target.size * rng.uniform(0.8, 1.2)
    margin = 0.6 * size.max() + 4
    start = target.centre[0]
    for _ in range(20):
        start = rng.uniform((margin, margin), (width - margin, height - margin))
        if np.linalg.norm(start - target.centre[0]) > 3 * target.size[0] + 10:
            break
    speed = rng.uniform(15, 100)
    path = _wander(rng, start, speed, n)
    centre = _fold_inside(path, margin, width, height)
    angle = rng.uniform(0, np.pi) + wave(rng, n, 0.3, (120, 400), 1)
    return Layer(blob(rng, rng.uniform(1.0, 2.4)), target.pyramid, centre, size, angle, np.ones(n, bool))
