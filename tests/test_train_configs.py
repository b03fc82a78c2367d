"""The training configs in export/configs: each one loads, builds its network config and starts from
something that exists (ImageNet, a committed state in export/resume, or another config's final.pt)."""

from __future__ import annotations

import re
from fnmatch import fnmatch
from functools import cache
from pathlib import Path

import pytest

pytest.importorskip("torch")

from dadiff.export.train import TrainConfig, model_config  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
CONFIGS = sorted((REPO / "export" / "configs").glob("*.toml"))


@cache
def _outs() -> dict[str, list[str]]:
    """Run folder -> the configs writing it (loaded here, not at collection: a broken config fails its own test)."""
    outs: dict[str, list[str]] = {}
    for path in CONFIGS:
        try:
            outs.setdefault(TrainConfig.from_toml(path).out, []).append(path.name)
        except ValueError:
            continue
    return outs


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.stem)
def test_config_loads_and_starts_from_something_that_exists(path: Path) -> None:
    cfg = TrainConfig.from_toml(path)
    assert model_config(cfg).family == cfg.family
    if cfg.init == "imagenet":
        return
    init = Path(cfg.init)
    chained = init.name == "final.pt" and str(init.parent) in _outs() and str(init.parent) != cfg.out
    assert (REPO / init).is_file() or chained, f"{path.name}: init {cfg.init} is neither committed nor a run's final.pt"


def test_every_config_writes_its_own_run_folder() -> None:
    shared = {out: names for out, names in _outs().items() if len(names) > 1}
    assert not shared, f"configs writing the same run folder: {shared}"


def _named_patterns(text: str) -> list[str]:
    """Config names a document writes out, or as `mobile-*-x.toml` / `mobile-{dadiff,ablation}-x.toml`."""
    patterns = []
    for token in re.findall(r"[\w*{},.-]+\.toml", text):
        head, brace, rest = token.partition("{")
        if not brace:
            patterns.append(token)
            continue
        options, _, tail = rest.partition("}")
        patterns += [head + option + tail for option in options.split(",")]
    return patterns


def test_docs_name_every_config() -> None:
    """README or a page of docs/ (training.md, the lab notebook) says what each config is for."""
    text = "\n".join(p.read_text() for p in [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))])
    missing = [p.name for p in CONFIGS if not any(fnmatch(p.name, pat) for pat in _named_patterns(text))]
    assert not missing, f"neither README nor docs/ names {missing}"
