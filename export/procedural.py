"""Procedural weights of the parity fixture (spec 13): every key's values drawn from its own seeded rng.

Lets the released-model path be checked bit for bit against the official implementation's outputs without
the released weights, and gives tests and users a released-format checkpoint to export.
"""

from __future__ import annotations

import zlib

import numpy as np
import torch


def procedural_tensor(key: str, shape: list[int]) -> np.ndarray:
    rng = np.random.default_rng(zlib.crc32(key.encode("utf-8")))
    if key.endswith("num_batches_tracked"):
        return np.zeros(shape, dtype=np.int64)
    if key.endswith("running_var"):
        return (1.0 + rng.random(shape)).astype(np.float32)
    n = rng.standard_normal(shape)
    if key.endswith("running_mean"):
        value = 0.1 * n
    elif key in ("e_zf", "e_xf"):
        value = n
    elif len(shape) >= 2:
        value = n / np.sqrt(np.prod(shape[1:]))
    elif key.endswith(".weight"):
        value = 1.0 + 0.1 * n
    else:
        value = 0.1 * n
    return np.asarray(value, dtype=np.float32)


def procedural_state_dict(shapes: dict[str, list[int]]) -> dict[str, torch.Tensor]:
    return {k: torch.from_numpy(np.array(procedural_tensor(k, s))) for k, s in shapes.items()}


def fixture_inputs() -> tuple[np.ndarray, np.ndarray]:
    """The fixture's template z (1,3,127,127) and search x (1,3,255,255), raw pixel values as float32."""
    g = np.random.default_rng(20240601)
    z = g.integers(0, 256, size=(1, 3, 127, 127)).astype(np.float32)
    x = g.integers(0, 256, size=(1, 3, 255, 255)).astype(np.float32)
    return z, x


def write_released_checkpoint(path: str, shapes: dict[str, list[int]], module_prefix: bool = False) -> None:
    """A checkpoint in the release's own format: {'epoch', 'state_dict', 'optimizer'}."""
    sd = procedural_state_dict(shapes)
    if module_prefix:
        sd = {f"module.{k}": v for k, v in sd.items()}
    torch.save({"epoch": 40, "state_dict": sd, "optimizer": {}}, path)


def main(argv: list[str] | None = None) -> int:
    """python -m dadiff.export.procedural SHAPES.json OUT.pth: a released-format checkpoint with fixture weights."""
    import argparse
    import json

    p = argparse.ArgumentParser(prog="python -m dadiff.export.procedural", description=main.__doc__)
    p.add_argument("shapes", help="dadiff_ban_state_dict_shapes.json (key -> shape)")
    p.add_argument("output")
    p.add_argument("--module-prefix", action="store_true", help="prefix keys with 'module.' (DataParallel)")
    args = p.parse_args(argv)
    with open(args.shapes) as f:
        write_released_checkpoint(args.output, json.load(f), args.module_prefix)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
