"""Depth maps fused into a triangle mesh: a truncated signed distance volume (numpy).

:func:`fuse_depth_maps` integrates depth maps seen from known cameras into a
volume of truncated signed distances (Curless and Levoy 1996, with
KinectFusion's projective distance) and extracts its zero level with
:func:`.isosurface.marching_tetrahedra`, colouring the vertices from the
views' images. :func:`keep_large_components` removes small islands.

Conventions:

- A :class:`DepthView` holds a :class:`mlx3d.cameras.Camera` and the camera z
  of every pixel (H, W): a finite positive depth is a surface seen there;
  ``inf`` means the pixel sees nothing (its ray is empty: it carves); 0 or NaN
  means the pixel says nothing.
- The signed distance is positive in front of a surface (the cameras' side)
  and negative behind it, stored divided by the truncation distance, in
  [-1, 1]; a node behind a surface by more than the truncation is not updated.
- Only space near a seen surface is stored: the volume is cut into blocks of
  :data:`BLOCK`\\ ³ nodes, and a block exists when some pixel's band (its depth
  plus or minus the truncation, along its ray) passes through it. Every view
  then updates every existing block in front of it. Nodes no view updated are
  unknown, and marching makes no triangle in a cube with an unknown corner, or
  with a corner that is only free space or only behind a surface (``|d| = 1``):
  unseen space stays empty, with no skirt around the seen surface and no blobs
  closing it, and surfaces are where the distance crosses zero between nearby
  observations.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .isosurface import marching_tetrahedra
from .mesh import MeshingError, SurfaceMesh, compact_faces

__all__ = ["BLOCK", "DEPTHS", "DepthView", "FusionGrid", "fuse_depth_maps", "fusion_grid", "keep_large_components"]

#: Nodes per side of a block, the unit in which space is stored.
BLOCK = 8
#: The space meshed by default reaches this many camera extents from the cameras' mean (see :func:`reach`).
REACH = 4.0
#: By default the volume holds the surfaces at least this fraction of the best-shared surface's views frame.
SHARED = 0.5
_BOUND_POINTS = 50_000  # surface points (at most) that set the default bounds
#: Default truncation, in voxels (the 2DGS paper's fusion uses 4 to 5).
TRUNCATION_VOXELS = 4.0
_NODES = BLOCK**3
_CHUNK_BLOCKS = 4096  # blocks integrated per batch (bounds temporary memory: about 100 MB)


@dataclass
class DepthView:
    """One camera's depth (H, W) camera z (conventions in the module docstring) and, optionally,
    its image (H, W, 3) RGB in [0, 1] for the vertex colours."""

    camera: object
    depth: np.ndarray
    color: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.depth = np.asarray(self.depth, dtype=np.float32)
        shape = (self.camera.height, self.camera.width)
        if self.depth.shape != shape:
            raise MeshingError(f"depth must be (H, W) = {shape} for its camera, got shape {self.depth.shape}")
        if np.isneginf(self.depth).any() or (self.depth < 0).any():
            raise MeshingError("depth must be camera z >= 0 (0 or NaN: unknown, inf: nothing seen), got negative values")
        if self.color is not None:
            self.color = np.asarray(self.color, dtype=np.float32)
            if self.color.shape != (*shape, 3):
                raise MeshingError(f"color must be (H, W, 3) = {(*shape, 3)}, got shape {self.color.shape}")


@dataclass(frozen=True)
class FusionGrid:
    """The volume's lattice: node ``(i, j, k)`` at ``origin + voxel * (i, j, k)``, ``shape`` nodes per axis
    (a multiple of :data:`BLOCK`); ``truncation`` in world units."""

    origin: np.ndarray
    voxel: float
    shape: tuple
    truncation: float

    @property
    def blocks(self) -> tuple:
        return tuple(s // BLOCK for s in self.shape)


def reach(cameras) -> tuple:
    """``(centre (3,), radius)`` of the space meshed by default: within :data:`REACH` times the cameras' extent
    (3DGS's: 1.1 x the largest distance of a camera from their mean) of their mean; radius ``inf`` for cameras at
    one point. Training puts a scene's backdrop 5 extents out (``TrainerConfig.backdrop_distance``), so the
    sky and far walls of a capture stay out of the volume and do not stretch its voxels."""
    from ..datasets.base import cameras_extent

    centres = np.array([c.center for c in cameras], dtype=np.float64).reshape(-1, 3)
    extent = cameras_extent(centres) if len(centres) else 0.0
    return (centres.mean(axis=0) if len(centres) else np.zeros(3)), (REACH * extent if extent > 0 else math.inf)


def fusion_grid(views, resolution: int = 256, voxel_size: float | None = None, truncation: float | None = None,
                bounds=None) -> FusionGrid:
    """The lattice for ``views``: over ``bounds`` ((2, 3) min and max corners, meshed as given: the surface
    ends at the box's walls) or, by default, over the bounds below plus the truncation, with ``voxel_size`` (default the bounds' longest side / ``resolution``) and ``truncation``
    (default :data:`TRUNCATION_VOXELS` voxels).

    Default bounds: the 0.5 to 99.5 percentiles, per axis, of the seen surface points within :func:`reach`
    of the views' cameras that the views share, i.e. that at least :data:`SHARED` times as many views frame
    (in front of the camera, inside the picture) as frame the most shared point, and at least two. What
    every view of an orbit looks at sets the volume, not the floor or the far walls at the edges of the
    photos, which the voxels would otherwise have to stretch over."""
    given = bounds is not None
    if not given:
        points = [_surface_points(v, stride=4) for v in views]
        points = np.concatenate(points) if points else np.zeros((0, 3))
        if len(points) == 0:
            raise MeshingError(f"none of the {len(views)} depth maps sees a surface (every depth is 0, NaN or inf)")
        centre, radius = reach([v.camera for v in views])
        near = points[np.linalg.norm(points - centre, axis=1) <= radius]
        if len(near) == 0:
            raise MeshingError(f"the depth maps see surfaces only farther than {radius:.4g} from the cameras' centre "
                               "(4 times their extent); give bounds to mesh them")
        bounds = np.percentile(_shared_points(near, views), [0.5, 99.5], axis=0)
    bounds = np.asarray(bounds, dtype=np.float64).reshape(2, 3)
    if not np.isfinite(bounds).all() or (bounds[1] < bounds[0]).any():
        raise MeshingError(f"bounds must be finite (min corner, max corner), got {bounds.tolist()}")
    extent = float(np.max(bounds[1] - bounds[0]))
    if voxel_size is None:
        if int(resolution) < 8:
            raise MeshingError(f"resolution must be at least 8 voxels, got {resolution!r}")
        voxel_size = max(extent, 1e-9) / int(resolution)
    voxel = float(voxel_size)
    if not (math.isfinite(voxel) and voxel > 0):
        raise MeshingError(f"voxel_size must be a positive length, got {voxel_size!r}")
    trunc = TRUNCATION_VOXELS * voxel if truncation is None else float(truncation)
    if not (math.isfinite(trunc) and trunc >= voxel):
        raise MeshingError(f"truncation must be at least one voxel ({voxel:.4g}), got {truncation!r}")
    margin = 0.0 if given else trunc
    origin = bounds[0] - margin
    nodes = np.ceil((bounds[1] + margin - origin) / voxel).astype(np.int64) + 1
    shape = tuple(int(BLOCK * math.ceil(n / BLOCK)) for n in nodes)
    if math.prod(shape) > 2**34:
        raise MeshingError(f"a {shape[0]}x{shape[1]}x{shape[2]} lattice is too large; use a larger voxel_size")
    return FusionGrid(origin=origin, voxel=voxel, shape=shape, truncation=trunc)


def _shared_points(points: np.ndarray, views) -> np.ndarray:
    """The ``points`` (M, 3) that at least :data:`SHARED` times the largest number of views framing one point
    frame, and at least two (all of them when no point is framed twice); at most ``_BOUND_POINTS``, evenly taken."""
    points = points[:: max(1, -(-len(points) // _BOUND_POINTS))]
    framed = np.zeros(len(points), np.int64)
    for view in views:
        framed += _sample(view, points)[2]
    need = max(2.0, SHARED * framed.max())
    return points[framed >= need] if framed.max() >= 2 else points


def _pixels(camera) -> np.ndarray:
    return camera.pixel_centers().reshape(-1, 2)


def _surface_points(view: DepthView, stride: int = 1) -> np.ndarray:
    """(M, 3) world points of the pixels that see a surface (every ``stride``-th row and column)."""
    depth = view.depth[::stride, ::stride]
    uv = view.camera.pixel_centers()[::stride, ::stride]
    seen = np.isfinite(depth) & (depth > 0)
    return np.asarray(view.camera.unproject(uv[seen], depth[seen]), dtype=np.float64)


def _in_lens(camera, pc: np.ndarray) -> np.ndarray:
    """Camera-space points (M, 3) in front of the camera and inside the range where its lens is one-to-one."""
    z = pc[:, 2]
    if camera.model == "orthographic":
        return np.ones(len(pc), bool)
    limit = camera.lens_limit
    if camera.model == "fisheye":
        theta = np.arctan2(np.hypot(pc[:, 0], pc[:, 1]), z)
        return (theta * theta <= limit) & (theta < np.pi / 2)
    front = z > 1e-6
    if math.isinf(limit):
        return front
    zs = np.where(front, z, 1.0)
    return front & ((pc[:, 0] / zs) ** 2 + (pc[:, 1] / zs) ** 2 <= limit)


def _sample(view: DepthView, points: np.ndarray):
    """Depth at the pixels ``points`` (M, 3) fall on (nearest pixel), their camera z, whether they land in the
    picture through the lens, and that pixel's flat index (0 outside), to read other images there:
    ``(depth, z, inside, pixel)``."""
    camera = view.camera
    pc = np.asarray(camera.world_to_camera(points), dtype=np.float64)
    uv, z = camera.camera_to_pixels(pc)
    uv = np.asarray(uv)
    col, row = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
    inside = _in_lens(camera, pc) & (col >= 0) & (col < camera.width) & (row >= 0) & (row < camera.height)
    pixel = np.where(inside, row * camera.width + col, 0)
    return view.depth.reshape(-1)[pixel], np.asarray(z), inside, pixel


def _touched_blocks(view: DepthView, grid: FusionGrid) -> np.ndarray:
    """Flat ids of the blocks the pixels' bands (depth +- truncation along each ray) pass through."""
    camera = view.camera
    seen = (np.isfinite(view.depth) & (view.depth > 0)).reshape(-1)
    if not seen.any():
        return np.zeros(0, np.int64)
    uv = _pixels(camera)[seen]
    depth = view.depth.reshape(-1)[seen].astype(np.float64)
    p0 = np.asarray(camera.unproject(uv, np.zeros(len(uv))), dtype=np.float64)
    ray = np.asarray(camera.unproject(uv, np.ones(len(uv))), dtype=np.float64) - p0  # world motion per unit of z
    per_z = np.linalg.norm(ray, axis=1)  # world length per unit of z
    nb = np.array(grid.blocks)
    steps = int(math.ceil(grid.truncation / (grid.voxel * BLOCK / 2)))  # samples half a block apart
    ids = []
    for s in np.linspace(-1.0, 1.0, 2 * steps + 1):
        z = depth + s * grid.truncation / per_z
        b = np.floor((p0 + ray * z[:, None] - grid.origin) / (grid.voxel * BLOCK)).astype(np.int64)
        ok = ((b >= 0) & (b < nb)).all(axis=1)
        b = b[ok]
        ids.append((b[:, 0] * nb[1] + b[:, 1]) * nb[2] + b[:, 2])
    return np.unique(np.concatenate(ids))


_OFFSETS = np.stack(np.meshgrid(*(np.arange(BLOCK),) * 3, indexing="ij"), axis=-1).reshape(-1, 3)


def _block_nodes(blocks: np.ndarray, grid: FusionGrid) -> np.ndarray:
    """(B * BLOCK³, 3) int64 lattice indices of the nodes of blocks ``blocks`` (flat ids), block by block."""
    nb = grid.blocks
    bi = np.stack(np.unravel_index(blocks, nb), axis=1) * BLOCK
    return (bi[:, None, :] + _OFFSETS[None]).reshape(-1, 3)


def _integrate(view: DepthView, grid: FusionGrid, blocks: np.ndarray, tsdf: np.ndarray, weight: np.ndarray) -> None:
    """Adds ``view``'s projective distances to the nodes of ``blocks`` (running mean, weight 1 per view)."""
    centres = grid.origin + grid.voxel * (np.stack(np.unravel_index(blocks, grid.blocks), axis=1) * BLOCK + (BLOCK - 1) / 2)
    _, z, _, _ = _sample(view, centres)
    radius = grid.voxel * BLOCK * math.sqrt(3) / 2
    near = np.flatnonzero(z > -radius)  # a cheap cull of blocks behind the camera; pixels decide the rest
    for a in range(0, len(near), _CHUNK_BLOCKS):
        rows = near[a : a + _CHUNK_BLOCKS]
        points = grid.origin + grid.voxel * _block_nodes(blocks[rows], grid)
        depth, zn, inside, _ = _sample(view, points)
        depth = depth.astype(np.float64)
        known = inside & ~np.isnan(depth) & (depth > 0)
        sdf = np.where(np.isinf(depth), grid.truncation, depth - zn)
        use = known & (sdf > -grid.truncation)
        if not use.any():
            continue
        obs = np.minimum(sdf / grid.truncation, 1.0).reshape(len(rows), _NODES)
        use = use.reshape(len(rows), _NODES)
        t, w = tsdf[rows], weight[rows]
        w_new = w + use
        tsdf[rows] = np.where(use, (t * w + obs) / np.maximum(w_new, 1), t)
        weight[rows] = w_new


def _dense(grid: FusionGrid, blocks: np.ndarray, values: np.ndarray, fill: float):
    """The blocks' values on one dense array over their bounding box: ``(array, first node index)``."""
    bi = np.stack(np.unravel_index(blocks, grid.blocks), axis=1)
    lo, hi = bi.min(axis=0), bi.max(axis=0) + 1
    dense = np.full(tuple((hi - lo) * BLOCK), fill, dtype=values.dtype)
    for b, (i, j, k) in enumerate(bi - lo):
        dense[i * BLOCK:(i + 1) * BLOCK, j * BLOCK:(j + 1) * BLOCK, k * BLOCK:(k + 1) * BLOCK] = values[b].reshape(BLOCK, BLOCK, BLOCK)
    return dense, lo * BLOCK


def vertex_colors(vertices: np.ndarray, views, truncation: float) -> np.ndarray:
    """(V, 3) mean colour of each vertex over the views that see it (their depth within ``truncation`` / 2 of
    the vertex's); 0.5 grey where none does."""
    total = np.zeros((len(vertices), 3))
    count = np.zeros(len(vertices))
    for view in views:
        if view.color is None:
            continue
        depth, z, inside, pixel = _sample(view, vertices)
        seen = inside & np.isfinite(depth) & (depth > 0) & (np.abs(depth - z) <= truncation / 2)
        total[seen] += view.color.reshape(-1, 3)[pixel[seen]]
        count[seen] += 1
    return np.where(count[:, None] > 0, total / np.maximum(count, 1)[:, None], 0.5).astype(np.float32)


def fuse_depth_maps(views, resolution: int = 256, voxel_size: float | None = None, truncation: float | None = None,
                    bounds=None, progress=None) -> SurfaceMesh:
    """A mesh of the surface ``views`` (a sequence of :class:`DepthView`) see.

    The volume (see :func:`fusion_grid`) is built in two passes over the views: the blocks near their
    surfaces, then every view's distances into every block in front of it; its zero level becomes the mesh
    (faces counter-clockwise seen from the cameras' side), coloured from the views' images. ``progress(done,
    total)`` is called per view and per pass and may raise to cancel. Raises ``MeshingError`` when no view
    sees a surface. Memory: 8 bytes per stored node (blocks near the surfaces only), plus a dense float32
    copy of the bounding box of those blocks while marching.
    """
    views = list(views)
    if not views:
        raise MeshingError("no depth maps to fuse")
    grid = fusion_grid(views, resolution, voxel_size, truncation, bounds)
    total = 2 * len(views)
    blocks = []
    for n, view in enumerate(views):
        blocks.append(_touched_blocks(view, grid))
        if progress is not None:
            progress(n + 1, total)
    blocks = np.unique(np.concatenate(blocks))
    if len(blocks) == 0:
        raise MeshingError("no depth map sees a surface inside the bounds")
    tsdf = np.zeros((len(blocks), _NODES), np.float32)
    weight = np.zeros((len(blocks), _NODES), np.float32)
    for n, view in enumerate(views):
        _integrate(view, grid, blocks, tsdf, weight)
        if progress is not None:
            progress(len(views) + n + 1, total)
    known = (weight > 0) & (np.abs(tsdf) < 1.0)
    values, first = _dense(grid, blocks, -tsdf, 0.0)  # marching's inside (> 0) is behind the surface
    mask, _ = _dense(grid, blocks, known, False)
    del tsdf, weight, known
    vertices, faces = marching_tetrahedra(values, 0.0, grid.origin + grid.voxel * first, grid.voxel, mask=mask)
    del values, mask
    if bounds is not None:  # the lattice's last nodes lie up to a voxel past a box given by hand
        lo, hi = np.asarray(bounds, dtype=np.float64).reshape(2, 3)
        inside = np.all((vertices >= lo) & (vertices <= hi), axis=1)
        vertices, faces, _ = compact_faces(vertices, faces, inside[faces].all(axis=1))
    if len(faces) == 0:
        raise MeshingError("the fused depth maps hold no surface (the views do not agree on any)")
    colors = vertex_colors(vertices, views, grid.truncation) if any(v.color is not None for v in views) else None
    return SurfaceMesh(vertices, faces, colors)


def _components(faces: np.ndarray, count: int) -> np.ndarray:
    """(count,) a label per vertex, equal for vertices joined by faces (min-label hooking and pointer jumping)."""
    parent = np.arange(count)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]]).astype(np.int64)
    while True:
        a, b = parent[edges[:, 0]], parent[edges[:, 1]]
        differ = a != b
        if not differ.any():
            return parent
        np.minimum.at(parent, np.maximum(a, b)[differ], np.minimum(a, b)[differ])
        while True:
            jumped = parent[parent]
            if np.array_equal(jumped, parent):
                break
            parent = jumped


def keep_large_components(mesh: SurfaceMesh, min_fraction: float = 0.01) -> SurfaceMesh:
    """``mesh`` without the connected pieces of fewer faces than ``min_fraction`` times the largest piece's
    (0 keeps every piece, 1 only the largest)."""
    if not 0.0 <= min_fraction <= 1.0:
        raise MeshingError(f"min_fraction must be in [0, 1], got {min_fraction!r}")
    if len(mesh.faces) == 0:
        return mesh
    label = _components(mesh.faces, len(mesh.vertices))[mesh.faces[:, 0]]
    _, inverse, sizes = np.unique(label, return_inverse=True, return_counts=True)
    vertices, faces, used = compact_faces(mesh.vertices, mesh.faces, sizes[inverse] >= min_fraction * sizes.max())
    return SurfaceMesh(vertices, faces, None if mesh.colors is None else mesh.colors[used])


# ------------------------------------------------------------------ from a splat model
#: A pixel sees a surface where the splats cover at least this much of it.
MIN_ALPHA = 0.5
#: A pixel sees empty space where they cover less than this; in between it says nothing (a gap between
#: splats or a silhouette's edge is not evidence that the surface behind it is absent).
EMPTY_ALPHA = 0.05


def is_surfel_model(model) -> bool:
    """True when the Gaussians are discs about their local z axis (2DGS): for most of them the third scale is
    under a tenth of the smaller of the other two. Their depth is then rendered planar (along each pixel's ray
    to the disc's plane, ``render_gaussians(planar_depth=True)``) instead of at their centres."""
    scales = np.exp(np.array(model.params["scales"], dtype=np.float64))
    if len(scales) == 0:
        return False
    return bool(np.median(scales[:, 2] / np.maximum(np.minimum(scales[:, 0], scales[:, 1]), 1e-30)) < 0.1)


DEPTHS = ("median", "expected")


def depth_views(model, cameras, depth: str = "median", min_alpha: float = MIN_ALPHA, planar: bool | None = None,
                progress=None) -> list:
    """The :class:`DepthView` of ``model`` (a ``GaussianModel``) from each of ``cameras``, with its colour.

    depth: ``'median'``, the depth at which the splats' accumulated opacity reaches ``min_alpha``
    (``mlx3d.render.render_gaussian_median_depth``: the front surface, even where splats behind it show
    through), or ``'expected'``, the alpha-weighted mean depth of every splat on the ray. Planar (each
    surfel's plane along the ray) for surfel models (:func:`is_surfel_model`) unless ``planar`` says. Pixels
    covered less than :data:`EMPTY_ALPHA` are empty space (``inf``), those between it and ``min_alpha``
    unknown (NaN). ``progress(done, total)`` per camera;
    it may raise to cancel."""
    import mlx.core as mx

    from ..render import render_gaussian_median_depth

    if depth not in DEPTHS:
        raise MeshingError(f"depth must be one of {', '.join(DEPTHS)}, got {depth!r}")
    if not EMPTY_ALPHA <= min_alpha < 1.0:
        raise MeshingError(f"min_alpha must be in [{EMPTY_ALPHA}, 1), got {min_alpha!r}")
    planar = is_surfel_model(model) if planar is None else bool(planar)
    cameras = list(cameras)
    views = []
    for n, camera in enumerate(cameras):
        out = model.render(camera, background=mx.zeros(3), render_depth=depth == "expected", planar_depth=planar)
        alpha = np.array(out["alpha"], dtype=np.float32)
        if depth == "median":
            z = render_gaussian_median_depth(camera, model.means, model.quats, model.scales, model.opacities,
                                             planar=planar, level=min_alpha)["depth"]
        else:
            z = out["depth"]
        z = np.array(z, dtype=np.float32)
        z = np.where(alpha >= min_alpha, np.where(z > 0, z, np.nan), np.where(alpha < EMPTY_ALPHA, np.inf, np.nan))
        color = np.array(out["image"], dtype=np.float32) / np.maximum(alpha, 1e-6)[..., None]  # rendered over black
        views.append(DepthView(camera, z, np.clip(color, 0.0, 1.0)))
        if progress is not None:
            progress(n + 1, len(cameras))
    return views


def require_surface(views, min_alpha: float = MIN_ALPHA, what: str = "the splats") -> None:
    """Raises ``MeshingError`` when none of ``views`` (from :func:`depth_views`) sees a surface."""
    if not any(np.isfinite(v.depth).any() for v in views):
        raise MeshingError(f"{what} cover no pixel of the {len(views)} views to opacity {min_alpha:g}: nothing to mesh "
                           "(they are too transparent there, or the cameras look away from them)")


def orbit_cameras(model, count: int = 60, size: int = 512, min_opacity: float = 0.5) -> list:
    """``count`` cameras on a spiral around ``model`` (from 30 degrees below to 60 above its centre, +Z up),
    ``size`` pixels square with a 50-degree view, far enough that the middle 98% of its opaque splats
    (opacity >= ``min_opacity``) fill about two thirds of the picture: the views to mesh an object from when
    no training cameras are at hand."""
    from ..cameras import Camera

    means = np.array(model.means, dtype=np.float64)
    opaque = means[np.array(model.opacities) >= min_opacity]
    points = opaque if len(opaque) else means
    if len(points) == 0:
        raise MeshingError("the model has no Gaussians to view")
    lo, hi = np.percentile(points, [1, 99], axis=0)
    centre, radius = (lo + hi) / 2, max(float(np.linalg.norm(hi - lo)) / 2, 1e-6)
    distance = radius / math.tan(math.radians(50 / 2) * 2 / 3)
    cameras = []
    for i in range(count):
        t = (i + 0.5) / count
        elevation, azimuth = math.radians(-30 + 90 * t), 2 * math.pi * 2.5 * t
        eye = centre + distance * np.array([math.cos(elevation) * math.cos(azimuth),
                                            math.cos(elevation) * math.sin(azimuth), math.sin(elevation)])
        cameras.append(Camera.look_at(eye, at=centre, up=(0.0, 0.0, 1.0), fov=50, width=size, height=size))
    return cameras
