"""The scene photos from scikit-image (bundled with it, no download), split once and for all into
`PHOTO_SPLITS` so that a test benchmark never shows a training photo. scikit-image is imported only when
photos are first loaded."""

from __future__ import annotations

import functools

import cv2
import numpy as np

from .scene_error import SceneError

PHOTO_SPLITS: dict[str, tuple[str, ...]] = {
    "train": (
        "astronaut",
        "brick",
        "camera",
        "coffee",
        "grass",
        "hubble_deep_field",
        "immunohistochemistry",
        "moon",
        "retina",
    ),
    "test": ("chelsea", "coins", "gravel", "motorcycle", "rocket"),
}
# skimage.data function (and index into its tuple result) for names that differ from the function name.
_PHOTO_LOADERS = {"motorcycle": ("stereo_motorcycle", 0)}


@functools.lru_cache(maxsize=4)
def _photos(split: str) -> tuple[tuple[str, np.ndarray], ...]:
    try:
        import skimage.data
    except ImportError:
        raise SceneError("the generated night scenes need scikit-image's photos, which are not installed here: "
                         'pip install "dadiff[eval]"') from None
    out = []
    for name in PHOTO_SPLITS[split]:
        func, index = _PHOTO_LOADERS.get(name, (name, None))
        try:
            image = getattr(skimage.data, func)()
        except Exception as exc:  # a missing bundled file surfaces as many different errors
            raise SceneError(f"scikit-image's bundled image '{func}' cannot be loaded ({exc})") from None
        image = np.asarray(image if index is None else image[index])
        if image.ndim == 2:
            image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        else:
            image = cv2.cvtColor(image[:, :, :3], cv2.COLOR_RGB2BGR)
        image = np.ascontiguousarray(image, dtype=np.uint8)
        image.flags.writeable = False
        out.append((name, image))
    return tuple(out)


def load_photos(split: str) -> dict[str, np.ndarray]:
    """The photographs of one split ('train' or 'test') as read-only BGR uint8 arrays, by name."""
    check_split(split)
    return dict(_photos(split))


def check_split(split: str) -> None:
    """SceneError unless `split` is one of `PHOTO_SPLITS` (the library uses the same two splits)."""
    if split not in PHOTO_SPLITS:
        raise SceneError(f"unknown photo split '{split}'; expected one of {', '.join(PHOTO_SPLITS)}")
