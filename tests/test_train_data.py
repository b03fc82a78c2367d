"""Training pairs: crops follow the tracker's geometry, targets are BAN's, sources read the usual layouts."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("torch")

from dadiff.export.train_data import CropConfig, PairStream, SceneSource, SequenceSource, ban_targets  # noqa: E402
from dadiff.runtime.evaluation.scenes import write_benchmark  # noqa: E402


def test_ban_targets_centre_positive_far_negative():
    cfg = CropConfig()
    label, loc = ban_targets(np.array([0.0, 0.0, 64.0, 48.0], np.float32), cfg)
    assert label[12, 12] == 1 and label[0, 0] == 0 and (label == -1).any()
    assert np.allclose(loc[:, 12, 12], [32, 24, 32, 24])  # l, t, r, b at the centre point
    tiny, _ = ban_targets(np.array([3.0, -2.0, 4.0, 4.0], np.float32), cfg)
    assert (tiny == 1).sum() == 1  # a box smaller than the stride still gets its nearest point


def test_sequence_folders_give_pairs_with_targets(tmp_path):
    root = write_benchmark(tmp_path / "bench", sequences=1, frames=8, seed=1, split="train")
    source = SequenceSource(root)
    stream = iter(PairStream([source], None, CropConfig(), seed=0, with_night=False))
    sample = next(stream)
    assert sample["z"].shape == (3, 127, 127) and sample["x"].shape == (3, 255, 255)
    assert sample["label"].shape == (25, 25) and (sample["label"] == 1).any()


def test_scene_pairs_with_rendered_night_are_paired():
    stream = iter(PairStream([SceneSource("train")], None, CropConfig(), seed=0))
    sample = next(stream)
    assert bool(sample["paired"]) and sample["x_night"].shape == (3, 255, 255)
    assert float(sample["x_night"].mean()) < float(sample["x"].mean())  # night is darker


def test_night_styles_mix_per_pair(monkeypatch):
    seen = []

    def fake_night(frame, rng, style):
        seen.append(style)
        return frame // 4

    one = iter(PairStream([SceneSource("train")], None, CropConfig(), seed=3))
    monkeypatch.setattr(PairStream, "_night", staticmethod(fake_night))
    mixed = PairStream([SceneSource("train")], None, CropConfig(), seed=3, night_styles=("real", "classic"))
    pairs = iter(mixed)
    for _ in range(12):
        next(pairs)
    assert set(seen) == {"real", "classic"}
    assert all(a == b for a, b in zip(seen[::2], seen[1::2], strict=True))  # template and search: one camera
    seen.clear()
    monkeypatch.undo()
    default_sample = next(one)
    classic = next(iter(PairStream([SceneSource("train")], None, CropConfig(), seed=3, night_styles=("classic",))))
    assert float(classic["x_night"].mean()) > float(default_sample["x_night"].mean())  # classic is brighter


def test_a_resumed_stream_draws_new_pairs():
    """Resuming at step k must not replay the pairs of steps 1..k (seeded generators would)."""
    def first(start_step):
        return next(iter(PairStream([SceneSource("train")], None, CropConfig(), seed=0, start_step=start_step)))

    fresh, again, resumed = first(0), first(0), first(600)
    assert np.array_equal(fresh["x"], again["x"])
    assert not np.array_equal(fresh["x"], resumed["x"])
