"""Fuzz tests for the PLY readers and writers (``mlx3d.io.ply``, ``mlx3d.io.mesh_ply``).

Valid seed files (3DGS splats in binary little-endian with SH degree 0-3,
big-endian, ASCII, a splat file with a list-valued property, and triangle
meshes) are mutated deterministically: truncation, bit and byte flips in the
header and the body, changed element counts and property types, dropped,
duplicated and reordered property lines, changed format lines, a missing
``end_header``, garbage in the header, trailing bytes, empty files and
header-only files.

Contract for every case, for both readers: the read either succeeds with a
self-consistent result (shapes and dtypes, the header's row count, the
``nonfinite`` policy, unchanged rows where the mutation left them alone, an
exact round trip through the writer) or raises :class:`PlyFormatError`.  Any
other exception, a hang (per-case time limit) or a warning other than the
readers' own ``UserWarning`` fails the test.

Every failure names the mutation kind, the case index, the seed file and the
mutation; the mutated file is kept under pytest's ``tmp_path`` and
``make_case(kind, index)`` rebuilds it::

    from tests.test_ply_fuzz import make_case
    seed, data, desc, expect = make_case("count", 17)

``PLY_FUZZ_SCALE=N`` runs N times as many cases per kind (the first ones are
unchanged) and ``PLY_FUZZ_SEED=S`` draws a different set, for longer runs.

Writers are checked for atomicity: a write that fails (bad arrays, failing
stream, failing rename/fsync, missing or read-only directory) leaves no file
and no temporary file, and an existing file at the path is unchanged.
"""

from __future__ import annotations

import contextlib
import errno
import os
import signal
import stat
import sys
import threading
import time
import tracemalloc
import warnings
import zlib
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np
import plyfile
import pytest

import mlx3d.io.atomic as atomic_mod
import mlx3d.io.mesh_ply as mesh_mod
import mlx3d.io.ply as ply_mod
from mlx3d.errors import PlyFormatError
from mlx3d.io import SplatArrays, read_splat_ply, write_splat_ply
from mlx3d.io.mesh_ply import read_mesh_ply, write_mesh_ply

from core_marks import runs_no_kernel  # noqa: E402

pytestmark = runs_no_kernel  # file formats, datasets and packaging: no kernel of ours runs here

# PLY_FUZZ_SEED=<int> draws a different set of cases (for longer exploratory runs).
BASE_SEED = int(os.environ.get("PLY_FUZZ_SEED", "20240611"))
CASE_TIME_LIMIT_S = 5.0     # one read (plus its round trip); normal cases take milliseconds
HUGE_COUNT_TIME_LIMIT_S = 2.0
CASE_MEMORY_HEADROOM = 2 << 30  # address space a read may add (a few-row file needs kilobytes)
HUGE_COUNT_MAX_ALLOC = 16 << 20
K1 = {0: 0, 1: 3, 2: 8, 3: 15}
STANDARD = ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest")
NORMALS = ("nx", "ny", "nz")


# --------------------------------------------------------------------------
# Seed files
# --------------------------------------------------------------------------

@dataclass(frozen=True)
class Seed:
    name: str
    data: bytes
    kind: str                 # "splat" or "mesh": which reader the file is meant for
    binary: bool
    n_vertex: int
    vertex_row_bytes: int     # fixed-size vertex rows directly after the header, else 0

    @property
    def header_end(self) -> int:
        return self.data.index(b"end_header\n") + len(b"end_header\n")


def _splat_names(degree: int) -> list[str]:
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * K1[degree])]
    return names + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]


def _values(rng, dtype, n):
    dtype = np.dtype(dtype)
    if dtype.kind == "f":
        v = (rng.standard_normal(n) * 3).astype(dtype)
        v[0] = -0.0
        if n > 1:
            v[1] = np.finfo(dtype).tiny / 4  # subnormal: must survive bit-exactly
        return v
    info = np.iinfo(dtype)
    return rng.integers(info.min, info.max, size=n, endpoint=True, dtype=dtype)


def _struct(n, degree, extras, order, seed):
    rng = np.random.default_rng(seed)
    fields = [(nm, order + "f4") for nm in _splat_names(degree)]
    fields += [(nm, np.dtype(dt).newbyteorder(order)) for nm, dt in extras]
    arr = np.empty(n, dtype=fields)
    for nm in arr.dtype.names:
        arr[nm] = _values(rng, arr.dtype[nm].newbyteorder("="), n)
    return arr


def _plyfile_bytes(tmp: Path, name: str, elements, *, text=False, byte_order="<") -> bytes:
    path = tmp / name
    plyfile.PlyData(elements, text=text, byte_order=byte_order,
                    comments=["fuzz seed"]).write(str(path))
    return path.read_bytes()


@lru_cache(maxsize=1)
def _seeds_cached(tmp: str) -> tuple[Seed, ...]:
    tmp = Path(tmp)
    seeds = []
    n = 6
    extras_by_degree = {
        0: {"seg": np.int32, "conf": np.uint8},
        1: {"w": np.float64},
        2: {"seg": np.int16, "tag": np.int8, "u": np.uint32},
        3: {"conf": np.uint8, "w": np.float64, "id": np.uint16},
    }
    for degree in range(4):
        rng = np.random.default_rng(degree)

        def f(*shape):
            return (rng.standard_normal(shape) * 3).astype(np.float32)

        extra = {nm: f(n) for nm in NORMALS}
        for nm, dt in extras_by_degree[degree].items():
            extra[nm] = _values(rng, dt, n)
        s = SplatArrays(means=f(n, 3), scales=f(n, 3), quats=f(n, 4), opacities=f(n),
                        sh_dc=f(n, 1, 3), sh_rest=f(n, K1[degree], 3), extra=extra)
        s.means[0, 0] = -0.0
        path = tmp / f"le_d{degree}.ply"
        write_splat_ply(path, s, comments=["fuzz seed", ""], fsync=False)
        data = path.read_bytes()
        hdr = data.index(b"end_header\n") + 11
        seeds.append(Seed(f"le_d{degree}", data, "splat", True, n, (len(data) - hdr) // n))

    arr = _struct(n, 1, [("red", "u1"), ("weight", "f8")], ">", seed=11)
    data = _plyfile_bytes(tmp, "be_d1.ply", [plyfile.PlyElement.describe(arr, "vertex")],
                          byte_order=">")
    seeds.append(Seed("be_d1", data, "splat", True, n, arr.dtype.itemsize))

    arr = _struct(n, 2, [("red", "u1"), ("splat_id", "i4")], "<", seed=12)
    data = _plyfile_bytes(tmp, "ascii_d2.ply", [plyfile.PlyElement.describe(arr, "vertex")],
                          text=True)
    seeds.append(Seed("ascii_d2", data, "splat", False, n, 0))

    # A list-valued vertex property (read through plyfile) and a face element after it.
    arr = _struct(n, 1, [], "<", seed=13)
    dt = arr.dtype.descr + [("ids", "O")]
    full = np.empty(n, dtype=dt)
    for nm in arr.dtype.names:
        full[nm] = arr[nm]
    for i in range(n):
        full["ids"][i] = np.arange(i % 3 + 1, dtype=np.int32)
    faces = np.empty(2, dtype=[("vertex_indices", "O")])
    faces["vertex_indices"] = [np.array([0, 1, 2], np.int32), np.array([2, 3, 4, 5], np.int32)]
    data = _plyfile_bytes(tmp, "list_d1.ply", [
        plyfile.PlyElement.describe(full, "vertex", len_types={"ids": "u1"}),
        plyfile.PlyElement.describe(faces, "face", len_types={"vertex_indices": "u1"}),
    ])
    seeds.append(Seed("list_d1", data, "splat", True, n, 0))

    rng = np.random.default_rng(14)
    v = (rng.standard_normal((7, 3)) * 2).astype(np.float32)
    faces3 = np.array([[0, 1, 2], [2, 3, 4], [4, 5, 6], [6, 0, 3], [1, 5, 3]], np.int32)
    colors = rng.random((7, 3)).astype(np.float32)
    path = tmp / "mesh.ply"
    write_mesh_ply(path, v, faces3, colors)
    seeds.append(Seed("mesh_bin", path.read_bytes(), "mesh", True, 7, 15))

    vert = np.empty(5, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    for nm in "xyz":
        vert[nm] = rng.standard_normal(5).astype(np.float32)
    polys = np.empty(3, dtype=[("vertex_indices", "O")])
    polys["vertex_indices"] = [np.array(p, np.int32) for p in ([0, 1, 2, 3], [1, 2, 4], [0, 2, 3, 4, 1])]
    data = _plyfile_bytes(tmp, "mesh_ascii.ply", [plyfile.PlyElement.describe(vert, "vertex"),
                                                  plyfile.PlyElement.describe(polys, "face")],
                          text=True)
    seeds.append(Seed("mesh_ascii", data, "mesh", False, 5, 0))
    return tuple(seeds)


@pytest.fixture(scope="module")
def seeds(tmp_path_factory) -> tuple[Seed, ...]:
    return _seeds_cached(str(tmp_path_factory.mktemp("ply_fuzz_seeds")))


@lru_cache(maxsize=1)
def _seeds_for_make_case() -> tuple[Seed, ...]:
    import tempfile
    with tempfile.TemporaryDirectory(prefix="ply_fuzz_seeds_") as directory:
        return _seeds_cached(directory)


# --------------------------------------------------------------------------
# The mutator
# --------------------------------------------------------------------------

@dataclass
class Expect:
    """What a case must do beyond the general contract (load consistently or PlyFormatError)."""

    splat: str = "any"            # "any", "raise" or "load" for read_splat_ply
    mesh: str = "any"             # ... for read_mesh_ply
    same_as_seed: bool = False    # a successful read equals the seed's read
    prefix_rows: int | None = None        # the first rows equal the seed's rows
    touched_rows: frozenset | None = None  # rows outside this set equal the seed's rows


def _header_lines(seed: Seed) -> list[bytes]:
    return seed.data[:seed.header_end].split(b"\n")[:-1]


def _join(lines: list[bytes], seed: Seed) -> bytes:
    return b"\n".join(lines) + b"\n" + seed.data[seed.header_end:]


def _own(seed: Seed, what: str) -> Expect:
    """Expect ``what`` from the reader the seed is meant for."""
    return Expect(**{seed.kind: what})


def _both(what: str) -> Expect:
    return Expect(splat=what, mesh=what)


def _s(b: bytes) -> str:
    return b.decode("ascii", "backslashreplace")


def _pick(rng, seq):
    return seq[int(rng.integers(len(seq)))]


def _flip_positions(rng, lo: int, hi: int, k: int) -> np.ndarray:
    return np.unique(rng.integers(lo, hi, size=k))


def m_truncate_header(seed, rng):
    cut = int(rng.integers(0, seed.header_end))
    return seed.data[:cut], f"truncate at byte {cut} (header ends at {seed.header_end})", _both("raise")


def m_truncate_body(seed, rng):
    if len(seed.data) <= seed.header_end:
        return seed.data, "no body to truncate", Expect()
    cut = int(rng.integers(seed.header_end, len(seed.data)))
    expect = _own(seed, "raise") if seed.binary else Expect()
    return seed.data[:cut], f"truncate at byte {cut} of {len(seed.data)}", expect


def m_header_bitflip(seed, rng):
    data = bytearray(seed.data)
    pos = _flip_positions(rng, 0, seed.header_end, int(rng.integers(1, 4)))
    bits = []
    for p in pos:
        b = int(rng.integers(8))
        data[p] ^= 1 << b
        bits.append(f"{p}:{b}")
    return bytes(data), f"flip header bits {' '.join(bits)}", Expect()


_BYTE_PALETTE = [0x00, 0x20, 0x0A, 0x0D, 0xFF, 0x80, 0x09, 0x0B, ord("0"), ord("9"), ord("-"), ord("x")]


def m_header_byteflip(seed, rng):
    data = bytearray(seed.data)
    pos = _flip_positions(rng, 0, seed.header_end, int(rng.integers(1, 4)))
    done = []
    for p in pos:
        new = int(rng.integers(256)) if rng.random() < 0.5 else _pick(rng, _BYTE_PALETTE)
        data[p] = new
        done.append(f"{p}={new:#04x}")
    return bytes(data), f"set header bytes {' '.join(done)}", Expect()


def m_body_byteflip(seed, rng):
    if len(seed.data) <= seed.header_end:
        return seed.data, "no body to change", Expect()
    data = bytearray(seed.data)
    pos = _flip_positions(rng, seed.header_end, len(data), int(rng.integers(1, 9)))
    for p in pos:
        data[p] = (data[p] + int(rng.integers(1, 256))) % 256
    expect = Expect()
    if seed.vertex_row_bytes:
        rel = (pos - seed.header_end) // seed.vertex_row_bytes
        expect.touched_rows = frozenset(int(r) for r in rel if r < seed.n_vertex)
    return bytes(data), f"change body bytes {pos.tolist()}", expect


_BAD_COUNTS = ["abc", "1.5", "1e3", "0x10", "", "5 5", "-0x1", "NaN", "inf", "٣"]
_HUGE_COUNTS = [2**31, 2**32 + 6, 10**9, 10**12, 2**62, 2**63 - 1, 2**64 + 6, 10**30]


def m_count(seed, rng):
    lines = _header_lines(seed)
    idx = [i for i, ln in enumerate(lines) if ln.startswith(b"element ")]
    vidx = [i for i in idx if ln_name(lines[i]) == b"vertex"]
    if not vidx:
        return seed.data, "no 'element vertex' line left to change", Expect()
    i = vidx[0] if (rng.random() < 0.7 or len(idx) == 1) else _pick(rng, [j for j in idx if j not in vidx])
    name = ln_name(lines[i])
    try:
        n = int(lines[i].split()[2])
    except (IndexError, ValueError):  # an earlier mutation (stacked cases) broke the count
        n = seed.n_vertex
    n = min(max(n, 0), 2**62)
    variant = _pick(rng, ["bigger", "smaller", "zero", "negative", "huge", "non-numeric", "padded"])
    expect = Expect()
    if variant == "bigger":
        count = str(n + int(rng.integers(1, 6)))
        if name == b"vertex" and seed.kind == "splat" and seed.binary:
            expect = Expect(splat="raise")
    elif variant == "smaller":
        k = int(rng.integers(0, max(n, 1)))
        count = str(k)
        if name == b"vertex" and seed.kind == "splat" and seed.vertex_row_bytes:
            expect = Expect(splat="load", prefix_rows=k)
    elif variant == "zero":
        count = "0"
        if name == b"vertex" and seed.kind == "splat" and seed.vertex_row_bytes:
            expect = Expect(splat="load", prefix_rows=0)
    elif variant == "negative":
        count = str(_pick(rng, [-1, -n, -(2**63), -(2**64)]))
        expect = _both("raise")
    elif variant == "huge":
        count = str(_pick(rng, _HUGE_COUNTS))
        expect = _both("raise")
    elif variant == "non-numeric":
        count = _pick(rng, _BAD_COUNTS)
        expect = _both("raise")
    else:
        count = f"  {n}\t"
        expect = Expect(same_as_seed=True)
    lines[i] = b"element " + name + b" " + count.encode("utf-8")
    return _join(lines, seed), f"element {_s(name)} count {n} -> {count!r} ({variant})", expect


def ln_name(line: bytes) -> bytes:
    parts = line.split()
    return parts[1] if len(parts) > 1 else b""


_NEW_TYPES = ["double", "uchar", "int", "short", "char", "ushort", "uint", "float64", "int8",
              "float32", "list uchar float", "list int int", "list float float", "float33",
              "half", "", "list uchar", "list"]


def m_prop_type(seed, rng):
    lines = _header_lines(seed)
    idx = [i for i, ln in enumerate(lines) if ln.startswith(b"property ")]
    if not idx:
        return seed.data, "no property line left to change", Expect()
    i = _pick(rng, idx)
    name = lines[i].split()[-1]
    new = _pick(rng, _NEW_TYPES)
    old = lines[i]
    lines[i] = b" ".join(p for p in (b"property", new.encode(), name) if p)
    return _join(lines, seed), f"{_s(old)!r} -> {_s(lines[i])!r}", Expect()


def m_prop_lines(seed, rng):
    lines = _header_lines(seed)
    idx = [i for i, ln in enumerate(lines) if ln.startswith(b"property ")]
    if not idx or len(lines) < 4:
        return seed.data, "no property line left to change", Expect()
    op = _pick(rng, ["drop", "duplicate", "swap", "move"])
    i = _pick(rng, idx)
    expect = Expect()
    if op == "drop":
        desc = f"drop {_s(lines[i])!r}"
        del lines[i]
    elif op == "duplicate":
        desc = f"duplicate {_s(lines[i])!r}"
        lines.insert(i + 1, lines[i])
        expect = _both("raise")
    elif op == "swap":
        j = _pick(rng, idx)
        desc = f"swap {_s(lines[i])!r} and {_s(lines[j])!r}"
        lines[i], lines[j] = lines[j], lines[i]
        if i == j:
            expect = Expect(same_as_seed=True)
    else:
        line = lines.pop(i)
        j = int(rng.integers(2, len(lines) - 1))  # after 'ply' and 'format', before 'end_header'
        lines.insert(j, line)
        desc = f"move {_s(line)!r} from line {i} to line {j}"
    return _join(lines, seed), desc, expect


def m_format(seed, rng):
    lines = _header_lines(seed)
    i = next((k for k, ln in enumerate(lines) if ln.startswith(b"format ")), None)
    if i is None:
        return seed.data, "no format line left to change", Expect()
    fmt = _s(lines[i].split()[1]) if len(lines[i].split()) > 1 else ""
    bad = {
        "unknown": "format binary_middle_endian 1.0",
        "version 2.0": f"format {fmt} 2.0",
        "version 1.1": f"format {fmt} 1.1",
        "version 0.9": f"format {fmt} 0.9",
        "no version": f"format {fmt}",
        "extra token": f"format {fmt} 1.0 extra",
        "bare": "format",
        "capitalised": f"Format {fmt} 1.0",
        "misspelt": "format binary_little_endan 1.0",
    }
    other = {
        "swap byte order": "format binary_big_endian 1.0" if fmt == "binary_little_endian"
        else "format binary_little_endian 1.0",
        "to ascii": "format ascii 1.0",
        "version 1": f"format {fmt} 1",
    }
    variant = _pick(rng, sorted(bad) + sorted(other) + ["removed", "duplicated", "after element"])
    expect = _both("raise")
    if variant == "removed":
        del lines[i]
    elif variant == "duplicated":
        lines.insert(i + 1, lines[i])
    elif variant == "after element":
        line = lines.pop(i)
        j = next((k for k, ln in enumerate(lines) if ln.startswith(b"element ")), len(lines) - 2) + 1
        lines.insert(j, line)
    elif variant in bad:
        lines[i] = bad[variant].encode()
    else:
        lines[i] = other[variant].encode()
        expect = Expect()
    return _join(lines, seed), f"format line {variant}: {fmt}", expect


def m_end_header(seed, rng):
    lines = _header_lines(seed)
    variant = _pick(rng, ["removed", "renamed", "upper case", "with text", "moved up"])
    if variant == "removed":
        lines.pop()
    elif variant == "renamed":
        lines[-1] = b"end_headers"
    elif variant == "upper case":
        lines[-1] = b"END_HEADER"
    elif variant == "with text":
        lines[-1] = b"end_header 1"
    else:  # a premature end_header: the rest of the header becomes body bytes
        j = int(rng.integers(1, max(2, len(lines) - 1)))
        lines.insert(j, lines.pop())
    return _join(lines, seed), f"end_header {variant}", Expect() if variant == "moved up" else _both("raise")


def _garbage(rng) -> tuple[bytes, str]:
    variant = _pick(rng, ["random bytes", "NUL run", "non-ASCII comment", "printable", "high bytes"])
    k = int(rng.integers(1, 41))
    if variant == "random bytes":
        g = bytes(int(b) for b in rng.integers(0, 256, k) if b not in (10, 13))
    elif variant == "NUL run":
        g = b"\x00" * k
    elif variant == "non-ASCII comment":
        g = "comment café – ünïcode".encode()
    elif variant == "printable":
        g = bytes(int(b) for b in rng.integers(33, 127, k))
    else:
        g = bytes(int(b) for b in rng.integers(128, 256, k))
    return g, variant


def m_header_garbage(seed, rng):
    lines = _header_lines(seed)
    g, variant = _garbage(rng)
    if rng.random() < 0.5:
        j = int(rng.integers(1, len(lines) + 1))
        lines.insert(j, g)
        desc = f"insert line {j}: {variant} {g[:24]!r}"
    else:
        j = int(rng.integers(0, len(lines)))
        col = int(rng.integers(0, len(lines[j]) + 1))
        lines[j] = lines[j][:col] + g + lines[j][col:]
        desc = f"insert into line {j} at column {col}: {variant} {g[:24]!r}"
    return _join(lines, seed), desc, Expect()


def m_trailing(seed, rng):
    variant = _pick(rng, ["random", "newline", "NULs", "second header"])
    k = int(rng.integers(1, 257))
    if variant == "random":
        tail = rng.integers(0, 256, k).astype(np.uint8).tobytes()
    elif variant == "newline":
        tail = b"\n"
    elif variant == "NULs":
        tail = b"\x00" * k
    else:
        tail = seed.data[:seed.header_end]
    expect = Expect(same_as_seed=True)
    if seed.binary:
        setattr(expect, seed.kind, "load")
    return seed.data + tail, f"append {len(tail)} bytes ({variant})", expect


def m_empty(seed, rng):
    return b"", "empty file", _both("raise")


def m_header_only(seed, rng):
    variant = _pick(rng, ["header", "header without final newline", "header plus one byte"])
    data = seed.data[:seed.header_end]
    if variant == "header without final newline":
        data = data[:-1]
    elif variant == "header plus one byte":
        data = seed.data[:seed.header_end + 1]
    return data, variant, _both("raise")


def m_stacked(seed, rng):
    """Two or three mutations in a row, each applied to the previous one's output."""
    descs = []
    data = seed.data
    for _ in range(int(rng.integers(2, 4))):
        if b"end_header\n" not in data:  # the header is broken already: only append bytes
            tail = rng.integers(0, 256, int(rng.integers(1, 65))).astype(np.uint8).tobytes()
            data += tail
            descs.append(f"append {len(tail)} random bytes")
            continue
        kind = _pick(rng, _STACKABLE)
        current = Seed(seed.name, data, seed.kind, seed.binary, seed.n_vertex, 0)
        data, d, _ = MUTATIONS[kind](current, rng)
        descs.append(f"{kind}: {d}")
    return data, " | ".join(descs), Expect()


MUTATIONS = {
    "truncate_header": m_truncate_header,
    "truncate_body": m_truncate_body,
    "header_bitflip": m_header_bitflip,
    "header_byteflip": m_header_byteflip,
    "body_byteflip": m_body_byteflip,
    "count": m_count,
    "prop_type": m_prop_type,
    "prop_lines": m_prop_lines,
    "format": m_format,
    "end_header": m_end_header,
    "header_garbage": m_header_garbage,
    "trailing": m_trailing,
    "empty": m_empty,
    "header_only": m_header_only,
    "stacked": m_stacked,
}
_STACKABLE = ["truncate_body", "header_bitflip", "header_byteflip", "body_byteflip", "count",
              "prop_type", "prop_lines", "header_garbage", "trailing"]

# Cases per mutation kind (the seeds are used in turn: case i mutates seed i % len(seeds)).
CASES = {kind: 36 for kind in MUTATIONS}
CASES.update(empty=9, header_only=18, count=54, stacked=45)
# PLY_FUZZ_SCALE=20 runs 20 times as many cases (new indices; the first ones are unchanged).
_SCALE = max(1, int(os.environ.get("PLY_FUZZ_SCALE", "1")))
CASES = {kind: n * _SCALE if kind != "empty" else n for kind, n in CASES.items()}


def _rng(kind: str, index: int) -> np.random.Generator:
    return np.random.default_rng([BASE_SEED, zlib.crc32(kind.encode()), index])


def _make_case(seeds, kind: str, index: int):
    seed = seeds[index % len(seeds)]
    data, desc, expect = MUTATIONS[kind](seed, _rng(kind, index))
    return seed, data, desc, expect


def make_case(kind: str, index: int):
    """Rebuild case ``index`` of mutation ``kind``: ``(seed, bytes, description, expect)``."""
    return _make_case(_seeds_for_make_case(), kind, index)


# --------------------------------------------------------------------------
# Running one read under a time limit and checking the result
# --------------------------------------------------------------------------

class CaseTimeout(BaseException):
    """Raised by the alarm when one case runs past its time limit."""


@contextlib.contextmanager
def time_limit(seconds: float):
    """Interrupt the block with :class:`CaseTimeout` after ``seconds`` (main thread, POSIX)."""
    if not hasattr(signal, "setitimer") or threading.current_thread() is not threading.main_thread():
        yield
        return

    def on_alarm(signum, frame):
        raise CaseTimeout()

    old = signal.signal(signal.SIGALRM, on_alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


@contextlib.contextmanager
def memory_limit(headroom: int):
    """Cap the address space at its current size plus ``headroom`` (Linux), so that a
    huge allocation raises ``MemoryError`` instead of exhausting a shared machine."""
    try:
        import resource
    except ImportError:
        yield
        return
    if not sys.platform.startswith("linux"):
        yield
        return
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    with open("/proc/self/statm") as fh:
        limit = int(fh.read().split()[0]) * resource.getpagesize() + headroom
    if (hard != resource.RLIM_INFINITY and limit > hard) or \
            (soft != resource.RLIM_INFINITY and soft <= limit):
        yield
        return
    resource.setrlimit(resource.RLIMIT_AS, (limit, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


def _call(fn, *args, **kwargs):
    """``(result, exception, unexpected_warnings, seconds)`` of one guarded call."""
    t0 = time.perf_counter()
    result = exc = None
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            with time_limit(CASE_TIME_LIMIT_S), memory_limit(CASE_MEMORY_HEADROOM):
                result = fn(*args, **kwargs)
        except CaseTimeout:
            exc = TimeoutError(f"no result after {CASE_TIME_LIMIT_S} s (hang)")
        except Exception as e:  # noqa: BLE001 - classified by the caller
            exc = e
    # The readers warn (UserWarning) about skipped elements and properties.  A
    # ResourceWarning is left out: plyfile wraps the reader's (closed) handle in
    # a TextIOWrapper that is collected later, at a moment unrelated to the case.
    odd = [f"{w.category.__name__}: {w.message}" for w in caught
           if w.category not in (UserWarning, ResourceWarning)]
    return result, exc, odd, time.perf_counter() - t0


def _judge_reader(out, key, tag, read, expected, describe, check, round_trip, error_names=None) -> None:
    """Run ``read()`` under :func:`_call` and add to ``out`` what went wrong.

    key: 'splat' or 'mesh' (``out.loaded[key]``); expected: the case's
    :class:`Expect` field ('any', 'load' or 'raise'); describe(result): what was loaded, for a case that must raise;
    check(result) and round_trip(result): lists of problems, the round trip
    only when nothing is wrong so far; error_names: text a PlyFormatError must
    contain (the file's path).
    """
    result, exc, odd, secs = _call(read)
    out.problems += [f"{tag}: unexpected warning {w}" for w in odd]
    out.loaded[key] = exc is None
    if exc is not None:
        if not isinstance(exc, PlyFormatError):
            out.problems.append(f"{tag}: raised {type(exc).__name__}: {exc}")
        elif expected == "load":
            out.problems.append(f"{tag}: must load, raised PlyFormatError: {exc}")
        elif error_names is not None and error_names not in str(exc):
            out.problems.append(f"{tag}: error message does not name the file: {exc}")
    else:
        if expected == "raise":
            out.problems.append(f"{tag}: must raise PlyFormatError, loaded {describe(result)}")
        out.problems += [f"{tag}: {p}" for p in check(result)]
        if not out.problems:
            out.problems += [f"{tag}: {p}" for p in round_trip(result)]
    if secs > CASE_TIME_LIMIT_S:
        out.problems.append(f"{tag}: took {secs:.1f} s")


def _bits(a) -> np.ndarray:
    a = np.ascontiguousarray(a)
    if a.dtype.kind in "fiu" and a.dtype.itemsize > 1:
        a = a.astype(a.dtype.newbyteorder("="))
        return a.view(np.dtype(f"u{a.dtype.itemsize}"))
    return a


def _same(a, b) -> bool:
    a, b = np.asarray(a), np.asarray(b)
    return a.shape == b.shape and a.dtype == b.dtype and np.array_equal(_bits(a), _bits(b))


def _declared_vertex_count(data: bytes) -> int | None:
    """The vertex count the (mutated) header declares, parsed as the readers parse it."""
    head = data.split(b"end_header", 1)[0]
    found = [ln.split() for ln in head.replace(b"\r", b"\n").split(b"\n")]
    found = [t for t in found if len(t) == 3 and t[0] == b"element" and t[1] == b"vertex"]
    if len(found) != 1:
        return None
    try:
        return int(found[0][2])
    except ValueError:
        return None


def _splat_rows(s: SplatArrays, rows) -> dict:
    rows = np.asarray(sorted(rows), dtype=np.int64)
    out = {nm: getattr(s, nm)[rows] for nm in STANDARD}
    out.update({f"extra[{k}]": v[rows] for k, v in s.extra.items()})
    return out


def _check_splat(s: SplatArrays, data: bytes, mode: str, sh_degree, expect: Expect,
                 ref: SplatArrays | None, seed: Seed) -> list[str]:
    problems = []
    if not isinstance(s, SplatArrays):
        return [f"returned {type(s).__name__}, not SplatArrays"]
    try:
        s.validate()
    except ValueError as e:
        return [f"result fails validate(): {e}"]
    n = s.count
    for nm in STANDARD:
        a = getattr(s, nm)
        if a.dtype != np.float32 or a.shape[0] != n:
            problems.append(f"{nm}: dtype {a.dtype} shape {a.shape} (count {n})")
    for k, v in s.extra.items():
        if v.shape != (n,) or not v.dtype.isnative:
            problems.append(f"extra[{k!r}]: dtype {v.dtype} shape {v.shape}")
    if sh_degree is not None and s.sh_rest.shape[1] != K1[sh_degree]:
        problems.append(f"sh_rest has {s.sh_rest.shape[1]} coefficients, sh_degree={sh_degree}")
    bad_rows = np.zeros(n, bool)
    for nm in STANDARD:
        a = getattr(s, nm)
        bad_rows |= ~np.isfinite(a.reshape(n, int(np.prod(a.shape[1:])))).all(axis=1)
    n_bad = int(bad_rows.sum())
    if mode in ("error", "drop") and n_bad:
        problems.append(f"{n_bad} non-finite rows returned with nonfinite={mode!r}")
    if mode == "keep" and s.nonfinite_rows != n_bad:
        problems.append(f"nonfinite_rows={s.nonfinite_rows} but {n_bad} non-finite rows returned")
    if mode == "drop" and s.dropped_rows != s.nonfinite_rows:
        problems.append(f"dropped_rows={s.dropped_rows} != nonfinite_rows={s.nonfinite_rows}")
    if mode != "drop" and s.dropped_rows:
        problems.append(f"dropped_rows={s.dropped_rows} with nonfinite={mode!r}")
    declared = _declared_vertex_count(data)
    if declared is not None and n + s.dropped_rows != declared:
        problems.append(f"{n} rows (+{s.dropped_rows} dropped) but the header declares {declared}")
    if problems or ref is None or sh_degree is not None or s.dropped_rows:
        return problems
    # Rows the mutation did not touch must be unchanged.
    rows = None
    if expect.same_as_seed:
        rows = range(ref.count)
        if n != ref.count:
            return [f"{n} rows, the seed has {ref.count}"]
    elif expect.prefix_rows is not None:
        rows = range(expect.prefix_rows)
    elif expect.touched_rows is not None:
        rows = [r for r in range(ref.count) if r not in expect.touched_rows]
    if rows is not None and n >= len(rows):
        if list(s.extra) != list(ref.extra):
            return [f"extra properties {list(s.extra)} != seed's {list(ref.extra)}"]
        got, want = _splat_rows(s, rows), _splat_rows(ref, rows)
        for k in want:
            if not _same(got[k], want[k]):
                problems.append(f"{k}: rows {list(rows)} the mutation left alone changed")
    return problems


def _splat_round_trip(s: SplatArrays, out: Path) -> list[str]:
    """Write what the reader returned and read it back: the same arrays, exactly."""
    try:
        write_splat_ply(out, s, fsync=False)
    except Exception as e:  # noqa: BLE001
        return [f"writer refused the reader's result: {type(e).__name__}: {e}"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            back = read_splat_ply(out, nonfinite="keep")
        except Exception as e:  # noqa: BLE001
            return [f"re-reading the written file failed: {type(e).__name__}: {e}"]
        finally:
            out.unlink(missing_ok=True)
    problems = [f"round trip changed {nm}" for nm in STANDARD
                if not _same(getattr(s, nm), getattr(back, nm))]
    for k, v in s.extra.items():
        if k not in back.extra or not _same(v, back.extra[k]):
            problems.append(f"round trip changed extra[{k!r}]")
    for k in set(back.extra) - set(s.extra):  # the writer fills missing normals with zeros
        if k not in NORMALS or np.any(back.extra[k] != 0):
            problems.append(f"round trip added extra[{k!r}]")
    return problems


def _check_mesh(m, data: bytes, expect: Expect, ref, seed: Seed) -> list[str]:
    v, f, c = m.vertices, m.faces, m.colors
    problems = []
    if v.dtype != np.float32 or v.ndim != 2 or v.shape[1] != 3:
        problems.append(f"vertices: dtype {v.dtype} shape {v.shape}")
    elif not np.isfinite(v).all():
        problems.append("non-finite vertices returned")
    if f.dtype != np.int32 or f.ndim != 2 or f.shape[1] != 3:
        problems.append(f"faces: dtype {f.dtype} shape {f.shape}")
    elif f.size and (f.min() < 0 or f.max() >= len(v)):
        problems.append("face indices out of range")
    if c is not None and (c.shape != v.shape or c.dtype != np.float32
                          or not np.all((c >= 0) & (c <= 1))):
        problems.append(f"colors: dtype {c.dtype} shape {c.shape} or outside [0, 1]")
    declared = _declared_vertex_count(data)
    if declared is not None and len(v) != declared:
        problems.append(f"{len(v)} vertices but the header declares {declared}")
    if problems or ref is None:
        return problems
    if expect.same_as_seed:
        if not (_same(v, ref.vertices) and _same(f, ref.faces)
                and (c is None) == (ref.colors is None) and (c is None or _same(c, ref.colors))):
            problems.append("result differs from the seed's")
    elif expect.touched_rows is not None and len(v) == len(ref.vertices):
        rows = [r for r in range(len(v)) if r not in expect.touched_rows]
        if not _same(v[rows], ref.vertices[rows]):
            problems.append(f"vertex rows {rows} the mutation left alone changed")
    return problems


def _mesh_round_trip(m, out: Path) -> list[str]:
    try:
        write_mesh_ply(out, m.vertices, m.faces, m.colors)
        back = read_mesh_ply(out)
    except Exception as e:  # noqa: BLE001
        return [f"mesh round trip failed: {type(e).__name__}: {e}"]
    finally:
        out.unlink(missing_ok=True)
    problems = []
    if not _same(m.vertices, back.vertices):
        problems.append("round trip changed vertices")
    if not _same(m.faces, back.faces):
        problems.append("round trip changed faces")
    if (m.colors is None) != (back.colors is None) or (
            m.colors is not None and np.abs(m.colors - back.colors).max() > 0.5 / 255 + 1e-6):
        problems.append("round trip changed colours beyond uchar quantisation")
    return problems


@dataclass
class Outcome:
    problems: list[str] = field(default_factory=list)
    loaded: dict = field(default_factory=dict)


def _run_case(seed: Seed, data: bytes, expect: Expect, refs: dict, work: Path,
              rng: np.random.Generator, label: str) -> Outcome:
    path = work / f"{label}.ply"
    path.write_bytes(data)
    mode = _pick(rng, ["error", "error", "drop", "keep"])
    sh_degree = _pick(rng, [None, None, None, 0, 1, 2, 3])
    out = Outcome()

    _judge_reader(
        out, "splat", f"read_splat_ply(nonfinite={mode!r}, sh_degree={sh_degree})", lambda: read_splat_ply(path, nonfinite=mode, sh_degree=sh_degree), expect.splat, repr,
        lambda s: _check_splat(s, data, mode, sh_degree, expect, refs.get(seed.name) if seed.kind == "splat" else None, seed),
        lambda s: _splat_round_trip(s, work / f"{label}.rt.ply"), error_names=str(path),
    )
    _judge_reader(
        out, "mesh", "read_mesh_ply", lambda: read_mesh_ply(path), expect.mesh, lambda m: f"{len(m.vertices)} vertices",
        lambda m: _check_mesh(m, data, expect, refs.get(seed.name) if seed.kind == "mesh" else None, seed),
        lambda m: _mesh_round_trip(m, work / f"{label}.rt.ply"),
    )
    if not out.problems:
        path.unlink()
    return out


@pytest.fixture(scope="module")
def refs(seeds, tmp_path_factory) -> dict:
    """What the readers return for the unmutated seeds."""
    directory = tmp_path_factory.mktemp("ply_fuzz_refs")
    out = {}
    for seed in seeds:
        p = directory / f"{seed.name}.ply"
        p.write_bytes(seed.data)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # list-valued property / other elements skipped
            out[seed.name] = read_splat_ply(p) if seed.kind == "splat" else read_mesh_ply(p)
    return out


# --------------------------------------------------------------------------
# Tests
# --------------------------------------------------------------------------

def test_seeds_are_valid(seeds, refs):
    assert len(seeds) == 9
    for seed in seeds:
        r = refs[seed.name]
        if seed.kind == "splat":
            assert r.count == seed.n_vertex, seed.name
        else:
            assert len(r.vertices) == seed.n_vertex and len(r.faces) > 0, seed.name


@pytest.mark.parametrize("kind", list(MUTATIONS))
def test_fuzz(kind, seeds, refs, tmp_path):
    """Every mutated file loads consistently or raises PlyFormatError, for both readers."""
    failures = []
    loaded = {"splat": 0, "mesh": 0}
    for index in range(CASES[kind]):
        label = f"{kind}-{index}"
        seed, desc = seeds[index % len(seeds)], "?"
        try:
            seed, data, desc, expect = _make_case(seeds, kind, index)
            out = _run_case(seed, data, expect, refs, tmp_path, _rng(kind + "/read", index), label)
        except BaseException as e:  # the harness itself must not hide a case
            failures.append(f"[{kind} #{index}] seed={seed.name} ({desc}): harness error {e!r}")
            continue
        for k, v in out.loaded.items():
            loaded[k] += v
        for p in out.problems:
            failures.append(f"[{kind} #{index}] seed={seed.name} ({desc}): {p} "
                            f"[file: {tmp_path / (label + '.ply')}]")
    assert not failures, (
        f"{len(failures)} problem(s) in {CASES[kind]} '{kind}' cases "
        f"(rebuild one with make_case({kind!r}, index)):\n" + "\n".join(failures[:40]))
    # The mutations must not all be rejected outright (a fuzzer that only makes
    # unreadable files tests little); the always-invalid kinds are exempt.
    if kind in ("count", "trailing", "body_byteflip", "prop_lines", "prop_type"):
        assert loaded["splat"] + loaded["mesh"] > 0, f"no '{kind}' case loaded at all"


def test_mutator_is_deterministic(seeds):
    for kind in MUTATIONS:
        for index in (0, 5):
            a = _make_case(seeds, kind, index)
            b = _make_case(seeds, kind, index)
            assert a[1] == b[1] and a[2] == b[2], (kind, index)


# ---- regression cases: huge declared counts fail fast, without allocating ----

def _with_count(data: bytes, element: bytes, count: int) -> bytes:
    lines = data.split(b"\n")
    for i, ln in enumerate(lines):
        t = ln.split()
        if len(t) == 3 and t[0] == b"element" and t[1] == element:
            lines[i] = b"element " + element + b" " + str(count).encode()
            return b"\n".join(lines)
    raise AssertionError(f"no element {element!r}")


@pytest.mark.parametrize("count", [10**6, 2**31, 10**9, 10**12, 2**63 - 1, 10**30])
def test_huge_counts_fail_fast_without_allocating(seeds, tmp_path, count):
    path = tmp_path / "huge.ply"
    problems = []
    for seed in seeds:
        for element in (b"vertex", b"face"):
            if b"element " + element + b" " not in seed.data:
                continue
            path.write_bytes(_with_count(seed.data, element, count))
            for reader in (read_splat_ply, read_mesh_ply):
                tracemalloc.start()
                try:
                    _, exc, _, secs = _call(reader, path)
                    peak = tracemalloc.get_traced_memory()[1]
                finally:
                    tracemalloc.stop()
                what = f"{reader.__name__} on {seed.name} with element {element.decode()} {count}"
                if not isinstance(exc, PlyFormatError):
                    problems.append(f"{what}: {type(exc).__name__}: {exc}")
                if secs > HUGE_COUNT_TIME_LIMIT_S:
                    problems.append(f"{what}: took {secs:.2f} s")
                if peak > HUGE_COUNT_MAX_ALLOC:
                    problems.append(f"{what}: allocated {peak / 2**20:.0f} MiB")
    assert not problems, "\n".join(problems)


def test_propertyless_element_with_huge_count(tmp_path):
    """An element without properties takes no bytes per row: a huge count must not loop forever."""
    names = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
             "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    for fmt, body in (("binary_little_endian", b"\x00" * (4 * 14 + 1)), ("ascii", b"0 " * 14 + b"0\n")):
        for first in (True, False):
            empty = ["element nothing 1000000000000"]
            vertex = ["element vertex 1"] + [f"property float {n}" for n in names] + \
                ["property list uchar int ids"]
            lines = ["ply", f"format {fmt} 1.0"] + (empty + vertex if first else vertex + empty)
            path = tmp_path / "p.ply"
            path.write_bytes(("\n".join(lines + ["end_header"]) + "\n").encode() + body)
            for reader in (read_splat_ply, read_mesh_ply):
                _, exc, _, secs = _call(reader, path)
                assert isinstance(exc, PlyFormatError), (fmt, first, reader.__name__, exc)
                assert secs < HUGE_COUNT_TIME_LIMIT_S, (fmt, first, reader.__name__, secs)


_MESH_XYZ = ["property float x", "property float y", "property float z"]


@pytest.mark.parametrize("vertex_props, rows, face_prop, face_rows, fragment", [
    (["property list uchar float x", "property float y", "property float z"],
     "2 0 0 0 0\n1 1 0 0\n1 0 1 0\n", "property list uchar int vertex_indices", "3 0 1 2\n",
     "vertex property x is a list"),
    (["property list uchar float x", "property float y", "property float z"],
     "1 0 0 0\n1 1 0 0\n1 0 1 0\n", "property list uchar int vertex_indices", "3 0 1 2\n",
     "vertex property x is a list"),
    (_MESH_XYZ + ["property list uchar uchar red", "property uchar green", "property uchar blue"],
     "0 0 0 1 5 1 1\n1 0 0 1 5 1 1\n0 1 0 2 5 5 1 1\n", "property list uchar int vertex_indices",
     "3 0 1 2\n", "vertex property red is a list"),
    (_MESH_XYZ, "0 0 0\n1 0 0\n0 1 0\n", "property int vertex_indices", "2\n",
     "'vertex_indices' is a scalar"),
    (["property double x", "property float y", "property float z"], "1e300 0 0\n1 0 0\n0 1 0\n",
     "property list uchar int vertex_indices", "3 0 1 2\n", "beyond the float32 range"),
], ids=["list x", "list x of length 1", "list red", "scalar face indices", "double beyond float32"])
def test_mesh_reader_refuses_wrongly_typed_properties(tmp_path, vertex_props, rows, face_prop,
                                                      face_rows, fragment):
    """Regression: these leaked ValueError/IndexError, or returned inf vertices."""
    header = ["ply", "format ascii 1.0", "element vertex 3", *vertex_props, "element face 1",
              face_prop, "end_header"]
    for fmt in ("ascii", "binary_little_endian"):
        path = tmp_path / f"m_{fmt}.ply"
        if fmt == "ascii":
            path.write_text("\n".join(header) + "\n" + rows + face_rows)
        else:  # the same content through plyfile's binary writer
            data = plyfile.PlyData.read(str(tmp_path / "m_ascii.ply"))
            data.text = False
            data.write(str(path))
        _, exc, odd, _ = _call(read_mesh_ply, path)
        assert isinstance(exc, PlyFormatError) and fragment in str(exc), (fmt, exc)
        assert not odd, odd


def test_signalling_nan_is_refused_without_numpy_warnings(tmp_path):
    """Regression: converting a signalling NaN leaked numpy's 'invalid value' RuntimeWarning."""
    snan64 = np.array([0x7FF0000000000001], "<u8").tobytes()
    snan32 = np.array([0x7F800001], "<u4").tobytes()
    names = ["y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
             "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    header = ["ply", "format binary_little_endian 1.0", "element vertex 1", "property double x"]
    header += [f"property float {nm}" for nm in names] + ["end_header"]
    splat = tmp_path / "s.ply"
    splat.write_bytes(("\n".join(header) + "\n").encode() + snan64 + bytes(4 * len(names)))
    s, exc, odd, _ = _call(read_splat_ply, splat)
    assert isinstance(exc, PlyFormatError) and "NaN or Inf" in str(exc) and not odd, (exc, odd)
    s, exc, odd, _ = _call(read_splat_ply, splat, nonfinite="keep")
    assert exc is None and np.isnan(s.means[0, 0]) and not odd, (exc, odd)

    mesh = tmp_path / "m.ply"
    header = ["ply", "format binary_little_endian 1.0", "element vertex 3", *_MESH_XYZ,
              "element face 1", "property list uchar int vertex_indices", "end_header"]
    verts = snan32 + bytes(32)
    mesh.write_bytes(("\n".join(header) + "\n").encode() + verts
                     + b"\x03" + np.array([0, 1, 2], "<i4").tobytes())
    _, exc, odd, _ = _call(read_mesh_ply, mesh)
    assert isinstance(exc, PlyFormatError) and "NaN or Inf" in str(exc) and not odd, (exc, odd)


# ---- writers: a failed write leaves nothing behind ----

def _splats(n=40, degree=2, seed=0) -> SplatArrays:
    rng = np.random.default_rng(seed)

    def f(*shape):
        return rng.standard_normal(shape).astype(np.float32)

    return SplatArrays(means=f(n, 3), scales=f(n, 3), quats=f(n, 4), opacities=f(n),
                       sh_dc=f(n, 1, 3), sh_rest=f(n, K1[degree], 3),
                       extra={"nx": f(n), "ny": f(n), "nz": f(n),
                              "seg": rng.integers(0, 9, n).astype(np.int32)})


@pytest.fixture
def existing(tmp_path):
    """A directory holding one existing file ``out.ply`` (mode 0640); checks it afterwards."""
    target = tmp_path / "out.ply"
    write_splat_ply(target, _splats(seed=99), fsync=False)
    os.chmod(target, 0o640)
    before = target.read_bytes()

    def unchanged(what: str):
        names = sorted(p.name for p in tmp_path.iterdir())
        assert names == ["out.ply"], f"{what}: directory holds {names}"
        assert target.read_bytes() == before, f"{what}: existing file changed"
        assert stat.S_IMODE(target.stat().st_mode) == 0o640, f"{what}: mode changed"

    return target, unchanged


def _bad_splats():
    good = _splats(10, 1)
    nan = _splats(10, 1)
    nan.means[3, 1] = np.nan

    def with_(**kw):
        s = _splats(10, 1)
        for k, v in kw.items():
            setattr(s, k, v)
        return s

    return [
        ("means (N, 2)", with_(means=good.means[:, :2])),
        ("scales short", with_(scales=good.scales[:9])),
        ("sh_rest 4 coefficients", with_(sh_rest=np.zeros((10, 4, 3), np.float32))),
        ("integer quats", with_(quats=np.zeros((10, 4), np.int32))),
        ("object opacities", with_(opacities=np.array([None] * 10, dtype=object))),
        ("extra complex", with_(extra={"c": np.zeros(10, np.complex64)})),
        ("extra bool", with_(extra={"b": np.zeros(10, bool)})),
        ("extra wrong length", with_(extra={"e": np.zeros(11, np.float32)})),
        ("extra name with space", with_(extra={"a b": np.zeros(10, np.float32)})),
        ("extra name non-ASCII", with_(extra={"é": np.zeros(10, np.float32)})),
        ("extra clashes", with_(extra={"opacity": np.zeros(10, np.float32)})),
        ("extra f_rest", with_(extra={"f_rest_99": np.zeros(10, np.float32)})),
        ("extra not a dict", with_(extra=[("a", np.zeros(10))])),
    ], nan


def test_splat_writer_refuses_bad_arrays_without_touching_disk(existing):
    target, unchanged = existing
    cases, nan = _bad_splats()
    for what, s in cases:
        with pytest.raises(ValueError):
            write_splat_ply(target, s)
        unchanged(what)
        with pytest.raises(ValueError):
            write_splat_ply(target.with_name("new.ply"), s)
        unchanged(what + " (new file)")
    for comments in (["two\nlines"], ["café"], [3]):
        with pytest.raises(ValueError):
            write_splat_ply(target, _splats(), comments=comments)
        unchanged(f"comments {comments!r}")
    # NaN is written as it is; the reader refuses it unless asked to keep it.
    write_splat_ply(target.with_name("nan.ply"), nan, fsync=False)
    with pytest.raises(PlyFormatError, match="NaN or Inf"):
        read_splat_ply(target.with_name("nan.ply"))
    with pytest.warns(UserWarning, match="dropped 1 of 10"):
        assert read_splat_ply(target.with_name("nan.ply"), nonfinite="drop").count == 9


class _FailingStream:
    """Proxy for the temporary file that fails on its ``fail_at``-th write."""

    def __init__(self, fh, fail_at: int, exc: BaseException):
        self._fh, self._fail_at, self._exc, self.writes = fh, fail_at, exc, 0

    def write(self, data):
        self.writes += 1
        if self.writes == self._fail_at:
            self._fh.write(bytes(memoryview(data)[: len(memoryview(data)) // 2]))  # a partial write
            raise self._exc
        return self._fh.write(data)

    def __getattr__(self, name):
        return getattr(self._fh, name)


def _inject(monkeypatch, module, fail_at: int, exc: BaseException) -> dict:
    real = atomic_mod.atomic_write
    seen = {"writes": 0}

    @contextlib.contextmanager
    def failing(path, mode="wb", **kw):
        with real(path, mode, **kw) as fh:
            proxy = _FailingStream(fh, fail_at, exc)
            try:
                yield proxy
            finally:
                seen["writes"] = proxy.writes

    monkeypatch.setattr(module, "atomic_write", failing)
    return seen


@pytest.mark.parametrize("exc", [OSError(errno.ENOSPC, "No space left on device"), KeyboardInterrupt()],
                         ids=["ENOSPC", "KeyboardInterrupt"])
def test_splat_writer_stream_failure_leaves_nothing(existing, monkeypatch, exc):
    target, unchanged = existing
    monkeypatch.setattr(ply_mod, "_CHUNK_BYTES", 2048)  # several chunks, several writes
    s = _splats(200, 3, seed=5)
    fail_at, total = 1, None
    while True:
        seen = _inject(monkeypatch, ply_mod, fail_at, exc)
        try:
            write_splat_ply(target, s, fsync=False)
        except type(exc):
            unchanged(f"failure at write {fail_at}")
            fail_at += 1
            continue
        total = seen["writes"]
        break
    assert total is not None and total >= 4 and fail_at == total + 1
    back = read_splat_ply(target)  # the last, unfailed write replaced the file
    assert np.array_equal(back.means, s.means) and back.sh_degree == 3


def test_splat_writer_worker_failure_leaves_nothing(existing, monkeypatch):
    """Several writer threads: a failure in any chunk of any thread leaves nothing."""
    target, unchanged = existing
    monkeypatch.setattr(ply_mod, "_CHUNK_BYTES", 4096)
    monkeypatch.setattr(ply_mod, "_BYTES_PER_WORKER", 1)
    monkeypatch.setattr(ply_mod.os, "cpu_count", lambda: 3)
    real = ply_mod._copy_columns
    s = _splats(300, 3, seed=6)
    calls = {"n": 0, "fail": 0}
    lock = threading.Lock()

    def failing(*args, **kwargs):
        with lock:
            calls["n"] += 1
            hit = calls["n"] == calls["fail"]
        if hit:
            raise OSError(errno.EIO, "I/O error (injected)")
        return real(*args, **kwargs)

    monkeypatch.setattr(ply_mod, "_copy_columns", failing)
    calls["fail"] = -1
    write_splat_ply(target.with_name("probe.ply"), s, fsync=False)
    total = calls["n"]
    target.with_name("probe.ply").unlink()
    assert total >= 6
    for k in range(1, total + 1):
        calls.update(n=0, fail=k)
        with pytest.raises(OSError, match="injected"):
            write_splat_ply(target, s, fsync=False)
        unchanged(f"failure in chunk {k} of {total}")


def test_writers_fsync_and_rename_failures_leave_nothing(existing, monkeypatch):
    target, unchanged = existing
    v = np.zeros((4, 3), np.float32)
    f = np.array([[0, 1, 2]], np.int32)

    def boom(*args, **kwargs):
        raise OSError(errno.EIO, "injected")

    for attr in ("replace", "fsync"):
        with monkeypatch.context() as mp:
            mp.setattr(atomic_mod.os, attr, boom)
            with pytest.raises(OSError, match="injected"):
                write_splat_ply(target, _splats())
            unchanged(f"splat, failing os.{attr}")
            with pytest.raises(OSError, match="injected"):
                write_mesh_ply(target, v, f)
            unchanged(f"mesh, failing os.{attr}")


def test_writers_bad_destination(tmp_path):
    missing = tmp_path / "no" / "such" / "dir" / "out.ply"
    with pytest.raises(FileNotFoundError):
        write_splat_ply(missing, _splats())
    with pytest.raises(FileNotFoundError):
        write_mesh_ply(missing, np.zeros((3, 3)), np.array([[0, 1, 2]]))
    assert sorted(p.name for p in tmp_path.iterdir()) == []
    (tmp_path / "d.ply").mkdir()
    with pytest.raises(IsADirectoryError):
        write_splat_ply(tmp_path / "d.ply", _splats())
    with pytest.raises(IsADirectoryError):
        write_mesh_ply(tmp_path / "d.ply", np.zeros((3, 3)), np.array([[0, 1, 2]]))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.ply"]
    assert list((tmp_path / "d.ply").iterdir()) == []


def test_writers_unwritable_directory_simulated(existing, monkeypatch):
    """Creating the temporary file fails (as in a read-only directory, also when run as root)."""
    target, unchanged = existing

    def refuse(file, mode="r", *args, **kwargs):
        if "x" in mode:
            raise PermissionError(errno.EACCES, "Permission denied (injected)", file)
        return open(file, mode, *args, **kwargs)

    monkeypatch.setattr(atomic_mod, "open", refuse, raising=False)
    with pytest.raises(PermissionError, match="injected"):
        write_splat_ply(target, _splats())
    unchanged("splat, temporary file refused")
    with pytest.raises(PermissionError, match="injected"):
        write_mesh_ply(target.with_name("new.ply"), np.zeros((3, 3)), np.array([[0, 1, 2]]))
    unchanged("mesh, temporary file refused")


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() == 0,
                    reason="needs a non-root POSIX user: root writes into read-only directories")
def test_writers_read_only_directory(existing):
    target, unchanged = existing
    directory = target.parent
    os.chmod(directory, 0o500)
    try:
        with pytest.raises(PermissionError):
            write_splat_ply(target, _splats())
        with pytest.raises(PermissionError):
            write_mesh_ply(target, np.zeros((3, 3)), np.array([[0, 1, 2]]))
    finally:
        os.chmod(directory, 0o700)
    unchanged("read-only directory")


def test_mesh_writer_failures_leave_nothing(existing, monkeypatch):
    target, unchanged = existing
    rng = np.random.default_rng(3)
    v = rng.standard_normal((30, 3)).astype(np.float32)
    f = rng.integers(0, 30, (40, 3)).astype(np.int32)
    c = rng.random((30, 3)).astype(np.float32)
    nan_v = v.copy()
    nan_v[4, 2] = np.nan
    bad = [
        ("NaN vertex", nan_v, f, c),
        ("inf colour", v, f, np.where(c > 0.5, np.inf, c)),
        ("float32 overflow", v.astype(np.float64) * 1e300, f, c),
        ("index out of range", v, np.where(f == 7, 30, f), c),
        ("negative index", v, np.where(f == 7, -1, f), c),
        ("float faces", v, f.astype(np.float32), c),
        ("faces (F, 4)", v, np.zeros((3, 4), np.int32), c),
        ("colours short", v, f, c[:29]),
        ("vertices (V, 2)", v[:, :2], f, c),
    ]
    for what, vv, ff, cc in bad:
        with pytest.raises(ValueError):
            write_mesh_ply(target, vv, ff, cc)
        unchanged(what)
    for exc in (OSError(errno.ENOSPC, "No space left on device"), KeyboardInterrupt()):
        fail_at = 1
        while True:
            seen = _inject(monkeypatch, mesh_mod, fail_at, exc)
            try:
                write_mesh_ply(target, v, f, c)
            except type(exc):
                unchanged(f"{type(exc).__name__} at write {fail_at}")
                fail_at += 1
                continue
            break
        assert fail_at == seen["writes"] + 1 == 4
        monkeypatch.undo()
        m = read_mesh_ply(target)  # the last, unfailed write replaced the file
        assert np.array_equal(m.vertices, v) and np.array_equal(m.faces, f)
        write_splat_ply(target, _splats(seed=99), fsync=False)  # the fixture's file again
        os.chmod(target, 0o640)
        unchanged("restored")
