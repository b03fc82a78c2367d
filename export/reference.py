"""PyTorch reference backend: the network run by the runtime's own pre/post-processing.

Plugging this into `dadiff.runtime.Tracker` gives a reference tracker that shares every line of crop and
decode code with the onboard one, so comparing the two isolates the exported graphs.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from .checkpoint import LoadedCheckpoint, load_checkpoint
from .onnx_export import DEFAULT_OPSET, SearchGraph, TemplateGraph, model_metadata


class TorchBackend:
    """Implements dadiff.runtime.Backend with the PyTorch network (CPU, eval mode, no grad)."""

    def __init__(self, loaded: LoadedCheckpoint, name: str = "torch-reference") -> None:
        self.name = name
        self._meta = model_metadata(loaded, name, DEFAULT_OPSET)
        self._template = TemplateGraph(loaded.model.eval())
        self._search = SearchGraph(loaded.model)
        self._outputs = json.loads(self._meta["template_outputs"])
        self._kernels = json.loads(self._meta["search_inputs"])[1:]

    @classmethod
    def from_checkpoint(cls, path: str | Path) -> TorchBackend:
        return cls(load_checkpoint(path))

    @property
    def meta(self) -> dict[str, str]:
        return self._meta

    def template(self, z: np.ndarray, roi: np.ndarray | None = None) -> dict[str, np.ndarray]:
        args = [torch.from_numpy(np.ascontiguousarray(z, dtype=np.float32))]
        if self._template.layout.roi:  # DaDiff-GAT: the target's box in template-crop pixels
            args.append(torch.from_numpy(np.asarray(roi, dtype=np.float32).reshape(1, 4)))
        with torch.no_grad():
            outs = self._template(*args)
        return {name: t.numpy() for name, t in zip(self._outputs, outs, strict=True)}

    def search(self, x: np.ndarray, feeds: dict[str, np.ndarray]) -> tuple[np.ndarray, ...]:
        kernels = [torch.from_numpy(feeds[name]) for name in self._kernels]
        with torch.no_grad():
            maps = self._search(torch.from_numpy(np.ascontiguousarray(x, dtype=np.float32)), *kernels)
        return tuple(m.numpy() for m in maps)
