"""Models shipped with dadiff, and resolution of `--model` arguments to a model folder.

A shipped model is a folder under this package holding `template.onnx` and `search.onnx` (the layout of
docs/model-format.md) and its MODEL_CARD.md. `DEFAULT_MODEL` names the one used when no model is given:
the trained dadiff-mobile in models/dadiff-mobile. Its checkpoint.pt (what dadiff-export needs to re-make the
graphs) stays in the repository, out of the installed package: the runtime reads only the graphs.
"""

from __future__ import annotations

from pathlib import Path

from dadiff.runtime.errors import DadiffError

__all__ = ["DEFAULT_MODEL", "GRAPH_FILES", "ModelNotFoundError", "list_models", "resolve"]

DEFAULT_MODEL = "dadiff-mobile"
GRAPH_FILES = ("template.onnx", "search.onnx")
_HERE = Path(__file__).resolve().parent


class ModelNotFoundError(DadiffError, LookupError):
    """No model folder matches the given name or path (message is one line)."""


def _is_model_folder(folder: Path) -> bool:
    return all((folder / name).is_file() for name in GRAPH_FILES)


def list_models() -> list[str]:
    """Names of the shipped models, sorted."""
    return sorted(p.name for p in _HERE.iterdir() if p.is_dir() and _is_model_folder(p))


def resolve(name_or_path: str | Path | None) -> Path:
    """Model folder for a folder path, an .onnx file inside one, a shipped model name, or None (default).

    Only existence is checked here; the runtime reports missing or broken graph files when it loads them.
    """
    if name_or_path is None:
        if DEFAULT_MODEL in list_models():
            return _HERE / DEFAULT_MODEL
        raise ModelNotFoundError(
            "no trained default model is shipped yet; pass --model with a folder written by dadiff-export"
        )
    path = Path(name_or_path).expanduser()
    if path.is_dir():
        return path
    if path.is_file():
        if path.suffix.lower() == ".onnx":
            return path.parent
        raise ModelNotFoundError(f"{path}: not a model folder or an .onnx file")
    text = str(name_or_path)
    if text in list_models():
        return _HERE / text
    shipped = ", ".join(list_models()) or "none yet"
    raise ModelNotFoundError(
        f"model '{text}' not found: no such folder or .onnx file, "
        f"and not a shipped model (shipped: {shipped})"
    )
