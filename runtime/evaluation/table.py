"""One Markdown table over several sets: each tracker's success and precision per set, its paired bootstrap
interval against a baseline, and the spread over seeds where one model was trained several times.

A set is (label, dataset, sequence pattern, results folder `<results>/<dataset>`); every tracker folder under it is
scored on the sequences the pattern selects. Folders named `NAME@SEED` (e.g. `dadiff-mobile@1`, `dadiff-mobile@2`,
from `dadiff-eval run --name`) are one model trained with several seeds: the cell shows their mean ± standard
deviation, and the bootstrap compares their per-sequence mean with the baseline's.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..datamaking.datasets import load_dataset
from ..errors import InputError
from .evaluate import TrackerScores, result_folders, score_folder
from .metrics import PairedDifference, paired_difference

SEED_MARK = "@"  # NAME@SEED: one of several seeds of the model NAME


@dataclass(frozen=True)
class TableSet:
    """One column of the table: which sequences of which dataset, and where the trackers' results are."""

    label: str
    dataset: Path
    pattern: str
    results: Path


@dataclass(frozen=True)
class Cell:
    """One tracker (all its seeds) on one set."""

    success: float
    precision: float
    success_spread: float | None  # standard deviation over seeds; None for a single run
    precision_spread: float | None
    runs: int
    against: PairedDifference | None  # success minus the baseline's; None for the baseline itself


def model_name(folder_name: str) -> str:
    """The model a result folder belongs to: `NAME@SEED` -> `NAME`."""
    return folder_name.split(SEED_MARK, 1)[0]


def _per_sequence(runs: Sequence[TrackerScores], names: list[str]) -> list[float]:
    """Each sequence's success, averaged over the runs (seeds)."""
    return [float(np.mean([run.sequences[n].success.mean() for run in runs])) for n in names]


def _spread(values: list[float]) -> float | None:
    return float(np.std(values, ddof=1)) if len(values) > 1 else None


def score_set(table_set: TableSet, baseline: str, first: int = 0) -> dict[str, Cell]:
    """Every model under the set's results folder, scored on its sequences from frame `first` on, with its interval
    against `baseline`."""
    dataset = load_dataset(table_set.dataset).select([table_set.pattern])
    models: dict[str, list[TrackerScores]] = {}
    for name, folder in result_folders([table_set.results], dataset):
        models.setdefault(model_name(name), []).append(score_folder(dataset, folder, name, first))
    if baseline not in models:
        raise InputError(f"--against {baseline}: no such tracker in {table_set.results} (set {table_set.label}: "
                         f"{', '.join(models)})")
    names = [s.name for s in dataset.sequences]
    base = _per_sequence(models[baseline], names)
    cells = {}
    for model, runs in models.items():
        success = [run.overall.success for run in runs]
        precision = [run.overall.precision for run in runs]
        against = None if model == baseline else paired_difference(_per_sequence(runs, names), base)
        cells[model] = Cell(float(np.mean(success)), float(np.mean(precision)), _spread(success), _spread(precision),
                            len(runs), against)
    return cells


def _value(mean: float, spread: float | None) -> str:
    return f"{mean:.3f}" if spread is None else f"{mean:.3f} ± {spread:.3f}"


def format_cell(cell: Cell | None) -> str:
    if cell is None:
        return "–"
    text = f"{_value(cell.success, cell.success_spread)} / {_value(cell.precision, cell.precision_spread)}"
    if cell.against is None:
        return text + " (baseline)"
    d = cell.against
    return text + f" ({d.mean:+.3f} [{d.low:+.3f}, {d.high:+.3f}])"


def markdown_table(sets: Sequence[TableSet], cells: Sequence[dict[str, Cell]], baseline: str,
                   trackers: Sequence[str] | None = None, first: int = 0) -> str:
    """Rows: trackers (`trackers` in that order, else every one found, baseline first); columns: the sets."""
    found = list(dict.fromkeys(name for per_set in cells for name in per_set))
    rows = list(trackers) if trackers else [baseline, *(n for n in found if n != baseline)]
    for name in rows:
        if name not in found:
            raise InputError(f"--trackers {name}: no such tracker in any set ({', '.join(found)})")
    counts = [{name: per_set[name].runs for name in per_set} for per_set in cells]
    lines = [f"| tracker | {' | '.join(f'{s.label} ({s.pattern})' for s in sets)} |",
             "|---|" + "---|" * len(sets)]
    for name in rows:
        seeds = max(c.get(name, 1) for c in counts)
        label = name if seeds == 1 else f"{name} ({seeds} seeds)"
        lines.append(f"| {label} | {' | '.join(format_cell(per_set.get(name)) for per_set in cells)} |")
    lines.append("")
    lines.append(f"Success (area under the success plot) / precision at 20 px; in brackets success minus {baseline}'s "
                 "with its 95 % paired bootstrap interval over the set's sequences; ± the standard deviation over "
                 f"seeds (result folders NAME{SEED_MARK}SEED)"
                 + (", over frames after the init frame." if first else "."))
    return "\n".join(lines)
