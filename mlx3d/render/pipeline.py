"""The render entry: plan the stages a call needs, then project, bin and rasterize.

Effects on demand: ``plan_render`` decides from the scene, camera and options
which stages run — EWA or unscented projection (UT only for cameras EWA cannot
represent, or when asked), SH evaluation only up to the degree present and
none for plain colours, the geometry channels (depth, depth², normals) only
when asked, the antialiasing compensation only when asked, a surface layer
composited as a background image when it has no finite depth and depth-tested
otherwise (``surface``) — and
``render_gaussians`` returns that plan and the stages it actually ran, so tests
and benchmarks can see the decision. Every channel asked for is composited in
the same rasterization pass as the colour.

All inputs are activated values: scales are standard deviations, opacities in
[0, 1], quaternions any length (normalised inside).

The render functions keep the original mlx3D signatures (positional order and
defaults, except ``projection='auto'``, which is EWA for every camera EWA can
represent) and dict results; our options are keyword-only and our extra
results are extra keys.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mlx.core as mx
import numpy as np

from ..splatting.sh import MAX_SH_DEGREE
from . import geometry_channels
from .binning import TILE_SIZE, Bins, bin_tiles
from .projection import project_ewa, project_ut
from .rasterize import BACKENDS, CHUNK_SIZE, composite, composite_features, resolve_backend
from .sh_color import num_coefficients, sh_colors
from .surface import Surface, composite_surface, surface_mode, surface_stages

PROJECTIONS = ("auto", "ewa", "ut")

__all__ = [
    "BACKENDS",
    "PROJECTIONS",
    "RenderPlan",
    "plan_render",
    "render_gaussian_depth",
    "render_gaussian_features",
    "render_gaussian_median_depth",
    "render_gaussians",
    "render_gaussians_reference",
    "resolve_backend",
]


@dataclass(frozen=True)
class RenderPlan:
    """Which stages a render runs. ``stages`` lists them in order."""

    projection: str  # 'ewa' | 'ut'
    sh_degree: int | None  # SH degree evaluated; None when plain colours are given
    depth: bool
    antialias: bool
    backend: str
    depth_variance: bool = False  # composite inverse depth and its square
    normals: bool = False
    planar_depth: bool = False  # surfel planes instead of centres (see geometry_channels)
    surface: str | None = None  # None | 'behind' | 'depth_test' (see mlx3d.render.surface)

    @property
    def channels(self) -> tuple:
        """Composited channel groups in order: rgb (3), depth (1, planes 3), depth2 (2: 1/z and its square), normals (3)."""
        planes = "_planes" if self.planar_depth else ""
        out = ["rgb"]
        if self.depth:
            out.append("depth" + planes)
        if self.depth_variance:
            out.append("depth2")
        if self.normals:
            out.append("normals")
        return tuple(out)

    @property
    def stages(self) -> tuple:
        out = [f"project_{self.projection}"]
        if self.antialias:
            out.append("antialias_compensation")
        out.append("bin_tiles")
        if self.sh_degree is not None:
            out.append(f"eval_sh_degree_{self.sh_degree}")
        if self.normals or self.planar_depth:
            out.append("gaussian_normals")
        out.extend(surface_stages(self.surface, self.backend, "rasterize_" + "+".join(self.channels)))
        return tuple(out)


def _projection_method(camera, projection: str) -> str:
    """'ewa' or 'ut' for ``projection`` ('auto': UT only where EWA cannot represent the camera)."""
    if projection not in PROJECTIONS:
        raise ValueError(f"projection must be one of {PROJECTIONS}, got {projection!r}")
    if projection == "ewa" and camera.needs_ut:
        raise ValueError(f"a {camera.model!r} camera needs projection='ut' (EWA assumes an undistorted pinhole camera)")
    return "ut" if projection == "ut" or (projection == "auto" and camera.needs_ut) else "ewa"


def _sh_degree_present(num_bases: int) -> int:
    """Highest SH degree whose (degree+1)² coefficients fit in ``num_bases`` (at most 3)."""
    if num_bases < 1:
        raise ValueError(f"sh must have at least one coefficient per channel, got K={num_bases}")
    return min(MAX_SH_DEGREE, math.isqrt(int(num_bases)) - 1)


def plan_render(
    camera, colors=None, sh=None, sh_degree: int = 3, projection: str = "auto", antialias: bool = False, render_depth: bool = False,
    backend: str = "auto", render_depth_variance: bool = False, render_normals: bool = False, planar_depth: bool = False,
    surface: Surface | None = None,
) -> RenderPlan:
    """Decide the stages for a render (see the module docstring); raises ValueError for conflicts."""
    method = _projection_method(camera, projection)
    mode = surface_mode(surface, camera)
    if mode is not None and (render_depth or render_depth_variance or render_normals):
        raise ValueError("render_depth, render_depth_variance and render_normals cannot be combined with surface= (the surface has colour only)")
    if (colors is None) == (sh is None):
        raise ValueError("pass exactly one of colors=(N,3) or sh=(N,K,3)")
    degree = None
    if sh is not None:
        degree = min(int(sh_degree), _sh_degree_present(num_coefficients(sh)))
    depth = bool(render_depth)
    return RenderPlan(
        method, degree, depth, bool(antialias), resolve_backend(backend), bool(render_depth_variance), bool(render_normals),
        bool(planar_depth) and depth, mode,
    )


def _project(camera, means, quats, scales, opacities, method: str, antialias: bool, blur, ran: list, backend: str):
    """Projection ('ewa' or 'ut') and the opacities it leaves (times the antialias compensation)."""
    if method == "ut":
        proj = project_ut(camera, means, quats, scales, blur=blur, antialias=antialias)
    else:
        proj = project_ewa(camera, means, quats, scales, blur=blur, antialias=antialias, backend=backend)
    ran.append(f"project_{method}")
    if antialias:
        opacities = opacities * proj.compensation
        ran.append("antialias_compensation")
    return proj, opacities


def _project_and_bin(camera, means, quats, scales, opacities, method: str, antialias: bool, blur, tile_size, backend: str, ran=None):
    """Projection, antialias compensation, tile binning (extents tightened by the opacities)."""
    ran = [] if ran is None else ran
    proj, opac = _project(camera, means, quats, scales, opacities, method, antialias, blur, ran, backend)
    bins = bin_tiles(proj.means2d, proj.radii, proj.depths, camera.width, camera.height, tile_size, proj.conics, opac, backend)
    ran.append("bin_tiles")
    return proj, opac, bins


def _projection_outputs(proj) -> dict:
    """The per-Gaussian entries of every render result."""
    return {
        "means2d": proj.means2d,
        "conics": proj.conics,
        "depths": proj.depths,
        "radii": proj.radii.astype(mx.float32),
        "compensation": proj.compensation,
        "visible": proj.radii > 0,
    }


def render_gaussians(
    camera,
    means,
    quats,
    scales,
    opacities,
    colors=None,
    sh=None,
    sh_degree: int = 3,
    background=None,
    refine_tiles: bool = False,
    antialias: bool = False,
    projection: str = "auto",
    *,
    render_depth: bool = False,
    backend: str = "auto",
    blur: float = 0.3,
    tile_size: int = TILE_SIZE,
    means2d_offset=None,
    render_depth_variance: bool = False,
    render_normals: bool = False,
    planar_depth: bool = False,
    depth_reference: float | None = None,
    surface: Surface | None = None,
) -> dict:
    """Render Gaussians from ``camera``; differentiable w.r.t. every float input (not with a depth-tested ``surface``).

    The original mlx3D signature: means (N,3), quats (N,4) w,x,y,z, scales
    (N,3) std-devs, opacities (N,) in [0,1]; colour from ``colors`` (N,3) or
    SH ``sh`` (N,K,3) evaluated toward the camera up to ``sh_degree`` (and at
    most the degree K holds), clamped at 0 as in 3DGS (``sh`` may also be the
    pair (sh_dc, sh_rest), which saves concatenating them); background: (3,) or
    None (black); refine_tiles: accepted for compatibility and changes
    nothing (the binning always drops the tiles a Gaussian cannot reach with
    alpha >= 1/255, which leaves the image unchanged); antialias:
    Mip-Splatting opacity compensation; projection: 'ewa', 'ut' or 'auto'
    (the default; EWA for pinhole cameras, as the original's 'ewa', and the
    unscented transform for distorted, fisheye and orthographic cameras,
    which EWA cannot represent; 'ewa' with such a camera raises ValueError).

    Returns a dict: ``image`` (H,W,3), ``alpha`` (H,W), ``final_T`` (H,W) =
    1 - alpha, ``n_contrib`` (H,W) int32, ``means2d`` (N,2), ``conics``
    (N,3), ``depths`` (N,), ``radii`` (N,) float32 (0 = culled),
    ``compensation`` (N,), ``visible`` (N,) bool, ``plan`` and ``stages``
    (what ran), and the geometry asked for, each 0 where nothing is hit:

    - ``render_depth``: ``depth`` (H,W), the alpha-normalised expected camera z;
    - ``render_depth_variance``: ``depth_variance`` (H,W), the alpha-weighted
      variance of the Gaussians' inverse depth 1/z (1/length²) along each
      pixel's ray, the spread 2DGS's depth distortion measures, which a far
      background barely changes (for an orthographic camera, of z: length²;
      computed around ``depth_reference``, default the mean visible depth, to
      keep float32 cancellation small);
    - ``render_normals``: ``normals`` (H,W,3), the alpha-weighted world-space
      local z axes facing the camera (``facing_normals``), normalised to unit
      length;
    - ``planar_depth``: the depth of each Gaussian's plane (a surfel's) instead
      of its centre, see ``geometry_channels``.

    ``surface``: a ``Surface`` (premultiplied colour (H,W,3), alpha, camera-z
    depth) composited with the Gaussians in depth order, before the
    background; ``alpha`` then includes its coverage. Forward-only where it
    has a finite depth (stage ``...+surface_depth_test``, on every
    backend's rasterizer), a background image otherwise (stage ``surface_behind``); not combinable with the geometry
    channels. See ``mlx3d.render.surface``.

    Keyword-only additions: the geometry options above, ``backend`` ('auto',
    'cpu', 'metal', 'mlx', 'reference'; see ``resolve_backend``), ``blur`` (pixels², 0.3), ``tile_size`` and
    ``means2d_offset``: optional (N,2) added to the projected 2D means. Pass
    zeros and differentiate w.r.t. it to get dL/d(means2d), the screen-space
    gradient that density control accumulates.
    """
    del refine_tiles  # see the docstring
    plan = plan_render(
        camera, colors, sh, sh_degree, projection, antialias, render_depth, backend, render_depth_variance, render_normals, planar_depth, surface
    )
    ran = []
    proj, opac, bins = _project_and_bin(camera, means, quats, scales, opacities, plan.projection, plan.antialias, blur, tile_size, plan.backend, ran)
    if plan.sh_degree is not None:
        rgb = sh_colors(sh, means, camera.center, plan.sh_degree, plan.backend)
        ran.append(f"eval_sh_degree_{plan.sh_degree}")
    else:
        rgb = colors
    if plan.depth_variance and depth_reference is None:
        depth_reference = geometry_channels.reference_depth(proj.depths, proj.radii)
    blocks = [rgb] + geometry_channels.pack(plan, camera, means, quats, proj, depth_reference)
    if plan.normals or plan.planar_depth:
        ran.append("gaussian_normals")
    features = mx.concatenate(blocks, axis=1) if len(blocks) > 1 else rgb
    means2d = proj.means2d if means2d_offset is None else proj.means2d + means2d_offset
    bg = None
    if background is not None:
        bg = mx.array(background, dtype=mx.float32)
        if features.shape[1] > 3:
            bg = mx.concatenate([bg, mx.zeros((features.shape[1] - 3,))])
    if plan.surface is None:
        accum, alpha, last = composite(means2d, proj.conics, features, opac, bins, camera.width, camera.height, bg, plan.backend)
    else:
        accum, alpha, last = composite_surface(
            means2d, proj.conics, features, opac, proj.depths, bins, camera.width, camera.height, surface, plan.surface, bg, plan.backend
        )
    ran.extend(surface_stages(plan.surface, plan.backend, "rasterize_" + "+".join(plan.channels)))
    out = {"image": accum[..., :3], "alpha": alpha, "final_T": 1.0 - alpha, "n_contrib": last}
    out.update(_projection_outputs(proj))
    out.update({"plan": plan, "stages": tuple(ran)})
    out.update(geometry_channels.unpack(plan, camera, accum, alpha))
    return out


def render_gaussian_features(
    camera,
    means,
    quats,
    scales,
    opacities,
    features,
    background=None,
    normalize: bool = False,
    refine_tiles: bool = False,
    antialias: bool = False,
    projection: str = "auto",
    *,
    backend: str = "auto",
    blur: float = 0.3,
    tile_size: int = TILE_SIZE,
    chunk_size: int = CHUNK_SIZE,
) -> dict:
    """Render arbitrary per-Gaussian features (N,C) with one projection and binning.

    background: None, a scalar or (C,) (ignored with ``normalize``);
    normalize: the alpha-weighted mean of the features (0 where nothing is
    hit) instead of the composite. ``refine_tiles``, ``antialias`` and
    ``projection`` as in ``render_gaussians``.

    Returns ``{"features" (H,W,C), "alpha", "final_T", "n_contrib"}`` plus
    the per-Gaussian ``means2d``, ``conics``, ``depths``, ``radii``,
    ``compensation``, ``visible``. Keyword-only additions: ``backend``,
    ``blur``, ``tile_size``, ``chunk_size`` (channels per rasterizer pass).
    """
    del refine_tiles  # see render_gaussians
    method = _projection_method(camera, projection)
    features = features if isinstance(features, mx.array) else mx.array(features)
    if features.ndim != 2:
        raise ValueError(f"features must have shape (N, C), got {tuple(features.shape)}")
    proj, opac, bins = _project_and_bin(camera, means, quats, scales, opacities, method, bool(antialias), blur, tile_size, resolve_backend(backend))
    out = composite_features(proj.means2d, proj.conics, features, opac, bins, camera.width, camera.height, background, normalize, backend, chunk_size)
    out.update(_projection_outputs(proj))
    return out


def render_gaussian_depth(
    camera,
    means,
    quats,
    scales,
    opacities,
    refine_tiles: bool = False,
    antialias: bool = False,
    projection: str = "auto",
    *,
    backend: str = "auto",
    blur: float = 0.3,
    tile_size: int = TILE_SIZE,
) -> dict:
    """Expected depth: the alpha-normalised camera z of the Gaussians' centres, 0 where nothing is hit.

    Returns ``{"depth" (H,W), "alpha", "final_T", "n_contrib"}`` plus the
    per-Gaussian entries of ``render_gaussian_features``. Differentiable.
    (``render_gaussians(..., render_depth=True)`` composites the depth in the
    colour pass, and can use surfel planes.)
    """
    method = _projection_method(camera, projection)
    proj, opac, bins = _project_and_bin(camera, means, quats, scales, opacities, method, bool(antialias), blur, tile_size, resolve_backend(backend))
    out = composite_features(proj.means2d, proj.conics, proj.depths[:, None], opac, bins, camera.width, camera.height, normalize=True, backend=backend)
    out["depth"] = out.pop("features")[..., 0]
    out.update(_projection_outputs(proj))
    return out


def render_gaussian_median_depth(
    camera,
    means,
    quats,
    scales,
    opacities,
    *,
    planar: bool = False,
    level: float = 0.5,
    iterations: int = 16,
    antialias: bool = False,
    projection: str = "auto",
    backend: str = "auto",
    blur: float = 0.3,
    tile_size: int = TILE_SIZE,
) -> dict:
    """Median depth (2DGS): per pixel, the depth of the Gaussians at which the accumulated opacity first
    reaches ``level``, the front surface even where splats behind it show through. Forward-only.

    The depth-tested composite (``mlx3d.render.surface``) with an opaque surface at depth D gives the
    coverage of the Gaussians in front of D; ``iterations`` bisections of D per pixel find the crossing
    Gaussians' centre depths within (deepest visible centre) / 2^iterations, and the composite between the
    bracket's two ends gives their own depth: their centres', or with ``planar`` their planes' along the
    pixel's ray (surfels, see ``geometry_channels``). Costs ``iterations + 2`` rasterizations of 1 to 4
    channels, after one projection and binning.

    Returns ``{"depth" (H,W) camera z, 0 where the coverage never reaches ``level``; "alpha" (H,W)}``.
    """
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must be in (0, 1), got {level!r}")
    if int(iterations) < 1:
        raise ValueError(f"iterations must be >= 1, got {iterations!r}")
    be = resolve_backend(backend)
    method = _projection_method(camera, projection)
    proj, opac, bins = _project_and_bin(camera, means, quats, scales, opacities, method, bool(antialias), blur, tile_size, be)
    ones = mx.ones((proj.depths.shape[0], 1), dtype=mx.float32)
    if planar:
        normals = geometry_channels.facing_normals(camera, means, quats)
        a, g = geometry_channels.depth_planes(camera, means, normals, mx.where(proj.radii > 0, proj.depths, 1.0), proj.means2d)
        features = mx.concatenate([ones, a[:, None], g], axis=1)
    else:
        features = mx.concatenate([ones, proj.depths[:, None]], axis=1)
    w, h = camera.width, camera.height

    def in_front_of(depth, feats):
        channels = feats.shape[1]
        wall = Surface(mx.zeros((h, w, channels)), mx.ones((h, w)), depth)
        accum, _, _ = composite_surface(proj.means2d, proj.conics, feats, opac, proj.depths, bins, w, h, wall,
                                        surface_mode(wall, camera, channels), None, be)
        return accum

    _, alpha, _ = composite(proj.means2d, proj.conics, ones, opac, bins, w, h, None, be)
    visible = proj.radii > 0
    deepest = float(mx.max(mx.where(visible, proj.depths, 0.0)).item()) if proj.depths.shape[0] else 0.0
    lo = mx.zeros((h, w), dtype=mx.float32)
    hi = mx.full((h, w), deepest * (1.0 + 1e-6) + 1e-6, dtype=mx.float32)
    for _ in range(int(iterations)):
        mid = 0.5 * (lo + hi)
        reached = in_front_of(mid, ones)[..., 0] >= level
        hi, lo = mx.where(reached, mid, hi), mx.where(reached, lo, mid)
        mx.eval(hi, lo)
    between = in_front_of(hi, features) - in_front_of(lo, features)  # the crossing Gaussians' own share
    weight = between[..., 0]
    if planar:
        own = geometry_channels.planes_at_pixels(camera, between[..., 1:4]) / mx.maximum(weight, 1e-12)
    else:
        own = between[..., 1] / mx.maximum(weight, 1e-12)
    depth = mx.where(weight > 1e-6, own, hi)  # a share too small to divide by: the bracket's far end
    return {"depth": mx.where(alpha >= level, depth, 0.0), "alpha": alpha}


def _one_tile(radii, depths, width: int, height: int) -> Bins:
    """Every Gaussian with radius > 0 in one tile covering the image, sorted by depth then index."""
    r = np.asarray(radii)
    ids = np.flatnonzero(r > 0)
    ids = ids[np.argsort(np.asarray(mx.stop_gradient(depths), np.float32)[ids], kind="stable")]
    return Bins(mx.array(np.array([0, ids.size], np.int32)), mx.array(ids.astype(np.int32)), 1, 1, max(int(width), int(height)))


def render_gaussians_reference(
    camera, means, quats, scales, opacities, colors, background=None, antialias: bool = False, *, projection: str = "auto", blur: float = 0.3,
) -> dict:
    """Naive renderer: every projected Gaussian evaluated at every pixel, in global depth order.

    The test oracle for ``render_gaussians`` (same arguments, with colours or
    any (N,C) features as ``colors``; background None, scalar or (C,)). No
    tile binning: one list of all Gaussians with radius > 0 through the
    pure-MLX reference compositor, so it checks the binning and the compiled
    rasterizer at once. O(H·W·N) memory: small scenes only. Without the tiles
    it also keeps the faint (alpha < ~0.01) rim of a Gaussian beyond its
    3-sigma radius that the tiled renderer can cut, so compare with a
    tolerance there. Returns ``{"image" (H,W,C), "alpha", "final_T"}``;
    differentiable by MLX autodiff.
    """
    method = _projection_method(camera, projection)
    proj, opac = _project(camera, means, quats, scales, opacities, method, bool(antialias), blur, [], "reference")
    bins = _one_tile(proj.radii, proj.depths, camera.width, camera.height)
    out = composite_features(proj.means2d, proj.conics, colors, opac, bins, camera.width, camera.height, background, backend="reference")
    return {"image": out["features"], "alpha": out["alpha"], "final_T": out["final_T"]}
