"""Where a training run starts: the initial Gaussians and the settings they imply.

``initial_state(dataset, config, sh_degree)`` is the one way ``mlx3d train``,
the add-on's Train operator and the benchmarks build the model a run starts
from. It returns the model, a copy of the config with every "method default"
resolved (so what runs is what is printed and saved) and notes for the user.

- **Points.** The dataset's own (COLMAP ``points3D``, a ``ply_file_path`` in a
  nerfstudio ``transforms.json`` or a NeRF-synthetic ``transforms_train.json``).
  A dataset without points whose photos are opaque (a capture app's or
  Blender's NeRF export of an open scene) starts from where its photos agree:
  a plane sweep over the training views (``plane_sweep.sweep_points``) puts a
  point, coloured by its pixel, at each depth where neighbouring views see the
  same colour, and none along textureless rays (a plain sky), which the
  backdrop below covers; at most ``init_random_points`` of them. Random points
  do not suit such a scene: the ground runs out of any cube, and densification
  cannot start from random colours whose gradients dozens of neighbours share
  (held-out PSNR 20.2 dB against 33.3 dB from the sweep on the benchmark's
  open scene, vanilla, 3,000 steps). Photos with alpha (one object, the usual NeRF-synthetic layout), and
  opaque photos without texture enough for ``SWEEP_MIN_POINTS`` points, start,
  as the 3DGS reference does, from ``init_random_points`` points drawn uniformly in a
  cube with random colours (3DGS: 100k in [-1.3, 1.3]³ for lego, whose cameras
  are 4 units from the origin). The cube is centred on the point nearest to
  every training camera's optical axis (what the cameras look at) with a
  half-side of ``init_random_extent`` or, by default, the half-width of the
  narrowest view at the cameras' median distance from that point (1.45 for lego).
- **Background.** When the training photos are opaque (no alpha, no mask),
  the sky and whatever lies far away must be Gaussians too, and point clouds
  rarely reach them (structure from motion finds no points in a plain sky).
  Left to itself, MCMC builds that backdrop out of small Gaussians among the
  cameras: a sky-coloured Gaussian next to a ring of cameras that see each
  other against the sky fits every training view, is cheap under the scale
  regulariser, and the position noise and opacity-weighted relocation
  multiply it, so views off the ring look through a veil of it. Seeding the
  backdrop far away removes the incentive: ``init_background_points`` points
  on a sphere of radius ``init_background_radius`` × the scene extent around
  the camera centroid, kept where a training view sees them and coloured by
  the mean training pixel they project to. On by default for vanilla and MCMC
  on opaque photos (None; not for 2DGS, whose surfels are meant for meshes);
  0 turns it off, a count forces it for any method. Vanilla keeps it through
  its size prunes: the trainer's ``backdrop_distance`` exempts Gaussians that
  far from the cameras from them.
- **Opacity and scale.** ``init_opacity`` and ``init_scale`` (a factor on the
  mean distance to the 3 nearest points): 0.1 and 1 for vanilla and 2DGS as in
  3DGS; 0.5 and 0.1 for MCMC, as in gsplat's MCMC preset (many
  small, half-opaque Gaussians that relocation can sample from). Random
  points start with the cube's optical depth kept at most 4
  (``random_cube_opacity``): at vanilla's 0.1, 100,000 of them made the cube
  a wall of random colours that 2,000 steps never cleared (a full-orbit
  object without points: 9.4 dB held-out, against 32.3 dB from opacity
  0.01; see the design note on real captures).
- **Budget.** With ``max_gaussians`` below the point count, a seeded random
  subset of the points. MCMC grows to ``max_gaussians``; when that is None it
  becomes ``mcmc_budget(...)`` (see there).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..errors import Mlx3dError
from ..io.codec import logit
from ..splatting.model import GaussianModel

BACKDROP_METHODS = ("vanilla", "mcmc")  # methods that seed a backdrop on opaque photos by default

MCMC_MAX_BUDGET = 1_000_000  # gsplat's and 3DGS-MCMC's default cap_max
OPAQUE_ALPHA = 0.99  # a photo whose coverage is at least this everywhere has no background to leave out


class InitialisationError(Mlx3dError, ValueError):
    """The dataset cannot seed a model (e.g. no training views, no usable cameras)."""


@dataclass
class InitialState:
    """What ``initial_state`` returns: the model, the resolved config and notes (one line each)."""

    model: GaussianModel
    config: object  # TrainerConfig with max_gaussians, init_opacity and init_scale resolved
    notes: list


def mcmc_budget(initial: int, image_pixels: int) -> int:
    """MCMC's default Gaussian budget: one Gaussian per pixel of a training image,
    at least twice the initial count (so the model can grow), at most 1,000,000
    (the reference implementations' default cap).

    A Gaussian much smaller than a pixel in every view is not constrained by
    the photos, so at this count a model can give each pixel of a view its own
    Gaussian and more buys little; the bound keeps the default within what a
    CPU trains in reasonable time at the resolutions it handles.
    """
    return int(min(MCMC_MAX_BUDGET, max(2 * int(initial), int(image_pixels))))


def look_at_centre(cameras) -> np.ndarray:
    """(3,) the point nearest (least squares) to every camera's optical axis.

    Cameras that all look the same way (no point is near every axis) fall
    back towards their centroid through a small ridge term."""
    centres = np.array([c.center for c in cameras], dtype=np.float64).reshape(-1, 3)
    forward = np.array([c.R[2] for c in cameras], dtype=np.float64).reshape(-1, 3)  # camera +z in world
    a = np.zeros((3, 3))
    b = np.zeros(3)
    for c, d in zip(centres, forward):
        p = np.eye(3) - np.outer(d, d)
        a += p
        b += p @ c
    ridge = 1e-3 * len(centres)
    return np.linalg.solve(a + ridge * np.eye(3), b + ridge * centres.mean(axis=0))


def _look_at_and_distance(cameras) -> tuple[np.ndarray, float]:
    """(what the cameras look at (3,), their median distance from it)."""
    centre = look_at_centre(cameras)
    return centre, float(np.median([np.linalg.norm(c.center - centre) for c in cameras]))


def random_cube(cameras, count: int, extent: float | None = None, seed: int = 0):
    """``count`` points uniformly in the cube the cameras look at, random colours.

    Returns (points (count, 3) float32, colours (count, 3) uint8, centre (3,), half-side)."""
    centre, distance = _look_at_and_distance(cameras)
    if extent is None:
        half_fov = min(min(c.fov_x, c.fov_y) for c in cameras) / 2.0
        extent = distance * math.tan(min(half_fov, math.radians(60.0)))
    if not extent > 0:
        raise InitialisationError(f"the random initial points need a positive extent, got {extent}")
    rng = np.random.default_rng(seed)
    points = centre + rng.uniform(-extent, extent, size=(count, 3))
    colours = rng.integers(0, 256, size=(count, 3), dtype=np.uint8)
    return points.astype(np.float32), colours, centre, float(extent)


RANDOM_OPTICAL_DEPTH = 4.0  # the random cube's mean optical depth across it at the start, at most (MCMC's 100,000 at 0.5: 3.8)
RANDOM_MIN_OPACITY = 0.01  # and its points' opacity at least this (3DGS's opacity reset value)


def random_cube_opacity(log_scales, half: float, opacity: float) -> tuple[float, float]:
    """The opacity random points in a cube of half-side ``half`` start at: ``opacity``, or less where
    that would make the cube opaque, so that every view sees through them and each point's colour and
    opacity get gradients from the photos.

    A Gaussian of standard deviation s and opacity o integrates to o · 2π s² over a plane across it, so
    M of them spread over a cube of side 2h put a mean optical depth of o · Σ 2π s² / (2h)² on a ray
    crossing it. The opacity is chosen for at most ``RANDOM_OPTICAL_DEPTH`` (4, where MCMC's default
    start of 100,000 points at opacity 0.5 lies and trains; vanilla's 0.1 gives 77 there, and 15 for
    20,000 points), at least ``RANDOM_MIN_OPACITY``, at most ``opacity``. log_scales: (M, 3) the points'
    log standard deviations. Returns (the opacity, the optical depth it gives)."""
    s = np.exp(np.asarray(log_scales, dtype=np.float64))
    if s.size == 0 or not half > 0:
        return float(opacity), float("nan")
    depth_at_one = float(np.sum(2.0 * math.pi * s[:, 0] * s[:, 1])) / (2.0 * half) ** 2
    if not depth_at_one > 0:
        return float(opacity), 0.0
    chosen = float(min(opacity, max(RANDOM_MIN_OPACITY, RANDOM_OPTICAL_DEPTH / depth_at_one)))
    return chosen, chosen * depth_at_one


def opaque_photos(dataset, sample: int = 8) -> bool:
    """True when the training photos have no alpha or mask that leaves part of them out
    (checks up to ``sample`` of them, evenly spread)."""
    train = list(dataset.train)
    for i in train[:: max(len(train) // sample, 1)][:sample]:
        _, weight = dataset.load_image(i)
        if weight is not None and float(np.min(weight)) < OPAQUE_ALPHA:
            return False
    return True


def background_sphere(dataset, count: int, radius_factor: float = 10.0, seed: int = 0):
    """Up to ``count`` points on a sphere of radius ``radius_factor`` × the scene extent around
    the training cameras' centroid, where a training view sees them, coloured by the mean of the
    training pixels they project to. Returns (points (M, 3) float32, colours (M, 3) uint8, radius)."""
    train = list(dataset.train)
    centre = dataset.scene_centre()
    radius = radius_factor * dataset.scene_extent()
    rng = np.random.default_rng(seed)
    images = [(dataset.frames[i].camera, dataset.load_image(i, background="black")[0]) for i in train]
    points = np.zeros((0, 3))
    total, seen = np.zeros((0, 3)), np.zeros(0)
    draw = 4 * count
    for _ in range(4):  # the views see part of the sphere: draw more until ``count`` are seen
        directions = rng.normal(size=(draw, 3))
        batch = centre + radius * directions / np.linalg.norm(directions, axis=1, keepdims=True)
        colour_sum, hits = _seen_colours(images, batch)
        points, total, seen = np.concatenate([points, batch]), np.concatenate([total, colour_sum]), np.concatenate([seen, hits])
        found = int(np.count_nonzero(seen))
        if found >= count:
            break
        draw = int(min(64 * count, (count - found) * len(points) / max(found, 1) * 1.2 + 1))
    keep = np.flatnonzero(seen > 0)[:count]
    colours = np.clip(np.round(total[keep] / seen[keep, None] * 255.0), 0, 255).astype(np.uint8)
    return points[keep].astype(np.float32), colours, float(radius)


def _seen_colours(images, points):
    """For points (M, 3): the sum of the pixel colours they project to over ``images`` [(camera, rgb)]
    and how many images see them."""
    total = np.zeros((len(points), 3))
    seen = np.zeros(len(points))
    for camera, image in images:
        uv, depth = (np.asarray(a) for a in camera.project_points(points))
        ok = (depth > 0) & np.all(np.isfinite(uv), axis=1)
        ok &= (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)
        cols = uv[ok].astype(np.int64)
        total[ok] += image[cols[:, 1], cols[:, 0]]
        seen[ok] += 1
    return total, seen


SWEEP_MIN_POINTS = 1000  # fewer photo-consistent points than this: start from the random cube instead
SWEEP_SIZE = 256  # the sweep looks at the photos at most this many pixels across
SWEEP_RAYS = 150_000  # rays in all (2,048 per view up to 73 views, then fewer; at least 256 per view)


def swept_points(dataset, cameras, config, seed: int, progress=None):
    """Photo-consistent initial points of opaque photos (``plane_sweep.sweep_points``), at most
    ``init_random_points`` of them, swept from 0.1 x the cameras' median distance to what they look
    at out to the backdrop's radius, on the photos at most ``SWEEP_SIZE`` pixels across and along
    about ``SWEEP_RAYS`` rays. Returns (points, colours uint8, note), or None when fewer than
    ``SWEEP_MIN_POINTS`` are found (a textureless scene)."""
    from .plane_sweep import sweep_points

    from ..datasets.base import resize_image

    _, distance = _look_at_and_distance(cameras)
    far = config.init_background_radius * dataset.scene_extent()
    small, images = [], []
    for i, camera in zip(dataset.train, cameras):  # at most SWEEP_SIZE pixels across: memory and time stay bounded
        factor = min(1.0, SWEEP_SIZE / max(camera.width, camera.height))
        image = dataset.load_image(i, background="black")[0]
        if factor < 1.0:
            camera = camera.scaled(factor)
            image = resize_image(image, None, (camera.width, camera.height), "box")[0]
        small.append(camera)
        images.append(image)
    rays = max(256, min(2048, SWEEP_RAYS // len(cameras)))
    found = sweep_points(small, images, near=0.1 * distance, far=far, rays_per_view=rays, seed=seed, progress=progress)
    if len(found.points) < SWEEP_MIN_POINTS:
        return None
    points, colours = found.points, found.colours
    if len(points) > config.init_random_points:
        keep = np.sort(np.random.default_rng(seed).choice(len(points), config.init_random_points, replace=False))
        points, colours = points[keep], colours[keep]
    note = (f"initial points: {len(points):,} where the photos agree (a plane sweep found {len(found.points):,} "
            f"along {found.rays:,} rays, depths {found.near:.3g} to {found.far:.3g}); the dataset has none")
    return points, colours, note


def image_pixels(dataset) -> int:
    """The median pixel count of the training images."""
    sizes = [dataset.frames[i].camera.width * dataset.frames[i].camera.height for i in dataset.train]
    return int(np.median(sizes))


def initial_state(dataset, config, sh_degree: int = 3, progress=None) -> InitialState:
    """The model a run on ``dataset`` with ``config`` starts from (see the module docstring).

    dataset: an ``mlx3d.datasets.Dataset`` with training views; config: a
    ``TrainerConfig``; sh_degree: the model's SH degree (0..3); progress(done,
    total): called per view while the plane sweep runs (opaque photos without
    points), its longest part."""
    where = str(dataset.root) if dataset.root is not None else "the dataset"
    train = list(dataset.train)
    if not train:
        raise InitialisationError(f"{where}: the dataset has no training views")
    cameras = [dataset.frames[i].camera for i in train]
    notes = []
    seed = config.seed
    points, colours = dataset.points, dataset.point_colors
    opaque = opaque_photos(dataset)
    cube = None  # (count, half-side) of the random cube's points, which come first in the model
    if points is not None and len(points) >= 2:
        notes.append(f"initial points: the dataset's {len(points):,}")
    else:
        if points is not None and len(points):
            notes.append(f"the dataset's {len(points)} point is too few to start from")
        swept = swept_points(dataset, cameras, config, seed, progress) if opaque else None
        if swept is not None:
            points, colours, note = swept
            notes.append(note)
        else:
            points, colours, centre, half = random_cube(cameras, config.init_random_points, config.init_random_extent, seed)
            cube = (len(points), half)
            notes.append(
                f"initial points: {len(points):,} random points (random colours) in a cube of half-side {half:.3g} "
                f"around ({centre[0]:.3g}, {centre[1]:.3g}, {centre[2]:.3g}); the dataset has none"
            )
    cap = config.max_gaussians
    if cap is not None and len(points) > cap:
        keep = np.sort(np.random.default_rng(seed).choice(len(points), cap, replace=False))
        cube = None if cube is None else (cap, cube[1])
        whose = "the dataset's" if dataset.points is not None and len(dataset.points) >= 2 else "the random"
        notes.append(f"started from {cap:,} of {whose} {len(points):,} points (max Gaussians)")
        points = points[keep]
        colours = None if colours is None else colours[keep]

    background = config.init_background_points
    if background is None:
        background = max(1000, min(len(points) // 4, 20_000)) if config.method in BACKDROP_METHODS and opaque else 0
    seeded = 0
    if background > 0 and (cap is None or len(points) < cap):
        if cap is not None:
            background = min(background, cap - len(points))
        bg_points, bg_colours, radius = background_sphere(dataset, background, config.init_background_radius, seed)
        if len(bg_points):
            rgb = np.full((len(points), 3), 128, np.uint8) if colours is None else np.asarray(colours)
            if rgb.dtype != np.uint8:
                rgb = np.clip(np.round(rgb * 255.0), 0, 255).astype(np.uint8)
            points = np.concatenate([points, bg_points])
            colours = np.concatenate([rgb, bg_colours])
            notes.append(f"background: {len(bg_points):,} points on a sphere of radius {radius:.3g} (the photos are opaque)")
            seeded = len(bg_points)
    config = replace(config, init_background_points=seeded)  # what was seeded: decides the training background

    model = GaussianModel.from_points(points, colours, sh_degree=sh_degree, initial_opacity=config.init_opacity, seed=seed)
    if config.init_scale != 1.0:
        model.params["scales"] = model.params["scales"] + math.log(config.init_scale)
    notes.append(f"initial opacity {config.init_opacity:g}, scale {config.init_scale:g} x the mean distance to the 3 nearest points")
    if cube is not None:
        haze, depth = random_cube_opacity(np.asarray(model.params["scales"][: cube[0]]), cube[1], config.init_opacity)
        if haze < config.init_opacity:
            import mlx.core as mx

            model.params["opacities"] = mx.concatenate(
                [mx.full((cube[0],), float(logit(haze)), dtype=model.params["opacities"].dtype), model.params["opacities"][cube[0]:]])
            notes.append(f"random points at opacity {haze:.3g}: optical depth {depth:.2g} across the cube "
                         f"(at {config.init_opacity:g} it would be {depth * config.init_opacity / haze:.2g}, a wall every view sees)")
    if config.method == "mcmc" and cap is None:
        cap = mcmc_budget(len(model), image_pixels(dataset))
        notes.append(
            f"MCMC budget: {cap:,} Gaussians (one per pixel of a training image, at least twice the initial "
            f"{len(model):,}, at most {MCMC_MAX_BUDGET:,}; set max_gaussians to change it)"
        )
    if config.method != "mcmc":
        notes.append(
            f"densification: every {config.densify_every} steps from step {config.densify_from} to {config.densify_until}"
            + (f", opacity reset every {config.opacity_reset_every}" if config.opacity_reset_every else "")
            + (f", at most {cap:,} Gaussians" if cap is not None else ", no cap")
        )
    else:
        notes.append(
            f"MCMC growth: +{config.mcmc_growth:.0%} every {config.densify_every} steps from step {config.densify_from} "
            f"to {config.densify_until}, relocating Gaussians below opacity {config.mcmc_min_opacity:g}"
        )
    if config.bilateral_grid == "auto":
        from .exposure import exposure_varies

        varies, why = exposure_varies(dataset)
        config = replace(config, bilateral_grid=varies)
        if not varies:
            notes.append(f"bilateral grid: off ({why}; bilateral_grid)")
    else:
        why = "bilateral_grid"
    if config.bilateral_grid:
        notes.append(f"bilateral grid: {'x'.join(map(str, config.bilateral_grid_shape))} per training image, "
                     f"learning rate {config.bilateral_grid_lr:g} ({why})")
    spec = training_background(config, opaque)
    if spec is config.background:
        notes.append(f"training background: {_describe(spec)} (background)")
    else:
        why = "the photos are opaque" + (" and the backdrop covers the frame" if config.opaque_background == "auto" else "")
        notes.append(f"training background: {_describe(spec)} ({why}; opaque_background)")
    return InitialState(model, replace(config, max_gaussians=cap), notes)


def training_background(config, opaque: bool):
    """The background spec training renders use. With ``opaque`` training photos (see
    ``opaque_photos``): ``config.opaque_background``, where 'auto' means 'random' when the run
    seeded a backdrop (``init_background_points`` > 0 as ``initial_state`` returns it) and
    ``background`` otherwise. Photos with alpha: ``background``."""
    spec = config.opaque_background
    if spec == "auto":
        spec = "random" if (config.init_background_points or 0) > 0 else None
    return spec if opaque and spec is not None else config.background


def _describe(spec) -> str:
    if spec == "random":
        return "random, a new colour every step"
    return spec if isinstance(spec, str) else "(" + ", ".join(f"{float(c):g}" for c in spec) + ")"
