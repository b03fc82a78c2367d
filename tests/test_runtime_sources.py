"""Frame sources: dropped frames in live streams and video files, source detection, ground truth."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from dadiff.runtime import sources
from dadiff.runtime.commands import run as cli
from runtime_models import write_corr_model
from runtime_scenes import moving_sequence


class FakeCapture:
    """cv2.VideoCapture stand-in that plays a script of good (frame) and failed (None) reads."""

    script: list[np.ndarray | None] = []
    opened_after: int | None = None  # number of reads after which the capture reports closed

    def __init__(self, target: object) -> None:
        self.reads = 0

    def isOpened(self) -> bool:  # noqa: N802 (OpenCV's name)
        return self.opened_after is None or self.reads < self.opened_after

    def get(self, prop: int) -> float:
        return {cv2.CAP_PROP_FPS: 25.0, cv2.CAP_PROP_FRAME_COUNT: 0.0}.get(prop, 0.0)

    def read(self) -> tuple[bool, np.ndarray | None]:
        item = self.script[self.reads] if self.reads < len(self.script) else None
        self.reads += 1
        return (item is not None), item

    def release(self) -> None:
        pass


def _fake(monkeypatch: pytest.MonkeyPatch, script: list, opened_after: int | None) -> None:
    monkeypatch.setattr(FakeCapture, "script", script)
    monkeypatch.setattr(FakeCapture, "opened_after", opened_after)
    monkeypatch.setattr(sources.cv2, "VideoCapture", FakeCapture)
    monkeypatch.setattr(sources.time, "sleep", lambda s: None)


IMG = np.zeros((4, 4, 3), np.uint8)


def test_stream_skips_failed_reads(monkeypatch: pytest.MonkeyPatch) -> None:
    _fake(monkeypatch, [IMG, None, IMG, IMG, None, None, IMG], opened_after=7)
    source = sources.open_source("rtsp://camera.local/stream")
    assert source.kind == "stream" and source.live
    frames = list(source.frames())
    assert [f.index for f in frames] == [0, 2, 3, 6]
    assert source.skipped == 3


def test_dead_stream_ends_after_many_failures(monkeypatch: pytest.MonkeyPatch) -> None:
    _fake(monkeypatch, [IMG], opened_after=None)
    source = sources.open_source("0")
    assert source.kind == "camera"
    assert len(list(source.frames())) == 1
    assert source.skipped == sources.LIVE_FAILURES


def test_file_failures_then_end(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    path = tmp_path / "clip.avi"
    path.write_bytes(b"")
    _fake(monkeypatch, [IMG, None, None, IMG], opened_after=None)
    source = sources.open_source(str(path))
    assert source.kind == "file" and not source.live
    frames = list(source.frames())
    assert [f.index for f in frames] == [0, 3]
    assert [f.timestamp for f in frames] == [0.0, 3 / 25]
    assert source.skipped == 2  # the failures at the end of the file are not counted


def test_live_run_prints_status_lines(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    frames, boxes = moving_sequence(60)
    script = [frames[0], None] + frames[1:10]
    _fake(monkeypatch, script, opened_after=len(script))
    monkeypatch.setattr(cli, "STATUS_EVERY_S", 0.0)
    model = write_corr_model(tmp_path / "model")
    out = tmp_path / "t.csv"
    init = ",".join(map(str, boxes[0]))
    argv = ["--video", "rtsp://x/y", "--init", init, "--model", str(model), "--output", str(out)]
    assert cli.main(argv) == 0
    captured = capsys.readouterr()
    assert "dadiff-run: frame 2, " in captured.err and "1 skipped" in captured.err
    assert "10 frames, 0 lost, 1 skipped" in captured.out
    assert len(out.read_text().splitlines()) == 1 + 10


@pytest.mark.parametrize(
    ("text", "box"),
    [
        ("10,20,30,40", (10, 20, 30, 40)),
        ("10\t20\t30\t40", (10, 20, 30, 40)),
        ("10 20  30 40", (10, 20, 30, 40)),
        ("1,1,5,1,5,9,1,9", (1, 1, 4, 8)),  # polygon → bounding box
    ],
)
def test_parse_box(text: str, box: tuple) -> None:
    assert sources.parse_box(text) == box


@pytest.mark.parametrize("text", ["1,2,3", "a,b,c,d", "1,2,nan,4"])
def test_parse_box_rejects(text: str) -> None:
    with pytest.raises(ValueError, match="four numbers|numbers"):
        sources.parse_box(text)


def test_folder_natural_order_and_img_subfolder(tmp_path: Path) -> None:
    for name in ("10.jpg", "9.jpg", "1.jpg"):
        cv2.imwrite(str(tmp_path / name), IMG)
    (tmp_path / "readme.txt").write_text("not an image")
    source = sources.open_source(str(tmp_path))
    assert [p.name for p in source.files] == ["1.jpg", "9.jpg", "10.jpg"]
    assert source.init_box is None


def test_folder_truth_with_a_byte_order_mark(tmp_path: Path) -> None:
    cv2.imwrite(str(tmp_path / "1.jpg"), IMG)
    (tmp_path / "groundtruth_rect.txt").write_text("\ufeff4,5,6,7\n", encoding="utf-8")  # as Windows tools save
    assert sources.open_source(str(tmp_path)).init_box == (4.0, 5.0, 6.0, 7.0)


def test_folder_skips_an_image_of_another_size(tmp_path: Path) -> None:
    """A frame of another size was tracked as if its pixels were the first frame's; the target was lost."""
    for i in range(4):
        image = IMG if i != 2 else cv2.resize(IMG, (IMG.shape[1] // 2, IMG.shape[0] // 2))
        cv2.imwrite(str(tmp_path / f"{i + 1:04d}.png"), image)
    source = sources.open_source(str(tmp_path))
    assert [f.index for f in source.frames()] == [0, 1, 3]
    assert source.skipped == 1
