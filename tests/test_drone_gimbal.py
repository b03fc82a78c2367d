"""Gimbal following (`--follow gimbal`) through the MAVLink gimbal manager protocol: the control law and state
machine without a socket, then the service against a simulated gimbal manager that enforces who is in
control (loopback)."""

from __future__ import annotations

import math
import time

import pytest
from pymavlink.quaternion import QuaternionBase

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


def attitude(pitch=0.0, yaw=0.0, flags=mavlink.GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME):
    q = [float(v) for v in QuaternionBase([0.0, pitch, yaw]).q]
    nan = float("nan")
    return wire(mavlink.MAVLink_gimbal_device_attitude_status_message(0, 0, 0, flags, q, nan, nan, nan, 0, nan, nan, 1))


def in_control(autopilot="ardupilot", pitch=-0.2, yaw=0.3, flags=mavlink.GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME):
    """A follower in primary control whose aim has started from the reported attitude at t = 0."""
    f = GimbalFollower(CFG)
    f.autopilot = autopilot
    f.on_message(status(), ME)
    f.step(0.0, det(stamp=0.0), ME)
    f.on_message(ack(), ME)
    f.on_message(attitude(pitch, yaw, flags), ME, now=0.0)
    first = f.step(0.0, det(stamp=0.0), ME)
    assert len(first) == 1 and f.aim is not None
    assert (f.aim.pitch, f.aim.yaw) == (pytest.approx(pitch, abs=1e-6), pytest.approx(yaw, abs=1e-6))
    return f


def test_take_control_follow_stop_and_release() -> None:
    f = GimbalFollower(CFG)
    assert f.step(0.0, None, ME) == [] and f.state == gimbal.IDLE  # no target: nothing
    f.on_message(status(), ME)
    assert f.manager == (1, 154)
    out = f.step(0.0, det(stamp=0.0), ME)
    # take control, ask for the gimbal's attitude at 20 Hz and for its limits
    assert kinds(out) == ["CMD1001:1", "CMD511:285", "CMD512:280"]
    assert (out[0].param2, out[0].param3, out[0].param4) == (100, -1, -1)
    assert out[1].param2 == 50_000 and all((m.target_system, m.target_component) == (1, 154) for m in out)
    assert f.step(0.05, det(stamp=0.05), ME) == []  # waits for the answer
    f.on_message(ack(), ME)
    assert f.state == gimbal.CONTROL
    # in control but no attitude reported: nothing moves it (the interval request again, a second later)
    assert f.step(0.1, det((500, 400, 40, 40), stamp=0.1), ME) == [] and "attitude" in f.reason
    assert kinds(f.step(1.05, det((500, 400, 40, 40), stamp=1.05), ME)) == ["CMD511:285"]
    f.on_message(attitude(-0.2, 0.3), ME, now=1.1)
    start = f.step(1.1, det((500, 400, 40, 40), stamp=1.1), ME)[0]  # the aim starts where the gimbal points
    assert start.get_type() == "GIMBAL_MANAGER_SET_PITCHYAW" and math.isnan(start.pitch_rate)
    assert (start.pitch, start.yaw) == (pytest.approx(-0.2), pytest.approx(0.3))
    assert not start.flags & mavlink.GIMBAL_MANAGER_FLAGS_YAW_LOCK  # ArduPilot reports yaw in the vehicle frame
    # following: the aim moves by rate × time (right and low in the image: yaw right, pitch down)
    rates = rates_for(det((500, 400, 40, 40)), CFG)
    sp = f.step(1.15, det((500, 400, 40, 40), stamp=1.15), ME)[0]
    assert sp.yaw == pytest.approx(0.3 + rates.yaw * 0.05) and sp.pitch == pytest.approx(-0.2 + rates.pitch * 0.05)
    assert math.isnan(sp.yaw_rate) and math.isnan(sp.pitch_rate)
    aim = f.step(1.2, det((500, 400, 40, 40), stamp=1.2), ME)[0]
    assert aim.yaw == pytest.approx(sp.yaw + rates.yaw * 0.05)
    # lost: the aim stops on the result itself (not a tick later), then is repeated at the stream rate
    held = f.step(1.22, det(state="lost", stamp=1.22), ME, periodic=False)
    assert len(held) == 1 and (held[0].pitch, held[0].yaw) == (aim.pitch, aim.yaw)
    later = [f.step(1.25 + k * 0.05, det(state="lost", stamp=1.22), ME)[0] for k in range(10)]
    assert all((m.pitch, m.yaw) == (aim.pitch, aim.yaw) for m in later)
    assert f.step(1.8, det(state="lost", stamp=1.8), ME, periodic=False) == []  # already held
    # stale: the aim stops from the first tick past stale_after
    f.step(1.85, det((500, 220, 40, 40), stamp=1.85), ME)
    moved = f.step(1.9, det((500, 220, 40, 40), stamp=1.9), ME)[0].yaw
    stale = [f.step(1.95 + k * 0.05, det((500, 220, 40, 40), stamp=1.9), ME)[0].yaw for k in range(8)]
    assert stale[-1] == stale[-2] and stale[-1] <= moved + rates_for(det((500, 220, 40, 40)), CFG).yaw * 0.25
    # stopped: the aim once more, and control released
    out = f.step(2.5, det(state="idle", stamp=2.5), ME, periodic=False)
    assert kinds(out) == ["GIMBAL_MANAGER_SET_PITCHYAW", "CMD1001:-3"] and out[0].yaw == stale[-1]
    assert out[1].param2 == -3 and f.state == gimbal.IDLE


def test_px4_gets_set_attitude_with_a_quaternion() -> None:
    """PX4's MAVLink receiver has no GIMBAL_MANAGER_SET_PITCHYAW handler: the aim goes as a quaternion in
    GIMBAL_MANAGER_SET_ATTITUDE, rates NaN, yaw in the vehicle frame (PX4 reports YAW_LOCK, no frame flag)."""
    px4_flags = mavlink.GIMBAL_DEVICE_FLAGS_YAW_LOCK | mavlink.GIMBAL_DEVICE_FLAGS_NEUTRAL
    f = in_control("px4", -0.1, 0.5, px4_flags)
    assert f.aim is not None and not f.aim.earth
    sp = f.step(0.05, det((500, 220, 40, 40), stamp=0.05), ME)[0]
    assert sp.get_type() == "GIMBAL_MANAGER_SET_ATTITUDE" and (sp.target_system, sp.target_component) == (1, 154)
    assert all(math.isnan(v) for v in (sp.angular_velocity_x, sp.angular_velocity_y, sp.angular_velocity_z))
    _, pitch, yaw = QuaternionBase(list(sp.q)).euler
    assert pitch == pytest.approx(-0.1)
    assert yaw == pytest.approx(0.5 + rates_for(det((500, 220, 40, 40)), CFG).yaw * 0.05)
    assert not sp.flags & mavlink.GIMBAL_MANAGER_FLAGS_YAW_LOCK and sp.flags & mavlink.GIMBAL_MANAGER_FLAGS_PITCH_LOCK


def test_px4_never_sends_an_earth_framed_yaw_as_a_vehicle_framed_one() -> None:
    """A gimbal behind PX4 that reports a compass heading (YAW_IN_EARTH_FRAME): its yaw is not sent as a
    vehicle-frame angle (the gimbal would swing by the vehicle's heading); the gimbal is not moved."""
    f = GimbalFollower(CFG)
    f.autopilot = "px4"
    f.on_message(status(), ME)
    f.step(0.0, det(stamp=0.0), ME)
    f.on_message(ack(), ME)
    f.on_message(attitude(-0.1, 2.5, mavlink.GIMBAL_DEVICE_FLAGS_YAW_IN_EARTH_FRAME), ME, now=0.0)
    assert f.step(0.0, det(stamp=0.0), ME) == [] and f.aim is None
    assert "earth frame" in f.reason


def test_an_earth_framed_attitude_is_aimed_earth_locked_and_limits_hold() -> None:
    f = in_control("other", 0.0, 3.1, mavlink.GIMBAL_DEVICE_FLAGS_YAW_IN_EARTH_FRAME)
    assert f.aim is not None and f.aim.earth
    right = det((600, 220, 40, 40), stamp=0.05)
    sp = f.step(0.05, right, ME)[0]
    assert sp.flags & mavlink.GIMBAL_MANAGER_FLAGS_YAW_LOCK and -math.pi < sp.yaw < 0  # wrapped through ±180°
    # a vehicle-frame yaw stops at its stop, never wraps round (the gimbal would swing the long way)
    v = in_control("ardupilot", 0.0, 3.1)
    yaws = [v.step(k * 0.05, det((600, 220, 40, 40), stamp=k * 0.05), ME)[0].yaw for k in range(1, 10)]
    assert yaws[-1] == pytest.approx(math.pi) and all(y > 3.0 for y in yaws)
    # vehicle-frame yaw and pitch stop at the manager's limits (GIMBAL_MANAGER_INFORMATION)
    g = in_control("ardupilot", 0.0, 0.0)
    limits = mavlink.MAVLink_gimbal_manager_information_message(0, 0, 1, 0, 0, -1.0, 0.2, -0.3, 0.3)
    g.on_message(wire(limits), ME)
    out = [g.step(k * 0.05, det((630, 0, 10, 10), stamp=k * 0.05), ME)[0] for k in range(1, 40)]
    assert out[-1].yaw == pytest.approx(0.3) and out[-1].pitch == pytest.approx(0.2)


def test_status_grants_control_and_someone_else_takes_it() -> None:
    f = GimbalFollower(CFG)
    f.step(0.0, det(), ME)
    f.on_message(status(ME), ME)  # no ACK, but the manager says we are in control
    f.on_message(attitude(), ME, now=0.05)
    assert f.state == gimbal.CONTROL and f.step(0.05, det(stamp=0.05), ME)
    f.on_message(status((255, 190)), ME)  # the pilot took it
    assert f.state == gimbal.OVERRIDDEN
    assert f.step(0.1, det(stamp=0.1), ME) == [] and f.step(2.0, det(stamp=2.0), ME) == []  # not taken back
    assert kinds(f.step(2.1, det(stamp=2.1, target=2), ME))[0] == "CMD1001:1"  # a new target asks again


def test_refused_or_unanswered_configure() -> None:
    f = GimbalFollower(CFG)
    f.step(0.0, det(), ME)
    f.on_message(ack(mavlink.MAV_RESULT_DENIED), ME)
    assert f.state == gimbal.REFUSED and f.step(5.0, det(stamp=5.0), ME) == []
    silent = GimbalFollower(CFG)
    sent = [m for k in range(80) for m in silent.step(k * 0.1, det(stamp=k * 0.1), ME)]
    configures = [m for m in sent if m.command == mavlink.MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE]
    assert len(configures) == CFG.configure_tries and silent.state == gimbal.REFUSED  # every second, then quiet
    assert all(m.target_component == mavlink.MAV_COMP_ID_AUTOPILOT1 for m in sent)  # no manager heard: autopilot


def angles_held(commands, since: float) -> bool:
    after = [(c[3], c[4]) for c in commands if c[0] > since]
    return bool(after) and len(set(after)) == 1


def test_gimbal_follows_through_a_gimbal_manager() -> None:
    """ArduPilot's manager (SET_PITCHYAW, a rate target kept forever, attitude reported in the vehicle frame):
    the service points it with angles from the reported attitude, holds it still when the target is lost or
    the detection stale, lets the pilot have it, starts again from where the pilot left it, and releases."""
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
            assert rig.service.gimbal.limits.yaw_max == pytest.approx(gm.YAW_LIMIT)  # asked for and heard
            t0 = time.monotonic()
            time.sleep(1.0)
            following = [c for c in gm.commands if c[0] >= t0]
            assert rate([c[0] for c in following]) == pytest.approx(20.0, rel=0.15)
            for _, pitch_rate, yaw_rate, _, _, flags in following:
                assert math.isnan(pitch_rate) and math.isnan(yaw_rate) and flags == gimbal.LOCKS  # angles, vehicle yaw
            assert following[-1][4] > following[0][4] > 0 and following[-1][3] < following[0][3] < 0
            assert gm.yaw > math.radians(20) and gm.pitch < math.radians(-10)  # ~40°/s for 1 s, and pitch down

            # lost: the aim holds within a scheduler slice of the result, and the gimbal comes to rest
            rig.tracker.state = "lost"
            assert wait_until(lambda: any(s == "lost" for _, s, _ in rig.tracker.updates), 2)
            lost_at = next(t for t, s, _ in rig.tracker.updates if s == "lost")
            time.sleep(0.4)
            assert angles_held(gm.commands, lost_at + 0.1)
            first = next(c[0] for c in gm.commands if c[0] > lost_at)
            assert first - lost_at < 0.25  # ~2 ms on an idle machine: sent on the result, not a tick later
            assert rig.service.loop.stats.gimbal_reactions and min(rig.service.loop.stats.gimbal_reactions) < 0.05
            assert gm.speed_after(lost_at)[0] - lost_at < 0.3
            rig.tracker.state = "tracking"
            back = time.monotonic()
            assert wait_until(lambda: gm.speed_after(back)[1] > math.radians(10), 2)

            # stale (inference hangs): the aim holds after stale_after
            rig.tracker.running.clear()
            hung = time.monotonic()
            time.sleep(0.6)
            assert angles_held(gm.commands, hung + config.stale_after + 0.15)
            rig.tracker.running.set()

            # the pilot takes the gimbal and points it: we stop, the manager ignores nothing from us
            assert wait_until(lambda: gm.speed_after(time.monotonic() - 0.1)[1] > math.radians(10), 3)
            gm.take_control(255, 190)
            assert wait_until(lambda: rig.service.gimbal.state == "overridden", 2)
            gm.point(math.radians(-30), math.radians(-50))
            time.sleep(0.3)
            assert gm.ignored <= 2  # at most what was in flight

            # a new target takes control again from where the pilot left the gimbal (no jump); stop: release
            retake = time.monotonic()
            rig.start_tracking((0.1, 0.1, 0.2, 0.2))
            assert wait_until(lambda: gm.primary == ME, 3)
            assert wait_until(lambda: any(c[0] > retake for c in gm.commands), 2)
            start = next(c for c in gm.commands if c[0] > retake)
            pilots = (pytest.approx(math.radians(-30), abs=0.05), pytest.approx(math.radians(-50), abs=0.05))
            assert (start[3], start[4]) == pilots
            assert wait_until(lambda: gm.yaw < math.radians(-55), 2)  # target left and high: yaw left
            stop = time.monotonic()
            assert rig.gcs.call(mavlink.MAV_CMD_CAMERA_STOP_TRACKING).result == mavlink.MAV_RESULT_ACCEPTED
            assert wait_until(lambda: gm.primary == (0, 0), 2)
            released = next(c[0] for c in gm.configures if c[2] == -3)
            time.sleep(0.3)
            assert [c for c in gm.commands if c[0] > released] == [] and gm.ignored <= 2  # nothing after release
            assert gm.speed_after(stop)[0] - stop < 0.3  # at rest where it pointed
        finally:
            gm.close()


@pytest.mark.parametrize("flavour", ["ardupilot", "px4"])
@pytest.mark.parametrize("how", ["link cut", "killed"])
def test_the_gimbal_comes_to_rest_when_the_service_goes_silent(flavour: str, how: str) -> None:
    """Mid-follow (the gimbal turning at 40°/s), the service is killed (nothing more goes out, not even its
    shutdown) or the link is cut (the manager hears nothing more). Against managers that keep a rate target
    forever, the gimbal must come to rest within 1 s. PX4's manager (the autopilot, component 1) acts only
    on SET_ATTITUDE, so on PX4 this also shows that the service moves the gimbal at all."""
    config = GimbalConfig(rate_hz=20.0, max_rate=math.radians(40))
    compid = 1 if flavour == "px4" else 154
    with Rig(gimbal=config, flavour=flavour) as rig:
        gm = GimbalManager(f"udpout:127.0.0.1:{rig.port}", compid=compid, flavour=flavour).start()
        try:
            assert rig.connected()
            assert wait_until(lambda: rig.service.gimbal.manager == (1, compid), 3)
            rig.start_tracking((0.8, 0.45, 0.9, 0.55))  # far right: yaw right at the 40°/s limit
            assert wait_until(lambda: gm.primary == ME, 3)
            assert wait_until(lambda: gm.yaw > math.radians(15), 3), (gm.yaw, gm.unhandled)
            assert gm.unhandled == 0  # PX4 got only what it acts on
            time.sleep(0.6)  # turning steadily
            if how == "killed":
                rig.service.link.send = lambda msg, now: False  # SIGKILL: not one more packet
                silent = time.monotonic()
                rig.service.stop()
            else:
                gm.deaf = True
                silent = time.monotonic()
            before = [p for p in gm.path if silent - 0.5 <= p[0] <= silent]
            turning = (before[-1][2] - before[0][2]) / (before[-1][0] - before[0][0])  # mean yaw rate, last 0.5 s
            time.sleep(2.0)
            until, _ = gm.speed_after(silent)
            print(f"{flavour} {how}: turning {math.degrees(turning):.0f}°/s, at rest {until - silent:.3f} s later")
            assert turning > math.radians(20)  # it was turning
            assert until - silent < 1.0  # and stopped within a second (the bar against real autopilots: 1.5 s)
        finally:
            gm.close()
