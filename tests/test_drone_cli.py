"""dadiff-run --mavlink end to end with a real (tiny correlation) model and a video file: options from a TOML
config with the command line overriding it, the 275 boxes against the track log, the log file, exit
codes, one-line errors, and a run where torch, onnx and dadiff.export cannot be imported."""

from __future__ import annotations

import csv
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import cv2
import pytest

from dadiff.drone import cli
from dadiff.drone.mav import mavlink
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
        rc = cli.main(["--config", str(config), "--max-frames", "30"])  # the command line wins
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
        ("follow = 1", "'follow' is a switch"),
        ("sysid = 255", "'sysid': expected an integer from 1 to 254"),
        ('dialect = "px4"', "'dialect'"),
        ("init = [1, 2, 3]", "'init'"),
        ("this is not toml", "not valid TOML"),
    ],
)
def test_config_errors_are_one_line(tmp_path: Path, capsys: pytest.CaptureFixture, lines: str, message: str) -> None:
    config = tmp_path / "bad.toml"
    config.write_text(lines + "\n")
    assert cli.main(["--config", str(config), "--video", "0", "--mavlink", "udpin:127.0.0.1:1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("dadiff-run: error:") and message in err[0], err


def test_config_values_and_overrides(tmp_path: Path) -> None:
    from dadiff.drone.config import parse_args
    from dadiff.runtime import cli as runtime_cli

    config = tmp_path / "c.toml"
    config.write_text(
        'video = "/dev/video0"\nmavlink = "/dev/ttyAMA0,921600"\nfollow = true\nhp = {lr = 0.4}\n'
        "allow_sysid = [255, 254]\nmax-speed = 2\ncomponent = 101\n"
    )
    parser = runtime_cli.build_parser()
    cli.add_mavlink_arguments(parser)
    cli.add_mavlink_arguments(parser)  # twice is harmless
    args = parse_args(parser, ["--config", str(config), "--component", "102"])
    assert (args.video, args.mavlink, args.follow, args.hp) == (
        "/dev/video0",
        "/dev/ttyAMA0,921600",
        True,
        {"lr": "0.4"},
    )
    assert args.allow_sysid == {254, 255} and args.max_speed == 2.0 and args.component == 102
    assert args.tracking_rate == 10.0 and args.sysid is None


def test_bad_inputs_exit_2(media: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    base = ["--mavlink", "udpin:127.0.0.1:1", "--model", str(media["model"])]
    assert cli.main(["--video", str(tmp_path / "nope.mp4"), *base]) == 2
    key = tmp_path / "empty.key"
    key.write_bytes(b"")
    assert cli.main(["--video", str(media["video"]), *base, "--signing-key", str(key)]) == 2
    assert cli.main(["--video", str(media["video"]), "--mavlink", "udpin:127.0.0.1:1", "--model", "/no/model"]) == 2
    assert cli.main(["--video", str(media["video"]), *base, "--follow-rate", "50"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 4 and all(line.startswith("dadiff-run: error:") for line in err)


CHILD = PRELUDE + textwrap.dedent(
    """
    from dadiff.drone import cli

    video, model, port = sys.argv[1:4]
    argv = ["--video", video, "--model", model, "--mavlink", f"udpout:127.0.0.1:{port}", "--sysid", "1",
            "--init", "220,160,40,40", "--max-frames", "10", "--follow", "--threads", "1"]
    assert cli.main(argv) == 0
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


def test_sigterm_stops_cleanly(media: dict[str, Path], tmp_path: Path) -> None:
    """A live-looking run (a stream URL that never opens) under SIGTERM: exit 0, the log says stopped."""
    script = textwrap.dedent(
        """
        import sys
        from dadiff.drone import cli
        sys.exit(cli.main(sys.argv[1:]))
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
    proc = subprocess.Popen([sys.executable, "-c", script, *argv], stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    lines: list[bytes] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)  # type: ignore[arg-type]
    reader.start()
    try:
        assert wait_until(lambda: any(b"service started" in line for line in lines), 30)
        proc.terminate()
        assert proc.wait(timeout=15) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
    reader.join(5)
    assert any(b"service stopped" in line for line in lines), lines
