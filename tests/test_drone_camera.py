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
    assert camera.handle(long(RECT, 0.1, 0.1, 0.3, 0.3, src=(200, 190)), SYS, 0.0) == []  # not allowed
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
    assert all(math.isnan(v) for v in (msg.point_x, msg.point_y, msg.radius))
    coasting = tracking_status(snap("uncertain"))
    assert coasting.tracking_status == (
        mavlink.CAMERA_TRACKING_STATUS_FLAGS_ACTIVE | mavlink.CAMERA_TRACKING_STATUS_FLAGS_COASTING
    )
    clipped = tracking_status(snap(box=(-20.0, 400.0, 100.0, 200.0)))
    assert (clipped.rec_top_x, clipped.rec_bottom_y) == (0.0, 1.0)
    for state, flag in (("lost", "IDLE"), ("idle", "IDLE"), ("error", "ERROR")):
        msg = tracking_status(snap(state, None if state != "lost" else (1.0, 1.0, 5.0, 5.0)))
        assert msg.tracking_status == getattr(mavlink, f"CAMERA_TRACKING_STATUS_FLAGS_{flag}")
        assert msg.tracking_mode == mavlink.CAMERA_TRACKING_MODE_NONE
        assert all(math.isnan(getattr(msg, f)) for f in ("rec_top_x", "rec_top_y", "rec_bottom_x", "rec_bottom_y"))


def test_stalled_tracking_is_an_error() -> None:
    msg = tracking_status(snap(), stalled=True)
    assert msg.tracking_status == mavlink.CAMERA_TRACKING_STATUS_FLAGS_ERROR and math.isnan(msg.rec_top_x)
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
