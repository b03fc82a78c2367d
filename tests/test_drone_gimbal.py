"""Gimbal following (`--follow gimbal`) through the MAVLink gimbal manager protocol: the control law and state
machine without a socket, then the service against a simulated gimbal manager that enforces who is in
control (loopback)."""

from __future__ import annotations

import math
import time

import pytest

from dadiff.drone import gimbal
from dadiff.drone.follow import Detection
from dadiff.drone.gimbal import GimbalConfig, GimbalFollower, rates_for
from dadiff.drone.mav import mavlink
from drone_peers import HEIGHT, WIDTH, GimbalManager, Rig, rate, wait_until

ME = (1, 100)
CFG = GimbalConfig()


def det(box=(300, 220, 40, 40), state="tracking", stamp=0.0, target=1) -> Detection:
    return Detection(target, state, box, (WIDTH, HEIGHT), stamp)


def wire(msg, src=(1, 154)):
    sender = mavlink.MAVLink(None, srcSystem=src[0], srcComponent=src[1])
    return mavlink.MAVLink(None).decode(bytearray(msg.pack(sender)))


def status(primary=(0, 0)):
    return wire(mavlink.MAVLink_gimbal_manager_status_message(0, 0, 0, *primary, 0, 0))


def ack(result=mavlink.MAV_RESULT_ACCEPTED):
    return wire(mavlink.MAVLink_command_ack_message(mavlink.MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE, result, 0, 0, *ME))


def kinds(messages) -> list[str]:
    return [m.get_type() if m.get_type() != "COMMAND_LONG" else f"CMD{m.command}:{m.param1:g}" for m in messages]


def test_rates_from_the_box() -> None:
    assert rates_for(det((300, 220, 40, 40)), CFG) == gimbal.STILL  # centred (deadband)
    right_low = rates_for(det((500, 400, 40, 40)), CFG)
    assert right_low.yaw > 0 and right_low.pitch < 0  # right: yaw right; low in the image: pitch down
    left_high = rates_for(det((20, 10, 40, 40)), CFG)
    assert left_high.yaw < 0 and left_high.pitch > 0
    fast = rates_for(det((630, 0, 10, 10)), GimbalConfig(gain=10.0, max_rate=math.radians(30)))
    assert fast.yaw == pytest.approx(math.radians(30)) and fast.pitch == pytest.approx(math.radians(30))


def test_take_control_follow_stop_and_release() -> None:
    f = GimbalFollower(CFG)
    assert f.step(0.0, None, ME) == [] and f.state == gimbal.IDLE  # no target: nothing
    f.on_message(status(), ME)
    assert f.manager == (1, 154)
    out = f.step(0.0, det(stamp=0.0), ME)
    assert kinds(out) == ["CMD1001:1"] and (out[0].param2, out[0].param3, out[0].param4) == (100, -1, -1)
    assert (out[0].target_system, out[0].target_component) == (1, 154)
    assert f.step(0.05, det(stamp=0.05), ME) == []  # waits for the answer
    f.on_message(ack(), ME)
    assert f.state == gimbal.CONTROL
    sp = f.step(0.1, det((500, 400, 40, 40), stamp=0.1), ME)[0]
    assert sp.get_type() == "GIMBAL_MANAGER_SET_PITCHYAW" and math.isnan(sp.pitch) and math.isnan(sp.yaw)
    assert sp.yaw_rate > 0 and sp.pitch_rate < 0 and sp.flags & mavlink.GIMBAL_MANAGER_FLAGS_YAW_LOCK
    # lost: zero rates on the result itself (not a tick later), then zeros at the stream rate
    zero = f.step(0.12, det(state="lost", stamp=0.12), ME, periodic=False)
    assert len(zero) == 1 and zero[0].yaw_rate == 0 and zero[0].pitch_rate == 0
    assert f.step(0.15, det(state="lost", stamp=0.12), ME)[0].yaw_rate == 0
    assert f.step(0.16, det(state="lost", stamp=0.16), ME, periodic=False) == []  # already still
    # stale: zeros from the first tick past stale_after
    f2 = GimbalFollower(CFG)
    f2.step(0.0, det(stamp=0.0), ME)
    f2.on_message(ack(), ME)
    assert f2.step(0.1, det((500, 220, 40, 40), stamp=0.1), ME)[0].yaw_rate > 0
    assert f2.step(0.1 + CFG.stale_after + 0.01, det((500, 220, 40, 40), stamp=0.1), ME)[0].yaw_rate == 0
    # stopped: zero and release
    out = f2.step(0.5, det(state="idle", stamp=0.5), ME, periodic=False)
    assert kinds(out) == ["GIMBAL_MANAGER_SET_PITCHYAW", "CMD1001:-3"] and out[0].yaw_rate == 0
    assert out[1].param2 == -3 and f2.state == gimbal.IDLE


def test_status_grants_control_and_someone_else_takes_it() -> None:
    f = GimbalFollower(CFG)
    f.step(0.0, det(), ME)
    f.on_message(status(ME), ME)  # no ACK, but the manager says we are in control
    assert f.state == gimbal.CONTROL and f.step(0.05, det(stamp=0.05), ME)
    f.on_message(status((255, 190)), ME)  # the pilot took it
    assert f.state == gimbal.OVERRIDDEN
    assert f.step(0.1, det(stamp=0.1), ME) == [] and f.step(2.0, det(stamp=2.0), ME) == []  # not taken back
    assert kinds(f.step(2.1, det(stamp=2.1, target=2), ME)) == ["CMD1001:1"]  # a new target asks again


def test_refused_or_unanswered_configure() -> None:
    f = GimbalFollower(CFG)
    f.step(0.0, det(), ME)
    f.on_message(ack(mavlink.MAV_RESULT_DENIED), ME)
    assert f.state == gimbal.REFUSED and f.step(5.0, det(stamp=5.0), ME) == []
    silent = GimbalFollower(CFG)
    sent = [m for k in range(80) for m in silent.step(k * 0.1, det(stamp=k * 0.1), ME)]
    assert len(sent) == CFG.configure_tries and silent.state == gimbal.REFUSED  # retried every second, then quiet
    assert all(m.target_component == mavlink.MAV_COMP_ID_AUTOPILOT1 for m in sent)  # no manager heard: autopilot


def test_gimbal_follows_through_a_gimbal_manager() -> None:
    config = GimbalConfig(rate_hz=20.0, max_rate=math.radians(40))
    with Rig(gimbal=config) as rig:
        gm = GimbalManager(f"udpout:127.0.0.1:{rig.port}").start()
        try:
            assert rig.connected()
            assert wait_until(lambda: rig.service.gimbal.manager == (1, 154), 3)
            assert gm.commands == [] and gm.configures == []  # nothing before a target
            rig.start_tracking((0.7, 0.6, 0.8, 0.7))  # right of centre and low
            assert wait_until(lambda: gm.primary == ME and len(gm.commands) >= 10, 3)
            assert gm.configures[0][1:] == (ME, 1.0, 100.0) and gm.ignored == 0
            t0 = time.monotonic()
            time.sleep(1.0)
            following = [c for c in gm.commands if c[0] >= t0]
            assert rate([c[0] for c in following]) == pytest.approx(20.0, rel=0.15)
            for _, pitch_rate, yaw_rate, pitch, yaw, flags in following:
                assert math.isnan(pitch) and math.isnan(yaw) and flags == gimbal.FLAGS
                assert 0 < yaw_rate <= config.max_rate + 1e-6 and -config.max_rate - 1e-6 <= pitch_rate < 0

            # lost: zero rates within a scheduler slice of the result
            rig.tracker.state = "lost"
            assert wait_until(lambda: any(s == "lost" for _, s, _ in rig.tracker.updates), 2)
            lost_at = next(t for t, s, _ in rig.tracker.updates if s == "lost")
            assert wait_until(lambda: any(c[0] > lost_at and c[2] == 0 for c in gm.commands), 2)
            zero_at = next(c[0] for c in gm.commands if c[0] > lost_at and c[2] == 0)
            assert zero_at - lost_at < 0.25  # ~2 ms on an idle machine: sent on the result, not a tick later
            assert rig.service.loop.stats.gimbal_reactions and min(rig.service.loop.stats.gimbal_reactions) < 0.05
            time.sleep(0.3)
            assert all(c[1] == c[2] == 0 for c in gm.commands if c[0] > zero_at)  # still while lost
            rig.tracker.state = "tracking"
            back = time.monotonic()
            assert wait_until(lambda: any(c[0] > back and c[2] > 0 for c in gm.commands), 2)

            # stale (inference hangs): zero rates after stale_after
            rig.tracker.running.clear()
            hung = time.monotonic()
            assert wait_until(lambda: any(c[0] > hung and c[2] == 0 for c in gm.commands), 2)
            stale_zero = next(c[0] for c in gm.commands if c[0] > hung and c[2] == 0)
            rig.tracker.running.set()
            assert stale_zero - hung < config.stale_after + 0.3

            # the pilot takes the gimbal: we stop, and the manager ignores nothing from us
            assert wait_until(lambda: any(c[0] > stale_zero and c[2] > 0 for c in gm.commands), 3)
            gm.take_control(255, 190)
            assert wait_until(lambda: rig.service.gimbal.state == "overridden", 2)
            time.sleep(0.3)
            assert gm.ignored <= 2  # at most what was in flight

            # a new target takes control again; stop: zero rates and control released
            rig.start_tracking((0.1, 0.1, 0.2, 0.2))
            assert wait_until(lambda: gm.primary == ME, 3)
            assert wait_until(lambda: any(c[2] < 0 for c in gm.commands), 2)  # target left: yaw left
            stop = time.monotonic()
            assert rig.gcs.call(mavlink.MAV_CMD_CAMERA_STOP_TRACKING).result == mavlink.MAV_RESULT_ACCEPTED
            assert wait_until(lambda: gm.primary == (0, 0), 2)
            last = [c for c in gm.commands if c[0] > stop]
            assert last and last[-1][1] == last[-1][2] == 0
            released = next(c[0] for c in gm.configures if c[2] == -3)
            time.sleep(0.3)
            assert [c for c in gm.commands if c[0] > released] == [] and gm.ignored <= 2  # nothing after release
        finally:
            gm.close()
