"""Sequences from any video, moving camera included: a detector's per-frame boxes linked into tracks.

Background subtraction (`fixed_camera`) needs a camera that does not move; footage from a moving vehicle or a
drone does not have one. There, a detector (run once, offline, by whatever tool the user has) boxes the people or
vehicles in every frame, and this module links the boxes into pseudo-labelled tracks: a box continues a track
when it overlaps the track's last box clearly and no other box nearly as much (two people that could be this one
end the track instead of swapping it), short misses are bridged by interpolation, a scene cut ends every track,
and the boxes are smoothed over a few frames, since a detector's boxes jitter more than a target moves.

Detections are read in the MOTChallenge `det.txt` layout, which most detection tools can write:
`frame,id,x,y,w,h,score[,...]` per line, frames counted from 1, the id ignored.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from ..user_files import read_user_text
from .fixed_camera import Track, check_new_folder, read_video, video_info, write_tracks
from .geometry import iou_with_each
from .scene_error import SceneError

CUT_SIZE = (80, 45)  # frames are compared at this size to find scene cuts


@dataclass(frozen=True)
class LinkSettings:
    """How detections become tracks; the defaults suit people 24 px tall and up in a 640 x 360 video."""

    min_score: float = 0.35  # a detection below this is ignored
    start_score: float = 0.5  # a track starts only on a detection this sure ...
    start_clear_iou: float = 0.2  # ... overlapping no open track's last box by more than this
    min_iou: float = 0.4  # a detection continues a track when it overlaps its last box this much...
    ambiguous_iou: float = 0.3  # ... and no other detection overlaps it this much (else the track ends)
    max_gap: int = 8  # frames a track may miss before it ends (the gap is interpolated)
    min_frames: int = 30  # shortest sequence kept
    max_frames: int = 150  # a longer track is cut here
    min_height: float = 24.0  # px: smaller targets are too far to label reliably
    min_aspect: float = 1.2  # height over width a detection must reach (people stand upright) ...
    max_aspect: float = 5.0  # ... and not exceed (a sliver is a pole or a part of someone)
    nms_iou: float = 0.5  # overlapping detections of one frame (a detector run on tiles) are merged above this
    smoothing: int = 5  # frames the centre and log-size are averaged over (an even number counts one more; 1: none)
    cut_threshold: float = 25.0  # mean grey-level change between frames that counts as a scene cut


def read_detections(path: str | Path, frames: int, settings: LinkSettings = LinkSettings()) -> list[np.ndarray]:
    """Per video frame, the (x, y, w, h, score) rows of a MOTChallenge `det.txt`, kept when sure, tall and
    upright enough per `settings`, and merged by non-maximum suppression."""
    path = Path(path).expanduser()
    if not path.is_file():
        raise SceneError(f"{path}: no such detections file")
    rows: list[list[float]] = [[] for _ in range(frames)]
    for number, line in enumerate(read_user_text(path, errors="replace").splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        fields = line.replace(" ", "").split(",")
        try:
            values = [float(v) for v in fields[:7]]
        except ValueError:
            values = []
        if len(values) < 7 or not all(math.isfinite(v) for v in values):
            raise SceneError(f"{path}:{number}: expected frame,id,x,y,w,h,score numbers, got {line.strip()[:60]!r}")
        frame, _, x, y, w, h, score = values
        if frame != int(frame) or not 1 <= frame <= frames:
            raise SceneError(f"{path}:{number}: frame {frame:g} is outside the video's 1-{frames}")
        if w <= 0 or h <= 0:
            raise SceneError(f"{path}:{number}: box width and height must be positive, got {w:g} x {h:g}")
        if score >= settings.min_score and h >= settings.min_height and \
                settings.min_aspect <= h / w <= settings.max_aspect:
            rows[int(frame) - 1].append([x, y, w, h, score])
    return [non_maximum_suppression(np.array(r, np.float64).reshape(-1, 5), settings.nms_iou) for r in rows]


def non_maximum_suppression(rows: np.ndarray, threshold: float) -> np.ndarray:
    """The rows (x, y, w, h, score) not overlapping a surer one by more than `threshold` IoU, surest first."""
    kept: list[np.ndarray] = []
    for row in rows[np.argsort(-rows[:, 4], kind="stable")]:
        if not kept or iou_with_each(row[:4], np.array(kept)[:, :4]).max() <= threshold:
            kept.append(row)
    return np.array(kept, np.float64).reshape(-1, 5)


def scene_cuts(frames: list[np.ndarray], threshold: float) -> list[bool]:
    """Per frame, whether the picture changed wholesale from the one before (an edit, not motion)."""
    small = [cv2.resize(cv2.cvtColor(f, cv2.COLOR_BGR2GRAY), CUT_SIZE).astype(np.float32) for f in frames]
    return [False] + [float(np.mean(np.abs(b - a))) > threshold for a, b in zip(small, small[1:], strict=False)]


@dataclass(eq=False)
class _Open:
    """A track being built: its detections by frame (tracks compare by identity)."""

    boxes: dict[int, np.ndarray]
    last: int
    ended: bool = False


def link(detections: list[np.ndarray], cuts: list[bool], settings: LinkSettings = LinkSettings()) -> list[Track]:
    """Tracks of at least min_frames from per-frame detections, in order of first frame: gaps interpolated,
    boxes smoothed, each cut at max_frames."""
    active: list[_Open] = []
    done: list[_Open] = []
    for t, rows in enumerate(detections):
        if cuts[t]:
            done += active
            active = []
        used: set[int] = set()
        for track in active:
            overlap = iou_with_each(track.boxes[track.last], rows[:, :4]) if len(rows) else np.zeros(0)
            order = np.argsort(-overlap, kind="stable")
            second = overlap[order[1]] if len(order) > 1 else 0.0
            if second >= settings.ambiguous_iou:
                track.ended = True  # two people could be this one: better no label than a swapped one
            elif len(order) and overlap[order[0]] >= settings.min_iou and int(order[0]) not in used:
                used.add(int(order[0]))
                track.boxes[t], track.last = rows[order[0], :4], t
        finished = [k for k in active if k.ended or t - k.last > settings.max_gap]
        done += finished
        active = [k for k in active if k not in finished]
        for j, row in enumerate(rows):
            taken = any(iou_with_each(k.boxes[k.last], row[None, :4])[0] > settings.start_clear_iou for k in active)
            if j not in used and row[4] >= settings.start_score and not taken:
                active.append(_Open({t: row[:4]}, t))
    done += active
    tracks = [_finish(k, settings) for k in done if k.last - min(k.boxes) + 1 >= settings.min_frames]
    return sorted(tracks, key=lambda track: track.start)


def _finish(track: _Open, settings: LinkSettings) -> Track:
    """The track's boxes on every frame from its first detection to its last (at most max_frames): centre and
    log-size interpolated over misses, then averaged over `smoothing` frames centred on each."""
    frames = sorted(track.boxes)
    boxes = np.array([track.boxes[t] for t in frames])
    state = np.c_[boxes[:, :2] + boxes[:, 2:] / 2, np.log(boxes[:, 2:])]
    span = np.arange(frames[0], min(frames[-1] + 1, frames[0] + settings.max_frames))
    state = np.stack([np.interp(span, frames, state[:, i]) for i in range(4)], axis=1)
    return Track(int(span[0]), _boxes(_smooth(state, settings.smoothing // 2)))


def _smooth(state: np.ndarray, half: int) -> np.ndarray:
    """Each row replaced by a straight line fitted to the 2 * half + 1 rows around it: the moving average inside
    the track, and near its ends a fit over the first (last) rows, so that the first box, the one a tracker
    starts from, is averaged too and a target moving steadily keeps its place there instead of lagging."""
    width = min(2 * half + 1, len(state))
    if width < 3:
        return state
    out = np.empty_like(state)
    for i in range(len(state)):
        first = min(max(i - half, 0), len(state) - width)
        rows = np.arange(first, first + width)
        slope, offset = np.polyfit(rows, state[rows], 1)
        out[i] = slope * i + offset
    return out


def _boxes(state: np.ndarray) -> np.ndarray:
    """(x, y, w, h) boxes from rows of (centre x, centre y, log w, log h)."""
    size = np.exp(state[:, 2:])
    return np.c_[state[:, :2] - size / 2, size]


def write_detection_benchmark(video: str | Path, detections: str | Path, out: str | Path, seed: int = 0,
                              settings: LinkSettings = LinkSettings(), night: str = "real") -> list[Track]:
    """Link `detections` of `video` into tracks and write them as `<out>/vidNNN_day` and `_night` sequences
    (OTB layout, as `dadiff-eval video` does; `night`: fixed_camera.NIGHT_MODELS). Returns the tracks written."""
    out = Path(out).expanduser()
    check_new_folder(out)
    frames = read_video(video)
    boxes = read_detections(detections, len(frames), settings)
    tracks = link(boxes, scene_cuts(frames, settings.cut_threshold), settings)
    if not tracks:
        found = sum(len(b) for b in boxes)
        raise SceneError(f"{detections}: {found} usable detections link into no track of {settings.min_frames} "
                         "frames (try a lower --min-frames or --min-score)")
    info = {"generator": "dadiff.runtime.datamaking.detection_tracks", **video_info(video),
            "detections": str(detections), "settings": asdict(settings)}
    write_tracks(frames, tracks, out, seed, info, night)
    return tracks
