"""Camera component without a socket: command → ACK and tracker request, the 275 message, the stream schedule."""

from __future__ import annotations

import math

import pytest

from dadiff.drone.camera import CameraComponent, CameraSettings, StatusStream, tracking_status
from dadiff.drone.mav import mavlink
from dadiff.drone.tracking import Snapshot, Start, Stop, TrackFeed

SYS, COMP = 1, 100
ACCEPTED, DENIED = mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_DENIED
TEMP, UNSUPPORTED = mavlink.MAV_RESULT_TEMPORARILY_REJECTED, mavlink.MAV_RESULT_UNSUPPORTED
RECT, POINT, STOP = (
    mavlink.MAV_CMD_CAMERA_TRACK_RECTANGLE,
    mavlink.MAV_CMD_CAMERA_TRACK_POINT,
    mavlink.MAV_CMD_CAMERA_STOP_TRACKING,
)
NAN = float("nan")
FIELDS = ("point_x", "point_y", "radius", "rec_top_x", "rec_top_y", "rec_bottom_x", "rec_bottom_y")


def wire(msg, src=(255, 190)):
    """The message as it arrives: packed by a sender with this source, then decoded."""
    sender = mavlink.MAVLink(None, srcSystem=src[0], srcComponent=src[1])
    return mavlink.MAVLink(None).decode(bytearray(msg.pack(sender)))


def long(command, *params, target=(SYS, COMP), src=(255, 190)):
    p = list(params) + [0.0] * (7 - len(params))
    return wire(mavlink.MAVLink_command_long_message(target[0], target[1], command, 0, *p), src)


def cmd_int(command, p1, p2, p3, p4, x=0, y=0, z=0.0, target=(SYS, COMP)):
    return wire(mavlink.MAVLink_command_int_message(target[0], target[1], 0, command, 0, 0, p1, p2, p3, p4, x, y, z))


@pytest.fixture
def feed() -> TrackFeed:
    f = TrackFeed()
    f.saw_frame((640, 480), 0.0)
    return f


@pytest.fixture
def camera(feed: TrackFeed) -> CameraComponent:
    return CameraComponent(CameraSettings(), feed, lambda: 1234)


def ack(replies, command, to=(255, 190)):
    assert replies and replies[0].get_type() == "COMMAND_ACK"
    assert (replies[0].command, replies[0].target_system, replies[0].target_component) == (command, *to)
    return replies[0].result


def test_track_rectangle_long_and_int(camera: CameraComponent, feed: TrackFeed) -> None:
    assert ack(camera.handle(long(RECT, 0.25, 0.5, 0.5, 0.75), SYS, 0.0), RECT) == ACCEPTED
    request = feed.take_request()
    assert request == Start(rect=(0.25, 0.5, 0.5, 0.75))
    assert request.box(640, 480) == (160.0, 240.0, 160.0, 120.0)
    assert ack(camera.handle(cmd_int(RECT, 0.1, 0.1, 0.2, 0.3, x=COMP), SYS, 0.0), RECT) == ACCEPTED
    assert feed.take_request().rect == pytest.approx((0.1, 0.1, 0.2, 0.3))  # float32 on the wire


@pytest.mark.parametrize(
    "params",
    [
        (0.5, 0.5, 0.4, 0.6),  # right edge left of the left edge
        (0.2, 0.2, 0.2, 0.5),  # zero width
        (0.2, 0.2, 0.2005, 0.5),  # under a pixel
        (-0.1, 0.2, 0.4, 0.5),
        (0.1, 0.2, 1.2, 0.5),
        (NAN, 0.2, 0.4, 0.5),
        (0.1, 0.2, 0.4, 0.5, 101),  # another camera's id
    ],
)
def test_track_rectangle_denied(camera: CameraComponent, feed: TrackFeed, params) -> None:
    assert ack(camera.handle(long(RECT, *params), SYS, 0.0), RECT) == DENIED
    assert feed.take_request() is None


def test_no_frame_yet_is_temporarily_rejected() -> None:
    feed = TrackFeed()
    camera = CameraComponent(CameraSettings(), feed, lambda: 0)
    assert ack(camera.handle(long(RECT, 0.1, 0.1, 0.3, 0.3), SYS, 0.0), RECT) == TEMP
    assert ack(camera.handle(long(POINT, 0.5, 0.5, 0.05), SYS, 0.0), POINT) == TEMP
    assert ack(camera.handle(long(POINT, 1.5, 0.5, 0.05), SYS, 0.0), POINT) == DENIED  # bad values first
    assert feed.take_request() is None


def test_track_point_and_stop(camera: CameraComponent, feed: TrackFeed) -> None:
    assert ack(camera.handle(long(POINT, 0.5, 0.25, 0.05), SYS, 0.0), POINT) == ACCEPTED
    request = feed.take_request()
    assert request == Start(point=(0.5, 0.25, pytest.approx(0.05)))
    x, y, w, h = request.box(640, 480)
    assert (x + w / 2, y + h / 2) == pytest.approx((320, 120)) and w == pytest.approx(64)
    tiny = Start(point=(0.0, 0.0, 0.0)).box(640, 480)  # a tap at the corner: minimum box, inside the frame
    assert tiny[0] == 0 and tiny[1] == 0 and tiny[2] == pytest.approx(12) and tiny[3] == pytest.approx(12)
    assert ack(camera.handle(long(POINT, 0.5, 0.5, -0.1), SYS, 0.0), POINT) == DENIED
    assert ack(camera.handle(long(STOP), SYS, 0.0), STOP) == ACCEPTED
    assert isinstance(feed.take_request(), Stop)


def test_camera_information(camera: CameraComponent) -> None:
    for msg in (
        long(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_CAMERA_INFORMATION),
        long(mavlink.MAV_CMD_REQUEST_CAMERA_INFORMATION, 1),
    ):
        replies = camera.handle(msg, SYS, 0.0)
        assert ack(replies, msg.command) == ACCEPTED
        info = replies[1]
        assert info.get_type() == "CAMERA_INFORMATION"
        assert info.flags & mavlink.CAMERA_CAP_FLAGS_HAS_TRACKING_RECTANGLE
        assert info.flags & mavlink.CAMERA_CAP_FLAGS_HAS_TRACKING_POINT
        assert not info.flags & mavlink.CAMERA_CAP_FLAGS_HAS_TRACKING_GEO_STATUS
        assert (info.resolution_h, info.resolution_v) == (640, 480)
        assert bytes(info.vendor_name).rstrip(b"\0") == b"dadiff"
    replies = camera.handle(long(mavlink.MAV_CMD_REQUEST_CAMERA_INFORMATION, 2), SYS, 0.0)
    assert ack(replies, mavlink.MAV_CMD_REQUEST_CAMERA_INFORMATION) == DENIED and len(replies) == 1


def test_addressing_and_sources(camera: CameraComponent) -> None:
    assert camera.handle(long(RECT, 0.1, 0.1, 0.3, 0.3, target=(2, COMP)), SYS, 0.0) == []  # other vehicle
    assert camera.handle(long(RECT, 0.1, 0.1, 0.3, 0.3, target=(SYS, 101)), SYS, 0.0) == []  # other camera
    stranger = camera.handle(long(RECT, 0.1, 0.1, 0.3, 0.3, src=(200, 190)), SYS, 0.0)  # not allowed: DENIED
    assert ack(stranger, RECT, to=(200, 190)) == DENIED and len(stranger) == 1 and camera.ignored == 1
    mavsdk = camera.handle(long(RECT, 0.1, 0.1, 0.3, 0.3, src=(245, 190)), SYS, 0.0)  # MAVSDK's default id
    assert ack(mavsdk, RECT, to=(245, 190)) == ACCEPTED
    from_vehicle = camera.handle(long(RECT, 0.1, 0.1, 0.3, 0.3, src=(SYS, 1)), SYS, 0.0)
    assert ack(from_vehicle, RECT, to=(SYS, 1)) == ACCEPTED
    assert camera.handle(long(RECT, 0.1, 0.1, 0.3, 0.3), None, 0.0) == []  # our system id not known yet
    # broadcast: ours handled, other commands and other cameras left alone
    assert ack(camera.handle(long(RECT, 0.1, 0.1, 0.3, 0.3, target=(0, 0)), SYS, 0.0), RECT) == ACCEPTED
    assert camera.handle(long(RECT, 0.1, 0.1, 0.3, 0.3, 102, target=(SYS, 0)), SYS, 0.0) == []
    assert camera.handle(long(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1, target=(SYS, 0)), SYS, 0.0) == []
    assert camera.handle(long(mavlink.MAV_CMD_REQUEST_MESSAGE, 148, target=(SYS, 0)), SYS, 0.0) == []
    # addressed to us but not ours to do
    arm = mavlink.MAV_CMD_COMPONENT_ARM_DISARM
    assert ack(camera.handle(long(arm, 1), SYS, 0.0), arm) == UNSUPPORTED


def test_message_interval_commands(camera: CameraComponent) -> None:
    set_iv, get_iv = mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAV_CMD_GET_MESSAGE_INTERVAL
    status = mavlink.MAVLINK_MSG_ID_CAMERA_TRACKING_IMAGE_STATUS

    def interval() -> int:
        replies = camera.handle(long(get_iv, status), SYS, 0.0)
        assert ack(replies, get_iv) == ACCEPTED and replies[1].message_id == status
        return replies[1].interval_us

    assert interval() == 100_000  # default 10 Hz
    assert ack(camera.handle(long(set_iv, status, 50_000), SYS, 0.0), set_iv) == ACCEPTED and interval() == 50_000
    assert ack(camera.handle(long(set_iv, status, -1), SYS, 0.0), set_iv) == ACCEPTED and interval() == -1
    assert ack(camera.handle(long(set_iv, status, 0), SYS, 0.0), set_iv) == ACCEPTED and interval() == 100_000
    assert ack(camera.handle(long(set_iv, status, 1000), SYS, 0.0), set_iv) == ACCEPTED and interval() == 20_000
    assert ack(camera.handle(long(set_iv, status, -5), SYS, 0.0), set_iv) == DENIED
    assert ack(camera.handle(long(set_iv, 33, 100_000), SYS, 0.0), set_iv) == UNSUPPORTED


def snap(state="tracking", box=(64.0, 48.0, 128.0, 96.0)) -> Snapshot:
    return Snapshot(seq=1, target_id=1, state=state, box=box, score=0.8, frame_size=(640, 480))


def test_status_message_mapping() -> None:
    msg = tracking_status(snap())
    assert msg.tracking_status == mavlink.CAMERA_TRACKING_STATUS_FLAGS_ACTIVE
    assert msg.tracking_mode == mavlink.CAMERA_TRACKING_MODE_RECTANGLE
    assert msg.target_data == mavlink.CAMERA_TRACKING_TARGET_DATA_IN_STATUS
    assert (msg.rec_top_x, msg.rec_top_y, msg.rec_bottom_x, msg.rec_bottom_y) == (0.1, 0.1, 0.3, 0.3)
    assert (msg.point_x, msg.point_y, msg.radius) == pytest.approx((0.2, 0.2, 0.1))  # centre, half-width
    coasting = tracking_status(snap("uncertain"))
    assert coasting.tracking_status == (
        mavlink.CAMERA_TRACKING_STATUS_FLAGS_ACTIVE | mavlink.CAMERA_TRACKING_STATUS_FLAGS_COASTING
    )
    clipped = tracking_status(snap(box=(-20.0, 400.0, 100.0, 200.0)))
    assert (clipped.rec_top_x, clipped.rec_bottom_y) == (0.0, 1.0)
    for state in ("lost", "idle"):  # IDLE: a ground station reads nothing, NaN says "unknown"
        msg = tracking_status(snap(state, None if state != "lost" else (1.0, 1.0, 5.0, 5.0)))
        assert msg.tracking_status == mavlink.CAMERA_TRACKING_STATUS_FLAGS_IDLE
        assert msg.tracking_mode == mavlink.CAMERA_TRACKING_MODE_NONE
        assert all(math.isnan(getattr(msg, f)) for f in FIELDS)
    # any other status: QGroundControl reads the rectangle (mode RECTANGLE) or the point fields: never NaN
    for msg in (tracking_status(snap("error", None)), tracking_status(snap(), stalled=True)):
        assert msg.tracking_status == mavlink.CAMERA_TRACKING_STATUS_FLAGS_ERROR
        assert msg.tracking_mode == mavlink.CAMERA_TRACKING_MODE_NONE
        assert all(math.isfinite(getattr(msg, f)) for f in FIELDS)
    for state in ("tracking", "uncertain"):
        assert all(math.isfinite(getattr(tracking_status(snap(state)), f)) for f in FIELDS)
    assert tracking_status(snap("tracking", None)).tracking_status == mavlink.CAMERA_TRACKING_STATUS_FLAGS_ERROR


def test_stalled_tracking_is_an_error() -> None:
    msg = tracking_status(snap(), stalled=True)
    assert msg.tracking_status == mavlink.CAMERA_TRACKING_STATUS_FLAGS_ERROR and msg.rec_top_x == 0.0  # not the box
    assert tracking_status(snap("idle", None), stalled=True).tracking_status == 0  # idle stays idle


def test_stream_schedule_keeps_the_mean_rate() -> None:
    stream = StatusStream(default_hz=10.0, idle_hz=1.0)
    sent = [t / 30 for t in range(300) if stream.poll(t / 30, fresh=True, active=True, changed=False)]
    assert len(sent) == pytest.approx(100, abs=1)  # 30 FPS results, 10 Hz asked: 10 Hz exactly, on fresh results
    stream = StatusStream(default_hz=10.0, idle_hz=1.0)  # results at 4 FPS: repeats fill the gaps
    ticks = [k / 1000 for k in range(10_000)]
    sent = [t for t in ticks if stream.poll(t, fresh=(round(t * 1000) % 250 == 0), active=True, changed=False)]
    assert len(sent) == pytest.approx(100, abs=2)
    stream = StatusStream(default_hz=10.0, idle_hz=1.0)  # not tracking: at most 1 Hz
    sent = [t for t in ticks if stream.poll(t, fresh=False, active=False, changed=False)]
    assert len(sent) == pytest.approx(10, abs=1)
    assert stream.poll(5.0001, fresh=True, active=True, changed=True)  # a state change goes out at once
    assert stream.set_interval_us(-1, 6.0) and not stream.poll(7.0, fresh=True, active=True, changed=True)


def test_intervals_beyond_int32_are_refused() -> None:
    """MESSAGE_INTERVAL carries interval_us as int32: an accepted 3e9 could not be reported, and every GET
    after it dropped the link (a pack error read as a lost link)."""
    stream = StatusStream(default_hz=10.0, idle_hz=1.0)
    assert not stream.set_interval_us(3e9, 0.0) and not stream.set_interval_us(1e38, 0.0)
    assert stream.set_interval_us(2**31 - 1, 0.0) and stream.interval_us == 2**31 - 1


def test_who_may_command(feed: TrackFeed) -> None:
    def result(camera: CameraComponent, src: tuple[int, int], signed: bool = False, target=(SYS, COMP)):
        msg = long(STOP, src=src, target=target)
        msg._signed = signed
        replies = camera.handle(msg, SYS, 0.0)
        return replies[0].result if replies else None

    default = CameraComponent(CameraSettings(), feed, lambda: 0)
    assert [result(default, (s, 190)) for s in (255, 245, SYS, 200)] == [ACCEPTED, ACCEPTED, ACCEPTED, DENIED]
    assert result(default, (200, 190), signed=True) == DENIED  # signed, but signing is off here
    anyone = CameraComponent(CameraSettings(allowed_sysids=None), feed, lambda: 0)
    assert result(anyone, (200, 190)) == ACCEPTED and result(anyone, (17, 1)) == ACCEPTED
    only = CameraComponent(CameraSettings(allowed_sysids=frozenset({200})), feed, lambda: 0)  # replaces the list
    assert [result(only, (s, 190)) for s in (200, 255, 245, SYS)] == [ACCEPTED, DENIED, DENIED, ACCEPTED]
    signed = CameraComponent(CameraSettings(allowed_sysids=frozenset(), trust_signed=True), feed, lambda: 0)
    assert result(signed, (200, 190), signed=True) == ACCEPTED and result(signed, (200, 190)) == DENIED
    # a refused sender's broadcast command that is not ours stays unanswered (it is for someone else)
    arm = wire(
        mavlink.MAVLink_command_long_message(SYS, 0, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0),
        (200, 1),
    )
    assert default.handle(arm, SYS, 0.0) == []
    assert result(default, (200, 190), target=(SYS, 0)) == DENIED  # a broadcast STOP is ours: DENIED


def test_what_ground_stations_request(camera: CameraComponent) -> None:
    """The requests QGroundControl and MAVSDK retry or poll: answered with minimal valid content."""
    request = mavlink.MAV_CMD_REQUEST_MESSAGE
    expected = {260: "CAMERA_SETTINGS", 261: "STORAGE_INFORMATION", 262: "CAMERA_CAPTURE_STATUS"}
    for msg_id, name in expected.items():
        replies = camera.handle(long(request, msg_id), SYS, 0.0)
        assert ack(replies, request) == ACCEPTED and [r.get_type() for r in replies[1:]] == [name]
    legacy = [
        (mavlink.MAV_CMD_REQUEST_CAMERA_SETTINGS, (1,), "CAMERA_SETTINGS"),
        (mavlink.MAV_CMD_REQUEST_STORAGE_INFORMATION, (0, 1), "STORAGE_INFORMATION"),
        (mavlink.MAV_CMD_REQUEST_CAMERA_CAPTURE_STATUS, (1,), "CAMERA_CAPTURE_STATUS"),
    ]
    for command, params, name in legacy:
        replies = camera.handle(long(command, *params), SYS, 0.0)
        assert ack(replies, command) == ACCEPTED and [r.get_type() for r in replies[1:]] == [name]
    settings = camera.handle(long(request, 260), SYS, 0.0)[1]
    assert settings.mode_id == mavlink.CAMERA_MODE_VIDEO and math.isnan(settings.zoomLevel)
    storage = camera.handle(long(request, 261), SYS, 0.0)[1]
    assert (storage.storage_id, storage.storage_count, storage.status) == (1, 1, mavlink.STORAGE_STATUS_NOT_SUPPORTED)
    capture = camera.handle(long(request, 262), SYS, 0.0)[1]
    assert (capture.image_status, capture.video_status, capture.recording_time_ms) == (0, 0, 0)
    for msg in (settings, storage, capture):  # they pack: valid messages
        assert wire(msg).get_type() == msg.get_type()
    assert ack(camera.handle(long(request, 261, 2), SYS, 0.0), request) == DENIED  # no second storage
    # no --stream-url: no video stream to tell about
    assert not camera.information().flags & mavlink.CAMERA_CAP_FLAGS_HAS_VIDEO_STREAM
    for params in ((request, 269), (request, 270), (mavlink.MAV_CMD_REQUEST_VIDEO_STREAM_INFORMATION, 0)):
        assert ack(camera.handle(long(*params), SYS, 0.0), params[0]) == UNSUPPORTED
    assert camera.handle(long(request, 269, target=(SYS, 0)), SYS, 0.0) == []  # broadcast: not ours


def test_video_stream_advertised() -> None:
    feed = TrackFeed()
    url = "rtsp://192.168.1.10:8554/cam"
    camera = CameraComponent(CameraSettings(stream_url=url), feed, lambda: 0)
    request = mavlink.MAV_CMD_REQUEST_MESSAGE
    assert camera.information().flags & mavlink.CAMERA_CAP_FLAGS_HAS_VIDEO_STREAM
    assert ack(camera.handle(long(request, 269), SYS, 0.0), request) == TEMP  # resolution not known yet
    feed.saw_frame((1280, 720), 0.0)
    feed.saw_frame((1280, 720), 0.04)
    for command, params, name in (
        (request, (269, 0), "VIDEO_STREAM_INFORMATION"),
        (request, (270, 1), "VIDEO_STREAM_STATUS"),
        (mavlink.MAV_CMD_REQUEST_VIDEO_STREAM_INFORMATION, (1,), "VIDEO_STREAM_INFORMATION"),
        (mavlink.MAV_CMD_REQUEST_VIDEO_STREAM_STATUS, (0,), "VIDEO_STREAM_STATUS"),
    ):
        replies = camera.handle(long(command, *params), SYS, 0.0)
        assert ack(replies, command) == ACCEPTED and replies[1].get_type() == name
        msg = wire(replies[1])
        assert (msg.stream_id, msg.resolution_h, msg.resolution_v) == (1, 1280, 720)  # what the tracker normalises on
        assert msg.flags & mavlink.VIDEO_STREAM_STATUS_FLAGS_RUNNING and msg.framerate == pytest.approx(25.0)
    info = wire(camera.handle(long(request, 269), SYS, 0.0)[1])
    assert (info.count, info.type, info.uri) == (1, mavlink.VIDEO_STREAM_TYPE_RTSP, url)
    assert ack(camera.handle(long(request, 269, 2), SYS, 0.0), request) == DENIED  # one stream
    assert ack(camera.handle(long(mavlink.MAV_CMD_VIDEO_START_STREAMING, 1), SYS, 0.0), 2502) == ACCEPTED


def test_qgc_tracking_status_interval(camera: CameraComponent) -> None:
    """QGroundControl: SET_MESSAGE_INTERVAL(275, 500000) after TRACK_RECTANGLE, (275, -1) after STOP."""
    set_iv, status = mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_CAMERA_TRACKING_IMAGE_STATUS
    assert ack(camera.handle(long(RECT, 0.4, 0.4, 0.6, 0.6), SYS, 0.0), RECT) == ACCEPTED
    assert ack(camera.handle(long(set_iv, status, 500000), SYS, 0.0), set_iv) == ACCEPTED
    assert camera.stream.interval_us == 500000
    assert ack(camera.handle(long(STOP), SYS, 0.0), STOP) == ACCEPTED
    assert ack(camera.handle(long(set_iv, status, -1), SYS, 0.0), set_iv) == ACCEPTED
    assert camera.stream.interval_us == -1
