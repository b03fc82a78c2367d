"""The ONNX detector runner: TF Object Detection API outputs mapped from the frame and its tiles to pixels."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from dadiff.runtime.commands.eval import main as eval_main
from dadiff.runtime.datamaking.detection_tracks import LinkSettings, read_detections
from dadiff.runtime.datamaking.detector import Detector, tiles

onnx = pytest.importorskip("onnx")
from detector_models import write_fake_detector as _detector  # noqa: E402
from onnx import TensorProto  # noqa: E402


def test_tiles_cover_the_long_side_with_half_overlap():
    assert tiles(640, 360, 0) == [(0, 0, 640, 360)]
    assert tiles(640, 360, 3) == [(0, 0, 640, 360), (0, 0, 320, 360), (160, 0, 320, 360), (320, 0, 320, 360)]
    assert tiles(300, 600, 1) == [(0, 0, 300, 600), (0, 0, 300, 600)]


def test_relative_boxes_become_pixels_of_the_image(tmp_path: Path):
    model = _detector(tmp_path / "d.onnx", [[0.25, 0.5, 0.75, 0.75]], [0.9], [1.0])
    rows = Detector(model).detect(np.zeros((200, 400, 3), np.uint8))
    np.testing.assert_allclose(rows, [[200, 50, 100, 100, 0.9, 1.0]], atol=1e-4)


def test_detector_threads_are_bounded_as_the_trackers(tmp_path: Path):
    from dadiff.runtime.errors import InputError

    model = _detector(tmp_path / "d.onnx", [[0.25, 0.5, 0.75, 0.75]], [0.9], [1.0])
    with pytest.raises(InputError, match="threads is 100000; at most"):  # went straight to onnxruntime
        Detector(model, threads=100_000)


def test_command_writes_each_tile_box_in_frame_pixels_and_keeps_the_wanted_class(tmp_path: Path, capsys):
    # one person box and one car box per pass, relative to whatever it is shown
    model = _detector(tmp_path / "d.onnx", [[0.1, 0.25, 0.9, 0.5], [0.0, 0.0, 0.5, 0.5]], [0.8, 0.9], [1.0, 3.0])
    video = tmp_path / "frames"
    video.mkdir()
    for i in range(3):
        cv2.imwrite(str(video / f"{i:04d}.png"), np.full((100, 400, 3), 60 * i, np.uint8))
    det = tmp_path / "det.txt"
    assert eval_main(["detect", "--video", str(video), "--detector", str(model), "--output", str(det),
                      "--tiles", "3"]) == 0
    assert "wrote 12 detections of class 1 in 3 frames" in capsys.readouterr().out
    frame1 = [line.split(",") for line in det.read_text().splitlines() if line.startswith("1,")]
    boxes = np.array([[float(v) for v in row[2:7]] for row in frame1])
    # whole frame (400 wide), then tiles of 200 px at x = 0, 100, 200: x0 + 0.25 w, 0.1 h, 0.25 w, 0.8 h
    np.testing.assert_allclose(boxes, [[100, 10, 100, 80, 0.8], [50, 10, 50, 80, 0.8], [150, 10, 50, 80, 0.8],
                                       [250, 10, 50, 80, 0.8]], atol=0.01)
    rows = read_detections(det, 3, LinkSettings(min_height=10, min_aspect=0.5, nms_iou=0.9))
    assert [len(r) for r in rows] == [4, 4, 4]  # det.txt reads back as pseudo-label reads it


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda tmp: tmp / "missing.onnx", "missing.onnx: no such detector file"),
        (lambda tmp: (tmp / "junk.onnx").write_bytes(b"not a model") and tmp / "junk.onnx",
         "not a readable ONNX model"),
        (lambda tmp: _detector(tmp / "f.onnx", [[0, 0, 1, 1]], [1.0], [1.0], TensorProto.FLOAT),
         "expected one uint8 image input of rank 4"),
        (lambda tmp: _detector(tmp / "r.onnx", [[0, 0, 1, 1]], [1.0], [1.0], box_shape=[4]),
         "the detector failed on a 80 x 50 image: "),
    ],
)
def test_a_bad_detector_is_one_line_and_exit_2(tmp_path: Path, capsys, make, message):
    video = tmp_path / "frames"
    video.mkdir()
    for i in range(2):
        cv2.imwrite(str(video / f"{i:04d}.png"), np.zeros((50, 80, 3), np.uint8))
    model = make(tmp_path)
    assert eval_main(["detect", "--video", str(video), "--detector", str(model), "-o", str(tmp_path / "d.txt")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and message in err and err.startswith("dadiff-eval: error:")


def test_detect_out_never_replaces_the_video_its_frames_or_the_detector(tmp_path: Path, capsys):
    model = _detector(tmp_path / "d.onnx", [[0.1, 0.25, 0.9, 0.5]], [0.8], [1.0])
    video = tmp_path / "frames"
    video.mkdir()
    for i in range(2):
        cv2.imwrite(str(video / f"{i:04d}.png"), np.zeros((50, 80, 3), np.uint8))
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    for out, message in [(video / "0000.png", "lies inside the input folder"), (model, "names the input file")]:
        assert eval_main(["detect", "--video", str(video), "--detector", str(model), "--output", str(out)]) == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and message in err and err.startswith("dadiff-eval: error:")
    assert {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()} == before
