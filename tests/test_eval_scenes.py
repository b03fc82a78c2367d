"""Night-scene generator: determinism, exact boxes, night rendering, the benchmark on disk."""

from __future__ import annotations

import subprocess
import sys

import cv2
import numpy as np
import pytest

from dadiff.runtime.evaluation import scenes
from dadiff.runtime.evaluation.datasets import load_dataset
from dadiff.runtime.evaluation.scenes import (
    PHOTO_SPLITS,
    Scene,
    SceneError,
    load_photos,
    make_sequence,
    render_night,
    visible_box,
    write_benchmark,
)

pytest.importorskip("skimage")  # the scene photos

SMALL = (192, 128)


def test_photo_splits_are_fixed_disjoint_and_bgr():
    assert set(PHOTO_SPLITS) == {"train", "test"}
    assert not set(PHOTO_SPLITS["train"]) & set(PHOTO_SPLITS["test"])
    photos = load_photos("test")
    assert sorted(photos) == sorted(PHOTO_SPLITS["test"])
    for image in photos.values():
        assert image.dtype == np.uint8 and image.ndim == 3 and image.shape[2] == 3
    with pytest.raises(SceneError, match="unknown photo split 'val'"):
        load_photos("val")


def test_importing_the_generator_does_not_import_skimage():
    code = "import sys, dadiff.runtime.evaluation.scenes; sys.exit('skimage' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], timeout=120).returncode == 0


def test_scene_is_deterministic_and_random_access():
    photos = load_photos("test")
    a = Scene.random(np.random.default_rng(7), photos, size=SMALL, frames=6)
    b = Scene.random(np.random.default_rng(7), photos, size=SMALL, frames=6)
    late_a, box_a = a.render(5)
    for i in range(6):
        b.render(i)
    late_b, box_b = b.render(5)
    assert np.array_equal(late_a, late_b) and np.array_equal(box_a, box_b)
    assert late_a.shape == (SMALL[1], SMALL[0], 3) and late_a.dtype == np.uint8
    assert box_a.dtype == np.float64 and box_a.shape == (4,)
    with pytest.raises(IndexError):
        a.render(6)


def test_box_is_tight_around_the_drawn_object():
    photos = load_photos("test")
    for seed in range(40):
        scene = Scene.random(np.random.default_rng(seed), photos, size=(320, 240), frames=4)
        if scene.distractor is None and scene.brightness[3] == 1:
            break
    frame, box = scene.render(3)
    plain = cv2.warpAffine(
        scene.background, scene.cameras[3], (320, 240), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101
    )
    changed = np.abs(frame.astype(int) - plain.astype(int)).max(axis=2) > 2
    ys, xs = np.nonzero(changed)
    drawn = np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], float)
    truth = np.array([box[0], box[1], box[0] + box[2], box[1] + box[3]])
    assert np.all(np.abs(drawn - truth) <= 1.0), (drawn, truth)


def test_visible_box_subtracts_the_occluder():
    square = np.array([[0, 0], [10, 0], [10, 10], [0, 10]], float)
    left_half = np.array([[-5, -5], [5, -5], [5, 15], [-5, 15]], float)
    assert visible_box(square, left_half, 100, 100).tolist() == [5, 0, 5, 10]
    corner = np.array([[-5, -5], [5, -5], [5, 5], [-5, 5]], float)  # the bounding box stays whole
    assert visible_box(square, corner, 100, 100).tolist() == [0, 0, 10, 10]
    everything = np.array([[-1, -1], [11, -1], [11, 11], [-1, 11]], float)
    assert np.isnan(visible_box(square, everything, 100, 100)).all()


def test_objects_are_mostly_low_resolution():
    photos = load_photos("test")
    sides = [
        Scene.random(np.random.default_rng(s), photos, size=(320, 240), frames=2).boxes[0, 2:].max() for s in range(24)
    ]
    assert np.mean(np.array(sides) < 25) >= 0.5
    assert max(sides) <= 75


def test_render_night_is_darker_noisy_and_deterministic():
    day, _ = Scene.random(np.random.default_rng(3), load_photos("test"), size=SMALL, frames=1).render(0)
    night = render_night(day, np.random.default_rng(1), darkness=0.8)
    again = render_night(day, np.random.default_rng(1), darkness=0.8)
    assert night.shape == day.shape and night.dtype == np.uint8
    assert np.array_equal(night, again)
    assert night.mean() < day.mean()
    with pytest.raises(SceneError, match="darkness"):
        render_night(day, np.random.default_rng(1), darkness=1.5)
    with pytest.raises(SceneError, match="uint8 BGR"):
        render_night(day.astype(np.float32), np.random.default_rng(1))


def test_poisson_table_matches_the_distribution():
    rng = np.random.default_rng(0)
    for lam in (0.5, 4.0, 30.0, 2000.0):
        x = scenes.poisson(np.full((200, 200), lam, np.float32), rng)
        assert x.mean() == pytest.approx(lam, rel=0.03)
        assert x.var() == pytest.approx(lam, rel=0.08)


def test_make_sequence():
    seq = make_sequence(11, frames=3, size=SMALL)
    assert seq.name == "scene11" and len(seq.day) == len(seq.night) == 3
    assert seq.boxes.shape == (3, 4) and np.isfinite(seq.boxes).all()
    assert seq.night_attributes[-1] == "LAI" and "LAI" not in seq.attributes
    assert np.array_equal(seq.night[2], make_sequence(11, frames=3, size=SMALL).night[2])


def test_write_benchmark_is_read_back_as_an_otb_dataset(tmp_path):
    root = write_benchmark(tmp_path / "bench", sequences=2, frames=3, seed=5, size=SMALL, workers=1)
    dataset = load_dataset(root)
    assert (dataset.name, dataset.layout) == ("bench", "otb")
    assert [s.name for s in dataset.sequences] == ["seq001_day", "seq001_night", "seq002_day", "seq002_night"]
    day, night = dataset.sequences[:2]
    assert "LAI" in night.attributes and "LAI" not in day.attributes
    assert np.allclose(day.boxes, night.boxes) and len(day) == 3
    assert (root / "seq001_day" / "img" / "0003.jpg").is_file()
    with pytest.raises(SceneError, match="not an empty folder"):
        write_benchmark(root, sequences=1, frames=1, seed=5)
