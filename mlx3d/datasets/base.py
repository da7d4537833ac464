"""The common dataset type, lazy image loading and the helpers the readers share.

Images are decoded with Pillow into float32 ``[0, 1]``; sRGB values stay as
they are (3DGS trains on sRGB values). An alpha channel is kept separately
(straight, not premultiplied) and a mask image becomes a 0/1 plane; both are
"coverage": at load time they are composited onto a background or returned
as a per-pixel loss weight (see :meth:`Dataset.load_image`).

Downscaling by ``factor`` (done by the readers through :func:`resolve_image`):
a ready-made downscaled copy (COLMAP's ``images_2/4/8``) is used when it
exists and is ``W/f x H/f`` to within a pixel; otherwise the full image is
resized with Pillow to the size of ``camera.scaled(1/f)``, i.e.
``round(W/f) x round(H/f)`` (halves up). Either way the frame's camera is
scaled to exactly the pixel grid of the image it is paired with. Colour and
alpha are resized premultiplied, so a downscaled RGBA image composited on a
background equals the composited full image downscaled.
"""

from __future__ import annotations

import math
import operator
import threading
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple, Sequence

import numpy as np

from mlx3d.cameras import Camera

from . import DatasetError

#: Default byte budget of the decoded-image cache (1 GiB).
DEFAULT_CACHE_BYTES = 1 << 30

_RESAMPLE = ("lanczos", "box")
# Below this coverage the straight colour of a resized pixel is taken from the
# unpremultiplied resize instead of dividing by (almost) zero.
_MIN_ALPHA = 1e-6


def _pil():
    try:
        from PIL import Image
    except ImportError as exc:  # pragma: no cover - Pillow is a dependency
        raise ImportError("mlx3d.datasets needs Pillow to decode images: pip install 'pillow>=10'") from exc
    return Image


# -- frames and splits


@dataclass(frozen=True)
class Frame:
    """One posed image.

    camera: the :class:`Camera` of the image as it is loaded (downscale applied).
    image_path: the file decoded by :meth:`Dataset.load_image` (a downscaled
        copy when one was used).
    name: the dataset's name for the image (COLMAP image name, relative
        ``file_path``), unique within the dataset.
    mask_path: optional mask image (nonzero = keep), any size with the
        image's aspect ratio (resized to the camera's size).
    """

    camera: Camera
    image_path: Path
    name: str
    mask_path: Path | None = None


def cameras_extent(centres) -> float:
    """3DGS's ``cameras_extent`` of camera centres (C, 3): 1.1 x the largest distance of one from their mean."""
    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    return float(np.linalg.norm(centres - centres.mean(axis=0), axis=1).max() * 1.1)


def holdout_split(n: int, test_every: int | None = 8) -> dict[str, list[int]]:
    """Every ``test_every``-th frame held out for testing: indices 0, k, 2k, ... go to ``test``.

    This is the 3DGS / mip-NeRF 360 ("LLFF hold") convention, applied to the
    frames in the dataset's order (COLMAP images sorted by name). ``None`` or
    ``0`` puts every frame in ``train``.
    """
    if test_every is None or test_every == 0:
        return {"train": list(range(n)), "test": []}
    if isinstance(test_every, bool):
        raise ValueError(f"test_every must be an integer >= 2, 0 or None, got {test_every!r}")
    try:
        k = operator.index(test_every)
    except TypeError:
        raise ValueError(f"test_every must be an integer >= 2, 0 or None, got {test_every!r}") from None
    if k < 2:
        raise ValueError(f"test_every must be an integer >= 2, 0 or None, got {test_every!r}")
    return {"train": [i for i in range(n) if i % k], "test": list(range(0, n, k))}


# -- image files


def check_factor(factor) -> float:
    """``factor`` as a positive finite float (ValueError otherwise)."""
    if isinstance(factor, bool):
        raise ValueError(f"factor must be a positive number, got {factor!r}")
    try:
        f = float(factor)
    except (TypeError, ValueError):
        raise ValueError(f"factor must be a positive number, got {factor!r}") from None
    if not (math.isfinite(f) and f > 0):
        raise ValueError(f"factor must be a positive number, got {factor!r}")
    return f


def image_size(path: Path, what: str = "image") -> tuple[int, int]:
    """``(width, height)`` of an image file from its header (the pixels are not decoded)."""
    Image = _pil()
    try:
        with Image.open(path) as im:
            return im.size
    except FileNotFoundError:
        raise DatasetError(f"{path}: {what} not found") from None
    except (OSError, ValueError, Image.DecompressionBombError) as exc:
        raise DatasetError(f"{path}: cannot read {what}: {exc}") from None


def fit_camera(camera: Camera, width: int, height: int, path: Path) -> Camera:
    """``camera`` for an image of ``width x height`` pixels showing the same view.

    Same size: the camera itself. Otherwise the intrinsics scale by ``w/W`` and
    ``h/H`` (as :meth:`Camera.scaled`), provided the aspect ratio agrees to
    within a pixel of rounding; a different aspect ratio is a DatasetError.
    """
    if (width, height) == (camera.width, camera.height):
        return camera
    sx, sy = width / camera.width, height / camera.height
    if abs(sx * camera.height - height) > 1.0 or abs(sy * camera.width - width) > 1.0:
        raise DatasetError(
            f"{path}: image is {width}x{height} but its camera is {camera.width}x{camera.height} "
            "(a different aspect ratio)"
        )
    return Camera(width, height, camera.fx * sx, camera.fy * sy, camera.cx * sx, camera.cy * sy,
                  camera.viewmat, near=camera.near, far=camera.far, model=camera.model, dist=camera.dist)


def resolve_image(path: Path, camera: Camera, factor: float, downscaled: Path | None = None,
                  size: tuple[int, int] | None = None) -> tuple[Path, Camera]:
    """The file to decode for ``path`` at ``factor`` and the camera of its pixel grid.

    camera: the camera of the full-resolution view (any size with the image's
        aspect ratio; it is fitted to the file's actual size first).
    downscaled: a ready-made ``1/factor`` copy to prefer when it exists (it
        must be ``W/f x H/f`` of the camera to within one pixel).
    size: the already known ``(w, h)`` of ``path``, to skip reading its header.
    Otherwise the returned camera is ``fit(camera).scaled(1/factor)`` and the
    image is resized to it on load.
    """
    if factor != 1.0 and downscaled is not None and downscaled.is_file():
        w, h = image_size(downscaled)
        ew, eh = camera.width / factor, camera.height / factor
        if abs(w - ew) > 1.0 or abs(h - eh) > 1.0:
            raise DatasetError(
                f"{downscaled}: image is {w}x{h}, but factor {factor:g} of its {camera.width}x{camera.height} "
                f"camera gives {ew:g}x{eh:g}"
            )
        return downscaled, fit_camera(camera, w, h, downscaled)
    if size is None:
        if not path.is_file():
            raise DatasetError(f"{path}: image not found")
        size = image_size(path)
    cam = fit_camera(camera, size[0], size[1], path)
    if factor != 1.0:
        try:
            cam = cam.scaled(1.0 / factor)
        except ValueError as exc:
            raise DatasetError(f"{path}: {exc}") from None
    return path, cam


def _decode(path: Path, what: str):
    Image = _pil()
    try:
        im = Image.open(path)
    except FileNotFoundError:
        raise DatasetError(f"{path}: {what} not found") from None
    except (OSError, ValueError, Image.DecompressionBombError) as exc:
        raise DatasetError(f"{path}: cannot read {what}: {exc}") from None
    try:
        with im:
            im.load()
            return _pixels(im)
    except (OSError, ValueError, Image.DecompressionBombError) as exc:
        raise DatasetError(f"{path}: cannot decode {what}: {exc}") from None


def _pixels(im):
    """(rgb (H, W, 3) float32 in [0, 1], alpha (H, W) float32 or None) of an open Pillow image."""
    mode = im.mode
    if mode in ("I;16", "I;16L", "I;16B", "I;16N", "I"):  # 16-bit grey
        g = np.asarray(im).astype(np.float32) / np.float32(65535.0)
        g = np.clip(g, 0.0, 1.0)
        return np.repeat(g[..., None], 3, axis=-1), None
    if mode == "F":
        g = np.asarray(im, dtype=np.float32)
        return np.repeat(g[..., None], 3, axis=-1), None
    has_alpha = mode in ("RGBA", "LA", "PA", "RGBa", "La") or "transparency" in im.info
    if has_alpha:
        a = np.asarray(im.convert("RGBA"))
        alpha8 = a[..., 3]
        rgb = a[..., :3].astype(np.float32) / np.float32(255.0)
        if np.all(alpha8 == 255):  # opaque everywhere: no coverage information
            return rgb, None
        return rgb, alpha8.astype(np.float32) / np.float32(255.0)
    a = np.asarray(im if mode == "RGB" else im.convert("RGB"))
    return a.astype(np.float32) / np.float32(255.0), None


def decode_image(path: Path):
    """Decode an image file: ``(rgb (H, W, 3) float32 in [0, 1], alpha (H, W) float32 or None)``.

    Grey images are replicated to three channels, palette images expanded,
    16-bit grey scaled by 1/65535; alpha is None when the file has none or it
    is opaque everywhere.
    """
    return _decode(Path(path), "image")


def decode_mask(path: Path) -> np.ndarray:
    """A mask image as an (H, W) float32 plane: 1 where any colour channel is nonzero, else 0."""
    Image = _pil()
    path = Path(path)
    try:
        im = Image.open(path)
    except FileNotFoundError:
        raise DatasetError(f"{path}: mask not found") from None
    except (OSError, ValueError, Image.DecompressionBombError) as exc:
        raise DatasetError(f"{path}: cannot read mask: {exc}") from None
    try:
        with im:
            im.load()
            if im.mode not in ("1", "L", "I", "I;16", "F", "RGB", "RGBA", "LA"):
                im = im.convert("RGB")
            a = np.asarray(im)
            if a.ndim == 3:
                a = a[..., :1] if im.mode == "LA" else a[..., :3]
                keep = np.any(a != 0, axis=-1)
            else:
                keep = a != 0
    except (OSError, ValueError, Image.DecompressionBombError) as exc:
        raise DatasetError(f"{path}: cannot decode mask: {exc}") from None
    return keep.astype(np.float32)


def _resize_plane(a: np.ndarray, size: tuple[int, int], resample: str) -> np.ndarray:
    Image = _pil()
    filt = Image.Resampling.LANCZOS if resample == "lanczos" else Image.Resampling.BOX
    im = Image.fromarray(np.ascontiguousarray(a, dtype=np.float32))  # mode "F"
    return np.asarray(im.resize(size, filt), dtype=np.float32)


def resize_image(rgb: np.ndarray, alpha: np.ndarray | None, size: tuple[int, int], resample: str = "lanczos"):
    """Resize straight ``rgb`` (H, W, 3) and optional ``alpha`` (H, W) to ``size = (w, h)``.

    Colour is resized premultiplied by alpha and divided back, so composited
    results do not bleed the colour of transparent pixels. Float32 throughout;
    results are clipped to [0, 1] (Lanczos overshoots).
    """
    if alpha is None:
        out = np.stack([_resize_plane(rgb[..., c], size, resample) for c in range(3)], axis=-1)
        return np.clip(out, 0.0, 1.0), None
    a = np.clip(_resize_plane(alpha, size, resample), 0.0, 1.0)
    pre = np.stack([_resize_plane(rgb[..., c] * alpha, size, resample) for c in range(3)], axis=-1)
    straight = np.stack([_resize_plane(rgb[..., c], size, resample) for c in range(3)], axis=-1)
    ok = a > _MIN_ALPHA
    out = np.where(ok[..., None], pre / np.where(ok, a, 1.0)[..., None], straight)
    return np.clip(out, 0.0, 1.0).astype(np.float32), a


def read_points_ply(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Initial points from a PLY file: ``(xyz (M, 3) float32, rgb (M, 3) uint8 or None)``.

    Reads the ``vertex`` element's ``x y z`` and, when present, ``red green
    blue`` (integers 0..255, or floats in [0, 1] which are scaled by 255).
    """
    import plyfile

    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: point cloud not found")
    try:
        ply = plyfile.PlyData.read(str(path))
        v = ply["vertex"].data
    except KeyError:
        raise DatasetError(f"{path}: no 'vertex' element") from None
    except Exception as exc:  # plyfile raises several types for malformed files
        raise DatasetError(f"{path}: cannot read PLY: {exc}") from None
    names = v.dtype.names or ()
    missing = [n for n in ("x", "y", "z") if n not in names]
    if missing:
        raise DatasetError(f"{path}: vertex element has no {', '.join(missing)} properties")
    xyz = np.stack([np.asarray(v[n], dtype=np.float32) for n in ("x", "y", "z")], axis=-1)
    colors = None
    if all(n in names for n in ("red", "green", "blue")):
        c = np.stack([np.asarray(v[n]) for n in ("red", "green", "blue")], axis=-1)
        if np.issubdtype(c.dtype, np.floating):
            c = np.round(np.clip(c.astype(np.float64), 0.0, 1.0) * 255.0)
        colors = np.clip(c, 0, 255).astype(np.uint8)
    return xyz, colors


# -- the image cache


class CacheInfo(NamedTuple):
    """Counters of a dataset's decoded-image cache."""

    hits: int
    misses: int
    items: int
    bytes: int
    max_items: int | None
    max_bytes: int | None


class _LRUCache:
    """Least-recently-used cache bounded by entry count and total bytes; thread-safe."""

    def __init__(self, max_items: int | None, max_bytes: int | None):
        for name, v in (("cache_images", max_items), ("cache_bytes", max_bytes)):
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 0):
                raise ValueError(f"{name} must be a non-negative integer or None, got {v!r}")
        self.max_items = None if max_items is None else int(max_items)
        self.max_bytes = None if max_bytes is None else int(max_bytes)
        self._data: OrderedDict[int, tuple] = OrderedDict()
        self._sizes: dict[int, int] = {}
        self._bytes = 0
        self._hits = 0
        self._misses = 0
        self._lock = threading.Lock()

    def get(self, key):
        with self._lock:
            value = self._data.get(key)
            if value is None:
                self._misses += 1
                return None
            self._data.move_to_end(key)
            self._hits += 1
            return value

    def put(self, key, value, nbytes: int):
        with self._lock:
            if key in self._data:
                self._bytes -= self._sizes.pop(key)
                del self._data[key]
            if (self.max_items is not None and self.max_items == 0) or (
                self.max_bytes is not None and nbytes > self.max_bytes
            ):
                return
            self._data[key] = value
            self._sizes[key] = nbytes
            self._bytes += nbytes
            while (self.max_items is not None and len(self._data) > self.max_items) or (
                self.max_bytes is not None and self._bytes > self.max_bytes
            ):
                old, _ = self._data.popitem(last=False)
                self._bytes -= self._sizes.pop(old)

    def clear(self):
        with self._lock:
            self._data.clear()
            self._sizes.clear()
            self._bytes = 0

    def info(self) -> CacheInfo:
        with self._lock:
            return CacheInfo(self._hits, self._misses, len(self._data), self._bytes, self.max_items, self.max_bytes)


_BACKGROUND_HELP = "background must be None, 'white', 'black', 'random' or (r, g, b)"


def _background(background, rng) -> np.ndarray:
    if isinstance(background, str):
        key = background.lower()
        if key == "white":
            return np.ones(3, dtype=np.float32)
        if key == "black":
            return np.zeros(3, dtype=np.float32)
        if key == "random":
            return rng.random(3).astype(np.float32)
        raise ValueError(f"{_BACKGROUND_HELP}, got {background!r}")
    try:
        bg = np.asarray(background, dtype=np.float32)
    except (TypeError, ValueError):
        raise ValueError(f"{_BACKGROUND_HELP}, got {background!r}") from None
    if bg.shape != (3,) or not np.all(np.isfinite(bg)):
        raise ValueError(f"background must be three finite numbers (r, g, b) in [0, 1], got {background!r}")
    return bg


def _readonly(a):
    if a is not None:
        a.setflags(write=False)
    return a


# -- the dataset


class Dataset:
    """Posed images with splits, initial points and a lazily filled image cache.

    frames: list of :class:`Frame` (cameras already at the loading factor).
    splits: named lists of frame indices; ``None`` holds out every
        ``test_every``-th frame (indices 0, 8, 16, ... with the default 8 go to
        ``test``, the 3DGS / mip-NeRF 360 convention) and trains on the rest.
    points, point_colors: initial points (M, 3) float32 and their colours
        (M, 3) uint8, when the dataset has them (else None).
    observations: where each frame's photo sees the points, when the
        dataset knows (a structure-from-motion model's tracks), else None:
        per frame ``(xy (K, 2) float32`` pixels of its camera, ``index (K,)``
        into ``points)``.
    cache_images, cache_bytes: bounds of the LRU cache of decoded images
        (entry count, total bytes of the cached float32 planes); either may
        be None (unbounded) and ``cache_images=0`` disables caching. The
        default keeps at most :data:`DEFAULT_CACHE_BYTES` (1 GiB).
    resample: ``'lanczos'`` (default) or ``'box'``, the Pillow filter used
        when an image must be resized to its camera.
    seed: seed of the generator used for ``background='random'`` when no
        ``rng`` is passed to :meth:`load_image`.
    root, kind, factor: where the dataset came from, its format name and
        the downscale factor applied (informational).
    """

    def __init__(self, frames: Sequence[Frame], *, splits: dict[str, Sequence[int]] | None = None,
                 test_every: int | None = 8, points=None, point_colors=None, observations=None, root=None, kind: str = "custom",
                 factor: float = 1.0, cache_images: int | None = None,
                 cache_bytes: int | None = DEFAULT_CACHE_BYTES, resample: str = "lanczos", seed=None):
        self.frames: list[Frame] = list(frames)
        for i, fr in enumerate(self.frames):
            if not isinstance(fr, Frame):
                raise TypeError(f"frames[{i}] must be a Frame, got {type(fr).__name__}")
        n = len(self.frames)
        if splits is None:
            splits = holdout_split(n, test_every)
        self.splits: dict[str, list[int]] = {}
        for name, idx in splits.items():
            idx = [operator.index(i) for i in idx]
            bad = [i for i in idx if not 0 <= i < n]
            if bad:
                raise ValueError(f"split {name!r} has indices outside 0..{n - 1}: {bad[:5]}")
            self.splits[str(name)] = idx
        if points is not None:
            points = np.asarray(points, dtype=np.float32)
            if points.ndim != 2 or points.shape[1] != 3:
                raise ValueError(f"points must have shape (M, 3), got {points.shape}")
        if point_colors is not None:
            point_colors = np.asarray(point_colors)
            if points is None or point_colors.shape != points.shape:
                raise ValueError(f"point_colors must have the shape of points, got {point_colors.shape}")
            point_colors = point_colors.astype(np.uint8)
        if observations is not None:
            if points is None or len(observations) != n:
                raise ValueError(f"observations need points and one entry per frame ({n}), got {len(observations)}")
            for i, (xy, index) in enumerate(observations):
                if np.shape(xy) != (len(index), 2) or len(index) and not 0 <= np.min(index) <= np.max(index) < len(points):
                    raise ValueError(f"observations[{i}] must be (xy (K, 2), index (K,) into the {len(points)} points)")
        self.points = points
        self.point_colors = point_colors
        self.observations = observations
        if resample not in _RESAMPLE:
            raise ValueError(f"resample must be one of {_RESAMPLE}, got {resample!r}")
        self.resample = resample
        self.root = None if root is None else Path(root)
        self.kind = kind
        self.factor = factor
        self._cache = _LRUCache(cache_images, cache_bytes)
        self._rng = np.random.default_rng(seed)

    # -- frames and splits

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i) -> Frame:
        return self.frames[i]

    def __iter__(self):
        return iter(self.frames)

    def __repr__(self) -> str:
        sp = ", ".join(f"{k}={len(v)}" for k, v in self.splits.items())
        pts = "no points" if self.points is None else f"{len(self.points)} points"
        return f"Dataset({self.kind}, {len(self.frames)} frames, {sp}, {pts}, factor={self.factor:g})"

    @property
    def cameras(self) -> list[Camera]:
        """The frames' cameras, in frame order."""
        return [f.camera for f in self.frames]

    def split(self, name: str) -> list[int]:
        """Frame indices of split ``name`` (``'train'``, ``'test'``, and ``'val'`` where the dataset has one)."""
        try:
            return list(self.splits[name])
        except KeyError:
            raise ValueError(f"no split {name!r}; this dataset has {sorted(self.splits)}") from None

    @property
    def train(self) -> list[int]:
        """Indices of the training frames."""
        return list(self.splits.get("train", []))

    @property
    def test(self) -> list[int]:
        """Indices of the held-out test frames."""
        return list(self.splits.get("test", []))

    def _camera_centres(self, indices) -> np.ndarray:
        if indices is None:
            indices = self.train or range(len(self.frames))
        centers = np.array([self.frames[i].camera.center for i in indices], dtype=np.float64).reshape(-1, 3)
        if len(centers) == 0:
            raise ValueError("the scene's extent and centre need at least one camera")
        return centers

    def scene_extent(self, indices: Sequence[int] | None = None) -> float:
        """3DGS's ``cameras_extent``: 1.1 x the largest distance of a camera centre from their mean.

        indices: the cameras to use; default the training split (as 3DGS), or
        every frame when the dataset has no training frames.
        """
        return cameras_extent(self._camera_centres(indices))

    def scene_centre(self, indices: Sequence[int] | None = None) -> np.ndarray:
        """(3,) the mean of the camera centres (the same cameras as ``scene_extent``)."""
        return self._camera_centres(indices).mean(axis=0)

    # -- images

    def _entry(self, i: int):
        entry = self._cache.get(i)
        if entry is not None:
            return entry
        fr = self.frames[i]
        cam = fr.camera
        size = (cam.width, cam.height)
        rgb, alpha = decode_image(fr.image_path)
        if rgb.shape[1::-1] != size:
            rgb, alpha = resize_image(rgb, alpha, size, self.resample)
        mask = None
        if fr.mask_path is not None:
            mask = decode_mask(fr.mask_path)
            if mask.shape[::-1] != size:
                mask = np.clip(_resize_plane(mask, size, "box"), 0.0, 1.0)
        entry = tuple(_readonly(np.ascontiguousarray(a, dtype=np.float32)) if a is not None else None
                      for a in (rgb, alpha, mask))
        self._cache.put(i, entry, sum(a.nbytes for a in entry if a is not None))
        return entry

    def load_image(self, i: int, background=None, rng: np.random.Generator | None = None, *,
                   return_background: bool = False):
        """Frame ``i``'s image at its camera's size: ``(rgb, weight)``.

        rgb: (H, W, 3) float32 in [0, 1]; weight: (H, W) float32 in [0, 1] or None.

        The image's coverage is its alpha channel times its mask (nonzero =
        keep), whichever of the two exist.

        - ``background=None``: rgb is the file's colour as is (straight, not
          premultiplied) and ``weight`` is the coverage, to use as a per-pixel
          loss weight (train one object without its background); None when
          the image has neither alpha nor mask.
        - ``background='white'``, ``'black'``, ``(r, g, b)`` or ``'random'``
          (a fresh uniform colour per call, drawn from ``rng`` or the
          dataset's own generator): rgb is composited,
          ``rgb * coverage + background * (1 - coverage)``, and weight is None.

        return_background: also return the background colour used ((3,)
            float32, or None when ``background`` is None), so a renderer can
            draw with the same random colour.

        Cached arrays are returned read-only; copy before writing into them.
        """
        try:
            i = operator.index(i)
        except TypeError:
            raise TypeError(f"frame index must be an integer, got {type(i).__name__}") from None
        n = len(self.frames)
        if not -n <= i < n:
            raise IndexError(f"frame index {i} out of range for {n} frames")
        i %= n
        rgb, alpha, mask = self._entry(i)
        if alpha is None:
            cov = mask
        elif mask is None:
            cov = alpha
        else:
            cov = alpha * mask
        bg = None if background is None else _background(background, self._rng if rng is None else rng)
        if bg is None or cov is None:
            out = (rgb, cov if bg is None else None)
        else:
            c = cov[..., None]
            out = ((rgb * c + bg * (1.0 - c)).astype(np.float32), None)
        return (*out, bg) if return_background else out

    def cache_info(self) -> CacheInfo:
        """Counters of the image cache: hits, misses, items, bytes and the bounds."""
        return self._cache.info()

    def clear_cache(self) -> None:
        """Drop every cached image."""
        self._cache.clear()
