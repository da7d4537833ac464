"""Recognise a dataset's format from its files and load it."""

from __future__ import annotations

from pathlib import Path

from . import DatasetError
from .base import Dataset
from .colmap import _find_sparse, load_colmap
from .nerf import load_nerf_synthetic, load_nerfstudio

FORMATS = ("colmap", "nerf_synthetic", "nerfstudio")


def detect_format(path) -> str:
    """``'colmap'``, ``'nerf_synthetic'`` or ``'nerfstudio'`` for a dataset path.

    A folder with a COLMAP model (``sparse/0`` or ``sparse`` holding
    ``cameras.bin|txt``) is COLMAP; else one with ``transforms_train.json`` is
    NeRF-synthetic; else one with ``transforms.json`` is nerfstudio. A path to
    one of the json files names its format directly.
    """
    p = Path(path)
    if p.is_file():
        if p.name.startswith("transforms_") and p.suffix == ".json":
            return "nerf_synthetic"
        if p.suffix == ".json":
            return "nerfstudio"
        raise DatasetError(f"{p}: not a dataset (expected a folder, transforms.json or transforms_train.json)")
    if not p.is_dir():
        raise DatasetError(f"{p}: dataset not found")
    try:
        _find_sparse(p)
        return "colmap"
    except DatasetError:
        pass
    if (p / "transforms_train.json").is_file():
        return "nerf_synthetic"
    if (p / "transforms.json").is_file():
        return "nerfstudio"
    raise DatasetError(
        f"{p}: no dataset found (looked for sparse/0 or sparse with cameras.bin|txt, "
        "transforms_train.json and transforms.json)"
    )


def load_dataset(path, factor=1, *, kind: str | None = None, **kw) -> Dataset:
    """Load a COLMAP, NeRF-synthetic or nerfstudio dataset, detecting which (see :func:`detect_format`).

    factor: downscale factor (see the readers); kind: one of :data:`FORMATS`
    to skip detection;
    kw: passed to the reader (e.g. ``test_every``, ``images_dir``,
    ``val_in_train``) and to :class:`Dataset` (``cache_images``,
    ``cache_bytes``, ``resample``, ``seed``).
    """
    fmt = detect_format(path) if kind is None else kind
    if fmt == "colmap":
        return load_colmap(path, factor, **kw)
    if fmt == "nerf_synthetic":
        return load_nerf_synthetic(path, factor, **kw)
    if fmt == "nerfstudio":
        return load_nerfstudio(path, factor, **kw)
    raise ValueError(f"kind must be one of {FORMATS} or None, got {kind!r}")
