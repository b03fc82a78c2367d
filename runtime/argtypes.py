"""argparse types the commands share, light enough for any parser to import (no onnxruntime, no OpenCV)."""

from __future__ import annotations

import argparse
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
