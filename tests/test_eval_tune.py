"""dadiff-eval tune: grid parsing, the coordinate search, and agreement with `dadiff-eval run`."""

from __future__ import annotations

import csv
import json
from types import SimpleNamespace

import pytest

from dadiff.runtime.commands.eval import main
from dadiff.runtime.errors import InputError
from dadiff.runtime.evaluation.tune import best_trial, coordinate_search, parse_grid

pytest.importorskip("skimage")  # the scene photos


def test_parse_grid_reads_keys_and_values():
    grid = parse_grid(["penalty_k=0.05,0.1", "lr=0.5"])
    assert grid == {"penalty_k": (0.05, 0.1), "lr": (0.5,)}


@pytest.mark.parametrize(
    ("item", "message"),
    [("penalty_k", "expected KEY=V1,V2"), ("speed=1,2", "unknown parameter 'speed'"),
     ("lr=fast", "must be numbers"), ("lr=nan", "finite")],
)
def test_parse_grid_names_the_bad_item(item, message):
    with pytest.raises(InputError, match=message):
        parse_grid([item])


def test_coordinate_search_finds_the_peak_and_evaluates_each_setting_once():
    calls = []

    def evaluate(values):
        calls.append(tuple(sorted(values.items())))
        return SimpleNamespace(success=-(values["a"] - 0.3) ** 2 - (values["b"] - 0.6) ** 2)

    trials = coordinate_search(evaluate, {"a": 0.1, "b": 0.1}, {"a": (0.1, 0.2, 0.3, 0.4), "b": (0.2, 0.6, 0.9)},
                               rounds=3)
    assert best_trial(trials).values == {"a": 0.3, "b": 0.6}
    assert len(calls) == len(set(calls)) == len(trials)
    assert trials[0].values == {"a": 0.1, "b": 0.1}  # the start comes first: what the search is judged against


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    root = tmp_path_factory.mktemp("tune") / "bench"
    args = ["generate", "-o", str(root), "--sequences", "2", "--max-frames", "6", "--seed", "5", "--size", "192x128",
            "--workers", "1"]
    assert main(args) == 0
    return root


def test_tune_start_trial_scores_what_run_scores(bench, tmp_path, capsys):
    """The in-memory loop must track exactly as `dadiff-eval run` does, or tuned values mean nothing."""
    out = tmp_path / "trials.csv"
    assert main(["tune", "--model", "dadiff-mobile", "--dataset", str(bench), "--grid", "penalty_k=0.02,0.3",
                 "--rounds", "1", "--threads", "1", "--output", str(out)]) == 0
    printed = capsys.readouterr().out
    rows = list(csv.DictReader(open(out)))
    assert [r["penalty_k"] for r in rows] == ["0.088", "0.02", "0.3"]  # the model's default first
    best = max(rows, key=lambda r: float(r["success"]))
    assert f"success {float(best['success']):.3f}" in printed.splitlines()[-1]

    assert main(["run", "--model", "dadiff-mobile", "--dataset", str(bench), "--output", str(tmp_path / "res"),
                 "--threads", "1", "--no-plots", "--no-progress"]) == 0
    capsys.readouterr()
    assert main(["score", "--dataset", str(bench), "--json", str(tmp_path / "res" / "bench")]) == 0
    scored = json.loads(capsys.readouterr().out)
    assert scored["dadiff-mobile"]["success"] == pytest.approx(float(rows[0]["success"]), abs=1e-4)


def test_tune_bad_grid_is_one_line_and_exit_2(bench, capsys):
    assert main(["tune", "--model", "dadiff-mobile", "--dataset", str(bench), "--grid", "speed=1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unknown parameter 'speed'" in err[0]


def test_tune_out_never_replaces_input_or_other_files(bench, tmp_path, capsys):
    """--out replaced any file, a dataset's ground truth included; now only a new file or an earlier trials CSV."""
    gt = bench / "seq001_day" / "groundtruth_rect.txt"
    other = tmp_path / "notes.txt"
    other.write_text("mine\n")
    before = gt.read_bytes()
    cases = [(gt, "--output lies inside the input folder"), (other, "--output exists and is not a trials CSV")]
    for out, message in cases:
        assert main(["tune", "--model", "dadiff-mobile", "--dataset", str(bench), "--grid", "lr=0.3",
                     "--rounds", "1", "--output", str(out)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0], err
    assert gt.read_bytes() == before and other.read_text() == "mine\n"
