"""The tracker: released SiamBAN pre/post-processing (spec section 8) around any backend, or the released
SiamGAT one (runtime/decode_gat.py) for a model whose metadata says `decoder` siamgat (DaDiff-GAT).

Differences from the released tracker, all switchable through parameters:
- a lost/found state (runtime/lost.py): while lost, box centre and size stay where they were and the
  search region grows;
- when the whole picture jolts (a gust, a quick yaw), the search region moves with it first
  (`motion_compensation`, runtime/motion.py);
- a box that stands still on the ground around it after moving (a lock on a post or a lamp) is 'uncertain',
  not 'tracking' (`still_frames`, runtime/still.py);
- so is a box whose colours have left the start box's (a lock on another walker after a crossing,
  `swap_frames`, runtime/swap.py);
- with `colour_prior` (off by default) the cell is picked with a weight for the start box's colours against
  its surroundings' (runtime/colour_prior.py);
- plausibility: the size changes by at most `max_scale_step` per frame and stays within `max_scale_change`
  (scale) and `max_aspect_change` (aspect) of the initial box; a box held at those limits or covering more
  than `max_frame_cover` of the frame is never 'tracking'; tracking/uncertain follow a smoothed confidence
  with hysteresis.
`lost_score=0` turns all of this off and gives the released behaviour exactly.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dadiff.models import ModelNotFoundError, resolve

from .backend import Backend
from .colour_prior import ColourPrior
from .config import Params, parse_geometry, resolve_params
from .crop import context_side, crop_side, mean_colour, subwindow
from .decode import Decoder, Detection
from .decode_gat import GatDecoder, template_roi
from .errors import InputError, ModelError
from .frames import as_image, to_blob
from .lost import LOST, LostMonitor
from .motion import PictureMotion
from .onnx_backend import OnnxBackend
from .still import StillCheck
from .swap import SwapCheck


@dataclass(frozen=True)
class TrackResult:
    """One frame's output. `box` is (x, y, w, h) in frame pixels; `score` the raw foreground
    probability of the chosen cell (what evaluation compares); `state` is decided on `confidence`, the
    smoothed score, zero for an implausible box (see LostMonitor); `latency` seconds per stage
    (crop, search, post, total)."""

    box: tuple[float, float, float, float]
    score: float
    state: str
    latency: dict[str, float] = field(default_factory=dict)
    confidence: float | None = None


def check_box(box: Sequence[float], width: int, height: int) -> tuple[float, float, float, float]:
    """(x, y, w, h) as floats, or InputError naming why this box names no target in a width x height frame."""
    if isinstance(box, str | bytes | Mapping):  # "1234" unpacked as four digits, a dict as its keys
        raise InputError(f"init box must be four numbers (x, y, w, h), got {box!r}")
    try:
        x, y, w, h = (float(v) for v in box)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"init box must be four numbers (x, y, w, h), got {box!r}") from None
    if not all(math.isfinite(v) for v in (x, y, w, h)):
        raise InputError(f"init box must be finite, got {box!r}")
    if w <= 0 or h <= 0:
        raise InputError(f"init box has zero or negative size (w={w:g}, h={h:g})")
    if w < MIN_BOX_SIDE or h < MIN_BOX_SIDE:  # smaller (1e-300): a context side of 0, a ZeroDivisionError
        raise InputError(f"init box is under {MIN_BOX_SIDE:g} px (w={w:g}, h={h:g})")
    if x >= width or y >= height or x + w <= 0 or y + h <= 0:
        raise InputError(f"init box ({x:g}, {y:g}, {w:g}, {h:g}) lies outside the {width}x{height} frame")
    if w > MAX_BOX_FRAMES * width or h > MAX_BOX_FRAMES * height:  # 1e300 overflows the crop arithmetic
        raise InputError(f"init box ({x:g}, {y:g}, {w:g}, {h:g}) is more than {MAX_BOX_FRAMES}x the "
                         f"{width}x{height} frame")
    return x, y, w, h


MIN_BOX_SIDE = 0.1  # px: a box side smaller than a tenth of a pixel names no target
MAX_BOX_FRAMES = 4  # an init box may reach past the frame's edges, not be many frames wide
_TINY = 1e-9  # a non-positive proposed side counts as the largest shrink


def _reach(offset: float, slope: float, bound: float) -> float:
    """Largest t >= 0 with |offset + t·slope| <= bound, or with it no worse where already outside."""
    if slope > 0:
        return max(0.0, (bound - offset) / slope)
    if slope < 0:
        return max(0.0, (-bound - offset) / slope)
    return math.inf


def bound_size(
    size: tuple[float, float], previous: tuple[float, float], start: tuple[float, float], p: Params
) -> tuple[float, float, bool]:
    """The proposed (w, h) limited to what the target could plausibly have become since the last frame,
    and whether the bounds relative to the initial box held it back.

    Width and height each change by at most `max_scale_step`; then the box moves from the previous one
    towards that, in log space, only as far as sqrt(area) stays within `max_scale_change` and w/h within
    `max_aspect_change` of the initial box (both sets are convex and hold the previous box, so both
    bounds hold). The network's box is low-passed by lr but still drifts: this stops the drift at a size,
    and a network that keeps pushing against that limit is not to be trusted (the flag).
    """
    step = math.log(p.max_scale_step)
    u = min(max(math.log(max(size[0], _TINY) / previous[0]), -step), step)
    v = min(max(math.log(max(size[1], _TINY) / previous[1]), -step), step)
    log_prev = (math.log(previous[0]), math.log(previous[1]))
    log_start = (math.log(start[0]), math.log(start[1]))
    scale = (log_prev[0] + log_prev[1] - log_start[0] - log_start[1]) / 2
    aspect = (log_prev[0] - log_prev[1]) - (log_start[0] - log_start[1])
    t = min(_reach(scale, (u + v) / 2, math.log(p.max_scale_change)),
            _reach(aspect, u - v, math.log(p.max_aspect_change)))
    held = t < 1.0
    t = min(t, 1.0)
    return previous[0] * math.exp(t * u), previous[1] * math.exp(t * v), held


def _check_shift(shift: object, limit: float) -> tuple[float, float]:
    """`look`'s (dx, dy) in crop pixels: two finite numbers, at most the search crop's side each way."""
    try:
        dx, dy = (float(v) for v in shift)  # type: ignore[union-attr]
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"shift must be two numbers (dx, dy) in crop pixels, got {shift!r}") from None
    if not (math.isfinite(dx) and math.isfinite(dy)) or max(abs(dx), abs(dy)) > limit:
        raise InputError(f"shift must be finite and within ±{limit:g} crop pixels, got {shift!r}")
    return dx, dy


def covers_frame(size: tuple[float, float], width: int, height: int, share: float) -> bool:
    """Whether a box of this size covers more than `share` of the frame: no target the tracker was
    given at its usual scale becomes that, so the box has drifted onto the background."""
    return size[0] * size[1] > share * width * height


class Tracker:
    """Single-object tracker. `init` once per target (or again to re-target), then `update` per frame."""

    def __init__(
        self,
        backend: Backend,
        *,
        preset: str | None = None,
        overrides: Mapping[str, object] | None = None,
    ) -> None:
        self.backend = backend
        source = str(getattr(backend, "name", type(backend).__name__))
        meta = dict(backend.meta)
        self.geometry = parse_geometry(meta, source)
        self.params: Params = resolve_params(meta, source, preset, overrides)
        g = self.geometry
        self._gat = g.decoder == "siamgat"
        self._decode = (GatDecoder(g.score_size, g.stride, g.point_origin, g.exemplar_size, g.region_s, g.region_l)
                        if self._gat else Decoder(g.score_size, g.stride, g.point_origin))
        self._monitor = LostMonitor(self.params)
        compensate = self.params.motion_compensation > 0 and not self.params.released
        self._motion = PictureMotion(self.params.motion_compensation) if compensate else None
        judge_still = self.params.still_frames > 0 and not self.params.released
        self._still = StillCheck(self.params.still_frames, self.params.still_travel) if judge_still else None
        judge_swap = self.params.swap_frames > 0 and not self.params.released
        self._swap = SwapCheck(self.params.swap_frames, self.params.swap_distance) if judge_swap else None
        use_prior = self.params.colour_prior > 0 and not self.params.released and not self._gat
        self._prior = ColourPrior() if use_prior else None
        self._feeds: dict[str, np.ndarray] | None = None
        self._centre = (0.0, 0.0)
        self._size = (0.0, 0.0)
        self._start = (1.0, 1.0)
        self._fill: tuple[float, ...] = ()
        self._frame_size: tuple[int, ...] = ()

    @classmethod
    def load(
        cls,
        model: str | Path | None = None,
        *,
        provider: str | None = None,
        threads: int | None = None,
        preset: str | None = None,
        overrides: Mapping[str, object] | None = None,
    ) -> Tracker:
        """Tracker on onnxruntime for a model folder (or an .onnx in it), a shipped name, or the default."""
        if model is not None and not isinstance(model, str | os.PathLike):
            raise InputError(f"model must be a folder, an .onnx file or a shipped model's name, got {model!r}")
        try:
            folder = resolve(model)
        except ModelNotFoundError as exc:
            raise ModelError(str(exc)) from None
        backend = OnnxBackend(folder, provider=provider, threads=threads)
        return cls(backend, preset=preset, overrides=overrides)

    @property
    def state(self) -> str:
        """State after the last update ('tracking' right after init)."""
        return self._monitor.state

    def _context_side(self) -> float:
        return context_side(*self._size, self.geometry.context_amount)

    def _patch(self, image: np.ndarray, out_size: int, side: float) -> np.ndarray:
        """The uint8 crop of `side` frame pixels around the current centre, resized to `out_size`."""
        return subwindow(image, self._centre, out_size, crop_side(side), self._fill)

    def _crop(self, image: np.ndarray, out_size: int, side: float, out: np.ndarray | None = None) -> np.ndarray:
        return to_blob(self._patch(image, out_size, side), self.geometry.channel_order, out)

    def init(self, frame: np.ndarray, box: Sequence[float]) -> None:
        """Start tracking `box` = (x, y, w, h) in `frame`; runs the template graph once.

        As in the released tracker the centre is x + (w − 1)/2 (spec 8.1).
        """
        image = as_image(frame)
        x, y, w, h = check_box(box, image.shape[1], image.shape[0])
        self._centre = (x + (w - 1) / 2, y + (h - 1) / 2)
        self._size = (w, h)
        self._start = (max(w, self.geometry.min_size), max(h, self.geometry.min_size))  # as the first clip makes it
        self._fill = mean_colour(image)
        self._frame_size = image.shape[:2]
        side = self._context_side()
        z = self._crop(image, self.geometry.exemplar_size, side)
        if self._gat:  # its template graph masks the target's box (released: s_z rounded, the box unclipped)
            self._feeds = self.backend.template(z, roi=template_roi(w, h, crop_side(side), self.geometry.exemplar_size))
        else:
            self._feeds = self.backend.template(z)
        self._monitor = LostMonitor(self.params)
        if self._motion is not None:
            self._motion.reset(image)
        if self._still is not None:
            self._still.reset()
            self._still.observe(image, (*self._centre, w, h))
        if self._swap is not None:
            self._swap.reset()
            self._swap.observe(image, (*self._centre, w, h))
        if self._prior is not None:
            self._prior.reset(image, self._centre, (w, h))

    def update(self, frame: np.ndarray) -> TrackResult:
        """Track one frame; the search graph runs once."""
        if self._feeds is None:
            raise InputError("Tracker.update() called before init()")
        t0 = time.perf_counter()
        image = as_image(frame)
        if image.shape[:2] != self._frame_size:  # the box is in the first frame's pixels: it means nothing here
            (h, w), (h0, w0) = image.shape[:2], self._frame_size
            raise InputError(f"frame is {w}×{h} but tracking started on a {w0}×{h0} frame; init() again to "
                             "track at another size")
        g = self.geometry
        if self._motion is not None and (moved := self._motion.jolt(image)) is not None:
            self._centre = (self._centre[0] + moved[0], self._centre[1] + moved[1])  # where the jolt took it
        t_motion = time.perf_counter()
        growth = self._monitor.growth
        s_z = self._context_side()
        scale = g.exemplar_size / s_z / growth  # crop pixels per frame pixel
        # Backends that bind their input (OnnxBackend) take the crop in place; others get a fresh array.
        patch = self._patch(image, g.instance_size, s_z * g.instance_size / g.exemplar_size * growth)
        x = to_blob(patch, g.channel_order, getattr(self.backend, "input_buffer", None))
        t1 = time.perf_counter()
        maps = self.backend.search(x, self._feeds)
        t2 = time.perf_counter()
        img_h, img_w = image.shape[:2]
        w, h = self._size
        if all(np.isfinite(m).all() for m in maps):
            prior = None if self._prior is None else self._prior.weights(
                patch, (w * scale, h * scale), (self._decode.px, self._decode.py), self.params.colour_prior)
            det = self._detect(maps, w * scale, h * scale, scale, prior)
        else:  # a broken model (NaN weights) or a NaN input: a miss that holds the box and counts towards lost
            det = Detection(0.0, 0.0, w * scale, h * scale, 0.0, 0.0, -1)
        size, plausible = self._propose_size(det, scale, img_w, img_h)
        state = self._monitor.observe(det.score, plausible)
        cx, cy = self._centre
        if state != LOST:
            cx, cy = cx + det.dx / scale, cy + det.dy / scale
            w, h = size
        cx, cy = max(0.0, min(cx, img_w)), max(0.0, min(cy, img_h))
        w, h = self._clip_size((w, h), img_w, img_h)
        self._centre, self._size = (cx, cy), (w, h)
        if self._still is not None and self._still.observe(image, (cx, cy, w, h)):
            state = self._monitor.demote()
        if self._swap is not None and self._swap.observe(image, (cx, cy, w, h)):
            state = self._monitor.demote()
        t3 = time.perf_counter()
        latency = {"motion": t_motion - t0, "crop": t1 - t_motion, "search": t2 - t1, "post": t3 - t2, "total": t3 - t0}
        return TrackResult((cx - w / 2, cy - h / 2, w, h), det.score, state, latency, self._monitor.confidence)

    def look(self, frame: np.ndarray, box: Sequence[float], shift: tuple[float, float] = (0.0, 0.0)
             ) -> tuple[float, float, float, float]:
        """The network's own box (x, y, w, h in frame pixels) with the search crop cut around `box` at its
        size, its centre moved by `shift` crop pixels: one search-graph run, read before the size smoothing,
        the bounds and the lost state, and the tracker's state left as it was. A measuring tool
        (`dadiff-eval box-read`): tracking mixes the network's box error with its own history."""
        if self._feeds is None:
            raise InputError("Tracker.look() called before init()")
        image = as_image(frame)
        x, y, w, h = check_box(box, image.shape[1], image.shape[0])
        g = self.geometry
        shift = _check_shift(shift, g.instance_size)
        kept = self._centre, self._size
        try:
            self._size = (w, h)
            s_z = self._context_side()
            scale = g.exemplar_size / s_z  # crop pixels per frame pixel
            self._centre = (x + (w - 1) / 2 + shift[0] / scale, y + (h - 1) / 2 + shift[1] / scale)
            crop = self._crop(image, g.instance_size, s_z * g.instance_size / g.exemplar_size)
            det = self._detect(self.backend.search(crop, self._feeds), w * scale, h * scale, scale)
            cx, cy = self._centre[0] + det.dx / scale, self._centre[1] + det.dy / scale
        finally:
            self._centre, self._size = kept
        bw, bh = det.w / scale, det.h / scale
        return cx - bw / 2, cy - bh / 2, bw, bh

    def _detect(self, maps: Sequence[np.ndarray], target_w: float, target_h: float, scale: float,
                prior: np.ndarray | None = None) -> Detection:
        """The decoder's choice on the search graph's maps, for a target of this size in crop pixels."""
        p = self.params
        if self._gat:
            cls, loc, cen = maps[:3]
            return self._decode(cls, loc, cen, target_w, target_h, scale, p.penalty_k, p.window_influence)
        return self._decode(maps[0], maps[1], target_w, target_h, p.penalty_k, p.window_influence, prior)

    def _propose_size(self, det: Detection, scale: float, img_w: int, img_h: int) -> tuple[tuple[float, float], bool]:
        """The size this detection leads to (released lr blend, then the bounds and the frame clip) and
        whether it is plausible; applied only when the frame is not lost."""
        p = self.params
        w, h = self._size
        lr = det.penalty * det.step_score * p.lr
        size = (w * (1 - lr) + det.w / scale * lr, h * (1 - lr) + det.h / scale * lr)
        if p.released:
            return self._clip_size(size, img_w, img_h), True
        bw, bh, held = bound_size(size, self._size, self._start, p)
        size = self._clip_size((bw, bh), img_w, img_h)
        return size, not held and not covers_frame(size, img_w, img_h, p.max_frame_cover)

    def _clip_size(self, size: tuple[float, float], img_w: int, img_h: int) -> tuple[float, float]:
        """The released clip: at least `min_size`, never larger than the frame."""
        low = self.geometry.min_size  # then the frame again: a frame under the floor (a 1x1 image) caps it
        return min(max(low, min(size[0], img_w)), img_w), min(max(low, min(size[1], img_h)), img_h)
