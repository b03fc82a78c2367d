"""Loopback MAVLink peers for the drone tests: a simulated autopilot and a ground station (pymavlink on
127.0.0.1, each on its own thread), plus a scripted fake tracker and a synthetic live video source.

Every wait here is bounded; nothing leaves the loopback interface.
"""

from __future__ import annotations

import math
import socket
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from pymavlink.quaternion import QuaternionBase

from dadiff.drone.follow import AUTOPILOT_ARDUPILOT, AUTOPILOT_PX4
from dadiff.drone.mav import mavlink, mavutil
from dadiff.runtime.sources import Frame

if TYPE_CHECKING:
    from dadiff.drone.service import Service

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


class Px4(Autopilot):
    """PX4's OFFBOARD rules, as PX4 SIH enforces them: the switch into OFFBOARD is refused unless setpoints
    are streaming (one within `switch_window`), and in OFFBOARD a gap longer than `loss_timeout`
    (COM_OF_LOSS_T, default 1 s) is a failsafe: with PX4's defaults and no RC the vehicle lands (AUTO_LAND)
    and `failsafes` counts it. MAV_CMD_DO_SET_MODE (base mode CUSTOM, param2 main mode, param3 sub mode) is
    obeyed and ACKed, as PX4's commander does; `mode_requests` records (time, custom_mode) of each."""

    OFFBOARD, POSCTL = 6 << 16, 3 << 16
    HOLD, LAND = (4 << 16) | (3 << 24), (4 << 16) | (6 << 24)  # AUTO_LOITER, AUTO_LAND

    def __init__(self, url: str, loss_timeout: float = 1.0, switch_window: float = 0.5, **kw: Any) -> None:
        super().__init__(url, "px4", **kw)
        self.loss_timeout, self.switch_window = loss_timeout, switch_window
        self.failsafes = 0
        self.max_gap = 0.0  # longest gap between setpoints while in OFFBOARD
        self.mode_requests: list[tuple[float, int]] = []
        self.refuse_modes = False  # True: DO_SET_MODE is DENIED (a vehicle that cannot hold position)
        self._offboard_since: float | None = None
        self._handled = 0

    def _commands(self) -> None:
        with self._lock:
            new, self._handled = self.log[self._handled :], len(self.log)
        for r in new:
            msg = r.msg
            if msg.get_type() != "COMMAND_LONG" or msg.command != mavlink.MAV_CMD_DO_SET_MODE:
                continue
            if msg.target_system != self.sysid or msg.target_component not in (0, self.compid):
                continue
            mode = (int(msg.param2) << 16) | (int(msg.param3) << 24)
            self.mode_requests.append((r.at, mode))
            if int(msg.param1) & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED and not self.refuse_modes:
                self._offboard_since = time.monotonic() if mode == self.OFFBOARD else None
                self.set_mode(self.armed, mode)
                result = mavlink.MAV_RESULT_ACCEPTED
            else:
                result = mavlink.MAV_RESULT_DENIED
            source = (msg.get_srcSystem(), msg.get_srcComponent())
            self.send(mavlink.MAVLink_command_ack_message(msg.command, result, 0, 0, *source))

    def request_offboard(self) -> bool:
        last = self.setpoints()
        if not last or time.monotonic() - last[-1].at > self.switch_window:
            return False
        self.set_mode(True, self.OFFBOARD)
        self._offboard_since = time.monotonic()
        return True

    def tick(self) -> None:
        self._commands()
        if self.custom_mode == self.OFFBOARD and self._offboard_since is not None:
            now = time.monotonic()
            times = [self._offboard_since] + [r.at for r in self.setpoints(self._offboard_since)]
            gaps = [b - a for a, b in zip(times, times[1:], strict=False)] + [now - times[-1]]
            self.max_gap = max(self.max_gap, *gaps)
            if now - times[-1] > self.loss_timeout:
                self.failsafes += 1
                self._offboard_since = None
                self.set_mode(True, self.LAND)
        super().tick()


class GimbalManager(Peer):
    """A MAVLink gimbal manager (protocol v2) with a gimbal behind it, as ArduPilot's AP_Mount or PX4's gimbal
    module run one (`flavour`):
    - GIMBAL_MANAGER_STATUS at 5 Hz; MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE sets (or with -3 releases) primary
      control and is ACKed; setpoints are obeyed only from the primary controller (others count in `ignored`);
      MAV_CMD_REQUEST_MESSAGE for GIMBAL_MANAGER_INFORMATION gets its limits (±90° pitch, ±170° yaw);
    - ArduPilot acts on GIMBAL_MANAGER_SET_PITCHYAW and _SET_ATTITUDE; PX4 only on _SET_ATTITUDE (its MAVLink
      receiver has no SET_PITCHYAW handler: those count in `unhandled`);
    - an angle target is approached at `slew` rad/s (≈ 90°/s) per axis and then held; a rate target is integrated
      until replaced, forever (ArduPilot 4.7.0-dev as measured, PX4's gimbal module), up to the limits;
    - GIMBAL_DEVICE_ATTITUDE_STATUS at 20 Hz: ArduPilot's with yaw in the vehicle frame, PX4's (its output
      angles) with YAW_LOCK and no frame flag, as each sends it.
    `commands` records (time, pitch_rate, yaw_rate, pitch, yaw, flags) of the obeyed setpoints, `path`
    (time, pitch, yaw) of the gimbal at 50 Hz; `deaf = True` drops everything received (a cut link)."""

    PITCH_LIMIT, YAW_LIMIT = math.radians(90), math.radians(170)

    def __init__(
        self, url: str, sysid: int = 1, compid: int = 154, flavour: str = "ardupilot", slew: float = 1.6, **kw: Any
    ) -> None:
        super().__init__(url, sysid, compid, **kw)
        self.flavour, self.slew = flavour, slew
        self.primary = (0, 0)
        self.commands: list[tuple[float, float, float, float, float, int]] = []
        self.ignored = self.unhandled = 0
        self.configures: list[tuple[float, tuple[int, int], float, float]] = []
        self.answer = True  # False: ignore CONFIGURE commands (a manager that does not answer)
        self.deaf = False
        self.pitch = self.yaw = 0.0
        self.target: tuple[str, float, float] = ("angle", 0.0, 0.0)  # ("angle" | "rate", pitch, yaw)
        self.path: list[tuple[float, float, float]] = []
        self._next = self._next_attitude = self._next_path = 0.0
        self._moved_at = time.monotonic()
        self._handled = 0

    def take_control(self, sysid: int, compid: int) -> None:
        """Someone else (a pilot in the ground station) takes primary control."""
        self.primary = (sysid, compid)
        self._next = 0.0

    def point(self, pitch: float, yaw: float) -> None:
        """Someone else (RC, the pilot) pointed the gimbal here."""
        self.pitch, self.yaw, self.target = pitch, yaw, ("angle", pitch, yaw)

    def tick(self) -> None:
        with self._lock:
            new, self._handled = self.log[self._handled :], len(self.log)
        for r in new:
            if not self.deaf:
                self._handle(r)
        now = time.monotonic()
        self._move(now)
        if now >= self._next:
            self._next = now + 0.2
            self.send(mavlink.MAVLink_gimbal_manager_status_message(0, 0, 0, *self.primary, 0, 0))
        if now >= self._next_attitude:
            self._next_attitude = now + 0.05
            self.send(self._attitude())

    def _move(self, now: float) -> None:
        dt, self._moved_at = now - self._moved_at, now
        kind, a, b = self.target
        if kind == "rate":
            self.pitch += a * dt
            self.yaw += b * dt
        else:
            step = self.slew * dt
            self.pitch += max(-step, min(step, a - self.pitch))
            self.yaw += max(-step, min(step, b - self.yaw))
        self.pitch = max(-self.PITCH_LIMIT, min(self.PITCH_LIMIT, self.pitch))
        self.yaw = max(-self.YAW_LIMIT, min(self.YAW_LIMIT, self.yaw))
        if now >= self._next_path:
            self._next_path = now + 0.02
            self.path.append((now, self.pitch, self.yaw))

    def _attitude(self) -> Any:
        q = [float(v) for v in QuaternionBase([0.0, self.pitch, self.yaw]).q]
        locks = mavlink.GIMBAL_DEVICE_FLAGS_ROLL_LOCK | mavlink.GIMBAL_DEVICE_FLAGS_PITCH_LOCK
        if self.flavour == "px4":
            flags = locks | mavlink.GIMBAL_DEVICE_FLAGS_YAW_LOCK | mavlink.GIMBAL_DEVICE_FLAGS_NEUTRAL
        else:
            flags = locks | mavlink.GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME
        nan = float("nan")
        return mavlink.MAVLink_gimbal_device_attitude_status_message(0, 0, 0, flags, q, nan, nan, nan, 0, nan, nan, 1)

    def speed_after(self, since: float) -> tuple[float, float]:
        """(last time the gimbal moved faster than 1°/s after `since`, or `since`; its fastest since then)."""
        track = [p for p in self.path if p[0] >= since]
        moving, fastest = since, 0.0
        for (t0, p0, y0), (t1, p1, y1) in zip(track, track[1:], strict=False):
            speed = math.hypot(p1 - p0, y1 - y0) / max(t1 - t0, 1e-6)
            fastest = max(fastest, speed)
            if speed > math.radians(1.0):
                moving = t1
        return moving, fastest

    def _handle(self, r: Received) -> None:
        msg, source = r.msg, (r.msg.get_srcSystem(), r.msg.get_srcComponent())
        kind = msg.get_type()
        if kind == "COMMAND_LONG" and msg.command == mavlink.MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE:
            if msg.target_component not in (0, self.compid) or not self.answer:
                return
            self.configures.append((r.at, source, msg.param1, msg.param2))
            if msg.param1 == -3 and msg.param2 == -3:
                if self.primary == source:
                    self.primary = (0, 0)
            elif msg.param1 == -2:
                self.primary = source
            elif msg.param1 >= 0:
                self.primary = (int(msg.param1), int(msg.param2))
            self._next = 0.0
            self.send(mavlink.MAVLink_command_ack_message(msg.command, mavlink.MAV_RESULT_ACCEPTED, 0, 0, *source))
        elif kind == "COMMAND_LONG" and msg.command == mavlink.MAV_CMD_REQUEST_MESSAGE and msg.param1 == 280:
            if msg.target_component not in (0, self.compid):
                return
            self.send(mavlink.MAVLink_command_ack_message(msg.command, mavlink.MAV_RESULT_ACCEPTED, 0, 0, *source))
            p, y = self.PITCH_LIMIT, self.YAW_LIMIT
            self.send(mavlink.MAVLink_gimbal_manager_information_message(0, 0, 1, 0, 0, -p, p, -y, y))
        elif kind in ("GIMBAL_MANAGER_SET_PITCHYAW", "GIMBAL_MANAGER_SET_ATTITUDE"):
            if msg.target_component not in (0, self.compid):
                return
            if kind == "GIMBAL_MANAGER_SET_PITCHYAW" and self.flavour == "px4":
                self.unhandled += 1
                return
            if source != self.primary:
                self.ignored += 1
                return
            if kind == "GIMBAL_MANAGER_SET_PITCHYAW":
                angles, rates = (msg.pitch, msg.yaw), (msg.pitch_rate, msg.yaw_rate)
            else:
                q = [float(v) for v in msg.q]
                euler = QuaternionBase(q).euler if all(math.isfinite(v) for v in q) else (math.nan,) * 3
                angles, rates = (float(euler[1]), float(euler[2])), (msg.angular_velocity_y, msg.angular_velocity_z)
            if all(math.isfinite(v) for v in angles):
                self.target = ("angle", *angles)
            elif all(math.isfinite(v) for v in rates):
                self.target = ("rate", *rates)
            self.commands.append((r.at, rates[0], rates[1], angles[0], angles[1], msg.flags))


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
        self.pattern: list[str] | None = None  # states to cycle through, one per update (a flickering score)
        self.drift = 1.0  # px per update

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
            state = self.pattern[len(self.updates) % len(self.pattern)] if self.pattern else self.state
            if state != "lost":
                self.box = (x + self.drift, y, w, h)
            score = {"tracking": 0.55, "uncertain": 0.45}.get(state, 0.1) if self.pattern else None
            score = score if score is not None else (0.9 if state == "tracking" else 0.3)
            result = FakeResult(self.box, score, state, {"total": 0.001})
            self.updates.append((time.monotonic(), state, self.box))
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
        autopilot: Any = None,
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
        make = autopilot or (lambda url, **kw: Autopilot(url, flavour, **kw))
        self.ap = make(f"udpout:127.0.0.1:{self.port}", key=ap_key)
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


class Running:
    """A service running in a thread for the length of a `with` block; it must stop when the block ends."""

    def __init__(self, service: Service) -> None:
        self.service = service
        self.thread = threading.Thread(target=service.run, daemon=True)

    def __enter__(self) -> Service:
        self.thread.start()
        assert self.service.started.wait(5)
        return self.service

    def __exit__(self, *exc: object) -> None:
        self.service.stop()
        self.thread.join(10)
        assert not self.thread.is_alive()
