"""The console entry points of every dadiff command: signals are handled from the first instruction on.

Each command's module imports heavy libraries (OpenCV, onnxruntime, torch: seconds on a small computer)
before its `main` runs. The rule: a stop signal at any time ends a command with one line and exit 130, never a
traceback, and every output is closed whole (an MP4 keeps its index). So SIGTERM and SIGHUP (an SSH session
dropping) stop a command as Ctrl-C does (KeyboardInterrupt: outputs are closed on the way out), and an
interruption before `main` has taken over is one line and exit 130. Only the standard library is imported
here, and each command's module only after the handlers are in place.
"""

from __future__ import annotations

import importlib
import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from typing import NoReturn

STOP_SIGNALS = (signal.SIGTERM, signal.SIGHUP)  # SIGINT raises KeyboardInterrupt already
INTERRUPTED = 130


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


@contextmanager
def stop_signals_interrupt() -> Iterator[None]:
    """SIGTERM and SIGHUP raise KeyboardInterrupt for the length of the block, as Ctrl-C does.

    A signal the process was started ignoring stays ignored (`nohup` ignores SIGHUP on purpose); outside the
    main thread (a command run inside another program) nothing changes.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {sig: signal.getsignal(sig) for sig in STOP_SIGNALS}
    for sig, handler in previous.items():
        if handler is not signal.SIG_IGN:
            signal.signal(sig, _interrupt)
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler if handler is not None else signal.SIG_DFL)


@contextmanager
def signals_held() -> Iterator[None]:
    """A stop signal (Ctrl-C, SIGTERM, SIGHUP) that arrives inside the block acts when it ends: one frame's
    record then reaches every output or none (the CSV log and the video never end a frame apart). The
    handlers are swapped, not the signal mask: onnxruntime's and OpenCV's threads would take a masked signal
    for the process. Outside the main thread nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught: list[int] = []
    held = [sig for sig in (signal.SIGINT, *STOP_SIGNALS) if signal.getsignal(sig) not in (signal.SIG_IGN, None)]
    previous = {sig: signal.signal(sig, lambda signum, frame: caught.append(signum)) for sig in held}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if caught:  # now, as it would have acted
            handler = previous[caught[0]]
            if callable(handler):
                handler(caught[0], None)
            else:
                signal.raise_signal(caught[0])


def launch(prog: str, module: str) -> NoReturn:
    """Install the signal handling, then import `module` and exit with what its `main()` returns."""
    with stop_signals_interrupt():
        try:
            code = importlib.import_module(module).main()
        except KeyboardInterrupt:  # before `main` took over (while importing), or one it let through
            print(f"{prog}: interrupted", file=sys.stderr)
            code = INTERRUPTED
    sys.exit(code)


def dadiff_run() -> NoReturn:
    launch("dadiff-run", "dadiff.runtime.commands.run")


def dadiff_eval() -> NoReturn:
    launch("dadiff-eval", "dadiff.runtime.commands.eval")


def dadiff_bench() -> NoReturn:
    launch("dadiff-bench", "dadiff.runtime.commands.bench")


def dadiff_export() -> NoReturn:
    launch("dadiff-export", "dadiff.export.cli")


def dadiff_train() -> NoReturn:
    launch("dadiff-train", "dadiff.export.train_cli")
