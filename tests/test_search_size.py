"""`dadiff-export --search-size`: a trained network exported at a smaller search crop still tracks."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
ort = pytest.importorskip("onnxruntime")

from dadiff.export.checkpoint import CheckpointError, load_checkpoint  # noqa: E402
from dadiff.export.cli import main  # noqa: E402
from dadiff.export.search_size import search_sizes, with_search_size  # noqa: E402


def test_sizes_shrink_by_twice_the_stride():
    assert search_sizes(255, 16, 127) == [255, 223, 191, 159]
    assert search_sizes(255, 8, 127)[:3] == [255, 239, 223]


def test_smaller_search_takes_the_centre_of_the_start_noise(mobile_checkpoint):
    loaded = load_checkpoint(mobile_checkpoint)
    noise = loaded.model.e_xf.clone()
    small = with_search_size(loaded, 223)
    tr = small.config.tracker
    assert (tr.instance_size, tr.score_size, tr.point_origin, small.config.search_feature_size) == (223, 11, -80, 14)
    assert torch.equal(small.model.e_xf, noise[..., 1:15, 1:15])
    assert small.model.cfg == small.config
    with torch.no_grad():
        kcls, kloc = small.model.head.kernels(small.model.template(torch.zeros(1, 3, 127, 127)))
        cls, loc = small.model.track(torch.zeros(1, 3, 223, 223), kcls, kloc)
    assert cls.shape[-2:] == (11, 11) and loc.shape[-2:] == (11, 11)


def test_a_size_that_would_off_centre_the_map_is_refused(mobile_checkpoint):
    with pytest.raises(CheckpointError, match="must be one of 255, 223, 191, 159"):
        with_search_size(load_checkpoint(mobile_checkpoint), 239)
    small = with_search_size(load_checkpoint(mobile_checkpoint), 223)
    with pytest.raises(CheckpointError, match="larger than this dadiff-mobile checkpoint's 223 px"):
        with_search_size(small, 255)


def test_cli_refuses_a_bad_size_in_one_line(tmp_path, capsys, mobile_checkpoint):
    code = main([str(mobile_checkpoint), "-o", str(tmp_path / "m"), "--search-size", "239"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "search size 239" in err
    assert not (tmp_path / "m").exists()


def test_trained_model_at_223_tracks_a_night_sequence(tmp_path, capsys):
    """The default's final state (trained at 255 px) at 223 px tracks one generated night sequence (> 0.8).

    A 239 px export, its grid 8 px off centre, drifts to 0.60 there.
    """
    from dadiff.runtime import Tracker
    from dadiff.runtime.datamaking.scenes import make_sequence
    from dadiff.runtime.evaluation.evaluate import protocol_box
    from dadiff.runtime.evaluation.metrics import success_curve

    resume = Path(__file__).resolve().parents[1] / "export" / "resume"
    checkpoint = resume / "mobile-dadiff-tracks-s81-ema-average.pt"
    code = main([str(checkpoint), "-o", str(tmp_path / "m223"), "--search-size", "223"])
    out = capsys.readouterr().out
    assert code == 0 and "search crop 223 px, score map 11 x 11" in out
    meta = ort.InferenceSession(str(tmp_path / "m223" / "search.onnx")).get_modelmeta().custom_metadata_map
    assert (meta["instance_size"], meta["score_size"], meta["point_origin"]) == ("223", "11", "-80")
    sequence = make_sequence(3, split="test", frames=60)
    tracker = Tracker.load(tmp_path / "m223", threads=1)
    first = protocol_box(sequence.boxes[0])
    tracker.init(sequence.night[0], first)
    boxes = [first] + [tracker.update(frame).box for frame in sequence.night[1:]]
    assert success_curve(np.asarray(sequence.boxes), np.asarray(boxes)).mean() > 0.8
