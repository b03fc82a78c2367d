"""The `torch` marker set by tests/conftest.py: `-m "not torch"` (the companion computer's install) relies on it."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import TESTS, _function_needs_torch, _module_needs_torch, random_crops, slow_tests


def _torch_inside() -> None:
    import torch  # noqa: F401


def _torch_skipped() -> None:
    pytest.importorskip("torch")


def _calls_a_torch_helper() -> None:
    _torch_inside()


def _numpy_only() -> None:
    import numpy  # noqa: F401


@pytest.mark.parametrize(("function", "needs"), [
    (_torch_inside, True), (_torch_skipped, True), (_calls_a_torch_helper, True), (_numpy_only, False)])
def test_a_function_needs_torch_by_what_it_imports(function, needs: bool) -> None:
    assert _function_needs_torch(function) is needs


def test_a_module_needs_torch_by_its_top_level_only(tmp_path: Path) -> None:
    top = tmp_path / "top.py"
    top.write_text('import pytest\ntorch = pytest.importorskip("torch")\n')
    inner = tmp_path / "inner.py"
    inner.write_text("def f():\n    import torch\n")
    assert _module_needs_torch(str(top)) and not _module_needs_torch(str(inner))


def test_random_crops_are_seeded() -> None:
    """Needs torch only through conftest's helper: the marker follows the call (see the next test)."""
    first, second = random_crops(), random_crops()
    assert all(bool((a == b).all()) for a, b in zip(first, second, strict=True))


def test_the_marker_lands_on_collected_tests() -> None:
    """Collected with `-m torch`, this module yields exactly the test above: the hook marks it and only it."""
    result = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider",
                             "-m", "torch", __file__], capture_output=True, text=True, timeout=120, cwd=TESTS.parent)
    selected = [line for line in result.stdout.splitlines() if "::" in line]
    assert [line.split("::")[1] for line in selected] == ["test_random_crops_are_seeded"], result.stdout


def _first_torch_import(path: Path) -> ast.stmt | None:
    for statement in ast.parse(path.read_text()).body:
        if isinstance(statement, ast.FunctionDef | ast.ClassDef):
            continue
        names = [a.name for a in statement.names] if isinstance(statement, ast.Import) else []
        if isinstance(statement, ast.ImportFrom):
            names = [statement.module or ""]
        if any(n.split(".")[0] == "torch" for n in names) or "importorskip" in ast.unparse(statement) \
                and "torch" in ast.unparse(statement):
            return statement
    return None


def test_test_modules_import_torch_only_through_importorskip() -> None:
    """A bare top-level `import torch` stops collection on the companion computer's install (no torch)."""
    bare = []
    for path in sorted(TESTS.glob("*.py")):
        statement = _first_torch_import(path)
        if statement is not None and "importorskip" not in ast.unparse(statement):
            bare.append(f"{path.name}:{statement.lineno}")
    assert not bare, f"import torch through pytest.importorskip at the top of: {bare}"


def test_every_slow_entry_names_a_test() -> None:
    """A test renamed or removed leaves no stale line in slow-tests.txt (it would mark nothing)."""
    missing = []
    for entry in sorted(slow_tests()):
        file, function = entry.split("::")
        path = TESTS / file
        tree = ast.parse(path.read_text()) if path.is_file() else ast.Module(body=[], type_ignores=[])
        names = {n.name for n in ast.walk(tree) if isinstance(n, ast.FunctionDef)}
        if function not in names:
            missing.append(entry)
    assert not missing, f"tests/slow-tests.txt names tests that are not there: {missing}"
