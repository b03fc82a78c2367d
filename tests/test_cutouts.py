"""Target cut-outs from labelled frames (`dadiff-eval cutouts`) and their use as library scene targets."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from dadiff.runtime.commands.eval import main
from dadiff.runtime.datamaking import library_scenes
from dadiff.runtime.datamaking.cutouts import CutoutTargets, CutSettings, cut_out, cutout_images, write_cutouts
from dadiff.runtime.datamaking.datasets import load_dataset
from dadiff.runtime.datamaking.library import LibraryError, LibraryImage, split_of
from dadiff.runtime.datamaking.scenes import write_benchmark, write_boxes, write_frame


def _background(h: int, w: int, seed: int) -> np.ndarray:
    """A smooth colour texture (paving, grass): GrabCut has a background model to learn."""
    rng = np.random.default_rng(seed)
    small = rng.integers(60, 200, size=(h // 16 + 1, w // 16 + 1, 3)).astype(np.uint8)
    return cv2.GaussianBlur(cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR), (0, 0), 3)


def _person_mask(h: int, w: int, x: int, y: int, scale: float = 1.0) -> np.ndarray:
    """An upright walker's silhouette (head, body, two legs) with its top-left corner near (x, y)."""
    mask = np.zeros((h, w), np.uint8)
    s = scale
    cv2.ellipse(mask, (int(x + 20 * s), int(y + 12 * s)), (int(8 * s), int(10 * s)), 0, 0, 360, 255, -1)
    cv2.ellipse(mask, (int(x + 20 * s), int(y + 45 * s)), (int(16 * s), int(25 * s)), 0, 0, 360, 255, -1)
    cv2.rectangle(mask, (int(x + 10 * s), int(y + 60 * s)), (int(x + 17 * s), int(y + 100 * s)), 255, -1)
    cv2.rectangle(mask, (int(x + 23 * s), int(y + 60 * s)), (int(x + 30 * s), int(y + 100 * s)), 255, -1)
    return mask


def _scene(seed: int, x: int = 120, y: int = 50) -> tuple[np.ndarray, np.ndarray, tuple[float, ...]]:
    frame = _background(240, 320, seed)
    mask = _person_mask(240, 320, x, y)
    frame[mask > 0] = (30, 25, 90)  # a dark red coat
    ys, xs = np.nonzero(mask)
    box = (float(xs.min()), float(ys.min()), float(xs.max() - xs.min() + 1), float(ys.max() - ys.min() + 1))
    return frame, mask, box


def test_cut_out_separates_the_target_from_its_background():
    frame, mask, box = _scene(1)
    bgra, reason = cut_out(frame, box)
    assert reason == "" and bgra is not None and bgra.shape[2] == 4
    x, y, w, h = (int(v) for v in box)
    assert abs(bgra.shape[1] - w) <= 3 and abs(bgra.shape[0] - h) <= 3
    truth = mask[y:y + h, x:x + w] > 0
    got = np.zeros_like(truth)
    got[: bgra.shape[0], : bgra.shape[1]] = bgra[: truth.shape[0], : truth.shape[1], 3] > 127
    assert (truth & got).sum() / (truth | got).sum() > 0.85
    assert np.abs(bgra[..., :3][bgra[..., 3] == 255].astype(int) - (30, 25, 90)).max() <= 2  # the coat, not ground


def test_cut_out_refuses_what_is_not_one_whole_target():
    frame, _, box = _scene(2)
    assert cut_out(frame, (0.0, 10.0, 40.0, 100.0)) == (None, "box at the frame's edge")
    assert cut_out(_background(240, 320, 3), box) == (None, "nothing separated")  # ground only
    x, y, w, h = box
    assert cut_out(frame, (x - 30, y, w + 60, h)) == (None, "fills too little of the box")  # a loose box
    cut = frame.copy()
    band = slice(int(y + h / 2), int(y + h / 2) + 3)
    cut[band] = _background(240, 320, 2)[band]  # a thin occluder across the waist
    assert cut_out(cut, box) == (None, "only part of the target")


def _dataset(root: Path, sequences: int = 3, frames: int = 9) -> Path:
    for k in range(sequences):
        folder = root / f"vid{k + 1:03d}_day"
        (folder / "img").mkdir(parents=True)
        boxes = []
        for i in range(frames):
            frame, _, box = _scene(10 * k + i, x=60 + 8 * i, y=40 + 3 * k)
            write_frame(folder / "img", i, frame)
            boxes.append(box)
        write_boxes(folder / "groundtruth_rect.txt", np.array(boxes))
    return root


def test_cutouts_are_written_indexed_and_read_back_as_library_targets(tmp_path):
    dataset = load_dataset(_dataset(tmp_path / "film"))
    index = write_cutouts(dataset, tmp_path / "cuts", "public domain", CutSettings(every=4, min_height=48), log=print)
    assert index["licence"] == "public domain" and len(index["cutouts"]) == 9  # frames 0, 4, 8 of 3 sequences
    for item in index["cutouts"]:
        assert item["split"] == split_of("cutouts:film", item["sequence"])  # by sequence: a person in one split
        assert (tmp_path / "cuts" / item["file"]).is_file()
    by_split = {s: cutout_images(tmp_path / "cuts", s) for s in {i["split"] for i in index["cutouts"]}}
    image = next(iter(by_split.values()))[0]
    assert image.role == "target" and image.licence == "public domain"
    pixels = image.load()
    assert pixels.shape == (image.height, image.width, 4) and pixels[..., 3].max() == 255
    assert sum(len(v) for v in by_split.values()) == 9
    again = write_cutouts(dataset, tmp_path / "cuts", "public domain", CutSettings(every=4), log=print)
    assert again["cutouts"] == index["cutouts"]  # deterministic, and an earlier cut-out folder is rewritten
    fewer = write_cutouts(dataset, tmp_path / "cuts", "public domain", CutSettings(every=8), log=print)
    assert len(fewer["cutouts"]) == 6  # frames 0 and 8: the earlier run's other cut-outs are gone
    assert sorted(p.name for p in (tmp_path / "cuts").glob("*.png")) == sorted(i["file"] for i in fewer["cutouts"])


def test_cutout_folders_that_cannot_be_used_are_one_clear_error(tmp_path):
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    dataset = load_dataset(_dataset(tmp_path / "film", sequences=1, frames=1))
    with pytest.raises(LibraryError, match="not empty and holds no cut-out index"):
        write_cutouts(dataset, tmp_path / "other", "x")
    with pytest.raises(LibraryError, match="no cut-out index here"):
        cutout_images(tmp_path / "other", "train")
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "index.json").write_text(json.dumps({"cutouts": [{"file": "a.png"}]}))
    with pytest.raises(LibraryError, match="not a valid cut-out index"):
        cutout_images(tmp_path / "bad", "train")
    write_cutouts(dataset, tmp_path / "cuts", "x", CutSettings(every=1))
    split = json.loads((tmp_path / "cuts" / "index.json").read_text())["cutouts"][0]["split"]
    other = "test" if split == "train" else "train"
    with pytest.raises(LibraryError, match=f"no cut-outs in split '{other}'"):
        cutout_images(tmp_path / "cuts", other)


class _Backgrounds:
    def images(self, role: str, split: str) -> list[str]:
        return [f"{role}/{split}"]

    def licences(self) -> dict[str, str]:
        return {"photos": "CC0"}


def test_cutout_targets_replace_the_library_targets_and_keep_its_backgrounds(tmp_path):
    write_cutouts(load_dataset(_dataset(tmp_path / "film", sequences=2, frames=1)), tmp_path / "cuts", "x",
                  CutSettings(every=1))
    library = CutoutTargets(_Backgrounds(), tmp_path / "cuts")
    splits = {i["split"] for i in json.loads((tmp_path / "cuts" / "index.json").read_text())["cutouts"]}
    split = sorted(splits)[0]
    assert library.images("background", split) == [f"background/{split}"]
    assert all(i.package == "cutouts:cuts" for i in library.images("target", split))
    assert library.licences() == {"photos": "CC0"}


class _PhotoLibrary:
    """Two texture photos per split as the library's backgrounds (real files, as the cache holds them)."""

    def __init__(self, folder: Path) -> None:
        folder.mkdir()
        self.backgrounds = {}
        for split in ("train", "test"):
            images = []
            for k in range(2):
                path = folder / f"{split}{k}.jpg"
                cv2.imwrite(str(path), _background(480, 640, 100 + k))
                images.append(LibraryImage(path, "photos", path.name, "background", split, "CC0", 640, 480))
            self.backgrounds[split] = images

    def images(self, role: str, split: str) -> list[LibraryImage]:
        return list(self.backgrounds[split]) if role == "background" else []


def test_a_benchmark_over_cutouts_shows_them_and_says_so(tmp_path, monkeypatch):
    monkeypatch.setattr(library_scenes, "_LIBRARY_CACHE", {})  # what this test's scenes load, nothing else
    write_cutouts(load_dataset(_dataset(tmp_path / "film", sequences=7, frames=1)), tmp_path / "cuts", "x",
                  CutSettings(every=1))
    splits = {i["split"] for i in json.loads((tmp_path / "cuts" / "index.json").read_text())["cutouts"]}
    assert splits == {"train", "test"}  # seven sequences: the stable hash puts vid007 in the test split
    library = CutoutTargets(_PhotoLibrary(tmp_path / "photos"), tmp_path / "cuts")
    root = write_benchmark(tmp_path / "bench", sequences=2, frames=2, seed=3, size=(320, 240), workers=1,
                           source="library", library=library)
    info = json.loads((root / "benchmark.json").read_text())
    assert info["cutouts"] == str((tmp_path / "cuts").resolve()) and info["split"] == "test"
    loaded = {key[3] for key in library_scenes._LIBRARY_CACHE if key[0] == "target"}
    assert loaded and loaded <= {i.source for i in cutout_images(tmp_path / "cuts", "test")}


def _one_error_line(capsys) -> str:
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1, lines
    return lines[0]


def test_cli_cuts_a_dataset_and_refuses_bad_input_in_one_line(tmp_path, capsys):
    root = _dataset(tmp_path / "film", sequences=2, frames=5)
    assert main(["cutouts", "--dataset", str(root), "--output", str(tmp_path / "cuts"), "--licence", "CC0",
                 "--every", "2"]) == 0
    assert "wrote 6 cut-outs" in capsys.readouterr().out
    assert main(["cutouts", "--dataset", str(tmp_path / "none"), "-o", str(tmp_path / "c2"), "--licence", "x"]) == 2
    assert "no such dataset folder" in _one_error_line(capsys)
    assert main(["cutouts", "--dataset", str(root), "--output", str(tmp_path / "c3"), "--licence", "x",
                 "--min-height", "0"]) == 2
    assert "--min-height 0" in _one_error_line(capsys)
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x.txt").write_text("x")
    assert main(["cutouts", "--dataset", str(root), "--output", str(tmp_path / "full"), "--licence", "x"]) == 2
    assert "holds no cut-out index" in _one_error_line(capsys)
    assert main(["generate", "--output", str(tmp_path / "g"), "--cutouts", str(tmp_path / "cuts")]) == 2
    assert "--cutouts needs --source library" in _one_error_line(capsys)


def test_training_scenes_take_cutouts_only_over_the_library():
    pytest.importorskip("torch")
    from dadiff.export.train_data import make_day_source

    with pytest.raises(ValueError, match="cutouts is 'people'; it needs source"):
        make_day_source({"kind": "scenes", "split": "train", "cutouts": "people"})
