"""Run a tracker over a dataset into pysot-format result files, and score result folders (OPE).

Result files: `<results>/<dataset>/<tracker>/<sequence>.txt`, one `x,y,w,h` line per frame. Frame 0 holds
the init box of the test protocol (spec 8.5): GT (x, y, w, h) becomes (x + 0.5, y + 0.5, w, h), for every
tracker, so that all trackers share frame 0. Beside each, `<sequence>.states` holds what the tracker told its
user in each frame, `score,state` (frame 0: `1,init`), so that reports can check the state against the
truth. A run is resumable: a sequence whose result file already has one line per frame is skipped. Files are
written whole (temporary file, then rename), so an interrupted run never leaves a truncated file behind.
`run.json` in the folder records what produced it (tracker, model hashes, --preset, --hp, NanoTrack weights, --gamma):
a run with other settings is refused, so that results of one setting are never reported as another's.
"""

from __future__ import annotations

import json
import math
import os
import re
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np
from tqdm import tqdm

from ..crop import protocol_box
from ..datamaking.datasets import Dataset, DatasetError, load_dataset, plural, read_boxes, read_frame
from ..errors import DadiffError, InputError
from ..files import write_atomic
from ..user_files import read_user_text
from .metrics import Scores, SequenceCurves, summarise

Box = tuple[float, float, float, float]
STATES = ".states"  # suffix of the per-frame score,state file beside each result file
KNOWN_STATES = ("init", "tracking", "uncertain", "lost")  # what the run loop writes after each score


class EvalError(DadiffError):
    """Results missing or malformed, a tracker unavailable, a frame unreadable (one-line message)."""


class BoxTracker(Protocol):
    """What the run loop drives: `init` with frame 0 and its GT box, then `update` per frame."""

    def init(self, frame: np.ndarray, gt_box: Box) -> None: ...

    def update(self, frame: np.ndarray) -> tuple[Box, float, str]: ...


class RuntimeTracker:
    """Adapter for `dadiff.runtime.Tracker`, initialised with the protocol box as in the released script."""

    def __init__(self, tracker: object) -> None:
        self.tracker = tracker

    def init(self, frame: np.ndarray, gt_box: Box) -> None:
        self.tracker.init(frame, protocol_box(gt_box))

    def update(self, frame: np.ndarray) -> tuple[Box, float, str]:
        result = self.tracker.update(frame)
        return tuple(result.box), float(result.score), str(result.state)


OPENCV_TRACKERS = {"csrt": "TrackerCSRT", "kcf": "TrackerKCF", "nano": "TrackerNano"}
OPENCV_NAMES = {"csrt": "CSRT", "kcf": "KCF", "nano": "NANO"}
# NanoTrack v2 as cv2.TrackerNano loads it; third-party weights, not shipped. Found through --nano-dir, else
# DADIFF_NANO_DIR, else ../shared/weights/nanotrack/v2 beside the source checkout this package runs from (a
# non-editable install has no checkout: that path would point into site-packages, so it counts only if present).
NANO_FILES = ("nanotrack_backbone_sim.onnx", "nanotrack_head_sim.onnx")
NANO_ENV = "DADIFF_NANO_DIR"
CHECKOUT_NANO_DIR = Path(__file__).resolve().parents[2].parent / "shared" / "weights" / "nanotrack" / "v2"
NANO_HINT = f"--nano-dir DIR or {NANO_ENV}=DIR"


class TrackerUnavailable(EvalError):
    """A baseline this OpenCV build or this machine cannot run (missing module or weights)."""


def opencv_available(kind: str) -> bool:
    """Whether this OpenCV build has the tracker `kind` (csrt, kcf: contrib; nano: the main build)."""
    return hasattr(getattr(cv2, OPENCV_TRACKERS[kind], None), "create")


def default_nano_dir() -> tuple[Path | None, str]:
    """Where the NanoTrack v2 weights are looked for without --nano-dir, and where that folder came from:
    $DADIFF_NANO_DIR (read at each call, so a shell or a test can set it), else the checkout's ../shared."""
    env = os.environ.get(NANO_ENV, "").strip()
    if env:
        return Path(env).expanduser(), f"from {NANO_ENV}"
    if CHECKOUT_NANO_DIR.is_dir():
        return CHECKOUT_NANO_DIR, "the default beside the source checkout"
    return None, ""


def _nano_weights(folder: Path | None) -> tuple[tuple[Path, Path] | None, str, str]:
    """The two weight files (or None), the names of those missing, and where they were looked for."""
    if folder is not None:
        folder, origin = Path(folder).expanduser(), "given by --nano-dir"
    else:
        folder, origin = default_nano_dir()
        if folder is None:
            return None, " and ".join(NANO_FILES), (
                f"found nowhere (not shipped; no --nano-dir or {NANO_ENV} given, and no "
                "../shared/weights/nanotrack/v2 beside a source checkout)")
    paths = (folder / NANO_FILES[0], folder / NANO_FILES[1])
    missing = [p.name for p in paths if not p.is_file()]
    if missing:
        return None, " and ".join(missing), f"not found in {folder} ({origin})"
    return paths, "", ""


def nano_files(folder: Path | None = None, option: str = "--tracker nano") -> tuple[Path, Path]:
    """(backbone, neck/head) ONNX files of NanoTrack v2 in `folder` (default: `default_nano_dir()`).

    `option` is how the command that asked names TrackerNano (`--nano` for dadiff-bench), so that the error
    names an option of the command that was used."""
    paths, missing, where = _nano_weights(folder)
    if paths is None:
        raise TrackerUnavailable(f"{option} needs NanoTrack v2's {missing}, {where}: give the folder that holds "
                                 f"them with {NANO_HINT}")
    return paths


def nano_problem(folder: Path | None = None) -> str | None:
    """Why TrackerNano cannot run here (no cv2.TrackerNano, or no weights, with how to give them), or None."""
    if not opencv_available("nano"):
        return f"this OpenCV ({cv2.__version__}) has no cv2.TrackerNano (OpenCV >= 4.7 has it)"
    paths, missing, where = _nano_weights(folder)
    verb = "were" if " and " in missing else "was"
    return None if paths is not None else f"NanoTrack v2's {missing} {verb} {where}; give {NANO_HINT}"


def nano_available(folder: Path | None = None) -> bool:
    """Whether cv2.TrackerNano and the NanoTrack v2 weights are both here."""
    return nano_problem(folder) is None


def nano_label() -> str:
    """How reports name the NanoTrack baseline, with the OpenCV version that runs it."""
    return f"TrackerNano (NanoTrack v2, OpenCV {cv2.__version__})"


def _nano_factory(folder: Path | None, option: str) -> Callable[[], object]:
    backbone, head = nano_files(folder, option)

    def create() -> object:
        params = cv2.TrackerNano_Params()
        params.backbone, params.neckhead = str(backbone), str(head)
        level = cv2.utils.logging.getLogLevel()  # its DNN setup warns about targets on every create
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
        try:
            return cv2.TrackerNano.create(params)
        except cv2.error as exc:  # a damaged or foreign .onnx: OpenCV names the file in its message
            said = re.search(r"error: \([^)]*\) (.*?)(?: in function .*)?$", str(exc).strip(), re.MULTILINE)
            detail = said.group(1) if said else str(exc).strip().splitlines()[-1]
            raise TrackerUnavailable(f"{option}: OpenCV cannot load NanoTrack v2's weights in {backbone.parent} "
                                     f"({detail})") from None
        finally:
            cv2.utils.logging.setLogLevel(level)

    create()  # now, not at the first sequence: a run.json (or a benchmark) is not begun for weights that fail
    return create


class OpenCVTracker:
    """OpenCV's CSRT, KCF (opencv-contrib) or TrackerNano (NanoTrack v2 weights, `nano_dir`).

    The score is the tracker's own where it has one (TrackerNano), else 1; a failed update (or one that raises
    cv2.error, as CSRT does on some sequences) keeps the last box and reports 'lost'. `option`: how the calling
    command names this tracker in errors (default `--tracker KIND`, as dadiff-eval run).
    """

    def __init__(self, kind: str, *, nano_dir: Path | None = None, option: str | None = None) -> None:
        kind = kind.lower()
        if kind not in OPENCV_TRACKERS:
            raise EvalError(f"unknown OpenCV tracker '{kind}'; expected one of {', '.join(OPENCV_TRACKERS)}")
        option = option or f"--tracker {kind}"
        if not opencv_available(kind):
            hint = (f"pip install opencv-contrib-python-headless=={cv2.__version__}.* (or dadiff[baselines])"
                    if kind != "nano" else "it is in OpenCV >= 4.7")
            contrib = "OpenCV's contrib modules" if kind != "nano" else "a newer OpenCV"
            raise TrackerUnavailable(
                f"{option} needs {contrib} (cv2.{OPENCV_TRACKERS[kind]} is missing): {hint}"
            )
        self.kind = kind
        self._create = (_nano_factory(nano_dir, option) if kind == "nano"
                        else getattr(cv2, OPENCV_TRACKERS[kind]).create)
        self._tracker = None
        self._last: Box = (0.0, 0.0, 0.0, 0.0)

    def init(self, frame: np.ndarray, gt_box: Box) -> None:
        x, y, w, h = (float(v) for v in gt_box)
        rect = (round(x), round(y), max(1, round(w)), max(1, round(h)))
        self._tracker = self._create()
        self._tracker.init(frame, rect)
        self._last = (x, y, w, h)

    def update(self, frame: np.ndarray) -> tuple[Box, float, str]:
        try:
            ok, rect = self._tracker.update(frame)
        except cv2.error:  # CSRT asserts inside resize once its box has shrunk to nothing: a failed update
            ok, rect = False, (0, 0, 0, 0)
        if ok and rect[2] > 0 and rect[3] > 0:
            self._last = tuple(float(v) for v in rect)
            return self._last, self._score(), "tracking"
        return self._last, 0.0, "lost"

    def _score(self) -> float:
        score = getattr(self._tracker, "getTrackingScore", None)
        return float(score()) if score is not None else 1.0


class GammaTracker:
    """Any tracker with a plain gamma curve on each frame first (255 * (v / 255) ** gamma per channel): the
    simplest night enhancement, a baseline that a trained night tracker has to beat (gamma < 1 lifts the dark)."""

    def __init__(self, tracker: BoxTracker, gamma: float) -> None:
        self.tracker, self.gamma = tracker, gamma
        self._table = np.clip(np.rint(255 * (np.arange(256) / 255) ** gamma), 0, 255).astype(np.uint8)

    def brighten(self, frame: np.ndarray) -> np.ndarray:
        return cv2.LUT(frame, self._table)

    def init(self, frame: np.ndarray, gt_box: Box) -> None:
        self.tracker.init(self.brighten(frame), gt_box)

    def update(self, frame: np.ndarray) -> tuple[Box, float, str]:
        return self.tracker.update(self.brighten(frame))


# ----------------------------------------------------------------------------------------- result files


def tracker_folder(results: Path, dataset: str, tracker: str) -> Path:
    """`<results>/<dataset>/<tracker>`."""
    return Path(results) / dataset / tracker


def write_result(path: Path, boxes: Iterable[Sequence[float]]) -> None:
    """Write `x,y,w,h` lines atomically."""
    write_atomic(path, "".join(",".join(_number(v) for v in box) + "\n" for box in boxes))


def write_states(path: Path, states: Iterable[tuple[float, str]]) -> None:
    """Write `score,state` lines atomically."""
    write_atomic(path, "".join(f"{_number(score)},{state}\n" for score, state in states))


def _number(value: float) -> str:
    value = float(value)
    return "nan" if math.isnan(value) else f"{value:.4f}".rstrip("0").rstrip(".")


def read_states(dataset: Dataset, folder: Path) -> dict[str, list[str]] | None:
    """The state of every frame of every sequence in `folder`, or None where any `.states` file is missing
    (runs from before they were written, other tools' results). Every file that is there is checked line by
    line first (`bogus`, `x` or `,` is an error, never a flagged frame)."""
    present = {}
    for seq in dataset.sequences:
        path = Path(folder) / f"{seq.name}{STATES}"
        if path.is_file():
            lines = [line.strip() for line in read_user_text(path, encoding="utf-8").splitlines()]
            present[seq.name] = (path, [_state(path, n, line) for n, line in enumerate(lines, 1) if line])
    out = {}
    for seq in dataset.sequences:
        if seq.name not in present:
            return None
        path, states = present[seq.name]
        if len(states) != len(seq):
            raise EvalError(f"{path}: {plural(len(states), 'state')}, but {seq.name} has "
                            f"{plural(len(seq), 'ground-truth frame')}")
        out[seq.name] = states
    return out


def _state(path: Path, number: int, line: str) -> str:
    """The state of one `score,state` line, or EvalError naming the file and line."""
    score, comma, state = line.partition(",")
    if not (comma and state in KNOWN_STATES and score == score.strip() and _is_float(score)):
        raise EvalError(f"{path}: line {number}: expected 'score,state' with a number and one of "
                        f"{', '.join(KNOWN_STATES)}, got {line!r}")
    return state


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def read_result(path: Path) -> np.ndarray:
    """(N, 4) boxes from a result file (comma, tab or space separated x,y,w,h lines)."""
    try:
        return read_boxes(path)
    except DatasetError as exc:
        raise EvalError(str(exc)) from None


def _complete(path: Path, frames: int) -> bool:
    try:
        return len(read_result(path)) == frames
    except EvalError:
        return False


# ------------------------------------------------------------------------------------------- run record

RUN_RECORD = "run.json"  # what produced a tracker's result folder: checked before a run resumes into it
# record key -> (how the command line names it, the entries that decide equality); entries not listed here
# are shown only (paths: the same model or weights copied elsewhere give the same boxes)
_IDENTITY = {"model": ("--model", ("template_sha256", "search_sha256")),
             "nano": ("--nano-dir", ("backbone_sha256", "head_sha256"))}


def _shown(value: object) -> str:
    """A recorded setting as the message shows it."""
    if value is None:
        return "none"
    if isinstance(value, dict):  # a model or weight folder: its path and the start of its main file's hash
        digest = value.get("search_sha256") or value.get("backbone_sha256") or ""
        return f"{value.get('folder')}" + (f" (sha256 {digest[:12]})" if digest else "")
    return str(value)


def run_record_differences(old: dict, new: dict) -> list[str]:
    """'SETTING: OLD before, NEW now' for each setting that differs between two run records."""
    if old.get("tracker") != new.get("tracker"):  # the rest differs as a consequence
        return [f"--tracker: {_shown(old.get('tracker'))} before, {_shown(new.get('tracker'))} now"]
    out = []
    for key in sorted(set(old) | set(new)):
        before, now = old.get(key), new.get(key)
        if key == "hp":
            before, now = before or {}, now or {}
            for name in sorted(set(before) | set(now)):
                if before.get(name) != now.get(name):
                    out.append(f"--hp {name}: {before.get(name, 'unset')} before, {now.get(name, 'unset')} now")
        elif key in _IDENTITY:
            option, fields = _IDENTITY[key]
            same = (isinstance(before, dict) and isinstance(now, dict)
                    and all(before.get(f) == now.get(f) for f in fields))
            if not same and before != now:
                out.append(f"{option}: {_shown(before)} before, {_shown(now)} now")
        elif key != "record" and before != now:
            out.append(f"--{key}: {_shown(before)} before, {_shown(now)} now")
    return out


def claim_folder(folder: Path, record: dict) -> str | None:
    """Check `record` (what this run would track with) against the one in `folder`, before tracking.

    Other settings: EvalError naming each setting that differs (a run never resumes into results of another
    setting, whose scores it would report as its own). No folder yet, or one without results
    (a run that failed before its first sequence left only its record): the record is written. Results without
    a record (older versions): a warning to print, nothing written, since they may come from other settings.
    """
    folder = Path(folder)
    path = folder / RUN_RECORD
    record = json.loads(json.dumps(record))  # as it reads back: tuples as lists, keys as strings
    has_results = folder.is_dir() and any(p.suffix in (".txt", STATES) and not p.name.startswith(".")
                                          for p in folder.iterdir())
    if path.is_file() and has_results:
        try:
            old = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise EvalError(f"{path}: unreadable run record ({exc}); delete the folder or use --name NEW") from None
        if not isinstance(old, dict):
            raise EvalError(f"{path}: not a run record (a JSON object); delete the folder or use --name NEW")
        differences = run_record_differences(old, record)
        if differences:
            raise EvalError(f"{folder} holds results of other settings ({'; '.join(differences)}): give --name NEW "
                            f"(or another --output) for these settings; nothing tracked")
        return None
    if has_results:
        return (f"{folder} has results but no {RUN_RECORD} (written by an older dadiff-eval): their settings "
                f"cannot be checked against this run's; resuming")
    write_atomic(path, json.dumps(record, indent=1, sort_keys=True) + "\n")
    return None


# ------------------------------------------------------------------------------------------------ run


@dataclass
class RunReport:
    """What a run did: sequences tracked and skipped (already done), frames tracked, tracking time."""

    tracker: str
    folder: Path
    ran: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    frames: int = 0
    seconds: float = 0.0

    @property
    def fps(self) -> float | None:
        return self.frames / self.seconds if self.seconds > 0 else None


def check_first_box(name: str, box: np.ndarray) -> None:
    if not (np.all(np.isfinite(box)) and box[2] > 0 and box[3] > 0):
        raise EvalError(f"sequence {name}: first ground-truth box {box.tolist()} is invalid; cannot initialise")


def run_tracker(
    tracker: BoxTracker,
    name: str,
    dataset: Dataset,
    results: Path,
    *,
    progress: bool = True,
) -> RunReport:
    """Track every sequence of `dataset` not yet in `<results>/<dataset>/<name>/`; one-pass, no re-init."""
    folder = tracker_folder(results, dataset.name, name)
    report = RunReport(name, folder)
    todo = []
    for seq in dataset.sequences:
        if _complete(folder / f"{seq.name}.txt", len(seq)):
            report.skipped.append(seq.name)
        else:
            check_first_box(seq.name, seq.boxes[0])
            todo.append(seq)
    bar = tqdm(
        total=sum(len(s) for s in todo),
        desc=f"{name} on {dataset.name}",
        unit="frame",
        file=sys.stderr,
        disable=not progress or not todo,
        dynamic_ncols=True,
    )
    with bar:
        for seq in todo:
            bar.set_postfix_str(seq.name)
            frame = read_frame(seq.frames[0])
            tracker.init(frame, tuple(seq.boxes[0]))
            boxes: list[Sequence[float]] = [protocol_box(seq.boxes[0])]
            states: list[tuple[float, str]] = [(1.0, "init")]
            bar.update(1)
            for path in seq.frames[1:]:
                frame = read_frame(path)
                start = time.perf_counter()
                try:
                    box, score, state = tracker.update(frame)
                except InputError as exc:  # a frame of another size than the first
                    raise EvalError(f"{path}: {exc}") from None
                report.seconds += time.perf_counter() - start
                boxes.append(box)
                states.append((score, state))
                bar.update(1)
            report.frames += len(seq) - 1
            write_states(folder / f"{seq.name}{STATES}", states)  # first: a complete .txt marks the sequence done
            write_result(folder / f"{seq.name}.txt", boxes)
            report.ran.append(seq.name)
    return report


# ---------------------------------------------------------------------------------------------- score


@dataclass(frozen=True)
class TrackerScores:
    """Scores of one result folder: overall, per attribute, and the per-sequence curves behind them."""

    name: str
    folder: Path
    overall: Scores
    by_attribute: dict[str, Scores]
    sequences: dict[str, SequenceCurves]


def read_results(dataset: Dataset, folder: Path) -> dict[str, np.ndarray]:
    """The boxes in `folder` for every sequence of `dataset`, each as many as its ground truth."""
    folder = Path(folder)
    missing = [s.name for s in dataset.sequences if not (folder / f"{s.name}.txt").is_file()]
    if missing:
        shown = ", ".join(missing[:3]) + (", ..." if len(missing) > 3 else "")
        raise EvalError(
            f"{folder}: no results for {len(missing)} of {len(dataset.sequences)} sequences of {dataset.name} ({shown})"
        )
    results = {}
    for seq in dataset.sequences:
        path = folder / f"{seq.name}.txt"
        pred = read_result(path)
        if len(pred) != len(seq):
            raise EvalError(f"{path}: {plural(len(pred), 'box', 'boxes')}, but {seq.name} has "
                            f"{plural(len(seq), 'ground-truth frame')}")
        results[seq.name] = pred
    return results


def score_folder(dataset: Dataset, folder: Path, name: str | None = None, first: int = 0) -> TrackerScores:
    """Score the result files in `folder` against every sequence of `dataset`, from frame `first` on (1: leave out
    the init frame, whose box is the truth for every tracker and half of a two-frame sequence)."""
    folder = Path(folder)
    results = read_results(dataset, folder)
    curves = {seq.name: SequenceCurves.from_boxes(seq.boxes[first:], results[seq.name][first:])
              for seq in dataset.sequences}
    by_attribute = {
        attr: summarise(curves[s.name] for s in dataset.sequences if attr in s.attributes)
        for attr in dataset.attributes()
    }
    return TrackerScores(name or folder.name, folder, summarise(curves.values()), by_attribute, curves)


def result_folders(paths: Iterable[Path], dataset: Dataset) -> list[tuple[str, Path]]:
    """(name, folder) per tracker: a path holding `<seq>.txt` files is one tracker; a path whose
    sub-folders hold them (such as `<results>/<dataset>`) gives one tracker per sub-folder.

    Names are the folder names, prefixed with the parent folder's name where two would clash.
    """
    wanted = {f"{s.name}.txt" for s in dataset.sequences}

    def holds_results(folder: Path) -> bool:
        return folder.is_dir() and any(p.name in wanted for p in folder.iterdir())

    found: list[Path] = []
    for path in paths:
        path = Path(path).expanduser()
        if not path.is_dir():
            raise EvalError(f"{path}: no such results folder")
        if holds_results(path):
            found.append(path)
            continue
        subs = sorted(p for p in path.iterdir() if holds_results(p))
        if not subs:
            raise EvalError(f"{path}: no result files for {dataset.name} (expected <sequence>.txt files)")
        found.extend(subs)
    counts: dict[str, int] = {}
    for folder in found:
        counts[folder.name] = counts.get(folder.name, 0) + 1
    out, seen = [], set()
    for folder in found:
        name = folder.name if counts[folder.name] == 1 else f"{folder.parent.name}/{folder.name}"
        if folder.resolve() in seen:
            continue
        seen.add(folder.resolve())
        out.append((name, folder))
    return out


def generated_night_set(root: Path, sequences: int, frames: int, seed: int, workers: int | None = None) -> Dataset:
    """The night half of a generated benchmark (test photos) written to `root`, as `dadiff-eval generate`
    writes it; frames are read from disk while tracking, so scoring many sequences keeps memory flat."""
    from ..datamaking.scenes import write_benchmark  # the generator pulls in scikit-image's photos: only when asked

    write_benchmark(root, sequences, frames, seed, "test", workers=workers or min(sequences, os.cpu_count() or 1))
    return load_dataset(root).select(["*_night"])


def score_tracker(tracker: object, dataset: Dataset, results: Path, name: str) -> TrackerScores:
    """One-pass evaluation of a `dadiff.runtime.Tracker` (or anything with its init/update) on `dataset`."""
    run_tracker(RuntimeTracker(tracker), name, dataset, results, progress=False)
    return score_folder(dataset, tracker_folder(results, dataset.name, name), name)
