"""Mesh PLY files (mlx3d.io.mesh_ply): round trips, plyfile interop, errors, atomicity."""

from __future__ import annotations

import contextlib
import os

import numpy as np
import plyfile
import pytest

from mlx3d.errors import PlyFormatError
from mlx3d.io import mesh_ply
from mlx3d.io.mesh_ply import read_mesh_ply, write_mesh_ply
from mlx3d.meshing import SurfaceMesh

from core_marks import runs_no_kernel  # noqa: E402

pytestmark = runs_no_kernel  # file formats, datasets and packaging: no kernel of ours runs here


def random_mesh(nv=50, nf=90, seed=0):
    rng = np.random.default_rng(seed)
    v = (rng.standard_normal((nv, 3)) * 10).astype(np.float32)
    f = rng.integers(0, nv, (nf, 3)).astype(np.int32)
    c = rng.random((nv, 3)).astype(np.float32)
    return v, f, c


def listing(directory) -> list[str]:
    return sorted(os.listdir(directory))


def write_plyfile(path, vertex_rows, faces, text=False, byte_order="<", face_prop="vertex_indices"):
    """Writes a PLY with plyfile (polygon faces given as a list of index lists)."""
    fa = np.empty(len(faces), dtype=[(face_prop, "O")])
    for i, poly in enumerate(faces):
        fa[i] = (np.asarray(poly, dtype=np.int32),)
    elements = [plyfile.PlyElement.describe(vertex_rows, "vertex"),
                plyfile.PlyElement.describe(fa, "face")]
    plyfile.PlyData(elements, text=text, byte_order=byte_order).write(str(path))


# --------------------------------------------------------------------------- #
# round trips
# --------------------------------------------------------------------------- #
def test_round_trip_with_colors(tmp_path):
    v, f, c = random_mesh()
    path = tmp_path / "m.ply"
    write_mesh_ply(path, v, f, c)
    m = read_mesh_ply(path)
    assert isinstance(m, SurfaceMesh)
    assert m.vertices.dtype == np.float32 and m.faces.dtype == np.int32 and m.colors.dtype == np.float32
    assert np.array_equal(m.vertices, v)
    assert np.array_equal(m.faces, f)
    assert np.abs(m.colors - c).max() <= 0.5 / 255 + 1e-7
    np.testing.assert_array_equal(m.colors * 255, np.rint(c.astype(np.float64) * 255))
    assert listing(tmp_path) == ["m.ply"]


def test_round_trip_without_colors_and_clipping(tmp_path):
    v, f, _ = random_mesh(seed=1)
    write_mesh_ply(tmp_path / "a.ply", v.astype(np.float64), f.astype(np.int64))
    m = read_mesh_ply(tmp_path / "a.ply")
    assert m.colors is None
    assert np.array_equal(m.vertices, v) and np.array_equal(m.faces, f)
    colors = np.array([[-0.5, 0.5, 1.5]] * len(v))
    write_mesh_ply(tmp_path / "b.ply", v, f, colors)
    np.testing.assert_allclose(read_mesh_ply(tmp_path / "b.ply").colors[0], [0.0, 128 / 255, 1.0])


def test_empty_mesh_round_trip(tmp_path):
    write_mesh_ply(tmp_path / "e.ply", np.zeros((0, 3)), np.zeros((0, 3), np.int32))
    m = read_mesh_ply(tmp_path / "e.ply")
    assert m.vertices.shape == (0, 3) and m.faces.shape == (0, 3)


def test_surface_mesh_save_ply(tmp_path):
    v, f, c = random_mesh(seed=2)
    SurfaceMesh(v, f, c).save_ply(tmp_path / "s.ply")
    m = read_mesh_ply(tmp_path / "s.ply")
    assert np.array_equal(m.vertices, v) and np.array_equal(m.faces, f)


def test_file_is_standard_binary_ply(tmp_path):
    v, f, c = random_mesh(nv=7, nf=5, seed=3)
    path = tmp_path / "m.ply"
    write_mesh_ply(path, v, f, c)
    raw = path.read_bytes()
    header = raw[: raw.index(b"end_header\n") + len(b"end_header\n")].decode("ascii")
    assert header == (
        "ply\nformat binary_little_endian 1.0\nelement vertex 7\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        "element face 5\nproperty list uchar int vertex_indices\nend_header\n"
    )
    assert len(raw) == len(header) + 7 * 15 + 5 * 13
    data = plyfile.PlyData.read(str(path))
    assert not data.text and data.byte_order == "<"
    vert = data["vertex"].data
    np.testing.assert_array_equal(np.stack([vert["x"], vert["y"], vert["z"]], 1), v)
    assert vert["red"].dtype == np.uint8
    np.testing.assert_array_equal(vert["green"], np.rint(c[:, 1].astype(np.float64) * 255))
    faces = np.stack(data["face"].data["vertex_indices"])
    np.testing.assert_array_equal(faces, f)


# --------------------------------------------------------------------------- #
# reading other writers' files
# --------------------------------------------------------------------------- #
VERTS = np.array(
    [(0, 0, 0, 255, 0, 0), (1, 0, 0, 0, 255, 0), (1, 1, 0, 0, 0, 255), (0, 1, 0, 51, 102, 153),
     (2, 0, 0, 0, 0, 0)],
    dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")],
)


@pytest.mark.parametrize("text, order", [(True, "="), (False, "<"), (False, ">")])
def test_polygons_are_fan_triangulated(tmp_path, text, order):
    path = tmp_path / "p.ply"
    write_plyfile(path, VERTS, [[0, 1, 2, 3], [1, 4, 2], [0, 1, 4, 2, 3]], text=text, byte_order=order)
    m = read_mesh_ply(path)
    np.testing.assert_array_equal(
        m.faces, [[0, 1, 2], [0, 2, 3], [1, 4, 2], [0, 1, 4], [0, 4, 2], [0, 2, 3]]
    )
    np.testing.assert_allclose(m.colors[3], [0.2, 0.4, 0.6], atol=1e-7)
    np.testing.assert_array_equal(m.vertices[:, 0], VERTS["x"])


def test_vertex_index_property_and_float_colors(tmp_path):
    verts = np.array([(0, 0, 0, 0.25, 0.5, 1.0), (1, 0, 0, 0, 0, 0), (0, 1, 0, 1, 1, 1)],
                     dtype=[("x", "f8"), ("y", "f8"), ("z", "f8"),
                            ("red", "f4"), ("green", "f4"), ("blue", "f4")])
    path = tmp_path / "q.ply"
    write_plyfile(path, verts, [[0, 1, 2]], face_prop="vertex_index")
    m = read_mesh_ply(path)
    np.testing.assert_array_equal(m.faces, [[0, 1, 2]])
    np.testing.assert_allclose(m.colors[0], [0.25, 0.5, 1.0])


# --------------------------------------------------------------------------- #
# malformed files
# --------------------------------------------------------------------------- #
def test_truncated_file_raises(tmp_path):
    v, f, c = random_mesh(seed=4)
    path = tmp_path / "m.ply"
    write_mesh_ply(path, v, f, c)
    raw = path.read_bytes()
    for cut in (len(raw) - 1, len(raw) - 13 * 10, len(raw) - 13 * 90 - 5, 40):
        path.write_bytes(raw[:cut])
        with pytest.raises(PlyFormatError, match="m.ply"):
            read_mesh_ply(path)


def test_malformed_files_raise(tmp_path):
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"not a ply file at all\n")
    with pytest.raises(PlyFormatError, match="not a readable PLY"):
        read_mesh_ply(bad)

    points_only = tmp_path / "points.ply"
    plyfile.PlyData([plyfile.PlyElement.describe(VERTS, "vertex")]).write(str(points_only))
    with pytest.raises(PlyFormatError, match="no 'face' element"):
        read_mesh_ply(points_only)

    path = tmp_path / "f.ply"
    write_plyfile(path, VERTS, [[0, 1, 2], [3, 4]])
    with pytest.raises(PlyFormatError, match="fewer than 3 vertices"):
        read_mesh_ply(path)

    write_plyfile(path, VERTS, [[0, 1, 5]])
    with pytest.raises(PlyFormatError, match=r"outside \[0, 5\)"):
        read_mesh_ply(path)

    flat = np.zeros(3, dtype=[("x", "f4"), ("y", "f4")])
    write_plyfile(path, flat, [[0, 1, 2]])
    with pytest.raises(PlyFormatError, match="lacks properties z"):
        read_mesh_ply(path)

    nan = VERTS.copy()
    nan["y"][2] = np.nan
    write_plyfile(path, nan, [[0, 1, 2]])
    with pytest.raises(PlyFormatError, match="NaN or Inf"):
        read_mesh_ply(path)

    with pytest.raises(FileNotFoundError):
        read_mesh_ply(tmp_path / "missing.ply")


# --------------------------------------------------------------------------- #
# bad input to the writer: ValueError, nothing written
# --------------------------------------------------------------------------- #
V, F, C = random_mesh(nv=6, nf=4, seed=5)


@pytest.mark.parametrize(
    "vertices, faces, colors, match",
    [
        (V[:, :2], F, None, r"vertices must have shape \(N, 3\)"),
        (np.where(np.arange(6)[:, None] == 2, np.nan, V), F, None, r"vertices has 1 rows with NaN or Inf \(first at row 2\)"),
        (V * np.float64(1e39), F, None, "float32 range"),
        (V, F[:, :2], None, r"faces must have shape"),
        (V, F.astype(np.float32), None, "faces must be an integer array"),
        (V, np.where(np.arange(4)[:, None] == 1, 6, F), None, r"faces has 1 rows with vertex indices outside \[0, 6\) \(first at row 1"),
        (V, np.where(np.arange(4)[:, None] == 3, -1, F), None, r"outside \[0, 6\)"),
        (V, F, C[:5], r"colors must have shape \(6, 3\)"),
        (V, F, np.full((6, 3), np.inf), "colors has 6 rows with NaN or Inf"),
        (V.astype(str), F, None, "vertices must be a real numeric array"),
    ],
)
def test_bad_input_writes_nothing(tmp_path, vertices, faces, colors, match):
    path = tmp_path / "out.ply"
    with pytest.raises(ValueError, match=match):
        write_mesh_ply(path, vertices, faces, colors)
    assert listing(tmp_path) == []


def test_failed_write_leaves_no_partial_file(tmp_path, monkeypatch):
    v, f, c = random_mesh(seed=6)
    path = tmp_path / "m.ply"
    write_mesh_ply(path, v, f, c)
    before = path.read_bytes()
    real = mesh_ply.atomic_write

    class DiskFull:
        def __init__(self, fh):
            self.fh, self.writes = fh, 0

        def write(self, data):
            self.writes += 1
            if self.writes == 2:  # header written, vertex data fails
                raise OSError(28, "No space left on device")
            return self.fh.write(data)

    @contextlib.contextmanager
    def failing(path_, mode="wb", **kw):
        with real(path_, mode, **kw) as fh:
            yield DiskFull(fh)

    monkeypatch.setattr(mesh_ply, "atomic_write", failing)
    with pytest.raises(OSError, match="No space"):
        write_mesh_ply(path, v[:10], f[:3] % 10)
    assert listing(tmp_path) == ["m.ply"]  # no temporary left behind
    assert path.read_bytes() == before  # the old file is untouched
    with pytest.raises(OSError, match="No space"):
        write_mesh_ply(tmp_path / "new.ply", v, f)
    assert listing(tmp_path) == ["m.ply"]
