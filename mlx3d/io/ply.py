"""Read and write 3D Gaussian Splatting PLY files (numpy only, no MLX).

File layout (the de-facto standard written by the reference 3DGS trainer and
read by most viewers): one ``vertex`` element whose properties are, in order,

``x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 f_rest_0 .. f_rest_{3(K-1)-1}
opacity scale_0 scale_1 scale_2 rot_0 rot_1 rot_2 rot_3``

all ``float`` (float32), written binary little-endian.  ``K = (degree+1)**2``
is the number of SH coefficients per colour channel.  Values are raw:
``opacity`` is a logit, ``scale_*`` are log standard deviations and
``rot_*`` is an unnormalised quaternion ``w, x, y, z``.

``f_rest`` is *channel-major*: property ``f_rest_i`` with
``i = c * (K-1) + k`` holds channel ``c`` (0..2) of SH coefficient ``k + 1``.
In memory :class:`SplatArrays` keeps ``sh_rest`` coefficient-major,
shape ``(N, K-1, 3)`` with the channel last, so
``sh_rest[n, k, c] == f_rest_{c*(K-1)+k}``.

``nx ny nz`` are optional on read; every property other than the standard
ones is an "extra" and is kept with its own dtype, in file order.

Reading accepts binary little-endian, binary big-endian and ASCII files.  The
common case (binary, all standard properties float32, no list properties)
copies the vertex rows straight from the file into the output arrays in
cache-sized chunks, on several threads for large files.
"""

from __future__ import annotations

import io
import os
import re
import sys
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Iterable, Sequence

import numpy as np
import numpy.lib.recfunctions as _rfn

from ..errors import PlyFormatError
from .atomic import atomic_write

__all__ = ["NONFINITE_MODES", "NORMAL_NAMES", "SplatArrays", "read_splat_ply", "sniff_ply", "write_splat_ply"]

NONFINITE_MODES = ("error", "drop", "keep")

# PLY scalar type names -> numpy type codes (without byte order).
_PLY_TYPES = {
    "char": "i1", "int8": "i1",
    "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4",
    "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}
# numpy dtype -> PLY type name used when writing.
_PLY_NAME_OF = {
    np.dtype("i1"): "char", np.dtype("u1"): "uchar",
    np.dtype("i2"): "short", np.dtype("u2"): "ushort",
    np.dtype("i4"): "int", np.dtype("u4"): "uint",
    np.dtype("f4"): "float", np.dtype("f8"): "double",
}
_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}

_REST_PER_CHANNEL = {0: 0, 1: 3, 2: 8, 3: 15}  # degree -> K-1
_DEGREE_OF_REST_PER_CHANNEL = {v: k for k, v in _REST_PER_CHANNEL.items()}
_DEGREE_OF_REST_COUNT = {3 * v: k for k, v in _REST_PER_CHANNEL.items()}  # 0, 9, 24, 45

_MEANS = ("x", "y", "z")
NORMAL_NAMES = ("nx", "ny", "nz")  # optional normals: kept in ``extra``
_DC = ("f_dc_0", "f_dc_1", "f_dc_2")
_SCALES = ("scale_0", "scale_1", "scale_2")
_ROTS = ("rot_0", "rot_1", "rot_2", "rot_3")
_REQUIRED = _MEANS + _DC + ("opacity",) + _SCALES + _ROTS
_F_REST_RE = re.compile(r"f_rest_(\d+)\Z")

_MAX_HEADER_BYTES = 16 << 20
_CHUNK_BYTES = 1 << 20           # rows are copied through buffers of about this size
_BYTES_PER_WORKER = 8 << 20      # below this much data per thread, fewer threads are used
_MAX_WORKERS = 8


# --------------------------------------------------------------------------
# The in-memory type
# --------------------------------------------------------------------------

@dataclass(eq=False)
class SplatArrays:
    """Splat parameters as plain numpy arrays (raw values, as stored in PLY).

    The interchange type between files, :class:`~mlx3d.splatting.GaussianModel`
    and the Blender add-on.  Equality is identity; compare fields explicitly.

    Attributes:
        means: ``(N, 3)`` float32 positions.
        scales: ``(N, 3)`` float32 log standard deviations.
        quats: ``(N, 4)`` float32 quaternions ``w, x, y, z`` as stored
            (not normalised).
        opacities: ``(N,)`` float32 logits.
        sh_dc: ``(N, 1, 3)`` float32 degree-0 SH coefficients.
        sh_rest: ``(N, K-1, 3)`` float32 higher-order SH coefficients,
            coefficient-major (channel last); ``K-1`` is 0, 3, 8 or 15.
        extra: other vertex properties in file order, each ``(N,)`` with its
            own dtype; includes ``nx``/``ny``/``nz`` when the file had them.
        comments: header comments of the file read (not compared, not
            written back automatically).
        nonfinite_rows: rows of the file with NaN/Inf in a standard property.
        dropped_rows: how many of those were dropped (``nonfinite="drop"``).
    """

    means: np.ndarray
    scales: np.ndarray
    quats: np.ndarray
    opacities: np.ndarray
    sh_dc: np.ndarray
    sh_rest: np.ndarray
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    comments: list[str] = field(default_factory=list, compare=False)
    nonfinite_rows: int = field(default=0, compare=False)
    dropped_rows: int = field(default=0, compare=False)

    @property
    def count(self) -> int:
        """Number of splats ``N``."""
        return int(np.shape(self.means)[0])

    @property
    def sh_degree(self) -> int:
        """SH degree (0-3) implied by ``sh_rest.shape[1]``."""
        k1 = int(np.shape(self.sh_rest)[1])
        try:
            return _DEGREE_OF_REST_PER_CHANNEL[k1]
        except KeyError:
            raise ValueError(
                f"sh_rest has {k1} coefficients per channel; expected 0, 3, 8 or 15"
            ) from None

    def validate(self) -> None:
        """Check shapes and dtypes; raise ``ValueError`` naming the bad field."""
        _validated(self)

    def __repr__(self) -> str:
        try:
            degree = self.sh_degree
        except Exception:
            degree = "?"
        return (
            f"SplatArrays(count={self.count}, sh_degree={degree}, "
            f"extra={list(self.extra)})"
        )


# --------------------------------------------------------------------------
# Header parsing
# --------------------------------------------------------------------------

@dataclass
class _Prop:
    name: str
    code: str                     # numpy type code without byte order, e.g. "f4"
    is_list: bool = False
    len_code: str | None = None


@dataclass
class _Element:
    name: str
    count: int
    props: list[_Prop]

    @property
    def fixed_size(self) -> bool:
        return not any(p.is_list for p in self.props)

    @property
    def row_bytes(self) -> int:
        return sum(np.dtype(p.code).itemsize for p in self.props)


@dataclass
class _Header:
    fmt: str
    comments: list[str]
    elements: list[_Element]
    data_offset: int

    @property
    def byte_order(self) -> str | None:
        return _FORMATS[self.fmt]


def _malformed(path: str, lineno: int, problem: str) -> PlyFormatError:
    return PlyFormatError(f"{path}: malformed PLY header (line {lineno}): {problem}")


def _read_header(f, path: str, file_size: int) -> _Header:
    """Parse the header of an open binary file positioned at 0."""
    if file_size == 0:
        raise PlyFormatError(f"{path}: file is empty (0 bytes); expected a PLY file")
    buf = f.read(min(file_size, 1 << 16))
    if buf[:3] != b"ply" or buf[3:4] not in (b"\n", b"\r"):
        raise PlyFormatError(
            f"{path}: not a PLY file (expected the magic line 'ply', found {buf[:16]!r})"
        )
    if buf[3:5] == b"\r\n":
        nl = b"\r\n"
    else:
        nl = buf[3:4]
    pos = 3 + len(nl)
    lineno = 1
    fmt = None
    comments: list[str] = []
    elements: list[_Element] = []
    seen_elements: set[str] = set()
    seen_props: set[str] = set()
    while True:
        end = buf.find(nl, pos)
        if end < 0:
            if len(buf) >= file_size or len(buf) >= _MAX_HEADER_BYTES:
                where = "before the end of the file" if len(buf) >= file_size else (
                    f"within the first {_MAX_HEADER_BYTES >> 20} MiB")
                raise _malformed(path, lineno + 1, f"no 'end_header' line {where}")
            more = f.read(min(len(buf), file_size - len(buf), _MAX_HEADER_BYTES))
            if not more:
                raise _malformed(path, lineno + 1, "no 'end_header' line before the end of the file")
            buf += more
            continue
        raw = buf[pos:end]
        pos = end + len(nl)
        lineno += 1
        try:
            line = raw.decode("ascii").strip()
        except UnicodeDecodeError:
            raise _malformed(path, lineno, f"non-ASCII bytes {raw[:40]!r}") from None
        if not line:
            continue
        keyword = line.split(None, 1)[0]
        rest = line[len(keyword):].strip()
        tokens = rest.split()
        if keyword == "end_header":
            if fmt is None:
                raise _malformed(path, lineno, "'end_header' before any 'format' line")
            if tokens:
                raise _malformed(path, lineno, f"unexpected text after 'end_header': {rest!r}")
            return _Header(fmt, comments, elements, pos)
        if keyword == "comment":
            comments.append(line[len(keyword) + 1:])
            continue
        if keyword == "obj_info":
            continue
        if keyword == "format":
            if fmt is not None or elements:
                raise _malformed(path, lineno, "unexpected 'format' line")
            if len(tokens) != 2 or tokens[0] not in _FORMATS:
                raise _malformed(
                    path, lineno,
                    f"expected 'format ascii|binary_little_endian|binary_big_endian 1.0', got {line!r}")
            if tokens[1] not in ("1.0", "1"):
                raise _malformed(path, lineno, f"unsupported PLY version {tokens[1]!r}")
            fmt = tokens[0]
            continue
        if fmt is None:
            raise _malformed(path, lineno, f"expected a 'format' line, got {line!r}")
        if keyword == "element":
            if len(tokens) != 2:
                raise _malformed(path, lineno, f"expected 'element <name> <count>', got {line!r}")
            name, count_s = tokens
            try:
                count = int(count_s)
            except ValueError:
                count = -1
            if count < 0:
                raise _malformed(path, lineno, f"element {name!r} has an invalid count {count_s!r}")
            if name in seen_elements:
                raise _malformed(path, lineno, f"duplicate element {name!r}")
            seen_elements.add(name)
            seen_props = set()
            elements.append(_Element(name, count, []))
            continue
        if keyword == "property":
            if not elements:
                raise _malformed(path, lineno, "'property' line before any 'element' line")
            if tokens[:1] == ["list"]:
                if len(tokens) != 4:
                    raise _malformed(
                        path, lineno, f"expected 'property list <count type> <type> <name>', got {line!r}")
                _, len_t, val_t, name = tokens
                if len_t not in _PLY_TYPES or _PLY_TYPES[len_t][0] not in "iu":
                    raise _malformed(path, lineno, f"invalid list length type {len_t!r} for property {name!r}")
                if val_t not in _PLY_TYPES:
                    raise _malformed(path, lineno, f"unknown type {val_t!r} for property {name!r}")
                prop = _Prop(name, _PLY_TYPES[val_t], True, _PLY_TYPES[len_t])
            else:
                if len(tokens) != 2:
                    raise _malformed(path, lineno, f"expected 'property <type> <name>', got {line!r}")
                type_s, name = tokens
                if type_s not in _PLY_TYPES:
                    raise _malformed(path, lineno, f"unknown type {type_s!r} for property {name!r}")
                prop = _Prop(name, _PLY_TYPES[type_s])
            if name in seen_props:
                raise _malformed(path, lineno, f"duplicate property {name!r} in element {elements[-1].name!r}")
            seen_props.add(name)
            elements[-1].props.append(prop)
            continue
        raise _malformed(path, lineno, f"unexpected keyword {keyword!r}")


# --------------------------------------------------------------------------
# Vertex layout: which property goes where
# --------------------------------------------------------------------------

@dataclass
class _Layout:
    vertex: _Element
    index: int                     # position of the vertex element
    file_k1: int                   # f_rest coefficients per channel in the file
    out_k1: int                    # ... in the result
    extras: list[_Prop]            # scalar extras, file order
    dropped_lists: list[str]       # list-valued extras that are not kept

    def rest_name(self, k: int, c: int) -> str:
        return f"f_rest_{c * self.file_k1 + k}"


def _layout(header: _Header, path: str, sh_degree: int | None) -> _Layout:
    names = [e.name for e in header.elements]
    if "vertex" not in names:
        listed = ", ".join(repr(n) for n in names) or "none"
        raise PlyFormatError(f"{path}: no 'vertex' element (elements in the file: {listed})")
    index = names.index("vertex")
    vertex = header.elements[index]
    by_name = {p.name: p for p in vertex.props}
    for name in _REQUIRED:
        prop = by_name.get(name)
        if prop is None:
            raise PlyFormatError(f"{path}: missing property {name!r} in element 'vertex'")
    rest_props = [p for p in vertex.props if _F_REST_RE.match(p.name)]
    n_rest = len(rest_props)
    if n_rest not in _DEGREE_OF_REST_COUNT:
        raise PlyFormatError(
            f"{path}: unsupported number of f_rest properties: {n_rest} "
            "(expected 0, 9, 24 or 45 for SH degree 0, 1, 2 or 3)"
        )
    for i in range(n_rest):
        if f"f_rest_{i}" not in by_name:
            raise PlyFormatError(f"{path}: missing property 'f_rest_{i}' in element 'vertex'")
    for name in _REQUIRED + tuple(f"f_rest_{i}" for i in range(n_rest)):
        if by_name[name].is_list:
            raise PlyFormatError(
                f"{path}: property {name!r} is a list property; a scalar is required"
            )
    file_k1 = n_rest // 3
    if sh_degree is None:
        out_k1 = file_k1
    else:
        out_k1 = _REST_PER_CHANNEL[sh_degree]
    standard = set(_REQUIRED) | {p.name for p in rest_props}
    extras = [p for p in vertex.props if p.name not in standard and not p.is_list]
    lists = [p.name for p in vertex.props if p.name not in standard and p.is_list]
    return _Layout(vertex, index, file_k1, out_k1, extras, lists)


def _allocate(layout: _Layout, n: int):
    """Empty output arrays, plus column ops ``(array2d, col0, width, byte_offset, itemsize)``.

    ``array2d`` is an unsigned-integer view of an output array (so copies are
    bit-exact); ``byte_offset`` is the property's offset within a vertex row
    (only meaningful for fixed-size binary rows).
    """
    means = np.empty((n, 3), np.float32)
    scales = np.empty((n, 3), np.float32)
    quats = np.empty((n, 4), np.float32)
    opac = np.empty((n,), np.float32)
    dc = np.empty((n, 1, 3), np.float32)
    rest = np.empty((n, layout.out_k1, 3), np.float32)
    extra = {p.name: np.empty((n,), np.dtype(p.code)) for p in layout.extras}

    offsets = {}
    off = 0
    for p in layout.vertex.props:
        offsets[p.name] = off
        off += np.dtype(p.code).itemsize

    def uview(a: np.ndarray) -> np.ndarray:
        return a.view(np.dtype(f"u{a.dtype.itemsize}"))

    # (target 2-D uint view, [property names of its columns])
    targets = [
        (uview(means), list(_MEANS)),
        (uview(scales), list(_SCALES)),
        (uview(quats), list(_ROTS)),
        (uview(opac).reshape(n, 1), ["opacity"]),
        (uview(dc).reshape(n, 3), list(_DC)),
    ]
    kk = min(layout.file_k1, layout.out_k1)
    if kk:
        rest_u = uview(rest)
        for c in range(3):
            targets.append((rest_u[:, :kk, c], [layout.rest_name(k, c) for k in range(kk)]))
    for p in layout.extras:
        targets.append((uview(extra[p.name]).reshape(n, 1), [p.name]))

    ops = []
    for arr2d, names in targets:
        isz = arr2d.dtype.itemsize
        j = 0
        while j < len(names):
            start = j
            base = offsets[names[j]]
            j += 1
            while j < len(names) and offsets[names[j]] == base + (j - start) * isz:
                j += 1
            ops.append((arr2d, start, j - start, base, isz))
    arrays = dict(means=means, scales=scales, quats=quats, opacities=opac,
                  sh_dc=dc, sh_rest=rest, extra=extra)
    return arrays, ops, kk


def _copy_columns(ops, rows: np.ndarray, s: int, e: int, swap: bool, to_rows: bool) -> None:
    """Copy columns between a chunk of raw rows and rows ``s:e`` of the arrays.

    ``rows`` is a ``(e-s, row_bytes)`` uint8 array.  ``to_rows`` selects the
    direction (arrays -> rows when writing, rows -> arrays when reading).
    Blocks that are contiguous on both sides are copied as opaque items.
    """
    for arr2d, j0, w, off, isz in ops:
        nb = w * isz
        raw = rows[:, off:off + nb]
        if arr2d is None:  # zero fill (writer only)
            raw[...] = 0
            continue
        a = arr2d[s:e, j0:j0 + w]
        src, dst = (a, raw) if to_rows else (raw, a)
        if w == 1 or a.strides[1] == isz:
            vt = np.dtype(f"V{nb}")
            dst.view(vt)[:, 0] = src.view(vt)[:, 0]
        elif to_rows:
            raw.view(a.dtype)[...] = a
        else:
            a[...] = raw.view(a.dtype)
        if swap and isz > 1:
            if to_rows:
                raw.view(a.dtype).byteswap(inplace=True)
            else:
                a.byteswap(inplace=True)


def _n_workers(total_bytes: int) -> int:
    cpus = os.cpu_count() or 1
    return max(1, min(cpus, _MAX_WORKERS, total_bytes // _BYTES_PER_WORKER))


def _split(n: int, parts: int) -> list[tuple[int, int]]:
    bounds = [n * i // parts for i in range(parts + 1)]
    return [(bounds[i], bounds[i + 1]) for i in range(parts) if bounds[i + 1] > bounds[i]]


def _run_parallel(fn, ranges: list[tuple[int, int]]) -> list:
    """``[fn(lo, hi) for lo, hi in ranges]``, on one thread per range."""
    if len(ranges) <= 1:
        return [fn(lo, hi) for lo, hi in ranges]
    with ThreadPoolExecutor(max_workers=len(ranges)) as pool:
        futures = [pool.submit(fn, lo, hi) for lo, hi in ranges]
        return [fut.result() for fut in futures]


# --------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------

def _std_arrays(a: dict) -> list[np.ndarray]:
    return [a["means"], a["sh_dc"], a["sh_rest"], a["opacities"], a["scales"], a["quats"]]


def _read_binary_rows(path: str, layout: _Layout, offset: int, byte_order: str):
    """Fast path: fixed-size rows, standard properties float32."""
    n = layout.vertex.count
    row_bytes = layout.vertex.row_bytes
    arrays, ops, kk = _allocate(layout, n)
    swap = byte_order != ("<" if sys.byteorder == "little" else ">")
    rest = arrays["sh_rest"]
    std = _std_arrays(arrays)
    chunk_rows = max(1, _CHUNK_BYTES // max(row_bytes, 1))
    # When every property is float32, one check over whole rows is cheapest; a
    # hit there (possibly in a non-standard column) triggers the exact check.
    whole_row = None
    if all(p.code == "f4" for p in layout.vertex.props):
        whole_row = np.dtype(byte_order + "f4")

    def work(lo: int, hi: int) -> bool:
        finite = True
        buf = np.empty(min(chunk_rows, hi - lo) * row_bytes, np.uint8)
        view = memoryview(buf)
        with open(path, "rb", buffering=0) as f:
            f.seek(offset + lo * row_bytes)
            for s in range(lo, hi, chunk_rows):
                e = min(hi, s + chunk_rows)
                nb = (e - s) * row_bytes
                got = 0
                while got < nb:
                    r = f.readinto(view[got:nb])
                    if not r:
                        raise PlyFormatError(
                            f"{path}: truncated file: vertex row {s + got // row_bytes} of {n} "
                            "could not be read (the file changed while reading?)"
                        )
                    got += r
                rows = buf[:nb].reshape(e - s, row_bytes)
                _copy_columns(ops, rows, s, e, swap, to_rows=False)
                if kk < layout.out_k1:
                    rest[s:e, kk:] = 0
                if finite:
                    if whole_row is not None:
                        finite = bool(np.isfinite(rows.view(whole_row)).all())
                    else:
                        finite = all(np.isfinite(a[s:e]).all() for a in std)
        return finite

    flags = _run_parallel(work, _split(n, _n_workers(n * row_bytes)))
    return arrays, not all(flags)


def _from_structured(arr: np.ndarray, layout: _Layout):
    """General path: extract outputs from a structured array of vertex rows."""
    n = len(arr)

    def cols(names: Sequence[str]) -> np.ndarray:
        if not names:
            return np.empty((n, 0), np.float32)
        # out-of-range doubles -> inf, signalling NaNs -> NaN: reported later
        with np.errstate(over="ignore", invalid="ignore"):
            out = _rfn.structured_to_unstructured(arr[list(names)], dtype=np.float32)
        return np.ascontiguousarray(out, dtype=np.float32)

    kk = min(layout.file_k1, layout.out_k1)
    rest = np.zeros((n, layout.out_k1, 3), np.float32)
    if kk:
        names = [layout.rest_name(k, c) for k in range(kk) for c in range(3)]
        rest[:, :kk, :] = cols(names).reshape(n, kk, 3)
    extra = {}
    for p in layout.extras:
        native = np.dtype(p.code)
        extra[p.name] = np.array(arr[p.name], dtype=native, copy=True)
    return dict(
        means=cols(_MEANS), scales=cols(_SCALES), quats=cols(_ROTS),
        opacities=cols(["opacity"]).reshape(n), sh_dc=cols(_DC).reshape(n, 1, 3),
        sh_rest=rest, extra=extra,
    )


def _struct_dtype(props: Iterable[_Prop], byte_order: str) -> np.dtype:
    return np.dtype([(p.name, byte_order + p.code) for p in props])


def _min_row_bytes(element: _Element, fmt: str) -> int:
    """The fewest bytes one row of ``element`` can take in a file of format ``fmt``.

    ASCII: every value (a list's length included) is at least one character
    followed by a space or the line end.  Binary: the scalars plus each list's
    length field.  A row without properties counts as one byte (an empty line
    in ASCII); a file cannot declare more such rows than it has bytes.
    """
    if not element.props:
        return 1
    if fmt == "ascii":
        return 2 * len(element.props)
    return sum(np.dtype(p.len_code if p.is_list else p.code).itemsize for p in element.props)


def _check_counts(header: _Header, path: str, file_size: int, elements: Sequence[_Element]) -> None:
    """Refuse element counts the file is too short to hold, before anything is allocated."""
    avail = max(0, file_size - header.data_offset)
    slack = 1 if header.fmt == "ascii" else 0  # the last line may lack its line end
    need = 0
    for e in elements:
        row = _min_row_bytes(e, header.fmt)
        need += e.count * row
        if need > avail + slack:
            raise PlyFormatError(
                f"{path}: truncated file: element {e.name!r} declares {e.count} rows of at least "
                f"{row} bytes each ({header.fmt}); the elements up to it need at least {need} bytes, "
                f"but only {avail} bytes follow the header"
            )


def _read_with_plyfile(path: str) -> np.ndarray:
    """Fallback for list properties before/in the vertex element."""
    import struct

    import plyfile

    try:
        data = plyfile.PlyData.read(path, mmap=False)["vertex"].data
    except (plyfile.PlyParseError, ValueError, IndexError, KeyError, struct.error,
            EOFError, OverflowError) as exc:
        raise PlyFormatError(f"{path}: could not read vertex data: {exc}") from exc
    # Keep the scalar fields only (list fields are object arrays).
    scalar = [nm for nm in data.dtype.names if not data.dtype[nm].hasobject]
    out = np.empty(len(data), dtype=[(nm, data.dtype[nm]) for nm in scalar])
    for nm in scalar:
        out[nm] = data[nm]
    return out


def _read_ascii(path: str, header: _Header, layout: _Layout) -> np.ndarray:
    n = layout.vertex.count
    skip = sum(e.count for e in header.elements[:layout.index])
    dtype = _struct_dtype(layout.vertex.props, "=")
    if n == 0:
        return np.empty(0, dtype)
    with open(path, "rb") as f:
        f.seek(header.data_offset)
        text = io.TextIOWrapper(f, encoding="ascii", newline=None)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # "input contained no data" -> handled below
                arr = np.loadtxt(text, dtype=dtype, comments=None, skiprows=skip,
                                 max_rows=n, ndmin=1)
        except (ValueError, OverflowError) as exc:
            raise PlyFormatError(f"{path}: could not parse ASCII vertex data: {exc}") from exc
    if len(arr) < n:
        raise PlyFormatError(
            f"{path}: truncated file: expected {n} vertex rows, found {len(arr)}"
        )
    return arr


def _check_nonfinite(arrays: dict, layout: _Layout):
    """Return ``(bad_row_mask, count, detail)``; ``(None, 0, "")`` when all finite."""
    n = arrays["means"].shape[0]
    bad = np.zeros(n, bool)
    groups = [
        (arrays["means"].reshape(n, -1), list(_MEANS)),
        (arrays["sh_dc"].reshape(n, -1), list(_DC)),
        (arrays["sh_rest"].reshape(n, -1),
         [layout.rest_name(k, c) for k in range(layout.out_k1) for c in range(3)]),
        (arrays["opacities"].reshape(n, -1), ["opacity"]),
        (arrays["scales"].reshape(n, -1), list(_SCALES)),
        (arrays["quats"].reshape(n, -1), list(_ROTS)),
    ]
    for a, _ in groups:
        if a.shape[1]:
            bad |= ~np.isfinite(a).all(axis=1)
    count = int(bad.sum())
    if not count:
        return None, 0, ""
    row = int(np.argmax(bad))
    # Report the first offending property in file order.
    position = {p.name: i for i, p in enumerate(layout.vertex.props)}
    hits = []
    for a, names in groups:
        for j in np.flatnonzero(~np.isfinite(a[row])):
            hits.append((position[names[j]], names[j], a[row, j]))
    _, name, value = min(hits)
    return bad, count, f"first: row {row}, property {name!r} = {value}"


def sniff_ply(head: bytes, path: str) -> bool:
    """Whether ``head`` starts a PLY file (``ply`` and a line end)."""
    return head.startswith((b"ply\n", b"ply\r\n"))


def read_splat_ply(
    path: str | os.PathLike,
    *,
    sh_degree: int | None = None,
    nonfinite: str = "error",
) -> SplatArrays:
    """Read a 3DGS PLY file into :class:`SplatArrays`.

    Args:
        path: file to read (binary little/big-endian or ASCII PLY).
        sh_degree: SH degree of the result.  ``None`` keeps the file's; a lower
            degree keeps the first coefficients of each channel; a higher one
            pads with zeros.
        nonfinite: what to do with rows that have NaN/Inf in a standard
            property (position, SH, opacity, scale, rotation): ``"error"``
            raises :class:`PlyFormatError`, ``"drop"`` removes those rows and
            warns, ``"keep"`` keeps them and warns.  The count is recorded in
            ``nonfinite_rows`` (and ``dropped_rows``).

    Raises:
        PlyFormatError: the file is not a readable 3DGS PLY file (empty, not
            PLY, malformed header, no ``vertex`` element, missing or list-valued
            required property, unsupported ``f_rest`` count, truncated or
            unparsable data, non-finite values with ``nonfinite="error"``).
        ValueError: invalid ``sh_degree`` or ``nonfinite`` argument.
        OSError: the file cannot be opened.

    Elements other than ``vertex`` (e.g. ``face``) are skipped with a warning;
    so are list-valued extra vertex properties.
    """
    if nonfinite not in NONFINITE_MODES:
        raise ValueError(
            f"nonfinite must be one of {', '.join(map(repr, NONFINITE_MODES))}; got {nonfinite!r}"
        )
    if sh_degree is not None and (
        isinstance(sh_degree, bool) or not isinstance(sh_degree, (int, np.integer))
        or sh_degree not in _REST_PER_CHANNEL
    ):
        raise ValueError(f"sh_degree must be None or an integer 0-3; got {sh_degree!r}")
    path = os.fspath(path)
    if isinstance(path, bytes):
        path = os.fsdecode(path)

    with open(path, "rb") as f:
        file_size = os.fstat(f.fileno()).st_size
        header = _read_header(f, path, file_size)
    layout = _layout(header, path, None if sh_degree is None else int(sh_degree))

    others = [e.name for e in header.elements if e.name != "vertex"]
    if others:
        warnings.warn(
            f"{path}: ignoring element(s) {', '.join(map(repr, others))}; only 'vertex' is read",
            UserWarning, stacklevel=2,
        )
    if layout.dropped_lists:
        warnings.warn(
            f"{path}: ignoring list-valued vertex propert(y/ies) "
            f"{', '.join(map(repr, layout.dropped_lists))}",
            UserWarning, stacklevel=2,
        )

    n = layout.vertex.count
    order = header.byte_order
    before = header.elements[:layout.index]
    flagged = True
    if order is not None and all(e.fixed_size for e in before) and layout.vertex.fixed_size:
        offset = header.data_offset + sum(e.count * e.row_bytes for e in before)
        row_bytes = layout.vertex.row_bytes
        need = n * row_bytes
        avail = max(0, file_size - offset)
        if avail < need:
            raise PlyFormatError(
                f"{path}: truncated file: element 'vertex' needs {n} rows x {row_bytes} bytes "
                f"= {need} bytes from byte {offset}, but only {avail} bytes "
                f"({avail // row_bytes if row_bytes else 0} complete rows) are present"
            )
        std_codes = {p.code for p in layout.vertex.props
                     if p.name in _REQUIRED or _F_REST_RE.match(p.name)}
        if n and std_codes == {"f4"}:
            arrays, flagged = _read_binary_rows(path, layout, offset, order)
        else:
            with open(path, "rb") as f:
                f.seek(offset)
                arr = np.fromfile(f, dtype=_struct_dtype(layout.vertex.props, order), count=n)
            if len(arr) != n:  # the file shrank since it was measured
                raise PlyFormatError(
                    f"{path}: truncated file: expected {n} vertex rows, read {len(arr)}")
            arrays = _from_structured(arr, layout)
    elif order is None and layout.vertex.fixed_size:
        _check_counts(header, path, file_size, header.elements[:layout.index + 1])
        arrays = _from_structured(_read_ascii(path, header, layout), layout)
    else:
        _check_counts(header, path, file_size, header.elements)
        arrays = _from_structured(_read_with_plyfile(path), layout)

    nonfinite_rows = dropped = 0
    if flagged and n:
        bad, nonfinite_rows, detail = _check_nonfinite(arrays, layout)
        if nonfinite_rows:
            what = f"{nonfinite_rows} of {n} row(s) contain NaN or Inf values ({detail})"
            if nonfinite == "error":
                raise PlyFormatError(
                    f"{path}: {what}; pass nonfinite='drop' to discard those rows "
                    "or nonfinite='keep' to load them as they are"
                )
            if nonfinite == "drop":
                keep = ~bad
                for key in ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest"):
                    arrays[key] = arrays[key][keep]
                arrays["extra"] = {k: v[keep] for k, v in arrays["extra"].items()}
                dropped = nonfinite_rows
                warnings.warn(f"{path}: dropped {what}", UserWarning, stacklevel=2)
            else:
                warnings.warn(f"{path}: kept {what}", UserWarning, stacklevel=2)

    return SplatArrays(
        means=arrays["means"], scales=arrays["scales"], quats=arrays["quats"],
        opacities=arrays["opacities"], sh_dc=arrays["sh_dc"], sh_rest=arrays["sh_rest"],
        extra=arrays["extra"], comments=list(header.comments),
        nonfinite_rows=nonfinite_rows, dropped_rows=dropped,
    )


# --------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------

_RESERVED = set(_REQUIRED)


def _as_float(name: str, value, shape: tuple, shape_text: str) -> np.ndarray:
    try:
        a = np.asarray(value)
    except Exception as exc:  # e.g. objects that are not array-like
        raise ValueError(f"{name}: cannot convert {type(value).__name__} to an array") from exc
    if a.shape != shape:
        raise ValueError(f"{name}: expected shape {shape_text} = {shape}, got {a.shape}")
    if a.dtype.kind != "f":
        raise ValueError(
            f"{name}: expected a floating-point array of shape {shape_text}, "
            f"got dtype {a.dtype} with shape {a.shape}")
    return np.ascontiguousarray(a, dtype=np.float32)


def _validated(splats: SplatArrays) -> dict:
    """Shape/dtype checks; returns contiguous float32 arrays and checked extras."""
    means = np.asarray(splats.means)
    if means.ndim != 2 or means.shape[1] != 3:
        raise ValueError(f"means: expected shape (N, 3), got {means.shape}")
    n = means.shape[0]
    out = {"means": _as_float("means", means, (n, 3), "(N, 3)")}
    out["scales"] = _as_float("scales", splats.scales, (n, 3), "(N, 3)")
    out["quats"] = _as_float("quats", splats.quats, (n, 4), "(N, 4)")
    out["opacities"] = _as_float("opacities", splats.opacities, (n,), "(N,)")
    out["sh_dc"] = _as_float("sh_dc", splats.sh_dc, (n, 1, 3), "(N, 1, 3)")
    rest = np.asarray(splats.sh_rest)
    if rest.ndim != 3 or rest.shape[0] != n or rest.shape[2] != 3 \
            or rest.shape[1] not in _DEGREE_OF_REST_PER_CHANNEL:
        raise ValueError(
            f"sh_rest: expected shape (N, K-1, 3) with N = {n} and K-1 in (0, 3, 8, 15), "
            f"got {rest.shape}"
        )
    out["sh_rest"] = _as_float("sh_rest", rest, rest.shape, "(N, K-1, 3)")

    if not isinstance(splats.extra, dict):
        raise ValueError(f"extra: expected a dict of arrays, got {type(splats.extra).__name__}")
    extra = {}
    for name, value in splats.extra.items():
        if not isinstance(name, str) or not name or not name.isascii() \
                or any(ch.isspace() for ch in name):
            raise ValueError(f"extra: invalid property name {name!r} (non-empty ASCII, no spaces)")
        if name in _RESERVED or _F_REST_RE.match(name):
            raise ValueError(f"extra[{name!r}]: name clashes with a standard splat property")
        a = np.asarray(value)
        if a.shape != (n,):
            raise ValueError(f"extra[{name!r}]: expected shape (N,) = ({n},), got {a.shape}")
        native = a.dtype.newbyteorder("=")
        if np.dtype(native.str[1:]) not in _PLY_NAME_OF:
            raise ValueError(
                f"extra[{name!r}]: dtype {a.dtype} has no PLY type "
                "(use int8/uint8/int16/uint16/int32/uint32/float32/float64)"
            )
        extra[name] = np.ascontiguousarray(a, dtype=native)
    out["extra"] = extra
    return out


def _check_comments(comments) -> list[str]:
    if isinstance(comments, str):
        comments = [comments]
    result = []
    for c in comments:
        if not isinstance(c, str):
            raise ValueError(f"comments: expected strings, got {type(c).__name__}")
        if "\n" in c or "\r" in c or not c.isascii():
            raise ValueError(f"comments: {c!r} must be a single line of ASCII text")
        result.append(c)
    return result


def write_splat_ply(
    path: str | os.PathLike,
    splats: SplatArrays,
    *,
    comments: Iterable[str] = (),
    fsync: bool = True,
) -> None:
    """Write ``splats`` as a binary little-endian 3DGS PLY file, atomically.

    Properties are written in the standard order
    ``x y z nx ny nz f_dc_* f_rest_* opacity scale_* rot_*`` (float32), then
    the extras other than ``nx``/``ny``/``nz`` in their stored order and with
    their own dtypes.  ``nx``/``ny``/``nz`` come from ``splats.extra`` when
    present, else are zeros.  Shapes and dtypes are checked before the disk
    is touched (``ValueError`` naming the field).  The file is written to a
    temporary file in the same directory, ``fsync``-ed (unless
    ``fsync=False``) and renamed over ``path``, so an existing file is
    replaced only by a complete new one.
    """
    arrays = _validated(splats)
    comments = _check_comments(comments)
    n = arrays["means"].shape[0]
    k1 = arrays["sh_rest"].shape[1]
    extra = arrays["extra"]

    f32 = np.dtype(np.float32)
    props: list[tuple[str, np.dtype]] = [(nm, f32) for nm in _MEANS]
    props += [(nm, extra[nm].dtype if nm in extra else f32) for nm in NORMAL_NAMES]
    props += [(nm, f32) for nm in _DC]
    props += [(f"f_rest_{i}", f32) for i in range(3 * k1)]
    props += [("opacity", f32)] + [(nm, f32) for nm in _SCALES] + [(nm, f32) for nm in _ROTS]
    props += [(nm, a.dtype) for nm, a in extra.items() if nm not in NORMAL_NAMES]

    lines = ["ply", "format binary_little_endian 1.0"]
    lines += [f"comment {c}" if c else "comment" for c in comments]
    lines.append(f"element vertex {n}")
    lines += [f"property {_PLY_NAME_OF[np.dtype(dt.str[1:])]} {nm}" for nm, dt in props]
    lines.append("end_header")
    header = ("\n".join(lines) + "\n").encode("ascii")

    offsets = {}
    row_bytes = 0
    for nm, dt in props:
        offsets[nm] = row_bytes
        row_bytes += dt.itemsize

    def uview(a):
        return a.view(np.dtype(f"u{a.dtype.itemsize}"))

    ops = [
        (uview(arrays["means"]), 0, 3, offsets["x"], 4),
        (uview(arrays["sh_dc"]).reshape(n, 3), 0, 3, offsets["f_dc_0"], 4),
        (uview(arrays["opacities"]).reshape(n, 1), 0, 1, offsets["opacity"], 4),
        (uview(arrays["scales"]), 0, 3, offsets["scale_0"], 4),
        (uview(arrays["quats"]), 0, 4, offsets["rot_0"], 4),
    ]
    if k1:
        rest_u = uview(arrays["sh_rest"])
        for c in range(3):
            ops.append((rest_u[:, :, c], 0, k1, offsets[f"f_rest_{c * k1}"], 4))
    for nm in NORMAL_NAMES:
        if nm in extra:
            a = extra[nm]
            ops.append((uview(a).reshape(n, 1), 0, 1, offsets[nm], a.dtype.itemsize))
        else:
            ops.append((None, 0, 1, offsets[nm], 4))
    for nm, a in extra.items():
        if nm not in NORMAL_NAMES:
            ops.append((uview(a).reshape(n, 1), 0, 1, offsets[nm], a.dtype.itemsize))
    swap = sys.byteorder != "little"
    chunk_rows = max(1, _CHUNK_BYTES // row_bytes)

    ranges = _split(n, _n_workers(n * row_bytes))
    body_start = len(header)

    def fill(lo: int, hi: int, out) -> None:
        """Assemble rows ``lo:hi`` chunk by chunk and write them to ``out``."""
        buf = np.empty((min(chunk_rows, hi - lo), row_bytes), np.uint8)
        for s in range(lo, hi, chunk_rows):
            e = min(hi, s + chunk_rows)
            rows = buf[:e - s]
            _copy_columns(ops, rows, s, e, swap, to_rows=True)
            out.write(rows)

    with atomic_write(path, "wb", fsync=fsync) as f:
        f.write(header)
        if len(ranges) == 1:
            fill(*ranges[0], f)
        elif ranges:
            # Each thread writes its own row range through its own handle.
            f.flush()
            f.truncate(body_start + n * row_bytes)

            def work(lo: int, hi: int) -> None:
                with open(f.name, "r+b") as g:
                    g.seek(body_start + lo * row_bytes)
                    fill(lo, hi, g)

            _run_parallel(work, ranges)
            f.seek(0, os.SEEK_END)
