"""GaussianSplats3D ``.ksplat`` files (mkkellogg's viewer; numpy only).

Little-endian throughout.  No magic number: a 4096-byte main header, one
1024-byte header per section, then each section's buckets and splats::

    main header (4096 bytes; the rest zero)
        0   u8      version major (0)          1   u8   version minor (>= 1)
        4   u32     section count (max)         8   u32  section count (loaded)
        12  u32     splat count (max)           16  u32  splat count (loaded)
        20  u16     compression level 0, 1 or 2
        24  f32 x3  scene centre (not used for reading)
        36  f32     SH minimum, 40 f32 SH maximum (level 2's 8-bit range;
                    0 reads as -1.5 / 1.5)
    section header (1024 bytes each; the rest zero)
        0   u32     splat count                 4   u32  splat capacity (records stored)
        8   u32     bucket size (splats in a full bucket)
        12  u32     bucket count                16  f32  bucket block size
        20  u16     bytes per bucket centre (12)
        24  u32     position quantisation range (0: 32767)
        28  u32     section byte size           32  u32  full bucket count
        36  u32     partial bucket count        40  u16  SH degree (0-2; 3 read)
    section data
        u32 x partial count     the partial buckets' splat counts
        f32 x3 x bucket count   bucket centres (levels 1 and 2 only)
        records x capacity      the full buckets' splats, then the partial ones'

A record, per compression level (0 | 1 | 2)::

    position  3 x f32 | 3 x u16: c + (q - R) * (B / 2) / R for the splat's
                        bucket centre c, block size B, range R
    scale     3 x f32 | 3 x f16: linear standard deviations exp(scale_i)
    rotation  4 x f32 | 4 x f16: unit quaternion w, x, y, z
    colour    4 x u8:   r, g, b = 255 * (0.5 + SH_C0 * f_dc), a = 255 * sigmoid(opacity)
    SH        K x f32 | K x f16 | K x u8 (lo + q / 255 * (hi - lo)):
              degree 1 as r0 r1 r2 g0 g1 g2 b0 b1 b2, then degree 2 the same
              with five coefficients per channel (K = 9 or 24); degree 3, a
              block of 21 that splat-transform reads, is read too.

The reader follows splat-transform 3.7.0's reader (the same decoded values; a
stored scale <= 0 reads as log scale -10, as there).  The writer writes one
section: at level 0 the splats in their order; at levels 1 and 2 grouped by
bucket as the original generator does (blocks of ``block_size`` from the
scene's minimum corner, up to ``bucket_size`` splats a bucket, full buckets
first), so reading gives the splats in that order (:func:`bucket_order`).  It
rounds colours and SH to the nearest step (GaussianSplats3D floors; readers
decode both alike), writes at most SH degree 2 (the original's limit; degree
3 is dropped with a warning) and no extras.

Quantisation bounds (writer and reader together; raw units):

- positions: level 0 exact; levels 1-2 within half a step, ``B / (4 R)``
  (3.8e-5 for the default 5.0 block), plus float32 rounding of the result;
- log scales: level 0 within ``6e-8 + ulp(s) / 2``; levels 1-2 the linear
  scale within ``2^-11`` relative (log scale within 4.9e-4) for log scales in
  [-9.7, 11.09], within ``2^-25`` absolute below (float16 subnormals; a scale
  that rounds to 0 reads as -10); log scales above 11.09 are clamped there;
- rotation: level 0 the rotation matrix within 1e-6; levels 1-2 each unit
  quaternion component within ``2^-12``, the matrix within 2e-3;
- ``f_dc``: ``0.5 / 255 / SH_C0 = 0.00695`` for colours in [0, 1] (others
  clamped); opacity: alpha within ``0.5 / 255``, logits read back within
  +-13.8;
- ``sh_rest``: level 0 exact; level 1 within ``2^-11`` relative (``2^-25``
  absolute below 6.1e-5; magnitudes above 65504 clamped); level 2 within
  half a step, ``(hi - lo) / 510`` over the file's SH range.
"""

from __future__ import annotations

import os
import struct
import warnings

import numpy as np

from .atomic import atomic_write
from .codec import SH_C0, Bytes, logit, normalized_quats, sigmoid
from .ply import SplatArrays

__all__ = ["bucket_order", "read_ksplat", "sniff_ksplat", "write_ksplat"]

MAIN_HEADER = 4096
SECTION_HEADER = 1024
LEVELS = (0, 1, 2)
_SH_COUNT = (0, 9, 24, 45)
_DEFAULT_RANGE = 32767
_DEFAULT_SH = 1.5
_HALF_MAX = float(np.finfo(np.float16).max)
_FLOAT_MAX = float(np.finfo(np.float32).max)


def _record(level: int, degree: int) -> np.dtype:
    """The record dtype of a compression level and SH degree."""
    f = "<f4" if level == 0 else "<f2"
    sh = {0: "<f4", 1: "<f2", 2: "u1"}[level]
    return np.dtype([("position", "<f4" if level == 0 else "<u2", 3), ("scale", f, 3), ("rotation", f, 4),
                     ("color", "u1", 4), ("sh", sh, _SH_COUNT[degree])])


def _bands(degree: int):
    """``(sh_rest slice, file slice, width)`` of each SH band 1..degree."""
    for band in range(1, degree + 1):
        k, w = band * band - 1, 2 * band + 1
        yield slice(k, k + w), slice(3 * k, 3 * (k + w)), w


def _sh_from_file(raw: np.ndarray, degree: int) -> np.ndarray:
    """File SH ``(n, K)`` (each band channel by channel) -> ``sh_rest (n, K/3, 3)``."""
    n = len(raw)
    return np.concatenate([raw[:, f].reshape(n, 3, w).transpose(0, 2, 1) for _, f, w in _bands(degree)]
                          or [np.zeros((n, 0, 3))], axis=1)


def _sh_to_file(rest: np.ndarray, degree: int) -> np.ndarray:
    """``sh_rest (n, K/3, 3)`` -> file SH ``(n, K)``."""
    n = len(rest)
    return np.concatenate([rest[:, r].transpose(0, 2, 1).reshape(n, 3 * w) for r, _, w in _bands(degree)]
                          or [np.zeros((n, 0))], axis=1)


# --------------------------------------------------------------------------
# detection
# --------------------------------------------------------------------------

def _main_header(head) -> tuple:
    """``(major, minor, max_sections, sections, max_splats, splats, level)`` of a main header."""
    major, minor = head[0], head[1]
    max_sections, sections, max_splats, splats, level = struct.unpack_from("<4IH", head, 4)
    return major, minor, max_sections, sections, max_splats, splats, level


def sniff_ksplat(head: bytes, path: str) -> bool:
    """A consistent main header: version 0.1+, level 0-2, section and splat
    counts that fit the file's size.  Never a ``.splat`` file (headerless)."""
    path = os.fspath(path)
    if path.lower().endswith(".splat") or len(head) < MAIN_HEADER:
        return False
    major, minor, max_sections, sections, max_splats, splats, level = _main_header(head)
    if major != 0 or minor < 1 or level > 2 or head[2:4] != b"\0\0" or not 1 <= max_sections \
            or sections > max_sections or splats > max_splats:
        return False
    if not np.all(np.isfinite(np.frombuffer(head, "<f4", 5, 24))):
        return False
    try:
        size = os.path.getsize(path)
    except OSError:
        return False
    return MAIN_HEADER + SECTION_HEADER * max_sections + (44 if level == 0 else 24) * splats <= size


# --------------------------------------------------------------------------
# reading
# --------------------------------------------------------------------------

def _section_header(raw) -> dict:
    (count, capacity, bucket_size, bucket_count, block, bucket_bytes, qrange, _, full, partial,
     degree) = struct.unpack_from("<4IfH2x4IH", raw)
    return dict(count=count, capacity=capacity, bucket_size=bucket_size, bucket_count=bucket_count, block=block,
                bucket_bytes=bucket_bytes, qrange=qrange, full=full, partial=partial, degree=degree)


def _bucket_of_splats(b: Bytes, sec: dict, lengths: np.ndarray, where: str) -> np.ndarray:
    """Bucket index of each of the section's splats."""
    n, size, full = sec["count"], sec["bucket_size"], sec["full"]
    in_full = min(n, full * size)
    if in_full and size == 0:
        raise b.error(f"{where}: {full} full buckets of size 0")
    rest = n - in_full
    if int(lengths.sum()) < rest:
        raise b.error(f"{where}: {rest} splats outside the full buckets, but the partial buckets hold "
                      f"{int(lengths.sum())}")
    buckets = np.concatenate([np.arange(in_full) // max(size, 1),
                              np.repeat(full + np.arange(len(lengths)), lengths)[:rest]])
    if n and int(buckets.max()) >= sec["bucket_count"]:
        raise b.error(f"{where}: splats refer to bucket {int(buckets.max())} of {sec['bucket_count']}")
    return buckets


def read_ksplat(path: str | os.PathLike) -> SplatArrays:
    """Read a ``.ksplat`` file into :class:`SplatArrays` (SH padded to the highest section's degree).

    Raises :class:`SplatFormatError` naming the file for a short or truncated
    file, an unsupported version or compression level, or section sizes that
    do not add up.
    """
    path = os.fspath(path)
    with open(path, "rb") as f:
        b = Bytes(path, f.read(), ".ksplat file")
    head = b.take(MAIN_HEADER, "the 4096-byte main header")
    major, minor, max_sections, _, _, n, level = _main_header(head)
    if major != 0 or minor < 1:
        raise b.error(f"unsupported .ksplat version {major}.{minor} (0.1 and later 0.x are read)")
    if level not in LEVELS:
        raise b.error(f"unsupported .ksplat compression level {level} (0, 1 and 2 exist)")
    lo, hi = (float(v) or d for v, d in zip(np.frombuffer(head, "<f4", 2, 36), (-_DEFAULT_SH, _DEFAULT_SH)))
    sections = [_section_header(b.take(SECTION_HEADER, f"section header {i}")) for i in range(max_sections)]
    total = sum(s["count"] for s in sections)
    if total != n:
        raise b.error(f"the main header says {n} splats but its {max_sections} sections hold {total}")
    degree = 0
    for i, sec in enumerate(sections):
        if sec["degree"] > 3:
            raise b.error(f"section {i} has SH degree {sec['degree']} (at most 3)")
        if sec["count"] > sec["capacity"]:
            raise b.error(f"section {i} holds {sec['count']} splats but has room for {sec['capacity']}")
        if sec["count"]:
            degree = max(degree, sec["degree"])

    parts = []
    for i, sec in enumerate(sections):
        where = f"section {i}"
        lengths = b.array("<u4", sec["partial"], f"{where}'s partial bucket sizes")
        region = b.take(sec["bucket_bytes"] * sec["bucket_count"], f"{where}'s bucket centres")
        if level and sec["count"]:
            if sec["bucket_bytes"] != 12:
                raise b.error(f"{where}: bucket centres of {sec['bucket_bytes']} bytes (12 expected)")
            centers = np.frombuffer(region, "<f4").reshape(-1, 3)
        rec = _record(level, sec["degree"])
        records = np.frombuffer(b.take(rec.itemsize * sec["capacity"], f"{where}'s {sec['capacity']} splats"),
                                rec)[:sec["count"]]
        count = len(records)
        if not count:
            continue
        if level:
            buckets = _bucket_of_splats(b, sec, lengths, where)
            qrange = sec["qrange"] or _DEFAULT_RANGE
            means = (records["position"].astype(np.float64) - qrange) * (sec["block"] / 2.0 / qrange) \
                + centers[buckets].astype(np.float64)
        else:
            means = records["position"].astype(np.float64)
        linear = records["scale"].astype(np.float64)
        scales = np.where(linear > 0, np.log(np.where(linear > 0, linear, 1.0)), -10.0)
        raw_sh = records["sh"].astype(np.float32)
        if level == 2:
            raw_sh = lo + raw_sh.astype(np.float64) / 255.0 * (hi - lo)
        rest = np.zeros((count, (degree + 1) ** 2 - 1, 3), np.float32)
        rest[:, :(sec["degree"] + 1) ** 2 - 1] = _sh_from_file(raw_sh, sec["degree"])
        rgba = records["color"].astype(np.float64) / 255.0
        parts.append(dict(means=means, scales=scales, quats=records["rotation"].astype(np.float64),
                          opacities=logit(rgba[:, 3]), sh_dc=(rgba[:, :3] - 0.5) / SH_C0, sh_rest=rest))

    def cat(key, shape):
        if not parts:
            return np.zeros(shape, np.float32)
        return np.concatenate([p[key] for p in parts]).astype(np.float32)

    return SplatArrays(
        means=cat("means", (0, 3)), scales=cat("scales", (0, 3)), quats=cat("quats", (0, 4)),
        opacities=cat("opacities", (0,)), sh_dc=cat("sh_dc", (0, 3)).reshape(n, 1, 3),
        sh_rest=cat("sh_rest", (0, (degree + 1) ** 2 - 1, 3)))


# --------------------------------------------------------------------------
# writing
# --------------------------------------------------------------------------

def bucket_order(means, block_size: float = 5.0, bucket_size: int = 256):
    """How the writer groups splats into buckets at levels 1 and 2.

    Returns ``(order, centers, partial_lengths, full_count)``: ``order`` the
    splats' indices in file order (full buckets of ``bucket_size``, then the
    partial ones, each block's splats in their order), ``centers`` each
    bucket's block centre ``(buckets, 3)`` float64, ``partial_lengths`` the
    partial buckets' sizes.  Blocks are ``block_size`` cubes from the minimum
    corner of ``means (N, 3)``.
    """
    p = np.asarray(means, np.float64)
    n = len(p)
    if n == 0:
        return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, np.int64), 0
    low = p.min(axis=0)
    cells = np.floor((p - low) / block_size).astype(np.int64)
    order = np.lexsort(cells.T[::-1])  # stable: by block, then input order
    ordered = cells[order]
    first = np.concatenate([[True], np.any(ordered[1:] != ordered[:-1], axis=1)])
    keys = ordered[first]
    sizes = np.diff(np.append(np.flatnonzero(first), n))
    cell_of = np.cumsum(first) - 1
    rank = np.arange(n) - np.flatnonzero(first)[cell_of]
    in_full = rank < (sizes // bucket_size * bucket_size)[cell_of]
    full_cells = np.repeat(np.arange(len(keys)), sizes // bucket_size)
    partial_cells = np.flatnonzero(sizes % bucket_size)
    centers = (keys[np.concatenate([full_cells, partial_cells])] + 0.5) * block_size + low
    return (np.concatenate([order[in_full], order[~in_full]]), centers,
            (sizes % bucket_size)[partial_cells], len(full_cells))


def write_ksplat(path: str | os.PathLike, splats: SplatArrays, *, fsync: bool = True, level: int = 0,
                 block_size: float = 5.0, bucket_size: int = 256) -> None:
    """Write ``splats`` as a one-section ``.ksplat`` at compression ``level`` (0, 1 or 2), atomically.

    ``block_size`` and ``bucket_size`` set the buckets of levels 1 and 2
    (the original generator's defaults).  SH above degree 2 is dropped with a
    warning.  Values must be finite (:func:`~mlx3d.io.write_splats` checks).
    """
    if level not in LEVELS:
        raise ValueError(f"level must be 0, 1 or 2; got {level!r}")
    if not block_size > 0 or not isinstance(bucket_size, (int, np.integer)) or bucket_size < 1:
        raise ValueError(f"block_size must be > 0 and bucket_size a positive integer; got {block_size}, {bucket_size}")
    path = os.fspath(path)
    n = splats.count
    rest = np.asarray(splats.sh_rest, np.float32)
    if rest.shape[1] > 8:
        warnings.warn(f"{path}: .ksplat holds SH up to degree 2; degree 3 is not written", UserWarning, stacklevel=2)
        rest = rest[:, :8]
    degree = {0: 0, 3: 1, 8: 2}[rest.shape[1]]
    rec = np.zeros(n, _record(level, degree))
    means = np.asarray(splats.means, np.float64)
    qrange = _DEFAULT_RANGE if level else 0
    if level:
        order, centers, lengths, full = bucket_order(means, block_size, bucket_size)
        centers32 = centers.astype(np.float32)
        buckets = np.concatenate([np.arange(full * bucket_size) // bucket_size,
                                  np.repeat(full + np.arange(len(lengths)), lengths)])
        delta = means[order] - centers32[buckets].astype(np.float64)
        q = np.rint(delta * (qrange / (block_size / 2.0))) + qrange
        rec["position"] = np.clip(q, 0, 2 * qrange + 1)
        bucket_bytes = lengths.astype("<u4").tobytes() + centers32.astype("<f4").tobytes()
    else:
        order, lengths, full, centers32 = np.arange(n), np.zeros(0), 0, np.zeros((0, 3))
        rec["position"] = means
        bucket_bytes = b""
    with np.errstate(over="ignore"):
        scales = np.exp(np.asarray(splats.scales, np.float64)[order])
    rec["scale"] = np.minimum(scales, _HALF_MAX if level else _FLOAT_MAX)
    rec["rotation"] = normalized_quats(np.asarray(splats.quats)[order])
    rgb = 0.5 + SH_C0 * np.asarray(splats.sh_dc, np.float64).reshape(n, 3)[order]
    rgba = np.concatenate([rgb, sigmoid(np.asarray(splats.opacities)[order])[:, None]], axis=1)
    rec["color"] = np.clip(np.rint(rgba * 255.0), 0, 255)
    lo, hi = -_DEFAULT_SH, _DEFAULT_SH
    values = _sh_to_file(rest[order], degree)
    if level == 1:
        values = np.clip(values, -_HALF_MAX, _HALF_MAX)
    elif level == 2 and values.size:
        lo, hi = float(np.float32(min(values.min(), -1e-6))), float(np.float32(max(values.max(), 1e-6)))
        values = np.clip(np.rint((values.astype(np.float64) - lo) / (hi - lo) * 255.0), 0, 255)
    rec["sh"] = values

    header = bytearray(MAIN_HEADER)
    header[0:2] = bytes([0, 1])
    struct.pack_into("<4IH2x3f2f", header, 4, 1, 1, n, n, level,
                     *((means.min(axis=0) + means.max(axis=0)) / 2 if n else np.zeros(3)), lo, hi)
    section = bytearray(SECTION_HEADER)
    struct.pack_into("<4IfH2x4IH", section, 0, n, n, bucket_size if level else 0, len(centers32),
                     block_size if level else 0.0, 12 if level else 0, qrange,
                     len(bucket_bytes) + rec.nbytes, full, len(lengths), degree)
    with atomic_write(path, "wb", fsync=fsync) as f:
        f.write(bytes(header))
        f.write(bytes(section))
        f.write(bucket_bytes)
        f.write(rec.tobytes())
