"""`dadiff-eval tune`: coordinate search of the tracker's hyper-parameters on a validation set.

The released presets (lr, penalty_k, window_influence) were tuned for DaDiff-BAN: stride 8, a 25x25 score
map, real benchmarks. A family with another map (dadiff-mobile: stride 16, 13x13) or other training wants
its own values. Tune on sequences held apart from the ones you report on; the frames are decoded once and
kept in memory, so each trial costs only the tracking.
"""

from __future__ import annotations

import csv
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config import TUNABLE_KEYS
from ..datamaking.datasets import Dataset, read_frame
from ..errors import InputError
from .evaluate import BoxTracker, check_first_box, protocol_box
from .metrics import Scores, SequenceCurves, summarise

# what a search varies when the user names no grid: the released keys around their usual ranges
DEFAULT_GRID: dict[str, tuple[float, ...]] = {
    "penalty_k": (0.02, 0.05, 0.088, 0.14, 0.2),
    "window_influence": (0.2, 0.3, 0.4, 0.5, 0.6),
    "lr": (0.3, 0.473, 0.6, 0.8),
}
SCORE_COLUMNS = ("success", "precision", "norm_precision")  # the last columns of a trials CSV


@dataclass(frozen=True)
class LoadedSequence:
    """One sequence with its frames decoded, so that trials do not re-read the disk."""

    name: str
    frames: list[np.ndarray]
    boxes: np.ndarray


@dataclass(frozen=True)
class Trial:
    """The overrides tried and what they scored."""

    values: dict[str, float]
    scores: Scores


def parse_grid(items: Iterable[str]) -> dict[str, tuple[float, ...]]:
    """'key=v1,v2,...' per item; keys are the tracker's tunable parameters."""
    grid: dict[str, tuple[float, ...]] = {}
    for item in items:
        key, sep, raw = item.partition("=")
        key = key.strip()
        if not sep or not raw.strip():
            raise InputError(f"--grid {item!r}: expected KEY=V1,V2,... (e.g. penalty_k=0.05,0.1)")
        if key not in TUNABLE_KEYS:
            raise InputError(f"--grid {item!r}: unknown parameter '{key}' (tunable: {', '.join(TUNABLE_KEYS)})")
        try:
            values = tuple(float(v) for v in raw.split(","))
        except ValueError:
            raise InputError(f"--grid {item!r}: values must be numbers") from None
        if not all(np.isfinite(values)):
            raise InputError(f"--grid {item!r}: values must be finite")
        grid[key] = values
    return grid


def load_sequences(dataset: Dataset) -> list[LoadedSequence]:
    """Decode every frame of `dataset` once (about 0.7 MB a 640x360 frame)."""
    loaded = []
    for seq in dataset.sequences:
        check_first_box(seq.name, seq.boxes[0])
        loaded.append(LoadedSequence(seq.name, [read_frame(p) for p in seq.frames], seq.boxes))
    return loaded


def track_sequences(tracker: BoxTracker, sequences: Sequence[LoadedSequence]) -> Scores:
    """One-pass evaluation as `dadiff-eval run` does it (e.g. a `RuntimeTracker`: the protocol init box)."""
    curves = []
    for seq in sequences:
        tracker.init(seq.frames[0], tuple(seq.boxes[0]))
        boxes = [protocol_box(seq.boxes[0])]
        boxes += [tracker.update(frame)[0] for frame in seq.frames[1:]]
        curves.append(SequenceCurves.from_boxes(seq.boxes, np.asarray(boxes, dtype=np.float64)))
    return summarise(curves)


def coordinate_search(
    evaluate: Callable[[dict[str, float]], Scores],
    start: Mapping[str, float],
    grid: Mapping[str, Sequence[float]],
    rounds: int = 2,
    report: Callable[[Trial], None] | None = None,
) -> list[Trial]:
    """Vary one key at a time over its values with the others at the best so far; repeat `rounds` times
    or until a round changes nothing. Each setting is evaluated once; ties keep the earlier best."""
    best = {k: float(v) for k, v in start.items()}
    seen: dict[tuple[tuple[str, float], ...], Trial] = {}

    def trial(values: dict[str, float]) -> Trial:
        key = tuple(sorted(values.items()))
        if key not in seen:
            seen[key] = Trial(dict(values), evaluate(dict(values)))
            if report is not None:
                report(seen[key])
        return seen[key]

    top = trial(best)
    for _ in range(rounds):
        before = dict(best)
        for key, values in grid.items():
            for value in values:
                candidate = trial({**best, key: float(value)})
                if candidate.scores.success > top.scores.success:
                    top = candidate
            best = dict(top.values)
        if best == before:
            break
    return list(seen.values())


def best_trial(trials: Sequence[Trial]) -> Trial:
    """The highest success; the first tried among equals."""
    return max(trials, key=lambda t: t.scores.success)


def check_trials_out(path: Path) -> None:
    """InputError unless `path` is new or a trials CSV that `write_trials` wrote: `--output` replaced any file,
    a dataset's ground truth or a video included."""
    if not path.exists():
        return
    try:
        with open(path, "rb") as f:
            first = f.read(4096).split(b"\n", 1)[0].strip()
    except OSError:
        first = b""
    if not first.endswith(b"," + ",".join(SCORE_COLUMNS).encode()):
        raise InputError(f"{path}: --output exists and is not a trials CSV of dadiff-eval tune; choose a new file "
                         "(nothing written)")


def write_trials(path: Path, trials: Sequence[Trial]) -> None:
    keys = sorted({k for t in trials for k in t.values})
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow([*keys, *SCORE_COLUMNS])
        for t in trials:
            writer.writerow([*(f"{t.values[k]:g}" for k in keys), f"{t.scores.success:.4f}",
                             f"{t.scores.precision:.4f}", f"{t.scores.norm_precision:.4f}"])
