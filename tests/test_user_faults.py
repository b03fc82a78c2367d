"""What a new user ran into (issue 55), below the command line: the bounded reader, the Tracker API's errors and
init convention, onnxruntime's telemetry line, torch's pickle warning, an unwritable training folder and a
udpin port that a second program could share. The command-line cases are in tests/test_fault_battery.py."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from dadiff.runtime import InputError, ModelError, Tracker
from runtime_models import write_corr_model
from runtime_scenes import moving_sequence


def test_user_files_are_regular_and_bounded(tmp_path: Path) -> None:
    from dadiff.runtime.user_files import read_user_bytes, read_user_text

    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    with pytest.raises(OSError, match="a FIFO, not a regular file"):  # at once: no writer is waited for
        read_user_bytes(fifo)
    with pytest.raises(OSError, match="a character device, not a regular file"):
        read_user_bytes("/dev/zero")
    with pytest.raises(OSError, match="a folder, not a regular file"):
        read_user_bytes(tmp_path)
    big = tmp_path / "big.toml"
    big.write_bytes(b"# \n" * 1000)
    with pytest.raises(OSError, match="larger than") as caught:
        read_user_bytes(big, limit=2999)
    assert caught.value.filename == str(big)
    assert read_user_bytes(big, limit=3000) == b"# \n" * 1000
    big.write_bytes(b"\xef\xbb\xbfvideo = 1\n")
    assert read_user_text(big) == "video = 1\n"  # a byte-order mark dropped


@pytest.fixture(scope="module")
def model(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_corr_model(tmp_path_factory.mktemp("api") / "model")


def test_api_errors_are_value_errors_naming_the_problem(model: Path) -> None:
    assert issubclass(ModelError, ValueError) and issubclass(InputError, ValueError)  # as README says
    with pytest.raises(ValueError, match="no such|not found|cannot"):
        Tracker.load(model / "missing")
    with pytest.raises(InputError, match="model must be a folder.*got 5"):
        Tracker.load(5)  # was a TypeError from inside the path handling


def test_update_refuses_a_frame_of_another_size(model: Path) -> None:
    frames, boxes = moving_sequence(3)
    tracker = Tracker.load(model)
    tracker.init(frames[0], boxes[0])
    tracker.update(frames[1])
    h, w = frames[2].shape[:2]
    with pytest.raises(InputError, match=rf"frame is {w // 2}×{h // 2} but tracking started on a {w}×{h} frame"):
        tracker.update(np.ascontiguousarray(frames[2][: h // 2, : w // 2]))  # a box partly outside it came back
    tracker.update(frames[2])  # the track goes on with frames of its size


def test_the_cli_init_is_the_api_init_of_protocol_box(model: Path, tmp_path: Path) -> None:
    """`dadiff-run --init x,y,w,h` tracks exactly as `Tracker.init(frame, protocol_box((x, y, w, h)))`."""
    import cv2

    from dadiff.runtime.commands import run as cli
    from dadiff.runtime.crop import protocol_box

    frames, boxes = moving_sequence(6)
    folder = tmp_path / "seq"
    folder.mkdir()
    for k, frame in enumerate(frames):
        cv2.imwrite(str(folder / f"{k + 1:04d}.png"), frame)
    out = tmp_path / "track.csv"
    box = ",".join(str(v) for v in boxes[0])
    assert cli.main(["--video", str(folder), "--init", box, "--model", str(model), "--output", str(out)]) == 0
    rows = [line.split(",") for line in out.read_text().splitlines()[1:]]
    tracker = Tracker.load(model)
    tracker.init(frames[0], protocol_box(boxes[0]))
    assert [float(v) for v in rows[0][2:6]] == pytest.approx(protocol_box(boxes[0]))
    for row, frame in zip(rows[1:], frames[1:], strict=True):
        assert [float(v) for v in row[2:6]] == pytest.approx(tracker.update(frame).box, abs=1e-3)


def test_no_telemetry_line_without_a_writable_home() -> None:
    env = {**os.environ, "HOME": os.devnull}  # no home to keep onnxruntime's device id in (the service's user)
    env.pop("ORT_DISABLE_TELEMETRY", None)
    proc = subprocess.run([sys.executable, "-c", "import dadiff.runtime.onnx_backend"], capture_output=True,
                          text=True, env=env, timeout=120)
    assert proc.returncode == 0 and "telemetry" not in proc.stderr, proc.stderr


def test_a_code_carrying_pickle_is_refused_without_torch_warnings(tmp_path: Path) -> None:
    pytest.importorskip("torch")
    import pickle

    from dadiff.export.checkpoint import CheckpointError, read_checkpoint_file

    class Code:
        def __reduce__(self) -> tuple:
            return (os.system, ("echo owned",))

    path = tmp_path / "evil.pt"
    path.write_bytes(pickle.dumps({"w": Code()}, protocol=4))
    with warnings.catch_warnings(record=True) as caught, pytest.raises(CheckpointError, match="refused"):
        warnings.simplefilter("always")
        read_checkpoint_file(path)
    assert [str(w.message) for w in caught] == []  # torch's "Detected pickle protocol 4" added two lines


def test_train_into_a_folder_it_cannot_make_is_one_line(tmp_path: Path, capsys) -> None:
    pytest.importorskip("torch")
    import cv2

    from dadiff.export.train import main

    images = tmp_path / "images"
    images.mkdir()
    rng = np.random.default_rng(0)
    for k in range(3):
        cv2.imwrite(str(images / f"{k}.png"), rng.integers(0, 255, (160, 200, 3), dtype=np.uint8))
    blocker = tmp_path / "a-file"
    blocker.write_text("")  # `out` below a file: mkdir fails as on a read-only filesystem, for root too
    toml = tmp_path / "run.toml"
    toml.write_text(f"[train]\nout = '{blocker / 'run'}'\nstage = 'baseline'\nsteps = 1\nbatch_size = 2\n"
                    f"day = [{{ kind = 'images', root = '{images}' }}]\n")
    assert main(["--config", str(toml)]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip() and "%|" not in line]
    assert len(err) == 1 and err[0].startswith(f"dadiff-train: error: {blocker / 'run'}"), err


def test_a_udpin_port_cannot_be_shared_once_open() -> None:
    from dadiff.drone.link import Link, LinkSettings
    from drone_peers import free_port

    port = free_port()
    link = Link(LinkSettings(f"udpin:127.0.0.1:{port}"))
    link.maintain(0.0)
    assert link.is_open
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as second:
            second.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as a second pymavlink udpin binds
            with pytest.raises(OSError):
                second.bind(("127.0.0.1", port))
    finally:
        link.conn.close()


def test_a_stop_signal_inside_signals_held_acts_when_the_block_ends() -> None:
    """One frame's record reaches every output or none: Ctrl-C (or SIGTERM under the commands' handling) that
    arrives while the record is written is raised after it, not in between two outputs."""
    from dadiff.runtime.commands.launch import signals_held, stop_signals_interrupt

    for sig in (signal.SIGINT, signal.SIGTERM):
        written = []
        with stop_signals_interrupt(), pytest.raises(KeyboardInterrupt):
            with signals_held():
                written.append("csv")
                os.kill(os.getpid(), sig)
                for _ in range(1000):  # Python runs a handler between bytecodes: give it every chance
                    pass
                written.append("mp4")
        assert written == ["csv", "mp4"]
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
