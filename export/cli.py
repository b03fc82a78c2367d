"""`dadiff-export checkpoint.pt`: checkpoint -> parity-checked ONNX model folder (docs/model-format.md).

With `--quantize int8` the search graph of the exported model (or of an existing fp32 model folder) is
quantised as well: export/quantize.py.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from dadiff.models import ModelNotFoundError, resolve
from dadiff.runtime.argtypes import add_renamed, float_in, int_in
from dadiff.runtime.config import GEOMETRY_LIMITS
from dadiff.runtime.errors import DadiffError, OneLineParser
from dadiff.runtime.sources import SourceError, open_source, parse_box

from .config import FAMILIES, HP_PRESETS
from .defaults import (
    DEFAULT_BENCH_RUNS,
    DEFAULT_CALIBRATION_FRAMES,
    DEFAULT_EVAL_FRAMES,
    DEFAULT_EVAL_SEQUENCES,
    DEFAULT_OPSET,
    DEFAULT_RECIPE,
    MAX_CALIBRATION_FRAMES,
    PARITY_TOLERANCE,
    PRECISIONS,
    SUPPORTED_OPSETS,
)

if TYPE_CHECKING:  # torch and onnx load after the arguments are checked (--help stays fast)
    from .checkpoint import LoadedCheckpoint
    from .quantize import QuantizeReport, QuantizeSettings

EXPORT_EXTRA = 'pip install "dadiff[export]"'


class UserError(DadiffError):
    """A problem the user can fix; main prints it as one line and exits 2."""


PROG = "dadiff-export"
MAX_MIN_SIZE = GEOMETRY_LIMITS["min_size"]  # the runtime's bound: one a model's metadata may hold


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
                      epilog="Exit codes: 0 written, 1 parity check failed (no files written), 2 bad input (one "
                             f"'{PROG}: error:' line).")
    p.add_argument("checkpoint", help="released DaDiff-BAN checkpoint (.pth) or a dadiff checkpoint (.pt); with "
                                      "--quantize also an fp32 model folder or shipped model name")
    p.add_argument("-o", "--output", help="output model folder (default: ./<name>; ./<name>-int8 with --quantize)")
    p.add_argument("--name", help="model name stored in the metadata (default: the -o folder's name, else the "
                                  "checkpoint's file stem)")
    p.add_argument("--force", action="store_true",
                   help="replace the graphs of a model already in the -o folder (refused without it)")
    p.add_argument("--steps", type=int, help="DDIM steps K to unroll, 1..20 (default: the checkpoint's, 2)")
    p.add_argument("--search-size", type=int_in(1), metavar="PX",
                   help="search crop side the graphs take, the trained size or smaller by a multiple of twice the "
                        "stride (dadiff-mobile: 255 trained, 223, 191, 159; default: the trained size)")
    # box side >= 1: the tracker divides by it; at most MAX_MIN_SIZE: 1e308 overflows the runtime's crop arithmetic
    p.add_argument("--min-size", type=float_in(1, MAX_MIN_SIZE), metavar="PX",
                   help=f"smallest box side the runtime keeps, in frame pixels, 1..{MAX_MIN_SIZE:g}; it also sets how "
                        "far the crops magnify a tiny target (metadata min_size; default: the checkpoint's, 10 as "
                        "released)")
    p.add_argument("--opset", type=int, default=DEFAULT_OPSET,
                   help=f"ONNX opset, {SUPPORTED_OPSETS.start}..{SUPPORTED_OPSETS.stop - 1} (default {DEFAULT_OPSET})")
    p.add_argument("--family", choices=FAMILIES, help="require this model family (default: any)")
    p.add_argument("--preset", metavar="NAME",
                   help="hyper-parameter preset the runtime uses by default, one of the checkpoint's "
                        f"(the released ones: {', '.join(sorted(HP_PRESETS))}; default: the checkpoint's)")
    # finite and >= 0: nan would switch the parity gate off, a negative tolerance fail it late
    p.add_argument("--tolerance", type=float_in(0), default=PARITY_TOLERANCE,
                   help=f"max-abs torch/onnxruntime difference allowed, >= 0 (default {PARITY_TOLERANCE:g})")
    _add_quantize_options(p)
    return p


def _add_quantize_options(p: argparse.ArgumentParser) -> None:
    q = p.add_argument_group("int8 quantisation (writes OUT = fp32 template.onnx + int8 search.onnx)")
    q.add_argument("--quantize", metavar="PRECISION", help="quantise the search graph: int8 (default: fp32 only)")
    q.add_argument("--calibration", metavar="SRC",
                   help="video file or sequence folder to calibrate on (default: generated night scenes of the "
                        "training photos)")
    q.add_argument("--calibration-init", metavar="X,Y,W,H",
                   help="target box in the first frame of --calibration when it has no ground-truth file")
    q.add_argument("--calibration-frames", type=int_in(1, MAX_CALIBRATION_FRAMES), default=DEFAULT_CALIBRATION_FRAMES,
                   metavar="N", help=f"search crops to calibrate on, at most {MAX_CALIBRATION_FRAMES} "
                                     f"(default {DEFAULT_CALIBRATION_FRAMES})")
    q.add_argument("--eval-sequences", type=int_in(1), default=DEFAULT_EVAL_SEQUENCES, metavar="N",
                   help="sequences of the generated night test set used to compare fp32 and int8 "
                        f"(default {DEFAULT_EVAL_SEQUENCES})")
    add_renamed(q, "--max-frames", former=["--eval-frames"], type=int_in(2), default=DEFAULT_EVAL_FRAMES, metavar="N",
                help=f"frames per evaluation sequence (default {DEFAULT_EVAL_FRAMES})")
    q.add_argument("--recipe", default=DEFAULT_RECIPE,
                   help=f"which parts stay in float (default {DEFAULT_RECIPE}; see export/quantize.py RECIPES)")
    q.add_argument("--bench-runs", type=int_in(0), default=DEFAULT_BENCH_RUNS, metavar="N",
                   help=f"search-graph runs per precision for the latency comparison, 0 to skip "
                        f"(default {DEFAULT_BENCH_RUNS})")
    q.add_argument("--reduce-range", action=argparse.BooleanOptionalAction, default=None,
                   help="7-bit weights, as onnxruntime advises for x86 CPUs without VNNI (default: on exactly "
                        "when this CPU lacks AVX-512 VNNI / AVX-VNNI)")


def _split_negative_box(argv: list[str]) -> list[str]:
    """`--calibration-init -5,-5,15,9` as `--calibration-init=-5,...`: argparse takes '-5,...' for an option."""
    out: list[str] = []
    for i, arg in enumerate(argv):
        if i and argv[i - 1] == "--calibration-init" and arg.startswith("-") and arg[1:2].isdigit():
            out[-1] = f"--calibration-init={arg}"
            continue
        out.append(arg)
    return out


def _mb(n: int) -> str:
    return f"{n / 1e6:.1f} MB"


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(_split_negative_box(list(sys.argv[1:] if argv is None else argv)))
    if args.opset not in SUPPORTED_OPSETS:
        parser.error(f"unsupported opset {args.opset}; use {SUPPORTED_OPSETS.start}..{SUPPORTED_OPSETS.stop - 1}")
    if args.steps is not None and not 1 <= args.steps <= 20:
        parser.error(f"--steps must be in 1..20, got {args.steps}")
    try:
        _import_torch_side()
    except ModuleNotFoundError as e:
        return _fail(f"exporting needs PyTorch and onnx, which are not installed here (no module {e.name!r}): "
                     f"{EXPORT_EXTRA}")
    try:
        return _main(args)
    except DadiffError as e:
        return _fail(str(e))
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted; no files written", file=sys.stderr)
        return 130


def _import_torch_side() -> None:
    """Import the torch side now, not at module level: --help and usage errors stay fast (and work without it)."""
    from . import checkpoint, quantize  # noqa: F401


def _main(args: argparse.Namespace) -> int:
    if args.quantize is None:
        _refuse_quantize_options(args)
        name = args.name or _folder_name(args.output) or Path(args.checkpoint).stem
        out = Path(args.output) if args.output else Path(name)
        _refuse_replacing(out, args.force)
        return _export(args, out, name)
    settings = quantize_settings(args)
    folder = model_folder(args.checkpoint)
    if folder is not None:
        _refuse_checkpoint_options(args)
        out = Path(args.output) if args.output else Path(f"{folder.name}-int8")
        _refuse_replacing(out, args.force)
        print(f"{PROG}: {args.checkpoint}: fp32 model folder, quantising its search graph to int8", flush=True)
        return _quantize(folder, out, settings)
    _refuse_folder(args.checkpoint)
    name = args.name or Path(args.checkpoint).stem
    out = Path(args.output) if args.output else Path(f"{name}-int8")
    _refuse_replacing(out, args.force)
    with tempfile.TemporaryDirectory(prefix="dadiff-export-") as tmp:
        code = _export(args, Path(tmp) / name, name, label="fp32 model (temporary)")
        return code or _quantize(Path(tmp) / name, out, settings)


def _folder_name(output: str | None) -> str:
    """The name of the -o folder ('' without one): exporting models/dadiff-mobile/checkpoint.pt into its own
    folder named the model `checkpoint`."""
    return Path(output).expanduser().resolve().name if output else ""


def _refuse_replacing(out: Path, force: bool) -> None:
    """UserError when `out` already holds a model and --force is not given, so that no model's graphs are
    replaced without a word. Checked before the checkpoint is loaded."""
    held = [f for f in ("template.onnx", "search.onnx") if (out / f).exists()]
    if held and not force:
        raise UserError(f"{out}: holds a model already ({', '.join(held)}); add --force to replace it, or choose "
                        "another -o")


def _fail(message: str, code: int = 2) -> int:
    print(f"{PROG}: error: {message}", file=sys.stderr)
    return code


def model_folder(spec: str) -> Path | None:
    """The model folder `spec` names (a folder, an .onnx file in one, a shipped name), or None (a checkpoint)."""
    try:
        return resolve(spec)
    except ModelNotFoundError:
        return None


def quantize_settings(args: argparse.Namespace) -> QuantizeSettings:
    """Check the quantisation options before anything slow runs; errors are one line (exit 2)."""
    from .quantize import QuantizeSettings

    if args.quantize.lower() not in PRECISIONS:
        raise UserError(f"--quantize {args.quantize}: unsupported precision; available: {', '.join(PRECISIONS)}")
    init = _init_box(args.calibration_init) if args.calibration_init is not None else None
    if init is not None and args.calibration is None:
        raise UserError("--calibration-init applies to --calibration SRC only")
    if args.calibration is not None:
        _check_calibration_source(args.calibration, init)
    settings = QuantizeSettings(calibration=args.calibration, init=init, frames=args.calibration_frames,
                                eval_sequences=args.eval_sequences, eval_frames=args.max_frames,
                                bench_runs=args.bench_runs, recipe=args.recipe, reduce_range=args.reduce_range)
    settings.check()
    return settings


def _init_box(text: str) -> tuple[float, float, float, float]:
    try:
        box = parse_box(text)
    except ValueError as e:
        raise UserError(f"--calibration-init: {e}") from None
    if box[2] <= 0 or box[3] <= 0:
        raise UserError(f"--calibration-init: width and height must be positive, got {text!r}")
    return box


def _check_calibration_source(spec: str, init: tuple[float, float, float, float] | None) -> None:
    path = Path(spec).expanduser()
    if not path.exists():
        raise UserError(f"--calibration {spec}: no such file or folder (give a video file or a sequence folder)")
    try:
        source = open_source(str(path))
    except SourceError as e:
        raise UserError(f"--calibration: {e}") from None
    has_truth = source.init_box is not None
    source.close()
    if init is None and not has_truth:
        raise UserError(f"--calibration {spec}: no ground-truth file to start from; give --calibration-init "
                            "x,y,w,h (the target in its first frame)")


def _refuse_quantize_options(args: argparse.Namespace) -> None:
    given = [opt for opt, value, default in (
        ("--calibration", args.calibration, None), ("--calibration-init", args.calibration_init, None),
        ("--calibration-frames", args.calibration_frames, DEFAULT_CALIBRATION_FRAMES),
        ("--eval-sequences", args.eval_sequences, DEFAULT_EVAL_SEQUENCES),
        ("--max-frames", args.max_frames, DEFAULT_EVAL_FRAMES), ("--bench-runs", args.bench_runs, DEFAULT_BENCH_RUNS),
        ("--recipe", args.recipe, DEFAULT_RECIPE), ("--reduce-range", args.reduce_range, None),
    ) if value != default]
    if given:
        raise UserError(f"{given[0]} applies to --quantize int8 only")
    _refuse_folder(args.checkpoint)


def _refuse_folder(spec: str) -> None:
    """A folder given where a checkpoint file is wanted: say which kind of folder it is."""
    path = Path(spec)
    if not path.is_dir():
        return
    checkpoints = sorted(p.name for p in path.iterdir() if p.suffix in (".pt", ".pth"))
    if (path / "search.onnx").exists():
        raise UserError(f"{spec}: is a model folder, not a checkpoint; add --quantize int8 to quantise it")
    if checkpoints:
        pick = "final.pt" if "final.pt" in checkpoints else checkpoints[0]
        raise UserError(f"{spec}: is a folder of checkpoints ({', '.join(checkpoints[:4])}), not one; give a file, "
                        f"e.g. {path / pick}")
    raise UserError(f"{spec}: is a folder holding neither a checkpoint (.pt/.pth) nor a model (search.onnx)")


def _refuse_checkpoint_options(args: argparse.Namespace) -> None:
    given = [opt for opt, value, default in (
        ("--name", args.name, None), ("--steps", args.steps, None), ("--family", args.family, None),
        ("--preset", args.preset, None), ("--search-size", args.search_size, None),
        ("--min-size", args.min_size, None),
        ("--opset", args.opset, DEFAULT_OPSET),
        ("--tolerance", args.tolerance, PARITY_TOLERANCE),
    ) if value != default]
    if given:
        raise UserError(f"{given[0]} applies to checkpoints; {args.checkpoint} is an exported model folder")


def _with_min_size(loaded: LoadedCheckpoint, side: float) -> LoadedCheckpoint:
    """`loaded` with the runtime's smallest box side set to `side` px (metadata `min_size`).

    The tracker floors the box at it and sizes both crops from the floored box, so below the released 10 px
    a target of 6-9 px is cut nearer the magnification the network was trained on instead of a smaller one.
    """
    new_cfg = replace(loaded.config, tracker=replace(loaded.config.tracker, min_size=side))
    loaded.model.cfg = new_cfg
    return replace(loaded, config=new_cfg)


def _export(args: argparse.Namespace, out: Path, name: str, label: str | None = None) -> int:
    """The fp32 export of a checkpoint, parity-gated; prints what it wrote."""
    from .checkpoint import load_checkpoint
    from .onnx_export import ExportError, export_model
    from .search_size import with_search_size

    try:
        loaded = load_checkpoint(args.checkpoint, family=args.family, steps=args.steps, preset=args.preset)
        if args.search_size is not None:
            loaded = with_search_size(loaded, args.search_size)
        if args.min_size is not None:
            loaded = _with_min_size(loaded, args.min_size)
        print(f"{PROG}: {args.checkpoint}: {loaded.config.family} ({loaded.source} format, "
              f"sha256 {loaded.sha256[:12]}…)", flush=True)
        report = export_model(loaded, out, name, args.opset, args.tolerance)
    except ExportError as e:
        return _fail(str(e), 1 if "parity" in str(e) else 2)
    sampler = loaded.model.sampler
    files = ", ".join(f"{f} {_mb(n)}" for f, n in report.files.items())
    parity = ", ".join(f"{k} {v:.1e}" for k, v in report.parity_abs.items())
    print(f"  wrote {label or str(out) + '/'}: {files}")
    block = (f"DDIM {len(sampler.timesteps)} steps, timesteps {sampler.timesteps}, start t {sampler.start_t}"
             if loaded.config.use_dadiff else "no DaDiff block")
    tr = loaded.config.tracker
    print(f"  search crop {tr.instance_size} px, score map {tr.score_size} x {tr.score_size}; GFLOP per search frame "
          f"{report.gflop_search:.2f}, template (once) {report.gflop_template:.2f}; {block}")
    print(f"  parity torch vs onnxruntime (max-abs, relative where |output| > 1): {report.max_parity:.1e} "
          f"(tolerance {args.tolerance:g}) OK; max-abs per output [{parity}]")
    print(f"  export time {report.seconds:.1f} s", flush=True)
    return 0


def _quantize(folder: Path, out: Path, settings: QuantizeSettings) -> int:
    from .quantize import quantize_model

    report = quantize_model(folder, out, settings, log=lambda line: print(line, flush=True))
    print_quantize_report(report)
    return 0


def print_quantize_report(report: QuantizeReport) -> None:
    """The measured numbers, as stored in the int8 graph's metadata."""
    t, s = report.files["template.onnx"], report.files["search.onnx"]
    print(f"  wrote {report.out_dir}/: template.onnx {_mb(t)} (fp32, unchanged), search.onnx {_mb(s)} (int8)")
    d = report.deviation
    print(f"  deviation from fp32 on {d['crops']} held-out crops: cls max-abs {d['cls_max_abs']:.3g}, mean-abs "
          f"{d['cls_mean_abs']:.3g}; loc max-abs {d['loc_max_abs']:.3g}, mean-abs {d['loc_mean_abs']:.3g}; "
          f"decoded cell the same in {d['cell_agreement']:.1%}, within one cell in {d['cell_within_one']:.1%}")
    fp32, int8 = report.success["fp32"], report.success["int8"]
    print(f"  night success ({report.success['set']}): fp32 {fp32:.3f}, int8 {int8:.3f} ({int8 - fp32:+.3f})")
    lat = report.latency_ms
    if lat:
        print(f"  search latency (CPU, {lat['threads']} threads, median of {lat['runs']} runs each): fp32 "
              f"{lat['fp32']:.2f} ms, int8 {lat['int8']:.2f} ms ({lat['fp32'] / lat['int8']:.2f}x)")
    print(f"  quantisation time {report.seconds:.1f} s")


if __name__ == "__main__":
    sys.exit(main())
