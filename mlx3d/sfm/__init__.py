"""Cameras from photos (structure from motion), for training on a user's own captures.

- :func:`solve_poses`: a folder of photos -> a COLMAP dataset (``images/``,
  ``sparse/0``, ``poses.json``) that :func:`mlx3d.datasets.load_dataset`
  reads, solved with pycolmap (an optional dependency: ``pip install
  "mlx3d-splat[poses]"``) and set upright (:mod:`.orient`);
- :func:`extract_frames`: a video -> sharp frames at a chosen rate (:mod:`.video`);
- :func:`solve_capture`: either of the two, as ``mlx3d poses`` runs it.

Nothing here imports Blender; pycolmap is imported only when a solve starts.
"""

from mlx3d.errors import Mlx3dError


class PosesError(Mlx3dError, ValueError):
    """Cameras cannot be solved from these photos (too few, unreadable, too few registered, no pycolmap)."""


from .orient import upright  # noqa: E402
from .solve import (  # noqa: E402
    MATCHING, PosesResult, choose_matching, list_photos, needs_solve, poses_folder, require_pycolmap, solve_capture, solve_poses,
)
from .video import VIDEO_SUFFIXES, extract_frames, is_video  # noqa: E402

__all__ = [
    "MATCHING",
    "VIDEO_SUFFIXES",
    "PosesError",
    "PosesResult",
    "choose_matching",
    "extract_frames",
    "is_video",
    "list_photos",
    "needs_solve",
    "poses_folder",
    "require_pycolmap",
    "solve_capture",
    "solve_poses",
    "upright",
]
