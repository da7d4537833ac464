"""Photos with known cameras, for testing the camera solve (``mlx3d.sfm``) against the truth.

``photo_orbit(folder, count)`` renders a textured scene (the demo's ground and sphere, each splat with its
own colour so that SIFT finds features everywhere) with our renderer from ``count`` cameras on two rings
and writes them as PNGs ``000.png``, ``001.png``, ...; it returns the true cameras in that order.
``similarity_errors`` aligns solved camera centres to true ones and reports rotation and position errors.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

TARGET = np.array([0.0, 0.0, 0.4])


def orbit_cameras(count: int, size: int = 256, distance: float = 4.0, elevations=(20.0, 40.0), fov: float = 50.0):
    """``count`` cameras alternating between rings at ``elevations`` (degrees), all looking at TARGET (z up)."""
    from mlx3d.cameras import Camera

    cameras = []
    for i in range(count):
        azimuth = 2 * math.pi * i / count
        elevation = math.radians(elevations[i % len(elevations)])
        eye = TARGET + distance * np.array([math.cos(elevation) * math.cos(azimuth),
                                            math.cos(elevation) * math.sin(azimuth), math.sin(elevation)])
        cameras.append(Camera.look_at(eye=eye, at=TARGET, up=(0, 0, 1), fov=fov, width=size, height=size))
    return cameras


def _scene(seed: int = 0):
    import mlx.core as mx

    from mlx3d.demo import demo_scene

    points, colours, floater = demo_scene(n_surface=40000, n_floaters=0, seed=seed)
    rng = np.random.default_rng(seed + 1)
    colours = np.clip(0.4 * colours + 0.6 * rng.uniform(0, 1, colours.shape), 0, 1).astype(np.float32)
    n = len(points)
    return (mx.array(points), mx.array(np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)).astype(np.float32)),
            mx.array(np.full((n, 3), 0.018, np.float32)), mx.array(np.full(n, 0.95, np.float32)), mx.array(colours))


def photo_orbit(folder, count: int = 24, size: int = 256, seed: int = 0, cameras=None):
    """Render the scene from ``cameras`` (default :func:`orbit_cameras`) into ``folder``; returns the cameras."""
    from PIL import Image

    from mlx3d.render import render_gaussians

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    cameras = orbit_cameras(count, size) if cameras is None else cameras
    means, quats, scales, opacities, colours = _scene(seed)
    sky = np.array([0.55, 0.65, 0.8], np.float32)
    for i, camera in enumerate(cameras):
        out = render_gaussians(camera, means, quats, scales, opacities, colors=colours, background=sky)
        rgb = np.clip(np.array(out["image"]) * 255 + 0.5, 0, 255).astype(np.uint8)
        Image.fromarray(rgb).save(folder / f"{i:03d}.png")
    return cameras


def umeyama(a: np.ndarray, b: np.ndarray):
    """(scale, rotation, translation) minimising |s R a + t - b|^2 over rows."""
    ma, mb = a.mean(0), b.mean(0)
    u, sv, vt = np.linalg.svd((b - mb).T @ (a - ma))
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rot = u @ d @ vt
    scale = float((sv * np.diag(d)).sum() / ((a - ma) ** 2).sum())
    return scale, rot, mb - scale * rot @ ma


def similarity(solved, truth):
    """(scale, rotation (3,3), translation (3,)) taking the solved cameras' frame to the true one: ``s R x + t``.

    Fitted (Umeyama) to each camera's centre and to points one spread of the centres along its viewing and up
    axes, so that cameras on a line (a walk) fix the roll about it too."""
    a = np.array([c.center for c in solved])
    b = np.array([c.center for c in truth])
    spread_a = float(np.sqrt(((a - a.mean(0)) ** 2).sum(1).mean()))
    spread_b = float(np.sqrt(((b - b.mean(0)) ** 2).sum(1).mean()))

    def marks(cameras, centres, spread):  # centre, and a point ahead and above each camera
        return np.concatenate([centres, centres + spread * np.array([c.R[2] for c in cameras]),
                               centres - spread * np.array([c.R[1] for c in cameras])])

    return umeyama(marks(solved, a, spread_a), marks(truth, b, spread_b))


def similarity_errors(solved, truth):
    """Align solved cameras to true ones by :func:`similarity` and return (max rotation error in degrees, max
    position error as a fraction of the true centres' diameter)."""
    a = np.array([c.center for c in solved])
    b = np.array([c.center for c in truth])
    scale, rot, shift = similarity(solved, truth)
    aligned = scale * a @ rot.T + shift
    diameter = float(np.max(np.linalg.norm(b[:, None] - b[None], axis=-1)))
    position = float(np.max(np.linalg.norm(aligned - b, axis=1))) / diameter
    angles = []
    for cs, ct in zip(solved, truth):
        # camera-to-world rotations: the solved one mapped into the true frame, against the true one
        r = (rot @ cs.R.T).T @ ct.R.T
        angles.append(math.degrees(math.acos(np.clip((np.trace(r) - 1) / 2, -1, 1))))
    return max(angles), position
