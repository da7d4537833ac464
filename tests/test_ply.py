"""Tests for the 3DGS PLY reader/writer (``mlx3d.io``)."""

from __future__ import annotations

import os
import stat
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import plyfile
import pytest

import mlx3d.io.ply as ply_mod
from mlx3d.errors import PlyFormatError
from mlx3d.io import SplatArrays, atomic_write, read_splat_ply, write_splat_ply

REPO = Path(__file__).resolve().parents[1]
OPENSPLAT = REPO.parent / "shared" / "data" / "opensplat_trained.ply"
K1 = {0: 0, 1: 3, 2: 8, 3: 15}
STANDARD = ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest")


# --------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------

def prop_names(degree: int, normals: bool = True) -> list[str]:
    names = ["x", "y", "z"] + (["nx", "ny", "nz"] if normals else [])
    names += ["f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(3 * K1[degree])]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    return names


def random_values(rng, dtype, n):
    dtype = np.dtype(dtype)
    if dtype.kind == "f":
        v = rng.standard_normal(n).astype(dtype) * dtype.type(10)
        if n >= 4:  # awkward but finite bit patterns must survive too
            v[:4] = [-0.0, np.finfo(dtype).tiny / 4, np.finfo(dtype).max, 1e-3]
        return v
    info = np.iinfo(dtype)
    return rng.integers(info.min, info.max, size=n, endpoint=True, dtype=dtype)


def make_struct(n, degree, *, seed=0, normals=True, extras=(), std_type="f4", byte_order="<"):
    """Structured vertex array in standard order plus ``extras`` [(name, dtype)]."""
    rng = np.random.default_rng(seed)
    fields = [(nm, byte_order + std_type) for nm in prop_names(degree, normals)]
    fields += [(nm, np.dtype(dt).newbyteorder(byte_order)) for nm, dt in extras]
    arr = np.empty(n, dtype=fields)
    for nm in arr.dtype.names:
        arr[nm] = random_values(rng, arr.dtype[nm].newbyteorder("="), n)
    return arr


def write_plyfile(path, arr, *, text=False, byte_order="<", more=(), comments=()):
    elements = [plyfile.PlyElement.describe(arr, "vertex")] + list(more)
    plyfile.PlyData(elements, text=text, byte_order=byte_order, comments=list(comments)).write(str(path))
    return path


def random_splats(n, degree, *, seed=0, extras=None) -> SplatArrays:
    rng = np.random.default_rng(seed)

    def f(*shape):
        return (rng.standard_normal(shape) * 3).astype(np.float32)

    s = SplatArrays(
        means=f(n, 3), scales=f(n, 3), quats=f(n, 4), opacities=f(n),
        sh_dc=f(n, 1, 3), sh_rest=f(n, K1[degree], 3), extra=dict(extras or {}),
    )
    if n >= 2:
        s.means[0] = [-0.0, np.float32(1e-45), np.finfo(np.float32).max]
        s.sh_rest.reshape(n, -1)[1, :] = -0.0
    return s


def bits(a: np.ndarray) -> np.ndarray:
    a = np.ascontiguousarray(a)
    return a.view(np.dtype(f"u{a.dtype.itemsize}"))


def assert_bits_equal(a, b, what=""):
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape, f"{what}: shape {a.shape} != {b.shape}"
    assert a.dtype.newbyteorder("=") == b.dtype.newbyteorder("="), f"{what}: dtype {a.dtype} != {b.dtype}"
    a = a.astype(a.dtype.newbyteorder("="))
    b = b.astype(b.dtype.newbyteorder("="))
    assert np.array_equal(bits(a), bits(b)), f"{what}: values differ"


def assert_splats_equal(a: SplatArrays, b: SplatArrays, *, extra=True):
    for name in STANDARD:
        assert getattr(a, name).dtype == np.float32, name
        assert_bits_equal(getattr(a, name), getattr(b, name), name)
    if extra:
        assert list(a.extra) == list(b.extra)
        for k in a.extra:
            assert_bits_equal(a.extra[k], b.extra[k], f"extra[{k!r}]")


def expected_from_struct(arr: np.ndarray, degree: int) -> dict:
    """What the reader must return for a structured array in file order."""
    n, k1 = len(arr), K1[degree]

    def cols(names):
        return np.stack([np.asarray(arr[nm], np.float32) for nm in names], axis=1) if names else \
            np.empty((n, 0), np.float32)

    rest = np.zeros((n, k1, 3), np.float32)
    for k in range(k1):
        for c in range(3):
            rest[:, k, c] = arr[f"f_rest_{c * k1 + k}"]
    std = set(prop_names(degree, normals=False))
    return dict(
        means=cols(["x", "y", "z"]), scales=cols(["scale_0", "scale_1", "scale_2"]),
        quats=cols(["rot_0", "rot_1", "rot_2", "rot_3"]), opacities=cols(["opacity"])[:, 0],
        sh_dc=cols(["f_dc_0", "f_dc_1", "f_dc_2"]).reshape(n, 1, 3), sh_rest=rest,
        extra={nm: np.asarray(arr[nm]) for nm in arr.dtype.names if nm not in std},
    )


def assert_matches_struct(s: SplatArrays, arr: np.ndarray, degree: int):
    exp = expected_from_struct(arr, degree)
    for name in STANDARD:
        assert_bits_equal(getattr(s, name), exp[name], name)
    assert list(s.extra) == list(exp["extra"])
    for k, v in exp["extra"].items():
        assert_bits_equal(s.extra[k], v, f"extra[{k!r}]")
        assert s.extra[k].dtype.isnative


def no_temp_files(directory: Path, expected: set[str]):
    assert {p.name for p in directory.iterdir()} == expected


MIXED_EXTRAS = [("red", "u1"), ("filter_3D", "f4"), ("splat_id", "i4"), ("weight", "f8"),
                ("green", "u1"), ("tag", "i2")]


# --------------------------------------------------------------------------
# round trips
# --------------------------------------------------------------------------

@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("normals", [True, False])
def test_round_trip_exact(tmp_path, degree, normals):
    n = 257
    rng = np.random.default_rng(degree)
    extras = {}
    if normals:
        extras.update(nx=rng.standard_normal(n).astype(np.float32),
                      ny=np.zeros(n, np.float32), nz=np.full(n, -0.0, np.float32))
    extras.update(red=rng.integers(0, 256, n, dtype=np.uint8),
                  filter_3D=rng.standard_normal(n).astype(np.float32),
                  splat_id=rng.integers(-2**31, 2**31 - 1, n, dtype=np.int32),
                  weight=rng.standard_normal(n))
    s = random_splats(n, degree, seed=degree, extras=extras)
    p1, p2 = tmp_path / "a.ply", tmp_path / "b.ply"
    write_splat_ply(p1, s, comments=["hello world"])
    r1 = read_splat_ply(p1)
    assert r1.count == n and r1.sh_degree == degree
    assert r1.comments == ["hello world"]
    if normals:
        assert_splats_equal(r1, s)
    else:  # normals are written as zeros and come back as extras
        assert_splats_equal(r1, s, extra=False)
        assert list(r1.extra) == ["nx", "ny", "nz"] + list(extras)
        for k in ("nx", "ny", "nz"):
            assert r1.extra[k].dtype == np.float32 and not r1.extra[k].any()
        for k in extras:
            assert_bits_equal(r1.extra[k], extras[k], k)
    write_splat_ply(p2, r1, comments=r1.comments)
    r2 = read_splat_ply(p2)
    assert_splats_equal(r2, r1)
    assert p1.read_bytes() == p2.read_bytes()

    # The standard property order, then the extras with their own types.
    el = plyfile.PlyData.read(str(p1))["vertex"]
    names = [p.name for p in el.properties]
    assert names == prop_names(degree) + ["red", "filter_3D", "splat_id", "weight"]
    types = {p.name: p.val_dtype for p in el.properties}
    assert types["red"] == "u1" and types["splat_id"] == "i4" and types["weight"] == "f8"
    assert types["x"] == "f4" and types["nx"] == "f4"
    with open(p1, "rb") as f:
        assert f.read(40).startswith(b"ply\nformat binary_little_endian 1.0\n")


def test_round_trip_through_plyfile_reading(tmp_path):
    """Our writer's output is read by plyfile as the same values."""
    s = random_splats(100, 3, seed=5, extras={"red": np.arange(100, dtype=np.uint8)})
    path = tmp_path / "w.ply"
    write_splat_ply(path, s)
    arr = plyfile.PlyData.read(str(path))["vertex"].data
    exp = expected_from_struct(arr, 3)
    for name in STANDARD:
        assert_bits_equal(getattr(s, name), exp[name], name)
    assert_bits_equal(arr["red"], s.extra["red"])


def test_threaded_chunked_paths_exact(tmp_path, monkeypatch):
    """Small chunks and several threads: chunk and thread boundaries are exact."""
    monkeypatch.setattr(ply_mod, "_CHUNK_BYTES", 3000)
    monkeypatch.setattr(ply_mod, "_BYTES_PER_WORKER", 1)
    monkeypatch.setattr(ply_mod.os, "cpu_count", lambda: 3)
    arr = make_struct(2000, 3, seed=11, extras=MIXED_EXTRAS)  # odd row size: unaligned columns
    for order in "<>":
        path = write_plyfile(tmp_path / f"in{order == '<'}.ply", arr.astype(arr.dtype.newbyteorder(order)),
                             byte_order=order)
        s = read_splat_ply(path)
        assert_matches_struct(s, arr, 3)
    out = tmp_path / "out.ply"
    write_splat_ply(out, s)
    assert_splats_equal(read_splat_ply(out), s)
    monkeypatch.setattr(ply_mod.os, "cpu_count", lambda: 1)
    single = tmp_path / "single.ply"
    write_splat_ply(single, s)
    assert single.read_bytes() == out.read_bytes()


def test_empty_splat_set_round_trip(tmp_path):
    s = random_splats(0, 2)
    path = tmp_path / "empty.ply"
    write_splat_ply(path, s)
    r = read_splat_ply(path)
    assert r.count == 0 and r.sh_degree == 2 and r.sh_rest.shape == (0, 8, 3)


# --------------------------------------------------------------------------
# SH layout, degree truncation and padding
# --------------------------------------------------------------------------

def distinct_rest_file(tmp_path, degree, n=6):
    arr = make_struct(n, degree, seed=1)
    for i in range(3 * K1[degree]):
        arr[f"f_rest_{i}"] = i
    return write_plyfile(tmp_path / f"rest{degree}.ply", arr)


def test_f_rest_is_channel_major(tmp_path):
    path = distinct_rest_file(tmp_path, 3)
    s = read_splat_ply(path)
    k, c = np.meshgrid(np.arange(15), np.arange(3), indexing="ij")
    assert s.sh_rest.shape == (6, 15, 3) and s.sh_rest.flags.c_contiguous
    assert np.array_equal(s.sh_rest, np.broadcast_to(c * 15 + k, (6, 15, 3)))


def test_truncate_keeps_first_coefficients_of_each_channel(tmp_path):
    path = distinct_rest_file(tmp_path, 3)
    s1 = read_splat_ply(path, sh_degree=1)
    assert s1.sh_degree == 1 and s1.sh_rest.shape == (6, 3, 3)
    # rows: coefficient k; columns: channel c
    assert np.array_equal(s1.sh_rest[0], [[0, 15, 30], [1, 16, 31], [2, 17, 32]])
    assert np.array_equal(s1.sh_rest[5], s1.sh_rest[0])
    s2 = read_splat_ply(path, sh_degree=2)
    assert np.array_equal(s2.sh_rest[0], np.array([[c * 15 + k for c in range(3)] for k in range(8)]))
    s0 = read_splat_ply(path, sh_degree=0)
    assert s0.sh_rest.shape == (6, 0, 3) and s0.sh_degree == 0
    full = read_splat_ply(path)
    for t in (s0, s1, s2):
        assert_bits_equal(t.sh_dc, full.sh_dc)
        assert_bits_equal(t.means, full.means)


def test_pad_with_zeros(tmp_path):
    path = distinct_rest_file(tmp_path, 1)
    s = read_splat_ply(path, sh_degree=3)
    assert s.sh_degree == 3 and s.sh_rest.shape == (6, 15, 3)
    assert np.array_equal(s.sh_rest[:, :3], np.broadcast_to([[0, 3, 6], [1, 4, 7], [2, 5, 8]], (6, 3, 3)))
    assert not s.sh_rest[:, 3:].any()
    path0 = distinct_rest_file(tmp_path, 0)
    s0 = read_splat_ply(path0, sh_degree=2)
    assert s0.sh_rest.shape == (6, 8, 3) and not s0.sh_rest.any()


def test_truncate_and_pad_general_path(tmp_path):
    """Same layout rules when the file needs the structured (mixed-type) path."""
    arr = make_struct(5, 3, seed=2)
    arr = arr.astype([(nm, "<f8") for nm in arr.dtype.names])  # doubles that fit in float32
    for i in range(45):
        arr[f"f_rest_{i}"] = i
    path = write_plyfile(tmp_path / "double.ply", arr)
    s1 = read_splat_ply(path, sh_degree=1)
    assert np.array_equal(s1.sh_rest[0], [[0, 15, 30], [1, 16, 31], [2, 17, 32]])
    s = read_splat_ply(path)
    assert s.means.dtype == np.float32
    assert_bits_equal(s.means, np.stack([arr["x"], arr["y"], arr["z"]], 1).astype(np.float32))


@pytest.mark.parametrize("bad", [4, -1, 1.0, "3", True])
def test_invalid_sh_degree(tmp_path, bad):
    path = distinct_rest_file(tmp_path, 1)
    with pytest.raises(ValueError, match="sh_degree"):
        read_splat_ply(path, sh_degree=bad)


# --------------------------------------------------------------------------
# encodings
# --------------------------------------------------------------------------

@pytest.mark.parametrize("degree", [1, 3])
def test_big_endian_and_ascii_equal_little_endian(tmp_path, degree):
    arr = make_struct(150, degree, seed=3, extras=MIXED_EXTRAS)
    le = read_splat_ply(write_plyfile(tmp_path / "le.ply", arr))
    assert_matches_struct(le, arr, degree)
    be_arr = arr.astype(arr.dtype.newbyteorder(">"))
    be_path = write_plyfile(tmp_path / "be.ply", be_arr, byte_order=">")
    assert b"binary_big_endian" in be_path.read_bytes()[:60]
    be = read_splat_ply(be_path)
    assert_splats_equal(be, le)
    txt_path = write_plyfile(tmp_path / "txt.ply", arr, text=True)
    assert b"format ascii" in txt_path.read_bytes()[:60]
    txt = read_splat_ply(txt_path)
    assert_splats_equal(txt, le)
    for s in (le, be, txt):
        assert all(v.dtype.isnative for v in s.extra.values())
    # truncation works the same way in all three encodings
    t_le, t_be, t_txt = (read_splat_ply(p, sh_degree=0) for p in
                         (tmp_path / "le.ply", be_path, txt_path))
    assert_splats_equal(t_be, t_le)
    assert_splats_equal(t_txt, t_le)


def test_crlf_header_and_comments(tmp_path):
    arr = make_struct(10, 1, seed=4)
    src = write_plyfile(tmp_path / "lf.ply", arr, comments=["made by  a test", ""])
    data = src.read_bytes()
    cut = data.index(b"end_header\n") + len(b"end_header\n")
    crlf = tmp_path / "crlf.ply"
    crlf.write_bytes(data[:cut].replace(b"\n", b"\r\n") + data[cut:])
    a, b = read_splat_ply(src), read_splat_ply(crlf)
    assert_splats_equal(a, b)
    assert a.comments == b.comments == ["made by  a test", ""]


def test_other_elements_are_skipped_with_warning(tmp_path):
    arr = make_struct(20, 2, seed=6)
    faces = np.empty(3, dtype=[("vertex_indices", "O")])
    faces["vertex_indices"] = [np.array([0, 1, 2], np.int32)] * 3
    face_el = plyfile.PlyElement.describe(faces, "face", len_types={"vertex_indices": "u1"},
                                          val_types={"vertex_indices": "i4"})
    after = write_plyfile(tmp_path / "after.ply", arr, more=[face_el])
    with pytest.warns(UserWarning, match="'face'"):
        s = read_splat_ply(after)
    assert_matches_struct(s, arr, 2)
    # A list element *before* the vertex data needs the general reader.
    before = tmp_path / "before.ply"
    plyfile.PlyData([face_el, plyfile.PlyElement.describe(arr, "vertex")]).write(str(before))
    with pytest.warns(UserWarning, match="'face'"):
        s2 = read_splat_ply(before)
    assert_matches_struct(s2, arr, 2)
    # ... and in ASCII, where rows are lines to skip
    before_txt = tmp_path / "before_txt.ply"
    plyfile.PlyData([face_el, plyfile.PlyElement.describe(arr, "vertex")], text=True).write(str(before_txt))
    with pytest.warns(UserWarning, match="'face'"):
        s3 = read_splat_ply(before_txt)
    assert_matches_struct(s3, arr, 2)


def test_list_valued_extra_is_dropped_with_warning(tmp_path):
    arr = make_struct(7, 1, seed=8)
    dt = arr.dtype.descr + [("ids", "O")]
    arr2 = np.empty(7, dtype=dt)
    for nm in arr.dtype.names:
        arr2[nm] = arr[nm]
    arr2["ids"] = [np.arange(i % 3, dtype=np.int32) for i in range(7)]
    path = write_plyfile(tmp_path / "lists.ply", arr2)
    with pytest.warns(UserWarning, match="'ids'"):
        s = read_splat_ply(path)
    assert_matches_struct(s, arr, 1)


# --------------------------------------------------------------------------
# bad files
# --------------------------------------------------------------------------

def good_bytes(n=4, degree=1, **kw) -> bytes:
    import io as _io
    buf = _io.BytesIO()
    plyfile.PlyData([plyfile.PlyElement.describe(make_struct(n, degree, **kw), "vertex")]).write(buf)
    return buf.getvalue()


def header_for(props, n=2, fmt="binary_little_endian", extra_lines=()):
    lines = ["ply", f"format {fmt} 1.0", *extra_lines, f"element vertex {n}"]
    lines += [p if p.startswith("property") else f"property float {p}" for p in props]
    return ("\n".join(lines) + "\nend_header\n").encode()


def expect_bad(path, *fragments):
    with pytest.raises(PlyFormatError) as info:
        read_splat_ply(path)
    msg = str(info.value)
    assert str(path) in msg
    for frag in fragments:
        assert frag in msg, f"{frag!r} not in {msg!r}"
    assert isinstance(info.value, ValueError)
    return msg


def test_empty_file(tmp_path):
    p = tmp_path / "empty.ply"
    p.write_bytes(b"")
    expect_bad(p, "empty")


@pytest.mark.parametrize("content", [b"PK\x03\x04 not a ply", b"plyx\n", b"\x00" * 100, b"ply"])
def test_not_a_ply(tmp_path, content):
    p = tmp_path / "magic.ply"
    p.write_bytes(content)
    expect_bad(p, "not a PLY file")


@pytest.mark.parametrize("header, fragment", [
    (b"ply\nformat binary_little_endian 1.0\nelement vertex abc\nend_header\n", "'abc'"),
    (b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty quux x\nend_header\n", "'quux'"),
    (b"ply\nformat binary_middle_endian 1.0\nelement vertex 2\nend_header\n", "format"),
    (b"ply\nformat ascii 2.0\nend_header\n", "version"),
    (b"ply\nelement vertex 2\nend_header\n", "'format'"),
    (b"ply\nformat ascii 1.0\nproperty float x\nend_header\n", "before any 'element'"),
    (b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float x\nend_header\n",
     "duplicate property 'x'"),
    (b"ply\nformat ascii 1.0\nelement vertex 2\nbogus line\nend_header\n", "'bogus'"),
    (b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\n", "end_header"),
    (b"ply\nformat ascii 1.0\ncomment caf\xe9\nend_header\n", "non-ASCII"),
])
def test_malformed_header(tmp_path, header, fragment):
    p = tmp_path / "hdr.ply"
    p.write_bytes(header)
    expect_bad(p, "malformed PLY header", fragment)


def test_no_vertex_element(tmp_path):
    p = tmp_path / "novertex.ply"
    p.write_bytes(b"ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int vertex_indices\n"
                  b"end_header\n3 0 1 2\n")
    expect_bad(p, "no 'vertex' element", "'face'")


@pytest.mark.parametrize("missing", ["x", "f_dc_1", "opacity", "scale_2", "rot_3"])
def test_missing_required_property(tmp_path, missing):
    props = [nm for nm in prop_names(1) if nm != missing]
    p = tmp_path / "missing.ply"
    p.write_bytes(header_for(props) + b"\0" * 4 * len(props) * 2)
    expect_bad(p, f"missing property '{missing}'")


def test_missing_f_rest_index(tmp_path):
    props = [nm if nm != "f_rest_4" else "f_rest_9" for nm in prop_names(1)]
    p = tmp_path / "gap.ply"
    p.write_bytes(header_for(props) + b"\0" * 4 * len(props) * 2)
    expect_bad(p, "missing property 'f_rest_4'")


def test_list_where_scalar_required(tmp_path):
    props = [nm if nm != "opacity" else "property list uchar float opacity" for nm in prop_names(0)]
    p = tmp_path / "list.ply"
    p.write_bytes(header_for(props, n=0))
    msg = expect_bad(p, "'opacity'", "list")
    assert "scalar" in msg


@pytest.mark.parametrize("count", [10, 3, 44, 48])
def test_bad_f_rest_count(tmp_path, count):
    props = prop_names(0) + [f"f_rest_{i}" for i in range(count)]
    p = tmp_path / "rest.ply"
    p.write_bytes(header_for(props, n=0))
    expect_bad(p, f"f_rest properties: {count}")


@pytest.mark.parametrize("order", ["<", ">"])
def test_truncated_binary(tmp_path, order):
    n = 50
    arr = make_struct(n, 3, extras=[("red", "u1")], byte_order=order)
    src = write_plyfile(tmp_path / "full.ply", arr, byte_order=order)
    data = src.read_bytes()
    row = 62 * 4 + 1
    hdr = len(data) - n * row
    p = tmp_path / "trunc.ply"
    p.write_bytes(data[:-(row + 7)])
    avail = n * row - row - 7
    expect_bad(p, "truncated", f"{n} rows", str(n * row), f"only {avail} bytes", f"{n - 2} complete rows")
    p.write_bytes(data[:hdr])  # header only
    expect_bad(p, "truncated", "only 0 bytes")
    # plyfile memory-maps and would not notice on its own; we also catch a
    # file that is one byte short
    p.write_bytes(data[:-1])
    expect_bad(p, "truncated")


def test_truncated_general_and_fallback_paths(tmp_path):
    data = good_bytes(n=6, degree=1, std_type="f8")
    p = tmp_path / "trunc_f8.ply"
    p.write_bytes(data[:-5])
    expect_bad(p, "truncated")
    arr = make_struct(6, 1)
    faces = np.empty(2, dtype=[("vertex_indices", "O")])
    faces["vertex_indices"] = [np.array([0, 1, 2], np.int32)] * 2
    face_el = plyfile.PlyElement.describe(faces, "face")
    full = tmp_path / "face_first.ply"
    plyfile.PlyData([face_el, plyfile.PlyElement.describe(arr, "vertex")]).write(str(full))
    p2 = tmp_path / "face_first_trunc.ply"
    p2.write_bytes(full.read_bytes()[:-10])
    with pytest.warns(UserWarning):
        expect_bad(p2, "could not read vertex data")


def test_truncated_ascii(tmp_path):
    arr = make_struct(5, 1, seed=9)
    src = write_plyfile(tmp_path / "t.ply", arr, text=True)
    lines = src.read_bytes().split(b"\n")
    p = tmp_path / "short.ply"
    p.write_bytes(b"\n".join(lines[:-3]) + b"\n")  # drop the last two rows
    expect_bad(p, "truncated", "expected 5 vertex rows, found 3")


def test_unparsable_ascii(tmp_path):
    arr = make_struct(5, 1, seed=9)
    src = write_plyfile(tmp_path / "t.ply", arr, text=True)
    text = src.read_bytes()
    cut = text.index(b"end_header\n") + len(b"end_header\n")
    rows = text[cut:].split(b"\n")
    fields = rows[2].split(b" ")
    p = tmp_path / "garbage.ply"
    p.write_bytes(text[:cut] + b"\n".join(rows[:2] + [b" ".join([b"abc"] + fields[1:])] + rows[3:]))
    expect_bad(p, "could not parse ASCII", "abc")
    p.write_bytes(text[:cut] + b"\n".join(rows[:2] + [b" ".join(fields[:-1])] + rows[3:]))
    expect_bad(p, "could not parse ASCII")


def test_missing_file_is_os_error(tmp_path):
    with pytest.raises(FileNotFoundError):
        read_splat_ply(tmp_path / "nope.ply")


# --------------------------------------------------------------------------
# non-finite rows
# --------------------------------------------------------------------------

def nonfinite_struct(order="<"):
    arr = make_struct(40, 3, seed=12, extras=[("red", "u1")])
    arr["scale_1"][7] = np.nan
    arr["f_rest_17"][21] = np.inf
    arr["rot_0"][21] = -np.inf
    arr["nx"][3] = np.nan  # not a standard property: does not count
    return arr.astype(arr.dtype.newbyteorder(order))


@pytest.mark.parametrize("order", ["<", ">"])
def test_nonfinite_error(tmp_path, order):
    path = write_plyfile(tmp_path / "nan.ply", nonfinite_struct(order), byte_order=order)
    msg = expect_bad(path, "2 of 40 row(s)", "row 7", "'scale_1'", "nonfinite='drop'", "nonfinite='keep'")
    assert "NaN or Inf" in msg


def test_nonfinite_drop(tmp_path):
    arr = nonfinite_struct()
    path = write_plyfile(tmp_path / "nan.ply", arr)
    with pytest.warns(UserWarning, match="dropped 2 of 40"):
        s = read_splat_ply(path, nonfinite="drop")
    assert s.count == 38 and s.nonfinite_rows == 2 and s.dropped_rows == 2
    keep = np.ones(40, bool)
    keep[[7, 21]] = False
    assert_matches_struct(s, arr[keep], 3)
    assert np.isnan(s.extra["nx"][3])  # the NaN normal row was kept


def test_nonfinite_keep(tmp_path):
    arr = nonfinite_struct()
    path = write_plyfile(tmp_path / "nan.ply", arr)
    with pytest.warns(UserWarning, match="kept 2 of 40"):
        s = read_splat_ply(path, nonfinite="keep")
    assert s.count == 40 and s.nonfinite_rows == 2 and s.dropped_rows == 0
    assert_matches_struct(s, arr, 3)
    assert np.isnan(s.scales[7, 1]) and s.sh_rest[21, 2, 1] == np.inf  # f_rest_17: c=1, k=2


def test_nonfinite_in_dropped_coefficients_is_ignored(tmp_path):
    arr = make_struct(10, 3, seed=13)
    arr["f_rest_40"][4] = np.nan  # channel 2, coefficient 10: not kept at degree 1
    path = write_plyfile(tmp_path / "nan_hi.ply", arr)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        s = read_splat_ply(path, sh_degree=1)
    assert s.nonfinite_rows == 0 and s.count == 10
    with pytest.raises(PlyFormatError, match="'f_rest_40'"):
        read_splat_ply(path)


def test_nonfinite_ascii_and_general_path(tmp_path):
    arr = nonfinite_struct()
    txt = write_plyfile(tmp_path / "nan.txt.ply", arr, text=True)
    expect_bad(txt, "2 of 40 row(s)", "'scale_1'")
    with pytest.warns(UserWarning):
        assert read_splat_ply(txt, nonfinite="drop").count == 38


def test_finite_file_has_no_warning(tmp_path):
    arr = make_struct(30, 2)
    arr["nx"][4] = np.nan  # only standard properties count
    arr["ny"][5] = np.inf
    path = write_plyfile(tmp_path / "ok.ply", arr)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        s = read_splat_ply(path)
    assert s.nonfinite_rows == 0 and s.dropped_rows == 0


def test_invalid_nonfinite_option(tmp_path):
    path = write_plyfile(tmp_path / "ok.ply", make_struct(3, 0))
    with pytest.raises(ValueError, match="nonfinite"):
        read_splat_ply(path, nonfinite="ignore")


# --------------------------------------------------------------------------
# writer validation and atomicity
# --------------------------------------------------------------------------

@pytest.mark.parametrize("field, value, fragment", [
    ("means", np.zeros((5, 2), np.float32), "means"),
    ("scales", np.zeros((4, 3), np.float32), "scales"),
    ("quats", np.zeros((5, 3), np.float32), "quats"),
    ("opacities", np.zeros((5, 1), np.float32), "opacities"),
    ("sh_dc", np.zeros((5, 3), np.float32), "sh_dc"),
    ("sh_rest", np.zeros((5, 7, 3), np.float32), "sh_rest"),
    ("sh_rest", np.zeros((5, 3, 1), np.float32), "sh_rest"),
    ("scales", np.zeros((5, 3), np.int32), "floating"),
    ("extra", {"red": np.zeros(4, np.uint8)}, "extra['red']"),
    ("extra", {"big": np.zeros(5, np.int64)}, "no PLY type"),
    ("extra", {"flag": np.zeros(5, bool)}, "no PLY type"),
    ("extra", {"opacity": np.zeros(5, np.float32)}, "clashes"),
    ("extra", {"f_rest_50": np.zeros(5, np.float32)}, "clashes"),
    ("extra", {"two words": np.zeros(5, np.float32)}, "invalid property name"),
])
def test_write_validation_before_touching_disk(tmp_path, field, value, fragment):
    s = random_splats(5, 1)
    setattr(s, field, value)
    target = tmp_path / "out.ply"
    target.write_bytes(b"previous content")
    with pytest.raises(ValueError) as info:
        write_splat_ply(target, s)
    assert fragment in str(info.value)
    if field != "extra":
        assert str(tuple(np.shape(value))) in str(info.value)
    assert target.read_bytes() == b"previous content"
    no_temp_files(tmp_path, {"out.ply"})


def test_write_rejects_bad_comments(tmp_path):
    with pytest.raises(ValueError, match="comments"):
        write_splat_ply(tmp_path / "c.ply", random_splats(2, 0), comments=["two\nlines"])
    assert not list(tmp_path.iterdir())


def test_failure_midway_leaves_target_untouched(tmp_path, monkeypatch):
    target = tmp_path / "scene.ply"
    write_splat_ply(target, random_splats(10, 1))
    before = target.read_bytes()
    mode_before = stat.S_IMODE(target.stat().st_mode)

    calls = {"n": 0}
    real = ply_mod._copy_columns

    def failing(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 3:
            raise OSError("disk full (simulated)")
        return real(*args, **kwargs)

    monkeypatch.setattr(ply_mod, "_copy_columns", failing)
    monkeypatch.setattr(ply_mod, "_CHUNK_BYTES", 4096)  # several chunks
    big = random_splats(500, 3, seed=3)
    with pytest.raises(OSError, match="simulated"):
        write_splat_ply(target, big)
    assert calls["n"] == 3
    assert target.read_bytes() == before
    no_temp_files(tmp_path, {"scene.ply"})

    # same with several writer threads
    calls["n"] = -10**9
    monkeypatch.setattr(ply_mod, "_BYTES_PER_WORKER", 1)
    monkeypatch.setattr(ply_mod.os, "cpu_count", lambda: 4)
    calls["n"] = 0
    with pytest.raises(OSError, match="simulated"):
        write_splat_ply(target, big)
    assert target.read_bytes() == before
    no_temp_files(tmp_path, {"scene.ply"})
    assert stat.S_IMODE(target.stat().st_mode) == mode_before


def test_failure_at_rename_leaves_target_untouched(tmp_path, monkeypatch):
    target = tmp_path / "scene.ply"
    target.write_bytes(b"old")

    def boom(src, dst):
        raise PermissionError("rename refused (simulated)")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(PermissionError):
        write_splat_ply(target, random_splats(20, 2))
    monkeypatch.undo()
    assert target.read_bytes() == b"old"
    no_temp_files(tmp_path, {"scene.ply"})


def test_atomic_write_helper(tmp_path):
    target = tmp_path / "f.txt"
    target.write_text("old")
    os.chmod(target, 0o640)
    with pytest.raises(RuntimeError):
        with atomic_write(target, "w") as f:
            f.write("partial")
            raise RuntimeError("stop")
    assert target.read_text() == "old"
    no_temp_files(tmp_path, {"f.txt"})
    with atomic_write(target, "w", encoding="utf-8") as f:
        assert Path(f.name).parent == tmp_path and f.name != str(target)
        f.write("new ✓")
    assert target.read_text(encoding="utf-8") == "new ✓"
    assert stat.S_IMODE(target.stat().st_mode) == 0o640
    with atomic_write(tmp_path / "g.bin", fsync=False) as f:
        f.write(b"\x00\x01")
    assert (tmp_path / "g.bin").read_bytes() == b"\x00\x01"
    no_temp_files(tmp_path, {"f.txt", "g.bin"})
    with pytest.raises(ValueError):
        with atomic_write(tmp_path / "h", "a"):
            pass


# --------------------------------------------------------------------------
# the dataclass, and the no-MLX import rule
# --------------------------------------------------------------------------

def test_splat_arrays_properties():
    s = random_splats(3, 2, extras={"red": np.zeros(3, np.uint8)})
    assert s.count == 3 and s.sh_degree == 2
    assert repr(s) == "SplatArrays(count=3, sh_degree=2, extra=['red'])"
    s.validate()
    s.sh_rest = np.zeros((3, 5, 3), np.float32)
    with pytest.raises(ValueError):
        _ = s.sh_degree
    with pytest.raises(ValueError, match="sh_rest"):
        s.validate()


def test_io_does_not_import_mlx():
    code = "import sys, mlx3d.io; assert 'mlx' not in sys.modules and 'mlx.core' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True, cwd=REPO)


# --------------------------------------------------------------------------
# a real file written by another trainer
# --------------------------------------------------------------------------

@pytest.mark.skipif(not OPENSPLAT.exists(), reason=f"real-data file not found: {OPENSPLAT}")
def test_opensplat_file(tmp_path):
    s = read_splat_ply(OPENSPLAT)
    assert s.count == 31995 and s.sh_degree == 3
    assert s.comments and s.comments[0].startswith("Generated by opensplat")
    assert list(s.extra) == ["nx", "ny", "nz"]
    ref = plyfile.PlyData.read(str(OPENSPLAT))["vertex"].data
    assert_matches_struct(s, ref, 3)
    assert s.nonfinite_rows == 0

    out = tmp_path / "rewritten.ply"
    write_splat_ply(out, s, comments=s.comments)
    again = read_splat_ply(out)
    assert_splats_equal(again, s)
    assert again.comments == s.comments
    # Same layout as the original, so the bytes are the same too.
    assert out.read_bytes() == OPENSPLAT.read_bytes()
