"""The renderer end to end: projection, hard cases, effects on demand, real data.

Oracles: a float64 numpy loop implementation of the same formulas
(tests/render_oracle.py), the pure-MLX reference rasterizer (for the compiled
kernel), central finite differences, and analytic cases.

Tolerances: images against the float64 oracle 2e-4 absolute (float32 math
through exp and products of up to hundreds of factors); CPU kernel against the
reference 1e-4 absolute for images and 1e-3 relative to the largest entry for
gradients; finite differences 2e-2 relative (float32, step 1e-3).
"""

import os

import mlx.core as mx
import numpy as np
import pytest

import render_oracle
from mlx3d import native
from mlx3d.cameras import Camera
from mlx3d.render import plan_render, project_gaussians, project_gaussians_ut, render_gaussian_depth, render_gaussian_features, render_gaussians
from mlx3d.splatting import GaussianModel

DATA = os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data")


# the renderers compared: the pure-MLX oracle, the MLX tiles, and the C++ kernels where mlx3d._core is available
BACKENDS = ["reference", "mlx"] + (["cpu"] if native.available() else [])
FAST = BACKENDS[-1]


def camera(width=48, height=40, **kw):
    return Camera.look_at(eye=(0.0, -4.0, 0.0), at=(0.0, 0.0, 0.0), up=(0, 0, 1), width=width, height=height, hfov=50.0, **kw)


def scene(n=40, seed=0, spread=1.0):
    rng = np.random.default_rng(seed)
    return {
        "means": rng.uniform(-spread, spread, (n, 3)).astype(np.float32),
        "quats": rng.normal(size=(n, 4)).astype(np.float32),
        "scales": rng.uniform(0.03, 0.3, (n, 3)).astype(np.float32),
        "opacities": rng.uniform(0.1, 0.95, n).astype(np.float32),
        "colors": rng.uniform(0, 1, (n, 3)).astype(np.float32),
    }


def as_mx(s):
    return {k: mx.array(v) for k, v in s.items()}


def loss_and_grads(cam, s, backend, weights_seed=1):
    """A fixed random linear function of image and alpha, and its gradients w.r.t. every input."""
    rng = np.random.default_rng(weights_seed)
    w_img = mx.array(rng.normal(size=(cam.height, cam.width, 3)).astype(np.float32))
    w_alpha = mx.array(rng.normal(size=(cam.height, cam.width)).astype(np.float32))
    names = ["means", "quats", "scales", "opacities", "colors"]

    def f(*args):
        out = render_gaussians(cam, *args[:4], colors=args[4], background=(0.2, 0.3, 0.4), backend=backend)
        return (out["image"] * w_img).sum() + (out["alpha"] * w_alpha).sum(), out

    (value, out), grads = mx.value_and_grad(f, argnums=tuple(range(5)))(*[mx.array(s[k]) for k in names])
    return float(value), out, dict(zip(names, grads))


def check_case(cam, s, oracle=True):
    """Finite image and gradients; zero gradient for culled Gaussians; backends agree; oracle agrees."""
    results = {}
    for backend in BACKENDS:
        value, out, grads = loss_and_grads(cam, s, backend)
        image = np.array(out["image"])
        assert np.isfinite(value) and np.isfinite(image).all(), backend
        visible = np.array(out["visible"])
        for name, g in grads.items():
            g = np.array(g)
            assert np.isfinite(g).all(), (backend, name)
            assert not g[~visible].any(), f"{backend}: culled Gaussians got a gradient for {name}"
        results[backend] = (image, np.array(out["alpha"]), {k: np.array(v) for k, v in grads.items()})
    ref = results["reference"]
    for backend in BACKENDS[1:]:
        got = results[backend]
        np.testing.assert_allclose(got[0], ref[0], atol=1e-4, err_msg=backend)
        np.testing.assert_allclose(got[1], ref[1], atol=1e-4, err_msg=backend)
        for name in ref[2]:
            scale = max(np.abs(ref[2][name]).max(), 1e-4)  # analytically-zero gradients carry ~1e-8 noise
            np.testing.assert_allclose(got[2][name], ref[2][name], atol=1e-3 * scale, err_msg=f"{backend} {name}")
    if oracle:
        image, alpha = render_oracle.render(cam, s["means"].astype(np.float64), s["quats"], s["scales"], s["opacities"], s["colors"], background=(0.2, 0.3, 0.4))
        np.testing.assert_allclose(results["reference"][0], image, atol=2e-4)
        np.testing.assert_allclose(results["reference"][1], alpha, atol=2e-4)
    return results


# ------------------------------------------------------------------ ordinary and hard cases
def test_random_scene_matches_float64_oracle():
    check_case(camera(), scene())


def test_behind_camera_near_plane_and_outside_frustum_are_culled():
    cam = camera()
    s = scene(8, seed=2, spread=0.3)
    # camera at y=-4 looking +y: depth = y + 4
    s["means"][0] = [0, -5.0, 0]  # behind
    s["means"][1] = [0, -4.0 + cam.near, 0]  # on the near plane (kept: depth == near)
    s["means"][2] = [0, -4.0 + 0.5 * cam.near, 0]  # just past it (culled)
    s["means"][3] = [50.0, 0.0, 0]  # far outside the frustum
    out = render_gaussians(cam, *[mx.array(s[k]) for k in ("means", "quats", "scales", "opacities")], colors=mx.array(s["colors"]), backend="reference")
    radii = np.array(out["radii"])
    assert radii[0] == 0 and radii[2] == 0 and radii[3] == 0
    check_case(cam, s)


@pytest.mark.parametrize("which", ["one_axis_zero", "all_axes_zero", "one_axis_tiny", "all_axes_tiny"])
def test_zero_and_tiny_scales(which):
    s = scene(12, seed=3, spread=0.5)
    if which == "one_axis_zero":
        s["scales"][:, 2] = 0.0
    elif which == "all_axes_zero":
        s["scales"][:] = 0.0
    elif which == "one_axis_tiny":
        s["scales"][:, 1] = 1e-8
    else:
        s["scales"][:] = 1e-8
    check_case(camera(), s)


def test_huge_full_screen_scales():
    s = scene(5, seed=4, spread=0.2)
    s["scales"][:] = 50.0
    s["opacities"][:] = 0.3
    check_case(camera(), s)


def test_zero_and_unnormalised_quaternions():
    s = scene(10, seed=5, spread=0.5)
    s["quats"][:3] = 0.0
    s["quats"][3:] *= 1e3
    check_case(camera(), s)


@pytest.mark.parametrize("logit", [30.0, -30.0])
def test_extreme_opacity_logits(logit):
    s = scene(10, seed=6, spread=0.5)
    s["opacities"][:] = 1 / (1 + np.exp(-logit))
    check_case(camera(), s)


def test_thousand_gaussians_stacked_on_one_pixel():
    n = 1000
    s = scene(n, seed=7, spread=0.0)
    s["means"][:] = [0.0, 0.0, 0.0]
    s["means"][:, 1] = np.linspace(0, 1, n)  # staggered depths
    s["scales"][:] = 0.02
    s["opacities"][:] = 0.99
    cam = camera(24, 24)
    results = check_case(cam, s, oracle=False)
    alpha = results["reference"][1]
    assert alpha.max() == pytest.approx(1 - 0.01**2, abs=1e-5)  # stops before T < 1e-4: two 0.99 layers
    image, alpha_o = render_oracle.render(cam, s["means"].astype(np.float64), s["quats"], s["scales"], s["opacities"], s["colors"], background=(0.2, 0.3, 0.4))
    np.testing.assert_allclose(results["reference"][0], image, atol=2e-4)


def test_scene_far_from_origin_seen_from_close():
    offset = np.array([1e4, -2e4, 1e4], np.float32)
    cam = Camera.look_at(eye=offset + [0, -3, 0], at=offset, up=(0, 0, 1), width=40, height=32, hfov=50.0)
    s = scene(20, seed=8, spread=0.5)
    s["means"] += offset
    results = check_case(cam, s, oracle=False)
    assert results["reference"][1].max() > 0.2  # the Gaussians are visible, not lost to float32 rounding


def test_degenerate_2d_covariance_is_culled():
    cam = camera()
    s = scene(3, seed=9, spread=0.2)
    s["scales"][:] = [0.1, 0.0, 0.0]  # a line: rank-1 2D covariance, det == 0 without blur
    args = [mx.array(s[k]) for k in ("means", "quats", "scales")]
    out = project_gaussians(cam, *args, blur=0.0)
    assert (np.array(out["radii"]) == 0).all()
    assert np.isfinite(np.array(out["conics"])).all()
    s["scales"][:] = 1e-4  # tiny: a negative blur makes the covariance negative definite (det > 0, a < 0)
    out = project_gaussians(cam, *[mx.array(s[k]) for k in ("means", "quats", "scales")], blur=-10.0)
    assert (np.array(out["radii"]) == 0).all()
    check_case(cam, scene(3, seed=9, spread=0.2) | {"scales": np.tile(np.float32([0.1, 0.0, 0.0]), (3, 1))})


def test_empty_scene_and_single_gaussian():
    cam = camera()
    empty = {k: v[:0] for k, v in scene(1).items()}
    for backend in BACKENDS:
        out = render_gaussians(cam, *[mx.array(empty[k]) for k in ("means", "quats", "scales", "opacities")], colors=mx.array(empty["colors"]), background=(1, 0, 0), backend=backend)
        np.testing.assert_array_equal(np.array(out["image"]), np.broadcast_to([1, 0, 0], (40, 48, 3)))
    check_case(cam, scene(1, seed=10, spread=0.1))


@pytest.mark.parametrize("backend", BACKENDS)
def test_gradients_match_finite_differences(backend):
    cam = camera(20, 16)
    s = scene(6, seed=11, spread=0.4)
    s["scales"][:] = np.maximum(s["scales"], 0.15)
    _, _, grads = loss_and_grads(cam, s, backend)
    rng = np.random.default_rng(0)
    for name in ("means", "scales", "opacities", "colors", "quats"):
        for _ in range(3):
            idx = tuple(rng.integers(0, d) for d in s[name].shape)
            h = 1e-3
            plus, minus = {k: v.copy() for k, v in s.items()}, {k: v.copy() for k, v in s.items()}
            plus[name][idx] += h
            minus[name][idx] -= h
            fd = (loss_and_grads(cam, plus, backend)[0] - loss_and_grads(cam, minus, backend)[0]) / (2 * h)
            g = float(np.array(grads[name])[idx])
            assert abs(fd - g) <= 2e-2 * max(abs(fd), abs(g), 1.0), (name, idx, fd, g)


# ------------------------------------------------------------------ projection
def test_ewa_matches_oracle_projection():
    cam = camera()
    s = scene(30, seed=12)
    proj = project_gaussians(cam, mx.array(s["means"]), mx.array(s["quats"]), mx.array(s["scales"]))
    for i in range(30):
        m2, conic, r, z = render_oracle.project_one(cam, s["means"][i].astype(np.float64), s["quats"][i], s["scales"][i])
        assert int(np.array(proj["radii"])[i]) == r
        if r:
            np.testing.assert_allclose(np.array(proj["means2d"])[i], m2, rtol=1e-5, atol=1e-4)
            np.testing.assert_allclose(np.array(proj["conics"])[i], conic, rtol=1e-4, atol=1e-6)


def test_ut_equals_ewa_for_small_gaussians_and_is_exact_for_orthographic():
    cam = camera()
    s = scene(30, seed=13, spread=0.5)
    s["scales"][:] = 0.01
    args = [mx.array(s[k]) for k in ("means", "quats", "scales")]
    ewa, ut = project_gaussians(cam, *args), project_gaussians_ut(cam, *args)
    np.testing.assert_allclose(np.array(ut["means2d"]), np.array(ewa["means2d"]), atol=1e-4)
    ewa_conics = np.array(ewa["conics"])
    scale = np.abs(ewa_conics).max(axis=1, keepdims=True)
    assert (np.abs(np.array(ut["conics"]) - ewa_conics) <= 2e-3 * scale).all()
    ortho = Camera(width=48, height=40, fx=20.0, fy=20.0, cx=24.0, cy=20.0, viewmat=cam.viewmat, model="orthographic")
    proj = project_gaussians_ut(ortho, *args)
    rot = np.asarray(cam.viewmat)[:3, :3]
    for i in range(5):
        m = render_oracle.quat_to_rot(s["quats"][i]) @ np.diag(s["scales"][i].astype(np.float64))
        cov = (rot @ m @ m.T @ rot.T)[:2, :2] * 400.0 + 0.3 * np.eye(2)
        want = np.array([cov[1, 1], -cov[0, 1], cov[0, 0]]) / np.linalg.det(cov)
        np.testing.assert_allclose(np.array(proj["conics"])[i], want, rtol=1e-4, atol=1e-5 * np.abs(want).max())


def test_a_distorted_lens_does_not_fold_far_off_axis_gaussians_into_the_picture():
    # A solved phone camera (k1 = -0.02): r (1 + k1 r^2) turns back at r = 1/sqrt(3 |k1|) = 4.1, so a Gaussian
    # 80 degrees off-axis landed, mirrored, inside the picture and one straddling the fold spread over all of it
    # (a veil of its colour over every view of a trained street capture).
    k1 = -0.0198
    lens = Camera(width=160, height=120, fx=180.0, fy=180.0, cx=80.0, cy=60.0, model="opencv", dist=(k1, 0, 0, 0, 0))
    assert lens.lens_limit == pytest.approx(1 / (3 * abs(k1)))
    # a backdrop Gaussian of a trained street capture that veiled a training view (in its camera's coordinates,
    # 79 degrees off-axis), and one in view
    means = mx.array([[-56.37, -6.4, 10.81], [0.0, 0.0, 4.0]], dtype=mx.float32)
    quats = mx.array([[0.6383, 0.7223, 0.2578, 0.0657], [1.0, 0.0, 0.0, 0.0]], dtype=mx.float32)
    scales = mx.array([[3.253, 6.497, 0.361], [0.05, 0.05, 0.05]], dtype=mx.float32)
    proj = project_gaussians_ut(lens, means, quats, scales)
    assert np.array(proj["radii"]).tolist() == [0, np.array(proj["radii"])[1]] and np.array(proj["radii"])[1] > 0
    image = render_gaussians(lens, means, quats, scales, mx.array([1.0, 1.0]), colors=mx.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]))
    rgb = np.array(image["image"])
    assert rgb[..., 2].max() == 0.0 and rgb[60, 80, 0] > 0.5  # no blue veil; the red Gaussian in view is drawn
    # within the limit the distorted projection is unchanged: a Gaussian 60 degrees off-axis still projects
    side = project_gaussians_ut(lens, mx.array([[1.7, 0.0, 1.0]], dtype=mx.float32), quats[:1], mx.array([[0.01] * 3], dtype=mx.float32))
    u = float(np.array(side["means2d"])[0, 0])
    assert u == pytest.approx(180.0 * 1.7 * (1 + k1 * 1.7**2) + 80.0, rel=1e-5)
    assert Camera(width=8, height=8, fx=8.0, fy=8.0, cx=4.0, cy=4.0).lens_limit == float("inf")
    assert Camera(width=8, height=8, fx=8.0, fy=8.0, cx=4.0, cy=4.0, model="opencv", dist=(0.1, 0, 0, 0, 0)).lens_limit == float("inf")


def test_antialias_compensation():
    cam = camera()
    s = scene(10, seed=14)
    args = [mx.array(s[k]) for k in ("means", "quats", "scales")]
    plain, aa = project_gaussians(cam, *args), project_gaussians(cam, *args, antialias=True)
    comp = np.array(aa["compensation"])[np.array(aa["radii"]) > 0]
    assert ((comp > 0) & (comp <= 1)).all() and (np.array(plain["compensation"])[np.array(plain["radii"]) > 0] == 1).all()


# ------------------------------------------------------------------ effects on demand
def test_plan_runs_only_needed_stages():
    cam = camera()
    s = as_mx(scene(10, seed=15))
    base = [s["means"], s["quats"], s["scales"], s["opacities"]]
    out = render_gaussians(cam, *base, colors=s["colors"], backend="reference")
    assert out["stages"] == ("project_ewa", "bin_tiles", "rasterize_rgb") == out["plan"].stages
    sh1 = mx.array(np.random.default_rng(0).normal(size=(10, 4, 3)).astype(np.float32))
    out = render_gaussians(cam, *base, sh=sh1, sh_degree=3, render_depth=True, antialias=True, backend="reference")
    assert out["stages"] == ("project_ewa", "antialias_compensation", "bin_tiles", "eval_sh_degree_1", "rasterize_rgb+depth") == out["plan"].stages
    fisheye = Camera(width=48, height=40, fx=30.0, fy=30.0, cx=24.0, cy=20.0, viewmat=cam.viewmat, model="fisheye", dist=(0.01, 0.0, 0.0, 0.0))
    out = render_gaussians(fisheye, *base, colors=s["colors"], backend="reference")
    assert out["stages"][0] == "project_ut"
    assert plan_render(cam, colors=s["colors"], projection="ut", backend="reference").projection == "ut"
    with pytest.raises(ValueError, match="needs projection='ut'"):
        plan_render(fisheye, colors=s["colors"], projection="ewa")
    with pytest.raises(ValueError, match="exactly one"):
        plan_render(cam)


@pytest.mark.parametrize("backend", BACKENDS)
def test_sh_evaluation_stops_at_the_requested_degree(monkeypatch, backend):
    import mlx3d.render.pipeline as pipeline

    seen = []
    real = pipeline.sh_colors
    monkeypatch.setattr(pipeline, "sh_colors", lambda sh, means, centre, degree, be: seen.append(degree) or real(sh, means, centre, degree, be))
    cam = camera()
    s = as_mx(scene(10, seed=16))
    sh3 = mx.array(np.random.default_rng(1).normal(size=(10, 16, 3)).astype(np.float32))
    two = render_gaussians(cam, s["means"], s["quats"], s["scales"], s["opacities"], sh=sh3, sh_degree=2, backend=backend)["image"]
    render_gaussians(cam, s["means"], s["quats"], s["scales"], s["opacities"], colors=s["colors"], backend=backend)
    assert seen == [2]
    cut = render_gaussians(cam, s["means"], s["quats"], s["scales"], s["opacities"], sh=sh3[:, :9], sh_degree=3, backend=backend)["image"]
    np.testing.assert_array_equal(np.array(two), np.array(cut))  # degree 2 ignores coefficients 9..15


def test_depth_and_features():
    cam = camera()
    one = scene(1, seed=17, spread=0.0)
    one["scales"][:] = 0.3
    one["opacities"][:] = 0.9
    s = as_mx(one)
    depth = np.array(render_gaussian_depth(cam, s["means"], s["quats"], s["scales"], s["opacities"], backend="reference")["depth"])
    hit = depth > 0
    assert hit.any() and np.allclose(depth[hit], 4.0, atol=1e-4)  # camera 4 units away
    feats = mx.array(np.arange(20, dtype=np.float32)[None, :])
    img = np.array(render_gaussian_features(cam, s["means"], s["quats"], s["scales"], s["opacities"], feats, normalize=True, chunk_size=7, backend="reference")["features"])
    assert img.shape == (40, 48, 20)
    covered = img[..., 0] >= 0
    np.testing.assert_allclose(img[hit][:, 5], 5.0, rtol=1e-5)
    assert covered.all()


def test_model_render_uses_its_sh():
    m = GaussianModel.from_points(np.random.default_rng(0).uniform(-0.5, 0.5, (50, 3)).astype(np.float32), sh_degree=1)
    out = m.render(camera(), background=(0, 0, 0), backend="reference")
    assert out["stages"][-2:] == ("eval_sh_degree_1", "rasterize_rgb")
    assert np.isfinite(np.array(out["image"])).all()


# ------------------------------------------------------------------ real data
@pytest.mark.skipif(not os.path.exists(os.path.join(DATA, "test_garden.npz")), reason="shared/data/test_garden.npz not present")
def test_real_garden_points_and_cameras():
    data = np.load(os.path.join(DATA, "test_garden.npz"))
    rng = np.random.default_rng(0)
    keep = rng.choice(len(data["means3d"]), 20000, replace=False)
    model = GaussianModel.from_points(data["means3d"][keep], data["colors"][keep], sh_degree=0, initial_opacity=0.5)
    w, h = int(data["width"]), int(data["height"])
    for view, k in zip(data["viewmats"], data["Ks"]):
        full = Camera(width=w, height=h, fx=float(k[0, 0]), fy=float(k[1, 1]), cx=float(k[0, 2]), cy=float(k[1, 2]), viewmat=view)
        cam = full.scaled(0.25)
        depth_cam = (np.asarray(model.means) @ np.asarray(view)[:3, :3].T + np.asarray(view)[:3, 3])[:, 2]
        out = model.render(cam, backend=FAST)
        radii = np.array(out["radii"])
        assert np.isfinite(np.array(out["image"])).all()
        assert (depth_cam < cam.near).any(), "the real data has points behind these cameras"
        assert (radii[depth_cam < cam.near] == 0).all()
        assert np.array(out["alpha"]).mean() > 0.1
        ref = model.render(cam, backend="reference")
        np.testing.assert_allclose(np.array(out["image"]), np.array(ref["image"]), atol=1e-4)


@pytest.mark.parametrize("backend", BACKENDS)
def test_screen_space_gradient_via_offset(backend):
    """d loss / d means2d from a zero offset equals a finite difference of the 2D means."""
    cam = camera(24, 20)
    s = as_mx(scene(8, seed=18, spread=0.4))
    w = mx.array(np.random.default_rng(2).normal(size=(20, 24, 3)).astype(np.float32))

    def loss(offset):
        out = render_gaussians(cam, s["means"], s["quats"], s["scales"], s["opacities"], colors=s["colors"], backend=backend, means2d_offset=offset)
        return (out["image"] * w).sum()

    zero = mx.zeros((8, 2))
    grad = np.array(mx.grad(loss)(zero))
    visible = np.array(render_gaussians(cam, s["means"], s["quats"], s["scales"], s["opacities"], colors=s["colors"], backend=backend)["visible"])
    assert not grad[~visible].any() and np.abs(grad[visible]).max() > 0
    for g in np.flatnonzero(visible)[:3]:
        step = np.zeros((8, 2), np.float32)
        step[g, 0] = 1e-2
        fd = (float(loss(mx.array(step))) - float(loss(mx.array(-step)))) / 2e-2
        assert abs(fd - grad[g, 0]) <= 2e-2 * max(abs(fd), 1.0)
