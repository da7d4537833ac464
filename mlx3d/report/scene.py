"""The built-in benchmark scene: a ground-truth Gaussian model, rendered into a dataset.

``ground_truth(seed)`` builds the scene as Gaussians (no Blender needed): a
checker ground square, a striped sphere whose colour changes with the view
direction (SH bands 1 and 3), and a cube with a tinted top face (SH band 2),
all made of flat, nearly opaque Gaussians lying on the surfaces.
``write_dataset`` renders it with mlx3d's own renderer from cameras on three
rings around the scene and writes what ``mlx3d.datasets.load_dataset`` reads:
``images/frame_NNNNN.png`` (composited on white), a nerfstudio
``transforms.json`` (pinhole cameras) and ``points.ply``, initial points
sampled from the ground truth with position noise and noisy colours, as a
capture with structure-from-motion would give. Every 8th view is held out by
the loader's default. Everything is deterministic for a seed.
"""

from __future__ import annotations

import json
import math
import os
import shutil
from dataclasses import asdict, dataclass

import numpy as np

from ..cameras import Camera
from ..io.atomic import atomic_write
from ..splatting.sh import C0

#: Where the cameras look and how far away they are (scene units).
LOOK_AT = (0.0, 0.0, 0.2)
RING_ELEVATIONS_DEG = (15.0, 35.0, 60.0)
CAMERA_DISTANCE = 3.2
FOV_DEG = 45.0
BACKGROUND = (1.0, 1.0, 1.0)

# The objects: ground square half-size, checker cell, sphere (centre, radius), cube (centre of its base, side).
GROUND_HALF = 1.2
CHECKER = 0.3
SPHERE_CENTRE = (0.35, -0.15, 0.4)
SPHERE_RADIUS = 0.4
CUBE_BASE = (-0.45, 0.35, 0.0)
CUBE_SIDE = 0.45


@dataclass(frozen=True)
class SceneSpec:
    """Size of a generated dataset: image side in pixels, number of views, initial points, ground-truth spacing."""

    image_size: int = 128
    num_views: int = 64
    num_points: int = 5000
    point_noise: float = 0.03  # position noise of the initial points, as a fraction of the scene radius
    spacing: float = 0.02  # distance between ground-truth Gaussians on the surfaces (scene units)
    seed: int = 0

    def describe(self) -> str:
        held = len(range(0, self.num_views, 8))
        return (
            f"{self.num_views} views at {self.image_size}x{self.image_size} on three rings ({', '.join(f'{e:g}' for e in RING_ELEVATIONS_DEG)} deg "
            f"elevation, distance {CAMERA_DISTANCE:g}, {FOV_DEG:g} deg field of view), every 8th held out "
            f"({self.num_views - held} training, {held} held-out views), composited on white; "
            f"{self.num_points:,} initial points with {100 * self.point_noise:g}% position noise; seed {self.seed}"
        )


def _quat_from_normal(normals: np.ndarray) -> np.ndarray:
    """Unit quaternions (w,x,y,z) rotating +z onto each normal (normals with n_z > -1)."""
    q = np.column_stack([1.0 + normals[:, 2], -normals[:, 1], normals[:, 0], np.zeros(len(normals))])
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _surfels(points, normals, rgb, size, rng, sh_rest=None):
    """Flat Gaussians (σ = 0.6·size, 0.6·size, 0.05·size) at points, facing their normals."""
    n = len(points)
    sigma = np.array([0.6, 0.6, 0.05]) * size
    return {
        "means": points,
        "scales": np.log(np.tile(sigma, (n, 1)) * rng.uniform(0.9, 1.1, (n, 1))),
        "quats": _quat_from_normal(normals),
        "opacities": np.full(n, 4.0),  # sigmoid(4) = 0.98
        "sh_dc": ((np.clip(rgb, 0, 1) - 0.5) / C0)[:, None, :],
        "sh_rest": np.zeros((n, 15, 3)) if sh_rest is None else sh_rest,
    }


def _ground(spacing, rng):
    ticks = np.arange(-GROUND_HALF + spacing / 2, GROUND_HALF, spacing)
    x, y = (a.ravel() for a in np.meshgrid(ticks, ticks, indexing="ij"))
    points = np.column_stack([x, y, np.zeros_like(x)])
    cell = (np.floor(x / CHECKER) + np.floor(y / CHECKER)) % 2
    rgb = np.where(cell[:, None] > 0, [0.86, 0.83, 0.74], [0.22, 0.30, 0.40])
    rgb = rgb + rng.normal(0, 0.02, rgb.shape)  # a little grain
    return _surfels(points, np.tile([0.0, 0.0, 1.0], (len(x), 1)), rgb, spacing, rng)


def _sphere(spacing, rng):
    area = 4 * math.pi * SPHERE_RADIUS**2
    n = int(area / spacing**2)
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = math.pi * (1.0 + 5.0**0.5) * i
    r = np.sqrt(1.0 - z * z)
    normals = np.column_stack([r * np.cos(phi), r * np.sin(phi), z])
    keep = normals[:, 2] > -0.999  # the bottom pole touches nothing visible
    normals = normals[keep]
    points = normals * SPHERE_RADIUS + SPHERE_CENTRE
    stripes = 0.5 + 0.5 * np.sin(7.0 * math.pi * normals[:, 2])
    rgb = np.column_stack([0.85 - 0.15 * stripes, 0.25 + 0.55 * stripes, 0.15 + 0.1 * stripes])
    # View-dependent colour: a band-1 tint (brighter seen from +x) and a band-3 lobe pattern around the vertical.
    sh_rest = np.zeros((len(points), 15, 3))
    sh_rest[:, 2, :] = [0.25, 0.2, 0.1]  # Y_1,1 ~ -x: viewed along -x (camera on +x) the colour rises
    sh_rest[:, 14, :] = [-0.1, 0.2, 0.35]  # Y_3,3 ~ x(x² - 3y²): three lobes in azimuth
    return _surfels(points, normals, rgb, spacing, rng, sh_rest)


def _cube(spacing, rng):
    side = CUBE_SIDE
    ticks = np.arange(-side / 2 + spacing / 2, side / 2, spacing)
    u, v = (a.ravel() for a in np.meshgrid(ticks, ticks, indexing="ij"))
    centre = np.array(CUBE_BASE) + [0.0, 0.0, side / 2]
    faces = {  # normal -> colour; the bottom face lies on the ground and is left out
        (1, 0, 0): (0.20, 0.55, 0.25), (-1, 0, 0): (0.85, 0.60, 0.10), (0, 1, 0): (0.30, 0.35, 0.80),
        (0, -1, 0): (0.75, 0.20, 0.55), (0, 0, 1): (0.90, 0.90, 0.90),
    }
    parts = []
    for normal, colour in faces.items():
        n = np.array(normal, float)
        a = np.array([0.0, 0.0, 1.0]) if abs(n[2]) < 0.5 else np.array([1.0, 0.0, 0.0])
        b = np.cross(n, a)
        points = centre + n * side / 2 + u[:, None] * a + v[:, None] * b
        grid = ((np.floor((u + side / 2) / (side / 6)) + np.floor((v + side / 2) / (side / 6))) % 2)[:, None]
        rgb = np.array(colour) * (0.75 + 0.25 * grid)  # a 6x6 tile pattern on every face
        sh_rest = None
        if normal == (0, 0, 1):  # the top face changes colour with the view (band 2)
            sh_rest = np.zeros((len(points), 15, 3))
            sh_rest[:, 7, :] = [0.3, -0.1, -0.3]  # Y_2,1 ~ xz
            sh_rest[:, 8, :] = [-0.2, 0.25, 0.1]  # Y_2,2 ~ x² - y²
        parts.append(_surfels(points, np.tile(n, (len(points), 1)), rgb, spacing, rng, sh_rest))
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def ground_truth(spacing: float = 0.02, seed: int = 0):
    """The scene as a ``GaussianModel`` (SH degree 3); about 22,000 Gaussians at the default spacing."""
    from ..splatting import GaussianModel

    rng = np.random.default_rng(seed)
    parts = [_ground(spacing, rng), _sphere(spacing, rng), _cube(spacing, rng)]
    params = {k: np.concatenate([p[k] for p in parts]).astype(np.float32) for k in parts[0]}
    return GaussianModel(params)


def cameras(num_views: int, image_size: int) -> list:
    """``num_views`` pinhole cameras on the rings, going round the rings in turn (so every 8th view samples all of them)."""
    out = []
    rings = len(RING_ELEVATIONS_DEG)
    for i in range(num_views):
        elevation = math.radians(RING_ELEVATIONS_DEG[i % rings])
        azimuth = 2 * math.pi * i / num_views + math.radians(20.0 * (i % rings))
        eye = np.array(LOOK_AT) + CAMERA_DISTANCE * np.array(
            [math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth), math.sin(elevation)]
        )
        out.append(Camera.look_at(eye, LOOK_AT, (0, 0, 1), width=image_size, height=image_size, fov=FOV_DEG))
    return out


def scene_radius() -> float:
    """Radius of the ground square's bounding circle: the scale the point noise is relative to."""
    return GROUND_HALF * math.sqrt(2.0)


def initial_points(model, num_points: int, noise: float, seed: int):
    """(points (M,3) float32, colours (M,3) uint8): Gaussians' centres picked at random, moved by
    N(0, (noise · scene radius)²) per axis, with their base colour plus N(0, 0.05²) noise."""
    rng = np.random.default_rng(seed + 1)
    means = np.array(model.means, dtype=np.float64)
    rows = rng.choice(len(means), size=min(num_points, len(means)), replace=False)
    points = means[rows] + rng.normal(0, noise * scene_radius(), (len(rows), 3))
    colours = np.array(model.colors, dtype=np.float64)[rows] + rng.normal(0, 0.05, (len(rows), 3))
    return points.astype(np.float32), np.clip(np.round(colours * 255), 0, 255).astype(np.uint8)


def _write_points_ply(path, points, colours) -> None:
    rows = np.empty(len(points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for k, name in enumerate("xyz"):
        rows[name] = points[:, k]
    for k, name in enumerate(("red", "green", "blue")):
        rows[name] = colours[:, k]
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(rows)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )
    with atomic_write(path) as f:
        f.write(header.encode("ascii"))
        f.write(rows.tobytes())


def render_view(model, camera) -> np.ndarray:
    """(H,W,3) float32 image of ``model`` from ``camera`` on the white background, in [0, 1]."""
    import mlx.core as mx

    image = mx.clip(model.render(camera, background=BACKGROUND)["image"], 0.0, 1.0)
    return np.array(image)


def write_dataset(folder, spec: SceneSpec, progress=None):
    """Render the scene into ``folder`` (created; replaced when it holds another spec) and return the ground-truth model.

    A complete dataset is marked by ``scene.json`` holding the spec; when it is
    already there with the same spec, nothing is rendered again. The dataset is
    built in a temporary sibling folder and renamed into place when complete,
    so an interrupted run never leaves a half-written dataset behind.
    progress(done, total) is called after each view.
    """
    from PIL import Image

    model = ground_truth(spec.spacing, spec.seed)
    folder = os.path.abspath(os.fspath(folder))
    marker = os.path.join(folder, "scene.json")
    if os.path.isfile(marker):
        with open(marker) as f:
            if json.load(f) == asdict(spec):
                return model
    parent = os.path.dirname(folder)
    os.makedirs(parent, exist_ok=True)
    tmp = folder + ".partial"
    shutil.rmtree(tmp, ignore_errors=True)
    os.makedirs(os.path.join(tmp, "images"))
    try:
        cams = cameras(spec.num_views, spec.image_size)
        frames = []
        for i, cam in enumerate(cams):
            name = f"images/frame_{i:05d}.png"
            image = render_view(model, cam)
            Image.fromarray((image * 255).round().astype(np.uint8)).save(os.path.join(tmp, name))
            frames.append({"file_path": name, "transform_matrix": cam.to_opengl_c2w().tolist()})
            if progress is not None:
                progress(i + 1, len(cams))
        cam = cams[0]
        meta = {
            "camera_model": "PINHOLE", "w": cam.width, "h": cam.height, "fl_x": cam.fx, "fl_y": cam.fy, "cx": cam.cx, "cy": cam.cy,
            "ply_file_path": "points.ply", "frames": frames,
        }
        with open(os.path.join(tmp, "transforms.json"), "w") as f:
            json.dump(meta, f, indent=1)
        points, colours = initial_points(model, spec.num_points, spec.point_noise, spec.seed)
        _write_points_ply(os.path.join(tmp, "points.ply"), points, colours)
        with open(os.path.join(tmp, "scene.json"), "w") as f:
            json.dump(asdict(spec), f, indent=1)
        shutil.rmtree(folder, ignore_errors=True)
        os.replace(tmp, folder)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return model
