"""The colour prior (runtime/colour_prior.py): cells on the start box's colours outweigh cells on a look-alike
of other colours; a grey picture gives no prior; the decoder picks by it without changing the reported score;
and the setting is checked."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_runtime_decode import _maps
from test_runtime_plausible import ScriptedBackend

from dadiff.runtime import Tracker
from dadiff.runtime.colour_prior import ColourPrior
from dadiff.runtime.decode import Decoder, point_grid
from dadiff.runtime.errors import InputError

RED, GREEN = (40, 40, 200), (40, 180, 40)  # BGR


def _scene(seed: int = 0) -> np.ndarray:
    """A 300 x 300 frame of noisy grey ground, a red 20 x 40 figure at (100, 150) and a green one at (200, 150)."""
    rng = np.random.default_rng(seed)
    frame = rng.integers(70, 110, size=(300, 300, 3)).astype(np.uint8)
    for (cx, cy), colour in (((100, 150), RED), ((200, 150), GREEN)):
        frame[cy - 20 : cy + 20, cx - 10 : cx + 10] = colour
    return frame


def test_cells_on_the_target_colours_outweigh_a_look_alike_of_other_colours() -> None:
    frame = _scene()
    prior = ColourPrior()
    prior.reset(frame, (99.5, 149.5), (20.0, 40.0))
    px, py = point_grid(25, 8.0, -96.0)  # a 25 x 25 map over a 200 px crop centred on the frame's centre
    patch = frame[50:250, 50:250]
    weights = prior.weights(patch, (20.0, 40.0), (px, py), 0.5)
    assert weights is not None and weights.shape == (25, 25)
    on_red = weights[np.unravel_index(np.argmin(np.hypot(px + 50, py)), px.shape)]  # crop x 100 -> frame x 100
    on_green = weights[np.unravel_index(np.argmin(np.hypot(px - 50, py)), px.shape)]
    assert on_red == pytest.approx(1.0, abs=0.05) and on_green < 0.6
    assert weights.min() >= 0.5 - 1e-6


def test_a_grey_picture_gives_no_prior() -> None:
    grey = _scene()[:, :, 1]
    prior = ColourPrior()
    prior.reset(grey, (99.5, 149.5), (20.0, 40.0))
    assert prior.weights(np.dstack([grey] * 3)[50:250, 50:250], (20.0, 40.0), point_grid(25, 8.0, -96.0), 0.5) is None


def test_the_decoder_picks_by_the_prior_and_reports_the_networks_score() -> None:
    decode = Decoder(3, 8.0, -8.0)
    cls, loc = _maps(3, (1, 2), math.log(3.0), (10, 6, 14, 10))
    cls[0, 1][1, 0] = math.log(3.0)  # two cells of score 0.75: the first argmax, (1, 0), wins without a prior
    assert decode(cls, loc, 24.0, 16.0, 0.2, 0.0).index == 3
    prior = np.ones((3, 3))
    prior[1, 0] = 0.5
    det = decode(cls, loc, 24.0, 16.0, 0.2, 0.0, prior)
    assert det.index == 5 and det.score == pytest.approx(0.75)


def test_colour_prior_setting_is_checked() -> None:
    with pytest.raises(InputError, match="colour_prior"):
        Tracker(ScriptedBackend([0.9], 20.0), overrides={"colour_prior": 1.5})


def test_the_tracker_reads_the_prior_only_when_asked(monkeypatch: pytest.MonkeyPatch) -> None:
    calls = []
    monkeypatch.setattr(ColourPrior, "weights", lambda self, *args: calls.append(args[3]))
    frame = _scene()
    for overrides in ({}, {"colour_prior": 0.4, "lost_score": 0}, {"colour_prior": 0.4}):
        tracker = Tracker(ScriptedBackend([0.97], 20.0), overrides=overrides)
        tracker.init(frame, (90.0, 130.0, 20.0, 40.0))
        tracker.update(frame)
    assert calls == [0.4]  # off by default, and the released tracker ignores it
