"""argparse types the commands share, light enough for any parser to import (no onnxruntime, no OpenCV)."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable


def int_in(low: int, high: int) -> Callable[[str], int]:
    """argparse type: an integer in [low, high], checked at parsing so that the error names the option
    (`dadiff-bench --clip 1` failed later naming a temporary video, `--frames 1e12` was an allocation
    traceback)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = low - 1
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"expected an integer from {low} to {high}, got {text!r}")
        return value

    return parse


def float_in(low: float, high: float, *, open_low: bool = False) -> Callable[[str], float]:
    """argparse type: a finite number in [low, high], or (low, high] with `open_low` (nan and inf used to reach
    the code: `data pack --max-mib inf` was an OverflowError)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"expected a finite number, got '{text}'")
        if not ((value > low if open_low else value >= low) and value <= high):
            span = f"{'above' if open_low else 'from'} {low:g} {'and at most' if open_low else 'to'} {high:g}"
            raise argparse.ArgumentTypeError(f"expected a number {span}, got '{text}'")
        return value

    return parse
