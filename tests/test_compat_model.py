"""mlx3D compatibility of ``GaussianModel``, ``mlx3d.structures.Meshes``, ``mlx3d.ops.poisson_reconstruction``
and ``mlx3d.transforms`` (rotations): called the way mlx3D's documentation and source use them.

Oracles are independent of the code under test: the f_rest count written in the PLY header, rotations
of vectors by the quaternion product ``q (0, v) q*`` written out here, the Rodrigues formula, the
selection rules of mlx3D's ``relocate_mcmc`` and ``densify_and_prune`` restated on small crafted
tables, and sphere volume/area for the reconstructed meshes.
"""

import math

import mlx.core as mx
import numpy as np
import pytest

from mlx3d.splatting import GaussianModel
from mlx3d.structures import Meshes, join_meshes_as_batch


# ------------------------------------------------------------------ helpers
def hamilton(a, b):
    """Quaternion product of (..., 4) w,x,y,z arrays, written out independently of mlx3d."""
    w1, x1, y1, z1 = np.moveaxis(np.asarray(a, np.float64), -1, 0)
    w2, x2, y2, z2 = np.moveaxis(np.asarray(b, np.float64), -1, 0)
    return np.stack([
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
    ], axis=-1)


def rotate(q, v):
    """v rotated by the unit quaternion of q: the vector part of q (0, v) q*."""
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    conj = q * np.array([1.0, -1.0, -1.0, -1.0])
    pure = np.concatenate([np.zeros(np.shape(v)[:-1] + (1,)), v], axis=-1)
    return hamilton(hamilton(q, pure), conj)[..., 1:]


def rodrigues(axis_angle):
    angle = np.linalg.norm(axis_angle)
    k = np.asarray(axis_angle) / angle
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * kx + (1 - math.cos(angle)) * kx @ kx


def table(n, degree=3, seed=0, **overrides):
    """A raw parameter dict of n Gaussians with distinct, recognisable rows."""
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2
    params = {
        "means": rng.uniform(-1, 1, (n, 3)),
        "scales": np.log(rng.uniform(0.01, 0.05, (n, 3))),
        "quats": rng.normal(size=(n, 4)),
        "opacities": np.full(n, 2.0),
        "sh_dc": rng.normal(size=(n, 1, 3)),  # unique per row: identifies a row's source after copies
        "sh_rest": rng.normal(0, 0.1, (n, k - 1, 3)),
    }
    params.update(overrides)
    return {name: mx.array(np.asarray(v, np.float32)) for name, v in params.items()}


def np_params(model):
    return {k: np.array(v) for k, v in model.params.items()}


def ply_f_rest_count(path):
    """Number of f_rest properties declared in a PLY header."""
    with open(path, "rb") as f:
        header = f.read(4096).split(b"end_header")[0].decode("ascii")
    return sum(1 for line in header.splitlines() if line.startswith("property") and line.split()[-1].startswith("f_rest_"))


# ------------------------------------------------------------------ SH degree and active_sh_degree
def test_load_ply_keeps_the_file_degree_and_makes_it_active(tmp_path):
    model = GaussianModel(table(40, degree=2))
    model.save_ply(tmp_path / "d2.ply")
    assert ply_f_rest_count(tmp_path / "d2.ply") == 3 * 8  # degree 2 on disk
    for kwargs in ({}, {"sh_degree": 3}, {"sh_degree": 2}, {"sh_degree": 1}, {"sh_degree": 0}, {"sh_degree": None}):
        back = GaussianModel.load_ply(tmp_path / "d2.ply", **kwargs)
        assert back.sh_degree == 2 and back.active_sh_degree == 2, kwargs  # mlx3D infers the degree from the file
        assert tuple(back.params["sh_rest"].shape) == (40, 8, 3)
        np.testing.assert_array_equal(np.array(back.params["sh_rest"]), np.array(model.params["sh_rest"]))
    # the padded model our own training used to get from load_ply is one call away
    padded = GaussianModel.load_ply(tmp_path / "d2.ply").with_sh_degree(3)
    assert padded.sh_degree == 3 and padded.active_sh_degree == 2
    np.testing.assert_array_equal(np.array(padded.params["sh_rest"])[:, :8], np.array(model.params["sh_rest"]))
    assert not np.array(padded.params["sh_rest"])[:, 8:].any()


def test_active_sh_degree_starts_at_zero_and_steps_up_to_the_degree():
    pts = np.random.default_rng(0).normal(size=(50, 3)).astype(np.float32)
    model = GaussianModel.from_points(pts, sh_degree=2)
    assert model.sh_degree == 2 and model.active_sh_degree == 0
    seen = []
    for _ in range(4):
        model.one_up_sh_degree()
        seen.append(model.active_sh_degree)
    assert seen == [1, 2, 2, 2]
    assert model.copy().active_sh_degree == 2
    assert model.compact(target_sh_degree=1).active_sh_degree == 1
    assert model.compact().active_sh_degree == 2
    assert GaussianModel(table(5)).active_sh_degree == 0


def test_constructor_takes_mlx3d_sh_degree_argument():
    params = table(6, degree=1)
    for model in (GaussianModel(params, 1), GaussianModel(params, sh_degree=1)):
        assert model.sh_degree == 1 and model.extra == {}
    with pytest.raises(ValueError, match="sh_degree=3"):
        GaussianModel(params, sh_degree=3)
    model = GaussianModel(params)
    np.testing.assert_allclose(np.array(model.scales_act), np.exp(np.array(params["scales"])), rtol=1e-6)
    np.testing.assert_allclose(np.array(model.opacities_act), 1 / (1 + np.exp(-np.array(params["opacities"]))), rtol=1e-6)


# ------------------------------------------------------------------ relocate_mcmc
def relocation_case(n=100, seed=0):
    rng = np.random.default_rng(seed)
    logits = rng.uniform(0.0, 3.0, n)
    transparent = np.array([3, 17, 25, 40, 41, 66, 70, 88, 91, 99])
    logits[transparent] = rng.uniform(-9.0, -5.0, transparent.size)  # opacity < 0.007
    count = np.full(n, 5.0)
    unseen = np.array([8, 50, 77])
    count[unseen] = 0
    accum = rng.uniform(0, 1e-4, n) * count
    accum[transparent[:3]] = 1.0  # high gradient, but transparent: a destination, never a source
    return GaussianModel(table(n, opacities=logits)), accum, count, np.sort(np.concatenate([transparent, unseen]))


def test_relocate_mcmc_moves_only_underused_rows_onto_the_highest_gradient_rows():
    model, accum, count, underused = relocation_case()
    before = np_params(model)
    stats = model.relocate_mcmc(mx.array(accum.astype(np.float32)), mx.array(count.astype(np.float32)), relocate_frac=0.2, min_opacity=0.01, jitter_scale=0.25)
    after = np_params(model)
    assert len(model) == 100 and stats["relocated"] == underused.size == 13
    moved = np.sort(np.array(stats["_moved_idx"]))
    np.testing.assert_array_equal(moved, underused)
    untouched = np.setdiff1d(np.arange(100), moved)
    for name in before:
        np.testing.assert_array_equal(after[name][untouched], before[name][untouched], err_msg=name)
    # each moved row is a copy of a distinct source, the highest mean gradients among the other rows
    mean_grad = accum / np.maximum(count, 1)
    expected_sources = untouched[np.argsort(-mean_grad[untouched], kind="stable")[:13]]
    sources = [int(np.flatnonzero((before["sh_dc"] == after["sh_dc"][i]).all(axis=(1, 2)))[0]) for i in moved]
    assert sorted(sources) == sorted(expected_sources.tolist())
    for i, s in zip(moved, sources):
        np.testing.assert_array_equal(after["quats"][i], before["quats"][s])
        np.testing.assert_array_equal(after["sh_rest"][i], before["sh_rest"][s])
        assert after["opacities"][i] == pytest.approx(math.log(0.05 / 0.95), abs=1e-6)
        np.testing.assert_allclose(after["scales"][i], before["scales"][s] - math.log(1.6), atol=1e-6)
        offset = after["means"][i] - before["means"][s]
        assert 0 < np.linalg.norm(offset) < 6 * 0.25 * np.exp(before["scales"][s]).max()


def test_relocate_mcmc_budget_fallback_and_jitter():
    model, accum, count, underused = relocation_case()
    # budget below the underused count: the most transparent / unseen first
    stats = model.copy().relocate_mcmc(accum, count, relocate_frac=0.05)
    moved = np.array(stats["_moved_idx"])
    assert stats["relocated"] == 5 and set(moved) <= set(underused)
    # no underused rows: the budget still moves the lowest-opacity rows (mlx3D's fallback)
    live = GaussianModel(table(50, opacities=np.linspace(0.5, 3.0, 50)))
    stats = live.relocate_mcmc(np.ones(50), np.ones(50), relocate_frac=0.1, jitter_scale=0.0)
    assert stats["relocated"] == 5 and sorted(np.array(stats["_moved_idx"]).tolist()) == [0, 1, 2, 3, 4]
    # jitter 0: copies sit on their sources
    means = np.array(live.means)
    assert all((means[i] == means).all(axis=1).sum() == 2 for i in range(5))
    # nothing to do
    assert model.relocate_mcmc(accum, count, relocate_frac=0.0) == {"relocated": 0}
    assert GaussianModel(table(1)).relocate_mcmc(np.ones(1), np.ones(1), relocate_frac=1.0) == {"relocated": 0}
    # reproducible with a generator; moved rows' optimizer moments are cleared
    from mlx3d.training import Adam

    a, b = model.copy(), model.copy()
    opt = Adam({k: 1.0 for k in model.params})
    opt.update(a.params, {k: mx.ones_like(v) for k, v in a.params.items()})
    sa = a.relocate_mcmc(accum, count, 0.2, rng=np.random.default_rng(3), optimizer=opt)
    b.relocate_mcmc(accum, count, 0.2, rng=np.random.default_rng(3))
    np.testing.assert_array_equal(np.array(a.means), np.array(b.means))
    moments = np.array(opt.m["means"])
    assert not moments[np.array(sa["_moved_idx"])].any() and moments[np.setdiff1d(np.arange(100), np.array(sa["_moved_idx"]))].all()


# ------------------------------------------------------------------ densify_and_prune
def densify_case():
    """10 rows: 0-2 small with high gradient (clone), 3-4 large with high gradient (split),
    5-6 transparent, the rest quiet."""
    scales = np.full((10, 3), math.log(0.005))
    scales[3:5] = math.log(0.2)
    logits = np.full(10, 2.0)
    logits[5:7] = -8.0
    grads = np.full(10, 1e-5)
    grads[:5] = 1e-3
    return GaussianModel(table(10, scales=scales, opacities=logits)), grads


def test_densify_and_prune_returns_the_row_layout_for_optimizer_state():
    model, grads = densify_case()
    before = np_params(model)
    stats = model.densify_and_prune(grads, np.ones(10), return_optimizer_state=True)
    assert {k: stats[k] for k in ("cloned", "split", "pruned")} == {"cloned": 3, "split": 2, "pruned": 2}
    keep, new = stats["_keep_idx"], stats["_new_count"]
    assert isinstance(keep, np.ndarray) and keep.dtype == np.int32 and isinstance(new, int)
    # survivors: neither split sources (3, 4) nor transparent (5, 6), in their order
    np.testing.assert_array_equal(keep, [0, 1, 2, 7, 8, 9])
    assert new == 3 + 2 * 2 and len(model) == keep.size + new
    after = np_params(model)
    for name in before:
        np.testing.assert_array_equal(after[name][: keep.size], before[name][keep], err_msg=name)
    # mlx3D's recipe for carrying per-row state over works on this layout
    state = np.arange(10, dtype=np.float64) + 1.0
    carried = np.concatenate([state[keep], np.zeros(new)])
    assert carried.shape == (len(model),) and (carried[: keep.size] == keep + 1).all()
    assert "_keep_idx" not in densify_case()[0].densify_and_prune(grads, np.ones(10))


def test_densify_and_prune_layout_with_our_optimizer_and_pruned_new_rows():
    from mlx3d.training import Adam

    model, grads = densify_case()
    opt = Adam({k: 1.0 for k in model.params})
    opt.update(model.params, {k: mx.ones_like(v) for k, v in model.params.items()})
    # max_screen_size also prunes what is larger than 0.1 x extent: the split children (0.2 / 1.6)
    stats = model.densify_and_prune(grads, np.ones(10), return_optimizer_state=True, optimizer=opt, max_screen_size=20.0)
    np.testing.assert_array_equal(stats["_keep_idx"], [0, 1, 2, 7, 8, 9])
    assert stats["_new_count"] == 3 and len(model) == 9 and opt.m["means"].shape[0] == 9
    moments = np.array(opt.m["means"])
    assert moments[:6].all() and not moments[6:].any()


# ------------------------------------------------------------------ surfels
def test_surfel_points_returns_points_and_each_surfels_own_z_axis():
    rng = np.random.default_rng(4)
    n = 300
    quats = rng.normal(size=(n, 4))
    scales = np.log(rng.uniform(0.01, 0.1, (n, 3)))  # z is often not the thinnest axis: still the normal
    model = GaussianModel(table(n, quats=quats, scales=scales))
    out = model.surfel_points()
    assert isinstance(out, tuple) and len(out) == 2
    points, normals = out
    assert isinstance(points, mx.array) and isinstance(normals, mx.array) and points.dtype == normals.dtype == mx.float32
    np.testing.assert_array_equal(np.array(points), np.array(model.means))
    z_axes = rotate(quats, np.tile([0.0, 0.0, 1.0], (n, 1)))
    np.testing.assert_allclose(np.array(normals), z_axes, atol=1e-5)  # no flipping of any kind
    # towards a point: flipped where they faced away, kept otherwise
    target = np.array([0.3, -2.0, 0.5])
    _, towards = model.surfel_points(orient_towards=tuple(target))
    facing = np.sign(np.sum(z_axes * (target - np.array(model.means)), axis=1))
    np.testing.assert_allclose(np.array(towards), z_axes * facing[:, None], atol=1e-5)
    _, towards_mx = model.surfel_points(orient_towards=mx.array(target.astype(np.float32)))
    np.testing.assert_allclose(np.array(towards_mx), np.array(towards), atol=1e-6)


def test_surfel_points_ranks_by_opacity_times_xy_scales_and_never_comes_back_empty():
    n = 40
    rng = np.random.default_rng(5)
    sx, sy, sz = rng.uniform(0.01, 0.1, (3, n))
    logits = rng.uniform(-1, 3, n)
    model = GaussianModel(table(n, scales=np.log(np.stack([sx, sy, sz], 1)), opacities=logits))
    opacity = 1 / (1 + np.exp(-logits))
    importance = opacity * sx * sy
    points, _ = model.surfel_points(min_opacity=0.3, max_points=7)
    candidates = np.flatnonzero(opacity >= 0.3)
    expected = np.sort(candidates[np.argsort(-importance[candidates])[:7]])
    np.testing.assert_array_equal(np.array(points), np.array(model.means)[expected])  # model order
    # nothing opaque enough: mlx3D keeps the single most important row
    points, normals = model.surfel_points(min_opacity=1.1)
    np.testing.assert_array_equal(np.array(points), np.array(model.means)[[int(np.argmax(importance))]])
    empty = GaussianModel(table(0))
    assert tuple(empty.surfel_points()[0].shape) == tuple(empty.surfel_points()[1].shape) == (0, 3)


# ------------------------------------------------------------------ meshes
def sphere_surfels(n=8000, radius=1.0, seed=0):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    quats = np.concatenate([1.0 + d[:, 2:3], -d[:, 1:2], d[:, 0:1], np.zeros((n, 1))], axis=1)  # +z onto d
    spacing = math.sqrt(4 * math.pi / n) * radius
    return GaussianModel(table(n, means=radius * d, quats=quats, scales=np.log(np.tile([spacing, spacing, 1e-3], (n, 1)))))


def test_extract_surface_mesh_returns_meshes():
    model = sphere_surfels()
    meshes = model.extract_surface_mesh(resolution=48)
    assert isinstance(meshes, Meshes) and len(meshes) == 1 and not meshes.isempty()
    verts, faces = meshes.verts_list()[0], meshes.faces_list()[0]
    assert verts.dtype == mx.float32 and faces.dtype == mx.int32
    v, f = np.array(meshes.verts_packed(), np.float64), np.array(meshes.faces_packed())
    volume = np.einsum("ij,ij->", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])) / 6
    assert volume == pytest.approx(4 / 3 * math.pi, rel=0.03)  # outward faces
    assert float(mx.sum(meshes.faces_areas_packed())) == pytest.approx(4 * math.pi, rel=0.03)
    assert np.abs(np.linalg.norm(v, axis=1) - 1).max() < 2 * 2.4 / 48
    normals = np.array(meshes.verts_normals_packed())
    assert np.mean(np.sum(normals * v, axis=1) / np.linalg.norm(v, axis=1)) > 0.99
    # the same through mlx3d.ops, from surfel_points as mlx3D builds it
    from mlx3d.ops import poisson_reconstruction

    points, normals = model.surfel_points()
    again = poisson_reconstruction(points, normals, 48, 0.1)
    assert isinstance(again, Meshes) and len(again) == 1
    assert again.surface_mesh().volume() == pytest.approx(4 / 3 * math.pi, rel=0.03)
    with pytest.raises(ValueError):
        model.extract_surface_mesh(resolution=1)



def test_extract_surface_mesh_hands_the_selected_surfels_to_poisson_reconstruction(monkeypatch):
    """mlx3D: ``mlx3d.ops.poisson_reconstruction(points, normals, resolution=, padding=)`` of the ``max_points``
    selected surfels, so a script that substitutes that function with mlx3D's signature keeps working."""
    import mlx3d.ops as ops

    model = sphere_surfels()
    seen = {}

    def replacement(points, normals, resolution=64, padding=0.1):  # mlx3D's signature, nothing more
        seen.update(points=points, normals=normals, resolution=resolution, padding=padding)
        return Meshes([mx.array(points[:3])], [mx.array([[0, 1, 2]], dtype=mx.int32)])

    monkeypatch.setattr(ops, "poisson_reconstruction", replacement)
    assert isinstance(model.extract_surface_mesh(resolution=12, padding=0.2, max_points=4), Meshes)
    assert isinstance(seen["points"], mx.array) and seen["points"].shape == (4, 3) and seen["normals"].shape == (4, 3)
    assert (seen["resolution"], seen["padding"]) == (12, 0.2)
    expected = np.array(model.surfel_samples(max_points=4)[0])
    np.testing.assert_array_equal(np.array(seen["points"]), expected)


def test_meshes_views_of_a_batch():
    tet_v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32)
    tet_f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], np.int64)
    tri_v, tri_f = tet_v[:3] + 5, tet_f[:1]
    meshes = Meshes([mx.array(tet_v), mx.array(tri_v)], [mx.array(tet_f), mx.array(tri_f)])
    assert len(meshes) == 2
    assert np.array(meshes.num_verts_per_mesh).tolist() == [4, 3] and np.array(meshes.num_faces_per_mesh).tolist() == [4, 1]
    np.testing.assert_array_equal(np.array(meshes.verts_packed()), np.concatenate([tet_v, tri_v]))
    np.testing.assert_array_equal(np.array(meshes.faces_packed()), np.concatenate([tet_f, tri_f + 4]))
    assert np.array(meshes.mesh_to_verts_packed_first_idx()).tolist() == [0, 4]
    assert np.array(meshes.mesh_to_faces_packed_first_idx()).tolist() == [0, 4]
    assert np.array(meshes.verts_packed_to_mesh_idx()).tolist() == [0] * 4 + [1] * 3
    assert np.array(meshes.faces_packed_to_mesh_idx()).tolist() == [0] * 4 + [1]
    padded_f = np.array(meshes.faces_padded())
    assert padded_f.shape == (2, 4, 3) and (padded_f[1, 1:] == -1).all()
    padded_v = np.array(meshes.verts_padded())
    assert padded_v.shape == (2, 4, 3) and not padded_v[1, 3].any()
    rebuilt = Meshes(meshes.verts_padded(), meshes.faces_padded())
    assert np.array(rebuilt.num_faces_per_mesh).tolist() == [4, 1]
    areas = np.array(meshes.faces_areas_packed())
    np.testing.assert_allclose(areas, [0.5, 0.5, 0.5, math.sqrt(3) / 2, 0.5], rtol=1e-6)
    assert np.array(meshes.edges_packed()).shape == (6 + 3, 2)
    np.testing.assert_allclose(np.array(meshes.bounding_boxes())[1], [[5, 6], [5, 6], [5, 5]])
    moved = meshes.offset_verts(mx.array([1.0, 0, 0]))
    np.testing.assert_allclose(np.array(moved.verts_list()[0]), tet_v + [1, 0, 0])
    one = meshes[1]
    assert len(one) == 1 and np.array(one.faces_list()[0]).tolist() == tri_f.tolist()
    assert len(join_meshes_as_batch([meshes, one])) == 3
    assert meshes[0].surface_mesh().volume() == pytest.approx(1 / 6)
    # gradients flow from the vertices through the packed views
    grad = mx.grad(lambda v: mx.sum(Meshes([v], [mx.array(tet_f)]).faces_areas_packed()))(mx.array(tet_v))
    assert np.isfinite(np.array(grad)).all() and np.abs(np.array(grad)).sum() > 0
    with pytest.raises(ValueError):
        Meshes([mx.array(tet_v)], [mx.array(tet_f), mx.array(tri_f)])


# ------------------------------------------------------------------ transforms
def test_quaternion_to_matrix_rotates_like_the_quaternion_product():
    from mlx3d.transforms import quaternion_to_matrix as from_package
    from mlx3d.transforms.rotations import quaternion_to_matrix

    assert from_package is quaternion_to_matrix
    rng = np.random.default_rng(7)
    q = rng.normal(size=(2, 5, 4)) * rng.uniform(0.2, 3.0, (2, 5, 1))  # any length: normalised
    v = rng.normal(size=(2, 5, 3))
    truth = rotate(q, v)
    m_np = quaternion_to_matrix(q)
    assert m_np.shape == (2, 5, 3, 3) and isinstance(m_np, np.ndarray)
    np.testing.assert_allclose(np.einsum("...ij,...j->...i", m_np, v), truth, atol=1e-12)
    m_mx = quaternion_to_matrix(mx.array(q.astype(np.float32)))
    assert isinstance(m_mx, mx.array) and m_mx.shape == (2, 5, 3, 3)
    np.testing.assert_allclose(np.einsum("...ij,...j->...i", np.array(m_mx), v), truth, atol=1e-5)
    # (w, x, y, z): a quarter turn about +z takes x to y
    np.testing.assert_allclose(quaternion_to_matrix(np.array([math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)])) @ [1, 0, 0], [0, 1, 0], atol=1e-12)


def test_rotation_conversions_under_mlx3d_names():
    from mlx3d.transforms import rotations as r

    rng = np.random.default_rng(8)
    aa = rng.normal(size=3)
    aa *= 2.0 / np.linalg.norm(aa)  # an angle below π, so the axis-angle round trip is unique
    for wrap in (np.asarray, lambda a: mx.array(np.asarray(a, np.float32))):
        atol = 1e-10 if wrap is np.asarray else 2e-5
        np.testing.assert_allclose(np.array(r.axis_angle_to_matrix(wrap(aa))), rodrigues(aa), atol=atol)
        q = r.axis_angle_to_quaternion(wrap(aa))
        np.testing.assert_allclose(np.array(r.quaternion_to_axis_angle(q)), aa, atol=atol * 10)
        np.testing.assert_allclose(np.array(r.matrix_to_axis_angle(r.axis_angle_to_matrix(wrap(aa)))), aa, atol=atol * 10)
        m = r.quaternion_to_matrix(q)
        back = np.array(r.matrix_to_quaternion(m))
        assert back[0] >= 0
        np.testing.assert_allclose(np.abs(back @ np.array(q) / np.linalg.norm(np.array(q))), 1.0, atol=atol)
        v = rng.normal(size=3)
        np.testing.assert_allclose(np.array(r.quaternion_apply(q, wrap(v))), rotate(np.array(q), v), atol=atol)
        qi = r.quaternion_invert(q)
        np.testing.assert_allclose(np.array(r.quaternion_multiply(q, qi)) / np.linalg.norm(np.array(q)) ** 2, [1, 0, 0, 0], atol=atol)
        np.testing.assert_allclose(np.array(r.rotation_6d_to_matrix(r.matrix_to_rotation_6d(m))), np.array(m), atol=atol)
        assert (np.array(r.standardize_quaternion(wrap([-1.0, 0.2, 0.3, 0.4])))[0]) == 1.0
        e = np.array(r.euler_angles_to_matrix(wrap([0.1, -0.4, 0.7]), "XYZ"))
        np.testing.assert_allclose(e, rodrigues([0.1, 0, 0]) @ rodrigues([0, -0.4, 0]) @ rodrigues([0, 0, 0.7]), atol=atol)
    rots = np.array(r.random_rotations(16))
    np.testing.assert_allclose(rots @ np.swapaxes(rots, -1, -2), np.broadcast_to(np.eye(3), (16, 3, 3)), atol=1e-5)
    assert np.allclose(np.linalg.det(rots), 1.0, atol=1e-5)


def test_render_depth_method():
    from mlx3d.cameras import Camera

    cam = Camera.look_at(eye=(0.0, 0.0, -3.0), at=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), width=33, height=25, focal=30.0)
    disc = GaussianModel(table(1, means=[[0.0, 0.0, 0.0]], quats=[[1.0, 0, 0, 0]], scales=np.log([[0.5, 0.5, 1e-3]]), opacities=[6.0]))
    out = disc.render_depth(cam)
    assert isinstance(out, dict) and tuple(out["depth"].shape) == (25, 33)
    assert float(out["depth"][12, 16]) == pytest.approx(3.0, rel=1e-3)
    assert float(out["alpha"][12, 16]) > 0.9 and float(out["alpha"][0, 0]) < 1e-3


def test_render_features_composites_like_the_rgb_render():
    """model.render_features(camera, features) returns mlx3D's dict; with the DC colours as features it is the degree-0 render."""
    from mlx3d.cameras import Camera

    rng = np.random.default_rng(4)
    model = GaussianModel.from_points(rng.uniform(-0.5, 0.5, (200, 3)), rng.uniform(0, 1, (200, 3)))
    cam = Camera.look_at(eye=(0.0, 0.0, -3.0), width=40, height=32, fov=50)
    colours = mx.maximum(model.colors, 0.0)
    out = model.render_features(cam, colours, background=mx.array([0.2, 0.4, 0.6]))
    assert {"features", "alpha"} <= set(out) and out["features"].shape == (32, 40, 3)
    rgb = model.render(cam, background=(0.2, 0.4, 0.6), sh_degree=0)
    np.testing.assert_allclose(np.array(out["features"]), np.array(rgb["image"]), atol=2e-5)
    np.testing.assert_allclose(np.array(out["alpha"]), np.array(rgb["alpha"]), atol=2e-6)
