"""The Gaussian splat model: raw parameters as MLX arrays plus the per-splat
extra properties a PLY file carried.

Raw parameters (``model.params``), N splats, K = (degree + 1)² SH coefficients:

==========  =========  ===============================================
name        shape      meaning
==========  =========  ===============================================
means       (N, 3)     centres, scene units
scales      (N, 3)     log standard deviations
quats       (N, 4)     orientation w,x,y,z, not necessarily normalised
opacities   (N,)       logits
sh_dc       (N, 1, 3)  SH degree-0 coefficient per RGB channel
sh_rest     (N, K-1,3) SH bands 1..degree, coefficient-major, channel last
==========  =========  ===============================================

``model.extra`` maps other PLY vertex properties (normals, ids, ...) to numpy
arrays of shape (N,); every row operation (select, append, compact, merge)
keeps them aligned so nothing of a file is lost on a round trip.

``model.active_sh_degree`` is mlx3D's training state: the SH degree in use,
0 for a new model (constructor, ``from_points``), the file's degree after
``load_ply``, raised by ``one_up_sh_degree`` up to ``sh_degree``. Rendering
uses ``sh_degree`` unless told otherwise (``render(sh_degree=...)``).
"""

from __future__ import annotations

import math
import numbers
import warnings
from typing import Iterable, Sequence

import mlx.core as mx
import numpy as np

from ..io.formats import read_splats, write_splats
from ..io.ply import SplatArrays, read_splat_ply, write_splat_ply
from ..meshing import DEFAULT_TRIM
from .ops import merge_splats, resize_sh_rest, transform_splats
from .sh import num_sh_bases, rgb_to_sh, sh_degree_from_bases, sh_to_rgb

PARAM_NAMES = ("means", "scales", "quats", "opacities", "sh_dc", "sh_rest")


def _as_index(keep, n: int) -> np.ndarray:
    """Row indices (int64) from a boolean mask of length n or an integer index array."""
    idx = np.asarray(keep)
    if idx.dtype == np.bool_:
        if idx.shape != (n,):
            raise ValueError(f"boolean keep mask must have shape ({n},), got {idx.shape}")
        return np.flatnonzero(idx)
    if idx.ndim != 1 or not np.issubdtype(idx.dtype, np.integer) and idx.size:
        raise ValueError(f"keep_idx must be a 1-D integer index or boolean mask, got dtype {idx.dtype} shape {idx.shape}")
    idx = idx.astype(np.int64)
    if idx.size and (idx.min() < -n or idx.max() >= n):
        raise ValueError(f"keep_idx out of range for {n} Gaussians (min {idx.min()}, max {idx.max()})")
    return idx % max(n, 1)


class _RowLayout:
    """Stands in for (or wraps) an optimizer in ``densify_and_prune`` to follow where rows go.

    ``origin`` holds, per current row, its row before the call or -1 for a new row."""

    def __init__(self, n: int, optimizer=None):
        self.optimizer = optimizer
        self.origin = np.arange(n, dtype=np.int64)

    def append(self, count: int) -> None:
        self.origin = np.concatenate([self.origin, np.full(int(count), -1, np.int64)])
        if self.optimizer is not None:
            self.optimizer.append(count)

    def select(self, rows) -> None:
        self.origin = self.origin[np.asarray(rows, dtype=np.int64)]
        if self.optimizer is not None:
            self.optimizer.select(rows)

    def __getattr__(self, name):
        optimizer = self.__dict__.get("optimizer")
        if optimizer is not None:
            return getattr(optimizer, name)
        if name.startswith("_"):
            raise AttributeError(name)
        return lambda *args, **kwargs: None  # other row edits (e.g. reset_rows) have no state to edit

    def result(self) -> tuple[np.ndarray, int]:
        """(kept old rows int32, new row count); the kept old rows come first."""
        old = self.origin >= 0
        kept = int(old.sum())
        if not old[:kept].all():
            raise RuntimeError("densify_and_prune placed new rows before kept ones; the row layout is not (kept, new)")
        return self.origin[:kept].astype(np.int32), int(len(self.origin) - kept)


def _directions_towards(points: np.ndarray, orient_towards) -> np.ndarray:
    """(M,3) vectors from each point to a target point (3,), or to the nearest of (C,3) positions."""
    targets = np.asarray(orient_towards, dtype=np.float64)
    if targets.size == 0:
        raise ValueError("orient_towards is empty; pass a point (3,), positions (C,3) or None")
    if targets.shape[-1] != 3 or targets.ndim > 2:
        raise ValueError(f"orient_towards must be a point (3,) or positions (C,3), got shape {targets.shape}")
    targets = targets.reshape(-1, 3)
    if not np.isfinite(targets).all():
        raise ValueError("orient_towards contains NaN or Inf")
    if targets.shape[0] == 1 or points.shape[0] == 0:
        return targets[0] - points
    from ..neighbors import knn

    nearest, _ = knn(targets, 1, queries=points)
    return targets[nearest[:, 0]] - points


class GaussianModel:
    """A set of 3D Gaussians with SH colour. See the module docstring for the layout."""

    def __init__(self, params: dict, extra: dict | None = None, *, sh_degree: int | None = None):
        """``params``: the raw arrays (see the module docstring); ``extra``: per-row PLY
        properties. ``sh_degree`` (mlx3D's second argument, also accepted positionally
        as an int) must match the SH arrays when given."""
        if isinstance(extra, numbers.Integral) and not isinstance(extra, bool):  # mlx3D: GaussianModel(params, sh_degree)
            extra, sh_degree = None, int(extra)
        missing = [k for k in PARAM_NAMES if k not in params]
        if missing:
            raise ValueError(f"GaussianModel params missing {missing}")
        self.params = {k: params[k] if isinstance(params[k], mx.array) else mx.array(np.asarray(params[k], np.float32)) for k in PARAM_NAMES}
        n = self.params["means"].shape[0]
        expected = {"means": (n, 3), "scales": (n, 3), "quats": (n, 4), "opacities": (n,), "sh_dc": (n, 1, 3)}
        for key, shape in expected.items():
            if tuple(self.params[key].shape) != shape:
                raise ValueError(f"param '{key}' must have shape {shape}, got {tuple(self.params[key].shape)}")
        rest = self.params["sh_rest"]
        if rest.ndim != 3 or rest.shape[0] != n or rest.shape[2] != 3:
            raise ValueError(f"param 'sh_rest' must have shape ({n}, K-1, 3), got {tuple(rest.shape)}")
        sh_degree_from_bases(rest.shape[1] + 1)  # validates K
        self.extra = {}
        for name, values in (extra or {}).items():
            values = np.asarray(values)
            if values.shape != (n,):
                raise ValueError(f"extra property '{name}' must have shape ({n},), got {values.shape}")
            self.extra[name] = values
        if sh_degree is not None and int(sh_degree) != self.sh_degree:
            raise ValueError(f"sh_degree={sh_degree} does not match the SH arrays (sh_rest holds degree {self.sh_degree})")
        self.active_sh_degree = 0

    # ----------------------------------------------------------------- views
    def __len__(self) -> int:
        return self.params["means"].shape[0]

    @property
    def num_gaussians(self) -> int:
        return len(self)

    @property
    def sh_degree(self) -> int:
        return sh_degree_from_bases(self.params["sh_rest"].shape[1] + 1)

    @property
    def means(self) -> mx.array:
        return self.params["means"]

    @property
    def scales(self) -> mx.array:
        """(N,3) standard deviations (exp of the raw log scales)."""
        from ..render import activation

        return activation.exp(self.params["scales"])

    @property
    def quats(self) -> mx.array:
        """(N,4) unit quaternions w,x,y,z."""
        q = self.params["quats"]
        return q / mx.maximum(mx.linalg.norm(q, axis=-1, keepdims=True), 1e-12)

    @property
    def opacities(self) -> mx.array:
        """(N,) opacities in (0, 1) (sigmoid of the logits)."""
        from ..render import activation

        return activation.sigmoid(self.params["opacities"])

    @property
    def scales_act(self) -> mx.array:
        """mlx3D's name for ``scales``: (N,3) standard deviations."""
        return self.scales

    @property
    def opacities_act(self) -> mx.array:
        """mlx3D's name for ``opacities``: (N,) opacities in (0, 1)."""
        return self.opacities

    def one_up_sh_degree(self) -> None:
        """Raise ``active_sh_degree`` by one, up to ``sh_degree`` (mlx3D's SH schedule step)."""
        if self.active_sh_degree < self.sh_degree:
            self.active_sh_degree += 1

    @property
    def sh(self) -> mx.array:
        """(N,K,3) all SH coefficients."""
        return mx.concatenate([self.params["sh_dc"], self.params["sh_rest"]], axis=1)

    @property
    def colors(self) -> mx.array:
        """(N,3) view-independent base colour (from the DC term)."""
        return sh_to_rgb(self.params["sh_dc"][:, 0, :])

    def __repr__(self) -> str:
        return f"GaussianModel(n={len(self)}, sh_degree={self.sh_degree}, active_sh_degree={self.active_sh_degree}, extra={list(self.extra)})"

    # ----------------------------------------------------------- conversion
    @classmethod
    def from_arrays(cls, arrays: SplatArrays) -> "GaussianModel":
        """Model from plain numpy arrays (as read from a PLY file); every SH degree active."""
        model = cls({k: mx.array(np.ascontiguousarray(getattr(arrays, k), dtype=np.float32)) for k in PARAM_NAMES}, arrays.extra)
        model.active_sh_degree = model.sh_degree
        return model

    def to_arrays(self, copy: bool = True) -> SplatArrays:
        """The raw parameters and extras as numpy arrays; ``copy=False`` returns
        read-only views of the MLX buffers (for writing them out)."""
        mx.eval(*self.params.values())
        if copy:
            return SplatArrays(**{k: np.array(self.params[k], dtype=np.float32) for k in PARAM_NAMES}, extra={k: v.copy() for k, v in self.extra.items()})
        views = {}
        for k in PARAM_NAMES:
            views[k] = np.asarray(self.params[k])
            views[k].flags.writeable = False
        return SplatArrays(**views, extra=dict(self.extra))

    @classmethod
    def load_ply(cls, path, sh_degree: int | None = 3, nonfinite: str = "error") -> "GaussianModel":
        """Read a 3DGS PLY file with the file's SH degree, all of it active
        (``active_sh_degree == sh_degree``), as mlx3D does: there the degree is
        inferred from the file whenever it differs from ``sh_degree``, so the
        argument never changes the result (use ``with_sh_degree`` or
        ``compact(target_sh_degree=...)`` to pad or truncate). ``nonfinite`` is
        'error', 'drop' or 'keep' for rows with NaN/Inf. Raises
        ``PlyFormatError`` for bad files."""
        if sh_degree is not None and not isinstance(sh_degree, numbers.Integral):
            raise ValueError(f"sh_degree must be an int or None, got {sh_degree!r}")
        return cls.from_arrays(read_splat_ply(path, sh_degree=None, nonfinite=nonfinite))

    def save_ply(self, path) -> None:
        """Write a standard binary 3DGS PLY (atomically; extras kept)."""
        write_splat_ply(path, self.to_arrays(copy=False))

    @classmethod
    def load(cls, path, nonfinite: str = "error") -> "GaussianModel":
        """Read a splat file of any format :func:`mlx3d.io.read_splats` reads
        (recognised by content), SH degree as stored, all of it active."""
        return cls.from_arrays(read_splats(path, nonfinite=nonfinite))

    def save(self, path, sh_degree: int | None = None) -> None:
        """Write the format the extension of ``path`` names (``.ply``, ``.spz``,
        ``.compressed.ply``, ``.sog``, ``.splat``, ``.glb``; see
        :func:`mlx3d.io.write_splats`), atomically."""
        write_splats(path, self.to_arrays(copy=False), sh_degree=sh_degree)

    # -------------------------------------------------------- construction
    @classmethod
    def from_points(
        cls,
        points,
        colors=None,
        sh_degree: int = 3,
        initial_opacity: float = 0.1,
        scale_init_max_ref: int = 10000,
        scale_init_chunk_size: int = 1024,
        scale_init_max_scale: float | None = None,
        seed: int = 0,
    ) -> "GaussianModel":
        """Isotropic Gaussians at ``points`` (N,3).

        colors: (N,3) RGB in [0,1] (floats) or 0..255 (uint8); grey when None.
        Each scale is the mean distance to the 3 nearest other points among
        at most ``scale_init_max_ref`` reference points (a seeded random
        subset), computed ``scale_init_chunk_size`` queries at a time, then
        capped at ``scale_init_max_scale`` when given.
        """
        from ..neighbors import mean_knn_distance

        pts = np.ascontiguousarray(np.asarray(points), dtype=np.float32)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"points must have shape (N, 3), got {pts.shape}")
        n = pts.shape[0]
        if n < 2:
            raise ValueError(f"from_points needs at least 2 points to size the Gaussians, got {n}")
        bad = ~np.isfinite(pts).all(axis=1)
        if bad.any():
            raise ValueError(f"points contain NaN/Inf in {int(bad.sum())} rows (first row {int(np.argmax(bad))})")
        if not 0.0 < initial_opacity < 1.0:
            raise ValueError(f"initial_opacity must be in (0, 1), got {initial_opacity}")
        if scale_init_max_ref < 2:
            raise ValueError(f"scale_init_max_ref must be >= 2, got {scale_init_max_ref}")
        if colors is None:
            rgb = np.full((n, 3), 0.5, np.float32)
        else:
            c = np.asarray(colors)
            if c.shape != (n, 3):
                raise ValueError(f"colors must have shape ({n}, 3), got {c.shape}")
            rgb = c.astype(np.float32) / 255.0 if np.issubdtype(c.dtype, np.integer) else c.astype(np.float32)

        if n > scale_init_max_ref:
            ref_rows = np.sort(np.random.default_rng(seed).choice(n, scale_init_max_ref, replace=False))
        else:
            ref_rows = np.arange(n)
        reference_index = np.full(n, -1, np.int64)
        reference_index[ref_rows] = np.arange(ref_rows.size)
        k = min(3, ref_rows.size - 1)
        dist = mean_knn_distance(pts[ref_rows], k, queries=pts, reference_index=reference_index, chunk_size=scale_init_chunk_size)
        dist = np.maximum(dist, 1e-7)
        if scale_init_max_scale is not None:
            dist = np.minimum(dist, scale_init_max_scale)
        log_scale = np.repeat(np.log(dist)[:, None], 3, axis=1)

        quats = np.zeros((n, 4), np.float32)
        quats[:, 0] = 1.0
        logit = math.log(initial_opacity / (1.0 - initial_opacity))
        params = {
            "means": pts,
            "scales": log_scale.astype(np.float32),
            "quats": quats,
            "opacities": np.full(n, logit, np.float32),
            "sh_dc": np.asarray(rgb_to_sh(rgb), np.float32)[:, None, :],
            "sh_rest": np.zeros((n, num_sh_bases(sh_degree) - 1, 3), np.float32),
        }
        return cls({k: mx.array(v) for k, v in params.items()})

    # ------------------------------------------------------- row operations
    def copy(self) -> "GaussianModel":
        """Independent copy (MLX arrays are immutable, so parameters are shared safely)."""
        out = GaussianModel(dict(self.params), {k: v.copy() for k, v in self.extra.items()})
        out.active_sh_degree = self.active_sh_degree
        return out

    def select(self, keep_idx) -> "GaussianModel":
        """Keep rows given by a boolean mask (N,) or integer indices, in place; returns self."""
        idx = _as_index(keep_idx, len(self))
        midx = mx.array(idx)
        self.params = {k: v[midx] for k, v in self.params.items()}
        self.extra = {k: v[idx] for k, v in self.extra.items()}
        return self

    def append(self, new_params: dict, extra: dict | None = None) -> "GaussianModel":
        """Append rows in place (same SH degree); extras missing from ``extra`` are zero-filled. Returns self."""
        if set(new_params) != set(PARAM_NAMES):
            raise ValueError(f"append needs exactly the params {list(PARAM_NAMES)}, got {sorted(new_params)}")
        other = GaussianModel(new_params, None)
        if other.sh_degree != self.sh_degree:
            raise ValueError(f"append: SH degree {other.sh_degree} does not match the model's {self.sh_degree}")
        m = len(other)
        extra = extra or {}
        unknown = set(extra) - set(self.extra)
        if unknown:
            raise ValueError(f"append: extra properties {sorted(unknown)} are not in the model")
        for name, values in self.extra.items():
            add = np.asarray(extra[name], values.dtype) if name in extra else np.zeros(m, values.dtype)
            if add.shape != (m,):
                raise ValueError(f"append: extra '{name}' must have shape ({m},), got {add.shape}")
            self.extra[name] = np.concatenate([values, add])
        self.params = {k: mx.concatenate([self.params[k], other.params[k]], axis=0) for k in PARAM_NAMES}
        return self

    def importance(self) -> np.ndarray:
        """(N,) float32 ``sigmoid(opacity) * max(scale)²``: how much a splat covers."""
        score = mx.sigmoid(self.params["opacities"]) * mx.exp(2.0 * mx.max(self.params["scales"], axis=1))
        return np.array(score, dtype=np.float32)

    def compact(self, min_opacity: float = 0.0, max_gaussians: int | None = None, target_sh_degree: int | None = None) -> "GaussianModel":
        """A smaller copy: drop splats with opacity below ``min_opacity``, keep the
        ``max_gaussians`` most important (see ``importance``), truncate SH to
        ``target_sh_degree``. Kept rows stay in their original order; never empty
        (the most important splat is kept); the model itself is unchanged."""
        if max_gaussians is not None and max_gaussians < 1:
            raise ValueError(f"max_gaussians must be >= 1, got {max_gaussians}")
        if target_sh_degree is not None and target_sh_degree > self.sh_degree:
            raise ValueError(f"target_sh_degree {target_sh_degree} exceeds the model's SH degree {self.sh_degree}")
        score = self.importance()
        opacity = np.array(self.opacities)
        keep = np.flatnonzero(opacity >= min_opacity)
        if keep.size == 0:
            keep = np.array([int(np.argmax(score))])
        if max_gaussians is not None and keep.size > max_gaussians:
            # stable sort on -score: ties keep the earlier row
            top = np.argsort(-score[keep], kind="stable")[:max_gaussians]
            keep = np.sort(keep[top])
        out = self.copy().select(keep)
        if target_sh_degree is not None:
            out.params["sh_rest"] = resize_sh_rest(out.params["sh_rest"], target_sh_degree)
            out.active_sh_degree = min(out.active_sh_degree, target_sh_degree)
        return out

    def with_sh_degree(self, degree: int) -> "GaussianModel":
        """A copy with SH truncated or zero-padded to ``degree`` (``active_sh_degree`` capped at it)."""
        out = self.copy()
        out.params["sh_rest"] = resize_sh_rest(out.params["sh_rest"], degree)
        out.active_sh_degree = min(out.active_sh_degree, degree)
        return out

    # ------------------------------------------------------------ density control
    def densify_and_prune(
        self, grad_accum, grad_count, grad_threshold: float = 0.0002, scene_extent: float = 1.0, percent_dense: float = 0.01,
        min_opacity: float = 0.005, return_optimizer_state: bool = False, optimizer=None, **kwargs,
    ) -> dict:
        """Clone/split/prune in place (see ``mlx3d.training.density``); returns the counts
        ``{'cloned', 'split', 'pruned'}``.

        With ``return_optimizer_state`` (mlx3D) the dict also holds the new row
        layout for per-row optimizer state: ``'_keep_idx'`` (int32 numpy, the old
        rows that survive, in order; they are the model's first rows) and
        ``'_new_count'`` (the new rows after them), so moments carry over as
        ``concatenate([m[_keep_idx], zeros(_new_count)])``. ``optimizer`` (an
        ``mlx3d.training.Adam``) has its moments edited in step instead; other
        keywords go to ``mlx3d.training.density.densify_and_prune``. Rows change,
        so extra PLY properties cannot follow: they are dropped with a warning."""
        from ..training.density import densify_and_prune

        layout = _RowLayout(len(self), optimizer)
        self.params, counts = densify_and_prune(
            self.params, grad_accum, grad_count, grad_threshold, scene_extent, percent_dense, min_opacity, optimizer=layout, **kwargs
        )
        self._drop_extra("densify_and_prune")
        if return_optimizer_state:
            counts["_keep_idx"], counts["_new_count"] = layout.result()
        return counts

    def relocate_mcmc(
        self, grad_accum, grad_count, relocate_frac: float = 0.02, min_opacity: float = 0.01, jitter_scale: float = 0.25,
        *, optimizer=None, rng: np.random.Generator | None = None,
    ) -> dict:
        """Fixed-budget relocation of underused Gaussians (mlx3D's MCMC-style density step), in place.

        N stays the same. Up to ``int(relocate_frac · N)`` rows (at most N - 1)
        are replaced: the underused ones — opacity below ``min_opacity`` or never
        visible (``grad_count <= 0``), most transparent first — and, when there
        are none, the most transparent rows. Each takes a copy of a distinct
        source among the other rows, highest mean gradient ``grad_accum /
        max(grad_count, 1)`` first (cycling through them when fewer remain), with
        opacity reset to 0.05, scales divided by 1.6 and its centre moved by
        ``jitter_scale`` times a normal sample of the source's Gaussian (its
        rotated standard deviations; ``rng`` or MLX's global random state).
        Sources are unchanged; extra PLY properties are copied with the rows.
        ``optimizer`` (an ``mlx3d.training.Adam``) has the moved rows' moments
        zeroed. Returns ``{'relocated': count, '_moved_idx': int32 mx.array of
        the replaced rows}`` (only ``{'relocated': 0}`` when nothing moves).
        """
        from ..transforms import quaternion_to_matrix

        n = len(self)
        budget = int(min(max(float(relocate_frac), 0.0), 1.0) * n)
        if budget <= 0 or n <= 1:
            return {"relocated": 0}
        accum = np.asarray(grad_accum, dtype=np.float64).reshape(-1)
        count = np.asarray(grad_count, dtype=np.float64).reshape(-1)
        if accum.shape != (n,) or count.shape != (n,):
            raise ValueError(f"grad_accum and grad_count must have shape ({n},), got {accum.shape} and {count.shape}")
        mean_grad = accum / np.maximum(count, 1.0)
        logits = np.array(self.params["opacities"], dtype=np.float64)
        opacity = 1.0 / (1.0 + np.exp(-logits))
        underused = (opacity < min_opacity) | (count <= 0)
        k = budget if not underused.any() else min(budget, int(underused.sum()))
        k = min(k, n - 1)
        # destinations: underused rows first, then by opacity (ascending), then by index
        dst = np.lexsort((np.arange(n), opacity, ~underused))[:k]
        others = np.setdiff1d(np.arange(n), dst)
        ranked = others[np.argsort(-mean_grad[others], kind="stable")]
        src = ranked[np.arange(k) % ranked.size]

        out = {name: np.array(v) for name, v in self.params.items()}
        for arr in out.values():
            arr[dst] = arr[src]
        out["opacities"][dst] = math.log(0.05 / 0.95)
        out["scales"][dst] -= math.log(1.6)
        if jitter_scale > 0:
            std = np.exp(np.array(self.params["scales"], dtype=np.float64)[src])
            noise = rng.normal(size=(k, 3)) if rng is not None else np.array(mx.random.normal((k, 3)), dtype=np.float64)
            rot = quaternion_to_matrix(np.array(self.params["quats"], dtype=np.float64)[src])
            offset = np.einsum("nij,nj->ni", rot, noise * std) * float(jitter_scale)
            out["means"][dst] = (np.array(self.params["means"], dtype=np.float64)[src] + offset).astype(out["means"].dtype)
        self.params = {name: mx.array(v) for name, v in out.items()}
        for name, values in self.extra.items():
            values = values.copy()
            values[dst] = values[src]
            self.extra[name] = values
        if optimizer is not None:
            for name in self.params:
                optimizer.reset_rows(name, dst)
        return {"relocated": int(k), "_moved_idx": mx.array(dst.astype(np.int32))}

    def reset_opacities(self, max_opacity: float = 0.01, optimizer=None) -> None:
        """Clamp opacities to at most ``max_opacity`` (3DGS's periodic reset), in place."""
        from ..training.density import reset_opacities

        self.params = reset_opacities(self.params, optimizer, max_opacity)

    def _drop_extra(self, why: str) -> None:
        if self.extra:
            warnings.warn(f"{why}: extra properties {sorted(self.extra)} dropped (rows changed)", stacklevel=3)
        self.extra = {}

    # ------------------------------------------------------------ surfels and meshes
    def apply_2dgs_constraints(self, max_thickness: float) -> None:
        """Clamp the third local scale (local z) to at most ``max_thickness`` (scene units), in place.

        Each Gaussian becomes an oriented disc whose normal is its local z axis;
        the file stays a standard 3DGS PLY (a flat ellipsoid)."""
        if not max_thickness > 0:
            raise ValueError(f"max_thickness must be > 0, got {max_thickness}")
        log_scales = self.params["scales"]
        thin = mx.minimum(log_scales[:, 2:], math.log(max_thickness))
        self.params["scales"] = mx.concatenate([log_scales[:, :2], thin], axis=1)

    def _surfels(self, min_opacity, max_points, orient_towards, normal_axis: str, keep_one: bool):
        """Rows kept as surfels and their float64 (points, normals, opacity · disc scale product)."""
        from ..transforms import quaternion_to_matrix

        if max_points is not None and max_points < 1:
            raise ValueError(f"max_points must be >= 1, got {max_points}")
        if normal_axis not in ("z", "thinnest"):
            raise ValueError(f"normal_axis must be 'z' or 'thinnest', got {normal_axis!r}")
        n = len(self)
        opacity = np.array(self.opacities, dtype=np.float64)
        scales = np.exp(np.array(self.params["scales"], dtype=np.float64))
        rows = np.arange(n)
        # the normal axis: local z, or the smallest scale (ties go to z, then y)
        axis = np.full(n, 2) if normal_axis == "z" else 2 - np.argmin(scales[:, ::-1], axis=1)
        disc = scales[rows, (axis + 1) % 3] * scales[rows, (axis + 2) % 3]
        score = opacity * disc
        keep = np.flatnonzero(opacity >= min_opacity)
        if keep.size == 0 and keep_one and n:
            keep = np.array([int(np.argmax(score))])
        if max_points is not None and keep.size > max_points:
            keep = keep[np.sort(np.argsort(-score[keep], kind="stable")[:max_points])]
        points = np.array(self.means, dtype=np.float64)[keep]
        rot = quaternion_to_matrix(np.array(self.params["quats"], dtype=np.float64)[keep])
        normals = rot[np.arange(keep.size), :, axis[keep]]
        if orient_towards is not None:
            towards = _directions_towards(points, orient_towards)
            normals *= np.where(np.sum(normals * towards, axis=1) < 0, -1.0, 1.0)[:, None]
        return keep, points, normals, score[keep]

    def surfel_points(self, min_opacity: float = 0.01, max_points: int | None = None, orient_towards=None) -> tuple[mx.array, mx.array]:
        """Oriented samples at the surfels' centres (mlx3D): ``(points, normals)``, (M,3) float32 MLX arrays.

        Each Gaussian is a disc (2DGS): its normal is its own local z axis, the
        first two scales span it. Rows with opacity below ``min_opacity`` are
        dropped (if that drops all, the one with the largest opacity · s_x · s_y
        is kept); with ``max_points`` the largest opacity · s_x · s_y are kept.
        Rows keep the model's order. ``orient_towards`` flips normals to face a
        point (3,) — or, an mlx3d addition, the nearest of several positions
        (C,3), e.g. the training cameras' centres; None keeps each surfel's own
        normal. For our own mesher's samples (thinnest axis, areas, colours)
        see ``surfel_samples``.
        """
        _, points, normals, _ = self._surfels(min_opacity, max_points, orient_towards, "z", keep_one=True)
        return mx.array(points.astype(np.float32)).reshape(-1, 3), mx.array(normals.astype(np.float32)).reshape(-1, 3)

    def surfel_samples(self, min_opacity: float = 0.01, max_points: int | None = None, orient_towards=None, normal_axis: str = "thinnest"):
        """Oriented, weighted, coloured samples for surface reconstruction (numpy).

        Each Gaussian is read as a disc: its normal is the axis of its smallest
        scale (``normal_axis='thinnest'``; local z for a surfel, ties go to z) or
        always local z (``'z'``, as ``surfel_points``), its area π·s_a·s_b from
        the two other scales. Rows with opacity below ``min_opacity`` are dropped
        (none may remain); with ``max_points`` the highest opacity·s_a·s_b are
        kept, in model order. ``orient_towards``: as ``surfel_points`` (a point,
        or the nearest of (C,3) positions); None keeps each disc's own normal.

        Returns ``(points (M,3) float32, normals (M,3) float32 unit,
        weights (M,) float32 = opacity · disc area in scene units²,
        colors (M,3) float32 base colour in [0,1])``.
        """
        keep, points, normals, score = self._surfels(min_opacity, max_points, orient_towards, normal_axis, keep_one=False)
        colors = np.clip(np.array(self.colors, dtype=np.float64)[keep], 0.0, 1.0)
        f32 = lambda a: np.ascontiguousarray(a, dtype=np.float32)  # noqa: E731
        return f32(points.reshape(-1, 3)), f32(normals.reshape(-1, 3)), f32(math.pi * score), f32(colors.reshape(-1, 3))

    def _mesh_samples(self, min_opacity, max_points, orient_towards, normal_axis):
        from ..meshing import MeshingError

        samples = self.surfel_samples(min_opacity, max_points, orient_towards, normal_axis)
        if samples[0].shape[0] == 0:
            raise MeshingError(f"no Gaussian has opacity >= {min_opacity} (of {len(self)}); nothing to mesh")
        return samples

    def surface_mesh(
        self, resolution: int = 64, padding: float = 0.1, min_opacity: float = 0.01, max_points: int | None = 200_000,
        orient_towards=None, trim: float | None = DEFAULT_TRIM, progress=None, normal_axis: str = "thinnest",
    ):
        """A triangle mesh of the surface the Gaussians describe, as a ``mlx3d.meshing.SurfaceMesh``.

        Poisson reconstruction (``mlx3d.meshing.reconstruct_surface``) of
        ``surfel_samples(min_opacity, max_points, orient_towards, normal_axis)``,
        weighted by their areas, on a ``resolution``³ grid over their bounding
        box plus ``padding``; faces farther than ``trim`` voxels from every
        sample are removed (None or 0 keeps all); vertex colours from the
        nearest samples. In the model's frame and units. Raises
        ``MeshingError`` when no Gaussian is opaque enough.
        ``progress(done, total)`` may raise to cancel.
        """
        from ..meshing import reconstruct_surface

        points, normals, weights, colors = self._mesh_samples(min_opacity, max_points, orient_towards, normal_axis)
        return reconstruct_surface(points, normals, weights, colors, resolution=resolution, padding=padding, trim=trim, progress=progress)

    def fused_mesh(
        self, cameras=None, resolution: int = 128, voxel_size: float | None = None, truncation: float | None = None,
        depth: str = "median", min_alpha: float = 0.5, cleanup: float = 0.01, progress=None, bounds=None,
    ):
        """A triangle mesh by depth fusion, as a ``mlx3d.meshing.SurfaceMesh`` with vertex colours.

        Renders depth (``'median'`` or ``'expected'``, see ``mlx3d.meshing.fusion.depth_views``; pixels
        covered less than ``min_alpha`` are empty) and colour from ``cameras`` (e.g. the training cameras;
        None: 60 views on a spiral around the model, ``mlx3d.meshing.fusion.orbit_cameras``), fuses the depths into a truncated signed
        distance volume (``mlx3d.meshing.fuse_depth_maps``: over ``bounds``, (2, 3) min and max corners, the mesh
        ending at its walls, default the surfaces the views share; ``resolution`` voxels along its longest side unless ``voxel_size``;
        ``truncation`` in scene units, default 4 voxels) and extracts its
        zero level; space no camera saw stays empty. Pieces of fewer faces than ``cleanup`` times the largest
        piece's are dropped (0 keeps all). In the model's frame and units. ``progress(done, total)`` may raise
        to cancel. Raises ``MeshingError`` when the cameras see no surface.
        """
        from ..meshing.fusion import depth_views, fuse_depth_maps, keep_large_components, orbit_cameras, require_surface

        cameras = orbit_cameras(self) if cameras is None else list(cameras)
        count = len(cameras)
        report = None if progress is None else (lambda offset: lambda done, total: progress(offset + done, 3 * count))
        views = depth_views(self, cameras, depth, min_alpha, progress=None if report is None else report(0))
        require_surface(views, min_alpha)
        mesh = fuse_depth_maps(views, resolution, voxel_size, truncation, bounds, progress=None if report is None else report(count))
        return keep_large_components(mesh, cleanup) if cleanup else mesh

    def extract_surface_mesh(
        self, resolution: int = 64, padding: float = 0.1, min_opacity: float = 0.01, max_points: int | None = 200_000,
        orient_towards=None, *, trim: float | None = DEFAULT_TRIM, progress=None, normal_axis: str = "thinnest",
    ):
        """A mesh of the surface the Gaussians describe, as a one-mesh ``mlx3d.structures.Meshes`` (mlx3D).

        ``mlx3d.ops.poisson_reconstruction`` of the oriented samples of
        ``surfel_samples`` (normal: the thinnest axis, which is local z for
        surfels; weighted by disc area; vertex colours in
        ``verts_colors_list()``); otherwise as ``surface_mesh``, which returns
        the same mesh as a ``SurfaceMesh``. A script that replaces
        ``mlx3d.ops.poisson_reconstruction`` gets mlx3D's call:
        ``(points, normals, resolution=, padding=)``, MLX arrays (M, 3). Raises ``MeshingError`` (a
        ``ValueError``) when no Gaussian is opaque enough or the grid is invalid.
        """
        from .. import ops
        from ..ops.geometry import poisson_reconstruction

        points, normals, weights, colors = self._mesh_samples(min_opacity, max_points, orient_towards, normal_axis)
        if ops.poisson_reconstruction is poisson_reconstruction:
            return poisson_reconstruction(points, normals, resolution, padding, weights=weights, colors=colors, trim=trim, progress=progress)
        # a substitute (a script's own mlx3d.ops.poisson_reconstruction) gets mlx3D's arguments and only those
        return ops.poisson_reconstruction(mx.array(points), mx.array(normals), resolution=resolution, padding=padding)

    # ------------------------------------------------------------ rendering
    def render(self, camera, background=None, antialias: bool = False, projection: str = "auto", render_depth: bool = False, sh_degree: int | None = None, **kwargs) -> dict:
        """Render from ``camera`` with SH colour up to ``sh_degree`` (default: the model's
        ``sh_degree``; mlx3D renders ``active_sh_degree``, pass ``sh_degree=model.active_sh_degree``
        for that). Returns ``mlx3d.render.render_gaussians``' dict (image, alpha, depth, ...)."""
        from ..render import render_gaussians

        return render_gaussians(
            camera, self.means, self.quats, self.scales, self.opacities, sh=(self.params["sh_dc"], self.params["sh_rest"]),
            sh_degree=self.sh_degree if sh_degree is None else sh_degree, background=background,
            antialias=antialias, projection=projection, render_depth=render_depth, **kwargs,
        )

    def render_depth(self, camera, antialias: bool = False, projection: str = "auto", **kwargs) -> dict:
        """Expected depth from ``camera`` (mlx3D's method): ``render_gaussians``' dict with
        ``depth`` (H,W) (camera z, alpha-normalised, 0 where nothing is hit) and ``alpha``."""
        from ..render import render_gaussians

        return render_gaussians(
            camera, self.means, self.quats, self.scales, self.opacities, colors=mx.zeros((len(self), 3)),
            antialias=antialias, projection=projection, render_depth=True, **kwargs,
        )

    def render_features(self, camera, features, background=None, normalize: bool = False, antialias: bool = False, projection: str = "auto", **kwargs):
        """Composited per-Gaussian ``features`` (N,F): what ``mlx3d.render.render_gaussian_features`` returns."""
        from ..render import render_gaussian_features

        return render_gaussian_features(
            camera, self.means, self.quats, self.scales, self.opacities, features, background=background,
            normalize=normalize, antialias=antialias, projection=projection, **kwargs,
        )

    # ------------------------------------------------------------ transform
    def transform(self, matrix) -> "GaussianModel":
        """A copy with the 4x4 affine ``matrix`` applied (see ``ops.transform_splats``).
        ``a.transform(A).transform(B)`` equals ``a.transform(B @ A)``."""
        out = GaussianModel.from_arrays(transform_splats(self.to_arrays(copy=False), matrix))
        out.active_sh_degree = min(self.active_sh_degree, out.sh_degree)
        return out


def merge(models: Sequence[GaussianModel] | Iterable[GaussianModel], sh_degree: int | None = None) -> GaussianModel:
    """One model from several, rows concatenated in order (see ``ops.merge_splats``:
    SH padded to the highest degree or set to ``sh_degree``, extras unioned)."""
    return GaussianModel.from_arrays(merge_splats([m.to_arrays(copy=False) for m in models], sh_degree))
