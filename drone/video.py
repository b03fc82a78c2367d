"""The frame grabber: reads a video source on its own thread and reopens it after loss.

Live sources (camera, stream) keep only the newest frame, so the tracker always works on the present
and never on a backlog. Files and folders: with `realtime` (the service's default, for rehearsing with a
recorded flight) they play at their own frame rate (a folder at DEFAULT_FPS) and are handed over as a
camera would deliver them (newest frame only: a slow tracker skips frames, it does not fall behind);
without it every frame is handed over as fast as the tracker takes them. At their end they end the run, or
with `loop` start again. Opening (an RTSP timeout can take many seconds) and reconnecting never block the
tracker loop.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Protocol

from dadiff.runtime.sources import Frame

from .logs import Throttle

log = logging.getLogger(__name__)

DEFAULT_FPS = 30.0  # pace of a source that does not say its frame rate (image folders)


class Source(Protocol):
    live: bool

    def frames(self) -> Iterator[Frame]: ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class Grabbed:
    frame: Frame
    grabbed_at: float  # monotonic seconds when the frame left the source


class FrameGrabber:
    """`open_source()` is called again after every loss (retry delay doubling from `retry_min` to
    `retry_max`); `get(timeout)` returns the next frame or None."""

    def __init__(
        self,
        open_source: Callable[[], Source],
        stop: threading.Event,
        retry_min: float = 0.5,
        retry_max: float = 5.0,
        realtime: bool = False,
        loop: bool = False,
    ) -> None:
        self._open, self._stop = open_source, stop
        self.retry_min, self.retry_max = retry_min, retry_max
        self.realtime, self.loop = realtime, loop
        self.plays = 0  # times a file or folder was played to its end
        self._cond = threading.Condition()
        self._slot: Grabbed | None = None
        self.finished = False  # a file or folder ended
        self.opens = 0
        self.dropped = 0  # live frames replaced before the tracker took them
        self._throttle = Throttle(log)

    def get(self, timeout: float) -> Grabbed | None:
        with self._cond:
            if self._slot is None and not self.finished:
                self._cond.wait(timeout)
            item, self._slot = self._slot, None
            self._cond.notify_all()
        return item

    def _put(self, item: Grabbed, live: bool) -> None:
        with self._cond:
            if not live:
                while self._slot is not None and not self._stop.is_set():
                    self._cond.wait(0.1)
            elif self._slot is not None:
                self.dropped += 1
            self._slot = item
            self._cond.notify_all()

    def _finish(self) -> None:
        with self._cond:
            self.finished = True
            self._cond.notify_all()

    def run(self) -> None:
        delay = self.retry_min
        resume_at: float | None = None  # --loop: when the next play's first frame is due (no seam)
        while not self._stop.is_set():
            try:
                source = self._open()
            except Exception as exc:  # SourceError, or anything an odd backend raises
                self._throttle.log(logging.WARNING, "open", "cannot open the video (%s); retrying", exc)
                self._stop.wait(delay)
                delay = min(delay * 2, self.retry_max)
                continue
            self.opens += 1
            live = bool(getattr(source, "live", True))
            paced = not live and self.realtime
            fps = float(getattr(source, "fps", None) or DEFAULT_FPS)
            opened = "live" if live else f"file, {fps:g} FPS realtime" if paced else "file"
            self._throttle.log(logging.INFO, "opened", "video opened (%s)", opened)  # a short --loop clip: each play
            start, count, yielded = resume_at or time.monotonic(), 0, 0
            resume_at = None
            try:
                for frame in source.frames():
                    delay = self.retry_min
                    yielded += 1
                    if paced:  # frame k is due k / fps after the first; late frames go at once, phase re-based
                        due = start + count / fps
                        wait = due - time.monotonic()
                        if wait > 0 and self._stop.wait(wait):
                            break
                        if wait < -1.0 / fps:
                            start = time.monotonic() - count / fps
                        count += 1
                    self._put(Grabbed(frame, time.monotonic()), live or paced)
                    if self._stop.is_set():
                        break
            except Exception as exc:
                self._throttle.log(logging.WARNING, "read", "video read failed (%s)", exc)
            finally:
                try:
                    source.close()
                except Exception:
                    log.debug("closing the video failed", exc_info=True)
            if self._stop.is_set():
                break
            if not live:
                self.plays += 1
                if self.loop and yielded:
                    self._throttle.log(logging.INFO, "replay", "video ended; playing it again (--loop)")
                    resume_at = start + count / fps if paced else None
                    continue
                if self.loop:  # nothing at all: do not spin on a broken file
                    log.warning("video gave no frames; retrying in %.1f s", delay)
                    self._stop.wait(delay)
                    delay = min(delay * 2, self.retry_max)
                    continue
                log.info("video ended")
                break
            log.warning("video lost; reopening in %.1f s", delay)
            self._stop.wait(delay)
            delay = min(delay * 2, self.retry_max)
        self._finish()
