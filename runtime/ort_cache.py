"""On-disk cache of onnxruntime-optimised graphs, so a restart skips graph optimisation.

ORT_ENABLE_ALL rewrites convolutions into the NCHWc layout of the CPU it runs on, so a saved graph is only
valid for that instruction set and onnxruntime version: the cache key holds both, and the model's bytes.
The cache lives in $DADIFF_CACHE_DIR, else $XDG_CACHE_HOME/dadiff/ort, else ~/.cache/dadiff/ort;
DADIFF_CACHE_DIR=off turns it off. A cache that cannot be written (read-only image) is simply not used.
"""

from __future__ import annotations

import hashlib
import os
import platform
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from functools import cache
from pathlib import Path

OFF = {"", "0", "off", "none", "false"}
KEEP = 16  # cached graphs kept (least recently used go first): a drone holds a handful of models


def cache_root() -> Path | None:
    """The cache folder, or None when the user turned caching off."""
    configured = os.environ.get("DADIFF_CACHE_DIR")
    if configured is not None:
        return None if configured.strip().lower() in OFF else Path(configured)
    base = os.environ.get("XDG_CACHE_HOME")
    if not base:
        try:
            base = str(Path.home() / ".cache")
        except (KeyError, RuntimeError):  # a service user without a home: no cache
            return None
    return Path(base) / "dadiff" / "ort"


@cache
def cpu_signature() -> str:
    """Machine type plus the CPU feature flags (what the NCHWc kernels were chosen for)."""
    flags = ""
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as info:
            flags = next((line for line in info if line.startswith(("flags", "Features"))), "")
    except OSError:
        pass
    return f"{platform.machine()} {' '.join(sorted(flags.split(':', 1)[-1].split()))}"


def file_sha256(path: Path) -> str:
    """Hex sha256 of a file, read in 1 MiB blocks (models and checkpoints are hundreds of MB)."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def cached_model_path(model: Path, runtime_version: str) -> Path | None:
    """Where the optimised copy of `model` lives for this CPU and runtime; None when caching is off."""
    root = cache_root()
    if root is None:
        return None
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    if not os.access(root, os.W_OK):
        return None
    key = hashlib.sha256(f"{file_sha256(model)} {runtime_version} {cpu_signature()}".encode()).hexdigest()
    path = root / f"{model.stem}-{key[:24]}.onnx"
    if path.is_file():
        path.touch()  # most recently used
    return path


def prune(root: Path, keep: int = KEEP) -> None:
    """Remove all but the `keep` most recently used cached graphs.

    Another process may prune the same folder at the same time: an entry that vanishes between the listing
    and its stat is skipped, so that one process's pruning never fails another's model load.
    """
    entries = []
    for path in root.glob("*.onnx"):
        try:
            entries.append((path.stat().st_mtime, path))
        except OSError:
            continue
    entries.sort(reverse=True)
    for _, old in entries[keep:]:
        old.unlink(missing_ok=True)


@contextmanager
def store_atomically(target: Path) -> Iterator[Path]:
    """A temporary path to write to; renamed to `target` when the block succeeds, removed otherwise.

    Two processes starting at once each write their own file, and readers never see half a graph.
    """
    fd, name = tempfile.mkstemp(prefix=f".{target.stem}-", suffix=".onnx", dir=target.parent)
    os.close(fd)
    staging = Path(name)
    try:
        yield staging
        if staging.stat().st_size > 0:
            os.replace(staging, target)
            prune(target.parent)
    finally:
        staging.unlink(missing_ok=True)
