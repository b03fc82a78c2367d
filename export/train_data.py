"""Training pairs for the Siamese tracker: labelled day pairs, their night versions, and BAN targets.

Day sources give (template frame, template box, search frame, search box): generated scenes from the
training split of photographs, GOT-10k / OTB-style sequence folders, or plain image folders (both crops cut
from one image). Night images come from a night renderer (the generator's, or the independent camera model;
the same content by night, which also pairs day and night features for L_align) or from unlabelled night
image folders / videos. Everything is produced on the fly, so nothing needs to fit in memory.
"""

from __future__ import annotations

import fnmatch
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from torch.utils.data import IterableDataset, get_worker_info

from dadiff.runtime.crop import context_side, crop_side, mean_colour, subwindow
from dadiff.runtime.datamaking.datasets import DatasetError, list_frames, plural, read_boxes, warn

from .train_check import CAMERA_NIGHT, DAY_KINDS

IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".png", ".bmp")


@dataclass(frozen=True)
class CropConfig:
    exemplar: int = 127
    instance: int = 255
    context: float = 0.5
    stride: int = 8
    score_size: int = 25
    template_shift: float = 4.0      # SiamBAN: template shift 4, scale 0.05
    template_scale: float = 0.05
    search_shift: float = 64.0       # search shift 64, scale 0.18, blur 0.2
    search_scale: float = 0.18
    blur: float = 0.2
    grey: float = 0.2
    colour: float = 1.0

    @property
    def origin(self) -> float:
        return -(self.score_size // 2) * self.stride


def box_centre(box: np.ndarray) -> tuple[float, float]:
    """Pixel-index centre of an (x, y, w, h) box, the tracker's convention (spec 8.1)."""
    return float(box[0] + (box[2] - 1) / 2), float(box[1] + (box[3] - 1) / 2)


@dataclass(frozen=True)
class CropWindow:
    centre: tuple[float, float]
    side: int
    out: int
    rel: np.ndarray  # the box (cx, cy, w, h) relative to the crop centre in crop pixels (the decoder's frame)

    def cut(self, frame: np.ndarray) -> np.ndarray:
        return subwindow(frame, self.centre, self.out, self.side, mean_colour(frame))


def jittered_window(box: np.ndarray, out: int, cfg: CropConfig, shift: float, scale: float,
                    rng: np.random.Generator) -> CropWindow:
    """The tracker's context crop around the box, randomly shifted (crop pixels) and rescaled."""
    cx, cy = box_centre(box)
    s = context_side(box[2], box[3], cfg.context) * out / cfg.exemplar
    side = crop_side(s * math.exp(rng.uniform(-scale, scale)))
    k = out / side
    dx, dy = rng.uniform(-shift, shift, size=2) / k
    centre = (cx + dx, cy + dy)
    rel = np.array([(cx - centre[0]) * k, (cy - centre[1]) * k, box[2] * k, box[3] * k], dtype=np.float32)
    return CropWindow(centre, side, out, rel)


def augment(crop: np.ndarray, cfg: CropConfig, rng: np.random.Generator, grey: bool, blur: bool) -> np.ndarray:
    img = crop.astype(np.float32)
    if cfg.colour > 0:  # per-channel gain and an overall brightness change
        img *= rng.uniform(0.85, 1.15, size=3).astype(np.float32) * rng.uniform(0.8, 1.2)
    if blur:
        sigma = rng.uniform(0.5, 1.5)
        img = cv2.GaussianBlur(img, (0, 0), sigma)
    if grey:
        g = cv2.cvtColor(np.clip(img, 0, 255).astype(np.uint8), cv2.COLOR_BGR2GRAY)
        img = np.repeat(g[:, :, None], 3, axis=2).astype(np.float32)
    return np.clip(img, 0, 255)


def ban_targets(rel: np.ndarray, cfg: CropConfig) -> tuple[np.ndarray, np.ndarray]:
    """SiamBAN point targets: label 1 inside the (w/4, h/4) ellipse, 0 outside (w/2, h/2), -1 between;
    loc = (l, t, r, b) distances of each point to the box edges."""
    line = cfg.origin + cfg.stride * np.arange(cfg.score_size, dtype=np.float32)
    px, py = np.meshgrid(line, line)
    cx, cy, w, h = rel
    d_pos = ((px - cx) / (w / 4)) ** 2 + ((py - cy) / (h / 4)) ** 2
    d_neg = ((px - cx) / (w / 2)) ** 2 + ((py - cy) / (h / 2)) ** 2
    label = np.full(px.shape, -1, dtype=np.int64)
    label[d_neg > 1] = 0
    label[d_pos < 1] = 1
    if not (label == 1).any():  # tiny boxes: the nearest point is positive
        label[np.unravel_index(np.argmin(d_pos), d_pos.shape)] = 1
    x1, y1, x2, y2 = cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2
    loc = np.stack([px - x1, py - y1, x2 - px, y2 - py]).astype(np.float32)
    return label, loc


def to_chw(img: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1), dtype=np.float32))


# ---- day sources: each yields (template frame, template box, search frame, search box) -------------------


class SceneSource:
    """Pairs of frames from generated scenes: over scikit-image's training photos (`source` "skimage") or
    over the real-photo library's training split (`source` "library": cut-outs over aerial textures and
    photos, after `dadiff-eval data fetch`). `cutouts`: a folder `dadiff-eval cutouts` wrote, whose cut-outs
    are the library scenes' targets instead of the library's own (people cut out of labelled video)."""

    def __init__(self, split: str = "train", max_gap: int = 60, pairs_per_scene: int = 4,
                 source: str = "skimage", companions: float = 0.0, stretch: float = 0.0,
                 cutouts: str | Path | None = None) -> None:
        from dadiff.runtime.datamaking.library import LibraryError
        from dadiff.runtime.datamaking.library_scenes import library_images, open_scene_library
        from dadiff.runtime.datamaking.photos import load_photos
        from dadiff.runtime.datamaking.scenes import SceneError

        if source not in ("skimage", "library"):
            raise ValueError(f"unknown scene source {source!r}; expected skimage or library")
        for option, share in (("companions", companions), ("stretch", stretch)):
            if not 0 <= share <= 1 or (share and source != "library"):
                raise ValueError(f"{option} is {share}; expected a share 0-1 of library scenes")
        if cutouts is not None and source != "library":
            raise ValueError(f"cutouts is {str(cutouts)!r}; it needs source = \"library\" (their backgrounds)")
        try:
            self.photos = load_photos(split) if source == "skimage" else None
            self.library = open_scene_library() if source == "library" else None
            if cutouts is not None:
                from dadiff.runtime.datamaking.cutouts import CutoutTargets

                self.library = CutoutTargets(self.library, cutouts)
                library_images(self.library, split)  # no cut-out of this split: say so now, not mid-run
        except (SceneError, LibraryError) as exc:
            raise ValueError(str(exc)) from None
        self.split = split
        self.max_gap = max_gap
        self.pairs_per_scene = pairs_per_scene  # building a scene costs ~10x rendering one of its frames
        self.companions = companions  # share of library scenes with a look-alike walking beside the target
        self.stretch = stretch  # share of library scenes whose target is not rigid, often upright like a walker
        self._scene, self._uses = None, 0

    def _new_scene(self, rng: np.random.Generator):
        from dadiff.runtime.datamaking.library_scenes import random_library_scene
        from dadiff.runtime.datamaking.scene import Scene

        if self.library is not None:
            companion = self.companions > 0 and rng.random() < self.companions  # no draw at 0: same stream
            stretch = self.stretch > 0 and rng.random() < self.stretch
            return random_library_scene(rng, self.library, self.split, frames=self.max_gap + 1,
                                        companion=companion, stretch=stretch)
        return Scene.random(rng, self.photos, frames=self.max_gap + 1)

    def sample(self, rng: np.random.Generator):
        if self._scene is None or self._uses >= self.pairs_per_scene:
            self._scene, self._uses = self._new_scene(rng), 0
        scene = self._scene
        self._uses += 1
        i, j = sorted(rng.integers(0, self.max_gap + 1, size=2))
        (fi, bi), (fj, bj) = scene.render(int(i)), scene.render(int(j))
        self._pair = (scene, int(i), int(j))
        return fi, np.asarray(bi, np.float32), fj, np.asarray(bj, np.float32)

    def other(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """A frame and box of another scene (another target), for a negative pair; later pairs come from it."""
        self._scene = None
        _, _, frame, box = self.sample(rng)
        return frame, box

    def night_pair(self, fi: np.ndarray, fj: np.ndarray, rng: np.random.Generator,
                   style: str, path_lamps: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """The last sampled pair at night as the evaluation's sequences are: one night camera over the scene
        and its street lights fixed on the ground, so the pool the template was lit by is still there in the
        search frame, with or without the target in it. `path_lamps`: the share of pairs that also get 1-3
        lamp heads beside the target in the template or search frame (no draw at 0: the stream stays as it was)."""
        from dadiff.runtime.datamaking.scenes import SceneNight

        scene, i, j = self._pair
        night = SceneNight(scene, rng, style)
        if path_lamps > 0 and rng.random() < path_lamps:
            night.add_path_lamps(rng, (i, j), int(rng.integers(1, 4)))
        return night(fi, i, rng), night(fj, j, rng)


def _count_mismatch(frames: int, boxes: int) -> str:
    """Why a sequence's boxes cannot be paired with its frames by index, or "" when they can.

    Trimming to the shorter side would pair boxes with other frames: OTB labels David from frame 300 (471
    boxes for 770 frames), so frame 1 would get frame 300's box; the evaluation refuses such sequences too."""
    if frames == boxes:
        return ""
    counts = f"{plural(boxes, 'box', 'boxes')} for {plural(frames, 'frame')}"
    if not frames:
        return f"no image files, {plural(boxes, 'box', 'boxes')}"
    if boxes == 1:
        return f"only the first frame is labelled: {counts}"
    return counts


class SequenceSource:
    """Two frames of one sequence from GOT-10k (`groundtruth.txt`) or OTB/UAV123 (`groundtruth_rect.txt`,
    frames in `img/`) folders under a root; `match` keeps the folders whose name matches it (`*_day`: the day
    half of a benchmark that `dadiff-eval video` or `pseudo-label` wrote; training renders its own nights)."""

    FAR_WIDTH = (10.0, 30.0)  # px: the target's width in a shrunk pair, as vtest's people at their smallest

    def __init__(self, root: str | Path, max_gap: int = 100, match: str = "*", far: float = 0.0,
                 one_night: bool = False) -> None:
        if not 0.0 <= far <= 1.0:
            raise ValueError(f"far is {far}; expected a share 0-1 of pairs")
        self.far = far  # share of pairs whose frames are shrunk so the target is 10-30 px wide
        self.one_night = one_night  # night_pair: one camera and fixed lights over both frames
        self._gap = 0  # frames between the last sampled pair's two frames
        self.sequences = []
        left_out = []  # "name (why)" of each sequence whose boxes do not pair one to one with its frames
        for gt in sorted(Path(root).expanduser().rglob("groundtruth*.txt")):
            if not fnmatch.fnmatchcase(gt.parent.name, match):
                continue
            try:
                boxes = read_boxes(gt)
            except DatasetError:
                continue
            try:
                frames = list(list_frames(gt.parent))  # the evaluation's order: 1, 2, ..., 10 (not 1, 10, 2)
            except DatasetError:
                frames = []
            why = _count_mismatch(len(frames), len(boxes))
            if why:
                left_out.append(f"{gt.parent.name} ({why})")
                continue
            valid = [k for k in range(len(boxes))
                     if boxes[k, 2] > 1 and boxes[k, 3] > 1 and np.isfinite(boxes[k]).all()]
            if len(valid) >= 2:
                self.sequences.append((frames, boxes, valid))
        shown = ", ".join(left_out[:5]) + (", ..." if len(left_out) > 5 else "")
        if not self.sequences:
            if left_out:
                raise ValueError(f"{root}: no usable sequence: {plural(len(left_out), 'sequence')} matching "
                                 f"{match!r} without one box per frame: {shown}")
            raise ValueError(f"{root}: no sequence folders matching {match!r} with groundtruth.txt / "
                             "groundtruth_rect.txt and frames")
        if left_out:
            warn(f"{root}: left out {plural(len(left_out), 'sequence')} without one box per frame "
                 f"(a box would be paired with another frame): {shown}", "dadiff-train")
        self.max_gap = max_gap

    def sample(self, rng: np.random.Generator):
        frames, boxes, valid = self.sequences[rng.integers(len(self.sequences))]
        a = int(rng.integers(len(valid)))
        near = [k for k in valid if abs(k - valid[a]) <= self.max_gap]
        b = near[int(rng.integers(len(near)))]
        self._gap = abs(b - valid[a])
        fa, fb = cv2.imread(str(frames[valid[a]])), cv2.imread(str(frames[b]))
        if fa is None or fb is None:
            raise ValueError(f"unreadable frame in {frames[0].parent}")
        box_a, box_b = boxes[valid[a]], boxes[b]
        if self.far > 0 and rng.random() < self.far:
            fa, box_a, fb, box_b = self._shrink(fa, box_a, fb, box_b, rng)
        return fa, box_a, fb, box_b

    def _shrink(self, fa: np.ndarray, box_a: np.ndarray, fb: np.ndarray, box_b: np.ndarray,
                rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Both frames shrunk by one factor (one camera further away) so the template's target is 10-30 px
        wide; the night is rendered afterwards, so its noise and blocking fall on a few-pixel person, whom
        the crop then enlarges, as on a far person filmed at night. A target already that small stays."""
        factor = rng.uniform(*self.FAR_WIDTH) / box_a[2]
        if factor >= 1.0:
            return fa, box_a, fb, box_b
        size = (max(1, round(fa.shape[1] * factor)), max(1, round(fa.shape[0] * factor)))
        sx, sy = size[0] / fa.shape[1], size[1] / fa.shape[0]
        scale = np.array([sx, sy, sx, sy], np.float64)
        small_a, small_b = (cv2.resize(f, size, interpolation=cv2.INTER_AREA) for f in (fa, fb))
        return small_a, box_a * scale, small_b, box_b * scale

    def night_pair(self, fi: np.ndarray, fj: np.ndarray, rng: np.random.Generator,
                   style: str, path_lamps: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """The last sampled pair at night. With `one_night`, as `dadiff-eval video` renders a sequence
        (`night_sequence`): one "real" night camera and street lights fixed in the image, the exposure locked
        on the template frame, so the template and the search frame are lit alike. Otherwise (and for the
        "classic" style) each frame gets its own random night. `path_lamps` is a scene's (it needs
        the scene's ground)."""
        from dadiff.runtime.datamaking.fixed_camera import night_sequence
        from dadiff.runtime.datamaking.night import render_night

        if not self.one_night or style != "real":
            return render_night(fi, rng, style=style), render_night(fj, rng, style=style)
        noise = [int(rng.integers(2**31))]
        first, second = night_sequence([fi, fj], rng, noise, [0, self._gap])
        return first, second


class ImageFolderSource:
    """Both crops cut from one still image around a random region (shift/scale come from the crop jitter)."""

    def __init__(self, root: str | Path) -> None:
        self.paths = sorted(p for p in Path(root).rglob("*") if p.suffix.lower() in IMAGE_EXTENSIONS)
        if not self.paths:
            raise ValueError(f"{root}: no images ({', '.join(IMAGE_EXTENSIONS)})")

    def sample(self, rng: np.random.Generator):
        img = cv2.imread(str(self.paths[rng.integers(len(self.paths))]))
        if img is None:
            raise ValueError("unreadable image in the image folder")
        h, w = img.shape[:2]
        bw, bh = rng.uniform(0.05, 0.3) * w, rng.uniform(0.05, 0.3) * h
        box = np.array([rng.uniform(0, w - bw), rng.uniform(0, h - bh), bw, bh], np.float32)
        return img, box, img, box


# ---- night sources: each yields one night image the size of a search crop or larger ---------------------


class NightFolderSource:
    """Unlabelled night images (NAT2021-train frames, any folder of images) or videos: random crops."""

    def __init__(self, root: str | Path) -> None:
        root = Path(root)
        self.images = sorted(p for p in root.rglob("*") if p.suffix.lower() in IMAGE_EXTENSIONS)
        self.videos = sorted(p for p in root.rglob("*") if p.suffix.lower() in (".mp4", ".avi", ".mov", ".mkv"))
        if not self.images and not self.videos:
            raise ValueError(f"{root}: no night images or videos")

    def sample(self, rng: np.random.Generator) -> np.ndarray:
        if self.images and (not self.videos or rng.random() < 0.5):
            img = cv2.imread(str(self.images[rng.integers(len(self.images))]))
        else:
            cap = cv2.VideoCapture(str(self.videos[rng.integers(len(self.videos))]))
            n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) or 1
            cap.set(cv2.CAP_PROP_POS_FRAMES, int(rng.integers(n)))
            ok, img = cap.read()
            cap.release()
            img = img if ok else None
        if img is None:
            raise ValueError("unreadable night image or video frame")
        return img


def make_day_source(spec: dict):
    kind = spec.get("kind")
    if kind == "scenes":
        return SceneSource(spec.get("split", "train"), pairs_per_scene=int(spec.get("pairs", 4)),
                           source=spec.get("source", "skimage"), companions=float(spec.get("companions", 0.0)),
                           stretch=float(spec.get("stretch", 0.0)), cutouts=spec.get("cutouts"))
    if kind in ("got10k", "otb", "sequences"):
        one_night = spec.get("one_night", False)
        if not isinstance(one_night, bool):
            raise ValueError(f"one_night is {one_night!r}; expected true or false")
        return SequenceSource(spec["root"], match=spec.get("match", "*"), far=float(spec.get("far", 0.0)),
                              one_night=one_night)
    if kind == "images":
        return ImageFolderSource(spec["root"])
    raise ValueError(f"unknown day data kind {kind!r}; expected one of {', '.join(DAY_KINDS)}")


def camera_night_pair(fz: np.ndarray, fx: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A pair's frames filmed at night by one camera of the independent night model (camera_night.py), so that
    the training does not learn the generator's night alone: the camera's lights fixed in the image and its
    exposure locked on the template's frame (frames of two sizes: each on its own, the same camera)."""
    from dadiff.runtime.datamaking.camera_night import render_night

    seed = [int(s) for s in rng.integers(0, 2**31, size=2)]
    if fz.shape == fx.shape:
        nz, nx = render_night([fz, fx], seed)[0]
        return nz, nx
    return render_night([fz], seed)[0][0], render_night([fx], seed)[0][0]


class PairStream(IterableDataset):
    """Endless stream of samples; each worker / rank draws from its own seeded generator."""

    def __init__(self, day_sources: list, night: str | Path | None, cfg: CropConfig, seed: int, rank: int = 0,
                 with_night: bool = True, night_styles: Sequence[str] = ("real",), start_step: int = 0,
                 night_pairs: str = "frame", night_path_lamps: float = 0.0, negative_pairs: float = 0.0) -> None:
        super().__init__()
        self.negative_pairs = negative_pairs  # share of pairs whose search crop holds another object
        self.night_pairs = night_pairs  # "scene": one night over a generated scene's pair; "frame": one per frame
        self.night_path_lamps = night_path_lamps  # share of scene-lit pairs with lamps beside the target
        self.day_sources, self.cfg, self.seed, self.rank = day_sources, cfg, seed, rank
        self.start_step = start_step  # a resumed run draws new pairs instead of replaying the first ones
        self.with_night = with_night  # the baseline stage never looks at night data
        self.night_source = NightFolderSource(night) if night and with_night else None
        self.night_styles = tuple(night_styles)

    def _night_style(self, rng: np.random.Generator) -> str:
        """One style per pair (one camera films both frames); no draw with a single style, so a stream
        rendered in one style does not depend on whether styles can be mixed."""
        if len(self.night_styles) == 1:
            return self.night_styles[0]
        return self.night_styles[int(rng.integers(len(self.night_styles)))]

    @staticmethod
    def _night(frame: np.ndarray, rng: np.random.Generator, style: str) -> np.ndarray:
        from dadiff.runtime.datamaking.night import render_night

        return render_night(frame, rng, style=style)

    def __iter__(self) -> Iterator[dict[str, torch.Tensor]]:
        info = get_worker_info()
        worker = info.id if info else 0
        entropy = [self.seed, self.rank, worker] + ([self.start_step] if self.start_step else [])
        rng = np.random.default_rng(entropy)
        cfg = self.cfg
        while True:
            source = self.day_sources[int(rng.integers(len(self.day_sources)))]
            try:
                fz, bz, fx, bx = source.sample(rng)
            except ValueError:
                continue
            negative = self.negative_pairs > 0 and rng.random() < self.negative_pairs  # no draw at 0
            if negative:  # a scene source moves on to another scene; other sources draw again
                fx, bx = source.other(rng) if hasattr(source, "other") else source.sample(rng)[2:]
            grey, blur = rng.random() < cfg.grey, rng.random() < cfg.blur
            wz = jittered_window(bz, cfg.exemplar, cfg, cfg.template_shift, cfg.template_scale, rng)
            wx = jittered_window(bx, cfg.instance, cfg, cfg.search_shift, cfg.search_scale, rng)
            z, x = wz.cut(fz), wx.cut(fx)
            label, loc = ban_targets(wx.rel, cfg)
            if negative:  # the other object is not the target: negative where its positives would be
                label = np.where(label == 1, 0, -1)
            if not self.with_night:
                zn, xn = z[:1, :1], x[:1, :1]  # placeholders, unused
            elif self.night_source is None:  # the same frames rendered at night (sensor noise at frame scale)
                style = self._night_style(rng)
                if style == CAMERA_NIGHT:
                    nz, nx = camera_night_pair(fz, fx, rng)
                elif self.night_pairs == "scene" and hasattr(source, "night_pair") and not negative:
                    nz, nx = source.night_pair(fz, fx, rng, style, self.night_path_lamps)
                else:
                    nz, nx = self._night(fz, rng, style), self._night(fx, rng, style)
                zn, xn = wz.cut(nz), wx.cut(nx)
            else:
                zn = self._crop_night(self.night_source.sample(rng), cfg.exemplar, rng)
                xn = self._crop_night(self.night_source.sample(rng), cfg.instance, rng)
            yield {"z": to_chw(augment(z, cfg, rng, grey, False)), "x": to_chw(augment(x, cfg, rng, grey, blur)),
                   "label": torch.from_numpy(label), "loc": torch.from_numpy(loc),
                   "z_night": to_chw(zn.astype(np.float32)), "x_night": to_chw(xn.astype(np.float32)),
                   "paired": torch.tensor(self.night_source is None)}

    @staticmethod
    def _crop_night(img: np.ndarray, out: int, rng: np.random.Generator) -> np.ndarray:
        h, w = img.shape[:2]
        side = int(min(h, w) * rng.uniform(0.3, 0.9))
        centre = (rng.uniform(side / 2, w - side / 2), rng.uniform(side / 2, h - side / 2))
        return subwindow(img, centre, out, max(side, 1), mean_colour(img))
