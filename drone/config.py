"""`--config FILE.toml`: every command-line option as a top-level key, the command line overriding it.

Keys are the long option names with or without the dashes turned to underscores (`max-frames` or
`max_frames`). Values go through the option's own parser, so a key accepts what the option accepts:
strings and numbers as typed, lists joined with commas (`init = [612, 300, 24, 18]`), tables as
`k=v` pairs (`hp = {lr = 0.4}`), and true/false for switches (`follow = true`). An unknown key or a bad
value is a one-line usage error naming the file and the key. Relative paths are taken from the working
directory, as on the command line (a service should use absolute ones).
"""

from __future__ import annotations

import argparse
import sys
import tomllib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from dadiff.runtime.errors import DadiffError
from dadiff.runtime.user_files import SETTINGS_LIMIT, read_user_text


class ConfigError(DadiffError):
    """A config file problem (one line)."""


def _options(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    options = {}
    for action in parser._actions:
        for option in action.option_strings:
            if option.startswith("--"):
                options[option[2:].replace("_", "-")] = action
    return options


def _convert(action: argparse.Action, key: str, value: Any) -> Any:
    if isinstance(action, argparse.BooleanOptionalAction):  # --realtime / --no-realtime
        if not isinstance(value, bool):
            raise ConfigError(f"'{key}' is a switch: use true or false, got {value!r}")
        return value
    if action.nargs == "?" and isinstance(value, bool):  # --follow [vehicle|gimbal]: true is the bare option
        return action.const if value else action.default
    if action.nargs == 0:  # store_true / store_false / store_const
        if not isinstance(value, bool):
            raise ConfigError(f"'{key}' is a switch: use true or false, got {value!r}")
        return action.const if value else action.default
    if isinstance(value, bool):
        raise ConfigError(f"'{key}' takes a value, not {str(value).lower()}")
    if isinstance(value, dict):
        text = ",".join(f"{k}={v}" for k, v in value.items())
    elif isinstance(value, list):
        text = ",".join(str(v) for v in value)
    else:
        text = str(value)
    converted: Any = text
    if action.type is not None:
        try:
            converted = action.type(text)  # type: ignore[operator]
        except (argparse.ArgumentTypeError, ValueError, TypeError) as exc:
            raise ConfigError(f"'{key}': {exc}") from None
    if action.choices is not None and converted not in action.choices:
        choices = ", ".join(map(str, action.choices))
        raise ConfigError(f"'{key}': {converted!r} is not one of {choices}")
    return converted


def config_defaults(parser: argparse.ArgumentParser, path: Path) -> dict[str, Any]:
    """{dest: value} for the keys of a TOML file, checked against `parser`'s options."""
    try:
        table = tomllib.loads(read_user_text(path, SETTINGS_LIMIT, encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a text file (TOML must be UTF-8)") from None
    except RecursionError:  # tomllib recurses once per nesting level
        raise ConfigError(f"{path}: not valid TOML (nested too deeply)") from None
    options = _options(parser)
    values: dict[str, Any] = {}
    for key, value in table.items():
        action = options.get(key.replace("_", "-"))
        if action is None or key.replace("_", "-") in ("config", "help"):
            raise ConfigError(f"{path}: unknown key '{key}' (keys are the long options, e.g. 'video', 'mavlink')")
        try:
            values[action.dest] = _convert(action, key, value)
        except ConfigError as exc:
            raise ConfigError(f"{path}: {exc}") from None
    return values


def parse_args(parser: argparse.ArgumentParser, argv: Sequence[str] | None = None) -> argparse.Namespace:
    """`parser.parse_args(argv)` with the defaults taken from `--config FILE` when it is given.

    Config problems go through `parser.error`, so they are reported like any other usage error.
    """
    args = list(sys.argv[1:] if argv is None else argv)
    # abbreviations as the real parser takes them: `--conf FILE` is --config there, so here too
    pre = argparse.ArgumentParser(add_help=False, allow_abbrev=parser.allow_abbrev, exit_on_error=False)
    pre.add_argument("--config", type=Path)
    try:
        known, _ = pre.parse_known_args(args)
    except (argparse.ArgumentError, SystemExit):
        known = argparse.Namespace(config=None)  # let the real parser report it
    if known.config is not None:
        try:
            values = config_defaults(parser, known.config)
        except ConfigError as exc:
            parser.error(str(exc))
        parser.set_defaults(**values)
        for action in parser._actions:
            if action.dest in values:
                action.required = False
    return parser.parse_args(args)
