"""Recovery without a restart: the link after its peer restarts (TCP and UDP), the camera after it drops
out, and the heartbeat and systemd watchdog withheld while the tracker loop hangs."""

from __future__ import annotations

import socket
import threading
import time

from dadiff.drone.follow import FollowConfig
from dadiff.drone.link import LinkSettings
from dadiff.drone.service import Service, ServiceSettings
from dadiff.drone.systemd import Notifier
from drone_peers import Autopilot, FakeTracker, Rig, Running, SourceFactory, free_port, rate, wait_until

FAST = {"retry_min": 0.1, "retry_max": 0.4, "silence_timeout": 1.5}


def camera_beats(peer: Autopilot, since: float = 0.0) -> list:
    return peer.received("HEARTBEAT", since, src_component=100)


def test_tcp_link_reconnects_after_the_autopilot_restarts() -> None:
    port = free_port(socket.SOCK_STREAM)
    url = f"tcpin:127.0.0.1:{port}"
    first = Autopilot(url).start()
    service = Service(
        ServiceSettings(LinkSettings(f"tcp:127.0.0.1:{port}", **FAST), heartbeat_hz=5.0), FakeTracker(), SourceFactory()
    )
    try:
        with Running(service):
            assert wait_until(lambda: len(camera_beats(first)) >= 2, 5)
            first.close()
            time.sleep(0.5)  # down for a while: connection refused, retried
            second = Autopilot(url).start()
            try:
                assert wait_until(lambda: len(camera_beats(second)) >= 2, 8)
                assert service.link.opens >= 2 and service.link.sysid == 1
            finally:
                second.close()
    finally:
        first.close()


def test_udp_link_survives_the_autopilot_restarting() -> None:
    port = free_port()
    url = f"udpin:127.0.0.1:{port}"
    first = Autopilot(url).start()
    service = Service(
        ServiceSettings(LinkSettings(f"udpout:127.0.0.1:{port}", sysid=1, **FAST), heartbeat_hz=5.0),
        FakeTracker(),
        SourceFactory(),
    )
    with Running(service):
        assert wait_until(lambda: len(camera_beats(first)) >= 2, 5)
        first.close()
        time.sleep(0.3)
        second = Autopilot(url).start()
        try:
            assert wait_until(lambda: len(camera_beats(second)) >= 2, 5)
            assert wait_until(lambda: service.loop.autopilot is not None, 3)  # and it hears the new one
            stamp = service.loop.autopilot.stamp
            assert wait_until(lambda: service.loop.autopilot.stamp > stamp, 3)
        finally:
            second.close()


def test_camera_reopens_after_dropping_out() -> None:
    with Rig(source={"fps": 50.0, "limit": 15}, video_retry=(0.05, 0.1)) as rig:
        assert rig.connected()
        rig.start_tracking()
        assert wait_until(lambda: len(rig.source.opened) >= 4, 8)
        since = time.monotonic()
        assert rig.gcs.wait_for("CAMERA_TRACKING_IMAGE_STATUS", 3, since, where=lambda m: m.tracking_status == 1)
        assert rig.tracker.inits and len(rig.tracker.inits) == 1  # the target survives the reconnects


def test_heartbeat_and_watchdog_only_while_the_tracker_loop_runs(tmp_path) -> None:
    path = str(tmp_path / "notify")
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    listener.bind(path)
    listener.settimeout(0.05)
    notifier = Notifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "200000"})
    notes: list[tuple[float, str]] = []
    stop = threading.Event()

    def collect() -> None:
        while not stop.is_set():
            try:
                notes.append((time.monotonic(), listener.recv(256).decode()))
            except TimeoutError:
                pass

    reader = threading.Thread(target=collect, daemon=True)
    reader.start()
    try:
        with Rig(notifier=notifier, heartbeat_hz=5.0, loop_stall=0.6, follow=FollowConfig()) as rig:
            assert rig.connected()
            rig.start_tracking()
            rig.ap.set_mode(True, 4)
            assert wait_until(lambda: len(rig.ap.setpoints()) > 3, 3)
            rig.tracker.running.clear()  # inference hangs
            hung = time.monotonic()
            time.sleep(1.5)
            resumed = time.monotonic()
            rig.tracker.running.set()
            assert wait_until(lambda: len(camera_beats(rig.gcs, resumed)) >= 2, 3)
            beats = [r.at for r in camera_beats(rig.gcs, hung - 1.0)]
            assert [b for b in beats if b < hung] and not [b for b in beats if hung + 0.7 < b < resumed]  # 0.6 s grace
            assert rate([r.at for r in camera_beats(rig.gcs, resumed)]) > 2.0
            # the detection went stale while hung: zero velocity, then silence until fresh results came back
            during = [r for r in rig.ap.setpoints(hung) if r.at < resumed]
            assert during and during[-1].msg.yaw_rate == 0 and during[-1].msg.vx == 0
            assert during[-1].at - hung < 0.6
            # 275 says ERROR instead of repeating the old box while hung
            statuses = rig.gcs.received("CAMERA_TRACKING_IMAGE_STATUS", hung)
            assert any(r.msg.tracking_status == 2 for r in statuses if r.at < resumed)
        watchdogs = [t for t, text in notes if text == "WATCHDOG=1"]
        assert notes[0][1].startswith("READY=1") and notes[-1][1] == "STOPPING=1"
        assert len(watchdogs) >= 5
        assert not [t for t in watchdogs if hung + 0.7 < t < resumed]
    finally:
        stop.set()
        reader.join(2)
        listener.close()
