"""Issue 13 on the onboard side: no data lost, no traceback for a user error, one error style.

Each test names the failure it guards against; before the fix each one failed (a traceback, exit 0 with
a clobbered input, a silent run, a usage block).
"""

from __future__ import annotations

import logging
import math
import os
import signal
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from dadiff.drone.cli import mavlink_conn
from dadiff.drone.link import parse_datagram
from dadiff.drone.mav import mavlink
from dadiff.runtime.commands import run as cli
from dadiff.runtime.cpu import INT8_WARNING, cpu_flags, int8_saturates, int8_warning
from dadiff.runtime.outputs import OutputError, TrackLog
from dadiff.runtime.sources import Frame, read_image
from runtime_models import write_corr_model

REPO = Path(__file__).resolve().parents[1]
BOX = "40,40,20,15"


def _write_video(path: Path, frames: int, fourcc: str = "mp4v") -> Path:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), 25.0, (160, 120))
    for i in range(frames):
        image = np.full((120, 160, 3), 30, np.uint8)
        cv2.rectangle(image, (40 + i, 40), (60 + i, 55), (220, 220, 220), -1)
        writer.write(image)
    writer.release()
    return path


@pytest.fixture(scope="module")
def media(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("reliability")
    avi = _write_video(root / "night.avi", 40, "MJPG")
    truncated = root / "truncated.avi"
    data = avi.read_bytes()
    truncated.write_bytes(data[: len(data) // 2])
    return {"root": root, "video": _write_video(root / "night.mp4", 12), "truncated": truncated,
            "model": write_corr_model(root / "model")}


def _one_error(capsys: pytest.CaptureFixture, prog: str = "dadiff-run") -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"{prog}: error: "), err
    return err[0]


def test_save_video_over_the_input_is_refused_and_the_input_kept(media, tmp_path, capsys) -> None:
    same = tmp_path / "same.mp4"
    same.write_bytes(media["video"].read_bytes())
    before = same.read_bytes()
    argv = ["--video", str(same), "--init", BOX, "--model", str(media["model"]), "--max-frames", "5"]
    assert cli.main([*argv, "--save-video", str(same)]) == 2  # was: exit 0 and a 3-frame file in its place
    assert "names the input video" in _one_error(capsys)
    assert same.read_bytes() == before
    log = tmp_path / "log.csv"
    link = tmp_path / "alias.mp4"
    link.symlink_to(same)
    assert cli.main([*argv, "--save-video", str(link), "--output", str(log)]) == 2
    assert same.read_bytes() == before and not log.exists()


def _image_folder(root: Path, frames: int = 6) -> Path:
    (root / "img").mkdir(parents=True)
    for i in range(frames):
        image = np.full((120, 160, 3), 30, np.uint8)
        cv2.rectangle(image, (40 + i, 40), (60 + i, 55), (220, 220, 220), -1)
        cv2.imwrite(str(root / "img" / f"{i + 1:04d}.jpg"), image)
    (root / "groundtruth_rect.txt").write_text("40,40,21,16\n" * frames)
    return root


def test_outputs_over_the_input_folders_files_are_refused_and_new_ones_kept(media, tmp_path, capsys) -> None:
    seq = _image_folder(tmp_path / "seq")
    before = {f: f.read_bytes() for f in [*(seq / "img").iterdir(), seq / "groundtruth_rect.txt"]}
    argv = ["--video", str(seq), "--model", str(media["model"]), "--max-frames", "4"]
    (seq / "frame.csv").symlink_to(seq / "img" / "0002.jpg")
    (seq / "truth.csv").symlink_to(seq / "groundtruth_rect.txt")
    for name in ("frame.csv", "truth.csv"):  # links: the suffixes alone would let them through
        assert cli.main([*argv, "--output", str(seq / name)]) == 2
        assert "an input file of" in _one_error(capsys)
    assert {f: f.read_bytes() for f in before} == before
    assert cli.main([*argv, "--output", str(seq / "track.csv"), "--save-video", str(seq / "img" / "out.mp4")]) == 0
    assert (seq / "track.csv").is_file() and (seq / "img" / "out.mp4").is_file()  # new files beside the input


def test_save_video_must_be_a_video_file(media, tmp_path, capsys) -> None:
    """`--save-video frames/%04d.jpg` went to OpenCV's image-sequence writer and replaced same-named frames."""
    argv = ["--video", str(media["video"]), "--init", BOX, "--model", str(media["model"]), "--max-frames", "3"]
    (tmp_path / "frames").mkdir()
    assert cli.main([*argv, "--save-video", str(tmp_path / "frames" / "%04d.jpg")]) == 2
    assert "--save-video must end in .mp4" in _one_error(capsys)
    assert not any((tmp_path / "frames").iterdir())


def test_service_mode_refuses_to_overwrite_its_input_too(media, tmp_path, capsys) -> None:
    same = tmp_path / "same.mp4"
    same.write_bytes(media["video"].read_bytes())
    argv = ["--video", str(same), "--mavlink", "udpin:127.0.0.1:9", "--model", str(media["model"]),
            "--save-video", str(same)]
    assert cli.main(argv) == 2
    assert "names the input video" in _one_error(capsys)
    assert same.read_bytes() == media["video"].read_bytes()


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full")
def test_full_disk_on_output_is_one_line(media, tmp_path, capsys) -> None:
    full = tmp_path / "full.csv"
    full.symlink_to("/dev/full")
    argv = ["--video", str(media["video"]), "--init", BOX, "--model", str(media["model"]), "--output", str(full)]
    assert cli.main(argv) == 2  # was: three chained OSError 28 tracebacks
    assert "No space left on device" in _one_error(capsys)


def test_track_log_that_fails_mid_run_reports_once_and_keeps_rows(tmp_path) -> None:
    log = TrackLog(tmp_path / "t.csv")
    frame = Frame(0, 0.0, np.zeros((4, 4, 3), np.uint8))
    from dadiff.runtime.outputs import Record

    log.write(frame, Record((1, 2, 3, 4), 0.9, "tracking"))

    class Full:
        def writerow(self, row: object) -> None:
            raise OSError(28, "No space left on device")

    log._csv = Full()  # type: ignore[assignment]
    with pytest.raises(OutputError, match="the first 1 rows were saved"):
        log.write(frame, Record((1, 2, 3, 4), 0.9, "tracking"))
    log.write(frame, Record((1, 2, 3, 4), 0.9, "tracking"))  # no second error
    log.close()
    assert (tmp_path / "t.csv").read_text().count("\n") == 2  # header + the row written before the failure


def test_config_that_is_not_utf8_is_one_line(tmp_path, capsys) -> None:
    config = tmp_path / "bad.toml"
    config.write_bytes(b'video = "\xff\xfe"\n')
    assert cli.main(["--config", str(config)]) == 2  # was: UnicodeDecodeError traceback
    assert "not a text file" in _one_error(capsys)


def test_config_nested_too_deeply_is_one_line(tmp_path, capsys) -> None:
    config = tmp_path / "deep.toml"
    config.write_text("init = " + "[" * 5000 + "]" * 5000 + "\n")
    assert cli.main(["--config", str(config)]) == 2  # was: RecursionError traceback
    assert "not valid TOML (nested too deeply)" in _one_error(capsys)


def test_an_abbreviated_config_option_is_read(media, tmp_path, capsys) -> None:
    """`--conf FILE` was taken as --config by the parser but never read: its keys were silently ignored."""
    config = tmp_path / "c.toml"
    config.write_text("bogus = 1\n")
    argv = ["--video", str(media["video"]), "--init", BOX, "--model", str(media["model"]), "--max-frames", "2"]
    assert cli.main(["--conf", str(config), *argv]) == 2
    assert "unknown key 'bogus'" in _one_error(capsys)


@pytest.mark.parametrize("box", ["0,0,10,1e308", "0,0,1e160,10", "0,0,700,10"])
def test_an_init_box_many_frames_wide_is_one_line(box: str, media, capsys) -> None:
    argv = ["--video", str(media["video"]), "--init", box, "--model", str(media["model"])]
    assert cli.main(argv) == 2  # was: OverflowError in crop.py for sides past ~1e155
    assert "is more than 4x the 160x120 frame" in _one_error(capsys)


def test_a_model_that_answers_nan_is_lost_not_tracking(tmp_path) -> None:
    """A checkpoint of NaN weights exported with 'parity OK' answered score nan on every frame, never lost."""
    from dadiff.runtime.tracker import Tracker
    from runtime_models import write_corr_model

    tracker = Tracker.load(write_corr_model(tmp_path / "nan", gain=float("nan")), threads=1)
    image = np.full((120, 160, 3), 30, np.uint8)
    tracker.init(image, (40, 40, 20, 15))
    states = [tracker.update(image) for _ in range(10)]
    assert all(r.box == states[0].box and np.isfinite(r.box).all() for r in states)
    assert states[0].state == "uncertain" and states[-1].state == "lost"


def test_demo_seed_names_the_option(capsys) -> None:
    assert cli.main(["--demo", "--seed", "-1"]) == 2  # was: "expected non-negative integer", no option named
    assert "argument --seed: expected an integer of at least 0, got '-1'" in _one_error(capsys)


def _api_tracker(media: dict[str, Path], **kw: object):
    from dadiff.runtime.tracker import Tracker

    return Tracker.load(media["model"], threads=1, **kw)


@pytest.mark.parametrize(("frame", "box", "message"), [
    (np.zeros((0, 5, 4), np.uint8), (0, 0, 1, 1), "frame is empty"),  # was: cv2.error from cvtColor
    (np.zeros((120, 160, 3), np.uint8), (10**400, 1, 2, 3), "four numbers"),  # was: OverflowError
    (np.zeros((120, 160, 3), np.uint8), "1234", "four numbers"),  # was: tracked as (1, 2, 3, 4)
    (np.zeros((120, 160, 3), np.uint8), b"1234", "four numbers"),  # was: (49, 50, 51, 52)
    (np.zeros((120, 160, 3), np.uint8), (159.9, 119.9, 1e-300, 1e-300), "under 0.1 px"),  # was: ZeroDivisionError
])
def test_api_init_refuses_with_one_line(frame, box, message: str, media) -> None:
    from dadiff.runtime.errors import InputError

    with pytest.raises(InputError, match=message) as info:
        _api_tracker(media).init(frame, box)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("overrides", [{"lr": 10**400}, {"lr": True}, "lr=1", [("lr", 1)]])
def test_api_overrides_are_checked(overrides, media) -> None:
    from dadiff.runtime.errors import InputError

    with pytest.raises(InputError):  # were: OverflowError, lr = 1.0, AttributeError, AttributeError
        _api_tracker(media, overrides=overrides)


@pytest.mark.parametrize("shift", [(math.nan, 0), (math.inf, 0), (1,), None, "ab", (1e300, 0)])
def test_api_look_checks_its_shift(shift, media) -> None:
    from dadiff.runtime.errors import InputError

    tracker = _api_tracker(media)
    image = np.full((120, 160, 3), 30, np.uint8)
    tracker.init(image, (40, 40, 20, 15))
    with pytest.raises(InputError, match="shift must be"):  # were: ValueError, OverflowError, IndexError, ...
        tracker.look(image, (40, 40, 20, 15), shift)


def test_api_box_never_larger_than_a_tiny_frame(media) -> None:
    tracker = _api_tracker(media)
    tracker.init(np.full((1, 1, 3), 30, np.uint8), (0, 0, 1, 1))
    x, y, w, h = tracker.update(np.full((1, 1, 3), 30, np.uint8)).box
    assert w <= 1 and h <= 1  # was: (-4, -4, 8, 8), the 8 px floor on a 1 px frame


def test_motion_read_of_a_tall_thin_frame_stays_small() -> None:
    from dadiff.runtime.motion import MAX_SMALL_HEIGHT, PictureMotion

    small = PictureMotion(0.1)._small(np.zeros((100_000, 1, 3), np.uint8))
    assert small.shape == (MAX_SMALL_HEIGHT, 160)  # was: 160 x 16 000 000, gigabytes and seconds a frame


def test_demo_refuses_options_it_does_not_apply(tmp_path, capsys) -> None:
    argv = ["--demo", "--demo-out", str(tmp_path / "d"), "--hp", "lr=0.9", "--output", str(tmp_path / "t.csv")]
    assert cli.main(argv) == 2  # was: exit 0, the options silently not applied, no t.csv
    assert "--output, --hp do not apply" in _one_error(capsys)


def test_demo_with_mavlink_is_refused(tmp_path, capsys) -> None:
    argv = ["--demo", "--demo-out", str(tmp_path / "d"), "--mavlink", "udpout:127.0.0.1:14599"]
    assert cli.main(argv) == 2  # was: the service started, --demo silently dropped
    assert "--demo tracks a generated sequence on its own" in _one_error(capsys)
    assert not (tmp_path / "d").exists()


def test_service_options_without_mavlink_are_refused(tmp_path, capsys) -> None:
    config, video = tmp_path / "c.toml", str(tmp_path / "v.mp4")
    config.write_text('follow = "gimbal"\n')
    (tmp_path / "v.mp4").write_bytes(b"never read")
    for argv in (["--video", video, "--init", "1,1,8,8", "--follow", "gimbal", "--loop", "--tracking-rate", "5"],
                 ["--config", str(config), "--video", video, "--init", "1,1,8,8"]):
        assert cli.main(argv) == 2  # was: a plain track, exit 0, the options applying to nothing
        assert "--follow" in (err := _one_error(capsys)) and "options of the MAVLink service" in err


def test_demo_out_naming_a_file_is_one_line(tmp_path, capsys) -> None:
    target = tmp_path / "afile"
    target.write_text("x")
    assert cli.main(["--demo", "--demo-out", str(target)]) == 2  # was: FileExistsError traceback
    assert "--demo-out exists and is not a folder" in _one_error(capsys)


def test_sigterm_during_demo_stops_cleanly(monkeypatch, tmp_path, capsys) -> None:
    import dadiff.runtime.commands.demo as demo

    def killed(*args: object, **kw: object) -> dict:
        os.kill(os.getpid(), signal.SIGTERM)  # what a service manager sends
        raise AssertionError("SIGTERM did not stop the demo")

    monkeypatch.setattr(demo, "run_demo", killed)
    assert cli.main(["--demo", "--demo-out", str(tmp_path / "d")]) == 130  # was: killed, no cleanup
    assert "interrupted" in capsys.readouterr().err


def test_negative_init_box_needs_no_equals_sign(media, tmp_path, capsys) -> None:
    out = tmp_path / "t.csv"
    argv = ["--video", str(media["video"]), "--init", "-5,-5,15,9", "--model", str(media["model"]),
            "--max-frames", "3", "--output", str(out)]
    assert cli.main(argv) == 0, capsys.readouterr().err  # was: "expected one argument" and no hint
    assert out.read_text().splitlines()[1].split(",")[2:6] == ["-4.5", "-4.5", "15.0", "9.0"]
    assert cli.join_negative_boxes(["--init", "-5,1,2,3", "--seed", "-1"]) == ["--init=-5,1,2,3", "--seed", "-1"]


def test_truncated_video_is_reported_not_silent(media, capsys) -> None:
    argv = ["--video", str(media["truncated"]), "--init", BOX, "--model", str(media["model"])]
    assert cli.main(argv) == 0
    captured = capsys.readouterr()
    assert "truncated or damaged file" in captured.err  # was: exit 0 and "0 skipped"
    assert " 0 skipped" not in captured.out


def test_max_frames_is_not_truncation(media, capsys) -> None:
    argv = ["--video", str(media["video"]), "--init", BOX, "--model", str(media["model"]), "--max-frames", "4"]
    assert cli.main(argv) == 0
    captured = capsys.readouterr()
    assert "truncated" not in captured.err and " 0 skipped" in captured.out


def test_damaged_jpeg_warnings_stay_off_stderr(tmp_path, capfd) -> None:
    image = np.random.default_rng(0).integers(0, 255, (64, 64, 3), np.uint8)
    cv2.imwrite(str(tmp_path / "a.jpg"), image)
    data = (tmp_path / "a.jpg").read_bytes()
    (tmp_path / "a.jpg").write_bytes(data[: len(data) // 2])
    read_image(tmp_path / "a.jpg")
    assert "JPEG" not in capfd.readouterr().err  # was: "Premature end of JPEG file" from libjpeg


@pytest.mark.parametrize("conn", ["foo:bar", "udpin:0.0.0.0", "udpout:host:port", "tcp::5760", "/dev/", "x,57600",
                                  "/dev/ttyS0,fast", "udpin:1.2.3.4:70000"])
def test_mavlink_connection_strings_are_checked(conn: str, media, capsys) -> None:
    assert cli.main(["--video", str(media["video"]), "--mavlink", conn]) == 2  # was: exit 0 without a link
    assert "argument --mavlink: expected" in _one_error(capsys)


def test_a_message_that_cannot_be_packed_keeps_the_link() -> None:
    import struct

    from dadiff.drone.link import Link, LinkSettings

    class Mav:
        srcSystem = srcComponent = 0

        def send(self, msg: object) -> None:
            raise struct.error("'i' format requires -2147483648 <= number <= 2147483647")

    class Conn:
        mav = Mav()

    link = Link(LinkSettings(url="udpin:127.0.0.1:9"))
    link.conn = Conn()  # type: ignore[assignment]
    msg = mavlink.MAVLink_message_interval_message(275, 2**31)
    assert link.send(msg, 0.0) is False
    assert link.conn is not None  # was: "lost (send failed: error ...); reconnecting", over and over


def test_service_log_file_over_the_input_is_refused(media, tmp_path, capsys) -> None:
    same = tmp_path / "same.mp4"
    same.write_bytes(media["video"].read_bytes())
    argv = ["--video", str(same), "--mavlink", "udpin:127.0.0.1:9", "--model", str(media["model"]),
            "--log-file", str(same), "--log-max-bytes", "10000"]
    assert cli.main(argv) == 2  # was: exit 0, the video rotated away to same.mp4.1 and replaced by log text
    assert "--log-file names the input video" in _one_error(capsys)
    assert same.read_bytes() == media["video"].read_bytes()


@pytest.mark.parametrize(("init", "message"), [("10,10,-5,-5", "box has zero or negative size"),
                                                ("1e300,1e300,1e300,1e300", "lies outside the 160x120 frame"),
                                                ("0,0,1e300,1e300", "more than 4x the 160x120 frame")])
def test_service_init_box_the_first_frame_refuses_is_one_line(init: str, message: str, media, capsys) -> None:
    """The service logged 'cannot start tracking', exited 0 and, without --max-frames, ran on in 'error'."""
    argv = ["--video", str(media["video"]), "--mavlink", "udpin:127.0.0.1:9", "--model", str(media["model"]),
            f"--init={init}", "--max-frames", "5", "--log-level", "ERROR"]
    assert cli.main(argv) == 2
    assert message in _one_error(capsys)


def test_a_second_signal_inside_the_first_does_not_deadlock() -> None:
    """Two SIGINTs 0.1 ms apart: the second handler ran inside the first one's Event.set() and waited on its
    lock for ever; the handler now stops the service once."""
    from dadiff.drone.cli import _run_with_signals

    class Service:
        def __init__(self) -> None:
            self.stops = 0

        def stop(self) -> None:
            self.stops += 1
            if self.stops == 1:
                os.kill(os.getpid(), signal.SIGINT)  # arrives while the first stop is running
                for _ in range(1000):  # let the handler run (it runs between bytecodes of this thread)
                    pass

        def run(self) -> int:
            os.kill(os.getpid(), signal.SIGINT)
            for _ in range(1000):
                pass
            return 0

    service = Service()
    assert _run_with_signals(service) == 130
    assert service.stops == 1


@pytest.mark.parametrize("conn", ["udpin:[::1]:14550", "udpout:fe80::1:14550", "tcp:[::]:5760"])
def test_ipv6_links_are_refused_at_start(conn: str, media, capsys) -> None:
    """pymavlink splits UDP/TCP specs on every ':' and opens IPv4 sockets: the service retried such a link
    forever."""
    assert cli.main(["--video", str(media["video"]), "--mavlink", conn]) == 2
    assert "not an IPv6 address" in _one_error(capsys)


@pytest.mark.parametrize("conn", ["udpin:0.0.0.0:14560", "udpout:127.0.0.1:14550", "tcp:localhost:5760",
                                  "tcpin:0.0.0.0:5760", "/dev/ttyAMA0,921600", "/dev/serial0", "COM3,57600"])
def test_real_connection_strings_pass(conn: str) -> None:
    assert mavlink_conn(conn) == conn


def test_junk_before_a_frame_does_not_cost_the_frame() -> None:
    sender = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    good = mavlink.MAVLink_command_long_message(1, 100, 511, 0, 275, 0, 0, 0, 0, 0, 0).pack(sender)
    rx = mavlink.MAVLink(None)
    rx.robust_parsing = True
    for junk in (b"\x01\x02", b"\xfd\xff\x00\x00", b"\xfd\x03" + bytes(9), b"\xfe\x05zz", b"\xfd" * 40):
        kinds = [m.get_type() for m in parse_datagram(rx, junk + good)]
        assert kinds[-1] == "COMMAND_LONG" and kinds.count("COMMAND_LONG") == 1, (junk[:4], kinds)
    assert [m.get_type() for m in parse_datagram(rx, good)] == ["COMMAND_LONG"]
    flood = parse_datagram(rx, b"\xfd" * 60000 + good)  # the work per datagram stays bounded
    assert [m.get_type() for m in flood] == ["BAD_DATA"]


def test_int8_saturation_is_detected_from_cpu_flags() -> None:
    assert cpu_flags("processor: 0\nflags\t: fpu avx2 avx512_vnni\n") == {"fpu", "avx2", "avx512_vnni"}
    assert int8_saturates("x86_64", "flags: avx2 avx512f")
    assert not int8_saturates("x86_64", "flags: avx2 avx_vnni")
    assert not int8_saturates("aarch64", "flags: neon")
    assert not int8_saturates("x86_64", "")  # unknown: no warning


def test_int8_model_on_a_saturating_cpu_warns(monkeypatch, media, capsys) -> None:
    import dadiff.runtime.cpu as cpu

    monkeypatch.setattr(cpu, "int8_saturates", lambda: True)
    assert int8_warning({"precision": "int8"}) == INT8_WARNING
    assert int8_warning({"precision": "int8", "quantization": '{"reduce_range": true}'}) is None
    assert int8_warning({"precision": "fp32"}) is None
    model = write_corr_model(media["root"] / "int8ish", meta={"precision": "int8"})
    argv = ["--video", str(media["video"]), "--init", BOX, "--model", str(model), "--max-frames", "2"]
    assert cli.main(argv) == 0
    assert "warning: this CPU has no AVX-512 VNNI" in capsys.readouterr().err


def test_rejected_commands_are_logged_throttled(caplog) -> None:
    from dadiff.drone.camera import CameraComponent, CameraSettings
    from dadiff.drone.tracking import TrackFeed

    camera = CameraComponent(CameraSettings(100, 10.0), TrackFeed(), lambda: 0)
    sender = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    with caplog.at_level(logging.INFO, logger="dadiff.drone.camera"):
        for _ in range(500):
            msg = mavlink.MAVLink_command_long_message(1, 100, mavlink.MAV_CMD_CAMERA_TRACK_RECTANGLE, 0,
                                                       float("nan"), 0, 0, 0, 0, 0, 0)
            msg.pack(sender)
            camera.handle(msg, 1, 0.0)
    assert len([r for r in caplog.records if "command" in r.getMessage()]) <= 2  # was: 500 lines


HELP_CASES = [
    ("dadiff.runtime.commands.run", "dadiff-run"),
    ("dadiff.runtime.commands.eval", "dadiff-eval"),
    ("dadiff.export.cli", "dadiff-export"),
    ("dadiff.export.train_cli", "dadiff-train"),
    ("dadiff.runtime.commands.bench", "dadiff-bench"),
]


@pytest.mark.parametrize(("module", "prog"), HELP_CASES)
def test_usage_errors_are_one_line_exit_2(module: str, prog: str, capsys) -> None:
    main = __import__(module, fromlist=["main"]).main
    try:
        code = main(["--no-such-option"])
    except SystemExit as exc:
        code = exc.code
    assert code == 2  # was: the whole usage block (export, eval, bench) and exit 1 (eval)
    assert _one_error(capsys, prog).endswith(f"(see {prog} --help)")


BLOCK_TORCH = """
import importlib.abc, sys
class Blocker(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in ('torch', 'onnx'):
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
sys.meta_path.insert(0, Blocker())
from MODULE import main
sys.exit(main(ARGV))
"""


@pytest.mark.parametrize(("module", "prog", "argv"), [
    ("dadiff.export.cli", "dadiff-export", ["model.pt"]),
    ("dadiff.export.train_cli", "dadiff-train", ["--config", "x.toml"]),
])
def test_without_torch_export_and_train_say_what_to_install(module: str, prog: str, argv: list[str]) -> None:
    def run(args: list[str]) -> subprocess.CompletedProcess:
        code = BLOCK_TORCH.replace("MODULE", module).replace("ARGV", repr(args))
        return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=REPO)

    helped = run(["--help"])
    assert helped.returncode == 0 and "usage:" in helped.stdout  # --help without torch (it loaded first before)
    failed = run(argv)
    assert failed.returncode == 2, failed.stderr  # was: ModuleNotFoundError traceback
    assert failed.stderr.strip().splitlines() == [failed.stderr.strip()]
    assert failed.stderr.startswith(f"{prog}: error: ") and 'pip install "dadiff[export]"' in failed.stderr


def test_help_texts_state_defaults() -> None:
    text = cli.build_parser().format_help()
    assert "one per physical core" in text and "CPU count" not in text
    for fragment in ("horizontal speed limit (default 3)", "rotate the log file at this size (default 10000000)",
                     "rotated log files kept (default 5)", "(default: INFO)", "(default: ./dadiff-demo)"):
        assert fragment in " ".join(text.split()), fragment
    from dadiff.runtime.commands.eval import build_parser

    sub = build_parser()._subparsers._group_actions[0].choices["generate"].format_help()  # type: ignore[union-attr]
    assert "sequences (default 16)" in sub and "frames per sequence (default 120)" in sub


def test_demo_folder_is_ignored_by_git() -> None:
    assert "/dadiff-demo/" in (REPO / ".gitignore").read_text().split()


BLOCK_SKIMAGE = """
import importlib.abc, sys
class Blocker(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] == 'skimage':
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
sys.meta_path.insert(0, Blocker())
from MODULE import main
sys.exit(main(ARGV))
"""


@pytest.mark.parametrize(("module", "prog", "argv"), [
    ("dadiff.runtime.commands.bench", "dadiff-bench",
     ["--max-frames", "2", "--clip", "3", "--warmup", "0", "--no-nano"]),
    ("dadiff.runtime.commands.run", "dadiff-run", ["--demo", "--demo-out", "{tmp}/demo"]),
    ("dadiff.runtime.commands.eval", "dadiff-eval", ["generate", "--output", "{tmp}/gen", "--sequences", "1"]),
])
def test_without_scikit_image_the_generator_says_what_to_install(module, prog, argv, tmp_path) -> None:
    args = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    code = BLOCK_SKIMAGE.replace("MODULE", module).replace("ARGV", repr(args))
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=REPO)
    assert done.returncode == 2, done.stderr  # was (dadiff-bench): a SceneError traceback
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"{prog}: error: ") and 'pip install "dadiff[eval]"' in lines[0]


def test_sub_command_usage_errors_keep_the_command_prefix(capsys) -> None:
    from dadiff.runtime.commands.eval import main

    with pytest.raises(SystemExit) as info:
        main(["run", "--dataset", "x"])
    assert info.value.code == 2
    assert _one_error(capsys, "dadiff-eval").startswith("dadiff-eval: error: run: one of the arguments -o/--output is "
                                                        "required")  # --results, its former spelling, counts too


@pytest.mark.parametrize("hp", ["search_growth=1e308,search_growth_max=1e308", "search_growth_max=1e308",
                                "max_scale_step=1e308", "max_scale_change=1e300", "max_aspect_change=1e300",
                                "penalty_k=1e308"])
def test_hp_growth_and_size_factors_are_bounded(hp: str, media, capsys) -> None:
    argv = ["--video", str(media["video"]), "--init", BOX, "--model", str(media["model"]), "--hp", hp]
    assert cli.main(argv) == 2  # was: accepted, then an OverflowError in crop.py once the target was lost
    assert "e+30" in (line := _one_error(capsys)) and ", expected [" in line  # penalty_k: numpy warnings


def test_hp_overflow_would_reach_the_crop() -> None:
    from dadiff.runtime.config import LOST_DEFAULTS, Params

    params = Params(0.4, 0.1, 0.4, **{**LOST_DEFAULTS, "search_growth": 1e308, "search_growth_max": 1e308})
    with pytest.raises(OverflowError):  # what an unbounded override led to: the reason for the bounds
        from dadiff.runtime.crop import crop_side

        crop_side(100.0 * params.search_growth * params.search_growth)


def test_readmes_csrt_environment_does_not_break_ruff(tmp_path) -> None:
    """Issue 55: the CSRT recipe (docs/evaluation.md) makes `csrt-env/` inside the checkout; `ruff check .` then
    reported 355 errors in the packages installed there and the test command stopped."""
    pytest.importorskip("ruff")
    root = Path(__file__).resolve().parent.parent
    (tmp_path / "pyproject.toml").write_text((root / "pyproject.toml").read_text())
    (tmp_path / "csrt-env" / "lib").mkdir(parents=True)
    (tmp_path / "csrt-env" / "lib" / "installed.py").write_text("import os, sys\nx=1;y = 2\n")
    proc = subprocess.run([sys.executable, "-m", "ruff", "check", "."], cwd=tmp_path, capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 0, proc.stdout
    assert "/csrt-env/" in (root / ".gitignore").read_text().splitlines()


class _HalfThenFull:
    """A raw file whose next write stores 3 bytes, then every write fails as on a full disk."""

    def __init__(self, raw) -> None:
        self.raw, self.writes = raw, 0

    def write(self, data) -> int:
        self.writes += 1
        if self.writes == 1:
            return self.raw.write(bytes(data[:3]))
        raise OSError(28, "No space left on device")

    def __getattr__(self, name: str):
        return getattr(self.raw, name)


@pytest.mark.parametrize("suffix", [".csv", ".jsonl"])
def test_track_log_cut_short_ends_at_its_last_whole_row(tmp_path, suffix) -> None:
    """Issue 55: a full disk mid-row left `…,0.98616` (CSV) or half an object (JSONL) at the end of the log."""
    from dadiff.runtime.outputs import Record

    path = tmp_path / f"t{suffix}"
    log = TrackLog(path)
    frame = Frame(0, 0.0, np.zeros((4, 4, 3), np.uint8))
    log.write(frame, Record((1, 2, 3, 4), 0.98616, "tracking"))
    log._file._raw = _HalfThenFull(log._file._raw)
    with pytest.raises(OutputError, match=rf"{path}: cannot write \(No space left on device\); the first 1 rows"):
        log.write(frame, Record((5, 6, 7, 8), 0.5, "uncertain"))
    log.close()
    text = path.read_text()
    assert text.endswith("\n") and text.count("\n") == (2 if suffix == ".csv" else 1)
    assert "uncertain" not in text
