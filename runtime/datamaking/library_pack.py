"""A small copy of the real-photo library that travels: training on a lent GPU machine, another computer.

The device machine takes at most 64 MiB of working tree and has no package registry, so `dadiff-eval data
pack` copies an even share of every package's training images (and, with `--split all`, its test images),
shrunk to a bounded side and re-encoded (cut-outs as PNG to keep their alpha, backgrounds as JPEG), until a
byte budget is spent, and writes an `index.json` in the library's own format: `open_library(pack)` reads it
like the full cache (`DADIFF_DATA_DIR=pack`).
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from .library import FORMAT, Library, LibraryError, LibraryImage

TARGET_SIDE = 384
BACKGROUND_SIDE = 960
JPEG_QUALITY = 88


def _shrunk(image: np.ndarray, side: int) -> np.ndarray:
    scale = side / max(image.shape[:2])
    if scale >= 1:
        return image
    size = (max(1, round(image.shape[1] * scale)), max(1, round(image.shape[0] * scale)))
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)


def _encode(item: LibraryImage) -> tuple[bytes, str, tuple[int, int]]:
    """The image re-encoded for the pack: bytes, suffix, (width, height)."""
    image = item.load()
    if item.role == "target":
        image = _shrunk(image, TARGET_SIDE)
        ok, data = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 9])
        suffix = ".png"
    else:
        image = _shrunk(image, BACKGROUND_SIDE)
        ok, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        suffix = ".jpg"
    if not ok:
        raise LibraryError(f"cannot re-encode library image {item.path}")
    return data.tobytes(), suffix, (image.shape[1], image.shape[0])


def _interleaved(library: Library, splits: tuple[str, ...]) -> list[LibraryImage]:
    """Images in round-robin over (role, package) groups, so a tight budget still covers every source."""
    groups: dict[tuple[str, str], list[LibraryImage]] = {}
    for split in splits:
        for role in ("target", "background"):
            for item in library.images(role, split):
                groups.setdefault((role, item.package), []).append(item)
    order, queues = [], [list(g) for _, g in sorted(groups.items())]
    while any(queues):
        for q in queues:
            if q:
                order.append(q.pop(0))
    return order


def pack_library(library: Library, out: Path, max_bytes: int, splits: tuple[str, ...] = ("train",)) -> dict:
    """Write the pack into `out` (a new or empty folder); returns counts {(role, split): n, 'bytes': total}."""
    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise LibraryError(f"{out}: exists and is not an empty folder; choose a new pack folder")
    if max_bytes <= 0:
        raise LibraryError(f"the pack budget must be positive, got {max_bytes} bytes")
    order = _interleaved(library, splits)
    if not order:  # an empty pack is an error, never an exit-0 'packed ... (0.0 MiB)'
        raise LibraryError(f"{library.root}: no {' or '.join(splits)} images to pack (nothing written)")
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    packages: dict[str, dict] = {}
    used, counts, smallest = 0, {}, max_bytes + 1
    for n, item in enumerate(order):
        data, suffix, (width, height) = _encode(item)
        smallest = min(smallest, len(data))
        if used + len(data) > max_bytes:
            continue  # a smaller image further on may still fit
        rel = Path("images") / item.package / f"{n:05d}{suffix}"
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        (out / rel).write_bytes(data)
        used += len(data)
        entry = packages.setdefault(item.package, {"licence": item.licence, "images": []})
        entry["images"].append({"file": str(rel), "source": item.source, "role": item.role, "split": item.split,
                                "width": width, "height": height})
        counts[f"{item.role}/{item.split}"] = counts.get(f"{item.role}/{item.split}", 0) + 1
    if not used:
        if created:
            out.rmdir()
        raise LibraryError(f"no image fits in the pack budget of {max_bytes} bytes (the smallest takes {smallest}); "
                           "raise --max-mib (nothing written)")
    (out / "index.json").write_text(json.dumps({"format": FORMAT, "packages": packages}, indent=1) + "\n")
    return {**counts, "bytes": used}
