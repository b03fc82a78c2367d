"""Gimbal following (`--follow gimbal`): the MAVLink gimbal manager protocol (v2) from the tracked box.

Pure like follow.py: no sockets and no clock of its own; `step` returns the messages to send now.

Protocol (common.xml, "Gimbal Protocol v2"):
- the gimbal manager (usually the autopilot, or a gimbal component) broadcasts GIMBAL_MANAGER_STATUS with
  who has primary control; its source ids are where our commands go (the autopilot, component 1, until one
  has been heard);
- with a target, we take primary control with MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE (param1/2: our system and
  component, secondary left unchanged, param7 the gimbal device), retried every `configure_retry` seconds
  until it is ACCEPTED or GIMBAL_MANAGER_STATUS names us, at most `configure_tries` times; with it go
  MAV_CMD_SET_MESSAGE_INTERVAL for GIMBAL_DEVICE_ATTITUDE_STATUS (where the gimbal points now) and
  MAV_CMD_REQUEST_MESSAGE for GIMBAL_MANAGER_INFORMATION (its angle limits: an aim past them would wind up,
  and the gimbal would sit at its stop while the aim came back);
- someone else takes primary control (a pilot in the ground station): we stop sending and do not take it
  back until the next target.

Angle targets, not rates. The box gives pitch/yaw rates (`rates_for`: offset from the image centre, clamped
to `max_rate`), but what goes out is an *angle*: the aim, started from the gimbal's reported attitude when we
take control and moved by rate × time at every step (what ArduPilot's mount library does itself with a rate
target). A rate target is kept by both autopilots until replaced (ArduPilot 4.6 and 4.7.0-dev
forever, 4.7 master for 3 s; PX4's gimbal module forever), so a service that dies, hangs or loses
its link mid-follow would leave the camera turning to its stops. An angle target that is no longer updated
just holds: the gimbal stops where the last aim was (for a servo mount at once; a gimbal with its own
controller after its own lag). Without a reported attitude there is no safe start, so the gimbal is not
moved (logged, `reason` says so).

Each autopilot gets what it acts on (HEARTBEAT autopilot type, `autopilot`):
- PX4: GIMBAL_MANAGER_SET_ATTITUDE with the aim as a quaternion and NaN angular rates (PX4's MAVLink receiver
  has no handler for GIMBAL_MANAGER_SET_PITCHYAW). Yaw in the vehicle frame: PX4 reports its output angles,
  which are vehicle-relative, and only then do the two agree whatever MNT_DO_STAB says;
- ArduPilot and anything else: GIMBAL_MANAGER_SET_PITCHYAW with the aim's angles and NaN rates, yaw in the
  frame the gimbal reports its attitude in (ArduPilot: the vehicle frame) so that the aim starts where the
  gimbal is; earth-locked (GIMBAL_MANAGER_FLAGS_YAW_LOCK) only where the attitude is earth-framed.

Target lost, not trusted, or a detection older than `stale_after`: the aim stops moving at once (the last
aim again on the result itself) and is repeated at the stream rate. Tracking stopped (or an error), or the
service stopping: the aim once more, then control released (MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE with -3:
"remove control if currently in control"); the gimbal stays where it points.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

from pymavlink.quaternion import QuaternionBase

from .follow import ACTIVE_STATES, TARGET_STATES, Detection, Trust
from .mav import mavlink

log = logging.getLogger(__name__)

NAN = float("nan")
LOCKS = mavlink.GIMBAL_MANAGER_FLAGS_ROLL_LOCK | mavlink.GIMBAL_MANAGER_FLAGS_PITCH_LOCK  # horizon-stabilised
LEAVE, RELEASE = -1.0, -3.0  # MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE special values
IDLE, REQUESTING, CONTROL, REFUSED, OVERRIDDEN = "idle", "requesting", "control", "refused", "overridden"
SETPOINT_MESSAGES = ("GIMBAL_MANAGER_SET_PITCHYAW", "GIMBAL_MANAGER_SET_ATTITUDE")
ATTITUDE_INTERVAL_US = 50_000.0  # GIMBAL_DEVICE_ATTITUDE_STATUS at 20 Hz while we point the gimbal
MAX_STEP = 0.2  # s: the most time one step moves the aim (a stalled loop does not jump the gimbal)


@dataclass(frozen=True)
class GimbalConfig:
    rate_hz: float = 20.0  # setpoint rate while in control (10-50)
    gain: float = 1.0  # rad/s per unit offset (−1..1 from the image centre to its edge)
    max_rate: float = math.radians(60.0)  # rad/s, each axis
    deadband: float = 0.02
    stale_after: float = 0.2
    gimbal_device_id: int = 0  # 0: all the manager's gimbals
    configure_retry: float = 1.0
    configure_tries: int = 5
    attitude_timeout: float = 1.0  # s: an attitude report older than this is no start for the aim
    trust_tau: float = 0.3
    trust_on: float = 0.7
    trust_off: float = 0.3


@dataclass(frozen=True)
class Rates:
    pitch: float = 0.0  # rad/s, positive up
    yaw: float = 0.0  # rad/s, positive right

    @property
    def is_zero(self) -> bool:
        return self.pitch == 0.0 and self.yaw == 0.0


STILL = Rates()


@dataclass(frozen=True)
class Aim:
    """Where the gimbal is told to point: pitch (positive up) and yaw (positive right), radians; yaw in the
    earth frame when `earth`, else relative to the vehicle's nose."""

    pitch: float
    yaw: float
    earth: bool = False


@dataclass(frozen=True)
class Limits:
    """The gimbal manager's angle limits (GIMBAL_MANAGER_INFORMATION), radians."""

    pitch_min: float = -math.pi / 2
    pitch_max: float = math.pi / 2
    yaw_min: float = -math.pi
    yaw_max: float = math.pi


def _clamp(value: float, limit: float) -> float:
    return max(-limit, min(limit, value))


def _wrap(angle: float) -> float:
    return math.remainder(angle, 2 * math.pi)


def rates_for(det: Detection, config: GimbalConfig) -> Rates:
    """Turn towards the box centre: right of centre → yaw right, below centre → pitch down."""
    x, y, w, h = det.box
    width, height = det.frame_size
    ex = 2.0 * (x + w / 2) / width - 1.0
    ey = 2.0 * (y + h / 2) / height - 1.0
    ex = 0.0 if abs(ex) < config.deadband else ex
    ey = 0.0 if abs(ey) < config.deadband else ey
    return Rates(_clamp(-config.gain * ey, config.max_rate), _clamp(config.gain * ex, config.max_rate))


def advance(aim: Aim, rates: Rates, dt: float, limits: Limits) -> Aim:
    """The aim moved by rates × dt, kept inside the gimbal's limits: a vehicle-frame yaw stops at them (never
    wrapped: +181° would send the gimbal the long way round to -179°), an earth-frame yaw is wrapped."""
    pitch = min(max(aim.pitch + rates.pitch * dt, limits.pitch_min), limits.pitch_max)
    yaw = aim.yaw + rates.yaw * dt
    yaw = _wrap(yaw) if aim.earth else min(max(yaw, limits.yaw_min), limits.yaw_max)
    return Aim(pitch, yaw, aim.earth)


def attitude_of(msg: Any, px4: bool = False) -> Aim | None:
    """Pitch and yaw of a GIMBAL_DEVICE_ATTITUDE_STATUS, in the frame its flags give (YAW_IN_EARTH_FRAME, or
    neither frame flag and YAW_LOCK: earth, except behind PX4, whose own reports set YAW_LOCK over a vehicle-
    frame yaw; otherwise the vehicle's); None for a quaternion that is not one."""
    q = [float(v) for v in msg.q]
    if not all(math.isfinite(v) for v in q) or abs(math.fsum(v * v for v in q) - 1.0) > 0.1:
        return None
    _, pitch, yaw = QuaternionBase(q).euler
    flags = msg.flags
    if flags & mavlink.GIMBAL_DEVICE_FLAGS_YAW_IN_EARTH_FRAME:
        earth = True
    elif flags & mavlink.GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME:
        earth = False
    else:
        earth = bool(flags & mavlink.GIMBAL_DEVICE_FLAGS_YAW_LOCK) and not px4
    return Aim(float(pitch), float(yaw), earth)


class GimbalFollower:
    """Call `step` at the stream rate (periodic=True) and on every new detection (periodic=False); feed it the
    gimbal manager's COMMAND_ACKs, GIMBAL_MANAGER_STATUS / _INFORMATION and GIMBAL_DEVICE_ATTITUDE_STATUS with
    `on_message`, and the autopilot's type ('ardupilot', 'px4' or 'other', from its HEARTBEAT) in
    `autopilot`."""

    def __init__(self, config: GimbalConfig) -> None:
        self.config = config
        self.state = IDLE
        self.reason = "no target"
        self.autopilot = "other"
        self.manager: tuple[int, int] | None = None  # (system, component) of the gimbal manager, once heard
        self.primary: tuple[int, int] | None = None  # who the manager says has primary control
        self.limits = Limits()
        self.attitude: Aim | None = None  # the gimbal's last reported attitude
        self.attitude_at = -math.inf
        self.aim: Aim | None = None  # what we last told it (None: not started in this control)
        self.trust = Trust(config.trust_tau, config.trust_on, config.trust_off)
        self.sent_rates = STILL  # the rates the aim last moved by
        self._aim_time = 0.0
        self._target_id: int | None = None
        self._refused_target: int | None = None  # no retry for this target (refused or overridden)
        self._next_configure = 0.0
        self._next_interval = 0.0
        self._tries = 0
        self._warned_attitude = False

    # -- what the manager says ------------------------------------------------------------------------
    def on_message(self, msg: Any, me: tuple[int, int], now: float = 0.0) -> None:
        kind = msg.get_type()
        source = (msg.get_srcSystem(), msg.get_srcComponent())
        if kind == "GIMBAL_DEVICE_ATTITUDE_STATUS":
            device = getattr(msg, "gimbal_device_id", 0)
            if self.config.gimbal_device_id and device not in (0, self.config.gimbal_device_id):
                return
            attitude = attitude_of(msg, px4=self.autopilot == "px4")
            if attitude is not None:
                self.attitude, self.attitude_at = attitude, now
        elif kind == "GIMBAL_MANAGER_STATUS":
            if self.config.gimbal_device_id and msg.gimbal_device_id not in (0, self.config.gimbal_device_id):
                return
            if self.manager != source:
                log.info("gimbal manager: system %d component %d", *source)
            self.manager = source
            self.primary = (msg.primary_control_sysid, msg.primary_control_compid)
            if self.state == REQUESTING and self.primary == me:
                self._go(CONTROL, "in primary control")
            elif self.state == CONTROL and self.primary != me and self.primary != (0, 0):
                log.warning("gimbal: control taken by system %d component %d; not taking it back", *self.primary)
                self._go(OVERRIDDEN, f"control taken by {self.primary[0]}/{self.primary[1]}")
                self._refused_target = self._target_id
        elif kind == "GIMBAL_MANAGER_INFORMATION":
            if self.manager is None:
                self.manager = source
            limits = (msg.pitch_min, msg.pitch_max, msg.yaw_min, msg.yaw_max)
            if all(math.isfinite(v) for v in limits) and msg.pitch_min <= msg.pitch_max and msg.yaw_min <= msg.yaw_max:
                self.limits = Limits(*limits)
        elif kind == "COMMAND_ACK" and msg.command == mavlink.MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE:
            if msg.target_system not in (0, me[0]) or msg.target_component not in (0, me[1]):
                return
            if self.state != REQUESTING:
                return
            if msg.result == mavlink.MAV_RESULT_ACCEPTED:
                self._go(CONTROL, "configure accepted")
            elif msg.result != mavlink.MAV_RESULT_IN_PROGRESS:
                log.warning("gimbal manager refused control (result %d)", msg.result)
                self._go(REFUSED, f"configure result {msg.result}")
                self._refused_target = self._target_id

    def _go(self, state: str, reason: str) -> None:
        if state != self.state:
            log.info("gimbal: %s -> %s (%s)", self.state, state, reason)
            if state == CONTROL:
                self.aim = None  # start again from where the gimbal points now
        self.state, self.reason = state, reason

    # -- messages -------------------------------------------------------------------------------------
    def _address(self, me: tuple[int, int]) -> tuple[int, int]:
        return self.manager or (me[0], mavlink.MAV_COMP_ID_AUTOPILOT1)

    def _configure(self, me: tuple[int, int], take: bool) -> Any:
        system, component = self._address(me)
        p1, p2 = (float(me[0]), float(me[1])) if take else (RELEASE, RELEASE)
        return mavlink.MAVLink_command_long_message(
            system, component, mavlink.MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE, 0,
            p1, p2, LEAVE, LEAVE, 0.0, 0.0, float(self.config.gimbal_device_id),
        )  # fmt: skip

    def _attitude_interval(self, me: tuple[int, int]) -> Any:
        system, component = self._address(me)
        return mavlink.MAVLink_command_long_message(
            system, component, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
            float(mavlink.MAVLINK_MSG_ID_GIMBAL_DEVICE_ATTITUDE_STATUS), ATTITUDE_INTERVAL_US, 0, 0, 0, 0, 0,
        )  # fmt: skip

    def _request_limits(self, me: tuple[int, int]) -> Any:
        system, component = self._address(me)
        return mavlink.MAVLink_command_long_message(
            system, component, mavlink.MAV_CMD_REQUEST_MESSAGE, 0,
            float(mavlink.MAVLINK_MSG_ID_GIMBAL_MANAGER_INFORMATION), 0, 0, 0, 0, 0, 0,
        )  # fmt: skip

    def _point(self, me: tuple[int, int], aim: Aim) -> Any:
        """The aim in the message this autopilot acts on (see the module docstring)."""
        system, component = self._address(me)
        self.aim = aim
        device = self.config.gimbal_device_id
        if self.autopilot == "px4":
            q = [float(v) for v in QuaternionBase([0.0, aim.pitch, aim.yaw]).q]
            return mavlink.MAVLink_gimbal_manager_set_attitude_message(
                system, component, LOCKS, device, q, NAN, NAN, NAN
            )
        flags = LOCKS | (mavlink.GIMBAL_MANAGER_FLAGS_YAW_LOCK if aim.earth else 0)
        return mavlink.MAVLink_gimbal_manager_set_pitchyaw_message(
            system, component, flags, device, aim.pitch, aim.yaw, NAN, NAN
        )

    def release(self, me: tuple[int, int]) -> list[Any]:
        """Hold the last aim and give control back (tracking stopped, or the service stopping)."""
        out: list[Any] = []
        if self.state == CONTROL:
            out = ([self._point(me, self.aim)] if self.aim is not None else []) + [self._configure(me, take=False)]
        elif self.state == REQUESTING:
            out = [self._configure(me, take=False)]
        if out:
            self._go(IDLE, "released")
        self.sent_rates = STILL
        return out

    # -- the state machine ----------------------------------------------------------------------------
    def step(self, now: float, det: Detection | None, me: tuple[int, int], periodic: bool = True) -> list[Any]:
        cfg = self.config
        if det is not None and det.target_id != self._target_id and det.state in ACTIVE_STATES:
            self._target_id = det.target_id
            if self.state in (REFUSED, OVERRIDDEN):
                self._go(IDLE, "new target")
        if det is not None and det.target_id == self._target_id:
            self.trust.update(det.target_id, det.state, det.stamp)
        present = det is not None and det.target_id == self._target_id and det.state in TARGET_STATES
        if not present:
            return self.release(me)
        if self.state in (REFUSED, OVERRIDDEN):
            return []
        if self.state == IDLE:
            if self._refused_target == self._target_id or det is None or det.state != "tracking":
                return []
            self._go(REQUESTING, "taking primary control")
            self._tries, self._next_configure = 0, now
        if self.state == REQUESTING:
            if now < self._next_configure:
                return []
            if self._tries >= cfg.configure_tries:
                log.warning("gimbal manager did not answer %d configure commands; giving up", self._tries)
                self._go(REFUSED, "no answer")
                self._refused_target = self._target_id
                return []
            self._tries += 1
            self._next_configure = self._next_interval = now + cfg.configure_retry
            return [self._configure(me, take=True), self._attitude_interval(me), self._request_limits(me)]
        # CONTROL
        assert det is not None
        if self.aim is None:
            return self._start_aim(now, me) if periodic else []
        fresh = now - det.stamp <= cfg.stale_after
        usable = fresh and det.state in ACTIVE_STATES and self.trust.trusted
        rates = rates_for(det, cfg) if usable else STILL
        if not periodic:
            if rates.is_zero and not self.sent_rates.is_zero:
                self.reason = "detection stale" if not fresh else f"target {det.state}"
                self.sent_rates = STILL
                self._aim_time = now
                return [self._point(me, self.aim)]  # lost, untrusted or stale: the aim stops at once
            return []
        self.reason = "following" if usable else ("detection stale" if not fresh else f"target {det.state}")
        aim = advance(self.aim, rates, min(max(now - self._aim_time, 0.0), MAX_STEP), self.limits)
        self.sent_rates, self._aim_time = rates, now
        return [self._point(me, aim)]

    def _start_aim(self, now: float, me: tuple[int, int]) -> list[Any]:
        """In control, the aim not started: from the gimbal's reported attitude once there is a fresh one."""
        if self.attitude is not None and now - self.attitude_at <= self.config.attitude_timeout:
            if self.autopilot == "px4" and self.attitude.earth:
                # SET_ATTITUDE goes to PX4 in the vehicle frame: a compass heading sent there would swing the
                # gimbal by the vehicle's heading the moment control is taken
                self.reason = "the gimbal reports its yaw in the earth frame; PX4 is aimed in the vehicle frame"
                return []
            self._warned_attitude = False
            self.sent_rates, self._aim_time = STILL, now
            return [self._point(me, self.attitude)]
        self.reason = "waiting for the gimbal attitude (GIMBAL_DEVICE_ATTITUDE_STATUS)"
        if now < self._next_interval:
            return []
        self._next_interval = now + self.config.configure_retry
        if not self._warned_attitude and self._tries >= self.config.configure_tries:
            log.warning("gimbal: no GIMBAL_DEVICE_ATTITUDE_STATUS from the gimbal manager; not moving the gimbal")
            self._warned_attitude = True
        self._tries += 1
        return [self._attitude_interval(me)]
