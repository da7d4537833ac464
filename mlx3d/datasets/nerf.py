"""NeRF-synthetic (Blender) and nerfstudio / instant-ngp ``transforms*.json`` datasets.

Both store ``transform_matrix`` as a camera-to-world pose with OpenGL camera
axes (x right, y up, looking down -z); cameras are built with
:meth:`Camera.from_opengl_c2w`, the one place the OpenGL -> OpenCV flip
happens. Principal points (nerfstudio ``cx``, ``cy``) are in the same pixel
frame as :mod:`mlx3d.cameras` (pixel centres at +0.5: nerfstudio generates
rays through ``pixel + 0.5`` and copies COLMAP's principal point unchanged);
the default is the image centre ``(W/2, H/2)``.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

from mlx3d.cameras import Camera

from . import DatasetError
from .base import Dataset, Frame, check_factor, image_size, read_points_ply, resolve_image

# Rotation blocks off by more than this are refused; smaller errors (rounded
# JSON values) are projected onto the nearest rotation.
_ORTHO_REPAIR_TOL = 1e-3


def read_json(path: Path):
    """Parse a JSON file; DatasetError naming the file (and line, column) otherwise."""
    try:
        with open(path, encoding="utf-8") as fh:
            return json.load(fh)
    except FileNotFoundError:
        raise DatasetError(f"{path}: file not found") from None
    except json.JSONDecodeError as exc:
        raise DatasetError(f"{path}:{exc.lineno}:{exc.colno}: malformed JSON: {exc.msg}") from None
    except UnicodeDecodeError as exc:
        raise DatasetError(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read: {exc}") from None


def _pose(value, where: str) -> np.ndarray:
    """A rigid (4, 4) float64 camera-to-world matrix from a JSON (3, 4) or (4, 4) list."""
    try:
        m = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise DatasetError(f"{where}: transform_matrix is not a numeric matrix") from None
    if m.shape == (3, 4):
        m = np.vstack([m, [0.0, 0.0, 0.0, 1.0]])
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise DatasetError(f"{where}: transform_matrix must be a finite 4x4 (or 3x4) matrix, got shape {m.shape}")
    r = m[:3, :3]
    err = float(np.max(np.abs(r @ r.T - np.eye(3))))
    if err > _ORTHO_REPAIR_TOL or np.linalg.det(r) <= 0:
        raise DatasetError(
            f"{where}: the rotation part of transform_matrix is not a rotation "
            f"(max |R R^T - I| = {err:.3g}, det = {np.linalg.det(r):.3g})"
        )
    if err > 0:
        u, _, vt = np.linalg.svd(r)
        m[:3, :3] = u @ vt
    m[3] = [0.0, 0.0, 0.0, 1.0]
    return m


def _number(d: dict, key: str, where: str, default=None, required: bool = False):
    if key not in d or d[key] is None:
        if required:
            raise DatasetError(f"{where}: missing '{key}'")
        return default
    v = d[key]
    if isinstance(v, bool):
        raise DatasetError(f"{where}: '{key}' must be a number, got {v!r}")
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise DatasetError(f"{where}: '{key}' must be a number, got {v!r}") from None
    if not math.isfinite(f):
        raise DatasetError(f"{where}: '{key}' must be finite, got {v!r}")
    return f


def _frames(meta, path: Path) -> list:
    if not isinstance(meta, dict):
        raise DatasetError(f"{path}: expected a JSON object at the top level")
    frames = meta.get("frames")
    if not isinstance(frames, list):
        raise DatasetError(f"{path}: missing 'frames' list")
    for j, fr in enumerate(frames):
        if not isinstance(fr, dict):
            raise DatasetError(f"{path}: frames[{j}] is not an object")
        if not isinstance(fr.get("file_path"), str):
            raise DatasetError(f"{path}: frames[{j}] has no 'file_path' string")
        if "transform_matrix" not in fr:
            raise DatasetError(f"{path}: frames[{j}] ({fr['file_path']}) has no 'transform_matrix'")
    return frames


def _rel(root: Path, p: Path) -> str:
    return Path(os.path.relpath(p, root)).as_posix()


def _norm(root: Path, file_path: str) -> Path:
    return Path(os.path.normpath(root / file_path))


def _downscaled(p: Path, factor: float) -> Path | None:
    """``<dir>_<k>/<name>`` next to the image's folder for an integer factor k (nerfstudio layout)."""
    if factor == 1.0 or not factor.is_integer():
        return None
    return p.parent.with_name(f"{p.parent.name}_{int(factor)}") / p.name


# -- NeRF-synthetic


def load_nerf_synthetic(path, factor=1, *, val_in_train: bool = False, **dataset_kw) -> Dataset:
    """A NeRF-synthetic (Blender) scene as a :class:`Dataset`.

    path: the scene folder holding ``transforms_train.json`` and optionally
        ``transforms_val.json`` and ``transforms_test.json`` (or one of them).
    Each file's ``camera_angle_x`` gives ``fx = fy = 0.5 W / tan(0.5 camera_angle_x)``
    with the principal point at the image centre, unless the file (or a frame)
    has nerfstudio intrinsics (``fl_x``, ``camera_model``, ``cx``, ...: what
    Blender's NeRF exporters and capture apps write), which then decide the
    camera as in :func:`load_nerfstudio` (``camera_model`` defaults to
    ``PINHOLE`` here); ``file_path`` is relative to
    the folder, ``.png`` is appended when it has no extension.
    Splits are the files' own: ``train``, ``val`` and ``test``
    (``val_in_train=True`` adds the val frames to ``train``).
    ``ply_file_path`` in ``transforms_train.json`` (relative to the folder, as
    in nerfstudio) gives initial points; without it the dataset has none and
    training starts from random points (``mlx3d.training.initial``).
    factor: downscale factor; images are resized on load (Pillow) and the
        cameras scaled to match. The scenes' RGBA images are composited or
        weighted by :meth:`Dataset.load_image`.
    dataset_kw: passed to :class:`Dataset`.
    """
    root = Path(path)
    if root.is_file():
        root = root.parent
    f = check_factor(factor)
    files = {s: root / f"transforms_{s}.json" for s in ("train", "val", "test")}
    if not files["train"].is_file():
        raise DatasetError(f"{files['train']}: file not found")
    frames: list[Frame] = []
    splits: dict[str, list[int]] = {}
    points = colors = None
    for split, jpath in files.items():
        if not jpath.is_file():
            continue
        meta = read_json(jpath)
        if split == "train":
            points, colors = _initial_points(meta, root, jpath)
        entries = _frames(meta, jpath)
        # Blender's NeRF exporters and capture apps write nerfstudio intrinsics (fl_x, camera_model, ...)
        # in these files, with or without camera_angle_x: those, when present, decide the camera.
        explicit = any(k in meta for k in ("fl_x", "camera_model")) or any(
            k in fr for fr in entries for k in ("fl_x", "camera_model"))
        if not explicit:
            angle = _number(meta, "camera_angle_x", str(jpath), required=True)
            if not 0.0 < angle < math.pi:
                raise DatasetError(f"{jpath}: camera_angle_x must be in (0, pi) radians, got {angle!r}")
        idx = []
        for j, fr in enumerate(entries):
            where = f"{jpath}: frames[{j}] ({fr['file_path']})"
            p = _norm(root, fr["file_path"])
            if not p.suffix and not p.is_file():
                p = p.with_name(p.name + ".png")
            if not p.is_file():
                raise DatasetError(f"{p}: image not found (listed in {jpath}, frames[{j}])")
            w, h = image_size(p)
            if explicit:
                merged = {"camera_model": "PINHOLE", **{k: meta[k] for k in _INTRINSIC_KEYS if k in meta},
                          **{k: fr[k] for k in _INTRINSIC_KEYS if k in fr}}
                cam = _nerfstudio_camera(merged, _pose(fr["transform_matrix"], where), (w, h), where)
            else:
                fx = 0.5 * w / math.tan(0.5 * angle)
                try:
                    cam = Camera.from_opengl_c2w(_pose(fr["transform_matrix"], where), w, h, fx)
                except ValueError as exc:
                    raise DatasetError(f"{where}: {exc}") from None
            image_path, cam = resolve_image(p, cam, f, size=(w, h))
            idx.append(len(frames))
            frames.append(Frame(cam, image_path, _rel(root, p)))
        splits[split] = idx
    if val_in_train:
        splits["train"] = splits["train"] + splits.get("val", [])
    splits.setdefault("test", [])
    return Dataset(frames, splits=splits, points=points, point_colors=colors, root=root, kind="nerf_synthetic", factor=f, **dataset_kw)


def _initial_points(meta: dict, root: Path, jpath: Path):
    """The points a transforms file's ``ply_file_path`` names: (xyz, rgb or None), or (None, None) without one."""
    ply = meta.get("ply_file_path")
    if ply is None:
        return None, None
    if not isinstance(ply, str):
        raise DatasetError(f"{jpath}: ply_file_path must be a string")
    return read_points_ply(_norm(root, ply))


# -- nerfstudio


_INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h", "k1", "k2", "k3", "k4", "p1", "p2",
                   "camera_model", "camera_angle_x", "camera_angle_y")
_PERSPECTIVE = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")


def _nerfstudio_camera(d: dict, c2w: np.ndarray, size: tuple[int, int], where: str) -> Camera:
    """A Camera from merged (top-level + frame) nerfstudio intrinsics."""
    w = _number(d, "w", where)
    h = _number(d, "h", where)
    w = size[0] if w is None else w
    h = size[1] if h is None else h
    if not (float(w).is_integer() and float(h).is_integer() and w > 0 and h > 0):
        raise DatasetError(f"{where}: w and h must be positive integers, got {w!r}, {h!r}")
    w, h = int(w), int(h)
    fx = _number(d, "fl_x", where)
    if fx is None:
        ax = _number(d, "camera_angle_x", where)
        if ax is None:
            raise DatasetError(f"{where}: missing 'fl_x' (or 'camera_angle_x')")
        fx = 0.5 * w / math.tan(0.5 * ax)
    fy = _number(d, "fl_y", where)
    if fy is None:
        ay = _number(d, "camera_angle_y", where)
        fy = fx if ay is None else 0.5 * h / math.tan(0.5 * ay)
    cx = _number(d, "cx", where, w / 2.0)
    cy = _number(d, "cy", where, h / 2.0)
    k1, k2, k3, k4, p1, p2 = (_number(d, k, where, 0.0) for k in ("k1", "k2", "k3", "k4", "p1", "p2"))
    name = d.get("camera_model", "OPENCV")
    if not isinstance(name, str):
        raise DatasetError(f"{where}: camera_model must be a string, got {name!r}")
    name = name.upper()
    if name in _PERSPECTIVE:
        if k4:
            raise DatasetError(f"{where}: camera_model {name} with k4 = {k4:g} (an r^8 radial term) is not supported")
        if name in ("PINHOLE", "SIMPLE_PINHOLE") and not (k1 or k2 or k3 or p1 or p2):
            model, dist = "pinhole", ()
        else:
            model, dist = "opencv", (k1, k2, p1, p2, k3)
    elif name == "OPENCV_FISHEYE":
        if p1 or p2:
            raise DatasetError(f"{where}: camera_model OPENCV_FISHEYE with tangential terms p1, p2 is not supported")
        model, dist = "fisheye", (k1, k2, k3, k4)
    else:
        raise DatasetError(
            f"{where}: unsupported camera_model {name} (supported: {', '.join(_PERSPECTIVE)}, OPENCV_FISHEYE)"
        )
    try:
        return Camera.from_opengl_c2w(c2w, w, h, fx, fy, cx, cy, model=model, dist=dist)
    except ValueError as exc:
        raise DatasetError(f"{where}: {exc}") from None


def load_nerfstudio(path, factor=1, *, test_every: int | None = 8, **dataset_kw) -> Dataset:
    """A nerfstudio (or instant-ngp) ``transforms.json`` as a :class:`Dataset`.

    path: the json file or the folder holding ``transforms.json``; every path
        in it is relative to its folder.
    Intrinsics ``fl_x, fl_y, cx, cy, w, h, k1, k2, k3, k4, p1, p2,
    camera_model`` are read from the frame, falling back to the top level
    (``fl_x`` may be replaced by ``camera_angle_x``; ``w``/``h`` default to
    the image's size, ``cx``/``cy`` to its centre). ``camera_model``:
    ``OPENCV`` (the default; ``(k1, k2, p1, p2, k3)``), ``PINHOLE`` (pinhole
    unless distortion terms are given), ``OPENCV_FISHEYE`` (``k1..k4``).
    ``applied_transform`` is ignored (poses and points already include it).
    ``ply_file_path`` gives the initial points (``x y z``, colours from
    ``red green blue`` when present). ``mask_path`` per frame gives its mask.
    Frames are sorted by ``file_path``. Splits: ``train_filenames`` /
    ``val_filenames`` / ``test_filenames`` when present (test falls back to
    val); otherwise every ``test_every``-th frame is held out (3DGS convention).
    factor: downscale factor; for an integer factor an ``<images>_<factor>``
        folder next to the image's folder is used when it holds the image.
    dataset_kw: passed to :class:`Dataset`.
    """
    jpath = Path(path)
    if jpath.is_dir():
        jpath = jpath / "transforms.json"
    root = jpath.parent
    f = check_factor(factor)
    meta = read_json(jpath)
    entries = _frames(meta, jpath)
    if not entries:
        raise DatasetError(f"{jpath}: 'frames' is empty")
    top = {k: meta[k] for k in _INTRINSIC_KEYS if k in meta}

    order = sorted(range(len(entries)), key=lambda j: _norm(root, entries[j]["file_path"]).as_posix())
    frames: list[Frame] = []
    by_path: dict[str, int] = {}
    for j in order:
        fr = entries[j]
        where = f"{jpath}: frames[{j}] ({fr['file_path']})"
        p = _norm(root, fr["file_path"])
        down = _downscaled(p, f)
        src = p
        if not p.is_file():
            if down is None or not down.is_file():
                raise DatasetError(f"{p}: image not found (listed in {jpath}, frames[{j}])")
            src = down
        d = {**top, **{k: fr[k] for k in _INTRINSIC_KEYS if k in fr}}
        if src is p:
            size = image_size(p)
        else:  # only the downscaled copy exists: the full size comes from w, h
            if _number(d, "w", where) is None or _number(d, "h", where) is None:
                raise DatasetError(f"{p}: image not found (listed in {jpath}, frames[{j}])")
            size = None
        cam = _nerfstudio_camera(d, _pose(fr["transform_matrix"], where), size or (0, 0), where)
        image_path, cam = resolve_image(p, cam, f, down, size=size)
        mask = None
        if fr.get("mask_path") is not None:
            if not isinstance(fr["mask_path"], str):
                raise DatasetError(f"{where}: mask_path must be a string")
            mask = _norm(root, fr["mask_path"])
            if not mask.is_file():
                raise DatasetError(f"{mask}: mask not found (listed in {jpath}, frames[{j}])")
        by_path[p.as_posix()] = len(frames)
        frames.append(Frame(cam, image_path, _rel(root, p), mask))

    splits = None
    named = {k: meta[k] for k in ("train_filenames", "val_filenames", "test_filenames") if k in meta}
    if named:
        idx = {}
        for key, names in named.items():
            if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
                raise DatasetError(f"{jpath}: '{key}' must be a list of file paths")
            sel = []
            for n in names:
                k = by_path.get(_norm(root, n).as_posix())
                if k is None:
                    raise DatasetError(f"{jpath}: '{key}' names {n!r}, which is not a frame's file_path")
                sel.append(k)
            idx[key.split("_")[0]] = sorted(sel)
        splits = {}
        test = idx.get("test", idx.get("val"))
        if "train" in idx:
            splits["train"] = idx["train"]
        else:
            held = set(test or []) | set(idx.get("val", []))
            splits["train"] = [i for i in range(len(frames)) if i not in held]
        if test is None:
            train = set(splits["train"])
            test = [i for i in range(len(frames)) if i not in train]
        splits["test"] = test
        if "val" in idx:
            splits["val"] = idx["val"]

    points, colors = _initial_points(meta, root, jpath)
    return Dataset(frames, splits=splits, test_every=test_every, points=points, point_colors=colors,
                   root=root, kind="nerfstudio", factor=f, **dataset_kw)
