"""Splats the file-format tests feed every codec, and how they compare them.

- :func:`real_splats`: 500 splats of a scene trained by another program
  (OpenSplat; ``tests/data/formats/opensplat_500.ply``), SH degree 3.
- :func:`adversarial_splats`: values at the edges of what formats quantise:
  huge and tiny scales, opacities near 0 and 1, unnormalised quaternions
  with negative ``w``, colours outside [0, 1], SH at +-1, positions far out.
- :func:`assert_close_splats`: field-by-field comparison with a bound per
  field, comparing rotations as matrices (``q`` and ``-q`` are equal) and
  opacities as alphas (a logit is unbounded where alpha is not).
- ``splat_transform``: the peer tool (:mod:`peer`), or a skip with the reason.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mlx3d.io import SplatArrays, read_splat_ply
from mlx3d.io.codec import sigmoid
from mlx3d.transforms import quaternion_to_matrix
from peer import SplatTransform, find_splat_transform

DATA = Path(__file__).resolve().parent / "data" / "formats"
REAL_PLY = DATA / "opensplat_500.ply"


@pytest.fixture(scope="session")
def splat_transform() -> SplatTransform:
    """The peer tool; skips the test with the reason where it is missing."""
    path, reason = find_splat_transform()
    if path is None:
        pytest.skip(reason)
    return SplatTransform(path)


def real_splats(degree: int = 3) -> SplatArrays:
    """The committed 500-splat scene, cut to SH ``degree``."""
    s = read_splat_ply(REAL_PLY, sh_degree=degree)
    s.extra.clear()
    return s


def adversarial_splats(n: int = 256, degree: int = 3, seed: int = 0, *, span: float = 50.0) -> SplatArrays:
    """Splats with values at the edges of the quantised formats' ranges.

    Positions within ``+-span``; log scales in [-12, 4]; opacity logits in
    [-12, 12] (alphas 6e-6 .. 0.999994); quaternions unnormalised, about half
    with negative ``w``, some axis-aligned (smallest-three edge cases);
    ``f_dc`` in [-2.5, 2.5] (colours outside [0, 1]); SH rest in [-1, 1].
    """
    rng = np.random.default_rng(seed)
    k1 = (degree + 1) ** 2 - 1
    quats = rng.normal(size=(n, 4)) * rng.uniform(0.2, 3.0, size=(n, 1))
    quats[: n // 8] = np.eye(4)[rng.integers(0, 4, n // 8)] * rng.choice([-1.0, 1.0], (n // 8, 1))
    means = rng.uniform(-span, span, (n, 3))
    means[:4] = [[span, -span, 0.0], [0.0, 0.0, 0.0], [1e-4, -1e-4, 1e-4], [-span, span, span]]
    return SplatArrays(
        means=means.astype(np.float32),
        scales=rng.uniform(-12.0, 4.0, (n, 3)).astype(np.float32),
        quats=quats.astype(np.float32),
        opacities=rng.uniform(-12.0, 12.0, n).astype(np.float32),
        sh_dc=rng.uniform(-2.5, 2.5, (n, 1, 3)).astype(np.float32),
        sh_rest=rng.uniform(-1.0, 1.0, (n, k1, 3)).astype(np.float32),
    )


def rotations(quats) -> np.ndarray:
    """``(N, 3, 3)`` float64 rotation matrices of (unnormalised) quaternions."""
    q = np.asarray(quats, np.float64)
    return quaternion_to_matrix(q / np.linalg.norm(q, axis=1, keepdims=True))


def assert_close_splats(
    got: SplatArrays,
    want: SplatArrays,
    *,
    means: float = 0.0,
    scales: float = 0.0,
    rotation: float = 0.0,
    alpha: float = 0.0,
    sh_dc: float = 0.0,
    sh_rest: float = 0.0,
    what: str = "",
) -> None:
    """Assert ``got`` equals ``want`` within each absolute bound.

    ``rotation`` bounds the rotation matrices' entries; ``alpha`` bounds
    ``sigmoid(opacity)``.  Counts and SH degrees must match exactly.
    """
    assert got.count == want.count, f"{what}: {got.count} splats, want {want.count}"
    assert got.sh_degree == want.sh_degree, f"{what}: SH degree {got.sh_degree}, want {want.sh_degree}"

    def check(name, a, b, bound):
        err = float(np.max(np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64)), initial=0.0))
        assert err <= bound, f"{what}: {name} differs by {err:.3g} > {bound:.3g}"

    check("means", got.means, want.means, means)
    check("scales", got.scales, want.scales, scales)
    check("rotation", rotations(got.quats), rotations(want.quats), rotation)
    check("alpha", sigmoid(got.opacities), sigmoid(want.opacities), alpha)
    check("sh_dc", got.sh_dc, want.sh_dc, sh_dc)
    check("sh_rest", got.sh_rest, want.sh_rest, sh_rest)
