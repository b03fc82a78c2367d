"""Follow controller: body-frame velocity and yaw rate from the tracked box, and the safety state machine
that decides when they may be sent.

Pure: no MAVLink and no clock of its own (callers pass `now`, monotonic seconds), so every rule is
unit-testable. The service turns a `Setpoint` into SET_POSITION_TARGET_LOCAL_NED (MAV_FRAME_BODY_NED,
velocity + yaw rate).

Safety rules:
- commands only while the autopilot's heartbeat (at most `heartbeat_timeout` old) says armed and in
  ArduCopter GUIDED or PX4 OFFBOARD; leaving that mode or disarming ends commanding without another word
  (PX4: leaving OFFBOARD goes back to streaming zeros, see below);
- target lost or tracking stopped, a detection older than `stale_after`, or the heartbeat lost: zero
  velocity at once (repeated `stop_repeats` times at the setpoint rate against packet loss), then nothing;
- trust (hysteresis): the controller follows the *trusted* target, not the tracker's raw state. Each new
  result moves a level towards 1 ('tracking') or 0 (anything else) with time constant `trust_tau`
  (frame time); trust is lost when the level falls to `trust_off` and regained when it climbs back to
  `trust_on`. A score hovering around the tracker's threshold (tracking/uncertain at frame rate) leaves
  the level in between and the controller where it was; a new target starts trusted (its init box);
- 'uncertain' (not trusted) holds: the velocity slews to zero and streaming goes on until the target is
  trusted again (follow) or lost (stop);
- PX4 only switches into OFFBOARD while setpoints are streaming, and fails safe when they pause
  (COM_OF_LOSS_T). So with an armed PX4 vehicle and a target (tracking, uncertain or lost: the tracker is
  still on it), the stream never pauses: zeros outside OFFBOARD (PX4 ignores them there), zeros in
  OFFBOARD whenever the detection is not trusted (lost or stale: zero at once, no slew), and real ones
  only after `prestream` seconds of streaming. Disarming, or the autopilot's heartbeat lost, ends it
  (zeros, then nothing); so does the target ending (stopped, or an error) outside OFFBOARD.
- PX4 in OFFBOARD when the target ends: a stream that stops is PX4's offboard-loss failsafe `COM_OF_LOSS_T`
  later, and with PX4's defaults and no RC that failsafe lands the vehicle. So we hand it over (HANDOVER):
  zeros go on streaming while we ask for Hold (MAV_CMD_DO_SET_MODE AUTO_LOITER, the mode MAVSDK's
  offboard stop hands over to; `Setpoint.hold` asks the link loop to send it, every `hold_retry` s), and
  end only when the heartbeat says the vehicle left OFFBOARD (Hold, or the pilot's choice) or disarmed. A
  PX4 that refuses Hold thus keeps getting zeros and holds in OFFBOARD. ArduCopter GUIDED needs none of
  this: it holds by itself `GUID_TIMEOUT` after the last setpoint.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

# MAVLink numbers (HEARTBEAT fields); tests check them against pymavlink.
AUTOPILOT_ARDUPILOT = 3  # MAV_AUTOPILOT_ARDUPILOTMEGA
AUTOPILOT_PX4 = 12  # MAV_AUTOPILOT_PX4
MODE_FLAG_ARMED = 128  # MAV_MODE_FLAG_SAFETY_ARMED
# MAV_TYPE of ArduCopter frames: quad, coaxial, heli, hexa, octo, tri, dodeca, deca
COPTER_TYPES = frozenset({2, 3, 4, 13, 14, 15, 29, 35})
ARDUCOPTER_GUIDED = 4  # copter custom_mode; 4 is AUTOTUNE on ArduPlane, hence the frame check
PX4_OFFBOARD = 6  # PX4 main mode, custom_mode bits 16-23
PX4_AUTO, PX4_AUTO_LOITER = 4, 3  # Hold: main mode AUTO, sub mode (bits 24-31) LOITER

OFF, PRESTREAM, FOLLOW, HOLD, STOPPING, HANDOVER = "off", "prestream", "follow", "hold", "stopping", "handover"
ACTIVE_STATES = ("tracking", "uncertain")
TARGET_STATES = ("tracking", "uncertain", "lost")  # the tracker is still on a target (it may find it again)
MAX_TRUST_STEP = 0.2  # s: the most frame time one result counts for in the trust level


@dataclass(frozen=True)
class Autopilot:
    """The fields of the autopilot's last HEARTBEAT and when (monotonic) it arrived."""

    autopilot: int
    vehicle_type: int
    base_mode: int
    custom_mode: int
    stamp: float

    @property
    def armed(self) -> bool:
        return bool(self.base_mode & MODE_FLAG_ARMED)

    @property
    def flavour(self) -> str:
        return {AUTOPILOT_ARDUPILOT: "ardupilot", AUTOPILOT_PX4: "px4"}.get(self.autopilot, "other")

    @property
    def in_control_mode(self) -> bool:
        """ArduCopter GUIDED or PX4 OFFBOARD: the modes that take external velocity setpoints."""
        if self.autopilot == AUTOPILOT_ARDUPILOT:
            return self.vehicle_type in COPTER_TYPES and self.custom_mode == ARDUCOPTER_GUIDED
        if self.autopilot == AUTOPILOT_PX4:
            return (self.custom_mode >> 16) & 0xFF == PX4_OFFBOARD
        return False


@dataclass(frozen=True)
class Detection:
    """One tracker result as the controller sees it; `stamp` is when its frame was grabbed (monotonic)."""

    target_id: int
    state: str
    box: tuple[float, float, float, float]
    frame_size: tuple[int, int]
    stamp: float


@dataclass(frozen=True)
class Velocity:
    """Body frame: forward (x), right (y), down (z) in m/s; yaw rate in rad/s, positive turning right."""

    forward: float = 0.0
    right: float = 0.0
    down: float = 0.0
    yaw_rate: float = 0.0

    @property
    def is_zero(self) -> bool:
        return self.forward == self.right == self.down == self.yaw_rate == 0.0


@dataclass(frozen=True)
class Gains:
    """Errors are normalised: horizontal/vertical −1..1 from the image centre to its edge; size is
    ln(reference size / apparent size), positive when the target looks smaller than at the start."""

    yaw: float = 1.0  # rad/s per unit horizontal error
    lateral: float = 0.0  # m/s per unit horizontal error (0: yaw alone centres the target)
    vertical: float = 1.0  # m/s per unit vertical error, used only with altitude control on
    forward: float = 2.0  # m/s per unit size error
    deadband: float = 0.02  # smaller errors count as zero, so that a centred target gives no jitter


@dataclass(frozen=True)
class Limits:
    speed: float = 3.0  # m/s, horizontal magnitude
    climb: float = 1.0  # m/s, vertical
    yaw_rate: float = math.radians(45.0)  # rad/s
    accel: float = 2.0  # m/s² per axis (slew of the commanded velocity)
    yaw_accel: float = math.radians(90.0)  # rad/s²


@dataclass(frozen=True)
class FollowConfig:
    gains: Gains = field(default_factory=Gains)
    limits: Limits = field(default_factory=Limits)
    altitude: bool = False  # vertical control; off holds altitude (down velocity 0)
    rate_hz: float = 15.0
    stale_after: float = 0.2
    heartbeat_timeout: float = 2.0
    prestream: float = 1.0
    stop_repeats: int = 3
    trust_tau: float = 0.3  # s of frame time: how fast the trust level follows the tracker's state
    trust_on: float = 0.7  # level at which trust comes back
    trust_off: float = 0.3  # level at which it is lost
    hold_retry: float = 0.5  # s between requests for PX4 Hold while handing over


@dataclass(frozen=True)
class Setpoint:
    velocity: Velocity
    reason: str
    hold: bool = False  # also ask the autopilot for Hold (PX4 AUTO_LOITER)


ZERO = Velocity()


def apparent_size(box: tuple[float, float, float, float], frame_size: tuple[int, int]) -> float:
    """Square root of the box's share of the image area (0..1): scale-free distance cue."""
    w, h = max(box[2], 0.0), max(box[3], 0.0)
    return math.sqrt(w * h / max(frame_size[0] * frame_size[1], 1))


def _dead(value: float, band: float) -> float:
    return 0.0 if abs(value) < band else value


def _clamp(value: float, limit: float) -> float:
    return max(-limit, min(limit, value))


def velocity_for(det: Detection, reference: float, config: FollowConfig) -> Velocity:
    """The control law: yaw (and optionally strafe) towards the target, fly forward or back to keep its
    apparent size at `reference`, climb or descend only with altitude control; clamped to the limits."""
    g, lim = config.gains, config.limits
    x, y, w, h = det.box
    width, height = det.frame_size
    ex = _dead(2.0 * (x + w / 2) / width - 1.0, g.deadband)
    ey = _dead(2.0 * (y + h / 2) / height - 1.0, g.deadband)
    size = apparent_size(det.box, det.frame_size)
    es = _dead(math.log(reference / size), g.deadband) if size > 0 and reference > 0 else 0.0
    forward, right = g.forward * es, g.lateral * ex
    horizontal = math.hypot(forward, right)
    if horizontal > lim.speed:
        forward, right = forward * lim.speed / horizontal, right * lim.speed / horizontal
    down = _clamp(g.vertical * ey, lim.climb) if config.altitude else 0.0
    return Velocity(forward, right, down, _clamp(g.yaw * ex, lim.yaw_rate))


def slew(previous: Velocity, target: Velocity, dt: float, limits: Limits) -> Velocity:
    """Move from `previous` towards `target` by at most accel·dt per axis (yaw_accel·dt for yaw rate)."""
    dv, dy = limits.accel * dt, limits.yaw_accel * dt

    def step(a: float, b: float, most: float) -> float:
        return a + _clamp(b - a, most)

    return Velocity(
        step(previous.forward, target.forward, dv),
        step(previous.right, target.right, dv),
        step(previous.down, target.down, dv),
        step(previous.yaw_rate, target.yaw_rate, dy),
    )


class Trust:
    """Hysteresis on the tracker's state: `update` once per result (its frame time), `trusted` the verdict.

    Works on the state string alone (whatever score thresholds the tracker uses): 'tracking' pulls the level
    to 1, any other state to 0, as a first-order filter of time constant `tau` in frame time."""

    def __init__(self, tau: float = 0.3, on: float = 0.7, off: float = 0.3) -> None:
        self.tau, self.on, self.off = tau, on, off
        self.level, self.trusted = 1.0, True
        self._target: int | None = None
        self._stamp: float | None = None
        self.flips = 0

    def update(self, target_id: int, state: str, stamp: float) -> bool:
        if target_id != self._target:
            self._target, self._stamp = target_id, stamp
            self.level, self.trusted = (1.0, True) if state == "tracking" else (0.0, False)
            return self.trusted
        if self._stamp is not None and stamp <= self._stamp:
            return self.trusted  # the same result again
        dt = 0.0 if self._stamp is None else min(stamp - self._stamp, MAX_TRUST_STEP)  # a gap is not evidence
        self._stamp = stamp
        x = 1.0 if state == "tracking" else 0.0
        self.level += (1.0 - math.exp(-dt / self.tau) if self.tau > 0 else 1.0) * (x - self.level)
        if self.trusted and self.level <= self.off:
            self.trusted, self.flips = False, self.flips + 1
        elif not self.trusted and self.level >= self.on:
            self.trusted, self.flips = True, self.flips + 1
        return self.trusted


class Follower:
    """The safety state machine around `velocity_for`; call `step` at the setpoint rate (periodic=True)
    and on every new detection (periodic=False). It returns the setpoint to send now, or None."""

    def __init__(self, config: FollowConfig) -> None:
        self.config = config
        self.state = OFF
        self.reason = "no target"
        self.trust = Trust(config.trust_tau, config.trust_on, config.trust_off)
        self._target_id: int | None = None
        self._reference = 0.0
        self._last = ZERO
        self._last_time: float | None = None
        self._prestream_since = 0.0
        self._stops_left = 0
        self._next_hold = 0.0

    def _observe_target(self, det: Detection | None) -> None:
        if det is None:
            return
        if det.target_id != self._target_id and det.state in ACTIVE_STATES:
            self._target_id = det.target_id
            self._reference = apparent_size(det.box, det.frame_size)  # first box of a target: its init box
        if det.target_id == self._target_id:
            self.trust.update(det.target_id, det.state, det.stamp)

    def _go(self, state: str, reason: str) -> None:
        self.state, self.reason = state, reason

    def _stop(self, reason: str) -> Setpoint:
        self._go(STOPPING, reason)
        self._stops_left = self.config.stop_repeats - 1
        self._last, self._last_time = ZERO, None
        if self._stops_left <= 0:
            self._go(OFF, reason)
        return Setpoint(ZERO, f"stop: {reason}")

    def step(
        self, now: float, autopilot: Autopilot | None, det: Detection | None, periodic: bool = True
    ) -> Setpoint | None:
        cfg = self.config
        self._observe_target(det)
        heartbeat = autopilot is not None and now - autopilot.stamp <= cfg.heartbeat_timeout
        armed = heartbeat and autopilot is not None and autopilot.armed
        in_mode = heartbeat and autopilot is not None and autopilot.in_control_mode
        fresh = det is not None and now - det.stamp <= cfg.stale_after
        target = det.state if det is not None else "idle"
        ours = det is not None and det.target_id == self._target_id
        usable = fresh and target in ACTIVE_STATES and ours
        trusted = usable and self.trust.trusted

        if self.state != OFF:
            if not heartbeat:
                return self._stop("autopilot heartbeat lost") if self.state != STOPPING else self._stopping(periodic)
            if not armed:
                self._go(OFF, "disarmed")
                return None
            if self.state in (STOPPING, HANDOVER):
                if autopilot is not None and autopilot.flavour == "px4" and ours and target in TARGET_STATES:
                    if self.state == HANDOVER:
                        self._prestream_since = now  # Hold may still come: zeros first, as after a switch
                    return self._px4(now, in_mode, fresh, target, trusted, det, periodic)  # a target again
                if self.state == HANDOVER:
                    return self._handing_over(now, periodic) if in_mode else self._quiet_off(autopilot)
                return self._stopping(periodic) if in_mode else self._quiet_off(autopilot)
            if autopilot is not None and autopilot.flavour == "px4":
                if not (ours and target in TARGET_STATES):
                    if in_mode:
                        return self._handover(now, f"target {target}")
                    return self._stop(f"target {target}")
                return self._px4(now, in_mode, fresh, target, trusted, det, periodic)
            if not in_mode:
                return self._quiet_off(autopilot)
            if not usable:
                why = "detection stale" if not fresh else f"target {target}"
                return self._stop(why)
            self._go(FOLLOW if trusted else HOLD, f"target {target}" + ("" if trusted else " (not trusted)"))
            return self._command(now, det) if periodic and det is not None else None

        # OFF: engage only on a trusted target, armed, in the right mode (or PX4's stream before it)
        if not (armed and trusted and target == "tracking" and autopilot is not None):
            self.reason = self._why_off(heartbeat, armed, usable and trusted, target)
            return None
        if autopilot.flavour == "ardupilot" and in_mode:
            self._go(FOLLOW, "target tracking")
            self._last, self._last_time = ZERO, None
            return self._command(now, det) if periodic and det is not None else None
        if autopilot.flavour == "px4":
            self._go(PRESTREAM, "streaming zeros for OFFBOARD")
            self._prestream_since = now
            self._last, self._last_time = ZERO, None
            return Setpoint(ZERO, "prestream") if periodic else None
        self.reason = "autopilot mode does not take velocity setpoints"
        return None

    def _quiet_off(self, autopilot: Autopilot | None) -> None:
        self._go(OFF, f"mode {autopilot.custom_mode if autopilot else '?'} is not GUIDED/OFFBOARD")
        return None

    @staticmethod
    def _why_off(heartbeat: bool, armed: bool, usable: bool, target: str) -> str:
        if not heartbeat:
            return "no autopilot heartbeat"
        if not armed:
            return "disarmed"
        if not usable or target != "tracking":
            return f"target {target}" + (" (not trusted)" if target == "tracking" else "")
        return "mode"

    def _px4(
        self, now: float, in_mode: bool, fresh: bool, target: str, trusted: bool, det: Detection | None, periodic: bool
    ) -> Setpoint | None:
        """PX4 armed with a target: a setpoint on every periodic step, whatever the detection says."""
        moving = not self._last.is_zero
        if not in_mode or now - self._prestream_since < self.config.prestream:
            self._go(PRESTREAM, "streaming zeros for OFFBOARD" if not in_mode else "OFFBOARD: zeros first")
            self._last, self._last_time = ZERO, None
            if moving:  # left OFFBOARD while moving: the zero goes out at once
                return Setpoint(ZERO, "prestream")
            return Setpoint(ZERO, "prestream") if periodic else None
        if not fresh or target not in ACTIVE_STATES:
            self._go(HOLD, "detection stale" if not fresh else f"target {target}")
            self._last, self._last_time = ZERO, None  # not trusted at all: zero at once, no slew
            if moving:
                return Setpoint(ZERO, f"zero: {self.reason}")
            return Setpoint(ZERO, self.reason) if periodic else None
        self._go(FOLLOW if trusted else HOLD, f"target {target}" + ("" if trusted else " (not trusted)"))
        return self._command(now, det) if periodic and det is not None else None

    def _handover(self, now: float, reason: str) -> Setpoint:
        """PX4 in OFFBOARD and the target gone: zero at once, and ask for Hold (see the module docstring)."""
        self._go(HANDOVER, f"{reason}: handing over to Hold")
        self._last, self._last_time = ZERO, None
        self._next_hold = now + self.config.hold_retry
        return Setpoint(ZERO, f"stop: {reason}", hold=True)

    def _handing_over(self, now: float, periodic: bool) -> Setpoint | None:
        if not periodic:
            return None
        hold = now >= self._next_hold
        if hold:
            self._next_hold = now + self.config.hold_retry
        return Setpoint(ZERO, self.reason, hold=hold)

    def _stopping(self, periodic: bool) -> Setpoint | None:
        if not periodic:
            return None
        self._stops_left -= 1
        if self._stops_left <= 0:
            self._go(OFF, self.reason)
        return Setpoint(ZERO, f"stop: {self.reason}")

    def _command(self, now: float, det: Detection) -> Setpoint:
        cfg = self.config
        target = velocity_for(det, self._reference, cfg) if self.state == FOLLOW else ZERO
        dt = 1.0 / cfg.rate_hz if self._last_time is None else min(max(now - self._last_time, 0.0), 0.5)
        self._last = slew(self._last, target, dt, cfg.limits)
        self._last_time = now
        return Setpoint(self._last, self.state)
