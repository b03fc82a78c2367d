"""Frame sources for dadiff-run: video files, cameras, streams, and OTB/UAV123-style image folders.

Live sources (camera, stream) skip frames the capture fails to deliver and carry on; so do folders with an
unreadable image. A video file ends after `FILE_FAILURES` failed reads in a row (or at its frame count).
"""

from __future__ import annotations

import math
import os
import re
import sys
import tempfile
import time
import typing
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from .errors import DadiffError
from .user_files import kind_of, read_user_text

IMAGE_EXTS = {".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp", ".pgm", ".ppm"}
GROUNDTRUTH_FILES = ("groundtruth_rect.txt", "groundtruth.txt")
FILE_FAILURES = 25
LIVE_FAILURES = 500  # about 5-20 s of a dead stream before giving up


class SourceError(DadiffError):
    """A source cannot be opened or yields nothing (one-line message)."""


# What image and video decoders print on damaged input straight to fd 2, past OpenCV's log level: libjpeg,
# libpng, OpenCV's own AVI/MJPEG reader, FFmpeg.
DECODER_NOISE = ("JPEG", "jpeg", "libpng", "Corrupt", "Premature end", "extraneous bytes", "marker", "Huffman",
                 "Unexpected element", "Expected:", "AVI", "avi", "mjpeg", "h264", "mpeg4", "moov", "[mov",
                 "Invalid", "invalid", "error while decoding", "decode_slice", "concealing",
                 "cap_ffmpeg_impl")  # OpenCV 5.1's FFmpeg backend logs its failed opens itself


class QuietDecoder:
    """Point file descriptor 2 at a scratch file while C decoders run, then pass on what is not their noise.

    On a damaged file libjpeg, OpenCV's AVI reader and FFmpeg print lines of their own; the user sees
    only the one `dadiff-run: error:` line. Output of other threads in that window is delayed, not lost.
    """

    def __init__(self) -> None:
        self._scratch: typing.BinaryIO | None = None
        self._saved: int | None = None

    def __enter__(self) -> QuietDecoder:
        try:
            if self._scratch is None:
                self._scratch = tempfile.TemporaryFile()
            sys.stderr.flush()
            self._saved = os.dup(2)
            os.dup2(self._scratch.fileno(), 2)
        except (OSError, ValueError):
            self._saved = None
        return self

    def __exit__(self, *exc: object) -> None:
        if self._saved is None or self._scratch is None:
            return
        sys.stderr.flush()
        os.dup2(self._saved, 2)
        os.close(self._saved)
        self._saved = None
        scratch = self._scratch
        if scratch.tell() == 0:
            return
        scratch.seek(0)
        text = scratch.read().decode(errors="replace")
        scratch.seek(0)
        scratch.truncate()
        kept = [line for line in text.splitlines() if line.strip() and not any(n in line for n in DECODER_NOISE)]
        if kept:
            print("\n".join(kept), file=sys.stderr, flush=True)

    def close(self) -> None:
        if self._scratch is not None:
            self._scratch.close()
            self._scratch = None


def read_image(path: Path, flags: int = cv2.IMREAD_COLOR) -> np.ndarray | None:
    """cv2.imread without the decoder's own warnings on stderr (a damaged image is the caller's to count)."""
    quiet = QuietDecoder()
    try:
        with quiet:
            return cv2.imread(str(path), flags)
    finally:
        quiet.close()


@contextmanager
def quiet_opencv() -> Iterator[None]:
    """Keep OpenCV/FFmpeg warnings off stderr so that errors stay one line; the user's own
    OPENCV_LOG_LEVEL / OPENCV_FFMPEG_LOGLEVEL settings win."""
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET, read when FFmpeg starts
    if "OPENCV_LOG_LEVEL" in os.environ:
        yield
        return
    previous = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
    try:
        yield
    finally:
        cv2.utils.logging.setLogLevel(previous)


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
        self.missing = 0  # frames a file's header promised but that never came (a truncated file)
        target: int | str = int(spec) if spec.isdigit() else spec
        self._quiet = QuietDecoder()
        with self._quiet:
            self._cap = cv2.VideoCapture(target)
        if not self._cap.isOpened():
            what = "cannot read video file" if kind == "file" else f"cannot open {kind}"
            raise SourceError(f"{what} '{spec}'")
        fps = self._cap.get(cv2.CAP_PROP_FPS)
        self.fps: float | None = fps if math.isfinite(fps) and 0 < fps < 1000 else None
        count = int(self._cap.get(cv2.CAP_PROP_FRAME_COUNT)) if not self.live else 0
        self.length: int | None = count if count > 0 else None

    def frames(self) -> Iterator[Frame]:
        self._read = 0
        yield from self._frames()
        self._count_missing()  # only at the real end: a generator closed early (--max-frames) is not truncated

    def _count_missing(self) -> None:
        """A file that ends before its frame count is truncated: say so, and count the frames as skipped."""
        if self.live or self.length is None or self._read >= self.length or self.missing:
            return
        self.missing = self.length - self._read
        self.skipped += self.missing

    def _frames(self) -> Iterator[Frame]:
        index, failures = 0, 0
        while True:
            with self._quiet:
                ok, image = self._cap.read()
            if ok and image is not None and image.size:
                if self.live:
                    stamp = time.time()
                else:
                    # failed reads followed by a good one are frames skipped, not the end of the file
                    self.skipped += failures
                    stamp = index / self.fps if self.fps else self._cap.get(cv2.CAP_PROP_POS_MSEC) / 1000
                failures = 0
                self._read = index + 1
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
        self._quiet.close()


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


def image_dir(folder: Path) -> Path:
    """Where a sequence folder keeps its frames: its img/ subfolder if it has one, else itself."""
    return folder / "img" if (folder / "img").is_dir() else folder


def image_files(folder: Path) -> list[Path]:
    """A sequence folder's frames, in natural order (1, 2, ..., 10)."""
    return sorted((p for p in image_dir(folder).iterdir() if p.suffix.lower() in IMAGE_EXTS), key=_natural_key)


def folder_inputs(folder: Path) -> list[Path]:
    """The files a FolderSource reads: its frames and its ground truth (what an output must never replace)."""
    return image_files(folder) + [folder / name for name in GROUNDTRUTH_FILES if (folder / name).is_file()]


class FolderSource:
    """Image files sorted by name (natural order) in a folder or its img/ subfolder; first ground-truth
    line (groundtruth_rect.txt) as the init box. Timestamps are the Unix time each image was read."""

    kind = "folder"
    live = False
    fps = None

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.files = image_files(folder)
        if not self.files:
            raise SourceError(f"{folder}: no image files found (looked in {image_dir(folder)})")
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
            lines = [line for line in read_user_text(path).splitlines() if line.strip()]
        except (OSError, UnicodeDecodeError) as exc:
            raise SourceError(f"{path}: cannot read ({exc})") from None
        if not lines:
            raise SourceError(f"{path}: empty ground-truth file")
        try:
            return parse_box(lines[0])
        except ValueError as exc:
            raise SourceError(f"{path}: first line: {exc}") from None

    def frames(self) -> Iterator[Frame]:
        """The readable images; one that cannot be read, or whose size differs from the first image's (another
        camera's frame, whose pixels the box does not refer to), is skipped and counted."""
        size: tuple[int, ...] = ()
        for index, path in enumerate(self.files):
            image = read_image(path)
            if image is None:
                if index == 0:
                    raise SourceError(f"{path}: cannot read the first image")
                self.skipped += 1
                continue
            if index == 0:
                size = image.shape[:2]
            elif image.shape[:2] != size:
                self.skipped += 1
                continue
            yield Frame(index, time.time(), image)

    def close(self) -> None:
        pass


def source_path(spec: str) -> Path:
    """The video file or image folder that a source spec which is no camera or stream names; SourceError when
    it is missing or neither (a FIFO with no writer would hold FFmpeg's probe forever), each case named."""
    path = Path(spec).expanduser()
    if path.is_dir() or path.is_file():
        return path
    if path.exists():
        raise SourceError(f"'{spec}': {kind_of(path)}, not a video file or image folder (a camera is /dev/video* "
                          "or its index, a stream its URL)")
    raise SourceError(f"no such file or folder: '{spec}'")


def open_source(spec: str) -> VideoSource | FolderSource:
    """Camera index ('0') or device (/dev/video0), stream URL (scheme://...), image folder, or video file."""
    if spec.isdigit() or spec.startswith("/dev/"):
        return VideoSource(spec, "camera")
    if "://" in spec:
        return VideoSource(spec, "stream")
    path = source_path(spec)
    return FolderSource(path) if path.is_dir() else VideoSource(str(path), "file")
