"""Initial points of opaque photos without a point cloud (mlx3d/training/plane_sweep.py).

Oracle: photos ray-traced here of known geometry (a textured ground plane z = 0
running to the horizon under a plain sky): every point found must lie on the
plane, where its colour is the plane's there; the sky, which has no depth to
find, gets none; a scene without texture gives too few points and training
starts from the random cube as before.
"""

import math

import numpy as np

from mlx3d.cameras import Camera
from mlx3d.datasets.base import Dataset, Frame
from mlx3d.training import TrainerConfig
from mlx3d.training.initial import initial_state, look_at_centre
from mlx3d.training.plane_sweep import sweep_points

SKY = np.array([0.55, 0.7, 0.95])


def ground_colour(x, y):
    """A texture without a period (incommensurate sinusoids), so a match has one depth."""
    r = 0.5 + 0.25 * np.sin(3.1 * x + 0.7) + 0.2 * np.sin(4.3 * y + 1.3 * x)
    g = 0.5 + 0.25 * np.sin(2.3 * y - 0.4) + 0.2 * np.sin(5.1 * x - 1.7 * y)
    b = 0.4 + 0.2 * np.sin(3.7 * (x + y)) + 0.15 * np.sin(6.3 * x)
    return np.clip(np.stack([r, g, b], axis=-1), 0.0, 1.0)


def ring(n=16, radius=4.0, height=1.6, size=64):
    return [Camera.look_at(eye=(radius * math.cos(a), radius * math.sin(a), height), at=(0.0, 0.0, 0.0), up=(0, 0, 1),
                           width=size, height=size, fov=60.0) for a in np.linspace(0, 2 * math.pi, n, endpoint=False)]


def photo(camera, textured=True):
    """The plane z = 0 (textured, or plain grey) under the sky, traced through every pixel centre."""
    origins, dirs = (np.asarray(a) for a in camera.rays())
    t = np.where(dirs[..., 2] < -1e-6, -origins[..., 2] / np.where(dirs[..., 2] < -1e-6, dirs[..., 2], -1.0), np.inf)
    hit = origins + dirs * np.where(np.isfinite(t), t, 0.0)[..., None]
    ground = ground_colour(hit[..., 0], hit[..., 1]) if textured else np.full(hit.shape, 0.45)
    return np.where(np.isfinite(t)[..., None], ground, SKY).astype(np.float32)


class PhotoDataset(Dataset):
    """Photos kept in memory (no files): ``load_image`` returns them as a loader would."""

    def __init__(self, cameras, images):
        super().__init__([Frame(c, f"view_{i}.png", f"view_{i}.png") for i, c in enumerate(cameras)], test_every=None)
        self.images = images

    def load_image(self, i, background=None, rng=None, *, return_background=False):
        return (self.images[i], None, None) if return_background else (self.images[i], None)


def test_points_lie_on_the_surface_and_the_sky_gets_none():
    cameras = ring()
    images = [photo(c) for c in cameras]
    found = sweep_points(cameras, images, near=0.4, far=60.0, rays_per_view=512, seed=0)
    assert len(found.points) > 0.1 * found.rays  # the near ground (the far ground is the backdrop's, the sky has no depth)
    z = found.points[:, 2]
    # Within the depth samples' spacing (64 in 1/depth from 0.4 to 60: 0.08 at 2 units, 0.2 at 3):
    # the error along a ray that meets the ground at a grazing angle is mostly sideways.
    assert np.median(np.abs(z)) < 0.04 and np.mean(np.abs(z) < 0.1) > 0.95, np.percentile(np.abs(z), [50, 90, 99])
    on = np.abs(z) < 0.1
    want = ground_colour(found.points[on, 0].astype(np.float64), found.points[on, 1].astype(np.float64))
    assert np.median(np.abs(found.colours[on] / 255.0 - want)) < 0.03
    # Nothing in the sky: hardly a point above the plane (chance matches next to the cameras), none
    # sky-coloured beyond one in 200, none near the far end of the sweep (the backdrop's).
    assert np.mean(z > 0.3) < 0.02
    sky = np.abs(found.colours / 255.0 - SKY).max(axis=1) < 0.05
    assert np.mean(sky) < 0.005 and np.linalg.norm(found.points, axis=1).max() < 30.0
    again = sweep_points(cameras, images, near=0.4, far=60.0, rays_per_view=512, seed=0)
    np.testing.assert_array_equal(again.points, found.points)


def test_initial_state_starts_opaque_photos_from_the_sweep_and_plain_ones_from_the_cube():
    cameras = ring()
    textured = PhotoDataset(cameras, [photo(c) for c in cameras])
    start = initial_state(textured, TrainerConfig(init_random_points=5000, seed=0))
    assert any("where the photos agree" in note for note in start.notes), start.notes
    means = np.asarray(start.model.means)
    near = np.linalg.norm(means - look_at_centre(cameras), axis=1) < 20.0  # the backdrop sphere is far away
    assert np.mean(np.abs(means[near, 2]) < 0.1) > 0.95

    plain = PhotoDataset(cameras, [photo(c, textured=False) for c in cameras])
    start = initial_state(plain, TrainerConfig(init_random_points=3000, seed=0))
    assert any("3,000 random points" in note for note in start.notes), start.notes


def test_progress_is_reported_per_view():
    cameras = ring(n=6, size=32)
    calls = []
    sweep_points(cameras, [photo(c) for c in cameras], near=0.4, far=60.0, rays_per_view=64, progress=lambda d, t: calls.append((d, t)))
    assert calls == [(k, 6) for k in range(1, 7)]
