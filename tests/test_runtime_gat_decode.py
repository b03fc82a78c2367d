"""The released SiamGAT post-processing against the official tracker's fixture (official-dadiff-gat README 4).

Two levels: the decoder alone, fed each frame's maps with the official tracker state before it (coarse and fine
peaks identical), and the whole runtime Tracker on the fixture's generated frames with a backend replaying the
official model outputs (template and search crops bit-identical, boxes within 1e-6 relative, for both presets
and for the synthetic maps that move the peak).
"""

from __future__ import annotations

import zlib

import numpy as np
import pytest

from conftest import gat_fixture_dir
from dadiff.export.config import gat_googlenet_config, tracker_metadata
from dadiff.runtime import Tracker
from dadiff.runtime.decode_gat import GatDecoder

RUNS = ("nutl", "uavdark70", "synth_nutl", "synth_uavdark70")
PRESETS = {"nutl": "NUT_L", "uavdark70": "UAVDark70"}
UP = 193


@pytest.fixture(scope="module")
def ref() -> dict[str, np.ndarray]:
    return dict(np.load(gat_fixture_dir() / "dadiff_gat_tracker_ref.npz"))


@pytest.fixture(scope="module")
def frames(ref, gat_frames) -> list[np.ndarray]:
    made, _ = gat_frames
    assert [zlib.crc32(f.tobytes()) for f in made] == ref["frame_crc32"].tolist()
    return made


def _maps(ref: dict[str, np.ndarray], run: str, i: int) -> tuple[np.ndarray, ...]:
    """Frame i+1's model outputs: recorded from the real model, or the synthetic ones."""
    if run.startswith("synth_"):
        return tuple(ref[f"synth_{k}"][i][None] for k in ("cls", "loc", "cen"))
    return tuple(ref[f"{run}_{k}"][i][None] for k in ("cls_raw", "loc", "cen_raw"))


def _preset(run: str) -> str:
    return PRESETS[run.removeprefix("synth_")]


def test_presets_are_the_release_s(ref):
    tr = gat_googlenet_config().tracker
    assert tr.default_preset == "NUT_L" and tr.point_origin == -98 and tr.min_size == 0.0
    assert set(tr.hp_presets) == {"NUT_L", "UAVDark70", "NAT", "OTB100", "GOT_10k", "LaSOT", "UAV123"}
    for run in RUNS:
        hp = tr.hp_presets[_preset(run)]
        assert [hp["lr"], hp["penalty_k"], hp["window_influence"]] == ref[f"{run}_hp"].tolist()


@pytest.mark.parametrize("run", RUNS)
def test_decoder_peaks_equal_the_official_tracker_s(ref, run):
    tr = gat_googlenet_config().tracker
    decode = GatDecoder(tr.score_size, tr.stride, tr.point_origin, tr.exemplar_size, tr.region_s, tr.region_l)
    hp = tr.hp_presets[_preset(run)]
    box = ref[f"{run}_init_box"]
    size = box[2:]
    for i in range(19):
        scale = ref[f"{run}_scale_z"][i]
        det = decode(*_maps(ref, run, i), size[0] * scale, size[1] * scale, scale, hp["penalty_k"],
                     hp["window_influence"])
        assert divmod(det.coarse, UP) == tuple(ref[f"{run}_coarse_rc"][i]), f"frame {i + 1}"
        assert divmod(det.index, UP) == tuple(ref[f"{run}_fine_rc"][i]), f"frame {i + 1}"
        assert det.weight == pytest.approx(ref[f"{run}_cls_up_at_peak"][i], rel=1e-6)
        size = ref[f"{run}_size"][i]


class ReplayBackend:
    """The official model's outputs, one frame after the other; keeps CRCs of the crops the tracker feeds."""

    def __init__(self, maps: list[tuple[np.ndarray, ...]]) -> None:
        self.meta = tracker_metadata(gat_googlenet_config().tracker)
        self.maps, self.crops, self.template_crc, self.roi = maps, [], None, None

    def template(self, z: np.ndarray, roi: np.ndarray | None = None) -> dict[str, np.ndarray]:
        self.template_crc, self.roi = zlib.crc32(np.ascontiguousarray(z, np.float32).tobytes()), roi
        return {}

    def search(self, x: np.ndarray, feeds: dict[str, np.ndarray]) -> tuple[np.ndarray, ...]:
        self.crops.append(zlib.crc32(np.ascontiguousarray(x, np.float32).tobytes()))
        return self.maps[len(self.crops) - 1]


@pytest.mark.parametrize("run", RUNS)
def test_tracker_boxes_equal_the_official_tracker_s(ref, frames, run):
    backend = ReplayBackend([_maps(ref, run, i) for i in range(19)])
    tracker = Tracker(backend, preset=_preset(run), overrides={"lost_score": 0})
    tracker.init(frames[0], ref[f"{run}_init_box"])
    assert backend.template_crc == int(ref[f"{run}_init_zcrop_crc32"][0])
    assert np.array_equal(backend.roi, ref[f"{run}_init_roi"])
    boxes = np.array([tracker.update(f).box for f in frames[1:]])
    assert backend.crops == ref[f"{run}_xcrop_crc32"].tolist()
    expected = ref[f"{run}_bbox"]
    assert np.abs(boxes - expected).max() <= 1e-6 * np.abs(expected).max()
    assert np.all(np.abs(boxes - expected) <= 1e-6 * np.abs(expected))


def test_runtime_additions_stay_switchable(ref, frames):
    """Lost state, plausibility and motion compensation run on a GAT model too (default settings), and the box
    a flat, hopeless response gives is held (lost), not moved."""
    maps = [_maps(ref, "synth_nutl", i) for i in range(19)]
    background = np.concatenate([np.full((1, 1, 25, 25), 5, np.float32), np.full((1, 1, 25, 25), -5, np.float32)], 1)
    flat = (background, np.full((1, 4, 25, 25), 10, np.float32), np.zeros((1, 1, 25, 25), np.float32))
    backend = ReplayBackend(maps[:5] + [flat] * 14)
    tracker = Tracker(backend)
    tracker.init(frames[0], ref["nutl_init_box"])
    results = [tracker.update(f) for f in frames[1:]]
    assert [r.state for r in results[:5]] != ["lost"] * 5 and results[-1].state == "lost"
    assert results[-1].box == results[-2].box and 0 <= results[-1].score < 0.01


@pytest.mark.parametrize(("change", "message"), [
    ({"decoder": "siamcar"}, "metadata key 'decoder' is 'siamcar'"),
    ({"region_s": None}, "metadata key 'region_s' is missing"),
    ({"region_s": "0.5", "region_l": "0.2"}, "must satisfy 0 < region_s <= region_l <= 1"),
    ({"stride": "7.5", "point_origin": "-90"}, "the siamgat decoder needs an integer"),
])
def test_bad_decoder_metadata_is_one_line_naming_the_key(change, message):
    from dadiff.runtime.config import check_metadata
    from dadiff.runtime.errors import ModelError

    meta = tracker_metadata(gat_googlenet_config().tracker)
    for key, value in change.items():
        if value is None:
            del meta[key]
        else:
            meta[key] = value
    with pytest.raises(ModelError, match=message):
        check_metadata(meta, "search.onnx")
