"""Every exception class the project defines is a DadiffError, so that an entry point catches one class."""

from __future__ import annotations

import importlib
import inspect
import pkgutil

import pytest

from dadiff.runtime.errors import DadiffError, InputError, ModelError

PACKAGES = ("dadiff.runtime", "dadiff.drone", "dadiff.export", "dadiff.models")
OPTIONAL = {"torch", "torchvision", "onnx", "onnxscript"}  # the export extra: absent on the companion computer


def _modules() -> list[str]:
    names = []
    for package in PACKAGES:
        root = importlib.import_module(package)
        names.append(package)
        names += [m.name for m in pkgutil.walk_packages(root.__path__, f"{package}.")]
    return names


def _project_exceptions() -> list[type[BaseException]]:
    found = []
    for name in _modules():
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:  # a torch-free install: the export side cannot load, nothing else
            if (exc.name or "").split(".")[0] not in OPTIONAL:
                raise
            continue
        found += [cls for _, cls in inspect.getmembers(module, inspect.isclass)
                  if cls.__module__ == name and issubclass(cls, BaseException)]
    return found


def test_every_project_exception_is_a_dadiff_error():
    classes = _project_exceptions()
    names = {cls.__name__ for cls in classes}
    assert {"ModelError", "InputError", "SourceError", "OutputError", "ConfigError", "SigningKeyError"} <= names
    outside = [f"{cls.__module__}.{cls.__qualname__}" for cls in classes if not issubclass(cls, DadiffError)]
    assert outside == []


def test_the_builtin_bases_callers_relied_on_stay():
    from dadiff.models import ModelNotFoundError
    from dadiff.runtime.user_files import UnreadableFile

    assert issubclass(ModelError, ValueError) and issubclass(InputError, ValueError)
    assert issubclass(ModelNotFoundError, LookupError)
    assert issubclass(UnreadableFile, OSError)
    with pytest.raises(ValueError):
        raise ModelError("a model error is still caught as a ValueError")


def test_an_entry_point_reports_any_dadiff_error_in_one_line(monkeypatch, capsys):
    from dadiff.runtime.commands import bench as bench_cli

    class NewProblem(DadiffError):
        pass

    def fail(args):
        raise NewProblem("clip.mp4: something a user can fix")

    monkeypatch.setattr(bench_cli, "run", fail)
    assert bench_cli.main(["--max-frames", "2"]) == 2
    assert capsys.readouterr().err == "dadiff-bench: error: clip.mp4: something a user can fix\n"
