"""The companion-computer service: frame grabber, tracker loop and MAVLink loop on their own threads,
watched by a supervisor that feeds the systemd watchdog, logs a status line, and ends the run.

A frame, a packet or a send that fails is logged and skipped inside its loop; a loop that dies all the
same ends the service with exit code 1, so that systemd restarts it (Restart=on-failure). The watchdog
is fed only while both the tracker loop and the MAVLink loop make progress.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from dadiff.runtime.outputs import Sink

from .camera import CameraComponent, CameraSettings
from .follow import FollowConfig, Follower
from .gimbal import GimbalConfig, GimbalFollower
from .link import Link, LinkSettings
from .linkloop import LinkLoop
from .systemd import Notifier
from .tracking import Start, TrackerLike, TrackFeed, TrackingLoop
from .video import FrameGrabber, Source

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ServiceSettings:
    link: LinkSettings
    camera: CameraSettings = field(default_factory=CameraSettings)
    follow: FollowConfig | None = None  # None: the vehicle follow controller is off
    gimbal: GimbalConfig | None = None  # None: gimbal following is off
    init_box: tuple[float, float, float, float] | None = None  # pixels; None: wait for a track command
    max_frames: int | None = None
    heartbeat_hz: float = 1.0
    status_every: float = 30.0
    loop_stall: float = 2.0
    video_retry: tuple[float, float] = (0.5, 5.0)
    realtime: bool = True  # a video file plays at its own frame rate, as a camera would deliver it
    loop: bool = False  # a video file starts again at its end


class Service:
    def __init__(
        self,
        settings: ServiceSettings,
        tracker: TrackerLike,
        open_source: Callable[[], Source],
        sinks: Sequence[Sink] = (),
        notifier: Notifier | None = None,
    ) -> None:
        self.settings = settings
        self.stop_event = threading.Event()
        self.notifier = notifier or Notifier({})
        self.sinks = list(sinks)
        self.feed = TrackFeed()
        self.grabber = FrameGrabber(
            open_source, self.stop_event, *settings.video_retry, realtime=settings.realtime, loop=settings.loop
        )
        self.tracking = TrackingLoop(tracker, self.grabber, self.feed, self.stop_event, sinks, settings.max_frames)
        self.link = Link(settings.link)
        boot = time.monotonic()
        camera = settings.camera
        if settings.link.signing_key is not None:  # signing on: every correctly signed sender may command
            camera = dataclasses.replace(camera, trust_signed=True)
        self.camera = CameraComponent(camera, self.feed, lambda: int((time.monotonic() - boot) * 1000))
        self.follower = Follower(settings.follow) if settings.follow is not None else None
        self.gimbal = GimbalFollower(settings.gimbal) if settings.gimbal is not None else None
        self.loop = LinkLoop(
            self.link,
            self.camera,
            self.feed,
            self.stop_event,
            self.follower,
            heartbeat_hz=settings.heartbeat_hz,
            loop_stall=settings.loop_stall,
            boot_time=boot,
            gimbal=self.gimbal,
        )
        if settings.init_box is not None:
            self.feed.request(Start(pixels=settings.init_box, configured=True))
        self._failed: dict[str, BaseException] = {}
        self.started = threading.Event()

    def stop(self) -> None:
        self.stop_event.set()

    def _guard(self, name: str, target: Callable[[], None]) -> Callable[[], None]:
        def run() -> None:
            try:
                target()
            except BaseException as exc:
                self._failed[name] = exc
                log.critical("%s loop died: %s", name, exc, exc_info=True)

        return run

    def run(self) -> int:
        """Block until stopped (0), the video file ends or --max-frames is reached (0), or a loop dies (1)."""
        threads = {
            name: threading.Thread(target=self._guard(name, fn), name=f"dadiff-{name}", daemon=True)
            for name, fn in (("video", self.grabber.run), ("tracker", self.tracking.run), ("mavlink", self.loop.run))
        }
        for thread in threads.values():
            thread.start()
        log.info("service started: MAVLink %s, component %d", self.settings.link.url, self.settings.camera.component)
        self.notifier.ready("running")
        self.started.set()
        watchdog_every = self.notifier.watchdog_interval
        next_watchdog = next_status = time.monotonic()
        try:
            while not self.stop_event.wait(0.2):
                if self._failed or not threads["tracker"].is_alive():
                    break  # a loop died, or the video file ended / --max-frames was reached
                now = time.monotonic()
                if watchdog_every is not None and now >= next_watchdog and self._healthy(now):
                    self.notifier.watchdog()
                    next_watchdog = now + watchdog_every
                if now >= next_status:
                    next_status = now + self.settings.status_every
                    line = self.status_line()
                    log.info("%s", line)
                    self.notifier.status(line)
        finally:
            self.stop_event.set()
            self.notifier.stopping()
            for thread in threads.values():
                thread.join(timeout=5.0)
            for sink in self.sinks:
                try:
                    sink.close()
                except Exception as exc:  # an output not written whole: exit 1, not 0
                    log.error("cannot close %s: %s", type(sink).__name__, exc)
                    self._failed[f"close {type(sink).__name__}"] = exc
            log.info("service stopped: %s", self.summary())
        return 1 if self._failed else 0

    def _healthy(self, now: float) -> bool:
        stall = self.settings.loop_stall
        return now - self.feed.loop_tick_at <= stall and now - self.loop.tick_at <= stall

    def status_line(self) -> str:
        snap = self.feed.latest()
        stats, link = self.loop.stats, self.link
        follow = f", follow {self.follower.state} ({self.follower.reason})" if self.follower else ""
        if self.gimbal is not None:
            follow += f", gimbal {self.gimbal.state} ({self.gimbal.reason}), {stats.gimbal} gimbal setpoints"
        fps = self.tracking.stats.fps_recent
        return (
            f"{snap.state} {snap.score:.2f}, {self.tracking.stats.frames} frames"
            f" ({fps or 0:.1f} FPS), link {'open' if link.is_open else 'down'} sysid {link.sysid}, "
            f"sent {stats.heartbeats} heartbeats {stats.statuses} status {stats.setpoints} setpoints{follow}"
        )

    def summary(self) -> str:
        line = self.tracking.stats.summary()
        latencies = self.loop.stats.latencies
        if latencies:
            p50, p95 = np.percentile(np.asarray(latencies) * 1000, [50, 95])
            line += f"; result to 275 p50 {p50:.2f} ms, p95 {p95:.2f} ms"
        errors = f"{self.tracking.errors} frame errors, {self.link.bad} bad packets, {self.link.opens} link opens"
        return f"{line}; {errors}"
