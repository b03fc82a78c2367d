"""The tracker loop and the feed it shares with the MAVLink thread.

The MAVLink thread asks (`TrackFeed.request`: start on a normalised rectangle or point, or stop); the
tracker loop applies the newest request on the next frame, runs the tracker, and publishes each result
(`TrackFeed.publish`, which wakes the MAVLink thread at once). One bad frame is logged and skipped; a
tracker that keeps failing ends the target with the 'error' state, never the loop.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from dadiff.runtime.errors import InputError
from dadiff.runtime.outputs import Record, Sink
from dadiff.runtime.runstats import RunStats

from .logs import Throttle
from .video import FrameGrabber, Grabbed

log = logging.getLogger(__name__)

POINT_MIN_SIDE = 0.05  # a tracked point's box is at least this share of the shorter image side
FAILURES_TO_ERROR = 25  # tracker failures in a row before the target is dropped with 'error'


class TrackerLike(Protocol):
    def init(self, frame: Any, box: Sequence[float]) -> None: ...

    def update(self, frame: Any) -> Any: ...  # .box, .score, .state, .latency like TrackResult


@dataclass(frozen=True)
class Start:
    """Start (or re-target) on a normalised rectangle (x0, y0, x1, y1), a normalised point (x, y, radius),
    or a pixel box (x, y, w, h); exactly one is set."""

    rect: tuple[float, float, float, float] | None = None
    point: tuple[float, float, float] | None = None
    pixels: tuple[float, float, float, float] | None = None
    configured: bool = False  # --init / the config's init: a box the first frame refuses is a startup error

    def box(self, width: int, height: int) -> tuple[float, float, float, float]:
        """(x, y, w, h) in pixels of a width × height frame."""
        if self.pixels is not None:
            return self.pixels
        if self.rect is not None:
            x0, y0, x1, y1 = self.rect
            return x0 * width, y0 * height, (x1 - x0) * width, (y1 - y0) * height
        assert self.point is not None
        px, py, radius = self.point
        side = max(2 * radius * width, POINT_MIN_SIDE * min(width, height))
        cx, cy = px * width, py * height
        x0, y0 = max(0.0, cx - side / 2), max(0.0, cy - side / 2)
        x1, y1 = min(float(width), cx + side / 2), min(float(height), cy + side / 2)
        return x0, y0, x1 - x0, y1 - y0


@dataclass(frozen=True)
class Stop:
    pass


@dataclass(frozen=True)
class Snapshot:
    """The latest tracker output. state: idle, tracking, uncertain, lost or error; `box` in pixels;
    `frame_stamp` when its frame was grabbed and `result_time` when the result existed (monotonic)."""

    seq: int = 0
    target_id: int = 0
    state: str = "idle"
    box: tuple[float, float, float, float] | None = None
    score: float = 0.0
    frame_size: tuple[int, int] = (0, 0)
    frame_stamp: float = 0.0
    result_time: float = 0.0
    frame_index: int = -1

    @property
    def active(self) -> bool:
        return self.state in ("tracking", "uncertain")


class TrackFeed:
    """Thread-safe hand-over between the tracker loop and the MAVLink thread."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._snapshot = Snapshot()
        self._request: Start | Stop | None = None
        self.on_publish: Callable[[], None] | None = None
        self.frame_size: tuple[int, int] | None = None
        self.last_frame_at: float | None = None
        self.loop_tick_at = time.monotonic()
        self._interval: float | None = None  # smoothed time between frames, seconds

    def request(self, request: Start | Stop) -> None:
        with self._lock:
            self._request = request  # the newest wins: a stop after a start cancels it

    def take_request(self) -> Start | Stop | None:
        with self._lock:
            request, self._request = self._request, None
        return request

    def publish(self, **fields: Any) -> Snapshot:
        with self._lock:
            self._snapshot = Snapshot(seq=self._snapshot.seq + 1, **fields)
            snapshot = self._snapshot
        if self.on_publish is not None:
            self.on_publish()
        return snapshot

    def latest(self) -> Snapshot:
        with self._lock:
            return self._snapshot

    def tick(self) -> None:
        self.loop_tick_at = time.monotonic()

    def saw_frame(self, size: tuple[int, int], at: float) -> None:
        last = self.last_frame_at
        if last is not None and 0 < at - last < 5.0:
            gap = at - last
            self._interval = gap if self._interval is None else self._interval + 0.1 * (gap - self._interval)
        self.frame_size, self.last_frame_at = size, at

    @property
    def frame_rate(self) -> float:
        """Frames per second the tracker receives (smoothed; 0 before two frames)."""
        return 0.0 if not self._interval else round(1.0 / self._interval, 2)


class TrackingLoop:
    """Frames from the grabber → tracker → feed and sinks, until `stop`, the end of a file or max_frames."""

    def __init__(
        self,
        tracker: TrackerLike,
        grabber: FrameGrabber,
        feed: TrackFeed,
        stop: threading.Event,
        sinks: Sequence[Sink] = (),
        max_frames: int | None = None,
    ) -> None:
        self.tracker, self.grabber, self.feed, self.stop = tracker, grabber, feed, stop
        self.sinks = list(sinks)
        self.max_frames = max_frames
        self.stats = RunStats()
        self.startup_error: str | None = None  # a configured init box the first frame refused: the service stops
        self.errors = 0
        self._throttle = Throttle(log)
        self._target_id = 0
        self._tracking = False
        self._failures = 0
        self._state = "idle"

    def run(self) -> None:
        frames = 0
        while not self.stop.is_set():
            self.feed.tick()
            item = self.grabber.get(timeout=0.2)
            if item is None:
                if self.grabber.finished:
                    break
                continue
            frames += 1
            try:
                self._process(item)
            except Exception as exc:  # never die on one frame
                self.errors += 1
                self._throttle.log(logging.ERROR, "frame", "frame %d failed: %s", item.frame.index, exc, exc_info=True)
            if self.max_frames and frames >= self.max_frames:
                log.info("reached --max-frames %d", self.max_frames)
                break
        self.stats.skipped = self.grabber.dropped

    def _process(self, item: Grabbed) -> None:
        image = item.frame.image
        height, width = image.shape[:2]
        self.feed.saw_frame((width, height), item.grabbed_at)
        request = self.feed.take_request()
        if isinstance(request, Stop):
            if self._tracking:
                log.info("tracking stopped")
            self._tracking = False
            self._publish(item, "idle", None, 0.0)
            return
        if isinstance(request, Start):
            self._start(item, request.box(width, height), request.configured)
            return
        if not self._tracking:
            return
        try:
            result = self.tracker.update(image)
        except Exception as exc:
            self._failures += 1
            self.errors += 1
            self._throttle.log(logging.ERROR, "update", "tracker failed on frame %d: %s", item.frame.index, exc)
            if self._failures >= FAILURES_TO_ERROR:
                log.error("tracker failed %d frames in a row; target dropped", self._failures)
                self._tracking = False
                self._publish(item, "error", None, 0.0)
            return
        self._failures = 0
        x, y, w, h = (float(v) for v in result.box)
        box = (x, y, w, h)
        state, score = str(result.state), float(result.score)
        latency = getattr(result, "latency", {}).get("total")
        self.stats.add(state, latency)
        if state != self._state:
            log.info("target %d %s (score %.2f)", self._target_id, state, score)
            self._state = state
        self._publish(item, state, box, score)
        self._emit(item, Record(box, score, state, self.stats.fps_recent))

    def _start(self, item: Grabbed, box: tuple[float, float, float, float], configured: bool = False) -> None:
        try:
            self.tracker.init(item.frame.image, box)
        except Exception as exc:
            if configured and isinstance(exc, InputError):  # the operator's setting, not a ground station's command
                self.startup_error = str(exc)
                self.stop.set()
                return
            log.error("cannot start tracking at %s: %s", tuple(round(v, 1) for v in box), exc)
            self._tracking = False
            self._publish(item, "error", None, 0.0)
            return
        self._tracking, self._failures, self._state = True, 0, "tracking"
        self._target_id += 1
        log.info("tracking target %d from %s", self._target_id, tuple(round(v, 1) for v in box))
        self.stats.add("init")
        self._publish(item, "tracking", box, 1.0)
        self._emit(item, Record(box, 1.0, "init"))

    def _publish(self, item: Grabbed, state: str, box: tuple[float, float, float, float] | None, score: float) -> None:
        image = item.frame.image
        self.feed.publish(
            target_id=self._target_id,
            state=state,
            box=box,
            score=score,
            frame_size=(image.shape[1], image.shape[0]),
            frame_stamp=item.grabbed_at,
            result_time=time.monotonic(),
            frame_index=item.frame.index,
        )

    def _emit(self, item: Grabbed, record: Record) -> None:
        for sink in self.sinks:
            try:
                sink.write(item.frame, record)
            except Exception as exc:  # a full disk must not stop the tracking
                self._throttle.log(logging.ERROR, f"sink{id(sink)}", "cannot write %s: %s", type(sink).__name__, exc)
