"""The MAVLink thread: receives and dispatches, and sends the heartbeat, the 275 stream and the follow
setpoints on their schedules. A tracker result wakes it at once (through a pipe), so a 275 or a stop
setpoint leaves within a scheduler slice of the result, not a period later.

Heartbeat: MAV_TYPE_CAMERA at `heartbeat_hz` from the moment the link is open (as system 1 until the
autopilot's heartbeat gives its id, unless --sysid), only while the tracker loop is alive (it ticks at least
every 0.2 s, frames or not); system_status BOOT before the first frame, ACTIVE while frames arrive,
CRITICAL when they stop (the camera is being reopened).

Gimbal following: GIMBAL_MANAGER_STATUS / _INFORMATION, GIMBAL_DEVICE_ATTITUDE_STATUS and the gimbal manager's
COMMAND_ACKs from our system go to the GimbalFollower, and the autopilot's type from its heartbeat; its
messages leave on every new result and at its own rate.
"""

from __future__ import annotations

import logging
import os
import select
import threading
import time
from dataclasses import dataclass, field
from typing import Any

from .camera import STALLED_AFTER, CameraComponent, tracking_status
from .follow import PX4_AUTO, PX4_AUTO_LOITER, ZERO, Autopilot, Detection, Follower, Setpoint
from .gimbal import SETPOINT_MESSAGES, GimbalFollower
from .link import Link, is_autopilot_heartbeat
from .logs import Throttle
from .mav import mavlink
from .tracking import Snapshot, TrackFeed

log = logging.getLogger(__name__)

TYPE_MASK_VELOCITY_YAW_RATE = (
    mavlink.POSITION_TARGET_TYPEMASK_X_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_Y_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_Z_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_AX_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_AY_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_AZ_IGNORE
    | mavlink.POSITION_TARGET_TYPEMASK_YAW_IGNORE
)  # = 1479: velocity and yaw rate only
GIMBAL_MESSAGES = (
    "GIMBAL_MANAGER_STATUS",
    "GIMBAL_MANAGER_INFORMATION",
    "GIMBAL_DEVICE_ATTITUDE_STATUS",
    "COMMAND_ACK",
)
MAX_SLICE = 0.05  # longest select() wait: bounds how late a link open or a silence check can be


@dataclass
class LinkStats:
    heartbeats: int = 0
    statuses: int = 0
    setpoints: int = 0
    hold_requests: int = 0  # MAV_CMD_DO_SET_MODE Hold sent (PX4 OFFBOARD handed over)
    gimbal: int = 0  # GIMBAL_MANAGER_SET_PITCHYAW / _SET_ATTITUDE sent
    gimbal_reactions: list[float] = field(default_factory=list)  # result → the aim held (lost, stop), s
    latencies: list[float] = field(default_factory=list)  # tracker result → 275 sent, seconds

    def add_latency(self, value: float) -> None:
        self.latencies.append(value)
        if len(self.latencies) > 10_000:
            del self.latencies[:5_000]


class LinkLoop:
    def __init__(
        self,
        link: Link,
        camera: CameraComponent,
        feed: TrackFeed,
        stop: threading.Event,
        follower: Follower | None = None,
        heartbeat_hz: float = 1.0,
        loop_stall: float = 2.0,
        boot_time: float | None = None,
        gimbal: GimbalFollower | None = None,
    ) -> None:
        self.link, self.camera, self.feed, self.stop, self.follower = link, camera, feed, stop, follower
        self.gimbal = gimbal
        self._next_gimbal = 0.0
        self.heartbeat_period = 1.0 / heartbeat_hz
        self.loop_stall = loop_stall
        self.boot = time.monotonic() if boot_time is None else boot_time
        self.stats = LinkStats()
        self.autopilot: Autopilot | None = None
        self.autopilot_component = mavlink.MAV_COMP_ID_AUTOPILOT1
        self.tick_at = time.monotonic()
        self._seen_seq = 0
        self._status_key: tuple[str, int] | None = None
        self._next_heartbeat = 0.0
        self._next_setpoint = 0.0
        self._follow_state = "off"
        self._throttle = Throttle(log)
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        os.set_blocking(self._wake_w, False)
        feed.on_publish = self.wake

    def time_boot_ms(self) -> int:
        return int((time.monotonic() - self.boot) * 1000) & 0xFFFFFFFF

    def wake(self) -> None:
        try:
            os.write(self._wake_w, b"\0")
        except (BlockingIOError, OSError):
            pass  # the pipe is full: the loop is awake anyway

    # -- loop ---------------------------------------------------------------------------------------
    def run(self) -> None:
        try:
            while not self.stop.is_set():
                self.tick_at = time.monotonic()
                try:
                    self._iteration()
                except Exception as exc:  # never die on one packet or one send
                    self._throttle.log(logging.ERROR, "loop", "MAVLink loop error: %s", exc, exc_info=True)
                    time.sleep(0.01)
            self._shutdown()
        finally:
            os.close(self._wake_r)
            os.close(self._wake_w)
            self.link.close()

    def _iteration(self) -> None:
        now = time.monotonic()
        self.link.maintain(now)
        fds = [self._wake_r]
        fd = self.link.fileno()
        if fd is not None:
            fds.append(fd)
        timeout = min(max(self._next_deadline() - now, 0.0), MAX_SLICE)
        readable, _, _ = select.select(fds, [], [], timeout)
        if self._wake_r in readable:
            try:
                while os.read(self._wake_r, 4096):
                    pass
            except BlockingIOError:
                pass
        now = time.monotonic()
        for msg in self.link.receive(now):
            self._dispatch(msg, now)
        self._on_snapshot(time.monotonic())
        self._periodic(time.monotonic())

    def _next_deadline(self) -> float:
        deadlines = [self._next_heartbeat]
        wake = self.camera.stream.next_wake(self.feed.latest().active)
        if wake is not None:
            deadlines.append(wake)
        if self.follower is not None:
            deadlines.append(self._next_setpoint)
        if self.gimbal is not None:
            deadlines.append(self._next_gimbal)
        return min(deadlines)

    # -- receive ------------------------------------------------------------------------------------
    def _dispatch(self, msg: Any, now: float) -> None:
        kind = msg.get_type()
        if kind == "HEARTBEAT":
            if is_autopilot_heartbeat(msg) and self._is_our_autopilot(msg):
                self.autopilot = Autopilot(msg.autopilot, msg.type, msg.base_mode, msg.custom_mode, now)
                self.autopilot_component = msg.get_srcComponent()
                if self.gimbal is not None:
                    self.gimbal.autopilot = self.autopilot.flavour
        elif kind in ("COMMAND_LONG", "COMMAND_INT"):
            for reply in self.camera.handle(msg, self.link.sysid, now):
                self.link.send(reply, now)
        if self.gimbal is not None and kind in GIMBAL_MESSAGES and msg.get_srcSystem() == self.link.sysid:
            self.gimbal.on_message(msg, self._me, now)

    @property
    def _me(self) -> tuple[int, int]:
        return self.link.sysid, self.link.settings.component

    def _is_our_autopilot(self, msg: Any) -> bool:
        sysid = msg.get_srcSystem()
        if self.link.adopt_sysid(sysid):
            return True
        self._throttle.log(
            logging.WARNING, "apsys", "autopilot heartbeat from system %d ignored (ours is %s)", sysid, self.link.sysid
        )
        return False

    # -- tracker results ----------------------------------------------------------------------------
    def _on_snapshot(self, now: float) -> None:
        snapshot = self.feed.latest()
        if snapshot.seq == self._seen_seq:
            return
        self._seen_seq = snapshot.seq
        changed = (snapshot.state, snapshot.target_id) != self._status_key
        if self.camera.stream.poll(now, fresh=True, active=snapshot.active, changed=changed):
            self._send_status(snapshot, now, fresh=True)
        if self.follower is not None:
            self._send_setpoint(self.follower.step(now, self.autopilot, _detection(snapshot), periodic=False), now)
        if self.gimbal is not None:
            messages = self.gimbal.step(now, _detection(snapshot), self._me, periodic=False)
            self._send_gimbal(messages, now)
            if any(m.get_type() in SETPOINT_MESSAGES for m in messages):
                self.stats.gimbal_reactions.append(time.monotonic() - snapshot.result_time)
                del self.stats.gimbal_reactions[:-1000]

    def _send_status(self, snapshot: Snapshot, now: float, fresh: bool) -> None:
        stalled = not fresh and now - snapshot.result_time > STALLED_AFTER
        if self.link.send(tracking_status(snapshot, stalled), now):
            self.stats.statuses += 1
            self._status_key = (snapshot.state, snapshot.target_id)
            if fresh:
                self.stats.add_latency(time.monotonic() - snapshot.result_time)

    # -- schedules ----------------------------------------------------------------------------------
    def _periodic(self, now: float) -> None:
        if now >= self._next_heartbeat:
            self._next_heartbeat = _advance(self._next_heartbeat, self.heartbeat_period, now)
            if now - self.feed.loop_tick_at <= self.loop_stall:
                if self.link.send(self._heartbeat(now), now):
                    self.stats.heartbeats += 1
            else:
                self._throttle.log(logging.ERROR, "stall", "tracker loop stalled: heartbeat withheld")
        snapshot = self.feed.latest()
        if self.camera.stream.poll(now, fresh=False, active=snapshot.active, changed=False):
            self._send_status(snapshot, now, fresh=False)
        if self.follower is not None and now >= self._next_setpoint:
            self._next_setpoint = _advance(self._next_setpoint, 1.0 / self.follower.config.rate_hz, now)
            self._send_setpoint(self.follower.step(now, self.autopilot, _detection(snapshot), periodic=True), now)
        if self.gimbal is not None and now >= self._next_gimbal:
            self._next_gimbal = _advance(self._next_gimbal, 1.0 / self.gimbal.config.rate_hz, now)
            self._send_gimbal(self.gimbal.step(now, _detection(snapshot), self._me, periodic=True), now)

    def _send_gimbal(self, messages: list[Any], now: float) -> None:
        for msg in messages:
            if self.link.send(msg, now) and msg.get_type() in SETPOINT_MESSAGES:
                self.stats.gimbal += 1

    def _heartbeat(self, now: float) -> Any:
        last = self.feed.last_frame_at
        if last is None:
            state = mavlink.MAV_STATE_BOOT
        elif now - last <= self.loop_stall:
            state = mavlink.MAV_STATE_ACTIVE
        else:
            state = mavlink.MAV_STATE_CRITICAL
        return mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_CAMERA, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, state, 3)

    def _send_setpoint(self, setpoint: Setpoint | None, now: float) -> None:
        assert self.follower is not None
        if self.follower.state != self._follow_state:
            log.info("follow: %s -> %s (%s)", self._follow_state, self.follower.state, self.follower.reason)
            self._follow_state = self.follower.state
        if setpoint is None:
            return
        v = setpoint.velocity
        msg = mavlink.MAVLink_set_position_target_local_ned_message(
            self.time_boot_ms(), self.link.sysid, self.autopilot_component, mavlink.MAV_FRAME_BODY_NED,
            TYPE_MASK_VELOCITY_YAW_RATE, 0.0, 0.0, 0.0, v.forward, v.right, v.down, 0.0, 0.0, 0.0, 0.0, v.yaw_rate,
        )  # fmt: skip
        if self.link.send(msg, now):
            self.stats.setpoints += 1
        if setpoint.hold:
            self._ask_for_hold(now)

    def _ask_for_hold(self, now: float) -> None:
        """MAV_CMD_DO_SET_MODE to PX4's Hold (AUTO_LOITER): the end of an OFFBOARD stream without failsafe."""
        command = mavlink.MAVLink_command_long_message(
            self.link.sysid, self.autopilot_component, mavlink.MAV_CMD_DO_SET_MODE, 0,
            float(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED), float(PX4_AUTO), float(PX4_AUTO_LOITER), 0, 0, 0, 0,
        )  # fmt: skip
        if self.link.send(command, now):
            self.stats.hold_requests += 1
            self._throttle.log(logging.INFO, "hold", "follow: asking PX4 for Hold before the setpoint stream ends")

    def _shutdown(self) -> None:
        """Stopping while commanding the vehicle: one last zero velocity (and, PX4 in OFFBOARD, Hold)."""
        ap = self.autopilot
        hold = self.follower is not None and self.follower.state != "off"
        hold = hold and ap is not None and ap.flavour == "px4" and ap.in_control_mode
        if self.follower is not None and (self.follower.state not in ("off", "prestream") or hold):
            self._send_setpoint(Setpoint(ZERO, "service stopping", hold=hold), time.monotonic())
            log.info("follow: zero velocity%s sent on shutdown", " and Hold" if hold else "")
        if self.gimbal is not None:
            messages = self.gimbal.release(self._me)
            if messages:
                self._send_gimbal(messages, time.monotonic())
                log.info("gimbal: aim held and control released on shutdown")


def _advance(due: float, period: float, now: float) -> float:
    """Next deadline: keeps the phase (mean rate exact) unless more than a period behind."""
    due += period
    return now + period if due <= now else due


def _detection(snapshot: Snapshot) -> Detection:
    return Detection(
        snapshot.target_id,
        snapshot.state,
        snapshot.box or (0.0, 0.0, 0.0, 0.0),
        snapshot.frame_size,
        snapshot.frame_stamp,
    )
