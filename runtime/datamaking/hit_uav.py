"""Tracking sequences from HIT-UAV's real night stills: the same object boxed in neighbouring images, linked.

HIT-UAV (Suo et al., Scientific Data 10, 227, 2023; CC BY 4.0) is a detection set: 640 x 512 thermal stills picked
from drone flights, each with its own boxes and no identities. Neighbouring stills of one flight (file names
`1_<altitude>_<pitch>_<?>_<index>.jpg`, the index counting video frames) often show the same parked car or standing
person, after the drone has moved the picture by tens to hundreds of pixels. A pair of neighbours is registered by
ORB features and a RANSAC similarity (robust where phase correlation locks onto the thermal sensor's fixed pattern
at zero shift); each box of the first still is carried through that transform and linked to the box of the same
class it then overlaps, only when the link is clear both ways: no second box nearly as good and no other box of
its class near where it should be (a group of people playing is refused, not guessed). Links chain into
sequences of two or more stills per object, written in the OTB layout with the stills' JPEG bytes unchanged.

The frames of a sequence are 0.5 s to several seconds apart and the camera jumps between them: a tracker must
find the target again after that jump, as a drone's tracker must after a dropped second of video.
"""

from __future__ import annotations

import json
import re
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from ..files import write_atomic
from ..sources import read_image
from .datasets import read_text
from .fixed_camera import check_new_folder
from .geometry import iou_with_each
from .scene_error import SceneError
from .scenes import write_boxes

SPLITS = ("train", "val", "test")
CLASSES = {0: "person", 1: "car", 2: "bicycle"}  # 3 OtherVehicle (rare) and 4 DontCare are left out
NIGHT_NAME = re.compile(r"(1_\d+_\d+_\d+)_(\d+)\.jpg")  # flight prefix (night, altitude, pitch, ?) and index
CHECKOUT_DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "hit-uav-night"
LICENCE = "CC BY 4.0 (https://creativecommons.org/licenses/by/4.0/)"
CITATION = ("Jiashun Suo, Tianyi Wang, Xingzhou Zhang, Haiyang Chen, Wei Zhou and Weisong Shi. HIT-UAV: A "
            "high-altitude infrared thermal dataset for Unmanned Aerial Vehicle-based object detection. Scientific "
            "Data 10, 227 (2023). https://doi.org/10.1038/s41597-023-02066-6")


@dataclass(frozen=True)
class ChainSettings:
    """How neighbouring stills are registered and their boxes linked."""

    max_gap: int = 20  # index difference (video frames) between neighbours that may be linked
    features: int = 2000  # ORB keypoints per still
    min_inliers: int = 40  # RANSAC inliers a registration needs ...
    min_inlier_share: float = 0.3  # ... and this share of the matched keypoints
    max_scale_change: float = 1.25  # a similarity that scales more (either way) is a wrong registration
    min_iou: float = 0.3  # a carried box links to a box it overlaps this much ...
    ambiguity: float = 0.5  # ... unless a second box overlaps it by this share of that ...
    crowd: float = 1.5  # ... or another box of its class has its centre within this many box sides of it
    min_side: float = 4.0  # px: smaller boxes are left out
    max_move: float | None = None  # box sides the target's centre may move in the image between stills (None: any)
    min_frames: int = 2  # shortest chain written
    max_frames: int = 30  # a longer chain is cut here (the rest starts another)


@dataclass(frozen=True)
class Still:
    """One night image of the split: its file, flight, index and boxes (x, y, w, h) with class ids."""

    name: str
    flight: str
    index: int
    boxes: np.ndarray
    classes: np.ndarray
    ids: tuple[int, ...]


@dataclass(frozen=True)
class Chain:
    """One object across neighbouring stills: still positions in the split's order and its box in each."""

    cls: int
    stills: tuple[int, ...]
    boxes: tuple[int, ...]  # the box's row in each still


def default_data_dir() -> Path | None:
    """../shared/data/hit-uav-night beside the source checkout, where this project keeps the set, if present."""
    return CHECKOUT_DATA if CHECKOUT_DATA.is_dir() else None


def read_split(root: Path, split: str, settings: ChainSettings = ChainSettings()) -> list[Still]:
    """The split's night stills (file name `1_...`) in flight and index order, each with its kept boxes."""
    path = Path(root) / "annotations" / f"{split}.json"
    if not path.is_file():
        raise SceneError(f"{path}: no such annotation file (expected HIT-UAV's annotations/{{train,val,test}}.json)")
    try:
        doc = json.loads(read_text(path))
    except ValueError as exc:
        raise SceneError(f"{path}: not JSON ({exc})") from None
    for key in ("images", "annotation"):
        if not isinstance(doc, dict) or not isinstance(doc.get(key), list):
            raise SceneError(f"{path}: no '{key}' list (HIT-UAV keeps its boxes under 'annotation')")
    rows: dict[int, list[tuple[list[float], int, int]]] = {}
    for number, item in enumerate(doc["annotation"]):
        try:
            box, cls, image = [float(v) for v in item["bbox"]], int(item["category_id"]), int(item["image_id"])
            ident = int(item["id"])
        except (KeyError, TypeError, ValueError):
            raise SceneError(f"{path}: annotation {number}: expected bbox [x, y, w, h], category_id, image_id and "
                             "id") from None
        if len(box) != 4:
            raise SceneError(f"{path}: annotation {number}: bbox has {len(box)} values, expected 4")
        if cls in CLASSES and min(box[2], box[3]) >= settings.min_side:
            rows.setdefault(image, []).append((box, cls, ident))
    stills = []
    for number, image in enumerate(doc["images"]):
        name = image.get("filename") if isinstance(image, dict) else None
        match = NIGHT_NAME.fullmatch(name) if isinstance(name, str) else None
        if match is None:
            continue  # a day image (0_...) or another file
        try:
            kept = rows.get(int(image["id"]), [])
        except (KeyError, TypeError, ValueError):
            raise SceneError(f"{path}: image {number} ({name}): no whole-number 'id'") from None
        stills.append(Still(name, match[1], int(match[2]),
                            np.array([r[0] for r in kept], dtype=np.float64).reshape(-1, 4),
                            np.array([r[1] for r in kept], dtype=np.int64), tuple(r[2] for r in kept)))
    if not stills:
        raise SceneError(f"{path}: no night image (file name 1_<altitude>_<pitch>_<?>_<index>.jpg)")
    return sorted(stills, key=lambda s: (s.flight, s.index))


class Registration:
    """ORB keypoints of each still (computed once) and the similarity that carries one still onto the next."""

    def __init__(self, images: Path, settings: ChainSettings) -> None:
        self.images, self.settings = images, settings
        self.orb = cv2.ORB_create(settings.features, fastThreshold=5)
        self.clahe = cv2.createCLAHE(2.0, (8, 8))  # thermal stills are flat: local contrast gives ORB corners
        self.matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
        self._cache: dict[str, tuple] = {}

    def grey(self, name: str) -> np.ndarray:
        path = self.images / name
        image = read_image(path, cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise SceneError(f"{path}: {'cannot read image' if path.is_file() else 'not found'}")
        return image

    def _features(self, name: str) -> tuple:
        if name not in self._cache:
            self._cache = {name: self.orb.detectAndCompute(self.clahe.apply(self.grey(name)), None)}
        return self._cache[name]

    def transform(self, first: str, second: str) -> tuple[np.ndarray | None, int]:
        """The 2 x 3 similarity from `first`'s pixels to `second`'s and its inlier count; None when it is not
        trustworthy (too few inliers, too small a share of them, an implausible scale change)."""
        keys1, desc1 = self._features(first)
        keys2, desc2 = self._features(second)  # the cache keeps this one for the next pair
        if desc1 is None or desc2 is None or len(keys1) < 2 or len(keys2) < 2:
            return None, 0
        pairs = self.matcher.knnMatch(desc1, desc2, k=2)
        good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < 0.8 * p[1].distance]
        if len(good) < self.settings.min_inliers:
            return None, 0
        src = np.float32([keys1[m.queryIdx].pt for m in good])
        dst = np.float32([keys2[m.trainIdx].pt for m in good])
        matrix, inliers = cv2.estimateAffinePartial2D(src, dst, method=cv2.RANSAC, ransacReprojThreshold=3.0)
        count = int(inliers.sum()) if inliers is not None else 0
        if matrix is None or count < self.settings.min_inliers or count < self.settings.min_inlier_share * len(good):
            return None, count
        scale = float(np.hypot(matrix[0, 0], matrix[1, 0]))
        if not 1 / self.settings.max_scale_change <= scale <= self.settings.max_scale_change:
            return None, count
        return matrix, count


def carry(boxes: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """Boxes (x, y, w, h) moved by a similarity: centres through it, sides times its scale."""
    centres = boxes[:, :2] + boxes[:, 2:] / 2
    moved = centres @ matrix[:, :2].T + matrix[:, 2]
    sides = boxes[:, 2:] * float(np.hypot(matrix[0, 0], matrix[1, 0]))
    return np.c_[moved - sides / 2, sides]


def _clear_best(box: np.ndarray, cls: int, boxes: np.ndarray, classes: np.ndarray,
                settings: ChainSettings) -> int | None:
    """The row of `boxes` that `box` (of class `cls`) clearly overlaps, or None: below min_iou, a rival of the same
    class overlapping nearly as much, or another box of its class with its centre within `crowd` box sides."""
    same = np.flatnonzero(classes == cls)
    if len(same) == 0:
        return None
    overlaps = iou_with_each(box, boxes[same])
    order = np.argsort(-overlaps)
    best = overlaps[order[0]]
    if best < settings.min_iou or (len(order) > 1 and overlaps[order[1]] >= settings.ambiguity * best):
        return None
    centre, side = box[:2] + box[2:] / 2, settings.crowd * float(np.sqrt(box[2] * box[3]))
    others = np.delete(boxes[same], order[0], axis=0)
    if len(others) and np.min(np.hypot(*(others[:, :2] + others[:, 2:] / 2 - centre).T)) < side:
        return None  # a look-alike right beside it: which one moved where cannot be told
    return int(same[order[0]])


def _move(before: np.ndarray, after: np.ndarray) -> float:
    """How far a box's centre moved in the image, in box sides (the geometric mean of its sides before)."""
    shift = (after[:2] + after[2:] / 2) - (before[:2] + before[2:] / 2)
    return float(np.hypot(*shift) / np.sqrt(before[2] * before[3]))


def link_pair(first: Still, second: Still, matrix: np.ndarray, settings: ChainSettings) -> dict[int, int]:
    """Box row in `first` -> box row in `second` for every object clearly seen in both, checked both ways."""
    if len(first.boxes) == 0 or len(second.boxes) == 0:
        return {}
    back = cv2.invertAffineTransform(matrix)
    forward, backward = carry(first.boxes, matrix), carry(second.boxes, back)
    links = {}
    for i, box in enumerate(forward):
        j = _clear_best(box, int(first.classes[i]), second.boxes, second.classes, settings)
        if j is None or _clear_best(backward[j], int(second.classes[j]), first.boxes, first.classes, settings) != i:
            continue
        if settings.max_move is None or _move(first.boxes[i], second.boxes[j]) <= settings.max_move:
            links[i] = j  # else a jump beyond a tracker's search region, left out of a 'within reach' set
    return links


def build_chains(stills: list[Still], registration: Registration,
                 settings: ChainSettings = ChainSettings()) -> tuple[list[Chain], list[dict]]:
    """Chains of linked boxes over neighbouring stills, and one record per neighbour pair (registered or not)."""
    chains: list[Chain] = []
    pairs: list[dict] = []
    open_chains: dict[int, tuple[int, list[int], list[int]]] = {}  # box row in the current still -> chain so far
    for k, still in enumerate(stills):
        following = stills[k + 1] if k + 1 < len(stills) else None
        links: dict[int, int] = {}
        if following is not None and following.flight == still.flight \
                and 0 < following.index - still.index <= settings.max_gap:
            matrix, inliers = registration.transform(still.name, following.name)
            if matrix is not None:
                links = link_pair(still, following, matrix, settings)
            pairs.append({"first": still.name, "second": following.name, "registered": matrix is not None,
                          "inliers": inliers, "links": len(links),
                          "transform": None if matrix is None else np.round(matrix, 4).tolist()})
        current = {row: open_chains.get(row, (int(still.classes[row]), [], [])) for row in range(len(still.boxes))}
        open_chains = {}
        for row, (cls, positions, rows) in current.items():
            positions, rows = [*positions, k], [*rows, row]
            if row in links and len(positions) < settings.max_frames:
                open_chains[links[row]] = (cls, positions, rows)
            elif len(positions) >= settings.min_frames:
                chains.append(Chain(cls, tuple(positions), tuple(rows)))
    return sorted(chains, key=lambda c: (c.stills[0], c.boxes[0])), pairs


def write_hit_uav_benchmark(root: str | Path, out: str | Path, split: str = "test",
                            settings: ChainSettings = ChainSettings()) -> list[Chain]:
    """Link `split`'s night stills into chains and write each as `<out>/hitNNNN_<class>` (OTB layout: the stills'
    JPEG files copied unchanged into img/, groundtruth_rect.txt), `attributes.json` (the class) and
    `benchmark.json` (source, split, licence and attribution, settings, the still behind every frame)."""
    root, out = Path(root).expanduser(), Path(out).expanduser()
    if split not in SPLITS:
        raise SceneError(f"split {split!r}: expected one of {', '.join(SPLITS)}")
    if not (root / "images").is_dir():
        raise SceneError(f"{root}: no images/ folder (expected HIT-UAV's night stills, see its README)")
    check_new_folder(out)
    stills = read_split(root, split, settings)
    chains, pairs = build_chains(stills, Registration(root / "images", settings), settings)
    if not chains:
        raise SceneError(f"{root}: no object of split {split} links across {settings.min_frames} neighbouring stills")
    attributes, records = {}, []
    for n, chain in enumerate(chains, 1):
        name = f"hit{n:04d}_{CLASSES[chain.cls]}"
        folder = out / name / "img"
        folder.mkdir(parents=True)
        for i, position in enumerate(chain.stills):
            shutil.copyfile(root / "images" / stills[position].name, folder / f"{i + 1:04d}.jpg")
        write_boxes(out / name / "groundtruth_rect.txt",
                    np.array([stills[p].boxes[r] for p, r in zip(chain.stills, chain.boxes, strict=True)]))
        attributes[name] = [CLASSES[chain.cls]]
        records.append({"name": name, "class": CLASSES[chain.cls],
                        "images": [stills[p].name for p in chain.stills],
                        "annotation_ids": [stills[p].ids[r] for p, r in zip(chain.stills, chain.boxes, strict=True)]})
    write_atomic(out / "attributes.json", json.dumps(attributes, indent=1) + "\n")
    info = {"generator": "dadiff.runtime.datamaking.hit_uav", "source": "HIT-UAV night images", "data": str(root),
            "split": split, "licence": LICENCE, "attribution": CITATION, "settings": asdict(settings),
            "stills": len(stills), "sequences": records, "pairs": pairs}
    write_atomic(out / "benchmark.json", json.dumps(info, indent=1) + "\n")
    return chains
