"""Niantic ``.spz`` files (numpy; ``zstandard`` for version 4).

Every version is read; version 4 (the default) or 3 (or 2) is written.
All integers are little-endian.  A file holds ``N`` splats as six attribute
blocks, in this order::

    positions  N x 3 x int24   fixed point: value = int * 2**-fractional_bits
                               (version 1: N x 3 x float16)
    alphas     N x uint8       255 * sigmoid(opacity)
    colours    N x 3 x uint8   255 * (0.5 + 0.15 * f_dc)   (0.15, not SH_C0)
    scales     N x 3 x uint8   16 * (log_scale + 10)
    rotations  versions 1-2:  N x 3 x uint8   x, y, z of the unit quaternion
                              with w >= 0, 127.5 * q + 127.5 (w derived)
               versions 3-4:  N x uint32      "smallest three": bits 30-31 the
                              index (x, y, z, w = 0..3) of the largest |q_i|,
                              made positive; then for the other three in
                              index order, highest bits first, a sign bit and
                              a 9-bit magnitude round(511 * |q_i| * sqrt 2)
    sh         N x K x 3 x uint8  degree 1-3 coefficients (K = 3, 8, 15),
                              coefficient-major, channel last (as sh_rest):
                              128 + 128 * c, rounded to buckets of 8 (degree 1)
                              or 16 (degrees 2-3) units

Versions 1-3: one gzip stream holding a 16-byte header ``magic "NGSP",
u32 version, u32 N, u8 sh_degree, u8 fractional_bits, u8 flags, u8 0``, the
blocks back to back, then (flag 0x2) extension records (a stream stored
without gzip is read too, as splat-transform does).  Version 4: a plain
32-byte header (the same fields, then ``u8 stream count, u32 toc_offset,
12 zero bytes``), extension records from byte 32 to ``toc_offset`` (flag
0x2), a table of ``u64 compressed, u64 uncompressed`` size per stream, then
one ZSTD stream per non-empty block (5 streams at degree 0, else 6) ending
exactly at the end of the file.  Flag 0x1 marks a scene trained with
anti-aliasing (mip-splatting).  Extension records are ``u32 type,
u32 length, payload``; unknown types are skipped by their length.

Coordinates.  The SPZ specification says the data is stored in RUB axes
(x right, y up, z back) and Niantic's library converts on load and save
when told the caller's axes; but its PLY converter and splat-transform (the
tools that make most files) pass "unspecified", so the bytes hold the PLY's
own axes unchanged (nianticlabs/spz issue #84; splat-transform's
``makeSpzPackOptions``).  This module does the same: values are read and
written as stored, in the PLY (RDF: x right, y down, z forward) convention,
and no extension is written.  A file that carries Adobe's coordinate-system
extension (``SPZ_ADOBE_coordinate_system``, type 0xADBE0003, payload the
u32 frame 1-16 of Niantic's ``CoordinateSystem``, e.g. 4 = RUB, 12 = RFU)
is converted from that frame to RDF: positions ``p -> M p`` with ``M`` the
signed permutation between the frames; rotations so that the covariance
becomes ``M S M^T`` (sign flips conjugate the quaternion as Niantic does; the
Z-up frames add the 90 degree turn about x); SH by the exact transform of
each band under ``M`` (sign flips per coefficient, rotations mixing within a
band).  Frame 0 ("unspecified", which Niantic's library reads as RUB) and
unknown values leave the data as stored (the latter with a warning).  Known difference: Blender 5.3's own SPZ
importer assumes RUB (file ``(x, y, z)`` becomes Blender ``(x, -z, y)``),
so a file from these tools opens upside down there but the right way round
here, in splat-transform and in Niantic's converter.

Anti-aliasing.  A file with flag 0x1 is read with the comment
``antialiased 1`` in :attr:`SplatArrays.comments` (Postshot's PLY header
comment, which splat-transform also reads).  The writer sets the flag when
the last of the comments ``antialiased 0|1`` or ``SplatRenderMode:
default|mip|2dgs`` (Brush's; case-insensitive) says so, as splat-transform
does for PLY input.

Writing follows Niantic's library (the one splat-transform runs) in its
float32 arithmetic and round-half-away-from-zero rounding: ``fractional_bits``
12, SH buckets of 5 bits (degree 1) and 4 bits (degrees 2-3), ZSTD level 12
(version 4), deflate level 6 with memory level 9 (versions 2-3); on the
test scenes the files are byte for byte those splat-transform 3.7.0 writes
from the same PLY.
Quantisation bounds of a file written here, for a value inside the format's
range (float32 rounding adds up to 1e-6 where a value is computed in float32):

- positions: within ``0.5 / 4096 = 1.2e-4``; the range is
  ``[-2048, 2047.9998]``: a position outside it is an error naming the
  splat (it would wrap around);
- log scales: within ``1/32`` on ``[-10, 5.94]``, clamped outside;
- alpha ``sigmoid(opacity)``: within ``0.5 / 255``; bytes 0 and 255 read
  as logits -13.8 and 13.8 (as splat-transform; Niantic's newest loader
  clamps them to alphas 1/255 and 254/255);
- ``f_dc``: within ``0.5 / 255 / 0.15 = 0.0131`` on ``[-3.33, 3.33]``,
  clamped outside;
- SH rest: within ``(b/2 + 0.5) / 128`` of ``clip(c, -1, 127/128)``, with
  ``b`` the bucket (8 or 16 units): 0.0352 for degree 1, 0.0664 for degrees
  2-3 (half a bucket plus the half unit of the first rounding to 1/128);
- rotation matrices: each entry within 0.004 for versions 3-4 (the three
  stored components are within ``0.5 / 511 / sqrt 2 = 6.9e-4`` each, the
  derived largest one, at least 1/2, within ``3 * 6.9e-4``; measured 0.0031
  over 2 million random rotations) and 0.2 for version 2 (8-bit x, y, z; w
  derived from them is poorly conditioned near w = 0; measured 0.196).

SH degree 4 files are refused (mlx3d supports degree 0-3).
"""

from __future__ import annotations

import os
import struct
import warnings
import zlib
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..errors import SplatFormatError
from ..sh_basis import rotate_sh_rest, sh_rest_rotation
from ..transforms import quaternion_multiply
from .atomic import atomic_write
from .codec import logit
from .ply import SplatArrays

__all__ = ["COORDINATE_SYSTEMS", "frame_matrix", "read_spz", "sh_transform", "sniff_spz", "write_spz"]

MAGIC = b"NGSP"
FLAG_ANTIALIASED = 0x1
FLAG_EXTENSIONS = 0x2
COLOR_SCALE = 0.15
#: Fractional bits of the positions this writer stores (Niantic's choice).
FRACTIONAL_BITS = 12
#: Bits kept of each degree-1 / higher SH coefficient (Niantic's defaults).
SH1_BITS, SH_REST_BITS = 5, 4
ZSTD_LEVEL = 12
EXT_COORDINATE_SYSTEM = 0xADBE0003

#: Niantic's ``CoordinateSystem`` values: the directions of axes 0, 1, 2
#: (Left/Right, Up/Down, Front/Back).  PLY is RDF.
COORDINATE_SYSTEMS = {
    1: "LDB", 2: "RDB", 3: "LUB", 4: "RUB", 5: "LDF", 6: "RDF", 7: "LUF", 8: "RUF",
    9: "LFD", 10: "RFD", 11: "LFU", 12: "RFU", 13: "LBD", 14: "RBD", 15: "LBU", 16: "RBU",
}

_LEGACY_HEADER = struct.Struct("<4sIIBBBB")
_V4_HEADER = struct.Struct("<4sIIBBBBI12x")
_BLOCKS = ("positions", "alphas", "colours", "scales", "rotations", "sh")
_SH_DIM = (0, 3, 8, 15, 24)
_F32 = np.float32
_SQRT1_2_F32 = np.float32(0.7071067811865476)


# --------------------------------------------------------------------------
# Detection and reading
# --------------------------------------------------------------------------

def sniff_spz(head: bytes, path: str) -> bool:
    """Whether ``head`` starts an SPZ file: ``NGSP``, or gzip holding ``NGSP``."""
    if head.startswith(MAGIC):
        return True
    if not head.startswith(b"\x1f\x8b"):
        return False
    try:
        return zlib.decompressobj(31).decompress(head, 4) == MAGIC
    except zlib.error:
        return False


def read_spz(path: str | os.PathLike) -> SplatArrays:
    """Read a ``.spz`` file (version 1-4, SH degree 0-3) into :class:`SplatArrays`.

    Values are as stored unless the file names its axes (see the module
    docstring); the anti-aliasing flag becomes the comment ``antialiased 1``.
    Raises :class:`SplatFormatError` naming the file and the problem.
    """
    path = os.fspath(path)
    with open(path, "rb") as f:
        data = f.read()
    if data.startswith(b"\x1f\x8b"):
        raw = _gunzip(path, data)
        if not raw.startswith(MAGIC):
            raise SplatFormatError(
                f"{path}: not an SPZ file: the gzip data starts with {raw[:4]!r}, not {MAGIC!r}")
        blocks, ext, header = _parse_legacy(path, raw, "gzip data")
    elif data.startswith(MAGIC):
        if len(data) < 8:
            raise SplatFormatError(f"{path}: truncated SPZ header: {len(data)} bytes")
        if struct.unpack_from("<I", data, 4)[0] >= 4:
            blocks, ext, header = _parse_v4(path, data)
        else:  # an uncompressed legacy stream (splat-transform reads these too)
            blocks, ext, header = _parse_legacy(path, data, "file")
    else:
        what = "empty file (0 bytes)" if not data else f"its first bytes {data[:4]!r} are neither {MAGIC!r} nor gzip"
        raise SplatFormatError(f"{path}: not an SPZ file: {what}")
    version, n, degree, fractional_bits, flags = header
    splats = _decode(blocks, n, version, degree, fractional_bits)
    frame = _coordinate_system(path, _extensions(path, ext) if flags & FLAG_EXTENSIONS else [])
    if frame is not None:
        splats = _to_rdf(splats, frame)
    if flags & FLAG_ANTIALIASED:
        splats.comments.append("antialiased 1")
    return splats


def _gunzip(path: str, data: bytes) -> bytes:
    d = zlib.decompressobj(31)
    try:
        raw = d.decompress(data)
    except zlib.error as exc:
        raise SplatFormatError(f"{path}: corrupt gzip stream ({exc})") from None
    if not d.eof:
        raise SplatFormatError(
            f"{path}: truncated gzip stream: it ends after {len(data)} bytes without its end marker")
    if d.unused_data:
        raise SplatFormatError(f"{path}: {len(d.unused_data)} unexpected bytes after the end of the gzip stream")
    return raw


def _check_header(path: str, version: int, n: int, degree: int, fractional_bits: int) -> None:
    if not 1 <= version <= 4:
        raise SplatFormatError(f"{path}: unsupported SPZ version {version} (this reader supports 1-4)")
    if degree == 4:
        raise SplatFormatError(
            f"{path}: SH degree 4 (band 4) is not supported: mlx3d reads SH up to degree 3")
    if degree > 4:
        raise SplatFormatError(f"{path}: invalid SH degree {degree} in the SPZ header (0-4 exist)")
    if fractional_bits > 24:
        raise SplatFormatError(f"{path}: invalid fractional bits {fractional_bits} in the SPZ header (at most 24)")


def _block_sizes(n: int, version: int, degree: int) -> list[int]:
    return [n * (6 if version == 1 else 9), n, 3 * n, 3 * n, n * (4 if version >= 3 else 3),
            3 * n * _SH_DIM[degree]]


def _parse_legacy(path: str, raw: bytes, what: str):
    """Header and blocks of a version 1-3 stream (already gunzipped)."""
    if len(raw) < _LEGACY_HEADER.size:
        raise SplatFormatError(
            f"{path}: truncated SPZ header: the {what} holds {len(raw)} bytes, the header needs 16")
    _, version, n, degree, fractional_bits, flags, _ = _LEGACY_HEADER.unpack_from(raw)
    _check_header(path, version, n, degree, fractional_bits)
    if version == 4:
        raise SplatFormatError(f"{path}: SPZ version 4 inside gzip; version 4 files are not gzip-compressed")
    blocks, pos = [], _LEGACY_HEADER.size
    for name, size in zip(_BLOCKS, _block_sizes(n, version, degree)):
        if pos + size > len(raw):
            raise SplatFormatError(
                f"{path}: truncated SPZ data: the {name} of {n} splats need {size} bytes at byte {pos} "
                f"of the {what}, only {len(raw) - pos} remain")
        blocks.append(raw[pos:pos + size])
        pos += size
    return blocks, raw[pos:], (version, n, degree, fractional_bits, flags)


def _parse_v4(path: str, data: bytes):
    """Header, extension bytes and decompressed blocks of a version 4 file."""
    if len(data) < _V4_HEADER.size:
        raise SplatFormatError(f"{path}: truncated SPZ header: {len(data)} bytes, version 4 needs 32")
    _, version, n, degree, fractional_bits, flags, count, toc = _V4_HEADER.unpack_from(data)
    _check_header(path, version, n, degree, fractional_bits)
    sizes = [s for s in _block_sizes(n, version, degree) if s]
    names = [b for b, s in zip(_BLOCKS, _block_sizes(n, version, degree)) if s]
    if count != len(sizes):
        raise SplatFormatError(
            f"{path}: the SPZ header lists {count} streams; {n} splats of SH degree {degree} need {len(sizes)}")
    if toc < _V4_HEADER.size:
        raise SplatFormatError(f"{path}: SPZ table of contents at byte {toc}, inside the 32-byte header")
    start = toc + 16 * count
    if start > len(data):
        raise SplatFormatError(
            f"{path}: truncated SPZ file: the table of contents ends at byte {start}, the file has {len(data)}")
    table = np.frombuffer(data, "<u8", 2 * count, toc).reshape(count, 2)
    pos = start
    spans = []
    for i, (name, size) in enumerate(zip(names, sizes)):
        packed, unpacked = int(table[i, 0]), int(table[i, 1])
        if unpacked != size:
            raise SplatFormatError(
                f"{path}: SPZ stream {i} ({name}) is listed as {unpacked} bytes uncompressed; "
                f"{n} splats need {size}")
        if packed > len(data) - pos:
            raise SplatFormatError(
                f"{path}: truncated SPZ file: stream {i} ({name}) needs {packed} bytes at byte {pos}, "
                f"only {len(data) - pos} remain")
        spans.append((pos, packed))
        pos += packed
    if pos != len(data):
        raise SplatFormatError(
            f"{path}: {len(data) - pos} unexpected bytes after the last SPZ stream (which ends at byte {pos})")
    zstd = _zstandard(path, "read")
    streams = {name: _unzstd(path, zstd, data[p:p + k], size, i, name)
               for i, ((p, k), size, name) in enumerate(zip(spans, sizes, names))}
    blocks = [streams.get(name, b"") for name in _BLOCKS]
    return blocks, data[_V4_HEADER.size:toc], (version, n, degree, fractional_bits, flags)


def _zstandard(path: str, verb: str):
    try:
        import zstandard
    except ImportError:
        raise SplatFormatError(
            f"{path}: SPZ version 4 is ZSTD-compressed; to {verb} it install the zstandard package "
            "(pip install zstandard)") from None
    return zstandard


def _unzstd(path: str, zstd, packed: bytes, size: int, index: int, name: str) -> bytes:
    """One stream's bytes (one or more ZSTD frames), exactly ``size`` of them."""
    out, rest = [], packed
    try:
        while True:
            d = zstd.ZstdDecompressor().decompressobj()
            out.append(d.decompress(rest))
            if not d.eof:
                raise SplatFormatError(
                    f"{path}: truncated ZSTD stream {index} ({name}): it stops after "
                    f"{sum(map(len, out))} of {size} bytes")
            rest = d.unused_data
            if not rest:
                break
    except zstd.ZstdError as exc:
        raise SplatFormatError(f"{path}: corrupt ZSTD stream {index} ({name}): {exc}") from None
    got = b"".join(out)
    if len(got) != size:
        raise SplatFormatError(
            f"{path}: ZSTD stream {index} ({name}) holds {len(got)} bytes; its table entry says {size}")
    return got


def _decode(blocks, n: int, version: int, degree: int, fractional_bits: int) -> SplatArrays:
    pos_b, alpha_b, colour_b, scale_b, rot_b, sh_b = blocks
    if version == 1:
        means = np.frombuffer(pos_b, "<f2").astype(np.float64)
    else:
        b = np.frombuffer(pos_b, np.uint8).reshape(-1, 3).astype(np.int32)
        fixed = b[:, 0] | (b[:, 1] << 8) | (b[:, 2] << 16)
        means = ((fixed ^ 0x800000) - 0x800000) * 2.0 ** -fractional_bits
    alphas = np.frombuffer(alpha_b, np.uint8) / 255.0
    colours = (np.frombuffer(colour_b, np.uint8) / 255.0 - 0.5) / COLOR_SCALE
    scales = np.frombuffer(scale_b, np.uint8) / 16.0 - 10.0
    if version >= 3:
        xyzw = _unpack_smallest_three(np.frombuffer(rot_b, "<u4"))
    else:
        xyz = np.frombuffer(rot_b, np.uint8).reshape(n, 3) / 127.5 - 1.0
        xyzw = np.concatenate([xyz, np.sqrt(np.maximum(0.0, 1.0 - (xyz * xyz).sum(1)))[:, None]], axis=1)
    k1 = _SH_DIM[degree]
    sh = (np.frombuffer(sh_b, np.uint8).astype(np.float32) - 128.0) / 128.0
    return SplatArrays(
        means=means.astype(np.float32).reshape(n, 3),
        scales=scales.astype(np.float32).reshape(n, 3),
        quats=xyzw[:, [3, 0, 1, 2]].astype(np.float32),
        opacities=logit(alphas).astype(np.float32),
        sh_dc=colours.astype(np.float32).reshape(n, 1, 3),
        sh_rest=sh.reshape(n, k1, 3),
    )


def _unpack_smallest_three(comp: np.ndarray) -> np.ndarray:
    """``(N, 4)`` float64 quaternions ``x, y, z, w`` from smallest-three words."""
    comp = comp.astype(np.uint32)
    largest = (comp >> 30).astype(np.intp)
    q = np.zeros((len(comp), 4))
    for i in range(3, -1, -1):  # the lowest bits hold the highest index
        other = largest != i
        mag = (comp & 0x1FF) * (np.sqrt(0.5) / 511.0)
        q[:, i] = np.where(other, np.where(((comp >> 9) & 1) == 1, -mag, mag), 0.0)
        comp = np.where(other, comp >> 10, comp)
    q[np.arange(len(q)), largest] = np.sqrt(np.maximum(0.0, 1.0 - (q * q).sum(1)))
    return q


def _extensions(path: str, ext: bytes) -> list[tuple[int, bytes]]:
    """The ``(type, payload)`` records of an extension block."""
    records, pos = [], 0
    while pos < len(ext):
        if len(ext) - pos < 8:
            raise SplatFormatError(
                f"{path}: truncated SPZ extension record at extension byte {pos}: "
                f"{len(ext) - pos} bytes, the record header needs 8")
        kind, length = struct.unpack_from("<II", ext, pos)
        if length > len(ext) - pos - 8:
            raise SplatFormatError(
                f"{path}: SPZ extension 0x{kind:08X} claims {length} bytes, "
                f"only {len(ext) - pos - 8} remain in the extension block")
        records.append((kind, ext[pos + 8:pos + 8 + length]))
        pos += 8 + length
    return records


def _coordinate_system(path: str, records) -> str | None:
    """The frame named by the first coordinate-system extension, if any (not RDF)."""
    for kind, payload in records:
        if kind != EXT_COORDINATE_SYSTEM:
            continue
        if len(payload) < 4:
            problem = f"a {len(payload)}-byte payload (it needs 4)"
        else:
            value = struct.unpack_from("<I", payload)[0]
            if value == 0:
                return None
            if value in COORDINATE_SYSTEMS:
                return None if value == 6 else COORDINATE_SYSTEMS[value]
            problem = f"the unknown coordinate system {value}"
        warnings.warn(
            f"{path}: SPZ coordinate-system extension 0xADBE0003 has {problem}; "
            "reading the values as stored", UserWarning, stacklevel=3)
        return None
    return None


# --------------------------------------------------------------------------
# Coordinate systems
# --------------------------------------------------------------------------

_DIRECTION = {"R": (0, 1.0), "L": (0, -1.0), "D": (1, 1.0), "U": (1, -1.0), "F": (2, 1.0), "B": (2, -1.0)}


def frame_matrix(frame: str) -> np.ndarray:
    """``(3, 3)`` signed permutation taking ``frame`` coordinates to RDF (PLY) ones."""
    m = np.zeros((3, 3))
    for axis, letter in enumerate(frame):
        row, sign = _DIRECTION[letter]
        m[row, axis] = sign
    return m


def sh_transform(m: np.ndarray, degree: int) -> np.ndarray:
    """``(K-1, K-1)`` block-diagonal map of ``sh_rest`` coefficients under ``p -> m p``.

    ``m`` is orthogonal (a rotation or reflection); band ``l`` of the result
    satisfies ``Y_l(m d) . (D_l c) == Y_l(d) . c``: :func:`mlx3d.sh_basis.sh_rest_rotation`.
    """
    return sh_rest_rotation(m, degree)


def _to_rdf(s: SplatArrays, frame: str) -> SplatArrays:
    """``s`` stored in ``frame`` axes, converted to RDF."""
    m = frame_matrix(frame)
    if frame[1] in "FB":  # Z-up frames: a quarter turn about x, then sign flips
        turn = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
        turn_q = np.array([np.sqrt(0.5), -np.sqrt(0.5), 0.0, 0.0])
    else:
        turn, turn_q = np.eye(3), np.array([1.0, 0.0, 0.0, 0.0])
    fx, fy, fz = np.diag(turn.T @ m)
    q = s.quats.astype(np.float64) * np.array([1.0, fy * fz, fx * fz, fx * fy])
    rest = s.sh_rest.astype(np.float64)
    return SplatArrays(
        means=(s.means.astype(np.float64) @ m.T).astype(np.float32),
        scales=s.scales, quats=quaternion_multiply(turn_q, q).astype(np.float32),
        opacities=s.opacities, sh_dc=s.sh_dc,
        sh_rest=rotate_sh_rest(rest, m).astype(np.float32),
        comments=list(s.comments))


# --------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------

def _round(x: np.ndarray) -> np.ndarray:
    """``std::round`` of float32 values (half away from zero), exactly, in float32."""
    x = np.asarray(x, _F32)
    whole = np.trunc(x)
    return np.where(np.abs(x - whole) == _F32(0.5), whole + np.sign(x), np.rint(x))


def _u8(x: np.ndarray) -> np.ndarray:
    return np.clip(_round(x), 0, 255).astype(np.uint8)


def _antialiased(comments) -> bool:
    """The anti-aliasing flag the comments set (the last deciding comment wins)."""
    flag = False
    for comment in comments:
        c = comment.strip().lower()
        if c.startswith("antialiased ") and c[12:].strip() in ("0", "1"):
            flag = c[12:].strip() == "1"
        elif c.startswith("splatrendermode:") and c[16:].strip() in ("default", "mip", "2dgs"):
            flag = c[16:].strip() == "mip"
    return flag


def _normalized_xyzw(quats: np.ndarray) -> np.ndarray:
    """``(N, 4)`` float32 ``x, y, z, w`` normalised in float32 as Niantic does (0 -> identity)."""
    q = np.asarray(quats, _F32)[:, [1, 2, 3, 0]]
    norm = np.sqrt(((q[:, 0] * q[:, 0] + q[:, 1] * q[:, 1]) + q[:, 2] * q[:, 2]) + q[:, 3] * q[:, 3])
    zero = norm == 0
    q = q / np.where(zero, _F32(1), norm)[:, None]
    q[zero] = (0, 0, 0, 1)
    return q


def _pack_smallest_three(q: np.ndarray) -> np.ndarray:
    mag_all = np.abs(q)
    largest = np.argmax(mag_all, axis=1)
    negate = q[np.arange(len(q)), largest] < 0
    comp = largest.astype(np.uint32)
    for i in range(4):
        mag = (_F32(511) * (mag_all[:, i] / _SQRT1_2_F32) + _F32(0.5)).astype(np.uint32)
        sign = ((q[:, i] < 0) ^ negate).astype(np.uint32)
        comp = np.where(largest != i, (comp << 10) | (sign << 9) | mag, comp)
    return comp.astype("<u4")


def _pack_first_three(q: np.ndarray) -> np.ndarray:
    s = np.where(q[:, 3:] < 0, _F32(-127.5), _F32(127.5))
    return _u8(q[:, :3] * s + _F32(127.5))


def _pack_positions(path: str, means: np.ndarray) -> np.ndarray:
    fixed = _round(np.asarray(means, _F32) * _F32(1 << FRACTIONAL_BITS))
    bad = ~((fixed >= -(1 << 23)) & (fixed < (1 << 23))).all(axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        lo, hi = -(1 << 23) / (1 << FRACTIONAL_BITS), ((1 << 23) - 0.5) / (1 << FRACTIONAL_BITS)
        raise SplatFormatError(
            f"{path}: splat {i} is at ({', '.join(f'{v:.6g}' for v in means[i])}), outside the "
            f"SPZ position range [{lo:g}, {hi:.7g}) (24-bit fixed point with {FRACTIONAL_BITS} "
            f"fractional bits); {int(bad.sum())} splat(s) are outside it")
    return fixed.astype("<i4").view(np.uint8).reshape(-1, 4)[:, :3]


def _pack_sh(rest: np.ndarray, rows: int = 2048) -> np.ndarray:
    """SH bytes ``(N, K-1, 3)``: 128 + 128 c rounded, then to a multiple of the bucket.

    Done in blocks of ``rows`` splats so the float32 temporaries stay in cache.
    """
    rest = np.asarray(rest, _F32)
    bucket = np.where(np.arange(rest.shape[1]) < 3, 1 << (8 - SH1_BITS), 1 << (8 - SH_REST_BITS))
    bucket = bucket.astype(_F32)[None, :, None]
    out = np.empty(rest.shape, np.uint8)
    for start in range(0, len(rest), rows):
        x = _round(rest[start:start + rows] * _F32(128))
        x += _F32(128) + bucket / 2
        x /= bucket
        np.floor(x, out=x)
        x *= bucket
        out[start:start + rows] = np.clip(x, 0, 255)
    return out


def _encode(path: str, splats: SplatArrays, version: int) -> list[bytes]:
    """The six attribute blocks of ``splats``."""
    n = splats.count
    with np.errstate(over="ignore"):
        alpha = _F32(1) / (_F32(1) + np.exp(-np.asarray(splats.opacities, _F32)))
    q = _normalized_xyzw(splats.quats)
    colours = np.asarray(splats.sh_dc, _F32).reshape(n, 3)
    return [
        _pack_positions(path, splats.means).tobytes(),
        _u8(alpha * _F32(255)).tobytes(),
        _u8(colours * (_F32(COLOR_SCALE) * _F32(255)) + _F32(127.5)).tobytes(),
        _u8((np.asarray(splats.scales, _F32) + _F32(10)) * _F32(16)).tobytes(),
        (_pack_smallest_three(q) if version >= 3 else _pack_first_three(q)).tobytes(),
        _pack_sh(splats.sh_rest).tobytes(),
    ]


def write_spz(path: str | os.PathLike, splats: SplatArrays, *, fsync: bool = True, version: int = 4) -> None:
    """Write ``splats`` as a ``.spz`` file of ``version`` 4 (default), 3 or 2, atomically.

    Values are stored as given (no axis conversion, no extension), as
    splat-transform and Niantic's PLY converter do.  Raises
    :class:`SplatFormatError` (before touching the disk) for a position
    outside ``[-2048, 2048)`` naming the splat, and when version 4 is asked
    for without the ``zstandard`` package.
    """
    path = os.fspath(path)
    if version not in (2, 3, 4):
        raise ValueError(f"SPZ version must be 2, 3 or 4; got {version!r}")
    blocks = _encode(path, splats, version)
    flags = FLAG_ANTIALIASED if _antialiased(splats.comments) else 0
    n, degree = splats.count, splats.sh_degree
    if version < 4:
        header = _LEGACY_HEADER.pack(MAGIC, version, n, degree, FRACTIONAL_BITS, flags, 0)
        gz = zlib.compressobj(6, zlib.DEFLATED, 31, 9)  # Niantic's settings: the peer's bytes
        out = [gz.compress(header + b"".join(blocks)), gz.flush()]
    else:
        zstd = _zstandard(path, "write")
        blocks = [b for b in blocks if b]
        with ThreadPoolExecutor(max_workers=max(1, min(len(blocks), os.cpu_count() or 1))) as pool:
            packed = list(pool.map(lambda b: zstd.ZstdCompressor(level=ZSTD_LEVEL).compress(b), blocks))
        header = _V4_HEADER.pack(MAGIC, version, n, degree, FRACTIONAL_BITS, flags, len(blocks),
                                 _V4_HEADER.size)
        toc = np.array([(len(p), len(b)) for p, b in zip(packed, blocks)], "<u8").tobytes()
        out = [header, toc, *packed]
    with atomic_write(path, "wb", fsync=fsync) as f:
        for part in out:
            f.write(part)
