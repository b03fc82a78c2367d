"""onnxruntime implementation of the backend protocol for a dadiff model folder.

Session settings follow what was measured on small CPUs: ORT_ENABLE_ALL (its layout pass roughly halves
conv time) and one intra-op thread per physical core. The pool threads spin between the kernels of one call
(a search call is some 300 small kernels, and waking a sleeping thread for each costs 10–13 % of the call
on a 2-core AVX2 CPU) and stop spinning when the call returns, so that an idle tracker burns no CPU
and the template and search sessions do not spin against each other. The optimised graph is cached on disk
per CPU (runtime/ort_cache.py), and the per-frame call goes through an IO binding whose kernels are bound
once per target: each frame only writes the search crop into a buffer the session already knows.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import onnxruntime as ort

from .config import REQUIRED_KEYS, TUNABLE_KEYS, check_metadata, parse_geometry
from .errors import InputError, ModelError
from .ort_cache import cached_model_path, store_atomically

# Tried in this order when present; the CPU provider always ends the list as the fallback.
PREFERRED_PROVIDERS = ("TensorrtExecutionProvider", "CUDAExecutionProvider", "OpenVINOExecutionProvider")
CPU = "CPUExecutionProvider"
_ALIASES = {"trt": "TensorrtExecutionProvider"}
ROI = "roi"  # the template graph's optional second input (docs/model-format.md)


def choose_providers(provider: str | None = None) -> list[str]:
    """Execution providers for a session: the best available ones, or exactly the one asked for.

    `provider` may be a full name (CUDAExecutionProvider) or a short one (cuda, tensorrt, trt, openvino, cpu).
    """
    available = ort.get_available_providers()
    if provider is None:
        return [p for p in PREFERRED_PROVIDERS if p in available] + [CPU]
    wanted = _ALIASES.get(provider.lower(), provider).lower()
    for name in available:
        if wanted in (name.lower(), name.lower().removesuffix("executionprovider")):
            return [name]
    raise InputError(f"provider '{provider}' is not available here (available: {', '.join(available)})")


def physical_cores() -> int:
    """Physical cores this process may run on (SMT siblings counted once): ORT's best intra-op thread count."""
    cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else range(os.cpu_count() or 1)
    cores = set()
    for cpu in cpus:
        topology = Path(f"/sys/devices/system/cpu/cpu{cpu}/topology")
        try:
            cores.add(((topology / "physical_package_id").read_text(), (topology / "core_id").read_text()))
        except OSError:
            cores.add(("cpu", str(cpu)))
    return max(1, len(cores))


THREADS_PER_CORE = 4  # more only queue behind each other


def thread_count(threads: int | None = None) -> int:
    """`threads` checked, or the physical core count when None."""
    if threads is None:
        return physical_cores()
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
        raise InputError(f"threads must be a positive integer, got {threads!r}")
    most = THREADS_PER_CORE * (os.cpu_count() or 1)
    if threads > most:  # far more threads than cores hang the process or take all memory
        raise InputError(f"threads is {threads}; at most {most} on this machine ({THREADS_PER_CORE} per logical core)")
    return threads


def session_options(threads: int | None = None, optimise: bool = True) -> ort.SessionOptions:
    """Options shared by both sessions; `threads` defaults to the physical core count.

    `optimise=False` is for graphs that onnxruntime already optimised (the on-disk cache).
    """
    threads = thread_count(threads)
    options = ort.SessionOptions()
    options.graph_optimization_level = (
        ort.GraphOptimizationLevel.ORT_ENABLE_ALL if optimise else ort.GraphOptimizationLevel.ORT_DISABLE_ALL
    )
    options.enable_mem_pattern = True
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.add_session_config_entry("session.intra_op.allow_spinning", "1")
    options.add_session_config_entry("session.force_spinning_stop", "1")
    options.add_session_config_entry("session.inter_op.allow_spinning", "0")
    options.log_severity_level = 3
    return options


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    line = text[0] if text else type(exc).__name__
    return line if len(line) <= 200 else line[:197] + "..."


def _open(path: Path, threads: int, providers: list[str], cache: bool) -> ort.InferenceSession:
    """A session for `path`, from the per-CPU cache of optimised graphs when there is one (CPU only)."""
    if not path.is_file():
        raise ModelError(f"{path}: file not found (a model folder holds template.onnx and search.onnx)")
    cached = cached_model_path(path, ort.__version__) if cache and providers == [CPU] else None
    if cached is not None and cached.is_file():
        try:
            return ort.InferenceSession(str(cached), session_options(threads, optimise=False), providers=providers)
        except Exception:  # a damaged cache entry: rebuild it from the model
            cached.unlink(missing_ok=True)
    if cached is not None:
        session = None
        try:
            with store_atomically(cached) as staging:
                options = session_options(threads)
                options.optimized_model_filepath = str(staging)
                session = ort.InferenceSession(str(path), sess_options=options, providers=providers)
        except Exception:  # the cache could not be written (a full disk): the session stands without it
            pass
        if session is not None:  # optimised once: a cache that failed after it costs no second optimisation
            return session
    try:
        return ort.InferenceSession(str(path), sess_options=session_options(threads), providers=providers)
    except Exception as exc:  # onnxruntime raises several unrelated types for unreadable models
        raise ModelError(f"{path}: not a loadable ONNX model ({_first_line(exc)})") from None


def _static_shape(arg: ort.NodeArg) -> tuple[int | None, ...]:
    return tuple(d if isinstance(d, int) else None for d in arg.shape)


def _check_shape(path: Path, arg: ort.NodeArg, expected: Sequence[int], what: str) -> None:
    shape = _static_shape(arg)
    ok = len(shape) == len(expected) and all(
        s is None or s == e for s, e in zip(shape, expected, strict=True)
    )
    if not ok:
        raise ModelError(
            f"{path}: {arg.name} has shape {list(arg.shape)}, expected {list(expected)} ({what})"
        )


class OnnxBackend:
    """Runs `template.onnx` once per init and `search.onnx` every frame; feeds the search graph by name.

    `cache=False` skips the on-disk cache of optimised graphs (DADIFF_CACHE_DIR=off does the same).
    """

    def __init__(
        self,
        folder: str | Path,
        *,
        provider: str | None = None,
        threads: int | None = None,
        cache: bool = True,
    ) -> None:
        folder = Path(folder)
        if folder.suffix.lower() == ".onnx" and not folder.is_dir():
            folder = folder.parent
        if not folder.is_dir():
            raise ModelError(f"{folder}: model folder not found")
        self.folder = folder
        self.name = str(folder)
        self.template_path = folder / "template.onnx"
        self.search_path = folder / "search.onnx"
        providers = choose_providers(provider)
        threads = thread_count(threads)  # checked, and the cores counted, once for both sessions
        self._template = _open(self.template_path, threads, providers, cache)
        self._search = _open(self.search_path, threads, providers, cache)
        if provider is not None and providers[0] not in self._search.get_providers():
            raise InputError(f"provider '{provider}' could not be started (onnxruntime fell back to CPU)")
        self._meta = self._read_metadata()
        self._check_io()
        self._binding: ort.IOBinding | None = None
        self._bound: dict[str, np.ndarray] | None = None

    @property
    def meta(self) -> Mapping[str, str]:
        return self._meta

    @property
    def search_inputs(self) -> list[str]:
        """Input names of the search graph: the image first, then the template kernels."""
        return [self._x_name, *self._feed_names]

    @property
    def providers(self) -> list[str]:
        """Providers the search session actually runs on."""
        return list(self._search.get_providers())

    def _read_metadata(self) -> dict[str, str]:
        metas = {}
        for path, session, graph in (
            (self.template_path, self._template, "template"),
            (self.search_path, self._search, "search"),
        ):
            meta = dict(session.get_modelmeta().custom_metadata_map)
            check_metadata(meta, str(path))
            if meta.get("graph", graph) != graph:
                raise ModelError(f"{path}: metadata key 'graph' is {meta['graph']!r}, expected '{graph}'")
            metas[graph] = meta
        for key in (*REQUIRED_KEYS, *TUNABLE_KEYS, "hp_presets", "channel_order", "decoder"):
            if metas["template"].get(key) != metas["search"].get(key):
                raise ModelError(
                    f"{self.folder}: template.onnx and search.onnx disagree on metadata key '{key}'"
                )
        return metas["search"]

    def _check_io(self) -> None:
        geo = parse_geometry(self._meta, str(self.search_path))
        t_inputs = [a for a in self._template.get_inputs() if a.name != ROI]
        if len(t_inputs) != 1:
            names = [a.name for a in self._template.get_inputs()]
            raise ModelError(f"{self.template_path}: expected one image input (and optionally '{ROI}'), found {names}")
        self._z_name = t_inputs[0].name
        roi = [a for a in self._template.get_inputs() if a.name == ROI]
        self.takes_roi = bool(roi)
        if roi:
            _check_shape(self.template_path, roi[0], (1, 4), "the target's box in template-crop pixels")
        _check_shape(
            self.template_path,
            t_inputs[0],
            (1, 3, geo.exemplar_size, geo.exemplar_size),
            "metadata exemplar_size",
        )
        self._template_outputs = [a.name for a in self._template.get_outputs()]
        images = [a for a in self._search.get_inputs() if a.name not in self._template_outputs]
        if len(images) != 1:
            names = [a.name for a in images]
            raise ModelError(
                f"{self.search_path}: inputs {names} are not template.onnx outputs; "
                "expected exactly one image input"
            )
        self._x_name = images[0].name
        _check_shape(
            self.search_path,
            images[0],
            (1, 3, geo.instance_size, geo.instance_size),
            "metadata instance_size",
        )
        self._feed_names = [a.name for a in self._search.get_inputs() if a.name != self._x_name]
        outputs = {a.name: a for a in self._search.get_outputs()}
        s = geo.score_size
        channels = {"cls": 2, "loc": 4} | ({"cen": 1} if geo.decoder == "siamgat" else {})
        for name, count in channels.items():
            if name not in outputs:
                raise ModelError(f"{self.search_path}: output '{name}' is missing")
            _check_shape(self.search_path, outputs[name], (1, count, s, s), "metadata score_size")
        # Buffers the IO binding points at: the tracker crops straight into `input_buffer`.
        self.input_buffer = np.zeros((1, 3, geo.instance_size, geo.instance_size), np.float32)
        self._outputs = {name: np.zeros((1, count, s, s), np.float32) for name, count in channels.items()}

    def template(self, z: np.ndarray, roi: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """All template-graph outputs by name (head kernels and diagnostic features). `roi`: the target's box
        (1, 4) in template-crop pixels, for a model whose template graph takes it (DaDiff-GAT); ignored otherwise."""
        feeds = {self._z_name: z}
        if self.takes_roi:
            if roi is None:
                raise InputError(f"{self.template_path}: this model's template graph takes the target's ROI; "
                                 "pass roi=(1, 4) x1, y1, x2, y2 in template-crop pixels")
            feeds[ROI] = np.asarray(roi, np.float32).reshape(1, 4)
        values = self._template.run(None, feeds)
        feeds = dict(zip(self._template_outputs, values, strict=True))
        self._bind(feeds)
        return feeds

    def _bind(self, feeds: dict[str, np.ndarray]) -> None:
        """Bind one target's kernels, the input buffer and the output buffers to the search session."""
        binding = self._search.io_binding()
        kept = {name: np.ascontiguousarray(feeds[name], dtype=np.float32) for name in self._feed_names}
        for name, value in kept.items():
            binding.bind_cpu_input(name, value)
        binding.bind_cpu_input(self._x_name, self.input_buffer)
        for name, buffer in self._outputs.items():
            binding.bind_output(name, "cpu", 0, np.float32, list(buffer.shape), buffer.ctypes.data)
        self._binding, self._bound, self._kept = binding, feeds, kept

    def search(self, x: np.ndarray, feeds: dict[str, np.ndarray]) -> tuple[np.ndarray, ...]:
        """(cls, loc) for one search crop, with the kernels taken from `feeds` by input name; (cls, loc, cen)
        for a SiamGAT model.

        One bound session call; `x` is copied only when it is not `input_buffer` itself, and the kernels
        are bound again only when `feeds` is not the dict the last `template` call returned.
        """
        if self._binding is None or feeds is not self._bound:
            self._bind(feeds)
        if x is not self.input_buffer:
            np.copyto(self.input_buffer, x)
        self._search.run_with_iobinding(self._binding)
        return tuple(buffer.copy() for buffer in self._outputs.values())
