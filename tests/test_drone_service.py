"""The service over loopback UDP: a simulated autopilot and ground station (pymavlink threads) talk to it.

Camera protocol (ACKs, CAMERA_INFORMATION, the 275 stream and its rate), follow setpoints and their
safety rules, bad frames and packets. Waits are bounded; rates are counted over bounded windows.
"""

from __future__ import annotations

import math
import socket
import threading
import time

import pytest

from dadiff.drone.follow import FollowConfig, Limits
from dadiff.drone.mav import mavlink
from drone_peers import HEIGHT, WIDTH, GroundStation, Rig, rate, wait_until

ACCEPTED, DENIED = mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_DENIED
TEMP = mavlink.MAV_RESULT_TEMPORARILY_REJECTED
RECT, POINT, STOP = (
    mavlink.MAV_CMD_CAMERA_TRACK_RECTANGLE,
    mavlink.MAV_CMD_CAMERA_TRACK_POINT,
    mavlink.MAV_CMD_CAMERA_STOP_TRACKING,
)
STATUS = "CAMERA_TRACKING_IMAGE_STATUS"
GUIDED, LOITER = 4, 5
LIMITS = Limits(speed=2.0, climb=0.5, yaw_rate=0.5, accel=4.0)


def normalised(box: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
    x, y, w, h = box
    return x / WIDTH, y / HEIGHT, (x + w) / WIDTH, (y + h) / HEIGHT


def rect_of(msg) -> tuple[float, float, float, float]:
    return msg.rec_top_x, msg.rec_top_y, msg.rec_bottom_x, msg.rec_bottom_y


def test_camera_protocol() -> None:
    with Rig() as rig:
        gcs, tracker = rig.gcs, rig.tracker
        assert rig.connected()
        hb = gcs.received("HEARTBEAT", src_component=100)[0].msg
        camera_type = (mavlink.MAV_TYPE_CAMERA, mavlink.MAV_AUTOPILOT_INVALID, 1)
        assert (hb.type, hb.autopilot, hb.get_srcSystem()) == camera_type
        info_id = mavlink.MAVLINK_MSG_ID_CAMERA_INFORMATION
        since = time.monotonic()
        assert gcs.call(mavlink.MAV_CMD_REQUEST_MESSAGE, info_id).result == ACCEPTED
        info = gcs.wait_for("CAMERA_INFORMATION", 3, since)
        assert info is not None and info.flags & mavlink.CAMERA_CAP_FLAGS_HAS_TRACKING_RECTANGLE
        assert gcs.call(mavlink.MAV_CMD_REQUEST_CAMERA_INFORMATION, 1).result == ACCEPTED

        for bad in [(0.5, 0.5, 0.4, 0.6), (0.1, 0.1, 1.5, 0.2), (math.nan, 0.1, 0.2, 0.2)]:
            assert gcs.call(RECT, *bad).result == DENIED
        assert gcs.call(POINT, 0.5, 0.5, 2.0).result == DENIED
        assert tracker.inits == []

        rig.start_tracking((0.25, 0.5, 0.5, 0.75))
        assert tracker.inits[0] == (160.0, 240.0, 160.0, 120.0)
        since = time.monotonic()
        assert wait_until(lambda: len(gcs.received(STATUS, since)) >= 5, 3)
        boxes = [normalised(box) for _, _, box in list(tracker.updates)]
        for r in gcs.received(STATUS, since):
            assert r.msg.tracking_status == mavlink.CAMERA_TRACKING_STATUS_FLAGS_ACTIVE
            assert r.msg.tracking_mode == mavlink.CAMERA_TRACKING_MODE_RECTANGLE
            assert any(rect_of(r.msg) == pytest.approx(b, abs=1e-6) for b in boxes)  # the tracker's box, exactly
            assert all(math.isfinite(v) for v in (r.msg.point_x, r.msg.point_y, r.msg.radius))  # QGC-safe

        tracker.state = "uncertain"
        coasting = mavlink.CAMERA_TRACKING_STATUS_FLAGS_ACTIVE | mavlink.CAMERA_TRACKING_STATUS_FLAGS_COASTING
        assert gcs.wait_for(STATUS, 3, time.monotonic(), where=lambda m: m.tracking_status == coasting)
        tracker.state = "lost"
        lost = gcs.wait_for(STATUS, 3, time.monotonic(), where=lambda m: m.tracking_status == 0)
        assert lost is not None and lost.tracking_mode == mavlink.CAMERA_TRACKING_MODE_NONE
        assert math.isnan(lost.rec_top_x)

        tracker.state = "tracking"
        since = time.monotonic()
        reply = gcs.call(POINT, 0.5, 0.5, 0.1, use_int=True)  # COMMAND_INT
        assert reply is not None and reply.result == ACCEPTED
        assert wait_until(lambda: len(tracker.inits) == 2, 3)
        x, y, w, h = tracker.inits[1]
        assert (x + w / 2, y + h / 2, w) == pytest.approx((320, 240, 128))

        assert gcs.call(STOP).result == ACCEPTED
        idle = gcs.wait_for(STATUS, 3, time.monotonic(), where=lambda m: m.tracking_status == 0)
        assert idle is not None and math.isnan(idle.rec_bottom_y)
        assert rig.service.loop.stats.latencies and max(rig.service.loop.stats.latencies) < 0.5


def test_commands_before_the_first_frame_and_from_strangers() -> None:
    gate = threading.Event()
    with Rig(source={"gate": gate}) as rig:
        assert rig.connected()
        hb = rig.gcs.received("HEARTBEAT", src_component=100)[-1].msg
        assert hb.system_status == mavlink.MAV_STATE_BOOT
        assert rig.gcs.call(RECT, 0.1, 0.1, 0.3, 0.3).result == TEMP
        assert rig.gcs.call(POINT, 0.5, 0.5, 0.1).result == TEMP
        assert rig.gcs.call(STOP).result == ACCEPTED
        gate.set()
        assert wait_until(lambda: rig.service.feed.frame_size is not None, 3)
        assert rig.gcs.call(RECT, 0.1, 0.1, 0.3, 0.3).result == ACCEPTED
        stranger = GroundStation(f"udpout:127.0.0.1:{rig.port}", sysid=200).start()
        mavsdk = GroundStation(f"udpout:127.0.0.1:{rig.port}", sysid=245).start()  # MAVSDK's default id
        try:
            assert stranger.call(RECT, 0.1, 0.1, 0.3, 0.3).result == DENIED  # refused, but never silence
            assert mavsdk.call(RECT, 0.1, 0.1, 0.3, 0.3).result == ACCEPTED
        finally:
            stranger.close()
            mavsdk.close()
        assert rig.service.camera.ignored >= 1


def test_message_rates() -> None:
    """Heartbeat 1 Hz, 275 at its default 10 Hz and at a requested 20 Hz, off (-1) and back (0)."""
    with Rig(follow=FollowConfig(limits=LIMITS)) as rig:
        gcs, ap = rig.gcs, rig.ap
        assert rig.connected()
        rig.start_tracking()
        ap.set_mode(True, GUIDED)
        t0 = time.monotonic()
        time.sleep(2.5)
        t1 = time.monotonic()
        status = [r.at for r in gcs.received(STATUS, t0) if r.at < t1]
        setpoints = [r.at for r in ap.setpoints(t0) if r.at < t1]
        assert rate(status) == pytest.approx(10.0, rel=0.15)
        assert rate(setpoints) == pytest.approx(15.0, rel=0.15)
        iv = mavlink.MAV_CMD_SET_MESSAGE_INTERVAL
        assert gcs.call(iv, 275, 50_000).result == ACCEPTED
        time.sleep(0.2)
        t2 = time.monotonic()
        time.sleep(1.5)
        t3 = time.monotonic()
        fast = [r.at for r in gcs.received(STATUS, t2) if r.at < t3]
        assert rate(fast) == pytest.approx(20.0, rel=0.15)
        assert rate(setpoints) == pytest.approx(15.0, rel=0.15)  # the controller is not slowed
        assert gcs.call(iv, 275, -1).result == ACCEPTED
        time.sleep(0.1)
        t4 = time.monotonic()
        time.sleep(0.8)
        assert gcs.received(STATUS, t4) == []
        assert gcs.call(iv, 275, 0).result == ACCEPTED
        assert gcs.wait_for(STATUS, 1.0, time.monotonic()) is not None
        beats = [r.at for r in gcs.received("HEARTBEAT", src_component=100) if r.at >= t0]
        assert rate(beats) == pytest.approx(1.0, rel=0.15) and len(beats) >= 4
    last = rig.ap.setpoints()[-1].msg  # stopping while following: one last zero velocity
    assert (last.vx, last.vy, last.vz, last.yaw_rate) == (0, 0, 0, 0)


def test_follow_setpoints_and_safety() -> None:
    follow = FollowConfig(limits=LIMITS)
    with Rig(follow=follow) as rig:
        ap, tracker = rig.ap, rig.tracker
        assert rig.connected()
        rig.start_tracking((0.7, 0.4, 0.8, 0.55))  # right of centre: yaw right
        t0 = time.monotonic()
        time.sleep(0.6)
        assert ap.setpoints(t0) == []  # disarmed
        ap.set_mode(True, LOITER)
        t0 = time.monotonic()
        time.sleep(0.6)
        assert ap.setpoints(t0) == []  # armed, but not GUIDED

        ap.set_mode(True, GUIDED)
        assert wait_until(lambda: len(ap.setpoints()) >= 10, 3)
        for r in ap.setpoints():
            m = r.msg
            assert (m.coordinate_frame, m.type_mask) == (mavlink.MAV_FRAME_BODY_NED, 1479)
            assert (m.target_system, m.target_component) == (1, 1)
            assert math.hypot(m.vx, m.vy) <= LIMITS.speed + 1e-6 and abs(m.vz) <= LIMITS.climb + 1e-6
            assert abs(m.yaw_rate) <= LIMITS.yaw_rate + 1e-6 and m.vz == 0.0  # altitude held
        assert ap.setpoints()[-1].msg.yaw_rate > 0

        # target lost: a zero setpoint before the tracker has seen the next frame, then silence
        tracker.state = "lost"
        assert wait_until(lambda: any(s == "lost" for _, s, _ in tracker.updates), 2)
        lost_at = next(t for t, s, _ in tracker.updates if s == "lost")
        assert wait_until(lambda: len(tracker.updates) > 0 and tracker.updates[-1][0] > lost_at + 0.05, 2)
        next_frame = next(t for t, _, _ in tracker.updates if t > lost_at)
        zero = next(r for r in ap.setpoints(lost_at) if r.msg.vx == r.msg.vy == r.msg.yaw_rate == 0)
        assert zero.at < next_frame
        time.sleep(0.5)
        quiet = time.monotonic()
        time.sleep(0.5)
        assert ap.setpoints(quiet) == []

        # found again: following resumes; then the autopilot heartbeat stops: zero, then silence
        tracker.state = "tracking"
        resumed = time.monotonic()
        assert wait_until(lambda: len(ap.setpoints(resumed)) >= 3, 3)
        ap.beating = False
        silent = time.monotonic()
        assert wait_until(lambda: rig.service.follower.state == "off", 4)
        time.sleep(0.1)  # the last repeat may still be in flight
        after = ap.setpoints(silent)
        assert after and after[-1].msg.yaw_rate == 0 and after[-1].msg.vx == 0
        assert after[-1].at - silent == pytest.approx(follow.heartbeat_timeout, abs=0.5)
        quiet = time.monotonic()
        time.sleep(0.4)
        assert ap.setpoints(quiet) == []


def test_px4_zero_stream_before_offboard() -> None:
    with Rig(follow=FollowConfig(limits=LIMITS), flavour="px4") as rig:
        ap = rig.ap
        assert rig.connected()
        rig.start_tracking((0.7, 0.4, 0.8, 0.55))
        t0 = time.monotonic()
        time.sleep(0.5)
        assert ap.setpoints(t0) == []  # disarmed: nothing
        ap.set_mode(True, 3 << 16)  # POSCTL
        assert wait_until(lambda: len(ap.setpoints(t0)) >= 5, 3)
        assert all(r.msg.yaw_rate == 0 and r.msg.vx == 0 for r in ap.setpoints(t0))
        ap.set_mode(True, 6 << 16)  # OFFBOARD
        moving = ap.wait_for("SET_POSITION_TARGET_LOCAL_NED", 4, t0, where=lambda m: m.yaw_rate > 0)
        assert moving is not None
        first_zero = ap.setpoints(t0)[0].at
        first_move = next(r.at for r in ap.setpoints(t0) if r.msg.yaw_rate > 0)
        assert first_move - first_zero >= 0.95  # 1 s at the sender; receive times jitter by a few ms


def test_bad_frames_and_packets_do_not_stop_it() -> None:
    with Rig() as rig:
        assert rig.connected()
        rig.start_tracking()
        rig.tracker.fail_next = 3
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as junk:
            for payload in (b"\xfd\x09garbage", b"\x00" * 300, bytes(range(256)), b"\xfe\x05\x00\x01"):
                junk.sendto(payload, ("127.0.0.1", rig.port))
        assert wait_until(lambda: rig.tracker.fail_next == 0, 3)
        since = time.monotonic()
        assert rig.gcs.call(mavlink.MAV_CMD_REQUEST_CAMERA_INFORMATION, 1).result == ACCEPTED
        assert rig.gcs.wait_for(STATUS, 2, since, where=lambda m: m.tracking_status == 1) is not None
        assert rig.service.tracking.errors >= 3
    assert rig.rc == 0
