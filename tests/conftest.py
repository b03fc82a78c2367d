"""Shared fixtures: the official fixture folder and small checkpoints made on the fly."""

from __future__ import annotations

import ast
import inspect
import json
import os
import signal
import textwrap
from functools import cache
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
FIXTURES = REPO.parent / "shared" / "fixtures" / "official-dadiff-ban"
GAT_FIXTURES = REPO.parent / "shared" / "fixtures" / "official-dadiff-gat"
TESTS = Path(__file__).resolve().parent


def _imports_torch(tree: ast.AST) -> bool:
    """`import torch`, `from torch... import` or `pytest.importorskip("torch")` anywhere in `tree`."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Import) and any(a.name.split(".")[0] == "torch" for a in node.names):
            return True
        if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "torch":
            return True
        if (isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", "")) == "importorskip"
                and node.args and isinstance(node.args[0], ast.Constant) and node.args[0].value == "torch"):
            return True
    return False


def _defined_in_tests(obj: object) -> bool:
    path = getattr(getattr(obj, "__code__", None), "co_filename", None)
    return path is not None and Path(path).resolve().is_relative_to(TESTS)


@cache
def _function_needs_torch(function) -> bool:
    """The function, or a helper of the test folder it names (followed through), imports torch."""
    try:
        definition = ast.parse(textwrap.dedent(inspect.getsource(function))).body[0]
    except (OSError, TypeError, SyntaxError):
        return False
    tree = ast.Module(body=getattr(definition, "body", [definition]), type_ignores=[])  # not its decorators
    if _imports_torch(tree):
        return True
    names = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)}
    helpers = (function.__globals__.get(name) for name in names)
    return any(inspect.isfunction(h) and h is not function and _defined_in_tests(h) and _function_needs_torch(h)
               for h in helpers)


@cache
def _module_needs_torch(path: str) -> bool:
    """The module imports torch at its top level (outside functions and classes)."""
    body = ast.parse(Path(path).read_text()).body
    top = [s for s in body if not isinstance(s, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef)]
    return _imports_torch(ast.Module(body=top, type_ignores=[]))


def _needs_torch(item: pytest.Item) -> bool:
    """What the test, its module, its fixtures or the test folder's helpers they call import decides it."""
    if _module_needs_torch(str(item.path)) or _function_needs_torch(getattr(item, "function", None)):
        return True
    fixturedefs = getattr(item, "_fixtureinfo", None)
    for name in item.fixturenames:
        for fixturedef in (fixturedefs.name2fixturedefs.get(name, ()) if fixturedefs else ()):
            if _defined_in_tests(fixturedef.func) and _function_needs_torch(fixturedef.func):
                return True
    return False


def slow_tests() -> set[str]:
    """`file::function` of each test listed in tests/slow-tests.txt."""
    lines = (TESTS / "slow-tests.txt").read_text().splitlines()
    return {line.strip() for line in lines if line.strip() and not line.startswith("#")}


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Mark `torch` every test that needs it, so that `-m "not torch"` is the companion computer's install, and
    `slow` those and the tests listed in slow-tests.txt, so that `-m "not slow"` is the quick check. A torch test
    builds, trains or exports a network (seconds each here, and which one pays the warm-up depends on the order)."""
    slow = slow_tests()
    for item in items:
        if _needs_torch(item):
            item.add_marker(pytest.mark.torch)
            item.add_marker(pytest.mark.slow)
        elif f"{item.path.name}::{getattr(item, 'originalname', item.name)}" in slow:
            item.add_marker(pytest.mark.slow)


if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:  # run as a background job: the Ctrl-C tests need Python's
    signal.signal(signal.SIGINT, signal.default_int_handler)  # handler here, and their children the default


def hangup_as_in_a_session() -> None:
    """In a child process (`preexec_fn`): SIGHUP back to its default, as in a login session. A test run
    started under `nohup` passes its ignored SIGHUP on, and the commands keep an ignored SIGHUP ignored on
    purpose, so a test of what a dropped SSH session does must give the child a SIGHUP that acts."""
    signal.signal(signal.SIGHUP, signal.SIG_DFL)

def fixture_dir(folder: Path = FIXTURES) -> Path:
    if not folder.is_dir():
        pytest.skip(f"official fixtures not found at {folder}")
    return folder


def gat_fixture_dir() -> Path:
    return fixture_dir(GAT_FIXTURES)


@pytest.fixture(scope="session", autouse=True)
def ort_cache_dir(tmp_path_factory) -> Path:
    """Optimised-graph cache of the runtime in a temporary folder (subprocesses inherit it), not ~/.cache."""
    path = tmp_path_factory.mktemp("ort-cache")
    previous = os.environ.get("DADIFF_CACHE_DIR")
    os.environ["DADIFF_CACHE_DIR"] = str(path)
    yield path
    if previous is None:
        os.environ.pop("DADIFF_CACHE_DIR", None)
    else:
        os.environ["DADIFF_CACHE_DIR"] = previous


@pytest.fixture(scope="session")
def ban_shapes() -> dict[str, list[int]]:
    with open(fixture_dir() / "dadiff_ban_state_dict_shapes.json") as f:
        return json.load(f)


@pytest.fixture(scope="session")
def gat_shapes() -> dict[str, list[int]]:
    with open(gat_fixture_dir() / "dadiff_gat_state_dict_shapes.json") as f:
        return json.load(f)


@pytest.fixture(scope="session")
def gat_frames() -> tuple[list, object]:
    """The GAT tracker fixture's 20 generated frames and their boxes (its make_frames.py, numpy only)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("make_frames", gat_fixture_dir() / "make_frames.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.make_frames()


@pytest.fixture(scope="session")
def gat_checkpoint(tmp_path_factory, gat_shapes) -> Path:
    """The GAT fixture's procedural weights as a released-format checkpoint (`module.` prefixes), once per run."""
    pytest.importorskip("torch")
    from dadiff.export.procedural import write_released_checkpoint

    path = tmp_path_factory.mktemp("gat") / "checkpoint_e45.pth"
    write_released_checkpoint(str(path), gat_shapes, module_prefix=True)
    return path


@pytest.fixture(scope="session")
def gat_loaded(gat_checkpoint):
    """That checkpoint loaded (strict, weights-only) into the network: the large GAT model is built once per run."""
    from dadiff.export.checkpoint import load_checkpoint

    return load_checkpoint(gat_checkpoint)


@pytest.fixture(scope="session")
def gat_model_dir(tmp_path_factory, gat_loaded):
    """The GAT checkpoint exported once per run (model folder and the export report)."""
    from dadiff.export.onnx_export import export_model

    out = tmp_path_factory.mktemp("models") / "gat"
    report = export_model(gat_loaded, out, "gat-procedural")
    return out, report


@pytest.fixture(scope="session")
def lite_checkpoint(tmp_path_factory) -> Path:
    """A freshly initialised dadiff-lite checkpoint (ImageNet backbone, the rest untrained) in our format."""
    torch = pytest.importorskip("torch")
    from dadiff.export.checkpoint import save_checkpoint
    from dadiff.export.config import lite_config
    from dadiff.export.network import build_model

    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("ckpt") / "lite.pt"
    save_checkpoint(path, build_model(lite_config(), pretrained_backbone=True))
    return path


@pytest.fixture(scope="session")
def mobile_checkpoint(tmp_path_factory) -> Path:
    """A freshly initialised dadiff-mobile checkpoint (no pretrained backbone) in our format."""
    torch = pytest.importorskip("torch")
    from dadiff.export.checkpoint import save_checkpoint
    from dadiff.export.config import mobile_config
    from dadiff.export.network import build_model

    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("ckpt") / "mobile.pt"
    save_checkpoint(path, build_model(mobile_config()))
    return path


@pytest.fixture(scope="session")
def lite_model_dir(tmp_path_factory, lite_checkpoint) -> Path:
    """The lite checkpoint exported to a model folder (template.onnx + search.onnx)."""
    from dadiff.export.checkpoint import load_checkpoint
    from dadiff.export.onnx_export import export_model

    out = tmp_path_factory.mktemp("models") / "lite"
    export_model(load_checkpoint(lite_checkpoint), out, "test-lite")
    return out


@pytest.fixture
def no_shipped_model(tmp_path, monkeypatch) -> None:
    """Pretend no trained default ships (the state before one was trained), to test that message."""
    import dadiff.models

    empty = tmp_path / "no-models"
    empty.mkdir()
    monkeypatch.setattr(dadiff.models, "_HERE", empty)


def random_crops():
    """A seeded random template (127) and search (255) crop, raw pixels 0..255, as torch tensors."""
    import torch

    g = torch.Generator().manual_seed(0)
    return torch.rand(1, 3, 127, 127, generator=g) * 255, torch.rand(1, 3, 255, 255, generator=g) * 255
