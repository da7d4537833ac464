"""Read the OpenEXR images Blender writes for render passes (numpy + zlib only).

:func:`read_exr` returns every channel of a file as a ``(H, W)`` float32
array, keyed by its full channel name: ``"R"``, ``"G"``, ``"B"``, ``"A"`` for
a plain image; ``"ViewLayer.Combined.R"``, ``"ViewLayer.Depth.Z"``,
``"ViewLayer.Environment.R"`` (``"ViewLayer.Env.R"`` before Blender 5.0) ...
for a multi-layer render.

Supported: single-part scanline files and multi-part files of scanline parts
(Blender 5.x writes a multi-layer EXR as one part per pass, Blender 4.5 as a
single part holding every pass), pixel types HALF, FLOAT and UINT (all
returned as float32), compression NONE, ZIPS and ZIP.  Anything else (tiled or deep parts, PIZ/RLE/PXR24/B44/DWA compression,
subsampled channels) raises :class:`ExrError`, as does a truncated or
malformed file; every message names the file.

Orientation and extent: row 0 of each array is the data window's smallest
y, the *top* of the image (EXR pixel space has y increasing downwards, and
scanlines are stored top first in Blender's files); Blender's ``Image.pixels`` are the other way up (bottom row
first).  The arrays cover the file's ``dataWindow``, which for Blender's
renders equals the ``displayWindow``; when the two differ the data window's
pixels are returned as they are, neither cropped nor padded to the display
window.

Layout reference: "OpenEXR File Layout" (openexr.com).
"""

from __future__ import annotations

import os
import struct
import zlib
from dataclasses import dataclass

import numpy as np

from ..errors import Mlx3dError

__all__ = ["ExrError", "read_exr"]

_MAGIC = 20000630
_FLAG_SINGLE_TILE = 0x200
_FLAG_NON_IMAGE = 0x800
_FLAG_MULTI_PART = 0x1000
_KNOWN_FLAGS = 0x200 | 0x400 | 0x800 | 0x1000

# pixel type id -> (name, little-endian numpy dtype)
_PIXEL_TYPES = {0: ("UINT", "<u4"), 1: ("HALF", "<f2"), 2: ("FLOAT", "<f4")}

_COMPRESSION_NAMES = {
    0: "NONE", 1: "RLE", 2: "ZIPS", 3: "ZIP", 4: "PIZ", 5: "PXR24",
    6: "B44", 7: "B44A", 8: "DWAA", 9: "DWAB", 10: "HTJ2K256", 11: "HTJ2K32",
}
# supported compression id -> scanlines per chunk
_LINES_PER_CHUNK = {0: 1, 2: 1, 3: 16}


class ExrError(Mlx3dError, ValueError):
    """An EXR file is unreadable here: malformed, truncated or unsupported (the message says which)."""


@dataclass
class _Channel:
    name: str
    dtype: np.dtype


@dataclass
class _Part:
    index: int
    name: str | None
    channels: list[_Channel]
    compression: int
    x_min: int
    y_min: int
    width: int
    height: int
    chunk_count: int

    @property
    def lines_per_chunk(self) -> int:
        return _LINES_PER_CHUNK[self.compression]

    @property
    def row_bytes(self) -> int:
        return self.width * sum(c.dtype.itemsize for c in self.channels)


class _Cursor:
    """Bounds-checked little-endian reads from the file's bytes."""

    def __init__(self, data: bytes, path: str):
        self.data = data
        self.path = path
        self.pos = 0

    def fail(self, problem: str) -> ExrError:
        return ExrError(f"{self.path}: {problem}")

    def take(self, n: int, what: str) -> bytes:
        if n < 0:
            raise self.fail(f"{what} at byte {self.pos} has a negative size ({n})")
        if self.pos + n > len(self.data):
            raise self.fail(f"file is truncated (ends inside {what} at byte {self.pos})")
        out = self.data[self.pos:self.pos + n]
        self.pos += n
        return out

    def unpack(self, fmt: str, what: str) -> tuple:
        return struct.unpack("<" + fmt, self.take(struct.calcsize("<" + fmt), what))

    def cstring(self, what: str) -> str:
        end = self.data.find(b"\0", self.pos, self.pos + 256)
        if end < 0:
            if len(self.data) - self.pos < 256:
                raise self.fail(f"file is truncated (ends inside {what} at byte {self.pos})")
            raise self.fail(f"{what} at byte {self.pos} is not a NUL-terminated name of at most 255 bytes")
        raw = self.data[self.pos:end]
        self.pos = end + 1
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            raise self.fail(f"{what} at byte {self.pos} is not valid UTF-8") from None


def read_exr(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read every channel of an OpenEXR file.

    Args:
        path: an ``.exr`` file: single-part scanline, or multi-part with
            scanline parts; HALF/FLOAT/UINT channels; NONE, ZIPS or ZIP
            compression.

    Returns:
        ``{channel name: (H, W) float32 array}`` over the data window, row 0
        the top scanline (EXR y increases downwards).  In a multi-part file a
        part's channels keep their names when these already start with
        ``"<part name>."`` (as Blender writes them) and are prefixed with
        ``"<part name>."`` otherwise.

    Raises:
        ExrError (a ``ValueError``): the file is not an EXR, is truncated or
            malformed, or uses a feature listed above as unsupported; the
            message names the file and the problem.
    """
    path = os.fspath(path)
    with open(path, "rb") as fh:
        data = fh.read()
    cur = _Cursor(data, path)
    magic = struct.pack("<i", _MAGIC)
    if data[:4] != magic:
        if data and magic.startswith(data):
            raise cur.fail("file is truncated (ends inside the magic number)")
        raise cur.fail("not an OpenEXR file (bad magic number)")
    cur.pos = 4
    (version,) = cur.unpack("I", "the version field")
    _check_version(cur, version)
    multi_part = bool(version & _FLAG_MULTI_PART)
    parts = _read_headers(cur, multi_part)
    offsets = [_read_offsets(cur, part) for part in parts]
    out: dict[str, np.ndarray] = {}
    for part, part_offsets in zip(parts, offsets):
        rows = _read_part_rows(cur, part, part_offsets, multi_part)
        for name, plane in _split_channels(part, rows).items():
            key = _full_name(part, name) if multi_part else name
            if key in out:
                raise cur.fail(f"channel {key!r} appears in more than one part")
            out[key] = plane
    return out


def _check_version(cur: _Cursor, version: int) -> None:
    if version & 0xFF != 2:
        raise cur.fail(f"unsupported OpenEXR format version {version & 0xFF} (expected 2)")
    if version & ~0xFF & ~_KNOWN_FLAGS:
        raise cur.fail(f"unknown version flags 0x{version & ~0xFF & ~_KNOWN_FLAGS:x}")
    if version & _FLAG_SINGLE_TILE:
        raise cur.fail("tiled images are not supported (scanline images only)")
    if version & _FLAG_NON_IMAGE:
        raise cur.fail("deep (non-image) data is not supported")


def _read_headers(cur: _Cursor, multi_part: bool) -> list[_Part]:
    if not multi_part:
        return [_read_header(cur, 0, multi_part)]
    parts = []
    while True:
        if cur.take(1, "the part headers") == b"\0":
            break
        cur.pos -= 1
        parts.append(_read_header(cur, len(parts), multi_part))
    if not parts:
        raise cur.fail("multi-part file has no parts")
    return parts


def _read_header(cur: _Cursor, index: int, multi_part: bool) -> _Part:
    attrs: dict[str, tuple[str, bytes]] = {}
    while True:
        name = cur.cstring("an attribute name")
        if not name:
            break
        type_name = cur.cstring(f"the type of attribute {name!r}")
        (size,) = cur.unpack("i", f"the size of attribute {name!r}")
        attrs[name] = (type_name, cur.take(size, f"attribute {name!r}"))
    where = f"part {index}" if multi_part else "header"

    def attr(name: str, type_name: str) -> bytes:
        if name not in attrs:
            raise cur.fail(f"{where} lacks the required attribute {name!r}")
        if attrs[name][0] != type_name:
            raise cur.fail(f"{where}: attribute {name!r} has type {attrs[name][0]!r}, expected {type_name!r}")
        return attrs[name][1]

    part_type = attrs["type"][1].decode("utf-8", "replace") if "type" in attrs else "scanlineimage"
    if part_type != "scanlineimage" or "tiles" in attrs:
        raise cur.fail(f"{where} is of type {part_type!r}: only scanline images are supported")
    compression = _unpack_exact(cur, attr("compression", "compression"), "B", f"{where} compression")[0]
    if compression not in _LINES_PER_CHUNK:
        label = _COMPRESSION_NAMES.get(compression, f"unknown ({compression})")
        raise cur.fail(f"{where} uses {label} compression: only NONE, ZIPS and ZIP are supported")
    x_min, y_min, x_max, y_max = _unpack_exact(cur, attr("dataWindow", "box2i"), "4i", f"{where} dataWindow")
    if x_max < x_min or y_max < y_min:
        raise cur.fail(f"{where} has an empty dataWindow ({x_min}, {y_min}, {x_max}, {y_max})")
    part = _Part(
        index=index,
        name=attr("name", "string").decode("utf-8", "replace") if multi_part or "name" in attrs else None,
        channels=_parse_chlist(cur, attr("channels", "chlist"), where),
        compression=compression,
        x_min=x_min, y_min=y_min, width=x_max - x_min + 1, height=y_max - y_min + 1,
        chunk_count=0,
    )
    expected = -(-part.height // part.lines_per_chunk)
    if multi_part:
        (part.chunk_count,) = _unpack_exact(cur, attr("chunkCount", "int"), "i", f"{where} chunkCount")
        if part.chunk_count != expected:
            raise cur.fail(f"{where}: chunkCount {part.chunk_count} does not match its data window ({expected})")
    else:
        part.chunk_count = expected
    return part


def _unpack_exact(cur: _Cursor, raw: bytes, fmt: str, what: str) -> tuple:
    if len(raw) != struct.calcsize("<" + fmt):
        raise cur.fail(f"{what} has {len(raw)} bytes, expected {struct.calcsize('<' + fmt)}")
    return struct.unpack("<" + fmt, raw)


def _parse_chlist(cur: _Cursor, raw: bytes, where: str) -> list[_Channel]:
    sub = _Cursor(raw, cur.path)
    channels = []
    while True:
        try:
            name = sub.cstring(f"{where} channel list")
            if not name:
                break
            pixel_type, _linear, x_sampling, y_sampling = sub.unpack("iB3xii", f"channel {name!r}")
        except ExrError:
            raise cur.fail(f"{where} has a malformed channel list") from None
        if pixel_type not in _PIXEL_TYPES:
            raise cur.fail(f"{where}: channel {name!r} has unknown pixel type {pixel_type}")
        if (x_sampling, y_sampling) != (1, 1):
            raise cur.fail(f"{where}: channel {name!r} is subsampled ({x_sampling}x{y_sampling}), not supported")
        channels.append(_Channel(name, np.dtype(_PIXEL_TYPES[pixel_type][1])))
    if not channels:
        raise cur.fail(f"{where} has no channels")
    return channels


def _read_offsets(cur: _Cursor, part: _Part) -> np.ndarray:
    raw = cur.take(8 * part.chunk_count, f"the offset table of part {part.index}")
    offsets = np.frombuffer(raw, dtype="<u8")
    if np.any(offsets >= len(cur.data)):
        raise cur.fail(f"part {part.index}'s offset table points past the end of the file (truncated or corrupt)")
    return offsets


def _read_part_rows(cur: _Cursor, part: _Part, offsets: np.ndarray, multi_part: bool) -> np.ndarray:
    """All scanlines of a part as raw bytes, shape ``(height, row_bytes)`` uint8."""
    rows = np.empty((part.height, part.row_bytes), dtype=np.uint8)
    seen = np.zeros(len(offsets), dtype=bool)
    for offset in offsets:
        cur.pos = int(offset)
        what = f"a pixel chunk of part {part.index} at byte {cur.pos}"
        if multi_part:
            (number,) = cur.unpack("i", what)
            if number != part.index:
                raise cur.fail(f"{what} belongs to part {number}")
        y, size = cur.unpack("ii", what)
        chunk = (y - part.y_min) // part.lines_per_chunk
        if (y - part.y_min) % part.lines_per_chunk or not 0 <= chunk < len(offsets) or seen[chunk]:
            raise cur.fail(f"{what} has an invalid or repeated scanline y={y}")
        seen[chunk] = True
        top = y - part.y_min
        lines = min(part.lines_per_chunk, part.height - top)
        block = _decompress(cur, part, cur.take(size, what), lines * part.row_bytes, what)
        rows[top:top + lines] = np.frombuffer(block, dtype=np.uint8).reshape(lines, part.row_bytes)
    return rows


def _decompress(cur: _Cursor, part: _Part, raw: bytes, expected: int, what: str) -> bytes:
    """Undo a chunk's compression; a chunk no smaller than its pixels is stored raw."""
    if part.compression == 0 or len(raw) >= expected:
        if len(raw) != expected:
            raise cur.fail(f"{what} has {len(raw)} bytes, expected {expected}")
        return raw
    try:
        out = zlib.decompress(raw)
    except zlib.error as exc:
        raise cur.fail(f"{what} is corrupt ({exc})") from None
    if len(out) != expected:
        raise cur.fail(f"{what} inflates to {len(out)} bytes, expected {expected}")
    return _unpredict(out)


def _unpredict(buf: bytes) -> bytes:
    """Reverse the ZIP filter: byte deltas (+128 bias), then the two-halves interleave."""
    d = np.frombuffer(buf, dtype=np.uint8).astype(np.int64)
    d[1:] -= 128
    t = (np.cumsum(d) & 0xFF).astype(np.uint8)
    out = np.empty_like(t)
    half = (len(t) + 1) // 2
    out[0::2] = t[:half]
    out[1::2] = t[half:]
    return out.tobytes()


def _split_channels(part: _Part, rows: np.ndarray) -> dict[str, np.ndarray]:
    """Cut ``(height, row_bytes)`` scanlines into one ``(height, width)`` float32 plane per channel."""
    planes = {}
    start = 0
    for ch in part.channels:
        stop = start + part.width * ch.dtype.itemsize
        plane = np.ascontiguousarray(rows[:, start:stop]).view(ch.dtype)
        planes[ch.name] = plane.astype(np.float32)
        start = stop
    return planes


def _full_name(part: _Part, name: str) -> str:
    if not part.name or name.startswith(part.name + "."):
        return name
    return f"{part.name}.{name}"
