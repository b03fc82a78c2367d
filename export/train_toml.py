"""Reading a `dadiff-train` config file: its tables flattened, and `extends` followed (no torch needed).

A recipe that differs from another in a few keys names it with `extends = "other.toml"` (a path relative to
the extending file) and lists only what changes. Each key replaces the base's value whole (a `day` list or a
`model` table too): what a run uses is always written out in one of the files, never a merge of two lists.
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path
from typing import Any

from dadiff.runtime.user_files import SETTINGS_LIMIT, read_user_text

TABLES = ("train", "loss", "data", "output")  # tables whose keys count as top-level keys
EXTENDS = "extends"


def read_flat_toml(path: str | Path) -> dict[str, Any]:
    """The file's keys with the tables above flattened; ValueError naming the file when it cannot be read."""
    try:
        raw = tomllib.loads(read_user_text(path, SETTINGS_LIMIT, encoding="utf-8"))
    except FileNotFoundError:
        raise ValueError(f"{path}: no such config file") from None
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"{path}: invalid TOML ({e})") from None
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a text file (TOML must be UTF-8)") from None
    except OSError as e:
        raise ValueError(f"{path}: cannot read ({e.strerror or e})") from None
    flat: dict[str, Any] = {}
    for key, value in raw.items():
        if isinstance(value, dict) and key in TABLES:
            flat.update(value)
        else:
            flat[key] = value
    return flat


def config_chain(path: str | Path) -> list[tuple[Path, dict[str, Any]]]:
    """(file, its own keys) from the first base to `path` itself, `extends` removed; a loop or a base that
    is not a file is a ValueError naming the file that points at it."""
    chain: list[tuple[Path, dict[str, Any]]] = []
    current = Path(path)
    while True:
        own = read_flat_toml(current)
        base = own.pop(EXTENDS, None)
        chain.append((current, own))
        if base is None:
            return chain[::-1]
        if not isinstance(base, str) or not base.strip():
            raise ValueError(f"{current}: '{EXTENDS}' is {base!r}; expected the path of another config file")
        following = current.parent / base
        if not following.is_file():
            raise ValueError(f"{current}: '{EXTENDS}' names {base!r}, which is not a file ({following})")
        if any(following.resolve() == seen.resolve() for seen, _ in chain):
            loop = " -> ".join(str(p) for p, _ in chain)
            raise ValueError(f"{current}: '{EXTENDS}' loops: {loop} -> {following}")
        current = following


def key_file(path: str | Path, key: str) -> Path:
    """The file of `path`'s chain whose `key` the run uses (the last that sets it; `path` when none does), so
    an error found only as the run is set up names the file to edit."""
    for file, own in reversed(config_chain(path)):
        if key in own:
            return file
    return Path(path)


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)  # TOML's basic strings take JSON's escapes
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{k} = {_toml_value(v)}" for k, v in value.items()) + " }" if value else "{}"
    if value and all(isinstance(v, dict) for v in value):
        return "[" + ",\n    ".join(_toml_value(v) for v in value) + "]"
    return "[" + ", ".join(_toml_value(v) for v in value) + "]"


def format_toml(values: dict[str, Any], header: str = "[train]") -> str:
    """`values` as one table (`header`: [train], or [[stages]] for a stage) that reads back to the same keys;
    TOML has no null, so a key set to None is written as a comment."""
    lines = [header]
    for key, value in values.items():
        lines.append(f"# {key}: not set" if value is None else f"{key} = {_toml_value(value)}")
    return "\n".join(lines) + "\n"
