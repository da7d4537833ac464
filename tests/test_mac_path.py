"""The Apple-GPU path, run on any machine: what a Mac runs, with only the kernel launches swapped.

The fixture ``mac`` forces what ``resolve_backend('auto')`` sees on an Apple GPU
(``metal_available()`` True), turns ``mlx3d._core`` off (``MLX3D_NO_CORE``:
any call into it raises, so a test passing here used none), and builds the
Metal kernels with ``tests/metal_emulator.py``: their exact sources compiled
as C++ and launched with MLX's ``metal_kernel`` arguments. Everything else
is the Mac's code path: the renderer picking 'metal' for every stage, the
MLX binning, projection, SH, activations, loss, Adam and density statistics,
``rasterize_metal``'s custom function and vjp, the surface composite, the
trainer's three methods and mesh extraction.

Never executed here (only a Mac runs it): the body of ``_metal_kernel`` in
``mlx3d/render/raster_metal.py`` (the ``mx.fast.metal_kernel`` call), the
Metal shader compiler on the kernel sources (they are compiled as C++ here,
with ``__METAL_VERSION__`` unset, so ``rm_pow2i``'s Metal branch in
``raster_math.h`` is not compiled), GPU threadgroup scheduling and float
atomics (run one thread at a time here), MLX's Metal backend for the MLX
operations, and ``mx.metal.is_available()`` returning True.
"""

from __future__ import annotations

import math

import mlx.core as mx
import numpy as np
import pytest

import metal_emulator
from mlx3d.cameras import Camera
from mlx3d.render import Surface, raster_metal, render_gaussians, resolve_backend
from mlx3d.splatting import GaussianModel
from mlx3d.training import GaussianTrainer, TrainerConfig

pytestmark = pytest.mark.skipif(metal_emulator.compiler() is None, reason="no C++ compiler to compile the Metal kernels' sources")


@pytest.fixture
def mac(monkeypatch):
    """The Mac's code path (module docstring); yields the emulator's launch counts."""
    monkeypatch.setenv("MLX3D_NO_CORE", "1")
    monkeypatch.setattr(raster_metal, "metal_available", lambda: True)
    metal_emulator.launches.clear()
    with raster_metal.use_builder(metal_emulator.metal_kernel):
        yield metal_emulator.launches


def cameras(n=6, width=40, height=32):
    return [Camera.look_at(eye=(3 * math.cos(a), 3 * math.sin(a), 0.8), at=(0, 0, 0), up=(0, 0, 1), width=width, height=height, hfov=45.0)
            for a in np.linspace(0, 2 * math.pi, n, endpoint=False)]


def scene(seed=0, n=80, sh_degree=1):
    rng = np.random.default_rng(seed)
    return GaussianModel.from_points(rng.uniform(-0.6, 0.6, (n, 3)).astype(np.float32), rng.uniform(0, 1, (n, 3)), sh_degree=sh_degree,
                                     initial_opacity=0.8)


def test_auto_is_metal_and_a_render_runs_the_kernels(mac, monkeypatch):
    assert resolve_backend("auto") == "metal"
    model, camera = scene(), cameras()[0]
    out = model.render(camera, background=(0.2, 0.3, 0.4), render_depth=True, render_normals=True)
    assert out["plan"].backend == "metal" and out["stages"] == out["plan"].stages
    assert mac["mlx3d_rasterize_forward"] == 1
    monkeypatch.setattr(raster_metal, "metal_available", lambda: False)  # the same inputs through the MLX tiles
    assert resolve_backend("auto") == "mlx"
    pure = model.render(camera, background=(0.2, 0.3, 0.4), render_depth=True, render_normals=True)
    for key in ("image", "alpha", "depth", "normals"):
        np.testing.assert_allclose(np.array(out[key]), np.array(pure[key]), atol=2e-5, err_msg=key)
    np.testing.assert_array_equal(np.array(out["n_contrib"]), np.array(pure["n_contrib"]))
    assert np.array(out["alpha"]).max() > 0.5


def test_gradients_run_the_backward_kernel(mac):
    model, camera = scene(1), cameras()[1]
    rng = np.random.default_rng(1)  # anisotropic, so that the rotations matter
    model.params["scales"] = model.params["scales"] + mx.array(rng.uniform(-1.0, 0.5, (len(model), 3)).astype(np.float32))
    target = mx.zeros((camera.height, camera.width, 3))

    def gradients(backend):
        def loss(means, quats, scales, sh_dc):
            out = render_gaussians(camera, means, quats, scales, model.opacities, sh=(sh_dc, model.params["sh_rest"]), sh_degree=1,
                                   backend=backend)
            return mx.mean(mx.abs(out["image"] - target))

        grads = mx.grad(loss, argnums=(0, 1, 2, 3))(model.means, model.quats, model.scales, model.params["sh_dc"])
        return [np.array(g) for g in grads]

    gpu = gradients("auto")
    assert mac["mlx3d_rasterize_backward"] == 1
    for a, b in zip(gpu, gradients("mlx")):  # the MLX tiles' own backward pass
        assert np.abs(b).max() > 0
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5 * np.abs(b).max())


def train(method: str, steps: int = 40) -> tuple:
    """(per-step infos, a render of the trained model) of a short run with density control from its 4th step."""
    truth = scene(2, sh_degree=1)
    cams = cameras()
    targets = [np.array(truth.render(c, background=(0, 0, 0))["image"]) for c in cams]
    rng = np.random.default_rng(3)
    start = GaussianModel.from_points(np.asarray(truth.means) + rng.normal(0, 0.05, (80, 3)).astype(np.float32), sh_degree=1, initial_opacity=0.3)
    config = TrainerConfig(method=method, steps=steps, densify_from=4, densify_every=8, densify_until=30, densify_grad_threshold=1e-7,
                           opacity_reset_every=1000, sh_increase_every=10, seed=1, background=(0, 0, 0), max_gaussians=200,
                           mcmc_min_opacity=0.2 if method == "mcmc" else TrainerConfig.mcmc_min_opacity)
    trainer = GaussianTrainer(start, config, scene_extent=3.0)
    infos = [trainer.step(cams[i % 6], targets[i % 6]) for i in range(steps)]
    return infos, np.array(trainer.model.render(cams[0], background=(0, 0, 0))["image"])


@pytest.mark.parametrize("method", ["vanilla", "mcmc", "2dgs"])
def test_training_each_method(mac, monkeypatch, method):
    infos, image = train(method)
    events = {e for info in infos for e in info["stages"]}
    assert "adam" in events and any(e.startswith("rasterize_rgb") for e in events)
    assert ("relocate" if method == "mcmc" else "densify") in events, events
    if method != "mcmc":
        assert "screen_statistics" in events
    if method == "2dgs":
        assert "thickness_clamp" in events
    assert mac["mlx3d_rasterize_backward"] == len(infos)
    # the same run on the MLX tiles: the same density decisions, and the losses within float rounding, which
    # density control (and 2DGS's normal and depth terms) amplify from step to step
    monkeypatch.setattr(raster_metal, "metal_available", lambda: False)
    pure_infos, pure_image = train(method)
    assert [i["num_gaussians"] for i in infos] == [i["num_gaussians"] for i in pure_infos]
    losses, pure_losses = [i["loss"] for i in infos], [i["loss"] for i in pure_infos]
    np.testing.assert_allclose(losses[:8], pure_losses[:8], rtol=1e-3)  # up to the first densification
    np.testing.assert_allclose(losses, pure_losses, rtol=5e-2)
    # the trained models render alike; 2DGS's depth and normal terms amplify float rounding more (the C++
    # kernels and the MLX tiles end 25 dB apart after these 40 steps too)
    assert -10 * np.log10(np.mean((image - pure_image) ** 2)) > (20 if method == "2dgs" else 35)


def test_surface_composite_runs_the_surface_kernel(mac, monkeypatch):
    model, camera = scene(4), cameras()[2]
    h, w = camera.height, camera.width
    depth = np.full((h, w), 3.0, np.float32)
    depth[:, : w // 2] = np.inf
    alpha = np.full((h, w), 0.7, np.float32)
    surface = Surface(np.full((h, w, 3), 0.5, np.float32) * alpha[..., None], alpha, depth)
    out = model.render(camera, background=(0, 0, 0), surface=surface)
    assert out["stages"][-1] == "rasterize_rgb+surface_depth_test" and mac["mlx3d_rasterize_surface"] == 1
    monkeypatch.setattr(raster_metal, "metal_available", lambda: False)
    pure = model.render(camera, background=(0, 0, 0), surface=surface)
    np.testing.assert_allclose(np.array(out["image"]), np.array(pure["image"]), atol=2e-5)
    np.testing.assert_allclose(np.array(out["alpha"]), np.array(pure["alpha"]), atol=2e-5)


def test_mesh_extraction(mac):
    rng = np.random.default_rng(5)
    d = rng.normal(size=(3000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    model = GaussianModel.from_points((0.5 * d).astype(np.float32), rng.uniform(0, 1, (3000, 3)), sh_degree=0, initial_opacity=0.9)
    mesh = model.surface_mesh(resolution=32)
    radius = np.linalg.norm(np.asarray(mesh.vertices), axis=1)
    assert len(mesh.faces) > 100 and abs(np.median(radius) - 0.5) < 0.05
