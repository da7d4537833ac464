"""PlayCanvas compressed PLY (``.compressed.ply``; numpy only).

A binary PLY (little-endian as written; big-endian read too) whose splats are
quantised in chunks of 256, in three elements, in this order::

    element chunk ceil(N / 256)     per chunk, float32:
        min_x min_y min_z max_x max_y max_z                  position bounds
        min_scale_x .. min_scale_z max_scale_x .. max_scale_z  log-scale bounds
        min_r min_g min_b max_r max_g max_b                  colour bounds (newer
                                                             files; older ones
                                                             lack these six)
    element vertex N                per splat, uint32 each:
        packed_position   x:11 | y:10 | z:11 bits (high to low), each a unorm
                          over the chunk's bounds: v = lo + (hi - lo) * q / (2^b - 1)
        packed_rotation   i:2 | a:10 | b:10 | c:10: ``i`` the index (in
                          ``rot_0..rot_3`` = w, x, y, z order) of the largest
                          component, made positive; a, b, c the other three in
                          order as ``(q / 1023 - 0.5) * sqrt(2)``; the largest is
                          ``sqrt(1 - a^2 - b^2 - c^2)``
        packed_scale      log scales, 11 | 10 | 11 bits over the chunk's bounds
        packed_color      r:8 | g:8 | b:8 | a:8: colour ``0.5 + SH_C0 * f_dc``
                          over the chunk's colour bounds (over [0, 1] without
                          them); ``a = sigmoid(opacity)`` over [0, 1]
    element sh N                    optional, uchar f_rest_0 .. f_rest_{3(K-1)-1}
                                    (9, 24 or 45: SH degree 1-3; channel-major as
                                    in PLY): byte ``b = trunc(256 * (v / 8 + 0.5))``
                                    clamped to 0..255, read back as
                                    ``8 * ((b + 0.5) / 256 - 0.5)``, 0 -> -4, 255 -> 4

Splat ``i`` uses chunk row ``i // 256``.  The writer writes what
splat-transform 3.7.0 writes, byte for byte but for the peer's ``comment``
line, a zero quaternion (the identity here, ``rot_3 = 1`` there), the sign
of a zero bound and a chunk range under 1e-5 (quantised here, all stored at
its minimum there): it first reorders the splats along a Morton (Z-order) curve
(:func:`morton_order`, the peer's order), so each chunk covers a small box
and its steps are small.  Keeping the input order would make chunks span
about the whole scene: on the 500-splat test scene the position error grows
from 0.00072 to 0.00104 at most (RMS 0.00027 to 0.00037; two chunks), on
100k random points in a unit cube the RMS error grows 3.5-6 times.  Readers
do not depend on the order (viewers sort by depth); reading keeps the file's.

Quantisation bounds (writer and reader together; raw units; "step" is the
chunk's ``hi - lo`` over ``2^b - 1``; each decoded value is also rounded to
float32 once):

- positions: half a step (11, 10, 11 bits for x, y, z);
- log scales: half a step of the chunk's range, which is clamped to
  [-20, 20] (a log scale beyond it is stored as +-20);
- ``f_dc``: half an 8-bit step of the chunk's colour range divided by
  ``SH_C0`` (no clamping: the bounds hold any colour); in a file without
  colour bounds, ``0.5 / 255 / SH_C0`` for colours in [0, 1];
- opacity: alpha within ``0.5 / 255``; alphas 0 and 1 read as logits
  -+13.8;
- rotation: the three stored components within ``h = sqrt(2) / 2046``; the
  rebuilt largest one (at least 1/2) within ``3 h``, so the unit quaternion
  within ``sqrt(12) h`` and the rotation matrix entries within twice that,
  0.005 (at most 0.0031 seen over 10^6 random rotations);
- ``sh_rest``: 1/64 for values in [-4 + 1/32, 4 - 1/32], 1/32 in [-4, 4]
  (the end bytes read as +-4); values outside [-4, 4] are clamped.
"""

from __future__ import annotations

import os

import numpy as np

from ..errors import SplatFormatError
from .atomic import atomic_write
from .codec import SH_C0, Bytes, logit
from .ply import SplatArrays, _read_header

__all__ = ["CHUNK_SIZE", "morton_order", "read_compressed_ply", "sniff_compressed_ply", "write_compressed_ply"]

#: Splats per chunk.
CHUNK_SIZE = 256

_POSITION_BOUNDS = ("min_x", "min_y", "min_z", "max_x", "max_y", "max_z")
_SCALE_BOUNDS = ("min_scale_x", "min_scale_y", "min_scale_z", "max_scale_x", "max_scale_y", "max_scale_z")
_COLOR_BOUNDS = ("min_r", "min_g", "min_b", "max_r", "max_g", "max_b")
_PACKED = ("packed_position", "packed_rotation", "packed_scale", "packed_color")
_SH_DEGREE_OF_COUNT = {9: 1, 24: 2, 45: 3}
_SCALE_LIMIT = 20.0
_ROT_NORM = 1.0 / (np.sqrt(2.0) * 0.5)  # smallest-three components lie in [-1/sqrt(2), 1/sqrt(2)]
# _OTHERS[i]: the components stored in packed_rotation when component i is the largest.
_OTHERS = np.array([[j for j in range(4) if j != i] for i in range(4)])


# --------------------------------------------------------------------------
# Detection
# --------------------------------------------------------------------------

def sniff_compressed_ply(head: bytes, path: str) -> bool:
    """Whether ``head`` starts a compressed PLY: a PLY header declaring a
    ``chunk`` element or a ``packed_position`` vertex property (a plain 3DGS
    PLY has neither)."""
    if not head.startswith((b"ply\n", b"ply\r\n")):
        return False
    element = None
    for raw in head.split(b"\n")[1:]:
        tokens = raw.split()
        if not tokens:
            continue
        if tokens[0] == b"end_header":
            break
        if tokens[0] == b"element" and len(tokens) == 3:
            element = tokens[1]
            if element == b"chunk":
                return True
        elif tokens[0] == b"property" and element == b"vertex" and tokens[-1] == b"packed_position":
            return True
    return False


# --------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------

def _unorm(bits: np.ndarray, count: int) -> np.ndarray:
    """The low ``count`` bits of ``bits`` as float64 in [0, 1]."""
    top = (1 << count) - 1
    return (bits & np.uint32(top)).astype(np.float64) / top


def _lerp(lo: np.ndarray, hi: np.ndarray, t: np.ndarray) -> np.ndarray:
    return lo * (1.0 - t) + hi * t


def _unpack_111011(packed: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """``(N, 3)`` float64 from 11-10-11-bit unorms over per-splat ``(N, 3)`` bounds."""
    t = np.stack([_unorm(packed >> 21, 11), _unorm(packed >> 11, 10), _unorm(packed, 11)], axis=1)
    return _lerp(lo, hi, t)


def _unpack_rotation(packed: np.ndarray) -> np.ndarray:
    """``(N, 4)`` float64 quaternions ``w, x, y, z`` from 2-10-10-10 smallest-three words."""
    n = len(packed)
    small = np.stack([(_unorm(packed >> s, 10) - 0.5) * _ROT_NORM for s in (20, 10, 0)], axis=1)
    largest = (packed >> 30).astype(np.intp)
    q = np.empty((n, 4))
    rows = np.arange(n)
    q[rows[:, None], _OTHERS[largest]] = small
    q[rows, largest] = np.sqrt(np.maximum(0.0, 1.0 - (small * small).sum(axis=1)))
    return q


def _sh_values(b: np.ndarray) -> np.ndarray:
    """float64 SH coefficients of quantised bytes (the ends exact at +-4)."""
    nrm = np.where(b == 0, 0.0, np.where(b == 255, 1.0, (b.astype(np.float64) + 0.5) / 256.0))
    return (nrm - 0.5) * 8.0


#: float32 SH coefficient of each byte.
_SH_OF_BYTE = _sh_values(np.arange(256)).astype(np.float32)


def _elements(path: str, header) -> tuple:
    """The ``chunk``, ``vertex`` and ``sh`` (or ``None``) elements, checked."""
    by_name = {e.name: e for e in header.elements}
    if header.byte_order is None:
        raise SplatFormatError(f"{path}: compressed PLY must be binary; this one is {header.fmt}")
    if "vertex" not in by_name:
        raise SplatFormatError(f"{path}: compressed PLY has no 'vertex' element")
    if "chunk" not in by_name:
        raise SplatFormatError(
            f"{path}: compressed PLY has no 'chunk' element (the per-256-splat bounds its packed "
            "vertex values are relative to)")
    for e in header.elements:
        lists = [p.name for p in e.props if p.is_list]
        if lists:
            raise SplatFormatError(
                f"{path}: element {e.name!r} has list propert(y/ies) {', '.join(lists)}; "
                "a compressed PLY has fixed-size rows only")
    chunk, vertex, sh = by_name["chunk"], by_name["vertex"], by_name.get("sh")

    def require(element, names, codes, what):
        types = {p.name: p.code for p in element.props}
        missing = [nm for nm in names if nm not in types]
        if missing:
            raise SplatFormatError(
                f"{path}: element {element.name!r} lacks the {what} propert(y/ies) {', '.join(missing)}")
        wrong = [f"{nm} ({types[nm]})" for nm in names if types[nm] not in codes]
        if wrong:
            raise SplatFormatError(
                f"{path}: element {element.name!r} has {what} propert(y/ies) of the wrong type: "
                f"{', '.join(wrong)}; expected {' or '.join(codes)}")

    numeric = ("f4", "f8", "i1", "u1", "i2", "u2", "i4", "u4")
    require(chunk, _POSITION_BOUNDS + _SCALE_BOUNDS, numeric, "bounds")
    present = [nm for nm in _COLOR_BOUNDS if nm in {p.name for p in chunk.props}]
    if present:
        require(chunk, _COLOR_BOUNDS, numeric, "colour bounds")
    require(vertex, _PACKED, ("u4", "i4"), "packed")
    chunks_needed = -(-vertex.count // CHUNK_SIZE)
    if chunk.count != chunks_needed:
        raise SplatFormatError(
            f"{path}: {vertex.count} splats need {chunks_needed} chunk rows of {CHUNK_SIZE} splats; "
            f"the file declares {chunk.count}")
    if sh is not None:
        if len(sh.props) not in _SH_DEGREE_OF_COUNT:
            raise SplatFormatError(
                f"{path}: element 'sh' has {len(sh.props)} properties; expected 9, 24 or 45 "
                "(SH degree 1, 2 or 3)")
        require(sh, [f"f_rest_{i}" for i in range(len(sh.props))], ("u1",), "SH")
        if sh.count != vertex.count:
            raise SplatFormatError(
                f"{path}: element 'sh' has {sh.count} rows but 'vertex' has {vertex.count}")
    return chunk, vertex, sh


def read_compressed_ply(path: str | os.PathLike) -> SplatArrays:
    """Read a compressed PLY file into :class:`SplatArrays`, in the file's order.

    Reads files with and without the chunk colour bounds and with or without
    the ``sh`` element.  Elements other than ``chunk``, ``vertex`` and ``sh``
    and other properties are skipped.  Raises :class:`SplatFormatError` for a
    malformed header, a missing element or property, counts that disagree
    (chunk rows vs ``ceil(N / 256)``, ``sh`` rows vs ``N``) or truncated data.
    """
    path = os.fspath(path)
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        header = _read_header(f, path, size)
        f.seek(0)
        data = f.read()
    chunk, vertex, sh = _elements(path, header)
    order = header.byte_order
    buf = Bytes(path, data, "compressed PLY")
    buf.seek(header.data_offset, "the header's end")
    tables = {}
    for e in header.elements:
        dtype = np.dtype([(p.name, order + p.code) for p in e.props])
        raw = buf.take(e.count * dtype.itemsize, f"element {e.name!r} ({e.count} rows of {dtype.itemsize} bytes)")
        tables[e.name] = np.frombuffer(raw, dtype)

    n = vertex.count
    ci = np.arange(n) // CHUNK_SIZE
    bounds = tables["chunk"]

    def per_splat(names):
        return np.stack([bounds[nm].astype(np.float64)[ci] for nm in names], axis=1)

    packed = {nm: tables["vertex"][nm].astype(np.uint32) for nm in _PACKED}
    means = _unpack_111011(packed["packed_position"], per_splat(_POSITION_BOUNDS[:3]),
                           per_splat(_POSITION_BOUNDS[3:]))
    scales = _unpack_111011(packed["packed_scale"], per_splat(_SCALE_BOUNDS[:3]), per_splat(_SCALE_BOUNDS[3:]))
    color = packed["packed_color"]
    rgb = np.stack([_unorm(color >> s, 8) for s in (24, 16, 8)], axis=1)
    if "min_r" in bounds.dtype.names:
        rgb = _lerp(per_splat(_COLOR_BOUNDS[:3]), per_splat(_COLOR_BOUNDS[3:]), rgb)
    if sh is None:
        rest = np.zeros((n, 0, 3), np.float32)
    else:
        k1 = len(sh.props) // 3
        column = {p.name: j for j, p in enumerate(sh.props)}
        # sh_rest[:, k, c] = f_rest_{c*k1 + k} (channel-major in the file).
        cols = [column[f"f_rest_{c * k1 + k}"] for k in range(k1) for c in range(3)]
        rest = _SH_OF_BYTE[tables["sh"].view(np.uint8).reshape(n, 3 * k1)[:, cols]].reshape(n, k1, 3)
    return SplatArrays(
        means=means.astype(np.float32),
        scales=scales.astype(np.float32),
        quats=_unpack_rotation(packed["packed_rotation"]).astype(np.float32),
        opacities=logit(_unorm(color, 8)).astype(np.float32),
        sh_dc=((rgb - 0.5) / SH_C0).astype(np.float32).reshape(n, 1, 3),
        sh_rest=rest,
        comments=list(header.comments),
    )


# --------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------

def _part1by2(v: np.ndarray) -> np.ndarray:
    """Spread the low 10 bits of ``v`` to every third bit (Morton interleave)."""
    v = v.astype(np.uint32) & np.uint32(0x3FF)
    v = (v ^ (v << np.uint32(16))) & np.uint32(0xFF0000FF)
    v = (v ^ (v << np.uint32(8))) & np.uint32(0x0300F00F)
    v = (v ^ (v << np.uint32(4))) & np.uint32(0x030C30C3)
    v = (v ^ (v << np.uint32(2))) & np.uint32(0x09249249)
    return v


def morton_order(means) -> np.ndarray:
    """``(N,)`` permutation putting ``(N, 3)`` finite positions in Morton (Z-curve) order.

    Positions are quantised to 10 bits per axis over their bounding box and
    stably sorted by the interleaved 30-bit code; every run of more than 256
    equal codes is sorted again over its own box (until its points coincide).
    This is splat-transform's order (``sortMortonOrder``).
    """
    pts_all = np.asarray(means, np.float64)
    n = len(pts_all)
    order = np.arange(n)
    starts, ends = np.array([0]), np.array([n])
    while len(starts) and n:
        lengths = ends - starts
        seg = np.repeat(np.arange(len(starts)), lengths)
        pos = np.arange(lengths.sum()) - np.repeat(np.cumsum(lengths) - lengths, lengths) + starts[seg]
        pts = pts_all[order[pos]]
        first = np.cumsum(lengths) - lengths
        lo = np.minimum.reduceat(pts, first, axis=0)
        ext = np.maximum.reduceat(pts, first, axis=0) - lo
        with np.errstate(divide="ignore"):
            mul = np.where(ext == 0.0, 0.0, 1024.0 / np.where(ext == 0.0, 1.0, ext))
        cells = np.minimum(1023.0, (pts - lo[seg]) * mul[seg]).astype(np.uint32)
        code = (_part1by2(cells[:, 2]) << np.uint32(2)) + (_part1by2(cells[:, 1]) << np.uint32(1)) \
            + _part1by2(cells[:, 0])
        sortable = (ext != 0.0).any(axis=1)
        code = np.where(sortable[seg], code, 0).astype(np.int64)
        key = (seg.astype(np.int64) << 30) | code
        perm = np.argsort(key, kind="stable")
        order[pos] = order[pos[perm]]
        # Runs of equal (segment, code) longer than a chunk are sorted again.
        key = key[perm]
        run_start = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
        run_end = np.r_[run_start[1:], len(key)]
        again = (run_end - run_start > CHUNK_SIZE) & sortable[seg[run_start]]
        starts, ends = pos[run_start[again]], pos[run_start[again]] + (run_end - run_start)[again]
    return order


def _normalize(x: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """``x`` over ``[lo, hi]`` clamped to [0, 1] (0 where ``hi <= lo``)."""
    span = hi - lo
    t = (x - lo) / np.where(span > 0.0, span, 1.0)
    return np.where(span > 0.0, np.clip(t, 0.0, 1.0), 0.0)


def _pack_unorm(t: np.ndarray, bits: int) -> np.ndarray:
    top = (1 << bits) - 1
    return np.clip(np.floor(t * top + 0.5), 0, top).astype(np.uint32)


def _pack_111011(t: np.ndarray) -> np.ndarray:
    return (_pack_unorm(t[..., 0], 11) << np.uint32(21)) | (_pack_unorm(t[..., 1], 10) << np.uint32(11)) \
        | _pack_unorm(t[..., 2], 11)


def _pack_rotation(quats: np.ndarray) -> np.ndarray:
    """2-10-10-10 smallest-three words of ``(N, 4)`` quaternions ``w, x, y, z``."""
    q = np.asarray(quats, np.float64)
    norm = np.sqrt(((q[:, 0] * q[:, 0] + q[:, 1] * q[:, 1]) + q[:, 2] * q[:, 2]) + q[:, 3] * q[:, 3])
    zero = norm == 0.0
    q = np.where(zero[:, None], [1.0, 0.0, 0.0, 0.0], q * (1.0 / np.where(zero, 1.0, norm))[:, None])
    rows = np.arange(len(q))
    largest = np.argmax(np.abs(q), axis=1)
    q = np.where(q[rows, largest][:, None] < 0.0, -q, q)
    small = q[rows[:, None], _OTHERS[largest]]
    codes = _pack_unorm(small * (np.sqrt(2.0) * 0.5) + 0.5, 10)
    return (largest.astype(np.uint32) << np.uint32(30)) | (codes[:, 0] << np.uint32(20)) \
        | (codes[:, 1] << np.uint32(10)) | codes[:, 2]


def _chunk_min_max(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-chunk min and max ``(C, D)`` of ``(N, D)`` values."""
    first = np.arange(0, len(values), CHUNK_SIZE)
    return np.minimum.reduceat(values, first, axis=0), np.maximum.reduceat(values, first, axis=0)


def _sh_bytes(rest: np.ndarray, order: np.ndarray) -> np.ndarray:
    """``(N, 3(K-1))`` uint8 ``sh`` rows of ``(N, K-1, 3)`` coefficients taken in ``order``.

    ``trunc(256 * (v / 8 + 0.5))`` clamped to 0..255, computed as the equal
    ``32 v + 128`` in float64, in blocks of splats to bound the temporaries.
    """
    n, k1 = len(order), rest.shape[1]
    out = np.empty((n, 3 * k1), np.uint8)
    for lo in range(0, n, 1 << 16):
        # f_rest_{c*k1 + k} = sh_rest[:, k, c]: channel-major columns.
        v = rest[order[lo:lo + (1 << 16)]].transpose(0, 2, 1).reshape(-1, 3 * k1).astype(np.float64)
        v *= 32.0
        v += 128.0
        out[lo:lo + len(v)] = np.clip(v, 0.0, 255.0, out=v)  # the cast truncates
    return out


def _encode(splats: SplatArrays) -> bytes:
    """The whole file's bytes (splats in Morton order)."""
    n = splats.count
    k1 = splats.sh_rest.shape[1]
    order = morton_order(splats.means)
    ci = np.arange(n) // CHUNK_SIZE

    means = np.asarray(splats.means, np.float64)[order]
    scales = np.asarray(splats.scales, np.float64)[order]
    rgb = (np.asarray(splats.sh_dc, np.float64).reshape(n, 3)[order] * SH_C0 + 0.5).astype(np.float32)
    rgb = rgb.astype(np.float64)
    alpha = 1.0 / (1.0 + np.exp(-np.asarray(splats.opacities, np.float64)[order]))

    p_lo, p_hi = _chunk_min_max(means)
    s_lo, s_hi = (np.clip(b, -_SCALE_LIMIT, _SCALE_LIMIT) for b in _chunk_min_max(scales))
    c_lo, c_hi = _chunk_min_max(rgb)

    vertex = np.empty((n, 4), "<u4")
    vertex[:, 0] = _pack_111011(_normalize(means, p_lo[ci], p_hi[ci]))
    vertex[:, 1] = _pack_rotation(np.asarray(splats.quats)[order])
    vertex[:, 2] = _pack_111011(_normalize(scales, s_lo[ci], s_hi[ci]))
    c = _normalize(rgb, c_lo[ci], c_hi[ci])
    vertex[:, 3] = (_pack_unorm(c[:, 0], 8) << np.uint32(24)) | (_pack_unorm(c[:, 1], 8) << np.uint32(16)) \
        | (_pack_unorm(c[:, 2], 8) << np.uint32(8)) | _pack_unorm(alpha, 8)
    chunks = np.concatenate([p_lo, p_hi, s_lo, s_hi, c_lo, c_hi], axis=1).astype("<f4")

    lines = ["ply", "format binary_little_endian 1.0", f"element chunk {len(chunks)}"]
    lines += [f"property float {nm}" for nm in _POSITION_BOUNDS + _SCALE_BOUNDS + _COLOR_BOUNDS]
    lines += [f"element vertex {n}"] + [f"property uint {nm}" for nm in _PACKED]
    parts = [chunks.tobytes(), vertex.tobytes()]
    if k1:
        parts.append(_sh_bytes(np.asarray(splats.sh_rest), order).tobytes())
        lines += [f"element sh {n}"] + [f"property uchar f_rest_{i}" for i in range(3 * k1)]
    lines.append("end_header\n")
    return "\n".join(lines).encode("ascii") + b"".join(parts)


def write_compressed_ply(path: str | os.PathLike, splats: SplatArrays, *, fsync: bool = True) -> None:
    """Write finite ``splats`` as a compressed PLY file, atomically.

    The splats are written in :func:`morton_order` (reading the file back
    gives them in that order); SH degree 1-3 goes into an ``sh`` element.
    """
    data = _encode(splats)
    with atomic_write(path, "wb", fsync=fsync) as f:
        f.write(data)
