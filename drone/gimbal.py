"""Gimbal following (`--follow gimbal`): the MAVLink gimbal manager protocol (v2) from the tracked box.

Pure like follow.py: no sockets and no clock of its own; `step` returns the messages to send now.

Protocol (common.xml, "Gimbal Protocol v2"):
- the gimbal manager (usually the autopilot, or a gimbal component) broadcasts GIMBAL_MANAGER_STATUS with
  who has primary control; its source ids are where our commands go (the autopilot, component 1, until one
  has been heard);
- with a target, we take primary control with MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE (param1/2: our system and
  component, secondary left unchanged, param7 the gimbal device), retried every `configure_retry` seconds
  until it is ACCEPTED or GIMBAL_MANAGER_STATUS names us, at most `configure_tries` times;
- in control: GIMBAL_MANAGER_SET_PITCHYAW at `rate_hz` with NaN angles and pitch/yaw rates from the box's
  offset from the image centre (positive yaw: right, positive pitch: up), clamped to `max_rate`; the yaw is
  earth-locked (GIMBAL_MANAGER_FLAGS_YAW_LOCK) so that the vehicle turning does not drag the camera;
- target lost or not trusted, or a detection older than `stale_after`: zero rates at once, then zero rates at
  the stream rate (the gimbal holds still, ready for the target to come back);
- tracking stopped (or an error), or the service stopping: zero rates, then control released
  (MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE with -3: "remove control if currently in control");
- someone else takes primary control (a pilot in the ground station): we stop sending and do not take it
  back until the next target.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

from .follow import ACTIVE_STATES, TARGET_STATES, Detection, Trust
from .mav import mavlink

log = logging.getLogger(__name__)

NAN = float("nan")
FLAGS = (  # horizon-stabilised, yaw earth-locked
    mavlink.GIMBAL_MANAGER_FLAGS_ROLL_LOCK
    | mavlink.GIMBAL_MANAGER_FLAGS_PITCH_LOCK
    | mavlink.GIMBAL_MANAGER_FLAGS_YAW_LOCK
)
LEAVE, RELEASE = -1.0, -3.0  # MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE special values
IDLE, REQUESTING, CONTROL, REFUSED, OVERRIDDEN = "idle", "requesting", "control", "refused", "overridden"


@dataclass(frozen=True)
class GimbalConfig:
    rate_hz: float = 20.0  # SET_PITCHYAW rate while in control (10-50)
    gain: float = 1.0  # rad/s per unit offset (−1..1 from the image centre to its edge)
    max_rate: float = math.radians(60.0)  # rad/s, each axis
    deadband: float = 0.02
    stale_after: float = 0.2
    gimbal_device_id: int = 0  # 0: all the manager's gimbals
    configure_retry: float = 1.0
    configure_tries: int = 5
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


def _clamp(value: float, limit: float) -> float:
    return max(-limit, min(limit, value))


def rates_for(det: Detection, config: GimbalConfig) -> Rates:
    """Turn towards the box centre: right of centre → yaw right, below centre → pitch down."""
    x, y, w, h = det.box
    width, height = det.frame_size
    ex = 2.0 * (x + w / 2) / width - 1.0
    ey = 2.0 * (y + h / 2) / height - 1.0
    ex = 0.0 if abs(ex) < config.deadband else ex
    ey = 0.0 if abs(ey) < config.deadband else ey
    return Rates(_clamp(-config.gain * ey, config.max_rate), _clamp(config.gain * ex, config.max_rate))


class GimbalFollower:
    """Call `step` at the stream rate (periodic=True) and on every new detection (periodic=False); feed it the
    gimbal manager's COMMAND_ACKs and GIMBAL_MANAGER_STATUS with `on_message`."""

    def __init__(self, config: GimbalConfig) -> None:
        self.config = config
        self.state = IDLE
        self.reason = "no target"
        self.manager: tuple[int, int] | None = None  # (system, component) of the gimbal manager, once heard
        self.primary: tuple[int, int] | None = None  # who the manager says has primary control
        self.trust = Trust(config.trust_tau, config.trust_on, config.trust_off)
        self.sent_rates = STILL
        self._target_id: int | None = None
        self._refused_target: int | None = None  # no retry for this target (refused or overridden)
        self._next_configure = 0.0
        self._tries = 0

    # -- what the manager says ------------------------------------------------------------------------
    def on_message(self, msg: Any, me: tuple[int, int]) -> None:
        kind = msg.get_type()
        source = (msg.get_srcSystem(), msg.get_srcComponent())
        if kind == "GIMBAL_MANAGER_STATUS":
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
        elif kind == "GIMBAL_MANAGER_INFORMATION" and self.manager is None:
            self.manager = source
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

    def _rates(self, me: tuple[int, int], rates: Rates) -> Any:
        system, component = self._address(me)
        self.sent_rates = rates
        return mavlink.MAVLink_gimbal_manager_set_pitchyaw_message(
            system, component, FLAGS, self.config.gimbal_device_id, NAN, NAN, rates.pitch, rates.yaw
        )

    def release(self, me: tuple[int, int]) -> list[Any]:
        """Zero rates and give control back (tracking stopped, or the service stopping)."""
        out: list[Any] = []
        if self.state == CONTROL:
            out = [self._rates(me, STILL), self._configure(me, take=False)]
        elif self.state == REQUESTING:
            out = [self._configure(me, take=False)]
        if out:
            self._go(IDLE, "released")
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
            self._next_configure = now + cfg.configure_retry
            return [self._configure(me, take=True)]
        # CONTROL
        assert det is not None
        fresh = now - det.stamp <= cfg.stale_after
        usable = fresh and det.state in ACTIVE_STATES and self.trust.trusted
        rates = rates_for(det, cfg) if usable else STILL
        if not periodic:
            if rates.is_zero and not self.sent_rates.is_zero:
                self.reason = "detection stale" if not fresh else f"target {det.state}"
                return [self._rates(me, STILL)]  # lost, untrusted or stale: still at once
            return []
        self.reason = "following" if usable else ("detection stale" if not fresh else f"target {det.state}")
        return [self._rates(me, rates)]
