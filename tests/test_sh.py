"""Tests for mlx3d.splatting.sh (3DGS spherical harmonics and their rotation)."""

import math

import mlx.core as mx
import numpy as np
import pytest

from mlx3d.splatting import sh as shm
from mlx3d.splatting.sh import (
    C0,
    MAX_SH_DEGREE,
    eval_sh,
    num_sh_bases,
    rgb_to_sh,
    rotate_sh,
    sh_basis,
    sh_degree_from_bases,
    sh_rotation,
    sh_to_rgb,
)

# ----------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------


def quat_to_matrix(q):
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def random_rotation(rng):
    """Uniformly distributed rotation (normalised Gaussian quaternion)."""
    return quat_to_matrix(rng.normal(size=4))


def random_reflection(rng):
    """Uniformly distributed orthogonal matrix with det -1."""
    return random_rotation(rng) @ np.diag([1.0, 1.0, -1.0])


def random_unit(rng, n):
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def full_sh(dc, rest):
    return np.concatenate([dc, rest], axis=-2)


# Independent transcription of the 3DGS basis (graphdeco-inria
# gaussian-splatting utils/sh_utils.py) with the constants written in closed
# form rather than copied from the module.
SQPI = math.sqrt(math.pi)
REF_C0 = 1.0 / (2.0 * SQPI)
REF_C1 = math.sqrt(3.0) / (2.0 * SQPI)
REF_C2 = [
    math.sqrt(15.0) / (2.0 * SQPI),
    -math.sqrt(15.0) / (2.0 * SQPI),
    math.sqrt(5.0) / (4.0 * SQPI),
    -math.sqrt(15.0) / (2.0 * SQPI),
    math.sqrt(15.0) / (4.0 * SQPI),
]
REF_C3 = [
    -math.sqrt(35.0 / (2.0 * math.pi)) / 4.0,
    math.sqrt(105.0) / (2.0 * SQPI),
    -math.sqrt(21.0 / (2.0 * math.pi)) / 4.0,
    math.sqrt(7.0) / (4.0 * SQPI),
    -math.sqrt(21.0 / (2.0 * math.pi)) / 4.0,
    math.sqrt(105.0) / (4.0 * SQPI),
    -math.sqrt(35.0 / (2.0 * math.pi)) / 4.0,
]


def ref_basis(d):
    """16 basis values at one unit direction, written out term by term."""
    x, y, z = (float(v) for v in d)
    xx, yy, zz = x * x, y * y, z * z
    return np.array(
        [
            REF_C0,
            -REF_C1 * y,
            REF_C1 * z,
            -REF_C1 * x,
            REF_C2[0] * x * y,
            REF_C2[1] * y * z,
            REF_C2[2] * (2 * zz - xx - yy),
            REF_C2[3] * x * z,
            REF_C2[4] * (xx - yy),
            REF_C3[0] * y * (3 * xx - yy),
            REF_C3[1] * x * y * z,
            REF_C3[2] * y * (4 * zz - xx - yy),
            REF_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            REF_C3[4] * x * (4 * zz - xx - yy),
            REF_C3[5] * z * (xx - yy),
            REF_C3[6] * x * (xx - 3 * yy),
        ]
    )


# ----------------------------------------------------------------------------
# acceptance oracle: rotating the splat keeps its colour
# ----------------------------------------------------------------------------

ORACLE_TOL = 1e-5  # absolute colour error, float32 coefficients
N_MATRICES = 20
N_SPLATS = 16
N_DIRS = 128


@pytest.mark.parametrize("kind", ["rotation", "reflection"])
@pytest.mark.parametrize("degree", [1, 2, 3])
def test_oracle_rotated_colour_matches(degree, kind):
    rng = np.random.default_rng(1000 + 10 * degree + (kind == "reflection"))
    K = num_sh_bases(degree)
    make = random_rotation if kind == "rotation" else random_reflection
    worst = 0.0
    for _ in range(N_MATRICES):
        R = make(rng)
        assert np.sign(np.linalg.det(R)) == (1 if kind == "rotation" else -1)
        dc = rng.normal(size=(N_SPLATS, 1, 3)).astype(np.float32)
        rest = rng.normal(size=(N_SPLATS, K - 1, 3)).astype(np.float32)
        d = random_unit(rng, N_DIRS)[:, None, :]  # (D, 1, 3) vs (N, K, 3)
        rotated = rotate_sh(rest, R)
        assert rotated.dtype == np.float32 and rotated.shape == rest.shape
        before = eval_sh(degree, full_sh(dc, rest), d)
        after = eval_sh(degree, full_sh(dc, rotated), d @ R.T)
        assert before.shape == (N_DIRS, N_SPLATS, 3)
        worst = max(worst, float(np.max(np.abs(after - before))))
    assert worst < ORACLE_TOL, worst


def test_oracle_mlx_arrays():
    rng = np.random.default_rng(7)
    degree, K = 3, 16
    for R in [random_rotation(rng), random_reflection(rng)]:
        dc = mx.array(rng.normal(size=(N_SPLATS, 1, 3)).astype(np.float32))
        rest = mx.array(rng.normal(size=(N_SPLATS, K - 1, 3)).astype(np.float32))
        d = random_unit(rng, N_DIRS)[:, None, :].astype(np.float32)
        rotated = rotate_sh(rest, R)
        assert isinstance(rotated, mx.array) and rotated.dtype == mx.float32
        before = eval_sh(degree, mx.concatenate([dc, rest], axis=-2), mx.array(d))
        after = eval_sh(
            degree,
            mx.concatenate([dc, rotated], axis=-2),
            mx.array((d @ R.T).astype(np.float32)),
        )
        assert float(mx.max(mx.abs(after - before))) < ORACLE_TOL


# ----------------------------------------------------------------------------
# basis: constants, signs, orthonormality
# ----------------------------------------------------------------------------


def test_constants_match_closed_forms():
    assert C0 == pytest.approx(REF_C0, abs=1e-15)
    assert shm.C1 == pytest.approx(REF_C1, abs=1e-15)
    np.testing.assert_allclose(shm.C2, REF_C2, rtol=0, atol=1e-14)
    np.testing.assert_allclose(shm.C3, REF_C3, rtol=0, atol=1e-14)
    assert MAX_SH_DEGREE == 3


def test_basis_at_axes_by_hand():
    c22, c24 = REF_C2[2], REF_C2[4]
    expected = {
        (0.0, 0.0, 1.0): [REF_C0, 0, REF_C1, 0, 0, 0, 2 * c22, 0, 0,
                          0, 0, 0, 2 * REF_C3[3], 0, 0, 0],
        (1.0, 0.0, 0.0): [REF_C0, 0, 0, -REF_C1, 0, 0, -c22, 0, c24,
                          0, 0, 0, 0, -REF_C3[4], 0, REF_C3[6]],
        (0.0, 1.0, 0.0): [REF_C0, -REF_C1, 0, 0, 0, 0, -c22, 0, -c24,
                          -REF_C3[0], 0, -REF_C3[2], 0, 0, 0, 0],
        (0.0, 0.0, -1.0): [REF_C0, 0, -REF_C1, 0, 0, 0, 2 * c22, 0, 0,
                           0, 0, 0, -2 * REF_C3[3], 0, 0, 0],
    }
    for d, vals in expected.items():
        got = sh_basis(3, np.array(d))
        # 1e-10: the epsilon guard in the normalisation shifts values by ~1e-12
        np.testing.assert_allclose(got, vals, rtol=0, atol=1e-10, err_msg=str(d))
    # literal numbers for a few entries (+z band-3 zonal, +x band-1)
    assert sh_basis(3, np.array([0.0, 0.0, 1.0]))[12] == pytest.approx(0.7463526651802308)
    assert sh_basis(1, np.array([1.0, 0.0, 0.0]))[3] == pytest.approx(-0.4886025119029199)


def test_basis_at_generic_directions_by_hand():
    rng = np.random.default_rng(3)
    dirs = np.concatenate(
        [random_unit(rng, 6), [[1.0, 2.0, 3.0]], [[-0.3, 0.8, -0.52]]], axis=0
    )
    unit = dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)
    got = sh_basis(3, dirs)  # un-normalised input is normalised inside
    assert got.shape == (len(dirs), 16)
    for g, d in zip(got, unit):
        np.testing.assert_allclose(g, ref_basis(d), rtol=0, atol=1e-10)
    # lower degrees are prefixes
    for deg in range(3):
        np.testing.assert_array_equal(sh_basis(deg, dirs), got[:, : num_sh_bases(deg)])


def test_basis_orthonormal_on_sphere():
    # Product Gauss-Legendre (in cos theta) x uniform phi: exact for the
    # degree <= 6 polynomials Y_i * Y_j.
    t, wt = np.polynomial.legendre.leggauss(10)
    m = 24
    phi = 2.0 * np.pi * np.arange(m) / m
    T, P = np.meshgrid(t, phi, indexing="ij")
    s = np.sqrt(1.0 - T * T)
    dirs = np.stack([s * np.cos(P), s * np.sin(P), T], axis=-1).reshape(-1, 3)
    w = (wt[:, None] * np.full(m, 2.0 * np.pi / m)[None, :]).reshape(-1)
    B = sh_basis(3, dirs)
    gram = B.T @ (w[:, None] * B)
    np.testing.assert_allclose(gram, np.eye(16), rtol=0, atol=1e-8)


def test_basis_zero_direction_is_finite_and_mx_matches_numpy():
    out = sh_basis(3, np.zeros(3))
    assert np.all(np.isfinite(out))
    rng = np.random.default_rng(4)
    d = rng.normal(size=(5, 3)).astype(np.float32)
    got = sh_basis(2, mx.array(d))
    assert isinstance(got, mx.array) and got.shape == (5, 9)
    np.testing.assert_allclose(np.array(got), sh_basis(2, d), rtol=0, atol=1e-6)


# ----------------------------------------------------------------------------
# rotation matrices
# ----------------------------------------------------------------------------


def _some_orthogonal(rng, n=6):
    return [random_rotation(rng) for _ in range(n)] + [
        random_reflection(rng) for _ in range(n)
    ]


def test_sh_rotation_shapes_and_orthogonality():
    rng = np.random.default_rng(5)
    for R in _some_orthogonal(rng):
        mats = sh_rotation(R)
        assert [D.shape for D in mats] == [(3, 3), (5, 5), (7, 7)]
        for D in mats:
            assert D.dtype == np.float64
            np.testing.assert_allclose(D @ D.T, np.eye(len(D)), rtol=0, atol=1e-12)
    assert len(sh_rotation(np.eye(3), degree=1)) == 1
    assert sh_rotation(np.eye(3), degree=0) == []


def test_sh_rotation_identity_and_inversion():
    for D in sh_rotation(np.eye(3)):
        np.testing.assert_allclose(D, np.eye(len(D)), rtol=0, atol=1e-12)
    # point reflection -I: band l picks up the parity (-1)^l
    for l, D in enumerate(sh_rotation(-np.eye(3)), start=1):
        np.testing.assert_allclose(D, (-1) ** l * np.eye(2 * l + 1), rtol=0, atol=1e-12)


def test_sh_rotation_band1_explicit():
    # 90 deg about +z: x -> y, y -> -x.  Band 1 basis is C1 * (-y, z, -x).
    Rz = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    (D1,) = sh_rotation(Rz, degree=1)
    # c = (1, 0, 0) is f(d) = -C1*d_y.  Its image g must satisfy g(R d) = f(d);
    # (R d)_x = -d_y, so g(e) = C1*e_x = -(-C1*e_x), i.e. c' = (0, 0, -1).
    # c = (0, 1, 0) is C1*d_z, unchanged by a rotation about z.
    np.testing.assert_allclose(D1 @ [1.0, 0.0, 0.0], [0.0, 0.0, -1.0], atol=1e-12)
    np.testing.assert_allclose(D1 @ [0.0, 1.0, 0.0], [0.0, 1.0, 0.0], atol=1e-12)


def test_sh_rotation_is_a_homomorphism():
    rng = np.random.default_rng(6)
    mats = _some_orthogonal(rng, 4)
    for R1, R2 in zip(mats, mats[::-1]):
        for A, B, C in zip(sh_rotation(R1), sh_rotation(R2), sh_rotation(R1 @ R2)):
            np.testing.assert_allclose(C, A @ B, rtol=0, atol=1e-12)


def test_rotate_then_transpose_gives_back_input():
    rng = np.random.default_rng(8)
    for R in _some_orthogonal(rng, 3):
        x64 = rng.normal(size=(10, 15, 3))
        back = rotate_sh(rotate_sh(x64, R), R.T)
        np.testing.assert_allclose(back, x64, rtol=0, atol=1e-12)
        x32 = x64.astype(np.float32)
        back32 = rotate_sh(rotate_sh(x32, R), R.T)
        assert back32.dtype == np.float32
        np.testing.assert_allclose(back32, x32, rtol=0, atol=1e-6)
        # the rotation actually changes generic coefficients
        assert np.max(np.abs(rotate_sh(x64, R) - x64)) > 1e-2


def test_rotate_sh_dtypes_types_and_degree0():
    rng = np.random.default_rng(9)
    R = random_rotation(rng)
    for K in (4, 9, 16):
        x = rng.normal(size=(3, K - 1, 3))
        for dt in (np.float32, np.float64):
            out = rotate_sh(x.astype(dt), R)
            assert isinstance(out, np.ndarray) and out.dtype == dt
            assert out.shape == x.shape
    mx_in = mx.array(rng.normal(size=(4, 8, 3)).astype(np.float32))
    mx_out = rotate_sh(mx_in, R)
    assert isinstance(mx_out, mx.array) and mx_out.dtype == mx.float32
    np.testing.assert_allclose(
        np.array(mx_out), rotate_sh(np.array(mx_in), R), rtol=0, atol=1e-6
    )
    # degree 0: nothing to rotate, a copy comes back
    empty = np.zeros((5, 0, 3), dtype=np.float32)
    out = rotate_sh(empty, R)
    assert out.shape == (5, 0, 3) and out.dtype == np.float32 and out is not empty
    out_mx = rotate_sh(mx.zeros((5, 0, 3)), R)
    assert isinstance(out_mx, mx.array) and out_mx.shape == (5, 0, 3)


def test_rotation_input_validation():
    rng = np.random.default_rng(10)
    rest = rng.normal(size=(2, 15, 3))
    with pytest.raises(ValueError, match="deviation|R\\^T R - I"):
        sh_rotation(np.diag([1.0, 1.0, 1.1]))
    with pytest.raises(ValueError, match="2.001e-03"):  # 1.001**2 - 1
        sh_rotation(np.diag([1.0, 1.0, 1.001]))
    # within tolerance is accepted
    sh_rotation(random_rotation(rng) + 1e-7)
    with pytest.raises(ValueError, match="3x3"):
        sh_rotation(np.eye(4))
    with pytest.raises(ValueError, match="NaN|Inf"):
        sh_rotation(np.full((3, 3), np.nan))
    with pytest.raises(ValueError):
        rotate_sh(rest, 2.0 * np.eye(3))
    with pytest.raises(ValueError, match="K=6"):
        rotate_sh(rng.normal(size=(2, 5, 3)), np.eye(3))
    with pytest.raises(ValueError, match="4"):
        sh_rotation(np.eye(3), degree=4)


# ----------------------------------------------------------------------------
# eval_sh
# ----------------------------------------------------------------------------


def test_eval_sh_matches_basis_sum():
    rng = np.random.default_rng(11)
    sh = rng.normal(size=(7, 16, 3))
    d = rng.normal(size=(7, 3))
    for deg in range(4):
        k = num_sh_bases(deg)
        expected = np.einsum("nk,nkc->nc", sh_basis(deg, d), sh[:, :k]) + 0.5
        np.testing.assert_allclose(eval_sh(deg, sh, d), expected, rtol=0, atol=1e-12)


def test_eval_sh_numpy_and_mlx_agree():
    rng = np.random.default_rng(12)
    sh = rng.normal(size=(6, 16, 3)).astype(np.float32)
    d = rng.normal(size=(6, 3)).astype(np.float32)
    for deg in range(4):
        ref = eval_sh(deg, sh, d)
        got = eval_sh(deg, mx.array(sh), mx.array(d))
        assert isinstance(ref, np.ndarray) and ref.dtype == np.float32
        assert isinstance(got, mx.array) and got.dtype == mx.float32
        np.testing.assert_allclose(np.array(got), ref, rtol=0, atol=1e-5)
    # mixed inputs give an mlx result
    assert isinstance(eval_sh(2, mx.array(sh), d), mx.array)


GRAD_ATOL = 2e-4  # float32 mlx gradient vs float64 central differences
GRAD_RTOL = 1e-3


def test_eval_sh_gradient_matches_finite_differences():
    rng = np.random.default_rng(13)
    deg = 3
    sh = rng.normal(size=(3, 16, 3))
    d = rng.normal(size=(3, 3)) * 1.7  # not unit: normalisation is in the graph
    w = rng.normal(size=(3, 3))

    def loss_np(s, dd):
        return float(np.sum(eval_sh(deg, s, dd) * w))

    def loss_mx(s, dd):
        return mx.sum(eval_sh(deg, s, dd) * mx.array(w.astype(np.float32)))

    g_sh, g_d = mx.grad(loss_mx, argnums=(0, 1))(
        mx.array(sh.astype(np.float32)), mx.array(d.astype(np.float32))
    )
    g_sh, g_d = np.array(g_sh), np.array(g_d)
    assert np.all(np.isfinite(g_sh)) and np.all(np.isfinite(g_d))

    h = 1e-6

    def fd(f, x):
        g = np.zeros_like(x)
        for idx in np.ndindex(x.shape):
            xp, xm = x.copy(), x.copy()
            xp[idx] += h
            xm[idx] -= h
            g[idx] = (f(xp) - f(xm)) / (2 * h)
        return g

    fd_sh = fd(lambda s: loss_np(s, d), sh)
    fd_d = fd(lambda dd: loss_np(sh, dd), d)
    np.testing.assert_allclose(g_sh, fd_sh, rtol=GRAD_RTOL, atol=GRAD_ATOL)
    np.testing.assert_allclose(g_d, fd_d, rtol=GRAD_RTOL, atol=GRAD_ATOL)
    assert np.max(np.abs(fd_d)) > 1e-2  # the direction gradient is not trivially 0


def test_eval_sh_ignores_extra_coefficients():
    rng = np.random.default_rng(14)
    sh = rng.normal(size=(5, 16, 3))
    d = rng.normal(size=(5, 3))
    for deg in range(3):
        k = num_sh_bases(deg)
        poisoned = sh.copy()
        poisoned[:, k:] = np.nan  # never read, so never propagates
        out = eval_sh(deg, poisoned, d)
        assert np.all(np.isfinite(out))
        np.testing.assert_array_equal(out, eval_sh(deg, sh[:, :k], d))


def test_eval_sh_degree0_and_broadcasting():
    rng = np.random.default_rng(15)
    sh = rng.normal(size=(4, 9, 3))
    np.testing.assert_allclose(eval_sh(0, sh, np.ones(3)), C0 * sh[:, 0] + 0.5, atol=1e-15)
    # several views of the same splats: dirs (V, N, 3) against sh (N, K, 3)
    dirs = rng.normal(size=(2, 4, 3))
    for deg in range(3):
        out = eval_sh(deg, sh, dirs)
        assert out.shape == (2, 4, 3)
        np.testing.assert_allclose(out[1], eval_sh(deg, sh, dirs[1]), atol=1e-14)
    assert eval_sh(0, mx.array(sh.astype(np.float32)), mx.array(dirs)).shape == (2, 4, 3)


def test_eval_sh_normalises_dirs():
    rng = np.random.default_rng(16)
    sh = rng.normal(size=(5, 16, 3))
    d = rng.normal(size=(5, 3))
    np.testing.assert_allclose(eval_sh(3, sh, d * 3.7), eval_sh(3, sh, d), atol=1e-12)
    assert np.all(np.isfinite(eval_sh(3, sh, np.zeros((5, 3)))))
    z = eval_sh(3, mx.array(sh.astype(np.float32)), mx.zeros((5, 3)))
    assert np.all(np.isfinite(np.array(z)))


def test_eval_sh_errors():
    sh = np.zeros((2, 9, 3))
    d = np.ones((2, 3))
    for bad in (-1, 4, 1.5, True):
        with pytest.raises(ValueError):
            eval_sh(bad, sh, d)
    with pytest.raises(ValueError, match="K=9"):
        eval_sh(3, sh, d)
    with pytest.raises(ValueError, match="dirs"):
        eval_sh(1, sh, np.ones((2, 2)))


# ----------------------------------------------------------------------------
# small helpers
# ----------------------------------------------------------------------------


def test_num_sh_bases_and_inverse():
    assert [num_sh_bases(d) for d in range(4)] == [1, 4, 9, 16]
    assert [sh_degree_from_bases(k) for k in (1, 4, 9, 16)] == [0, 1, 2, 3]
    assert num_sh_bases(np.int64(2)) == 9
    with pytest.raises(ValueError, match="4"):
        num_sh_bases(4)
    with pytest.raises(ValueError, match="-1"):
        num_sh_bases(-1)
    for k in (0, 2, 5, 25):
        with pytest.raises(ValueError, match=f"K={k}"):
            sh_degree_from_bases(k)


def test_rgb_sh_round_trip():
    rng = np.random.default_rng(17)
    rgb = rng.uniform(size=(10, 3))
    np.testing.assert_allclose(sh_to_rgb(rgb_to_sh(rgb)), rgb, atol=1e-14)
    np.testing.assert_allclose(rgb_to_sh(np.full(3, 0.5)), 0.0, atol=0)
    np.testing.assert_allclose(rgb_to_sh(1.0), 0.5 / C0)
    rgb_mx = mx.array(rgb.astype(np.float32))
    back = sh_to_rgb(rgb_to_sh(rgb_mx))
    assert isinstance(back, mx.array)
    np.testing.assert_allclose(np.array(back), rgb, atol=1e-6)
    # DC-only colour from eval_sh equals sh_to_rgb
    dc = rgb_to_sh(rgb)[:, None, :]
    np.testing.assert_allclose(eval_sh(0, dc, np.ones((10, 3))), rgb, atol=1e-14)
