"""The MAVLink camera component: ground-station commands → tracker requests and COMMAND_ACKs;
CAMERA_INFORMATION; the CAMERA_TRACKING_IMAGE_STATUS (275) message and its stream schedule.

No I/O here: `handle` returns the messages to send, so every rule is testable without a socket.

Commands (COMMAND_LONG or COMMAND_INT, from an allowed system id, to our system and component or
broadcast): MAV_CMD_CAMERA_TRACK_RECTANGLE, _TRACK_POINT, _STOP_TRACKING, MAV_CMD_REQUEST_MESSAGE
(CAMERA_INFORMATION, CAMERA_TRACKING_IMAGE_STATUS), MAV_CMD_REQUEST_CAMERA_INFORMATION,
MAV_CMD_SET_MESSAGE_INTERVAL / MAV_CMD_GET_MESSAGE_INTERVAL (275 only). Each gets a COMMAND_ACK:
ACCEPTED; DENIED for out-of-range, non-finite or degenerate values or another camera's id;
TEMPORARILY_REJECTED for a track command before the first frame; UNSUPPORTED for anything else addressed
to us. Broadcast commands we do not handle are left to the components they are for (no ACK).

Status mapping (275): tracking → ACTIVE; uncertain → ACTIVE|COASTING (COASTING, value 8, is a work-in-
progress flag in common.xml: a ground station that does not know it sees ACTIVE); lost, stopped → IDLE;
tracker failure, or no result for STALLED_AFTER seconds while tracking → ERROR. Mode RECTANGLE with the
box normalised to 0..1 while active, NONE and NaN otherwise; the point fields are always NaN.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from .logs import Throttle
from .mav import mavlink
from .tracking import Snapshot, Start, Stop, TrackFeed

log = logging.getLogger(__name__)

NAN = float("nan")
CAPABILITIES = mavlink.CAMERA_CAP_FLAGS_HAS_TRACKING_POINT | mavlink.CAMERA_CAP_FLAGS_HAS_TRACKING_RECTANGLE
FIRMWARE_VERSION = 0 << 24 | 0 << 16 | 1 << 8 | 0  # (dev, patch, minor, major) = 0.1.0
MIN_INTERVAL = 0.02  # 275 at most 50 Hz, whatever is asked
STALLED_AFTER = 1.0  # seconds without a tracker result while tracking: report ERROR, not the old box
STATUS_FLAGS = {
    "tracking": mavlink.CAMERA_TRACKING_STATUS_FLAGS_ACTIVE,
    "uncertain": mavlink.CAMERA_TRACKING_STATUS_FLAGS_ACTIVE | mavlink.CAMERA_TRACKING_STATUS_FLAGS_COASTING,
    "lost": mavlink.CAMERA_TRACKING_STATUS_FLAGS_IDLE,
    "idle": mavlink.CAMERA_TRACKING_STATUS_FLAGS_IDLE,
    "error": mavlink.CAMERA_TRACKING_STATUS_FLAGS_ERROR,
}

Reply = tuple[int | None, list[Any]]  # (MAV_RESULT or None for no ACK, messages after the ACK)
ACCEPTED = mavlink.MAV_RESULT_ACCEPTED
DENIED = mavlink.MAV_RESULT_DENIED
TEMPORARILY_REJECTED = mavlink.MAV_RESULT_TEMPORARILY_REJECTED
UNSUPPORTED = mavlink.MAV_RESULT_UNSUPPORTED


@dataclass(frozen=True)
class CameraSettings:
    component: int = mavlink.MAV_COMP_ID_CAMERA
    status_hz: float = 10.0  # default 275 rate while tracking (0: off until a ground station asks)
    idle_hz: float = 1.0  # 275 rate cap while not tracking
    allowed_sysids: frozenset[int] = frozenset({255})  # besides the vehicle's own
    vendor: str = "dadiff"
    model: str = "dadiff-tracker"


def _text(value: str, size: int) -> list[int]:
    return list(value.encode("utf-8")[:size].ljust(size, b"\0"))


def normalised_rect(snapshot: Snapshot) -> tuple[float, float, float, float]:
    """(top x, top y, bottom x, bottom y) of the box over the full image, clipped to 0..1."""
    assert snapshot.box is not None
    x, y, w, h = snapshot.box
    width, height = snapshot.frame_size

    def clip(v: float) -> float:
        return min(1.0, max(0.0, v))

    return clip(x / width), clip(y / height), clip((x + w) / width), clip((y + h) / height)


def tracking_status(snapshot: Snapshot, stalled: bool = False) -> Any:
    """CAMERA_TRACKING_IMAGE_STATUS for a tracker snapshot; `stalled`: the target was being tracked but no
    result has come for a while (camera lost, tracker hung), reported as ERROR rather than an old box."""
    flags = STATUS_FLAGS.get(snapshot.state, mavlink.CAMERA_TRACKING_STATUS_FLAGS_IDLE)
    if stalled and snapshot.active:
        flags = mavlink.CAMERA_TRACKING_STATUS_FLAGS_ERROR
    if flags & mavlink.CAMERA_TRACKING_STATUS_FLAGS_ACTIVE and snapshot.box is not None and snapshot.frame_size[0] > 0:
        rect = normalised_rect(snapshot)
        mode, data = mavlink.CAMERA_TRACKING_MODE_RECTANGLE, mavlink.CAMERA_TRACKING_TARGET_DATA_IN_STATUS
    else:
        rect, mode, data = (NAN, NAN, NAN, NAN), mavlink.CAMERA_TRACKING_MODE_NONE, 0
    return mavlink.MAVLink_camera_tracking_image_status_message(flags, mode, data, NAN, NAN, NAN, *rect, 0)


class StatusStream:
    """When to send 275: at the interval while tracking (deadline-scheduled, so the mean rate is the
    asked one whenever frames come at least that fast), on every state change at once, and at no more
    than `idle_hz` while not tracking. A fresh result goes out as soon as it is due; with no fresh
    result half an interval past due, the last one is repeated so that the rate holds."""

    def __init__(self, default_hz: float, idle_hz: float) -> None:
        self.default = 1.0 / default_hz if default_hz > 0 else None
        self.idle_interval = 1.0 / idle_hz if idle_hz > 0 else None
        self.interval = self.default
        self._due = 0.0

    def set_interval_us(self, value: float, now: float) -> bool:
        """MAV_CMD_SET_MESSAGE_INTERVAL: -1 stops, 0 restores the default, > 0 sets; False if invalid."""
        if not math.isfinite(value) or (value < 0 and value != -1):
            return False
        if value == -1:
            self.interval = None
        elif value == 0:
            self.interval = self.default
        else:
            self.interval = max(value / 1e6, MIN_INTERVAL)
        self._due = now
        return True

    @property
    def interval_us(self) -> int:
        return -1 if self.interval is None else round(self.interval * 1e6)

    def _effective(self, active: bool) -> float | None:
        if self.interval is None:
            return None
        if active or self.idle_interval is None:
            return self.interval
        return max(self.interval, self.idle_interval)

    def poll(self, now: float, fresh: bool, active: bool, changed: bool) -> bool:
        """True when a 275 should go out now (and the schedule moves on)."""
        interval = self._effective(active)
        if interval is None:
            return False
        if not (changed or (fresh and now >= self._due) or now >= self._due + interval / 2):
            return False
        self._due = now + interval if changed or now - self._due > interval else self._due + interval
        return True

    def next_wake(self, active: bool) -> float | None:
        interval = self._effective(active)
        return None if interval is None else self._due + interval / 2


def _finite(*values: float) -> bool:
    return all(math.isfinite(v) for v in values)


def _unit(*values: float) -> bool:
    return _finite(*values) and all(0.0 <= v <= 1.0 for v in values)


class CameraComponent:
    def __init__(self, settings: CameraSettings, feed: TrackFeed, clock_ms: Callable[[], int]) -> None:
        self.settings, self.feed, self.clock_ms = settings, feed, clock_ms
        self.stream = StatusStream(settings.status_hz, settings.idle_hz)
        self._throttle = Throttle(log)
        self.ignored = 0
        self._handlers: dict[int, Callable[[Sequence[float], bool, float], Reply]] = {
            mavlink.MAV_CMD_CAMERA_TRACK_RECTANGLE: self._track_rectangle,
            mavlink.MAV_CMD_CAMERA_TRACK_POINT: self._track_point,
            mavlink.MAV_CMD_CAMERA_STOP_TRACKING: self._stop_tracking,
            mavlink.MAV_CMD_REQUEST_MESSAGE: self._request_message,
            mavlink.MAV_CMD_REQUEST_CAMERA_INFORMATION: self._request_information,
            mavlink.MAV_CMD_SET_MESSAGE_INTERVAL: self._set_interval,
            mavlink.MAV_CMD_GET_MESSAGE_INTERVAL: self._get_interval,
        }

    # -- messages -----------------------------------------------------------------------------------
    def information(self) -> Any:
        width, height = self.feed.frame_size or (0, 0)
        s = self.settings
        return mavlink.MAVLink_camera_information_message(
            self.clock_ms(), _text(s.vendor, 32), _text(s.model, 32), FIRMWARE_VERSION,
            NAN, NAN, NAN, min(width, 65535), min(height, 65535), 0, CAPABILITIES, 0, b"", 0, 0,
        )  # fmt: skip

    def status(self) -> Any:
        return tracking_status(self.feed.latest())

    # -- commands -----------------------------------------------------------------------------------
    def handle(self, msg: Any, sysid: int | None, now: float) -> list[Any]:
        """Replies (COMMAND_ACK first) for a COMMAND_LONG / COMMAND_INT; [] for anything not ours."""
        kind = msg.get_type()
        if kind not in ("COMMAND_LONG", "COMMAND_INT") or sysid is None:
            return []
        component = self.settings.component
        if msg.target_system not in (0, sysid) or msg.target_component not in (0, component):
            return []
        source = msg.get_srcSystem()
        if source != sysid and source not in self.settings.allowed_sysids:
            self.ignored += 1
            self._throttle.log(logging.WARNING, f"src{source}", "ignored a command from system id %d", source)
            return []
        m = msg  # COMMAND_INT: x and y (ints) stand in for param5 and param6
        if kind == "COMMAND_LONG":
            params = (m.param1, m.param2, m.param3, m.param4, m.param5, m.param6, m.param7)
        else:
            params = (m.param1, m.param2, m.param3, m.param4, float(m.x), float(m.y), m.z)
        broadcast = m.target_component == 0
        handler = self._handlers.get(m.command)
        if handler is None:
            return [] if broadcast else [self._ack(m, UNSUPPORTED)]
        try:
            result, extra = handler(params, broadcast, now)
        except Exception:  # a bug must not cost the ground station its ACK
            log.exception("command %d failed", m.command)
            result, extra = mavlink.MAV_RESULT_FAILED, []
        if result is None:
            return []
        if result != ACCEPTED:
            log.info("command %d %s: result %d", m.command, tuple(round(p, 4) for p in params[:5]), result)
        return [self._ack(m, result), *extra]

    def _ack(self, msg: Any, result: int) -> Any:
        return mavlink.MAVLink_command_ack_message(
            msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()
        )

    def _other_camera(self, camera_id: float, broadcast: bool) -> tuple[bool, int | None]:
        """(True, verdict) when the command names another camera: stay silent if broadcast, else DENIED."""
        if not math.isfinite(camera_id) or camera_id == 0 or camera_id == self.settings.component:
            return False, None
        return True, (None if broadcast else DENIED)

    def _frame_size(self) -> tuple[int, int] | None:
        return self.feed.frame_size

    def _track_rectangle(self, p: Sequence[float], broadcast: bool, now: float) -> Reply:
        other, verdict = self._other_camera(p[4], broadcast)
        if other:
            return verdict, []
        x0, y0, x1, y1 = p[:4]
        if not _unit(x0, y0, x1, y1) or x1 <= x0 or y1 <= y0:
            return DENIED, []
        size = self._frame_size()
        if size is None:
            return TEMPORARILY_REJECTED, []
        if (x1 - x0) * size[0] < 1 or (y1 - y0) * size[1] < 1:
            return DENIED, []  # less than a pixel
        self.feed.request(Start(rect=(x0, y0, x1, y1)))
        return ACCEPTED, []

    def _track_point(self, p: Sequence[float], broadcast: bool, now: float) -> Reply:
        other, verdict = self._other_camera(p[3], broadcast)
        if other:
            return verdict, []
        x, y, radius = p[:3]
        if not _unit(x, y, radius):
            return DENIED, []
        if self._frame_size() is None:
            return TEMPORARILY_REJECTED, []
        self.feed.request(Start(point=(x, y, radius)))
        return ACCEPTED, []

    def _stop_tracking(self, p: Sequence[float], broadcast: bool, now: float) -> Reply:
        other, verdict = self._other_camera(p[0], broadcast)
        if other:
            return verdict, []
        self.feed.request(Stop())
        return ACCEPTED, []

    def _request_message(self, p: Sequence[float], broadcast: bool, now: float) -> Reply:
        if p[0] == mavlink.MAVLINK_MSG_ID_CAMERA_INFORMATION:
            return ACCEPTED, [self.information()]
        if p[0] == mavlink.MAVLINK_MSG_ID_CAMERA_TRACKING_IMAGE_STATUS:
            return ACCEPTED, [self.status()]
        return (None if broadcast else UNSUPPORTED), []

    def _request_information(self, p: Sequence[float], broadcast: bool, now: float) -> Reply:
        if p[0] == 1:
            return ACCEPTED, [self.information()]
        return (ACCEPTED if p[0] == 0 else DENIED), []

    def _set_interval(self, p: Sequence[float], broadcast: bool, now: float) -> Reply:
        if p[0] != mavlink.MAVLINK_MSG_ID_CAMERA_TRACKING_IMAGE_STATUS:
            return (None if broadcast else UNSUPPORTED), []
        if not self.stream.set_interval_us(p[1], now):
            return DENIED, []
        log.info("275 interval set to %d us", self.stream.interval_us)
        return ACCEPTED, []

    def _get_interval(self, p: Sequence[float], broadcast: bool, now: float) -> Reply:
        if p[0] != mavlink.MAVLINK_MSG_ID_CAMERA_TRACKING_IMAGE_STATUS:
            return (None if broadcast else UNSUPPORTED), []
        reply = mavlink.MAVLink_message_interval_message(int(p[0]), self.stream.interval_us)
        return ACCEPTED, [reply]
