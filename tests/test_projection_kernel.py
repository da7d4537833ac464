"""The CPU EWA projection primitive (project_ewa(backend='cpu')) against the MLX reference
(backend='reference'): every output and the gradients of means, quats and scales, with culled,
behind-the-camera, off-screen, flat and clamped Gaussians; bitwise equal for any thread count."""

import mlx.core as mx
import numpy as np
import pytest

from mlx3d.cameras import Camera
from mlx3d.render.projection import project_ewa
from thread_counts import per_thread_count
from core_marks import needs_core

pytestmark = needs_core

# the same float32 formulas in another evaluation order: outputs to a few ulp; gradients through the
# conic (which squares the 2D covariance's inverse) to 1e-3 of each entry's size, or 1e-6 of the
# largest entry where cancellation leaves an entry near zero
CONIC_RTOL = 1e-5
GRAD_RTOL = 1e-3
GRAD_FLOOR = 1e-6


def scene(n=3000, seed=0):
    rng = np.random.default_rng(seed)
    cam = Camera.look_at(eye=(0.3, -4, 1.0), at=(0, 0, 0), up=(0, 0, 1), width=64, height=48, hfov=60)
    means = rng.normal(0, 2.0, (n, 3))  # some behind the camera, many off screen
    means[:20] = np.asarray(cam.center) + rng.normal(0, 1e-3, (20, 3))  # on the camera
    quats = rng.normal(0, 1, (n, 4))
    quats[20:30] = 0.0  # zero quaternions
    scales = np.exp(rng.normal(-2, 1.0, (n, 3)))
    scales[30:60, 2] = 0.0  # flat (surfels)
    scales[60:70] = 0.0  # points
    scales[70:80] *= 1e4  # huge
    arrays = [mx.array(a.astype(np.float32)) for a in (means, quats, scales)]
    return cam, arrays, rng


def close(got, want, rtol, atol, name):
    """|got - want| <= rtol |want| + atol elementwise (atol may be per row)."""
    bad = np.abs(got - want) > rtol * np.abs(want) + atol
    assert not bad.any(), f"{name}: {bad.sum()} entries differ, e.g. {got[bad][:3]} vs {want[bad][:3]}"


def project(cam, arrays, antialias, backend):
    p = project_ewa(cam, *arrays, 0.3, antialias, backend=backend)
    return {"means2d": p.means2d, "conics": p.conics, "radii": p.radii, "depths": p.depths, "compensation": p.compensation}


@pytest.mark.parametrize("antialias", [False, True])
def test_outputs_match_the_reference(antialias):
    cam, arrays, _ = scene()
    cpu, ref = (project(cam, arrays, antialias, b) for b in ("cpu", "reference"))
    radii = np.array(ref["radii"])
    assert (radii == 0).sum() > 300 and (radii > 0).sum() > 300  # both culled and visible ones
    got = np.array(cpu["radii"])  # ceil(3 sqrt(λ)) may round to the next pixel: never culling, at most 1 px
    np.testing.assert_array_equal(got == 0, radii == 0)
    assert np.abs(got - radii).max() <= 1
    np.testing.assert_array_equal(np.array(cpu["depths"]), np.array(ref["depths"]))
    np.testing.assert_allclose(np.array(cpu["means2d"]), np.array(ref["means2d"]), rtol=1e-6, atol=1e-4)
    conics = np.array(ref["conics"])
    close(np.array(cpu["conics"]), conics, CONIC_RTOL, CONIC_RTOL * np.abs(conics).max(axis=1, keepdims=True), "conics")
    np.testing.assert_allclose(np.array(cpu["compensation"]), np.array(ref["compensation"]), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("antialias", [False, True])
def test_gradients_match_the_reference(antialias):
    cam, arrays, rng = scene(seed=1)
    n = arrays[0].shape[0]
    cots = [mx.array(rng.normal(0, 1, s).astype(np.float32)) for s in ((n, 2), (n, 3), (n,), (n,))]
    grads = {}
    for backend in ("cpu", "reference"):
        def f(m, q, s):
            p = project(cam, [m, q, s], antialias, backend)
            return p["means2d"], p["conics"], p["depths"], p["compensation"]
        grads[backend] = [np.array(g) for g in mx.vjp(f, arrays, cots)[1]]
    for name, got, want in zip(("means", "quats", "scales"), grads["cpu"], grads["reference"]):
        assert np.isfinite(got).all(), name
        close(got, want, GRAD_RTOL, GRAD_FLOOR * np.abs(want).max() + GRAD_RTOL * np.abs(want).max(axis=1, keepdims=True), name)


def test_culled_gaussians_get_gradients_only_through_their_depth():
    cam, arrays, rng = scene(seed=2)
    n = arrays[0].shape[0]
    radii = np.array(project(cam, arrays, False, "cpu")["radii"])
    behind = np.array(project(cam, arrays, False, "cpu")["depths"]) < cam.near

    def f(m, q, s):
        p = project(cam, [m, q, s], False, "cpu")
        return p["means2d"].sum() + p["conics"].sum()

    g = [np.array(x) for x in mx.grad(f, argnums=(0, 1, 2))(*arrays)]
    assert behind.sum() > 50 and not any(x[behind].any() for x in g)
    assert all(x[radii > 0].any() for x in g)


def test_bitwise_identical_for_any_thread_count():
    cam, arrays, rng = scene(n=9001, seed=3)
    cots = [mx.array(rng.normal(0, 1, s).astype(np.float32)) for s in ((9001, 2), (9001, 3), (9001,), (9001,))]

    def f(m, q, s):
        p = project(cam, [m, q, s], True, "cpu")
        return p["means2d"], p["conics"], p["depths"], p["compensation"]

    def run():
        outs, grads = mx.vjp(f, arrays, cots)
        return [np.array(a) for a in list(outs) + list(grads)]

    runs = per_thread_count(run)
    for other in runs[1:]:
        for a, b in zip(runs[0], other):
            np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("antialias", [False, True])
def test_each_gaussian_gets_the_bits_it_gets_alone(antialias):
    """The kernel projects several Gaussians at once (one per vector lane, with selects for the
    branches, the last batch padded): each one's outputs and gradients, the hard cases of scene()
    included (on the camera, zero quaternions, flat, points, huge), are bit for bit those of
    projecting it on its own."""
    n = 90
    cam, arrays, rng = scene(n=n, seed=4)
    cots = [mx.array(rng.normal(0, 1, s).astype(np.float32)) for s in ((n, 2), (n, 3), (n,), (n,))]

    def run(arrs, cs):
        def f(m, q, s):
            p = project(cam, [m, q, s], antialias, "cpu")
            return p["means2d"], p["conics"], p["depths"], p["compensation"]

        outs, grads = mx.vjp(f, arrs, cs)
        radii = project(cam, arrs, antialias, "cpu")["radii"]
        return [np.array(a) for a in list(outs) + list(grads) + [radii]]

    together = run(arrays, cots)
    for i in range(n):
        alone = run([a[i : i + 1] for a in arrays], [c[i : i + 1] for c in cots])
        for a, b in zip(together, alone):
            assert a[i : i + 1].tobytes() == b.tobytes()


def test_bad_shapes_are_refused_with_a_message():
    cam, (m, q, s), _ = scene(n=100)
    with pytest.raises(ValueError, match="quats must have shape"):
        project_ewa(cam, m, q[:, :3], s, backend="cpu")
    with pytest.raises(ValueError, match="scales must have shape"):
        project_ewa(cam, m, q, s[:5], backend="cpu")
