"""Real-photo scene library: object cut-outs and backgrounds taken from Debian packages, split once and for all.

`fetch` downloads packages with `apt-get download` (or takes .deb files from a folder), unpacks them with
`dpkg-deb -x` into the cache (`$DADIFF_DATA_DIR`, else ~/.cache/dadiff/library; never a git work tree),
picks the photographic images, and writes `<cache>/index.json`. Each image has a role ("target": a cut-out
with real alpha; "background": an opaque photo) and a split ("test" for ~20 % of the source files by a stable
hash of package and path, "train" otherwise). Files the index does not use are deleted after indexing, so the
1.3 GB flight-simulator package costs only its ground textures on disk. Re-running skips packages already done.

Per package (`_by_path` before decoding, then `_judge*`): Tux Paint stamps keep PNGs with real alpha that
are not flat-shaded clip art (fewer than 5 % of neighbouring opaque pixels share the exact same colour; SVG
and `cartoon/` skipped); GCompris keeps the images inside the Qt `.rcc` archives of its photo activities
(`GCOMPRIS_PHOTO_ARCHIVES`, extracted to files; drawings, painting puzzles and UI art are in the others);
FlightGear keeps its Terrain textures (not masks, overlays, grey detail maps, blend layers or DDS); the
wallpaper packages keep JPEG photos (their PNGs are rendered artwork) that are not smooth gradients, and for
Plasma and UKUI only those with camera EXIF data. Near duplicates (one picture at several resolutions, or
recoloured) are dropped within a package, keeping the largest, so one picture cannot sit in both splits.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import os
import re
import shutil
import struct
import subprocess
import tempfile
from collections import Counter
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..errors import DadiffError
from ..files import write_atomic
from .rcc import RccArchive, RccEntry, RccError, zstd_available

FORMAT = 1
RULES = 1  # bump when the selection rules change: packages indexed under older rules are fetched again
ROLES = ("target", "background")
SPLITS = ("train", "test")
TEST_PERCENT = 20
MIN_SIDE = 64

WALLPAPERS = ("lomiri-wallpapers-16.04", "plasma-workspace-wallpapers", "mate-backgrounds", "ukui-wallpapers")
# Wallpaper packages whose JPEGs mix photos and renders: there only JPEGs with camera EXIF data are photos.
CAMERA_EXIF_ONLY = ("plasma-workspace-wallpapers", "ukui-wallpapers")
ARTWORK_FOLDERS = ("/mate/desktop/",)  # distribution artwork (logos on gradients)
DEFAULT_PACKAGES = ("tuxpaint-stamps-default", "gcompris-qt-data", *WALLPAPERS, "flightgear-data-base")

# GCompris activities whose images are photographs, and the roles taken from each (clickgame's cut-out fish
# are two-frame sprite sheets, so only its sea photos are kept). Others hold drawings, puzzle pieces of
# paintings or UI art.
GCOMPRIS_PHOTO_ARCHIVES: dict[str, tuple[str, ...]] = {
    "categorization": ROLES,
    "erase": ROLES,
    "explore_farm_animals": ROLES,
    "explore_monuments": ROLES,
    "explore_world_animals": ROLES,
    "explore_world_music": ROLES,
    "gravity": ROLES,
    "leftright": ROLES,
    "louis-braille": ROLES,
    "solar_system": ROLES,
    "clickgame": ("background",),
}
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".webp")
SEEN_SUFFIXES = (*IMAGE_SUFFIXES, ".svg", ".svgz", ".dds")  # image files: used, or counted as skipped
FLIGHTGEAR_SKIP = re.compile(r"mask|relief|overlay|colou?rs|structure|grain|void|unknown")
CLIP_ART_FLAT = 0.05  # stamps: flat-shaded when >= 5 % of neighbouring opaque pixel pairs are identical
GRADIENT_FLAT = 0.8  # wallpapers: smooth gradient when >= 80 % of neighbouring pixel pairs are identical
GREY_SATURATION = 3.0  # terrain: mean HSV saturation below this is a grey detail map, not a photo
DUPLICATE_BITS = 4  # difference hashes this close (of 64 bits) are the same picture


class LibraryError(DadiffError, ValueError):
    """A library problem a user can fix: missing tool, bad .deb, bad folder, no index (one-line message)."""


def library_root() -> Path:
    """The default cache: $DADIFF_DATA_DIR, else ~/.cache/dadiff/library."""
    env = os.environ.get("DADIFF_DATA_DIR")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "dadiff" / "library"


def split_of(package: str, source: str) -> str:
    """'test' for ~20 % of source files, 'train' otherwise; a pure function of (package, source)."""
    digest = hashlib.sha256(f"{package}\n{source}".encode()).digest()
    return "test" if int.from_bytes(digest[:8], "big") % 100 < TEST_PERCENT else "train"


# ---------------------------------------------------------------------------------------------- library


@dataclass(frozen=True)
class LibraryImage:
    """One image file in the cache, with where it came from and what it is for."""

    path: Path
    package: str
    source: str
    role: str
    split: str
    licence: str
    width: int
    height: int

    def load(self) -> np.ndarray:
        """Target: BGRA uint8 (alpha kept); background: BGR uint8. Raises LibraryError naming the file."""
        flags = cv2.IMREAD_UNCHANGED if self.role == "target" else cv2.IMREAD_COLOR
        image = cv2.imread(str(self.path), flags)
        if image is None:
            raise LibraryError(f"cannot read library image {self.path} (run `dadiff-eval data fetch` again)")
        return _as_bgra(image) if self.role == "target" else image


class Library:
    """The indexed images of one cache folder."""

    def __init__(self, root: Path, images: Iterable[LibraryImage], licences: dict[str, str]) -> None:
        self.root = root
        self._images = tuple(sorted(images, key=lambda i: (i.package, i.source)))
        self._licences = dict(sorted(licences.items()))

    def images(self, role: str, split: str) -> list[LibraryImage]:
        """Images of one role and split, sorted by package and source (deterministic)."""
        if role not in ROLES:
            raise LibraryError(f"unknown library role '{role}'; expected one of {', '.join(ROLES)}")
        if split not in SPLITS:
            raise LibraryError(f"unknown library split '{split}'; expected one of {', '.join(SPLITS)}")
        return [i for i in self._images if i.role == role and i.split == split]

    def licences(self) -> dict[str, str]:
        """Package -> licence short names (from its Debian copyright file)."""
        return dict(self._licences)

    def __len__(self) -> int:
        return len(self._images)


def open_library(root: Path | None = None) -> Library | None:
    """The library in `root` (default `library_root()`), or None when nothing was fetched there."""
    root = Path(root) if root is not None else library_root()
    index = root / "index.json"
    if not index.is_file():
        return None
    try:
        data = json.loads(index.read_text())
        _check_index(data)
        return _library(root, data["packages"])
    except (ValueError, KeyError, TypeError, RecursionError) as exc:
        raise LibraryError(f"{index}: not a valid library index ({exc}); run `dadiff-eval data fetch` again") from None


def _check_index(data: object) -> None:
    """The index's shape, naming the first bad key (`{"packages": []}` is a LibraryError, not a traceback)."""
    def need(ok: bool, key: str, what: str) -> None:
        if not ok:
            raise ValueError(f"key {key} must be {what}")

    need(isinstance(data, dict), "(top level)", "an object")
    assert isinstance(data, dict)
    packages = data.get("packages")
    need(isinstance(packages, dict), "'packages'", "an object of package name -> entry")
    assert isinstance(packages, dict)
    for name, meta in packages.items():
        key = f"'packages.{name}"
        need(isinstance(meta, dict), key + "'", "an object")
        need(isinstance(meta.get("licence"), str), key + ".licence'", "a string")
        need(isinstance(meta.get("images"), list), key + ".images'", "a list")
        for k, item in enumerate(meta["images"]):
            at = f"{key}.images[{k}]"
            need(isinstance(item, dict), at + "'", "an object")
            for field in ("file", "source"):
                need(isinstance(item.get(field), str), f"{at}.{field}'", "a string")
            need(item.get("role") in ROLES, f"{at}.role'", f"one of {', '.join(ROLES)}")
            need(item.get("split") in SPLITS, f"{at}.split'", f"one of {', '.join(SPLITS)}")
            for field in ("width", "height"):
                value = item.get(field)
                need(isinstance(value, int) and not isinstance(value, bool) and value > 0, f"{at}.{field}'",
                     "a positive integer")


def _library(root: Path, packages: dict[str, dict]) -> Library:
    images = [
        LibraryImage(
            path=root / item["file"],
            package=name,
            source=item["source"],
            role=item["role"],
            split=item["split"],
            licence=meta["licence"],
            width=int(item["width"]),
            height=int(item["height"]),
        )
        for name, meta in packages.items()
        for item in meta["images"]
    ]
    return Library(root, images, {name: meta["licence"] for name, meta in packages.items()})


# ------------------------------------------------------------------------------------------------ fetch


def fetch(
    packages: Iterable[str] | None,
    cache: Path,
    deb_dir: Path | None = None,
    log: Callable[[str], None] = print,
) -> Library:
    """Download (apt-get) or take (deb_dir) the packages, unpack and index them into `cache`; incremental.

    `packages` None or empty: the defaults, or with `deb_dir` every .deb in it. A package apt cannot get is
    reported in one line and skipped; LibraryError when none could be had or a tool or .deb is unusable.
    """
    cache = _check_cache(Path(cache).expanduser())
    names = list(dict.fromkeys(packages or ()))
    _need("dpkg-deb", "dpkg-deb (from dpkg) is needed to unpack the packages")
    with _locked(cache):
        done = _fetch_debs(names, cache, deb_dir, log) if deb_dir is not None else _fetch_apt(names, cache, log)
        index = _write_index(cache)
    if not done and not index:
        raise LibraryError("no package could be fetched (see the lines above)")
    library = open_library(cache)
    assert library is not None
    return library


def _check_cache(cache: Path) -> Path:
    """Refuse a cache inside a git work tree: the data must never end up in a commit."""
    resolved = cache.resolve()
    for folder in (resolved, *resolved.parents):
        if (folder / ".git").exists():
            raise LibraryError(f"cache folder {cache} is inside the git work tree {folder}; choose one outside it")
    (cache / "packages").mkdir(parents=True, exist_ok=True)
    return cache


@contextlib.contextmanager
def _locked(cache: Path) -> Iterator[None]:
    """One fetch at a time per cache: a second one would delete the trees the first is indexing."""
    with (cache / ".lock").open("w") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise LibraryError(f"another fetch is writing {cache}; wait for it to finish") from None
        yield


def _need(tool: str, why: str) -> None:
    if shutil.which(tool) is None:
        raise LibraryError(f"{tool} not found: {why}")


def _fetch_apt(names: list[str], cache: Path, log: Callable[[str], None]) -> list[str]:
    _need("apt-get", "it downloads the packages (Debian/Ubuntu); or pass --deb DIR with downloaded .deb files")
    done = []
    for name in names or DEFAULT_PACKAGES:
        if _is_done(cache, name):
            log(f"{name}: already in the library, skipped")
            done.append(name)
            continue
        with tempfile.TemporaryDirectory(prefix="dadiff-apt-") as tmp:
            deb = _apt_download(name, Path(tmp), log)
            if deb is not None:
                _add_package(deb, cache, log)
                done.append(name)
    return done


def _apt_download(name: str, folder: Path, log: Callable[[str], None]) -> Path | None:
    """`apt-get download NAME` into folder; None (with one line logged) when apt cannot get it."""
    log(f"{name}: downloading with apt-get")
    try:
        run = subprocess.run(["apt-get", "download", "-q", name], cwd=folder, capture_output=True, text=True)
    except OSError as exc:
        raise LibraryError(f"apt-get cannot be run: {exc.strerror or exc}") from None
    debs = sorted(folder.glob("*.deb"))
    if run.returncode != 0 or not debs:
        log(f"{name}: not fetched: {_last_error(run.stderr or run.stdout, 'apt-get download failed')}")
        return None
    return debs[0]


def _last_error(text: str, default: str) -> str:
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    errors = [ln for ln in lines if ln.startswith("E:")]
    return (errors or lines or [default])[-1]


def _fetch_debs(names: list[str], cache: Path, deb_dir: Path, log: Callable[[str], None]) -> list[str]:
    if not deb_dir.is_dir():
        raise LibraryError(f"no such folder of .deb files: {deb_dir}")
    found = {}
    for deb in sorted(deb_dir.glob("*.deb")):
        found.setdefault(_deb_field(deb, "Package"), deb)
    if not found:
        raise LibraryError(f"no .deb files in {deb_dir}")
    done = []
    for name in names or list(found):
        if name not in found:
            log(f"{name}: not fetched: no {name}_*.deb in {deb_dir}")
        elif _is_done(cache, name, _deb_field(found[name], "Version")):
            log(f"{name}: already in the library, skipped")
            done.append(name)
        else:
            _add_package(found[name], cache, log)
            done.append(name)
    return done


def _deb_field(deb: Path, name: str) -> str:
    run = subprocess.run(["dpkg-deb", "-f", str(deb), name], capture_output=True, text=True)
    value = run.stdout.strip()
    if run.returncode != 0 or not value:
        raise LibraryError(f"{deb.name}: not a valid .deb ({_last_error(run.stderr, 'dpkg-deb -f failed')})")
    return value


def _package_json(cache: Path, name: str) -> Path:
    return cache / "packages" / f"{name}.json"


def _is_done(cache: Path, name: str, version: str | None = None) -> bool:
    """Indexed under the current rules (and the same version, when known) and its files still there."""
    path = _package_json(cache, name)
    try:
        meta = json.loads(path.read_text())
    except (OSError, ValueError):
        return False
    same = meta.get("rules") == RULES and (version is None or meta.get("version") == version)
    return same and all((cache / item["file"]).is_file() for item in meta.get("images", []))


# ---------------------------------------------------------------------------------------------- unpack


def _add_package(deb: Path, cache: Path, log: Callable[[str], None]) -> None:
    """Unpack, index, prune: the package's .json is written last, so an interrupted run redoes it."""
    name, version = _deb_field(deb, "Package"), _deb_field(deb, "Version")
    tree = cache / "packages" / name
    _package_json(cache, name).unlink(missing_ok=True)
    if tree.exists():
        shutil.rmtree(tree)
    log(f"{name}: unpacking {deb.name} ({deb.stat().st_size / 1e6:.0f} MB)")
    run = subprocess.run(["dpkg-deb", "-x", str(deb), str(tree)], capture_output=True, text=True)
    if run.returncode != 0:
        shutil.rmtree(tree, ignore_errors=True)
        raise LibraryError(f"{deb.name}: cannot be unpacked ({_last_error(run.stderr, 'dpkg-deb -x failed')})")
    licence, copyright_file = read_licence(tree, name)
    with _quiet_native_stderr():
        images, skipped = _index_tree(name, tree, cache)
    keep = {cache / i["file"] for i in images} | ({cache / copyright_file} if copyright_file else set())
    _prune(tree, keep)
    meta = {
        "package": name,
        "version": version,
        "rules": RULES,
        "licence": licence,
        "copyright": copyright_file,
        "skipped": dict(sorted(skipped.items())),
        "images": images,
    }
    _write_json(_package_json(cache, name), meta)
    log(_summary(name, images, skipped))


@contextlib.contextmanager
def _quiet_native_stderr() -> Iterator[None]:
    """Silence libpng's and OpenCV's C-level warnings (bad colour profiles and the like) while decoding
    thousands of files: unreadable files are counted instead. Python's own sys.stderr is untouched."""
    try:
        saved = os.dup(2)
    except OSError:  # no file descriptor 2 (embedded use): nothing to silence
        yield
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 2)
    try:
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)


def _summary(name: str, images: list[dict], skipped: Counter) -> str:
    counts = Counter((i["role"], i["split"]) for i in images)
    parts = [f"{role} {counts[role, 'train']} train / {counts[role, 'test']} test" for role in ROLES
             if counts[role, "train"] + counts[role, "test"]]
    skips = ", ".join(f"{n} {why}" for why, n in sorted(skipped.items(), key=lambda kv: -kv[1]))
    return f"{name}: {', '.join(parts) or 'no images'}" + (f"; skipped {skips}" if skips else "")


def read_licence(tree: Path, package: str) -> tuple[str, str]:
    """(licence short names from the `License:` fields, joined; copyright file relative to the cache)."""
    path = tree / "usr" / "share" / "doc" / package / "copyright"
    if not path.is_file():
        return "unknown (no copyright file)", ""
    names: list[str] = []
    for line in path.read_text(errors="replace").splitlines():
        if line.startswith("License:"):
            short = line[len("License:") :].strip()
            if short and short not in names:
                names.append(short)
    relative = path.relative_to(tree.parent.parent).as_posix()
    return (", ".join(names) or f"unknown (see {relative})"), relative


def _prune(tree: Path, keep: set[Path]) -> None:
    """Delete every file of the unpacked tree the index does not use, then the empty folders."""
    for folder, dirs, files in os.walk(tree, topdown=False):
        here = Path(folder)
        for file in files:
            if here / file not in keep:
                (here / file).unlink()
        for sub in dirs:
            path = here / sub
            if path.is_symlink():
                path.unlink()
            elif not any(path.iterdir()):
                path.rmdir()


def _write_json(path: Path, data: dict) -> None:
    write_atomic(path, json.dumps(data, indent=1, sort_keys=True) + "\n")


def _write_index(cache: Path) -> dict[str, dict]:
    """Rebuild index.json from every package indexed in the cache."""
    packages = {}
    for path in sorted((cache / "packages").glob("*.json")):
        try:
            meta = json.loads(path.read_text())
        except ValueError:
            continue
        if meta.get("rules") == RULES:
            packages[meta["package"]] = meta
    if packages:
        _write_json(cache / "index.json", {"format": FORMAT, "packages": packages})
    return packages


# ------------------------------------------------------------------------------------------------ index


@dataclass
class _Candidate:
    """An image worth judging: where its file is (or will be), its source, pixels, allowed roles."""

    file: Path
    source: str
    image: np.ndarray
    roles: tuple[str, ...] = ROLES
    group: str | None = None  # files with the same group are one picture (size variants)
    data: bytes | None = None  # bytes to write to `file` if kept (images extracted from an archive)


@dataclass
class _Pick:
    """A kept image before de-duplication."""

    candidate: _Candidate
    role: str
    width: int
    height: int
    fingerprint: int


def _index_tree(name: str, tree: Path, cache: Path) -> tuple[list[dict], Counter]:
    skipped: Counter = Counter()
    picks = []
    for cand in _candidates(name, tree, skipped):
        outcome = _judge(name, cand)
        if outcome not in ROLES:
            skipped[outcome] += 1
        elif outcome not in cand.roles:
            skipped[f"{outcome}s not used from this archive"] += 1
        else:
            height, width = cand.image.shape[:2]
            picks.append(_Pick(cand, outcome, width, height, _fingerprint(cand.image)))
            cand.image = np.empty(0, np.uint8)  # the pixels are no longer needed; keep memory flat
    records = [_record(name, pick, cache) for pick in _deduplicate(picks, skipped)]
    return sorted(records, key=lambda r: r["source"]), skipped


def _record(name: str, pick: _Pick, cache: Path) -> dict:
    cand = pick.candidate
    if cand.data is not None:
        cand.file.parent.mkdir(parents=True, exist_ok=True)
        cand.file.write_bytes(cand.data)
    return {
        "file": cand.file.relative_to(cache).as_posix(),
        "source": cand.source,
        "role": pick.role,
        "split": split_of(name, cand.source),
        "width": pick.width,
        "height": pick.height,
    }


def _candidates(name: str, tree: Path, skipped: Counter) -> Iterator[_Candidate]:
    """Each image file of the unpacked package worth judging (GCompris: the images inside its archives)."""
    if name == "gcompris-qt-data":
        yield from _rcc_candidates(tree, skipped)
        return
    for file in sorted(p for p in tree.rglob("*") if p.is_file() and not p.is_symlink()):
        source = "/" + file.relative_to(tree).as_posix()
        if source.startswith(("/usr/share/doc/", "/usr/share/icons/")) or file.suffix.lower() not in SEEN_SUFFIXES:
            continue
        reason = _by_path(name, source)
        image = None if reason else cv2.imread(str(file), cv2.IMREAD_UNCHANGED)
        if reason or image is None:
            skipped[reason or "unreadable"] += 1
        else:
            yield _Candidate(file, source, _as_uint8(image), group=_group(name, source))


def _rcc_candidates(tree: Path, skipped: Counter) -> Iterator[_Candidate]:
    """Images inside the Qt resource archives of the photo activities, decoded from memory."""
    for archive in sorted(tree.rglob("*.rcc")):
        roles = GCOMPRIS_PHOTO_ARCHIVES.get(archive.stem)
        if roles is None:
            skipped["archives of non-photo activities"] += 1
            continue
        try:
            rcc = RccArchive(archive.read_bytes())
            entries = list(rcc.entries())
        except RccError as exc:
            raise LibraryError(f"{archive.name}: {exc}") from None
        outer = "/" + archive.relative_to(tree).as_posix()
        for entry in entries:
            data = _rcc_image(rcc, entry, skipped)
            if data is None:
                continue
            image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
            if image is None:
                skipped["unreadable"] += 1
                continue
            file = tree / "rcc" / archive.stem / _safe_path(entry.path)
            yield _Candidate(file, f"{outer}:{entry.path}", _as_uint8(image), roles, data=data)


def _rcc_image(rcc: RccArchive, entry: RccEntry, skipped: Counter) -> bytes | None:
    suffix = Path(entry.path).suffix.lower()
    if suffix in (".svg", ".svgz"):
        skipped["svg (drawings)"] += 1
        return None
    if suffix not in IMAGE_SUFFIXES:
        return None
    if entry.compression == "zstd" and not zstd_available():
        skipped["zstd-compressed (no zstandard module)"] += 1
        return None
    try:
        return rcc.read(entry)
    except RccError:
        skipped["unreadable"] += 1
        return None


def _safe_path(inner: str) -> str:
    """An archive path as a relative file path: no '..', no odd characters."""
    parts = [re.sub(r"[^A-Za-z0-9._-]", "_", p) for p in inner.split("/") if p not in ("", ".", "..")]
    return "/".join(parts) or "unnamed"


def _group(name: str, source: str) -> str | None:
    """Files that are one picture by their path: a Plasma wallpaper folder, or `_WxH` size variants."""
    if name not in WALLPAPERS:
        return None
    folder = re.match(r"(.*/wallpapers/[^/]+)/contents/", source)
    if folder:
        return folder.group(1)
    return re.sub(r"[_-]\d+x\d+(?=\.[^.]+$)", "", source).rsplit(".", 1)[0]


# ------------------------------------------------------------------------------------------------ rules


def _by_path(name: str, source: str) -> str | None:
    """Why this file is skipped whatever its pixels (checked before decoding), or None."""
    suffix, file_name = Path(source).suffix.lower(), Path(source).name.lower()
    if suffix in (".svg", ".svgz"):
        return "svg (drawings)"
    if suffix == ".dds":
        return "dds (OpenCV cannot read it)"
    if name == "tuxpaint-stamps-default" and "/cartoon/" in source:
        return "cartoon stamps"
    if name == "flightgear-data-base":
        if "/Textures/Terrain" not in source:
            return "not a terrain texture"
        if FLIGHTGEAR_SKIP.search(file_name):
            return "masks, overlays and detail maps"
    if name in WALLPAPERS:
        if suffix not in (".jpg", ".jpeg"):
            return f"{suffix[1:]} (rendered artwork)"
        if "screenshot" in file_name:
            return "screenshots"
        if any(folder in source for folder in ARTWORK_FOLDERS):
            return "distribution artwork"
    return None


def _judge(name: str, cand: _Candidate) -> str:
    """The role for this image, or why it is skipped."""
    image = cand.image
    if min(image.shape[:2]) < MIN_SIDE:
        return f"smaller than {MIN_SIDE} px"
    if name == "tuxpaint-stamps-default":
        return _judge_stamp(image)
    if name == "flightgear-data-base":
        return _judge_terrain(image)
    if name in WALLPAPERS:
        return _judge_wallpaper(name, cand)
    return "target" if has_real_alpha(image) else "background"


def _judge_stamp(image: np.ndarray) -> str:
    if not has_real_alpha(image):
        return "no real alpha"
    opaque = image[:, :, 3] > 250
    return "target" if flat_fraction(image, opaque) < CLIP_ART_FLAT else "flat-shaded clip art"


def _judge_terrain(image: np.ndarray) -> str:
    if transparent_fraction(image) > 0.02:
        return "transparent blend layers"
    if _saturation(image) < GREY_SATURATION:
        return "grey detail maps"
    return "background"


def _judge_wallpaper(name: str, cand: _Candidate) -> str:
    image = cand.image
    if name in CAMERA_EXIF_ONLY and not camera_exif(_head(cand.file)):
        return "jpg without camera EXIF (rendered artwork)"
    height, width = image.shape[:2]
    y, x = max(0, height // 2 - 256), max(0, width // 2 - 256)
    if flat_fraction(image[y : y + 512, x : x + 512]) >= GRADIENT_FLAT:
        return "smooth gradients"
    return "background"


# ---------------------------------------------------------------------------------------- image measures


def _head(file: Path, size: int = 1 << 18) -> bytes:
    with file.open("rb") as handle:
        return handle.read(size)


def camera_exif(jpeg: bytes) -> dict[str, str]:
    """Make and Model from a JPEG's EXIF (first IFD); {} when there are none (renders, stripped files)."""
    if jpeg[:2] != b"\xff\xd8":
        return {}
    at = 2
    while at + 4 <= len(jpeg) and jpeg[at] == 0xFF:
        marker, (size,) = jpeg[at + 1], struct.unpack_from(">H", jpeg, at + 2)
        if marker == 0xE1 and jpeg[at + 4 : at + 10] == b"Exif\x00\x00":
            return _tiff_camera(jpeg[at + 10 : at + 2 + size])
        if marker in (0xD9, 0xDA):  # end of image, start of scan: no EXIF before the pixels
            return {}
        at += 2 + size
    return {}


def _tiff_camera(tiff: bytes) -> dict[str, str]:
    order = {b"II": "<", b"MM": ">"}.get(tiff[:2])
    try:
        (ifd,) = struct.unpack_from(f"{order}I", tiff, 4)
        (count,) = struct.unpack_from(f"{order}H", tiff, ifd)
        out = {}
        for k in range(count):
            at = ifd + 2 + 12 * k
            tag, kind, n, offset = struct.unpack_from(f"{order}HHII", tiff, at)
            if tag in (0x010F, 0x0110) and kind == 2:  # Make, Model (ASCII)
                raw = tiff[offset : offset + n] if n > 4 else tiff[at + 8 : at + 8 + n]
                text = raw.split(b"\x00")[0].decode("latin-1").strip()
                if text:
                    out["Make" if tag == 0x010F else "Model"] = text
        return out
    except (struct.error, TypeError):  # TypeError: no byte order mark (order None)
        return {}


def _as_uint8(image: np.ndarray) -> np.ndarray:
    if image.dtype == np.uint16:
        image = (image >> 8).astype(np.uint8)
    elif image.dtype != np.uint8:
        image = np.clip(image, 0, 255).astype(np.uint8)
    return image


def _as_bgra(image: np.ndarray) -> np.ndarray:
    image = _as_uint8(image)
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2BGRA)
    if image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2BGRA)
    return image


def _bgr(image: np.ndarray) -> np.ndarray:
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    return image[:, :, :3]


def transparent_fraction(image: np.ndarray) -> float:
    """Fraction of pixels with alpha below one half (0 without an alpha channel)."""
    if image.ndim != 3 or image.shape[2] != 4:
        return 0.0
    return float((image[:, :, 3] < 128).mean())


def has_real_alpha(image: np.ndarray) -> bool:
    """An alpha channel that cuts an object out: 2-95 % of the pixels transparent."""
    return 0.02 <= transparent_fraction(image) <= 0.95


def flat_fraction(image: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Fraction of horizontally neighbouring pixel pairs (both inside mask) with exactly the same colour.

    Photographs have sensor noise and texture, so nearly no two neighbours are equal; drawings and
    rendered gradients have large runs of identical pixels.
    """
    bgr = _bgr(image).astype(np.int16)
    same = (bgr[:, 1:] == bgr[:, :-1]).all(axis=2)
    if mask is not None:
        both = mask[:, 1:] & mask[:, :-1]
        return float(same[both].mean()) if both.sum() >= 100 else 1.0
    return float(same.mean()) if same.size else 1.0


def _saturation(image: np.ndarray) -> float:
    return float(cv2.cvtColor(np.ascontiguousarray(_bgr(image)), cv2.COLOR_BGR2HSV)[:, :, 1].mean())


def _fingerprint(image: np.ndarray) -> int:
    """64-bit difference hash of the picture (alpha composited on black): equal-ish for resized copies."""
    thumb = cv2.resize(image, (36, 32), interpolation=cv2.INTER_AREA).astype(np.float32)
    bgr = _bgr(thumb)
    if thumb.ndim == 3 and thumb.shape[2] == 4:
        bgr = bgr * (thumb[:, :, 3:4] / 255.0)
    grey = cv2.cvtColor(np.ascontiguousarray(bgr), cv2.COLOR_BGR2GRAY)
    small = cv2.resize(grey, (9, 8), interpolation=cv2.INTER_AREA)
    bits = (small[:, 1:] > small[:, :-1]).ravel()
    return int(sum(1 << k for k, bit in enumerate(bits) if bit))


def _deduplicate(picks: list[_Pick], skipped: Counter) -> list[_Pick]:
    """Keep the largest of each path group and of each set of near-identical fingerprints."""
    kept: list[_Pick] = []
    groups: set[str] = set()
    for pick in sorted(picks, key=lambda p: (-p.width * p.height, p.candidate.source)):
        group = pick.candidate.group or pick.candidate.source
        if group in groups or any((pick.fingerprint ^ k.fingerprint).bit_count() <= DUPLICATE_BITS for k in kept):
            skipped["near duplicates"] += 1
            continue
        groups.add(group)
        kept.append(pick)
    return kept
