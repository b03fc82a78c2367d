"""Decoding against hand-computed cases, and the whole update step against a scalar spec 8.3 loop.

The second part drives the Tracker through a plain-numpy backend, which also checks that a non-onnx
backend (the protocol a PyTorch backend will implement) plugs in.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from dadiff.runtime import Backend, Tracker
from dadiff.runtime.decode import Decoder, foreground_score, hann_window, size_penalty
from runtime_models import STRIDE8_META


def _maps(size: int, cell: tuple[int, int], logit: float, ltrb: tuple[float, ...]) -> tuple[np.ndarray, ...]:
    cls = np.zeros((1, 2, size, size), np.float32)
    cls[0, 1][cell] = logit
    loc = np.empty((1, 4, size, size), np.float32)
    loc[0] = np.asarray(ltrb, np.float32)[:, None, None]
    return cls, loc


def test_decode_hand_computed_cell() -> None:
    # 3×3 map, stride 8, origin −8: cell (row 1, col 2) sits at (8, 0). Its logits (0, ln 3) give score 0.75.
    # (l, t, r, b) = (10, 6, 14, 10): x1 = −2, y1 = −6, x2 = 22, y2 = 10 → centre (10, 2), size 24×16.
    # The target is 24×16, so no penalty; with no window the cell wins.
    decode = Decoder(3, 8.0, -8.0)
    cls, loc = _maps(3, (1, 2), math.log(3.0), (10, 6, 14, 10))
    det = decode(cls, loc, 24.0, 16.0, penalty_k=0.2, window_influence=0.0)
    assert det.index == 5
    assert (det.dx, det.dy, det.w, det.h) == pytest.approx((10.0, 2.0, 24.0, 16.0))
    assert det.score == pytest.approx(0.75)
    assert det.penalty == pytest.approx(1.0)
    # All other cells score 0.5; the 3×3 Hann window is 1 at the centre only, so with full window
    # influence the centre wins.
    assert decode(cls, loc, 24.0, 16.0, 0.2, 1.0).index == 4


def test_size_and_aspect_penalty_by_hand() -> None:
    # target 20×20, candidate 40×20: sz(40, 20) = √(70·50), sz(20, 20) = 40, so s_c = √3500 / 40;
    # aspect ratio change r_c = max(0.5, 2) = 2; penalty = exp(−(2·s_c − 1)·k).
    k = 0.1
    expected = math.exp(-(2 * math.sqrt(3500) / 40 - 1) * k)
    got = size_penalty(np.array([40.0]), np.array([20.0]), 20.0, 20.0, k)
    assert got[0] == pytest.approx(expected)
    assert expected == pytest.approx(0.8222, abs=1e-4)


def test_score_is_softmax_without_overflow() -> None:
    cls = np.array([[[[0.0, 800.0]], [[1.0, -800.0]]]], np.float32)  # (1, 2, 1, 2)
    with np.errstate(all="raise"):
        score = foreground_score(cls)
    assert score[0, 0] == pytest.approx(1 / (1 + math.exp(-1.0)))
    assert score[0, 1] == pytest.approx(0.0, abs=1e-12)


def test_hann_window_matches_definition() -> None:
    n = 25
    h = [0.5 - 0.5 * math.cos(2 * math.pi * i / (n - 1)) for i in range(n)]
    np.testing.assert_allclose(hann_window(n), np.outer(h, h), atol=1e-15)




class RandomBackend:
    """Seeded random head outputs, independent of the crops; records the calls it gets."""

    def __init__(self, seed: int = 0) -> None:
        self.meta = dict(STRIDE8_META)
        self.rng = np.random.default_rng(seed)
        self.calls: list[tuple[str, tuple[int, ...]]] = []
        self.outputs: list[tuple[np.ndarray, np.ndarray]] = []

    def template(self, z: np.ndarray) -> dict[str, np.ndarray]:
        self.calls.append(("template", z.shape))
        return {"kcls0": np.ones(3, np.float32)}

    def search(self, x: np.ndarray, feeds: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        self.calls.append(("search", x.shape))
        assert set(feeds) == {"kcls0"} and x.dtype == np.float32
        cls = self.rng.normal(0.0, 2.0, (1, 2, 25, 25)).astype(np.float32)
        loc = np.exp(self.rng.normal(3.5, 0.3, (1, 4, 25, 25))).astype(np.float32)
        self.outputs.append((cls, loc))
        return cls, loc


def spec_track(box: tuple[float, ...], frame_shape: tuple[int, int], outputs: list, hp: dict) -> list[tuple]:
    """Spec 8.1 and 8.3, literally, one cell at a time."""
    img_h, img_w = frame_shape
    x, y, w, h = box
    cx, cy, W, H = x + (w - 1) / 2, y + (h - 1) / 2, w, h  # noqa: N806
    boxes = []

    def sz(a: float, b: float) -> float:
        pad = (a + b) * 0.5
        return math.sqrt((a + pad) * (b + pad))

    def chg(r: float) -> float:
        return max(r, 1.0 / r)

    hann = [0.5 - 0.5 * math.cos(2 * math.pi * n / 24) for n in range(25)]
    for cls, loc in outputs:
        p = (W + H) / 2
        scale_z = 127 / math.sqrt((W + p) * (H + p))
        best, best_val = None, -math.inf
        for i in range(25):
            for j in range(25):
                c0, c1 = float(cls[0, 0, i, j]), float(cls[0, 1, i, j])
                score = math.exp(c1) / (math.exp(c0) + math.exp(c1))
                l, t, r, b = (float(v) for v in loc[0, :, i, j])  # noqa: E741
                px, py = -96 + 8 * j, -96 + 8 * i
                x1, y1, x2, y2 = px - l, py - t, px + r, py + b
                bw, bh = x2 - x1, y2 - y1
                s_c = chg(sz(bw, bh) / sz(W * scale_z, H * scale_z))
                r_c = chg((W / H) / (bw / bh))
                penalty = math.exp(-(r_c * s_c - 1) * hp["penalty_k"])
                pscore = (1 - hp["window_influence"]) * penalty * score + hp["window_influence"] * hann[
                    i
                ] * hann[j]
                if pscore > best_val:
                    best_val = pscore
                    best = ((x1 + x2) / 2, (y1 + y2) / 2, bw, bh, score, penalty)
        dx, dy, bw, bh, score, penalty = best
        lr = penalty * score * hp["lr"]
        cx, cy = cx + dx / scale_z, cy + dy / scale_z
        W, H = W * (1 - lr) + bw / scale_z * lr, H * (1 - lr) + bh / scale_z * lr  # noqa: N806
        cx, cy = max(0, min(cx, img_w)), max(0, min(cy, img_h))
        W, H = max(10, min(W, img_w)), max(10, min(H, img_h))  # noqa: N806
        boxes.append((cx - W / 2, cy - H / 2, W, H, score))
    return boxes


@pytest.mark.parametrize("preset", [None, "NAT"])
def test_update_matches_spec_loop(preset: str | None) -> None:
    backend = RandomBackend(seed=3)
    presets = {"NAT": {"lr": 0.45, "penalty_k": 0.14, "window_influence": 0.30}}
    backend.meta["hp_presets"] = json.dumps(presets)
    assert isinstance(backend, Backend)
    # lost_score 0: the lost/found logic never engages, so this is the released tracker exactly.
    tracker = Tracker(backend, preset=preset, overrides={"lost_score": 0})
    frame = np.full((360, 480, 3), 90, np.uint8)
    box = (200.0, 150.0, 40.0, 28.0)
    tracker.init(frame, box)
    ours = [tracker.update(frame) for _ in range(12)]
    hp = presets["NAT"] if preset else {"lr": 0.473, "penalty_k": 0.088, "window_influence": 0.401}
    ref = spec_track(box, frame.shape[:2], backend.outputs, hp)
    for got, want in zip(ours, ref, strict=True):
        assert got.box == pytest.approx(want[:4], rel=1e-9, abs=1e-9)
        assert got.score == pytest.approx(want[4], rel=1e-6)
        assert set(got.latency) == {"motion", "crop", "search", "post", "total"}
    assert [c[0] for c in backend.calls] == ["template"] + ["search"] * 12
    assert backend.calls[0][1] == (1, 3, 127, 127) and backend.calls[1][1] == (1, 3, 255, 255)


def test_box_is_clipped_like_the_release() -> None:
    backend = RandomBackend(seed=5)
    tracker = Tracker(backend, overrides={"lost_score": 0, "lr": 1.0})
    frame = np.zeros((100, 120), np.uint8)  # grey frames are accepted
    tracker.init(frame, (100.0, 80.0, 30.0, 30.0))
    for _ in range(20):
        x, y, w, h = tracker.update(frame).box
        cx, cy = x + w / 2, y + h / 2
        assert 0 <= cx <= 120 and 0 <= cy <= 100
        assert 10 <= w <= 120 and 10 <= h <= 100
