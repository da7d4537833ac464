"""COLMAP sparse models (binary and text) and COLMAP workspaces as datasets.

File formats, as COLMAP writes them (``doc/format.rst`` and
``src/colmap/scene/reconstruction_io.cc``; all binary data little-endian):

- ``cameras.bin``: ``uint64`` count, then per camera ``uint32 camera_id``,
  ``int32 model_id``, ``uint64 width``, ``uint64 height`` and the model's
  ``float64`` parameters. ``cameras.txt``: ``CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]``.
- ``images.bin``: ``uint64`` count, then per image ``uint32 image_id``,
  ``float64 qw qx qy qz tx ty tz``, ``uint32 camera_id``, the name as
  NUL-terminated UTF-8, ``uint64`` number of 2D points and that many
  ``(float64 x, float64 y, int64 point3D_id)``. ``images.txt``: two lines per
  image, ``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`` and the 2D points
  (possibly empty).
- ``points3D.bin``: ``uint64`` count, then per point ``uint64 point3D_id``,
  ``float64 x y z``, ``uint8 r g b``, ``float64 error``, ``uint64`` track
  length and that many ``(uint32 image_id, uint32 point2D_idx)``.
  ``points3D.txt``: ``POINT3D_ID X Y Z R G B ERROR TRACK[]``.

Poses: ``(qvec, tvec)`` is world-to-camera, ``x_cam = R(q) x_world + t`` with
a Hamilton ``(w, x, y, z)`` quaternion and OpenCV camera axes (x right, y
down, z forward), so it is :class:`Camera`'s ``viewmat`` as it stands.

Pixel convention: COLMAP's camera models put the upper-left image corner at
``(0, 0)`` and the centre of the upper-left pixel at ``(0.5, 0.5)`` (stated in
``src/colmap/sensor/models.h``; its SIFT extractors add 0.5 to VLFeat's
keypoints to follow it). That is :mod:`mlx3d.cameras`'s convention, so the
principal point is used unchanged.

Camera models: ``SIMPLE_PINHOLE (f, cx, cy)`` and ``PINHOLE (fx, fy, cx, cy)``
map to ``'pinhole'``; ``SIMPLE_RADIAL (f, cx, cy, k)``, ``RADIAL (f, cx, cy,
k1, k2)``, ``OPENCV (fx, fy, cx, cy, k1, k2, p1, p2)`` and ``FULL_OPENCV``
with ``k4 = k5 = k6 = 0`` to ``'opencv'`` ``(k1, k2, p1, p2, k3)`` with the
missing terms 0; ``OPENCV_FISHEYE (fx, fy, cx, cy, k1..k4)`` and its special
cases ``SIMPLE_RADIAL_FISHEYE``, ``RADIAL_FISHEYE``, ``SIMPLE_FISHEYE`` and
``FISHEYE`` (equidistant, no coefficients) to ``'fisheye'``. Any other model
is a DatasetError naming it.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np

from mlx3d.cameras import Camera
from mlx3d.transforms import quaternion_to_matrix

from . import DatasetError
from .base import Dataset, Frame, check_factor, resolve_image

# model id -> (name, number of parameters), as in COLMAP's sensor/models.h.
CAMERA_MODELS = {
    0: ("SIMPLE_PINHOLE", 3),
    1: ("PINHOLE", 4),
    2: ("SIMPLE_RADIAL", 4),
    3: ("RADIAL", 5),
    4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8),
    6: ("FULL_OPENCV", 12),
    7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5),
    10: ("THIN_PRISM_FISHEYE", 12),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
    12: ("SIMPLE_DIVISION", 4),
    13: ("DIVISION", 5),
    14: ("SIMPLE_FISHEYE", 3),
    15: ("FISHEYE", 4),
    16: ("EUCM", 6),
    17: ("EQUIRECTANGULAR", 2),
}
_NUM_PARAMS = {name: n for name, n in CAMERA_MODELS.values()}
SUPPORTED_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV",
                    "OPENCV_FISHEYE", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE", "SIMPLE_FISHEYE", "FISHEYE")


@dataclass(frozen=True)
class ColmapCamera:
    """One record of ``cameras.bin``/``cameras.txt``."""

    id: int
    model: str
    width: int
    height: int
    params: tuple


@dataclass(frozen=True)
class ColmapImage:
    """One record of ``images.bin``/``images.txt``.

    xys, point3d_ids: the 2D points that observe a 3D point, ``(K, 2)``
    float64 pixels (COLMAP's convention, see above) and ``(K,)`` int64
    ``point3D_id`` (keypoints without a 3D point are dropped); empty when
    the record has none."""

    id: int
    qvec: tuple  # w, x, y, z
    tvec: tuple
    camera_id: int
    name: str
    xys: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)), compare=False, repr=False)
    point3d_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64), compare=False, repr=False)


class ColmapModel(NamedTuple):
    """A sparse model: cameras and images by id; points (M, 3) float64, colours (M, 3) uint8 and
    their ``point3D_id`` (M,) int64, or None."""

    cameras: dict
    images: dict
    points: np.ndarray | None
    colors: np.ndarray | None
    point_ids: np.ndarray | None = None


def _observed(xys: np.ndarray, ids: np.ndarray) -> dict:
    """The 2D points of an image record that observe a 3D point (id -1: none)."""
    keep = ids != -1
    return {"xys": np.ascontiguousarray(xys[keep], dtype=np.float64), "point3d_ids": ids[keep].astype(np.int64)}


# -- binary


class _Bin:
    """Sequential little-endian reader over a whole file that reports truncation by record."""

    def __init__(self, path: Path):
        self.path = path
        try:
            self.buf = path.read_bytes()
        except FileNotFoundError:
            raise DatasetError(f"{path}: file not found") from None
        except OSError as exc:
            raise DatasetError(f"{path}: cannot read: {exc}") from None
        self.pos = 0

    def take(self, fmt: str, what: str):
        s = struct.calcsize("<" + fmt)
        if self.pos + s > len(self.buf):
            raise DatasetError(
                f"{self.path}: truncated file: {what} needs {s} bytes at byte {self.pos}, "
                f"but the file has {len(self.buf)} bytes"
            )
        out = struct.unpack_from("<" + fmt, self.buf, self.pos)
        self.pos += s
        return out

    def skip(self, nbytes: int, what: str):
        if self.pos + nbytes > len(self.buf):
            raise DatasetError(
                f"{self.path}: truncated file: {what} needs {nbytes} bytes at byte {self.pos}, "
                f"but the file has {len(self.buf)} bytes"
            )
        self.pos += nbytes

    def count(self, what: str) -> int:
        (n,) = self.take("Q", f"the number of {what}")
        return n

    def done(self, n: int, what: str):
        if self.pos != len(self.buf):
            raise DatasetError(
                f"{self.path}: {len(self.buf) - self.pos} unexpected bytes after the {n} {what} "
                f"the header announces (from byte {self.pos})"
            )


def read_cameras_binary(path) -> dict[int, ColmapCamera]:
    """``cameras.bin`` as ``{camera_id: ColmapCamera}``."""
    r = _Bin(Path(path))
    n = r.count("cameras")
    cams = {}
    for i in range(n):
        what = f"camera record {i + 1} of {n}"
        cam_id, model_id, w, h = r.take("IiQQ", what)
        if model_id not in CAMERA_MODELS:
            raise DatasetError(f"{r.path}: {what} (camera {cam_id}): unknown camera model id {model_id}")
        name, k = CAMERA_MODELS[model_id]
        params = r.take(f"{k}d", f"the {k} parameters of {what} ({name})")
        cams[cam_id] = ColmapCamera(cam_id, name, w, h, params)
    r.done(n, "cameras")
    return cams


def read_images_binary(path) -> dict[int, ColmapImage]:
    """``images.bin`` as ``{image_id: ColmapImage}``."""
    r = _Bin(Path(path))
    n = r.count("images")
    images = {}
    for i in range(n):
        what = f"image record {i + 1} of {n}"
        vals = r.take("I7dI", what)
        end = r.buf.find(b"\0", r.pos)
        if end < 0:
            raise DatasetError(f"{r.path}: truncated file: the name of {what} has no terminating NUL byte")
        try:
            name = r.buf[r.pos:end].decode("utf-8")
        except UnicodeDecodeError:
            raise DatasetError(f"{r.path}: {what}: the image name is not UTF-8") from None
        r.pos = end + 1
        (npts,) = r.take("Q", f"the 2D point count of {what} ({name})")
        start = r.pos
        r.skip(24 * npts, f"the {npts} 2D points of {what} ({name})")
        rec = np.frombuffer(r.buf, dtype=_POINT2D_DTYPE, count=npts, offset=start)
        images[vals[0]] = ColmapImage(vals[0], tuple(vals[1:5]), tuple(vals[5:8]), vals[8], name,
                                      **_observed(rec["xy"], rec["id"]))
    r.done(n, "images")
    return images


_POINT2D_DTYPE = np.dtype([("xy", "<f8", (2,)), ("id", "<i8")])
_POINT_DTYPE = np.dtype([("id", "<u8"), ("xyz", "<f8", (3,)), ("rgb", "u1", (3,)), ("error", "<f8")])
_POINT_HEAD = _POINT_DTYPE.itemsize  # 43 bytes before the track length


def read_points3d_binary(path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``points3D.bin`` as ``(xyz (M, 3) float64, rgb (M, 3) uint8, point3D_id (M,) int64)`` in file
    order (tracks skipped: the images' 2D points hold the same observations)."""
    r = _Bin(Path(path))
    n = r.count("points")
    buf, size = r.buf, len(r.buf)
    offsets = np.empty(n, dtype=np.int64)
    unpack_u64 = struct.Struct("<Q").unpack_from
    pos = r.pos
    for i in range(n):
        if pos + _POINT_HEAD + 8 > size:
            raise DatasetError(
                f"{r.path}: truncated file: point record {i + 1} of {n} needs {_POINT_HEAD + 8} bytes "
                f"at byte {pos}, but the file has {size} bytes"
            )
        offsets[i] = pos
        (track,) = unpack_u64(buf, pos + _POINT_HEAD)
        pos += _POINT_HEAD + 8 + 8 * track
        if pos > size:
            raise DatasetError(
                f"{r.path}: truncated file: the track of point record {i + 1} of {n} "
                f"({track} entries) ends at byte {pos}, but the file has {size} bytes"
            )
    r.pos = pos
    r.done(n, "points")
    raw = np.frombuffer(buf, dtype=np.uint8)
    xyz = np.empty((n, 3), dtype=np.float64)
    rgb = np.empty((n, 3), dtype=np.uint8)
    ids = np.empty(n, dtype=np.int64)
    cols = np.arange(_POINT_HEAD)
    chunk = 1 << 16
    for s in range(0, n, chunk):
        rec = raw[offsets[s:s + chunk, None] + cols].view(_POINT_DTYPE)[:, 0]
        xyz[s:s + chunk] = rec["xyz"]
        rgb[s:s + chunk] = rec["rgb"]
        ids[s:s + chunk] = rec["id"]
    return xyz, rgb, ids


# -- text


def _text_lines(path: Path):
    try:
        with open(path, encoding="utf-8") as fh:
            return fh.read().splitlines()
    except FileNotFoundError:
        raise DatasetError(f"{path}: file not found") from None
    except UnicodeDecodeError as exc:
        raise DatasetError(f"{path}: not a UTF-8 text file ({exc.reason} at byte {exc.start})") from None
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read: {exc}") from None


def _data_line(line: str) -> bool:
    s = line.strip()
    return bool(s) and not s.startswith("#")


def read_cameras_text(path) -> dict[int, ColmapCamera]:
    """``cameras.txt`` as ``{camera_id: ColmapCamera}``."""
    path = Path(path)
    cams = {}
    for no, line in enumerate(_text_lines(path), 1):
        if not _data_line(line):
            continue
        tok = line.split()
        try:
            if len(tok) < 4:
                raise ValueError("expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]")
            cam_id, model, w, h = int(tok[0]), tok[1], int(tok[2]), int(tok[3])
            params = tuple(float(t) for t in tok[4:])
        except ValueError as exc:
            raise DatasetError(f"{path}:{no}: malformed camera line: {exc}") from None
        k = _NUM_PARAMS.get(model)
        if k is not None and len(params) != k:
            raise DatasetError(f"{path}:{no}: camera {cam_id}: model {model} has {k} parameters, got {len(params)}")
        cams[cam_id] = ColmapCamera(cam_id, model, w, h, params)
    return cams


def read_images_text(path) -> dict[int, ColmapImage]:
    """``images.txt`` as ``{image_id: ColmapImage}``."""
    path = Path(path)
    lines = _text_lines(path)
    images = {}
    no = 0
    while no < len(lines):
        line = lines[no]
        no += 1
        if not _data_line(line):
            continue
        tok = line.split(maxsplit=9)
        try:
            if len(tok) < 10:
                raise ValueError("expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME")
            img_id = int(tok[0])
            vals = tuple(float(t) for t in tok[1:8])
            cam_id = int(tok[8])
        except ValueError as exc:
            raise DatasetError(f"{path}:{no}: malformed image line: {exc}") from None
        name = tok[9].strip()
        # The next line holds the image's 2D points (X Y POINT3D_ID triples); it may be empty.
        observed = {}
        if no < len(lines):
            pts = lines[no].split()
            if len(pts) % 3:
                raise DatasetError(
                    f"{path}:{no + 1}: expected the 2D points of image {img_id} ({name}) as X Y POINT3D_ID "
                    f"triples, got {len(pts)} values"
                )
            try:
                triples = np.array(pts, dtype=np.float64).reshape(-1, 3)
            except ValueError as exc:
                raise DatasetError(f"{path}:{no + 1}: malformed 2D points of image {img_id} ({name}): {exc}") from None
            observed = _observed(triples[:, :2], triples[:, 2].astype(np.int64))
            no += 1
        images[img_id] = ColmapImage(img_id, vals[:4], vals[4:], cam_id, name, **observed)
    return images


def read_points3d_text(path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``points3D.txt`` as ``(xyz (M, 3) float64, rgb (M, 3) uint8, point3D_id (M,) int64)`` in file order."""
    path = Path(path)
    xyz, rgb, ids = [], [], []
    for no, line in enumerate(_text_lines(path), 1):
        if not _data_line(line):
            continue
        tok = line.split(maxsplit=8)
        try:
            if len(tok) < 8:
                raise ValueError("expected POINT3D_ID X Y Z R G B ERROR TRACK[]")
            i = int(tok[0])
            p = (float(tok[1]), float(tok[2]), float(tok[3]))
            c = (int(tok[4]), int(tok[5]), int(tok[6]))
            if not all(0 <= v <= 255 for v in c):
                raise ValueError(f"colour {c} is outside 0..255")
        except ValueError as exc:
            raise DatasetError(f"{path}:{no}: malformed point line: {exc}") from None
        xyz.append(p)
        rgb.append(c)
        ids.append(i)
    return (np.array(xyz, dtype=np.float64).reshape(-1, 3), np.array(rgb, dtype=np.uint8).reshape(-1, 3),
            np.array(ids, dtype=np.int64))


def _model_file(sparse: Path, stem: str) -> Path | None:
    """``stem.bin`` if present (COLMAP prefers binary), else ``stem.txt``, else None."""
    for ext in (".bin", ".txt"):
        p = sparse / f"{stem}{ext}"
        if p.is_file():
            return p
    return None


def read_colmap_model(sparse_dir) -> ColmapModel:
    """Read ``cameras``, ``images`` and (optional) ``points3D`` from a sparse model folder.

    Each file is read as ``.bin`` when present, else ``.txt``. A missing
    ``points3D`` gives ``points = colors = None``.
    """
    sparse = Path(sparse_dir)
    if not sparse.is_dir():
        raise DatasetError(f"{sparse}: COLMAP model folder not found")
    found = {}
    for stem in ("cameras", "images"):
        p = _model_file(sparse, stem)
        if p is None:
            raise DatasetError(f"{sparse}: no {stem}.bin or {stem}.txt")
        found[stem] = p
    cp, ip = found["cameras"], found["images"]
    cameras = read_cameras_binary(cp) if cp.suffix == ".bin" else read_cameras_text(cp)
    images = read_images_binary(ip) if ip.suffix == ".bin" else read_images_text(ip)
    pp = _model_file(sparse, "points3D")
    points = colors = ids = None
    if pp is not None:
        points, colors, ids = read_points3d_binary(pp) if pp.suffix == ".bin" else read_points3d_text(pp)
    return ColmapModel(cameras, images, points, colors, ids)


# -- conversion


def camera_intrinsics(cam: ColmapCamera, source: str = "") -> dict:
    """``Camera`` keyword arguments (size, fx, fy, cx, cy, model, dist) of a COLMAP camera.

    COLMAP and :class:`Camera` share the pixel frame (pixel centres at +0.5),
    so cx, cy are taken as they are. DatasetError for unsupported models.
    """
    where = f"{source}: camera {cam.id}" if source else f"camera {cam.id}"
    name, p = cam.model, [float(v) for v in cam.params]
    k = _NUM_PARAMS.get(name)
    if k is not None and len(p) != k:
        raise DatasetError(f"{where}: model {name} has {k} parameters, got {len(p)}")
    if name == "SIMPLE_PINHOLE":
        f, cx, cy = p
        fx, fy, model, dist = f, f, "pinhole", ()
    elif name == "PINHOLE":
        fx, fy, cx, cy = p
        model, dist = "pinhole", ()
    elif name == "SIMPLE_RADIAL":
        f, cx, cy, k1 = p
        fx, fy, model, dist = f, f, "opencv", (k1, 0.0, 0.0, 0.0, 0.0)
    elif name == "RADIAL":
        f, cx, cy, k1, k2 = p
        fx, fy, model, dist = f, f, "opencv", (k1, k2, 0.0, 0.0, 0.0)
    elif name == "OPENCV":
        fx, fy, cx, cy, k1, k2, p1, p2 = p
        model, dist = "opencv", (k1, k2, p1, p2, 0.0)
    elif name == "FULL_OPENCV":
        fx, fy, cx, cy, k1, k2, p1, p2, k3, k4, k5, k6 = p
        if k4 or k5 or k6:
            raise DatasetError(
                f"{where}: unsupported camera model FULL_OPENCV with rational terms "
                f"k4, k5, k6 = {k4:g}, {k5:g}, {k6:g} (only k4 = k5 = k6 = 0 maps to 'opencv')"
            )
        model, dist = "opencv", (k1, k2, p1, p2, k3)
    elif name == "OPENCV_FISHEYE":
        fx, fy, cx, cy, k1, k2, k3, k4 = p
        model, dist = "fisheye", (k1, k2, k3, k4)
    elif name == "SIMPLE_RADIAL_FISHEYE":
        f, cx, cy, k1 = p
        fx, fy, model, dist = f, f, "fisheye", (k1, 0.0, 0.0, 0.0)
    elif name == "RADIAL_FISHEYE":
        f, cx, cy, k1, k2 = p
        fx, fy, model, dist = f, f, "fisheye", (k1, k2, 0.0, 0.0)
    elif name == "SIMPLE_FISHEYE":
        f, cx, cy = p
        fx, fy, model, dist = f, f, "fisheye", (0.0, 0.0, 0.0, 0.0)
    elif name == "FISHEYE":
        fx, fy, cx, cy = p
        model, dist = "fisheye", (0.0, 0.0, 0.0, 0.0)
    else:
        raise DatasetError(f"{where}: unsupported camera model {name} (supported: {', '.join(SUPPORTED_MODELS)})")
    return dict(width=cam.width, height=cam.height, fx=fx, fy=fy, cx=cx, cy=cy, model=model, dist=dist)


def image_viewmat(img: ColmapImage, source: str = "") -> np.ndarray:
    """(4, 4) world-to-camera matrix (OpenCV axes) of a COLMAP image: ``[R(q) | t]``."""
    q = np.array(img.qvec, dtype=np.float64)
    t = np.array(img.tvec, dtype=np.float64)
    norm = float(np.linalg.norm(q))
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(t)) and norm > 1e-12):
        where = f"{source}: image {img.id} ({img.name})" if source else f"image {img.id} ({img.name})"
        raise DatasetError(f"{where}: invalid pose qvec={img.qvec}, tvec={img.tvec}")
    m = np.eye(4)
    m[:3, :3] = quaternion_to_matrix(q / norm)
    m[:3, 3] = t
    return m


def _find_sparse(root: Path) -> Path:
    for cand in (root / "sparse" / "0", root / "sparse"):
        if cand.is_dir() and _model_file(cand, "cameras") is not None:
            return cand
    raise DatasetError(
        f"{root}: no COLMAP model (looked for sparse/0/cameras.bin|txt and sparse/cameras.bin|txt)"
    )


def _mask_for(masks: Path, name: str) -> Path:
    """The mask of image ``name``: ``masks/name``, ``masks/name.png`` or ``masks/<stem>.png``."""
    rel = Path(name)
    for cand in (masks / rel, masks / (name + ".png"), masks / rel.with_suffix(".png")):
        if cand.is_file():
            return cand
    raise DatasetError(f"{masks / rel}: mask not found (also tried {rel}.png and {rel.with_suffix('.png')})")


def load_colmap(path, factor=1, *, sparse_dir=None, images_dir: str = "images", masks_dir: str | None = None,
                test_every: int | None = 8, **dataset_kw) -> Dataset:
    """A COLMAP workspace as a :class:`Dataset`.

    path: the workspace folder, holding ``sparse/0`` (or ``sparse``) and ``images/``.
    factor: downscale factor; for an integer factor the folder
        ``images_<factor>`` is used when it exists (mip-NeRF 360 layout),
        otherwise the full images are resized on load (see :mod:`.base`).
    sparse_dir: the model folder, if not ``sparse/0`` or ``sparse``.
    images_dir: the image folder under ``path``; image names are relative to it.
    masks_dir: optional folder of masks (nonzero = keep) named like the images
        (``name``, ``name.png`` or ``<stem>.png``).
    test_every: frames are sorted by image name and every ``test_every``-th
        one (indices 0, 8, 16, ...) is held out as ``test`` (3DGS convention);
        None or 0 trains on all.
    dataset_kw: passed to :class:`Dataset` (cache bounds, ``resample``, ``seed``).

    Initial points and colours come from ``points3D`` (None when absent).
    """
    root = Path(path)
    f = check_factor(factor)
    sparse = Path(sparse_dir) if sparse_dir is not None else _find_sparse(root)
    model = read_colmap_model(sparse)
    img_file = _model_file(sparse, "images")
    cam_file = _model_file(sparse, "cameras")
    if not model.images:
        raise DatasetError(f"{img_file}: the model has no images")

    images_root = root / images_dir
    down_root = None
    if f != 1.0 and f.is_integer():
        cand = root / f"{images_dir}_{int(f)}"
        down_root = cand if cand.is_dir() else None
    if not images_root.is_dir() and down_root is None:
        raise DatasetError(f"{images_root}: images folder not found")
    masks = None
    if masks_dir is not None:
        masks = root / masks_dir
        if not masks.is_dir():
            raise DatasetError(f"{masks}: masks folder not found")

    # The whole model is checked before any image file is looked at.
    cams: dict[int, Camera] = {}
    posed_images = []
    for img in sorted(model.images.values(), key=lambda im: im.name):
        col = model.cameras.get(img.camera_id)
        if col is None:
            raise DatasetError(f"{img_file}: image {img.id} ({img.name}) uses camera {img.camera_id}, "
                               f"which {cam_file} does not define")
        if img.camera_id not in cams:
            kw = camera_intrinsics(col, str(cam_file))
            try:
                cams[img.camera_id] = Camera(**kw)
            except ValueError as exc:
                raise DatasetError(f"{cam_file}: camera {col.id}: {exc}") from None
        base = cams[img.camera_id]
        try:
            posed = Camera(base.width, base.height, base.fx, base.fy, base.cx, base.cy,
                           image_viewmat(img, str(img_file)), model=base.model, dist=base.dist)
        except ValueError as exc:
            raise DatasetError(f"{img_file}: image {img.id} ({img.name}): {exc}") from None
        posed_images.append((img, posed))

    frames = []
    for img, posed in posed_images:
        down = None if down_root is None else down_root / img.name
        image_path, cam = resolve_image(images_root / img.name, posed, f, down)
        mask = None if masks is None else _mask_for(masks, img.name)
        frames.append(Frame(cam, image_path, img.name, mask))

    points = colors = observations = None
    if model.points is not None:
        points = model.points.astype(np.float32)
        colors = model.colors
        observations = _observations(model, [img for img, _ in posed_images], frames)
    return Dataset(frames, test_every=test_every, points=points, point_colors=colors, observations=observations,
                   root=root, kind="colmap", factor=f, **dataset_kw)


def _observations(model: ColmapModel, images: list, frames: list) -> list:
    """Per frame, the sparse points its photo observes: ``(xy (K, 2) float32`` pixels of the frame's
    camera, ``index (K,) int64`` into ``model.points)``. 2D points naming a 3D point the model
    lacks are dropped."""
    order = np.argsort(model.point_ids, kind="stable")
    sorted_ids = model.point_ids[order]
    out = []
    for img, frame in zip(images, frames):
        col = model.cameras[img.camera_id]
        at = np.searchsorted(sorted_ids, img.point3d_ids)
        at = np.minimum(at, max(len(sorted_ids) - 1, 0))
        known = (sorted_ids[at] == img.point3d_ids) if len(sorted_ids) else np.zeros(len(at), bool)
        scale = np.array([frame.camera.width / col.width, frame.camera.height / col.height])
        out.append(((img.xys[known] * scale).astype(np.float32), order[at[known]].astype(np.int64)))
    return out


__all__ = [
    "CAMERA_MODELS",
    "SUPPORTED_MODELS",
    "ColmapCamera",
    "ColmapImage",
    "ColmapModel",
    "camera_intrinsics",
    "image_viewmat",
    "load_colmap",
    "read_cameras_binary",
    "read_cameras_text",
    "read_colmap_model",
    "read_images_binary",
    "read_images_text",
    "read_points3d_binary",
    "read_points3d_text",
]

