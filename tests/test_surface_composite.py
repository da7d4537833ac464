"""Compositing the splats with a per-pixel surface layer (mlx3d.render.surface).

Oracle: tests/render_oracle.py, a float64 numpy loop with its own projection,
per pixel over every projected Gaussian of the pixel's tile (the tile
rule, which the renderer's binning matches) in global (depth, index) order,
with the surface event of the module docstring. Restricting to the tile rule
keeps the comparison tight: without it the oracle would also add the faint
rims (alpha up to ~0.01 · opacity) beyond a Gaussian's 3-sigma radius that the
tiled renderer cuts.

Tolerances: images and alphas against the oracle 2e-4 absolute, as in
test_render.py (float32 exp and products of up to hundreds of factors against
float64); the pure-MLX reference against the CPU kernel 1e-5; the
background-image path against the depth-tested kernel 1e-6 (the same math
rounded in another order). The surface depths are checked to lie over 4e-6
(8 float32 ulps at depths 4 to 8) from every Gaussian's depth, so that the
oracle's own float64 projection and the renderer's float32 one (a few ulps
apart) order them alike.
Bitwise equality where the same kernel runs: an absent surface, thread
counts, ISA variants and culling.
"""

import mlx.core as mx
import numpy as np
import pytest

import render_oracle
from mlx3d.cameras import Camera
from mlx3d.render import Surface, plan_render, render_gaussians
from mlx3d.render.raster_cpu import rasterize_cpu, rasterize_cpu_surface
from mlx3d.splatting import GaussianModel
from core_marks import FAST, needs_core
from thread_counts import per_thread_count

WIDTH, HEIGHT = 24, 20
BACKGROUND = (0.2, 0.3, 0.4)
ORACLE_ATOL = 2e-4
REFERENCE_ATOL = 1e-5
DEPTH_GAP = 4e-6  # least |surface depth - Gaussian depth| the oracle comparisons allow
PLANE_COLOR = np.array([0.9, 0.1, 0.5], np.float32)


def camera():
    return Camera.look_at(eye=(0.0, -4.0, 0.0), at=(0.0, 0.0, 0.0), up=(0, 0, 1), width=WIDTH, height=HEIGHT, hfov=50.0)


def scene(n=60, seed=0):
    """Random Gaussians in [-1, 1]³, 3 to 5 units from the camera."""
    rng = np.random.default_rng(seed)
    return {
        "means": rng.uniform(-1.0, 1.0, (n, 3)).astype(np.float32),
        "quats": rng.normal(size=(n, 4)).astype(np.float32),
        "scales": rng.uniform(0.05, 0.3, (n, 3)).astype(np.float32),
        "opacities": rng.uniform(0.2, 0.95, n).astype(np.float32),
        "colors": rng.uniform(0, 1, (n, 3)).astype(np.float32),
    }


def layer(depth, alpha=1.0, color=PLANE_COLOR):
    """numpy (color (H,W,3) premultiplied, alpha (H,W), depth (H,W)) of a surface of that colour."""
    alpha = np.broadcast_to(np.asarray(alpha, np.float32), (HEIGHT, WIDTH)).copy()
    depth = np.broadcast_to(np.asarray(depth, np.float32), (HEIGHT, WIDTH)).copy()
    return np.asarray(color, np.float32) * alpha[..., None], alpha, depth


def render(s, surface, backend="auto", **kw):
    args = [mx.array(s[k]) for k in ("means", "quats", "scales", "opacities")]
    return render_gaussians(camera(), *args, colors=mx.array(s["colors"]), background=BACKGROUND, backend=backend,
                            surface=None if surface is None else Surface(*surface), **kw)


def oracle(s, surface):
    return render_oracle.render(camera(), s["means"].astype(np.float64), s["quats"], s["scales"], s["opacities"], s["colors"],
                                background=BACKGROUND, surface=surface)


def check_against_oracle(s, surface):
    """The default rasterizer (the CPU kernel, or the MLX tiles without mlx3d._core) against the float64 oracle,
    and the MLX tiles and the pure-MLX reference against it; returns the default's result."""
    depths = np.array(render(s, None)["depths"])
    gap = np.abs(depths[:, None] - np.unique(surface[2][np.isfinite(surface[2])])[None, :])
    assert gap.size == 0 or gap.min() > DEPTH_GAP, "a plane lies too close to a Gaussian's depth for this tolerance"
    image, alpha = oracle(s, surface)
    out = render(s, surface)
    assert "rasterize_rgb+surface_depth_test" in out["stages"]
    assert out["stages"] == out["plan"].stages
    np.testing.assert_allclose(np.array(out["image"]), image, atol=ORACLE_ATOL)
    np.testing.assert_allclose(np.array(out["alpha"]), alpha, atol=ORACLE_ATOL)
    for backend in ("mlx", "reference"):
        ref = render(s, surface, backend=backend)
        np.testing.assert_allclose(np.array(ref["image"]), np.array(out["image"]), atol=REFERENCE_ATOL, err_msg=backend)
        np.testing.assert_allclose(np.array(ref["alpha"]), np.array(out["alpha"]), atol=REFERENCE_ATOL, err_msg=backend)
    return out


def test_opaque_plane_in_front_shows_only_the_plane():
    s = scene()
    out = check_against_oracle(s, layer(1.0))
    np.testing.assert_array_equal(np.array(out["image"]), np.broadcast_to(PLANE_COLOR, (HEIGHT, WIDTH, 3)))
    np.testing.assert_array_equal(np.array(out["alpha"]), 1.0)
    np.testing.assert_array_equal(np.array(out["n_contrib"]), 0)


def test_opaque_plane_behind_shows_splats_over_it():
    s = scene()
    out = check_against_oracle(s, layer(20.0))
    plain = render(s, None)
    T = 1.0 - np.array(plain["alpha"])[..., None]
    want = np.array(plain["image"]) - T * np.array(BACKGROUND, np.float32) + T * PLANE_COLOR
    np.testing.assert_allclose(np.array(out["image"]), want, atol=1e-6)
    np.testing.assert_array_equal(np.array(out["n_contrib"]), np.array(plain["n_contrib"]))


@pytest.mark.parametrize("seed", [0, 1])
def test_opaque_plane_through_the_cloud(seed):
    s = scene(seed=seed)
    z = np.sort(np.array(render(s, None)["depths"]))
    k = len(z) // 3 + np.argmax(np.diff(z[len(z) // 3 : 2 * len(z) // 3 + 1]))  # the widest gap in the middle third
    out = check_against_oracle(s, layer((z[k] + z[k + 1]) / 2))
    plain = render(s, None)
    assert np.abs(np.array(out["image"]) - np.array(plain["image"])).max() > 0.1  # the wall hides some splats


def test_tilted_plane():
    s = scene(seed=2)
    depth = np.linspace(2.5, 5.5, WIDTH, dtype=np.float32)[None, :] + np.linspace(0.0, 0.4, HEIGHT, dtype=np.float32)[:, None]
    check_against_oracle(s, layer(depth))


def test_semi_transparent_surface_and_partial_coverage():
    s = scene(seed=3)
    check_against_oracle(s, layer(4.0, alpha=0.5))
    # left half covered, an anti-aliased column, right half empty (alpha 0, no depth)
    alpha = np.zeros((HEIGHT, WIDTH), np.float32)
    alpha[:, : WIDTH // 2] = 1.0
    alpha[:, WIDTH // 2] = 0.4
    depth = np.where(alpha > 0, np.float32(3.7), np.float32(np.inf))
    check_against_oracle(s, layer(depth, alpha))


def test_absent_surface_is_bitwise_the_plain_render():
    s = scene(seed=4)
    plain = render(s, None)
    out = render(s, layer(4.0, alpha=0.0))  # depth-tested, alpha 0 everywhere
    assert "rasterize_rgb+surface_depth_test" in out["stages"]
    for key in ("image", "alpha", "n_contrib"):
        np.testing.assert_array_equal(np.array(out[key]), np.array(plain[key]), err_msg=key)


def kernel_inputs(s):
    """The projected, binned scene as the CPU kernels take it."""
    from mlx3d.render.binning import bin_tiles

    out = render(s, None)
    bins = bin_tiles(out["means2d"], out["radii"], out["depths"], WIDTH, HEIGHT, 16, out["conics"], mx.array(s["opacities"]))
    return (out["means2d"], out["conics"], mx.array(s["colors"]), mx.array(s["opacities"]), bins.tile_offsets, bins.flatten_ids), out["depths"]


@needs_core
def test_kernel_without_surface_equals_plain_kernel_bitwise():
    args, depths = kernel_inputs(scene(seed=5))
    color, alpha, depth = layer(np.inf, alpha=0.0)
    plain = rasterize_cpu(*args, WIDTH, HEIGHT)
    with_surface = rasterize_cpu_surface(*args, depths, color, alpha, depth, WIDTH, HEIGHT)
    for a, b in zip(plain, with_surface):
        np.testing.assert_array_equal(np.array(a), np.array(b))


def tilted_semi_transparent():
    depth = np.linspace(2.8, 5.2, WIDTH, dtype=np.float32)[None, :] + np.zeros((HEIGHT, 1), np.float32)
    return layer(depth, alpha=np.linspace(0.2, 1.0, HEIGHT, dtype=np.float32)[:, None])


@needs_core
def test_bitwise_equal_across_thread_counts():
    s, surface = scene(n=80, seed=6), tilted_semi_transparent()
    results = per_thread_count(lambda: [np.array(render(s, surface)[k]) for k in ("image", "alpha", "n_contrib")])
    for other in results[1:]:
        for a, b in zip(results[0], other):
            np.testing.assert_array_equal(a, b)


@needs_core
@pytest.mark.parametrize("env", [("MLX3D_RASTER_ISA", "baseline"), ("MLX3D_RASTER_CULL", "0")])
def test_bitwise_equal_across_isa_variants_and_culling(monkeypatch, env):
    s, surface = scene(n=80, seed=7), tilted_semi_transparent()
    want = [np.array(render(s, surface)[k]) for k in ("image", "alpha", "n_contrib")]
    monkeypatch.setenv(*env)
    got = [np.array(render(s, surface)[k]) for k in ("image", "alpha", "n_contrib")]
    for a, b in zip(want, got):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("backend", [FAST, "mlx", "reference"])
def test_surface_without_depth_is_a_background_image(backend):
    s = scene(seed=8)
    rng = np.random.default_rng(0)
    alpha = rng.uniform(0, 1, (HEIGHT, WIDTH)).astype(np.float32)
    color = rng.uniform(0, 1, (HEIGHT, WIDTH, 3)).astype(np.float32) * alpha[..., None]
    behind = render(s, (color, alpha, np.full((HEIGHT, WIDTH), np.inf, np.float32)), backend)
    tested = render(s, (color, alpha, np.full((HEIGHT, WIDTH), 1e30, np.float32)), backend)  # finite, behind every splat
    assert behind["stages"][-2:] == ("rasterize_rgb", "surface_behind") and behind["plan"].stages == behind["stages"]
    assert tested["stages"][-1] == "rasterize_rgb+surface_depth_test"
    for key in ("image", "alpha"):
        np.testing.assert_allclose(np.array(behind[key]), np.array(tested[key]), atol=1e-6, err_msg=key)


@pytest.mark.parametrize("backend", ["metal", "mlx"])
def test_every_backend_plans_the_depth_test_in_its_own_rasterizer(backend):
    s = scene()
    plan = plan_render(camera(), colors=s["colors"], backend=backend, surface=Surface(*layer(4.0)))
    assert plan.stages[-2:] == ("bin_tiles", "rasterize_rgb+surface_depth_test")
    plan = plan_render(camera(), colors=s["colors"], backend=backend, surface=Surface(*layer(np.inf)))
    assert plan.stages[-2:] == ("rasterize_rgb", "surface_behind")


def test_model_render_forwards_the_surface():
    s = scene(seed=9)
    model = GaussianModel.from_points(s["means"], s["colors"])
    out = model.render(camera(), background=BACKGROUND, backend=FAST, surface=Surface(*layer(1.0)))
    np.testing.assert_array_equal(np.array(out["image"]), np.broadcast_to(PLANE_COLOR, (HEIGHT, WIDTH, 3)))


@pytest.mark.parametrize(
    "surface, match",
    [
        (lambda: layer(4.0)[:2] + (np.full((HEIGHT, WIDTH + 1), 4.0, np.float32),), r"Surface.depth must have shape \(H, W\)"),
        (lambda: layer(np.where(np.eye(HEIGHT, WIDTH) > 0, np.nan, 4.0)), "Surface.depth contains NaN"),
        (lambda: layer(4.0, alpha=1.5), r"Surface.alpha must lie in \[0, 1\]"),
        (lambda: layer(-1.0), "Surface.depth must be >= 0"),
        (lambda: (np.zeros((HEIGHT, WIDTH), np.float32),) + layer(4.0)[1:], r"Surface.color must have shape \(H, W, C\)"),
        (lambda: (np.zeros((HEIGHT, WIDTH, 3), bool),) + layer(4.0)[1:], "Surface.color must be a real floating-point array"),
    ],
)
def test_surface_validation(surface, match):
    with pytest.raises(ValueError, match=match):
        Surface(*surface())


def test_render_validation():
    s = scene()
    with pytest.raises(ValueError, match="for this camera"):
        render(s, tuple(a[:-1] for a in layer(4.0)))
    with pytest.raises(ValueError, match="cannot be combined with surface"):
        render(s, layer(4.0), render_depth=True)
    with pytest.raises(ValueError, match="must be a mlx3d.render.Surface"):
        plan_render(camera(), colors=s["colors"], surface=layer(4.0))


def test_gradients_raise():
    s = scene(n=20)
    surface = Surface(*layer(4.0))
    args = [mx.array(s[k]) for k in ("means", "quats", "scales", "opacities")]

    def loss(means):
        return render_gaussians(camera(), means, *args[1:], colors=mx.array(s["colors"]), backend=FAST, surface=surface)["image"].sum()

    with pytest.raises(RuntimeError, match="compositing over a surface is forward-only"):
        mx.eval(mx.grad(loss)(args[0]))
