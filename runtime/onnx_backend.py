"""onnxruntime implementation of the backend protocol for a dadiff model folder.

Session settings follow what was measured on small CPUs: ORT_ENABLE_ALL (its layout pass roughly halves
conv time), and no spinning intra-op threads, since the template and search sessions share the cores.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import onnxruntime as ort

from .config import REQUIRED_KEYS, TUNABLE_KEYS, check_metadata, parse_geometry
from .errors import InputError, ModelError

# Tried in this order when present; the CPU provider always ends the list as the fallback.
PREFERRED_PROVIDERS = ("TensorrtExecutionProvider", "CUDAExecutionProvider", "OpenVINOExecutionProvider")
CPU = "CPUExecutionProvider"
_ALIASES = {"trt": "TensorrtExecutionProvider"}


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


def session_options(threads: int | None = None) -> ort.SessionOptions:
    """Options shared by both sessions; `threads` defaults to os.cpu_count()."""
    if threads is None:
        threads = os.cpu_count() or 1
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
        raise InputError(f"threads must be a positive integer, got {threads!r}")
    options = ort.SessionOptions()
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    options.add_session_config_entry("session.inter_op.allow_spinning", "0")
    options.log_severity_level = 3
    return options


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    line = text[0] if text else type(exc).__name__
    return line if len(line) <= 200 else line[:197] + "..."


def _open(path: Path, options: ort.SessionOptions, providers: list[str]) -> ort.InferenceSession:
    if not path.is_file():
        raise ModelError(f"{path}: file not found (a model folder holds template.onnx and search.onnx)")
    try:
        return ort.InferenceSession(str(path), sess_options=options, providers=providers)
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
    """Runs `template.onnx` once per init and `search.onnx` every frame; feeds the search graph by name."""

    def __init__(
        self, folder: str | Path, *, provider: str | None = None, threads: int | None = None
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
        options = session_options(threads)
        self._template = _open(self.template_path, options, providers)
        self._search = _open(self.search_path, options, providers)
        if provider is not None and providers[0] not in self._search.get_providers():
            raise InputError(f"provider '{provider}' could not be started (onnxruntime fell back to CPU)")
        self._meta = self._read_metadata()
        self._check_io()

    @property
    def meta(self) -> Mapping[str, str]:
        return self._meta

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
        for key in (*REQUIRED_KEYS, *TUNABLE_KEYS, "hp_presets", "channel_order"):
            if metas["template"].get(key) != metas["search"].get(key):
                raise ModelError(
                    f"{self.folder}: template.onnx and search.onnx disagree on metadata key '{key}'"
                )
        return metas["search"]

    def _check_io(self) -> None:
        geo = parse_geometry(self._meta, str(self.search_path))
        t_inputs = self._template.get_inputs()
        if len(t_inputs) != 1:
            names = [a.name for a in t_inputs]
            raise ModelError(f"{self.template_path}: expected one image input, found {names}")
        self._z_name = t_inputs[0].name
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
        for name, channels in (("cls", 2), ("loc", 4)):
            if name not in outputs:
                raise ModelError(f"{self.search_path}: output '{name}' is missing")
            _check_shape(self.search_path, outputs[name], (1, channels, s, s), "metadata score_size")

    def template(self, z: np.ndarray) -> dict[str, np.ndarray]:
        """All template-graph outputs by name (head kernels and diagnostic features)."""
        values = self._template.run(None, {self._z_name: z})
        return dict(zip(self._template_outputs, values, strict=True))

    def search(self, x: np.ndarray, feeds: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """(cls, loc) for one search crop, with the kernels taken from `feeds` by input name."""
        inputs = {self._x_name: x}
        for name in self._feed_names:
            inputs[name] = feeds[name]
        cls, loc = self._search.run(["cls", "loc"], inputs)
        return cls, loc
