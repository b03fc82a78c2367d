"""Tracking datasets on disk: find the layout, list the sequences, read ground truth and attributes.

Layouts (`load_dataset(path)` tells them apart):

- official: `path/data_seq/<seq>/` frames + `path/anno/<seq>.txt` (UAVDark70, NUT-L, NUT-LR, NAT2021-test);
  optional attribute files `path/att/<seq>.txt` (or `attribute/`).
- otb: `path/<seq>/img/` frames + `path/<seq>/groundtruth_rect.txt` (OTB, UAV123, the generated night
  benchmark); OTB's two-target folders (`groundtruth_rect.1.txt`, `.2.txt`) become `<seq>-1`, `<seq>-2`.
- got10k: `path/<seq>/` frames + `path/<seq>/groundtruth.txt` (sequence order from `list.txt` if present).
- json: a pysot-toolkit file (`path` itself, or `path/<folder name>.json`): `{seq: {"img_names": [...],
  "gt_rect": [...], "attr": [...]}}`, image paths relative to the file's folder.

Any layout may carry `path/attributes.json` = `{seq: ["SV", "OCC", ...]}`. An attribute file holds names
(comma or space separated) or 0/1 flags in a known order (`ATTRIBUTE_ORDERS`). Boxes are x, y, w, h lines
separated by commas, tabs or spaces; NaN rows stay NaN (the metrics count them as the toolkit does).
"""

from __future__ import annotations

import fnmatch
import json
import re
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp")
NUT_LR_ATTRIBUTES = ("ARC", "BC", "CM", "FM", "OCC", "SV", "SOB", "VC", "IV", "LAI")
UAV123_ATTRIBUTES = ("SV", "ARC", "LR", "FM", "FOC", "POC", "OV", "BC", "IV", "VC", "CM", "SO")
ATTRIBUTE_ORDERS = {len(NUT_LR_ATTRIBUTES): NUT_LR_ATTRIBUTES, len(UAV123_ATTRIBUTES): UAV123_ATTRIBUTES}
EXPECTED_LAYOUTS = (
    "data_seq/ + anno/ (UAVDark70, NUT-L, NUT-LR, NAT2021), <seq>/img/ + <seq>/groundtruth_rect.txt "
    "(OTB, UAV123), <seq>/groundtruth.txt (GOT-10k), or a pysot-toolkit .json file"
)
_SPLIT = re.compile(r"[,\t ]+")


class DatasetError(Exception):
    """A dataset folder or file is missing, unreadable or not in a known layout (one-line message)."""


@dataclass(frozen=True)
class Sequence:
    """One sequence: frame paths in order, (N, 4) ground-truth boxes, attribute names."""

    name: str
    frames: tuple[Path, ...]
    boxes: np.ndarray
    attributes: tuple[str, ...] = ()

    def __len__(self) -> int:
        return len(self.boxes)


@dataclass(frozen=True)
class Dataset:
    """A named set of sequences; `name` is what result folders are filed under."""

    name: str
    path: Path
    layout: str
    sequences: tuple[Sequence, ...]

    def attributes(self) -> list[str]:
        """Attribute names that at least one sequence carries, sorted."""
        return sorted({a for s in self.sequences for a in s.attributes})

    def select(self, patterns: list[str] | None) -> Dataset:
        """Only the sequences whose name matches one of the glob `patterns` (all when None or empty)."""
        if not patterns:
            return self
        kept = tuple(s for s in self.sequences if any(fnmatch.fnmatchcase(s.name, p) for p in patterns))
        if not kept:
            raise DatasetError(f"{self.path}: no sequence matches {' '.join(patterns)}")
        return replace(self, sequences=kept)


def read_text(path: Path) -> str:
    """A dataset's text file; unreadable or not text (a damaged file) is one DatasetError naming it."""
    try:
        return Path(path).read_text()
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except UnicodeDecodeError:
        raise DatasetError(f"{path}: not a text file") from None


def read_boxes(path: Path) -> np.ndarray:
    """(N, 4) float64 boxes from a text file of x, y, w, h lines (comma, tab or space separated)."""
    text = read_text(path)
    rows = []
    for number, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line:
            continue
        parts = [p for p in _SPLIT.split(line) if p]
        try:
            values = [float(p) for p in parts]
        except ValueError:
            raise DatasetError(f"{path}:{number}: expected 4 numbers x,y,w,h, got {line!r}") from None
        if len(values) != 4:
            raise DatasetError(f"{path}:{number}: expected 4 numbers x,y,w,h, got {len(values)}")
        rows.append(values)
    if not rows:
        raise DatasetError(f"{path}: no boxes")
    return np.asarray(rows, dtype=np.float64)


def list_frames(folder: Path) -> tuple[Path, ...]:
    """Image files directly in `folder`, sorted by name."""
    frames = tuple(sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES))
    if not frames:
        raise DatasetError(f"{folder}: no image files")
    return frames


def parse_attributes(text: str, source: str) -> tuple[str, ...]:
    """Attribute names from a line of names or of 0/1 flags in one of the `ATTRIBUTE_ORDERS`."""
    parts = [p for p in _SPLIT.split(text.strip()) if p]
    if parts and all(p in ("0", "1") for p in parts):
        order = ATTRIBUTE_ORDERS.get(len(parts))
        if order is None:
            known = " or ".join(f"{n} ({', '.join(o)})" for n, o in ATTRIBUTE_ORDERS.items())
            raise DatasetError(f"{source}: {len(parts)} attribute flags; expected {known}")
        return tuple(name for name, flag in zip(order, parts, strict=True) if flag == "1")
    return tuple(parts)


def _warn(message: str) -> None:
    prog = Path(sys.argv[0]).name if Path(sys.argv[0]).name.startswith("dadiff-") else "dadiff-eval"
    print(f"{prog}: warning: {message}", file=sys.stderr)  # the commands' one style (eval, bench, export)


def _make_sequence(name: str, frames: tuple[Path, ...], boxes: np.ndarray, source: Path) -> Sequence:
    if len(frames) != len(boxes):
        _warn(f"{source}: {len(boxes)} boxes for {len(frames)} frames; using the first {min(len(frames), len(boxes))}")
        n = min(len(frames), len(boxes))
        frames, boxes = frames[:n], boxes[:n]
    return Sequence(name, frames, boxes)


def _official(path: Path) -> list[Sequence]:
    seq_root, anno = path / "data_seq", path / "anno"
    sequences = []
    for folder in sorted(p for p in seq_root.iterdir() if p.is_dir()):
        gt = anno / f"{folder.name}.txt"
        if not gt.is_file():
            raise DatasetError(f"{gt}: missing annotation for sequence {folder.name}")
        sequence = _make_sequence(folder.name, list_frames(folder), read_boxes(gt), gt)
        for att in (path / "att" / f"{folder.name}.txt", path / "attribute" / f"{folder.name}.txt"):
            if att.is_file():
                sequence = replace(sequence, attributes=parse_attributes(read_text(att), str(att)))
                break
        sequences.append(sequence)
    return sequences


def _otb(path: Path) -> list[Sequence]:
    sequences = []
    for folder in sorted(p for p in path.iterdir() if p.is_dir() and (p / "img").is_dir()):
        single = folder / "groundtruth_rect.txt"
        multi = sorted(folder.glob("groundtruth_rect.*.txt"))
        frames = list_frames(folder / "img")
        if single.is_file():
            sequences.append(_make_sequence(folder.name, frames, read_boxes(single), single))
        for gt in multi:
            target = gt.name.split(".")[1]
            sequences.append(_make_sequence(f"{folder.name}-{target}", frames, read_boxes(gt), gt))
    return sequences


def _got10k(path: Path) -> list[Sequence]:
    listed = path / "list.txt"
    if listed.is_file():
        names = [line.strip() for line in read_text(listed).splitlines() if line.strip()]
        folders = [path / n for n in names]
    else:
        folders = sorted(p for p in path.iterdir() if (p / "groundtruth.txt").is_file())
    sequences = []
    for folder in folders:
        gt = folder / "groundtruth.txt"
        if not gt.is_file():
            raise DatasetError(f"{gt}: missing (listed in {listed})")
        sequences.append(_make_sequence(folder.name, list_frames(folder), read_boxes(gt), gt))
    return sequences


def _json(file: Path) -> list[Sequence]:
    try:
        meta = json.loads(file.read_text())
    except (OSError, ValueError) as exc:
        raise DatasetError(f"{file}: not a readable pysot-toolkit JSON file ({exc})") from None
    except RecursionError:  # json's decoder recurses per level: '[' * 100000 was a traceback
        raise DatasetError(f"{file}: not a pysot-toolkit JSON file (nested too deeply)") from None
    if not isinstance(meta, dict):
        raise DatasetError(f"{file}: expected a JSON object {{sequence: {{img_names, gt_rect, ...}}}}")
    root, sequences = file.parent, []
    for name, entry in meta.items():
        if not isinstance(entry, dict) or "img_names" not in entry or "gt_rect" not in entry:
            raise DatasetError(f"{file}: sequence {name!r} lacks img_names or gt_rect")
        frames = tuple(root / str(n) for n in entry["img_names"])
        if frames and not frames[0].is_file():
            raise DatasetError(f"{frames[0]}: first frame of {name} not found (paths are relative to {root})")
        try:
            boxes = np.asarray([[np.nan if v is None else float(v) for v in row] for row in entry["gt_rect"]])
        except (TypeError, ValueError):
            raise DatasetError(f"{file}: sequence {name!r} has a gt_rect that is not a list of numbers") from None
        if boxes.ndim != 2 or boxes.shape[1] != 4:
            raise DatasetError(f"{file}: sequence {name!r}: gt_rect rows must be x, y, w, h")
        attr = entry.get("attr") or []
        if all(str(a) in ("0", "1") for a in attr):
            names = parse_attributes(" ".join(str(a) for a in attr), f"{file} ({name})") if attr else ()
        else:
            names = tuple(str(a) for a in attr)
        sequences.append(replace(_make_sequence(str(name), frames, boxes, file), attributes=names))
    return sequences


def _apply_attributes_json(path: Path, sequences: list[Sequence]) -> list[Sequence]:
    file = path / "attributes.json"
    if not file.is_file():
        return sequences
    try:
        table = json.loads(file.read_text())
        table = {str(k): tuple(str(a) for a in v) for k, v in table.items()}
    except (OSError, ValueError, AttributeError, TypeError, RecursionError):
        raise DatasetError(f"{file}: expected a JSON object {{sequence: [attribute, ...]}}") from None
    return [replace(s, attributes=table[s.name]) if s.name in table else s for s in sequences]


def detect_layout(path: Path) -> tuple[str, Path]:
    """(layout, the file or folder to read) for a dataset path; DatasetError naming what was expected."""
    if path.is_file() and path.suffix.lower() == ".json":
        return "json", path
    if not path.is_dir():
        raise DatasetError(f"{path}: no such dataset folder or .json file")
    if (path / "data_seq").is_dir() and (path / "anno").is_dir():
        return "official", path
    named_json = path / f"{path.name}.json"
    if named_json.is_file():
        return "json", named_json
    subdirs = [p for p in path.iterdir() if p.is_dir()]
    if any((p / "img").is_dir() and any(p.glob("groundtruth_rect*.txt")) for p in subdirs):
        return "otb", path
    if any((p / "groundtruth.txt").is_file() for p in subdirs):
        return "got10k", path
    raise DatasetError(f"{path}: unknown dataset layout; expected {EXPECTED_LAYOUTS}")


def load_dataset(path: str | Path) -> Dataset:
    """Read a dataset in any of the supported layouts (see the module docstring)."""
    path = Path(path).expanduser()
    layout, target = detect_layout(path)
    readers = {"official": _official, "otb": _otb, "got10k": _got10k, "json": _json}
    try:
        sequences = readers[layout](target)
    except OSError as exc:
        raise DatasetError(f"{getattr(exc, 'filename', None) or path}: cannot read ({exc.strerror or exc})") from None
    folder = target.parent if layout == "json" else target
    sequences = _apply_attributes_json(folder, sequences)
    if not sequences:
        raise DatasetError(f"{path}: no sequences found ({layout} layout)")
    name = target.stem if layout == "json" else target.name
    return Dataset(name=name, path=path, layout=layout, sequences=tuple(sequences))
