"""The night of any day dataset, rendered by the independent camera model (`dadiff-eval night`).

A validation set whose nights come from the training's own renderer measures the fit to that renderer. This
takes the day sequences of any dataset on disk (the generated sets' `*_day`, `dadiff-eval video`'s, OTB,
UAV123, ...) and writes each as `<name>_day` (its frames copied) and `<name>_night` (filmed by a
`camera_night.NightCamera` drawn from the seed and the sequence's name) in the OTB layout, with
`attributes.json` and `benchmark.json` (the source, the seed and every camera's settings). It imports nothing
of the generator (night.py, scene.py, library_scenes.py); a test checks it.
"""

from __future__ import annotations

import json
import shutil
import zlib
from pathlib import Path

import cv2
import numpy as np

from ..files import write_atomic
from ..sources import read_image
from .camera_night import MODEL, night_statistics, render_night
from .datasets import Sequence, check_new_folder, load_dataset
from .scene_error import SceneError

DAY_SUFFIX = "_day"
STATISTICS_EVERY = 10  # every 10th night frame goes into the printed statistics


def base_name(sequence: str) -> str:
    """`seq001_day` -> `seq001`; a name without the suffix stays as it is."""
    return sequence[: -len(DAY_SUFFIX)] if sequence.endswith(DAY_SUFFIX) else sequence


def day_sequences(dataset_dir: str | Path, patterns: list[str] | None = None) -> list[Sequence]:
    """The sequences to render: those matching `patterns`; without them the `*_day` ones, or all if none is."""
    dataset = load_dataset(dataset_dir)
    if patterns:
        return list(dataset.select(patterns).sequences)
    days = [s for s in dataset.sequences if s.name.endswith(DAY_SUFFIX)]
    return days or list(dataset.sequences)


def read_frames(sequence: Sequence) -> list[np.ndarray]:
    """A sequence's frames (BGR uint8), one size throughout."""
    frames = []
    for path in sequence.frames:
        image = read_image(path)
        if image is None:
            raise SceneError(f"{path}: cannot be read as an image")
        if frames and image.shape != frames[0].shape:
            raise SceneError(f"{path}: {image.shape[1]}x{image.shape[0]}, not the sequence's "
                             f"{frames[0].shape[1]}x{frames[0].shape[0]}")
        frames.append(image)
    return frames


def _write_sequence(folder: Path, boxes: np.ndarray, frames: list[np.ndarray] | None = None,
                    copies: tuple[Path, ...] = ()) -> None:
    """An OTB sequence folder: `frames` written as JPEG (quality 95) or `copies` copied, and the boxes."""
    (folder / "img").mkdir(parents=True)
    for i, image in enumerate(frames or []):
        if not cv2.imwrite(str(folder / "img" / f"{i + 1:04d}.jpg"), image, [cv2.IMWRITE_JPEG_QUALITY, 95]):
            raise SceneError(f"{folder}: cannot write frames")
    for i, path in enumerate(copies):
        shutil.copyfile(path, folder / "img" / f"{i + 1:04d}{path.suffix.lower()}")
    np.savetxt(folder / "groundtruth_rect.txt", boxes, fmt="%.3f", delimiter=",")


def write_camera_nights(dataset_dir: str | Path, out: str | Path, seed: int = 0,
                        patterns: list[str] | None = None) -> tuple[int, dict[str, float]]:
    """Write the day sequences of `dataset_dir` and their nights by the camera model to `out` (new or empty);
    returns how many and the median night statistics over every STATISTICS_EVERY-th night frame."""
    out = Path(out).expanduser()
    check_new_folder(out)
    sequences = day_sequences(dataset_dir, patterns)
    bases = [base_name(s.name) for s in sequences]
    if len(set(bases)) != len(bases):
        raise SceneError(f"{dataset_dir}: two sequences share a name once '{DAY_SUFFIX}' is dropped; "
                         "pick them with --sequences")
    table, cameras, rows = {}, {}, []
    for sequence, base in zip(sequences, bases, strict=True):
        day = read_frames(sequence)
        night, cameras[f"{base}_night"] = render_night(day, [seed, zlib.crc32(base.encode())])
        _write_sequence(out / f"{base}_day", sequence.boxes, copies=sequence.frames)
        _write_sequence(out / f"{base}_night", sequence.boxes, frames=night)
        kept = [a for a in sequence.attributes if a != "LAI"]
        table[f"{base}_day"], table[f"{base}_night"] = kept, [*kept, "LAI"]
        rows += [night_statistics(f) for f in night[::STATISTICS_EVERY]]
    write_atomic(out / "attributes.json", json.dumps(table, indent=1) + "\n")
    info = {"generator": "dadiff.runtime.datamaking.night_sets", "night": MODEL, "source": str(dataset_dir),
            "seed": seed, "sequences": bases, "night_cameras": cameras}
    write_atomic(out / "benchmark.json", json.dumps(info, indent=1) + "\n")
    return len(bases), {key: float(np.nanmedian([r[key] for r in rows])) for key in rows[0]}


def format_statistics(stats: dict[str, float]) -> str:
    """One line of the night statistics, in the order of ../shared/notes/real-night-footage.md's table."""
    return (f"mean luma {stats['mean']:.1f}, B/G/R {stats['blue']:.1f}/{stats['green']:.1f}/{stats['red']:.1f}, "
            f"share < 20 {stats['below_20']:.2f}, share > 245 {stats['above_245']:.1e}, "
            f"dark noise {stats['noise']:.2f}")
