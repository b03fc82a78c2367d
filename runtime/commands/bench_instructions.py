"""Instructions per tracker update on a CPU without AVX-512, counted under valgrind (`dadiff-bench --instructions`).

The speed bar is for companion computers without AVX-512, and the machines we develop on may have it; onnxruntime
and OpenCV pick their kernels from CPUID at run time, with no switch to turn AVX-512 off. Valgrind shows the
program it runs a CPU without AVX-512 (CPUID leaf 7 and XCR0 cleared) and stops it with SIGILL on any AVX-512
instruction, so a run that completes under it ran the AVX2/FMA kernels an AVX2-only CPU runs. Callgrind counts
the instructions executed: per update = (count after `updates[1]` updates - count after `updates[0]`) / their
difference, everything else (imports, sessions, loading the clip, the init) being the same in both runs. That
difference is only as good as the rest is repeatable: with the video decoded inside the counted program, totals
of the same program differed by up to 1.5e8 instructions, so the clip is decoded once, outside valgrind, and
loaded as an array, and Python's hash seed is fixed; the totals then differ by under 1e7 (onnxruntime's set-up),
though runs with 1.1e8 more in one of the two were seen (a 2-core Xeon, 2026-12-05; cause not found), against
5e7 or more per update of a real tracker (TrackerNano), times 32 updates: up to 7 % on the per-update count.
Instructions are not seconds (kernels differ in instructions per cycle), so the ratio of two trackers' counts
estimates the ratio of their frame rates on such a CPU; it is not a timing.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

from ..errors import DadiffError

CLIP = 48  # frames every worker run loads, whatever its update count
UPDATES = (4, 36)  # the two update counts whose difference is counted
_TOTALS = re.compile(r"^(?:summary|totals):\s+(\d+)", re.MULTILINE)


class InstructionCountError(DadiffError):
    """One line for the user."""


@dataclass(frozen=True)
class UpdateCount:
    """Instructions per `update` of one tracker, from two valgrind runs."""

    name: str
    instructions: float  # per update
    runs: tuple[int, int]  # total instructions of the two runs


def valgrind_path() -> str:
    found = shutil.which("valgrind")
    if found is None:
        raise InstructionCountError("--instructions needs valgrind (Debian: apt-get install valgrind)")
    return found


def callgrind_total(text: str) -> int:
    """The total instruction count (Ir) in a callgrind output file's text."""
    match = _TOTALS.search(text)
    if match is None:
        raise InstructionCountError("callgrind wrote no 'summary:' or 'totals:' line")
    return int(match.group(1))


def per_update(name: str, totals: tuple[int, int], updates: tuple[int, int] = UPDATES) -> UpdateCount:
    """Instructions per update from the totals of two runs that differ only in their update counts."""
    if updates[1] <= updates[0]:
        raise ValueError(f"update counts must grow, got {updates}")
    if totals[1] <= totals[0]:
        raise InstructionCountError(f"{name}: the longer run counted no more instructions ({totals[1]} <= {totals[0]})")
    return UpdateCount(name, (totals[1] - totals[0]) / (updates[1] - updates[0]), totals)


def write_clip(video: Path, path: Path) -> Path:
    """The first CLIP frames of `video` as one uint8 array in `path` (.npy), what the counted program loads."""
    import numpy as np

    from ..frames import decode_video

    frames = decode_video(str(video), CLIP)
    if len(frames) < 2:
        raise InstructionCountError(f"{video}: fewer than 2 frames")
    np.save(path, np.stack(frames))
    return path


def _worker_command(kind: str, target: str, clip: Path, box: tuple[float, ...], updates: int) -> list[str]:
    return [sys.executable, "-m", "dadiff.runtime.commands.bench_instructions", kind, target, str(clip),
            ",".join(f"{v:g}" for v in box), str(updates)]


def count_updates(
    kind: str, target: str, clip: Path, box: tuple[float, ...], name: str, updates: tuple[int, int] = UPDATES
) -> UpdateCount:
    """Count one tracker's instructions per update under callgrind on `clip` (`write_clip`; one clip serves every
    tracker compared). `kind`: "model" (`target` = model folder) or "nano" (`target` = NanoTrack v2 folder)."""
    valgrind = valgrind_path()
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "DADIFF_CACHE_DIR": "off",
           "PYTHONHASHSEED": "0",
           # numpy reads its CPU features its own way and would take AVX-512 paths valgrind cannot run
           "NPY_DISABLE_CPU_FEATURES": "AVX512F AVX512CD AVX512_SKX AVX512_CLX AVX512_CNL AVX512_ICL AVX512_SPR"}
    totals = []
    with tempfile.TemporaryDirectory(prefix="dadiff-callgrind-") as tmp:
        for count in updates:
            out = Path(tmp) / f"callgrind-{count}.out"
            command = [valgrind, "--tool=callgrind", f"--callgrind-out-file={out}", "--dump-instr=no",
                       *_worker_command(kind, target, clip, box, count)]
            done = subprocess.run(command, capture_output=True, text=True, env=env)
            if done.returncode != 0:
                lines = [x for x in done.stderr.splitlines() if x.strip() and not x.startswith("==")]
                illegal = "SIGILL" in done.stderr
                tail = "an instruction valgrind cannot run (SIGILL)" if illegal else (lines or ["no output"])[-1]
                raise InstructionCountError(f"{name}: the run under valgrind failed: {tail}")
            totals.append(callgrind_total(out.read_text()))
    return per_update(name, (totals[0], totals[1]), updates)


def _load_tracker(kind: str, target: str):
    import cv2

    cv2.setNumThreads(1)
    if kind == "nano":
        from ..evaluation.evaluate import OpenCVTracker

        return OpenCVTracker("nano", nano_dir=Path(target))
    from ..tracker import Tracker

    return Tracker.load(target, threads=1)


def _work(argv: list[str]) -> None:
    """The counted program: load the clip, init on its first frame, run `updates` updates."""
    import numpy as np

    p = argparse.ArgumentParser(prog="python -m dadiff.runtime.commands.bench_instructions")
    p.add_argument("kind", choices=("model", "nano"))
    p.add_argument("target")
    p.add_argument("clip", help="frames as one .npy array (write_clip)")
    p.add_argument("box")
    p.add_argument("updates", type=int)
    args = p.parse_args(argv)
    frames = np.load(args.clip)
    tracker = _load_tracker(args.kind, args.target)
    tracker.init(frames[0], tuple(float(v) for v in args.box.split(",")))
    for i in range(args.updates):
        tracker.update(frames[1 + i % (len(frames) - 1)])


if __name__ == "__main__":
    _work(sys.argv[1:])
