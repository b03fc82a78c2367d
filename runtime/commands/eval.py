"""dadiff-eval: one-pass evaluation (run, score) and the night-scene benchmark generator (generate).

dadiff-eval run --model M --dataset D --output R [--attributes]
dadiff-eval run --tracker csrt|kcf|nano [--nano-dir DIR] --dataset D --output R [--gamma 0.5]
dadiff-eval score --dataset D [--json] RESULT_DIR...
dadiff-eval table --set LABEL DATASET GLOB RESULTS [--set ...] --against TRACKER [--trackers NAME ...] [--skip-first]
dadiff-eval anatomy --dataset D [--sequences GLOB] RESULT_DIR...
dadiff-eval box-read --dataset D [--sequences GLOB] [--model M] [--shifts 0 4 8 12 | --sizes 0.7 1 1.4]
dadiff-eval generate --output DIR --sequences 16 --max-frames 120 --seed 2026 [--source skimage|library]
                     [--night classic|real] [--cutouts DIR] [--gusts]
dadiff-eval video --video FILE --output DIR [--seed 0] [--min-frames 60] [--max-frames 150] [--min-aspect 0]
                  [--night real|camera|sensor]
dadiff-eval uncut --video FILE --truth DIR --output DIR [--night-seed N]
dadiff-eval uncut-score --dataset D RESULT_DIR...
dadiff-eval night --dataset D --output DIR [--seed 0] [--sequences GLOB]
dadiff-eval detect --video FILE --detector MODEL.onnx --output det.txt [--classes 1] [--tiles 3] [--min-score 0.3]
dadiff-eval pseudo-label --video FILE --detections det.txt --output DIR [--seed 0] [--min-frames 30] [--min-score 0.35]
                         [--night real|camera|sensor]
dadiff-eval hit-uav --output DIR [--data DIR] [--split test|val|train] [--max-gap 20] [--min-frames 2] [--max-move 2]
dadiff-eval cutouts --dataset D --output DIR --licence TEXT [--sequences GLOB] [--every 8] [--min-height 48]
dadiff-eval data fetch [--cache DIR] [--packages NAME ...] [--deb DIR]
dadiff-eval data list [--cache DIR]
dadiff-eval tune --model M --dataset D [--dataset D2] [--sequences GLOB] [--grid KEY=V1,V2 ...] [--output trials.csv]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections import Counter
from collections.abc import Sequence
from pathlib import Path

from ..argtypes import add_renamed, float_in, non_negative_int, positive_int
from ..datamaking.datasets import Dataset, load_dataset, plural
from ..datamaking.detection_tracks import LinkSettings, write_detection_benchmark
from ..datamaking.detector import Detector, detect_video, write_det_txt
from ..datamaking.fixed_camera import NIGHT_MODELS, LabelSettings, read_video, write_fixed_camera_benchmark
from ..datamaking.hit_uav import CLASSES as HIT_CLASSES
from ..datamaking.hit_uav import SPLITS as HIT_SPLITS
from ..datamaking.hit_uav import ChainSettings, write_hit_uav_benchmark
from ..datamaking.hit_uav import default_data_dir as default_hit_uav_dir
from ..datamaking.library import (
    DEFAULT_PACKAGES,
    ROLES,
    SPLITS,
    Library,
    LibraryError,
    fetch,
    library_root,
    open_library,
)
from ..datamaking.night import NIGHT_STYLES
from ..datamaking.night_sets import format_statistics, write_camera_nights
from ..datamaking.photos import PHOTO_SPLITS
from ..datamaking.scene import MAX_SIDE, frame_size
from ..datamaking.scenes import SOURCES, SceneError, write_benchmark
from ..errors import DadiffError, InputError, ModelError, OneLineParser, os_error_line
from ..evaluation.anatomy import anatomy, check_frames, format_anatomy, format_honesty, grey_bins, honesty
from ..evaluation.evaluate import (
    NANO_ENV,
    EvalError,
    GammaTracker,
    OpenCVTracker,
    RuntimeTracker,
    TrackerScores,
    TrackerUnavailable,
    claim_folder,
    nano_files,
    read_results,
    read_states,
    result_folders,
    run_tracker,
    score_folder,
    tracker_folder,
)
from ..evaluation.metrics import Scores, paired_difference
from ..evaluation.plots import write_plots
from ..evaluation.table import TableSet, markdown_table, score_set
from ..outputs import inside_folder, same_file
from ..sources import quiet_opencv
from .run import hp_arg

PROG = "dadiff-eval"
NOTE = (
    "Norm. Prec.: area under the normalised precision plot over [0, 0.5] (the paper's definition); "
    "NPrec@0.2: the pysot toolkit's value at 0.2."
)


MIN_SIZE, MAX_SIZE = 0.25, 4.0  # box-read --sizes: a quarter to four times the true box
MAX_SHIFT = 255.0  # box-read --shifts, crop px: the largest shipped search crop's side; 1e308 overflowed crop.py
MAX_GAMMA = 10.0  # run --gamma: above it every frame is black but its brightest pixels
MAX_PACK_MIB = 65536.0  # data pack --max-mib: 64 GiB; finite and bounded, so nan and inf are one-line errors


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT such as 640x360, got '{text}'") from None
    try:
        return frame_size((w, h), 1)  # bounded at parse time, before OpenCV is asked to allocate the frame
    except SceneError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def tracker_name(text: str) -> str:
    """argparse type for `run --name`: one folder name (`../x` wrote outside the results and `""` the default)."""
    if text in ("", ".", "..") or "/" in text or (os.altsep and os.altsep in text) or "\0" in text:
        raise argparse.ArgumentTypeError(f"expected a folder name without '/', not '.' or '..', got {text!r}")
    return text


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog=PROG, description="One-pass evaluation of single-object trackers.",
                           epilog="Exit codes: 0 done, 2 bad input (one 'dadiff-eval: error:' line), 130 interrupted "
                                  "(finished sequences are kept).")
    sub = parser.add_subparsers(dest="command", required=True,
                                metavar="{run,score,table,anatomy,box-read,generate,video,night,uncut,uncut-score,"
                                        "detect,pseudo-label,hit-uav,cutouts,data,tune}")

    selection = argparse.ArgumentParser(add_help=False)
    selection.add_argument("--dataset", required=True, type=Path, help="dataset folder or pysot-toolkit .json file")
    selection.add_argument("--sequences", action="append", metavar="GLOB",
                           help="only sequences matching this pattern (repeat for several)")
    common = argparse.ArgumentParser(add_help=False, parents=[selection])
    common.add_argument("--attributes", action="store_true", help="also print (and plot) scores per attribute")

    run = sub.add_parser("run", parents=[common], help="run a tracker over a dataset, then score and plot")
    add_renamed(run, "-o", "--output", former=["--results"], required=True, type=Path,
                help="results root: <output>/<dataset>/<tracker>/")
    run.add_argument("--model", help="dadiff model folder, .onnx file or shipped name (default: shipped default)")
    run.add_argument("--tracker", choices=("dadiff", "csrt", "kcf", "nano"), default="dadiff",
                     help="tracker to run (nano: OpenCV's TrackerNano with NanoTrack v2 weights)")
    run.add_argument("--nano-dir", type=Path, metavar="DIR",
                     help="folder of nanotrack_backbone_sim.onnx and nanotrack_head_sim.onnx (default: "
                          f"${NANO_ENV}, else ../shared/weights/nanotrack/v2 beside a source checkout)")
    run.add_argument("--gamma", type=float_in(0, MAX_GAMMA, open_low=True), metavar="G",
                     help="apply a plain gamma curve, 255*(v/255)**G, to each frame before the tracker sees it "
                          "(0.5 lifts the dark: a night baseline); recorded in run.json, and the default --name "
                          "gets '-gammaG'")
    run.add_argument("--name", type=tracker_name,
                     help="tracker name for the results folder (default: model folder name, CSRT, KCF, NANO); "
                          "a folder holds one setting (its run.json records it): give a new name for another --model, "
                          "--preset or --hp")
    run.add_argument("--preset", help="hyper-parameter preset of the model (e.g. UAVDark70, NUT_L)")
    run.add_argument("--hp", type=hp_arg, default={}, metavar="k=v,...",
                     help="tracker settings over the preset's, as dadiff-run --hp (e.g. motion_compensation=0)")
    run.add_argument("--threads", type=positive_int,
                     help="onnxruntime threads (default: one per physical core)")
    run.add_argument("--compare", nargs="+", type=Path, default=[], metavar="DIR", help="more result folders")
    run.add_argument("--plots", type=Path, help="plot folder (default: <results>/plots/<dataset>)")
    run.add_argument("--no-plots", action="store_true", help="do not draw plots")
    run.add_argument("--no-progress", action="store_true",
                     help="no progress bar (default: a bar when stderr is a terminal)")

    score = sub.add_parser("score", parents=[common], help="score result folders of any tracker")
    score.add_argument("dirs", nargs="+", type=Path, metavar="DIR", help="tracker result folders, or their parent")
    score.add_argument(
        "--json", action="store_true", help='print {tracker: {"success", "norm_precision", "precision"}}; with '
        '--attributes also "attributes": {name: {"sequences", "success", "norm_precision", "precision"}}'
    )
    score.add_argument("--plots", type=Path, help="also draw plots into this folder")
    score.add_argument("--against", metavar="TRACKER",
                       help="also print each tracker's success minus this one's, with a 95%% bootstrap interval "
                            "over the sequences")

    table = sub.add_parser("table", help="one Markdown table: each tracker's success / precision on several sets, "
                           "with 95%% paired bootstrap intervals against a baseline and the spread over seeds")
    table.add_argument("--set", dest="sets", action="append", nargs=4, required=True,
                       metavar=("LABEL", "DATASET", "GLOB", "RESULTS"),
                       help="a column: its label, the dataset, its sequences (glob; '*' for all) and the results "
                            "folder <results>/<dataset> holding one folder per tracker (repeat for more sets); "
                            "folders NAME@SEED are seeds of one model")
    table.add_argument("--against", required=True, metavar="TRACKER", help="the baseline the intervals compare with")
    table.add_argument("--trackers", nargs="+", metavar="NAME", help="rows, in this order (default: all found)")
    table.add_argument("--skip-first", action="store_true",
                       help="score the frames after the init frame only (its box is the truth for every tracker: "
                            "half of a two-frame sequence such as hit-uav's)")

    anat = sub.add_parser("anatomy", parents=[selection],
                          help="where trackers lose frames: centred share, IoU there, by the target's grey level")
    anat.add_argument("dirs", nargs="+", type=Path, metavar="DIR", help="tracker result folders, or their parent")

    read = sub.add_parser("box-read", parents=[selection],
                          help="the network's own box around each true box, before the tracker smooths it")
    read.add_argument("--model", help="dadiff model folder, .onnx file or shipped name (default: shipped default)")
    read.add_argument("--shifts", nargs="+", type=float_in(-MAX_SHIFT, MAX_SHIFT), metavar="PX",
                      help="move the search crop's centre this many crop pixels right of the true centre, one read "
                           "per shift (default: every quarter of the model's stride over one stride: 0 4 8 12 at 16; "
                           "the stride of its points, so for a finer head give its features' cells); at most "
                           f"{MAX_SHIFT:g} either way and the model's search crop")
    read.add_argument("--sizes", nargs="+", type=float_in(MIN_SIZE, MAX_SIZE), metavar="F",
                      help="instead of shifts: cut each crop as if the tracker held the true box times F (centre "
                           "kept) and print how far the read follows F, its slope and the size the tracker settles "
                           f"at (e.g. 0.7 0.85 1 1.18 1.4); {MIN_SIZE:g}-{MAX_SIZE:g}")
    read.add_argument("--threads", type=positive_int, help="onnxruntime threads (default: one per physical core)")

    gen = sub.add_parser("generate", help="write a night-scene benchmark (OTB layout, day and night)")
    add_renamed(gen, "-o", "--output", former=["--out"], required=True, type=Path, help="new (or empty) output folder")
    gen.add_argument("--sequences", type=positive_int, default=16, help="sequences (default 16)")
    add_renamed(gen, "--max-frames", former=["--frames"], type=positive_int, default=120,
                help="frames per sequence (default 120)")
    gen.add_argument("--seed", type=non_negative_int, default=0, help="first sequence's seed (default 0)")
    gen.add_argument("--split", choices=tuple(PHOTO_SPLITS), default="test", help="photo split (default: test)")
    gen.add_argument("--size", type=_size, default=(640, 360), metavar="WxH",
                     help=f"frame size, 64 to {MAX_SIDE} px a side (default 640x360)")
    gen.add_argument("--workers", type=positive_int, help="processes (default: one per core)")
    gen.add_argument(
        "--source",
        choices=SOURCES,
        default="skimage",
        help="pictures: skimage (blobs over scikit-image photos, default) or library (real cut-outs over aerial "
        "backgrounds and photos; needs dadiff-eval data fetch)",
    )
    gen.add_argument(
        "--night",
        choices=NIGHT_STYLES,
        help="night look: classic (the seed-2026 benchmark's) or real (as measured on real night drone video); "
        "default: classic for skimage, real for library",
    )
    gen.add_argument("--cutouts", type=Path, help="with --source library: targets from this cut-out folder "
                     "(dadiff-eval cutouts) instead of the library's")
    gen.add_argument("--gusts", action="store_true", help="with --source library: a gust knocks each sequence's "
                     "camera once (the picture jumps 20-40 px a frame, then drifts back): fast motion")
    _add_video_parser(sub)
    _add_uncut_parsers(sub, selection)
    _add_night_parser(sub, selection)
    _add_detect_parser(sub)
    _add_pseudo_label_parser(sub)
    _add_hit_uav_parser(sub)
    _add_cutouts_parser(sub)
    _add_data_parser(sub)
    _add_tune_parser(sub)
    return parser


def _add_video_parser(sub: argparse._SubParsersAction) -> None:
    video = sub.add_parser("video", help="day and night sequences from a fixed-camera video, its movers labelled "
                           "by background subtraction (OTB layout)")
    video.add_argument("--video", required=True, type=Path, help="video file (or folder of frames) from a camera "
                       "that does not move")
    add_renamed(video, "-o", "--output", former=["--out"], required=True, type=Path,
                help="new (or empty) output folder")
    video.add_argument("--seed", type=non_negative_int, default=0,
                       help="seed of the night cameras and lights (default 0)")
    video.add_argument("--min-frames", type=positive_int, default=60, help="shortest sequence (default 60)")
    video.add_argument("--max-frames", type=positive_int, default=150, help="longest sequence (default 150)")
    video.add_argument("--min-aspect", type=float, default=0.0,
                       help="height over width every box must reach (1.8: lone upright people; default 0: any)")
    video.add_argument("--threshold", type=positive_int, default=30,
                       help="grey-level difference from the background that counts as moving (default 30)")
    video.add_argument("--min-area", type=positive_int, default=150, help="smallest box in px (default 150)")
    _add_night_model_argument(video)


def _add_night_model_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--night", choices=NIGHT_MODELS, default="real",
                        help="night model: real (the generator's, default), camera (an independently written "
                        "camera simulation in linear light, camera_night.py) or sensor (a third, written apart from "
                        "both: a Bayer sensor and a budget ISP, sensor_night.py)")


def _add_night_parser(sub: argparse._SubParsersAction, selection: argparse.ArgumentParser) -> None:
    night = sub.add_parser("night", parents=[selection], help="the day sequences of any dataset and their nights "
                           "by the independent camera model (OTB layout)")
    add_renamed(night, "-o", "--output", former=["--out"], required=True, type=Path,
                help="new (or empty) output folder")
    night.add_argument("--seed", type=non_negative_int, default=0, help="seed of the night cameras (default 0)")


def _add_uncut_parsers(sub: argparse._SubParsersAction, selection: argparse.ArgumentParser) -> None:
    uncut = sub.add_parser("uncut", help="whole-clip sequences (OTB layout) from a video and hand-checked truth "
                           "that marks frames unknown or absent (docs/vtest-uncut for vtest.avi)")
    uncut.add_argument("--video", required=True, type=Path, help="the video the truth was made for")
    uncut.add_argument("--truth", required=True, type=Path, help="truth folder: clips.json and one folder per clip")
    add_renamed(uncut, "-o", "--output", former=["--out"], required=True, type=Path,
                help="new (or empty) output folder")
    uncut.add_argument("--night-seed", type=non_negative_int, metavar="N",
                       help="render the video at night first (video's night camera and lights, drawn by N)")
    score = sub.add_parser("uncut-score", parents=[selection],
                           help="success, precision and 'tracking' while off the person on uncut clips")
    score.add_argument("dirs", nargs="+", type=Path, metavar="DIR", help="tracker result folders, or their parent")


def _add_detect_parser(sub: argparse._SubParsersAction) -> None:
    detect = sub.add_parser("detect", help="a video's per-frame boxes from an ONNX object detector (TF Object "
                            "Detection API interface), as a MOTChallenge det.txt for pseudo-label")
    detect.add_argument("--video", required=True, type=Path, help="video file (or folder of frames)")
    detect.add_argument("--detector", required=True, type=Path, help="the detector, .onnx")
    add_renamed(detect, "-o", "--output", former=["--out"], required=True, type=Path, help="det.txt to write")
    detect.add_argument("--classes", type=_class_ids, default={1}, metavar="ID[,ID...]",
                        help="class ids to keep (COCO: 1 person, 3 car; default 1)")
    detect.add_argument("--tiles", type=int, choices=range(0, 9), default=3, metavar="0-8",
                        help="overlapping tiles along the frame's long side, besides the whole frame (default 3)")
    detect.add_argument("--min-score", type=float, default=0.3, help="detections below are not written (default 0.3)")
    detect.add_argument("--threads", type=positive_int, default=1, help="onnxruntime threads (default 1)")


def _class_ids(text: str) -> set[int]:
    try:
        ids = {int(v) for v in text.split(",")}
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected class ids such as 1 or 1,3, got '{text}'") from None
    return ids


def _add_cutouts_parser(sub: argparse._SubParsersAction) -> None:
    cut = sub.add_parser("cutouts", help="target cut-outs (BGRA PNGs) from a labelled dataset's frames by GrabCut, "
                         "for the library scenes' targets")
    cut.add_argument("--dataset", required=True, type=Path,
                     help="labelled sequences (what pseudo-label or video wrote)")
    cut.add_argument("--sequences", nargs="+", default=["*_day"], metavar="GLOB",
                     help="sequences to cut from (default: *_day)")
    add_renamed(cut, "-o", "--output", former=["--out"], required=True, type=Path,
                help="new (or empty, or an earlier cut-out) folder")
    cut.add_argument("--licence", required=True, help="the footage's licence, recorded in the index")
    cut.add_argument("--every", type=positive_int, default=8, help="every N-th frame of a sequence (default 8)")
    cut.add_argument("--min-height", type=float, default=48.0, help="smallest box height in px (default 48)")


def _add_pseudo_label_parser(sub: argparse._SubParsersAction) -> None:
    label = sub.add_parser("pseudo-label", help="day and night sequences from any video (moving camera too), its "
                           "people linked from a detector's per-frame boxes (OTB layout)")
    label.add_argument("--video", required=True, type=Path, help="video file (or folder of frames)")
    label.add_argument("--detections", required=True, type=Path,
                       help="the detector's boxes as a MOTChallenge det.txt: frame,id,x,y,w,h,score per line, "
                       "frames from 1")
    add_renamed(label, "-o", "--output", former=["--out"], required=True, type=Path,
                help="new (or empty) output folder")
    label.add_argument("--seed", type=non_negative_int, default=0,
                       help="seed of the night cameras and lights (default 0)")
    label.add_argument("--min-frames", type=positive_int, default=30, help="shortest sequence (default 30)")
    label.add_argument("--max-frames", type=positive_int, default=150, help="longest sequence (default 150)")
    label.add_argument("--min-score", type=float, default=0.35, help="detections below are ignored (default 0.35)")
    label.add_argument("--min-height", type=float, default=24.0, help="smallest box height in px (default 24)")
    label.add_argument("--aspect", type=_aspect_range, default=(1.2, 5.0), metavar="MIN-MAX",
                       help="height over width a box must have (default 1.2-5: upright people; 0.2-5: any object)")
    _add_night_model_argument(label)


def _add_hit_uav_parser(sub: argparse._SubParsersAction) -> None:
    hit = sub.add_parser("hit-uav", help="tracking sequences from HIT-UAV's real night thermal stills: the same "
                         "object's boxes in neighbouring stills of a flight, linked (OTB layout)")
    add_renamed(hit, "-o", "--output", former=["--out"], required=True, type=Path,
                help="new (or empty) output folder, outside the repository")
    hit.add_argument("--data", type=Path, help="the HIT-UAV night folder (images/, annotations/; default: "
                     "../shared/data/hit-uav-night beside a source checkout)")
    hit.add_argument("--split", choices=HIT_SPLITS, default="test",
                     help="the dataset's own split (default: test, never trained on)")
    hit.add_argument("--max-gap", type=positive_int, default=ChainSettings.max_gap,
                     help="most video frames between two linked stills (default: %(default)s)")
    hit.add_argument("--max-move", type=float_in(0, open_low=True), metavar="SIDES",
                     help="keep only links where the target's centre moves at most this many box sides in the image "
                          "(within a tracker's search region; default: any move, camera jumps included)")
    hit.add_argument("--min-frames", type=positive_int, default=ChainSettings.min_frames,
                     help="fewest stills in a sequence, at least 2 (default: %(default)s)")


def _aspect_range(text: str) -> tuple[float, float]:
    try:
        low, high = (float(v) for v in text.split("-"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected MIN-MAX such as 1.2-5, got '{text}'") from None
    if not 0 < low < high:
        raise argparse.ArgumentTypeError(f"expected 0 < MIN < MAX, got '{text}'")
    return low, high


def _add_tune_parser(sub: argparse._SubParsersAction) -> None:
    tune = sub.add_parser("tune", help="search the tracking hyper-parameters on a validation set")
    tune.add_argument("--dataset", required=True, type=Path, action="append",
                      help="validation dataset (repeat for several; keep it apart from the sets you report on)")
    tune.add_argument("--sequences", action="append", metavar="GLOB", help="only sequences matching this pattern")
    tune.add_argument("--model", help="dadiff model folder, .onnx file or shipped name (default: shipped default)")
    tune.add_argument("--preset", help="preset to start from (default: the model's)")
    tune.add_argument("--grid", action="append", default=[], metavar="KEY=V1,V2",
                      help="values to try for one parameter (repeat; default: lr, penalty_k, window_influence)")
    tune.add_argument("--rounds", type=positive_int, default=2, help="passes over the parameters (default 2)")
    tune.add_argument("--threads", type=positive_int, help="onnxruntime threads (default: one per physical core)")
    add_renamed(tune, "-o", "--output", former=["--out"], type=Path, help="write every trial to this CSV file")


def _add_data_parser(sub: argparse._SubParsersAction) -> None:
    """`data fetch`, `data list` and `data pack`."""
    data = sub.add_parser("data", help="the real-photo scene library (Debian packages, cached outside git)")
    actions = data.add_subparsers(dest="action", required=True, metavar="{fetch,list,pack}")
    cache = argparse.ArgumentParser(add_help=False)
    where = "library folder (default: $DADIFF_DATA_DIR, else ~/.cache/dadiff/library)"
    cache.add_argument("--cache", type=Path, metavar="DIR", help=where)
    get = actions.add_parser("fetch", parents=[cache], help="download, unpack and index packages (incremental)")
    get.add_argument("--packages", nargs="+", metavar="NAME",
                     help=f"Debian packages (default: {' '.join(DEFAULT_PACKAGES)})")
    get.add_argument("--deb", type=Path, metavar="DIR", help="take .deb files from this folder instead of apt-get")
    actions.add_parser("list", parents=[cache], help="images per package, role and split, and licences")
    pack = actions.add_parser("pack", parents=[cache],
                              help="a small copy of the library (e.g. to train on a lent GPU machine)")
    add_renamed(pack, "-o", "--output", former=["--out"], type=Path, required=True, metavar="DIR",
                help="new or empty folder for the pack")
    pack.add_argument("--max-mib", type=float_in(0, MAX_PACK_MIB, open_low=True), default=40.0,
                      help=f"size budget in MiB, above 0 and at most {MAX_PACK_MIB:g} (default: %(default)s)")
    pack.add_argument("--split", choices=("train", "all"), default="train",
                      help="which images to pack (default: %(default)s)")


# ---------------------------------------------------------------------------------------------- output


def format_table(title: str, scores: Sequence[TrackerScores], attribute: str | None = None) -> str:
    """Plain-text table, best success first."""
    rows = []
    for item in sorted(scores, key=lambda s: -_pick(s, attribute).success):
        s = _pick(item, attribute)
        rows.append(
            (
                item.name,
                f"{s.success:.3f}",
                f"{s.norm_precision:.3f}",
                f"{s.precision:.3f}",
                f"{s.norm_precision_at_20:.3f}",
            )
        )
    header = ("Tracker", "Succ.", "Norm. Prec.", "Prec.", "NPrec@0.2")
    widths = [max(len(r[k]) for r in [header, *rows]) for k in range(len(header))]
    lines = [title] + ["  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip() for r in [header, *rows]]
    return "\n".join(lines)


def _pick(item: TrackerScores, attribute: str | None):
    return item.overall if attribute is None else item.by_attribute[attribute]


def attribute_names(dataset: Dataset, wanted: bool, label: str) -> list[str]:
    """The attributes to report under --attributes; a note on stderr when there are none (an option that
    changes nothing says why)."""
    if not wanted:
        return []
    names = dataset.attributes()
    if not names:
        print(f"{PROG}: note: --attributes: no sequence of {label} has attributes (attributes.json, "
              "att/<seq>.txt or a pysot .json's attr); overall scores only", file=sys.stderr)
    return names


def _scores_json(s: Scores) -> dict[str, float]:
    return {"success": s.success, "norm_precision": s.norm_precision, "precision": s.precision}


def scores_table(dataset: Dataset, scores: Sequence[TrackerScores], names: list[str]) -> dict:
    """`score --json`'s document: overall scores per tracker, and per attribute when `names` are given
    (--attributes reaches the JSON as it reaches the table)."""
    table = {}
    for item in scores:
        entry: dict = _scores_json(item.overall)
        if names:
            entry["attributes"] = {
                attr: {"sequences": sum(attr in q.attributes for q in dataset.sequences),
                       **_scores_json(item.by_attribute[attr])}
                for attr in names
            }
        table[item.name] = entry
    return table


def report(
    dataset: Dataset, scores: list[TrackerScores], attributes: bool, plots: Path | None, subset: list[str] | None
) -> None:
    """Print the overall table (and per attribute), then draw the plots."""
    label = dataset.name + (f" ({' '.join(subset)})" if subset else "")
    names = attribute_names(dataset, attributes, label)  # its note before the tables, not between them
    print(format_table(f"{label}: {plural(len(dataset.sequences), 'sequence')}", scores))
    for attr in names:
        count = sum(attr in s.attributes for s in dataset.sequences)
        print()
        print(format_table(f"{attr}: {plural(count, 'sequence')}", scores, attr))
    print(NOTE)
    if plots is not None:
        written = write_plots({s.name: s.overall for s in scores}, plots, label)
        for attr in names:
            written += write_plots({s.name: s.by_attribute[attr] for s in scores}, plots, label, attr)
        print(f"plots: {len(written)} PNG files in {plots}")


# -------------------------------------------------------------------------------------------- commands


def check_output(option: str, path: Path | None, inputs: Sequence[Path]) -> None:
    """InputError when an output would land on an input file or inside an input folder, before any work:
    no command writes over what it reads (`tune --output ds/a/groundtruth_rect.txt` is refused)."""
    if path is None:
        return
    for source in inputs:
        source = Path(source).expanduser()
        if source.is_dir() and inside_folder(path, source):
            raise InputError(f"{path}: {option} lies inside the input folder {source}; choose a path outside it "
                             "(nothing written)")
        if same_file(path.expanduser(), source):
            raise InputError(f"{path}: {option} names the input file {source}; choose another (nothing written)")


def _check_results(results: Path, dataset: str, name: str) -> None:
    """`run --output` and the folders under it must be folders where they exist: checked before tracking,
    so that a bad output path fails at once, not after the run."""
    for path in (results, results / dataset, tracker_folder(results, dataset, name)):
        if path.exists() and not path.is_dir():
            raise InputError(f"{path}: is a file, not a folder; --output needs a folder here (nothing tracked)")


def _make_tracker(args: argparse.Namespace) -> tuple[object, str]:
    tracker, name = _make_plain_tracker(args)
    if args.gamma is None:
        return tracker, name
    return GammaTracker(tracker, args.gamma), args.name or f"{name}-gamma{args.gamma:g}"


def _make_plain_tracker(args: argparse.Namespace) -> tuple[object, str]:
    if args.tracker != "dadiff":
        for option in ("model", "preset", "hp", "threads"):
            if getattr(args, option):
                raise InputError(f"--{option} does not apply to --tracker {args.tracker}")
        if args.nano_dir and args.tracker != "nano":
            raise InputError(f"--nano-dir does not apply to --tracker {args.tracker}")
        return OpenCVTracker(args.tracker, nano_dir=args.nano_dir), args.name or args.tracker.upper()
    if args.nano_dir:
        raise InputError("--nano-dir applies to --tracker nano only")
    from dadiff.models import ModelNotFoundError, resolve

    from ..tracker import Tracker

    try:
        name = args.name or resolve(args.model).name
    except ModelNotFoundError as exc:
        raise ModelError(str(exc)) from None
    tracker = Tracker.load(args.model, preset=args.preset, threads=args.threads, overrides=args.hp)
    return RuntimeTracker(tracker), name


def _plain(value: object) -> object:
    """A setting's value as JSON keeps it."""
    return value if isinstance(value, (bool, int, float, str)) or value is None else str(value)


def run_record(args: argparse.Namespace, tracker: object) -> dict:
    """What decides this run's boxes, for the result folder's run.json: the tracker, the model's files (by
    hash: a model re-exported in place is another model), every tunable setting's value in effect and the
    NanoTrack weights. Not --threads or --sequences, which change no box; not the --preset name or the --hp
    keys typed, which refused identical settings (no --preset then the model's default one)."""
    from ..config import TUNABLE_KEYS
    from ..ort_cache import file_sha256

    record: dict = {"record": 1, "tracker": args.tracker}
    if isinstance(tracker, GammaTracker):
        record["gamma"] = tracker.gamma
        tracker = tracker.tracker
    if isinstance(tracker, RuntimeTracker):
        backend, params = tracker.tracker.backend, tracker.tracker.params
        record["model"] = {"folder": str(Path(backend.folder).resolve()),
                           "template_sha256": file_sha256(backend.template_path),
                           "search_sha256": file_sha256(backend.search_path)}
        record["hp"] = {key: _plain(getattr(params, key)) for key in TUNABLE_KEYS}  # lr=.05 and lr=0.05 are one
    elif args.tracker == "nano":
        backbone, head = nano_files(args.nano_dir)
        record["nano"] = {"folder": str(backbone.parent.resolve()), "backbone_sha256": file_sha256(backbone),
                          "head_sha256": file_sha256(head)}
    return record


def cmd_run(args: argparse.Namespace) -> int:
    dataset = load_dataset(args.dataset).select(args.sequences)
    try:
        tracker, name = _make_tracker(args)
    except TrackerUnavailable as exc:  # this machine lacks a module or weights: exit 2 like other bad input
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    _check_results(args.output, dataset.name, name)
    results = tracker_folder(args.output, dataset.name, name)
    check_output("--output", results, [args.dataset])
    plots = None if args.no_plots else (args.plots or args.output / "plots" / dataset.name)
    check_output("--plots", plots, [args.dataset])
    warning = claim_folder(results, run_record(args, tracker))  # before tracking: other settings are refused
    if warning:
        print(f"{PROG}: warning: {warning}", file=sys.stderr)
    # a bar only on a terminal, as dadiff-run: redirected, it filled logs with one line per refresh
    progress = not args.no_progress and sys.stderr.isatty()
    done = run_tracker(tracker, name, dataset, args.output, progress=progress)
    fps = f", {done.fps:.1f} FPS" if done.fps else ""
    print(
        f"{name}: tracked {plural(len(done.ran), 'sequence')} ({done.frames} frames{fps}), "
        f"{len(done.skipped)} already done, results in {done.folder}"
    )
    scores = [score_folder(dataset, done.folder, name)]
    for other, folder in result_folders([done.folder.parent, *args.compare], dataset):
        if folder.resolve() == done.folder.resolve():
            continue
        try:
            scores.append(score_folder(dataset, folder, other))
        except EvalError as exc:
            print(f"{PROG}: note: not compared: {exc}", file=sys.stderr)
    report(dataset, scores, args.attributes, plots, args.sequences)
    return 0


def format_differences(scores: Sequence[TrackerScores], against: str) -> str:
    """One line per tracker: success minus `against`'s, absolute and relative, with its interval."""
    base = next((s for s in scores if s.name == against), None)
    if base is None:
        raise InputError(f"--against {against}: no such tracker among {', '.join(s.name for s in scores)}")
    if len(scores) == 1:  # a table needs a row to compare: say so rather than print a bare heading
        return f"--against {against}: nothing to compare ({against} is the only tracker given)"
    names = list(base.sequences)
    lines = [f"success minus {against} (per-sequence bootstrap, 95% interval):"]
    for item in scores:
        if item is base:
            continue
        d = paired_difference([item.sequences[n].success.mean() for n in names],
                              [base.sequences[n].success.mean() for n in names])
        relative = 100 * d.mean / base.overall.success if base.overall.success else float("nan")
        lines.append(f"  {item.name}: {d.mean:+.3f} ({relative:+.1f} %) [{d.low:+.3f}, {d.high:+.3f}] "
                     f"over {plural(d.sequences, 'sequence')}")
    return "\n".join(lines)


def cmd_score(args: argparse.Namespace) -> int:
    check_output("--plots", args.plots, [args.dataset])
    dataset = load_dataset(args.dataset).select(args.sequences)
    scores = [score_folder(dataset, folder, name) for name, folder in result_folders(args.dirs, dataset)]
    differences = format_differences(scores, args.against) if args.against else None
    if args.json:
        label = dataset.name + (f" ({' '.join(args.sequences)})" if args.sequences else "")
        names = attribute_names(dataset, args.attributes, label)
        print(json.dumps(scores_table(dataset, scores, names), indent=2))
        if differences:
            print(differences, file=sys.stderr)  # stdout stays one JSON document
        if args.plots:
            write_plots({s.name: s.overall for s in scores}, args.plots, label)
            for attr in names:
                write_plots({s.name: s.by_attribute[attr] for s in scores}, args.plots, label, attr)
        return 0
    report(dataset, scores, args.attributes, args.plots, args.sequences)
    if differences:
        print(differences)
    return 0


def cmd_table(args: argparse.Namespace) -> int:
    sets = [TableSet(label, Path(dataset), pattern, Path(results)) for label, dataset, pattern, results in args.sets]
    first = 1 if args.skip_first else 0
    cells = [score_set(table_set, args.against, first) for table_set in sets]
    print(markdown_table(sets, cells, args.against, args.trackers, first))
    return 0


def cmd_anatomy(args: argparse.Namespace) -> int:
    dataset = load_dataset(args.dataset).select(args.sequences)
    check_frames(dataset)
    folders = result_folders(args.dirs, dataset)
    gts = [seq.boxes for seq in dataset.sequences]
    # every result and state file is read and checked before the (slow) pass over the frames
    runs = [(name, read_results(dataset, folder), read_states(dataset, folder)) for name, folder in folders]
    runs = [(name, [boxes[seq.name] for seq in dataset.sequences], states) for name, boxes, states in runs]
    bins = grey_bins(dataset)
    print(format_anatomy(dataset, [anatomy(name, gts, preds, bins) for name, preds, _ in runs], bins))
    told = [honesty(name, gts, preds, [states[seq.name] for seq in dataset.sequences])
            for name, preds, states in runs if states is not None]
    if told:
        print(format_honesty(told))
    return 0


def cmd_generate(args: argparse.Namespace) -> int:
    start = time.perf_counter()
    root = write_benchmark(
        args.output,
        args.sequences,
        args.max_frames,
        args.seed,
        args.split,
        size=args.size,
        workers=args.workers,
        source=args.source,
        night=args.night,
        library=_cutout_library(args),
        gusts=args.gusts,
    )
    took = time.perf_counter() - start
    night = json.loads((root / "benchmark.json").read_text())["night"]
    print(
        f"wrote {args.sequences} day + {args.sequences} night sequences of {args.max_frames} frames to {root} "
        f"({args.source} pictures, {night} night) in {took:.1f} s"
    )
    return 0


def _cutout_library(args: argparse.Namespace):
    """`generate --cutouts`: the library with that folder's cut-outs as its targets (None without it)."""
    if args.cutouts is None:
        return None
    if args.source != "library":
        raise SceneError("--cutouts needs --source library (the cut-outs are pasted over its backgrounds)")
    from ..datamaking.cutouts import CutoutTargets
    from ..datamaking.library_scenes import open_scene_library

    return CutoutTargets(open_scene_library(), args.cutouts)


def cmd_cutouts(args: argparse.Namespace) -> int:
    from ..datamaking.cutouts import CutSettings, write_cutouts

    if not args.min_height > 0:
        raise SceneError(f"--min-height {args.min_height} must be above 0 (px)")
    start = time.perf_counter()
    dataset = load_dataset(args.dataset).select(args.sequences)
    index = write_cutouts(dataset, args.output, args.licence, CutSettings(args.every, args.min_height))
    splits = Counter(item["split"] for item in index["cutouts"])
    rejected = ", ".join(f"{n} {why}" for why, n in index["rejected"].items()) or "none"
    print(f"wrote {len(index['cutouts'])} cut-outs ({splits['train']} train, {splits['test']} test) from "
          f"{len(dataset.sequences)} sequences to {args.output} in {time.perf_counter() - start:.1f} s; "
          f"rejected: {rejected}")
    return 0


def _check_sequence_lengths(args: argparse.Namespace) -> None:
    if args.max_frames < args.min_frames:
        raise SceneError(f"--max-frames {args.max_frames} is below --min-frames {args.min_frames}")


def cmd_video(args: argparse.Namespace) -> int:
    _check_sequence_lengths(args)
    if not 0 <= args.min_aspect < 100:
        raise SceneError(f"--min-aspect {args.min_aspect} must be in [0, 100)")
    if args.threshold > 254:
        raise SceneError(f"--threshold {args.threshold} must be below 255 (grey levels)")
    settings = LabelSettings(threshold=args.threshold, min_area=args.min_area, min_frames=args.min_frames,
                             max_frames=args.max_frames, min_aspect=args.min_aspect)
    start = time.perf_counter()
    tracks = write_fixed_camera_benchmark(args.video, args.output, args.seed, settings, night=args.night)
    frames = sum(len(t.boxes) for t in tracks)
    print(f"wrote {len(tracks)} day + {len(tracks)} night sequences ({frames} frames each way, "
          f"{min(len(t.boxes) for t in tracks)}-{max(len(t.boxes) for t in tracks)} per sequence) from "
          f"{args.video} to {args.output} in {time.perf_counter() - start:.1f} s")
    return 0


def cmd_uncut(args: argparse.Namespace) -> int:
    from ..evaluation.uncut import write_uncut_clips

    start = time.perf_counter()
    frames = write_uncut_clips(args.video, args.truth, args.output, args.night_seed)
    look = "day" if args.night_seed is None else f"night (seed {args.night_seed})"
    print(f"wrote the clips of {args.truth} over {frames} frames of {args.video} ({look}) to {args.output} "
          f"in {time.perf_counter() - start:.1f} s")
    return 0


def cmd_uncut_score(args: argparse.Namespace) -> int:
    from ..evaluation.uncut import format_uncut, uncut_scores

    dataset = load_dataset(args.dataset).select(args.sequences)
    rows = {name: uncut_scores(dataset, folder) for name, folder in result_folders(args.dirs, dataset)}
    print(format_uncut(rows))
    return 0


def cmd_night(args: argparse.Namespace) -> int:
    check_output("--output", args.output, [args.dataset])
    start = time.perf_counter()
    count, stats = write_camera_nights(args.dataset, args.output, args.seed, args.sequences)
    print(f"wrote {count} day + {count} night sequences (camera night, seed {args.seed}) from {args.dataset} to "
          f"{args.output} in {time.perf_counter() - start:.1f} s; night: {format_statistics(stats)}")
    return 0


def format_library(library: Library) -> str:
    """One row per package and role: images per split and the licence; then the folder and its size."""
    counts = Counter((i.package, i.role, i.split) for r in ROLES for s in SPLITS for i in library.images(r, s))
    rows = [("package", "role", "train", "test", "licence")]
    for package, licence in library.licences().items():
        roles = [r for r in ROLES if counts[package, r, "train"] + counts[package, r, "test"]] or ["-"]
        for role in roles:
            train, test = (str(counts[package, role, s]) for s in ("train", "test"))
            rows.append((package, role, train, test, _short_licence(licence)))
    w = [max(len(r[k]) for r in rows) for k in range(4)]
    lines = [f"{r[0]:<{w[0]}}  {r[1]:<{w[1]}}  {r[2]:>{w[2]}}  {r[3]:>{w[3]}}  {r[4]}" for r in rows]
    size = sum(f.stat().st_size for f in library.root.rglob("*") if f.is_file() and not f.is_symlink())
    lines.append(f"{len(library)} images in {library.root} ({size / 1e6:.0f} MB on disk)")
    return "\n".join(lines)


def _short_licence(licence: str, most: int = 5) -> str:
    """At most five licence names on a row; index.json keeps them all."""
    names = licence.split(", ")
    return licence if len(names) <= most else ", ".join(names[:most]) + f" (+{len(names) - most} more)"


def _pack(cache: Path, args: argparse.Namespace) -> int:
    from ..datamaking.library_pack import pack_library

    library = open_library(cache)
    if library is None:
        raise LibraryError(f"no library in {cache}: run `{PROG} data fetch` first")
    splits = ("train", "test") if args.split == "all" else ("train",)
    counts = pack_library(library, args.output, int(args.max_mib * 2**20), splits)
    size = counts.pop("bytes")
    parts = ", ".join(f"{k} {v}" for k, v in sorted(counts.items()))
    print(f"{PROG}: packed {parts} into {args.output} ({size / 2**20:.1f} MiB); "
          f"use it with DADIFF_DATA_DIR={args.output}")
    return 0


def _check_min_score(args: argparse.Namespace) -> None:
    if not 0 <= args.min_score <= 1:
        raise SceneError(f"--min-score {args.min_score} must be in [0, 1]")


def cmd_detect(args: argparse.Namespace) -> int:
    _check_min_score(args)
    check_output("--output", args.output, [args.video, args.detector])
    detector = Detector(args.detector, threads=args.threads)
    frames = read_video(args.video)
    start = time.perf_counter()
    count = write_det_txt(args.output, detect_video(frames, detector, args.classes, args.min_score, args.tiles))
    print(f"wrote {count} detections of class {','.join(map(str, sorted(args.classes)))} in {len(frames)} frames "
          f"of {args.video} to {args.output} in {time.perf_counter() - start:.1f} s")
    return 0


def cmd_pseudo_label(args: argparse.Namespace) -> int:
    _check_sequence_lengths(args)
    _check_min_score(args)
    settings = LinkSettings(min_frames=args.min_frames, max_frames=args.max_frames, min_score=args.min_score,
                            start_score=max(args.min_score, LinkSettings.start_score), min_height=args.min_height,
                            min_aspect=args.aspect[0], max_aspect=args.aspect[1])
    start = time.perf_counter()
    tracks = write_detection_benchmark(args.video, args.detections, args.output, args.seed, settings, args.night)
    lengths = [len(t.boxes) for t in tracks]
    print(f"wrote {len(tracks)} day + {len(tracks)} night sequences ({sum(lengths)} frames each way, "
          f"{min(lengths)}-{max(lengths)} per sequence) from {args.video} and {args.detections} to {args.output} "
          f"in {time.perf_counter() - start:.1f} s")
    return 0


def cmd_hit_uav(args: argparse.Namespace) -> int:
    data = args.data or default_hit_uav_dir()
    if data is None:
        raise InputError("no --data given and no ../shared/data/hit-uav-night beside this checkout: give the HIT-UAV "
                         "night folder with --data DIR")
    if args.min_frames < 2:
        raise InputError(f"--min-frames {args.min_frames}: a sequence needs at least 2 stills")
    check_output("--output", args.output, [data])
    settings = ChainSettings(max_gap=args.max_gap, min_frames=args.min_frames, max_move=args.max_move)
    start = time.perf_counter()
    chains = write_hit_uav_benchmark(data, args.output, args.split, settings)
    classes = Counter(HIT_CLASSES[c.cls] for c in chains)
    print(f"wrote {plural(len(chains), 'sequence')} ({', '.join(f'{n} {k}' for k, n in classes.items())}; "
          f"{sum(len(c.stills) for c in chains)} frames) from HIT-UAV's {args.split} split in {data} to {args.output} "
          f"in {time.perf_counter() - start:.1f} s (CC BY 4.0: cite HIT-UAV, see benchmark.json)")
    return 0


def cmd_box_read(args: argparse.Namespace) -> int:
    from ..evaluation.box_read import box_read, format_box_read
    from ..tracker import Tracker

    if args.sizes and args.shifts:
        raise EvalError("--sizes and --shifts: give one (a size read is taken at the true centre)")
    tracker = Tracker.load(args.model, threads=args.threads)
    if args.sizes:
        from ..evaluation.size_response import format_size_response, size_response

        dataset = load_dataset(args.dataset).select(args.sequences)
        print(format_size_response(dataset, size_response(tracker, dataset, args.sizes)))
        return 0
    stride = tracker.geometry.stride
    shifts = args.shifts or [stride * k / 4 for k in range(4)]
    crop = tracker.geometry.instance_size
    if any(abs(s) > crop for s in shifts):  # checked before the pass over the frames, naming the option
        raise EvalError(f"--shifts {' '.join(f'{s:g}' for s in shifts)}: at most {crop} crop px either way "
                        f"(this model's search crop)")
    dataset = load_dataset(args.dataset).select(args.sequences)
    print(format_box_read(dataset, box_read(tracker, dataset, shifts)))
    return 0


def cmd_tune(args: argparse.Namespace) -> int:
    from ..evaluation.tune import (
        DEFAULT_GRID,
        best_trial,
        check_trials_out,
        coordinate_search,
        load_sequences,
        parse_grid,
        track_sequences,
        write_trials,
    )
    from ..tracker import Tracker

    grid = parse_grid(args.grid) or DEFAULT_GRID
    if args.output:  # written after minutes of tuning: checked first
        check_output("--output", args.output, args.dataset)
        check_trials_out(args.output)
    first_tracker = Tracker.load(args.model, preset=args.preset, threads=args.threads)  # before minutes of decoding
    sequences = [s for path in args.dataset for s in load_sequences(load_dataset(path).select(args.sequences))]
    backend = first_tracker.backend  # one onnxruntime session for every trial
    start = {k: getattr(first_tracker.params, k) for k in grid}

    def show(trial) -> None:
        values = ", ".join(f"{k}={v:g}" for k, v in trial.values.items())
        print(f"{values}: success {trial.scores.success:.3f}, precision {trial.scores.precision:.3f}", flush=True)

    def evaluate(values: dict[str, float]):
        return track_sequences(RuntimeTracker(Tracker(backend, preset=args.preset, overrides=values)), sequences)

    print(f"tuning {', '.join(grid)} on {len(sequences)} sequences ({sum(len(s.frames) for s in sequences)} frames)")
    trials = coordinate_search(evaluate, start, grid, args.rounds, show)
    if args.output:
        write_trials(args.output, trials)
    best, first = best_trial(trials), trials[0]
    values = ", ".join(f"{k}={v:g}" for k, v in best.values.items())
    print(f"best of {len(trials)} trials: {values}: success {best.scores.success:.3f} "
          f"(start {first.scores.success:.3f})")
    return 0


def cmd_data(args: argparse.Namespace) -> int:
    """`data fetch` and `data list`; library errors exit 2 like other bad input (in `main`)."""
    cache = args.cache or library_root()
    if args.action == "fetch":
        library = fetch(args.packages, cache, args.deb)
    elif args.action == "pack":
        return _pack(cache, args)
    else:
        library = open_library(cache)
        if library is None:
            raise LibraryError(f"no library in {cache}: run `{PROG} data fetch` first")
    print(format_library(library))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of `dadiff-eval`; returns the exit status."""
    args = build_parser().parse_args(argv)
    commands = {"run": cmd_run, "score": cmd_score, "table": cmd_table, "anatomy": cmd_anatomy,
                "box-read": cmd_box_read, "generate": cmd_generate,
                "video": cmd_video, "night": cmd_night, "uncut": cmd_uncut, "uncut-score": cmd_uncut_score,
                "detect": cmd_detect, "pseudo-label": cmd_pseudo_label, "cutouts": cmd_cutouts,
                "hit-uav": cmd_hit_uav,
                "data": cmd_data,
                "tune": cmd_tune}
    try:
        with quiet_opencv():
            return commands[args.command](args)
    except OSError as exc:  # first: an UnreadableFile is a DadiffError too, and reads best as `<file>: <why>`
        print(f"{PROG}: error: {os_error_line(exc)}", file=sys.stderr)
        return 2
    except DadiffError as exc:
        print(f"{PROG}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted; finished sequences are kept, run again to resume", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
