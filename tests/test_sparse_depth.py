"""The solve's sparse points as depth (``TrainerConfig.lambda_sparse_depth``): the targets a view gets, the loss
and its gradient, and what it does to training.

Oracles: the pinhole projection written out here (u = fx x / z + cx on the camera's axes) and each point's
distance along the camera's optical axis (its forward direction from the camera's centre, not the view matrix's
third row); the loss against its formula in numpy and its gradient against finite differences; in training, a
wall of one colour on a background of that colour, its own render as the photo, where the photo cannot tell
depth, so only the points can move it.
"""

import mlx.core as mx
import numpy as np
import pytest

from mlx3d.cameras import Camera
from mlx3d.splatting import GaussianModel
from mlx3d.training import GaussianTrainer, TrainerConfig
from mlx3d.training.geometry import sparse_depth_loss, sparse_points
from mlx3d.training.trainer import TrainingView


def _camera():
    return Camera.look_at(eye=(0.4, -3.0, 1.2), at=(0.0, 0.0, 0.2), up=(0, 0, 1), width=40, height=30, hfov=55.0)


def _project(camera, world):
    """Pixels and depth along the optical axis of ``world`` (N, 3), written out from the camera's centre and axes."""
    rot = np.asarray(camera.viewmat)[:3, :3]  # rows: the camera's x (right), y (down), z (forward) in world terms
    rel = world - np.asarray(camera.camera_center).reshape(3)
    x, y, z = rel @ rot[0], rel @ rot[1], rel @ rot[2]
    return np.stack([camera.fx * x / z + camera.cx, camera.fy * y / z + camera.cy], axis=1), z


def test_a_view_gets_the_axis_depth_of_the_points_it_observes_in_front_of_it_inside_its_image():
    camera = _camera()
    rng = np.random.default_rng(1)
    world = rng.uniform(-0.6, 0.6, (50, 3))
    pixels, depth = _project(camera, world)
    behind = 2.0 * np.asarray(camera.camera_center).reshape(3) - world[0]  # mirrored through the camera: behind it
    points = np.concatenate([world, [behind, world[1]]])
    observed = np.concatenate([pixels, [[5.0, 5.0], [-3.0, 10.0]]])  # the last observation is off the image
    index = np.arange(len(points))[::-1].copy()  # observations name points in any order
    got = sparse_points(camera, points, observed[::-1], index)
    assert got is not None
    xy, z = got
    assert xy.dtype == np.float32 and z.dtype == np.float32 and xy.shape == (50, 2)
    np.testing.assert_allclose(z, depth[::-1], rtol=1e-6)
    np.testing.assert_array_equal(xy, pixels[::-1].astype(np.float32))
    assert sparse_points(camera, points, observed[50:], np.array([50, 51])) is None


def test_the_loss_is_the_mean_inverse_depth_error_times_the_scale_and_its_gradient_reads_the_points_pixels():
    rng = np.random.default_rng(2)
    depth = rng.uniform(1.0, 4.0, (6, 8)).astype(np.float32)
    depth[0, 0] = 0.0  # a pixel the render leaves empty
    pixels = np.array([[0.2, 0.7], [3.5, 2.1], [3.9, 2.9], [7.99, 5.5]], np.float32)  # two points in pixel (2, 3)
    z = np.array([2.0, 0.9, 0.8, 2.5], np.float32)  # both points of pixel (2, 3) nearer than any depth there
    rows, cols = np.floor(pixels[:, 1]).astype(int), np.floor(pixels[:, 0]).astype(int)
    read = depth[rows, cols]
    inverse = np.where(read > 0, 1.0 / np.maximum(read, 1e-12), 0.0)
    want = np.mean(np.abs(inverse - 1.0 / z)) * 4.0
    assert float(sparse_depth_loss(mx.array(depth), pixels, z, 4.0)) == pytest.approx(want, rel=1e-6)

    grad = np.array(mx.grad(lambda d: sparse_depth_loss(d, pixels, z, 4.0))(mx.array(depth)))
    numeric = np.zeros_like(depth, dtype=np.float64)
    with np.errstate(divide="ignore"):  # the empty pixel's 1 / 0, which np.where then drops
        for r, c in {(int(r), int(c)) for r, c in zip(rows, cols)} - {(0, 0)}:
            step = np.zeros_like(depth, dtype=np.float64)
            step[r, c] = 1e-3
            up = np.mean(np.abs(np.where(read > 0, 1.0 / (read + step[rows, cols]), 0.0) - 1.0 / z)) * 4.0
            down = np.mean(np.abs(np.where(read > 0, 1.0 / (read - step[rows, cols]), 0.0) - 1.0 / z)) * 4.0
            numeric[r, c] = (up - down) / 2e-3
    np.testing.assert_allclose(grad, numeric, rtol=2e-3, atol=1e-6)
    assert grad[2, 3] != 0 and np.count_nonzero(grad) == 2  # the empty pixel pulls on nothing


def _wall(depth_shift: float):
    """A wall of grey Gaussians 2.5 in front of the camera (moved by ``depth_shift`` along its axis) on a grey
    background, its own render as the photo (grey everywhere: it cannot tell depth) and the camera."""
    camera = Camera.look_at(eye=(0.0, -2.5, 0.0), at=(0.0, 0.0, 0.0), up=(0, 0, 1), width=32, height=24, hfov=50.0)
    g = np.linspace(-1.6, 1.6, 14)
    xs, zs = np.meshgrid(g, g)
    means = np.stack([xs.ravel(), np.full(xs.size, depth_shift), zs.ravel()], axis=1).astype(np.float32)
    model = GaussianModel.from_points(means, np.full((len(means), 3), 0.5), sh_degree=0, initial_opacity=0.9)
    model.params["scales"] = mx.full((len(means), 3), np.log(0.18), dtype=mx.float32)
    target = np.array(model.render(camera, background=(0.5, 0.5, 0.5))["image"])  # no residual: no photometric pull
    return model, camera, target


@pytest.mark.parametrize("weight", [0.0, 0.5])
def test_points_behind_a_wall_the_photo_cannot_place_pull_it_back_to_their_depth(weight):
    model, camera, target = _wall(-0.4)  # the wall 0.4 in front of where the points say it is
    rng = np.random.default_rng(3)
    pixels = rng.uniform([4, 4], [28, 20], (40, 2)).astype(np.float32)
    points = (pixels, np.full(40, 2.5, np.float32))
    config = TrainerConfig(steps=1000, lambda_sparse_depth=weight, densify_from=10**6, lambda_dssim=0.0, sh_increase_every=0,
                           lr_means=4e-3, lr_means_final=4e-3)  # up to 0.01 a step: the 0.4 in 80 steps
    trainer = GaussianTrainer(model, config, scene_extent=2.5)

    def depth_at_points():
        d = np.array(trainer.model.render_depth(camera)["depth"])
        return d[np.floor(pixels[:, 1]).astype(int), np.floor(pixels[:, 0]).astype(int)].mean()

    before = depth_at_points()
    assert before == pytest.approx(2.1, abs=0.02)
    for _ in range(80):
        info = trainer.step_batch([TrainingView(camera, target, background=(0.5, 0.5, 0.5), points=points)])
    after = depth_at_points()
    if weight:
        assert "loss_sparse_depth" in info["stages"]
        assert abs(after - 2.5) < 0.25 * abs(before - 2.5), (before, after)
    else:
        assert "loss_sparse_depth" not in info["stages"]
        assert after == before  # the photo alone leaves it where it was


def test_a_run_takes_its_targets_from_the_datasets_observations_for_its_training_frames_only():
    from mlx3d.datasets.base import Dataset, Frame

    cameras = [_camera(), Camera.look_at(eye=(-2.0, -2.0, 1.0), at=(0, 0, 0), up=(0, 0, 1), width=40, height=30, hfov=55.0),
               Camera.look_at(eye=(2.5, 1.0, 0.5), at=(0, 0, 0), up=(0, 0, 1), width=40, height=30, hfov=55.0)]
    world = np.random.default_rng(4).uniform(-0.5, 0.5, (30, 3))
    observations = []
    for k, camera in enumerate(cameras):
        index = np.arange(k, 30, 2) if k < 2 else np.zeros(0, np.int64)  # the third observes nothing
        observations.append((_project(camera, world[index])[0].astype(np.float32), index))
    frames = [Frame(c, f"f{k}.png", f"f{k}") for k, c in enumerate(cameras)]
    dataset = Dataset(frames, splits={"train": [1, 2], "test": [0]}, points=world, observations=observations)
    model = GaussianModel.from_points(world.astype(np.float32), np.full((30, 3), 0.5), sh_degree=0)
    targets = GaussianTrainer(model, TrainerConfig(lambda_sparse_depth=0.01), scene_extent=1.0).sparse_depth_targets(dataset)
    assert list(targets) == [1]  # frame 0 is held out, frame 2 observes no point
    np.testing.assert_allclose(targets[1][1], _project(cameras[1], world[1::2])[1], rtol=1e-6)
    assert GaussianTrainer(model, TrainerConfig(), scene_extent=1.0).sparse_depth_targets(dataset) == {}
