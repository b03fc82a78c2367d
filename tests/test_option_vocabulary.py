"""One option vocabulary across the commands: `--model`, `-o/--output`, `--max-frames`; the former spellings
still parse to the same values for one release, with one deprecation line on stderr naming the new spelling."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

import pytest

from dadiff.export.cli import build_parser as export_parser
from dadiff.export.train_cli import build_parser as train_parser
from dadiff.runtime.argtypes import add_renamed
from dadiff.runtime.commands.bench import build_parser as bench_parser
from dadiff.runtime.commands.eval import build_parser as eval_parser
from dadiff.runtime.commands.run import build_parser as run_parser

Parser = Callable[[], argparse.ArgumentParser]

# (parser, prog as the note names it, the rest of a valid command line, former spelling, new spelling, value)
RENAMED: list[tuple[Parser, str, list[str], str, str, str]] = [
    (bench_parser, "dadiff-bench", [], "--frames", "--max-frames", "7"),
    (eval_parser, "dadiff-eval run", ["run", "--dataset", "d"], "--results", "--output", "res"),
    (eval_parser, "dadiff-eval generate", ["generate", "-o", "g"], "--frames", "--max-frames", "7"),
    (export_parser, "dadiff-export", ["final.pt"], "--eval-frames", "--max-frames", "7"),
    (train_parser, "dadiff-train", ["--config", "c.toml"], "--out", "--output", "run"),
]
EVAL_OUTPUTS = {  # every dadiff-eval sub-command that writes a file or folder, with its other required options
    "generate": [], "video": ["--video", "v.mp4"], "night": ["--dataset", "d"],
    "uncut": ["--video", "v.mp4", "--truth", "t"], "detect": ["--video", "v.mp4", "--detector", "p.onnx"],
    "cutouts": ["--dataset", "d", "--licence", "CC0"], "pseudo-label": ["--video", "v.mp4", "--detections", "det.txt"],
    "hit-uav": [], "tune": ["--dataset", "d"], "data pack": [],
}
for command, required in EVAL_OUTPUTS.items():
    RENAMED.append((eval_parser, f"dadiff-eval {command}", [*command.split(), *required], "--out", "--output", "o"))


def _note(prog: str, former: str, new: str) -> str:
    spelled = "-o/--output" if new == "--output" else new
    return f"{prog}: warning: {former} is deprecated and goes in the next release; use {spelled}\n"


@pytest.mark.parametrize(("parser", "prog", "rest", "former", "new", "value"), RENAMED,
                         ids=[f"{r[1]} {r[3]}" for r in RENAMED])
def test_the_new_spelling_works_and_the_former_one_still_does_with_a_note(parser, prog, rest, former, new, value,
                                                                         capsys):
    current = parser().parse_args([*rest, new, value])
    assert capsys.readouterr().err == ""
    assert str(getattr(current, new.lstrip("-").replace("-", "_"))) == value
    if new == "--output":
        assert parser().parse_args([*rest, "-o", value]) == current
    assert parser().parse_args([*rest, former, value]) == current
    assert capsys.readouterr().err == _note(prog, former, new)


def test_dadiff_run_writes_its_track_log_with_o_too(capsys):
    assert run_parser().parse_args(["--video", "v.mp4", "-o", "log.csv"]).output == Path("log.csv")
    assert capsys.readouterr().err == ""


def test_dadiff_bench_takes_models_with_model_and_still_as_plain_arguments(capsys):
    current = bench_parser().parse_args(["--model", "a", "--model", "b"])
    assert current.models == ["a", "b"] and capsys.readouterr().err == ""
    assert bench_parser().parse_args([]).models is None  # the shipped default
    assert bench_parser().parse_args(["a", "b"]) == current
    assert capsys.readouterr().err == ("dadiff-bench: warning: MODEL without --model is deprecated and goes in the "
                                       "next release; use --model\n")


def test_a_required_output_stays_required_and_takes_one_spelling(capsys):
    with pytest.raises(SystemExit):
        eval_parser().parse_args(["generate"])
    assert "one of the arguments -o/--output is required" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        eval_parser().parse_args(["generate", "--out", "a", "-o", "b"])
    assert "argument -o/--output: not allowed with argument --out" in capsys.readouterr().err


def test_former_spellings_stay_out_of_the_help():
    text = eval_parser()._subparsers._group_actions[0].choices["generate"].format_help()
    assert "--output" in text and "--max-frames" in text and "--out " not in text and "--frames" not in text
    assert "--eval-frames" not in export_parser().format_help()
    assert "MODELS" not in bench_parser().format_help()


def test_a_former_positional_needs_a_list_valued_option():
    with pytest.raises(ValueError, match="list-valued"):
        add_renamed(argparse.ArgumentParser(), "--model", former=["model"])


def test_dadiff_train_parses_once_so_the_note_is_one_line(tmp_path, capsys):
    pytest.importorskip("torch")
    from dadiff.export.train_cli import main

    config = tmp_path / "base.toml"
    config.write_text('[train]\nout = "runs/base"\nsteps = 40\nday = [{ kind = "scenes", split = "train" }]\n')
    assert main(["--config", str(config), "--show-config", "--out", str(tmp_path / "elsewhere")]) == 0
    captured = capsys.readouterr()
    assert f'out = "{tmp_path / "elsewhere"}"' in captured.out
    assert captured.err == _note("dadiff-train", "--out", "--output")
