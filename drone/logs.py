"""Logging for the service: stdout (journald under systemd), an optional rotating file, and a rate limit
so that a stream of bad frames or packets cannot flood either."""

from __future__ import annotations

import logging
import logging.handlers
import os
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from dadiff.runtime.files import RowFile

LOGGER = "dadiff"


@contextmanager
def service_logging(level: str, added: list[logging.Handler]) -> Iterator[logging.Logger]:
    """`added` (from `log_handlers`) on the `dadiff` logger for the length of a run; the logger is
    restored afterwards, so that the service can also run inside another program or a test."""
    logger = logging.getLogger(LOGGER)
    saved = (list(logger.handlers), logger.level, logger.propagate)
    for handler in saved[0]:
        logger.removeHandler(handler)
    for handler in added:
        logger.addHandler(handler)
    logger.setLevel(level.upper())
    logger.propagate = False
    try:
        yield logger
    finally:
        for handler in added:
            logger.removeHandler(handler)
            handler.close()
        for handler in saved[0]:
            logger.addHandler(handler)
        logger.setLevel(saved[1])
        logger.propagate = saved[2]


def log_handlers(file: Path | None = None, max_bytes: int = 10_000_000, backups: int = 5) -> list[logging.Handler]:
    """stdout always, plus a RotatingFileHandler when `file` is given; OSError when it cannot be opened.

    Under systemd (JOURNAL_STREAM set) stdout lines carry no timestamp: journald adds its own.
    """
    plain = "%(levelname)s %(name)s: %(message)s"
    stamped = "%(asctime)s " + plain
    out = logging.StreamHandler(sys.stdout)
    out.setFormatter(logging.Formatter(plain if os.environ.get("JOURNAL_STREAM") else stamped))
    handlers: list[logging.Handler] = [out]
    if file is not None:
        rotating = LogFileHandler(file, maxBytes=max_bytes, backupCount=backups)
        rotating.setFormatter(logging.Formatter(stamped))
        handlers.append(rotating)
    return handlers


class LogFileHandler(logging.handlers.RotatingFileHandler):
    """The rotating log file, written through RowFile (a failed write leaves the file ending at its last
    whole line), that reports a write failure once instead of a `--- Logging error ---` traceback per record.

    On a full disk the stock handler prints a traceback on stderr for every record and loses the log without
    a word. Here: one warning line naming the file when writes start failing; the records still go to stdout
    (journald); each later record tries the file again, and the first that gets through is preceded in the
    file by a line saying how many records it missed.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.missed = 0

    def _open(self) -> RowFile:  # type: ignore[override]
        return RowFile(self.baseFilename, "a")

    def emit(self, record: logging.LogRecord) -> None:
        try:
            if self.missed:
                if self.stream is None:
                    self.stream = self._open()
                note = logging.LogRecord(record.name, logging.WARNING, __file__, 0, f"{self.missed} log records "
                                         "are missing here: the file could not be written", None, None)
                self.stream.write(self.format(note) + "\n")
                self.missed = 0
            if self.shouldRollover(record):
                self.doRollover()
            logging.FileHandler.emit(self, record)
        except OSError as exc:
            if not self.missed:
                print(f"dadiff-run: warning: {self.baseFilename}: cannot write the log ({exc.strerror or exc}); "
                      "records go to stdout only until it can be written again", file=sys.stderr, flush=True)
            self.missed += 1

    def handleError(self, record: logging.LogRecord) -> None:
        """FileHandler.emit hands its OSError here: raise it to `emit`, which reports it once."""
        exc = sys.exc_info()[1]
        if isinstance(exc, OSError):
            raise exc
        super().handleError(record)


class Throttle:
    """At most one record per key every `every` seconds; the next one says how many were held back."""

    def __init__(self, logger: logging.Logger, every: float = 5.0) -> None:
        self.logger, self.every = logger, every
        self._last: dict[str, float] = {}
        self._held: dict[str, int] = {}

    def log(self, level: int, key: str, message: str, *args: object, exc_info: bool = False,
            counted: bool = True) -> None:
        """`counted=False` for a condition checked every loop (a quiet link), not an event: the held-back
        count would be loop ticks ('150 more since the last report' every 5 s of silence)."""
        now = time.monotonic()
        if now - self._last.get(key, -1e9) < self.every:
            if counted:
                self._held[key] = self._held.get(key, 0) + 1
            return
        held = self._held.pop(key, 0)
        self._last[key] = now
        if held:
            message += f" ({held} more since the last report)"
        self.logger.log(level, message, *args, exc_info=exc_info)
