"""The render entry: plan the stages a call needs, then project, bin and rasterize.

Effects on demand: ``plan_render`` decides from the scene, camera and options
which stages run — EWA or unscented projection (UT only for cameras EWA cannot
represent, or when asked), SH evaluation only up to the degree present and
none for plain colours, the geometry channels (depth, depth², normals) only
when asked, the antialiasing compensation only when asked — and
``render_gaussians`` returns that plan and the stages it actually ran, so tests
and benchmarks can see the decision. Every channel asked for is composited in
the same rasterization pass as the colour.

All inputs are activated values: scales are standard deviations, opacities in
[0, 1], quaternions any length (normalised inside).
"""

from __future__ import annotations

from dataclasses import dataclass

import mlx.core as mx

from ..splatting.sh import eval_sh, sh_degree_from_bases
from . import geometry_channels
from .binning import TILE_SIZE, bin_gaussians
from .projection import project_gaussians, project_gaussians_ut

BACKENDS = ("auto", "cpu", "metal", "reference")
PROJECTIONS = ("auto", "ewa", "ut")


def resolve_backend(backend: str) -> str:
    """'auto' -> 'metal' on Apple GPUs, else 'cpu' (the C++ kernel)."""
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if backend == "auto":
        from .raster_metal import metal_available

        return "metal" if metal_available() else "cpu"
    return backend


def rasterize_features(means2d, conics, features, opacities, bins, width: int, height: int, background=None, backend: str = "auto"):
    """Composite (N,C) features of projected, binned Gaussians into (image (H,W,C), alpha (H,W)).

    background: None (black) or (C,) added where the image is not opaque.
    """
    backend = resolve_backend(backend)
    args = (means2d, conics, features, opacities, bins.tile_offsets, bins.flatten_ids, width, height, bins.tile_size)
    if backend == "reference":
        from .raster_reference import rasterize_reference

        accum, alpha = rasterize_reference(*args)
    elif backend == "cpu":
        from .raster_cpu import rasterize_cpu

        accum, alpha, _ = rasterize_cpu(*args)
    else:
        from .raster_metal import rasterize_metal

        accum, alpha, _ = rasterize_metal(*args)
    if background is not None:
        accum = accum + (1.0 - alpha)[..., None] * mx.array(background, dtype=mx.float32)
    return accum, alpha


@dataclass(frozen=True)
class RenderPlan:
    """Which stages a render runs. ``stages`` lists them in order."""

    projection: str  # 'ewa' | 'ut'
    sh_degree: int | None  # SH degree evaluated; None when plain colours are given
    depth: bool
    antialias: bool
    backend: str
    depth_variance: bool = False  # also composite depth² (implies depth)
    normals: bool = False
    planar_depth: bool = False  # surfel planes instead of centres (see geometry_channels)

    @property
    def channels(self) -> tuple:
        """Composited channel groups in order: rgb (3), depth (1, planes 3), depth2 (1, with planar depth 2), normals (3)."""
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
        out.append("rasterize_" + "+".join(self.channels))
        return tuple(out)


def plan_render(
    camera, colors=None, sh=None, sh_degree: int = 3, projection: str = "auto", antialias: bool = False, render_depth: bool = False,
    backend: str = "auto", render_depth_variance: bool = False, render_normals: bool = False, planar_depth: bool = False,
) -> RenderPlan:
    """Decide the stages for a render (see the module docstring); raises ValueError for conflicts."""
    if projection not in PROJECTIONS:
        raise ValueError(f"projection must be one of {PROJECTIONS}, got {projection!r}")
    if projection == "ewa" and camera.needs_ut:
        raise ValueError(f"a {camera.model!r} camera needs projection='ut' (EWA assumes an undistorted pinhole camera)")
    method = "ut" if projection == "ut" or (projection == "auto" and camera.needs_ut) else "ewa"
    if (colors is None) == (sh is None):
        raise ValueError("pass exactly one of colors=(N,3) or sh=(N,K,3)")
    degree = None
    if sh is not None:
        degree = min(int(sh_degree), sh_degree_from_bases(sh.shape[1]))
    variance = bool(render_depth_variance)
    depth = bool(render_depth) or variance
    return RenderPlan(method, degree, depth, bool(antialias), resolve_backend(backend), variance, bool(render_normals), bool(planar_depth) and depth)


def _project_and_bin(camera, means, quats, scales, opacities, plan: RenderPlan, blur, tile_size, ran=None):
    """Projection (EWA or UT per ``plan``), antialias compensation, tile binning."""
    ran = [] if ran is None else ran
    project = project_gaussians_ut if plan.projection == "ut" else project_gaussians
    proj = project(camera, means, quats, scales, blur=blur, antialias=plan.antialias)
    ran.append(f"project_{plan.projection}")
    opac = opacities
    if plan.antialias:
        opac = opacities * proj.compensation
        ran.append("antialias_compensation")
    bins = bin_gaussians(proj.means2d, proj.radii, proj.depths, camera.width, camera.height, tile_size, proj.conics, opac)
    ran.append("bin_tiles")
    return proj, opac, bins


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
    antialias: bool = False,
    projection: str = "auto",
    render_depth: bool = False,
    backend: str = "auto",
    blur: float = 0.3,
    tile_size: int = TILE_SIZE,
    means2d_offset=None,
    render_depth_variance: bool = False,
    render_normals: bool = False,
    planar_depth: bool = False,
    depth_reference: float | None = None,
) -> dict:
    """Render Gaussians from ``camera``; differentiable w.r.t. every float input.

    means (N,3), quats (N,4) w,x,y,z, scales (N,3) std-devs, opacities (N,) in
    [0,1]; colour from ``colors`` (N,3) or SH ``sh`` (N,K,3) evaluated up to
    ``sh_degree`` (clamped at 0 as in 3DGS). background: (3,) or None (black).
    Returns a dict: ``image`` (H,W,3), ``alpha`` (H,W), ``means2d`` (N,2),
    ``conics``, ``radii`` (N,) int32, ``depths`` (N,), ``visible`` (N,) bool,
    ``plan`` and ``stages`` (what ran), and the geometry asked for, each 0
    where nothing is hit:

    - ``render_depth``: ``depth`` (H,W), the alpha-normalised expected camera z;
    - ``render_depth_variance``: also ``depth_variance`` (H,W), the
      alpha-weighted variance of the Gaussians' z along each pixel's ray
      (computed around ``depth_reference``, default the mean visible depth, to
      keep float32 cancellation small);
    - ``render_normals``: ``normals`` (H,W,3), the alpha-weighted world-space
      local z axes facing the camera (``facing_normals``), normalised to unit
      length;
    - ``planar_depth``: the depth of each Gaussian's plane (a surfel's) instead
      of its centre, see ``geometry_channels``.

    means2d_offset: optional (N,2) added to the projected 2D means. Pass zeros
    and differentiate w.r.t. it to get dL/d(means2d), the screen-space
    gradient that density control accumulates.
    """
    plan = plan_render(camera, colors, sh, sh_degree, projection, antialias, render_depth, backend, render_depth_variance, render_normals, planar_depth)
    ran = []
    proj, opac, bins = _project_and_bin(camera, means, quats, scales, opacities, plan, blur, tile_size, ran)
    if plan.sh_degree is not None:
        centre = mx.array(camera.center, dtype=mx.float32)
        rgb = mx.maximum(eval_sh(plan.sh_degree, sh, means - centre), 0.0)
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
    accum, alpha = rasterize_features(means2d, proj.conics, features, opac, bins, camera.width, camera.height, bg, plan.backend)
    ran.append("rasterize_" + "+".join(plan.channels))
    out = {
        "image": accum[..., :3],
        "alpha": alpha,
        "means2d": proj.means2d,
        "conics": proj.conics,
        "radii": proj.radii,
        "depths": proj.depths,
        "visible": proj.radii > 0,
        "plan": plan,
        "stages": tuple(ran),
    }
    out.update(geometry_channels.unpack(plan, camera, accum, alpha, depth_reference))
    return out


def render_gaussian_depth(camera, means, quats, scales, opacities, **kwargs) -> mx.array:
    """(H,W) expected depth (camera z, 0 where nothing is hit)."""
    n = means.shape[0]
    return render_gaussians(camera, means, quats, scales, opacities, colors=mx.zeros((n, 3)), render_depth=True, **kwargs)["depth"]


def render_gaussian_features(
    camera,
    means,
    quats,
    scales,
    opacities,
    features,
    background=None,
    normalize: bool = False,
    antialias: bool = False,
    projection: str = "auto",
    backend: str = "auto",
    blur: float = 0.3,
    tile_size: int = TILE_SIZE,
    chunk_size: int = 16,
) -> mx.array:
    """(H,W,F) arbitrary per-Gaussian features (N,F), rasterized ``chunk_size``
    channels per pass (one projection and binning for all); ``normalize``
    divides by alpha (a weighted mean instead of a weighted sum)."""
    plan = plan_render(camera, colors=features, projection=projection, antialias=antialias, backend=backend)
    proj, opac, bins = _project_and_bin(camera, means, quats, scales, opacities, plan, blur, tile_size)
    parts, alpha = [], None
    for start in range(0, features.shape[1], chunk_size):
        bg = None if background is None else mx.array(background, dtype=mx.float32)[start : start + chunk_size]
        accum, alpha = rasterize_features(proj.means2d, proj.conics, features[:, start : start + chunk_size], opac, bins, camera.width, camera.height, bg, plan.backend)
        parts.append(accum)
    image = mx.concatenate(parts, axis=-1)
    if normalize:
        image = mx.where(alpha[..., None] > 0, image / mx.maximum(alpha[..., None], 1e-10), 0.0)
    return image
