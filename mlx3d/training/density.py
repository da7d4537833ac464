"""Adaptive density control of 3DGS (Kerbl et al. 2023): clone, split, prune, reset.

Operates on a raw parameter dict (see ``mlx3d.splatting.model``) and an
optional ``Adam`` whose moments are edited in step (new rows start at zero,
removed rows go). Decisions are made in numpy on small per-Gaussian vectors.

- Gaussians whose mean screen-space gradient (accumulated over views, in NDC
  units as in 3DGS) reaches ``grad_threshold`` are densified: small ones
  (max scale ≤ ``percent_dense`` · scene extent) are cloned, large ones split
  into two samples drawn from themselves with scales divided by 1.6.
- Pruned: split originals, opacity below ``min_opacity``, and — once
  ``max_screen_size`` is set — those larger than it on screen (pixels) or
  than 0.1 · scene extent in the world.
- ``max_gaussians`` caps growth: the candidates with the largest gradients win.
"""

from __future__ import annotations

import math

import mlx.core as mx
import numpy as np

from ..transforms import quaternion_to_matrix


def _take(params: dict, rows: np.ndarray) -> dict:
    idx = mx.array(rows.astype(np.int64))
    return {k: v[idx] for k, v in params.items()}


def _concat(a: dict, b: dict) -> dict:
    return {k: mx.concatenate([a[k], b[k]], axis=0) for k in a}


def _keep(params: dict, optimizer, keep: np.ndarray) -> dict:
    rows = np.flatnonzero(keep)
    if optimizer is not None:
        optimizer.select(rows)
    return _take(params, rows)


def densify_and_prune(
    params: dict,
    grad_accum,
    grad_count,
    grad_threshold: float = 0.0002,
    scene_extent: float = 1.0,
    percent_dense: float = 0.01,
    min_opacity: float = 0.005,
    optimizer=None,
    max_screen_size: float | None = None,
    max_radii=None,
    max_gaussians: int | None = None,
    rng: np.random.Generator | None = None,
) -> tuple[dict, dict]:
    """One densification round. Returns (new params, counts {'cloned', 'split', 'pruned'})."""
    rng = rng or np.random.default_rng(0)
    n = params["means"].shape[0]
    count = np.asarray(grad_count, dtype=np.float64)
    grads = np.where(count > 0, np.asarray(grad_accum, dtype=np.float64) / np.maximum(count, 1), 0.0)
    log_scales = np.array(params["scales"], dtype=np.float64)
    max_scale = np.exp(log_scales.max(axis=1))
    candidates = grads >= grad_threshold
    if max_gaussians is not None:
        room = max(int(max_gaussians) - n, 0)
        # a split adds one net Gaussian like a clone; keep the strongest gradients within the room
        if candidates.sum() > room:
            order = np.argsort(-np.where(candidates, grads, -np.inf), kind="stable")[:room]
            candidates = np.zeros(n, bool)
            candidates[order] = True
    small = max_scale <= percent_dense * scene_extent
    clone = candidates & small
    split = candidates & ~small

    new_parts = []
    if clone.any():
        new_parts.append(_take(params, np.flatnonzero(clone)))
    if split.any():
        rows = np.flatnonzero(split)
        src = _take(params, np.repeat(rows, 2))
        rot = np.array(quaternion_to_matrix(np.array(src["quats"], dtype=np.float64)))
        std = np.exp(np.array(src["scales"], dtype=np.float64))
        offsets = np.einsum("nij,nj->ni", rot, rng.normal(size=std.shape) * std)
        src["means"] = mx.array((np.array(src["means"], dtype=np.float64) + offsets).astype(np.float32))
        src["scales"] = mx.array((np.array(src["scales"], dtype=np.float64) - math.log(1.6)).astype(np.float32))
        new_parts.append(src)
    added = sum(p["means"].shape[0] for p in new_parts)
    for part in new_parts:
        params = _concat(params, part)
    if optimizer is not None and added:
        optimizer.append(added)

    total = n + added
    opacity = 1.0 / (1.0 + np.exp(-np.array(params["opacities"], dtype=np.float64)))
    prune = opacity < min_opacity
    prune[:n] |= split
    if max_screen_size is not None:
        world_max = np.exp(np.array(params["scales"], dtype=np.float64).max(axis=1))
        prune |= world_max > 0.1 * scene_extent
        if max_radii is not None:
            radii = np.zeros(total)
            radii[:n] = np.asarray(max_radii, dtype=np.float64)
            prune |= radii > max_screen_size
    params = _keep(params, optimizer, ~prune)
    return params, {"cloned": int(clone.sum()), "split": int(split.sum()), "pruned": int(prune.sum()) - int(split.sum())}


def reset_opacities(params: dict, optimizer=None, max_opacity: float = 0.01) -> dict:
    """Clamp every opacity to at most ``max_opacity`` and zero its optimizer moments (3DGS)."""
    cap = math.log(max_opacity / (1.0 - max_opacity))
    out = dict(params)
    out["opacities"] = mx.minimum(params["opacities"], cap)
    if optimizer is not None:
        optimizer.reset_rows("opacities", np.arange(params["opacities"].shape[0]))
    return out
