"""What the tracker needs from an inference engine, so that onnxruntime and PyTorch can be swapped."""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np

if TYPE_CHECKING:
    from .onnx_backend import OnnxBackend


@runtime_checkable
class Backend(Protocol):
    """One dadiff model: a template graph run once per init and a search graph run every frame.

    `meta` holds the model metadata (docs/model-format.md, string values). Inputs are float32 NCHW crops
    of raw pixels 0..255 in the model's channel order; `search` returns the (1, 2, S, S) cls and
    (1, 4, S, S) loc maps, and a (1, 1, S, S) centerness map for a SiamGAT model (`decoder` siamgat), whose
    `template` also takes `roi=`, the target's box (1, 4) in template-crop pixels. `feeds` is whatever
    `template` returned, passed back unchanged.
    """

    @property
    def meta(self) -> Mapping[str, str]: ...

    def template(self, z: np.ndarray) -> dict[str, np.ndarray]: ...

    def search(self, x: np.ndarray, feeds: dict[str, np.ndarray]) -> tuple[np.ndarray, ...]: ...


class RecordingBackend:
    """Wraps an OnnxBackend and keeps copies of what the tracker feeds it: every template crop, and every
    `every`-th search feed (crop and kernels, by the search graph's input names) up to `limit` of them.

    Calibration (int8) and the torch comparison of dadiff-bench both need the real inputs of the graphs.
    """

    def __init__(self, inner: OnnxBackend, limit: int, every: int = 1) -> None:
        self.inner, self.limit, self.every = inner, limit, max(1, every)
        self.name = getattr(inner, "name", "recorded")
        self.image_name, *self.kernel_names = inner.search_inputs
        self.templates: list[np.ndarray] = []
        self.rois: list[np.ndarray | None] = []
        self.recorded: list[dict[str, np.ndarray]] = []
        self._calls = 0

    @property
    def meta(self) -> Mapping[str, str]:
        return self.inner.meta

    @property
    def full(self) -> bool:
        return len(self.recorded) >= self.limit

    def template(self, z: np.ndarray, roi: np.ndarray | None = None) -> dict[str, np.ndarray]:
        self.templates.append(z.copy())
        self.rois.append(None if roi is None else roi.copy())
        return self.inner.template(z, roi)

    def search(self, x: np.ndarray, feeds: dict[str, np.ndarray]) -> tuple[np.ndarray, ...]:
        if self._calls % self.every == 0 and not self.full:
            self.recorded.append({self.image_name: x.copy(), **{k: feeds[k] for k in self.kernel_names}})
        self._calls += 1
        return self.inner.search(x, feeds)
