"""Read and write triangle meshes as PLY files (numpy + plyfile, no MLX).

Written layout (binary little-endian)::

    element vertex V
    property float x, y, z
    property uchar red, green, blue        (only with colours)
    element face F
    property list uchar int vertex_indices

Colours are stored as ``round(clip(c, 0, 1) * 255)``. Files are written
through :func:`~mlx3d.io.atomic.atomic_write`: a failed write leaves no
partial file. Reading accepts any PLY format plyfile reads (binary either
endianness, ASCII), integer or float colours (``red green blue``) and polygon
faces (``vertex_indices`` or ``vertex_index``), fan-triangulated.
"""

from __future__ import annotations

import os

import numpy as np

from ..errors import PlyFormatError
from ..meshing.mesh import SurfaceMesh
from .atomic import atomic_write
from .ply import _check_counts, _read_header

__all__ = ["write_mesh_ply", "read_mesh_ply"]

_FACE_PROPERTIES = ("vertex_indices", "vertex_index")
_TRIANGLE_LISTS = {p: 3 for p in _FACE_PROPERTIES}


# --------------------------------------------------------------------------- #
# writing
# --------------------------------------------------------------------------- #
def _check_rows(name: str, value: object, width: int, kinds: str, rows: int | None = None) -> np.ndarray:
    arr = np.asarray(value)
    if arr.dtype.kind not in kinds:
        what = "an integer" if kinds == "iu" else "a real numeric"
        raise ValueError(f"{name} must be {what} array, got dtype {arr.dtype}")
    if arr.size == 0 and arr.ndim == 1:
        arr = arr.reshape(0, width)
    if arr.ndim != 2 or arr.shape[1] != width or (rows is not None and arr.shape[0] != rows):
        want = f"(N, {width})" if rows is None else f"({rows}, {width}) (one row per vertex)"
        raise ValueError(f"{name} must have shape {want}, got shape {arr.shape}")
    if arr.dtype.kind == "f":
        finite = np.isfinite(arr).all(axis=1)
        if not finite.all():
            bad = np.flatnonzero(~finite)
            raise ValueError(
                f"{name} has {bad.size} rows with NaN or Inf (first at row {int(bad[0])})"
            )
    return arr


def write_mesh_ply(
    path: str | os.PathLike,
    vertices: np.ndarray,
    faces: np.ndarray,
    colors: np.ndarray | None = None,
) -> None:
    """Write a triangle mesh as a binary little-endian PLY file (atomically).

    Args:
        path: destination file (replaced only once fully written).
        vertices: (V, 3) finite coordinates, stored as float32.
        faces: (F, 3) integer vertex indices in [0, V), stored as int32.
        colors: (V, 3) finite RGB in [0, 1] (clipped), stored as uchar; or None.

    Raises:
        ValueError: bad shape or dtype, NaN/Inf, or a face index out of range
            (nothing is written).
    """
    v = _check_rows("vertices", vertices, 3, "iuf")
    with np.errstate(over="ignore"):
        v32 = v.astype("<f4")
    if not np.isfinite(v32).all():
        raise ValueError("vertices has coordinates beyond the float32 range (|x| > 3.4e38)")
    f = _check_rows("faces", faces, 3, "iu")
    nv = v.shape[0]
    if f.size:
        lo, hi = int(f.min()), int(f.max())
        if lo < 0 or hi >= nv:
            bad = np.flatnonzero(((f < 0) | (f >= nv)).any(axis=1))
            raise ValueError(
                f"faces has {bad.size} rows with vertex indices outside [0, {nv}) "
                f"(first at row {int(bad[0])}: {f[bad[0]].tolist()})"
            )
    c = None
    if colors is not None:
        c = _check_rows("colors", colors, 3, "iuf", rows=nv)
        c = np.rint(np.clip(c.astype(np.float64), 0.0, 1.0) * 255.0).astype("u1")

    vfields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if c is not None:
        vfields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    vrec = np.empty(nv, dtype=vfields)
    vrec["x"], vrec["y"], vrec["z"] = v32[:, 0], v32[:, 1], v32[:, 2]
    if c is not None:
        vrec["red"], vrec["green"], vrec["blue"] = c[:, 0], c[:, 1], c[:, 2]
    frec = np.empty(f.shape[0], dtype=[("n", "u1"), ("v", "<i4", (3,))])
    frec["n"] = 3
    frec["v"] = f

    header = ["ply", "format binary_little_endian 1.0", f"element vertex {nv}"]
    header += [f"property float {a}" for a in "xyz"]
    if c is not None:
        header += [f"property uchar {a}" for a in ("red", "green", "blue")]
    header += [f"element face {f.shape[0]}", "property list uchar int vertex_indices", "end_header"]
    with atomic_write(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(vrec.tobytes())
        fh.write(frec.tobytes())


# --------------------------------------------------------------------------- #
# reading
# --------------------------------------------------------------------------- #
def _color_scale(dtype: np.dtype) -> float:
    if dtype.kind == "f":
        return 1.0
    if dtype.kind in "iu":
        return float(np.iinfo(dtype).max)
    raise PlyFormatError(f"colour properties have unsupported type {dtype}")


def _triangulate(lists: np.ndarray, nv: int, path: str) -> np.ndarray:
    """(F, 3) int32 triangles from a face list property (fans for polygons)."""
    if lists.dtype != object:  # fixed-length fast path: (F, n) array
        arr = np.asarray(lists)
        polys = {arr.shape[1]: (np.arange(arr.shape[0]), arr)} if arr.size else {}
    else:
        lengths = np.fromiter((len(x) for x in lists), dtype=np.int64, count=len(lists))
        polys = {}
        for n in np.unique(lengths):
            rows = np.flatnonzero(lengths == n)
            polys[int(n)] = (rows, np.array([lists[i] for i in rows]).reshape(len(rows), int(n)))
    short = [n for n in polys if n < 3]
    if short:
        n = short[0]
        raise PlyFormatError(f"{path}: {len(polys[n][0])} faces have fewer than 3 vertices ({n})")
    order, tris = [], []
    stride = max(polys, default=3) - 2  # triangles per face at most
    for n, (rows, idx) in polys.items():
        if idx.dtype.kind not in "iu":
            raise PlyFormatError(f"{path}: face vertex indices have non-integer type {idx.dtype}")
        idx = idx.astype(np.int64)
        for k in range(1, n - 1):  # fan: (0, k, k+1)
            tris.append(idx[:, [0, k, k + 1]])
            order.append(rows * stride + (k - 1))  # keep file order, then fan order
    if not tris:
        return np.zeros((0, 3), dtype=np.int32)
    tris_all = np.concatenate(tris)
    tris_all = tris_all[np.argsort(np.concatenate(order), kind="stable")]
    if tris_all.size and (tris_all.min() < 0 or tris_all.max() >= nv):
        bad = int(((tris_all < 0) | (tris_all >= nv)).any(axis=1).sum())
        raise PlyFormatError(f"{path}: {bad} faces reference vertices outside [0, {nv})")
    return tris_all.astype(np.int32)


def read_mesh_ply(path: str | os.PathLike) -> SurfaceMesh:
    """Read a PLY triangle mesh.

    Args:
        path: PLY file with a ``vertex`` element (``x y z``, optional
            ``red green blue``) and a ``face`` element (list property
            ``vertex_indices`` or ``vertex_index``). Polygons with more than 3
            vertices are fan-triangulated.

    Returns:
        :class:`~mlx3d.meshing.SurfaceMesh` (colours as float32 in [0, 1]:
        integer colours divided by their type's maximum, e.g. 255 for uchar).

    Raises:
        PlyFormatError: unreadable or truncated file, missing elements or
            properties, faces with fewer than 3 vertices or out-of-range
            indices, non-finite coordinates.
        FileNotFoundError: ``path`` does not exist.
    """
    import plyfile

    name = os.fspath(path)
    if not os.path.exists(name):
        raise FileNotFoundError(f"{name}: no such file")
    # plyfile allocates every element's rows before reading them: check the
    # declared counts against the file size first.
    with open(name, "rb") as fh:
        size = os.fstat(fh.fileno()).st_size
        try:
            header = _read_header(fh, name, size)
        except PlyFormatError as exc:
            problem = str(exc).removeprefix(f"{name}: ")
            raise PlyFormatError(f"{name}: not a readable PLY file ({problem})") from exc
    _check_counts(header, name, size, header.elements)
    try:
        try:  # triangles: memory-mapped fast path
            with open(name, "rb") as fh:
                data = plyfile.PlyData.read(fh, known_list_len={"face": _TRIANGLE_LISTS})
        except plyfile.PlyElementParseError as exc:
            if exc.element is None or exc.element.name != "face":
                raise
            with open(name, "rb") as fh:  # polygons (or a bad face list): per-row reader
                data = plyfile.PlyData.read(fh)
    except (plyfile.PlyParseError, ValueError, EOFError, UnicodeDecodeError, IndexError) as exc:
        raise PlyFormatError(f"{name}: not a readable PLY file ({exc})") from exc
    elements = {e.name: e for e in data.elements}
    if "vertex" not in elements:
        raise PlyFormatError(f"{name}: no 'vertex' element")
    if "face" not in elements:
        raise PlyFormatError(f"{name}: no 'face' element (not a mesh)")
    vdata = elements["vertex"].data
    fdata = elements["face"].data
    vlists = [p.name for p in elements["vertex"].properties if isinstance(p, plyfile.PlyListProperty)
              and p.name in ("x", "y", "z", "red", "green", "blue")]
    if vlists:
        what = f"property {vlists[0]} is a list" if len(vlists) == 1 else \
            f"properties {', '.join(vlists)} are lists"
        raise PlyFormatError(f"{name}: vertex {what}; scalars are required")

    vnames = vdata.dtype.names or ()
    missing = [a for a in "xyz" if a not in vnames]
    if missing:
        raise PlyFormatError(f"{name}: vertex element lacks properties {', '.join(missing)}")
    # Doubles beyond the float32 range become inf and signalling NaNs NaN: refused below.
    with np.errstate(over="ignore", invalid="ignore"):
        vertices = np.stack([np.asarray(vdata[a], dtype=np.float64) for a in "xyz"], axis=1)
        vertices = vertices.astype(np.float32)
    if not np.isfinite(vertices).all():
        bad = int((~np.isfinite(vertices).all(axis=1)).sum())
        raise PlyFormatError(
            f"{name}: {bad} vertices have NaN or Inf coordinates (or beyond the float32 range)")
    colors = None
    if all(a in vnames for a in ("red", "green", "blue")):
        cols = [np.asarray(vdata[a]) for a in ("red", "green", "blue")]
        with np.errstate(invalid="ignore"):  # signalling NaNs -> NaN: refused below
            colors = np.stack([c.astype(np.float64) / _color_scale(c.dtype) for c in cols], axis=1)
        if not np.isfinite(colors).all():
            raise PlyFormatError(f"{name}: vertex colours contain NaN or Inf")
        colors = np.clip(colors, 0.0, 1.0)

    fnames = fdata.dtype.names or ()
    prop = next((p for p in _FACE_PROPERTIES if p in fnames), None)
    if prop is None:
        raise PlyFormatError(
            f"{name}: face element has no 'vertex_indices' list (properties: {', '.join(fnames)})"
        )
    if not isinstance(elements["face"].ply_property(prop), plyfile.PlyListProperty):
        raise PlyFormatError(
            f"{name}: face property {prop!r} is a scalar; a list of vertex indices is required")
    faces = _triangulate(fdata[prop], len(vertices), name)
    return SurfaceMesh(vertices, faces, None if colors is None else colors.astype(np.float32))
