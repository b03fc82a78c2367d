"""Dataset layouts: one small folder per supported format, attributes, separators, and clear errors."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from dadiff.runtime.datamaking.datasets import DatasetError, load_dataset, parse_attributes, read_boxes


def _frames(folder: Path, n: int, pattern: str = "{:04d}.jpg") -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        cv2.imwrite(str(folder / pattern.format(i + 1)), np.full((8, 8, 3), 40 * i, np.uint8))


def test_read_boxes_accepts_comma_tab_space_and_nan(tmp_path):
    path = tmp_path / "gt.txt"
    path.write_text("1,2,3,4\n5\t6\t7\t8\n9 10  11 12\nNaN,NaN,NaN,NaN\n\n")
    boxes = read_boxes(path)
    assert boxes.shape == (4, 4)
    assert boxes[:3].tolist() == [[1, 2, 3, 4], [5, 6, 7, 8], [9, 10, 11, 12]]
    assert all(math.isnan(v) for v in boxes[3])


def test_read_boxes_names_the_bad_line(tmp_path):
    path = tmp_path / "gt.txt"
    path.write_text("1,2,3,4\n1,2,3\n")
    with pytest.raises(DatasetError, match=r"gt.txt:2: expected 4 numbers"):
        read_boxes(path)


def test_official_layout_with_nut_lr_attribute_flags(tmp_path):
    root = tmp_path / "NUT-LR"
    for name in ("car1", "bike2"):
        _frames(root / "data_seq" / name, 3)
        (root / "anno" / f"{name}.txt").parent.mkdir(parents=True, exist_ok=True)
        (root / "anno" / f"{name}.txt").write_text("1,2,3,4\n1,2,3,4\n1,2,3,4\n")
    (root / "att").mkdir()
    # NUT-LR order: ARC, BC, CM, FM, OCC, SV, SOB, VC, IV, LAI
    (root / "att" / "car1.txt").write_text("1,0,0,0,1,0,0,0,0,1\n")
    dataset = load_dataset(root)
    assert (dataset.name, dataset.layout) == ("NUT-LR", "official")
    assert [s.name for s in dataset.sequences] == ["bike2", "car1"]
    assert dataset.sequences[1].attributes == ("ARC", "OCC", "LAI")
    assert dataset.sequences[0].attributes == ()
    assert len(dataset.sequences[1]) == 3 and dataset.sequences[1].frames[0].name == "0001.jpg"


def test_official_layout_missing_annotation(tmp_path):
    root = tmp_path / "UAVDark70"
    _frames(root / "data_seq" / "car1", 2)
    (root / "anno").mkdir()
    with pytest.raises(DatasetError, match=r"car1.txt: missing annotation"):
        load_dataset(root)


def test_otb_layout_with_two_targets_and_attributes_json(tmp_path):
    root = tmp_path / "OTB"
    _frames(root / "Basketball" / "img", 2)
    (root / "Basketball" / "groundtruth_rect.txt").write_text("1\t2\t3\t4\n5\t6\t7\t8\n")
    _frames(root / "Jogging" / "img", 2)
    (root / "Jogging" / "groundtruth_rect.1.txt").write_text("1,1,2,2\n1,1,2,2\n")
    (root / "Jogging" / "groundtruth_rect.2.txt").write_text("3,3,2,2\n3,3,2,2\n")
    (root / "attributes.json").write_text(json.dumps({"Jogging-2": ["OCC", "SV"]}))
    dataset = load_dataset(root)
    assert dataset.layout == "otb"
    assert [s.name for s in dataset.sequences] == ["Basketball", "Jogging-1", "Jogging-2"]
    assert dataset.sequences[2].boxes[0].tolist() == [3, 3, 2, 2]
    assert dataset.attributes() == ["OCC", "SV"]
    assert [s.name for s in dataset.select(["Jog*"]).sequences] == ["Jogging-1", "Jogging-2"]
    with pytest.raises(DatasetError, match="no sequence matches"):
        dataset.select(["nothing*"])


def test_got10k_layout_follows_list_txt(tmp_path):
    root = tmp_path / "val"
    for name in ("GOT-10k_Val_000002", "GOT-10k_Val_000001"):
        _frames(root / name, 2, "{:08d}.jpg")
        (root / name / "groundtruth.txt").write_text("1,2,3,4\n2,3,4,5\n")
    (root / "list.txt").write_text("GOT-10k_Val_000002\nGOT-10k_Val_000001\n")
    dataset = load_dataset(root)
    assert dataset.layout == "got10k"
    assert [s.name for s in dataset.sequences] == ["GOT-10k_Val_000002", "GOT-10k_Val_000001"]


def test_pysot_json_layout(tmp_path):
    root = tmp_path / "UAV123"
    _frames(root / "bike1", 2, "{:06d}.jpg")
    meta = {
        "bike1": {
            "video_dir": "bike1",
            "init_rect": [1, 2, 3, 4],
            "img_names": ["bike1/000001.jpg", "bike1/000002.jpg"],
            "gt_rect": [[1, 2, 3, 4], [None, None, None, None]],
            "attr": ["Scale Variation", "Low Resolution"],
        }
    }
    (root / "UAV123.json").write_text(json.dumps(meta))
    for path in (root, root / "UAV123.json"):
        dataset = load_dataset(path)
        assert (dataset.name, dataset.layout) == ("UAV123", "json")
        seq = dataset.sequences[0]
        assert seq.attributes == ("Scale Variation", "Low Resolution")
        assert seq.frames[1] == root / "bike1" / "000002.jpg"
        assert math.isnan(seq.boxes[1, 0])


def test_frame_and_box_count_mismatch_is_refused_not_trimmed(tmp_path):
    """Trimming to the shorter side (with a warning) paired OTB's later-starting labels with the first frames;
    test_dataset_layouts.py has the cases and the messages."""
    root = tmp_path / "OTB"
    _frames(root / "Car" / "img", 3)
    (root / "Car" / "groundtruth_rect.txt").write_text("1,2,3,4\n1,2,3,4\n\n")
    with pytest.raises(DatasetError, match=r"OTB: no sequence to score; left out 1 sequence whose boxes do not fit "
                                           r"their frames: Car \(2 boxes for 3 frames\)"):
        load_dataset(root)


def test_a_pysot_json_sequence_whose_rows_do_not_fit_is_left_out(tmp_path, capsys):
    """The json layout refused the whole file for one sequence's img_names / gt_rect mismatch."""
    root = tmp_path / "J"
    _frames(root / "a", 2)
    meta = {"a": {"img_names": ["a/0001.jpg", "a/0002.jpg"], "gt_rect": [[1, 2, 3, 4]] * 2},
            "b": {"img_names": ["a/0001.jpg", "a/0002.jpg"], "gt_rect": [[1, 2, 3, 4]] * 3}}
    (root / "J.json").write_text(json.dumps(meta))
    assert [s.name for s in load_dataset(root).sequences] == ["a"]
    assert capsys.readouterr().err.strip() == (
        "dadiff-eval: warning: J: left out 1 sequence whose boxes do not fit their frames: b (2 img_names for "
        f"3 gt_rect rows); give one img_name per gt_rect row in {root / 'J.json'}")


def test_unknown_layout_names_what_was_expected(tmp_path):
    (tmp_path / "stuff" / "x").mkdir(parents=True)
    with pytest.raises(DatasetError, match=r"unknown dataset layout; expected data_seq/ \+ anno/"):
        load_dataset(tmp_path / "stuff")
    with pytest.raises(DatasetError, match="no such dataset folder"):
        load_dataset(tmp_path / "missing")


def test_attribute_flags_of_unknown_length():
    assert parse_attributes("SV, OCC LR", "x") == ("SV", "OCC", "LR")
    assert parse_attributes("1 0 1 0 0 0 0 0 0 0 0 1", "x") == ("SV", "LR", "SOB")
    with pytest.raises(DatasetError, match="3 attribute flags"):
        parse_attributes("1,0,1", "x")


def test_deeply_nested_json_is_a_dataset_error_not_a_recursion_traceback(tmp_path):
    deep = "[" * 100000 + "]" * 100000  # json's decoder recurses per level
    (tmp_path / "deep.json").write_text(deep)
    with pytest.raises(DatasetError, match="deep.json: not a pysot-toolkit JSON file \\(nested too deeply\\)"):
        load_dataset(tmp_path / "deep.json")
    root = tmp_path / "OTB"
    _frames(root / "Basketball" / "img", 1)
    (root / "Basketball" / "groundtruth_rect.txt").write_text("1,2,3,4\n")
    (root / "attributes.json").write_text(deep)
    with pytest.raises(DatasetError, match="attributes.json: expected a JSON object"):
        load_dataset(root)
