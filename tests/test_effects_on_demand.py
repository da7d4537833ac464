"""Effects on demand: a training step runs exactly the stages its plan lists, and the plan lists
only what the scene, camera and configuration need."""

import math

import numpy as np
import pytest

from mlx3d.cameras import Camera
from mlx3d.cli import main
from mlx3d.splatting import GaussianModel
from mlx3d.training.plan import OPTIONAL_STAGES, step_plan
from mlx3d.training.trainer import GaussianTrainer, TrainerConfig, TrainingView


def problem(camera_model="pinhole"):
    rng = np.random.default_rng(0)
    model = GaussianModel.from_points(rng.uniform(-0.5, 0.5, (80, 3)).astype(np.float32), rng.uniform(0, 1, (80, 3)), sh_degree=2, initial_opacity=0.6)
    kw = {"dist": (0.02, 0.0, 0.0, 0.0)} if camera_model == "fisheye" else {}
    cam = Camera.look_at(eye=(0.0, -3.0, 1.0), at=(0, 0, 0), up=(0, 0, 1), width=32, height=24, hfov=50.0, model=camera_model, **kw)
    target = rng.uniform(0, 1, (24, 32, 3)).astype(np.float32)
    return model, cam, target


# (config, camera model, step, stages that must run, stages that must not)
CASES = [
    (dict(), "pinhole", 0, {"project_ewa", "eval_sh_degree_0", "rasterize_rgb", "loss_l1", "loss_dssim", "screen_statistics"},
     {"project_ut", "antialias_compensation", "gaussian_normals", "bilateral_grid", "loss_depth_variance", "sgld_noise", "thickness_clamp"}),
    (dict(lambda_dssim=0.0), "pinhole", 0, {"loss_l1"}, {"loss_dssim"}),
    (dict(antialias=True), "pinhole", 0, {"antialias_compensation"}, set()),
    (dict(projection="ut"), "pinhole", 0, {"project_ut"}, {"project_ewa"}),
    (dict(), "fisheye", 0, {"project_ut"}, {"project_ewa"}),
    (dict(sh_increase_every=1), "pinhole", 2, {"eval_sh_degree_2"}, {"eval_sh_degree_0"}),
    (dict(method="mcmc"), "pinhole", 0, {"loss_opacity_l1", "loss_scale_l1", "sgld_noise"}, {"thickness_clamp", "gaussian_normals", "screen_statistics"}),
    (dict(method="mcmc", mcmc_opacity_reg=0.0, mcmc_noise_lr=0.0), "pinhole", 0, {"loss_scale_l1"}, {"loss_opacity_l1", "sgld_noise"}),
    (dict(method="2dgs"), "pinhole", 0, {"thickness_clamp", "rasterize_rgb"}, {"gaussian_normals", "loss_depth_variance", "loss_normal_consistency"}),
    (dict(method="2dgs", geometry_from=0), "pinhole", 0,
     {"gaussian_normals", "rasterize_rgb+depth_planes+depth2+normals", "loss_depth_variance", "loss_normal_consistency"}, set()),
    (dict(method="2dgs", geometry_from=0, lambda_2d_normal_consistency=0.0), "pinhole", 0,
     {"rasterize_rgb+depth2", "loss_depth_variance"}, {"loss_normal_consistency", "gaussian_normals"}),
    (dict(lambda_2d_normal_consistency=0.1, geometry_from=0), "pinhole", 0, {"rasterize_rgb+depth+normals", "loss_normal_consistency"}, {"thickness_clamp"}),
    (dict(bilateral_grid=True), "pinhole", 0, {"bilateral_grid", "loss_bilateral_tv"}, set()),
    (dict(bilateral_grid=True, lambda_bilateral_tv=0.0), "pinhole", 0, {"bilateral_grid"}, {"loss_bilateral_tv"}),
    (dict(densify_from=0, densify_every=1), "pinhole", 0, {"densify", "screen_statistics"}, {"relocate"}),
    # the densification statistics are gathered up to the last densification, and not when none comes
    (dict(densify_from=0, densify_every=10, densify_until=50), "pinhole", 49, {"densify", "screen_statistics"}, set()),
    (dict(densify_from=0, densify_every=10, densify_until=50), "pinhole", 50, set(), {"densify", "screen_statistics"}),
    (dict(densify_from=60, densify_until=90), "pinhole", 0, set(), {"screen_statistics"}),
]


@pytest.mark.parametrize("index", range(len(CASES)))
def test_a_step_runs_exactly_its_plan_and_nothing_unneeded(index):
    overrides, camera_model, done, must, must_not = CASES[index]
    model, cam, target = problem(camera_model)
    config = TrainerConfig(steps=100, **overrides)
    trainer = GaussianTrainer(model, config, scene_extent=3.0, num_images=1)
    trainer.step_count = done
    trainer.active_sh_degree = min(done // config.sh_increase_every, model.sh_degree)
    plan = step_plan(config, cam, trainer.active_sh_degree, done)
    info = trainer.step(cam, target, image_index=0)
    assert info["stages"] == plan.stages
    assert math.isfinite(info["loss"])
    stages = set(plan.stages)
    assert must <= stages, must - stages
    assert not (must_not & stages), must_not & stages
    assert set(plan.skipped) & stages == set()
    assert set(OPTIONAL_STAGES) - stages <= set(plan.skipped)


def test_sparse_depth_renders_depth_only_for_a_view_that_observes_points():
    model, cam, target = problem()
    points = (np.array([[10.5, 8.5], [20.0, 12.0]], np.float32), np.array([3.0, 3.2], np.float32))
    trainer = GaussianTrainer(model, TrainerConfig(steps=100, lambda_sparse_depth=0.1), scene_extent=3.0)
    with_points = trainer.step_batch([TrainingView(cam, target, points=points)])
    assert {"rasterize_rgb+depth", "loss_sparse_depth"} <= set(with_points["stages"])
    assert with_points["sparse_depth_loss"] > 0
    without = trainer.step(cam, target)
    assert "rasterize_rgb" in without["stages"] and "loss_sparse_depth" not in without["stages"]
    off = GaussianTrainer(model, TrainerConfig(steps=100), scene_extent=3.0).step_batch([TrainingView(cam, target, points=points)])
    assert "rasterize_rgb" in off["stages"] and "loss_sparse_depth" not in off["stages"] and "sparse_depth_loss" not in off


def test_a_plain_render_runs_only_projection_binning_sh_and_colour():
    model, cam, _ = problem()
    out = model.render(cam)
    assert out["stages"] == ("project_ewa", "bin_tiles", "eval_sh_degree_2", "rasterize_rgb")
    assert "depth" not in out and "normals" not in out


def test_info_plan_prints_the_stages(tmp_path, capsys):
    model, _, _ = problem()
    model.save_ply(tmp_path / "m.ply")
    assert main(["info", "--plan", str(tmp_path / "m.ply"), "--method", "2dgs", "--step", "2000", "--camera", "fisheye"]) == 0
    out = capsys.readouterr().out
    assert "render:              project_ut -> bin_tiles -> eval_sh_degree_2 -> rasterize_rgb" in out
    assert "training step 2,000 (2dgs, SH degree 1): project_ut" in out
    assert "loss_normal_consistency -> adam -> thickness_clamp -> screen_statistics -> sh_up" in out
    assert "not run:             antialias_compensation, bilateral_grid" in out
