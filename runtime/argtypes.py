"""argparse types the commands share, light enough for any parser to import (no onnxruntime, no OpenCV).

Every command's bounded integers and numbers use these, so that a refusal reads the same everywhere and names
the range and the text given: "expected an integer from 1 to 20, got '0'", "expected an integer of at least 1,
got 'x'", "expected a number above 0, got 'nan'". Values are checked at parsing, so that the error names the
option (`dadiff-bench --clip 1` failed later naming a temporary video, `--frames 1e12` was an allocation
traceback, `data pack --max-mib inf` an OverflowError).
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable


def int_in(low: int, high: int | None = None) -> Callable[[str], int]:
    """argparse type: an integer in [low, high], or of at least `low` when `high` is None. Integers only:
    '1e3', '2.0', 'inf' and words are refused."""
    span = f"of at least {low}" if high is None else f"from {low} to {high}"

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = None
        if value is None or value < low or (high is not None and value > high):
            raise argparse.ArgumentTypeError(f"expected an integer {span}, got {text!r}")
        return value

    return parse


def float_in(low: float, high: float | None = None, *, open_low: bool = False) -> Callable[[str], float]:
    """argparse type: a finite number in [low, high], or (low, high] with `open_low`; no upper bound when `high`
    is None. nan and inf are refused (they used to reach the code)."""
    if high is None:
        span = f"above {low:g}" if open_low else f"of at least {low:g}"
    else:
        span = f"above {low:g} and at most {high:g}" if open_low else f"from {low:g} to {high:g}"

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        in_range = (value > low if open_low else value >= low) and (high is None or value <= high)
        if not (math.isfinite(value) and in_range):
            raise argparse.ArgumentTypeError(f"expected a number {span}, got {text!r}")
        return value

    return parse


positive_int = int_in(1)  # counts, threads, frames
non_negative_int = int_in(0)  # seeds: numpy refuses negative ones with a traceback, often after an output is made
