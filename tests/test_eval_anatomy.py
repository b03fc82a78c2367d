"""dadiff-eval anatomy: centred share, IoU where centred, and both by the target's grey level."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from dadiff.runtime.commands.eval import main
from dadiff.runtime.datamaking.datasets import load_dataset
from dadiff.runtime.evaluation.anatomy import anatomy, grey_bins

BOX = (20, 10, 10, 10)
FRAMES = 4


def write_sequence(root: Path, name: str, background: int, target: int) -> None:
    folder = root / name / "img"
    folder.mkdir(parents=True)
    x, y, w, h = BOX
    for k in range(FRAMES):
        image = np.full((48, 64), background, np.uint8)
        image[y:y + h, x:x + w] = target
        cv2.imwrite(str(folder / f"{k + 1:04d}.png"), image)
    (root / name / "groundtruth_rect.txt").write_text(f"{x},{y},{w},{h}\n" * FRAMES)


def write_results(folder: Path, shift: dict[str, int]) -> None:
    folder.mkdir(parents=True)
    x, y, w, h = BOX
    for name, dx in shift.items():
        rows = [f"{x},{y},{w},{h}"] + [f"{x + dx},{y},{w},{h}"] * (FRAMES - 1)
        (folder / f"{name}.txt").write_text("\n".join(rows) + "\n")


@pytest.fixture
def bench(tmp_path: Path) -> Path:
    write_sequence(tmp_path / "set", "lit", background=10, target=100)
    write_sequence(tmp_path / "set", "dark", background=2, target=4)
    write_results(tmp_path / "res" / "exact", {"lit": 0, "dark": 0})
    write_results(tmp_path / "res" / "loses_dark", {"lit": 3, "dark": 30})  # 3 px: still centred, IoU 0.54
    return tmp_path


def test_centred_share_and_iou_by_the_targets_grey_level(bench):
    dataset = load_dataset(bench / "set")
    bins = grey_bins(dataset)
    assert sorted(int(b[0]) for b in bins) == [0, 4]  # grey 4 in [0, 8), grey 100 in [60, 256)
    gts = [s.boxes for s in dataset.sequences]
    shifted = {s.name: s.boxes + [[3 if s.name == "lit" else 30, 0, 0, 0]] for s in dataset.sequences}
    exact = anatomy("exact", gts, gts, bins)
    loses = anatomy("loses_dark", gts, [shifted[s.name] for s in dataset.sequences], bins)
    assert exact.centred == 1.0 and exact.iou_centred == pytest.approx(1.0)
    assert loses.centred == 0.5  # the dark sequence's frames 2-4 are off by 3 target sizes
    assert loses.iou_centred == pytest.approx(7 / 13)  # 7x10 overlap, 130 union
    assert loses.centred_by_grey[0] == 0.0 and loses.centred_by_grey[4] == 1.0
    assert all(math.isnan(v) for v in loses.centred_by_grey[1:4])


def test_cli_prints_one_row_per_tracker_and_names_a_missing_result(bench, capsys):
    assert main(["anatomy", "--dataset", str(bench / "set"), str(bench / "res")]) == 0
    out = capsys.readouterr().out.splitlines()
    rows = {line.split()[0]: line.split()[1:] for line in out[3:]}
    assert rows["exact"][:3] == ["1.000", "1.000", "1.000"]
    assert rows["loses_dark"][:3] == ["0.500", "0.538", "0.000"]
    assert rows["exact"][3:6] == ["-", "-", "-"]  # grey bins without a frame: a dash, not nan
    (bench / "res" / "exact" / "dark.txt").unlink()
    assert main(["anatomy", "--dataset", str(bench / "set"), str(bench / "res" / "exact")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no results for 1 of 2 sequences" in err[0] and "dark" in err[0]


def write_states(folder: Path, states: dict[str, list[str]]) -> None:
    for name, told in states.items():
        (folder / f"{name}.states").write_text("1,init\n" + "".join(f"0.5,{s}\n" for s in told))


def test_reported_state_against_the_truth(bench, capsys):
    """The second table appears only where every sequence has its states, and counts frames 2..N."""
    folder = bench / "res" / "loses_dark"
    write_states(folder, {"lit": ["tracking"] * 3, "dark": ["tracking", "lost", "uncertain"]})
    assert main(["anatomy", "--dataset", str(bench / "set"), str(bench / "res")]) == 0
    out = capsys.readouterr().out.splitlines()
    title = out.index(next(line for line in out if line.startswith("reported state against the truth")))
    rows = {line.split()[0]: line.split()[1:] for line in out[title + 2:]}
    assert list(rows) == ["loses_dark"]  # 'exact' has no .states files: no row
    # 4 of 6 frames tracking; 1 of those off (dark); 2 of the 3 off frames flagged; no centred frame flagged
    assert rows["loses_dark"] == ["0.667", "0.250", "0.667", "0.000"]
    (folder / "dark.states").write_text("1,init\n0.5,tracking\n")
    assert main(["anatomy", "--dataset", str(bench / "set"), str(folder)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "dark.states" in err[0] and "2 states" in err[0]


def test_nan_and_inf_true_boxes_are_skipped_not_a_crash(bench, capsys):
    """UAV123 marks a target out of view with a NaN row: int() of it (or of inf) stopped the run."""
    truth = bench / "set" / "lit" / "groundtruth_rect.txt"
    x, y, w, h = BOX
    truth.write_text(f"{x},{y},{w},{h}\nNaN,NaN,NaN,NaN\ninf,{y},{w},{h}\n{x},{y},{w},{h}\n")
    assert main(["anatomy", "--dataset", str(bench / "set"), str(bench / "res" / "exact")]) == 0
    out = capsys.readouterr().out.splitlines()
    assert "4 frames after the first" in out[0]  # 3 of dark, 1 of lit: the two unknown boxes left out
    assert out[3].split()[:3] == ["exact", "1.000", "1.000"]


@pytest.mark.parametrize("line", ["bogus", "x", ",", "0.5,sleeping", "0.5, tracking"])
def test_a_malformed_states_line_is_one_line_naming_the_file_and_line(bench, capsys, line):
    folder = bench / "res" / "exact"
    write_states(folder, {"lit": ["tracking"] * 3, "dark": ["tracking"] * 3})
    (folder / "dark.states").write_text(f"1,init\n0.5,tracking\n{line}\n0.5,lost\n")
    assert main(["anatomy", "--dataset", str(bench / "set"), str(folder)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "dark.states: line 3" in err[0] and repr(line) in err[0], err


def test_sequences_of_one_frame_are_refused_not_a_table_of_nan(bench, capsys):
    for name in ("lit", "dark"):
        truth = bench / "set" / name / "groundtruth_rect.txt"
        truth.write_text(truth.read_text().splitlines()[0] + "\n")
        for frame in sorted((bench / "set" / name / "img").iterdir())[1:]:
            frame.unlink()
    assert main(["anatomy", "--dataset", str(bench / "set"), str(bench / "res" / "exact")]) == 2
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert not captured.out and len(err) == 1 and "no frames after the first" in err[0], err
