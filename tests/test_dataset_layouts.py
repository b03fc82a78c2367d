"""Dataset layouts as downloaded, from a walkthrough with tiny fake datasets: frame order, one box line per
frame, GOT-10k's test split, skipped OTB folders, attribute files, UAV123's nested layout, and the messages."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from dadiff.runtime.commands.eval import main
from dadiff.runtime.datamaking.datasets import DatasetError, load_dataset, read_frame
from dadiff.runtime.sources import image_files


def _frames(folder: Path, n: int, pattern: str = "{:04d}.jpg") -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        cv2.imwrite(str(folder / pattern.format(i + 1)), np.full((8, 8, 3), 20 * i, np.uint8))


def _boxes(n: int, shift: int = 0) -> str:
    return "".join(f"{1 + i + shift},2,3,4\n" for i in range(n))


def _otb(root: Path, name: str, frames: int = 3, lines: int | None = None, pattern: str = "{:04d}.jpg") -> Path:
    _frames(root / name / "img", frames, pattern)
    (root / name / "groundtruth_rect.txt").write_text(_boxes(frames if lines is None else lines))
    return root / name


def _perfect_results(dataset_path: Path, folder: Path) -> None:
    folder.mkdir(parents=True)
    for seq in load_dataset(dataset_path).sequences:
        np.savetxt(folder / f"{seq.name}.txt", seq.boxes, delimiter=",")


def _error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith("dadiff-eval: error: ")
    return err[0]


# 1. frame order


def test_frames_without_leading_zeros_are_in_number_order_as_dadiff_run_reads_them(tmp_path):
    """1.jpg ... 11.jpg were sorted as text (1, 10, 11, 2, ...) and scored against other frames' boxes."""
    seq = _otb(tmp_path / "unpadded", "seqA", frames=11, pattern="{}.jpg")
    frames = load_dataset(tmp_path / "unpadded").sequences[0].frames
    assert [p.name for p in frames] == [f"{i}.jpg" for i in range(1, 12)]
    assert list(frames) == image_files(seq)  # dadiff-run's own listing


# 2. one box line per frame


@pytest.mark.parametrize(("lines", "expected"), [
    (2, "David (2 boxes for 3 frames); remove the unlabelled frames or give a pysot .json whose img_names list them"),
    (5, "David (5 boxes for 3 frames, a frame missing); restore the missing frames"),
])
def test_box_and_frame_counts_must_agree(tmp_path, capsys, lines, expected):
    """Fewer or more lines than frames used to be trimmed with a warning and scored: boxes on the wrong frames.
    Such a sequence is left out; only a dataset with none left is refused."""
    root = tmp_path / "OTB"
    _otb(root, "David", frames=3, lines=lines)
    with pytest.raises(DatasetError) as info:
        load_dataset(root)
    assert str(info.value) == (f"{root}: no sequence to score; left out 1 sequence whose boxes do not fit their "
                               f"frames: {expected}")
    assert main(["score", "--dataset", str(root), str(tmp_path)]) == 2
    assert _error_line(capsys) == f"dadiff-eval: error: {info.value}"
    _otb(root, "Basketball")
    assert [s.name for s in load_dataset(root).sequences] == ["Basketball"]
    assert capsys.readouterr().err.strip().splitlines() == [
        f"dadiff-eval: warning: OTB: left out 1 sequence whose boxes do not fit their frames: {expected}"]


def test_otb100_as_downloaded_loads_without_its_misfits(tmp_path, capsys):
    """One bad sequence refused the whole dataset, and --sequences (applied after loading) could not leave it
    out: OTB100 as downloaded could not be loaded at all."""
    root = tmp_path / "OTB100"
    _otb(root, "Basketball", frames=4)
    _otb(root, "David", frames=7, lines=4)
    _otb(root, "Diving", frames=5, lines=4)
    _perfect_results(root, tmp_path / "res" / "T")
    capsys.readouterr()
    assert main(["score", "--dataset", str(root), "--sequences", "Basketball", "--json", str(tmp_path / "res")]) == 0
    captured = capsys.readouterr()
    assert list(json.loads(captured.out)) == ["T"]  # stdout stays one JSON document
    assert captured.err.strip().splitlines() == [
        "dadiff-eval: warning: OTB100: left out 2 sequences whose boxes do not fit their frames: David (4 boxes for "
        "7 frames), Diving (4 boxes for 5 frames); remove the unlabelled frames or give a pysot .json whose "
        "img_names list them"]


def test_trailing_blank_lines_and_a_byte_order_mark_are_not_boxes(tmp_path):
    """A BOM was read as part of the first number ('\\ufeff1,2,3,4' refused); blank lines are not frames."""
    seq = _otb(tmp_path / "OTB", "a", frames=3)
    (seq / "groundtruth_rect.txt").write_text("\ufeff" + _boxes(3) + "\n\n", encoding="utf-8")
    boxes = load_dataset(tmp_path / "OTB").sequences[0].boxes
    assert boxes.tolist() == [[1, 2, 3, 4], [2, 2, 3, 4], [3, 2, 3, 4]]


# 3. GOT-10k's test split


def test_got10k_test_split_with_only_the_first_box_is_refused(tmp_path, capsys):
    """It used to track nothing ('0 frames') and print a success of 0.905 from the first frames alone."""
    root = tmp_path / "test"
    for name in ("GOT-10k_Test_000001", "GOT-10k_Test_000002"):
        _frames(root / name, 6, "{:08d}.jpg")
        (root / name / "groundtruth.txt").write_text("1,2,3,4\n")
    (root / "list.txt").write_text("GOT-10k_Test_000001\nGOT-10k_Test_000002\n")
    assert main(["score", "--dataset", str(root), str(tmp_path)]) == 2
    assert _error_line(capsys) == (
        f"dadiff-eval: error: {root}: no sequence to score; left out 2 sequences whose boxes do not fit their "
        "frames: GOT-10k_Test_000001 (only the first of 6 frames labelled), GOT-10k_Test_000002 (only the first "
        "of 6 frames labelled); nothing to score there (GOT-10k's test split is scored by its evaluation server)")


# 4. OTB folders without groundtruth_rect.txt


def test_otb_folders_with_another_truth_file_are_named_in_one_warning(tmp_path, capsys):
    """A folder with groundtruth.txt instead of groundtruth_rect.txt was dropped silently."""
    root = tmp_path / "OTB"
    _otb(root, "a")
    _frames(root / "b" / "img", 3)
    (root / "b" / "groundtruth.txt").write_text(_boxes(3))
    _frames(root / "c" / "img", 3)  # frames and no truth file at all
    _frames(root / "Jogging" / "img", 3)  # two targets, no groundtruth_rect.txt: not skipped
    (root / "Jogging" / "groundtruth_rect.1.txt").write_text(_boxes(3))
    (root / "Jogging" / "groundtruth_rect.2.txt").write_text(_boxes(3, 5))
    _frames(root / "plots", 2, "plot{}.png")  # not sequence folders: not reported
    (root / "results").mkdir()
    (root / "results" / "a.txt").write_text(_boxes(3))
    dataset = load_dataset(root)
    assert [s.name for s in dataset.sequences] == ["Jogging-1", "Jogging-2", "a"]
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"dadiff-eval: warning: {root}: skipped 2 sequence folders without groundtruth_rect.txt: "
                   "b (has groundtruth.txt), c (no ground truth)"]


def test_otb_sequence_with_frames_beside_its_truth_file_and_a_root_without_any(tmp_path):
    """A folder of frames (no img/) beside groundtruth_rect.txt is a sequence, as dadiff-run reads it; a root
    where no folder has groundtruth_rect.txt is refused (layout), not an empty dataset."""
    root = tmp_path / "OTB"
    _otb(root, "a")
    (root / "a" / "groundtruth_rect.txt").rename(root / "a" / "groundtruth_rect.txt.txt")
    (root / "b").mkdir()
    (root / "b" / "groundtruth_rect.txt").write_text(_boxes(3))
    _frames(root / "b", 3)  # frames beside the truth file, no img/: a sequence too (as dadiff-run reads it)
    assert [s.name for s in load_dataset(root).sequences] == ["b"]
    (root / "b" / "groundtruth_rect.txt").unlink()
    (root / "b" / "gt.txt").write_text(_boxes(3))
    with pytest.raises(DatasetError, match=r"OTB: unknown dataset layout"):
        load_dataset(root)


# 5. attribute files beside OTB-style sequences; --attributes without any


def test_att_files_beside_otb_sequences(tmp_path):
    """docs/datasets.md: attributes come from att/<seq>.txt; it was read only in the data_seq/ + anno/ layout."""
    root = tmp_path / "UAV123"
    _otb(root, "bike1")
    _otb(root, "car1")
    (root / "att").mkdir()
    (root / "att" / "bike1.txt").write_text("1,0,0,0,0,0,0,0,0,0,0,1\n")  # UAV123's twelve flags
    (root / "att" / "car1.txt").write_text("FM POC\n")
    dataset = load_dataset(root)
    assert [s.attributes for s in dataset.sequences] == [("SV", "SOB"), ("FM", "POC")]


def test_attributes_option_without_attributes_says_so(tmp_path, capsys):
    _otb(tmp_path / "OTB", "a")
    _perfect_results(tmp_path / "OTB", tmp_path / "res" / "T")
    assert main(["score", "--dataset", str(tmp_path / "OTB"), "--attributes", str(tmp_path / "res")]) == 0
    captured = capsys.readouterr()
    assert captured.err.strip().splitlines() == [
        "dadiff-eval: note: --attributes: no sequence of OTB has attributes (attributes.json, att/<seq>.txt or a "
        "pysot .json's attr); overall scores only"]
    assert "OTB: 1 sequence" in captured.out


# 6. UAV123 as downloaded; folders that hold datasets


def _uav123_download(tmp_path: Path) -> Path:
    root = tmp_path / "Dataset_UAV123" / "UAV123"
    for seq in ("bike1", "car1"):
        _frames(root / "data_seq" / "UAV123" / seq, 3, "{:06d}.jpg")
    for name, seqs in (("UAV123", ("bike1", "car1")), ("UAV20L", ("car1",))):
        (root / "anno" / name / "att").mkdir(parents=True)
        for seq in seqs:
            (root / "anno" / name / f"{seq}.txt").write_text(_boxes(3))
            (root / "anno" / name / "att" / f"{seq}.txt").write_text("1,0,0,1,0,0,0,0,0,0,0,0\n")
    return root


def test_uav123_as_downloaded_with_uav20l_over_the_same_frames(tmp_path):
    root = _uav123_download(tmp_path)
    dataset = load_dataset(root)
    assert (dataset.name, dataset.layout) == ("UAV123", "official")
    assert [s.name for s in dataset.sequences] == ["bike1", "car1"]
    assert dataset.sequences[0].frames[0] == root / "data_seq" / "UAV123" / "bike1" / "000001.jpg"
    assert dataset.sequences[0].attributes == ("SV", "FM")
    long = load_dataset(root / "anno" / "UAV20L")
    assert (long.name, [s.name for s in long.sequences]) == ("UAV20L", ["car1"])
    assert long.sequences[0].frames[2] == root / "data_seq" / "UAV123" / "car1" / "000003.jpg"


def test_uav123_parts_of_one_clip_are_left_out_with_the_way_out(tmp_path, capsys):
    """bird1_1, bird1_2 are frame ranges of data_seq/UAV123/bird1 that the download does not record: left out,
    named, and the unsplit sequences load (the parts used to refuse the whole of UAV123)."""
    root = _uav123_download(tmp_path)
    (root / "anno" / "UAV123" / "car1.txt").rename(root / "anno" / "UAV123" / "car1_1.txt")
    (root / "anno" / "UAV123" / "car1_2.txt").write_text(_boxes(2))
    assert [s.name for s in load_dataset(root).sequences] == ["bike1"]
    why = "a part of car1 whose frame range is not in the download"
    assert capsys.readouterr().err.strip().splitlines() == [
        f"dadiff-eval: warning: UAV123: left out 2 sequences whose boxes do not fit their frames: car1_1 ({why}), "
        f"car1_2 ({why}); give a pysot-toolkit UAV123.json instead (its img_names list each part's frames, "
        "relative to the .json's folder)"]


def test_anno_with_several_datasets_and_no_name_match_asks_for_one(tmp_path):
    root = _uav123_download(tmp_path)
    renamed = root.parent / "UAV"
    root.rename(renamed)
    with pytest.raises(DatasetError, match=r"UAV: anno/ holds the boxes of 2 datasets; give one of: .*anno/UAV123, "
                                           r".*anno/UAV20L$"):
        load_dataset(renamed)


def test_a_folder_of_datasets_and_a_missing_anno_are_named(tmp_path, capsys):
    """Both were 'unknown dataset layout' with the list of every layout."""
    for name in ("NUT-LR", "UAVDark70"):
        _frames(tmp_path / "off" / name / "data_seq" / "car1", 2)
    assert main(["score", "--dataset", str(tmp_path / "off"), str(tmp_path)]) == 2
    assert _error_line(capsys).endswith(
        f"{tmp_path / 'off'}: a folder of datasets; give one of: {tmp_path / 'off' / 'NUT-LR'}, "
        f"{tmp_path / 'off' / 'UAVDark70'}")
    with pytest.raises(DatasetError, match=r"UAVDark70: data_seq/ but no anno/ folder"):
        load_dataset(tmp_path / "off" / "UAVDark70")


# 7. attribute values


def test_attribute_values_must_be_lists_of_names(tmp_path):
    """{"a": "SV"} was split letter by letter into the attributes S and V."""
    _otb(tmp_path / "OTB", "a")
    (tmp_path / "OTB" / "attributes.json").write_text('{"a": "SV"}')
    with pytest.raises(DatasetError, match=r"attributes.json: sequence 'a': expected a list of attribute names "
                                           r"such as \[\"SV\", \"OCC\"\], got \"SV\"$"):
        load_dataset(tmp_path / "OTB")
    (tmp_path / "OTB" / "attributes.json").write_text('{"a": ["SV", 3]}')
    with pytest.raises(DatasetError, match="sequence 'a': expected a list of attribute names"):
        load_dataset(tmp_path / "OTB")
    root = tmp_path / "json"
    _frames(root / "a", 1)
    meta = {"a": {"img_names": ["a/0001.jpg"], "gt_rect": [[1, 2, 3, 4]], "attr": "SV"}}
    (root / "json.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match="json.json: sequence 'a': expected a list of attribute names"):
        load_dataset(root)


# 8. missing frames of a .json


def test_a_missing_later_frame_of_a_json_is_not_found_before_tracking(tmp_path):
    """It was 'cannot read image' after tracking up to it, as if the file were damaged."""
    root = tmp_path / "UAVjson"
    _frames(root / "bike1", 2, "{:06d}.jpg")
    names = [f"bike1/{i + 1:06d}.jpg" for i in range(4)]
    (root / "UAVjson.json").write_text(json.dumps({"bike1": {"img_names": names, "gt_rect": [[1, 2, 3, 4]] * 4}}))
    with pytest.raises(DatasetError) as info:
        load_dataset(root)
    assert str(info.value) == f"{root / 'bike1' / '000003.jpg'}: frame 3 of bike1 not found (paths are relative " \
                              f"to {root})"
    with pytest.raises(DatasetError, match=r"000003.jpg: not found$"):
        read_frame(root / "bike1" / "000003.jpg")
    (root / "bike1" / "000002.jpg").write_bytes(b"not an image")
    with pytest.raises(DatasetError, match=r"000002.jpg: cannot read image$"):
        read_frame(root / "bike1" / "000002.jpg")


# 9. score --json --attributes


def test_score_json_carries_the_attribute_scores(tmp_path, capsys):
    """--json with --attributes printed the overall numbers only."""
    root = tmp_path / "OTB"
    _otb(root, "a")
    _otb(root, "b")
    (root / "attributes.json").write_text(json.dumps({"a": ["SV", "OCC"], "b": ["SV"]}))
    _perfect_results(root, tmp_path / "res" / "T")
    assert main(["score", "--dataset", str(root), "--json", "--attributes", str(tmp_path / "res")]) == 0
    table = json.loads(capsys.readouterr().out)
    assert set(table["T"]) == {"success", "norm_precision", "precision", "attributes"}
    assert set(table["T"]["attributes"]) == {"OCC", "SV"}
    assert table["T"]["attributes"]["SV"]["sequences"] == 2 and table["T"]["attributes"]["OCC"]["sequences"] == 1
    assert table["T"]["attributes"]["OCC"]["precision"] == 1.0
    assert main(["score", "--dataset", str(root), "--json", str(tmp_path / "res")]) == 0
    assert set(json.loads(capsys.readouterr().out)["T"]) == {"success", "norm_precision", "precision"}
