"""argparse types the commands share, light enough for any parser to import (no onnxruntime, no OpenCV), and
`add_renamed`, which keeps an option's former spelling working for one release with a deprecation note.

Every command's bounded integers and numbers use these, so that a refusal reads the same everywhere and names
the range and the text given: "expected an integer from 1 to 20, got '0'", "expected an integer of at least 1,
got 'x'", "expected a number above 0, got 'nan'". Values are checked at parsing, so that the error names the
option, not a temporary file, an allocation or an OverflowError met later (`dadiff-bench --clip 1`,
`--max-frames 1e12`, `data pack --max-mib inf`).
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable, Sequence
from typing import Any


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
    is None. nan and inf are refused (the code past parsing assumes finite numbers)."""
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
non_negative_int = int_in(0)  # seeds: numpy refuses negative ones, and only after an output may be made


class _FormerSpelling(argparse.Action):
    """A renamed option's former spelling, hidden from --help: one note on stderr, then the option's own action."""

    def __init__(self, option_strings: list[str], dest: str, current: argparse.Action, former: str, **kwargs: Any):
        super().__init__(option_strings, dest, **kwargs)
        self.current, self.former = current, former

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any,
                 option_string: str | None = None) -> None:
        print(f"{parser.prog}: warning: {self.former} is deprecated and goes in the next release; use "
              f"{'/'.join(self.current.option_strings)}", file=sys.stderr)
        self.current(parser, namespace, values, option_string)


def add_renamed(container: Any, *spellings: str, former: Sequence[str], **kwargs: Any) -> argparse.Action:
    """`container.add_argument(*spellings, **kwargs)`, also taking the `former` spellings for one release.

    A former option string (`--out`) takes what the option takes; a former name without dashes is a positional
    (`dadiff-bench MODEL ...`) whose values go to a list-valued option (`--model`, action "extend"). Either
    prints one deprecation line on stderr naming the new spelling. A required option stays required: the
    former and new spellings form a required group, one of them needed.
    """
    required = kwargs.pop("required", False)
    target = container.add_mutually_exclusive_group(required=True) if required else container
    current = target.add_argument(*spellings, **kwargs)
    hidden = {"action": _FormerSpelling, "current": current, "default": argparse.SUPPRESS, "help": argparse.SUPPRESS}
    for old in former:
        if old.startswith("-"):
            target.add_argument(old, dest=current.dest, nargs=current.nargs, type=current.type,
                                choices=current.choices, metavar=current.metavar, former=old, **hidden)
        else:
            if kwargs.get("action") != "extend":
                raise ValueError(f"a former positional {old!r} needs a list-valued option (action='extend')")
            name = current.metavar or current.dest.upper()
            target.add_argument(old, nargs="*", type=current.type, metavar=name,
                                former=f"{name} without {spellings[-1]}", **hidden)
    return current
