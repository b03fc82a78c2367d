"""Export a loaded checkpoint to the dadiff model format (docs/model-format.md) and prove parity.

Two static-shape graphs, template and search, each carrying every tracker setting as ONNX metadata. The
DDIM sampler is unrolled with its timesteps baked in, so the time embeddings fold into constants and the
graphs hold no random ops. Parity against PyTorch is measured on every export; above the tolerance the
export fails and leaves no files behind.
"""

from __future__ import annotations

import copy
import json
import math
import shutil
import tempfile
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch
from torch import nn
from torch.utils.flop_counter import FlopCounterMode

from dadiff.runtime.errors import DadiffError

from .checkpoint import LoadedCheckpoint
from .config import GAT_BACKBONE, GAT_FAMILY, is_lite0, tracker_metadata
from .defaults import DEFAULT_OPSET, PARITY_TOLERANCE, SUPPORTED_OPSETS
from .network import DaDiffNet

TEMPLATE_FILE, SEARCH_FILE = "template.onnx", "search.onnx"


class ExportError(DadiffError):
    """Export failed; str() is one line for the user."""


def dadiff_version() -> str:
    try:
        return version("dadiff")
    except PackageNotFoundError:
        return "0+unknown"


class TemplateGraph(nn.Module):
    """z (and, for DaDiff-GAT, the target's ROI) -> the template graph's outputs in `GraphLayout` order."""

    def __init__(self, net: DaDiffNet) -> None:
        super().__init__()
        self.net = net
        self.layout = GraphLayout.of(net)
        self.eval()  # a fresh wrapper is in training mode, and export restores that mode on `net` too

    def forward(self, z: torch.Tensor, *roi: torch.Tensor) -> tuple[torch.Tensor, ...]:
        if self.layout.roi:
            return (self.net.template(z, *roi),)
        zf, kcls, kloc = self.net.template_kernels(z)
        return (*zf, *kcls, *kloc)


@dataclass(frozen=True)
class GraphLayout:
    """The one place the tensors between the two graphs are ordered: the template graph returns zf*, kcls*,
    kloc* (one per level); the search graph takes x, then kcls*, kloc*, and zf* for a model whose layer
    attends to the template. DaDiff-GAT (`roi`): the template graph takes z and roi and returns zf0 only,
    the search graph takes x and zf0 and returns cls, loc and cen. The names go into the metadata, which the
    runtime feeds by."""

    levels: int
    reads_template: bool = False
    roi: bool = False

    @classmethod
    def of(cls, net: DaDiffNet) -> GraphLayout:
        return cls(len(net.cfg.level_names), net.reads_template(), net.cfg.family == GAT_FAMILY)

    def template_inputs(self) -> list[str]:
        return ["z", "roi"] if self.roi else ["z"]

    def template_outputs(self) -> list[str]:
        return self._features() + self._kernels()

    def search_outputs(self) -> list[str]:
        return ["cls", "loc", "cen"] if self.roi else ["cls", "loc"]

    def search_inputs(self) -> list[str]:
        """The search graph's inputs after x."""
        return self._kernels() + (self._features() if self.reads_template else [])

    def search_args(self, template_values: Sequence[torch.Tensor]) -> list[torch.Tensor]:
        """The template graph's outputs, reordered as the search graph's inputs after x."""
        n = self.levels
        return [*template_values[n:], *(template_values[:n] if self.reads_template else [])]

    def split_search_args(self, args: Sequence[torch.Tensor]
                          ) -> tuple[list[torch.Tensor], list[torch.Tensor], list[torch.Tensor] | None]:
        """(kcls, kloc, zf or None) from the search graph's inputs after x."""
        n, k = self.levels, len(self._kernels()) // 2
        return list(args[:k]), list(args[k:2 * k]), list(args[2 * k:2 * k + n]) if self.reads_template else None

    def _features(self) -> list[str]:
        return [f"zf{i}" for i in range(self.levels)]

    def _kernels(self) -> list[str]:
        if self.roi:  # the graph attention reads the template's features themselves
            return []
        return [f"kcls{i}" for i in range(self.levels)] + [f"kloc{i}" for i in range(self.levels)]


class SearchGraph(nn.Module):
    """x, then the template graph's outputs the search side reads, in `GraphLayout` order."""

    def __init__(self, net: DaDiffNet) -> None:
        super().__init__()
        self.net = net
        self.layout = GraphLayout.of(net)
        self.eval()

    def forward(self, x: torch.Tensor, *kernels: torch.Tensor) -> tuple[torch.Tensor, ...]:
        kcls, kloc, zf = self.layout.split_search_args(kernels)
        if self.layout.roi:
            return self.net.track(x, zf[0])
        return self.net.track(x, kcls, kloc)


def model_metadata(loaded: LoadedCheckpoint, name: str, opset: int) -> dict[str, str]:
    cfg, tr = loaded.config, loaded.config.tracker
    layout = GraphLayout.of(loaded.model)
    mean = _module_constant(cfg.backbone, "PIXEL_MEAN", [0.0] * 3)
    std = _module_constant(cfg.backbone, "PIXEL_STD", [1.0] * 3)
    sampler = loaded.model.sampler
    meta = tracker_metadata(tr) | {
        "name": name, "family": cfg.family, "dadiff_version": dadiff_version(),
        "source_sha256": loaded.sha256, "source_format": loaded.source, "opset": str(opset),
        "levels": str(len(cfg.level_names)), "channel_order": "BGR", "pixel_range": "0-255",
        "pixel_mean": json.dumps([float(v) for v in mean]),
        "pixel_std": json.dumps([float(v) for v in std]), "ddim_steps": str(cfg.ddim_steps),
        "ddim_timesteps": json.dumps(sampler.timesteps), "ddim_start_t": str(sampler.start_t),
        "template_inputs": json.dumps(layout.template_inputs()),
        "template_outputs": json.dumps(layout.template_outputs()),
        "search_inputs": json.dumps(["x", *layout.search_inputs()]),
        "search_outputs": json.dumps(layout.search_outputs()),
    }
    return meta


def _module_constant(backbone: str, name: str, default: list[float]) -> list[float]:
    """The in-graph pixel normalisation of a backbone (the released ResNet takes raw pixels)."""
    if backbone == GAT_BACKBONE:  # (v - 127.5) / 127.5 after reordering to RGB (export/inception.py)
        return [127.5] * 3
    if is_lite0(backbone):
        from . import efficientnet_lite

        return list(getattr(efficientnet_lite, name))
    return default


@dataclass
class ExportReport:
    out_dir: Path
    files: dict[str, int]                  # file name -> bytes
    gflop_search: float
    gflop_template: float
    parity: dict[str, float] = field(default_factory=dict)      # output -> scaled error (see parity_error)
    parity_abs: dict[str, float] = field(default_factory=dict)  # output -> plain max-abs difference
    seconds: float = 0.0

    @property
    def max_parity(self) -> float:
        return max(self.parity.values())


def count_gflop(module: nn.Module, *args: torch.Tensor) -> float:
    """GFLOP (2 x multiply-accumulates) of one call, from torch's FLOP counter."""
    trainable = [p for p in module.parameters() if p.requires_grad]
    for p in trainable:  # the counter's module tracker trips over grad-requiring views made under no_grad
        p.requires_grad_(False)
    try:
        counter = FlopCounterMode(display=False)
        with counter, torch.no_grad():
            module(*args)
        return counter.get_total_flops() / 1e9
    finally:
        for p in trainable:
            p.requires_grad_(True)


def parity_inputs(cfg) -> tuple[torch.Tensor, torch.Tensor]:
    """Fixed pseudo-random pixel crops: deterministic, in the 0..255 range the graphs take."""
    g = np.random.default_rng(0)
    e, i = cfg.tracker.exemplar_size, cfg.tracker.instance_size
    z = g.integers(0, 256, size=(1, 3, e, e)).astype(np.float32)
    x = g.integers(0, 256, size=(1, 3, i, i)).astype(np.float32)
    return torch.from_numpy(z), torch.from_numpy(x)


PARITY_TARGET = (40.0, 30.0)  # frame pixels: the DaDiff-GAT fixture's target, its ROI masks 63 of 169 cells


def template_args(net: DaDiffNet, z: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """The template graph's inputs for crop z: (z,) or, for DaDiff-GAT, (z, roi) of a 40 x 30 target as the
    tracker builds it (runtime/decode_gat.py)."""
    if not GraphLayout.of(net).roi:
        return (z,)
    from dadiff.runtime.crop import context_side, crop_side
    from dadiff.runtime.decode_gat import template_roi

    w, h = PARITY_TARGET
    tr = net.cfg.tracker
    side = crop_side(context_side(w, h, tr.context_amount))  # the window the tracker cuts (Tracker.init)
    return z, torch.from_numpy(template_roi(w, h, side, tr.exemplar_size))


def _export_graph(module: nn.Module, args: tuple, path: Path, inputs: list[str], outputs: list[str],
                  opset: int, meta: dict[str, str]) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", torch.jit.TracerWarning)  # shape branches frozen on purpose (static shapes)
        torch.onnx.export(module, args, str(path), dynamo=False, opset_version=opset, input_names=inputs,
                          output_names=outputs, do_constant_folding=True)
    model = onnx.load(str(path))
    onnx.helper.set_model_props(model, meta)
    model.producer_name, model.producer_version = "dadiff-export", meta["dadiff_version"]
    onnx.save(model, str(path))


def random_ops(path: Path) -> list[str]:
    model = onnx.load(str(path), load_external_data=False)
    return sorted({n.op_type for n in model.graph.node if n.op_type.startswith("Random")})


def ort_session(path: Path) -> ort.InferenceSession:
    opts = ort.SessionOptions()
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])


def parity_error(ours: np.ndarray, ref: np.ndarray) -> tuple[float, float]:
    """(max-abs difference, the same divided by max(1, max |ref|)).

    The gate uses the second: plain max-abs where outputs are of order 1 (cls logits, the fixture's loc), and
    relative where they are large, as a trained model's `loc` is (box distances of tens of pixels that come
    out of exp(): float32 kernels that differ in summation order put ~1e-5 relative there, ~5e-4 absolute).
    NaN or inf on either side is (inf, inf): NaN compares false with any tolerance and would pass the gate.
    """
    if not (np.isfinite(ours).all() and np.isfinite(ref).all()):
        return math.inf, math.inf
    diff = float(np.abs(ours - ref).max())
    return diff, diff / max(1.0, float(np.abs(ref).max()))


def check_parity(net: DaDiffNet, folder: Path) -> dict[str, tuple[float, float]]:
    """Per output (max-abs, scaled) difference between PyTorch and onnxruntime on the same inputs."""
    z, x = parity_inputs(net.cfg)
    args = template_args(net, z)
    with torch.no_grad():
        t_out = TemplateGraph(net)(*args)
    tmpl = ort_session(folder / TEMPLATE_FILE)
    names = [o.name for o in tmpl.get_outputs()]
    o_out = tmpl.run(None, {i.name: a.numpy() for i, a in zip(tmpl.get_inputs(), args, strict=True)})
    parity = {n: parity_error(a, b.numpy()) for n, a, b in zip(names, o_out, t_out, strict=True)}
    search = ort_session(folder / SEARCH_FILE)
    outputs = dict(zip(names, o_out, strict=True))
    feeds = {"x": x.numpy()} | {i.name: outputs[i.name] for i in search.get_inputs()[1:]}
    kernels = [torch.from_numpy(feeds[i.name]) for i in search.get_inputs()[1:]]
    with torch.no_grad():
        t_maps = SearchGraph(net)(x, *kernels)
    outputs = GraphLayout.of(net).search_outputs()
    for name, ours, ref in zip(outputs, search.run(outputs, feeds), t_maps, strict=True):
        parity[name] = parity_error(ours, ref.numpy())
    return parity


def staging_folder(out: Path, prefix: str) -> Path:
    """A temporary folder next to the model folder `out`, to be moved into place only when all went well.

    `out` may be missing, empty or an earlier model folder (overwritten); anything else is refused.
    """
    if out.exists() and not out.is_dir():
        raise ExportError(f"{out}: exists and is not a folder")
    if out.exists() and any(out.iterdir()) and not (out / SEARCH_FILE).exists():
        raise ExportError(f"{out}: folder is not empty and holds no dadiff model; choose another -o")
    parent = out.parent if out.parent != Path("") else Path(".")
    try:
        parent.mkdir(parents=True, exist_ok=True)
        return Path(tempfile.mkdtemp(prefix=prefix, dir=parent))
    except OSError as e:
        raise ExportError(f"{parent}: cannot write the output there ({e.strerror or e})") from None


def _check_runtime_loads(folder: Path) -> None:
    """Open the written graphs as the runtime does (metadata, inputs, output shapes): a model it refuses
    is never shipped, whatever the parity."""
    from dadiff.runtime.errors import InputError, ModelError
    from dadiff.runtime.onnx_backend import OnnxBackend

    try:
        OnnxBackend(folder, provider="cpu", threads=1, cache=False)
    except (ModelError, InputError) as e:
        raise ExportError(f"the runtime refuses the exported model ({e}); no files written") from None


def _probe_geometry(net: DaDiffNet, z: torch.Tensor, x: torch.Tensor) -> list[torch.Tensor]:
    """Run both graphs once on the stored crop sizes; the search graph's inputs after x.

    A stored exemplar_size / instance_size the network's stored start noise does not fit fails here with a
    tensor-size error deep in the denoiser: one line naming the keys instead.
    """
    cfg, tr = net.cfg, net.cfg.tracker
    try:
        with torch.no_grad():
            kernels = GraphLayout.of(net).search_args(TemplateGraph(net)(*template_args(net, z)))
            SearchGraph(net)(x, *kernels)
    except RuntimeError as e:
        reason = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise ExportError(f"the network does not run on its stored crop sizes (tracker.exemplar_size "
                          f"{tr.exemplar_size}, tracker.instance_size {tr.instance_size}; template_feature_size "
                          f"{cfg.template_feature_size}, search_feature_size {cfg.search_feature_size}): {reason}"
                          ) from None
    return kernels


def folded_for_export(net: DaDiffNet) -> DaDiffNet:
    """A copy of `net` with the backbone's input normalisation folded into its first conv, where it can be.

    The parity check compares the graphs written from this copy against `net` itself, so a fold that
    changed the results beyond the tolerance would stop the export.
    """
    if not hasattr(net.backbone, "fold_normalisation"):
        return net
    folded = copy.deepcopy(net).eval()
    folded.backbone.fold_normalisation()
    return folded


def export_model(loaded: LoadedCheckpoint, out_dir: str | Path, name: str, opset: int = DEFAULT_OPSET,
                 tolerance: float = PARITY_TOLERANCE) -> ExportReport:
    """Write out_dir/template.onnx and out_dir/search.onnx; nothing is left behind on failure."""
    if opset not in SUPPORTED_OPSETS:
        raise ExportError(f"unsupported opset {opset}; use {SUPPORTED_OPSETS.start}..{SUPPORTED_OPSETS.stop - 1}")
    out = Path(out_dir)
    staging = staging_folder(out, ".dadiff-export-")
    start = time.perf_counter()
    net = loaded.model.eval()
    graphs_net = folded_for_export(net)
    try:
        meta = model_metadata(loaded, name, opset)
        layout = GraphLayout.of(net)
        z, x = parity_inputs(loaded.config)
        kernels = _probe_geometry(net, z, x)
        gflop_search = count_gflop(SearchGraph(net), x, *kernels)
        gflop_template = count_gflop(TemplateGraph(net), *template_args(net, z))
        meta |= {"gflop_search": f"{gflop_search:.4f}", "gflop_template": f"{gflop_template:.4f}"}
        _export_graph(TemplateGraph(graphs_net), template_args(net, z), staging / TEMPLATE_FILE,
                      layout.template_inputs(), layout.template_outputs(), opset, meta | {"graph": "template"})
        _export_graph(SearchGraph(graphs_net), (x, *kernels), staging / SEARCH_FILE, ["x", *layout.search_inputs()],
                      layout.search_outputs(), opset, meta | {"graph": "search"})
        found = random_ops(staging / TEMPLATE_FILE) + random_ops(staging / SEARCH_FILE)
        if found:
            raise ExportError(f"the exported graphs contain random ops ({', '.join(found)}); refusing to ship")
        errors = check_parity(net, staging)
        parity = {k: v[1] for k, v in errors.items()}
        worst = max(parity, key=parity.get)
        if not math.isfinite(parity[worst]):
            raise ExportError(f"parity check failed: output {worst} holds NaN or inf (PyTorch or onnxruntime); a "
                              f"model must give finite outputs; no files written")
        if parity[worst] > tolerance:
            raise ExportError(f"parity check failed: output {worst} differs by {errors[worst][0]:.3g} "
                              f"(scaled {parity[worst]:.3g}) between PyTorch and onnxruntime (tolerance "
                              f"{tolerance:g}); no files written")
        _check_runtime_loads(staging)
        report = ExportReport(
            out_dir=out, files={f: (staging / f).stat().st_size for f in (TEMPLATE_FILE, SEARCH_FILE)},
            gflop_search=gflop_search, gflop_template=gflop_template,
            parity=parity, parity_abs={k: v[0] for k, v in errors.items()})
        out.mkdir(parents=True, exist_ok=True)
        for f in (TEMPLATE_FILE, SEARCH_FILE):
            shutil.move(str(staging / f), str(out / f))
        report.seconds = time.perf_counter() - start
        return report
    except OSError as e:
        raise ExportError(f"{out}: cannot write the model ({e.strerror or e})") from None
    finally:
        shutil.rmtree(staging, ignore_errors=True)
