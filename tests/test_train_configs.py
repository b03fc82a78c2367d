"""The shipped training configs: each one (each stage of a staged recipe) loads, builds its network config and
starts from something that exists (ImageNet, a committed state in export/resume, another config's final.pt or
the previous stage's final state)."""

from __future__ import annotations

import re
from fnmatch import fnmatch
from functools import cache
from pathlib import Path

import pytest

pytest.importorskip("torch")

from dadiff.export.train import load_recipe, model_config  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
CONFIGS = sorted((REPO / "export" / "configs").glob("*.toml"))


@cache
def _outs() -> dict[str, list[str]]:
    """Run folder -> the configs writing it (loaded here, not at collection: a broken config fails its own test)."""
    outs: dict[str, list[str]] = {}
    for path in CONFIGS:
        try:
            for stage in load_recipe(path):
                outs.setdefault(stage.cfg.out, []).append(path.name)
        except ValueError:
            continue
    return outs


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.stem)
def test_config_loads_and_starts_from_something_that_exists(path: Path) -> None:
    recipe = load_recipe(path)
    for before, stage in zip([None, *recipe], recipe, strict=False):
        cfg = stage.cfg
        assert model_config(cfg).family == cfg.family
        if before is not None:  # a later stage starts from the previous one's final state
            assert cfg.init == str(before.result) and before.result.parent == Path(before.cfg.out)
            continue
        if cfg.init == "imagenet":
            continue
        init = Path(cfg.init)
        chained = init.name == "final.pt" and str(init.parent) in _outs() and str(init.parent) != cfg.out
        assert (REPO / init).is_file() or chained, f"{path.name}: init {cfg.init} is neither committed nor a final.pt"


def test_the_default_and_its_ablation_are_one_command_each() -> None:
    """The default's recipe from ImageNet, and its ablation the same stages without the DaDiff block."""
    default, ablation = (load_recipe(REPO / "export" / "configs" / name)
                         for name in ("dadiff-mobile.toml", "dadiff-mobile-no-dadiff.toml"))
    assert default[0].cfg.init == ablation[0].cfg.init == "imagenet" and len(default) == len(ablation) == 11
    assert default[-1].result.name == ablation[-1].result.name == "final-ema.pt"
    joined = next(i for i, stage in enumerate(default) if stage.cfg.stage == "dadiff")
    assert all(stage.cfg.stage == "baseline" for stage in ablation) and joined == 3
    for ours, twin in zip(default[joined:], ablation[joined:], strict=True):  # same data, seed, steps, schedule
        same = ("day", "seed", "steps", "lr", "night_pairs", "night_path_lamps", "lambda_side", "ema_decay")
        assert all(getattr(ours.cfg, k) == getattr(twin.cfg, k) for k in same), ours.plan.name
        assert ours.plan.stop_at == twin.plan.stop_at


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
