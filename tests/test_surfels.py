"""Surfels: geometry channels of the renderer, the 2DGS regularisers, surfel training and oriented samples.

Oracles: analytic compositing of two Gaussians on one ray, central finite
differences, analytic planes (their normals and depths), and invariances.
"""

import math

import mlx.core as mx
import numpy as np
import pytest

from mlx3d.cameras import Camera
from mlx3d.render import facing_normals, render_gaussian_features, render_gaussian_median_depth, render_gaussians
from mlx3d.splatting import GaussianModel
from mlx3d.training import geometry
from mlx3d.training.trainer import GaussianTrainer, TrainerConfig
from mlx3d.transforms import matrix_to_quaternion, quaternion_to_matrix
from core_marks import FAST


def front_camera(width=41, height=33, **kw):
    """Looks along +y from y=-4; odd sizes put the principal point on a pixel centre."""
    return Camera.look_at(eye=(0.0, -4.0, 0.0), at=(0.0, 0.0, 0.0), up=(0, 0, 1), width=width, height=height, hfov=50.0, **kw)


def quat_from_z_to(normals):
    """(N,4) quaternions rotating local z onto each unit normal (any twist)."""
    normals = np.asarray(normals, np.float64)
    helper = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    x = np.cross(helper, normals)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(normals, x)
    return matrix_to_quaternion(np.stack([x, y, normals], axis=2)).astype(np.float32)


def plane_surfels(n_side=24, size=2.0, tilt_deg=0.0, seed=0):
    """Discs on a square in the plane y = 0 (facing the front camera), optionally tilted about z."""
    g = (np.arange(n_side) + 0.5) / n_side * size - size / 2
    xx, zz = np.meshgrid(g, g)
    pts = np.stack([xx.ravel(), np.zeros(xx.size), zz.ravel()], 1)
    normal = np.array([0.0, -1.0, 0.0])
    spacing = size / n_side
    quats = quat_from_z_to(np.repeat(normal[None], len(pts), 0))
    if tilt_deg:
        a = math.radians(tilt_deg)
        tilt = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
        pts = pts @ tilt.T
        quats = matrix_to_quaternion(tilt[None] @ quaternion_to_matrix(quats.astype(np.float64))).astype(np.float32)
    rng = np.random.default_rng(seed)
    return {
        "means": mx.array(pts.astype(np.float32)),
        "quats": mx.array(quats),
        "scales": mx.array(np.tile(np.float32([spacing, spacing, 1e-4]), (len(pts), 1))),
        "opacities": mx.array(np.full(len(pts), 0.9, np.float32)),
        "colors": mx.array(rng.uniform(0, 1, (len(pts), 3)).astype(np.float32)),
    }


# ------------------------------------------------------------------ geometry channels
@pytest.mark.parametrize("planar", [False, True])
def test_geometry_channels_composite_like_the_analytic_two_layer_case(planar):
    cam = front_camera()
    z = np.array([3.0, 4.5])  # camera depths of two discs on the optical axis
    a = np.array([0.6, 0.7])
    normals = np.array([[0.0, -1.0, 0.0], [0.6, 0.8, 0.0]])  # the second faces away: it must be flipped
    s = {
        "means": mx.array(np.float32([[0, zi - 4.0, 0] for zi in z])),
        "quats": mx.array(quat_from_z_to(normals)),
        "scales": mx.array(np.float32([[0.5, 0.5, 1e-3]] * 2)),
        "opacities": mx.array(a.astype(np.float32)),
        "colors": mx.array(np.float32([[1, 0, 0], [0, 1, 0]])),
    }
    out = render_gaussians(cam, **s, render_depth=True, render_depth_variance=True, render_normals=True, planar_depth=planar, backend=FAST)
    i, j = cam.height // 2, cam.width // 2  # the projected means: planar and centre depths agree there
    w = np.array([a[0], a[1] * (1 - a[0])])  # both discs peak (G = 1) at the centre pixel
    mean = (w @ z) / w.sum()
    assert float(out["alpha"][i, j]) == pytest.approx(w.sum(), abs=1e-5)
    assert float(out["depth"][i, j]) == pytest.approx(mean, abs=1e-4)
    inverse_mean = (w @ (1 / z)) / w.sum()
    assert float(out["depth_variance"][i, j]) == pytest.approx((w @ (1 / z - inverse_mean) ** 2) / w.sum(), rel=1e-3)
    facing = normals * np.array([[1.0], [-1.0]])
    expected = w @ facing
    np.testing.assert_allclose(np.array(out["normals"][i, j]), expected / np.linalg.norm(expected), atol=1e-4)
    planes = "_planes" if planar else ""
    assert out["stages"] == ("project_ewa", "bin_tiles", "gaussian_normals", f"rasterize_rgb+depth{planes}+depth2+normals")
    # where nothing is hit every geometry channel is 0, and the colour is unchanged by the extra channels
    assert float(out["alpha"][0, 0]) == 0 and not np.array(out["normals"][0, 0]).any() and float(out["depth_variance"][0, 0]) == 0
    plain = render_gaussians(cam, **s, backend=FAST)
    np.testing.assert_allclose(np.array(plain["image"]), np.array(out["image"]), atol=1e-6)
    assert plain["stages"][-1] == "rasterize_rgb" and "normals" not in plain and "depth_variance" not in plain


@pytest.mark.parametrize("model", ["pinhole", "orthographic"])
def test_planar_depth_follows_a_tilted_disc(model):
    kw = {"focal": 12.0} if model == "orthographic" else {"hfov": 50.0}
    cam = Camera.look_at(eye=(0.0, -4.0, 0.0), at=(0.0, 0.0, 0.0), up=(0, 0, 1), width=41, height=33, model=model, **kw)
    normal = np.array([0.5, -0.7, 0.3])
    normal /= np.linalg.norm(normal)
    centre = np.array([0.1, 0.2, -0.1])
    s = {"means": mx.array(centre[None].astype(np.float32)), "quats": mx.array(quat_from_z_to(normal[None])),
         "scales": mx.array(np.float32([[0.6, 0.4, 1e-4]])), "opacities": mx.array(np.float32([0.99])), "colors": mx.zeros((1, 3))}
    origins, dirs = cam.rays()
    t = ((centre - origins) @ normal) / (dirs @ normal)
    truth = (origins + t[..., None] * dirs - cam.center) @ cam.camtoworld[:3, 2]
    inside = np.array(render_gaussians(cam, **s, render_depth=True, backend=FAST)["alpha"]) > 0.5
    planar = np.array(render_gaussians(cam, **s, render_depth=True, planar_depth=True, backend=FAST)["depth"])
    flat = np.array(render_gaussians(cam, **s, render_depth=True, backend=FAST)["depth"])
    assert inside.sum() > 40
    spread = np.abs(truth[inside] - truth[inside].mean()).max()
    assert spread > 0.2  # the disc is steep in depth
    assert np.abs(planar[inside] - truth[inside]).max() < (1e-4 if model == "orthographic" else 0.1 * spread)  # first order
    assert np.abs(flat[inside] - truth[inside]).max() > 0.5 * spread


@pytest.mark.parametrize("planar", [False, True])
def test_median_depth_is_the_layer_where_the_coverage_reaches_one_half(planar):
    """Two discs on the optical axis: the median depth is the front one's when it alone covers half the
    pixel, the back one's when it does not; the expected depth lies between (the analytic two-layer case)."""
    cam = front_camera()
    i, j = cam.height // 2, cam.width // 2
    for front, layer in ((0.7, 0), (0.3, 1)):
        s = {"means": mx.array(np.float32([[0, -1.0, 0], [0, 0.5, 0]])), "quats": mx.array(quat_from_z_to([[0, -1.0, 0]] * 2)),
             "scales": mx.array(np.float32([[0.5, 0.5, 1e-3]] * 2)), "opacities": mx.array(np.float32([front, 0.9]))}
        median = render_gaussian_median_depth(cam, **s, planar=planar, backend=FAST)
        expected = render_gaussians(cam, **s, colors=mx.zeros((2, 3)), render_depth=True, planar_depth=planar, backend=FAST)
        assert float(median["depth"][i, j]) == pytest.approx([3.0, 4.5][layer], abs=1e-4)
        assert 3.05 < float(expected["depth"][i, j]) < 4.45
        assert float(median["alpha"][i, j]) == pytest.approx(float(expected["alpha"][i, j]), abs=1e-6)
        covered = np.array(median["alpha"]) >= 0.5
        assert (np.array(median["depth"])[~covered] == 0).all() and (np.array(median["depth"])[covered] > 2.9).all()
    with pytest.raises(ValueError, match="level"):
        render_gaussian_median_depth(cam, **s, level=1.0)


def test_median_planar_depth_follows_a_tilted_disc_in_front_of_another():
    cam = front_camera()
    normal = np.array([0.5, -0.7, 0.3]) / np.linalg.norm([0.5, -0.7, 0.3])
    centre = np.array([0.1, 0.2, -0.1])
    s = {"means": mx.array(np.float32([centre, [0.0, 2.0, 0.0]])), "quats": mx.array(quat_from_z_to([normal, [0, -1.0, 0]])),
         "scales": mx.array(np.float32([[0.6, 0.4, 1e-4], [3.0, 3.0, 1e-4]])), "opacities": mx.array(np.float32([0.99, 0.99]))}
    origins, dirs = cam.rays()
    t = ((centre - origins) @ normal) / (dirs @ normal)
    truth = (origins + t[..., None] * dirs - cam.center) @ cam.camtoworld[:3, 2]
    alone = {k: v[:1] for k, v in s.items()}
    inside = np.array(render_gaussians(cam, **alone, colors=mx.zeros((1, 3)), backend=FAST)["alpha"]) > 0.6
    median = np.array(render_gaussian_median_depth(cam, **s, planar=True, backend=FAST)["depth"])
    expected = np.array(render_gaussians(cam, **s, colors=mx.zeros((2, 3)), render_depth=True, planar_depth=True, backend=FAST)["depth"])
    assert inside.sum() > 40
    assert np.abs(median[inside] - truth[inside]).max() < 0.05
    assert np.abs(expected[inside] - truth[inside]).max() > 0.5  # the disc behind pulls the mean depth back


def test_geometry_channels_match_explicit_feature_renders():
    rng = np.random.default_rng(3)
    n = 60
    s = {
        "means": mx.array(rng.uniform(-1, 1, (n, 3)).astype(np.float32)),
        "quats": mx.array(rng.normal(size=(n, 4)).astype(np.float32)),
        "scales": mx.array(rng.uniform(0.05, 0.3, (n, 3)).astype(np.float32)),
        "opacities": mx.array(rng.uniform(0.2, 0.9, n).astype(np.float32)),
    }
    cam = front_camera(48, 40)
    out = render_gaussians(cam, **s, colors=mx.zeros((n, 3)), render_depth=True, render_depth_variance=True, render_normals=True,
                           depth_reference=4.0, backend=FAST)
    depth = np.asarray(s["means"])[:, 1] + 4.0
    feats = np.concatenate([depth[:, None], (1 / depth[:, None] - 0.25) ** 2, np.array(facing_normals(cam, s["means"], s["quats"])),
                            1 / depth[:, None] - 0.25], 1)
    ref = np.array(render_gaussian_features(cam, s["means"], s["quats"], s["scales"], s["opacities"], mx.array(feats.astype(np.float32)), normalize=True, backend="reference")["features"])
    hit = np.array(out["alpha"]) > 1e-3
    np.testing.assert_allclose(np.array(out["depth"])[hit], ref[..., 0][hit], atol=2e-4)
    variance = ref[..., 1] - ref[..., 5] ** 2
    np.testing.assert_allclose(np.array(out["depth_variance"])[hit], np.maximum(variance, 0)[hit], atol=1e-5)
    n_ref = ref[..., 2:5] / np.maximum(np.linalg.norm(ref[..., 2:5], axis=-1, keepdims=True), 1e-12)
    strong = hit & (np.linalg.norm(ref[..., 2:5], axis=-1) > 0.05)
    np.testing.assert_allclose(np.array(out["normals"])[strong], n_ref[strong], atol=2e-3)
    # facing: every normal has a non-positive dot product with the viewing direction
    view = np.asarray(s["means"]) - cam.center
    assert (np.sum(np.array(facing_normals(cam, s["means"], s["quats"])) * view, axis=1) <= 1e-6).all()


def test_geometry_channel_gradients_match_finite_differences():
    rng = np.random.default_rng(5)
    n = 12
    base = {
        "means": rng.uniform(-0.5, 0.5, (n, 3)).astype(np.float32),
        "quats": rng.normal(size=(n, 4)).astype(np.float32),
        "scales": rng.uniform(0.15, 0.4, (n, 3)).astype(np.float32),
        "opacities": rng.uniform(0.3, 0.8, n).astype(np.float32),
    }
    cam = front_camera(24, 20)
    w_var = mx.array(rng.normal(size=(20, 24)).astype(np.float32))
    w_n = mx.array(rng.normal(size=(20, 24, 3)).astype(np.float32))

    def loss(means, quats):
        out = render_gaussians(cam, means, quats, mx.array(base["scales"]), mx.array(base["opacities"]), colors=mx.zeros((n, 3)),
                               render_depth_variance=True, render_normals=True, planar_depth=True, depth_reference=4.0, backend=FAST)
        return mx.sum(w_var * out["depth_variance"]) + mx.sum(w_n * out["normals"])

    g_means, g_quats = mx.grad(loss, argnums=(0, 1))(mx.array(base["means"]), mx.array(base["quats"]))
    for name, grad, index in (("means", g_means, (3, 1)), ("means", g_means, (7, 0)), ("quats", g_quats, (2, 3)), ("quats", g_quats, (9, 1))):
        h = 1e-3
        vals = []
        for sign in (1, -1):
            p = {k: v.copy() for k, v in base.items()}
            p[name][index] += sign * h
            vals.append(float(loss(mx.array(p["means"]), mx.array(p["quats"]))))
        fd = (vals[0] - vals[1]) / (2 * h)
        analytic = float(np.array(grad)[index])
        assert analytic == pytest.approx(fd, rel=3e-2, abs=3e-2 * max(1.0, abs(fd))), (name, index)


# ------------------------------------------------------------------ regularisers
@pytest.mark.parametrize("model", ["pinhole", "fisheye"])
def test_depth_normals_of_an_analytic_plane(model):
    kw = {"dist": (0.05, -0.01, 0.0, 0.0)} if model == "fisheye" else {}
    cam = Camera.look_at(eye=(0.3, -3.0, 1.2), at=(0.0, 0.0, 0.0), up=(0, 0, 1), width=40, height=30, hfov=60.0, model=model, **kw)
    normal = np.array([0.2, -0.9, 0.3])
    normal /= np.linalg.norm(normal)
    origins, dirs = cam.rays()
    t = -(origins @ normal) / (dirs @ normal)  # plane through the origin
    hits = origins + t[..., None] * dirs
    depth = (hits - cam.center) @ cam.camtoworld[:3, 2]  # camera z
    unprojector = geometry.DepthUnprojector()
    points = np.array(unprojector.points(cam, mx.array(depth.astype(np.float32))))
    np.testing.assert_allclose(points, hits, atol=2e-4)
    n = np.array(geometry.depth_normals(mx.array(points)))
    facing = normal if normal @ (cam.center - hits.mean((0, 1))) > 0 else -normal
    np.testing.assert_allclose(n, np.broadcast_to(facing, n.shape), atol=2e-3)
    assert unprojector.maps(cam)[0] is unprojector.maps(cam)[0]  # cached per camera


def test_depth_variance_loss_is_the_2dgs_depth_distortion_per_unit_alpha():
    """2DGS's depth distortion, as its rasterizer accumulates it front to back, is
    ``sum_i w_i sum_{j<i} w_j (m_i - m_j)^2`` (w_i = alpha_i T_i) in NDC, m = f/(f-n) (1 - n/z) with n = 0.2,
    f = 100. Ours is the same sum in scale/z divided by alpha^2, so its weight does not depend on a pixel's
    coverage or the scene's units: checked on three discs along a ray against that sum written out here."""
    cam = front_camera()
    z, a = np.array([3.0, 3.4, 4.5]), np.array([0.5, 0.4, 0.7])
    s = {"means": mx.array(np.float32([[0, zi - 4.0, 0] for zi in z])), "quats": mx.array(quat_from_z_to([[0, -1.0, 0]] * 3)),
         "scales": mx.array(np.float32([[0.5, 0.5, 1e-3]] * 3)), "opacities": mx.array(a.astype(np.float32)), "colors": mx.zeros((3, 3))}
    out = render_gaussians(cam, **s, render_depth_variance=True, planar_depth=True, backend=FAST)
    i, j = cam.height // 2, cam.width // 2
    w = a * np.concatenate([[1.0], np.cumprod(1 - a)[:-1]])  # the discs peak (G = 1) at the centre pixel
    near, far = 0.2, 100.0
    ndc = far / (far - near) * (1 - near / z)
    distortion = sum(w[k] * w[m] * (ndc[k] - ndc[m]) ** 2 for k in range(3) for m in range(k))
    mask = np.zeros((cam.height, cam.width), np.float32)
    mask[i, j] = 1.0
    scale = 2.5
    ours = geometry.depth_variance_loss(out["depth_variance"], out["alpha"] * mx.array(mask), 0.5, scale)  # that pixel alone
    assert float(out["alpha"][i, j]) == pytest.approx(w.sum(), abs=1e-5)
    assert float(ours) == pytest.approx(distortion * (scale * (far - near) / (far * near) / w.sum()) ** 2, rel=1e-3)
    # an orthographic camera's NDC depth is affine in z: there the variance is of z, in units of scale²
    ortho = Camera.look_at(eye=(0.0, -4.0, 0.0), at=(0.0, 0.0, 0.0), up=(0, 0, 1), width=cam.width, height=cam.height, model="orthographic", focal=12.0)
    out = render_gaussians(ortho, **s, render_depth_variance=True, planar_depth=True, backend=FAST)
    ours = geometry.depth_variance_loss(out["depth_variance"], out["alpha"] * mx.array(mask), 0.5, scale, orthographic=True)
    linear = sum(w[k] * w[m] * (z[k] - z[m]) ** 2 for k in range(3) for m in range(k))
    assert float(ours) == pytest.approx(linear / (w.sum() * scale) ** 2, rel=1e-3)


def test_a_far_backdrop_keeps_the_depth_variance_of_a_surface_edge_bounded():
    """A half-covering disc at depth 4 in front of a backdrop disc: the variance of inverse depth is bounded by the
    disc's own (1/4)², wherever the backdrop is (camera z's variance would grow with its distance squared: from 40
    to 4000 away, 10,000 times as much)."""
    cam = front_camera()
    i, j = cam.height // 2, cam.width // 2
    mask = np.zeros((cam.height, cam.width), np.float32)
    mask[i, j] = 1.0
    w = np.array([0.5, 0.99 * 0.5])  # both discs peak (G = 1) at the centre pixel
    mix = w[0] * w[1] / w.sum() ** 2
    for far in (40.0, 4000.0):
        s = {"means": mx.array(np.float32([[0, 0, 0], [0, far - 4.0, 0]])), "quats": mx.array(quat_from_z_to([[0, -1.0, 0]] * 2)),
             "scales": mx.array(np.float32([[0.5, 0.5, 1e-3], [far, far, 1e-3]])), "opacities": mx.array(np.float32([0.5, 0.99])),
             "colors": mx.zeros((2, 3))}
        out = render_gaussians(cam, **s, render_depth_variance=True, backend=FAST)
        loss = float(geometry.depth_variance_loss(out["depth_variance"], out["alpha"] * mx.array(mask), 0.5, 4.0))
        assert loss == pytest.approx(mix * 16 * (1 / 4 - 1 / far) ** 2, rel=1e-3) and loss < mix, far


def test_the_depth_the_normal_term_shapes_is_the_depth_fusion_reads_on_one_surface():
    """Normal consistency differentiates the planar expected depth; mesh fusion reads the planar median depth.
    Where a ray meets one surface (what the depth distortion term drives training to) they agree; where two
    layers overlap, the median keeps the front one and the mean falls between."""
    from mlx3d.render import render_gaussian_median_depth

    cam = front_camera(48, 40)
    for tilt in (0.0, 35.0):
        s = plane_surfels(tilt_deg=tilt)
        expected = render_gaussians(cam, **s, render_depth=True, planar_depth=True, backend=FAST)
        median = render_gaussian_median_depth(cam, **{k: v for k, v in s.items() if k != "colors"}, planar=True, backend=FAST)
        covered = np.array(expected["alpha"]) >= 0.9
        assert covered.sum() > 500
        np.testing.assert_allclose(np.array(median["depth"])[covered], np.array(expected["depth"])[covered], rtol=2e-3)
    front, back = plane_surfels(), plane_surfels(seed=1)
    front["opacities"] = mx.full(front["opacities"].shape, 0.15)  # covers the pixels a little over half
    back["means"] = back["means"] + mx.array([0.0, 0.3, 0.0])
    both = {k: mx.concatenate([front[k], back[k]]) for k in front}
    expected = np.array(render_gaussians(cam, **both, render_depth=True, planar_depth=True, backend=FAST)["depth"])
    median = np.array(render_gaussian_median_depth(cam, **{k: v for k, v in both.items() if k != "colors"}, planar=True, backend=FAST)["depth"])
    centre = (cam.height // 2, cam.width // 2)
    alone = float(render_gaussians(cam, **front, backend=FAST)["alpha"][centre])
    assert 0.5 < alone < 0.9
    assert median[centre] == pytest.approx(4.0, abs=2e-3) and expected[centre] > 4.05


def test_normal_consistency_and_depth_variance_tell_surfels_on_a_surface_from_others():
    cam = front_camera(48, 40)
    unprojector = geometry.DepthUnprojector()

    def losses(s):
        out = render_gaussians(cam, **s, render_depth=True, render_depth_variance=True, render_normals=True, planar_depth=True, backend=FAST)
        nc = geometry.normal_consistency_loss(out["normals"], out["depth"], out["alpha"], cam, unprojector, 0.5)
        dv = geometry.depth_variance_loss(out["depth_variance"], out["alpha"], 0.5, 4.0)
        return float(nc), float(dv)

    # the variance uses disc centres, so overlapping discs of a tilted plane show a little of it
    for tilt, max_variance in ((0.0, 1e-8), (35.0, 1e-4)):
        nc, dv = losses(plane_surfels(tilt_deg=tilt))
        assert nc < 0.02 and dv < max_variance, (tilt, nc, dv)
    # the same centres with discs turned edge-on to the plane (normals lying in it)
    sideways = dict(plane_surfels(), quats=mx.array(quat_from_z_to(np.tile([1.0, 0, 0], (24 * 24, 1)))))
    sideways["scales"] = mx.array(np.tile(np.float32([2 / 24, 1e-4, 2 / 24]), (24 * 24, 1)))  # thin along local y = world y: still a wall seen face on
    assert losses(sideways)[0] > 0.5
    # two parallel layers 0.3 apart: variance of two inverse depths
    front, back = plane_surfels(), plane_surfels()
    for layer in (front, back):
        layer["opacities"] = layer["opacities"] * 0.4  # so the back layer shows through
    back["means"] = back["means"] + mx.array([0.0, 0.3, 0.0])
    two = {k: mx.concatenate([front[k], back[k]]) for k in front}
    # oracle: per pixel the front layer weighs a_f and the back one (1 - a_f)·a_b, so the variance of
    # the two inverse depths is w_f·w_b/(w_f + w_b)²·(1/4 - 1/4.3)²
    a_f = np.array(render_gaussians(cam, **front, backend=FAST)["alpha"], np.float64)
    a_b = np.array(render_gaussians(cam, **back, backend=FAST)["alpha"], np.float64)
    w_f, w_b = a_f, (1 - a_f) * a_b
    covered = w_f + w_b >= 0.5
    expected = np.mean((w_f * w_b / np.maximum(w_f + w_b, 1e-12) ** 2 * (1 / 4 - 1 / 4.3) ** 2)[covered]) * 16.0
    assert losses(two)[1] == pytest.approx(expected, rel=0.02)


# ------------------------------------------------------------------ surfel training
def surfel_problem(seed=0):
    """A textured plane (the truth) seen from above at several angles; surfels start on it with random orientations."""
    rng = np.random.default_rng(seed)
    truth = plane_surfels(20)
    truth["colors"] = mx.array(rng.uniform(0, 1, (400, 3)).astype(np.float32))
    cams = [Camera.look_at(eye=(2.5 * math.sin(a), -3.0, 2.5 * math.cos(a)), at=(0, 0, 0), up=(0, 0, 1), width=40, height=32, hfov=50.0)
            for a in np.linspace(-0.8, 0.8, 5)]
    targets = [np.array(render_gaussians(c, **truth, background=(0, 0, 0))["image"]) for c in cams]
    start = GaussianModel.from_points(np.asarray(truth["means"]), np.asarray(truth["colors"]), sh_degree=0, initial_opacity=0.5)
    start.params["quats"] = mx.array(rng.normal(size=(400, 4)).astype(np.float32))
    return start, cams, targets


def plane_alignment(model) -> float:
    """Mean |<local z, plane normal>| (1: every disc lies in the plane y = 0)."""
    rot = quaternion_to_matrix(np.array(model.params["quats"], np.float64))
    return float(np.abs(rot[:, 1, 2]).mean())


def test_2dgs_keeps_discs_thin_and_the_normal_regulariser_lays_them_on_the_surface():
    results = {}
    for lam in (0.0, 0.5):
        model, cams, targets = surfel_problem()
        config = TrainerConfig(method="2dgs", steps=150, densify_from=10_000, geometry_from=0, lambda_2d_normal_consistency=lam, lambda_2d_depth_variance=0.0, lr_quats=1e-2)
        trainer = GaussianTrainer(model, config, scene_extent=3.0)
        limit = config.two_d_thickness * 3.0
        assert np.exp(np.array(model.params["scales"])[:, 2]).max() <= limit * (1 + 1e-5)  # clamped from the start
        infos = [trainer.step(cams[i % 5], targets[i % 5]) for i in range(150)]
        assert all(math.isfinite(i["loss"]) for i in infos)
        assert np.exp(np.array(trainer.model.params["scales"])[:, 2]).max() <= limit * (1 + 1e-5)
        assert ("normal_loss" in infos[-1]) == (lam > 0)
        results[lam] = plane_alignment(trainer.model)
    assert results[0.5] > results[0.0] + 0.1, results


def test_geometry_channels_are_rendered_only_when_their_losses_are_on(monkeypatch):
    from mlx3d.training import trainer as trainer_module

    calls = []
    real = trainer_module.render_gaussians

    def spy(*args, **kwargs):
        calls.append({k: kwargs[k] for k in ("render_depth", "render_depth_variance", "render_normals")})
        return real(*args, **kwargs)

    monkeypatch.setattr(trainer_module, "render_gaussians", spy)
    model, cams, targets = surfel_problem(1)
    for config, expected in (
        (TrainerConfig(method="vanilla", steps=4), [False, False, False]),
        (TrainerConfig(method="2dgs", steps=4, geometry_from=2, lambda_2d_normal_consistency=0.0), [False, True, False]),
        (TrainerConfig(method="2dgs", steps=4, geometry_from=2, lambda_2d_depth_variance=0.0), [True, False, True]),
    ):
        calls.clear()
        trainer = GaussianTrainer(model.copy(), config, scene_extent=3.0)
        for i in range(4):
            trainer.step(cams[i], targets[i])
        assert [list(c.values()) for c in calls] == [[False, False, False]] * 2 + [expected] * 2, config


def test_2dgs_training_fits_the_images_and_reduces_the_geometry_losses():
    model, cams, targets = surfel_problem(2)
    config = TrainerConfig(method="2dgs", steps=200, densify_from=10_000, geometry_from=50, lambda_2d_depth_variance=100.0)  # strong, to see it in 150 steps
    trainer = GaussianTrainer(model, config, scene_extent=3.0)
    infos = [trainer.step(cams[i % 5], targets[i % 5]) for i in range(200)]
    assert all(math.isfinite(i["loss"]) for i in infos)
    assert np.mean([i["psnr"] for i in infos[-5:]]) > np.mean([i["psnr"] for i in infos[:5]]) + 3
    for key, factor in (("depth_variance_loss", 0.85), ("normal_loss", 0.6)):
        assert key not in infos[49] and key in infos[50]
        assert np.mean([i[key] for i in infos[-5:]]) < factor * np.mean([i[key] for i in infos[50:55]]), key


# ------------------------------------------------------------------ model helpers
def test_apply_2dgs_constraints_clamps_only_the_third_scale():
    model = GaussianModel.from_points(np.random.default_rng(0).normal(size=(30, 3)))
    before = np.exp(np.array(model.params["scales"]))
    model.apply_2dgs_constraints(0.01)
    after = np.exp(np.array(model.params["scales"]))
    np.testing.assert_allclose(after[:, :2], before[:, :2], rtol=1e-6)
    np.testing.assert_allclose(after[:, 2], np.minimum(before[:, 2], 0.01), rtol=1e-5)
    with pytest.raises(ValueError, match="max_thickness"):
        model.apply_2dgs_constraints(0.0)


def sphere_model(n=2000, radius=1.0, seed=0, thin_axis=2, random_signs=False):
    """Discs tangent to a sphere; local axis ``thin_axis`` is the normal, outward (or of random sign)."""
    rng = np.random.default_rng(seed)
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    signed = normals * (rng.choice([-1.0, 1.0], size=(n, 1)) if random_signs else 1.0)
    rot = quaternion_to_matrix(quat_from_z_to(signed).astype(np.float64))
    quats = matrix_to_quaternion(np.roll(rot, thin_axis - 2, axis=2))  # a cyclic shift keeps det = +1
    scales = np.full((n, 3), 0.05)
    scales[:, thin_axis] = 1e-3
    scales[:, (thin_axis + 1) % 3] = rng.uniform(0.03, 0.06, n)
    params = {
        "means": (radius * normals).astype(np.float32),
        "scales": np.log(scales).astype(np.float32),
        "quats": quats.astype(np.float32),
        "opacities": np.full(n, 2.0, np.float32),
        "sh_dc": np.zeros((n, 1, 3), np.float32),
        "sh_rest": np.zeros((n, 0, 3), np.float32),
    }
    return GaussianModel(params), signed


@pytest.mark.parametrize("thin_axis", [2, 0])
def test_surfel_samples_keep_the_thinnest_axis_with_its_own_sign(thin_axis):
    model, truth = sphere_model(thin_axis=thin_axis, random_signs=True)
    points, normals, weights, colors = model.surfel_samples()
    assert points.shape == normals.shape == colors.shape == (2000, 3) and weights.shape == (2000,)
    np.testing.assert_allclose(np.sum(normals * truth, axis=1), 1.0, atol=1e-5)  # the rotation's own axis, sign kept
    assert 0.3 < np.mean(np.sum(normals * points, axis=1) > 0) < 0.7  # about half face inward: no flip
    scales = np.exp(np.array(model.params["scales"], np.float64))
    discs = np.sort(scales, axis=1)[:, 1:].prod(axis=1)
    np.testing.assert_allclose(weights, math.pi * discs / (1 + math.exp(-2.0)), rtol=1e-5)
    np.testing.assert_allclose(colors, 0.5, atol=1e-6)
    # towards a point far out on +x: every normal then faces it
    _, towards = model.surfel_samples(orient_towards=[10.0, 0, 0])[:2]
    assert (np.sum(towards * (np.array([10.0, 0, 0]) - points), axis=1) > 0).all()
    # towards the nearest of several positions: outside on both sides of x = 0, every normal turns outward
    _, outward = model.surfel_samples(orient_towards=[[10.0, 0, 0], [-10.0, 0, 0], [0, 10.0, 0], [0, -10.0, 0], [0, 0, 10.0], [0, 0, -10.0]])[:2]
    np.testing.assert_allclose(np.sum(outward * points, axis=1), 1.0, atol=1e-5)
    # normal_axis='z' reads local z whatever the scales say
    _, z_normals, z_weights, _ = model.surfel_samples(normal_axis="z")
    rot = quaternion_to_matrix(np.array(model.params["quats"], np.float64))
    np.testing.assert_allclose(z_normals, rot[:, :, 2], atol=1e-6)
    np.testing.assert_allclose(z_weights, math.pi * scales[:, 0] * scales[:, 1] / (1 + math.exp(-2.0)), rtol=1e-5)


def test_surfel_samples_filter_by_opacity_and_cap_by_disc_size():
    model, _ = sphere_model(200)
    opac = np.full(200, 2.0, np.float32)
    opac[:50] = -6.0  # opacity 0.0025
    model.params["opacities"] = mx.array(opac)
    points, *_ = model.surfel_samples(min_opacity=0.01)
    assert len(points) == 150
    capped, _, weights, _ = model.surfel_samples(min_opacity=0.01, max_points=20)
    all_points, _, all_weights, _ = model.surfel_samples(min_opacity=0.01)
    assert len(capped) == 20 and weights.min() >= np.sort(all_weights)[-20]
    order = [int(np.flatnonzero((all_points == p).all(1))[0]) for p in capped]
    assert order == sorted(order)  # kept rows stay in model order
    assert len(model.surfel_samples(min_opacity=0.99)[0]) == 0  # no fallback row here: the mesher reports it
    for method in (model.surfel_samples, model.surfel_points):
        with pytest.raises(ValueError, match="max_points"):
            method(max_points=0)
        with pytest.raises(ValueError, match="orient_towards"):
            method(orient_towards=np.zeros((0, 3)))
        with pytest.raises(ValueError, match="orient_towards"):
            method(orient_towards=np.zeros((4, 2)))
    with pytest.raises(ValueError, match="normal_axis"):
        model.surfel_samples(normal_axis="x")


def test_surface_mesh_from_surfels_on_a_sphere():
    model, _ = sphere_model(20_000, radius=2.0, seed=4)
    mesh = model.surface_mesh(resolution=96)
    assert mesh.is_watertight()
    assert mesh.area() == pytest.approx(4 * math.pi * 4.0, rel=0.02)
    assert mesh.volume() == pytest.approx(4 / 3 * math.pi * 8.0, rel=0.02)  # positive: faces point outward
    radius = np.linalg.norm(mesh.vertices, axis=1)
    voxel = 4.0 * 1.2 / 96
    assert np.abs(radius - 2.0).max() < voxel
    np.testing.assert_allclose(mesh.colors, 0.5, atol=1e-5)
    # oriented towards a camera inside the sphere, the surface turns inside out
    inside = model.surface_mesh(resolution=48, orient_towards=[[0.0, 0.0, 0.0]])
    assert inside.volume() < 0
    # extract_surface_mesh is the same mesh as a Meshes
    meshes = model.extract_surface_mesh(resolution=48)
    same = model.surface_mesh(resolution=48)
    assert len(meshes) == 1
    np.testing.assert_array_equal(np.array(meshes.verts_list()[0]), same.vertices)
    np.testing.assert_array_equal(np.array(meshes.faces_list()[0]), same.faces)
    np.testing.assert_array_equal(np.array(meshes.verts_colors_list()[0]), same.colors)


def test_surface_mesh_refuses_transparent_or_empty_models():
    from mlx3d.meshing import MeshingError

    model, _ = sphere_model(100)
    model.params["opacities"] = mx.full((100,), -10.0)
    for method in (model.surface_mesh, model.extract_surface_mesh):
        with pytest.raises(MeshingError, match=r"no Gaussian has opacity >= 0.01 \(of 100\)"):
            method()
    with pytest.raises(MeshingError, match="no Gaussian"):
        model.select(np.zeros(100, bool)).surface_mesh()
