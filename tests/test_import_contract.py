"""The architecture's import rules (pyproject's [tool.importlinter] contracts) hold: the onboard side never
imports torch, onnx or the training side; only runtime/commands joins runtime and drone; evaluation and data
making are read only by those the contracts name."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def test_import_contracts_are_kept(capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    try:
        from importlinter.cli import lint_imports
    except ImportError:
        pytest.fail("import-linter is not installed: pip install -e '.[dev]' (or '.[test]')")
    monkeypatch.chdir(REPO)
    code = lint_imports(config_filename=os.fspath(REPO / "pyproject.toml"), no_cache=True, no_logo=True)
    report = capsys.readouterr().out
    assert code == 0, report
    assert "0 broken" in report, report
