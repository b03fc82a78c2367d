"""int8 static quantisation of a dadiff model (`dadiff-export --quantize int8`).

Only `search.onnx` is quantised: it runs every frame, while `template.onnx` runs once per target and is copied
unchanged (fp32). The search graph goes through onnxruntime's static QDQ quantiser (uint8 activations,
per-channel int8 weights: the u8s8 pairing that AVX-512 VNNI runs fastest), calibrated on the inputs the
runtime tracker really feeds it: search crops and template kernels recorded while the fp32 model tracks
generated night sequences of the *training* photos, or a user's own video. Parts of the graph where int8 is
slower than float or costs accuracy stay in float (`RECIPES`; `DEFAULT_RECIPE` was chosen by measuring them).

Every quantisation is measured before it is written: output deviation from fp32 on held-out crops, night
success of fp32 and int8 on a small generated *test-split* benchmark (dadiff-eval's one-pass evaluation),
and search-graph latency with the runtime's session settings. The numbers are printed and stored in the
int8 graph's metadata (`precision` = `int8`, `quantization` = JSON).
"""

from __future__ import annotations

import fnmatch
import json
import logging
import shutil
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
from onnxruntime.quantization import CalibrationDataReader, CalibrationMethod, QuantFormat, QuantType, quantize_static
from onnxruntime.quantization.shape_inference import quant_pre_process

from dadiff.runtime.backend import RecordingBackend
from dadiff.runtime.cpu import INT8_WARNING, int8_saturates
from dadiff.runtime.datamaking.datasets import Dataset
from dadiff.runtime.datamaking.scenes import make_sequence
from dadiff.runtime.decode import foreground_score, hann_window
from dadiff.runtime.errors import DadiffError, InputError, ModelError
from dadiff.runtime.evaluation.evaluate import generated_night_set, score_tracker
from dadiff.runtime.onnx_backend import OnnxBackend, session_options
from dadiff.runtime.sources import open_source
from dadiff.runtime.tracker import Tracker

from .defaults import (
    DEFAULT_BENCH_RUNS,
    DEFAULT_CALIBRATION_FRAMES,
    DEFAULT_EVAL_FRAMES,
    DEFAULT_EVAL_SEQUENCES,
    DEFAULT_RECIPE,
    MAX_CALIBRATION_FRAMES,
)
from .onnx_export import SEARCH_FILE, TEMPLATE_FILE, ExportError, random_ops, staging_folder

CALIBRATION_SEED = 7  # generated calibration sequences: training photos, seeds 7, 8, ...
CALIBRATION_SEQUENCE_FRAMES = 25  # search crops per generated calibration sequence (many short sequences)
EVAL_SEED = 2026  # the generated benchmark's seed (test photos; docs/evaluation.md)
HELDOUT_CROPS = 200  # search feeds kept, spread evenly, from the fp32 evaluation run: the deviation check
BENCH_THREADS = 2
_CALIBRATION_CHUNK = 10  # crops per calibration pass: bounds what the calibrator holds in memory

Box = tuple[float, float, float, float]
Feed = dict[str, np.ndarray]
Log = Callable[[str], None]


class QuantizeError(DadiffError):
    """Quantisation failed or was asked for something impossible; str() is one line for the user."""


# ------------------------------------------------------------------------------------------------ recipes


@dataclass(frozen=True)
class Recipe:
    """Which nodes of the pre-processed search graph stay in float.

    `rules` are (node-name pattern, op types quantised there) pairs: the first pattern that matches a node
    decides, `()` keeps the whole region in float; nodes no pattern matches are quantised.
    """

    name: str
    rules: tuple[tuple[str, tuple[str, ...]], ...] = ()
    note: str = ""

    def excluded(self, model: onnx.ModelProto) -> list[str]:
        """Names of the nodes this recipe leaves in float."""
        out = []
        for node in model.graph.node:
            for pattern, quantised in self.rules:
                if fnmatch.fnmatchcase(node.name, pattern):
                    if node.op_type not in quantised:
                        out.append(node.name)
                    break
        return out


def _float(*patterns: str) -> tuple[tuple[str, tuple[str, ...]], ...]:
    return tuple((p, ()) for p in patterns)


# Node names of the exported graphs after quant_pre_process (its optimiser names the tracking-oriented
# layer's token reshapes gemm_* and the layout change in front of the head Transpose).
_ATTENTION = _float("/align_track/layer/MatMul_1*", "/align_track/layer/Mul_3", "/align_track/layer/Softmax",
                    "/align_track/layer/MatMul_2*")
_ALIGN = _float("/align_track/*", "gemm_*", "Transpose")
_EARLY = _float("/backbone/_conv_stem/*", "/backbone/_blocks.0/*", "/backbone/_blocks.1/*")
_DENOISER_CONVS = (("/sampler/*", ("Conv",)),)
RECIPES: dict[str, Recipe] = {r.name: r for r in (
    Recipe("all", note="everything onnxruntime can quantise (its int8 softmax is 9x slower than float)"),
    Recipe("no-attention", _ATTENTION, note="attention scores, softmax and weighted sum in float"),
    Recipe("no-attention-xcorr", _ATTENTION + _float("/head/cls/Conv", "/head/loc/Conv"),
           note="also the head's depthwise cross-correlation (its weights are graph inputs) in float"),
    Recipe("no-stem", _float("/backbone/_conv_stem/*") + _ATTENTION, note="first conv and attention in float"),
    Recipe("no-align", _ALIGN, note="the whole tracking-oriented layer in float"),
    Recipe("no-align-denoiser", _ALIGN + _float("/sampler/*"),
           note="tracking-oriented layer and denoiser in float: backbone, neck and head in int8"),
    Recipe("no-align-denoiser-convs", _ALIGN + _DENOISER_CONVS,
           note="tracking-oriented layer in float; of the denoiser only the convs in int8 (GroupNorm, SiLU, "
                "DDIM arithmetic in float)"),
    Recipe("int8-core", _ALIGN + _EARLY + _float("/sampler/*nin_shortcut*") + _DENOISER_CONVS,
           note="no-align-denoiser-convs, with the first conv, backbone blocks 0-1 (where night images lose "
                "most to 8 bits) and the denoiser's 1x1 shortcuts in float"),
    Recipe("int8-core-b2", _float("/backbone/_blocks.2/*") + _ALIGN + _EARLY + _float("/sampler/*nin_shortcut*")
           + _DENOISER_CONVS, note="int8-core with backbone block 2 in float too: closer to fp32, ~0.2 ms slower"),
)}
METHODS = {"minmax": CalibrationMethod.MinMax, "entropy": CalibrationMethod.Entropy,
           "percentile": CalibrationMethod.Percentile}
DEFAULT_METHOD = "minmax"  # entropy and percentile measured no better, at 5-7x the calibration time


# -------------------------------------------------------------------------------------------- recording


def generated_sequences(crops: int, seed: int = CALIBRATION_SEED) -> Iterator[tuple[Iterable[np.ndarray], Box]]:
    """Night sequences of the training photos (never the test split: that is the benchmark), GT init box;
    short ones (`CALIBRATION_SEQUENCE_FRAMES` crops each) for variety, none longer than `crops` needs."""
    k = 0
    while True:
        seq = make_sequence(seed + k, split="train", frames=min(crops, CALIBRATION_SEQUENCE_FRAMES) + 1)
        k += 1
        first = seq.boxes[0]
        if np.all(np.isfinite(first)) and first[2] > 0 and first[3] > 0:
            yield seq.night, (float(first[0]), float(first[1]), float(first[2]), float(first[3]))


def source_sequence(spec: str, init: Box | None) -> Iterator[tuple[Iterable[np.ndarray], Box]]:
    """A user's video or sequence folder as one sequence; init box from `init` or the folder's ground truth."""
    source = open_source(spec)
    try:
        box = init or source.init_box
        if box is None:
            raise QuantizeError(f"--calibration {spec}: no ground truth to start from; give --calibration-init "
                                "x,y,w,h")
        yield (frame.image for frame in source.frames()), box
    finally:
        source.close()


def record_search_inputs(folder: Path, sequences: Iterable[tuple[Iterable[np.ndarray], Box]],
                         limit: int) -> list[Feed]:
    """Track with the fp32 model of `folder` and keep the first `limit` search-graph feeds."""
    recorder = RecordingBackend(OnnxBackend(folder), limit)
    tracker = Tracker(recorder)
    for frames, box in sequences:
        it = iter(frames)
        first = next(it, None)
        if first is None:
            continue
        tracker.init(first, box)
        for frame in it:
            if recorder.full:
                break
            tracker.update(frame)
        if recorder.full:
            break
    return recorder.recorded


class FeedReader(CalibrationDataReader):
    """Calibration reader over recorded feeds; `set_range` lets onnxruntime calibrate chunk by chunk."""

    def __init__(self, feeds: Sequence[Feed]) -> None:
        self.feeds = list(feeds)
        self.set_range(0, len(self.feeds))

    def __len__(self) -> int:
        return len(self.feeds)

    def set_range(self, start_index: int, end_index: int) -> None:
        self._it = iter(self.feeds[start_index:end_index])

    def get_next(self) -> Feed | None:
        return next(self._it, None)


def _chunk(n: int) -> int:
    """Largest divisor of n up to _CALIBRATION_CHUNK (onnxruntime's strided calibration needs one)."""
    return max(d for d in range(1, min(n, _CALIBRATION_CHUNK) + 1) if n % d == 0)


# --------------------------------------------------------------------------------------------- quantise


def quantize_search(fp32_search: Path, out: Path, feeds: Sequence[Feed], recipe: Recipe, method: str,
                    workdir: Path, activations: QuantType = QuantType.QUInt8,
                    weights: QuantType = QuantType.QInt8, reduce_range: bool = False) -> list[str]:
    """Write the int8 search graph to `out`; returns the names of the nodes left in float.

    Pre-processing (symbolic shape inference, constant folding) comes first so that the quantiser sees
    static shapes and no shape arithmetic; int8 was measured 7 % faster with it.
    """
    pre = workdir / "search.pre.onnx"
    quant_pre_process(str(fp32_search), str(pre), skip_symbolic_shape=False)
    excluded = recipe.excluded(onnx.load(str(pre)))
    extra: dict[str, object] = {"CalibStridedMinMax": _chunk(len(feeds))}
    if method == "percentile":
        extra["CalibPercentile"] = 99.999
    quantize_static(
        str(pre), str(out), FeedReader(feeds), quant_format=QuantFormat.QDQ, per_channel=True,
        activation_type=activations, weight_type=weights, calibrate_method=METHODS[method],
        nodes_to_exclude=excluded, extra_options=extra, reduce_range=reduce_range,
    )
    return excluded


def read_metadata(path: Path) -> dict[str, str]:
    """metadata_props of an ONNX file."""
    model = onnx.load(str(path), load_external_data=False)
    return {p.key: p.value for p in model.metadata_props}


def set_metadata(path: Path, meta: Mapping[str, str]) -> None:
    """Replace the metadata of an ONNX file (the quantiser does not promise to keep it)."""
    model = onnx.load(str(path))
    del model.metadata_props[:]
    onnx.helper.set_model_props(model, dict(meta))
    onnx.save(model, str(path))


# ---------------------------------------------------------------------------------------------- measure


def _session(path: Path, threads: int | None = None) -> ort.InferenceSession:
    """A session as the runtime opens one (its options), on the CPU provider."""
    return ort.InferenceSession(str(path), session_options(threads), providers=["CPUExecutionProvider"])


def output_deviation(fp32: Path, int8: Path, feeds: Sequence[Feed], window_influence: float) -> dict[str, float]:
    """int8 against fp32 on the same feeds: max-abs and mean-abs of cls and loc, and how often the decoded
    cell (argmax of the foreground score blended with the cosine window, the tracker's decoding without its
    size penalty) is the same one, or at most one cell away."""
    ref_session, int8_session = _session(fp32), _session(int8)
    worst, total = {"cls": 0.0, "loc": 0.0}, {"cls": 0.0, "loc": 0.0}
    same = near = 0
    for feed in feeds:
        ref = dict(zip(("cls", "loc"), ref_session.run(["cls", "loc"], feed), strict=True))
        got = dict(zip(("cls", "loc"), int8_session.run(["cls", "loc"], feed), strict=True))
        for key in worst:
            diff = np.abs(got[key] - ref[key])
            worst[key] = max(worst[key], float(diff.max()))
            total[key] += float(diff.mean())
        (i0, j0), (i1, j1) = (_decoded_cell(o["cls"], window_influence) for o in (ref, got))
        same += int((i0, j0) == (i1, j1))
        near += int(max(abs(i0 - i1), abs(j0 - j1)) <= 1)
    n = max(1, len(feeds))
    return {"cls_max_abs": worst["cls"], "cls_mean_abs": total["cls"] / n, "loc_max_abs": worst["loc"],
            "loc_mean_abs": total["loc"] / n, "cell_agreement": same / n, "cell_within_one": near / n,
            "crops": len(feeds)}


def _decoded_cell(cls: np.ndarray, window_influence: float) -> tuple[int, int]:
    score = foreground_score(cls)
    blended = score * (1 - window_influence) + hann_window(score.shape[-1]) * window_influence
    i, j = np.unravel_index(int(np.argmax(blended)), blended.shape)
    return int(i), int(j)


def compare_latency(paths: Sequence[Path], feeds: Sequence[Feed], runs: int,
                    threads: int = BENCH_THREADS) -> list[float]:
    """Median search latency (ms) of each graph, runtime session settings, after a warm-up.

    The graphs take turns in rounds of 10 runs, so that load from other processes hits all of them alike.
    """
    sessions = [_session(p, threads) for p in paths]
    for session in sessions:
        for i in range(20):
            session.run(["cls", "loc"], feeds[i % len(feeds)])
    times: list[list[float]] = [[] for _ in sessions]
    for start in range(0, runs, 10):
        for session, spent in zip(sessions, times, strict=True):
            for i in range(start, min(start + 10, runs)):
                begin = time.perf_counter()
                session.run(["cls", "loc"], feeds[i % len(feeds)])
                spent.append(time.perf_counter() - begin)
    return [float(np.median(t)) * 1e3 for t in times]


@dataclass(frozen=True)
class NightSet:
    """A generated benchmark of the test photos on disk (dadiff-eval generate's layout)."""

    root: Path
    dataset: Dataset
    sequences: int
    frames: int
    seed: int = EVAL_SEED

    def describe(self) -> str:
        return f"generated night, test split, {self.sequences} x {self.frames} frames, seed {self.seed}"


def make_night_set(workdir: Path, sequences: int, frames: int, seed: int = EVAL_SEED) -> NightSet:
    """The generated night benchmark of dadiff-eval (test photos), written under `workdir`."""
    root = workdir / "nightbench"
    return NightSet(root, generated_night_set(root, sequences, frames, seed), sequences, frames, seed)


def night_success(folder: Path, bench: NightSet, name: str, record: int = 0) -> tuple[float, list[Feed]]:
    """One-pass night success of a model folder, and (if `record`) that many search feeds spread over the run."""
    backend = OnnxBackend(folder)
    recorder = None
    if record:
        updates = sum(len(s) - 1 for s in bench.dataset.sequences)
        recorder = RecordingBackend(backend, record, every=-(-updates // record))
    scores = score_tracker(Tracker(recorder or backend), bench.dataset, bench.root.parent / "results", name)
    return scores.overall.success, (recorder.recorded if recorder else [])


# ----------------------------------------------------------------------------------------------- driver


@dataclass(frozen=True)
class QuantizeSettings:
    """What `quantize_model` does; the defaults are the shipped choice."""

    calibration: str | None = None  # video file or sequence folder; None = generated night scenes
    init: Box | None = None  # init box for a calibration video without ground truth
    frames: int = DEFAULT_CALIBRATION_FRAMES
    eval_sequences: int = DEFAULT_EVAL_SEQUENCES
    eval_frames: int = DEFAULT_EVAL_FRAMES
    bench_runs: int = DEFAULT_BENCH_RUNS  # 0 skips the latency comparison
    recipe: str = DEFAULT_RECIPE
    method: str = DEFAULT_METHOD
    reduce_range: bool | None = None  # 7-bit weights; None = exactly when this CPU's int8 kernels saturate

    @property
    def use_reduce_range(self) -> bool:
        return int8_saturates() if self.reduce_range is None else self.reduce_range

    def check(self) -> None:
        if self.recipe not in RECIPES:
            raise QuantizeError(f"unknown recipe '{self.recipe}'; expected one of {', '.join(RECIPES)}")
        if self.method not in METHODS:
            raise QuantizeError(f"unknown calibration method '{self.method}'; expected one of {', '.join(METHODS)}")
        for name, value, low in (("calibration frames", self.frames, 1), ("eval sequences", self.eval_sequences, 1),
                                 ("eval frames", self.eval_frames, 2), ("bench runs", self.bench_runs, 0)):
            if value < low:
                raise QuantizeError(f"{name} must be at least {low}, got {value}")
        if self.frames > MAX_CALIBRATION_FRAMES:  # code calling quantize_model directly, not only the command
            raise QuantizeError(f"calibration frames must be at most {MAX_CALIBRATION_FRAMES}, got {self.frames}")


@dataclass
class QuantizeReport:
    """What was done and measured; `metadata()` is what the int8 graph carries."""

    out_dir: Path
    recipe: str
    method: str
    calibration: str
    calibration_frames: int
    float_nodes: int
    reduce_range: bool = False
    deviation: dict[str, float] = field(default_factory=dict)
    success: dict[str, float | str] = field(default_factory=dict)
    latency_ms: dict[str, float | int] = field(default_factory=dict)
    files: dict[str, int] = field(default_factory=dict)
    seconds: float = 0.0

    def metadata(self) -> dict[str, str]:
        record = asdict(self)
        for key in ("out_dir", "files", "seconds"):
            record.pop(key)
        record.update(format="QDQ", activations="uint8 per-tensor", weights="int8 per-channel",
                      onnxruntime=ort.__version__)
        return {"precision": "int8", "quantization": json.dumps(record, sort_keys=True)}


def check_source(folder: Path) -> dict[str, str]:
    """The search metadata of an fp32 model folder; anything else is refused in one line."""
    try:
        backend = OnnxBackend(folder)
    except (ModelError, InputError) as exc:
        raise QuantizeError(str(exc)) from None
    meta = dict(backend.meta)
    if meta.get("precision", "fp32") != "fp32":
        raise QuantizeError(f"{folder}: already quantised (precision {meta['precision']}); give an fp32 model")
    if meta.get("decoder", "siamban") != "siamban":  # its recipes and deviation checks name SiamBAN's head
        raise QuantizeError(f"{folder}: int8 quantisation covers the SiamBAN-head families; this "
                            f"{meta.get('family', meta['decoder'])} model stays fp32")
    return meta


def _staging(out: Path, source: Path) -> Path:
    """A temporary folder next to `out`, after export_model's checks; `out` must not be the source."""
    if out.is_dir() and out.resolve() == source.resolve():
        raise QuantizeError(f"{out}: is the fp32 source folder; write the int8 model to another -o")
    try:
        return staging_folder(out, ".dadiff-quantize-")
    except ExportError as exc:
        raise QuantizeError(str(exc)) from None


def quantize_model(source: str | Path, out: str | Path, settings: QuantizeSettings | None = None,
                   log: Log = print) -> QuantizeReport:
    """Write `out` = the fp32 template graph of `source` + an int8 search graph; nothing is left on failure."""
    settings = settings or QuantizeSettings()
    settings.check()
    source, out = Path(source), Path(out)
    meta = check_source(source)
    staging = _staging(out, source)
    started = time.perf_counter()
    try:
        report = _quantize(source, staging, meta, settings, log)
        out.mkdir(parents=True, exist_ok=True)
        for name in (TEMPLATE_FILE, SEARCH_FILE):
            shutil.move(str(staging / "model" / name), str(out / name))
        report.out_dir, report.seconds = out, time.perf_counter() - started
        return report
    except OSError as exc:
        raise QuantizeError(f"{out}: cannot write the model ({exc.strerror or exc})") from None
    except QuantizeError:
        raise
    except DadiffError as exc:  # a bad calibration source, scene, model: one line under the quantiser's name
        raise QuantizeError(str(exc)) from None
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def _calibration_feeds(source: Path, settings: QuantizeSettings, log: Log) -> tuple[list[Feed], str]:
    if settings.calibration is None:
        what = f"generated night scenes, train split, seeds {CALIBRATION_SEED}+"
        sequences = generated_sequences(settings.frames)
    else:
        what = str(settings.calibration)
        sequences = source_sequence(str(settings.calibration), settings.init)
    start = time.perf_counter()
    feeds = record_search_inputs(source, sequences, settings.frames)
    if not feeds:
        raise QuantizeError(f"--calibration {settings.calibration}: gave no search crop (it needs 2 frames or more)")
    log(f"  calibration: {len(feeds)} search crops from {what} ({time.perf_counter() - start:.1f} s)")
    return feeds, what


def _quantize(source: Path, staging: Path, meta: dict[str, str], settings: QuantizeSettings,
              log: Log) -> QuantizeReport:
    feeds, what = _calibration_feeds(source, settings, log)
    model = staging / "model"
    model.mkdir()
    shutil.copyfile(source / TEMPLATE_FILE, model / TEMPLATE_FILE)
    recipe = RECIPES[settings.recipe]
    start = time.perf_counter()
    reduce = settings.use_reduce_range
    if int8_saturates():
        log(f"  warning: {INT8_WARNING}; reduce_range {'on' if reduce else 'off (--no-reduce-range)'}")
    with _quiet_quantizer():
        excluded = quantize_search(source / SEARCH_FILE, model / SEARCH_FILE, feeds, recipe, settings.method,
                                   staging, reduce_range=reduce)
    report = QuantizeReport(Path(), recipe.name, settings.method, what, len(feeds), len(excluded), reduce)
    del feeds
    found = random_ops(model / SEARCH_FILE)
    if found:
        raise QuantizeError(f"the int8 search graph contains random ops ({', '.join(found)}); refusing to ship")
    meta = meta | {"name": f"{meta.get('name', source.name)}-int8"}
    set_metadata(model / SEARCH_FILE, meta | report.metadata())  # the runtime loads it for the checks below
    log(f"  quantised search.onnx: recipe {recipe.name} ({len(excluded)} nodes kept in float), "
        f"{settings.method} calibration ({time.perf_counter() - start:.1f} s)")
    _measure(source, model, staging, report, meta, settings, log)
    set_metadata(model / SEARCH_FILE, meta | report.metadata())
    report.files = {f: (model / f).stat().st_size for f in (TEMPLATE_FILE, SEARCH_FILE)}
    return report


def _measure(source: Path, model: Path, staging: Path, report: QuantizeReport, meta: Mapping[str, str],
             settings: QuantizeSettings, log: Log) -> None:
    start = time.perf_counter()
    bench = make_night_set(staging, settings.eval_sequences, settings.eval_frames)
    fp32_success, heldout = night_success(source, bench, "fp32", record=HELDOUT_CROPS)
    int8_success, _ = night_success(model, bench, "int8")
    report.success = {"fp32": fp32_success, "int8": int8_success, "set": bench.describe()}
    report.deviation = output_deviation(source / SEARCH_FILE, model / SEARCH_FILE, heldout,
                                        float(meta.get("window_influence", 0.0)))
    log(f"  evaluated on {bench.describe()} ({time.perf_counter() - start:.1f} s)")
    if settings.bench_runs:
        fp32_ms, int8_ms = compare_latency([source / SEARCH_FILE, model / SEARCH_FILE], heldout, settings.bench_runs)
        report.latency_ms = {"fp32": fp32_ms, "int8": int8_ms, "runs": settings.bench_runs, "threads": BENCH_THREADS}


@contextmanager
def _quiet_quantizer() -> Iterator[None]:
    """Silence onnxruntime.quantization's advice and progress logging (it logs on the root logger) while it
    runs; real failures still raise."""
    level = logging.root.level
    logging.root.setLevel(logging.ERROR)
    try:
        yield
    finally:
        logging.root.setLevel(level)
