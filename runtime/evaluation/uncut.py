"""Uncut clips: one person followed from a start box to the end of a real video, crossings and exit included.

The fixed-camera benchmark (`fixed_camera`) cuts a sequence where its person meets another, so it never
tests what a follow-me drone meets most: a look-alike crossing, the target leaving the view. Here each clip
runs from its start frame to the video's last frame and its truth says, per frame, one of three things: a
box (the person is in view), unknown (even by eye it cannot be told who is who; a NaN row, skipped as
`anatomy` skips it) or absent (the person has left the view: a NaN row with a 1 in `absence.label`, GOT-10k's
name for the same mark). A tracker that reports `tracking` on an absent frame is confidently on something
else, so absent frames count as off the target.

A truth folder (`docs/vtest-uncut/` for OpenCV's `vtest.avi`) holds `clips.json` ({clip: {"first_frame": N,
...}}, N counted from 0) and per clip `<clip>/groundtruth_rect.txt` (one row per video frame from N to the
end) and `<clip>/absence.label`. `write_uncut_clips` adds the video's frames, so that `dadiff-eval run` runs
any tracker on them as on any OTB-layout set, and `uncut_scores` scores its result and `.states` files.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..datamaking.datasets import Dataset, DatasetError, read_boxes, read_text
from ..datamaking.fixed_camera import check_new_folder, night_sequence, read_video
from ..datamaking.scene_error import SceneError
from ..datamaking.scenes import write_frame
from .anatomy import centred_frames, known_frames
from .evaluate import EvalError, read_results, read_states
from .metrics import PRECISION_INDEX, SequenceCurves

ABSENCE = "absence.label"  # one 0/1 line per frame: 1 where the target is out of view (GOT-10k's file name)
CLIPS = "clips.json"
TRUTH = "groundtruth_rect.txt"
FRAMES = "_frames"  # the video's frames, written once; each clip's img/ links to its part


def read_absence(path: Path, frames: int) -> np.ndarray:
    """`absence.label` as a bool array of `frames` flags (0 or 1 per line)."""
    lines = [line.strip() for line in read_text(path).splitlines() if line.strip()]
    if any(line not in ("0", "1") for line in lines):
        bad = next(n for n, line in enumerate(lines, 1) if line not in ("0", "1"))
        raise DatasetError(f"{path}: line {bad}: expected 0 or 1, got {lines[bad - 1]!r}")
    if len(lines) != frames:
        raise DatasetError(f"{path}: {len(lines)} flags for {frames} frames")
    return np.array([line == "1" for line in lines])


def read_truth(folder: Path) -> dict[str, tuple[int, np.ndarray, np.ndarray]]:
    """{clip: (first video frame, boxes, absent)} of a truth folder; absent rows must be NaN rows."""
    folder = Path(folder).expanduser()
    try:
        clips = json.loads(read_text(folder / CLIPS))
    except ValueError as exc:
        raise DatasetError(f"{folder / CLIPS}: not readable JSON ({exc})") from None
    if not isinstance(clips, dict) or not clips:
        raise DatasetError(f"{folder / CLIPS}: expected {{clip: {{\"first_frame\": N, ...}}}}")
    out = {}
    for name, info in clips.items():
        if not name or name in (".", "..") or "/" in name or "\\" in name or name == FRAMES:
            raise DatasetError(f"{folder / CLIPS}: clip name {name!r} is not a plain folder name")
        first = info.get("first_frame") if isinstance(info, dict) else None
        if not isinstance(first, int) or first < 0:
            raise DatasetError(f"{folder / CLIPS}: clip {name!r} needs a first_frame >= 0")
        boxes = read_boxes(folder / name / TRUTH)
        absent = read_absence(folder / name / ABSENCE, len(boxes))
        if np.isfinite(boxes[absent]).any():
            raise DatasetError(f"{folder / name / TRUTH}: a box on a frame marked absent in {ABSENCE}")
        if not known_frames(boxes[:1])[0]:
            raise DatasetError(f"{folder / name / TRUTH}: the first row (the start box) is not a box")
        out[name] = (first, boxes, absent)
    return out


def _link(source: Path, target: Path) -> None:
    """A hard link (the clips share the video's frames), a copy where the file system has none."""
    try:
        os.link(source, target)
    except OSError:
        shutil.copyfile(source, target)


def write_uncut_clips(video: str | Path, truth: str | Path, out: str | Path, night_seed: int | None = None) -> int:
    """Each clip of `truth` as `<out>/<clip>/` (OTB layout: img/ from its first frame to the video's end,
    groundtruth_rect.txt, absence.label), the video's frames in `<out>/_frames/`; with `night_seed`, the frames
    at night (`fixed_camera`'s night: one camera and fixed lights for the whole video). Returns the frames."""
    out = Path(out).expanduser()
    clips = read_truth(Path(truth))
    check_new_folder(out)
    frames = read_video(video)
    for name, (first, boxes, _) in clips.items():
        if first + len(boxes) != len(frames):
            raise SceneError(f"{truth}: clip {name} has {len(boxes)} rows from frame {first}, but {video} has "
                             f"{len(frames)} frames (not the video the truth was made for?)")
    if night_seed is not None:
        frames = night_sequence(frames, np.random.default_rng([night_seed]), [night_seed, 1_000_003])
    (out / FRAMES).mkdir(parents=True)
    for i, frame in enumerate(frames):
        write_frame(out / FRAMES, i, frame)
    for name, (first, _, _) in clips.items():
        (out / name / "img").mkdir(parents=True)
        for i in range(first, len(frames)):
            _link(out / FRAMES / f"{i + 1:04d}.jpg", out / name / "img" / f"{i - first + 1:04d}.jpg")
        for file in (TRUTH, ABSENCE):
            shutil.copyfile(Path(truth) / name / file, out / name / file)
    return len(frames)


@dataclass(frozen=True)
class UncutScores:
    """One tracker on one clip (or pooled): frames after the first, in view and absent (unknown left out).

    `success` and `precision` (at 20 px) over the frames in view; `tracking_off`: of the frames in view or
    absent, the share reported 'tracking' while the box's centre is not on the person (`anatomy`'s centred
    test) or the person is absent; `tracking_absent`: the part of it on absent frames; `tracking_on`: of the
    frames in view with the box's centre on the person, the share reported 'tracking' (what a rule that
    withholds 'tracking' costs)."""

    clip: str
    in_view: int
    absent: int
    success: float
    precision: float
    tracking_off: float
    tracking_absent: float
    tracking_on: float


def _clip_frames(gt: np.ndarray, pred: np.ndarray, absent: np.ndarray, states: Sequence[str]) -> dict:
    """Per-frame masks of one clip, frames 2..N (frame 1 is the given box)."""
    seen = known_frames(gt)[1:]
    gone = absent[1:] & ~seen
    tracking = (np.asarray(states) == "tracking")[1:]
    off = ~centred_frames(gt, pred)[1:] | gone
    return {"gt": gt[1:][seen], "pred": pred[1:][seen], "seen": seen, "gone": gone,
            "wrong": tracking & off & (seen | gone), "wrong_gone": tracking & gone,
            "on": ~off & seen, "right": tracking & ~off & seen}


def _scores(clip: str, parts: Sequence[dict]) -> UncutScores:
    gt = np.concatenate([p["gt"] for p in parts])
    pred = np.concatenate([p["pred"] for p in parts])
    curves = SequenceCurves.from_boxes(gt, pred) if len(gt) else None
    count = sum(int(p["seen"].sum() + p["gone"].sum()) for p in parts)
    wrong = sum(int(p["wrong"].sum()) for p in parts)
    wrong_gone = sum(int(p["wrong_gone"].sum()) for p in parts)
    share = (lambda n: n / count) if count else (lambda n: float("nan"))
    on = sum(int(p["on"].sum()) for p in parts)
    right = sum(int(p["right"].sum()) for p in parts)
    return UncutScores(clip, len(gt), sum(int(p["gone"].sum()) for p in parts),
                       float(curves.success.mean()) if curves else float("nan"),
                       float(curves.precision[PRECISION_INDEX]) if curves else float("nan"),
                       share(wrong), share(wrong_gone), right / on if on else float("nan"))


def clip_absence(dataset: Dataset) -> dict[str, np.ndarray]:
    """`absence.label` of every sequence of an OTB-layout `dataset` (all False where a folder has none)."""
    out = {}
    for seq in dataset.sequences:
        path = Path(dataset.path) / seq.name / ABSENCE
        out[seq.name] = read_absence(path, len(seq)) if path.is_file() else np.zeros(len(seq), bool)
    return out


def uncut_scores(dataset: Dataset, folder: Path) -> list[UncutScores]:
    """Per clip, then pooled over the frames of all clips ('all') and the mean of the clips' values ('mean': a
    long absence in one clip weighs no more than any clip), for the results and states in `folder`."""
    states = read_states(dataset, folder)
    if states is None:
        raise EvalError(f"{folder}: no .states files beside the results (run it with dadiff-eval run)")
    results, absence = read_results(dataset, folder), clip_absence(dataset)
    parts = {s.name: _clip_frames(s.boxes, results[s.name], absence[s.name], states[s.name])
             for s in dataset.sequences}
    clips = [_scores(name, [part]) for name, part in parts.items()]
    mean = UncutScores("mean", sum(c.in_view for c in clips), sum(c.absent for c in clips),
                       *(float(np.nanmean([getattr(c, key) for c in clips]))
                         for key in ("success", "precision", "tracking_off", "tracking_absent", "tracking_on")))
    return [*clips, _scores("all", list(parts.values())), mean]


def format_uncut(rows: dict[str, list[UncutScores]]) -> str:
    """One table, a row per tracker and clip: frames, success, precision and the wrong-lock shares."""
    width = max(8, *(len(name) for name in rows))
    lines = ["frames after the first; success and precision (20 px) over the frames in view; tracking-off: share "
             "of in-view + absent frames reported 'tracking' with the centre off the person or the person gone; "
             "tracking-on: share of the frames centred on the person reported 'tracking'",
             f"{'Tracker':<{width}}  {'clip':<8}  in view  absent  success  precision  tracking-off  (absent)  "
             "tracking-on"]
    for name, items in rows.items():
        lines += [f"{name:<{width}}  {r.clip:<8}  {r.in_view:7d}  {r.absent:6d}  {r.success:7.3f}  "
                  f"{r.precision:9.3f}  {r.tracking_off:11.1%}  {r.tracking_absent:8.1%}  {r.tracking_on:11.1%}"
                  for r in items]
    return "\n".join(lines)
