"""Scenes over the real-photo library (runtime/datamaking/library.py, fetched by `dadiff-eval data fetch`).

A drone camera hovers over an aerial texture or photo, drifting, turning and climbing (on request knocked by a
gust: the whole picture jumps 20-40 px a frame and drifts back); the target is a real
cut-out (BGRA) pasted with its alpha, walking away or coming closer (strong scale change); distractors are
other cut-outs of the same split, with the library's own train/test split. The box is computed from the
alpha's outline (alpha > 0.5), as exactly as for the blobs (behind an occluder: leaving out slivers under half
a pixel thick). The scenes are `Scene`s (scene.py); library images are prepared once and kept in a small cache.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from .geometry import place, polygon_area, rotation, visible_box
from .paths import drone_path, fold, smoothstep, wave
from .photos import check_split
from .scene import (
    SUPERSAMPLE,
    Layer,
    Scene,
    frame_size,
    prepare_background,
    random_lighting,
    random_occluder,
    texture_pyramid,
)
from .scene_error import SceneError

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
        """The outline centred on its bounding box, long side 1 (as `Layer.shape`)."""
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
    if len(outline) < 3 or polygon_area(outline) <= 0:
        raise SceneError("a library target's opaque part is too thin to outline")
    levels = texture_pyramid(image)
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


class _CutoutLayer(Layer):
    """A `Layer` drawn from a cut-out with its own alpha (outline: the cut-out's alpha > 0.5 outline).

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
        ss = SUPERSAMPLE  # rasterised at 1/4 px, opened by 1/2 px
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

    def __init__(
        self,
        cutout: _Cutout,
        centre: np.ndarray,
        size: np.ndarray,
        angle: np.ndarray,
        stretch: np.ndarray | None = None,
    ) -> None:
        super().__init__(cutout.shape, list(cutout.pyramid), centre, size, angle, np.ones(len(size), bool))
        self.cutout = cutout
        # Per frame, log(height / width) added to the cut-out's own: a body that is not rigid. 0: as photographed.
        self.stretch = np.zeros(len(size)) if stretch is None else np.asarray(stretch, np.float64)

    def _axes(self, i: int) -> np.ndarray:
        """The cut-out's x and y scale for frame i's stretch (area kept)."""
        half = 0.5 * float(self.stretch[i])
        return np.array([math.exp(-half), math.exp(half)])

    def outline(self, i: int) -> np.ndarray:
        return place(self.shape * self._axes(i), self.centre[i], self.size[i], self.angle[i])

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
        axes = self._axes(i)
        full = self.pyramid[0].shape
        # The coarsest level whose pixels are no larger than the frame's (as `_paste` does), along either axis.
        finest = max(full[:2]) * scale * float(axes.max())
        level = next((p for p in reversed(self.pyramid) if max(p.shape[:2]) >= finest), self.pyramid[0])
        steps = np.array([full[1] / level.shape[1], full[0] / level.shape[0]])  # level px -> level-0 px
        rot = scale * rotation(self.angle[i]) * axes[None, :]
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
        size = near * np.exp(wave(rng, n, rng.uniform(0.05, 0.25), (60, 200), 2))
    return np.clip(size * zoom / zoom[0], 5, 0.9 * height)


def _stretch_path(rng: np.random.Generator, cutout: _Cutout, n: int) -> np.ndarray:
    """Log(height / width) added to a cut-out over the frames, for a body that is not rigid: half of the time
    to an upright walker's shape (height 1.5-4x the width; the library's cut-outs are mostly about as wide as
    tall, people on real footage 2-4x taller than wide), else a mild stretch either way; on top, the sway of a
    gait (width +-3-12 % over 12-40 frames). The lasting part is at most 3.5x the cut-out's own shape."""
    width, height = np.ptp(cutout.outline, axis=0)
    if rng.random() < 0.5:
        base = rng.uniform(math.log(1.5), math.log(4.0)) - math.log(height / width)
    else:
        base = rng.uniform(-0.3, 0.3)
    base = float(np.clip(base, -math.log(3.5), math.log(3.5)))
    return base + wave(rng, n, rng.uniform(0.03, 0.12), (12, 40))


def _cutout_layer(
    rng: np.random.Generator,
    cutout: _Cutout,
    size: np.ndarray,
    width: int,
    height: int,
    n: int,
    stretch: np.ndarray | None = None,
) -> _CutoutLayer:
    """The cut-out moving about the frame (upright, slightly tilting), kept inside it whatever its size."""
    if rng.random() < 0.5:
        cutout = cutout.flipped()
    speed = rng.uniform(0.02, 0.2)
    ux = fold(rng.uniform(0, 1) + wave(rng, n, speed, (40, 200)), 0, 1)
    uy = fold(rng.uniform(0, 1) + wave(rng, n, speed * 0.7, (40, 200)), 0, 1)
    reach = 1.0 if stretch is None else np.exp(np.abs(stretch) / 2)  # the stretched long side over the plain one
    margin = 0.6 * size * reach + 4
    centre = np.stack(
        [margin + ux * np.maximum(width - 2 * margin, 0), margin + uy * np.maximum(height - 2 * margin, 0)], 1
    )
    angle = rng.uniform(-0.15, 0.15) + wave(rng, n, rng.uniform(0, 0.1), (60, 200), 1)
    return _CutoutLayer(cutout, centre, size, angle, stretch)


def _companion_layer(
    rng: np.random.Generator, cutout: _Cutout, target: Layer, height: int, n: int, stretch: np.ndarray | None = None
) -> _CutoutLayer:
    """A cut-out that walks beside the target, 0.9-2.5 of its long side from it in a slowly turning direction,
    as the next person of a group or the next car of a queue does: the look-alike a tracker jumps to."""
    if rng.random() < 0.5:
        cutout = cutout.flipped()
    heading = rng.uniform(0, 2 * np.pi) + wave(rng, n, 0.6, (60, 200))
    reach = target.size * np.clip(rng.uniform(0.9, 2.0) + wave(rng, n, 0.3, (60, 200)), 0.9, 2.5)
    centre = target.centre + reach[:, None] * np.stack([np.cos(heading), np.sin(heading)], 1)
    size = np.clip(target.size * rng.uniform(0.7, 1.3) * np.exp(wave(rng, n, 0.15, (60, 200), 1)), 5, 0.9 * height)
    angle = rng.uniform(-0.15, 0.15) + wave(rng, n, rng.uniform(0, 0.1), (60, 200), 1)
    return _CutoutLayer(cutout, centre, size, angle, stretch)


def _gust(rng: np.random.Generator, target_centre: np.ndarray, width: int, height: int, n: int) -> np.ndarray:
    """Frame-pixel offsets (N, 2) of a gust that knocks the hovering camera once: the whole picture jumps
    60-200 px in 3-5 frames (20-40 px a frame on average, past OTB's 20 px fast-motion mark at the peak)
    and drifts back over 20-60 frames as the drone recovers. The jump pushes the target towards the frame's
    centre and not past a quarter frame beyond it, so that it stays in view (a target near the centre of a
    small frame therefore jumps less)."""
    length = int(rng.integers(3, 6))
    i0 = int(rng.integers(n // 5, max(n // 5 + 1, n - length - 1)))
    recover = int(rng.integers(20, 61))
    towards = np.array([width / 2, height / 2]) - target_centre[i0]
    away = float(np.linalg.norm(towards))
    towards = towards / away if away > 1e-6 else np.array([1.0, 0.0])
    distance = min(rng.uniform(20, 40) * length, away + min(width, height) / 4)  # not out of the other side
    t = np.arange(n, dtype=np.float64)
    knock = smoothstep((t - i0) / length) - smoothstep((t - i0 - length) / recover)
    return distance * knock[:, None] * towards


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


def library_images(library, split: str) -> tuple[list, list]:
    """The library's background and target images of `split`; SceneError when it has none of either."""
    backgrounds, targets = library.images("background", split), library.images("target", split)
    for role, images in (("background", backgrounds), ("target", targets)):
        if not images:
            raise SceneError(f"the real-photo library has no {role} images in split '{split}'")
    return backgrounds, targets


def random_library_scene(
    rng: np.random.Generator,
    library,
    split: str = "train",
    frames: int = 120,
    size: tuple[int, int] = (640, 360),
    companion: bool = False,
    stretch: bool = False,
    gust: bool = False,
) -> Scene:
    """A random scene over the real-photo library: one of its backgrounds of `split` seen by a drone camera,
    a cut-out target of `split` (alpha-pasted, exact box), sometimes an occluder and a look-alike distractor
    (another cut-out of `split`). `companion`: the distractor always, walking beside the target, half the
    time a copy of the target's own cut-out (training; the evaluation's scenes leave it off). `stretch`: the
    target not rigid, often upright like a walker (`_stretch_path`; a companion copy of it stretched alike;
    training, off in the evaluation's scenes). `gust`: the camera knocked once (`_gust`; `dadiff-eval generate
    --gusts`). Each option off, the scenes are those of before it. `library`:
    what `library.open_library()` returns. Deterministic from the generator state and the library's contents."""
    check_split(split)
    width, height = frame_size(size, frames)
    backgrounds, targets = library_images(library, split)
    photos = _usable(backgrounds, "background", rng)
    photo = next(photos)
    diagonal = math.ceil(math.hypot(width, height))
    background = prepare_background(rng, photo, diagonal, diagonal)
    cameras, zoom = drone_path(rng, background.shape, width, height, frames)
    cutouts = _usable(targets, "target", rng)
    target_cutout = next(cutouts)
    sizes = _walk_sizes(rng, zoom, height, frames)
    shape = _stretch_path(rng, target_cutout, frames) if stretch else None  # no draw when off: same scenes
    target = _cutout_layer(rng, target_cutout, sizes, width, height, frames, shape)
    occluder = random_occluder(rng, next(photos, photo), target, frames)  # textured by another background
    distractor = None
    if companion:
        look_alike = target_cutout if rng.random() < 0.5 else next(cutouts, target_cutout)
        alike = shape if look_alike is target_cutout else None  # a copy of the target walks as it does
        distractor = _companion_layer(rng, look_alike, target, height, frames, alike)
    else:
        look_alike = next(cutouts, None) if len(targets) > 1 and rng.random() < 0.3 else None
        if look_alike is not None:
            sizes = target.size * rng.uniform(0.7, 1.3) * np.exp(wave(rng, frames, 0.2, (60, 200), 1))
            distractor = _cutout_layer(rng, look_alike, np.clip(sizes, 5, 0.9 * height), width, height, frames)
    brightness, lights = random_lighting(rng, background, zoom, frames)
    if gust and frames > 12:  # drawn last: the scene is the one without the gust, knocked
        knock = _gust(rng, target.centre, width, height, frames)
        for layer in (target, occluder, distractor):
            if layer is not None:
                layer.centre += knock  # the whole picture moves: what is on the ground and the ground
        cameras[:, :, 2] += knock
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
