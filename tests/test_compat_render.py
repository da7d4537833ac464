"""The rendering API of ``mlx3d.splatting`` as the original mlx3D library defines it.

Called the way the original's documentation and tests call it (dict results,
``(sorted_ids, tile_ranges, tiles_x, tiles_y)`` from ``bin_gaussians``), and
checked against independent oracles: the analytic pinhole projection, a
brute-force float64 compositor (numpy loops), the per-tile overlap rule, the
naive every-Gaussian-at-every-pixel renderer, and the original signatures.
"""

import inspect
import math

import mlx.core as mx
import numpy as np
import pytest

from mlx3d.cameras import Camera
from mlx3d.splatting import (
    TILE_SIZE,
    bin_gaussians,
    eval_sh,
    num_sh_bases,
    project_gaussians,
    project_gaussians_ut,
    quat_scale_to_cov3d,
    rasterize,
    rasterize_depth,
    rasterize_features,
    render_gaussian_depth,
    render_gaussian_features,
    render_gaussians,
    render_gaussians_reference,
    rgb_to_sh,
    sh_to_rgb,
)

# The original's positional parameters and defaults (src/mlx3d/splatting/*.py).
# ``projection`` defaults to 'auto' here (see test_default_projection_is_ewa_for_pinhole_cameras).
ORIGINAL_SIGNATURES = {
    "project_gaussians": [("camera",), ("means",), ("quats",), ("scales",), ("blur", 0.3), ("antialias", False)],
    "project_gaussians_ut": [("camera",), ("means",), ("quats",), ("scales",), ("blur", 0.3), ("antialias", False)],
    "quat_scale_to_cov3d": [("quats",), ("scales",)],
    "bin_gaussians": [("means2d",), ("radii",), ("depths",), ("width",), ("height",), ("conics", None)],
    "rasterize": [("means2d",), ("conics",), ("colors",), ("opacities",), ("sorted_ids",), ("tile_ranges",), ("width",), ("height",),
                  ("tiles_x",), ("tiles_y",), ("background", None)],
    "rasterize_features": [("means2d",), ("conics",), ("features",), ("opacities",), ("sorted_ids",), ("tile_ranges",), ("width",),
                           ("height",), ("tiles_x",), ("tiles_y",), ("background", None), ("normalize", False)],
    "rasterize_depth": [("means2d",), ("conics",), ("opacities",), ("depths",), ("sorted_ids",), ("tile_ranges",), ("width",), ("height",),
                        ("tiles_x",), ("tiles_y",)],
    "render_gaussians_reference": [("camera",), ("means",), ("quats",), ("scales",), ("opacities",), ("colors",), ("background", None),
                                   ("antialias", False)],
    "render_gaussians": [("camera",), ("means",), ("quats",), ("scales",), ("opacities",), ("colors", None), ("sh", None), ("sh_degree", 3),
                         ("background", None), ("refine_tiles", False), ("antialias", False), ("projection", "auto")],
    "render_gaussian_depth": [("camera",), ("means",), ("quats",), ("scales",), ("opacities",), ("refine_tiles", False), ("antialias", False),
                              ("projection", "auto")],
    "render_gaussian_features": [("camera",), ("means",), ("quats",), ("scales",), ("opacities",), ("features",), ("background", None),
                                 ("normalize", False), ("refine_tiles", False), ("antialias", False), ("projection", "auto")],
    "eval_sh": [("degree",), ("sh",), ("dirs",)],
    "rgb_to_sh": [("rgb",)],
    "sh_to_rgb": [("sh_dc",)],
}


def camera(width=48, height=40, focal=45.0):
    return Camera.look_at(eye=(0.0, 0.0, -4.0), at=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), width=width, height=height, focal=focal)


def random_scene(n=120, seed=0, opacity=(0.2, 0.95), scale=(-3.2, -2.0)):
    rng = np.random.default_rng(seed)
    f = lambda a: mx.array(np.asarray(a, np.float32))  # noqa: E731
    return (
        f(rng.normal(size=(n, 3)) * 0.5),
        f(rng.normal(size=(n, 4))),
        f(np.exp(rng.uniform(*scale, (n, 3)))),
        f(rng.uniform(*opacity, n)),
        f(rng.uniform(0, 1, (n, 3))),
    )


def close(a, b, atol):
    np.testing.assert_allclose(np.array(a), np.array(b), rtol=0, atol=atol)


# ------------------------------------------------------------------ names and signatures
@pytest.mark.parametrize("name", sorted(ORIGINAL_SIGNATURES))
def test_original_positional_parameters_and_defaults(name):
    import mlx3d.splatting as splatting

    params = list(inspect.signature(getattr(splatting, name)).parameters.values())
    want = ORIGINAL_SIGNATURES[name]
    got = [(p.name,) if p.default is inspect.Parameter.empty else (p.name, p.default) for p in params[: len(want)]]
    assert got == want
    assert all(p.kind == inspect.Parameter.POSITIONAL_OR_KEYWORD for p in params[: len(want)])
    extra = params[len(want):]
    assert all(p.kind == inspect.Parameter.KEYWORD_ONLY for p in extra), [p.name for p in extra]


def test_tile_size_and_sh_helpers():
    assert TILE_SIZE == 16 and num_sh_bases(3) == 16
    rgb = mx.array(np.random.default_rng(0).uniform(0, 1, (10, 3)).astype(np.float32))
    close(sh_to_rgb(rgb_to_sh(rgb)), rgb, 1e-6)
    close(rgb_to_sh(mx.full((1, 3), 0.5)), mx.zeros((1, 3)), 0)  # the DC coefficient of grey is 0
    dirs = np.random.default_rng(1).normal(size=(10, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    dirs = mx.array(dirs.astype(np.float32))
    close(eval_sh(0, rgb_to_sh(rgb)[:, None, :], dirs), rgb, 1e-6)
    close(eval_sh(3, mx.zeros((10, 16, 3)), dirs), mx.full((10, 3), 0.5), 0)  # colours are offset by +0.5, not clamped
    sh = mx.array(np.random.default_rng(2).normal(size=(10, 4, 3)).astype(np.float32))
    c1 = 0.4886025119029199
    x, y, z = (np.array(dirs)[:, k : k + 1] for k in range(3))
    s = np.array(sh)
    want = 0.28209479177387814 * s[:, 0] - c1 * y * s[:, 1] + c1 * z * s[:, 2] - c1 * x * s[:, 3] + 0.5
    close(eval_sh(1, sh, dirs), want, 1e-5)


# ------------------------------------------------------------------ projection
def test_project_gaussians_matches_the_pinhole_projection():
    cam = camera(64, 48, focal=50.0)
    # on screen, off screen (in front of the camera), behind the camera
    means = np.array([[0.3, -0.2, 0.5], [9.0, 0.0, 0.0], [0.0, 0.0, -6.0]], np.float32)
    s = 0.05
    proj = project_gaussians(cam, mx.array(means), mx.array([[1.0, 0, 0, 0]] * 3), mx.full((3, 3), s))
    assert set(proj) == {"means2d", "conics", "depths", "radii", "compensation"}
    assert proj["radii"].dtype == mx.float32 and proj["means2d"].shape == (3, 2) and proj["conics"].shape == (3, 3)
    view = np.asarray(cam.viewmat, np.float64)
    p = means.astype(np.float64) @ view[:3, :3].T + view[:3, 3]
    uv = np.stack([cam.fx * p[:, 0] / p[:, 2] + cam.cx, cam.fy * p[:, 1] / p[:, 2] + cam.cy], 1)
    close(proj["depths"], p[:, 2], 1e-5)
    close(proj["means2d"][:2], uv[:2], 1e-3)  # the centre of an off-screen Gaussian too
    radii = np.array(proj["radii"])
    assert radii[0] > 0 and radii[1] == 0 and radii[2] == 0  # off screen and behind: culled
    assert np.array(proj["compensation"])[2] == 0 and np.array(proj["compensation"])[0] == 1
    # isotropic Gaussian: 2D covariance diag((f s / z)^2 (1 + (x/z)^2 terms)) + blur; on the axis exactly (f s / z)^2 + 0.3
    axis = project_gaussians(cam, mx.array([[0.0, 0.0, 0.0]]), mx.array([[1.0, 0, 0, 0]]), mx.full((1, 3), s))
    var = (cam.fx * s / 4.0) ** 2 + 0.3
    close(axis["conics"][0], [1 / var, 0.0, 1 / var], 1e-5 / var)
    # 3 sigma of the larger eigenvalue, floored as in 3DGS: lambda + sqrt(max(0.1, mid^2 - det))
    assert float(axis["radii"][0]) == math.ceil(3 * math.sqrt(var + math.sqrt(0.1)))
    aa = project_gaussians(cam, mx.array([[0.0, 0.0, 0.0]]), mx.array([[1.0, 0, 0, 0]]), mx.full((1, 3), s), antialias=True)
    close(aa["compensation"], [(var - 0.3) / var], 1e-5)  # sqrt(det Σ / det(Σ + blur I))


def test_project_gaussians_ut_agrees_with_ewa_for_small_gaussians():
    cam = camera()
    means, quats, _, _, _ = random_scene(20, seed=3)
    scales = mx.full((20, 3), 1e-3)
    ewa, ut = project_gaussians(cam, means, quats, scales), project_gaussians_ut(cam, means, quats, scales)
    assert set(ut) == set(ewa)
    close(ut["means2d"], ewa["means2d"], 1e-3)
    np.testing.assert_allclose(np.array(ut["conics"]), np.array(ewa["conics"]), rtol=0.05, atol=1e-3)
    np.testing.assert_array_equal(np.array(ut["radii"]) > 0, np.array(ewa["radii"]) > 0)


def test_quat_scale_to_cov3d():
    rng = np.random.default_rng(4)
    q = rng.normal(size=(6, 4))
    s = rng.uniform(0.1, 2.0, (6, 3))
    cov = np.array(quat_scale_to_cov3d(mx.array(q.astype(np.float32)), mx.array(s.astype(np.float32))))
    for i in range(6):
        w, x, y, z = q[i] / np.linalg.norm(q[i])
        r = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                      [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                      [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
        np.testing.assert_allclose(cov[i], r @ np.diag(s[i] ** 2) @ r.T, atol=1e-5)


# ------------------------------------------------------------------ binning
def _tiles_touched(x, y, r, tiles_x, tiles_y):
    """Tiles of the square [x - r, x + r] x [y - r, y + r] (the radius rule), clipped to the grid."""
    lo_x, hi_x = max(0, math.floor((x - r) / 16)), min(tiles_x - 1, math.floor((x + r) / 16))
    lo_y, hi_y = max(0, math.floor((y - r) / 16)), min(tiles_y - 1, math.floor((y + r) / 16))
    return {ty * tiles_x + tx for ty in range(lo_y, hi_y + 1) for tx in range(lo_x, hi_x + 1)}


def test_bin_gaussians_lists_exactly_the_overlapping_gaussians_front_to_back():
    cam = camera(70, 50)
    means, quats, scales, _, _ = random_scene(150, seed=5)
    proj = project_gaussians(cam, means, quats, scales)
    result = bin_gaussians(proj["means2d"], proj["radii"], proj["depths"], cam.width, cam.height)
    assert len(result) == 4
    sorted_ids, tile_ranges, tiles_x, tiles_y = result
    assert type(tiles_x) is int and type(tiles_y) is int and (tiles_x, tiles_y) == (5, 4)
    assert sorted_ids.dtype == mx.int32 and tile_ranges.dtype == mx.int32 and tile_ranges.shape == (20, 2)
    ids, ranges = np.array(sorted_ids), np.array(tile_ranges)
    xy, r, z = np.array(proj["means2d"]), np.array(proj["radii"]), np.array(proj["depths"])
    assert (ranges[:, 1] >= ranges[:, 0]).all() and (ranges[:, 1] - ranges[:, 0]).sum() == ids.size > 0
    listed = {t: ids[s:e].tolist() for t, (s, e) in enumerate(ranges)}
    for g in range(len(r)):
        touched = _tiles_touched(xy[g, 0], xy[g, 1], r[g], tiles_x, tiles_y) if r[g] > 0 else set()
        for t in range(tiles_x * tiles_y):
            assert (g in listed[t]) == (t in touched), (g, t)  # every listed id overlaps its tile, every overlap is listed
    for t, gs in listed.items():
        assert len(set(gs)) == len(gs) and (np.diff(z[gs]) >= 0).all(), t  # render order: front to back


def test_bin_gaussians_with_conics_lists_fewer_entries_and_renders_the_same_image():
    cam = camera(64, 48)
    means, quats, scales, opac, colors = random_scene(150, seed=6, scale=(-1.8, -0.8))
    proj = project_gaussians(cam, means, quats, scales)
    args = (proj["means2d"], proj["radii"], proj["depths"], cam.width, cam.height)
    plain, refined = bin_gaussians(*args), bin_gaussians(*args, conics=proj["conics"])
    p_ids, p_ranges = np.array(plain[0]), np.array(plain[1])
    r_ids, r_ranges = np.array(refined[0]), np.array(refined[1])
    assert r_ids.size < p_ids.size
    xy, con = np.array(proj["means2d"], np.float64), np.array(proj["conics"], np.float64)
    tiles_x = refined[2]
    for t in range(len(p_ranges)):
        kept = set(r_ids[r_ranges[t, 0] : r_ranges[t, 1]].tolist())
        assert kept <= set(p_ids[p_ranges[t, 0] : p_ranges[t, 1]])
        # every Gaussian of the plain list that reaches alpha >= 1/255 at opacity 1 at a pixel centre of the tile stays
        u = (t % tiles_x) * 16 + np.arange(16) + 0.5
        v = (t // tiles_x) * 16 + np.arange(16) + 0.5
        u, v = u[u < cam.width][None, :], v[v < cam.height][:, None]
        for g in p_ids[p_ranges[t, 0] : p_ranges[t, 1]]:
            dx, dy = u - xy[g, 0], v - xy[g, 1]
            q = con[g, 0] * dx * dx + 2 * con[g, 1] * dx * dy + con[g, 2] * dy * dy
            if q.min() <= 2 * math.log(255.0):
                assert g in kept, (t, g, q.min())
    images = [rasterize_features(proj["means2d"], proj["conics"], colors, opac, ids, ranges, cam.width, cam.height, tx, ty)["features"]
              for ids, ranges, tx, ty in (plain, refined)]
    close(images[0], images[1], 0)


# ------------------------------------------------------------------ a pipeline built by hand
@pytest.mark.parametrize("antialias", [False, True])
def test_hand_built_pipeline_equals_render_gaussians(antialias):
    cam = camera()
    means, quats, scales, opac, colors = random_scene(seed=7)
    bg = mx.array([0.1, 0.2, 0.3])
    proj = project_gaussians(cam, means, quats, scales, antialias=antialias)
    sorted_ids, tile_ranges, tiles_x, tiles_y = bin_gaussians(proj["means2d"], proj["radii"], proj["depths"], cam.width, cam.height)
    o = opac * proj["compensation"] if antialias else opac
    out = rasterize_features(proj["means2d"], proj["conics"], colors, o, sorted_ids, tile_ranges, cam.width, cam.height, tiles_x, tiles_y,
                             background=bg)
    assert {"features", "alpha", "final_T", "n_contrib"} <= set(out)
    ref = render_gaussians(cam, means, quats, scales, opac, colors=colors, background=bg, antialias=antialias)
    assert {"image", "alpha", "means2d", "depths", "radii", "compensation", "final_T", "n_contrib"} <= set(ref)
    close(out["features"], ref["image"], 1e-6)
    close(out["alpha"], ref["alpha"], 1e-6)
    close(out["final_T"], 1.0 - np.array(ref["alpha"]), 1e-6)
    np.testing.assert_array_equal(np.array(out["n_contrib"]) > 0, np.array(ref["alpha"]) > 0)
    # binned as render_gaussians bins (keyword-only opacities tighten the tiles): the same tile lists
    tight = bin_gaussians(proj["means2d"], proj["radii"], proj["depths"], cam.width, cam.height, proj["conics"], opacities=o)
    same = rasterize_features(proj["means2d"], proj["conics"], colors, o, *tight[:2], cam.width, cam.height, *tight[2:], background=bg)
    np.testing.assert_array_equal(np.array(same["n_contrib"]), np.array(ref["n_contrib"]))
    assert np.array(ref["n_contrib"]).max() > 1
    close(ref["radii"], proj["radii"], 0)
    close(ref["compensation"], proj["compensation"], 0)
    img = rasterize(proj["means2d"], proj["conics"], colors, o, sorted_ids, tile_ranges, cam.width, cam.height, tiles_x, tiles_y, bg)
    close(img["image"], ref["image"], 1e-6)


def test_rasterize_features_accepts_ranges_in_any_layout():
    """Empty tiles as (0, 0) (the original's layout) and ids in a permuted buffer give the same image."""
    cam = camera(96, 64)
    means, quats, scales, opac, colors = random_scene(12, seed=8)
    proj = project_gaussians(cam, means, quats, scales)
    sorted_ids, tile_ranges, tiles_x, tiles_y = bin_gaussians(proj["means2d"], proj["radii"], proj["depths"], cam.width, cam.height)
    args = (proj["means2d"], proj["conics"], colors, opac)
    base = rasterize_features(*args, sorted_ids, tile_ranges, cam.width, cam.height, tiles_x, tiles_y)["features"]
    ranges = np.array(tile_ranges)
    zeroed = np.where((ranges[:, 1] == ranges[:, 0])[:, None], 0, ranges)
    assert (zeroed != ranges).any()
    close(rasterize_features(*args, sorted_ids, mx.array(zeroed), cam.width, cam.height, tiles_x, tiles_y)["features"], base, 0)
    # tiles stored in reverse order inside the id buffer
    ids = np.array(sorted_ids)
    chunks = [ids[s:e] for s, e in ranges][::-1]
    starts = np.cumsum([0] + [len(c) for c in chunks])[:-1][::-1]
    moved = np.stack([starts, starts + (ranges[:, 1] - ranges[:, 0])], 1)
    out = rasterize_features(*args, mx.array(np.concatenate(chunks)), mx.array(moved), cam.width, cam.height, tiles_x, tiles_y)
    close(out["features"], base, 0)
    with pytest.raises(ValueError, match="tiles_x"):
        rasterize_features(*args, sorted_ids, tile_ranges, cam.width, cam.height, tiles_x + 1, tiles_y)


# ------------------------------------------------------------------ depth against a float64 brute force
def brute_force_depth(means2d, conics, opacities, depths, width, height):
    """(depth, alpha) float64: every Gaussian at every pixel centre, front to back, the 3DGS rules."""
    order = np.argsort(depths, kind="stable")
    depth = np.zeros((height, width))
    alpha_img = np.zeros((height, width))
    for py in range(height):
        for px in range(width):
            t, acc = 1.0, 0.0
            for g in order:
                dx, dy = means2d[g, 0] - (px + 0.5), means2d[g, 1] - (py + 0.5)
                a, b, c = conics[g]
                power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
                if power > 0:
                    continue
                alpha = min(0.99, opacities[g] * math.exp(power))
                if alpha < 1 / 255:
                    continue
                if t * (1 - alpha) < 1e-4:
                    break
                acc += alpha * t * depths[g]
                t *= 1 - alpha
            alpha_img[py, px] = 1 - t
            depth[py, px] = acc / (1 - t) if t < 1 else 0.0
    return depth, alpha_img


def test_rasterize_depth_matches_a_float64_brute_force():
    cam = camera(40, 32)
    rng = np.random.default_rng(9)
    n = 7
    means = mx.array(np.c_[rng.uniform(-0.5, 0.5, (n, 2)), rng.uniform(-1.0, 1.5, n)].astype(np.float32))
    quats = mx.array(rng.normal(size=(n, 4)).astype(np.float32))
    scales = mx.array(rng.uniform(0.1, 0.3, (n, 3)).astype(np.float32))
    # below 0.35 the alpha 1/255 contour lies inside 3 sigma, so the tiles cut nothing the brute force keeps
    opac = mx.array(rng.uniform(0.2, 0.34, n).astype(np.float32))
    proj = project_gaussians(cam, means, quats, scales)
    assert (np.array(proj["radii"]) > 0).all()
    sorted_ids, tile_ranges, tiles_x, tiles_y = bin_gaussians(proj["means2d"], proj["radii"], proj["depths"], cam.width, cam.height)
    out = rasterize_depth(proj["means2d"], proj["conics"], opac, proj["depths"], sorted_ids, tile_ranges, cam.width, cam.height, tiles_x, tiles_y)
    assert {"depth", "alpha", "final_T"} <= set(out) and out["depth"].shape == (32, 40)
    f64 = lambda a: np.array(a).astype(np.float64)  # noqa: E731
    depth, alpha = brute_force_depth(f64(proj["means2d"]), f64(proj["conics"]), f64(opac), f64(proj["depths"]), cam.width, cam.height)
    assert (alpha > 0.3).any() and (alpha == 0).any()
    close(out["alpha"], alpha, 2e-5)
    close(out["depth"], depth, 2e-4)
    whole = render_gaussian_depth(cam, means, quats, scales, opac)
    assert {"depth", "alpha", "means2d", "depths", "radii"} <= set(whole)
    close(whole["depth"], out["depth"], 1e-6)


# ------------------------------------------------------------------ features, reference renderer
def test_render_gaussian_features_dict_normalize_background_and_errors():
    cam = camera()
    means, quats, scales, opac, _ = random_scene(seed=10)
    n = means.shape[0]
    feats = mx.concatenate([means, mx.arange(2 * n, dtype=mx.float32).reshape(n, 2) / n], axis=1)  # 5 channels
    bg = mx.linspace(-0.2, 0.2, 5)
    out = render_gaussian_features(cam, means, quats, scales, opac, feats, background=bg)
    assert out["features"].shape == (40, 48, 5) and {"alpha", "means2d", "depths", "radii"} <= set(out)
    ref = render_gaussians_reference(cam, means, quats, scales, opac, feats, background=bg)
    close(out["features"], ref["image"], 2e-3)
    depth = render_gaussian_depth(cam, means, quats, scales, opac)
    norm = render_gaussian_features(cam, means, quats, scales, opac, depth["depths"][:, None], background=mx.array([10.0]), normalize=True)
    hit = np.array(depth["alpha"]) > 0
    assert hit.any() and (~hit).any()
    close(np.array(norm["features"][..., 0])[hit], np.array(depth["depth"])[hit], 1e-4)
    assert not np.array(norm["features"])[~hit].any()  # normalized: no background
    scalar = render_gaussian_features(cam, means, quats, scales, opac, feats[:, :1], background=0.25)
    close(np.array(scalar["features"])[~hit], 0.25, 1e-6)
    with pytest.raises(ValueError, match="features must have shape"):
        render_gaussian_features(cam, means, quats, scales, opac, feats[:, 0])
    with pytest.raises(ValueError, match="same first dimension"):
        render_gaussian_features(cam, means, quats, scales, opac, feats[:-1])


@pytest.mark.parametrize("antialias", [False, True])
def test_reference_renderer_matches_render_gaussians(antialias):
    cam = camera()
    means, quats, scales, opac, colors = random_scene(seed=11)
    bg = mx.array([0.1, 0.2, 0.3])
    out = render_gaussians(cam, means, quats, scales, opac, colors=colors, background=bg, antialias=antialias)
    ref = render_gaussians_reference(cam, means, quats, scales, opac, colors, background=bg, antialias=antialias)
    assert set(ref) == {"image", "alpha", "final_T"}
    diff = np.abs(np.array(out["image"]) - np.array(ref["image"])).max(axis=-1)
    # the naive renderer also keeps the faint rim beyond 3 sigma that the tiles may cut
    assert diff.max() < 2e-2 and (diff > 1e-5).mean() < 0.01, (diff.max(), (diff > 1e-5).mean())
    close(out["alpha"], ref["alpha"], 2e-2)
    assert float(mx.max(ref["alpha"])) > 0.5


def test_reference_renderer_gradients_match_render_gaussians():
    cam = camera(32, 24, focal=30.0)
    means, quats, scales, opac, colors = random_scene(40, seed=12, opacity=(0.1, 0.34))
    target = mx.array(np.random.default_rng(13).uniform(0, 1, (24, 32, 3)).astype(np.float32))

    def loss(fn, kw):
        def f(m, q, s, o, c):
            r = fn(cam, m, q, s, o, colors=c, background=mx.zeros((3,))) if kw else fn(cam, m, q, s, o, c, background=mx.zeros((3,)))
            return ((r["image"] - target) ** 2).mean() + 0.05 * r["alpha"].mean()
        return f

    gk = mx.grad(loss(render_gaussians, True), argnums=(0, 1, 2, 3, 4))(means, quats, scales, opac, colors)
    gr = mx.grad(loss(render_gaussians_reference, False), argnums=(0, 1, 2, 3, 4))(means, quats, scales, opac, colors)
    for name, a, b in zip(["means", "quats", "scales", "opacities", "colors"], gk, gr):
        a, b = np.array(a), np.array(b)
        assert np.abs(b).max() > 0, name
        assert np.abs(a - b).max() <= 1e-3 * np.abs(b).max(), name


# ------------------------------------------------------------------ defaults and positional calls
def test_default_projection_is_ewa_for_pinhole_cameras():
    cam = camera()
    means, quats, scales, opac, colors = random_scene(seed=14)
    default = render_gaussians(cam, means, quats, scales, opac, colors=colors)
    ewa = render_gaussians(cam, means, quats, scales, opac, colors=colors, projection="ewa")
    assert default["stages"][0] == ewa["stages"][0] == "project_ewa"
    close(default["image"], ewa["image"], 0)
    ut = render_gaussians(cam, means, quats, scales, opac, colors=colors, projection="ut")
    assert ut["stages"][0] == "project_ut"
    fisheye = Camera(width=48, height=40, fx=45.0, fy=45.0, cx=24.0, cy=20.0, viewmat=cam.viewmat, model="fisheye", dist=(0.05, 0.0, 0.0, 0.0))
    assert render_gaussians(fisheye, means, quats, scales, opac, colors=colors)["stages"][0] == "project_ut"
    with pytest.raises(ValueError, match="needs projection='ut'"):
        render_gaussians(fisheye, means, quats, scales, opac, colors=colors, projection="ewa")


def test_positional_calls_in_the_original_order():
    cam = camera()
    means, quats, scales, opac, colors = random_scene(seed=15)
    bg = mx.array([0.3, 0.2, 0.1])
    by_name = render_gaussians(cam, means, quats, scales, opac, colors=colors, background=bg, antialias=True)
    for refine in (False, True):  # refine_tiles never changes the image
        positional = render_gaussians(cam, means, quats, scales, opac, colors, None, 3, bg, refine, True, "ewa")
        close(positional["image"], by_name["image"], 0)
    sh = mx.array(np.random.default_rng(16).normal(size=(means.shape[0], 9, 3)).astype(np.float32) * 0.3)
    with_sh = render_gaussians(cam, means, quats, scales, opac, None, sh, 2, bg)
    centre = mx.array(cam.center, dtype=mx.float32)
    dirs = means - centre
    dirs = dirs / mx.linalg.norm(dirs, axis=-1, keepdims=True)
    rgb = mx.maximum(eval_sh(2, sh, dirs), 0.0)  # what the original evaluates for sh=
    close(with_sh["image"], render_gaussians(cam, means, quats, scales, opac, colors=rgb, background=bg)["image"], 1e-6)
    depth = render_gaussian_depth(cam, means, quats, scales, opac, True, True, "ewa")
    close(depth["depth"], render_gaussian_depth(cam, means, quats, scales, opac, antialias=True)["depth"], 0)


def test_camera_matrices_in_mlx_arithmetic():
    """mlx3D's ``x_cam = R x + t`` with its MLX matrices: ours are float64 numpy, so MLX arithmetic converts them
    first (``mx.array(cam.R)``, ``cam.world_to_camera_matrix``); the result is the projection's depth and means2d."""
    cam = Camera.look_at(eye=(0.3, -0.2, -3.0), at=(0, 0, 0), width=80, height=48, fov=55.0)
    means = mx.array(np.random.default_rng(11).normal(size=(16, 3)).astype(np.float32) * 0.4)
    assert isinstance(cam.R, np.ndarray) and cam.R.dtype == np.float64  # a documented difference
    p_cam = means @ mx.array(cam.R, dtype=mx.float32).T + mx.array(cam.t, dtype=mx.float32)
    view = cam.world_to_camera_matrix
    np.testing.assert_allclose(np.array(means @ view[:3, :3].T + view[:3, 3]), np.array(p_cam), atol=1e-6)
    out = project_gaussians(cam, means, mx.array(np.tile([1.0, 0, 0, 0], (16, 1)).astype(np.float32)), mx.full((16, 3), 0.05))
    np.testing.assert_allclose(np.array(out["depths"]), np.array(p_cam[:, 2]), atol=1e-5)
    uv = mx.stack([cam.fx * p_cam[:, 0] / p_cam[:, 2] + cam.cx, cam.fy * p_cam[:, 1] / p_cam[:, 2] + cam.cy], axis=-1)
    np.testing.assert_allclose(np.array(out["means2d"]), np.array(uv), atol=1e-4)
