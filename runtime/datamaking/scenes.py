"""Night-scene benchmark generator: seeded sequences of small objects over real photographs, by day and at
night, with exact boxes (`make_sequence`), and OTB-layout benchmarks of them on disk (`write_benchmark`).

A sequence is a generated `Scene` (scene.py: camera, object, occluder, distractor; exact boxes from the
geometry) rendered frame by frame, and its night (`SceneNight`: one night camera for the whole scene, from
night.py: style "classic" or "real"). Two picture sources: "skimage" (photos.py: scikit-image's bundled
images, split once and for all into `PHOTO_SPLITS`) and "library" (library_scenes.py: real cut-outs over
aerial textures and photos seen by a drone camera, with the library's own train/test split).
"""

from __future__ import annotations

import ctypes
import json
import multiprocessing
import os
import shutil
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..files import write_atomic
from .library_scenes import library_images, open_scene_library, random_library_scene
from .night import FrameLights, NightStyle, RealNight, check_night_style
from .photos import check_split, load_photos
from .scene import Scene, frame_size
from .scene_error import SceneError  # also the generator's error for its callers


@dataclass(frozen=True)
class SceneSequence:
    """A rendered sequence: day and night frames (BGR uint8), exact boxes (N, 4), attributes of the day
    version (`night_attributes` adds LAI)."""

    name: str
    day: list[np.ndarray]
    night: list[np.ndarray]
    boxes: np.ndarray
    attributes: tuple[str, ...]

    @property
    def night_attributes(self) -> tuple[str, ...]:
        return (*self.attributes, "LAI")


SOURCES = ("skimage", "library")  # where scenes take their pictures from


def _source_and_night(source: str, night: str | None) -> str:
    """Check `source` and `night`; the night style (None: classic for skimage, real for library)."""
    if source not in SOURCES:
        raise SceneError(f"unknown scene source '{source}'; expected one of {', '.join(SOURCES)}")
    if night is None:
        return "classic" if source == "skimage" else "real"
    check_night_style(night)
    return night


def _night_rng(entropy: list[int], i: int) -> np.random.Generator:
    return np.random.default_rng([*entropy, 1_000_003, i])


class SceneNight:
    """The night over one scene, the same in all its frames: one night camera and, for style "real", street
    lights fixed on the ground and an exposure locked on frame 0. `night(day, i, rng)` is frame i at night
    (`rng`: that frame's noise); random access. `classic`: the classic camera (default: drawn from `rng`)."""

    def __init__(
        self, scene: Scene, rng: np.random.Generator, style: str = "real", classic: NightStyle | None = None
    ) -> None:
        check_night_style(style)
        self.scene, self.style = scene, style
        if style == "classic":
            self.classic = classic or NightStyle.random(rng)
        else:
            self.real = RealNight.random(rng)
            self.lights = scene.night_lights(rng, self.real.kind)
            self.gain = self.real.exposure(scene.render(0)[0], self._lights(0))

    def add_path_lamps(self, rng: np.random.Generator, frames: tuple[int, ...], count: int) -> None:
        """Put `count` more street lamps beside the target's path ("real" style only): each beside the target
        in one of `frames` (0.7-2.5 target sizes from its centre, half of them over a pool), fixed on the
        ground. Training uses it to show the lamp heads that night trackers lock on more often than the
        scenes place them by chance; the exposure stays the one locked on frame 0."""
        if self.style == "classic":
            return
        for _ in range(count):
            k = int(frames[int(rng.integers(len(frames)))])
            x, y, w, h = self.scene.boxes[k]
            angle, reach = rng.uniform(0, 2 * np.pi), rng.uniform(0.7, 2.5) * max(np.sqrt(w * h), 8.0)
            where = np.array([x + w / 2 + reach * np.cos(angle), y + h / 2 + reach * np.sin(angle)])
            gx, gy = self.scene.on_ground(k, where)
            self.lights = self.lights.with_lamp_at(
                rng, self.real.kind, float(gx), float(gy), self.scene.ground_unit(k), rng.random() < 0.5
            )

    def _lights(self, i: int) -> FrameLights:
        return self.lights.at(self.scene.cameras[i], i, *self.scene.size)

    def __call__(self, day: np.ndarray, i: int, rng: np.random.Generator) -> np.ndarray:
        if self.style == "classic":
            return self.classic.apply(day, rng, self.scene.lights_at(i))
        return self.real.apply(day, rng, self._lights(i), self.scene.motion(i), self.gain)


def _scene_and_night(
    entropy: list[int], split: str, frames: int, size: tuple[int, int], source: str, night: str, library,
    gusts: bool = False,
) -> tuple[Scene, SceneNight]:
    rng = np.random.default_rng(entropy)
    if source == "skimage":
        scene = Scene.random(rng, load_photos(split), size=size, frames=frames)
    else:
        scene = random_library_scene(rng, library or open_scene_library(), split, frames, size, gust=gusts)
    classic = NightStyle.random(rng)  # drawn whatever the style: the seeded sequences stay as they were
    return scene, SceneNight(scene, np.random.default_rng([*entropy, 2_000_003]), night, classic)


def make_sequence(
    seed: int,
    split: str = "test",
    frames: int = 120,
    size: tuple[int, int] = (640, 360),
    *,
    source: str = "skimage",
    night: str | None = None,
    library=None,
) -> SceneSequence:
    """One sequence rendered by day and at night, deterministic from `seed`.

    `source`: "skimage" (blobs textured from scikit-image photos) or "library" (the real-photo library:
    `library`, default `open_scene_library()`); `night`: "classic" or "real" (None: classic for skimage, so
    that seeded sequences stay as they always were, real for library)."""
    check_split(split)
    style = _source_and_night(source, night)
    entropy = [int(seed)]
    scene, camera = _scene_and_night(entropy, split, frames, size, source, style, library)
    day, nights = [], []
    for i in range(frames):
        frame, _ = scene.render(i)
        day.append(frame)
        nights.append(camera(frame, i, _night_rng(entropy, i)))
    return SceneSequence(f"scene{seed}", day, nights, scene.boxes.copy(), scene.attributes)


def write_boxes(path: Path, boxes: np.ndarray) -> None:
    """An OTB `groundtruth_rect.txt`: one x,y,w,h line per frame."""
    path.write_text("".join(",".join(f"{v:.3f}" for v in row) + "\n" for row in boxes))


def write_frame(img_folder: Path, index: int, image: np.ndarray) -> None:
    """Frame `index` (from 0) of an OTB sequence as `img_folder/NNNN.jpg` (from 0001, JPEG quality 92)."""
    if not cv2.imwrite(str(img_folder / f"{index + 1:04d}.jpg"), image, [cv2.IMWRITE_JPEG_QUALITY, 92]):
        raise SceneError(f"{img_folder}: cannot write frames")


def _tune_worker() -> None:
    """Set up a generator worker process: one OpenCV thread each, and glibc told to keep freed memory.

    Each frame allocates and frees some 50 MB of temporaries; by default glibc hands that back to the
    system and takes the page faults again on the next frame (a third of the CPU time). Only ever called
    in the worker processes that `write_benchmark` starts.
    """
    cv2.setNumThreads(1)
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(-1, 1 << 30)  # M_TRIM_THRESHOLD
        libc.mallopt(-3, 32 << 20)  # M_MMAP_THRESHOLD (glibc's maximum)
    except (OSError, AttributeError):
        pass  # not glibc: only slower


def _write_sequence(job: tuple) -> tuple[str, tuple[str, ...]]:
    root, name, entropy, split, frames, size, source, night, library, gusts = job
    scene, camera = _scene_and_night(entropy, split, frames, size, source, night, library, gusts)
    folders = {kind: root / f"{name}_{kind}" for kind in ("day", "night")}
    for folder in folders.values():
        (folder / "img").mkdir(parents=True, exist_ok=True)
    for i in range(frames):
        day, _ = scene.render(i)
        night = camera(day, i, _night_rng(entropy, i))
        for kind, image in (("day", day), ("night", night)):
            write_frame(folders[kind] / "img", i, image)
    for folder in folders.values():
        write_boxes(folder / "groundtruth_rect.txt", scene.boxes)
    write_atomic(root / UNFINISHED / f"{name}.json", json.dumps(list(scene.attributes)))  # last: marks it whole
    return name, scene.attributes


UNFINISHED = ".unfinished"  # in a benchmark being written: settings.json, and <seq>.json per finished sequence


def _resume_point(root: Path, info: dict) -> dict[str, tuple[str, ...]]:
    """The finished sequences (name -> attributes) of an interrupted `write_benchmark` into `root` with the same
    settings, {} for a new or empty `root`; SceneError for any other folder."""
    if not root.exists() or (root.is_dir() and not any(root.iterdir())):
        return {}
    marker = root / UNFINISHED / "settings.json"
    if not marker.is_file():
        raise SceneError(f"{root}: exists and is not an empty folder; choose a new --output")
    try:
        earlier = json.loads(marker.read_text())
    except (OSError, ValueError):
        earlier = None
    if earlier != info:
        differ = sorted(k for k in {*info, *(earlier or {})} if (earlier or {}).get(k) != info.get(k))
        raise SceneError(f"{root}: holds an interrupted generation with other settings ({', '.join(differ)}); "
                         "run it with the same options to finish it, or choose a new --output")
    done = {}
    for path in (root / UNFINISHED).glob("seq*.json"):
        try:
            done[path.stem] = tuple(json.loads(path.read_text()))
        except (OSError, ValueError):
            continue  # cut short: written again
    return done


def write_benchmark(
    root: str | Path,
    sequences: int,
    frames: int,
    seed: int,
    split: str = "test",
    *,
    size: tuple[int, int] = (640, 360),
    workers: int | None = None,
    source: str = "skimage",
    night: str | None = None,
    library=None,
    gusts: bool = False,
) -> Path:
    """Write an OTB-layout benchmark: `<root>/seqNNN_day/img/0001.jpg...`, `groundtruth_rect.txt`, the same
    for `_night`, `attributes.json` and `benchmark.json`. Sequence k uses seed entropy [seed, k]. `source`,
    `night` and `library` as for `make_sequence`; `gusts` (library only): each sequence's camera knocked once
    by a gust (fast motion of the whole picture). Returns `root`."""
    check_split(split)
    night = _source_and_night(source, night)
    if gusts and source != "library":
        raise SceneError("gusts need the library source (--source library)")
    if sequences < 1 or frames < 1:
        raise SceneError(f"need at least one sequence and one frame, got {sequences} x {frames}")
    frame_size(size, frames)  # here, not only in the workers: a bad size must not leave an empty root behind
    if int(seed) < 0:
        raise SceneError(f"seed must be >= 0, got {seed}")
    root = Path(root).expanduser()
    info = {"generator": "dadiff.runtime.scenes", "seed": seed, "split": split, "source": source, "night": night,
            "sequences": sequences, "frames": frames}
    if gusts:
        info["gusts"] = True
    if getattr(library, "folder", None) is not None:  # a CutoutTargets: whose targets the scenes show
        info["cutouts"] = str(Path(library.folder).resolve())
    settings = {**info, "size": list(size)}
    done = _resume_point(root, settings)
    if source == "library":  # fail early, before anything is written (the workers open their own)
        library_images(library or open_scene_library(), split)
    if source == "skimage":  # likewise: without scikit-image an empty --output folder was left behind
        load_photos(split)
    try:
        (root / UNFINISHED).mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SceneError(f"{root}: cannot create ({exc.strerror or exc})") from None
    write_atomic(root / UNFINISHED / "settings.json", json.dumps(settings))
    names = [f"seq{k + 1:03d}" for k in range(sequences)]
    jobs = [
        (root, name, [int(seed), k], split, frames, tuple(size), source, night, library, gusts)
        for k, name in enumerate(names) if name not in done
    ]
    workers = max(1, min(workers or os.cpu_count() or 1, len(jobs)))
    if workers == 1:
        results = [_write_sequence(job) for job in jobs]
    else:
        spawn = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(workers, mp_context=spawn, initializer=_tune_worker) as pool:
            results = list(pool.map(_write_sequence, jobs))
    attributes = done | dict(results)
    table: dict[str, list[str]] = {}
    for name in names:
        table[f"{name}_day"] = list(attributes[name])
        table[f"{name}_night"] = [*attributes[name], "LAI"]
    lines = ",\n".join(f" {json.dumps(k)}: {json.dumps(v)}" for k, v in table.items())
    write_atomic(root / "attributes.json", "{\n" + lines + "\n}\n")
    write_atomic(root / "benchmark.json", json.dumps(settings, indent=1) + "\n")
    shutil.rmtree(root / UNFINISHED, ignore_errors=True)
    return root
