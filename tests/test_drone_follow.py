"""Follow controller: the control law, the limits and the safety state machine (no MAVLink, no clock)."""

from __future__ import annotations

import math

import pytest

from dadiff.drone import follow
from dadiff.drone.follow import (
    ZERO,
    Autopilot,
    Detection,
    FollowConfig,
    Follower,
    Gains,
    Limits,
    Velocity,
    slew,
    velocity_for,
)
from dadiff.drone.mav import mavlink

W, H = 640, 480
GUIDED = 4
LOITER = 5
PX4_OFFBOARD = 6 << 16
PX4_POSCTL = 3 << 16
CFG = FollowConfig()


def det(box=(300, 220, 40, 40), state="tracking", stamp=0.0, target=1) -> Detection:
    return Detection(target, state, box, (W, H), stamp)


def ardupilot(stamp: float = 0.0, armed: bool = True, mode: int = GUIDED, vehicle: int = 2) -> Autopilot:
    base = follow.MODE_FLAG_ARMED if armed else 0
    return Autopilot(follow.AUTOPILOT_ARDUPILOT, vehicle, base, mode, stamp)


def px4(stamp: float = 0.0, armed: bool = True, mode: int = PX4_OFFBOARD) -> Autopilot:
    return Autopilot(follow.AUTOPILOT_PX4, 2, follow.MODE_FLAG_ARMED if armed else 0, mode, stamp)


def test_constants_match_pymavlink() -> None:
    assert follow.AUTOPILOT_ARDUPILOT == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
    assert follow.AUTOPILOT_PX4 == mavlink.MAV_AUTOPILOT_PX4
    assert follow.MODE_FLAG_ARMED == mavlink.MAV_MODE_FLAG_SAFETY_ARMED
    copters = ("QUADROTOR", "COAXIAL", "HELICOPTER", "HEXAROTOR", "OCTOROTOR", "TRICOPTER", "DODECAROTOR", "DECAROTOR")
    assert follow.COPTER_TYPES == {getattr(mavlink, f"MAV_TYPE_{n}") for n in copters}


def test_centred_target_at_reference_size_gives_zero() -> None:
    d = det((300, 220, 40, 40))
    ref = follow.apparent_size(d.box, d.frame_size)
    assert velocity_for(d, ref, CFG) == ZERO


def test_directions() -> None:
    ref = follow.apparent_size((0, 0, 40, 40), (W, H))
    right = velocity_for(det((500, 220, 40, 40)), ref, CFG)
    assert right.yaw_rate > 0 and right.forward == 0 and right.down == 0
    left = velocity_for(det((20, 220, 40, 40)), ref, CFG)
    assert left.yaw_rate < 0
    smaller = velocity_for(det((310, 230, 20, 20)), ref, CFG)
    assert smaller.forward > 0
    bigger = velocity_for(det((280, 200, 80, 80)), ref, CFG)
    assert bigger.forward < 0
    below = det((300, 400, 40, 40))
    assert velocity_for(below, ref, CFG).down == 0  # altitude held by default
    climb = FollowConfig(altitude=True)
    assert velocity_for(below, ref, climb).down > 0  # target low in the image: descend
    strafe = FollowConfig(gains=Gains(lateral=1.0))
    assert velocity_for(det((500, 220, 40, 40)), ref, strafe).right > 0


def test_limits() -> None:
    limits = Limits(speed=1.5, climb=0.5, yaw_rate=0.3)
    cfg = FollowConfig(gains=Gains(yaw=10, lateral=10, vertical=10, forward=50), limits=limits, altitude=True)
    ref = follow.apparent_size((0, 0, 200, 200), (W, H))
    v = velocity_for(det((630, 470, 5, 5)), ref, cfg)
    assert math.hypot(v.forward, v.right) == pytest.approx(1.5)
    assert abs(v.down) == pytest.approx(0.5) and abs(v.yaw_rate) == pytest.approx(0.3)


def test_slew_limits_change_per_step() -> None:
    limits = Limits(accel=2.0, yaw_accel=1.0)
    out = slew(ZERO, Velocity(3.0, -3.0, 1.0, 2.0), 0.1, limits)
    assert out == Velocity(pytest.approx(0.2), pytest.approx(-0.2), pytest.approx(0.2), pytest.approx(0.1))
    assert slew(out, out, 0.1, limits) == out


def run(follower: Follower, t: float, ap: Autopilot | None, d: Detection | None, periodic: bool = True):
    return follower.step(t, ap, d, periodic)


def test_ardupilot_follows_only_armed_in_guided() -> None:
    f = Follower(CFG)
    assert run(f, 0.0, ardupilot(armed=False), det()) is None
    assert run(f, 0.1, ardupilot(0.1, mode=LOITER), det(stamp=0.1)) is None
    assert run(f, 0.2, ardupilot(0.2, vehicle=mavlink.MAV_TYPE_FIXED_WING), det(stamp=0.2)) is None  # plane mode 4
    assert run(f, 0.3, None, det(stamp=0.3)) is None
    sp = run(f, 0.4, ardupilot(0.4), det((500, 220, 40, 40), stamp=0.4))
    assert sp is not None and f.state == follow.FOLLOW and sp.velocity.yaw_rate > 0
    # pilot switches to LOITER: silence at once, not even a zero
    assert run(f, 0.5, ardupilot(0.5, mode=LOITER), det(stamp=0.5)) is None and f.state == follow.OFF
    assert run(f, 0.6, ardupilot(0.6, mode=LOITER), det(stamp=0.6)) is None


def test_uncertain_holds_with_slew_then_resumes() -> None:
    f = Follower(CFG)
    run(f, 0.0, ardupilot(0.0), det((300, 220, 40, 40), stamp=0.0))  # reference
    sp = None
    for k in range(1, 20):
        sp = run(f, k / 15, ardupilot(k / 15), det((600, 220, 40, 40), stamp=k / 15))
    assert sp is not None and sp.velocity.yaw_rate > 0.5
    # one uncertain result is not enough (hysteresis); a sustained one is
    k = 20
    assert run(f, k / 15, ardupilot(k / 15), det((600, 220, 40, 40), "uncertain", stamp=k / 15)) is not None
    assert f.state == follow.FOLLOW
    while f.state == follow.FOLLOW and k < 40:
        k += 1
        held = run(f, k / 15, ardupilot(k / 15), det((600, 220, 40, 40), "uncertain", stamp=k / 15))
    assert f.state == follow.HOLD and held is not None
    assert 20 / 15 + 0.25 < k / 15 < 20 / 15 + 0.5  # trust_tau 0.3 s: lost after ~0.36 s of 'uncertain'
    assert 0 < held.velocity.yaw_rate < sp.velocity.yaw_rate  # slewing down, not a jump
    start = k
    while f.state == follow.HOLD and k < start + 20:
        k += 1
        back = run(f, k / 15, ardupilot(k / 15), det((600, 220, 40, 40), stamp=k / 15))
    assert f.state == follow.FOLLOW and back is not None and 0.25 < (k - start) / 15 < 0.5


def test_trust_hysteresis_on_a_flickering_state() -> None:
    """A score hovering around the tracker's threshold flips tracking/uncertain at frame rate: the level stays
    in the band between trust_off and trust_on and the controller's state does not flip."""
    trust = follow.Trust(0.3, 0.7, 0.3)
    assert trust.update(1, "tracking", 0.0)
    for k in range(1, 300):  # 10 s at 30 FPS, every other frame uncertain
        trust.update(1, "tracking" if k % 2 else "uncertain", k / 30)
        assert 0.3 < trust.level < 0.7 or k < 30
    assert trust.trusted and trust.flips == 0
    assert trust.update(1, "uncertain", 10.0) is True  # same pace, still in the band
    for k in range(1, 15):
        trust.update(1, "uncertain", 10.0 + k / 30)
    assert not trust.trusted and trust.flips == 1
    assert trust.update(2, "tracking", 11.0) and trust.level == 1.0  # a new target starts trusted
    assert not follow.Trust().update(3, "uncertain", 0.0)  # ... unless it starts uncertain

    f = Follower(CFG)
    states = []
    for k in range(150):  # 5 s at 30 FPS, periodic steps at 15 Hz in between
        t = k / 30
        d = det((500, 220, 40, 40), "tracking" if k % 2 == 0 else "uncertain", stamp=t)
        run(f, t, ardupilot(t), d, periodic=False)
        run(f, t + 0.001, ardupilot(t), d, periodic=k % 2 == 0)
        states.append(f.state)
    changes = sum(1 for a, b in zip(states, states[1:], strict=False) if a != b)
    assert changes == 0 and states[-1] == follow.FOLLOW


def test_px4_stream_never_pauses_while_armed_with_a_target() -> None:
    """PX4 in OFFBOARD fails safe when setpoints pause: zeros whenever the detection is not trusted, lost or
    stale, and on every periodic step, whatever the tracker does."""
    f = Follower(CFG)
    period = 1 / CFG.rate_hz
    sent: list[tuple[float, Velocity]] = []
    script = ["tracking"] * 30 + ["uncertain", "tracking"] * 20 + ["lost"] * 30 + ["tracking"] * 30
    script += ["uncertain"] * 30 + ["lost", "uncertain"] * 15 + ["tracking"] * 20
    t = 0.0
    for k, state in enumerate(script):  # a result every 1/30 s, periodic steps at 15 Hz
        t = k / 30
        stamp = t - 0.5 if k % 37 == 36 else t  # now and then a stale result
        d = det((500, 220, 40, 40), state, stamp=stamp)
        out = run(f, t, px4(t), d, periodic=False)
        if out is not None:
            sent.append((t, out.velocity))
        if k % 2 == 0:
            out = run(f, t + 0.001, px4(t), d)
            assert out is not None, (k, state, f.state, f.reason)
            sent.append((t + 0.001, out.velocity))
    gaps = [b[0] - a[0] for a, b in zip(sent, sent[1:], strict=False)]
    assert max(gaps) <= period + 0.01  # >= 15 Hz, never a pause
    assert any(v.yaw_rate > 0 for _, v in sent)  # it did follow (after the prestream second)
    first_lost = 30 + 40
    assert all(v.is_zero for t_, v in sent if first_lost / 30 <= t_ < (first_lost + 30) / 30)  # lost: zeros at once
    # the pilot leaves OFFBOARD: zeros go on (so that OFFBOARD can be selected again); stop: a zero, then nothing
    assert run(f, t + 0.1, px4(t + 0.1, mode=PX4_POSCTL), det(stamp=t + 0.1)).velocity == ZERO
    assert f.state == follow.PRESTREAM
    # (outside OFFBOARD a stop is one zero, then nothing: PX4 ignores setpoints there)
    posctl = px4(t + 0.2, mode=PX4_POSCTL)
    stops = [run(f, t + 0.2 + k * period, posctl, det(state="idle", stamp=t + 0.2)) for k in range(5)]
    assert [s.velocity if s else None for s in stops] == [ZERO] + [None] * 4
    assert f.state == follow.OFF


@pytest.mark.parametrize("cause", ["lost", "idle", "stale", "heartbeat"])
def test_stop_sends_zero_at_once_then_nothing(cause: str) -> None:
    f = Follower(CFG)
    run(f, 0.0, ardupilot(0.0), det((300, 220, 40, 40), stamp=0.0))
    assert run(f, 0.1, ardupilot(0.1), det((500, 220, 40, 40), stamp=0.1)).velocity.yaw_rate > 0
    t = 0.15
    if cause in ("lost", "idle"):
        first = run(f, t, ardupilot(t), det(state=cause, stamp=t), periodic=False)  # on the result, not a tick
    elif cause == "stale":
        t = 0.1 + CFG.stale_after + 0.01
        first = run(f, t, ardupilot(t), det(stamp=0.1))
    else:
        t = 0.1 + CFG.heartbeat_timeout + 0.01
        first = run(f, t, ardupilot(0.1), det(stamp=t))
    assert first is not None and first.velocity == ZERO and first.reason.startswith("stop")
    repeats = [run(f, t + k / 15, ardupilot(t + k / 15) if cause != "heartbeat" else None, None) for k in (1, 2, 3, 4)]
    assert [r.velocity if r else None for r in repeats] == [ZERO] * (CFG.stop_repeats - 1) + [None] * (
        5 - CFG.stop_repeats
    )
    assert f.state == follow.OFF


def test_px4_streams_zeros_before_offboard() -> None:
    f = Follower(CFG)
    t = 0.0
    out = []
    for k in range(10):  # armed in POSCTL, target tracked: zeros so that the pilot can switch
        t = k / 15
        out.append(run(f, t, px4(t, mode=PX4_POSCTL), det((500, 220, 40, 40), stamp=t)))
    assert all(sp is not None and sp.velocity == ZERO for sp in out) and f.state == follow.PRESTREAM
    # OFFBOARD after 0.6 s of zeros: still zeros until a full second of them
    t += 1 / 15
    assert run(f, t, px4(t), det((500, 220, 40, 40), stamp=t)).velocity == ZERO
    t = CFG.prestream + 0.01
    sp = run(f, t, px4(t), det((500, 220, 40, 40), stamp=t))
    assert f.state == follow.FOLLOW and sp is not None and sp.velocity.yaw_rate > 0


def test_px4_disarmed_or_no_target_sends_nothing() -> None:
    f = Follower(CFG)
    assert run(f, 0.0, px4(armed=False, mode=PX4_POSCTL), det()) is None
    assert run(f, 0.1, px4(0.1, mode=PX4_POSCTL), det(state="lost", stamp=0.1)) is None
    assert run(f, 0.2, px4(0.2, mode=PX4_POSCTL), None) is None
    assert f.state == follow.OFF


PX4_HOLD = (4 << 16) | (3 << 24)  # AUTO_LOITER


def following_px4(t: float = 2.0) -> Follower:
    """A follower streaming real setpoints to PX4 in OFFBOARD at time t."""
    f = Follower(CFG)
    for k in range(int(t * 15) + 1):
        run(f, k / 15, px4(k / 15), det((500, 220, 40, 40), stamp=k / 15))
    assert f.state == follow.FOLLOW
    return f


@pytest.mark.parametrize("end", ["idle", "error"])
def test_px4_offboard_hands_over_to_hold_without_a_gap(end: str) -> None:
    """Tracking stopped (or given up with an error) in OFFBOARD: zero at once with a request for Hold, zeros at
    the setpoint rate (never a pause PX4 would fail safe on) with the request every hold_retry, until the
    heartbeat says the vehicle left OFFBOARD; then nothing."""
    f = following_px4()
    t = 2.1
    first = run(f, t, px4(t), det(state=end, stamp=t), periodic=False)  # on the result itself
    assert first is not None and first.velocity == ZERO and first.hold and f.state == follow.HANDOVER
    period = 1 / CFG.rate_hz
    out = [(t + k * period, run(f, t + k * period, px4(t + k * period), det(state=end, stamp=t))) for k in range(1, 46)]
    assert all(sp is not None and sp.velocity == ZERO for _, sp in out)  # 3 s of zeros: no gap
    holds = [when for when, sp in out if sp.hold]
    assert len(holds) == pytest.approx(3.0 / CFG.hold_retry, abs=1)  # asked again every 0.5 s
    t = out[-1][0] + period
    assert run(f, t, px4(t, mode=PX4_HOLD), det(state=end, stamp=t)) is None and f.state == follow.OFF
    assert run(f, t + period, px4(t + period, mode=PX4_HOLD), det(state=end, stamp=t)) is None


def test_px4_handover_ends_on_disarm_or_heartbeat_loss_and_a_new_target_streams_zeros_first() -> None:
    f = following_px4()
    assert run(f, 2.1, px4(2.1), det(state="idle", stamp=2.1)).hold
    assert run(f, 2.2, px4(2.2, armed=False), det(state="idle", stamp=2.1)) is None and f.state == follow.OFF
    g = following_px4()
    run(g, 2.1, px4(2.1), det(state="idle", stamp=2.1))
    t = 2.1 + CFG.heartbeat_timeout + 0.1
    lost = run(g, t, px4(2.1), None)  # no heartbeat: zeros, then nothing (PX4's link-loss failsafe decides)
    assert lost.velocity == ZERO and g.state == follow.STOPPING
    h = following_px4()
    run(h, 2.1, px4(2.1), det(state="idle", stamp=2.1))
    times = [2.2 + k / 15 for k in range(30)]
    new = [run(h, t, px4(t), det((500, 220, 40, 40), stamp=t, target=2)) for t in times]
    assert all(sp is not None for sp in new)
    assert all(sp.velocity == ZERO for sp in new[:14]) and new[-1].velocity.yaw_rate > 0  # a second of zeros first


def test_guided_stop_is_unchanged() -> None:
    """ArduCopter GUIDED holds by itself (GUID_TIMEOUT): zeros stop_repeats times, no mode request."""
    f = Follower(CFG)
    run(f, 0.0, ardupilot(0.0), det(stamp=0.0))
    out = [run(f, 0.1 + k / 15, ardupilot(0.1 + k / 15), det(state="idle", stamp=0.1)) for k in range(6)]
    assert [sp.velocity if sp else None for sp in out] == [ZERO] * CFG.stop_repeats + [None] * (6 - CFG.stop_repeats)
    assert not any(getattr(sp, "hold", False) for sp in out if sp)
