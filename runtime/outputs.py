"""Where dadiff-run sends each frame's result: a CSV/JSONL track log and an annotated video.

Each sink has `write(frame, record)` and `close()`; other sinks (a MAVLink link, say) plug in the same way.
"""

from __future__ import annotations

import csv
import json
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

from .errors import DadiffError
from .files import RowFile
from .sources import Frame, folder_inputs

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv")  # containers that take the mp4v stream
LOG_FIELDS = ("frame", "timestamp", "x", "y", "w", "h", "score", "state")
STATE_COLOURS = {
    "tracking": (0, 200, 0),
    "uncertain": (0, 200, 255),
    "lost": (0, 0, 255),
    "init": (255, 160, 0),
}


class OutputError(DadiffError):
    """An output file cannot be written (one-line message)."""


def same_file(a: Path, b: Path) -> bool:
    """Whether two paths name one file (through links too), or would once created."""
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)  # hard and symbolic links too
        return a.resolve() == b.resolve()
    except OSError:
        return False


def inside_folder(path: Path, folder: Path) -> bool:
    """Whether `path` lies in `folder` or below it, links resolved."""
    try:
        return path.expanduser().resolve().is_relative_to(folder.resolve())
    except OSError:
        return False


def check_distinct(video: str | None, outputs: dict[str, Path | None]) -> None:
    """OutputError when an output names the input video, a frame or the ground truth of the input folder, or
    another output: opening it would truncate input (`--save-video same.mp4` would overwrite the video being
    read). A new file inside the input folder is fine: only image files are read as frames."""
    named = [(option, Path(path)) for option, path in outputs.items() if path is not None]
    spec = str(video or "")
    is_file = bool(spec) and "://" not in spec and not spec.isdigit() and not spec.startswith("/dev/")
    source = Path(spec).expanduser() if is_file else None
    inputs = folder_inputs(source) if source is not None and source.is_dir() else []
    for i, (option, path) in enumerate(named):
        if (given := next((f for f in inputs if same_file(path, f)), None)) is not None:
            raise OutputError(f"{path}: {option} names {given.name}, an input file of {source}; choose another "
                              "file (nothing written)")
        if source is not None and same_file(path, source):
            raise OutputError(f"{path}: {option} names the input video; choose another file (nothing written)")
        for other, earlier in named[:i]:
            if same_file(path, earlier):
                raise OutputError(f"{path}: given to both {other} and {option}; choose two files")


def _write_error(path: Path, exc: OSError, rows: int) -> OutputError:
    return OutputError(f"{path}: cannot write ({exc.strerror or exc}); the first {rows} rows were saved")


@dataclass(frozen=True)
class Record:
    """What is reported for one frame (frame 0 holds the init box, state 'init')."""

    box: tuple[float, float, float, float]
    score: float
    state: str
    fps: float | None = None


class Sink(Protocol):
    def write(self, frame: Frame, record: Record) -> None: ...

    def close(self) -> None: ...


class TrackLog:
    """One row per frame: frame, timestamp, x, y, w, h, score, state; CSV or JSON Lines by file suffix.

    Each row goes to the kernel as it is written (a crash or power cut loses at most the current row), and a
    full disk or I/O error leaves the file ending at its last whole row (runtime/files.py).
    """

    def __init__(self, path: Path) -> None:
        suffix = path.suffix.lower()
        if suffix not in (".csv", ".jsonl"):
            raise OutputError(f"{path}: --output must end in .csv or .jsonl")
        self.path, self._jsonl = path, suffix == ".jsonl"
        self.rows, self._failed = 0, False
        try:
            self._file = RowFile(path)
        except OSError as exc:
            raise OutputError(f"{path}: cannot write ({exc.strerror or exc})") from None
        self._csv = None if self._jsonl else csv.writer(self._file, lineterminator="\n")
        if self._csv is not None:
            self._guarded(self._csv.writerow, LOG_FIELDS)

    def _guarded(self, write: Callable[[object], object], value: object) -> None:
        """Write one line; a full disk or I/O error becomes one OutputError (the rows before it are on disk,
        whole), and later writes are dropped without another error (the service keeps tracking)."""
        if self._failed:
            return
        try:
            write(value)
        except OSError as exc:
            self._failed = True
            raise _write_error(self.path, exc, self.rows) from None

    def write(self, frame: Frame, record: Record) -> None:
        x, y, w, h = (round(float(v), 3) for v in record.box)
        row = (frame.index, round(frame.timestamp, 6), x, y, w, h, round(record.score, 5), record.state)
        if self._csv is not None:
            self._guarded(self._csv.writerow, row)
        else:
            self._guarded(self._file.write, json.dumps(dict(zip(LOG_FIELDS, row, strict=True))) + "\n")
        self.rows += not self._failed

    def close(self) -> None:
        self._file.close()


def draw_overlay(image: np.ndarray, record: Record) -> np.ndarray:
    """Box coloured by state, with score, state and FPS written above it (draws in place)."""
    colour = STATE_COLOURS.get(record.state, (255, 255, 255))
    x, y, w, h = record.box
    cv2.rectangle(image, (round(x), round(y)), (round(x + w), round(y + h)), colour, 2)
    text = f"{record.state} {record.score:.2f}"
    if record.fps:
        text += f"  {record.fps:.0f} FPS"
    # a dark plate behind the label (an outline stroke renders wider than the text in OpenCV 5),
    # kept inside the frame so the label stays readable near the right and top edges
    (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, 0.5, 1)
    left = min(max(0, round(x)), max(0, image.shape[1] - tw - 4))
    bottom = max(th + base + 2, round(y) - 4)
    cv2.rectangle(image, (left, bottom - th - base - 2), (left + tw + 4, bottom), (0, 0, 0), -1)
    cv2.putText(image, text, (left + 2, bottom - base), cv2.FONT_HERSHEY_SIMPLEX, 0.5, colour, 1, cv2.LINE_AA)
    return image


class Mp4Writer:
    """An mp4v video writer that knows whether its file came out whole.

    OpenCV reports no write error: on a full disk it writes frames into nothing and then fails to write the
    index (the `moov` atom, written last), leaving a file no player opens, while the run ends with exit 0.
    `close` opens the written file again and counts its frames; a file that does not hold every frame is
    removed and OutputError names it. Frames are finalised on every ending the process sees (the commands
    turn SIGINT, SIGTERM and SIGHUP into KeyboardInterrupt, so `close` runs: runtime/commands/launch.py).
    """

    def __init__(self, path: Path, size: tuple[int, int], fps: float = 30.0) -> None:
        self.path, self.frames = path, 0
        self._writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, size)
        if not self._writer.isOpened():
            raise OSError(f"{path}: cannot write video (mp4v)")

    def write(self, image: np.ndarray) -> None:
        self._writer.write(image)
        self.frames += 1

    def close(self) -> None:
        """Finish the file, then check it; OutputError (the file removed) when it does not hold every frame."""
        if self._writer is None:
            return
        self._writer.release()
        self._writer = None
        found = _frames_in(self.path)
        if found == self.frames:
            return
        reason = "no space left on device" if _disk_full(self.path.parent) else "the file came out incomplete"
        self.path.unlink(missing_ok=True)
        raise OutputError(f"{self.path}: cannot write video ({reason}: {found} of {self.frames} frames readable); "
                          "the unplayable file was removed")



def _frames_in(path: Path) -> int:
    """How many frames the container of `path` says it holds (0 when it does not open)."""
    capture = cv2.VideoCapture(str(path))
    try:
        return int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) if capture.isOpened() else 0
    finally:
        capture.release()


def _disk_full(folder: Path) -> bool:
    try:
        return os.statvfs(folder).f_bavail == 0
    except OSError:
        return False


def open_mp4(path: Path, size: tuple[int, int], fps: float = 30.0) -> Mp4Writer:
    """An mp4v writer for frames of `size` (width, height); OSError naming the file when it cannot open."""
    return Mp4Writer(path, size, fps)


class VideoSink:
    """Annotated mp4 (fourcc mp4v) at the source frame rate; opened on the first frame to learn its size."""

    def __init__(self, path: Path, fps: float | None) -> None:
        if path.suffix.lower() not in VIDEO_SUFFIXES:  # another suffix picks another muxer: `%04d.jpg` writes frames
            raise OutputError(f"{path}: --save-video must end in {', '.join(VIDEO_SUFFIXES)}")
        if not path.parent.is_dir():
            raise OutputError(f"{path}: folder {path.parent} does not exist")
        self.path, self.fps = path, fps or 30.0
        self._writer: Mp4Writer | None = None
        self._size: tuple[int, int] | None = None

    def write(self, frame: Frame, record: Record) -> None:
        image = frame.image if frame.image.ndim == 3 else cv2.cvtColor(frame.image, cv2.COLOR_GRAY2BGR)
        if self._writer is None:
            self._size = (image.shape[1], image.shape[0])
            try:
                self._writer = open_mp4(self.path, self._size, self.fps)
            except OSError as exc:
                raise OutputError(str(exc)) from None
        if (image.shape[1], image.shape[0]) != self._size:
            image = cv2.resize(image, self._size)
        self._writer.write(draw_overlay(image, record))

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
