"""Tracking datasets on disk: find the layout, list the sequences, read ground truth and attributes.

Layouts (`load_dataset(path)` tells them apart):

- official: `path/data_seq/<seq>/` frames + `path/anno/<seq>.txt` (UAVDark70, NUT-L, NUT-LR, NAT2021-test);
  optional attribute files `path/att/<seq>.txt` (or `attribute/`, `anno/att/`). UAV123 as downloaded has
  one more level, `data_seq/UAV123/<seq>/` + `anno/UAV123/<seq>.txt` (+ `anno/UAV123/att/`), and keeps
  UAV20L's boxes in `anno/UAV20L/` over the same frames: `path` picks `anno/<path's name>/` (or the only
  folder in anno/), `path/anno/<NAME>` picks that one.
- otb: `path/<seq>/img/` frames + `path/<seq>/groundtruth_rect.txt` (OTB, UAV123, the generated night
  benchmark); OTB's two-target folders (`groundtruth_rect.1.txt`, `.2.txt`) become `<seq>-1`, `<seq>-2`;
  attribute files `path/att/<seq>.txt` as above. Folders with img/ but no such file are skipped with a warning.
- got10k: `path/<seq>/` frames + `path/<seq>/groundtruth.txt` (sequence order from `list.txt` if present).
- json: a pysot-toolkit file (`path` itself, or `path/<folder name>.json`): `{seq: {"img_names": [...],
  "gt_rect": [...], "attr": [...]}}`, image paths relative to the file's folder.

Frames are taken in dadiff-run's order (`sources.image_files`: by number, so 2.jpg before 10.jpg), and a
sequence needs exactly one box line per frame: fewer lines (OTB labels some sequences from a later frame,
GOT-10k's test split only the first) or more (a missing frame) would pair boxes with the wrong frames, so
such a sequence is left out, not trimmed, with one warning per load naming each (UAV123's split parts such
as bird1_1 too: the download lacks their frame ranges); only a dataset with none left is refused. Blank
lines do not count.

Any layout may carry `path/attributes.json` = `{seq: ["SV", "OCC", ...]}`. An attribute file holds names
(comma or space separated) or 0/1 flags in a known order (`ATTRIBUTE_ORDERS`). Boxes are x, y, w, h lines
separated by commas, tabs or spaces; NaN rows stay NaN (the metrics count them as the toolkit does).
Text files may start with a UTF-8 byte-order mark (Windows editors write one).
"""

from __future__ import annotations

import fnmatch
import json
import re
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..errors import DadiffError
from ..sources import image_dir, image_files, read_image
from ..user_files import read_user_text
from .scene_error import SceneError

NUT_LR_ATTRIBUTES = ("ARC", "BC", "CM", "FM", "OCC", "SV", "SOB", "VC", "IV", "LAI")
UAV123_ATTRIBUTES = ("SV", "ARC", "LR", "FM", "FOC", "POC", "OV", "BC", "IV", "VC", "CM", "SOB")  # SOB: similar object
ATTRIBUTE_ORDERS = {len(NUT_LR_ATTRIBUTES): NUT_LR_ATTRIBUTES, len(UAV123_ATTRIBUTES): UAV123_ATTRIBUTES}
EXPECTED_LAYOUTS = (
    "data_seq/ + anno/ (UAVDark70, NUT-L, NUT-LR, NAT2021, UAV123 as downloaded), <seq>/img/ + "
    "<seq>/groundtruth_rect.txt (OTB, UAV123), <seq>/groundtruth.txt (GOT-10k), or a pysot-toolkit .json file"
)
ATTRIBUTE_FOLDERS = ("att", "attribute")
OTB_TRUTH = re.compile(r"groundtruth_rect(?:\.(\d+))?\.txt")  # groundtruth_rect.txt, OTB's .1.txt / .2.txt
SPLIT_CLIP = re.compile(r"(.+)_(\d+)")  # UAV123's bird1_1, bird1_2: parts of data_seq/UAV123/bird1
_SPLIT = re.compile(r"[,\t ]+")


class DatasetError(DadiffError):
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
class LeftOut:
    """A sequence whose truth does not fit its frames: `why` for the list, `fix` for the advice after it."""

    name: str
    why: str
    fix: str


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


def check_new_folder(out: Path) -> None:
    """Refuse to write a benchmark over anything: `out` must not exist or be an empty folder."""
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise SceneError(f"{out}: exists and is not an empty folder; choose a new --output")


def plural(count: int, word: str, words: str | None = None) -> str:
    """'1 box', '2 boxes': the count messages ('1 boxes for 6 frames' read wrong)."""
    return f"{count} {word if count == 1 else words or word + 's'}"


def read_text(path: Path) -> str:
    """A dataset's text file; unreadable or not text (a damaged file) is one DatasetError naming it.

    utf-8-sig: a byte-order mark (Notepad's) was kept as part of the first number and refused the file."""
    try:
        return read_user_text(path)
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
    """A sequence folder's image files (in its img/ subfolder if it has one) in dadiff-run's order.

    `sources.image_files` sorts by number (1.jpg, 2.jpg, ..., 10.jpg); sorting the names as text put 10.jpg
    before 2.jpg and scored every frame from the third on against another frame's box."""
    frames = tuple(p for p in image_files(folder) if p.is_file())
    if not frames:
        raise DatasetError(f"{image_dir(folder)}: no image files")
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


def warn(message: str, default_prog: str = "dadiff-eval") -> None:
    """One `PROG: warning: ...` line on stderr, PROG the running dadiff command (the commands' one style: eval,
    bench, export, train); `default_prog` where it runs from elsewhere (a test, the API)."""
    prog = Path(sys.argv[0]).name if Path(sys.argv[0]).name.startswith("dadiff-") else default_prog
    print(f"{prog}: warning: {message}", file=sys.stderr)


def _make_sequence(name: str, frames: tuple[Path, ...], boxes: np.ndarray) -> Sequence | LeftOut:
    """One box line per frame, or a LeftOut saying why not and how to fix it.

    A count mismatch is never trimmed to fit: trimming pairs boxes with the wrong frames (OTB labels some
    sequences from a later frame, David from frame 300; a missing frame shifts every later box). The sequence
    is left out with the reason, not the dataset refused (OTB100 has five such sequences)."""
    if len(frames) == len(boxes):
        return Sequence(name, frames, boxes)
    counts = f"{plural(len(boxes), 'box', 'boxes')} for {plural(len(frames), 'frame')}"
    if len(boxes) == 1:
        return LeftOut(name, f"only the first of {plural(len(frames), 'frame')} labelled",
                       "nothing to score there (GOT-10k's test split is scored by its evaluation server)")
    if len(boxes) < len(frames):  # the labels start at a later frame (OTB's David) or stop early
        return LeftOut(name, counts, "remove the unlabelled frames or give a pysot .json whose img_names list them")
    return LeftOut(name, f"{counts}, a frame missing", "restore the missing frames")


def _left_out_message(left: list[LeftOut], most: int = 20) -> str:
    """'left out N sequences whose boxes do not fit their frames: David (471 boxes for 770 frames), ...; FIX'."""
    shown = ", ".join(f"{item.name} ({item.why})" for item in left[:most])
    if len(left) > most:
        shown += f", and {len(left) - most} more"
    fixes = "; ".join(dict.fromkeys(item.fix for item in left))
    return f"left out {plural(len(left), 'sequence')} whose boxes do not fit their frames: {shown}; {fixes}"


def _with_attribute_file(sequence: Sequence | LeftOut, folders: list[Path], *names: str) -> Sequence | LeftOut:
    """`sequence` with the attributes of the first `<folder>/<name>.txt` that exists (names in order)."""
    if isinstance(sequence, LeftOut):
        return sequence
    for folder in folders:
        for name in (sequence.name, *names):
            att = folder / f"{name}.txt"
            if att.is_file():
                return replace(sequence, attributes=parse_attributes(read_text(att), str(att)))
    return sequence


def _official(path: Path) -> list[Sequence | LeftOut]:
    seq_root, anno = path / "data_seq", path / "anno"
    sequences = []
    for folder in sorted(p for p in seq_root.iterdir() if p.is_dir()):
        gt = anno / f"{folder.name}.txt"
        if not gt.is_file():
            raise DatasetError(f"{gt}: missing annotation for sequence {folder.name}")
        sequence = _make_sequence(folder.name, list_frames(folder), read_boxes(gt))
        sequences.append(_with_attribute_file(sequence, [path / f for f in ATTRIBUTE_FOLDERS] + [anno / "att"]))
    return sequences


def _official_nested(anno: Path) -> list[Sequence | LeftOut]:
    """UAV123 as downloaded: boxes in `anno/<NAME>/<seq>.txt`, frames in `data_seq/<NAME>/<seq>/` (or in the
    only folder of data_seq/: UAV20L's boxes are over UAV123's frames), attributes in `anno/<NAME>/att/`."""
    root = anno.parent.parent
    frames_root = root / "data_seq" / anno.name
    if not frames_root.is_dir():
        inside = [p for p in (root / "data_seq").iterdir() if p.is_dir()]
        if len(inside) != 1:
            raise DatasetError(f"{frames_root}: missing (the frames of the boxes in {anno})")
        frames_root = inside[0]
    sequences = []
    for gt in sorted(p for p in anno.iterdir() if p.suffix == ".txt" and p.is_file()):
        folder = frames_root / gt.stem
        if not folder.is_dir():
            clip = SPLIT_CLIP.fullmatch(gt.stem)
            if clip and (frames_root / clip[1]).is_dir():
                sequences.append(LeftOut(gt.stem, f"a part of {clip[1]} whose frame range is not in the download",
                                         f"give a pysot-toolkit {anno.name}.json instead (its img_names list each "
                                         "part's frames, relative to the .json's folder)"))
                continue
            raise DatasetError(f"{folder}: missing (the frames of {gt})")
        sequence = _make_sequence(gt.stem, list_frames(folder), read_boxes(gt))
        sequences.append(_with_attribute_file(sequence, [anno / f for f in ATTRIBUTE_FOLDERS]))
    return sequences


def _nested_anno(path: Path) -> Path | None:
    """The `anno/<NAME>` folder to read when anno/ holds one folder per dataset (UAV123 as downloaded) and no
    boxes of its own; None for the flat official layout."""
    anno = path / "anno"
    if any(p.suffix == ".txt" for p in anno.iterdir()):
        return None
    names = sorted(p for p in anno.iterdir() if p.is_dir() and p.name not in ATTRIBUTE_FOLDERS
                   and any(q.suffix == ".txt" for q in p.iterdir()))
    if not names:
        return None
    if (anno / path.name) in names:
        return anno / path.name
    if len(names) == 1:
        return names[0]
    raise DatasetError(f"{path}: anno/ holds the boxes of {len(names)} datasets; give one of: "
                       f"{', '.join(str(p) for p in names)}")


def _sequence_folders(path: Path) -> list[Path]:
    """OTB-style sequence folders: img/, or frames beside a groundtruth*.txt (not results or plots folders)."""
    folders = []
    for folder in sorted(p for p in path.iterdir() if p.is_dir()):
        if (folder / "img").is_dir() or any(f.name.startswith("groundtruth") for f in folder.glob("*.txt")):
            folders.append(folder)
    return folders


def _otb(path: Path) -> list[Sequence | LeftOut]:
    sequences, skipped = [], []
    for folder in _sequence_folders(path):
        truths = sorted((int(m[1] or 0), m[1] or "", folder / m[0])
                        for f in folder.iterdir() if (m := OTB_TRUTH.fullmatch(f.name)))
        if not truths:
            others = sorted(f.name for f in folder.glob("*.txt"))
            skipped.append(f"{folder.name} ({'has ' + ', '.join(others[:2]) if others else 'no ground truth'})")
            continue
        frames = list_frames(folder)
        for _, target, gt in truths:
            name = f"{folder.name}-{target}" if target else folder.name
            sequence = _make_sequence(name, frames, read_boxes(gt))
            sequences.append(_with_attribute_file(sequence, [path / f for f in ATTRIBUTE_FOLDERS], folder.name))
    if skipped:
        shown = ", ".join(skipped[:5]) + (", ..." if len(skipped) > 5 else "")
        warn(f"{path}: skipped {plural(len(skipped), 'sequence folder')} without groundtruth_rect.txt: {shown}")
    return sequences


def _got10k(path: Path) -> list[Sequence | LeftOut]:
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
        sequence = _make_sequence(folder.name, list_frames(folder), read_boxes(gt))
        sequences.append(_with_attribute_file(sequence, [path / f for f in ATTRIBUTE_FOLDERS]))
    return sequences


def _attribute_list(value: object, file: Path, name: str, kinds: tuple[type, ...] = (str,)) -> tuple[str, ...]:
    """A sequence's attributes as a list of names (of `kinds`: pysot's attr may hold 0/1 flags as numbers);
    a string ("SV") is refused, never split into the attributes S and V."""
    if not isinstance(value, list) or not all(isinstance(a, kinds) and not isinstance(a, bool) for a in value):
        raise DatasetError(f"{file}: sequence {name!r}: expected a list of attribute names such as "
                           f'["SV", "OCC"], got {json.dumps(value)[:60]}')
    return tuple(str(a) for a in value)


def _json(file: Path) -> list[Sequence | LeftOut]:
    try:
        meta = json.loads(read_text(file))
    except ValueError as exc:
        raise DatasetError(f"{file}: not a readable pysot-toolkit JSON file ({exc})") from None
    except RecursionError:  # json's decoder recurses per level: a deep nesting is bad input, one line
        raise DatasetError(f"{file}: not a pysot-toolkit JSON file (nested too deeply)") from None
    if not isinstance(meta, dict):
        raise DatasetError(f"{file}: expected a JSON object {{sequence: {{img_names, gt_rect, ...}}}}")
    root, sequences = file.parent, []
    for name, entry in meta.items():
        if not isinstance(entry, dict) or "img_names" not in entry or "gt_rect" not in entry:
            raise DatasetError(f"{file}: sequence {name!r} lacks img_names or gt_rect")
        frames = tuple(root / str(n) for n in entry["img_names"])
        # every frame is checked before any tracking, so a missing one is named at load time, not mid-run
        missing = next((k for k, f in enumerate(frames) if not f.is_file()), None)
        if missing is not None:
            which = "first frame" if missing == 0 else f"frame {missing + 1}"
            raise DatasetError(f"{frames[missing]}: {which} of {name} not found (paths are relative to {root})")
        try:
            boxes = np.asarray([[np.nan if v is None else float(v) for v in row] for row in entry["gt_rect"]])
        except (TypeError, ValueError):
            raise DatasetError(f"{file}: sequence {name!r} has a gt_rect that is not a list of numbers") from None
        if boxes.ndim != 2 or boxes.shape[1] != 4:
            raise DatasetError(f"{file}: sequence {name!r}: gt_rect rows must be x, y, w, h")
        if len(frames) != len(boxes):
            counts = f"{plural(len(frames), 'img_name')} for {plural(len(boxes), 'gt_rect row')}"
            sequences.append(LeftOut(str(name), counts, f"give one img_name per gt_rect row in {file}"))
            continue
        attr = _attribute_list(entry.get("attr") or [], file, str(name), (str, int))
        if attr and all(a in ("0", "1") for a in attr):
            names = parse_attributes(" ".join(attr), f"{file} ({name})")
        else:
            names = attr
        sequence = _make_sequence(str(name), frames, boxes)
        sequences.append(sequence if isinstance(sequence, LeftOut) else replace(sequence, attributes=names))
    return sequences


def _apply_attributes_json(path: Path, sequences: list[Sequence]) -> list[Sequence]:
    file = path / "attributes.json"
    if not file.is_file():
        return sequences
    try:
        table = json.loads(read_text(file))
    except (ValueError, RecursionError):
        table = None
    if not isinstance(table, dict):
        raise DatasetError(f"{file}: expected a JSON object {{sequence: [attribute, ...]}}")
    table = {str(k): _attribute_list(v, file, str(k)) for k, v in table.items()}
    return [replace(s, attributes=table[s.name]) if s.name in table else s for s in sequences]


def _has_frames(folder: Path) -> bool:
    return (folder / "img").is_dir() or any(p.is_file() for p in image_files(folder))


def detect_layout(path: Path) -> tuple[str, Path]:
    """(layout, the file or folder to read) for a dataset path; DatasetError naming what was expected."""
    if path.is_file() and path.suffix.lower() == ".json":
        return "json", path
    if not path.is_dir():
        raise DatasetError(f"{path}: no such dataset folder or .json file")
    if (path / "data_seq").is_dir() and (path / "anno").is_dir():
        nested = _nested_anno(path)
        return ("nested", nested) if nested else ("official", path)
    if path.parent.name == "anno" and path.name not in ATTRIBUTE_FOLDERS and (path.parent.parent / "data_seq").is_dir():
        return "nested", path  # <root>/anno/UAV20L: that one of the datasets in anno/
    named_json = path / f"{path.name}.json"
    if named_json.is_file():
        return "json", named_json
    subdirs = sorted(p for p in path.iterdir() if p.is_dir())
    if any(any(OTB_TRUTH.fullmatch(f.name) for f in p.iterdir()) and _has_frames(p) for p in subdirs):
        return "otb", path
    if any((p / "groundtruth.txt").is_file() for p in subdirs):
        return "got10k", path
    if (path / "data_seq").is_dir():
        raise DatasetError(f"{path}: data_seq/ but no anno/ folder (the official layout keeps each sequence's "
                           "boxes in anno/<seq>.txt beside data_seq/)")
    inside = [p for p in subdirs if (p / "data_seq").is_dir()]
    if inside:
        raise DatasetError(f"{path}: a folder of datasets; give one of: {', '.join(str(p) for p in inside)}")
    raise DatasetError(f"{path}: unknown dataset layout; expected {EXPECTED_LAYOUTS}")


def load_dataset(path: str | Path) -> Dataset:
    """Read a dataset in any of the supported layouts (see the module docstring)."""
    path = Path(path).expanduser()
    layout, target = detect_layout(path)
    readers = {"official": _official, "nested": _official_nested, "otb": _otb, "got10k": _got10k, "json": _json}
    try:
        sequences = readers[layout](target)
    except OSError as exc:
        raise DatasetError(f"{getattr(exc, 'filename', None) or path}: cannot read ({exc.strerror or exc})") from None
    left = [s for s in sequences if isinstance(s, LeftOut)]
    sequences = [s for s in sequences if not isinstance(s, LeftOut)]
    name = target.stem if layout == "json" else target.name
    if left and not sequences:
        raise DatasetError(f"{path}: no sequence to score; {_left_out_message(left)}")
    if left:  # one line per load; on stderr, so `score --json` stays one document
        warn(f"{name}: {_left_out_message(left)}")
    folder = target.parent if layout == "json" else path if layout == "nested" else target
    sequences = _apply_attributes_json(folder, sequences)
    if not sequences:
        raise DatasetError(f"{path}: no sequences found ({layout} layout)")
    return Dataset(name=name, path=path, layout="official" if layout == "nested" else layout,
                   sequences=tuple(sequences))


def read_frame(path: Path) -> np.ndarray:
    """A frame to track; the error tells a missing file ('not found') from a damaged one ('cannot read
    image')."""
    image = read_image(path)  # libjpeg's own warnings on a damaged frame stay off stderr
    if image is None:
        raise DatasetError(f"{path}: {'cannot read image' if Path(path).is_file() else 'not found'}")
    return image
