"""Exceptions for problems a user can fix (as opposed to bugs), and the one-line reporting every command shares.

`DadiffError` is the base of every exception class the project defines (runtime/, drone/, export/, models/), so
that an entry point catches one class; each subclass also keeps a built-in base, so callers that
catch that still catch it (`ModelError` is a ValueError, `UnreadableFile` an OSError). Torch-free: the runtime
and the drone import it.
"""

from __future__ import annotations

import argparse
from typing import NoReturn


class DadiffError(Exception):
    """A problem a user can fix, reported by the commands as one line and exit status 2."""


class ModelError(DadiffError, ValueError):
    """A model folder or file is missing, unreadable, or not a valid dadiff model.

    The message is one line naming the file and, where it applies, the metadata key. A ValueError, as
    InputError: one `except ValueError` catches every problem a caller can fix.
    """


class InputError(DadiffError, ValueError):
    """A caller-supplied value is unusable: init box, frame, preset, override, provider, threads."""


class OneLineParser(argparse.ArgumentParser):
    """argparse whose usage errors are one line, `<prog>: error: <what> (see <prog> --help)`, exit 2.

    The whole usage block on every typo buries the one line that matters; all dadiff commands report alike.
    Sub-command parsers inherit the class (argparse builds them with type(parent)).
    """

    def error(self, message: str) -> NoReturn:  # type: ignore[override]
        top, _, sub = self.prog.partition(" ")  # "dadiff-eval run": the command, then its sub-command
        where = f"{sub}: " if sub else ""
        self.exit(2, f"{top}: error: {where}{message} (see {self.prog} --help)\n")


def os_error_line(exc: OSError, fallback: object = None) -> str:
    """`<file>: <why>` for an OSError that reached a command's entry point: a folder the user may not read, a
    read-only filesystem, a FIFO given as a config. Every command reports these alike, in one line."""
    where = exc.filename or fallback
    why = exc.strerror or str(exc) or type(exc).__name__
    return f"{where}: {why}" if where else why
