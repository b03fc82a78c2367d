"""A real ground station library against the running service: MAVSDK (PyPI `mavsdk` >= 4, the native binding
that carries MAVSDK's C++ library: no mavsdk_server process, nothing beyond loopback) with its default ids
(system 245, component 190) discovers the camera, lists it, tracks a rectangle and a point, stops, gets a bad
rectangle DENIED, changes the 275 rate with SET_MESSAGE_INTERVAL, and receives 275 (MavlinkDirect).

Skipped, with the reason, where the wheel does not install or its library does not load."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest

try:  # ImportError where it is not installed; OSError where its C++ library cannot load on this platform
    import mavsdk
    from mavsdk import ComponentType, Configuration, Mavsdk
    from mavsdk.plugins.camera import Camera, CameraError, CameraResult
    from mavsdk.plugins.mavlink_direct import MavlinkDirect, MavlinkMessage
except Exception as exc:  # noqa: BLE001
    pytest.skip(
        f"MAVSDK is not usable here ({type(exc).__name__}: {exc}); install it with `pip install 'mavsdk>=4.1'` "
        "(part of the dev extra) where PyPI has a wheel for this platform and Python",
        allow_module_level=True,
    )

from dadiff.drone.mav import mavlink
from drone_peers import Rig, rate, wait_until

CAMERA = 100
STATUS = "CAMERA_TRACKING_IMAGE_STATUS"


class Session:
    """The service (a Rig on loopback) and a MAVSDK ground station connected to it."""

    def __init__(self, rig: Rig, sdk: Any) -> None:
        self.rig, self.sdk = rig, sdk
        self.system: Any = None
        self.camera: Any = None
        self.direct: Any = None
        self.statuses: list[tuple[float, int, int, dict[str, Any]]] = []  # (time, sysid, compid, fields)
        self._lock = threading.Lock()

    def on_status(self, msg: Any, _user: Any) -> None:
        with self._lock:
            self.statuses.append((time.monotonic(), msg.system_id, msg.component_id, json.loads(msg.fields_json)))

    def since(self, t: float) -> list[tuple[float, int, int, dict[str, Any]]]:
        with self._lock:
            return [s for s in self.statuses if s[0] >= t]

    def command_long(self, command: int, *params: float) -> dict[str, Any]:
        """COMMAND_LONG to the camera through MavlinkDirect; the final COMMAND_ACK's fields."""
        p = list(params) + [0.0] * (7 - len(params))
        fields = {"target_system": 1, "target_component": CAMERA, "command": command, "confirmation": 0}
        fields.update({f"param{i + 1}": v for i, v in enumerate(p)})
        msg = MavlinkMessage("COMMAND_LONG", 245, 190, 1, CAMERA, json.dumps(fields))
        return json.loads(self.direct.send_command(msg).fields_json)


@pytest.fixture(scope="module")
def session() -> Iterator[Session]:
    if not hasattr(mavsdk, "Mavsdk"):
        pytest.skip("mavsdk < 4 (the gRPC wrapper) is installed; these tests use the native binding mavsdk>=4.1")
    from mavsdk.logging import LogLevel, log_subscribe

    log_subscribe(lambda level, message, file, line: level < LogLevel.WARN)  # keep MAVSDK's chatter out of -q runs
    with Rig() as rig:
        sdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))  # 245/190
        try:
            assert sdk.add_any_connection(f"udpout://127.0.0.1:{rig.port}") == mavsdk.ConnectionResult.SUCCESS
            s = Session(rig, sdk)
            assert wait_until(lambda: any(x.has_camera() for x in sdk.get_systems()), 10), "MAVSDK saw no camera"
            s.system = next(x for x in sdk.get_systems() if x.has_camera())
            s.camera, s.direct = Camera(s.system), MavlinkDirect(s.system)
            handle = s.direct.subscribe_message(STATUS, s.on_status)
            assert wait_until(lambda: rig.service.feed.frame_size is not None, 5)
            yield s
            s.direct.unsubscribe_message(handle)
        finally:
            sdk.destroy()


def test_discovers_the_camera(session: Session) -> None:
    assert session.system.get_system_id() == 1 and CAMERA in session.system.component_ids()
    assert session.system.has_camera()
    assert wait_until(lambda: bool(session.camera.camera_list().cameras), 5)  # after CAMERA_INFORMATION
    info = session.camera.camera_list().cameras[0]
    assert (info.component_id, info.vendor_name, info.model_name) == (CAMERA, "dadiff", "dadiff-tracker")
    assert (info.horizontal_resolution_px, info.vertical_resolution_px) == (640, 480)
    assert session.rig.service.camera.ignored == 0  # MAVSDK's 245 is allowed by default


def test_track_rectangle_point_and_stop_with_275(session: Session) -> None:
    rig, camera = session.rig, session.camera
    inits = len(rig.tracker.inits)
    start = time.monotonic()
    assert camera.track_rectangle(CAMERA, 0.4, 0.4, 0.6, 0.6) == CameraResult.SUCCESS
    assert wait_until(lambda: len(rig.tracker.inits) == inits + 1, 3)
    assert rig.tracker.inits[-1] == pytest.approx((256.0, 192.0, 128.0, 96.0), abs=1e-3)
    time.sleep(1.2)
    active = [s for s in session.since(start + 0.1) if s[3]["tracking_status"] == 1]
    assert len(active) >= 8 and {(s[1], s[2]) for s in active} == {(1, CAMERA)}
    assert rate([s[0] for s in active]) == pytest.approx(10.0, rel=0.2)
    last = active[-1][3]
    assert last["tracking_mode"] == mavlink.CAMERA_TRACKING_MODE_RECTANGLE
    assert last["rec_top_y"] == pytest.approx(0.4, abs=1e-6) and last["rec_bottom_y"] == pytest.approx(0.6, abs=1e-6)
    assert all(last[k] is not None for k in ("point_x", "point_y", "radius"))  # no NaN (null in JSON)

    assert camera.track_point(CAMERA, 0.5, 0.5, 0.1) == CameraResult.SUCCESS
    assert wait_until(lambda: len(rig.tracker.inits) == inits + 2, 3)
    x, y, w, h = rig.tracker.inits[-1]
    assert (x + w / 2, y + h / 2, w) == pytest.approx((320, 240, 128))

    stop = time.monotonic()
    assert camera.track_stop(CAMERA) == CameraResult.SUCCESS
    assert wait_until(lambda: any(s[3]["tracking_status"] == 0 for s in session.since(stop)), 3)


def test_bad_rectangle_is_denied(session: Session) -> None:
    inits = len(session.rig.tracker.inits)
    with pytest.raises(CameraError) as denied:
        session.camera.track_rectangle(CAMERA, 0.6, 0.6, 0.4, 0.4)  # right edge left of the left one
    assert denied.value.result == CameraResult.DENIED
    with pytest.raises(CameraError) as bad_point:
        session.camera.track_point(CAMERA, 0.5, 0.5, 2.0)
    assert bad_point.value.result == CameraResult.DENIED
    time.sleep(0.1)
    assert len(session.rig.tracker.inits) == inits


def test_set_message_interval(session: Session) -> None:
    camera = session.camera
    assert camera.track_rectangle(CAMERA, 0.2, 0.2, 0.4, 0.4) == CameraResult.SUCCESS
    ack = session.command_long(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 275, 50_000)  # 20 Hz
    assert (ack["command"], ack["result"], ack["target_system"]) == (511, mavlink.MAV_RESULT_ACCEPTED, 245)
    time.sleep(0.2)
    t0 = time.monotonic()
    time.sleep(1.0)
    fast = [s[0] for s in session.since(t0) if s[3]["tracking_status"] == 1]
    assert rate(fast) == pytest.approx(20.0, rel=0.2)
    ack = session.command_long(mavlink.MAV_CMD_GET_MESSAGE_INTERVAL, 275)
    assert ack["result"] == mavlink.MAV_RESULT_ACCEPTED
    assert session.command_long(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 275, -1)["result"] == 0
    time.sleep(0.15)
    quiet = time.monotonic()
    time.sleep(0.5)
    assert session.since(quiet) == []  # off
    assert session.command_long(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 275, 0)["result"] == 0  # back to default
    assert wait_until(lambda: bool(session.since(quiet)), 2)
    bad = session.command_long(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 275, -5)
    assert bad["result"] == mavlink.MAV_RESULT_DENIED
    assert camera.track_stop(CAMERA) == CameraResult.SUCCESS
