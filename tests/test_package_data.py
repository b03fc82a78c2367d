"""The installed package carries the graphs the torch-free runtime reads, and no PyTorch checkpoint (those
stay in the repository for dadiff-export)."""

from __future__ import annotations

import tomllib
from fnmatch import fnmatch
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _ships(relative: str) -> bool:
    """Whether setuptools' package-data patterns of pyproject.toml put models/<relative> into the wheel."""
    setup = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    included = setup.get("package-data", {}).get("dadiff.models", [])
    excluded = setup.get("exclude-package-data", {}).get("dadiff.models", [])
    return any(fnmatch(relative, p) for p in included) and not any(fnmatch(relative, p) for p in excluded)


def test_the_wheel_ships_graphs_and_no_checkpoints() -> None:
    folders = [p for p in (REPO / "models").iterdir() if (p / "search.onnx").is_file()]
    assert [p.name for p in folders] == ["dadiff-mobile"]  # dadiff-lite's weights retired
    for folder in folders:
        for graph in ("template.onnx", "search.onnx"):
            assert _ships(f"{folder.name}/{graph}")
        assert (folder / "checkpoint.pt").is_file()  # in the repository, for dadiff-export
        assert not _ships(f"{folder.name}/checkpoint.pt")  # was: 1.6 MB of PyTorch in the runtime's wheel
