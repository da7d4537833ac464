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
  than 0.1 · scene extent in the world, except the backdrop: Gaussians
  farther than ``backdrop_radius`` from ``scene_centre`` (a sky or a far
  environment behind opaque photos must be large, on screen and in the world).
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
    scene_centre=None,
    backdrop_radius: float | None = None,
) -> tuple[dict, dict]:
    """One densification round. Returns (new params, counts {'cloned', 'split', 'pruned'}).

    scene_centre (3,) and backdrop_radius (scene units): Gaussians farther than
    that from the centre are exempt from the size prunes; None: none is."""
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
        too_big = world_max > 0.1 * scene_extent
        if max_radii is not None:
            radii = np.zeros(total)
            radii[:n] = np.asarray(max_radii, dtype=np.float64)
            too_big |= radii > max_screen_size
        if scene_centre is not None and backdrop_radius is not None:
            distance = np.linalg.norm(np.array(params["means"], dtype=np.float64) - np.asarray(scene_centre, np.float64), axis=1)
            too_big &= distance <= backdrop_radius
        prune |= too_big
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


# --------------------------------------------------------------------------- MCMC (3DGS as MCMC)
MCMC_MAX_COPIES = 51  # size of the paper's binomial table: N is clamped to 1..51


def relocation_correction(opacity: np.ndarray, scale: np.ndarray, copies: np.ndarray):
    """Opacity and scale for each of N copies of a Gaussian so that together they render
    about like the original (Kheradmand et al. 2024, eq. 9):

        o' = 1 - (1 - o)^(1/N)
        s' = o / (Σ_{i=1..N} Σ_{k=0..i-1} C(i-1, k) (-1)^k o'^(k+1) / sqrt(k+1)) · s

    opacity (M,) in (0,1), scale (M,3) std-devs, copies (M,) >= 1 (clamped to 51).
    """
    n = np.clip(np.asarray(copies, dtype=np.int64), 1, MCMC_MAX_COPIES)
    o = np.clip(np.asarray(opacity, dtype=np.float64), 1e-12, 1 - 1e-12)
    new_o = 1.0 - (1.0 - o) ** (1.0 / n)
    binom = np.zeros((MCMC_MAX_COPIES, MCMC_MAX_COPIES))
    for i in range(MCMC_MAX_COPIES):
        for k in range(i + 1):
            binom[i, k] = math.comb(i, k)
    denom = np.zeros_like(o)
    for j in range(len(o)):
        total = 0.0
        for i in range(1, n[j] + 1):
            k = np.arange(i)
            total += float(np.sum(binom[i - 1, :i] * (-1.0) ** k * new_o[j] ** (k + 1) / np.sqrt(k + 1)))
        denom[j] = total
    new_scale = (o / denom)[:, None] * np.asarray(scale, dtype=np.float64)
    return new_o, new_scale


def _sample_by_opacity(opacity: np.ndarray, count: int, rng) -> np.ndarray:
    p = np.asarray(opacity, dtype=np.float64)
    p = p / p.sum()
    return rng.choice(len(p), size=count, replace=True, p=p)


def _apply_copies(params: dict, optimizer, sources: np.ndarray, targets: np.ndarray, min_opacity: float) -> dict:
    """Copy ``sources`` rows onto ``targets`` rows (and into themselves) with the corrected
    opacity/scale for the number of copies each source now has; zero their moments.

    The corrected opacity is kept above ``min_opacity`` (as the reference implementation
    does): a copy born "dead" would be relocated again at the next event."""
    n = params["means"].shape[0]
    copies = np.bincount(sources, minlength=n) + 1  # the source itself plus its new copies
    srcs = np.unique(sources)
    opacity = 1.0 / (1.0 + np.exp(-np.array(params["opacities"], dtype=np.float64)))
    scales = np.exp(np.array(params["scales"], dtype=np.float64))
    new_o, new_s = relocation_correction(opacity[srcs], scales[srcs], copies[srcs])
    new_o = np.clip(new_o, min_opacity, 1.0 - np.finfo(np.float32).eps)
    logit = np.log(new_o / (1.0 - new_o))
    out = {k: np.array(v) for k, v in params.items()}
    out["opacities"][srcs] = logit
    out["scales"][srcs] = np.log(new_s)
    for k in out:
        out[k][targets] = out[k][sources]
    if optimizer is not None:
        rows = np.concatenate([srcs, targets])
        for k in out:
            optimizer.reset_rows(k, rows)
    return {k: mx.array(v.astype(np.float32)) for k, v in out.items()}


def relocate_dead(params: dict, optimizer=None, min_opacity: float = 0.005, rng=None, max_frac: float = 1.0, jitter_scale: float = 0.0) -> tuple[dict, int]:
    """Move Gaussians with opacity ≤ ``min_opacity`` onto live ones sampled in proportion to
    opacity, correcting opacity and scale for the copies. N stays constant.

    max_frac: at most this fraction of N moves per call (the most transparent first; when
    every Gaussian is dead, the others are the sources, so a fraction below 1 still moves);
    jitter_scale: moved copies are offset by that many of their standard deviations in a
    random direction (0: on top of their source, as in the paper). Returns (params, moved)."""
    rng = rng or np.random.default_rng(0)
    n = params["means"].shape[0]
    opacity = 1.0 / (1.0 + np.exp(-np.array(params["opacities"], dtype=np.float64)))
    dead = np.flatnonzero(opacity <= min_opacity)
    alive = np.flatnonzero(opacity > min_opacity)
    limit = int(max_frac * n)
    if dead.size > limit:
        dead = np.sort(dead[np.argsort(opacity[dead], kind="stable")[:limit]])
    if alive.size == 0:  # all dead: the copies' sources are the rows this call does not move
        alive = np.setdiff1d(np.arange(n), dead)
    if dead.size == 0 or alive.size == 0:
        return params, 0
    sources = alive[_sample_by_opacity(opacity[alive], dead.size, rng)]
    out = _apply_copies(params, optimizer, sources, dead, min_opacity)
    if jitter_scale > 0:
        rot = np.array(quaternion_to_matrix(np.array(out["quats"], dtype=np.float64)[dead]))
        std = np.exp(np.array(out["scales"], dtype=np.float64)[dead])
        offset = np.einsum("nij,nj->ni", rot, jitter_scale * std * rng.normal(size=std.shape))
        means = np.array(out["means"], dtype=np.float64)
        means[dead] += offset
        out["means"] = mx.array(means.astype(np.float32))
    return out, int(dead.size)


def add_gaussians_mcmc(params: dict, optimizer=None, cap: int | None = None, growth: float = 0.05, rng=None,
                       min_opacity: float = 0.005) -> tuple[dict, int]:
    """Grow by ``growth`` (fraction of N, up to ``cap``): new Gaussians are copies of ones
    sampled in proportion to opacity, with the copy correction (opacity kept above
    ``min_opacity``). Returns (params, added)."""
    rng = rng or np.random.default_rng(0)
    n = params["means"].shape[0]
    target = int(n * (1.0 + growth)) if cap is None else min(int(cap), int(n * (1.0 + growth)))
    add = max(target - n, 0)
    if add == 0:
        return params, 0
    opacity = 1.0 / (1.0 + np.exp(-np.array(params["opacities"], dtype=np.float64)))
    sources = _sample_by_opacity(opacity, add, rng)
    grown = _concat(params, _take(params, sources))
    if optimizer is not None:
        optimizer.append(add)
    return _apply_copies(grown, optimizer, sources, np.arange(n, n + add), min_opacity), add


def sgld_noise(params: dict, lr_means: float, noise_scale: float = 5e5, rng=None, isotropic: float = 0.0) -> mx.array:
    """MCMC position noise, the means (N, 3) after it.

    The paper's term: N(0, Σ) scaled by ``noise_scale · lr_means`` and gated by
    opacity with sigmoid(100 · ((1 - o) - 0.995)), so only near-transparent
    Gaussians move much. ``isotropic``: also N(0, isotropic² I) on every mean
    (scene units; the original mlx3D's ``mcmc_noise_scale · extent · sqrt(lr_means)``).
    """
    rng = rng or np.random.default_rng(0)
    means = params["means"]
    if noise_scale > 0:
        opacity = mx.sigmoid(params["opacities"])
        gate = mx.sigmoid(100.0 * ((1.0 - opacity) - 0.995))
        rot = quaternion_to_matrix(params["quats"])
        std = mx.exp(params["scales"])
        z = mx.array(rng.normal(size=tuple(means.shape)).astype(np.float32))
        noise = (rot @ ((std * std) * z)[..., None])[..., 0]  # Σ z with Σ = R S² Rᵀ, since Rᵀ z' ~ z for isotropic z
        means = means + noise * (gate * noise_scale * lr_means)[:, None]
    if isotropic > 0:
        means = means + mx.array(rng.normal(scale=isotropic, size=tuple(means.shape)).astype(np.float32))
    return means
