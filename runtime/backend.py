"""What the tracker needs from an inference engine, so that onnxruntime and PyTorch can be swapped."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class Backend(Protocol):
    """One dadiff model: a template graph run once per init and a search graph run every frame.

    `meta` holds the model metadata (docs/model-format.md, string values). Inputs are float32 NCHW crops
    of raw pixels 0..255 in the model's channel order; `search` returns the (1, 2, S, S) cls and
    (1, 4, S, S) loc maps. `feeds` is whatever `template` returned, passed back unchanged.
    """

    @property
    def meta(self) -> Mapping[str, str]: ...

    def template(self, z: np.ndarray) -> dict[str, np.ndarray]: ...

    def search(self, x: np.ndarray, feeds: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]: ...
