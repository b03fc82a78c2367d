"""dadiff-run: track one object in a video file, camera, stream or image-sequence folder.

User errors (bad model, unreadable video, bad init box, bad option) print one line
`dadiff-run: error: ...` on stderr and exit with code 2. Ctrl-C (or SIGTERM) stops cleanly: every output
is flushed and closed and the summary is printed (exit code 130); so does SIGHUP (an SSH session dropping).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

from tqdm import tqdm

from ..argtypes import non_negative_int, positive_int
from ..config import TUNABLE_KEYS
from ..cpu import warn_int8
from ..crop import protocol_box
from ..errors import DadiffError, InputError, os_error_line
from ..outputs import OutputError, Record, Sink, TrackLog, VideoSink, check_distinct
from ..runstats import RunStats
from ..sources import FolderSource, Frame, SourceError, VideoSource, open_source, parse_box, quiet_opencv
from ..tracker import Tracker
from .launch import signals_held, stop_signals_interrupt

PROG = "dadiff-run"
STATUS_EVERY_S = 5.0


class UsageError(DadiffError):
    """A command-line problem, reported as one line."""


BOX_OPTIONS = ("--init",)


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # type: ignore[override]
        if any(f"argument {o}: expected one argument" in message for o in BOX_OPTIONS):
            message += " (a box starting with '-' is written --init=-5,-5,15,9)"
        raise UsageError(f"{message} (see {PROG} --help)")


def join_negative_boxes(argv: Sequence[str], options: Sequence[str] = BOX_OPTIONS) -> list[str]:
    """`--init -5,-5,15,9` as `--init=-5,-5,15,9`: argparse takes a value starting with '-' for an option."""
    out: list[str] = []
    for arg in argv:
        if out and out[-1] in options and len(arg) > 1 and arg[0] == "-" and (arg[1].isdigit() or arg[1] == "."):
            out[-1] = f"{out[-1]}={arg}"
            continue
        out.append(arg)
    return out


def _box_arg(text: str) -> tuple[float, float, float, float]:
    try:
        box = parse_box(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    if box[2] <= 0 or box[3] <= 0:  # checked here too: the service only meets the box at its first frame
        raise argparse.ArgumentTypeError(f"box has zero or negative size (w={box[2]:g}, h={box[3]:g}), got {text!r}")
    return box


def hp_arg(text: str) -> dict[str, str]:
    """argparse type: tracker settings as key=value pairs separated by commas (checked by the tracker)."""
    values = {}
    for item in filter(None, (p.strip() for p in text.split(","))):
        key, sep, value = item.partition("=")
        if not sep or not key.strip() or not value.strip():
            raise argparse.ArgumentTypeError(f"expected key=value pairs separated by commas, got {item!r}")
        values[key.strip()] = value.strip()
    return values


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog=PROG,
        description="Track one object with a dadiff model (onnxruntime, no torch).",
        epilog="The track log has one row per frame: frame, timestamp, x, y, w, h, score, state. Frame 0 "
        "holds the init box as the released toolkit writes it, (x + 0.5, y + 0.5, w, h), state 'init'. "
        "Exit codes: 0 done, 2 bad input (one line on stderr), 130 interrupted (outputs are complete).",
    )
    parser.add_argument(
        "--video",
        metavar="SRC",
        help="video file, camera index (0) or device (/dev/video0), stream URL (rtsp://, "
        "http://), or an OTB/UAV123-style image folder",
    )
    parser.add_argument(
        "--init",
        type=_box_arg,
        metavar="x,y,w,h",
        help="target box in the first frame (default for folders: first line of groundtruth_rect.txt)",
    )
    parser.add_argument(
        "--model",
        help="model folder written by dadiff-export (or an .onnx file in it), or a "
        "shipped model name; default: the shipped default",
    )
    parser.add_argument("--preset", help="named hyper-parameter preset from the model (e.g. UAVDark70)")
    parser.add_argument(
        "--hp",
        type=hp_arg,
        default={},
        metavar="k=v,...",
        help="override " + ", ".join(TUNABLE_KEYS),
    )
    parser.add_argument(
        "--provider", help="onnxruntime provider (cpu, cuda, tensorrt, openvino; default: best)"
    )
    parser.add_argument("--threads", type=positive_int, help="threads per session (default: one per physical core)")
    parser.add_argument("-o", "--output", type=Path, metavar="FILE", help="track log, .csv or .jsonl")
    parser.add_argument("--save-video", type=Path, metavar="OUT.mp4", help="annotated video (mp4v)")
    parser.add_argument(
        "--max-frames", type=positive_int, metavar="N", help="stop after N frames (incl. the first)"
    )
    parser.add_argument(
        "--demo",
        action="store_true",
        help="generate one night sequence, track it, write the annotated video and print FPS and success",
    )
    parser.add_argument("--demo-out", type=Path, default=Path("dadiff-demo"),
                        help="folder for --demo's video (default: ./dadiff-demo)")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="sequence seed for --demo (default: 0)")
    from dadiff.drone.cli import add_mavlink_arguments  # light: no pymavlink at parser time

    add_mavlink_arguments(parser)
    return parser


DEMO_IGNORES = ("video", "init", "output", "save_video", "preset", "hp", "threads", "provider", "max_frames")


def _demo(args: argparse.Namespace) -> int:
    given = [f"--{k.replace('_', '-')}" for k in DEMO_IGNORES if getattr(args, k, None) not in (None, {}, [])]
    if given:  # an option the demo would not apply is an error, never ignored
        raise InputError(f"--demo runs the default setup on a generated sequence; {', '.join(given)} "
                         "do not apply to it (use --model, --seed, --demo-out)")
    if args.demo_out.exists() and not args.demo_out.is_dir():
        raise OutputError(f"{args.demo_out}: --demo-out exists and is not a folder")
    from .demo import run_demo  # the generator needs scikit-image's photos: loaded only here

    run_demo(args.model, args.demo_out, seed=args.seed)
    return 0


def _open_sinks(args: argparse.Namespace, fps: float | None) -> list[Sink]:
    sinks: list[Sink] = []
    try:
        if args.output is not None:
            sinks.append(TrackLog(args.output))
        if args.save_video is not None:
            sinks.append(VideoSink(args.save_video, fps))
    except OutputError:
        for sink in sinks:
            sink.close()
        raise
    return sinks


def _track(args: argparse.Namespace, stats: RunStats) -> bool:
    """Load, open, initialise, then run the loop; returns True when interrupted.

    Raises the one-line errors (ModelError, InputError, SourceError, OutputError) for bad input.
    """
    if args.output is not None and args.output.suffix.lower() not in (".csv", ".jsonl"):
        raise OutputError(f"{args.output}: --output must end in .csv or .jsonl")
    check_distinct(args.video, {"--output": args.output, "--save-video": args.save_video})
    tracker = Tracker.load(
        args.model, provider=args.provider, threads=args.threads, preset=args.preset, overrides=args.hp
    )
    warn_int8(PROG, tracker)
    source = open_source(args.video)
    sinks: list[Sink] = []
    failed: OutputError | None = None
    try:
        box = args.init or source.init_box
        if box is None:
            where = "groundtruth_rect.txt in the folder" if source.kind == "folder" else "the source"
            raise InputError(f"no --init x,y,w,h given and no box in {where}")
        frames = source.frames()
        first = next(frames, None)
        if first is None:
            raise SourceError(f"cannot read a frame from {source.kind} '{args.video}'")
        init_box = protocol_box(box)  # spec 8.5: the released toolkit's init convention
        tracker.init(first.image, init_box)
        sinks = _open_sinks(args, source.fps)
        _emit(sinks, first, Record(init_box, 1.0, "init"))
        stats.begin()
        stats.add("init")
        return _loop(tracker, source, frames, sinks, args.max_frames, stats)
    except OutputError as exc:
        failed = exc
        raise
    finally:
        stats.skipped = source.skipped
        try:
            _close_all(sinks, failed)
        finally:
            source.close()
            _warn_missing(source)


def _warn_missing(source: VideoSource | FolderSource) -> None:
    missing = getattr(source, "missing", 0)
    if missing:
        print(f"{PROG}: warning: '{source.spec}' ended {missing} frames before its stated length "  # type: ignore[union-attr]
              f"{source.length} (truncated or damaged file); they are counted as skipped", file=sys.stderr)


def _close_all(sinks: Sequence[Sink], failed: OutputError | None = None) -> None:
    """Close every sink even when one fails; after all are closed, one OutputError tells every output that
    could not be written whole (`failed`: the one that stopped the run, if any)."""
    failures = [failed] if failed is not None else []
    for sink in sinks:
        try:
            sink.close()
        except OutputError as exc:
            failures.append(exc)
    if len(failures) > (failed is not None):
        raise OutputError("; ".join(map(str, failures)))


def _loop(
    tracker: Tracker,
    source: VideoSource | FolderSource,
    frames: Iterator[Frame],
    sinks: Sequence[Sink],
    max_frames: int | None,
    stats: RunStats,
) -> bool:
    """Track every frame after the first; progress bar for files/folders, a status line for live sources."""
    total = None if source.live else source.length
    if total is not None and max_frames:
        total = min(total, max_frames)
    bar = tqdm(total=total, initial=1, unit="frame", disable=True if source.live else None, file=sys.stderr)
    next_status = time.monotonic() + STATUS_EVERY_S
    try:
        for frame in frames:
            if max_frames and stats.frames >= max_frames:
                break
            result = tracker.update(frame.image)
            stats.skipped = source.skipped
            stats.add(result.state, result.latency["total"])
            _emit(sinks, frame, Record(result.box, result.score, result.state, stats.fps_recent))
            bar.update(1)
            bar.set_postfix(state=result.state, score=f"{result.score:.2f}", refresh=False)
            if source.live and time.monotonic() >= next_status:
                next_status += STATUS_EVERY_S
                print(
                    f"{PROG}: frame {frame.index}, {stats.fps_recent or 0:.1f} FPS, {result.state} "
                    f"{result.score:.2f}, {stats.lost} lost, {source.skipped} skipped",
                    file=sys.stderr,
                    flush=True,
                )
    except KeyboardInterrupt:
        return True
    finally:
        bar.close()
    return False


def _emit(sinks: Sequence[Sink], frame: Frame, record: Record) -> None:
    with signals_held():  # every output gets the frame or none does
        for sink in sinks:
            sink.write(frame, record)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of dadiff-run; returns the exit code."""
    parser = build_parser()
    try:
        from dadiff.drone.config import parse_args as parse_with_config

        # --config FILE.toml; the command line wins
        args = parse_with_config(parser, join_negative_boxes(sys.argv[1:] if argv is None else argv))
    except UsageError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    except SystemExit as exc:  # --help
        return exc.code if isinstance(exc.code, int) else 0
    if args.mavlink and args.demo:
        print(f"{PROG}: error: --demo tracks a generated sequence on its own; it does not run with --mavlink",
              file=sys.stderr)
        return 2
    if not args.mavlink:
        from dadiff.drone.cli import service_options_given

        given = service_options_given(build_parser(), args)  # a fresh parser: --config changed the defaults
        if given:
            print(f"{PROG}: error: {', '.join(given)}: options of the MAVLink service, which runs only with "
                  "--mavlink CONN", file=sys.stderr)
            return 2
    if args.mavlink:
        from dadiff.drone.cli import run_mavlink

        with quiet_opencv():
            return run_mavlink(args)
    if args.demo:
        try:
            with stop_signals_interrupt(), quiet_opencv():
                return _demo(args)
        except OSError as exc:  # first: an UnreadableFile is a DadiffError too, and reads best as `<file>: <why>`
            print(f"{PROG}: error: {os_error_line(exc, args.demo_out)}", file=sys.stderr)
            return 2
        except (DadiffError, ValueError, ImportError) as exc:
            print(f"{PROG}: error: {exc}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            print(f"{PROG}: interrupted", file=sys.stderr)
            return 130
    if args.video is None:
        print(f"{PROG}: error: one of --video SRC, --demo or --mavlink CONN is required (see {PROG} --help)",
              file=sys.stderr)
        return 2
    stats = RunStats()
    try:
        with stop_signals_interrupt(), quiet_opencv():
            interrupted = _track(args, stats)
    except OSError as exc:  # an input the user may not read (a chmod 700 image folder)
        print(f"{PROG}: error: {os_error_line(exc)}", file=sys.stderr)
        return 2
    except DadiffError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
    print(f"{PROG}: {stats.summary(interrupted)}")
    return 130 if interrupted else 0


if __name__ == "__main__":
    sys.exit(main())
