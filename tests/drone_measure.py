"""Rates and latencies of the MAVLink service over loopback, for the "Measured" lines of docs/drone.md:
`python3 tests/drone_measure.py [SECONDS]` (default 5 s windows). Not a test (pytest does not collect it):
the tests assert the same things with margins, this prints the numbers. It uses the test rig (fake tracker,
synthetic 30 FPS camera, simulated autopilot, PX4 and gimbal manager)."""

from __future__ import annotations

import math
import socket
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from dadiff.drone.follow import FollowConfig, Limits  # noqa: E402
from dadiff.drone.gimbal import GimbalConfig  # noqa: E402
from dadiff.drone.mav import mavlink  # noqa: E402
from drone_peers import GimbalManager, Px4, Rig, rate, wait_until  # noqa: E402

LIMITS = Limits(speed=2.0, climb=0.5, yaw_rate=0.5, accel=4.0)
STATUS = "CAMERA_TRACKING_IMAGE_STATUS"


def ms(values: list[float], q: float) -> float:
    return float(np.percentile(np.asarray(values) * 1000, q))


def window(seconds: float) -> tuple[float, float]:
    start = time.monotonic()
    time.sleep(seconds)
    return start, time.monotonic()


def between(times: list[float], span: tuple[float, float]) -> list[float]:
    return [t for t in times if span[0] <= t < span[1]]


def max_gap(times: list[float]) -> float:
    return float(np.max(np.diff(times))) * 1000 if len(times) > 1 else float("nan")


def ack_round_trips(port: int, count: int = 200) -> list[float]:
    """COMMAND_ACK round trip with a blocking socket: no polling loop in the measurement."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.settimeout(1.0)
    sender, parser = mavlink.MAVLink(None, srcSystem=255, srcComponent=190), mavlink.MAVLink(None)
    out = []
    for k in range(count):
        command, param = (mavlink.MAV_CMD_REQUEST_CAMERA_INFORMATION, 1) if k % 2 else (512, 262)
        msg = mavlink.MAVLink_command_long_message(1, 100, command, 0, param, 0, 0, 0, 0, 0, 0)
        start = time.perf_counter()
        sock.sendto(msg.pack(sender), ("127.0.0.1", port))
        while True:
            received = parser.parse_buffer(sock.recv(4096)) or []
            if any(m.get_type() == "COMMAND_ACK" and m.target_system == 255 for m in received):
                out.append(time.perf_counter() - start)
                break
        time.sleep(0.005)
    sock.close()
    return out


def camera_and_vehicle(w: float) -> None:
    with Rig(follow=FollowConfig(limits=LIMITS)) as rig:
        assert rig.connected()
        rig.start_tracking((0.7, 0.4, 0.8, 0.55))
        rig.ap.set_mode(True, 4)
        time.sleep(0.5)
        span = window(w)
        beats = between([r.at for r in rig.gcs.received("HEARTBEAT", src_component=100)], span)
        status = between([r.at for r in rig.gcs.received(STATUS)], span)
        setpoints = between([r.at for r in rig.ap.setpoints()], span)
        print(f"heartbeat {rate(beats):.3f} Hz; 275 at the default {rate(status):.2f} Hz")
        print(f"setpoints (ArduCopter GUIDED) {rate(setpoints):.2f} Hz, longest gap {max_gap(setpoints):.1f} ms")
        for interval, name in ((50_000, "20 Hz asked"), (500_000, "QGroundControl's 500000 us")):
            rig.gcs.call(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 275, interval)
            time.sleep(0.6)
            span = window(w)
            status = between([r.at for r in rig.gcs.received(STATUS)], span)
            setpoints = between([r.at for r in rig.ap.setpoints()], span)
            print(f"275 at {name}: {rate(status):.2f} Hz (setpoints meanwhile {rate(setpoints):.2f} Hz)")
        latencies = rig.service.loop.stats.latencies
        print(f"tracker result -> 275 sent: p50 {ms(latencies, 50):.2f} ms, p95 {ms(latencies, 95):.2f} ms")
        trips = ack_round_trips(rig.port)
        print(
            f"COMMAND_ACK round trip (n={len(trips)}): p50 {ms(trips, 50):.2f} ms, p95 {ms(trips, 95):.2f} ms,"
            f" max {max(trips) * 1000:.2f} ms"
        )


def px4(w: float) -> None:
    with Rig(follow=FollowConfig(limits=LIMITS), autopilot=lambda url, **kw: Px4(url, loss_timeout=0.5, **kw)) as rig:
        ap = rig.ap
        assert rig.connected()
        rig.start_tracking((0.7, 0.4, 0.8, 0.55))
        ap.set_mode(True, Px4.POSCTL)
        assert wait_until(lambda: len(ap.setpoints()) > 3, 3) and ap.request_offboard()
        start = time.monotonic()
        rig.tracker.pattern = ["tracking", "uncertain"]  # a score hovering around the threshold
        time.sleep(w / 2)
        rig.tracker.pattern = ["lost"] * 30 + ["tracking"] * 30  # lost for a second, found again
        time.sleep(w / 2)
        setpoints = between([r.at for r in ap.setpoints()], (start, time.monotonic()))
        print(
            f"PX4 OFFBOARD through flicker and loss: {rate(setpoints):.2f} Hz, longest gap"
            f" {max_gap(setpoints):.1f} ms, failsafes {ap.failsafes}"
        )
        stop = time.monotonic()
        rig.gcs.call(mavlink.MAV_CMD_CAMERA_STOP_TRACKING)
        assert wait_until(lambda: ap.custom_mode == Px4.HOLD, 3)
        held = time.monotonic()
        time.sleep(1.5)
        gap = max_gap([r.at for r in ap.setpoints(start)] + [held])
        print(
            f"PX4 STOP_TRACKING in OFFBOARD -> Hold: {(held - stop) * 1000:.0f} ms (longest setpoint gap before it"
            f" {gap:.1f} ms), failsafes {ap.failsafes}"
        )


def swing(rig: Rig, gm: GimbalManager) -> None:
    """Put the target left of centre if the gimbal points right, else right, at the image's mid-height: the
    gimbal swings back and forth, never resting at a stop, so that "at rest" after a loss is the service's
    doing."""
    with rig.tracker.lock:
        x, y, w, h = rig.tracker.box
        rig.tracker.box = ((0.1 if gm.yaw > 0 else 0.8) * 640, 240 - h / 2, w, h)


def gimbal_follow(w: float) -> None:
    with Rig(gimbal=GimbalConfig(rate_hz=20.0)) as rig:
        gm = GimbalManager(f"udpout:127.0.0.1:{rig.port}").start()
        try:
            assert rig.connected() and wait_until(lambda: rig.service.gimbal.manager is not None, 3)
            rig.start_tracking((0.7, 0.6, 0.8, 0.7))
            assert wait_until(lambda: gm.primary == (1, 100), 3)
            time.sleep(0.5)
            span = window(w)
            commands = between([c[0] for c in gm.commands], span)
            print(f"gimbal SET_PITCHYAW (angles) {rate(commands):.2f} Hz, longest gap {max_gap(commands):.1f} ms")
            reactions, rests = [], []
            for _ in range(15):
                swing(rig, gm)
                rig.tracker.state = "tracking"
                time.sleep(0.6)
                assert wait_until(lambda: gm.speed_after(time.monotonic() - 0.1)[1] > math.radians(10), 3)
                seen = len(rig.tracker.updates)
                rig.tracker.state = "lost"
                assert wait_until(lambda seen=seen: any(s == "lost" for _, s, _ in rig.tracker.updates[seen:]), 2)
                lost_at = next(t for t, s, _ in rig.tracker.updates[seen:] if s == "lost")
                assert wait_until(lambda lost_at=lost_at: any(c[0] > lost_at for c in gm.commands), 2)
                reactions.append(next(c[0] for c in gm.commands if c[0] > lost_at) - lost_at)
                time.sleep(0.5)
                rests.append(gm.speed_after(lost_at)[0] - lost_at)
            own = rig.service.loop.stats.gimbal_reactions
            print(
                f"gimbal loss ('lost' result -> the aim held at the manager, n={len(reactions)}):"
                f" p50 {ms(reactions, 50):.2f} ms, p95 {ms(reactions, 95):.2f} ms"
                f" (in the service: p50 {ms(own, 50):.2f} ms, p95 {ms(own, 95):.2f} ms);"
                f" gimbal at rest (< 1°/s) after p50 {ms(rests, 50):.0f} ms, max {max(rests) * 1000:.0f} ms"
            )
            rig.tracker.state = "tracking"
            stale = []
            for _ in range(5):
                swing(rig, gm)
                time.sleep(0.6)
                assert wait_until(lambda: gm.speed_after(time.monotonic() - 0.1)[1] > math.radians(10), 3)
                rig.tracker.running.clear()
                hung = time.monotonic()
                time.sleep(0.8)
                stale.append(gm.speed_after(hung)[0] - hung)
                rig.tracker.running.set()
            print(f"gimbal, tracker hung -> gimbal at rest: {min(stale) * 1000:.0f}-{max(stale) * 1000:.0f} ms")
        finally:
            gm.close()


def gimbal_silent(repeats: int = 3) -> None:
    """Mid-follow at 40°/s, the service killed (not one more packet) or the link cut: time to rest."""
    for flavour in ("ardupilot", "px4"):
        for how in ("killed", "link cut"):
            rests = []
            for _ in range(repeats):
                compid = 1 if flavour == "px4" else 154
                with Rig(gimbal=GimbalConfig(rate_hz=20.0, max_rate=math.radians(40)), flavour=flavour) as rig:
                    gm = GimbalManager(f"udpout:127.0.0.1:{rig.port}", compid=compid, flavour=flavour).start()
                    try:
                        assert rig.connected() and wait_until(lambda rig=rig: rig.service.gimbal.manager is not None, 3)
                        rig.start_tracking((0.8, 0.45, 0.9, 0.55))
                        assert wait_until(lambda gm=gm: gm.yaw > math.radians(15), 3)
                        time.sleep(0.5)
                        if how == "killed":
                            rig.service.link.send = lambda msg, now: False
                            silent = time.monotonic()
                            rig.service.stop()
                        else:
                            gm.deaf = True
                            silent = time.monotonic()
                        time.sleep(2.0)
                        rests.append(gm.speed_after(silent)[0] - silent)
                    finally:
                        gm.close()
            print(
                f"gimbal on {flavour}, service {how} mid-follow (40°/s) -> at rest (< 1°/s) after"
                f" {', '.join(f'{r * 1000:.0f}' for r in rests)} ms"
            )


if __name__ == "__main__":
    seconds = float(sys.argv[1]) if len(sys.argv) > 1 else 5.0
    camera_and_vehicle(seconds)
    px4(seconds)
    gimbal_follow(seconds)
    gimbal_silent()
