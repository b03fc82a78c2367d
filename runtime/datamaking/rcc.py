"""Reader for Qt binary resource archives (`.rcc`, as written by `rcc -binary`), pure Python.

Layout (all integers big-endian), format versions 1 to 3:

    "qres", version u32, tree offset u32, data offset u32, names offset u32, [version >= 3: overall flags u32]

The tree is an array of fixed-size nodes (14 bytes, 22 from version 2 on: a u64 modification time follows),
node 0 being the root directory:

    name offset u32, flags u16 (1 zlib, 2 directory, 4 zstd),
    directory: child count u32, index of the first child node u32
    file:      territory u16, language u16, data offset u32

A name is u16 length, u32 hash, then that many UTF-16BE code units. A data blob is a u32 size and the bytes;
zlib blobs (Qt's qCompress) start with the u32 uncompressed size, zstd blobs are a plain zstd frame.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass

from ..errors import DadiffError

MAGIC = b"qres"
FLAG_ZLIB = 0x01
FLAG_DIRECTORY = 0x02
FLAG_ZSTD = 0x04


class RccError(DadiffError, ValueError):
    """The bytes are not a readable rcc archive (one-line message)."""


@dataclass(frozen=True)
class RccEntry:
    """One file in an archive: its path (starting with "/") and how its blob is stored."""

    path: str
    flags: int
    data_offset: int

    @property
    def compression(self) -> str:
        if self.flags & FLAG_ZSTD:
            return "zstd"
        return "zlib" if self.flags & FLAG_ZLIB else "none"


class RccArchive:
    """An rcc archive held in memory; `entries()` lists the files, `read(entry)` returns their bytes."""

    def __init__(self, data: bytes) -> None:
        if len(data) < 20 or data[:4] != MAGIC:
            raise RccError("not a Qt resource archive (no 'qres' header)")
        self.data = data
        self.version, self.tree, self.blobs, self.names = struct.unpack_from(">4I", data, 4)
        if not 1 <= self.version <= 3:
            raise RccError(f"unsupported rcc format version {self.version}")
        self.node_size = 14 if self.version == 1 else 22
        for offset in (self.tree, self.blobs, self.names):
            if offset >= len(data):
                raise RccError(f"rcc offset {offset} is past the end of the {len(data)}-byte archive")

    def _node(self, index: int) -> tuple[int, int, int, int]:
        """(name offset, flags, a, b): a, b are child count and first child, or locale and data offset."""
        at = self.tree + index * self.node_size
        if at + 14 > len(self.data):
            raise RccError(f"rcc tree node {index} is past the end of the archive")
        name, flags = struct.unpack_from(">IH", self.data, at)
        if flags & FLAG_DIRECTORY:
            count, first = struct.unpack_from(">II", self.data, at + 6)
            return name, flags, count, first
        locale, offset = struct.unpack_from(">II", self.data, at + 6)
        return name, flags, locale, offset

    def _name(self, offset: int) -> str:
        at = self.names + offset
        if at + 6 > len(self.data):
            raise RccError(f"rcc name offset {offset} is past the end of the archive")
        (length,) = struct.unpack_from(">H", self.data, at)
        raw = self.data[at + 6 : at + 6 + 2 * length]
        if len(raw) != 2 * length:
            raise RccError(f"rcc name at offset {offset} is cut off")
        return raw.decode("utf-16-be", errors="replace")

    def entries(self) -> Iterator[RccEntry]:
        """Every file, depth first in tree order; the walk is bounded so a corrupt tree cannot loop."""
        stack = [(0, "")]
        seen = 0
        while stack:
            index, prefix = stack.pop()
            seen += 1
            if seen > (len(self.data) - self.tree) // self.node_size + 1:
                raise RccError("rcc tree has more nodes than the archive can hold")
            name_offset, flags, a, b = self._node(index)
            path = prefix if index == 0 else f"{prefix}/{self._name(name_offset)}"
            if flags & FLAG_DIRECTORY:
                stack.extend((child, path) for child in reversed(range(b, b + a)))
            else:
                yield RccEntry(path or "/", flags, b)

    def read(self, entry: RccEntry) -> bytes:
        """The file's bytes, decompressed. Raises RccError (zstd without the `zstandard` module, bad data)."""
        at = self.blobs + entry.data_offset
        if at + 4 > len(self.data):
            raise RccError(f"{entry.path}: data offset past the end of the archive")
        (size,) = struct.unpack_from(">I", self.data, at)
        blob = self.data[at + 4 : at + 4 + size]
        if len(blob) != size:
            raise RccError(f"{entry.path}: data cut off ({len(blob)} of {size} bytes)")
        if entry.flags & FLAG_ZSTD:
            return _unzstd(blob, entry.path)
        if entry.flags & FLAG_ZLIB:
            return _unzlib(blob, entry.path)
        return blob


def _unzlib(blob: bytes, path: str) -> bytes:
    if len(blob) < 4:
        raise RccError(f"{path}: zlib data shorter than its length prefix")
    (expected,) = struct.unpack_from(">I", blob)
    try:
        out = zlib.decompress(blob[4:])
    except zlib.error as exc:
        raise RccError(f"{path}: bad zlib data ({exc})") from None
    if len(out) != expected:
        raise RccError(f"{path}: zlib data gives {len(out)} bytes, its prefix says {expected}")
    return out


def zstd_available() -> bool:
    """Whether zstd entries (Qt >= 5.13 may write them) can be read: needs the optional `zstandard` module."""
    try:
        import zstandard  # noqa: F401
    except ImportError:
        return False
    return True


def _unzstd(blob: bytes, path: str) -> bytes:
    try:
        import zstandard
    except ImportError:
        raise RccError(f"{path}: zstd-compressed and the 'zstandard' module is not installed") from None
    try:
        return zstandard.ZstdDecompressor().decompress(blob, max_output_size=1 << 30)
    except zstandard.ZstdError as exc:
        raise RccError(f"{path}: bad zstd data ({exc})") from None
