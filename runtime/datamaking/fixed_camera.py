"""A day and night benchmark from a real fixed-camera video: its moving targets labelled by background subtraction.

Public tracking sets cannot be downloaded here and the generated scenes paste cut-outs over photos; this turns
any video from a camera that does not move (OpenCV's own `vtest.avi`: people crossing a plaza seen from a raised
mast; a hovering drone's camera for a few seconds) into OTB-layout sequences with real pixels, real gait and real
look-alikes. A fixed camera sees the same background in every frame, so the median of the frames is the
background and what differs from it is what moves. A sequence follows one such foreground blob from a frame in
which it is seen alone until it merges with another, splits, changes size abruptly, stops being seen, or reaches
the frame's border, so every box is a mover seen whole and alone. Its night is the generated benchmark's "real"
night (`RealNight`), with the lights fixed in the image (the camera does not move) and the exposure locked on
the sequence's first frame; or, with `night="camera"`, the independent camera model's (camera_night.py).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from ..files import write_atomic
from ..frames import decode_video
from ..ort_cache import file_sha256
from .datasets import check_new_folder, list_frames
from .geometry import iou_with_each
from .night import NightLights, RealNight
from .scene_error import SceneError
from .scenes import write_boxes, write_frame

BACKGROUND_FRAMES = 60  # frames the median background is taken over (evenly spaced)


@dataclass(frozen=True)
class LabelSettings:
    """How movers are found and followed; the defaults suit people of 15-60 px in a 768 x 576 video."""

    threshold: int = 30  # grey-level difference from the background that counts as foreground
    min_area: int = 150  # px of a blob's box; smaller ones are noise or too far to track
    min_frames: int = 60  # shortest sequence kept
    max_frames: int = 150  # a longer track is cut here (the rest may start another sequence)
    border: int = 4  # px: a blob this close to the frame's edge is leaving or entering, not whole
    min_iou: float = 0.3  # a blob in the next frame continues the track when it overlaps this much...
    max_growth: float = 1.5  # ... and its box area changed by less than this factor (else merged or split)
    max_height_change: float = 1.2  # per frame: a mover's height is steady; one in front or behind changes it
    min_aspect: float = 0.0  # height over width every box must reach: 1.8 keeps lone upright people, not groups


@dataclass(frozen=True)
class Track:
    """One labelled mover: its first frame in the video and its boxes (x, y, w, h) from there on."""

    start: int
    boxes: np.ndarray

    def box_at(self, frame: int) -> np.ndarray | None:
        i = frame - self.start
        return self.boxes[i] if 0 <= i < len(self.boxes) else None


def read_video(path: str | Path, max_frames: int | None = None) -> list[np.ndarray]:
    """All frames (BGR uint8) of a video file, or of a folder of images in name order."""
    path = Path(path).expanduser()
    if path.is_dir():
        frames = [cv2.imread(str(p), cv2.IMREAD_COLOR) for p in list_frames(path)[:max_frames]]
        if any(f is None for f in frames):
            raise SceneError(f"{path}: an image in it cannot be read")
    else:
        if not path.is_file():
            raise SceneError(f"{path}: no such video file or image folder")
        frames = decode_video(str(path), max_frames)
    if len(frames) < 2:
        raise SceneError(f"{path}: not a readable video ({len(frames)} frames decoded)")
    if any(f.shape != frames[0].shape for f in frames):
        raise SceneError(f"{path}: frames change size within the video")
    return frames


def background(greys: list[np.ndarray]) -> np.ndarray:
    """The median of up to BACKGROUND_FRAMES evenly spaced frames: what a fixed camera sees behind the movers."""
    picks = np.linspace(0, len(greys) - 1, min(len(greys), BACKGROUND_FRAMES)).round().astype(int)
    return np.median(np.stack([greys[i] for i in picks]), axis=0).astype(np.uint8)


def foreground_boxes(grey: np.ndarray, back: np.ndarray, settings: LabelSettings) -> np.ndarray:
    """Boxes (x, y, w, h) of the blobs that differ from the background: thresholded, speckle removed, the
    parts of one mover (head, legs) joined by a closing taller than wide."""
    mask = (cv2.absdiff(grey, back) > settings.threshold).astype(np.uint8)
    mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3)))
    mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 9)))
    count, _, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    boxes = stats[1:count, :4].astype(np.float64)
    return boxes[boxes[:, 2] * boxes[:, 3] >= settings.min_area]


def _whole(box: np.ndarray, size: tuple[int, int], settings: LabelSettings) -> bool:
    """Inside the frame by `border` px and upright enough: a mover seen whole, not one entering or a group."""
    x, y, w, h = box
    border = settings.border
    inside = x >= border and y >= border and x + w <= size[0] - border and y + h <= size[1] - border
    return inside and h >= settings.min_aspect * w


def follow(blobs: list[np.ndarray], start: int, box: np.ndarray, size: tuple[int, int],
           settings: LabelSettings) -> np.ndarray:
    """The boxes of the mover `box` from frame `start` on, while exactly one blob continues it, whole and with a
    plausible change of size and height; stops at a merge, a split, a loss or the border, or after max_frames."""
    boxes = [box]
    for t in range(start + 1, min(len(blobs), start + settings.max_frames)):
        overlap = iou_with_each(boxes[-1], blobs[t]) if len(blobs[t]) else np.zeros(0)
        following = np.flatnonzero(overlap > settings.min_iou)
        if len(following) != 1:
            break
        nxt = blobs[t][following[0]]
        growth = (nxt[2] * nxt[3]) / (boxes[-1][2] * boxes[-1][3])
        stretch = nxt[3] / boxes[-1][3]
        if not 1 / settings.max_growth < growth < settings.max_growth or not _whole(nxt, size, settings):
            break
        if not 1 / settings.max_height_change < stretch < settings.max_height_change:
            break
        if np.count_nonzero(iou_with_each(nxt, blobs[t]) > settings.min_iou) != 1:
            break  # another blob also touches the one that continues the track: they are about to merge
        boxes.append(nxt)
    return np.array(boxes)


def label_tracks(frames: list[np.ndarray], settings: LabelSettings = LabelSettings()) -> list[Track]:
    """Every mover seen whole and alone for at least min_frames, in order of first frame; a mover already in a
    kept track is not started again while that track lasts."""
    greys = [cv2.cvtColor(f, cv2.COLOR_BGR2GRAY) for f in frames]
    back = background(greys)
    blobs = [foreground_boxes(g, back, settings) for g in greys]
    size = (frames[0].shape[1], frames[0].shape[0])
    tracks: list[Track] = []
    for start in range(len(frames) - settings.min_frames + 1):
        for box in blobs[start]:
            if not _whole(box, size, settings):
                continue
            if any((b := t.box_at(start)) is not None and iou_with_each(b, box[None])[0] > 0.5 for t in tracks):
                continue
            boxes = follow(blobs, start, box, size, settings)
            if len(boxes) >= settings.min_frames:
                tracks.append(Track(start, boxes))
    return tracks


def night_sequence(day: list[np.ndarray], rng: np.random.Generator, seed: list[int],
                   numbers: list[int] | None = None) -> list[np.ndarray]:
    """The frames at night: one night camera and street lights fixed in the image, exposure locked on the
    first frame; `numbers`: each frame's number in its sequence, where moving lights have got to (default
    0, 1, 2, ...; training passes a pair's two frame numbers)."""
    height, width = day[0].shape[:2]
    camera = RealNight.random(rng)
    lights = NightLights.random(rng, camera.kind, width, height)
    numbers = list(range(len(day))) if numbers is None else numbers
    gain = camera.exposure(day[0], lights.at(None, numbers[0], width, height))
    return [camera.apply(frame, np.random.default_rng([*seed, i]), lights.at(None, n, width, height), gain=gain)
            for i, (frame, n) in enumerate(zip(day, numbers, strict=True))]


# the generator's "real" night, or one of two night models written apart from it and from each other: the camera
# model (camera_night.py) and the sensor model (sensor_night.py; written by someone who had read neither, so it
# stays independent of a training that renders with the other two)
INDEPENDENT_NIGHTS = ("camera", "sensor")
NIGHT_MODELS = ("real", *INDEPENDENT_NIGHTS)


def independent_night(model: str):
    """The `render_night(day, seed) -> (frames, record)` of an independent night model by its name."""
    if model == "camera":
        from .camera_night import render_night
    elif model == "sensor":
        from .sensor_night import render_night
    else:
        raise ValueError(f"unknown independent night model {model!r}; expected one of {', '.join(INDEPENDENT_NIGHTS)}")
    return render_night


def write_tracks(frames: list[np.ndarray], tracks: list[Track], out: Path, seed: int, info: dict,
                 night: str = "real") -> None:
    """Each track as `<out>/vidNNN_day` and `_night` (OTB layout) with `attributes.json`, and `info` with the
    sequences' video frames as `benchmark.json`; `night`: which night model renders the nights (NIGHT_MODELS);
    an independent model's settings for each sequence are recorded under `night_cameras`."""
    table, cameras = {}, {}
    for k, track in enumerate(tracks):
        name = f"vid{k + 1:03d}"
        day = frames[track.start:track.start + len(track.boxes)]
        if night in INDEPENDENT_NIGHTS:  # they share no code with night.py
            dark, cameras[f"{name}_night"] = independent_night(night)(day, [seed, k])
        else:
            dark = night_sequence(day, np.random.default_rng([seed, k]), [seed, k, 1_000_003])
        for kind, images in (("day", day), ("night", dark)):
            folder = out / f"{name}_{kind}"
            (folder / "img").mkdir(parents=True)
            for i, image in enumerate(images):
                write_frame(folder / "img", i, image)
            write_boxes(folder / "groundtruth_rect.txt", track.boxes)
        table[f"{name}_day"], table[f"{name}_night"] = [], ["LAI"]
    write_atomic(out / "attributes.json", json.dumps(table, indent=1) + "\n")
    info = {**info, "seed": seed, "night": night,
            "sequences": [{"name": f"vid{k + 1:03d}", "video_frames": [t.start + 1, t.start + len(t.boxes)]}
                          for k, t in enumerate(tracks)]}
    if cameras:
        info["night_cameras"] = cameras
    write_atomic(out / "benchmark.json", json.dumps(info, indent=1) + "\n")


def video_info(video: str | Path) -> dict:
    """Where a benchmark's frames came from: the video's path and, for a file, its SHA-256."""
    return {"video": str(video), "video_sha256": file_sha256(Path(video)) if Path(video).is_file() else None}


def write_fixed_camera_benchmark(video: str | Path, out: str | Path, seed: int = 0,
                                 settings: LabelSettings = LabelSettings(), max_sequences: int | None = None,
                                 max_video_frames: int | None = None, night: str = "real") -> list[Track]:
    """Label `video`'s movers and write them as `<out>/vidNNN_day` and `_night` sequences (OTB layout), with
    `attributes.json` and `benchmark.json`; `night` as in `write_tracks`. Returns the tracks written."""
    out = Path(out).expanduser()
    check_new_folder(out)
    frames = read_video(video, max_video_frames)
    if len(frames) < settings.min_frames:
        raise SceneError(f"{video}: {len(frames)} frames, fewer than the {settings.min_frames} of one sequence")
    tracks = label_tracks(frames, settings)[:max_sequences]
    if not tracks:
        raise SceneError(f"{video}: no mover seen whole and alone for {settings.min_frames} frames (is the camera "
                         "fixed? try a lower --min-frames)")
    info = {"generator": "dadiff.runtime.datamaking.fixed_camera", **video_info(video), "settings": asdict(settings)}
    write_tracks(frames, tracks, out, seed, info, night)
    return tracks
