"""Both crop paths (window canvas + resize; remap) against a plain implementation of get_subwindow (spec 8.2)."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import skimage.data

from dadiff.runtime.crop import MAX_CANVAS_SIDE, _remap_subwindow, crop_side, mean_colour, subwindow


def get_subwindow_reference(
    image: np.ndarray, centre: tuple[float, float], out_size: int, side: int, avg: np.ndarray
) -> np.ndarray:
    """Spec 8.2 step by step: pad a uint8 canvas with the mean colour when needed, slice, resize."""
    h, w = image.shape[:2]
    c = (side + 1) / 2
    x_min = math.floor(centre[0] - c + 0.5)
    y_min = math.floor(centre[1] - c + 0.5)
    x_max, y_max = x_min + side - 1, y_min + side - 1
    left, top = max(0, -x_min), max(0, -y_min)
    right, bottom = max(0, x_max - w + 1), max(0, y_max - h + 1)
    if left or top or right or bottom:
        canvas = np.zeros((h + top + bottom, w + left + right, *image.shape[2:]), np.uint8)
        canvas[...] = avg  # the uint8 store truncates the mean
        canvas[top : top + h, left : left + w] = image
        patch = canvas[y_min + top : y_max + top + 1, x_min + left : x_max + left + 1]
    else:
        patch = image[y_min : y_max + 1, x_min : x_max + 1]
    if side != out_size:
        patch = cv2.resize(patch, (out_size, out_size))
    return patch


@pytest.fixture(scope="module")
def frame() -> np.ndarray:
    rgb = skimage.data.astronaut()
    return np.ascontiguousarray(cv2.resize(rgb, (640, 480), interpolation=cv2.INTER_AREA)[:, :, ::-1])


CASES = [
    # (cx, cy, window side as a float before rounding, out size)
    (320.0, 240.0, 160.4, 255),  # inside, upscale
    (320.5, 240.5, 80.2, 255),  # inside, strong upscale
    (320.0, 240.0, 255.0, 255),  # same size: plain copy
    (300.3, 200.7, 400.7, 255),  # downscale
    (10.0, 10.0, 160.0, 255),  # top-left corner, padded
    (630.0, 470.0, 90.0, 127),  # bottom-right corner, template size
    (-30.0, 200.0, 120.0, 255),  # centre off the frame
    (700.0, -40.0, 300.0, 255),  # centre off two sides
    (320.0, 240.0, 37.0, 127),  # tiny window, 3.4× upscale
    (100.3, 50.7, 1511.5, 255),  # window much larger than the frame
    (0.0, 479.0, 126.5, 127),  # round half to even: side 126
    (-400.0, 900.0, 200.0, 255),  # window wholly off the frame: all fill
    (320.0, 240.0, 1024.0, 255),  # the largest window cut on a canvas
]


@pytest.mark.parametrize("crop", [subwindow, _remap_subwindow])
def test_crop_matches_get_subwindow(frame: np.ndarray, crop) -> None:
    avg = np.floor(frame.reshape(-1, 3).mean(axis=0))
    fill = mean_colour(frame)
    assert fill == tuple(avg)
    worst = worst_interior = 0
    for cx, cy, size, out in CASES:
        side = crop_side(size)
        ours = crop(frame, (cx, cy), out, side, fill).astype(int)
        ref = get_subwindow_reference(frame, (cx, cy), out, side, avg).astype(int)
        assert ours.shape == ref.shape == (out, out, 3)
        diff = np.abs(ours - ref)
        if side == out or (crop is subwindow and side <= MAX_CANVAS_SIDE):
            assert diff.max() == 0, (cx, cy, size)  # the released steps themselves
        worst = max(worst, int(diff.max()))
        worst_interior = max(worst_interior, int(diff[3:-3, 3:-3].max()))
    print(f"crop max abs difference vs get_subwindow: {worst} (interior {worst_interior})")
    assert worst <= 1


def test_grey_frames_crop_like_colour(frame: np.ndarray) -> None:
    grey = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
    colour = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR)
    for cx, cy, size, out in CASES[:6]:
        side = crop_side(size)
        a = subwindow(grey, (cx, cy), out, side, mean_colour(grey))
        b = subwindow(colour, (cx, cy), out, side, mean_colour(colour))
        np.testing.assert_array_equal(a, b[:, :, 0])


def test_crop_side_rounds_half_to_even() -> None:
    assert [crop_side(v) for v in (126.5, 127.5, 128.49, 0.2)] == [126, 128, 128, 1]


def test_mean_colour_truncates() -> None:
    image = np.zeros((2, 2, 3), np.uint8)
    image[0, 0] = (255, 3, 1)  # means 63.75, 0.75, 0.25
    assert mean_colour(image) == (63.0, 0.0, 0.0)
