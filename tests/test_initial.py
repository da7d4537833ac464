"""Where training starts (mlx3d.training.initial): random points for datasets without any, the
backdrop sphere for opaque photos, the methods' initial opacity and scale, MCMC's default budget."""

import json
import math

import numpy as np
import pytest
from PIL import Image
from plyfile import PlyData, PlyElement

from mlx3d.cameras import Camera
from mlx3d.cli import main
from mlx3d.datasets import load_dataset
from mlx3d.datasets.base import Dataset, Frame
from mlx3d.training import GaussianTrainer, TrainerConfig
from mlx3d.training.initial import initial_state, look_at_centre, mcmc_budget, random_cube

SKY = (0.45, 0.62, 0.9)


def _ring(n=8, radius=4.0, size=32, at=(0.0, 0.0, 0.0), height=1.5, fov=40.0):
    return [Camera.look_at(eye=(at[0] + radius * math.cos(a), at[1] + radius * math.sin(a), at[2] + height), at=at,
                           up=(0, 0, 1), width=size, height=size, fov=fov) for a in np.linspace(0, 2 * math.pi, n, endpoint=False)]


def _write_images(folder, cameras, colour, alpha=None):
    rgba = np.zeros((cameras[0].height, cameras[0].width, 4), np.uint8)
    rgba[..., :3] = np.round(np.array(colour) * 255)
    rgba[..., 3] = 255 if alpha is None else alpha
    for i, _ in enumerate(cameras):
        Image.fromarray(rgba).save(folder / f"r_{i}.png")


def _nerf_synthetic(folder, cameras, alpha=0, ply=None):
    """A NeRF-synthetic folder: transforms_{train,test}.json, RGBA images (alpha 0: transparent)."""
    _write_images(folder, cameras, SKY, alpha)
    angle = 2 * math.atan(0.5 * cameras[0].width / cameras[0].fx)
    frames = [{"file_path": f"./r_{i}", "transform_matrix": c.to_opengl_c2w().tolist()} for i, c in enumerate(cameras)]
    train = {"camera_angle_x": angle, "frames": frames[1:]}
    if ply is not None:
        train["ply_file_path"] = ply
    (folder / "transforms_train.json").write_text(json.dumps(train))
    (folder / "transforms_test.json").write_text(json.dumps({"camera_angle_x": angle, "frames": frames[:1]}))
    return folder


def test_look_at_centre_and_random_cube_follow_the_cameras():
    at = (1.0, -2.0, 0.5)
    cams = _ring(12, radius=4.03, at=at, height=0.0, fov=2 * math.degrees(0.3456))  # lego: 4.03 away, fov 0.69 rad
    np.testing.assert_allclose(look_at_centre(cams), at, atol=1e-6)
    points, colours, centre, half = random_cube(cams, 5000, seed=3)
    assert half == pytest.approx(4.03 * math.tan(0.3456), rel=1e-4)  # 1.45; the 3DGS reference uses 1.3 for lego
    assert points.shape == (5000, 3) and colours.shape == (5000, 3) and colours.dtype == np.uint8
    lo, hi = points.min(axis=0) - centre, points.max(axis=0) - centre
    assert np.all(lo >= -half) and np.all(hi <= half) and np.all(lo < -0.95 * half) and np.all(hi > 0.95 * half)  # fills the cube
    assert colours.std() > 60  # random colours, not one grey
    fixed = random_cube(cams, 10, extent=0.25)[0]
    assert np.abs(fixed - np.array(at)).max() <= 0.25


def test_a_nerf_synthetic_scene_without_points_starts_from_random_points(tmp_path):
    cams = _ring()
    dataset = load_dataset(_nerf_synthetic(tmp_path, cams))
    assert dataset.points is None
    start = initial_state(dataset, TrainerConfig(init_random_points=3000, seed=1))
    assert len(start.model) == 3000
    assert any("3,000 random points" in note for note in start.notes)
    means = np.asarray(start.model.means)
    assert np.abs(means).max() <= math.hypot(4.0, 1.5) * math.tan(math.radians(20.0)) * 1.001  # the cube the ring looks at
    # the same seed gives the same start
    again = initial_state(dataset, TrainerConfig(init_random_points=3000, seed=1))
    np.testing.assert_array_equal(np.asarray(again.model.means), means)


def test_ply_file_path_in_transforms_train_gives_the_points(tmp_path):
    points = np.random.default_rng(0).uniform(-0.5, 0.5, (40, 3)).astype(np.float32)
    verts = np.zeros(40, dtype=[("x", "f4"), ("y", "f4"), ("z", "f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    for i, axis in enumerate("xyz"):
        verts[axis] = points[:, i]
    verts["red"] = 200
    (tmp_path / "pts").mkdir()
    PlyData([PlyElement.describe(verts, "vertex")]).write(str(tmp_path / "pts" / "sparse.ply"))
    dataset = load_dataset(_nerf_synthetic(tmp_path, _ring(), ply="pts/sparse.ply"))
    np.testing.assert_array_equal(dataset.points, points)
    assert (dataset.point_colors[:, 0] == 200).all()
    start = initial_state(dataset, TrainerConfig())
    assert len(start.model) == 40 and "the dataset's 40" in start.notes[0]


def _dataset(cameras, folder, alpha=None, points=None):
    _write_images(folder, cameras, SKY, alpha)
    frames = [Frame(c, folder / f"r_{i}.png", f"r_{i}.png") for i, c in enumerate(cameras)]
    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.5, 0.5, (400, 3)).astype(np.float32) if points is None else points
    return Dataset(frames, points=pts, point_colors=np.full((len(pts), 3), 90, np.uint8), root=folder)


def test_mcmc_on_opaque_photos_seeds_a_far_backdrop_coloured_by_the_photos(tmp_path):
    cams = _ring(12)
    dataset = _dataset(cams, tmp_path)
    start = initial_state(dataset, TrainerConfig(method="mcmc", init_background_points=500))
    model = start.model
    assert len(model) == 400 + 500
    means = np.asarray(model.means)[400:]
    centroid = np.mean([dataset.frames[i].camera.center for i in dataset.train], axis=0)
    radius = 10.0 * dataset.scene_extent()
    np.testing.assert_allclose(np.linalg.norm(means - centroid, axis=1), radius, rtol=1e-5)
    seen = np.zeros(len(means), bool)
    for c in (dataset.frames[i].camera for i in dataset.train):
        uv, depth = c.project_points(means)
        seen |= (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < c.width) & (uv[:, 1] >= 0) & (uv[:, 1] < c.height)
    assert seen.all()  # each lands inside some training view
    np.testing.assert_allclose(np.asarray(model.colors)[400:], np.tile(SKY, (500, 1)), atol=1.5 / 255)  # the sky's colour
    # the methods' starting opacity and scale: MCMC 0.5 and 0.1 x the 3-NN distance, vanilla 0.1 and 1
    vanilla = initial_state(dataset, TrainerConfig(method="vanilla"))
    assert len(vanilla.model) == 400 + 1000  # vanilla seeds its backdrop by default too (at least 1,000 points)
    assert len(initial_state(dataset, TrainerConfig(method="2dgs")).model) == 400  # surfels for meshes: none
    np.testing.assert_allclose(np.asarray(model.opacities)[:400], 0.5, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(vanilla.model.opacities), 0.1, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(model.params["scales"])[:400], np.asarray(vanilla.model.params["scales"])[:400] + math.log(0.1), atol=1e-5)


def test_no_backdrop_when_the_photos_have_alpha_or_when_turned_off(tmp_path):
    cams = _ring(6)
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    with_alpha = _dataset(cams, tmp_path / "a", alpha=np.where(np.arange(32)[:, None] < 16, 255, 0))
    assert len(initial_state(with_alpha, TrainerConfig(method="mcmc")).model) == 400
    opaque = _dataset(cams, tmp_path / "b")
    assert len(initial_state(opaque, TrainerConfig(method="mcmc", init_background_points=0)).model) == 400
    assert len(initial_state(opaque, TrainerConfig(method="mcmc")).model) == 400 + 1000  # the default: at least 1,000


def test_mcmc_grows_to_its_default_budget_on_schedule(tmp_path):
    assert mcmc_budget(20_000, 256 * 256) == 65_536
    assert mcmc_budget(20_000, 128 * 128) == 40_000  # at least twice the start
    assert mcmc_budget(900_000, 4000 * 3000) == 1_000_000
    cams = _ring(6, size=16)
    dataset = _dataset(cams, tmp_path, points=np.random.default_rng(1).uniform(-0.5, 0.5, (150, 3)).astype(np.float32))
    config = TrainerConfig(method="mcmc", steps=80, densify_from=4, densify_every=4, init_background_points=0, sh_increase_every=0)
    start = initial_state(dataset, config)
    assert start.config.max_gaussians == 300 and any("MCMC budget: 300" in n for n in start.notes)
    trainer = GaussianTrainer(start.model, start.config, scene_extent=dataset.scene_extent())
    history = trainer.fit(dataset)
    counts = {h["step"]: h["num_gaussians"] for h in history}
    expected, n = {}, 150
    for step in range(1, 81):
        if step > 4 and step % 4 == 0:
            n = min(300, int(n * 1.05))
        expected[step] = n
    assert counts == expected  # +5% every event, then flat at the budget
    assert counts[60] < 300 and counts[68] == 300  # the 15th event (step 64) reaches it: 150 * 1.05^15 > 300


def test_a_trainer_without_a_budget_still_grows(tmp_path):
    """Scripts that build GaussianTrainer themselves get the same default budget from fit()."""
    cams = _ring(6, size=24)
    dataset = _dataset(cams, tmp_path)
    from mlx3d.splatting import GaussianModel

    model = GaussianModel.from_points(dataset.points, dataset.point_colors, sh_degree=0)
    trainer = GaussianTrainer(model, TrainerConfig(method="mcmc", steps=12, densify_from=2, densify_every=5), scene_extent=1.0)
    trainer.fit(dataset)
    assert trainer.config.max_gaussians == 800 and len(trainer.model) > 400


def test_mlx3d_train_prints_its_defaults_and_trains_a_scene_without_points(tmp_path, capsys):
    folder = tmp_path / "lego"
    folder.mkdir()
    _nerf_synthetic(folder, _ring(6, size=24), alpha=255)
    out = tmp_path / "out" / "model.ply"
    out.parent.mkdir()
    assert main(["train", str(folder), "--out", str(out), "--method", "mcmc", "--steps", "3", "--random-points", "500"]) == 0
    printed = capsys.readouterr().out
    assert "500 random points" in printed and "the dataset has none" in printed
    assert "initial opacity 0.5, scale 0.1" in printed
    assert "MCMC budget: 3,000 Gaussians" in printed  # twice the 500 + 1,000 backdrop points
    assert "+5% every 100 steps from step 500 to 25000" in printed
    assert "training background: random, a new colour every step (the photos are opaque and the backdrop covers the frame" in printed
    assert main(["train", str(folder), "--out", str(out), "--steps", "2", "--random-points", "300"]) == 0
    printed = capsys.readouterr().out
    assert "initial opacity 0.1, scale 1" in printed and "densification: every 100 steps from step 500 to 15000" in printed
    assert "training background: random" in printed  # vanilla seeds its backdrop too
    assert main(["train", str(folder), "--out", str(out), "--method", "2dgs", "--steps", "1", "--random-points", "300"]) == 0
    assert "training background: black (background)" in capsys.readouterr().out  # 2dgs seeds none: nothing to cover the frame with
    assert main(["train", str(folder), "--out", str(out), "--steps", "1", "--random-points", "300", "--opaque-background", "same", "--background", "white"]) == 0
    assert "training background: white (background)" in capsys.readouterr().out
    assert "bilateral grid: off (the exposure spread is not measurable without the sparse model's tracks" in printed
    for method, lr in (("mcmc", "0.001"), ("vanilla", "0.002")):
        assert main(["train", str(folder), "--out", str(out), "--method", method, "--steps", "1", "--random-points", "300", "--bilateral-grid"]) == 0
        assert f"bilateral grid: 16x16x8 per training image, learning rate {lr}" in capsys.readouterr().out
