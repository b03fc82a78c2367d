"""dadiff-run --mavlink end to end with a real (tiny correlation) model and a video file: options from a TOML
config with the command line overriding it, the 275 boxes against the track log, the log file, exit
codes, one-line errors, and a run where torch, onnx and dadiff.export cannot be imported."""

from __future__ import annotations

import csv
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import cv2
import pytest

from conftest import hangup_as_in_a_session
from dadiff.drone import cli
from dadiff.drone.mav import mavlink
from dadiff.runtime.commands import run
from drone_peers import GroundStation, free_port, wait_until
from runtime_models import write_corr_model
from runtime_scenes import FRAME_H, FRAME_W, moving_sequence
from torchless import PRELUDE


@pytest.fixture(scope="module")
def media(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("drone-cli")
    frames, boxes = moving_sequence(40)
    video = root / "clip.mp4"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"mp4v"), 25.0, (FRAME_W, FRAME_H))
    for frame in frames:
        writer.write(frame)
    writer.release()
    return {"root": root, "video": video, "model": write_corr_model(root / "model"), "box": boxes[0]}


def test_config_file_run_streams_the_tracked_boxes(media: dict[str, Path], tmp_path: Path) -> None:
    port = free_port()
    gcs = GroundStation(f"udpin:127.0.0.1:{port}").start()  # the service sends to it (udpout, --sysid)
    x, y, w, h = media["box"]
    config = tmp_path / "tracker.toml"
    config.write_text(
        textwrap.dedent(
            f"""
            video = "{media["video"]}"
            model = "{media["model"]}"
            mavlink = "udpout:127.0.0.1:{port}"
            sysid = 1
            init = [{x}, {y}, {w}, {h}]
            tracking_rate = 50
            max-frames = 1000
            threads = 1
            output = "{tmp_path / "track.csv"}"
            log-file = "{tmp_path / "tracker.log"}"
            """
        )
    )
    try:
        rc = run.main(["--config", str(config), "--max-frames", "30"])  # the command line wins
    finally:
        assert wait_until(lambda: len(gcs.received("CAMERA_TRACKING_IMAGE_STATUS")) > 0, 2)
        gcs.close()
    assert rc == 0
    with (tmp_path / "track.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 30 and rows[0]["state"] == "init"
    boxes = [tuple(float(r[k]) for k in "xywh") for r in rows]
    norm = [(bx / FRAME_W, by / FRAME_H, (bx + bw) / FRAME_W, (by + bh) / FRAME_H) for bx, by, bw, bh in boxes]
    statuses = [r.msg for r in gcs.received("CAMERA_TRACKING_IMAGE_STATUS")]
    active = [m for m in statuses if m.tracking_status & mavlink.CAMERA_TRACKING_STATUS_FLAGS_ACTIVE]
    assert active
    for m in active:
        rect = (m.rec_top_x, m.rec_top_y, m.rec_bottom_x, m.rec_bottom_y)
        assert any(all(abs(a - b) < 2e-3 for a, b in zip(rect, n, strict=True)) for n in norm)
    log = (tmp_path / "tracker.log").read_text()
    assert "service started" in log and "service stopped: 30 frames" in log


@pytest.mark.parametrize(
    ("lines", "message"),
    [
        ('vidoe = "x.mp4"', "unknown key 'vidoe'"),
        ("follow = 1", "'follow': '1' is not one of vehicle, gimbal"),
        ("realtime = 1", "'realtime' is a switch"),
        ('allow-sysid = "everyone"', "or 'any'"),
        ("sysid = 255", "'sysid': expected an integer from 1 to 254"),
        ('dialect = "px4"', "'dialect'"),
        ("init = [1, 2, 3]", "'init'"),
        ("this is not toml", "not valid TOML"),
    ],
)
def test_config_errors_are_one_line(tmp_path: Path, capsys: pytest.CaptureFixture, lines: str, message: str) -> None:
    config = tmp_path / "bad.toml"
    config.write_text(lines + "\n")
    assert run.main(["--config", str(config), "--video", "0", "--mavlink", "udpin:127.0.0.1:1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("dadiff-run: error:") and message in err[0], err


def test_config_values_and_overrides(tmp_path: Path) -> None:
    from dadiff.drone.config import parse_args

    config = tmp_path / "c.toml"
    config.write_text(
        'video = "/dev/video0"\nmavlink = "/dev/ttyAMA0,921600"\nfollow = true\nhp = {lr = 0.4}\n'
        "allow_sysid = [255, 254]\nmax-speed = 2\ncomponent = 101\n"
    )
    parser = run.build_parser()
    cli.add_mavlink_arguments(parser)
    cli.add_mavlink_arguments(parser)  # twice is harmless
    args = parse_args(parser, ["--config", str(config), "--component", "102"])
    assert (args.video, args.mavlink, args.follow, args.hp) == (
        "/dev/video0",
        "/dev/ttyAMA0,921600",
        "vehicle",
        {"lr": "0.4"},
    )
    assert args.allow_sysid == {254, 255} and args.max_speed == 2.0 and args.component == 102
    assert args.tracking_rate == 10.0 and args.sysid is None
    assert args.follow == "vehicle" and args.realtime is True and args.loop is False  # follow = true: the vehicle
    config.write_text('allow_sysid = "any"\nfollow = "gimbal"\nrealtime = false\nloop = true\ngimbal-rate = 30\n')
    args = parse_args(parser, ["--config", str(config), "--stream-url", "rtsp://10.0.0.2:8554/cam"])
    assert (args.allow_sysid, args.follow, args.realtime, args.loop, args.gimbal_rate) == (
        None,
        "gimbal",
        False,
        True,
        30,
    )
    assert args.stream_url == "rtsp://10.0.0.2:8554/cam"
    fresh = run.build_parser()
    args = parse_args(fresh, ["--mavlink", "udpin:0.0.0.0:14560", "--follow", "--video", "0", "--no-realtime"])
    assert (args.follow, args.realtime, args.allow_sysid) == ("vehicle", False, {255, 245})
    assert parse_args(fresh, ["--follow", "gimbal", "--allow-sysid", "any"]).allow_sysid is None
    assert parse_args(fresh, []).follow is None


def test_bad_inputs_exit_2(media: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    base = ["--mavlink", "udpin:127.0.0.1:1", "--model", str(media["model"])]
    assert run.main(["--video", str(tmp_path / "nope.mp4"), *base]) == 2
    key = tmp_path / "empty.key"
    key.write_bytes(b"")
    assert run.main(["--video", str(media["video"]), *base, "--signing-key", str(key)]) == 2
    assert run.main(["--video", str(media["video"]), "--mavlink", "udpin:127.0.0.1:1", "--model", "/no/model"]) == 2
    assert run.main(["--video", str(media["video"]), *base, "--follow-rate", "50"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 4 and all(line.startswith("dadiff-run: error:") for line in err)


CHILD = PRELUDE + textwrap.dedent(
    """
    from dadiff.runtime.commands import run

    video, model, port = sys.argv[1:4]
    argv = ["--video", video, "--model", model, "--mavlink", f"udpout:127.0.0.1:{port}", "--sysid", "1",
            "--init", "220,160,40,40", "--max-frames", "10", "--follow", "--threads", "1"]
    assert run.main(argv) == 0
    loaded = [m for m in sys.modules if any(m == b or m.startswith(b + ".") for b in BLOCKED)]
    assert not loaded, loaded
    print("drone ok without torch/onnx/export")
    """
)


def test_drone_runs_without_torch_onnx_or_export(media: dict[str, Path]) -> None:
    port = free_port()
    proc = subprocess.run(
        [sys.executable, "-c", CHILD, str(media["video"]), str(media["model"]), str(port)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr + proc.stdout
    assert "drone ok without torch/onnx/export" in proc.stdout


@pytest.mark.parametrize("sig, code", [(signal.SIGTERM, 0), (signal.SIGHUP, 130)], ids=["SIGTERM", "SIGHUP"])
def test_sigterm_stops_cleanly(media: dict[str, Path], tmp_path: Path, sig: int, code: int) -> None:
    """A live-looking run (a stream URL that never opens) under SIGTERM: exit 0, the log says stopped. SIGHUP
    (the SSH session that started it dropping; it killed the service at once) stops it the same way, exit 130."""
    script = textwrap.dedent(
        """
        import sys
        from dadiff.runtime.commands import run
        sys.exit(run.main(sys.argv[1:]))
        """
    )
    port = free_port()
    argv = [
        "--video",
        "rtsp://127.0.0.1:1/none",
        "--model",
        str(media["model"]),
        "--mavlink",
        f"udpin:127.0.0.1:{port}",
    ]
    proc = subprocess.Popen([sys.executable, "-c", script, *argv], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            preexec_fn=hangup_as_in_a_session)
    lines: list[bytes] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)  # type: ignore[arg-type]
    reader.start()
    try:
        assert wait_until(lambda: any(b"service started" in line for line in lines), 30)
        proc.send_signal(sig)
        assert proc.wait(timeout=15) == code
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
    reader.join(5)
    assert any(b"service stopped" in line for line in lines), lines


def test_rehearse_a_recorded_flight_with_a_ground_station(media: dict[str, Path]) -> None:
    """A recorded clip (25 FPS, 40 frames) in service mode plays at its own pace and `--loop` replays it, so a
    ground station has time to draw a box; udpout without --sysid: the camera speaks first as system 1."""
    port = free_port()
    gcs = GroundStation(f"udpin:127.0.0.1:{port}").start()
    argv = ["--video", str(media["video"]), "--model", str(media["model"]), "--threads", "1",
            "--mavlink", f"udpout:127.0.0.1:{port}", "--loop", "--max-frames", "60"]  # fmt: skip
    result: list[int] = []
    start = time.monotonic()
    runner = threading.Thread(target=lambda: result.append(run.main(argv)), daemon=True)
    try:
        runner.start()
        beat = gcs.wait_for("HEARTBEAT", 10, where=lambda m: m.get_srcComponent() == 100)
        assert beat is not None and beat.get_srcSystem() == 1
        assert wait_until(lambda: bool(gcs.received("CAMERA_TRACKING_IMAGE_STATUS")), 5)  # the camera is up
        deadline = time.monotonic() + 5
        while True:  # before its first frame the camera answers TEMPORARILY_REJECTED: a ground station retries
            reply = gcs.call(mavlink.MAV_CMD_CAMERA_TRACK_RECTANGLE, 0.3, 0.3, 0.5, 0.5, target=(1, 100))
            if reply is None or reply.result != mavlink.MAV_RESULT_TEMPORARILY_REJECTED or time.monotonic() > deadline:
                break
            time.sleep(0.1)
        assert reply is not None and reply.result == mavlink.MAV_RESULT_ACCEPTED
        active = gcs.wait_for("CAMERA_TRACKING_IMAGE_STATUS", 3, where=lambda m: m.tracking_status == 1)
        assert active is not None
        runner.join(20)
    finally:
        gcs.close()
    elapsed = time.monotonic() - start
    assert result == [0] and elapsed >= 60 / 25 - 0.2  # 60 frames at 25 FPS, not as fast as they decode


def test_options_reach_the_service_settings() -> None:
    import math

    from dadiff.drone.camera import DEFAULT_ALLOWED
    from dadiff.drone.config import parse_args

    assert cli.ALLOWED_DEFAULT == DEFAULT_ALLOWED == {255, 245}  # the parser's copy (no pymavlink at parse time)
    base = ["--video", "0", "--mavlink", "udpout:127.0.0.1:14550"]
    extra = ["--follow", "gimbal", "--gimbal-rate", "40", "--max-gimbal-rate", "30"]
    extra += ["--stream-url", "rtsp://10.0.0.2/cam", "--no-realtime", "--loop"]
    args = parse_args(run.build_parser(), [*base, *extra])
    s = cli._settings(args, b"k" * 32)
    assert s.follow is None and s.gimbal is not None and s.gimbal.rate_hz == 40
    assert s.gimbal.max_rate == pytest.approx(math.radians(30))
    assert (s.realtime, s.loop, s.link.sysid) == (False, True, None)
    assert (s.camera.stream_url, s.camera.trust_signed, s.camera.allowed_sysids) == (
        "rtsp://10.0.0.2/cam",
        True,
        {255, 245},
    )
    s = cli._settings(parse_args(run.build_parser(), [*base, "--follow", "--allow-sysid", "any"]), None)
    assert s.follow is not None and s.gimbal is None and s.camera.allowed_sysids is None and s.realtime
    assert not s.camera.trust_signed
