"""Target cut-outs from labelled video: `dadiff-eval cutouts`.

The library's target cut-outs are animals, fruit, tools and vehicles with two people among them, and on real
people at night the tracker's box is wrong in a way the generated scenes never show (docs/lab-notebook.md, "Real
footage"). A labelled sequence (what `dadiff-eval pseudo-label` or `video` writes) gives a box per frame;
GrabCut (OpenCV), started from that box with a margin of the frame around it, separates the person from the
background (outside the box is background by construction). A cut is kept only when it looks like one
whole target: its largest connected part fills `FILL` of the box (less: a loose box or a faint target;
more: the box's background taken in) and spans most of its height and width (less: a part cut off, by an
occluder or a shadow). Kept cuts are written as BGRA PNGs cropped to
the part's bounds, with a soft one-pixel edge, and listed in `index.json`; the scene generator and training
use them as targets (`cutout_images`). The split is by sequence (a stable hash, as the library's), so one
person's frames never sit in both splits.
"""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..user_files import read_user_text
from .datasets import Dataset, read_frame
from .library import LibraryError, LibraryImage, split_of

FORMAT = 1
MARGIN = 0.5  # of the box's side, on each side: the background GrabCut learns from
FILL = (0.25, 0.85)  # share of the box the kept part covers
SPAN = (0.85, 0.5)  # the kept part's height and width, at least this share of the box's
ITERATIONS = 5


@dataclass(frozen=True)
class CutSettings:
    """Which frames to cut: every `every`-th frame of a sequence whose box is at least `min_height` px tall."""

    every: int = 8
    min_height: float = 48.0


def cut_out(frame: np.ndarray, box: Sequence[float], seed: int = 0) -> tuple[np.ndarray | None, str]:
    """The target inside `box` (x, y, w, h) as a BGRA image cropped to its bounds, or None and why not."""
    x, y, w, h = (float(v) for v in box)
    height, width = frame.shape[:2]
    x0, y0 = max(0, int(x - MARGIN * w)), max(0, int(y - MARGIN * h))
    x1, y1 = min(width, int(np.ceil(x + w + MARGIN * w))), min(height, int(np.ceil(y + h + MARGIN * h)))
    rect = (int(round(x)) - x0, int(round(y)) - y0, int(round(w)), int(round(h)))
    if rect[0] < 1 or rect[1] < 1 or rect[0] + rect[2] >= x1 - x0 or rect[1] + rect[3] >= y1 - y0:
        return None, "box at the frame's edge"
    roi = np.ascontiguousarray(frame[y0:y1, x0:x1])
    mask = np.zeros(roi.shape[:2], np.uint8)
    cv2.setRNGSeed(seed)  # GrabCut's k-means start draws from OpenCV's generator
    cv2.grabCut(roi, mask, rect, np.zeros((1, 65)), np.zeros((1, 65)), ITERATIONS, cv2.GC_INIT_WITH_RECT)
    fg = ((mask == cv2.GC_FGD) | (mask == cv2.GC_PR_FGD)).astype(np.uint8)
    fg = cv2.morphologyEx(fg, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    count, labels, stats, _ = cv2.connectedComponentsWithStats(fg, connectivity=8)
    if count < 2:
        return None, "nothing separated"
    part = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    px, py, pw, ph, area = (int(v) for v in stats[part])
    reason = _judge(rect, (px, py, pw, ph), area)
    if reason:
        return None, reason
    alpha = cv2.GaussianBlur((labels == part).astype(np.float32), (3, 3), 0.7)
    bgra = np.dstack([roi, np.round(alpha * 255).astype(np.uint8)])
    return bgra[py:py + ph, px:px + pw].copy(), ""


def _judge(rect: tuple[int, int, int, int], part: tuple[int, int, int, int], area: int) -> str:
    """Why a separated part is not one whole target, or '' when it is."""
    _, _, rw, rh = rect
    _, _, pw, ph = part
    fill = area / float(rw * rh)
    if not FILL[0] <= fill <= FILL[1]:
        return "fills too little of the box" if fill < FILL[0] else "fills too much of the box"
    if ph < SPAN[0] * rh or pw < SPAN[1] * rw:
        return "only part of the target"
    return ""


def write_cutouts(
    dataset: Dataset,
    out: Path,
    licence: str,
    settings: CutSettings = CutSettings(),
    log: Callable[[str], None] = print,
) -> dict:
    """Cut every chosen frame's target out of `dataset`'s sequences into `out` (PNGs and index.json); returns
    the index. Refuses a non-empty `out` that is not a cut-out folder, so nothing else is overwritten."""
    out = Path(out).expanduser()
    if out.exists() and any(out.iterdir()) and not (out / "index.json").is_file():
        raise LibraryError(f"{out} is not empty and holds no cut-out index; give a new or empty folder")
    out.mkdir(parents=True, exist_ok=True)
    _remove_listed(out)  # an earlier run's cut-outs: this run's index is the folder's whole content
    records, rejected = [], Counter()
    for seq in dataset.sequences:
        split = split_of(f"cutouts:{dataset.name}", seq.name)
        kept = 0
        for k in range(0, len(seq.frames), settings.every):
            box = seq.boxes[k]
            if not (np.isfinite(box).all() and box[3] >= settings.min_height and box[2] > 1):
                rejected["too small or unlabelled"] += 1
                continue
            image, reason = cut_out(read_frame(seq.frames[k]), box, seed=k)
            if image is None:
                rejected[reason] += 1
                continue
            name = f"{seq.name}-{k:04d}.png"
            if not cv2.imwrite(str(out / name), image):
                raise LibraryError(f"cannot write {out / name}")
            records.append({"file": name, "sequence": seq.name, "frame": k, "split": split,
                            "width": int(image.shape[1]), "height": int(image.shape[0])})
            kept += 1
        log(f"{seq.name}: {kept} cut-outs ({split})")
    index = {"format": FORMAT, "dataset": str(dataset.path), "licence": licence,
             "rejected": dict(sorted(rejected.items())), "cutouts": records}
    (out / "index.json").write_text(json.dumps(index, indent=1, sort_keys=True) + "\n")
    return index


def _remove_listed(folder: Path) -> None:
    """Delete the PNGs an earlier index in `folder` lists (and that index), nothing else."""
    try:
        listed = [item["file"] for item in json.loads((folder / "index.json").read_text())["cutouts"]]
    except (OSError, ValueError, KeyError, TypeError, RecursionError):
        return
    for name in listed:
        if isinstance(name, str) and "/" not in name and name.endswith(".png"):
            (folder / name).unlink(missing_ok=True)
    (folder / "index.json").unlink(missing_ok=True)


def cutout_images(folder: str | Path, split: str) -> list[LibraryImage]:
    """The cut-outs of `split` in a folder `write_cutouts` made, as library target images (the scene
    generator reads them as it reads the library's). LibraryError naming the folder when it holds none."""
    folder = Path(folder).expanduser()
    index = folder / "index.json"
    try:
        meta = json.loads(read_user_text(index, encoding="utf-8"))
        images = [
            LibraryImage(path=folder / item["file"], package=f"cutouts:{folder.name}", source=item["file"],
                         role="target", split=item["split"], licence=meta["licence"],
                         width=int(item["width"]), height=int(item["height"]))
            for item in meta["cutouts"]
        ]
    except FileNotFoundError:
        raise LibraryError(f"{index}: no cut-out index here (make one with dadiff-eval cutouts)") from None
    except OSError as exc:
        raise LibraryError(f"{index}: cannot read ({exc.strerror or exc})") from None
    except (ValueError, KeyError, TypeError, RecursionError) as exc:
        raise LibraryError(f"{index}: not a valid cut-out index ({exc})") from None
    chosen = [i for i in images if i.split == split]
    if not chosen:
        raise LibraryError(f"{folder}: no cut-outs in split '{split}'")
    return chosen


class CutoutTargets:
    """A scene library whose targets are one cut-out folder's and whose backgrounds are `library`'s: what
    `random_library_scene` reads, so scenes over real photos get these targets (training's `cutouts`,
    `dadiff-eval generate --cutouts`)."""

    def __init__(self, library, folder: str | Path) -> None:
        self.library, self.folder = library, Path(folder).expanduser()
        self._targets: dict[str, list[LibraryImage]] = {}  # per split: the index is read once, not per scene

    def images(self, role: str, split: str) -> list[LibraryImage]:
        if role != "target":
            return self.library.images(role, split)
        if split not in self._targets:
            self._targets[split] = cutout_images(self.folder, split)
        return list(self._targets[split])

    def licences(self) -> dict[str, str]:
        return self.library.licences()

