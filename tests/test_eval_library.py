"""The real-photo scene library on tiny hand-built .deb packages: no network, no apt (a fake apt-get at most)."""

from __future__ import annotations

import json
import shutil
import struct
import subprocess
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from dadiff.runtime.commands.eval import main
from dadiff.runtime.datamaking import library as lib
from dadiff.runtime.datamaking.library import LibraryError, fetch, library_root, open_library, split_of
from dadiff.runtime.datamaking.rcc import FLAG_DIRECTORY, FLAG_ZLIB, FLAG_ZSTD, RccArchive, RccError

pytestmark = pytest.mark.skipif(shutil.which("dpkg-deb") is None, reason="needs dpkg-deb to build test packages")

GENERIC = "dadiff-test-photos"
COPYRIGHT = """Format: https://www.debian.org/doc/packaging-manuals/copyright-format/1.0/
Upstream-Name: test

Files: *
Copyright: 2026 nobody
License: GPL-2+

Files: photos/*
License: CC-BY-SA-4.0

License: GPL-2+
 License: text lines are indented, so they are not fields.
"""


# ------------------------------------------------------------------------------------------- test data


def _noise(h: int, w: int, seed: int) -> np.ndarray:
    """A photo-like picture: a smooth pattern plus sensor noise (no two neighbours alike)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w] / max(h, w)
    base = np.stack([128 + 90 * np.sin(6 * x + seed), 128 + 90 * np.cos(5 * y), 128 + 60 * np.sin(4 * (x + y))], 2)
    return np.clip(base + rng.normal(0, 6, (h, w, 3)), 0, 255).astype(np.uint8)


def _cutout(h: int, w: int, seed: int) -> np.ndarray:
    """BGRA: a photo-like ellipse on a transparent background."""
    alpha = np.zeros((h, w), np.uint8)
    cv2.ellipse(alpha, (w // 2, h // 2), (w // 3, h // 3), 0, 0, 360, 255, -1)
    return np.dstack([_noise(h, w, seed), alpha])


def _png(image: np.ndarray) -> bytes:
    return cv2.imencode(".png", image)[1].tobytes()


def _jpeg(image: np.ndarray, make: str | None = None) -> bytes:
    """A JPEG, with an EXIF APP1 segment naming a camera maker when `make` is given."""
    data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes()
    if make is None:
        return data
    text = make.encode() + b"\x00"
    tiff = b"MM\x00*" + struct.pack(">I", 8) + struct.pack(">H", 1)
    tiff += struct.pack(">HHII", 0x010F, 2, len(text), 8 + 2 + 12 + 4) + struct.pack(">I", 0) + text
    app1 = b"Exif\x00\x00" + tiff
    return data[:2] + b"\xff\xe1" + struct.pack(">H", len(app1) + 2) + app1 + data[2:]


SVG = b'<svg xmlns="http://www.w3.org/2000/svg" width="100" height="100"><circle r="40" cx="50" cy="50"/></svg>'


def build_rcc(files: list[tuple[str, bytes, int]], version: int = 3) -> bytes:
    """A Qt binary resource archive with one folder `images` holding `files` (name, stored bytes, flags)."""
    names, name_at = b"", {}
    for name in ["images", *[f[0] for f in files]]:
        name_at[name] = len(names)
        names += struct.pack(">HI", len(name), 0) + name.encode("utf-16-be")
    data, data_at = b"", []
    for _, stored, flags in files:
        if flags & FLAG_ZLIB:
            stored = struct.pack(">I", len(stored)) + zlib.compress(stored)
        data_at.append(len(data))
        data += struct.pack(">I", len(stored)) + stored
    stamp = b"\x00" * 8 if version >= 2 else b""
    tree = struct.pack(">IHII", 0, FLAG_DIRECTORY, 1, 1) + stamp  # root: one child, node 1
    tree += struct.pack(">IHII", name_at["images"], FLAG_DIRECTORY, len(files), 2) + stamp
    for (name, _, flags), offset in zip(files, data_at, strict=True):
        tree += struct.pack(">IHHHI", name_at[name], flags, 0, 0, offset) + stamp
    header = 24 if version >= 3 else 20
    data_offset, names_offset = header, header + len(data)
    tree_offset = names_offset + len(names)
    head = b"qres" + struct.pack(">4I", version, tree_offset, data_offset, names_offset)
    head += struct.pack(">I", 0) if version >= 3 else b""
    return head + data + names + tree


def build_deb(folder: Path, package: str, files: dict[str, bytes], version: str = "1.0-1") -> Path:
    """`dpkg-deb -b` of a package holding `files` (path inside the package -> bytes)."""
    root = folder / f"{package}-build"
    (root / "DEBIAN").mkdir(parents=True)
    (root / "DEBIAN" / "control").write_text(
        f"Package: {package}\nVersion: {version}\nArchitecture: all\nMaintainer: test <t@example.org>\n"
        "Description: dadiff library test package\n"
    )
    for path, data in files.items():
        (root / path).parent.mkdir(parents=True, exist_ok=True)
        (root / path).write_bytes(data)
    deb = folder / f"{package}_{version}_all.deb"
    subprocess.run(["dpkg-deb", "-Zgzip", "--root-owner-group", "-b", str(root), str(deb)], check=True,
                   capture_output=True)
    shutil.rmtree(root)
    return deb


def _packages(folder: Path) -> None:
    big = _noise(150, 200, 3)
    build_deb(folder, GENERIC, {
        "usr/share/test/photos/cutout.png": _png(_cutout(80, 96, 1)),
        "usr/share/test/photos/scene.jpg": _jpeg(_noise(120, 160, 2)),
        "usr/share/test/photos/big.png": _png(big),
        "usr/share/test/photos/big-small-copy.png": _png(cv2.resize(big, (100, 75), interpolation=cv2.INTER_AREA)),
        "usr/share/test/photos/tiny.png": _png(_noise(32, 32, 4)),
        "usr/share/test/logo.svg": SVG,
        "usr/share/test/README": b"not an image\n",
        f"usr/share/doc/{GENERIC}/copyright": COPYRIGHT.encode(),
    })
    erase = build_rcc([
        ("hand.png", _png(_cutout(90, 70, 5)), FLAG_ZLIB),
        ("sea.jpg", _jpeg(_noise(100, 140, 6)), 0),
        ("clip.svg", SVG, FLAG_ZLIB),
        ("packed.webp", b"(zstd frame)", FLAG_ZSTD),
    ])
    lang = build_rcc([("drawing.png", _png(_cutout(90, 90, 7)), 0)])
    build_deb(folder, "gcompris-qt-data", {
        "usr/share/gcompris-qt/rcc/erase.rcc": erase,
        "usr/share/gcompris-qt/rcc/lang.rcc": lang,
        "usr/share/doc/gcompris-qt-data/copyright": b"Files: *\nLicense: GPL-3+\n\nFiles: images/*\nLicense: CC0-1.0\n",
    })
    flat = np.zeros((100, 100, 4), np.uint8)
    cv2.circle(flat, (50, 50), 40, (0, 0, 255, 255), -1)
    build_deb(folder, "tuxpaint-stamps-default", {
        "usr/share/tuxpaint/stamps/animals/photo.png": _png(_cutout(120, 110, 8)),
        "usr/share/tuxpaint/stamps/shapes/disc.png": _png(flat),
        "usr/share/tuxpaint/stamps/shapes/star.svg": SVG,
    })
    build_deb(folder, "ukui-wallpapers", {
        "usr/share/backgrounds/camera.jpg": _jpeg(_noise(90, 160, 9), make="Canon"),
        "usr/share/backgrounds/render.jpg": _jpeg(_noise(90, 160, 10)),
        "usr/share/backgrounds/render.png": _png(_noise(90, 160, 11)),
        "usr/share/doc/ukui-wallpapers/copyright": b"License: CC-BY-SA-3.0\n",
    })


@pytest.fixture(scope="module")
def debs(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("debs")
    _packages(folder)
    return folder


@pytest.fixture(scope="module")
def fetched(debs, tmp_path_factory) -> tuple[Path, list[str]]:
    cache = tmp_path_factory.mktemp("cache") / "library"
    lines: list[str] = []
    fetch(None, cache, debs, log=lines.append)
    return cache, lines


def _sources(library, role: str) -> list[str]:
    return sorted(i.source for split in ("train", "test") for i in library.images(role, split))


# ----------------------------------------------------------------------------------------------- tests


def test_rcc_reader_lists_and_decompresses_entries():
    png = _png(_cutout(70, 70, 1))
    archive = RccArchive(build_rcc([("a.png", png, FLAG_ZLIB), ("b.txt", b"plain", 0)]))
    entries = list(archive.entries())
    assert [e.path for e in entries] == ["/images/a.png", "/images/b.txt"]
    assert [e.compression for e in entries] == ["zlib", "none"]
    assert archive.read(entries[0]) == png and archive.read(entries[1]) == b"plain"
    assert [e.path for e in RccArchive(build_rcc([("c.png", png, 0)], version=1)).entries()] == ["/images/c.png"]
    with pytest.raises(RccError, match="no 'qres' header"):
        RccArchive(b"PK\x03\x04" + bytes(40))


def test_fetch_picks_roles_and_records_licences(fetched):
    cache, lines = fetched
    library = open_library(cache)
    assert library is not None and library.root == cache
    assert _sources(library, "target") == [
        "/usr/share/gcompris-qt/rcc/erase.rcc:/images/hand.png",
        "/usr/share/test/photos/cutout.png",
        "/usr/share/tuxpaint/stamps/animals/photo.png",
    ]
    assert _sources(library, "background") == [
        "/usr/share/backgrounds/camera.jpg",  # the render.jpg beside it has no camera EXIF
        "/usr/share/gcompris-qt/rcc/erase.rcc:/images/sea.jpg",
        "/usr/share/test/photos/big.png",  # its smaller copy is a near duplicate
        "/usr/share/test/photos/scene.jpg",
    ]
    assert library.licences() == {
        GENERIC: "GPL-2+, CC-BY-SA-4.0",
        "gcompris-qt-data": "GPL-3+, CC0-1.0",
        "tuxpaint-stamps-default": "unknown (no copyright file)",
        "ukui-wallpapers": "CC-BY-SA-3.0",
    }
    index = json.loads((cache / "index.json").read_text())["packages"]
    assert index[GENERIC]["copyright"] == f"packages/{GENERIC}/usr/share/doc/{GENERIC}/copyright"
    assert (cache / index[GENERIC]["copyright"]).is_file()
    assert index[GENERIC]["skipped"] == {"near duplicates": 1, "smaller than 64 px": 1, "svg (drawings)": 1}
    skipped_gc = index["gcompris-qt-data"]["skipped"]
    assert skipped_gc["svg (drawings)"] == 1 and skipped_gc["archives of non-photo activities"] == 1
    zstd = "zstd-compressed (no zstandard module)"
    assert skipped_gc.get(zstd, 0) + skipped_gc.get("unreadable", 0) == 1
    assert index["tuxpaint-stamps-default"]["skipped"] == {"flat-shaded clip art": 1, "svg (drawings)": 1}
    assert any(line.startswith(f"{GENERIC}: target ") and "1 near duplicates" in line for line in lines)
    assert not (cache / "packages" / GENERIC / "usr/share/test/README").exists()  # pruned: not an indexed image


def test_images_load_with_the_right_shapes(fetched):
    library = open_library(fetched[0])
    for split in ("train", "test"):
        for image in library.images("target", split):
            pixels = image.load()
            assert pixels.dtype == np.uint8 and pixels.shape == (image.height, image.width, 4)
            assert image.path.is_file() and image.path.is_relative_to(library.root)
            assert image.licence == library.licences()[image.package]
        for image in library.images("background", split):
            assert image.load().shape == (image.height, image.width, 3)
    hand = next(i for s in ("train", "test") for i in library.images("target", s) if i.source.endswith("hand.png"))
    assert (hand.width, hand.height) == (70, 90) and hand.load()[0, 0, 3] == 0  # alpha kept
    broken = lib.LibraryImage(library.root / "gone.png", GENERIC, "/gone.png", "target", "train", "x", 1, 1)
    with pytest.raises(LibraryError, match="gone.png"):
        broken.load()
    with pytest.raises(LibraryError, match="unknown library role"):
        library.images("object", "train")


def test_split_is_a_stable_fifth_by_package_and_path(fetched):
    library = open_library(fetched[0])
    for split in ("train", "test"):
        for role in ("target", "background"):
            images = library.images(role, split)
            assert all(i.split == split == split_of(i.package, i.source) for i in images)
            assert images == sorted(images, key=lambda i: (i.package, i.source))
    splits = [split_of("pkg", f"/usr/share/x/{k}.png") for k in range(4000)]
    assert 0.17 < splits.count("test") / len(splits) < 0.23
    assert splits == [split_of("pkg", f"/usr/share/x/{k}.png") for k in range(4000)]
    assert split_of("a", "/x.png") == split_of("a", "/x.png")


def test_rerun_is_incremental(debs, tmp_path):
    cache = tmp_path / "lib"
    fetch([GENERIC], cache, debs, log=lambda _: None)
    image = open_library(cache).images("background", "train")[0].path
    before = (image.stat().st_mtime_ns, (cache / "index.json").read_text())
    lines: list[str] = []
    library = fetch([GENERIC, "ukui-wallpapers"], cache, debs, log=lines.append)
    assert f"{GENERIC}: already in the library, skipped" in lines
    assert any(line.startswith("ukui-wallpapers: background") for line in lines)
    assert image.stat().st_mtime_ns == before[0]
    assert set(library.licences()) == {GENERIC, "ukui-wallpapers"}


def test_cli_fetch_and_list(debs, tmp_path, capsys):
    cache = tmp_path / "lib"
    assert main(["data", "fetch", "--cache", str(cache), "--deb", str(debs), "--packages", GENERIC, "nosuch"]) == 0
    out = capsys.readouterr().out
    assert f"nosuch: not fetched: no nosuch_*.deb in {debs}" in out
    assert main(["data", "list", "--cache", str(cache)]) == 0
    rows = [line.split() for line in capsys.readouterr().out.splitlines()]
    assert rows[0] == ["package", "role", "train", "test", "licence"]
    counts = {(r[0], r[1]): int(r[2]) + int(r[3]) for r in rows[1:-1]}
    assert counts == {(GENERIC, "target"): 1, (GENERIC, "background"): 2}
    assert rows[1][4:] == ["GPL-2+,", "CC-BY-SA-4.0"]
    assert rows[-1][:3] == ["3", "images", "in"]


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith("dadiff-eval: error: ")
    return err[0]


def test_bad_input_is_one_line_and_exit_2(debs, tmp_path, capsys, monkeypatch):
    cache = str(tmp_path / "lib")
    assert main(["data", "fetch", "--cache", cache, "--deb", str(tmp_path / "nope")]) == 2
    assert "no such folder of .deb files" in _one_error_line(capsys)
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "broken_1.0_all.deb").write_bytes(b"!<arch>\nnot really")
    assert main(["data", "fetch", "--cache", cache, "--deb", str(bad)]) == 2
    assert "broken_1.0_all.deb: not a valid .deb" in _one_error_line(capsys)
    assert main(["data", "list", "--cache", str(tmp_path / "empty")]) == 2
    assert "no library in" in _one_error_line(capsys)
    repo = tmp_path / "repo"
    (repo / ".git").mkdir(parents=True)
    assert main(["data", "fetch", "--cache", str(repo / "data"), "--deb", str(debs)]) == 2
    assert "inside the git work tree" in _one_error_line(capsys)
    which = shutil.which
    monkeypatch.setattr(lib.shutil, "which", lambda tool: None if tool == "apt-get" else which(tool))
    assert main(["data", "fetch", "--cache", cache]) == 2
    assert "apt-get not found" in _one_error_line(capsys)


def test_apt_failures_are_one_line_each_and_the_rest_goes_on(debs, tmp_path, monkeypatch, capsys):
    """A stand-in apt-get: knows one package (copies its .deb), fails like apt for the others."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    script = bin_dir / "apt-get"
    script.write_text(
        "#!/bin/sh\n"
        f'if [ "$3" = "{GENERIC}" ]; then cp {debs}/{GENERIC}_*.deb . && exit 0; fi\n'
        'echo "Reading package lists..."; echo "E: Unable to locate package $3" >&2; exit 100\n'
    )
    script.chmod(0o755)
    monkeypatch.setenv("PATH", f"{bin_dir}:{Path(shutil.which('dpkg-deb')).parent}")
    cache = tmp_path / "lib"
    assert main(["data", "fetch", "--cache", str(cache), "--packages", "nosuch", GENERIC]) == 0
    out = capsys.readouterr().out.splitlines()
    assert "nosuch: not fetched: E: Unable to locate package nosuch" in out
    assert any(line.startswith(f"{GENERIC}: target") for line in out)
    assert main(["data", "fetch", "--cache", str(tmp_path / "other"), "--packages", "nosuch"]) == 2
    assert "no package could be fetched" in _one_error_line(capsys)


def test_library_root_and_empty_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("DADIFF_DATA_DIR", str(tmp_path / "data"))
    assert library_root() == tmp_path / "data"
    monkeypatch.delenv("DADIFF_DATA_DIR")
    assert library_root() == Path.home() / ".cache" / "dadiff" / "library"
    assert open_library(tmp_path) is None
    (tmp_path / "index.json").write_text("{not json")
    with pytest.raises(LibraryError, match="not a valid library index"):
        open_library(tmp_path)


def test_camera_exif_reads_make_only_when_present():
    picture = _noise(40, 60, 1)
    assert lib.camera_exif(_jpeg(picture, make="Canon")) == {"Make": "Canon"}
    assert lib.camera_exif(_jpeg(picture)) == {}
    assert lib.camera_exif(b"not a jpeg") == {}


def test_a_second_fetch_into_the_same_cache_is_refused_while_one_runs(debs, tmp_path):
    import fcntl

    cache = tmp_path / "lib"
    (cache / "packages").mkdir(parents=True)
    with (cache / ".lock").open("w") as held:
        fcntl.flock(held, fcntl.LOCK_EX)
        with pytest.raises(LibraryError, match="another fetch is writing"):
            fetch([GENERIC], cache, debs, log=lambda _: None)
    assert len(fetch([GENERIC], cache, debs, log=lambda _: None)) == 3


def _small_library(folder: Path, split: str = "train") -> Path:
    """A one-background library written directly (no .deb): for index and pack checks."""
    (folder / "images").mkdir(parents=True)
    (folder / "images" / "b.jpg").write_bytes(_jpeg(_noise(64, 80, 3)))
    image = {"file": "images/b.jpg", "source": "/b.jpg", "role": "background", "split": split, "width": 80,
             "height": 64}
    (folder / "index.json").write_text(json.dumps({"format": 1, "packages": {"pkg": {"licence": "MIT",
                                                                                      "images": [image]}}}))
    return folder


@pytest.mark.parametrize(("index", "key"), [({"packages": []}, "'packages'"),
                                            ({"packages": {"pkg": {"licence": "MIT", "images": [{}]}}},
                                             "'packages.pkg.images[0].file'")])
def test_a_malformed_index_is_one_line_naming_the_file_and_key(tmp_path, capsys, index, key):
    (tmp_path / "index.json").write_text(json.dumps(index))
    for argv in (["data", "list"], ["data", "pack", "--output", str(tmp_path / "pack")]):
        assert main([*argv, "--cache", str(tmp_path)]) == 2
        line = _one_error_line(capsys)
        assert "index.json: not a valid library index" in line and key in line, line


@pytest.mark.parametrize(("max_mib", "message"), [("nan", "expected a number above 0 and at most 65536, got 'nan'"),
                                                  ("inf", "expected a number above 0 and at most 65536, got 'inf'"),
                                                  ("0", "expected a number above 0")])
def test_pack_budget_must_be_finite_and_positive(tmp_path, capsys, max_mib, message):
    with pytest.raises(SystemExit) as exit_:
        main(["data", "pack", "--cache", str(_small_library(tmp_path / "lib")), "--output", str(tmp_path / "p"),
              "--max-mib", max_mib])
    assert exit_.value.code == 2
    line = _one_error_line(capsys)
    assert "--max-mib" in line and message in line, line


def test_pack_refuses_an_empty_result(tmp_path, capsys):
    """'packed  into P (0.0 MiB)' and exit 0 used to leave an empty pack."""
    library = str(_small_library(tmp_path / "lib"))
    assert main(["data", "pack", "--cache", library, "--output", str(tmp_path / "p1"), "--max-mib", "0.0001"]) == 2
    assert "no image fits in the pack budget of 104 bytes" in _one_error_line(capsys)
    assert not (tmp_path / "p1").exists()
    test_only = str(_small_library(tmp_path / "test_only", split="test"))
    assert main(["data", "pack", "--cache", test_only, "--output", str(tmp_path / "p2")]) == 2
    assert "no train images to pack" in _one_error_line(capsys)
    assert main(["data", "pack", "--cache", library, "--output", str(tmp_path / "p3")]) == 0
    assert "background/train 1" in capsys.readouterr().out
