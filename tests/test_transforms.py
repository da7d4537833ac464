"""Rotations and affine maps on Gaussians, checked against independent constructions.

Tolerances: float64 math is checked to 1e-12; results stored as float32 to
1e-5 relative (the acceptance bound for covariances).
"""

import mlx.core as mx
import numpy as np
import pytest

from core_marks import needs_core
from mlx3d.errors import TransformError
from mlx3d.transforms import (
    compose_affine,
    covariances,
    euler_to_matrix,
    matrix_to_quaternion,
    quaternion_multiply,
    quaternion_to_matrix,
    split_affine,
    transform_gaussians,
    transform_normals,
)


def rodrigues(axis, angle):
    """Rotation about a unit axis by an angle (radians), from the Rodrigues formula."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def random_gaussians(n, seed=0):
    rng = np.random.default_rng(seed)
    return rng.normal(size=(n, 3)), rng.normal(size=(n, 4)), rng.normal(-1, 1, size=(n, 3))


def test_quaternion_to_matrix_matches_axis_angle():
    rng = np.random.default_rng(1)
    for _ in range(20):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        angle = rng.uniform(-np.pi, np.pi)
        q = np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis]) * rng.uniform(0.1, 10)  # any length
        np.testing.assert_allclose(quaternion_to_matrix(q), rodrigues(axis, angle), atol=1e-12)


def test_quaternion_to_matrix_numpy_and_mlx_agree():
    q = np.random.default_rng(2).normal(size=(50, 4)).astype(np.float32)
    np.testing.assert_allclose(np.array(quaternion_to_matrix(mx.array(q))), quaternion_to_matrix(q), atol=1e-6)


def test_zero_quaternion_is_finite():
    assert np.isfinite(quaternion_to_matrix(np.zeros(4))).all()


def test_matrix_to_quaternion_round_trip_including_half_turns():
    rng = np.random.default_rng(3)
    mats = [rodrigues(rng.normal(size=3), rng.uniform(-np.pi, np.pi)) for _ in range(200)]
    mats += [rodrigues(axis, np.pi) for axis in np.eye(3)] + [rodrigues([1, 1, 0], np.pi - 1e-9), np.eye(3)]
    mats = np.array(mats)
    q = matrix_to_quaternion(mats)
    assert (q[:, 0] >= 0).all()
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1, atol=1e-12)
    np.testing.assert_allclose(quaternion_to_matrix(q), mats, atol=1e-9)


def test_quaternion_multiply_composes_rotations():
    rng = np.random.default_rng(4)
    a, b = rng.normal(size=(2, 10, 4))
    np.testing.assert_allclose(quaternion_to_matrix(quaternion_multiply(a, b)), quaternion_to_matrix(a) @ quaternion_to_matrix(b), atol=1e-12)


def test_euler_is_x_then_y_then_z_about_world_axes():
    angles = (80.0, -180.0, 30.0)
    expected = rodrigues([0, 0, 1], np.radians(30)) @ rodrigues([0, 1, 0], np.radians(-180)) @ rodrigues([1, 0, 0], np.radians(80))
    np.testing.assert_allclose(euler_to_matrix(angles), expected, atol=1e-12)
    np.testing.assert_allclose(euler_to_matrix((0, 0, 90)) @ [1, 0, 0], [0, 1, 0], atol=1e-12)


def test_compose_affine_order_is_scale_rotate_translate():
    m = compose_affine(2.0, (0, 0, 90), (1, 2, 3))
    np.testing.assert_allclose(m @ [1, 0, 0, 1], [1, 4, 3, 1], atol=1e-12)


AFFINES = {
    "similarity": compose_affine(0.06, (80, -180, 30), (0.05, -0.3, 0.6)),
    "nonuniform": compose_affine((1.0, 3.0, 0.2), (10, 20, 30), (1, 0, 0)),
    "shear": np.array([[1.0, 0.7, 0.0, 0.1], [0.0, 1.0, 0.3, 0.2], [0.2, 0.0, 1.5, 0.3], [0, 0, 0, 1]]),
    "mirror": np.diag([-1.0, 1.0, 1.0, 1.0]),
    "mirror_scaled": compose_affine(2.5, (15, 0, 40), (0, 0, 0)) @ np.diag([1.0, -1.0, 1.0, 1.0]),
}


@pytest.mark.parametrize("name", sorted(AFFINES))
def test_covariance_follows_linear_part(name):
    a = AFFINES[name]
    means, quats, log_scales = random_gaussians(500)
    new_means, new_quats, new_scales = transform_gaussians(a, means, quats, log_scales)
    lin = a[:3, :3]
    expected_cov = lin @ covariances(quats, log_scales) @ lin.T
    got_cov = covariances(new_quats, new_scales)
    rel = np.linalg.norm(got_cov - expected_cov, axis=(1, 2)) / np.linalg.norm(expected_cov, axis=(1, 2))
    assert rel.max() < 1e-5, rel.max()
    np.testing.assert_allclose(new_means, means @ lin.T + a[:3, 3], rtol=1e-6, atol=1e-6)
    assert new_means.dtype == new_quats.dtype == new_scales.dtype == np.float32


def test_similarity_keeps_quaternion_length_and_adds_log_scale():
    a = AFFINES["similarity"]
    _, quats, log_scales = random_gaussians(10)
    _, new_quats, new_scales = transform_gaussians(a, np.zeros((10, 3)), quats, log_scales)
    np.testing.assert_allclose(np.linalg.norm(new_quats, axis=1), np.linalg.norm(quats, axis=1), rtol=1e-6)
    np.testing.assert_allclose(new_scales, log_scales + np.log(0.06), atol=1e-5)


def test_composition_equals_product():
    a, b = AFFINES["shear"], AFFINES["similarity"] @ AFFINES["mirror"]
    means, quats, log_scales = random_gaussians(300, seed=5)
    step1 = transform_gaussians(a, means, quats, log_scales)
    two_steps = transform_gaussians(b, *step1)
    one_step = transform_gaussians(b @ a, means, quats, log_scales)
    np.testing.assert_allclose(two_steps[0], one_step[0], rtol=1e-5, atol=1e-6)
    c2, c1 = covariances(*two_steps[1:]), covariances(*one_step[1:])
    rel = np.linalg.norm(c2 - c1, axis=(1, 2)) / np.linalg.norm(c1, axis=(1, 2))
    assert rel.max() < 1e-5


def test_split_affine_rotation_part():
    parts = split_affine(AFFINES["mirror_scaled"])
    assert parts.uniform_scale == pytest.approx(2.5)
    assert np.linalg.det(parts.rotation) == pytest.approx(-1.0)
    assert split_affine(AFFINES["nonuniform"]).uniform_scale is None
    np.testing.assert_allclose(split_affine(AFFINES["nonuniform"]).rotation, euler_to_matrix((10, 20, 30)), atol=1e-12)


def test_normals_use_inverse_transpose():
    a = AFFINES["nonuniform"]
    rng = np.random.default_rng(6)
    normals = rng.normal(size=(50, 3))
    normals[0] = 0
    tangents = np.cross(normals, rng.normal(size=(50, 3)))
    new_normals = transform_normals(a, normals)
    new_tangents = tangents @ a[:3, :3].T  # tangents map with the linear part
    assert np.abs((new_normals * new_tangents).sum(1)).max() < 1e-5 * np.linalg.norm(new_tangents, axis=1).max()
    np.testing.assert_allclose(np.linalg.norm(new_normals[1:], axis=1), 1, atol=1e-6)
    assert (new_normals[0] == 0).all()


@pytest.mark.parametrize(
    "matrix, words",
    [
        (np.zeros((4, 4)) + np.diag([1, 1, 0, 1]), "singular"),
        (np.eye(3), "shape"),
        (np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0.5, 1]]), "projective"),
        (np.diag([1, np.nan, 1, 1]), "NaN"),
    ],
)
def test_bad_transforms_are_refused(matrix, words):
    with pytest.raises(TransformError, match=words):
        transform_gaussians(matrix, *random_gaussians(3))


@needs_core
@pytest.mark.parametrize("name", ["nonuniform", "shear", "mirror_scaled"])
def test_native_kernel_matches_numpy_reference_on_hard_cases(name):
    a = AFFINES[name] @ compose_affine((1.0, 1.0, 1.0 + 1e-9), (0, 0, 0), (0, 0, 0))  # force the general path
    rng = np.random.default_rng(7)
    n = 3000
    quats = rng.normal(size=(n, 4))
    log_scales = rng.normal(-2, 1, size=(n, 3))
    log_scales[:500, 2] = np.log(1e-8)  # flat disks
    log_scales[500:1000] = -3.0  # isotropic: any eigenbasis is right
    log_scales[1000:1500] = [4.0, 4.0, -12.0]  # huge and tiny at once
    quats[1500:1600] = 0.0  # zero quaternion (treated as identity-like, finite)
    quats[1500:1600, 0] = 1e-30
    ref = transform_gaussians(a, np.zeros((n, 3)), quats, log_scales, backend="numpy")
    nat = transform_gaussians(a, np.zeros((n, 3)), quats, log_scales, backend="native")
    assert np.isfinite(nat[1]).all() and np.isfinite(nat[2]).all()
    np.testing.assert_allclose(np.linalg.norm(nat[1], axis=1), 1.0, atol=1e-6)
    c_ref, c_nat = covariances(*ref[1:]), covariances(*nat[1:])
    rel = np.linalg.norm(c_nat - c_ref, axis=(1, 2)) / np.linalg.norm(c_ref, axis=(1, 2))
    assert rel.max() < 1e-5
    # the smallest scale keeps its relative precision (no squaring of the covariance)
    np.testing.assert_allclose(np.sort(nat[2], axis=1), np.sort(ref[2], axis=1), atol=1e-5)


def test_unknown_backend_is_refused():
    with pytest.raises(ValueError, match="backend"):
        transform_gaussians(np.eye(4), *random_gaussians(2), backend="gpu")
