"""The built-in end-to-end demo (``mlx3d demo``), run on a generated scene.

Data-layer workflow: build a scene and an object as splat files, insert the
object with the classic 3DGS object-insertion transform (scale 0.06, Euler
(80, -180, 30) degrees, translation (0.05, -0.3, 0.6)), merge, remove the
floaters that were planted in the scene, compact, and summarise each file.
"""

from __future__ import annotations

import os
import time

import numpy as np

from .progress import ProgressLine, step

INSERT_SCALE = 0.06
INSERT_ROTATION_DEG = (80.0, -180.0, 30.0)
INSERT_TRANSLATION = (0.05, -0.3, 0.6)


def demo_scene(n_surface: int = 60000, n_floaters: int = 300, seed: int = 0):
    """A ground plane and a striped sphere with planted floaters.

    Returns points (N,3) float32, colours (N,3) float32 in [0,1] and a boolean
    (N,) mask that is True for the planted floaters (scattered 3-6 units away).
    """
    rng = np.random.default_rng(seed)
    n_ground = n_surface // 2
    ground = np.column_stack([rng.uniform(-2, 2, n_ground), rng.uniform(-2, 2, n_ground), rng.normal(0, 0.002, n_ground)])
    checker = (np.floor(ground[:, 0] * 2) + np.floor(ground[:, 1] * 2)) % 2
    ground_rgb = np.where(checker[:, None] > 0, [0.8, 0.8, 0.75], [0.25, 0.3, 0.35])
    n_sphere = n_surface - n_ground
    d = rng.normal(size=(n_sphere, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    sphere = d * 0.6 + [0.0, 0.0, 0.6]
    sphere_rgb = np.column_stack([0.5 + 0.5 * np.sin(8 * d[:, 2]), 0.4 + 0.3 * d[:, 0], 0.6 - 0.3 * d[:, 1]])
    direction = rng.normal(size=(n_floaters, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    floaters = direction * rng.uniform(3.0, 6.0, (n_floaters, 1))
    points = np.concatenate([ground, sphere, floaters]).astype(np.float32)
    colors = np.clip(np.concatenate([ground_rgb, sphere_rgb, rng.uniform(0, 1, (n_floaters, 3))]), 0, 1).astype(np.float32)
    is_floater = np.zeros(len(points), bool)
    is_floater[-n_floaters:] = True
    return points, colors, is_floater


def demo_object(n: int = 20000, seed: int = 1):
    """A colourful torus (radii 1 and 0.35) as points (N,3) and colours (N,3)."""
    rng = np.random.default_rng(seed)
    u, v = rng.uniform(0, 2 * np.pi, (2, n))
    points = np.column_stack([(1 + 0.35 * np.cos(v)) * np.cos(u), (1 + 0.35 * np.cos(v)) * np.sin(u), 0.35 * np.sin(v)])
    colors = np.column_stack([0.5 + 0.5 * np.cos(u), 0.5 + 0.5 * np.sin(u), 0.5 + 0.5 * np.sin(v)])
    return points.astype(np.float32), colors.astype(np.float32)


def _with_view_dependence(model, seed: int, strength: float = 0.05):
    """Give a model small random higher-order SH so that rotations visibly matter."""
    import mlx.core as mx

    rng = np.random.default_rng(seed)
    model.params["sh_rest"] = mx.array(rng.normal(0, strength, tuple(model.params["sh_rest"].shape)).astype(np.float32))
    return model


def run_demo(out_dir: str = "demo_out") -> dict:
    """Run the demo, writing PLY files into ``out_dir``; returns a dict of results."""
    from .cli import _print_summary, splat_summary
    from .floaters import statistical_outliers
    from .splatting import GaussianModel, merge
    from .transforms import compose_affine

    t0 = time.perf_counter()
    os.makedirs(out_dir, exist_ok=True)
    path = lambda name: os.path.join(out_dir, name)  # noqa: E731

    points, colors, is_floater = demo_scene()
    with step(f"scene: {len(points):,} points -> Gaussians"):
        scene = _with_view_dependence(GaussianModel.from_points(points, colors, sh_degree=3), seed=2)
        scene.save_ply(path("scene.ply"))
    obj_points, obj_colors = demo_object()
    with step(f"object: {len(obj_points):,} points -> Gaussians"):
        obj = _with_view_dependence(GaussianModel.from_points(obj_points, obj_colors, sh_degree=3), seed=3)
        obj.save_ply(path("object.ply"))

    with step("insert object (scale 0.06, rotate (80, -180, 30) deg, translate (0.05, -0.3, 0.6)) and merge"):
        matrix = compose_affine(INSERT_SCALE, INSERT_ROTATION_DEG, INSERT_TRANSLATION)
        merged = merge([scene, obj.transform(matrix)])
        merged.save_ply(path("merged.ply"))

    result = statistical_outliers(np.array(merged.means), k=25, std_ratio=10.5, progress=ProgressLine("floater search"))
    planted = np.concatenate([is_floater, np.zeros(len(obj), bool)])
    found = int((~result.keep & planted).sum())
    print(f"floaters: removed {result.removed:,}; {found} of {int(planted.sum())} planted floaters among them")
    cleaned = merged.copy().select(result.keep)
    cleaned.save_ply(path("cleaned.ply"))

    compact = cleaned.compact(max_gaussians=len(cleaned) // 2, target_sh_degree=1)
    compact.save_ply(path("compact.ply"))
    sizes = {name: os.path.getsize(path(name)) for name in ("merged.ply", "cleaned.ply", "compact.ply")}
    print(f"compact: {len(cleaned):,} -> {len(compact):,} splats, SH 3 -> 1, {sizes['cleaned.ply'] / 1e6:.1f} MB -> {sizes['compact.ply'] / 1e6:.1f} MB")
    print()
    _print_summary(splat_summary(path("compact.ply")))
    elapsed = time.perf_counter() - t0
    print(f"\ndemo finished in {elapsed:.1f} s; files in {out_dir}/")
    return {"removed": result.removed, "planted_found": found, "planted": int(planted.sum()), "compact": len(compact), "seconds": elapsed}
