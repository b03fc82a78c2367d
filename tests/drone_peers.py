"""Loopback MAVLink peers for the drone tests: a simulated autopilot and a ground station (pymavlink on
127.0.0.1, each on its own thread), plus a scripted fake tracker and a synthetic live video source.

Every wait here is bounded; nothing leaves the loopback interface.
"""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from dadiff.drone.follow import AUTOPILOT_ARDUPILOT, AUTOPILOT_PX4
from dadiff.drone.mav import mavlink, mavutil
from dadiff.runtime.sources import Frame

WIDTH, HEIGHT = 640, 480


def free_port(kind: int = socket.SOCK_DGRAM) -> int:
    with socket.socket(socket.AF_INET, kind) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def wait_until(condition: Callable[[], bool], timeout: float, step: float = 0.01) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(step)
    return condition()


@dataclass
class Received:
    msg: Any
    at: float  # monotonic


class Peer:
    """A pymavlink endpoint on its own thread that records every message it receives."""

    def __init__(self, url: str, sysid: int, compid: int, key: bytes | None = None) -> None:
        self.url, self.sysid, self.compid, self.key = url, sysid, compid, key
        self.log: list[Received] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._conn_lock = threading.Lock()
        self.conn: Any = None
        self._thread: threading.Thread | None = None

    def _connect(self) -> None:
        self.conn = mavutil.mavlink_connection(
            self.url, source_system=self.sysid, source_component=self.compid, dialect="ardupilotmega", retries=0
        )
        if self.key is not None:
            self.conn.setup_signing(self.key, sign_outgoing=True, allow_unsigned_callback=None, link_id=7)

    def start(self) -> Peer:
        self._connect()
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2)
        with self._conn_lock:
            if self.conn is not None:
                self.conn.close()
                self.conn = None

    def _run(self) -> None:
        while not self._stop.is_set():
            self.tick()
            with self._conn_lock:
                conn = self.conn
                if conn is None:
                    break
                try:
                    msg = conn.recv_msg()
                except OSError:
                    msg = None
            if msg is None:
                time.sleep(0.002)
                continue
            if msg.get_type() != "BAD_DATA":
                with self._lock:
                    self.log.append(Received(msg, time.monotonic()))

    def tick(self) -> None:
        """Periodic work of a subclass (heartbeats)."""

    def send(self, msg: Any) -> None:
        with self._conn_lock:
            if self.conn is not None:
                self.conn.mav.send(msg)

    def received(self, kind: str, since: float = 0.0, src_component: int | None = None) -> list[Received]:
        with self._lock:
            return [
                r
                for r in self.log
                if r.msg.get_type() == kind
                and r.at >= since
                and (src_component is None or r.msg.get_srcComponent() == src_component)
            ]

    def wait_for(
        self, kind: str, timeout: float, since: float = 0.0, where: Callable[[Any], bool] | None = None
    ) -> Any | None:
        found: list[Any] = []

        def seen() -> bool:
            found[:] = [r.msg for r in self.received(kind, since) if where is None or where(r.msg)]
            return bool(found)

        return found[0] if wait_until(seen, timeout) else None


class Autopilot(Peer):
    """Heartbeats (ArduCopter quad or PX4) at `rate` Hz with the mode and armed state given; records the
    setpoints it gets. `beating = False` silences the heartbeat (heartbeat loss)."""

    def __init__(self, url: str, flavour: str = "ardupilot", sysid: int = 1, rate: float = 10.0, **kw: Any) -> None:
        super().__init__(url, sysid, mavlink.MAV_COMP_ID_AUTOPILOT1, **kw)
        self.autopilot = AUTOPILOT_ARDUPILOT if flavour == "ardupilot" else AUTOPILOT_PX4
        self.vehicle_type = mavlink.MAV_TYPE_QUADROTOR
        self.armed = False
        self.custom_mode = 0
        self.beating = True
        self.period = 1.0 / rate
        self._next = 0.0

    def set_mode(self, armed: bool, custom_mode: int) -> None:
        self.armed, self.custom_mode = armed, custom_mode
        self._next = 0.0  # announce at once

    def tick(self) -> None:
        now = time.monotonic()
        if not self.beating or now < self._next:
            return
        self._next = now + self.period
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mavlink.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0)
        self.send(
            mavlink.MAVLink_heartbeat_message(
                self.vehicle_type, self.autopilot, base, self.custom_mode, mavlink.MAV_STATE_ACTIVE, 3
            )
        )

    def setpoints(self, since: float = 0.0) -> list[Received]:
        return self.received("SET_POSITION_TARGET_LOCAL_NED", since)


class GroundStation(Peer):
    def __init__(self, url: str, sysid: int = 255, compid: int = 190, **kw: Any) -> None:
        super().__init__(url, sysid, compid, **kw)
        self._next = 0.0

    def tick(self) -> None:
        now = time.monotonic()
        if now >= self._next:
            self._next = now + 0.5
            self.send(
                mavlink.MAVLink_heartbeat_message(
                    mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE, 3
                )
            )

    def command(self, command: int, *params: float, target: tuple[int, int] = (1, 100), use_int: bool = False) -> float:
        """Send COMMAND_LONG (or COMMAND_INT: params 5 and 6 as ints); returns the send time."""
        p = list(params) + [0.0] * (7 - len(params))
        if use_int:
            msg = mavlink.MAVLink_command_int_message(
                target[0], target[1], 0, command, 0, 0, p[0], p[1], p[2], p[3], int(p[4]), int(p[5]), p[6]
            )
        else:
            msg = mavlink.MAVLink_command_long_message(target[0], target[1], command, 0, *p)
        at = time.monotonic()
        self.send(msg)
        return at

    def ack(self, command: int, since: float, timeout: float = 3.0) -> Any | None:
        return self.wait_for("COMMAND_ACK", timeout, since, where=lambda m: m.command == command)

    def call(self, command: int, *params: float, timeout: float = 3.0, **kw: Any) -> Any | None:
        """Send a command and wait (bounded) for its ACK; None when none came."""
        since = self.command(command, *params, **kw)
        return self.ack(command, since, timeout)


@dataclass
class FakeResult:
    box: tuple[float, float, float, float]
    score: float
    state: str
    latency: dict[str, float] = field(default_factory=dict)


class FakeTracker:
    """init/update like dadiff.runtime.Tracker: the box drifts 1 px right per frame; `state` is what the
    next update reports; `fail_next` makes updates raise; `running` cleared makes them hang. Records the
    init boxes and (time, state, box) of every update."""

    def __init__(self) -> None:
        self.inits: list[tuple[float, float, float, float]] = []
        self.box = (0.0, 0.0, 0.0, 0.0)
        self.state = "tracking"
        self.fail_next = 0
        self.running = threading.Event()  # clear it to make update() hang (a stuck inference)
        self.running.set()
        self.updates: list[tuple[float, str, tuple[float, float, float, float]]] = []
        self.lock = threading.Lock()

    def init(self, frame: np.ndarray, box: tuple[float, float, float, float]) -> None:
        with self.lock:
            self.inits.append(tuple(float(v) for v in box))  # type: ignore[arg-type]
            self.box = tuple(float(v) for v in box)  # type: ignore[assignment]

    def update(self, frame: np.ndarray) -> FakeResult:
        self.running.wait(10)
        with self.lock:
            if self.fail_next > 0:
                self.fail_next -= 1
                raise RuntimeError("simulated tracker failure")
            x, y, w, h = self.box
            if self.state != "lost":
                self.box = (x + 1.0, y, w, h)
            result = FakeResult(self.box, 0.9 if self.state == "tracking" else 0.3, self.state, {"total": 0.001})
            self.updates.append((time.monotonic(), self.state, self.box))
            return result


class FakeSource:
    """A live source of grey frames at `fps`; ends after `limit` frames when given (a camera that drops
    out); `gate` holds the first frame back until it is set."""

    live = True

    def __init__(self, fps: float = 30.0, limit: int | None = None, gate: threading.Event | None = None) -> None:
        self.fps, self.limit, self.gate = fps, limit, gate
        self.closed = False

    def frames(self) -> Iterator[Frame]:
        index = 0
        image = np.full((HEIGHT, WIDTH, 3), 90, np.uint8)
        next_at = time.monotonic()
        while not self.closed and (self.limit is None or index < self.limit):
            if self.gate is not None and not self.gate.wait(0.05):
                continue
            next_at += 1.0 / self.fps
            time.sleep(max(0.0, next_at - time.monotonic()))
            yield Frame(index, time.time(), image)
            index += 1

    def close(self) -> None:
        self.closed = True


class SourceFactory:
    """open_source for the service: counts the opens; each source is a FakeSource(**kw)."""

    def __init__(self, **kw: Any) -> None:
        self.kw = kw
        self.opened: list[FakeSource] = []

    def __call__(self) -> FakeSource:
        source = FakeSource(**self.kw)
        self.opened.append(source)
        return source


def rate(times: list[float]) -> float:
    """Messages per second from arrival times (mean over the intervals between them)."""
    if len(times) < 2:
        return 0.0
    return (len(times) - 1) / (times[-1] - times[0])


class Rig:
    """A service (fake tracker, synthetic camera) on udpin:127.0.0.1:PORT with a simulated autopilot and a
    ground station connected to it; `with Rig(...) as rig:` starts all and stops all (bounded)."""

    def __init__(
        self,
        follow: Any = None,
        key: bytes | None = None,
        ap_key: bytes | None = None,
        gcs_key: bytes | None = None,
        flavour: str = "ardupilot",
        source: dict[str, Any] | None = None,
        notifier: Any = None,
        **settings: Any,
    ) -> None:
        from dadiff.drone.link import LinkSettings
        from dadiff.drone.service import Service, ServiceSettings

        self.port = free_port()
        self.url = f"udpin:127.0.0.1:{self.port}"
        self.tracker = FakeTracker()
        self.source = SourceFactory(**(source or {"fps": 30.0}))
        link = LinkSettings(self.url, signing_key=key, **settings.pop("link", {}))
        self.service = Service(
            ServiceSettings(link, follow=follow, **settings), self.tracker, self.source, notifier=notifier
        )
        # peers sign with the service's key unless given their own (b"": unsigned)
        ap_key = (ap_key if ap_key is not None else key) or None
        gcs_key = (gcs_key if gcs_key is not None else key) or None
        self.ap = Autopilot(f"udpout:127.0.0.1:{self.port}", flavour, key=ap_key)
        self.gcs = GroundStation(f"udpout:127.0.0.1:{self.port}", key=gcs_key)
        self.rc: int | None = None
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        self.rc = self.service.run()

    def __enter__(self) -> Rig:
        self._thread.start()
        assert self.service.started.wait(5)
        self.ap.start()
        self.gcs.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.service.stop()
        self._thread.join(timeout=10)
        self._drain(self.ap)  # the service's last words (a final zero velocity) are still in flight
        self.ap.close()
        self.gcs.close()
        assert not self._thread.is_alive(), "service did not stop"

    @staticmethod
    def _drain(peer: Any, quiet: float = 0.2, limit: float = 2.0) -> None:
        """Wait until `peer` has received nothing new for `quiet` seconds (at most `limit`)."""
        end = time.monotonic() + limit
        count = len(peer.received("SET_POSITION_TARGET_LOCAL_NED"))
        while time.monotonic() < end:
            time.sleep(quiet)
            now = len(peer.received("SET_POSITION_TARGET_LOCAL_NED"))
            if now == count:
                return
            count = now

    def connected(self, timeout: float = 5.0) -> bool:
        """The service knows its system id and the ground station hears its heartbeat."""
        return self.gcs.wait_for("HEARTBEAT", timeout, where=lambda m: m.get_srcComponent() == 100) is not None

    def start_tracking(self, rect: tuple[float, float, float, float] = (0.45, 0.4, 0.55, 0.55)) -> Any:
        assert wait_until(lambda: self.service.feed.frame_size is not None, 5)
        reply = self.gcs.call(mavlink.MAV_CMD_CAMERA_TRACK_RECTANGLE, *rect)
        assert reply is not None and reply.result == mavlink.MAV_RESULT_ACCEPTED
        assert wait_until(lambda: len(self.tracker.inits) > 0 and len(self.tracker.updates) > 2, 5)
        return reply
