"""The frame grabber: reads a video source on its own thread and reopens it after loss.

Live sources (camera, stream) keep only the newest frame, so the tracker always works on the present
and never on a backlog; files and folders hand over every frame and end the run at their end. Opening
(an RTSP timeout can take many seconds) and reconnecting never block the tracker loop.
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
    ) -> None:
        self._open, self._stop = open_source, stop
        self.retry_min, self.retry_max = retry_min, retry_max
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
            log.info("video opened (%s)", "live" if live else "file")
            try:
                for frame in source.frames():
                    delay = self.retry_min
                    self._put(Grabbed(frame, time.monotonic()), live)
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
                log.info("video ended")
                break
            log.warning("video lost; reopening in %.1f s", delay)
            self._stop.wait(delay)
            delay = min(delay * 2, self.retry_max)
        self._finish()
