"""Property-based stability of the renderer over many orders of magnitude.

Every case is rebuilt from ``(SEED, index)`` by ``build_case``: N in [1, 300]
Gaussians around a scene whose scale is log-uniform in [1e-3, 1e3], some of
them behind the camera, on the camera plane, exactly at the camera centre, on
the near plane, beyond ``far`` or far outside the image; scales log-uniform in
[1e-7, 1e3] times the scene scale with exactly degenerate axes; zero, tiny and
huge quaternions; opacities 0, tiny, uniform, 1 - 1e-7 and 1; plain colours or
SH of degree 0..3; every camera model (pinhole, opencv, fisheye, orthographic)
posed by ``Camera.look_at`` from a random direction and distance, image sizes
from 1x1 to 64x48 and focal lengths from a 179-degree field of view to a
telescope; EWA (where valid) or UT projection, antialias on or off, the
geometry channels (depth, variance, normals, planar depth) on some cases. The
C++ kernel renders most cases; every 10th case (at most 60 Gaussians) runs the
pure-MLX reference rasterizer instead and compares its maps with the kernel's.

``run_case`` checks that every output is finite and in range (alpha in [0, 1],
colour within what the Gaussians and the background can make, depth within
the visible Gaussians' depths, variance >= 0, normals at most unit length), and
that the gradient of a random linear function of every rendered map w.r.t.
means, quats, scales, opacities and colours/SH is finite, exactly zero for
culled Gaussians (radius 0, among them all whose centre lies outside
[near, far] and all placed well outside a pinhole or orthographic image) and
exactly zero for visible Gaussians that reach no pixel centre with
alpha >= 1/255 (checked independently in float64 from the projected 2D
Gaussians).

The tests at the end are reductions of cases this generator found (NaN
gradients and a negative radius from valid inputs), fixed in
``mlx3d/render/projection.py`` and ``geometry_channels.py``.

Reproduce case 17 (failure messages name the case and seed)::

    cd tests && python -c "import test_render_stability as t; print(t.build_case(17)); t.run_case(t.build_case(17))"

Explore more cases: ``MLX3D_STABILITY_SEED=7 MLX3D_STABILITY_CASES=2000 pytest tests/test_render_stability.py``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import mlx.core as mx
import numpy as np
import pytest

from mlx3d.cameras import Camera
from mlx3d.render import project_gaussians, project_gaussians_ut, render_gaussians
from mlx3d.splatting.sh import eval_sh

from core_marks import FAST

SEED = int(os.environ.get("MLX3D_STABILITY_SEED", "20250611"))
NUM_CASES = int(os.environ.get("MLX3D_STABILITY_CASES", "300"))
REFERENCE_EVERY = 10  # the slow pure-MLX rasterizer on every 10th case (small ones)

MODELS = ("pinhole", "opencv", "fisheye", "orthographic")
SIZES = ((1, 1), (3, 5), (5, 3), (17, 9), (64, 48), (33, 20))
KINDS = ("cluster", "spread", "behind", "camera_plane", "camera_centre", "near_plane", "beyond_far", "outside_image")
KIND_P = (0.5, 0.1, 0.08, 0.06, 0.05, 0.05, 0.08, 0.08)
ALPHA_MIN = 1.0 / 255.0


def _log_uniform(rng, lo, hi, size=None):
    return 10.0 ** rng.uniform(np.log10(lo), np.log10(hi), size)


@dataclass
class Case:
    index: int
    seed: int
    camera: Camera
    scene_scale: float
    distance: float
    means: np.ndarray  # (N,3) float32
    quats: np.ndarray
    scales: np.ndarray
    opacities: np.ndarray
    colors: np.ndarray | None
    sh: np.ndarray | None
    sh_degree: int
    background: tuple | None
    antialias: bool
    projection: str
    backend: str
    render_depth: bool
    render_depth_variance: bool
    render_normals: bool
    planar_depth: bool
    kinds: np.ndarray = field(repr=False)  # (N,) the placement of each Gaussian (KINDS)
    weights_seed: int = 0

    @property
    def label(self) -> str:
        c = self.camera
        return (
            f"case {self.index} (seed {self.seed}; rebuild with build_case({self.index}, seed={self.seed})): "
            f"{c.model} {c.width}x{c.height} f={c.fx:.3g} near={c.near:.3g} far={c.far:.3g} dist={self.dist_str()}, "
            f"N={len(self.means)}, scene scale {self.scene_scale:.3g}, projection={self.projection}, "
            f"antialias={self.antialias}, backend={self.backend}, "
            f"{'colors' if self.sh is None else f'sh (K={self.sh.shape[1]}) up to degree {self.sh_degree}'}, "
            f"depth={self.render_depth} variance={self.render_depth_variance} normals={self.render_normals} planar={self.planar_depth}"
        )

    def dist_str(self) -> str:
        return "(" + ", ".join(f"{d:.3g}" for d in self.camera.dist) + ")"

    def inputs(self) -> list:
        colour = self.colors if self.sh is None else self.sh
        return [mx.array(a) for a in (self.means, self.quats, self.scales, self.opacities, colour)]

    def render(self, means, quats, scales, opacities, colour, backend=None):
        kw = {"colors": colour} if self.sh is None else {"sh": colour, "sh_degree": self.sh_degree}
        return render_gaussians(
            self.camera, means, quats, scales, opacities, background=self.background, antialias=self.antialias,
            projection=self.projection, backend=backend or self.backend, render_depth=self.render_depth,
            render_depth_variance=self.render_depth_variance, render_normals=self.render_normals,
            planar_depth=self.planar_depth, **kw,
        )


def _random_camera(rng, scale):
    """A random camera looking at a random target; returns (camera, its distance to the target, the target)."""
    model = MODELS[rng.integers(len(MODELS))]
    width, height = SIZES[rng.integers(len(SIZES))]
    target = rng.normal(size=3) * scale * (_log_uniform(rng, 1.0, 1e3) if rng.random() < 0.2 else 1.0)
    distance = scale * _log_uniform(rng, 0.3, 30.0)
    while True:
        direction = rng.normal(size=3)
        up = rng.normal(size=3) if rng.random() < 0.5 else np.array([0.0, 0.0, 1.0])
        direction /= np.linalg.norm(direction)
        if np.linalg.norm(np.cross(direction, up / np.linalg.norm(up))) > 1e-3:
            break
    eye = target + direction * distance
    kw = {"model": model}
    if model == "opencv":
        kw["dist"] = (0.0,) * 5 if rng.random() < 0.25 else (
            rng.uniform(-0.3, 0.3), rng.uniform(-0.1, 0.1), rng.uniform(-0.02, 0.02), rng.uniform(-0.02, 0.02), rng.uniform(-0.05, 0.05))
    elif model == "fisheye":
        kw["dist"] = tuple(rng.uniform(-0.05, 0.05, 4))
    if model == "orthographic":
        near = float(rng.choice([0.01, -distance * rng.uniform(0, 2), distance * rng.uniform(0, 0.9)]))
        focal = width / (scale * _log_uniform(rng, 1e-3, 1e3))
    else:
        near = distance * _log_uniform(rng, 1e-6, 0.5)
        focal = width * _log_uniform(rng, 1e-2, 1e4)  # from a 179-degree field of view to a telescope
    far = 1e10 if rng.random() < 0.5 else near + distance * _log_uniform(rng, 0.5, 100.0)
    kw.update(near=near, far=far)
    if model != "orthographic" and rng.random() < 0.3:
        cam = Camera.look_at(eye, target, up, width=width, height=height, hfov=float(rng.uniform(0.01, 179.0)), **kw)
    else:
        cam = Camera.look_at(eye, target, up, width=width, height=height, focal=focal, **kw)
    return cam, distance, target


def build_case(index: int, seed: int = SEED) -> Case:
    """Case ``index`` of the property test for ``seed``: deterministic, independent of the other cases."""
    rng = np.random.default_rng([seed, index])
    scale = float(_log_uniform(rng, 1e-3, 1e3))
    cam, distance, target = _random_camera(rng, scale)
    n = int(np.clip(np.round(_log_uniform(rng, 1, 300)), 1, 300))
    kinds = np.array(KINDS)[rng.choice(len(KINDS), n, p=KIND_P)]

    # camera-space placements for the special kinds, world-space for the scene itself
    c2w = cam.camtoworld
    perspective = cam.model != "orthographic"
    half_w = 0.5 * cam.width / cam.fx  # tan of the half field of view (orthographic: half the width in world units)
    half_h = 0.5 * cam.height / cam.fy
    far = min(cam.far, 1e12)
    means = target + rng.normal(size=(n, 3)) * scale
    spread = kinds == "spread"
    means[spread] = target + rng.normal(size=(spread.sum(), 3)) * scale * _log_uniform(rng, 1.0, 1e3, (spread.sum(), 1))
    cam_pts = np.zeros((n, 3))
    sigma_max = np.zeros(n)  # outside_image: largest scale that keeps the Gaussian off the image
    lateral = rng.normal(size=(n, 2)) * distance
    for g in range(n):
        k = kinds[g]
        if k == "behind":
            cam_pts[g] = [*lateral[g], min(cam.near, 0.0) * 1.01 - distance * _log_uniform(rng, 1e-3, 10.0)]
        elif k == "camera_plane":
            cam_pts[g] = [*lateral[g], 0.0]
        elif k == "camera_centre":
            cam_pts[g] = [0.0, 0.0, 0.0]
        elif k == "near_plane":
            cam_pts[g] = [*(lateral[g] * 0.1), cam.near]
        elif k == "beyond_far":
            z = far * _log_uniform(rng, 1.01, 100.0)
            cam_pts[g] = [*(lateral[g] * z / distance * 0.1), z]
        elif k == "outside_image":
            z = distance * _log_uniform(rng, 0.1, 10.0)
            if not perspective:
                z = distance * rng.uniform(0.1, 2.0) + max(cam.near, 0.0)
            depth_scale = z if perspective else 1.0
            axis = rng.integers(2)
            half = (half_w, half_h)[axis]
            # at least 2 half-widths and 10 pixels beyond the edge
            beyond = max(2.0, 10.0 / (half * (cam.fx, cam.fy)[axis])) * _log_uniform(rng, 1.0, 30.0)
            xy = rng.uniform(-1, 1, 2) * np.array([half_w, half_h])
            xy[axis] = (1.0 + beyond) * half * rng.choice([-1.0, 1.0])
            cam_pts[g] = [*(xy * depth_scale), z]
            # largest standard deviation that keeps even the linearised 3-sigma footprint (and the blur)
            # outside: the offset beyond the edge over the perspective stretch 1 + (x/z)^2 + (y/z)^2
            stretch = 1.0 + float(np.sum(xy * xy)) if perspective else 1.0
            sigma_max[g] = 0.1 * beyond * half * depth_scale / stretch
    placed = ~np.isin(kinds, ("cluster", "spread"))
    world = cam_pts @ c2w[:3, :3].T + c2w[:3, 3]
    means[placed] = world[placed]

    # scales: log-uniform over ten decades of the scene scale, anisotropic, some exactly degenerate
    scales = scale * _log_uniform(rng, 1e-7, 1e3, (n, 1)) * _log_uniform(rng, 1e-2, 1.0, (n, 3))
    degenerate = rng.random(n)
    for g in np.flatnonzero(degenerate < 0.2):
        axes = rng.choice(3, 1 if degenerate[g] < 0.1 else (2 if degenerate[g] < 0.17 else 3), replace=False)
        scales[g, axes] = 0.0 if rng.random() < 0.7 else 1e-30
    outside = kinds == "outside_image"
    if outside.any():
        # small enough that the 3-sigma box (blur included) stays outside the image
        scales[outside] = sigma_max[outside, None] * _log_uniform(rng, 1e-3, 1.0, (outside.sum(), 3))

    quats = rng.normal(size=(n, 4))
    qkind = rng.random(n)
    quats[qkind < 0.05] = 0.0
    small = (qkind >= 0.05) & (qkind < 0.15)
    quats[small] *= _log_uniform(rng, 1e-20, 1e-3, (small.sum(), 1))
    large = (qkind >= 0.15) & (qkind < 0.25)
    quats[large] *= _log_uniform(rng, 1e3, 1e15, (large.sum(), 1))

    opacities = rng.uniform(0, 1, n)
    okind = rng.random(n)
    opacities[okind < 0.1] = 0.0
    opacities[(okind >= 0.1) & (okind < 0.2)] = 1 - 1e-7
    opacities[(okind >= 0.2) & (okind < 0.25)] = 1.0
    tiny = (okind >= 0.25) & (okind < 0.35)
    opacities[tiny] = _log_uniform(rng, 1e-8, 1e-2, tiny.sum())

    colors = sh = None
    sh_degree = 3
    if rng.random() < 0.5:
        colors = (rng.uniform(0, 1, (n, 3)) * _log_uniform(rng, 1e-3, 1e2)).astype(np.float32)
    else:
        degree = int(rng.integers(0, 4))
        sh = (rng.normal(size=(n, (degree + 1) ** 2, 3)) * _log_uniform(rng, 1e-2, 1e1)).astype(np.float32)
        sh_degree = int(rng.integers(0, 4))
    background = None if rng.random() < 0.4 else tuple(float(v) for v in rng.uniform(0, 1, 3))
    projection = "ut" if (cam.needs_ut or rng.random() < 0.3) else str(rng.choice(["ewa", "auto"]))
    geometry = rng.random() < 0.5
    variance = geometry and rng.random() < 0.5
    depth = geometry and (variance or rng.random() < 0.8)
    backend = "reference" if index % REFERENCE_EVERY == 0 else FAST
    if backend == "reference":  # keep the oracle's cost bounded
        n_ref = min(n, 60)
        kinds, means, scales, quats, opacities = kinds[:n_ref], means[:n_ref], scales[:n_ref], quats[:n_ref], opacities[:n_ref]
        colors = None if colors is None else colors[:n_ref]
        sh = None if sh is None else sh[:n_ref]
    return Case(
        index=index, seed=seed, camera=cam, scene_scale=scale, distance=distance,
        means=means.astype(np.float32), quats=quats.astype(np.float32), scales=scales.astype(np.float32),
        opacities=opacities.astype(np.float32), colors=colors, sh=sh, sh_degree=sh_degree, background=background,
        antialias=bool(rng.random() < 0.5), projection=projection, backend=backend, render_depth=depth,
        render_depth_variance=variance, render_normals=geometry and rng.random() < 0.5,
        planar_depth=depth and rng.random() < 0.5, kinds=kinds, weights_seed=int(rng.integers(2**31)),
    )


# ------------------------------------------------------------------ checks
MAPS = ("image", "alpha", "depth", "depth_variance", "normals")
PARAMS = ("means", "quats", "scales", "opacities", "colour")


def _weights(case: Case) -> dict:
    """A random linear function of every rendered map (depth terms made dimensionless by the camera distance)."""
    rng = np.random.default_rng(case.weights_seed)
    h, w = case.camera.height, case.camera.width
    shapes = {"image": (h, w, 3), "alpha": (h, w), "depth": (h, w), "depth_variance": (h, w), "normals": (h, w, 3)}
    scale = {"depth": 1.0 / case.distance, "depth_variance": 1.0 / case.distance**2 if case.camera.model == "orthographic" else case.distance**2}
    return {k: mx.array((rng.normal(size=s) * scale.get(k, 1.0)).astype(np.float32)) for k, s in shapes.items()}


def _max_colour(case: Case) -> float:
    if case.sh is None:
        return float(case.colors.max())
    dirs = case.means.astype(np.float64) - case.camera.center
    degree = min(case.sh_degree, int(round(np.sqrt(case.sh.shape[1]))) - 1)
    return float(np.maximum(eval_sh(degree, case.sh.astype(np.float64), dirs), 0.0).max())


def _footprint_peak(camera, means2d, conics, opacities) -> np.ndarray:
    """(N,) float64 largest 3DGS alpha (before the 0.99 clamp) each 2D Gaussian reaches at a pixel centre."""
    u = np.arange(camera.width) + 0.5
    v = np.arange(camera.height) + 0.5
    px = np.stack(np.meshgrid(u, v), -1).reshape(-1, 2)
    d = px[None, :, :] - means2d[:, None, :].astype(np.float64)
    a, b, c = (conics[:, k, None].astype(np.float64) for k in range(3))
    power = -0.5 * (a * d[..., 0] ** 2 + c * d[..., 1] ** 2) - b * d[..., 0] * d[..., 1]
    alpha = np.where(power <= 0, opacities[:, None].astype(np.float64) * np.exp(np.minimum(power, 0.0)), 0.0)
    return alpha.max(axis=1)


def _fail(case, msg):
    return f"{case.label}: {msg}"


def run_case(case: Case) -> dict:
    """All the checks of one case (see the module docstring); returns the outputs and gradients."""
    cam = case.camera
    weights = _weights(case)

    def loss(*args):
        out = case.render(*args)
        total = mx.array(0.0)
        for k in MAPS:
            if k in out:
                total = total + (out[k] * weights[k]).sum()
        return total, out

    (value, out), grads = mx.value_and_grad(loss, argnums=tuple(range(5)))(*case.inputs())
    mx.eval(value, out["image"], grads)
    grads = {k: np.array(g) for k, g in zip(PARAMS, grads)}
    get = {k: np.array(out[k]) for k in ("image", "alpha", "means2d", "conics", "radii", "depths", "visible") + MAPS[2:] if k in out}
    assert np.isfinite(float(value)), _fail(case, f"loss is {float(value)}")
    h, w = cam.height, cam.width

    # ---- outputs finite and in range
    for k, arr in get.items():
        if arr.dtype.kind == "f":
            bad = ~np.isfinite(arr)
            assert not bad.any(), _fail(case, f"{k} has {bad.sum()} non-finite entries, e.g. at {np.argwhere(bad)[:3].tolist()}")
    image, alpha, radii, visible = get["image"], get["alpha"], get["radii"], get["visible"]
    assert image.shape == (h, w, 3) and alpha.shape == (h, w), _fail(case, f"shapes {image.shape}, {alpha.shape}")
    assert alpha.min() >= 0.0 and alpha.max() <= 1.0, _fail(case, f"alpha in [{alpha.min()}, {alpha.max()}]")
    assert radii.min(initial=0) >= 0, _fail(case, f"negative radii {radii[radii < 0][:5].tolist()}")
    assert np.array_equal(visible, radii > 0), _fail(case, "visible is not radii > 0")
    cmax = _max_colour(case)
    bg = np.zeros(3) if case.background is None else np.array(case.background)
    bound = alpha[..., None] * cmax + (1.0 - alpha[..., None]) * bg
    tol = 1e-4 * max(cmax, 1.0)
    assert image.min() >= -tol, _fail(case, f"image minimum {image.min()}")
    over = image - bound
    assert over.max() <= tol, _fail(case, f"image exceeds alpha*max_colour + (1-alpha)*background by {over.max()} at {np.unravel_index(over.argmax(), over.shape)}")
    empty = alpha == 0
    np.testing.assert_array_equal(image[empty], np.broadcast_to(bg.astype(np.float32), image[empty].shape), err_msg=_fail(case, "image where alpha == 0 is not the background"))

    z = get["depths"]
    if "depth" in get:
        depth = get["depth"]
        assert not depth[empty].any(), _fail(case, "depth non-zero where alpha == 0")
        if not case.planar_depth and visible.any() and (~empty).any():
            lo, hi = z[visible].min(), z[visible].max()
            slack = 1e-3 * max(abs(lo), abs(hi)) + 1e-30
            hit = depth[~empty]
            assert hit.min() >= lo - slack and hit.max() <= hi + slack, _fail(case, f"depth in [{hit.min()}, {hit.max()}] outside the visible depths [{lo}, {hi}]")
    if "depth_variance" in get:
        var = get["depth_variance"]
        assert var.min() >= 0.0 and not var[empty].any(), _fail(case, f"depth variance minimum {var.min()}")
    if "normals" in get:
        length = np.linalg.norm(get["normals"], axis=-1)
        assert length.max() <= 1.0 + 1e-5 and not length[empty].any(), _fail(case, f"normal length up to {length.max()}")

    # ---- culling: centres outside [near, far] and placed outside a pinhole/orthographic image
    z64 = (case.means.astype(np.float64) @ cam.viewmat[:3, :3].T + cam.viewmat[:3, 3])[:, 2]
    # float32 rounding of z = R m + t in the renderer
    rounding = 1e-6 * (np.abs(case.means.astype(np.float64)) @ np.abs(cam.viewmat[2, :3]) + abs(cam.viewmat[2, 3]))
    must_cull = (z64 < cam.near - rounding - 1e-6 * abs(cam.near)) | (z64 > cam.far + rounding + 1e-6 * abs(cam.far))
    if not cam.needs_ut or cam.model == "orthographic":
        must_cull |= case.kinds == "outside_image"
    assert not visible[must_cull].any(), _fail(case, f"Gaussians {np.flatnonzero(must_cull & visible)[:5].tolist()} "
                                                     f"({case.kinds[must_cull & visible][:5].tolist()}) should be culled")

    # ---- gradients: finite; exactly zero for culled Gaussians and for those reaching no pixel
    project = project_gaussians_ut if out["plan"].projection == "ut" else project_gaussians
    comp = np.array(project(cam, *case.inputs()[:3], antialias=case.antialias)["compensation"])
    peak = _footprint_peak(cam, get["means2d"], get["conics"], case.opacities * comp)
    unseen = visible & (peak < ALPHA_MIN * (1 - 1e-3))
    for name, g in grads.items():
        bad = ~np.isfinite(g)
        assert not bad.any(), _fail(case, f"d/d{name} has {bad.sum()} non-finite entries at Gaussians {np.unique(np.argwhere(bad)[:, 0])[:5].tolist()} "
                                          f"({case.kinds[np.unique(np.argwhere(bad)[:, 0])[:5]].tolist()})")
        rows = g.reshape(len(g), -1)
        culled_grad = ~visible & rows.any(axis=1)
        assert not culled_grad.any(), _fail(case, f"culled Gaussians {np.flatnonzero(culled_grad)[:5].tolist()} "
                                                  f"({case.kinds[culled_grad][:5].tolist()}) got a non-zero d/d{name}")
        unseen_grad = unseen & rows.any(axis=1)
        assert not unseen_grad.any(), _fail(case, f"Gaussians {np.flatnonzero(unseen_grad)[:5].tolist()} reach no pixel "
                                                  f"(peak alpha {peak[unseen_grad][:5].tolist()}) but got a non-zero d/d{name}")
    if case.backend == "reference":  # the C++ kernel composites the same pixels
        cpu = case.render(*case.inputs(), backend=FAST)
        for k, atol in (("image", 1e-5 * max(cmax, 1.0)), ("alpha", 1e-5), ("normals", 1e-5), ("depth", 1e-4 * np.abs(get.get("depth", 0.0)).max())):
            if k in get:
                np.testing.assert_allclose(np.array(cpu[k]), get[k], rtol=0, atol=atol, err_msg=_fail(case, f"cpu and reference {k} differ"))
    return {"out": get, "grads": grads, "peak": peak}


@pytest.mark.parametrize("index", range(NUM_CASES))
def test_random_case_is_finite_and_culled_gaussians_get_zero_gradient(index):
    run_case(build_case(index))


def test_generator_covers_the_hard_inputs():
    """The cases span what the module docstring promises, and enough of them draw something."""
    cases = [build_case(i) for i in range(NUM_CASES)]
    assert {c.camera.model for c in cases} == set(MODELS)
    assert {(c.camera.width, c.camera.height) for c in cases} == set(SIZES)
    assert {"ut" if c.projection == "ut" or c.camera.needs_ut else "ewa" for c in cases} == {"ewa", "ut"}
    assert "pinhole" in {c.camera.model for c in cases if c.projection == "ut"}  # UT where EWA would do too
    assert {c.backend for c in cases} == {FAST, "reference"} and {c.antialias for c in cases} == {False, True}
    assert {None if c.sh is None else c.sh.shape[1] for c in cases} == {None, 1, 4, 9, 16}
    for flag in ("render_depth", "render_depth_variance", "render_normals", "planar_depth"):
        assert {getattr(c, flag) for c in cases} == {False, True}, flag
    assert {k for c in cases for k in c.kinds} == set(KINDS)
    scene = [c.scene_scale for c in cases]
    assert min(scene) < 1e-2 and max(scene) > 1e2
    focal = [c.camera.fx / c.camera.width for c in cases if c.camera.model != "orthographic"]
    assert min(focal) < 0.05 and max(focal) > 1e3
    relative = np.concatenate([c.scales.ravel() / c.scene_scale for c in cases])
    assert (relative == 0).any() and relative[relative > 0].min() < 1e-6 and relative.max() > 1e2
    norms = np.concatenate([np.linalg.norm(c.quats, axis=1) for c in cases])
    assert (norms == 0).any() and norms[norms > 0].min() < 1e-15 and norms.max() > 1e12
    opacities = np.concatenate([c.opacities for c in cases])
    assert {0.0, np.float32(1 - 1e-7), 1.0} <= set(opacities.tolist())
    drawn = [float(np.array(c.render(*c.inputs(), backend=FAST)["alpha"]).max()) > 0.01 for c in cases[::4]]
    assert np.mean(drawn) > 0.3, f"only {np.mean(drawn):.0%} of the cases draw anything"


# ------------------------------------------------------------------ reduced cases found by the generator
def _small_camera(model="pinhole", dist=(), focal=30.0):
    return Camera(width=32, height=24, fx=focal, fy=focal, cx=16.0, cy=12.0, viewmat=np.eye(4), model=model, dist=dist)


def _check_small(camera, means, quats, scales, **kw):
    """Render two Gaussians (the first one the hard case), check finite gradients and culling; returns (radii, grads)."""
    case = Case(
        index=-1, seed=-1, camera=camera, scene_scale=1.0, distance=4.0, means=np.float32(means), quats=np.float32(quats),
        scales=np.float32(scales), opacities=np.float32([0.8, 0.5]), colors=np.float32([[0.5, 0.2, 0.1], [0.1, 0.4, 0.9]]), sh=None,
        sh_degree=3, background=None, antialias=kw.get("antialias", False), projection=kw.get("projection", "auto"), backend=FAST,
        render_depth=kw.get("render_depth", False), render_depth_variance=False, render_normals=kw.get("render_normals", False),
        planar_depth=kw.get("planar_depth", False), kinds=np.array(["hard", "plain"]), weights_seed=3,
    )
    result = run_case(case)
    return result["out"]["radii"], result["grads"]


@pytest.mark.parametrize("projection", ["ewa", "ut"])
def test_antialias_flat_gaussian_has_finite_gradient(projection):
    """A line-shaped Gaussian has a singular 2D covariance (compensation 0): sqrt's infinite slope at 0 gave NaN."""
    radii, grads = _check_small(_small_camera(), [[0, 0, 3.0], [0.2, 0, 4.0]], [[1, 0.2, 0.3, 0], [1, 0, 0, 0]],
                                [[0.3, 0, 0], [0.2, 0.2, 0.2]], antialias=True, projection=projection)
    assert radii[0] > 0


def test_antialias_culled_ut_gaussian_gets_zero_gradient():
    """Behind the camera (UT): the compensation of the benign stand-in covariance, sqrt(0), leaked NaN."""
    radii, _ = _check_small(_small_camera(), [[0, 0, -3.0], [0.2, 0, 4.0]], [[1, 0, 0, 0]] * 2, [[0.3, 0.2, 0.1], [0.2, 0.2, 0.2]],
                            antialias=True, projection="ut")
    assert radii[0] == 0


def test_planar_depth_with_a_culled_gaussian_on_the_camera_plane():
    """z = 0 divided the ray of a culled Gaussian by zero in the depth plane."""
    radii, _ = _check_small(_small_camera(), [[1.0, 0, 0], [0.2, 0, 4.0]], [[1, 0, 0, 0]] * 2, [[0.3, 0.2, 0.1], [0.2, 0.2, 0.2]],
                            render_depth=True, planar_depth=True)
    assert radii[0] == 0


def test_normals_of_a_zero_quaternion():
    """A visible Gaussian with q = 0 (allowed: normalised inside) got NaN through the normal's norm."""
    radii, _ = _check_small(_small_camera(), [[0, 0, 3.0], [0.2, 0, 4.0]], [[0, 0, 0, 0], [1, 0, 0, 0]], [[0.3, 0.2, 0.1], [0.2, 0.2, 0.2]],
                            render_normals=True, render_depth=True, planar_depth=True)
    assert radii[0] > 0


@pytest.mark.parametrize("antialias", [False, True])
@pytest.mark.parametrize("x, focal, culled", [(20.0, 30.0, False), (300.0, 1e3, True)])
def test_ut_far_outside_a_distorted_lens(x, focal, culled, antialias):
    """Brown-Conrady far beyond its image: at x/z = 20 the radius exceeds int32 (it was cast to a
    negative radius), at x/z = 300 the covariance exceeds float32 (culled, but with NaN gradients)."""
    cam = _small_camera("opencv", (0.1, 0.01, 0.0, 0.0, 0.05), focal)
    radii, _ = _check_small(cam, [[x, 0, 1.0], [0.2, 0, 4.0]], [[1, 0, 0, 0]] * 2, [[0.1, 0.1, 0.1], [0.2, 0.2, 0.2]], antialias=antialias)
    assert (radii[0] == 0) == culled and radii.min() >= 0


def _wide_camera(ut):
    """Pinhole for EWA; orthographic with no near plane for UT, whose sigma points must all lie in front."""
    if ut:
        return Camera(width=32, height=24, fx=1e3, fy=1e3, cx=16.0, cy=12.0, model="orthographic", near=-1e12)
    return _small_camera(focal=1e3)


@pytest.mark.parametrize("projection", [project_gaussians, project_gaussians_ut])
def test_conic_gradient_of_a_very_wide_gaussian(projection):
    """Without blur the conic scales as 1/λ² with the Gaussian: d/ds (w·conic) at λs is λ⁻³ times that
    at s. At λ = 1e5 (Σ ~ 1e12 px²) the quotient rule lost it to float32 overflow (NaN or wrong values)."""
    cam = _wide_camera(projection is project_gaussians_ut)
    means, quats = mx.array([[0.01, -0.02, 1.0]]), mx.array([[1.0, 0.1, 0.2, 0.3]])
    w = mx.array([[1.0, 0.3, 2.0]])

    def grad_at(s):
        return np.array(mx.grad(lambda sc: (projection(cam, means, quats, sc, blur=0.0)["conics"] * w).sum())(mx.array(s, dtype=mx.float32)))

    s = np.array([[0.01, 0.005, 0.002]])
    small, wide = grad_at(s), grad_at(1e5 * s)
    assert np.isfinite(wide).all()
    np.testing.assert_allclose(wide * 1e15, small, rtol=2e-3, atol=2e-3 * np.abs(small).max())


def test_antialias_compensation_gradient_of_a_very_wide_gaussian():
    """UT with antialias on a Gaussian of Σ ~ 1e15 px²: the quotient det_orig / det squared det and overflowed."""
    cam = _wide_camera(ut=True)
    means, quats = mx.array([[0.01, -0.02, 1.0]]), mx.array([[1.0, 0.1, 0.2, 0.3]])

    def comp(sc):
        return project_gaussians_ut(cam, means, quats, sc, antialias=True)["compensation"].sum()

    scales = mx.array([[3e4, 1e4, 2e4]])
    assert float(comp(scales)) == pytest.approx(1.0)
    g = np.array(mx.grad(comp)(scales))
    assert np.isfinite(g).all() and np.abs(g).max() < 1e-6
