"""OPE metrics against hand-computed values, including the toolkit's edge cases."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from dadiff.runtime.evaluation.metrics import (
    NORM_THRESHOLDS,
    PRECISION_THRESHOLDS,
    SUCCESS_THRESHOLDS,
    SequenceCurves,
    centre_errors,
    centres,
    iou,
    norm_precision_curve,
    paired_difference,
    precision_curve,
    success_curve,
    summarise,
)

NAN = math.nan


def test_thresholds_are_the_toolkits():
    assert len(SUCCESS_THRESHOLDS) == 21 and SUCCESS_THRESHOLDS[0] == 0 and SUCCESS_THRESHOLDS[-1] == 1
    assert len(PRECISION_THRESHOLDS) == 51 and PRECISION_THRESHOLDS[20] == 20
    assert len(NORM_THRESHOLDS) == 51 and NORM_THRESHOLDS[20] == 0.2 and NORM_THRESHOLDS[-1] == 0.5


def test_iou_spans_x_to_x_plus_w():
    # [0, 10] and [5, 15]: intersection 5 x 10 = 50, union 150.
    assert iou([[0, 0, 10, 10]], [[5, 0, 10, 10]]) == pytest.approx([1 / 3])
    # Touching boxes do not overlap; disjoint ones give 0, never negative.
    assert iou([[0, 0, 10, 10], [0, 0, 10, 10]], [[10, 0, 10, 10], [50, 50, 5, 5]]).tolist() == [0.0, 0.0]


def test_success_is_strictly_above_each_threshold():
    # IoU exactly 0.5 (a 10x10 box inside a 10x20 one) beats 0, 0.05, ..., 0.45 but not 0.5: 10 of 21.
    curve = success_curve([[0, 0, 10, 20]], [[0, 0, 10, 10]])
    assert curve.tolist() == [1.0] * 10 + [0.0] * 11
    # IoU exactly 0.25 beats 0 ... 0.2: 5 of 21.
    assert success_curve([[0, 0, 10, 10]], [[0, 0, 10, 2.5]]).sum() == 5
    # A perfect box still fails at threshold 1.0, so the best AUC is 20/21.
    perfect = SequenceCurves.from_boxes([[3, 4, 10, 10]], [[3, 4, 10, 10]])
    assert summarise([perfect]).success == pytest.approx(20 / 21)


def test_invalid_ground_truth_is_a_success_failure():
    gt = [[0, 0, 0, 10], [0, 0, 10, -1], [NAN, NAN, NAN, NAN], [0, 0, 10, 10]]
    pred = [[0, 0, 0, 10], [0, 0, 10, -1], [0, 0, 10, 10], [0, 0, 10, 10]]
    assert iou(gt, pred).tolist() == [-1.0, -1.0, -1.0, 1.0]
    # Only the last frame counts as a success, even at threshold 0: 1/4 everywhere but at 1.0.
    assert success_curve(gt, pred).tolist() == [0.25] * 20 + [0.0]


def test_nan_prediction_fails_everything():
    assert success_curve([[0, 0, 10, 10]], [[NAN, 0, 10, 10]]).sum() == 0
    assert precision_curve([[5, 5, 10, 10]], [[NAN, 5, 10, 10]]).sum() == 0


def test_centre_convention_and_precision_threshold_is_inclusive():
    assert centres([[0, 0, 10, 10]]).tolist() == [[4.5, 4.5]]
    gt = [[10, 10, 10, 10]]
    # A (12, 16) shift is 20 px exactly: a hit at 20, a miss at 19.
    curve = precision_curve(gt, [[22, 26, 10, 10]])
    assert curve[19] == 0 and curve[20] == 1 and curve[50] == 1
    assert precision_curve(gt, [[22, 26.01, 10, 10]])[20] == 0


def test_precision_counts_invalid_gt_centres_as_hits():
    # NaN GT, and a GT centre at 0 (x = 0, w = 1 gives centre x 0), are hits whatever the prediction.
    gt = [[NAN, NAN, NAN, NAN], [0, 5, 1, 10], [10, 10, 10, 10], [10, 10, 10, 10]]
    pred = [[500, 500, 5, 5], [500, 500, 5, 5], [10, 10, 10, 10], [500, 500, 5, 5]]
    assert centre_errors(gt, pred)[:2].tolist() == [-1.0, -1.0]
    assert precision_curve(gt, pred).tolist() == [0.75] * 51
    # A zero-size GT with a positive centre is an ordinary frame for precision (only success rejects it).
    assert precision_curve([[10, 10, 0, 0]], [[10, 10, 0, 0]])[0] == 1


def test_normalised_precision_divides_by_gt_size():
    gt = [[10, 10, 20, 40]]
    # 3.1 px along x on a 20 px wide box: 0.155, a hit from threshold 0.16 on (35 of 51 thresholds).
    curve = norm_precision_curve(gt, [[13.1, 10, 20, 40]])
    assert curve[:16].sum() == 0 and curve[16:].tolist() == [1.0] * 35
    scores = summarise([SequenceCurves.from_boxes(gt, [[13.1, 10, 20, 40]])])
    assert scores.norm_precision == pytest.approx(35 / 51)
    assert scores.norm_precision_at_20 == 1.0
    # The same 3.1 px on a 5 px wide box is 0.62: never within 0.5.
    assert norm_precision_curve([[10, 10, 5, 40]], [[13.1, 10, 5, 40]]).sum() == 0


def test_every_frame_counts_including_frame_zero():
    # Frame 0 (the init box) perfect, frame 1 lost: half the frames succeed below threshold 1.
    scores = summarise([SequenceCurves.from_boxes([[0, 0, 10, 10]] * 2, [[0, 0, 10, 10], [100, 100, 10, 10]])])
    assert scores.success == pytest.approx(0.5 * 20 / 21)
    assert scores.precision == 0.5


def test_sequences_are_weighted_equally():
    short = SequenceCurves.from_boxes([[0, 0, 10, 10]], [[0, 0, 10, 10]])
    long = SequenceCurves.from_boxes([[0, 0, 10, 10]] * 3, [[100, 100, 10, 10]] * 3)
    scores = summarise([short, long])
    assert scores.success == pytest.approx((20 / 21 + 0) / 2)
    assert scores.precision == pytest.approx(0.5)
    assert scores.sequences == 2
    assert np.allclose(scores.success_curve, [0.5] * 20 + [0.0])


def test_bad_shapes_are_rejected():
    with pytest.raises(ValueError, match="ground truth has 2"):
        SequenceCurves.from_boxes([[0, 0, 1, 1]] * 2, [[0, 0, 1, 1]])
    with pytest.raises(ValueError, match=r"\(N, 4\)"):
        iou([[0, 0, 1]], [[0, 0, 1]])
    with pytest.raises(ValueError, match="no sequences"):
        summarise([])


def test_paired_difference_interval_holds_the_mean_and_shrinks_with_agreement():
    rng = np.random.default_rng(1)
    theirs = rng.uniform(0.2, 0.8, 40)
    noisy = paired_difference(theirs + 0.05 + rng.normal(0, 0.2, 40), theirs)
    steady = paired_difference(theirs + 0.05, theirs)
    assert noisy.low < noisy.mean < noisy.high and noisy.sequences == 40
    assert steady.mean == pytest.approx(0.05) and steady.high - steady.low < 1e-9  # every draw is the same gap
    assert noisy.high - noisy.low > 0.05
    with pytest.raises(ValueError, match="same non-empty sequences"):
        paired_difference([0.1, 0.2], [0.1])


@pytest.mark.parametrize("value", [1e308, 1.7e308, -1e308])
def test_huge_finite_boxes_fail_without_numpy_warnings(value):
    """A result row of 1e308 used to print overflow RuntimeWarnings on stderr; it is a plain failure."""
    gt = [[10, 10, 10, 10]] * 2
    pred = [[value, value, abs(value), abs(value)]] * 2
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert success_curve(gt, pred).sum() == 0
        assert precision_curve(gt, pred).sum() == 0
        assert norm_precision_curve(gt, pred).sum() == 0
