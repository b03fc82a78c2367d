"""Writing files so that a full disk or an I/O error never leaves a damaged one behind.

Two ways, one per kind of output: `RowFile` for logs that grow a line at a time (a failed write leaves the
file ending at its last whole line), `write_atomic` for files written at once (a failure leaves the old file,
or none, and no temporary file). Both name the file in the OSError they raise: a write that fails on a full
disk carries no file name of its own, and `No space left on device` alone does not tell the user where.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path


def named(exc: OSError, path: str | Path) -> OSError:
    """`exc` with `path` as its file name (errno and reason kept), for a one-line `path: reason` message."""
    return OSError(exc.errno or errno.EIO, exc.strerror or str(exc), str(path))


class RowFile:
    """A text file written one whole line (or row) per `write`, each straight to the kernel (no buffer left
    to lose in a crash). A write that fails part-way cuts the file back to its last whole line and raises
    OSError naming the file, so a CSV never ends in half a row nor a JSON Lines file in half an object.

    File-like enough for `csv.writer` and `logging.StreamHandler` (write, flush, seek, tell, close).
    """

    def __init__(self, path: str | Path, mode: str = "w") -> None:
        if mode not in ("w", "a"):
            raise ValueError(f"mode must be 'w' or 'a', got {mode!r}")
        self.path = Path(path)
        self._raw = open(self.path, mode + "b", buffering=0)  # noqa: SIM115 - closed in close()
        self._raw.seek(0, os.SEEK_END)
        self.size = self._raw.tell()  # bytes of whole lines on disk

    @property
    def closed(self) -> bool:
        return self._raw.closed

    def write(self, text: str) -> int:
        encoded = text.encode()
        data = memoryview(encoded)
        try:
            while data:
                data = data[self._raw.write(data) or 0:]
        except BaseException as exc:  # a signal between two partial writes too
            self._cut()
            if isinstance(exc, OSError):
                raise named(exc, self.path) from None
            raise
        self.size += len(encoded)
        return len(text)

    def _cut(self) -> None:
        """Back to the last whole line (freeing the space the cut part took); the write's error is the news."""
        try:
            os.ftruncate(self._raw.fileno(), self.size)
            self._raw.seek(self.size)
        except OSError:
            pass

    def flush(self) -> None:
        """Nothing is buffered: each write went to the kernel."""

    def seek(self, offset: int, whence: int = os.SEEK_SET) -> int:
        return self._raw.seek(offset, whence)

    def tell(self) -> int:
        return self._raw.tell()

    def close(self) -> None:
        self._raw.close()

    def __enter__(self) -> RowFile:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def write_atomic(path: str | Path, data: str | bytes) -> None:
    """Write `data` to a temporary file beside `path`, then rename it over `path`: readers see the old file or
    the whole new one. On failure the temporary file is removed and the OSError names `path`."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(tmp, "wb") as f:
            f.write(data.encode() if isinstance(data, str) else data)
        os.replace(tmp, path)
    except BaseException as exc:  # Ctrl-C too: never leave the temporary file behind
        tmp.unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise named(exc, path) from None
        raise
