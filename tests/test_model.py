"""GaussianModel: construction, row operations, compaction, merging and object insertion.

Oracles: brute-force nearest neighbours for scale initialisation, a per-splat
loop for the insertion transform, the SH colour invariance
colour(rotated, R d) == colour(original, d), and the PLY file's own columns.
"""

import os
import warnings

import mlx.core as mx
import numpy as np
import pytest
from plyfile import PlyData

from mlx3d.splatting import GaussianModel, eval_sh, merge
from mlx3d.transforms import compose_affine

DATA = os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data")


def random_model(n=200, degree=3, seed=0, extra=None):
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2
    params = {
        "means": rng.normal(size=(n, 3)),
        "scales": rng.normal(-2, 0.5, size=(n, 3)),
        "quats": rng.normal(size=(n, 4)),
        "opacities": rng.normal(0, 2, size=n),
        "sh_dc": rng.normal(0, 0.5, size=(n, 1, 3)),
        "sh_rest": rng.normal(0, 0.1, size=(n, k - 1, 3)),
    }
    return GaussianModel({key: mx.array(v.astype(np.float32)) for key, v in params.items()}, extra)


def np_params(model):
    return {k: np.array(v) for k, v in model.params.items()}


# ---------------------------------------------------------------- from_points
def brute_mean_knn(ref, queries, k, self_rows=None):
    d = np.linalg.norm(queries[:, None, :].astype(np.float64) - ref[None, :, :], axis=-1)
    if self_rows is not None:
        for qi, ri in enumerate(self_rows):
            if ri >= 0:
                d[qi, ri] = np.inf
    return np.sort(d, axis=1)[:, :k].mean(axis=1)


def test_from_points_scales_are_mean_distance_to_three_neighbours():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-1, 1, (500, 3)).astype(np.float32)
    colors = rng.integers(0, 256, (500, 3)).astype(np.uint8)
    model = GaussianModel.from_points(pts, colors, sh_degree=2, initial_opacity=0.2)
    p = np_params(model)
    expected = brute_mean_knn(pts, pts, 3, self_rows=np.arange(500))
    np.testing.assert_allclose(np.exp(p["scales"]), np.repeat(expected[:, None], 3, 1), rtol=1e-5)
    np.testing.assert_allclose(np.array(model.colors), colors / 255.0, atol=1e-6)
    np.testing.assert_allclose(np.array(model.opacities), 0.2, atol=1e-6)
    np.testing.assert_array_equal(p["quats"], np.tile([1, 0, 0, 0], (500, 1)))
    assert p["sh_rest"].shape == (500, 8, 3) and not p["sh_rest"].any()
    assert model.sh_degree == 2


def test_from_points_uses_a_bounded_reference_subset_and_cap():
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(3000, 3)).astype(np.float32)
    model = GaussianModel.from_points(pts, scale_init_max_ref=400, scale_init_chunk_size=128, scale_init_max_scale=0.2, seed=7)
    ref_rows = np.sort(np.random.default_rng(7).choice(3000, 400, replace=False))
    self_rows = np.full(3000, -1)
    self_rows[ref_rows] = np.arange(400)
    expected = np.minimum(brute_mean_knn(pts[ref_rows], pts, 3, self_rows), 0.2)
    np.testing.assert_allclose(np.exp(np.array(model.params["scales"][:, 0])), expected, rtol=1e-5)
    assert np.isclose(np.exp(np.array(model.params["scales"])).max(), 0.2, rtol=1e-6)


def test_from_points_duplicates_stay_finite():
    pts = np.zeros((10, 3), np.float32)
    model = GaussianModel.from_points(pts)
    assert np.isfinite(np.array(model.params["scales"])).all()


@pytest.mark.parametrize(
    "kwargs, words",
    [
        ({"points": np.zeros((1, 3))}, "at least 2"),
        ({"points": np.zeros((5, 2))}, "shape"),
        ({"points": np.array([[0, 0, 0], [1, np.nan, 0], [2, 2, 2]])}, "NaN"),
        ({"points": np.zeros((5, 3)), "colors": np.zeros((4, 3))}, "colors"),
        ({"points": np.zeros((5, 3)), "initial_opacity": 1.0}, "initial_opacity"),
    ],
)
def test_from_points_bad_input(kwargs, words):
    with pytest.raises(ValueError, match=words):
        GaussianModel.from_points(**kwargs)


@pytest.mark.skipif(not os.path.exists(os.path.join(DATA, "test_garden.npz")), reason="shared/data/test_garden.npz not present")
def test_from_points_on_real_garden_points():
    data = np.load(os.path.join(DATA, "test_garden.npz"))
    model = GaussianModel.from_points(data["means3d"], data["colors"])
    assert len(model) == 138766
    scales = np.exp(np.array(model.params["scales"]))
    assert np.isfinite(scales).all() and (scales > 0).all()
    # scales are set against a 10k-point reference subset: they must be on the order of
    # (not smaller than) the true 3-NN spacing among those reference points
    assert np.median(scales) < 0.1 * np.linalg.norm(data["means3d"].max(0) - data["means3d"].min(0))


# ---------------------------------------------------------------- rows
def test_copy_select_append():
    m = random_model(10, extra={"id": np.arange(10, dtype=np.int32)})
    c = m.copy()
    c.select(np.array([True, False] * 5))
    assert len(m) == 10 and len(c) == 5
    np.testing.assert_array_equal(c.extra["id"], [0, 2, 4, 6, 8])
    np.testing.assert_array_equal(np.array(c.params["means"]), np.array(m.params["means"])[::2])
    c.select([4, 0])
    np.testing.assert_array_equal(c.extra["id"], [8, 0])
    other = random_model(3, seed=9)
    c.append(other.params)
    assert len(c) == 5
    np.testing.assert_array_equal(c.extra["id"], [8, 0, 0, 0, 0])
    np.testing.assert_array_equal(np.array(c.params["sh_rest"])[2:], np.array(other.params["sh_rest"]))
    with pytest.raises(ValueError, match="SH degree"):
        c.append(random_model(2, degree=1).params)
    with pytest.raises(ValueError, match="out of range"):
        c.select([7])


# ---------------------------------------------------------------- compact
def test_compact_keeps_most_important_in_original_order():
    m = random_model(100, extra={"id": np.arange(100, dtype=np.int32)})
    before = np_params(m)
    out = m.compact(max_gaussians=30)
    p = before
    importance = 1 / (1 + np.exp(-p["opacities"].astype(np.float64))) * np.exp(p["scales"].astype(np.float64)).max(1) ** 2
    expected_rows = np.sort(np.argsort(-importance)[:30])
    np.testing.assert_array_equal(out.extra["id"], expected_rows)
    np.testing.assert_array_equal(np.array(out.params["means"]), p["means"][expected_rows])
    for k, v in np_params(m).items():  # input untouched
        np.testing.assert_array_equal(v, before[k])


def test_compact_min_opacity_and_never_empty():
    m = random_model(50)
    opacity = np.array(m.opacities)
    out = m.compact(min_opacity=0.5)
    assert len(out) == int((opacity >= 0.5).sum())
    assert (np.array(out.opacities) >= 0.5).all()
    empty = m.compact(min_opacity=1.1)
    assert len(empty) == 1
    np.testing.assert_array_equal(np.array(empty.params["means"])[0], np.array(m.params["means"])[np.argmax(m.importance())])


def test_compact_sh_truncation_keeps_first_coefficients_of_each_channel(tmp_path):
    m = random_model(20, degree=3)
    m.save_ply(tmp_path / "in.ply")
    m.compact(target_sh_degree=1).save_ply(tmp_path / "out.ply")
    src = PlyData.read(str(tmp_path / "in.ply"))["vertex"]
    dst = PlyData.read(str(tmp_path / "out.ply"))["vertex"]
    assert len([p for p in dst.properties if p.name.startswith("f_rest_")]) == 9
    # channel-major: out f_rest_{c*3+j} == in f_rest_{c*15+j}
    for c in range(3):
        for j in range(3):
            np.testing.assert_array_equal(dst[f"f_rest_{c * 3 + j}"], src[f"f_rest_{c * 15 + j}"])


def test_compact_bad_arguments():
    m = random_model(5, degree=1)
    with pytest.raises(ValueError, match="max_gaussians"):
        m.compact(max_gaussians=0)
    with pytest.raises(ValueError, match="target_sh_degree"):
        m.compact(target_sh_degree=2)


# ---------------------------------------------------------------- merge
def test_merge_pads_or_truncates_sh_and_unions_extras():
    a = random_model(4, degree=1, extra={"id": np.arange(4, dtype=np.int32)})
    b = random_model(3, degree=3, seed=2)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = merge([a, b])
    assert any("id" in str(w.message) for w in caught)
    assert out.sh_degree == 3 and len(out) == 7
    rest = np.array(out.params["sh_rest"])
    np.testing.assert_array_equal(rest[:4, :3], np.array(a.params["sh_rest"]))
    assert not rest[:4, 3:].any()
    np.testing.assert_array_equal(rest[4:], np.array(b.params["sh_rest"]))
    np.testing.assert_array_equal(out.extra["id"], [0, 1, 2, 3, 0, 0, 0])
    with pytest.warns(UserWarning, match="id"):
        low = merge([a, b], sh_degree=1)
    assert low.sh_degree == 1
    np.testing.assert_array_equal(np.array(low.params["sh_rest"])[4:], np.array(b.params["sh_rest"])[:, :3])
    with pytest.raises(ValueError):
        merge([])


# ---------------------------------------------------------------- insertion
def rotation_from_euler_loop(rx, ry, rz):
    """Rz @ Ry @ Rx built from per-axis matrices written out here."""
    def axis_rot(axis, deg):
        c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
        i, j = [(1, 2), (2, 0), (0, 1)][axis]
        r = np.eye(3)
        r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
        return r

    return axis_rot(2, rz) @ axis_rot(1, ry) @ axis_rot(0, rx)


def covariance_of(q, log_s):
    w, x, y, z = q / np.linalg.norm(q)
    r = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    return r @ np.diag(np.exp(2 * log_s)) @ r.T


def test_object_insertion_recipe_against_per_splat_computation():
    scene = random_model(300, seed=11)
    obj = random_model(200, seed=12)
    s, euler, t = 0.06, (80.0, -180.0, 30.0), np.array([0.05, -0.3, 0.6])
    merged = merge([scene, obj.transform(compose_affine(s, euler, t))])
    assert len(merged) == 500
    got = np_params(merged)
    src = np_params(obj)
    for k in got:  # scene rows untouched
        np.testing.assert_array_equal(got[k][:300], np_params(scene)[k])
    rot = rotation_from_euler_loop(*euler)
    rng = np.random.default_rng(0)
    dirs = rng.normal(size=(64, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    for i in range(200):
        j = 300 + i
        np.testing.assert_allclose(got["means"][j], s * rot @ src["means"][i] + t, rtol=1e-5, atol=1e-6)
        want = s * s * rot @ covariance_of(src["quats"][i].astype(np.float64), src["scales"][i]) @ rot.T
        have = covariance_of(got["quats"][j].astype(np.float64), got["scales"][j].astype(np.float64))
        assert np.linalg.norm(have - want) <= 1e-5 * np.linalg.norm(want)
    # view-dependent colour follows the rotation: colour'(R d) == colour(d)
    sh_old = np.concatenate([src["sh_dc"], src["sh_rest"]], 1).astype(np.float64)
    sh_new = np.concatenate([got["sh_dc"][300:], got["sh_rest"][300:]], 1).astype(np.float64)
    before = eval_sh(3, sh_old[:, None], dirs[None])
    after = eval_sh(3, sh_new[:, None], (dirs @ rot.T)[None])
    np.testing.assert_allclose(after, before, atol=1e-5)


def test_transform_composition_and_normals():
    n = 50
    rng = np.random.default_rng(3)
    normals = rng.normal(size=(n, 3)).astype(np.float32)
    m = random_model(n, extra={"nx": normals[:, 0], "ny": normals[:, 1], "nz": normals[:, 2]})
    a = compose_affine((1.0, 2.0, 0.5), (30, 0, 10), (0, 1, 0))
    b = compose_affine(3.0, (0, 45, 0), (1, 0, 0))
    two, one = m.transform(a).transform(b), m.transform(b @ a)
    np.testing.assert_allclose(np.array(two.params["means"]), np.array(one.params["means"]), rtol=1e-5, atol=1e-5)
    dirs = rng.normal(size=(16, 3))
    np.testing.assert_allclose(
        eval_sh(3, np.array(two.sh)[:, None].astype(np.float64), dirs[None]),
        eval_sh(3, np.array(one.sh)[:, None].astype(np.float64), dirs[None]),
        atol=1e-5,
    )
    new_n = np.stack([two.extra[k] for k in ("nx", "ny", "nz")], 1)
    np.testing.assert_allclose(np.linalg.norm(new_n, axis=1), 1, atol=1e-5)
    assert two.extra["nx"].dtype == np.float32
    np.testing.assert_array_equal(np.array(m.params["means"]), np_params(m)["means"])  # input unchanged


# ---------------------------------------------------------------- files
def test_save_load_round_trip_and_sh_degree_option(tmp_path):
    m = random_model(30, degree=2, extra={"id": np.arange(30, dtype=np.int32)})
    m.save_ply(tmp_path / "m.ply")
    back = GaussianModel.load_ply(tmp_path / "m.ply", sh_degree=None)
    for k, v in np_params(m).items():
        np.testing.assert_array_equal(np.array(back.params[k]), v)
    np.testing.assert_array_equal(back.extra["id"], m.extra["id"])
    # the file's degree whatever sh_degree says (as mlx3D), all of it active
    for kwargs in ({}, {"sh_degree": 3}, {"sh_degree": 1}):
        loaded = GaussianModel.load_ply(tmp_path / "m.ply", **kwargs)
        assert loaded.sh_degree == loaded.active_sh_degree == 2, kwargs
    assert GaussianModel.load_ply(tmp_path / "m.ply").with_sh_degree(3).sh_degree == 3
    assert GaussianModel.load_ply(tmp_path / "m.ply").with_sh_degree(1).sh_degree == 1


def test_constructor_validates_shapes():
    p = np_params(random_model(4))
    p["quats"] = p["quats"][:, :3]
    with pytest.raises(ValueError, match="quats"):
        GaussianModel(p)
