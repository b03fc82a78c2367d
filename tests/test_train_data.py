"""Training pairs: crops follow the tracker's geometry, targets are BAN's, sources read the usual layouts."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("torch")

from dadiff.export.train_data import (  # noqa: E402
    CropConfig,
    PairStream,
    SceneSource,
    SequenceSource,
    ban_targets,
    make_day_source,
)
from dadiff.runtime.datamaking.scenes import write_benchmark  # noqa: E402


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


def test_camera_night_pairs_are_the_independent_models_night(monkeypatch):
    """night_styles "camera": both frames of a pair go through one camera of camera_night.py, which the generator's
    scene nights never call; the pair is darker than its day and shares the camera's exposure lock."""
    from dadiff.runtime.datamaking import camera_night

    calls = []
    render = camera_night.render_night

    def spy(day, seed):
        calls.append(len(day))
        return render(day, seed)

    monkeypatch.setattr(camera_night, "render_night", spy)
    stream = iter(PairStream([SceneSource("train")], None, CropConfig(), seed=5, night_pairs="scene",
                             night_styles=("camera",)))
    samples = [next(stream) for _ in range(4)]
    assert calls == [2] * 4  # template and search frames of each pair filmed together by one camera
    night, day = (sum(float(s[key].mean()) for s in samples) for key in ("x_night", "x"))
    assert night < 0.7 * day  # a crop under a lamp's pool can be bright; four are not
    calls.clear()
    next(iter(PairStream([SceneSource("train")], None, CropConfig(), seed=5, night_pairs="scene")))
    assert calls == []  # the default style never renders with the camera model


def test_camera_night_pair_of_two_frame_sizes_is_rendered_frame_by_frame():
    from dadiff.export.train_data import camera_night_pair

    rng = np.random.default_rng(0)
    big, small = np.full((120, 160, 3), 200, np.uint8), np.full((90, 100, 3), 200, np.uint8)
    nz, nx = camera_night_pair(big, small, rng)
    assert nz.shape == big.shape and nx.shape == small.shape and nz.mean() < 100 and nx.mean() < 100


def test_a_resumed_stream_draws_new_pairs():
    """Resuming at step k must not replay the pairs of steps 1..k (seeded generators would)."""
    def first(start_step):
        return next(iter(PairStream([SceneSource("train")], None, CropConfig(), seed=0, start_step=start_step)))

    fresh, again, resumed = first(0), first(0), first(600)
    assert np.array_equal(fresh["x"], again["x"])
    assert not np.array_equal(fresh["x"], resumed["x"])


def test_scene_night_pairs_share_one_camera_and_its_lights():
    """night_pairs "scene": a pair is lit as the evaluation's sequences are, by one night over the scene, so the
    same frame twice differs only by sensor noise; rendered per frame it gets two cameras and two light sets."""
    from dadiff.runtime.datamaking.night import render_night

    source = SceneSource("train")
    rng = np.random.default_rng(5)
    frame, _, _, _ = source.sample(rng)
    scene, i, _ = source._pair
    source._pair = (scene, i, i)
    a, b = (x.astype(np.float32) for x in source.night_pair(frame, frame, rng, "real"))
    c, d = (render_night(frame, rng).astype(np.float32) for _ in range(2))
    assert np.abs(a.mean(axis=2) - b.mean(axis=2)).mean() < 0.5 * np.abs(c.mean(axis=2) - d.mean(axis=2)).mean()


def test_sequence_one_night_lights_both_frames_alike_and_off_keeps_the_old_pairs(tmp_path):
    """A sequence source's `one_night`: the pair under one camera, fixed lights and the template's exposure, as
    `dadiff-eval video` renders a sequence, so the same frame twice differs only by sensor noise; off, each
    frame gets its own night with the same draws as before the option (recorded runs' streams unchanged)."""
    from dadiff.runtime.datamaking.night import render_night

    root = write_benchmark(tmp_path / "bench", sequences=1, frames=4, seed=3, split="train")
    plain, lit = SequenceSource(root), SequenceSource(root, one_night=True)
    frame = lit.sample(np.random.default_rng(1))[0]
    lit._gap = 0  # the frame with itself
    near, far = [], []
    for seed in range(4):
        a, b = (x.astype(np.float32).mean(axis=2) for x in lit.night_pair(frame, frame, np.random.default_rng(seed),
                                                                           "real"))
        c, d = (x.astype(np.float32).mean(axis=2) for x in plain.night_pair(frame, frame,
                                                                             np.random.default_rng(seed), "real"))
        near.append(np.abs(a - b).mean())
        far.append(np.abs(c - d).mean())
        rng = np.random.default_rng(seed)
        old = (render_night(frame, rng).astype(np.float32).mean(axis=2) for _ in range(2))
        assert all(np.array_equal(u, v) for u, v in zip(old, (c, d), strict=True))
    assert np.mean(near) < 0.5 * np.mean(far), (near, far)
    with pytest.raises(ValueError, match="one_night is 'yes'"):
        make_day_source({"kind": "sequences", "root": str(root), "one_night": "yes"})


def test_pair_stream_renders_scene_pairs_through_the_source_only_when_asked(monkeypatch):
    calls = []

    def one_night(self, fi, fj, rng, style, path_lamps):
        calls.append((style, path_lamps))
        return fi // 4, fj // 4

    monkeypatch.setattr(SceneSource, "night_pair", one_night)
    next(iter(PairStream([SceneSource("train")], None, CropConfig(), seed=0)))
    assert calls == []  # default "frame": each frame its own night, as earlier runs were trained
    next(iter(PairStream([SceneSource("train")], None, CropConfig(), seed=0, night_pairs="scene")))
    next(iter(PairStream([SceneSource("train")], None, CropConfig(), seed=0, night_pairs="scene",
                         night_path_lamps=0.5)))
    assert calls == [("real", 0.0), ("real", 0.5)]


def test_negative_pairs_put_another_scenes_object_in_the_search_crop(monkeypatch):
    """negative_pairs: the search crop is cut around another scene's target; the points where a target would
    be positive are negative and nothing else is labelled; at 0 no pair is negative (no other scene is drawn)."""
    calls = []
    other = SceneSource.other

    def counted(self, rng):
        calls.append(1)
        return other(self, rng)

    monkeypatch.setattr(SceneSource, "other", counted)
    cfg = CropConfig()
    plain = PairStream([SceneSource("train")], None, cfg, seed=0, night_pairs="scene")
    assert (next(iter(plain))["label"] == 1).any()
    assert calls == []
    stream = iter(PairStream([SceneSource("train")], None, cfg, seed=0, night_pairs="scene", negative_pairs=1.0))
    for _ in range(3):
        sample = next(stream)
        label = sample["label"].numpy()
        assert not (label == 1).any() and (label == 0).any()
        assert set(np.unique(label)) == {-1, 0}
        assert sample["x_night"].shape == sample["x"].shape  # its night is rendered too (one night per frame)
    assert len(calls) == 3
    assert (label == 0).sum() < label.size / 4  # only the other object's central points, not the background


def test_path_lamps_stand_beside_the_target_and_saturate():
    """night_path_lamps: each added lamp head is fixed on the ground 0.7-2.5 target sizes from the target in the
    chosen frame, saturates the picture there, and with the share at 0 nothing is drawn (streams stay as they were)."""
    from dadiff.runtime.datamaking.scenes import SceneNight

    source = SceneSource("train")
    frame, box, _, _ = source.sample(np.random.default_rng(3))
    scene, i, j = source._pair
    night = SceneNight(scene, np.random.default_rng(4), "real")
    before = len(night.lights.lamps)
    plain = night(frame, i, np.random.default_rng(9))
    night.add_path_lamps(np.random.default_rng(5), (i,), 3)
    lamps = night._lights(i).lamps[before:before + 3]
    assert len(night.lights.lamps) == before + 3
    x, y, w, h = scene.boxes[i]
    size = max(np.sqrt(w * h), 8.0)
    reach = np.hypot(lamps[:, 0] - (x + w / 2), lamps[:, 1] - (y + h / 2)) / size
    assert np.all((reach > 0.69) & (reach < 2.51))
    lit = night(frame, i, np.random.default_rng(9))
    inside = [(int(ly), int(lx)) for lx, ly in lamps[:, :2] if 0 <= lx < frame.shape[1] and 0 <= ly < frame.shape[0]]
    assert inside and all(lit[r, c].max() >= 240 > plain[r, c].max() for r, c in inside)
    rng_a, rng_b = np.random.default_rng(7), np.random.default_rng(7)
    source._pair = (scene, i, j)
    a = source.night_pair(frame, frame, rng_a, "real")
    b = source.night_pair(frame, frame, rng_b, "real", 0.0)
    assert all(np.array_equal(u, v) for u, v in zip(a, b, strict=True))


@pytest.mark.parametrize("option", ["companions", "stretch"])
@pytest.mark.parametrize("value, source", [(1.5, "library"), (-0.1, "library"), (0.5, "skimage")])
def test_library_scene_options_are_shares_of_library_scenes(option, value, source):
    """Look-alikes beside the target (`companions`) and targets that are not rigid (`stretch`) come from the
    real-photo library's scenes only, as a share; anything else is refused by name before a library is opened."""
    from dadiff.export.train_data import make_day_source

    with pytest.raises(ValueError, match=f"{option} is {value}"):
        make_day_source({"kind": "scenes", "split": "train", "source": source, option: value})


def test_far_pairs_shrink_both_frames_so_the_target_is_a_few_pixels_wide(tmp_path):
    """`far`: the share of a sequence source's pairs whose two frames are shrunk by one factor so the
    template's target is 10-30 px wide (a far person at night, whom the crop enlarges); boxes follow the
    frames. At 0 no draw is made, so the pairs are those of before the option."""
    root = write_benchmark(tmp_path / "bench", sequences=2, frames=10, seed=3, split="train")
    plain, far = SequenceSource(root), SequenceSource(root, far=1.0)
    shrunk = 0
    for seed in range(12):
        fa, ba, fb, bb = plain.sample(np.random.default_rng(seed))
        sa, sba, sb, sbb = far.sample(np.random.default_rng(seed))
        assert sa.shape == sb.shape
        factor = sa.shape[1] / fa.shape[1]
        if factor == 1.0:  # a target already as narrow as the drawn width stays as it is
            assert ba[2] <= SequenceSource.FAR_WIDTH[1] and np.array_equal(sba, ba)
            continue
        shrunk += 1
        assert SequenceSource.FAR_WIDTH[0] - 1 <= sba[2] <= SequenceSource.FAR_WIDTH[1] + 1
        np.testing.assert_allclose(sbb[2:], bb[2:] * factor, rtol=0.02)
        np.testing.assert_allclose(sba[2] / ba[2], factor, rtol=0.02)
    assert shrunk >= 3
    again = SequenceSource(root, far=0.0).sample(np.random.default_rng(0))
    assert all(np.array_equal(u, v) for u, v in zip(again, plain.sample(np.random.default_rng(0)), strict=True))
    with pytest.raises(ValueError, match="far is 1.5"):
        SequenceSource(root, far=1.5)


def _sequence(folder, frames, boxes, nan_at=()):
    """Frames 1.png..N.png in folder/img (unpadded, OTB-style), frame k's grey level 10 k, box k at x = k;
    `boxes` lines in groundtruth_rect.txt, NaN at the 1-based lines in `nan_at`."""
    import cv2

    (folder / "img").mkdir(parents=True)
    for k in range(1, frames + 1):
        cv2.imwrite(str(folder / "img" / f"{k}.png"), np.full((32, 32, 3), 10 * k, np.uint8))
    lines = ["nan,nan,nan,nan" if k in nan_at else f"{k},2,6,6" for k in range(1, boxes + 1)]
    (folder / "groundtruth_rect.txt").write_text("\n".join(lines) + "\n")


def test_unpadded_frame_names_pair_each_frame_with_its_own_box_and_nan_boxes_stay_out(tmp_path):
    """Text order (1, 10, 11, 2, ...) paired frame 10 with box 3; frames go in number order, as evaluated."""
    _sequence(tmp_path / "Walker", frames=11, boxes=11, nan_at=(5,))
    source = SequenceSource(tmp_path)
    (frames, boxes, valid), = source.sequences
    assert [p.name for p in frames] == [f"{k}.png" for k in range(1, 12)]
    assert 4 not in valid and len(valid) == 10  # the NaN line (frame 5) is never drawn
    rng = np.random.default_rng(0)
    for _ in range(20):
        fa, box_a, fb, box_b = source.sample(rng)
        assert fa[0, 0, 0] == 10 * box_a[0] and fb[0, 0, 0] == 10 * box_b[0]  # frame k read with box k


def test_a_sequence_with_fewer_boxes_than_frames_is_left_out_with_one_warning(tmp_path, capsys):
    """OTB's David is labelled from frame 300: trimming paired frame 1 with frame 300's box."""
    _sequence(tmp_path / "David", frames=12, boxes=8)
    _sequence(tmp_path / "Test", frames=6, boxes=1)  # GOT-10k test split: only the first frame labelled
    _sequence(tmp_path / "Good", frames=6, boxes=6)
    source = SequenceSource(tmp_path)
    assert [frames[0].parent.parent.name for frames, _, _ in source.sequences] == ["Good"]
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "warning" in err[0] and str(tmp_path) in err[0]
    assert "David (8 boxes for 12 frames)" in err[0] and "Test (only the first frame is labelled" in err[0]


def test_no_sequence_with_one_box_per_frame_is_an_error_naming_the_root(tmp_path):
    _sequence(tmp_path / "David", frames=12, boxes=8)
    _sequence(tmp_path / "Extra", frames=4, boxes=6)
    with pytest.raises(ValueError, match="no usable sequence") as info:
        SequenceSource(tmp_path)
    assert str(tmp_path) in str(info.value) and "\n" not in str(info.value)
    assert "David (8 boxes for 12 frames)" in str(info.value) and "Extra (6 boxes for 4 frames)" in str(info.value)
