"""Child process of the fault battery: runs command-line cases in-process, one after another.

`python fault_driver.py CASES.json RESULTS.jsonl`: each case is {"module", "argv", "limit"}, optionally "env"
(variables set for that case only); each result line holds the exit code, the case's own stderr (file
descriptor 2, so C libraries' output counts too), whether an exception escaped `main` (a traceback) and
whether it ran past its limit (a hang). A crash of the whole child shows as missing result lines.
"""

from __future__ import annotations

import importlib
import json
import os
import signal
import sys
import tempfile
import time
import traceback
from typing import Any


class Hang(BaseException):
    """Raised by the alarm: the case ran past its limit (BaseException: no `except Exception` hides it)."""


def _alarm(signum: int, frame: object) -> None:
    raise Hang


def _call(module: str, argv: list[str]) -> tuple[int | None, str | None]:
    main = importlib.import_module(module).main
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    except Hang:
        return None, "hang"
    except BaseException:  # noqa: BLE001 - this is what the battery looks for
        return None, traceback.format_exc()
    return code, None


def run_case(case: dict[str, Any]) -> dict[str, Any]:
    saved_env = {key: os.environ.get(key) for key in case.get("env", {})}
    os.environ.update(case.get("env", {}))
    try:
        return _run_case(case)
    finally:
        for key, value in saved_env.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


def _run_case(case: dict[str, Any]) -> dict[str, Any]:
    with tempfile.TemporaryFile() as err, tempfile.TemporaryFile() as out:
        sys.stdout.flush()
        sys.stderr.flush()
        saved = os.dup(1), os.dup(2)
        os.dup2(out.fileno(), 1)
        os.dup2(err.fileno(), 2)
        start = time.monotonic()
        signal.alarm(int(case.get("limit", 30)))
        try:
            code, escaped = _call(case["module"], case["argv"])
        finally:
            signal.alarm(0)
            sys.stdout.flush()
            sys.stderr.flush()
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])
        seconds = time.monotonic() - start
        err.seek(0)
        text = err.read().decode(errors="replace")
    return {"id": case["id"], "code": code, "stderr": text, "escaped": escaped, "seconds": round(seconds, 3)}


def main() -> None:
    signal.signal(signal.SIGALRM, _alarm)
    with open(sys.argv[1]) as f:
        cases = json.load(f)
    with open(sys.argv[2], "w") as results:
        for case in cases:
            results.write(json.dumps(run_case(case)) + "\n")
            results.flush()


if __name__ == "__main__":
    main()
