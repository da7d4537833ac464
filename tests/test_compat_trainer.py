"""``mlx3d.splatting.GaussianTrainer`` / ``TrainerConfig`` as the original mlx3D's documentation uses them.

Scripts written for the original import the trainer from ``mlx3d.splatting``,
construct ``TrainerConfig`` with its field names (``lr_*``,
``densify_grad_threshold``, ``sh_increase_every``, ``white_background``,
``mcmc_*``) and read ``step()``'s info keys. The defaults below are the
original's, written down from its ``TrainerConfig``.
"""

import math

import mlx.core as mx
import numpy as np
import pytest

from mlx3d.cameras import Camera
from mlx3d.splatting import GaussianModel, GaussianTrainer, TrainerConfig
from mlx3d.training import trainer as ours
from mlx3d.training.density import sgld_noise

ORIGINAL_DEFAULTS = {
    "method": "vanilla", "lr_means": 1.6e-4, "lr_means_final": 1.6e-6, "lr_means_max_steps": 30_000,
    "lr_scales": 5e-3, "lr_quats": 1e-3, "lr_opacities": 5e-2, "lr_sh_dc": 2.5e-3, "lr_sh_rest": 2.5e-3 / 20.0,
    "lambda_dssim": 0.2, "antialias": False, "lambda_2d_depth_variance": 0.0,
    "lambda_2d_normal_consistency": 0.0, "geometry_min_alpha": 0.05, "densify_from": 500, "densify_until": 15_000,
    "densify_every": 100, "densify_grad_threshold": 0.0002, "mcmc_relocate_frac": 0.02, "mcmc_min_opacity": 0.01,
    "mcmc_jitter_scale": 0.25, "mcmc_noise_scale": 0.01, "two_d_thickness": 1e-4, "opacity_reset_every": 3000,
    "sh_increase_every": 1000, "white_background": False, "max_gaussians": None, "low_memory": False, "cache_limit_gb": 2.0,
}


def _scene(n=300, seed=0):
    rng = np.random.default_rng(seed)
    points = rng.uniform(-0.6, 0.6, (n, 3)).astype(np.float32)
    colors = rng.uniform(0.1, 0.9, (n, 3)).astype(np.float32)
    camera = Camera.look_at(eye=(0.0, 0.0, -4.0), at=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), width=32, height=24, fov=50)
    return points, colors, camera


@pytest.mark.parametrize("method", ["vanilla", "mcmc", "2dgs"])
def test_defaults_are_the_originals(method):
    config = TrainerConfig(method=method)
    for name, value in ORIGINAL_DEFAULTS.items():
        if name != "method":
            assert getattr(config, name) == value, name
    assert config.background == "black" and TrainerConfig(white_background=True).background == "white"
    assert config.mcmc_growth == 0.0  # the original's MCMC keeps the count fixed
    assert config.projection == "auto"  # EWA on pinhole cameras, as the original's 'ewa'; see mlx3d.splatting.trainer


def test_original_field_names_drive_our_trainer():
    """The same fields in mlx3d.training (our defaults): the names mean the same there."""
    config = ours.TrainerConfig(lr_means_max_steps=10, lr_means=1e-3, lr_means_final=1e-5, lr_quats=2e-3, steps=100)
    model = GaussianModel.from_points(np.random.default_rng(0).normal(size=(20, 3)))
    trainer = ours.GaussianTrainer(model, config, scene_extent=2.0)
    assert trainer.learning_rates()["means"] == pytest.approx(1e-3 * 2.0)
    assert trainer.learning_rates()["quats"] == pytest.approx(2e-3)
    trainer.step_count = 5  # log-linear: the geometric mean halfway
    assert trainer.learning_rates()["means"] == pytest.approx(math.sqrt(1e-3 * 1e-5) * 2.0)
    trainer.step_count = 50  # past lr_means_max_steps (not `steps`): the final rate
    assert trainer.learning_rates()["means"] == pytest.approx(1e-5 * 2.0)
    assert [s for s in range(1, 40) if "sh_up" in ours.events_at(ours.TrainerConfig(sh_increase_every=7), s)] == [7, 14, 21, 28, 35]


def test_a_script_for_the_original_trains():
    """The original's README flow: from_points, TrainerConfig, GaussianTrainer(model, config, scene_extent), step()."""
    points, colors, camera = _scene()
    target_model = GaussianModel.from_points(points, colors)
    target = mx.stop_gradient(target_model.render(camera, background=mx.ones(3))["image"])
    for method in ("vanilla", "mcmc"):
        model = GaussianModel.from_points(points + 0.05, np.full_like(colors, 0.5))
        trainer = GaussianTrainer(model, TrainerConfig(method=method, white_background=True, densify_from=5, densify_every=10), scene_extent=1.0)
        infos = [trainer.step(camera, target) for _ in range(40)]
        for key in ("loss", "num_gaussians", "step", "active_sh_degree", "lr_means", "method", "densify", "opacity_reset",
                    "sh_degree_changed", "geometry"):
            assert key in infos[-1], key
        assert infos[-1]["method"] == method and infos[-1]["step"] == 40
        assert infos[-1]["loss"] < 0.8 * infos[0]["loss"]
        assert [i["step"] for i in infos if i["densify"] is not None] == [10, 20, 30, 40]
        if method == "mcmc":
            assert {i["num_gaussians"] for i in infos} == {len(points)}  # the original's MCMC: a fixed count
            assert all(set(i["densify"]) == {"relocated", "added"} for i in infos if i["densify"] is not None)


def test_isotropic_noise_has_the_original_scale():
    """mcmc_noise_scale: N(0, σ²) on every mean with σ = scale · extent · sqrt(means lr), opacity or not."""
    n = 20_000
    params = {
        "means": mx.zeros((n, 3)), "opacities": mx.full((n,), 8.0), "quats": mx.array(np.tile([1.0, 0, 0, 0], (n, 1)).astype(np.float32)),
        "scales": mx.full((n, 3), -2.0),
    }
    moved = np.array(sgld_noise(params, 1e-4, 0.0, np.random.default_rng(0), isotropic=0.01 * 3.0 * math.sqrt(1e-4)))
    assert moved.std() == pytest.approx(3e-4, rel=0.02) and abs(moved.mean()) < 1e-5
    # The trainer passes exactly that σ for the original's default config.
    points, colors, camera = _scene(50)
    model = GaussianModel.from_points(points, colors)
    trainer = GaussianTrainer(model, TrainerConfig(method="mcmc", densify_from=10**6), scene_extent=3.0)
    seen = {}
    original = ours.sgld_noise

    def spy(params, lr, noise_lr, rng, isotropic):
        seen.update(lr=lr, noise_lr=noise_lr, isotropic=isotropic)
        return original(params, lr, noise_lr, rng, isotropic)

    ours.sgld_noise, saved = spy, ours.sgld_noise
    try:
        trainer.step(camera, mx.zeros((24, 32, 3)))
    finally:
        ours.sgld_noise = saved
    assert seen["noise_lr"] == 0.0
    assert seen["isotropic"] == pytest.approx(0.01 * 3.0 * math.sqrt(1.6e-4 * 3.0))


def test_an_unknown_projection_is_refused_at_construction():
    """The original raises ValueError naming ``projection`` when the trainer is built with another name."""
    model = GaussianModel.from_points(np.random.default_rng(0).normal(size=(8, 3)))
    with pytest.raises(ValueError, match="projection"):
        GaussianTrainer(model, TrainerConfig(projection="bad"))
    for name in ("ewa", "ut", "auto"):
        assert GaussianTrainer(model, TrainerConfig(projection=name)).config.projection == name


def test_info_lr_means_is_the_rate_the_step_used():
    """``info['lr_means']`` is the means rate of the step just taken: the first equals ``learning_rates()`` before it."""
    points, colors, camera = _scene(30)
    model = GaussianModel.from_points(points, colors)
    config = TrainerConfig(lr_means=1e-2, lr_means_final=1e-4, lr_means_max_steps=2, densify_from=10**6, sh_increase_every=10**6)
    trainer = GaussianTrainer(model, config, scene_extent=2.0)
    before = trainer.learning_rates()["means"]
    rates = [trainer.step(camera, mx.zeros((24, 32, 3)))["lr_means"] for _ in range(3)]
    assert before == pytest.approx(2e-2)
    assert rates == pytest.approx([2e-2, math.sqrt(1e-2 * 1e-4) * 2.0, 2e-4])


def test_optimizers_expose_each_parameters_adam_state():
    """``trainer.optimizers[name].state[name]`` holds that parameter's Adam moments ``m``/``v`` (read and
    written through), ``.state['step']`` the step count; a densify resize keeps surviving rows, new rows zero."""
    points, colors, camera = _scene(6)
    model = GaussianModel.from_points(points, colors)
    trainer = GaussianTrainer(model, TrainerConfig(densify_from=10**6))
    trainer.step(camera, mx.zeros((24, 32, 3)))
    assert set(trainer.optimizers) == {"means", "scales", "quats", "opacities", "sh_dc", "sh_rest"}
    state = trainer.optimizers["scales"].state
    assert int(state["step"]) == 1 and float(trainer.optimizers["scales"].learning_rate) == pytest.approx(5e-3)
    np.testing.assert_array_equal(np.array(state["scales"]["m"]), np.array(trainer.optimizer.m["scales"]))
    moments = np.arange(18, dtype=np.float32).reshape(6, 3)
    state["scales"]["m"], state["scales"]["v"] = mx.array(moments), mx.array(moments + 1)
    state["step"] = mx.array(9, dtype=mx.uint64)
    assert trainer.optimizer.step_count == 9
    trainer._resize_optimizer_states_after_densify({"_keep_idx": np.array([4, 0]), "_new_count": 1})
    expected = np.concatenate([moments[[4, 0]], np.zeros((1, 3), np.float32)])
    np.testing.assert_array_equal(np.array(trainer.optimizers["scales"].state["scales"]["m"]), expected)
    np.testing.assert_array_equal(np.array(trainer.optimizers["scales"].state["scales"]["v"])[:2], moments[[4, 0]] + 1)
    assert trainer.optimizer.m["means"].shape == (3, 3)


def test_render_loss_is_the_steps_loss_with_geometry_metrics():
    """``_render_loss(params, probe, camera, target, background)`` returns ``(loss, (image, radii, metrics))``: the
    loss the next step takes, and the 2DGS geometry terms unweighted (0 unless their weights are set)."""
    points, colors, camera = _scene(40)
    model = GaussianModel.from_points(points * 0.5, colors)
    target = mx.array(np.random.default_rng(3).uniform(size=(24, 32, 3)).astype(np.float32))
    probe = mx.zeros((len(points), 2))
    weights = {"lambda_2d_depth_variance": 0.1, "lambda_2d_normal_consistency": 0.05, "geometry_min_alpha": 0.001}
    base = GaussianTrainer(model.copy(), TrainerConfig(method="2dgs", densify_from=10**6))
    weighted = GaussianTrainer(model.copy(), TrainerConfig(method="2dgs", densify_from=10**6, **weights))
    params = dict(weighted.model.params)  # with the 2DGS thickness both trainers applied
    base_loss, (image, radii, base_metrics) = base._render_loss(params, probe, camera, target, mx.zeros(3))
    loss, (_, _, metrics) = weighted._render_loss(params, probe, camera, target, mx.zeros(3))
    assert image.shape == (24, 32, 3) and radii.shape[0] == len(points)
    assert float(base_metrics["depth_variance"]) == 0.0 and float(base_metrics["normal_consistency"]) == 0.0
    assert float(metrics["depth_variance"]) > 0.0 and float(metrics["normal_consistency"]) > 0.0
    assert float(loss) == pytest.approx(float(base_loss) + 0.1 * float(metrics["depth_variance"])
                                        + 0.05 * float(metrics["normal_consistency"]), rel=1e-5)
    grads = mx.grad(lambda p, q: base._render_loss(p, q, camera, target, mx.zeros(3))[0], argnums=(0, 1))(params, probe)
    assert float(mx.abs(grads[1]).sum()) > 0.0 and float(mx.abs(grads[0]["means"]).sum()) > 0.0
    info = weighted.step(camera, target)
    assert info["loss"] == pytest.approx(float(loss), rel=1e-5)
    assert info["geometry"] == pytest.approx({k: float(v) for k, v in metrics.items()}, rel=1e-5)


def test_mcmc_relocates_its_fraction_when_every_gaussian_is_below_min_opacity():
    """With every opacity under ``mcmc_min_opacity``, an MCMC event still moves ``mcmc_relocate_frac`` of N,
    onto copies of the others, at a fixed count and with finite moments."""
    points, colors, camera = _scene(40)
    model = GaussianModel.from_points(points, colors)
    model.params["opacities"] = mx.full((40,), -3.0)  # opacity 0.047
    config = TrainerConfig(method="mcmc", densify_from=1, densify_every=2, mcmc_relocate_frac=0.25, mcmc_min_opacity=0.2,
                           mcmc_jitter_scale=0.0, mcmc_noise_scale=0.0)
    trainer = GaussianTrainer(model, config)
    events = [trainer.step(camera, mx.zeros((24, 32, 3)))["densify"] for _ in range(2)]
    assert events[0] is None and events[1]["relocated"] == 10
    assert len(model) == 40
    assert np.isfinite(np.array(trainer.optimizers["means"].state["means"]["m"])).all()
