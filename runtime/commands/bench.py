"""`dadiff-bench [--model MODEL ...]`: per-stage latency, FPS and memory of one or more models, side by side.

The models take turns of 50 frames (`--interleave`) on the same generated night video (same frames, same
threads), so that their ratios are measured over the same stretch of time; the first is the reference for
the ratios. `--compare-torch` times the PyTorch graph on the same crops (a subprocess:
this package never imports torch), `--sweep-steps` re-exports a checkpoint with other DDIM step counts and
sets speed beside night success, `--peak` measures the CPU's arithmetic limit. OpenCV's TrackerNano
(NanoTrack v2) runs on the same frames as a reference point when its weights are found (`--nano-dir`, else
$DADIFF_NANO_DIR, else ../shared/weights/nanotrack/v2 beside a source checkout); when they are not, one note on
stderr says so (`--no-nano` skips it without a note).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import subprocess
import sys
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path

import cv2
import numpy as np
import onnxruntime as ort
from tqdm import tqdm

from dadiff.models import ModelNotFoundError, resolve

from ..argtypes import add_renamed, int_in, non_negative_int, positive_int
from ..cpu import cpu_flags
from ..datamaking.datasets import Dataset
from ..errors import DadiffError, ModelError, OneLineParser, os_error_line
from ..evaluation.evaluate import (
    NANO_ENV,
    EvalError,
    OpenCVTracker,
    generated_night_set,
    nano_files,
    nano_label,
    nano_problem,
    run_tracker,
    score_folder,
    score_tracker,
    tracker_folder,
)
from ..onnx_backend import physical_cores, thread_count
from ..sources import quiet_opencv
from ..tracker import Tracker
from .bench_instructions import CLIP, UPDATES, count_updates, valgrind_path, write_clip
from .bench_lanes import (
    BenchLane,
    BenchRun,
    NightVideo,
    latency_ms,
    run_lanes,
    search_crops,
    time_search,
    write_night_video,
)
from .run import hp_arg

ROWS = (
    ("decode", "video decode"), ("motion", "picture motion (jolts)"), ("crop", "search crop"),
    ("search", "search graph (ONNX)"),
    ("post", "decode box + state"), ("encode", "MAVLink 275 encode"), ("tracker", "Tracker.update"),
    ("frame", "frame end to end"), ("template", "template branch (per init)"),
)
SUCCESS_SEED = 2026  # the README's generated benchmark: --success 16 --success-frames 120 is that set
MAX_FRAMES = 1_000_000  # --max-frames, --warmup, --interleave: the timing arrays take 72 MB at this count
MAX_CLIP = 1000  # --clip: the generated clip is rendered in memory, about 1.8 MB a frame
CPU_FLAGS = ("avx2", "avx512f", "avx512_vnni")  # what onnxruntime's and OpenCV's fast kernels dispatch on


class BenchError(DadiffError):
    """One line for the user."""


def build_parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog="dadiff-bench", description=__doc__)
    add_renamed(p, "--model", former=["models"], dest="models", action="extend", nargs=1, metavar="MODEL",
                help="model folder or shipped name; repeat to compare several (default: the shipped default)")
    add_renamed(p, "--max-frames", former=["--frames"], type=int_in(1, MAX_FRAMES), default=1000,
                help=f"timed frames per model, at most {MAX_FRAMES} (default 1000)")
    p.add_argument("--warmup", type=int_in(0, MAX_FRAMES), default=20, help="untimed frames first (default 20)")
    p.add_argument("--interleave", type=int_in(0, MAX_FRAMES), default=50, metavar="N",
                   help="frames each tracker runs per turn, the trackers taking turns until each has run "
                        "--max-frames (default 50), so that a busy stretch of a shared machine falls on all of "
                        "them; 0: one tracker after another")
    p.add_argument("--clip", type=int_in(2, MAX_CLIP), default=300,
                   help=f"length of the generated clip, looped: 2 to {MAX_CLIP} frames (300)")
    p.add_argument("--seed", type=non_negative_int, default=0, help="generated night sequence (default 0, test photos)")
    p.add_argument("--threads", type=positive_int, help="intra-op threads (default: physical cores)")
    p.add_argument("--provider", help="onnxruntime execution provider (default: the best available)")
    p.add_argument("--hp", type=hp_arg, default={}, metavar="k=v,...",
                   help="tracker settings for every model, as dadiff-run --hp (e.g. motion_compensation=0)")
    p.add_argument("--success", type=non_negative_int, default=0, metavar="N",
                   help="also score night success on the first N sequences of the generated night benchmark "
                        f"(seed {SUCCESS_SEED}, test photos)")
    p.add_argument("--success-frames", type=positive_int, default=100, help="frames per success sequence (100)")
    p.add_argument("--compare-torch", action="store_true",
                   help="time the PyTorch graph on the same crops (needs dadiff[export] and a checkpoint)")
    p.add_argument("--torch-crops", type=positive_int, default=50,
                   help="search crops timed on both engines for --compare-torch (default 50, each run 3 times)")
    p.add_argument("--checkpoint", help="checkpoint of the first model, for --compare-torch and --sweep-steps "
                                        "(default: checkpoint.pt in its folder)")
    p.add_argument("--sweep-steps", help="comma-separated DDIM step counts to re-export and compare, e.g. 1,2,4")
    p.add_argument("--peak", action="store_true", help="measure the CPU's arithmetic limit (needs dadiff[export])")
    p.add_argument("--nano", action=argparse.BooleanOptionalAction, default=None,
                   help="also time OpenCV's TrackerNano (NanoTrack v2) on the same frames "
                        "(default: on when its weights are found, else a note on stderr says why not)")
    p.add_argument("--nano-dir", type=Path, metavar="DIR",
                   help=f"NanoTrack v2 ONNX folder (default: ${NANO_ENV}, else ../shared/weights/nanotrack/v2 "
                        "beside a source checkout)")
    p.add_argument("--instructions", action="store_true",
                   help="instead of timing, count instructions per update under valgrind, which runs the "
                        "program as a CPU without AVX-512 would (AVX2/FMA kernels), beside TrackerNano's: a "
                        "speed estimate for such CPUs (minutes per tracker; needs valgrind)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of tables")
    return p


def _export_side(what: str) -> None:
    """Fail early, in one line, when torch or the export package is missing (found without importing them)."""
    try:
        found = all(importlib.util.find_spec(name) is not None for name in ("torch", "onnx", "dadiff.export"))
    except ImportError:
        found = False
    if not found:
        raise BenchError(f"{what} needs the export side: pip install 'dadiff[export]'")


def _subprocess_json(args: list[str], what: str) -> dict:
    done = subprocess.run([sys.executable, *args], capture_output=True, text=True)
    if done.returncode != 0:
        tail = (done.stderr.strip().splitlines() or ["no output"])[-1]
        raise BenchError(f"{what} failed: {tail}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def _checkpoint(args: argparse.Namespace, folder: Path) -> Path:
    path = Path(args.checkpoint) if args.checkpoint else folder / "checkpoint.pt"
    if not path.is_file():
        what = "--checkpoint: no such file" if args.checkpoint else "checkpoint not found (give --checkpoint)"
        raise BenchError(f"{path}: {what}")
    return path


def _model_tracker(model: Path, args: argparse.Namespace) -> Tracker:
    return Tracker.load(model, provider=args.provider, threads=args.threads, overrides=args.hp)


def _model_result(model: Path, lane: BenchLane, run: BenchRun, args: argparse.Namespace, video: NightVideo,
                  night: Dataset | None, torch: bool, results: Path) -> dict:
    """One model's report; `torch`: also time the PyTorch graph on the same crops."""
    tracker = lane.tracker
    meta = tracker.backend.meta
    result = {"model": str(model), "name": meta.get("name", model.name), "precision": meta.get("precision", "fp32"),
              "ddim_steps": int(meta.get("ddim_steps", 0)), "gflop_search": float(meta.get("gflop_search", "nan")),
              "providers": list(getattr(tracker.backend, "providers", [])), **run.summary()}
    if night is not None:
        scores = score_tracker(tracker, night, results, "model").overall
        result["night"] = {"success": scores.success, "precision": scores.precision, "sequences": scores.sequences}
    if torch:
        result["torch"] = _compare_torch(tracker, model, args, video)
    return result


def _compare_torch(tracker: Tracker, model: Path, args: argparse.Namespace, video: NightVideo) -> dict:
    checkpoint = _checkpoint(args, model)
    template, xs = search_crops(tracker, video, args.torch_crops)
    ort_times = time_search(tracker, template, xs)
    with tempfile.TemporaryDirectory(prefix="dadiff-bench-") as tmp:
        crops = Path(tmp) / "crops.npz"
        np.savez(crops, xs=xs, **template)
        threads = thread_count(args.threads)
        torch_out = _subprocess_json(
            ["-m", "dadiff.export.bench_torch", "search", str(checkpoint), str(crops), "--threads", str(threads),
             "--steps", tracker.backend.meta["ddim_steps"]], "the PyTorch run")
    ort_ms, torch_ms = latency_ms(ort_times), latency_ms(torch_out["times"])
    return {"checkpoint": str(checkpoint), "crops": len(xs), "torch_version": torch_out["torch"],
            "ort": ort_ms, "torch_eager": torch_ms, "ratio": torch_ms["p50"] / ort_ms["p50"]}


def _sweep_models(first: Path, args: argparse.Namespace, tmp: Path) -> list[Path]:
    """The first model's checkpoint exported once per --sweep-steps value, into `tmp`."""
    checkpoint = _checkpoint(args, first)
    try:
        steps = [int(s) for s in args.sweep_steps.split(",") if s.strip()]
    except ValueError:
        raise BenchError(f"--sweep-steps must be comma-separated integers, got {args.sweep_steps!r}") from None
    folders = []
    for k in steps:
        out = tmp / f"k{k}"
        done = subprocess.run([sys.executable, "-m", "dadiff.export.cli", str(checkpoint), "--steps", str(k), "-o",
                               str(out), "--name", f"{first.name}-k{k}"], capture_output=True, text=True)
        if done.returncode != 0:
            raise BenchError(f"exporting {checkpoint} with {k} steps failed: {done.stderr.strip()}")
        folders.append(out)
    return folders


def _cpu() -> dict:
    """CPU model, core counts, the instruction sets speed depends on (None where unknown), versions."""
    model = platform.processor() or platform.machine()
    flags: dict[str, bool | None] = dict.fromkeys(CPU_FLAGS)
    try:
        with open("/proc/cpuinfo") as f:
            text = f.read()
    except OSError:
        text = ""
    model = next((ln.split(":", 1)[1].strip() for ln in text.splitlines() if ln.startswith("model name")), model)
    present = cpu_flags(text)
    if present:
        flags = {flag: flag in present for flag in CPU_FLAGS}
    return {"cpu": model, "logical": os.cpu_count(), "physical": physical_cores(), "flags": flags,
            "onnxruntime": ort.__version__, "opencv": cv2.__version__}


def _flags_text(flags: dict[str, bool | None]) -> str:
    """'avx2 yes, avx512f yes, avx512_vnni no' (or '?' where /proc/cpuinfo could not say)."""
    return ", ".join(f"{k} {'?' if v is None else 'yes' if v else 'no'}" for k, v in flags.items())


def _use_nano(args: argparse.Namespace) -> tuple[bool, str | None]:
    """Whether to time TrackerNano, and the note to print when the timing starts if not. --nano: required (a
    missing weight is an error naming --nano); default: when the weights are here, else a note (a tracker left
    out of the report is always said so); --no-nano: never, no note."""
    if args.nano is False:
        return False, None
    if args.nano is None:
        problem = nano_problem(args.nano_dir)
        if problem is None:
            return True, None
        return False, f"dadiff-bench: note: TrackerNano was not timed: {problem} (--no-nano silences this note)"
    try:
        OpenCVTracker("nano", nano_dir=args.nano_dir, option="--nano")  # checks the module and the files
    except EvalError as exc:
        raise BenchError(str(exc)) from None
    return True, None


def _print_note(note: str | None) -> None:
    """The note once every input has been checked (bad input is one error line, with no note before it); on
    stderr, so that with --json stdout stays one JSON document."""
    if note:
        print(note, file=sys.stderr)


def _nano_result(lane: BenchLane, run: BenchRun, night: Dataset | None, results: Path) -> dict:
    """TrackerNano's report: its stages from the shared run, and night success with OpenCV's threads set to ours."""
    summary = run.summary()
    summary.pop("rss_mb", None)  # the process's memory, already in the models' columns
    result = {"name": nano_label(), "model": "cv2.TrackerNano", **summary}
    if night is not None:
        with lane.opencv_threads():
            run_tracker(lane.tracker, "nano", night, results, progress=False)
        scores = score_folder(night, tracker_folder(results, night.name, "nano"), "nano").overall
        result["night"] = {"success": scores.success, "precision": scores.precision, "sequences": scores.sequences}
    return result


def _cell(entry: dict | None) -> str:
    return "-" if entry is None else f"{entry['p50']:.2f} / {entry['p95']:.2f}"


def _ratio(base: float, value: float) -> str:
    """' (1.53x)' for value/base, empty for the reference itself."""
    return "" if base == value else f" ({value / base:.2f}x)"


def _or_dash(fmt: Callable[[dict], str]) -> Callable[[dict], str]:
    """A row formatter that prints '-' for a column without that entry (the baseline's)."""
    def cell(r: dict) -> str:
        try:
            return fmt(r)
        except KeyError:
            return "-"
    return cell


def _nano_line(ref: dict, nano: dict) -> str:
    """Our first model against TrackerNano: per-frame update and end-to-end FPS."""
    ours, theirs = ref["tracker"]["p50"], nano["tracker"]["p50"]
    return (f"{ref['name']} vs {nano['name']}: update p50 {ours:.2f} ms vs {theirs:.2f} ms, FPS end to end "
            f"{ref['fps']:.1f} vs {nano['fps']:.1f} -> {ref['name']} runs at {ref['fps'] / nano['fps']:.2f}x "
            f"TrackerNano's frame rate ({theirs / ours:.2f}x its update speed)")


def print_report(report: dict) -> None:
    results = report["results"]
    ref = results[0]
    columns = [*results, *([report["nano"]] if "nano" in report else [])]
    head = report["machine"]
    print(f"dadiff-bench: {head['cpu']}, {head['logical']} logical / {head['physical']} physical cores "
          f"({_flags_text(head['flags'])}), onnxruntime {head['onnxruntime']}, OpenCV {head['opencv']}, "
          f"{report['threads']} threads; {report['video']} "
          f"({report['frames']} timed frames after {report['warmup']} warm-up, clip looped with re-init)")
    width = max(22, *(len(r["name"]) + 2 for r in columns))
    print(f"{'ms (p50 / p95)':28s}" + "".join(f"{r['name']:>{width}s}" for r in columns))
    for key, label in ROWS:
        print(f"{label:28s}" + "".join(f"{_cell(r.get(key)):>{width}s}" for r in columns))
    lines = {
        "FPS end to end": lambda r: f"{r['fps']:.1f}" + _ratio(ref["fps"], r["fps"]),
        "outside ONNX (of update)": lambda r: f"{100 * r['outside_onnx_tracker']:.1f} %",
        "outside ONNX (of frame)": lambda r: f"{100 * r['outside_onnx_frame']:.1f} %",
        "RSS first -> last (MB)": lambda r: f"{r['rss_mb']['first']:.0f} -> {r['rss_mb']['last']:.0f}",
        "peak RSS (MB)": lambda r: f"{r['rss_mb']['peak']:.0f}",
        "precision / DDIM steps": lambda r: f"{r['precision']} / {r['ddim_steps']}",
    }
    if all("night" in r for r in results):
        lines["night success (prec.)"] = lambda r: f"{r['night']['success']:.3f} ({r['night']['precision']:.3f})"
    for label, fmt in lines.items():
        print(f"{label:28s}" + "".join(f"{_or_dash(fmt)(r):>{width}s}" for r in columns))
    if "nano" in report:
        print(_nano_line(ref, report["nano"]))
    for r in results:
        if "torch" in r:
            t = r["torch"]
            print(f"{r['name']}: search graph on {t['crops']} identical crops: onnxruntime p50 "
                  f"{t['ort']['p50']:.2f} ms, PyTorch {t['torch_version']} eager p50 "
                  f"{t['torch_eager']['p50']:.2f} ms -> onnxruntime {t['ratio']:.2f}x faster")
    if "peak_gflops" in report:
        peak = report["peak_gflops"]
        print(f"arithmetic limit: {peak:.0f} GFLOP/s (onnxruntime's dense 3x3 conv on {report['threads']} threads)")
        for r in results:
            if np.isfinite(r["gflop_search"]):
                floor = r["gflop_search"] / peak * 1000
                print(f"  {r['name']}: {r['gflop_search']:.2f} GFLOP per frame -> at least {floor:.1f} ms; "
                      f"measured {r['search']['p50']:.1f} ms = {100 * floor / r['search']['p50']:.0f} % of the limit")


def run_instructions(args: argparse.Namespace, models: list[Path]) -> dict:
    """Instructions per update of each model and of TrackerNano, counted under valgrind on one clip."""
    valgrind_path()
    use_nano, note = _use_nano(args)
    with tempfile.TemporaryDirectory(prefix="dadiff-bench-") as tmp:
        video = write_night_video(Path(tmp), args.seed, min(args.clip, CLIP))  # the counter reads no more
        clip = write_clip(video.path, Path(tmp) / "clip.npy")
        _print_note(note)
        counts = [count_updates("model", str(m), clip, video.first_box, m.name) for m in models]
        if use_nano:
            nano_dir = str(nano_files(args.nano_dir)[0].parent)  # `_use_nano` checked them, naming --nano
            counts.append(count_updates("nano", nano_dir, clip, video.first_box, nano_label()))
    report = {"machine": _cpu(), "mode": "instructions", "video": f"generated night sequence {video.name}",
              "updates": list(UPDATES), "results": [vars(c) for c in counts[:len(models)]]}
    if use_nano:
        report["nano"] = vars(counts[-1])
    return report


def print_instructions(report: dict) -> None:
    head = report["machine"]
    first, last = report["updates"]
    print(f"dadiff-bench --instructions: {head['cpu']} ({_flags_text(head['flags'])}) run under valgrind, which "
          f"shows a CPU with AVX2/FMA and without AVX-512; 1 thread; {report['video']}; instructions of "
          f"updates {first + 1}-{last} / {last - first}")
    nano = report.get("nano")
    rows = [*report["results"], *([nano] if nano else [])]
    width = max(len(r["name"]) for r in rows) + 2
    print(f"{'tracker':{width}s}{'instructions per update':>26s}" + (f"{'vs TrackerNano':>18s}" if nano else ""))
    for r in rows:
        ratio = f"{nano['instructions'] / r['instructions']:>17.2f}x" if nano else ""
        print(f"{r['name']:{width}s}{r['instructions'] / 1e6:>24.1f} M" + ratio)
    if nano:
        print("vs TrackerNano: its instructions per update / this one's, an estimate of the frame-rate ratio on "
              "a CPU without AVX-512 (instructions are not seconds)")


def _model_folders(args: argparse.Namespace) -> list[Path]:
    """The models asked for (default: the shipped default), as folders; an unknown one is a ModelError."""
    try:
        return [Path(resolve(m)) for m in (args.models or [None])]
    except ModelNotFoundError as exc:
        raise ModelError(str(exc)) from None


def run(args: argparse.Namespace) -> dict:
    if args.instructions:
        return run_instructions(args, _model_folders(args))
    if args.compare_torch:
        _export_side("--compare-torch")
    if args.peak or args.sweep_steps:
        _export_side("--peak" if args.peak else "--sweep-steps")
    models = _model_folders(args)
    if args.compare_torch:
        _checkpoint(args, models[0])  # before minutes of timing, not after
    threads = thread_count(args.threads)
    use_nano, note = _use_nano(args)
    with tempfile.TemporaryDirectory(prefix="dadiff-bench-") as tmp:
        if args.sweep_steps:
            models += _sweep_models(models[0], args, Path(tmp))
        trackers = [_model_tracker(m, args) for m in models]  # a bad --hp or model before the clip is rendered
        video = write_night_video(Path(tmp), args.seed, args.clip)
        night = None
        if args.success > 0:
            night = generated_night_set(Path(tmp) / "night", args.success, args.success_frames, SUCCESS_SEED)
        lanes = [BenchLane(tracker, video, args.max_frames) for tracker in trackers]
        if use_nano:  # OpenCV's threads set to ours while it runs (`_use_nano` checked the weights)
            nano_tracker = OpenCVTracker("nano", nano_dir=args.nano_dir, option="--nano")
            lanes.append(BenchLane(nano_tracker, video, args.max_frames, cv2_threads=threads))
        _print_note(note)
        with tqdm(total=args.max_frames * len(lanes), desc="frames", unit="frame", leave=False,
                  disable=args.json or not sys.stderr.isatty()) as bar:
            runs = run_lanes(lanes, args.warmup, args.interleave, progress=lambda _: bar.update())
        results = [_model_result(m, lane, r, args, video, night, args.compare_torch and i == 0,
                                 Path(tmp) / f"results{i}")
                   for i, (m, lane, r) in enumerate(zip(models, lanes, runs, strict=False))]
        nano = _nano_result(lanes[-1], runs[-1], night, Path(tmp) / "results-nano") if use_nano else None
    names = [r["name"] for r in results]
    for r in results:  # two models with one metadata name (an fp32 model and its int8 copy): show folders
        if names.count(r["name"]) > 1:
            r["name"] = Path(r["model"]).name
    report = {"machine": _cpu(), "threads": threads, "video": f"generated night sequence {video.name}",
              "frames": args.max_frames, "warmup": args.warmup, "results": results}
    if nano is not None:
        ref = results[0]
        nano["ratio"] = {"fps": ref["fps"] / nano["fps"], "update": nano["tracker"]["p50"] / ref["tracker"]["p50"]}
        report["nano"] = nano
    if args.peak:
        report["peak_gflops"] = _subprocess_json(
            ["-m", "dadiff.export.bench_torch", "peak", "--threads", str(threads)], "the peak measurement")["gflops"]
    return report


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.checkpoint and not (args.compare_torch or args.sweep_steps):  # an option that changes nothing: an error
        print("dadiff-bench: error: --checkpoint applies to --compare-torch and --sweep-steps only", file=sys.stderr)
        return 2
    try:
        with quiet_opencv():  # FFmpeg's own lines (`moov atom not found`) stay off stderr, as in every command
            report = run(args)
    except (DadiffError, OSError) as exc:  # e.g. the clip's video not written whole, scikit-image missing
        line = os_error_line(exc) if isinstance(exc, OSError) else exc
        print(f"dadiff-bench: error: {line}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("dadiff-bench: interrupted", file=sys.stderr)
        return 130
    if args.json:
        print(json.dumps(report, indent=1))
    elif args.instructions:
        print_instructions(report)
    else:
        print_report(report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
