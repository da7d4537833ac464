"""Training datasets: posed images as :class:`~mlx3d.cameras.Camera` objects.

Readers (numpy and Pillow only; no MLX, no Blender):

- :func:`load_colmap`: a COLMAP workspace, ``sparse/0/{cameras,images,points3D}.{bin,txt}``
  plus ``images/`` (and ``images_2/4/8`` for downscaled copies);
- :func:`load_nerf_synthetic`: NeRF-synthetic (Blender) scenes,
  ``transforms_{train,val,test}.json``;
- :func:`load_nerfstudio`: nerfstudio / instant-ngp ``transforms.json``;
- :func:`load_dataset`: detects which of the three a path holds.

Each returns a :class:`Dataset`: a list of :class:`Frame` (camera, image path,
optional mask path, name), named splits (``train``/``test``), the initial
points and colours when the dataset has them, ``scene_extent()`` and
``load_image()`` (lazy, through a bounded LRU cache).

Conventions: cameras follow :mod:`mlx3d.cameras` (OpenCV axes, pixel centres
at ``+0.5``); OpenGL camera-to-world poses (NeRF-synthetic, nerfstudio) go
through :meth:`Camera.from_opengl_c2w`, the one place the axis flip happens.
Bad inputs raise :class:`DatasetError` naming the file (and the line or
record for text and binary formats).
"""

from mlx3d.errors import Mlx3dError


class DatasetError(Mlx3dError, ValueError):
    """A dataset is missing a file or holds a malformed one (the message names it)."""


# Submodules import DatasetError from here, so they come after its definition.
from .base import DEFAULT_CACHE_BYTES, CacheInfo, Dataset, Frame  # noqa: E402
from .colmap import ColmapCamera, ColmapImage, load_colmap, read_colmap_model  # noqa: E402
from .detect import detect_format, load_dataset  # noqa: E402
from .nerf import load_nerf_synthetic, load_nerfstudio  # noqa: E402

__all__ = [
    "DEFAULT_CACHE_BYTES",
    "CacheInfo",
    "ColmapCamera",
    "ColmapImage",
    "Dataset",
    "DatasetError",
    "Frame",
    "detect_format",
    "load_colmap",
    "load_dataset",
    "load_nerf_synthetic",
    "load_nerfstudio",
    "read_colmap_model",
]
