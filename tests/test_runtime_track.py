"""End-to-end tracking with the correlation test model on onnxruntime."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from dadiff.runtime import InputError, OnnxBackend, Tracker
from runtime_models import write_corr_model
from runtime_scenes import iou, moving_sequence, occlusion_sequence


@pytest.fixture(scope="module")
def model_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_corr_model(tmp_path_factory.mktemp("corr") / "corr-test")


@pytest.fixture(scope="module")
def tracker(model_dir: Path) -> Tracker:
    return Tracker.load(model_dir, threads=1)


def _track(tracker: Tracker, frames: list[np.ndarray], box: tuple[float, ...]) -> list:
    tracker.init(frames[0], box)
    return [tracker.update(f) for f in frames[1:]]


def test_tracks_moving_scaling_object(tracker: Tracker) -> None:
    frames, boxes = moving_sequence(60)
    results = _track(tracker, frames, boxes[0])
    ious = [iou(r.box, b) for r, b in zip(results, boxes[1:], strict=True)]
    assert np.mean(ious) > 0.7 and min(ious) > 0.4
    assert {r.state for r in results} == {"tracking"}
    assert all(0.0 <= r.score <= 1.0 for r in results)
    assert all(set(r.latency) == {"motion", "crop", "search", "post", "total"} for r in results)
    # the object grows from 40 to about 60 px and shrinks again: the size estimate follows it
    sizes = [r.box[2] for r in results]
    assert max(sizes) > 52 and sizes[-1] < max(sizes) - 6


def test_grey_frames(tracker: Tracker) -> None:
    frames, boxes = moving_sequence(30)
    grey = [cv2.cvtColor(f, cv2.COLOR_BGR2GRAY) for f in frames]
    results = _track(tracker, grey, boxes[0])
    assert np.mean([iou(r.box, b) for r, b in zip(results, boxes[1:], strict=True)]) > 0.6


def test_occlusion_lost_then_found(model_dir: Path) -> None:
    frames, boxes = occlusion_sequence(before=20, hidden=10, after=20, jump=40)
    hidden = [k for k, b in enumerate(boxes) if b is None]
    tracker = Tracker.load(model_dir, threads=1)
    results = _track(tracker, frames, boxes[0])
    states = [r.state for r in results]
    during = [states[k - 1] for k in hidden]
    assert "lost" in during and "tracking" not in during
    # while lost the box does not move or change size
    lost_boxes = {r.box for r in results if r.state == "lost"}
    assert len(lost_boxes) == 1
    # it ends on the object, tracking
    assert results[-1].state == "tracking"
    assert iou(results[-1].box, boxes[-1]) > 0.5
    assert (
        sum(iou(r.box, b) > 0.5 for r, b in zip(results[hidden[-1] :], boxes[hidden[-1] + 1 :], strict=True))
        >= 15
    )

    # Control: the target reappears outside the normal search region, so without growth it is not found.
    fixed = Tracker.load(model_dir, threads=1, overrides={"search_growth_max": 1.0})
    assert iou(_track(fixed, frames, boxes[0])[-1].box, boxes[-1]) < 0.1


class CountingBackend:
    """Wraps a backend and counts graph runs."""

    def __init__(self, inner: OnnxBackend) -> None:
        self.inner, self.templates, self.searches = inner, 0, 0
        self.meta = inner.meta

    def template(self, z: np.ndarray) -> dict[str, np.ndarray]:
        self.templates += 1
        return self.inner.template(z)

    def search(self, x: np.ndarray, feeds: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        self.searches += 1
        return self.inner.search(x, feeds)


def test_reinit_without_reloading(model_dir: Path) -> None:
    backend = CountingBackend(OnnxBackend(model_dir, threads=1))
    tracker = Tracker(backend)
    frames, boxes = occlusion_sequence(before=12, hidden=0, after=0)
    _track(tracker, frames, boxes[0])
    moving, moving_boxes = moving_sequence(20)
    results = _track(tracker, moving, moving_boxes[0])
    assert np.mean([iou(r.box, b) for r, b in zip(results, moving_boxes[1:], strict=True)]) > 0.7
    assert (backend.templates, backend.searches) == (2, 11 + 19)


def test_template_outputs_feed_search_by_name(model_dir: Path) -> None:
    backend = OnnxBackend(model_dir, threads=1)
    feeds = backend.template(np.zeros((1, 3, 127, 127), np.float32))
    assert set(feeds) == {"zf0", "kcls0", "kloc0"}
    cls, loc = backend.search(np.zeros((1, 3, 255, 255), np.float32), feeds)
    assert cls.shape == (1, 2, 25, 25) and loc.shape == (1, 4, 25, 25)


def test_load_from_onnx_file_preset_and_overrides(model_dir: Path) -> None:
    tracker = Tracker.load(model_dir / "search.onnx", threads=1, preset="NAT", overrides={"lr": "0.2"})
    p = tracker.params
    assert (p.lr, p.penalty_k, p.window_influence) == (0.2, 0.14, 0.30)
    assert tracker.geometry.point_origin == -99.5  # read from the metadata, not assumed
    with pytest.raises(InputError, match="unknown preset 'nope'.*UAVDark70"):
        Tracker.load(model_dir, preset="nope")
    with pytest.raises(InputError, match="unknown override 'lrr'"):
        Tracker.load(model_dir, overrides={"lrr": 0.1})
    with pytest.raises(InputError, match="override 'window_influence' is 2.0"):
        Tracker.load(model_dir, overrides={"window_influence": 2})


@pytest.mark.parametrize(
    ("box", "message"),
    [
        ((10, 10, 0, 20), "zero or negative size"),
        ((10, 10, 20, -1), "zero or negative size"),
        ((500, 10, 20, 20), "outside the 480x360 frame"),
        ((-30, 10, 20, 20), "outside the 480x360 frame"),
        ((1, 2, 3), "four numbers"),
        ((1, 2, float("nan"), 4), "finite"),
    ],
)
def test_bad_init_box(tracker: Tracker, box: tuple, message: str) -> None:
    with pytest.raises(InputError, match=message):
        tracker.init(np.zeros((360, 480, 3), np.uint8), box)


def test_bad_frames(tracker: Tracker) -> None:
    with pytest.raises(InputError, match="uint8"):
        tracker.init(np.zeros((36, 48, 3), np.float32), (1, 1, 10, 10))
    with pytest.raises(InputError, match="shape"):
        tracker.init(np.zeros((36, 48, 2), np.uint8), (1, 1, 10, 10))
    with pytest.raises(InputError, match=r"H×W×1 \(grey\), H×W×3 \(BGR\) or H×W×4 \(BGRA\), got shape \(3, 36, 48\)"):
        tracker.init(np.zeros((3, 36, 48), np.uint8), (1, 1, 10, 10))  # channels first: every accepted layout named


def test_update_before_init(model_dir: Path) -> None:
    with pytest.raises(InputError, match="before init"):
        Tracker.load(model_dir, threads=1).update(np.zeros((36, 48, 3), np.uint8))
