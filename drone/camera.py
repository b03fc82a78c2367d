"""The MAVLink camera component: ground-station commands → tracker requests and COMMAND_ACKs;
CAMERA_INFORMATION; the CAMERA_TRACKING_IMAGE_STATUS (275) message and its stream schedule.

No I/O here: `handle` returns the messages to send, so every rule is testable without a socket.

Who may command (COMMAND_LONG or COMMAND_INT to our system and component, or broadcast): the vehicle
itself (our system id), the systems in `allowed_sysids` (default 255, QGroundControl, and 245, MAVSDK;
None: any), and with signing on every correctly signed sender (the link drops everything else before it
gets here). A refused sender's command that is ours gets COMMAND_ACK DENIED and a throttled log line.

Commands: MAV_CMD_CAMERA_TRACK_RECTANGLE, _TRACK_POINT, _STOP_TRACKING; MAV_CMD_REQUEST_MESSAGE for
CAMERA_INFORMATION, CAMERA_SETTINGS, STORAGE_INFORMATION, CAMERA_CAPTURE_STATUS, CAMERA_TRACKING_IMAGE_STATUS
and (with a stream URL) VIDEO_STREAM_INFORMATION / VIDEO_STREAM_STATUS; their legacy request commands
(MAV_CMD_REQUEST_CAMERA_INFORMATION, _CAMERA_SETTINGS, _STORAGE_INFORMATION, _CAMERA_CAPTURE_STATUS,
_VIDEO_STREAM_INFORMATION, _VIDEO_STREAM_STATUS) which QGroundControl and MAVSDK fall back to;
MAV_CMD_VIDEO_START/STOP_STREAMING (ACCEPTED: the stream is not ours to switch); MAV_CMD_SET_MESSAGE_INTERVAL /
MAV_CMD_GET_MESSAGE_INTERVAL (275 only: QGroundControl asks for 500000 us when it starts tracking and -1
when it stops). Each gets a COMMAND_ACK: ACCEPTED; DENIED for out-of-range, non-finite or degenerate values
or another camera's id; TEMPORARILY_REJECTED for a track or video-stream request before the first frame;
UNSUPPORTED for anything else addressed to us. Broadcast commands we do not handle are left to the
components they are for (no ACK).

The answers have minimal valid content: no storage (one STORAGE_STATUS_NOT_SUPPORTED entry), capture idle,
video mode with zoom and focus unknown; the video stream at the resolution of the frames the tracker
normalises against, so that a ground station places a drawn rectangle on the same image.

Status mapping (275): tracking → ACTIVE; uncertain → ACTIVE|COASTING (COASTING, value 8, is a work-in-
progress flag in common.xml: a ground station that does not know it sees ACTIVE); lost, stopped → IDLE;
tracker failure, or no result for STALLED_AFTER seconds while tracking → ERROR. While ACTIVE: mode
RECTANGLE with the box normalised to 0..1, and the point fields its centre and half-width. QGroundControl
reads the rectangle when the mode is RECTANGLE and the point fields otherwise, for any status but IDLE, so
nothing it reads is ever NaN: ERROR carries mode NONE with the point fields 0. IDLE: mode NONE, all NaN
("unknown", as common.xml says; ground stations read nothing then).
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

DEFAULT_ALLOWED = frozenset({255, 245})  # QGroundControl, MAVSDK

log = logging.getLogger(__name__)

NAN = float("nan")
CAPABILITIES = mavlink.CAMERA_CAP_FLAGS_HAS_TRACKING_POINT | mavlink.CAMERA_CAP_FLAGS_HAS_TRACKING_RECTANGLE
FIRMWARE_VERSION = 0 << 24 | 0 << 16 | 1 << 8 | 0  # (dev, patch, minor, major) = 0.1.0
MIN_INTERVAL = 0.02  # 275 at most 50 Hz, whatever is asked
INT32_MAX = 2**31 - 1  # MESSAGE_INTERVAL carries interval_us as int32
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
    allowed_sysids: frozenset[int] | None = DEFAULT_ALLOWED  # besides the vehicle's own; None: any
    trust_signed: bool = False  # signing on: every correctly signed sender may command
    stream_url: str | None = None  # advertise this video stream (VIDEO_STREAM_INFORMATION)
    vendor: str = "dadiff"
    model: str = "dadiff-tracker"


def stream_type(url: str) -> int:
    """VIDEO_STREAM_TYPE for a URL: rtsp:// → RTSP, udp:// or a bare port → RTP/UDP, tcp:// or http(s):// →
    MPEG on TCP, mpegts:// → MPEG-TS."""
    scheme = url.split("://", 1)[0].lower() if "://" in url else ""
    if scheme in ("rtsp", "rtsps"):
        return mavlink.VIDEO_STREAM_TYPE_RTSP
    if scheme in ("tcp", "http", "https"):
        return mavlink.VIDEO_STREAM_TYPE_TCP_MPEG
    if scheme in ("mpegts", "ts"):
        return mavlink.VIDEO_STREAM_TYPE_MPEG_TS
    return mavlink.VIDEO_STREAM_TYPE_RTPUDP


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
        point = ((rect[0] + rect[2]) / 2, (rect[1] + rect[3]) / 2, (rect[2] - rect[0]) / 2)
        mode, data = mavlink.CAMERA_TRACKING_MODE_RECTANGLE, mavlink.CAMERA_TRACKING_TARGET_DATA_IN_STATUS
    elif flags == mavlink.CAMERA_TRACKING_STATUS_FLAGS_IDLE:
        point, rect, mode, data = (NAN, NAN, NAN), (NAN, NAN, NAN, NAN), mavlink.CAMERA_TRACKING_MODE_NONE, 0
    else:  # ERROR (or ACTIVE without a box): read by ground stations, so finite
        if flags & mavlink.CAMERA_TRACKING_STATUS_FLAGS_ACTIVE:
            flags = mavlink.CAMERA_TRACKING_STATUS_FLAGS_ERROR
        point, rect, mode, data = (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 0.0), mavlink.CAMERA_TRACKING_MODE_NONE, 0
    return mavlink.MAVLink_camera_tracking_image_status_message(flags, mode, data, *point, *rect, 0)


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
        if not math.isfinite(value) or (value < 0 and value != -1) or value > INT32_MAX:
            return False  # MESSAGE_INTERVAL reports it as int32: 3e9 cannot be packed
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
        self.ignored = 0  # commands refused for their sender
        m = mavlink
        self._handlers: dict[int, Callable[[Sequence[float], bool, float], Reply]] = {
            m.MAV_CMD_CAMERA_TRACK_RECTANGLE: self._track_rectangle,
            m.MAV_CMD_CAMERA_TRACK_POINT: self._track_point,
            m.MAV_CMD_CAMERA_STOP_TRACKING: self._stop_tracking,
            m.MAV_CMD_REQUEST_MESSAGE: self._request_message,
            m.MAV_CMD_REQUEST_CAMERA_INFORMATION: self._request_information,
            m.MAV_CMD_REQUEST_CAMERA_SETTINGS: self._legacy(self.settings_message),
            m.MAV_CMD_REQUEST_STORAGE_INFORMATION: self._request_storage,
            m.MAV_CMD_REQUEST_CAMERA_CAPTURE_STATUS: self._legacy(self.capture_status),
            m.MAV_CMD_REQUEST_VIDEO_STREAM_INFORMATION: self._request_stream(self.stream_information),
            m.MAV_CMD_REQUEST_VIDEO_STREAM_STATUS: self._request_stream(self.stream_status),
            m.MAV_CMD_VIDEO_START_STREAMING: self._streaming,
            m.MAV_CMD_VIDEO_STOP_STREAMING: self._streaming,
            m.MAV_CMD_SET_MESSAGE_INTERVAL: self._set_interval,
            m.MAV_CMD_GET_MESSAGE_INTERVAL: self._get_interval,
        }
        self._messages: dict[int, Callable[[], Any]] = {
            m.MAVLINK_MSG_ID_CAMERA_INFORMATION: self.information,
            m.MAVLINK_MSG_ID_CAMERA_TRACKING_IMAGE_STATUS: self.status,
            m.MAVLINK_MSG_ID_CAMERA_SETTINGS: self.settings_message,
            m.MAVLINK_MSG_ID_STORAGE_INFORMATION: self.storage_information,
            m.MAVLINK_MSG_ID_CAMERA_CAPTURE_STATUS: self.capture_status,
        }

    # -- messages -----------------------------------------------------------------------------------
    @property
    def has_stream(self) -> bool:
        return bool(self.settings.stream_url)

    def information(self) -> Any:
        width, height = self.feed.frame_size or (0, 0)
        s = self.settings
        flags = CAPABILITIES | (mavlink.CAMERA_CAP_FLAGS_HAS_VIDEO_STREAM if self.has_stream else 0)
        return mavlink.MAVLink_camera_information_message(
            self.clock_ms(), _text(s.vendor, 32), _text(s.model, 32), FIRMWARE_VERSION,
            NAN, NAN, NAN, min(width, 65535), min(height, 65535), 0, flags, 0, b"", 0, 0,
        )  # fmt: skip

    def status(self) -> Any:
        return tracking_status(self.feed.latest())

    def settings_message(self) -> Any:
        return mavlink.MAVLink_camera_settings_message(self.clock_ms(), mavlink.CAMERA_MODE_VIDEO, NAN, NAN, 0)

    def storage_information(self) -> Any:
        return mavlink.MAVLink_storage_information_message(
            self.clock_ms(), 1, 1, mavlink.STORAGE_STATUS_NOT_SUPPORTED, 0.0, 0.0, 0.0, 0.0, 0.0,
            mavlink.STORAGE_TYPE_UNKNOWN, b"", 0,
        )  # fmt: skip

    def capture_status(self) -> Any:
        return mavlink.MAVLink_camera_capture_status_message(self.clock_ms(), 0, 0, 0.0, 0, 0.0, 0, 0)

    def _stream_size(self) -> tuple[int, int]:
        width, height = self.feed.frame_size or (0, 0)
        return min(width, 65535), min(height, 65535)

    def stream_information(self) -> Any:
        url = self.settings.stream_url or ""
        width, height = self._stream_size()
        return mavlink.MAVLink_video_stream_information_message(
            1, 1, stream_type(url), mavlink.VIDEO_STREAM_STATUS_FLAGS_RUNNING, float(self.feed.frame_rate),
            width, height, 0, 0, 0, self.settings.model.encode()[:32], url.encode()[:160],
            mavlink.VIDEO_STREAM_ENCODING_H264, 0,
        )  # fmt: skip

    def stream_status(self) -> Any:
        width, height = self._stream_size()
        return mavlink.MAVLink_video_stream_status_message(
            1, mavlink.VIDEO_STREAM_STATUS_FLAGS_RUNNING, float(self.feed.frame_rate), width, height, 0, 0, 0, 0
        )

    # -- commands -----------------------------------------------------------------------------------
    def may_command(self, msg: Any, sysid: int) -> bool:
        source = msg.get_srcSystem()
        allowed = self.settings.allowed_sysids
        if source == sysid or allowed is None or source in allowed:
            return True
        return self.settings.trust_signed and bool(getattr(msg, "_signed", False))

    def handle(self, msg: Any, sysid: int | None, now: float) -> list[Any]:
        """Replies (COMMAND_ACK first) for a COMMAND_LONG / COMMAND_INT; [] for anything not ours."""
        kind = msg.get_type()
        if kind not in ("COMMAND_LONG", "COMMAND_INT") or sysid is None:
            return []
        component = self.settings.component
        if msg.target_system not in (0, sysid) or msg.target_component not in (0, component):
            return []
        m = msg  # COMMAND_INT: x and y (ints) stand in for param5 and param6
        broadcast = m.target_component == 0
        handler = self._handlers.get(m.command)
        if not self.may_command(msg, sysid):
            if broadcast and handler is None:
                return []  # not ours anyway
            source = msg.get_srcSystem()
            self.ignored += 1
            self._throttle.log(
                logging.WARNING, f"src{source}",
                "denied command %d from system %d (not the vehicle, not in --allow-sysid, not signed)",
                m.command, source,
            )  # fmt: skip
            return [self._ack(m, DENIED)]
        if kind == "COMMAND_LONG":
            params = (m.param1, m.param2, m.param3, m.param4, m.param5, m.param6, m.param7)
        else:
            params = (m.param1, m.param2, m.param3, m.param4, float(m.x), float(m.y), m.z)
        if handler is None:
            return [] if broadcast else [self._ack(m, UNSUPPORTED)]
        try:
            result, extra = handler(params, broadcast, now)
        except Exception:  # a bug must not cost the ground station its ACK
            log.exception("command %d failed", m.command)
            result, extra = mavlink.MAV_RESULT_FAILED, []
        if result is None:
            return []
        if result != ACCEPTED:  # throttled per command: a flood of bad commands must not flood the log
            self._throttle.log(logging.INFO, f"result{m.command}", "command %d %s: result %d", m.command,
                               tuple(round(p, 4) for p in params[:5]), result)
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
        msg_id = p[0]
        if msg_id in (mavlink.MAVLINK_MSG_ID_VIDEO_STREAM_INFORMATION, mavlink.MAVLINK_MSG_ID_VIDEO_STREAM_STATUS):
            if not self.has_stream:
                return (None if broadcast else UNSUPPORTED), []
            info = msg_id == mavlink.MAVLINK_MSG_ID_VIDEO_STREAM_INFORMATION
            make = self.stream_information if info else self.stream_status
            return self._stream_reply(p[1], make)
        if msg_id == mavlink.MAVLINK_MSG_ID_STORAGE_INFORMATION and p[1] not in (0, 1) and math.isfinite(p[1]):
            return DENIED, []  # we have one (empty) storage entry
        make = self._messages.get(int(msg_id)) if math.isfinite(msg_id) and msg_id == int(msg_id) else None
        if make is None:
            return (None if broadcast else UNSUPPORTED), []
        return ACCEPTED, [make()]

    def _stream_reply(self, stream_id: float, make: Callable[[], Any]) -> Reply:
        if math.isfinite(stream_id) and stream_id not in (0, 1):
            return DENIED, []  # one stream, id 1
        if self.feed.frame_size is None:
            return TEMPORARILY_REJECTED, []  # its resolution is not known before the first frame
        return ACCEPTED, [make()]

    def _legacy(self, make: Callable[[], Any]) -> Callable[[Sequence[float], bool, float], Reply]:
        """MAV_CMD_REQUEST_CAMERA_SETTINGS / _CAMERA_CAPTURE_STATUS: param1 1 sends it, 0 is a no-op."""

        def handler(p: Sequence[float], broadcast: bool, now: float) -> Reply:
            if p[0] == 1:
                return ACCEPTED, [make()]
            return (ACCEPTED if p[0] == 0 else DENIED), []

        return handler

    def _request_storage(self, p: Sequence[float], broadcast: bool, now: float) -> Reply:
        """MAV_CMD_REQUEST_STORAGE_INFORMATION: param1 storage id (0 all), param2 1 to request."""
        if p[0] not in (0, 1) or p[1] not in (0, 1):
            return DENIED, []
        return ACCEPTED, ([self.storage_information()] if p[1] == 1 else [])

    def _request_stream(self, make: Callable[[], Any]) -> Callable[[Sequence[float], bool, float], Reply]:
        """MAV_CMD_REQUEST_VIDEO_STREAM_INFORMATION / _STATUS: param1 the stream id (0 all)."""

        def handler(p: Sequence[float], broadcast: bool, now: float) -> Reply:
            if not self.has_stream:
                return (None if broadcast else UNSUPPORTED), []
            return self._stream_reply(p[0], make)

        return handler

    def _streaming(self, p: Sequence[float], broadcast: bool, now: float) -> Reply:
        if not self.has_stream:
            return (None if broadcast else UNSUPPORTED), []
        return (ACCEPTED if p[0] in (0, 1) else DENIED), []

    def _request_information(self, p: Sequence[float], broadcast: bool, now: float) -> Reply:
        if p[0] == 1:
            return ACCEPTED, [self.information()]
        return (ACCEPTED if p[0] == 0 else DENIED), []

    def _set_interval(self, p: Sequence[float], broadcast: bool, now: float) -> Reply:
        if p[0] != mavlink.MAVLINK_MSG_ID_CAMERA_TRACKING_IMAGE_STATUS:
            return (None if broadcast else UNSUPPORTED), []
        if not self.stream.set_interval_us(p[1], now):
            return DENIED, []
        self._throttle.log(logging.INFO, "interval", "275 interval set to %d us", self.stream.interval_us)
        return ACCEPTED, []

    def _get_interval(self, p: Sequence[float], broadcast: bool, now: float) -> Reply:
        if p[0] != mavlink.MAVLINK_MSG_ID_CAMERA_TRACKING_IMAGE_STATUS:
            return (None if broadcast else UNSUPPORTED), []
        reply = mavlink.MAVLink_message_interval_message(int(p[0]), self.stream.interval_us)
        return ACCEPTED, [reply]
