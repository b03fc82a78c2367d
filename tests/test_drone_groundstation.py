"""What real ground stations and links do, over loopback: the camera speaks first without --sysid and adopts
the autopilot's id; a `udpout:` link to a silent peer stays up with its 1 Hz heartbeat; QGroundControl's
session (the requests it retries or polls, its 275 interval on start and stop) and ACK latency; the video
stream advertised with --stream-url."""

from __future__ import annotations

import logging
import math
import statistics
import time

import pytest

from dadiff.drone.camera import CameraSettings
from dadiff.drone.link import LinkSettings
from dadiff.drone.mav import mavlink
from dadiff.drone.service import Service, ServiceSettings
from drone_peers import FakeTracker, GroundStation, Peer, Rig, Running, SourceFactory, free_port, rate, wait_until

ACCEPTED, UNSUPPORTED = mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_UNSUPPORTED
REQUEST = mavlink.MAV_CMD_REQUEST_MESSAGE
STATUS = "CAMERA_TRACKING_IMAGE_STATUS"


def test_speaks_first_and_adopts_the_autopilot_id(caplog: pytest.LogCaptureFixture) -> None:
    """udpout to mavlink-router / a ground station listening, no --sysid: heartbeats at once as system 1, the
    ground station's commands work, and the autopilot's id (3) is adopted when its heartbeat arrives."""
    caplog.set_level(logging.INFO, logger="dadiff.drone.link")
    port = free_port()
    router = Peer(f"udpin:127.0.0.1:{port}", 255, 190).start()  # QGC behind a router: hears first, says nothing
    service = Service(
        ServiceSettings(LinkSettings(f"udpout:127.0.0.1:{port}", silence_timeout=1.0)), FakeTracker(), SourceFactory()
    )
    try:
        with Running(service):
            start = time.monotonic()
            first = router.wait_for("HEARTBEAT", 2, where=lambda m: m.get_srcComponent() == 100)
            assert first is not None and first.get_srcSystem() == 1 and first.type == mavlink.MAV_TYPE_CAMERA
            assert router.received("HEARTBEAT")[0].at - start < 0.5  # at once, not after a wait
            # a ground station behind the router (same socket here) commands it under system 1
            since = time.monotonic()
            router.send(
                mavlink.MAVLink_command_long_message(
                    1, 100, mavlink.MAV_CMD_REQUEST_CAMERA_INFORMATION, 0, 1, 0, 0, 0, 0, 0, 0
                )
            )
            reply = router.wait_for("COMMAND_ACK", 2, since)
            assert reply is not None and reply.result == ACCEPTED
            # the autopilot appears as system 3 (its heartbeat through the router): adopted, logged
            router.conn.mav.srcSystem, router.conn.mav.srcComponent = 3, 1
            router.send(mavlink.MAVLink_heartbeat_message(2, 3, 0, 4, 4, 3))
            assert wait_until(lambda: service.link.sysid == 3, 2)
            later = time.monotonic()
            beat = router.wait_for("HEARTBEAT", 2, later, where=lambda m: m.get_srcComponent() == 100)
            assert beat is not None and beat.get_srcSystem() == 3
    finally:
        router.close()
    assert any("system id 3 adopted from the autopilot heartbeat (was 1)" in r.getMessage() for r in caplog.records)


def test_udpout_to_a_silent_peer_stays_up() -> None:
    """A peer that never answers: the UDP link is not torn down for silence and the heartbeat keeps 1 Hz."""
    port = free_port()
    listener = Peer(f"udpin:127.0.0.1:{port}", 250, 190).start()  # receives, never sends
    service = Service(
        ServiceSettings(LinkSettings(f"udpout:127.0.0.1:{port}", silence_timeout=0.5, retry_min=0.1)),
        FakeTracker(),
        SourceFactory(),
    )
    try:
        with Running(service):
            time.sleep(3.3)
            beats = [r.at for r in listener.received("HEARTBEAT", src_component=100)]
            assert service.link.opens == 1 and service.link.is_open
    finally:
        listener.close()
    assert len(beats) >= 3 and rate(beats) == pytest.approx(1.0, rel=0.1)
    assert max(b - a for a, b in zip(beats, beats[1:], strict=False)) < 1.3  # was up to 6 s


def test_a_qgroundcontrol_session() -> None:
    """What QGroundControl sends to a MAVLink camera, in its order, all answered; ACK latency measured."""
    with Rig(camera=CameraSettings(stream_url="rtsp://127.0.0.1:8554/cam")) as rig:
        gcs = rig.gcs
        assert rig.connected()
        assert wait_until(lambda: rig.service.feed.frame_size is not None, 3)
        info = mavlink.MAVLINK_MSG_ID_CAMERA_INFORMATION
        since = time.monotonic()
        assert gcs.call(REQUEST, info).result == ACCEPTED
        camera = gcs.wait_for("CAMERA_INFORMATION", 2, since)
        assert camera.flags & mavlink.CAMERA_CAP_FLAGS_HAS_VIDEO_STREAM
        assert (camera.resolution_h, camera.resolution_v) == (640, 480)
        polls = [
            ((REQUEST, 260), "CAMERA_SETTINGS"),
            ((mavlink.MAV_CMD_REQUEST_CAMERA_SETTINGS, 1), "CAMERA_SETTINGS"),
            ((REQUEST, 261, 0), "STORAGE_INFORMATION"),
            ((mavlink.MAV_CMD_REQUEST_STORAGE_INFORMATION, 0, 1), "STORAGE_INFORMATION"),
            ((REQUEST, 262), "CAMERA_CAPTURE_STATUS"),
            ((mavlink.MAV_CMD_REQUEST_CAMERA_CAPTURE_STATUS, 1), "CAMERA_CAPTURE_STATUS"),
            ((REQUEST, 269, 0), "VIDEO_STREAM_INFORMATION"),
            ((mavlink.MAV_CMD_REQUEST_VIDEO_STREAM_INFORMATION, 1), "VIDEO_STREAM_INFORMATION"),
            ((REQUEST, 270, 1), "VIDEO_STREAM_STATUS"),
            ((mavlink.MAV_CMD_REQUEST_VIDEO_STREAM_STATUS, 1), "VIDEO_STREAM_STATUS"),
        ]
        latencies = []
        for params, name in polls:
            since = gcs.command(*params)
            reply = gcs.ack(params[0], since)
            assert reply is not None and reply.result == ACCEPTED, (params, reply)
            latencies.append(gcs.received("COMMAND_ACK", since)[0].at - since)
            assert gcs.wait_for(name, 2, since) is not None, name
        stream = gcs.received("VIDEO_STREAM_INFORMATION")[-1].msg
        assert (stream.resolution_h, stream.resolution_v, stream.uri) == (640, 480, "rtsp://127.0.0.1:8554/cam")
        assert stream.type == mavlink.VIDEO_STREAM_TYPE_RTSP

        # startTracking: TRACK_RECTANGLE, then SET_MESSAGE_INTERVAL(275, 500000): 275 at 2 Hz
        since = gcs.command(mavlink.MAV_CMD_CAMERA_TRACK_RECTANGLE, 0.4, 0.4, 0.6, 0.6)
        gcs.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 275, 500_000)
        assert gcs.ack(mavlink.MAV_CMD_CAMERA_TRACK_RECTANGLE, since).result == ACCEPTED
        assert gcs.ack(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, since).result == ACCEPTED
        latencies.append(gcs.received("COMMAND_ACK", since)[0].at - since)
        time.sleep(0.3)
        t0 = time.monotonic()
        time.sleep(2.1)
        slow = [r for r in gcs.received(STATUS, t0)]
        assert len(slow) in (4, 5) and rate([r.at for r in slow]) == pytest.approx(2.0, rel=0.15)
        for r in slow:  # QGC draws the rectangle from these: finite, in 0..1
            m = r.msg
            assert m.tracking_status == 1 and m.tracking_mode == mavlink.CAMERA_TRACKING_MODE_RECTANGLE
            assert all(0 <= v <= 1 for v in (m.rec_top_x, m.rec_top_y, m.rec_bottom_x, m.rec_bottom_y))
            assert all(math.isfinite(v) for v in (m.point_x, m.point_y, m.radius))
        # stopTracking: STOP_TRACKING, then SET_MESSAGE_INTERVAL(275, -1): 275 ends
        since = gcs.command(mavlink.MAV_CMD_CAMERA_STOP_TRACKING)
        gcs.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 275, -1)
        assert gcs.ack(mavlink.MAV_CMD_CAMERA_STOP_TRACKING, since).result == ACCEPTED
        assert gcs.ack(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, since).result == ACCEPTED
        time.sleep(0.2)
        quiet = time.monotonic()
        time.sleep(1.2)
        assert gcs.received(STATUS, quiet) == []
        # commands QGroundControl may send that a tracker does not do: answered, not ignored
        for command in (mavlink.MAV_CMD_IMAGE_START_CAPTURE, mavlink.MAV_CMD_SET_CAMERA_ZOOM):
            assert gcs.call(command, 0, 1).result == UNSUPPORTED
    p50 = statistics.median(latencies) * 1000
    p95 = sorted(latencies)[int(0.95 * (len(latencies) - 1))] * 1000
    print(f"\nACK latency over loopback: p50 {p50:.2f} ms, p95 {p95:.2f} ms, max {max(latencies) * 1000:.2f} ms")
    assert max(latencies) < 0.25


def test_a_refused_sender_gets_denied() -> None:
    """Not the vehicle, not allowed, not signed: COMMAND_ACK DENIED from 1/100 to the sender, never silence."""
    with Rig() as rig:
        assert rig.connected()
        stranger = GroundStation(f"udpout:127.0.0.1:{rig.port}", sysid=200, compid=1)
        stranger.start()
        try:
            reply = stranger.call(mavlink.MAV_CMD_REQUEST_CAMERA_INFORMATION, 1)
            assert reply is not None and reply.result == mavlink.MAV_RESULT_DENIED
            assert (reply.get_srcSystem(), reply.get_srcComponent()) == (1, 100)
            assert (reply.target_system, reply.target_component) == (200, 1)
        finally:
            stranger.close()
