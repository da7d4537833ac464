"""Initial points from the photos themselves: a plane sweep over the training views.

A dataset without points (a NeRF-layout capture, a phone app's export) gives
the trainer nothing to start from but the posed photos. Random points in a cube
work for one object in front of a plain background (3DGS's NeRF-synthetic
recipe), but not for an open scene: the ground runs out of any cube towards
the horizon, random colours hide the photos' content, and densification starts
from Gaussians whose gradients are shared among dozens of random neighbours.

``sweep_points`` finds where the photos agree instead. For rays through pixels
of each training view (the reference) it tries ``depths`` distances, uniform in
inverse depth between ``near`` and ``far``; at each it projects the point into
the reference's nearest training views and measures how much their colours
(on images blurred by a 3x3 box, against sub-pixel misalignment) differ from
the reference pixel's. A ray gets a point where that difference is smallest,
if it is small (``max_cost``) and unique: every depth away from it
(``window``) costs at least ``margin`` more, and not among the farthest
depths (``window`` of them): what lies that far is the backdrop's, which the
trainer seeds on its own sphere. Textureless rays (a plain sky, a uniform wall) have no such
depth and get none; the trainer's far backdrop and densification cover them.
Occlusion needs no special case: a view that sees something else in front
disagrees, and the median over the neighbours ignores a minority of them.

Cost: ``rays x depths x neighbours`` projections in numpy (75M for the
defaults on 72 views: about 30 s on two cores).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np

__all__ = ["SweepResult", "sweep_points"]


@dataclass
class SweepResult:
    """Points found by :func:`sweep_points`.

    points (M, 3) float32 world positions; colours (M, 3) uint8 (the reference
    pixels'); rays: how many rays were tried; near, far: the depth range.
    """

    points: np.ndarray
    colours: np.ndarray
    rays: int
    near: float
    far: float


def _box3(image: np.ndarray) -> np.ndarray:
    """3x3 box blur of (H, W, 3), edges replicated."""
    p = np.pad(image, ((1, 1), (1, 1), (0, 0)), mode="edge")
    h, w = image.shape[:2]
    return sum(p[i:i + h, j:j + w] for i in range(3) for j in range(3)) / 9.0


def _neighbours(cameras, k: int) -> list[np.ndarray]:
    """For each camera, the ``k`` other cameras nearest to it, weighing distance and viewing direction."""
    centres = np.array([c.center for c in cameras], dtype=np.float64)
    forward = np.array([c.R[2] for c in cameras], dtype=np.float64)
    spread = max(float(np.linalg.norm(centres - centres.mean(0), axis=1).max()), 1e-9)
    d = np.linalg.norm(centres[:, None] - centres[None], axis=-1) / spread
    angle = 1.0 - forward @ forward.T  # 0 for the same direction, 2 for opposite
    score = d + angle
    np.fill_diagonal(score, np.inf)
    return [np.argsort(row)[:k] for row in score]


def _sample(image: np.ndarray, uv: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Nearest-pixel colours (N, 3) of ``image`` at ``uv`` (N, 2); rows with ``ok`` False are NaN."""
    h, w = image.shape[:2]
    x = np.clip(np.floor(uv[:, 0]).astype(np.int64), 0, w - 1)
    y = np.clip(np.floor(uv[:, 1]).astype(np.int64), 0, h - 1)
    out = image[y, x].astype(np.float32)
    out[~ok] = np.nan
    return out


def sweep_points(
    cameras,
    images,
    *,
    near: float,
    far: float,
    rays_per_view: int = 2048,
    depths: int = 64,
    neighbours: int = 8,
    max_cost: float = 0.04,
    margin: float = 0.03,
    window: int = 3,
    seed: int = 0,
    progress=None,
) -> SweepResult:
    """Photo-consistent points of posed opaque photos (see the module docstring).

    cameras: the training ``Camera`` s; images: their (H, W, 3) float images in
    [0, 1], same order; near, far: the depth range swept (camera z, world
    units); rays_per_view: random pixels tried per view; depths: samples per
    ray, uniform in 1/depth; neighbours: views compared with each reference;
    max_cost: the largest accepted median colour difference (mean absolute
    difference over RGB, in [0, 1]); margin, window: every depth more than
    ``window`` samples from the best must cost at least ``margin`` more (the
    best depth is unique). Deterministic for a ``seed``. progress(done, total)
    is called after each reference view.
    """
    if not (0 < near < far and math.isfinite(far)):
        raise ValueError(f"sweep depth range must satisfy 0 < near < far < inf, got {near}, {far}")
    rng = np.random.default_rng(seed)
    blurred = [_box3(np.asarray(im, np.float32)) for im in images]
    nbrs = _neighbours(cameras, min(neighbours, len(cameras) - 1))
    inv = np.linspace(1.0 / near, 1.0 / far, depths)
    z = 1.0 / inv  # (D,)
    found_p, found_c = [], []
    total = 0
    for r, (cam, image) in enumerate(zip(cameras, blurred)):
        n = int(rays_per_view)
        uv = np.stack([rng.uniform(0, cam.width, n), rng.uniform(0, cam.height, n)], axis=1)
        ref = _sample(image, uv, np.ones(n, bool))  # (n, 3)
        pts = np.asarray(cam.unproject(np.repeat(uv, depths, axis=0), np.tile(z, n)), np.float64)  # (n*D, 3)
        diffs = []
        for j in nbrs[r]:
            other = cameras[j]
            puv, pz = (np.asarray(a, np.float64) for a in other.project_points(pts))
            ok = (pz > 0) & np.isfinite(puv).all(axis=1)
            ok &= (puv[:, 0] >= 0) & (puv[:, 0] < other.width) & (puv[:, 1] >= 0) & (puv[:, 1] < other.height)
            col = _sample(blurred[j], puv, ok).reshape(n, depths, 3)
            diffs.append(np.abs(col - ref[:, None, :]).mean(axis=-1))  # (n, D), NaN where unseen
        d = np.stack(diffs)  # (K, n, D)
        seen = np.isfinite(d).sum(axis=0)
        with warnings.catch_warnings():  # all-NaN slices (unseen samples) are expected
            warnings.simplefilter("ignore", RuntimeWarning)
            cost = np.where(seen >= 2, np.nanmedian(d, axis=0), np.inf)  # at least two other views see it
            best = np.argmin(cost, axis=1)
            best_cost = cost[np.arange(n), best]
        # The best depth must be unique: every depth more than ``window`` samples from it costs ``margin`` more.
        far_from_best = np.abs(np.arange(depths)[None, :] - best[:, None]) > window
        second = np.min(np.where(far_from_best, cost, np.inf), axis=1)
        keep = np.isfinite(best_cost) & (best_cost <= max_cost) & (second >= best_cost + margin)
        # A ray whose best depth is among the farthest is explained by the backdrop: no point.
        keep &= best < depths - 1 - window
        total += n
        if keep.any():
            idx = np.flatnonzero(keep)
            found_p.append(pts.reshape(n, depths, 3)[idx, best[idx]])
            found_c.append(ref[idx])
        if progress is not None:
            progress(r + 1, len(cameras))
    points = np.concatenate(found_p) if found_p else np.zeros((0, 3))
    colours = np.concatenate(found_c) if found_c else np.zeros((0, 3))
    return SweepResult(points.astype(np.float32), np.clip(np.round(colours * 255.0), 0, 255).astype(np.uint8),
                       total, float(near), float(far))
