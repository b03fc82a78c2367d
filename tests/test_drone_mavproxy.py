"""Through MAVProxy (headless): ground station and autopilot on MAVProxy's outputs, the service as its master.

Skipped when MAVProxy is not installed (`pip install --no-deps mavproxy==1.8.75 pyserial`).
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from dadiff.drone.follow import FollowConfig
from dadiff.drone.mav import mavlink
from drone_peers import Autopilot, GroundStation, Rig, free_port, wait_until

pytest.importorskip("MAVProxy", reason="MAVProxy is not installed")
pytest.importorskip("serial", reason="MAVProxy needs pyserial")
SCRIPT = shutil.which("mavproxy.py")


@pytest.mark.skipif(SCRIPT is None, reason="mavproxy.py is not on PATH")
def test_track_and_follow_through_mavproxy(tmp_path: Path) -> None:
    with Rig(follow=FollowConfig()) as rig:
        rig.ap.close()  # this test's peers talk to MAVProxy instead
        rig.gcs.close()
        ap_port, gcs_port = free_port(), free_port()
        command = [
            sys.executable,
            str(SCRIPT),
            f"--master=udpout:127.0.0.1:{rig.port}",
            f"--out=udpin:127.0.0.1:{ap_port}",
            f"--out=udpin:127.0.0.1:{gcs_port}",
            "--daemon",
            "--no-state",
            "--nowait",
            "--mav20",
            "--source-system=250",
            "--default-modules=link",
        ]
        proxy = subprocess.Popen(
            command, cwd=tmp_path, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT
        )
        ap = Autopilot(f"udpout:127.0.0.1:{ap_port}").start()
        gcs = GroundStation(f"udpout:127.0.0.1:{gcs_port}").start()
        try:
            assert wait_until(lambda: rig.service.link.sysid == 1, 15), "no autopilot heartbeat through MAVProxy"
            assert gcs.wait_for("HEARTBEAT", 5, where=lambda m: m.get_srcComponent() == 100) is not None
            assert wait_until(lambda: rig.service.feed.frame_size is not None, 5)
            reply = gcs.call(mavlink.MAV_CMD_CAMERA_TRACK_RECTANGLE, 0.7, 0.4, 0.8, 0.55, timeout=5)
            assert reply is not None and reply.result == mavlink.MAV_RESULT_ACCEPTED
            status = gcs.wait_for("CAMERA_TRACKING_IMAGE_STATUS", 5, where=lambda m: m.tracking_status == 1)
            assert status is not None and status.get_srcComponent() == 100
            ap.set_mode(True, 4)
            setpoint = ap.wait_for("SET_POSITION_TARGET_LOCAL_NED", 5, where=lambda m: m.yaw_rate > 0)
            assert setpoint is not None and setpoint.coordinate_frame == mavlink.MAV_FRAME_BODY_NED
            since = time.monotonic()
            assert gcs.call(mavlink.MAV_CMD_CAMERA_STOP_TRACKING, timeout=5).result == mavlink.MAV_RESULT_ACCEPTED
            zero = ap.wait_for("SET_POSITION_TARGET_LOCAL_NED", 3, since, where=lambda m: m.yaw_rate == 0)
            assert zero is not None
        finally:
            ap.close()
            gcs.close()
            proxy.terminate()
            try:
                proxy.communicate(timeout=10)
            except subprocess.TimeoutExpired:
                proxy.kill()
                proxy.communicate(timeout=5)
