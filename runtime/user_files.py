"""Reading a file the user named (a config, a key, ground truth, detections): a regular file, with a size bound.

A FIFO with no writer would block a reader forever, and `/dev/zero` would grow memory until the kernel's OOM
killer stops the process. Such a file is refused here with an `OSError` whose `strerror` says why, so every
reader's existing "cannot read" handling reports it in one line.
"""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

from .errors import DadiffError

MIB = 1 << 20
SETTINGS_LIMIT = 1 * MIB  # configs and keys: a few hundred bytes in practice
DATA_LIMIT = 256 * MIB  # ground truth, detections, indexes: the longest real ones are a few MiB

_KINDS = ((stat.S_ISDIR, "a folder"), (stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


class UnreadableFile(DadiffError, OSError):
    """A file that is not a regular file or is larger than its bound (errno EINVAL or EFBIG)."""


def _kind(mode: int) -> str:
    return next((name for test, name in _KINDS if test(mode)), "not a plain file")


def kind_of(path: Path) -> str:
    """What `path` is when it is not a regular file: 'a FIFO', 'a character device', ... (links followed)."""
    return _kind(path.stat().st_mode)


def read_user_bytes(path: str | Path, limit: int = DATA_LIMIT) -> bytes:
    """The bytes of `path`, a regular file of at most `limit` bytes; `OSError` otherwise (unreadable too)."""
    # O_NONBLOCK: opening a FIFO returns at once instead of waiting for a writer; no effect on a regular file
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise UnreadableFile(errno.EINVAL, f"{_kind(mode)}, not a regular file", str(path))
        with os.fdopen(fd, "rb", closefd=False) as f:
            data = f.read(limit + 1)  # the size stat gives can change under us: the read itself is bounded
    finally:
        os.close(fd)
    if len(data) > limit:
        raise UnreadableFile(errno.EFBIG, f"larger than {limit / MIB:g} MiB, the most this file may be", str(path))
    return data


def read_user_text(path: str | Path, limit: int = DATA_LIMIT, encoding: str = "utf-8-sig",
                   errors: str = "strict") -> str:
    """`read_user_bytes` decoded; `UnicodeDecodeError` for a file that is not text (utf-8-sig: a byte-order
    mark, as Notepad writes one, is dropped)."""
    return read_user_bytes(path, limit).decode(encoding, errors)
