"""Rehearsal with recorded video: in service mode a file plays at its own frame rate (as a camera delivers
it: the newest frame, a slow tracker skips), `--loop` plays it again; `--no-realtime` goes as fast as it
decodes. The frame grabber alone, with a synthetic file source."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest

from dadiff.drone.video import FrameGrabber
from dadiff.runtime.sources import Frame
from drone_peers import rate


class FileSource:
    """A 'video file' of `count` frames at `fps` (its media frame rate); decodes instantly."""

    live = False

    def __init__(self, count: int = 20, fps: float | None = 50.0) -> None:
        self.count, self.fps = count, fps

    def frames(self) -> Iterator[Frame]:
        image = np.zeros((8, 8, 3), np.uint8)
        for index in range(self.count):
            yield Frame(index, index / (self.fps or 30.0), image)

    def close(self) -> None:
        pass


def play(
    grabber: FrameGrabber, stop: threading.Event, limit: float = 5.0, slow: float = 0.0
) -> list[tuple[int, float]]:
    """Take frames until the grabber finishes (or `limit` s); `slow`: seconds of 'inference' per frame."""
    thread = threading.Thread(target=grabber.run, daemon=True)
    thread.start()
    got: list[tuple[int, float]] = []
    end = time.monotonic() + limit
    while time.monotonic() < end:
        item = grabber.get(timeout=0.05)
        if item is None:
            if grabber.finished:
                break
            continue
        got.append((item.frame.index, item.grabbed_at))
        time.sleep(slow)
    stop.set()
    thread.join(2)
    return got


def test_a_file_plays_at_its_frame_rate() -> None:
    stop = threading.Event()
    start = time.monotonic()
    got = play(FrameGrabber(lambda: FileSource(25, 50.0), stop, realtime=True), stop)
    assert [i for i, _ in got] == list(range(25))  # every frame while the tracker keeps up
    assert rate([t for _, t in got]) == pytest.approx(50.0, rel=0.1)
    assert got[-1][1] - start == pytest.approx(24 / 50, abs=0.1)


def test_as_fast_as_it_decodes_without_realtime() -> None:
    stop = threading.Event()
    start = time.monotonic()
    got = play(FrameGrabber(lambda: FileSource(200, 25.0), stop, realtime=False), stop)
    assert len(got) == 200 and got[-1][1] - start < 1.0  # 8 s of video in well under a second


def test_realtime_skips_frames_for_a_slow_tracker() -> None:
    """Like a camera: the tracker gets the newest frame, so it never falls behind the clock."""
    stop = threading.Event()
    grabber = FrameGrabber(lambda: FileSource(30, 50.0), stop, realtime=True)
    got = play(grabber, stop, slow=0.05)  # 20 FPS tracker on a 50 FPS file
    assert 8 <= len(got) <= 20 and grabber.dropped >= 10
    assert got[-1][0] >= 27  # it ends on (nearly) the last frame, at the file's own pace


def test_loop_plays_it_again() -> None:
    stop = threading.Event()
    grabber = FrameGrabber(lambda: FileSource(10, 50.0), stop, realtime=True, loop=True)
    got = play(grabber, stop, limit=0.75)
    assert grabber.plays >= 3
    indices = [i for i, _ in got]
    assert indices[:20] == list(range(10)) * 2
    assert rate([t for _, t in got]) == pytest.approx(50.0, rel=0.1)  # no pause at the seam


def test_a_short_loop_does_not_flood_the_log(caplog: pytest.LogCaptureFixture) -> None:
    """Each play of a 0.2 s clip logged two INFO lines, ten a second, without the throttle other lines have."""
    stop = threading.Event()
    grabber = FrameGrabber(lambda: FileSource(10, 50.0), stop, realtime=True, loop=True)
    with caplog.at_level(logging.INFO, logger="dadiff.drone.video"):
        play(grabber, stop, limit=0.75)
    assert grabber.plays >= 3
    for text in ("video opened", "playing it again"):
        assert sum(text in r.getMessage() for r in caplog.records) == 1


def test_folder_without_a_frame_rate_plays_at_the_default() -> None:
    stop = threading.Event()
    got = play(FrameGrabber(lambda: FileSource(10, None), stop, realtime=True), stop)
    assert len(got) == 10 and rate([t for _, t in got]) == pytest.approx(30.0, rel=0.1)
