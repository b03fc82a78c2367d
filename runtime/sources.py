"""Frame sources for dadiff-run: video files, cameras, streams, and OTB/UAV123-style image folders.

Live sources (camera, stream) skip frames the capture fails to deliver and carry on; so do folders with an
unreadable image. A video file ends after `FILE_FAILURES` failed reads in a row (or at its frame count).
"""

from __future__ import annotations

import math
import re
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

IMAGE_EXTS = {".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp", ".pgm", ".ppm"}
GROUNDTRUTH_FILES = ("groundtruth_rect.txt", "groundtruth.txt")
FILE_FAILURES = 25
LIVE_FAILURES = 500  # about 5-20 s of a dead stream before giving up


class SourceError(Exception):
    """A source cannot be opened or yields nothing (one-line message)."""


@dataclass(frozen=True)
class Frame:
    """A decoded frame: its index in the source, a timestamp in seconds, the BGR image."""

    index: int
    timestamp: float
    image: np.ndarray


class VideoSource:
    """cv2.VideoCapture on a file, a camera (index or /dev/video*), or a stream URL.

    Timestamps: media time for files (index / fps), Unix time of capture for live sources.
    """

    def __init__(self, spec: str, kind: str) -> None:
        self.spec, self.kind = spec, kind
        self.live = kind != "file"
        self.init_box: tuple[float, float, float, float] | None = None
        self.skipped = 0
        target: int | str = int(spec) if spec.isdigit() else spec
        self._cap = cv2.VideoCapture(target)
        if not self._cap.isOpened():
            what = "cannot read video file" if kind == "file" else f"cannot open {kind}"
            raise SourceError(f"{what} '{spec}'")
        fps = self._cap.get(cv2.CAP_PROP_FPS)
        self.fps: float | None = fps if math.isfinite(fps) and 0 < fps < 1000 else None
        count = int(self._cap.get(cv2.CAP_PROP_FRAME_COUNT)) if not self.live else 0
        self.length: int | None = count if count > 0 else None

    def frames(self) -> Iterator[Frame]:
        index, failures = 0, 0
        while True:
            ok, image = self._cap.read()
            if ok and image is not None and image.size:
                if self.live:
                    stamp = time.time()
                else:
                    # failed reads followed by a good one were frames skipped, not the end of the file
                    self.skipped += failures
                    stamp = index / self.fps if self.fps else self._cap.get(cv2.CAP_PROP_POS_MSEC) / 1000
                failures = 0
                yield Frame(index, stamp, image)
                index += 1
                continue
            if self.live and not self._cap.isOpened():
                return
            if not self.live and self.length is not None and index >= self.length:
                return
            failures += 1
            index += 1
            if self.live:
                self.skipped += 1
                if failures >= LIVE_FAILURES:
                    print(
                        f"dadiff-run: {self.kind} delivered no frame in {failures} reads; stopping",
                        file=sys.stderr,
                    )
                    return
                time.sleep(min(0.05, 0.001 * failures))
            elif failures >= FILE_FAILURES:
                return

    def close(self) -> None:
        self._cap.release()


def _natural_key(path: Path) -> list[object]:
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", path.name)]


def parse_box(text: str) -> tuple[float, float, float, float]:
    """(x, y, w, h) from 'x,y,w,h' (commas, tabs or spaces); 8 numbers are a polygon → its bounding box."""
    parts = [p for p in re.split(r"[,\s]+", text.strip()) if p]
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise ValueError(f"expected numbers x,y,w,h, got {text.strip()!r}") from None
    if len(values) == 8:
        xs, ys = values[0::2], values[1::2]
        values = [min(xs), min(ys), max(xs) - min(xs), max(ys) - min(ys)]
    if len(values) != 4 or not all(math.isfinite(v) for v in values):
        raise ValueError(f"expected four numbers x,y,w,h, got {text.strip()!r}")
    return values[0], values[1], values[2], values[3]


class FolderSource:
    """Image files sorted by name (natural order) in a folder or its img/ subfolder; first ground-truth
    line (groundtruth_rect.txt) as the init box. Timestamps are the Unix time each image was read."""

    kind = "folder"
    live = False
    fps = None

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        images = folder / "img" if (folder / "img").is_dir() else folder
        self.files = sorted((p for p in images.iterdir() if p.suffix.lower() in IMAGE_EXTS), key=_natural_key)
        if not self.files:
            raise SourceError(f"{folder}: no image files found (looked in {images})")
        self.length: int | None = len(self.files)
        self.skipped = 0
        self.init_box: tuple[float, float, float, float] | None = None
        for name in GROUNDTRUTH_FILES:
            path = folder / name
            if path.is_file():
                self.init_box = self._first_box(path)
                break

    @staticmethod
    def _first_box(path: Path) -> tuple[float, float, float, float]:
        try:
            lines = [line for line in path.read_text().splitlines() if line.strip()]
        except (OSError, UnicodeDecodeError) as exc:
            raise SourceError(f"{path}: cannot read ({exc})") from None
        if not lines:
            raise SourceError(f"{path}: empty ground-truth file")
        try:
            return parse_box(lines[0])
        except ValueError as exc:
            raise SourceError(f"{path}: first line: {exc}") from None

    def frames(self) -> Iterator[Frame]:
        for index, path in enumerate(self.files):
            image = cv2.imread(str(path), cv2.IMREAD_COLOR)
            if image is None:
                if index == 0:
                    raise SourceError(f"{path}: cannot read the first image")
                self.skipped += 1
                continue
            yield Frame(index, time.time(), image)

    def close(self) -> None:
        pass


def open_source(spec: str) -> VideoSource | FolderSource:
    """Camera index ('0') or device (/dev/video0), stream URL (scheme://...), image folder, or video file."""
    if spec.isdigit() or spec.startswith("/dev/"):
        return VideoSource(spec, "camera")
    if "://" in spec:
        return VideoSource(spec, "stream")
    path = Path(spec).expanduser()
    if path.is_dir():
        return FolderSource(path)
    if path.is_file():
        return VideoSource(str(path), "file")
    raise SourceError(f"no such file or folder: '{spec}'")
