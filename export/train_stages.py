"""A recipe in stages: one config whose `[[stages]]` run in order, each continuing from the one before.

A model's recipe is often several training runs: a stage-1 tracker, the DaDiff block joined to it,
fine-tuning on new data. Written as stages of one config, `dadiff-train --config FILE` runs them all, each
in its own folder (`<out>/NN-name`), and hands each stage's final state to the next, so no state is copied by hand; run
again, it skips finished stages and resumes the one that was stopped. The `[train]` table holds the keys
every stage shares; a stage lists what it changes (each key replaces the shared value whole) and:

- `name`: the stage's name (its folder's), lower-case letters, digits and '-';
- `resume = true`: go on with the previous stage's training state (step, optimiser, schedule to this
  stage's `steps`) instead of a new run from its weights (`init`);
- `stop_at = N`: stop this stage's schedule at step N; the next stage continues from that step's state.

This module reads and checks the stage list (no torch); export/train.py builds and runs the stages.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

STAGES = "stages"
STAGE_KEYS = ("name", "resume", "stop_at")  # the stage's own keys; the rest are training config keys
NAME = re.compile(r"[a-z0-9][a-z0-9-]*")


@dataclass(frozen=True)
class StagePlan:
    """One stage as written: its name, how it continues, and the training keys it changes."""

    index: int                 # 1-based
    name: str
    keys: dict[str, Any]
    resume: bool = False
    stop_at: int | None = None

    def label(self, path: str | Path) -> str:
        """How errors name the stage: the file, then the stage."""
        return f"{path}: stage {self.index} '{self.name}'"

    def folder(self, out: str | Path) -> Path:
        return Path(out) / f"{self.index:02d}-{self.name}"


def plan_stages(stages: Any, path: str | Path, known: set[str]) -> list[StagePlan]:
    """The `stages` list of the config in `path`, checked; ValueError naming the file, the stage and the key.

    `known` holds the training config keys a stage may set."""
    if not isinstance(stages, list) or not stages or not all(isinstance(s, dict) for s in stages):
        raise ValueError(f"{path}: '{STAGES}' must be a list of tables ([[stages]]), got {stages!r:.80}")
    plans: list[StagePlan] = []
    for index, raw in enumerate(stages, 1):
        keys = dict(raw)
        name = keys.pop("name", None)
        where = f"{path}: stage {index}"
        if not isinstance(name, str) or not NAME.fullmatch(name):
            raise ValueError(f"{where}: 'name' is {name!r}; expected lower-case letters, digits and '-'")
        if any(p.name == name for p in plans):
            raise ValueError(f"{where}: 'name' {name!r} is used by an earlier stage; each stage needs its own")
        where = f"{where} '{name}'"
        resume, stop_at = keys.pop("resume", False), keys.pop("stop_at", None)
        unknown = sorted(set(keys) - known)
        if unknown:
            raise ValueError(f"{where}: unknown keys: {', '.join(unknown)} (stage keys: {', '.join(STAGE_KEYS)}; "
                             f"dadiff-train --help lists the rest)")
        if "out" in keys:
            raise ValueError(f"{where}: 'out' is set by the recipe (<out>/NN-name); set 'out' in [train] instead")
        if index > 1 and "init" in keys:
            raise ValueError(f"{where}: 'init' is set by the previous stage (its final state); drop it here")
        if not isinstance(resume, bool):
            raise ValueError(f"{where}: 'resume' is {resume!r}; expected true or false")
        if resume and index == 1:
            raise ValueError(f"{where}: 'resume' needs a previous stage to resume; the first stage starts from 'init'")
        if stop_at is not None and (isinstance(stop_at, bool) or not isinstance(stop_at, int) or stop_at < 1):
            raise ValueError(f"{where}: 'stop_at' is {stop_at!r}; expected a step number >= 1")
        if stop_at is not None and index == len(stages):
            raise ValueError(f"{where}: 'stop_at' on the last stage: nothing continues from it; set 'steps' instead")
        plans.append(StagePlan(index, name, keys, resume, stop_at))
    return plans
