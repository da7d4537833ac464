"""The kernel library (mlx3d/csrc/kernels) built for each platform Blender ships on, run where it can run here.

- linux-x64 (the host compiler, as mlx3d._core), loaded in this process through ``mlx3d.kernel_library``:
  bit for bit ``mlx3d._core``'s results, and within float32 rounding of the pure MLX reference
  (``mlx3d.splatting.sh.eval_sh``), forward and backward, at several thread counts; the densification
  statistics bit for bit numpy's float64 expression.
- windows-x64 (a DLL, zig's x86_64-windows-gnu) under wine and linux-arm64 (zig's aarch64-linux-gnu,
  glibc 2.17) under qemu-user: the test driver (driver.c, built for the same platform) runs the same
  calls as the linux-x64 build's driver, and every output must equal that build's to the bit (the kernels
  are compiled without FMA contraction and use no libm function but the correctly rounded sqrt, so any
  difference is a bug, not rounding).
- macos-arm64 (a dylib, zig's aarch64-macos.11.0): built, and checked to be a 64-bit arm64 Mach-O
  library that exports the API's functions. It never runs here.

The inputs are a real trained splat file (tests/data/formats/opensplat_500.ply, 500 Gaussians of SH degree
3: its coefficients and centres) seen from a camera beside it, with fixed pseudo-random output gradients; for
the densification statistics pseudo-random visibility, pixel gradients and radii of its 500 Gaussians; for the
k-d tree its centres and points scattered around them (the numpy tree, mlx3d.kdtree, is the oracle).
The builds go to build/kernels-test/ (zig caches its own work, so a rebuild takes seconds). Skipped, with
the reason, where zig (``ziglang``), wine or qemu-user with the arm64 C library are missing: ``make
test-kernel-platforms`` installs them.
"""

from __future__ import annotations

import functools
import importlib.util
import os
import shutil
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.skipif(os.environ.get("MLX3D_KERNEL_PLATFORMS") != "1",
                                reason="builds for four platforms: runs in its own entry, make test-kernel-platforms")

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "mlx3d" / "csrc" / "kernels"))
import build as kernel_build  # noqa: E402  (mlx3d/csrc/kernels/build.py)

OUT = ROOT / "build" / "kernels-test"
SPLATS = ROOT / "tests" / "data" / "formats" / "opensplat_500.ply"
THREADS = (1, 2, 4)
ARM64_ROOT = Path("/usr/aarch64-linux-gnu")


def have_zig() -> bool:
    return importlib.util.find_spec("ziglang") is not None or shutil.which("zig") is not None


def wine_command() -> list[str] | None:
    for candidate in ("wine64", "/usr/lib/wine/wine64", "wine"):
        path = shutil.which(candidate) or (candidate if os.path.isfile(candidate) else None)
        if path:
            return [path]
    return None


def qemu_command() -> list[str] | None:
    qemu = shutil.which("qemu-aarch64-static") or shutil.which("qemu-aarch64")
    return [qemu, "-L", str(ARM64_ROOT)] if qemu and (ARM64_ROOT / "lib").is_dir() else None


@pytest.fixture(scope="session")
def builds():
    """{platform: folder with its library and driver}, built once per session (zig's cache makes it fast)."""
    made = {}

    def get(platform: str) -> Path:
        if platform not in made:
            if kernel_build.TARGETS[platform] is not None and not have_zig():
                pytest.skip("zig is not installed (pip install ziglang; `make test-kernel-platforms` does)")
            made[platform] = OUT / platform
            kernel_build.build(platform, made[platform], driver=platform != "macos-arm64")  # nothing runs a macOS driver
        return made[platform]

    return get


def use_library(monkeypatch, path: Path) -> None:
    """``mlx3d.kernel_library`` loads ``path`` on its next use (not the library it may have loaded already)."""
    from mlx3d import kernel_library

    monkeypatch.setenv(kernel_library.PATH_ENV, str(path))
    monkeypatch.setattr(kernel_library, "_lib", None)
    monkeypatch.setattr(kernel_library, "_failure", None)


# ------------------------------------------------------------------ the calls: a real splat file's SH
def sh_inputs():
    from mlx3d.io import read_splats

    arrays = read_splats(SPLATS)
    dc = np.ascontiguousarray(arrays.sh_dc, dtype=np.float32)
    rest = np.ascontiguousarray(arrays.sh_rest, dtype=np.float32)
    means = np.ascontiguousarray(arrays.means, dtype=np.float32)
    centre = (means.mean(axis=0) + np.array([0.0, -3.0, 1.0]) * np.ptp(means, axis=0).max()).astype(np.float32)
    cot = np.random.default_rng(7).normal(size=(len(means), 3)).astype(np.float32)
    return dc, rest, means, centre, cot


def sh_calls():
    """[(function, args)] for the driver: forward and backward at every degree, two blocks and one, several
    thread counts. args: ('f', array) inputs, ('i', int), ('o', count) outputs."""
    dc, rest, means, centre, cot = sh_inputs()
    n = len(means)
    both = np.concatenate([dc, rest], axis=1)
    calls = []
    for degree in range(4):
        for threads in THREADS:
            for b0, b1 in ((dc, rest), (both, None)):
                k0, k1 = b0.shape[1], 0 if b1 is None else b1.shape[1]
                block1 = ("f", np.zeros(0, np.float32) if b1 is None else b1)
                head = [("f", b0), ("i", k0), block1, ("i", k1), ("f", means), ("f", centre), ("i", n), ("i", degree)]
                calls.append(("mlx3d_sh_forward", head + [("i", threads), ("o", n * 3)]))
                calls.append(("mlx3d_sh_backward", head + [("f", cot), ("i", threads), ("o", n * k0 * 3), ("o", n * k1 * 3), ("o", n * 3)]))
    calls.append(("mlx3d_sh_forward", [("f", dc), ("i", 1), ("f", rest), ("i", 15), ("f", means), ("f", centre), ("i", n), ("i", 4),
                                       ("i", 1), ("o", n * 3)]))  # a bad degree: an error, the same message everywhere
    return calls


def statistics_calls():
    """Densification statistics of the same file's Gaussians: a view's visibility, pixel gradients (exact zeros
    among them) and radii added to running sums that hold a NaN radius, at several thread counts."""
    n = len(sh_inputs()[2])
    rng = np.random.default_rng(3)
    visible = rng.random(n) < 0.7
    grad2d = (rng.normal(size=(n, 2)) * 1e-4 * (rng.random((n, 1)) < 0.9)).astype(np.float32)
    radii = rng.integers(0, 40, n).astype(np.int32)
    start = [rng.random(n) * 1e-3, rng.integers(0, 5, n).astype(np.float64), rng.integers(0, 30, n).astype(np.float64)]
    start[2][::17] = np.nan
    return [("mlx3d_add_screen_statistics", [("u", visible), ("f", grad2d), ("n", radii), ("i", n), ("x", 0.5 * 648), ("x", 0.5 * 420),
                                             ("D", start[0]), ("D", start[1]), ("D", start[2]), ("i", threads)]) for threads in THREADS]


def knn_calls():
    """k nearest neighbours among the same file's Gaussian centres, for points spread around them: every output
    kind (neighbours, mean, k-th), several thread counts, a leaf size of 1 and of 16."""
    means = sh_inputs()[2]
    queries = (means[::3] + np.random.default_rng(5).normal(size=(len(means[::3]), 3)) * 0.05).astype(np.float32)
    n, m, k = len(means), len(queries), 8
    return [("mlx3d_knn", [("f", means), ("i", n), ("i", leaf), ("f", queries), ("i", m), ("i", k), ("i", output), ("i", threads),
                           ("o", m * k if output == 0 else m), ("l", m * k if output == 0 else 0)])
            for output in (0, 1, 2) for threads in THREADS for leaf in (1, 16)]


# ---- rasterizer calls ----
RASTER_SIZE = (72, 52, 16)  # width, height, tile: tiles cut by the image's edges


@functools.lru_cache(maxsize=1)
def splat_scene():
    """The real splat file's arrays and a small camera beside it (RASTER_SIZE), read once."""
    from mlx3d.cameras import Camera
    from mlx3d.io import read_splats

    arrays = read_splats(SPLATS)
    means = np.asarray(arrays.means, np.float32)
    width, height, _ = RASTER_SIZE
    centre, size = means.mean(axis=0), float(np.ptp(means, axis=0).max())
    camera = Camera.look_at(eye=tuple(centre + np.array([0.3, -1.2, 0.5]) * size), at=tuple(centre), up=(0, 0, 1), fov=60,
                            width=width, height=height)
    return arrays, camera


def raster_inputs(backend: str = "cpu"):
    """The real splat file projected and binned for the small camera (``backend``'s projection and binning):
    (means2d, conics, features (N, 3), opacities, tile_offsets, flatten_ids, depths) as numpy."""
    import mlx.core as mx

    from mlx3d.render.pipeline import _project_and_bin

    arrays, camera = splat_scene()
    means, quats, scales, _ = projection_inputs()
    opacities = mx.sigmoid(mx.array(np.asarray(arrays.opacities, np.float32).reshape(-1)))
    proj, opac, bins = _project_and_bin(camera, mx.array(means), mx.array(quats), mx.array(scales), opacities, "ewa", False, 0.3,
                                        RASTER_SIZE[2], backend)
    features = np.clip(0.5 + 0.28209479 * np.asarray(arrays.sh_dc, np.float32).reshape(-1, 3), 0, 1).astype(np.float32)
    return tuple(np.array(a) for a in (proj.means2d, proj.conics)) + (features, np.array(opac), np.array(bins.tile_offsets),
                                                                      np.array(bins.flatten_ids), np.array(proj.depths))


def raster_calls():
    """Forward (with and without a background) and backward passes of the real file's Gaussians at several thread
    counts, with pseudo-random output gradients; the backward pass's inputs from the in-process forward pass."""
    import mlx.core as mx

    from mlx3d import kernel_library

    width, height, tile = RASTER_SIZE
    means2d, conics, features, opac, offsets, ids, _ = raster_inputs()
    n, m = len(means2d), len(ids)
    background = np.array([0.2, 0.5, 0.9], np.float32)
    _, _, last, final_t = (np.array(a) for a in kernel_library.rasterize_forward(
        *(mx.array(a) for a in (means2d, conics, features, opac, offsets, ids)), width, height, tile))
    rng = np.random.default_rng(11)
    d_accum, d_alpha = (rng.normal(size=shape).astype(np.float32) for shape in ((height, width, 3), (height, width)))
    head = [("f", means2d), ("f", conics), ("f", features), ("f", opac), ("n", offsets), ("n", ids), ("i", n), ("i", 3), ("i", m),
            ("i", width), ("i", height), ("i", tile)]
    calls = []
    for threads in THREADS:
        for bg in (np.zeros(0, np.float32), background):
            calls.append(("mlx3d_rasterize_forward", head + [("f", bg), ("i", threads), ("o", height * width * 3),
                                                             ("o", height * width), ("o", height * width), ("o", height * width)]))
        calls.append(("mlx3d_rasterize_backward", head + [("n", last), ("f", final_t), ("f", d_accum), ("f", d_alpha),
                                                          ("f", np.zeros(0, np.float32)), ("i", threads), ("o", n * 2), ("o", n * 3),
                                                          ("o", n * 3), ("o", n)]))
    return calls


# ---- projection and tile binning calls ----
def projection_inputs():
    """The real splat file's means, quats and scales (float32) and the small camera: (means, quats, scales, camera)."""
    arrays, camera = splat_scene()
    return (np.ascontiguousarray(arrays.means, np.float32), np.ascontiguousarray(arrays.quats, np.float32),
            np.exp(np.asarray(arrays.scales, np.float32)), camera)


def camera_args(camera, blur: float = 0.3, antialias: bool = True) -> list:
    """mlx3d_project_ewa's camera arguments, as driver arguments."""
    return [("f", np.asarray(camera.viewmat, np.float32).reshape(-1)), ("x", camera.fx), ("x", camera.fy), ("x", camera.cx),
            ("x", camera.cy), ("i", camera.width), ("i", camera.height), ("x", camera.near), ("x", camera.far), ("x", blur),
            ("i", int(antialias))]


def binning_calls():
    """The real file's Gaussians binned (with the radii alone and tightened by conics and opacities) at several thread
    counts; the entry counts from the in-process library (the driver checks them)."""
    from mlx3d import kernel_library

    width, height, tile = RASTER_SIZE
    means2d, conics, _, opac, _, _, depths = raster_inputs()
    radii = np.ceil(3.0 * np.sqrt(np.maximum(conics[:, [2, 0]].max(axis=1) / np.maximum(
        conics[:, 0] * conics[:, 2] - conics[:, 1] ** 2, 1e-12), 0))).astype(np.float32)
    calls = []
    for extents in ((np.zeros(0, np.float32), np.zeros(0, np.float32)), (conics, opac)):
        tight = extents[0].size > 0
        m = len(kernel_library.bin_tiles(means2d, radii, depths, width, height, tile, 1, *(extents if tight else (None, None)))[1])
        for threads in THREADS:
            calls.append(("mlx3d_bin_tiles", [("f", means2d), ("f", radii), ("f", depths), ("i", len(means2d)), ("i", width),
                                              ("i", height), ("i", tile), ("f", extents[0]), ("f", extents[1]), ("i", threads),
                                              ("o", -(-width // tile) * -(-height // tile) + 1), ("o", m)]))
    return calls


def projection_calls():
    """The real file's Gaussians projected (with and without antialiasing) and the projection's backward pass with
    pseudo-random output gradients, at several thread counts."""
    means, quats, scales, camera = projection_inputs()
    n = len(means)
    rng = np.random.default_rng(13)
    cot = [rng.normal(size=shape).astype(np.float32) for shape in ((n, 2), (n, 3), (n,), (n,))]
    calls = []
    for threads in THREADS:
        for antialias in (False, True):
            head = [("f", means), ("f", quats), ("f", scales), ("i", n)] + camera_args(camera, antialias=antialias)
            calls.append(("mlx3d_project_ewa", head + [("i", threads), ("o", n * 2), ("o", n * 3), ("o", n), ("o", n), ("o", n)]))
            calls.append(("mlx3d_project_ewa_backward", head + [("f", c) for c in cot] + [("i", threads), ("o", n * 3), ("o", n * 4),
                                                                                          ("o", n * 3)]))
    return calls


# ---- photometric loss calls ----
_PHOTOMETRIC_CASES: list = []


def photometric_cases():
    """[(name, render, photo, weights)] float32 (H, W, C) and (H, W): the splat file rendered from a camera beside it
    (150 x 203: no multiple of the kernels' 8-row, 8-lane or 64-element blocks; values above 1 where splats add up)
    against its render from 3% of the scene's size away (the "photo"), and fixed pseudo-random images: C = 3, 4 and 1,
    one smaller than the SSIM window. Rendered once (pure MLX renderer) per session."""
    if not _PHOTOMETRIC_CASES:
        import mlx.core as mx

        from mlx3d.cameras import Camera
        from mlx3d.io import read_splats
        from mlx3d.render import render_gaussians

        arrays = read_splats(SPLATS)
        means = np.ascontiguousarray(arrays.means, dtype=np.float32)
        centre, span = means.mean(axis=0), float(np.ptp(means, axis=0).max())
        eye = centre + np.array([0.0, -0.7, 0.35]) * span

        def render(at):
            camera = Camera.look_at(eye=at, at=centre, up=(0, 0, 1), fov=60, width=203, height=150)
            out = render_gaussians(camera, mx.array(means), mx.array(arrays.quats), mx.exp(mx.array(arrays.scales)),
                                   mx.sigmoid(mx.array(arrays.opacities)), sh=(mx.array(arrays.sh_dc), mx.array(arrays.sh_rest)),
                                   background=np.array([0.55, 0.65, 0.8], np.float32), backend="reference")
            return np.ascontiguousarray(out["image"], dtype=np.float32)

        rng = np.random.default_rng(11)
        cases = [("render", render(eye), render(eye + np.array([0.03, 0.0, 0.015]) * span))]
        for h, w, c in ((37, 53, 3), (19, 45, 4), (64, 9, 1), (5, 7, 3)):
            x = rng.uniform(0, 1, (h, w, c)).astype(np.float32)
            cases.append((f"random {h}x{w}x{c}", x, np.clip(x + rng.normal(0, 0.15, x.shape), 0, 1).astype(np.float32)))
        _PHOTOMETRIC_CASES.extend((name, x, y, rng.uniform(0, 1, x.shape[:2]).astype(np.float32)) for name, x, y in cases)
    return _PHOTOMETRIC_CASES


def photometric_taps(window: int = 11, sigma: float = 1.5) -> np.ndarray:
    from mlx3d.training.metrics import _taps

    return np.array(_taps(window, sigma), np.float32)


def photometric_calls():
    """The loss and its gradient (and the photo's: the images swapped) of each case, without and with weights, at
    several thread counts (the render also with lambda 1, a 7-tap window and scratch memory given, returned as an
    output); the MSE, clipped and not, of each; and a bad lambda and an even window (errors, the same message
    everywhere)."""
    calls, taps = [], photometric_taps()

    def loss(x, y, w, threads, lam=0.2, t=taps, scratch=False):
        h, wd, c = x.shape
        return ("mlx3d_photometric_loss", [("f", x), ("f", y), ("f", w), ("i", h), ("i", wd), ("i", c), ("x", lam), ("f", t),
                                           ("i", t.size), ("i", threads), ("o", 8 * x.size if scratch else 0), ("o", 1), ("o", x.size)])

    none = np.zeros(0, np.float32)
    for name, x, y, w in photometric_cases():
        for threads in THREADS:
            for weights in (none, w):
                calls += [loss(x, y, weights, threads), loss(y, x, weights, threads)]
                for clip in (0, 1):
                    shown = x * np.float32(1.4) - np.float32(0.2)  # values outside [0, 1] for the clip
                    calls.append(("mlx3d_mse", [("f", shown), ("f", y), ("f", weights), *(("i", s) for s in x.shape), ("i", clip),
                                                ("i", threads), ("o", 1)]))
    x, y, w = photometric_cases()[0][1:]
    calls += [loss(x, y, w, 2, lam=1.0), loss(x, y, w, 4, t=photometric_taps(7, 1.0)), loss(x, y, none, 2, scratch=True)]
    calls += [loss(x, y, w, 1, lam=1.5), loss(x, y, w, 1, t=taps[:10])]  # errors
    return calls


# ---- optimizer and activations calls ----
ADAM_BETAS, ADAM_EPS = (0.9, 0.999), 1e-15


def numpy_moment(g, x, beta: float, squared: int) -> np.ndarray:
    """Adam's moment update by numpy's float32 expression (mlx3d.training.adam; the scalars rounded to float32)."""
    return np.float32(beta) * x + np.float32(1.0 - beta) * (g * g if squared else g)


def numpy_param(p, m, v, lr: float, eps: float, c1: float, c2: float) -> np.ndarray:
    f = np.float32
    return p - (f(lr) * (m / f(c1))) / (np.sqrt(v / f(c2)) + f(eps))


def numpy_adam(p, g, m, v, lr, c1, c2):
    """One Adam step by numpy's float32 expression: p', m', v'."""
    m2, v2 = numpy_moment(g, m, ADAM_BETAS[0], 0), numpy_moment(g, v, ADAM_BETAS[1], 1)
    return numpy_param(p, m2, v2, lr, ADAM_EPS, c1, c2), m2, v2


def adam_gradient(rng, shape, scale: float) -> np.ndarray:
    """A step's gradient: normal * scale, a fifth exact zeros (unseen Gaussians), a twentieth 1e6 times larger and one
    1e-25 times smaller (squares that underflow to 0), and denormals, -0 and 3e4 first."""
    g = rng.normal(size=shape) * scale
    u = rng.random(shape)
    g[u < 0.2] = 0.0
    g[(u >= 0.2) & (u < 0.25)] *= 1e6
    g[(u >= 0.25) & (u < 0.3)] *= 1e-25
    g.flat[:4] = [1e-40, -1e-45, -0.0, 3e4]
    return g.astype(np.float32)


def adam_steps(sh_rows: int, steps: int = 3) -> list:
    """Three Adam steps from zero moments of the splat file's centres, its SH rest coefficients (tiled to sh_rows rows),
    log-scales and opacity logits, with the trainer's learning rates: [(p, g, m, v, lr, c1, c2, numpy's (p', m', v'))]."""
    _, rest, means, _, _ = sh_inputs()
    rng = np.random.default_rng(17)
    rest = np.tile(rest.reshape(len(rest), -1), (-(-sh_rows // len(rest)), 1))[:sh_rows]
    params = [(means, 1.6e-4 * 3.0, 1e-5), (rest, 2.5e-3 / 20, 1e-6),
              (rng.normal(-4.5, 1.0, (len(means), 3)).astype(np.float32), 5e-3, 1e-4),
              (rng.normal(0.0, 2.0, (len(means), 1)).astype(np.float32), 5e-2, 1e-3)]
    out = []
    for p, lr, scale in params:
        m = v = np.zeros_like(p)
        for t in range(1, steps + 1):
            g = adam_gradient(rng, p.shape, scale)
            c1, c2 = 1.0 - ADAM_BETAS[0] ** t, 1.0 - ADAM_BETAS[1] ** t
            new = numpy_adam(p, g, m, v, lr, c1, c2)
            out.append((p, g, m, v, lr, c1, c2, new))
            p, m, v = new
    return out


def finite_inputs(n: int = 200_000, seed: int = 23) -> np.ndarray:
    """n finite float32 of every magnitude (random bit patterns, exponent 255 cleared to 254): denormals to 3.4e38."""
    bits = np.random.default_rng(seed).integers(0, 2**32, n, dtype=np.uint64).astype(np.uint32)
    bits[(bits & 0x7F800000) == 0x7F800000] &= ~np.uint32(0x00800000)
    return bits.view(np.float32)


def activation_inputs(stride: int = 16384) -> np.ndarray:
    """float32 over the whole range: every stride-th bit pattern (both signs, denormals, inf, NaNs with payloads), the
    edges (0, denormals, the +-88 cut-offs, exp's overflow and sigmoid's underflow, the largest floats, inf, NaNs), every
    float within 200 ulps of the finite edges, and typical log-scales and logits."""
    special = np.array([0.0, -0.0, 1e-45, -1e-45, 1e-40, -1e-40, 1.1754944e-38, -1.1754944e-38, 1e-30, -1e-30, 0.5, -0.5, 1.0, -1.0,
                        87.3, -87.3, 88.0, -88.0, 88.72283, 88.72284, -88.72283, 89.0, -89.0, 103.97, -103.97, -104.0, 1e10, -1e10,
                        3.4028235e38, -3.4028235e38, np.inf, -np.inf, np.nan], np.float32)
    nans = np.array([0x7FC00000, 0xFFC00000, 0x7FC00001, 0xFFFFFFFF, 0x7F800001, 0xFF800001], np.uint32).view(np.float32)
    sweep = (np.arange(0, 2**32, stride, dtype=np.uint64) + 1).astype(np.uint32).view(np.float32)
    edges = special[:30].view(np.uint32).astype(np.int64)
    near = ((edges[:, None] + np.arange(-200, 201)) % 2**32).astype(np.uint32).ravel().view(np.float32)
    rng = np.random.default_rng(29)
    typical = np.concatenate([rng.normal(-4.0, 2.0, 20000), rng.normal(0.0, 3.0, 20000), rng.uniform(-120, 120, 20000)]).astype(np.float32)
    return np.concatenate([special, nans, sweep, near, typical])


def affine_problem(n: int = 10000) -> list:
    """[(name, linear (3, 3) float64, quats (n, 4), log_scales (n, 3))] for the hard linear maps of test_transforms (non-uniform
    scale, shear, mirrored), with flat disks, isotropic Gaussians, huge and tiny scales at once, and near-zero quaternions."""
    from mlx3d.transforms import compose_affine

    rng = np.random.default_rng(31)
    quats = rng.normal(size=(n, 4))
    log_scales = rng.normal(-2, 1, size=(n, 3))
    log_scales[: n // 6, 2] = np.log(1e-8)
    log_scales[n // 6: n // 3] = -3.0
    log_scales[n // 3: n // 2] = [4.0, 4.0, -12.0]
    quats[n // 2: n // 2 + n // 30] = 0.0
    quats[n // 2: n // 2 + n // 30, 0] = 1e-30
    maps = {"nonuniform": compose_affine((1.0, 3.0, 0.2), (10, 20, 30), (1, 0, 0)),
            "shear": np.array([[1.0, 0.7, 0.0, 0.1], [0.0, 1.0, 0.3, 0.2], [0.2, 0.0, 1.5, 0.3], [0, 0, 0, 1]]),
            "mirror_scaled": compose_affine(2.5, (15, 0, 40), (0, 0, 0)) @ np.diag([1.0, -1.0, 1.0, 1.0])}
    return [(name, np.ascontiguousarray(a[:3, :3], np.float64), quats.astype(np.float32), log_scales.astype(np.float32))
            for name, a in maps.items()]


def optim_calls():
    """Adam's moments and parameter updates of three steps of four parameters (each from numpy's previous step), into
    fresh outputs and in place, at several thread counts; the finiteness check of arrays of every magnitude, with NaN,
    inf or -inf first, in the middle or last; exp and sigmoid over the float range; the affine re-decomposition; and
    bad arguments (errors, the same message everywhere)."""
    calls = []
    for k, (p, g, m, v, lr, c1, c2, (_, m2, v2)) in enumerate(adam_steps(sh_rows=1500)):
        threads, n = THREADS[k % len(THREADS)], p.size
        scalars = [("i", n), ("x", lr), ("x", ADAM_EPS), ("x", c1), ("x", c2), ("i", threads)]
        for x, beta, squared in ((m, ADAM_BETAS[0], 0), (v, ADAM_BETAS[1], 1)):
            calls.append(("mlx3d_adam_moment", [("f", g), ("f", x), ("i", n), ("x", beta), ("i", squared), ("i", threads), ("o", n)]))
            calls.append(("mlx3d_adam_moment", [("f", g), ("F", x), ("i", n), ("x", beta), ("i", squared), ("i", threads)]))
        calls.append(("mlx3d_adam_param", [("f", p), ("f", m2), ("f", v2)] + scalars + [("o", n)]))
        calls.append(("mlx3d_adam_param", [("F", p), ("f", m2), ("f", v2)] + scalars))
    x = finite_inputs()
    n = x.size
    for threads in THREADS:
        calls.append(("mlx3d_all_finite", [("f", x), ("i", n), ("i", threads), ("b", 1)]))
    for k, (at, bad) in enumerate((at, bad) for at in (0, n // 2, n - 1) for bad in (np.nan, np.inf, -np.inf)):
        y = x.copy()
        y[at] = bad
        calls.append(("mlx3d_all_finite", [("f", y), ("i", n), ("i", THREADS[k % len(THREADS)]), ("b", 1)]))
    x = activation_inputs()
    for name in ("mlx3d_exp", "mlx3d_sigmoid"):
        calls += [(name, [("f", x), ("i", x.size), ("i", threads), ("o", x.size)]) for threads in THREADS]
    for _, linear, quats, log_scales in affine_problem():
        n = len(quats)
        calls += [("mlx3d_affine_covariances", [("d", linear), ("f", quats), ("f", log_scales), ("i", n), ("i", threads), ("o", 4 * n),
                                                ("o", 3 * n)]) for threads in (1, 4)]
    g = adam_steps(sh_rows=1)[0][1]
    calls.append(("mlx3d_adam_moment", [("f", g), ("f", g), ("i", g.size), ("x", 0.9), ("i", 2), ("i", 1), ("o", g.size)]))  # errors
    calls.append(("mlx3d_adam_param", [("f", g), ("f", g), ("f", g), ("i", g.size), ("x", 1e-3), ("x", 1e-15), ("x", 0.0), ("x", 1e-3),
                                       ("i", 1), ("o", g.size)]))
    return calls


ARRAY_TYPES = {"f": "<f4", "u": "u1", "n": "<i4", "D": "<f8", "d": "<f8", "F": "<f4"}  # inputs (D, F: updated in place)


def write_calls(path: Path, calls) -> None:
    with open(path, "wb") as f:
        f.write(b"MLX3DK1\n")
        for name, args in calls:
            f.write(struct.pack("<I", len(name)) + name.encode() + struct.pack("<I", len(args)))
            for kind, value in args:
                if kind in ARRAY_TYPES:
                    data = np.ascontiguousarray(value, dtype=ARRAY_TYPES[kind]).ravel()
                    f.write(kind.encode() + struct.pack("<Q", data.size) + data.tobytes())
                elif kind == "x":
                    f.write(b"x" + struct.pack("<d", float(value)))
                else:
                    f.write(kind.encode() + struct.pack("<Q", int(value) & 0xFFFFFFFFFFFFFFFF))


def read_results(path: Path, calls) -> list:
    """[(return value, error message, [output arrays])] of the driver's OUT file."""
    data, at, results = path.read_bytes(), 0, []
    for _, args in calls:
        rc, length = struct.unpack_from("<iI", data, at)
        at += 8
        error = data[at:at + length].decode()
        at += length
        outs = []
        for kind, _ in args:
            if kind in ("o", "l", "D", "F", "b"):
                (count,) = struct.unpack_from("<Q", data, at)
                dtype = np.dtype({"o": "<f4", "l": "<i8", "D": "<f8", "F": "<f4", "b": "u1"}[kind])
                outs.append(np.frombuffer(data, dtype, count, at + 8).copy())
                at += 8 + dtype.itemsize * count
        results.append((rc, error, outs))
    assert at == len(data), "the driver wrote more than the calls asked for"
    return results


def run_driver(folder: Path, platform: str, runner: list[str], calls, tmp_path: Path, baseline: bool = True) -> list:
    """The driver's results of ``calls`` with ``platform``'s build; ``baseline``: the rasterizer at the lane width every
    build has (4), else at the widest its CPU check picks."""
    calls_file, out_file = tmp_path / f"calls_{platform}.bin", tmp_path / f"out_{platform}.bin"
    write_calls(calls_file, calls)
    env = dict(os.environ)
    env.pop("MLX3D_RASTER_ISA", None)
    if baseline:
        env["MLX3D_RASTER_ISA"] = "baseline"
    if platform == "windows-x64":
        env.update(WINEPREFIX=str(OUT / "wineprefix"), WINEDEBUG="-all", WINEDLLOVERRIDES="mscoree,mshtml=")
    # run from the library's folder with bare names: every platform's loader finds them there
    shutil.copy(calls_file, folder / calls_file.name)
    try:
        proc = subprocess.run([*runner, "./" + kernel_build.driver_name(platform) if not runner else kernel_build.driver_name(platform),
                               "./" + kernel_build.library_name(platform), calls_file.name, out_file.name],
                              cwd=folder, env=env, capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, proc.stderr[-2000:]
        return read_results(folder / out_file.name, calls)
    finally:
        for name in (calls_file.name, out_file.name):
            (folder / name).unlink(missing_ok=True)


def check_same(results, reference, calls):
    for (name, args), (rc, error, outs), (rc0, error0, outs0) in zip(calls, results, reference):
        where = f"{name} with {[a[1] for a in args if a[0] in 'ix']}"
        assert (rc, error) == (rc0, error0), where
        for out, out0 in zip(outs, outs0):
            assert out.tobytes() == out0.tobytes(), f"{where}: {np.abs(out - out0).max()} from the linux-x64 build"


# ------------------------------------------------------------------ the tests
def test_linux_build_is_core_and_the_reference(builds, monkeypatch):
    """In this process (ctypes): bit for bit mlx3d._core's colours and gradients, close to eval_sh's."""
    import mlx.core as mx

    from mlx3d import kernel_library, native
    from mlx3d.splatting.sh import eval_sh

    folder = builds("linux-x64")
    use_library(monkeypatch, folder / kernel_build.library_name("linux-x64"))
    assert kernel_library.available(), kernel_library.failure()
    dc, rest, means, centre, cot = (mx.array(a) for a in sh_inputs())
    for degree in range(4):
        def loss(fn, threads):
            return lambda a, b, m: (fn([a, b], m, centre, degree, threads) * cot).sum()

        def reference(a, b, m):
            return (mx.maximum(eval_sh(degree, mx.concatenate([a, b], axis=1), m - centre), 0.0) * cot).sum()

        ref = mx.grad(reference, argnums=(0, 1, 2))(dc, rest, means)
        for threads in THREADS:
            got = mx.grad(loss(kernel_library.sh_colors, threads), argnums=(0, 1, 2))(dc, rest, means)
            rgb = kernel_library.sh_colors([dc, rest], means, centre, degree, threads)
            np.testing.assert_allclose(np.array(rgb), np.maximum(np.array(eval_sh(degree, mx.concatenate([dc, rest], 1), means - centre)), 0),
                                       rtol=1e-5, atol=1e-6)
            for g, r in zip(got, ref):
                np.testing.assert_allclose(np.array(g), np.array(r), rtol=1e-4, atol=1e-5)
            if native.available():
                core = mx.grad(loss(native.core().sh_colors, threads), argnums=(0, 1, 2))(dc, rest, means)
                assert all(np.array_equal(np.array(g), np.array(c)) for g, c in zip(got, core))
                assert np.array_equal(np.array(rgb), np.array(native.core().sh_colors([dc, rest], means, centre, degree, threads)))


def test_bad_calls_are_errors_that_name_the_problem(builds, monkeypatch):
    import mlx.core as mx

    from mlx3d import kernel_library

    folder = builds("linux-x64")
    use_library(monkeypatch, folder / kernel_build.library_name("linux-x64"))
    dc, rest, means, centre, _ = (mx.array(a) for a in sh_inputs())
    strided = mx.concatenate([means, means], axis=1)[:, :3]  # rows 6 floats apart: read through one copy
    assert np.array_equal(np.array(kernel_library.sh_colors([dc, rest], strided, centre, 3)),
                          np.array(kernel_library.sh_colors([dc, rest], means, centre, 3)))
    with pytest.raises(ValueError, match="sh_colors: degree 3 needs K >= 16 coefficients, got 1"):
        kernel_library.sh_colors([dc], means, centre, 3)
    with pytest.raises(TypeError, match="means must be float32, got mlx.core.float16"):
        kernel_library.sh_colors([dc, rest], means.astype(mx.float16), centre, 3)
    with pytest.raises(ValueError, match=r"means must have shape \(N, 3\) = \(500, 3\), got \(499, 3\)"):
        kernel_library.sh_colors([dc, rest], means[1:], centre, 3)
    use_library(monkeypatch, folder / "nowhere.so")
    assert not kernel_library.available() and "nowhere.so does not exist" in kernel_library.failure()


def numpy_statistics(visible, grad2d, radii, sx, sy, accum, count, max_radii):
    """mlx3d.training.statistics' float64 expression, in numpy: the statistics after adding the view."""
    g = grad2d.astype(np.float64) * np.array([sx, sy])
    return (accum + np.where(visible, np.sqrt(g[:, 0] ** 2 + g[:, 1] ** 2), 0.0), count + visible,
            np.maximum(max_radii, radii.astype(np.float64)))


def test_statistics_in_process_are_numpys_and_cores(builds, monkeypatch):
    from mlx3d import kernel_library, native

    folder = builds("linux-x64")
    use_library(monkeypatch, folder / kernel_build.library_name("linux-x64"))
    for _, args in statistics_calls():
        visible, grad2d, radii = (a[1] for a in args[:3])
        sx, sy, threads = args[4][1], args[5][1], args[9][1]
        stats = [a[1].copy() for a in args[6:9]]
        kernel_library.add_screen_statistics(visible, grad2d, radii, sx, sy, *stats, threads)
        for got, expected in zip(stats, numpy_statistics(visible, grad2d, radii, sx, sy, *(a[1] for a in args[6:9]))):
            assert got.tobytes() == expected.tobytes()
        if native.available():
            core = [a[1].copy() for a in args[6:9]]
            native.core().add_screen_statistics(visible, grad2d, radii, sx, sy, *core, threads)
            assert all(c.tobytes() == g.tobytes() for c, g in zip(core, stats))
    with pytest.raises(ValueError, match="grad_count must be a writable C-contiguous float64"):
        kernel_library.add_screen_statistics(visible, grad2d, radii, sx, sy, stats[0], stats[1].astype(np.float32), stats[2])
    with pytest.raises(ValueError, match=r"must agree on N = 500, got 500, \(500, 2\) and 499"):
        kernel_library.add_screen_statistics(visible, grad2d, radii[1:], sx, sy, *stats)


def test_knn_in_process_is_cores_and_the_numpy_trees(builds, monkeypatch):
    from mlx3d import kdtree, kernel_library, native

    folder = builds("linux-x64")
    use_library(monkeypatch, folder / kernel_build.library_name("linux-x64"))
    means = sh_inputs()[2]
    queries = means[::2] + np.float32(0.01)
    own = np.arange(len(means), dtype=np.int64)
    trees = [kernel_library.KDTree(means, 4), kdtree.KDTree(means, 4)] + ([native.core().KDTree(means, 4)] if native.available() else [])
    assert len({(t.size, t.leaf_size, t.depth, t.node_count) for t in trees}) == 1
    assert sorted(trees[0].order()) == list(range(len(means)))
    assert all(np.array_equal(trees[0].order(), t.order()) for t in trees[2:])  # _core's tree is the same tree
    for threads in THREADS:
        got = [trees[0].query(queries, 6, num_threads=threads), trees[0].query(means, 3, self_index=own, num_threads=threads),
               trees[0].query_mean(queries, 5, num_threads=threads), trees[0].query_kth(queries, 5, num_threads=threads)]
        for other in trees[1:]:
            want = [other.query(queries, 6), other.query(means, 3, self_index=own), other.query_mean(queries, 5), other.query_kth(queries, 5)]
            for g, w in zip(got, want):
                for a, b in zip(g if isinstance(g, tuple) else (g,), w if isinstance(w, tuple) else (w,)):
                    assert np.asarray(a).tobytes() == np.asarray(b).astype(np.asarray(a).dtype).tobytes()
    with pytest.raises(ValueError, match="mlx3d_knn_query: k must be >= 1, got 0"):
        trees[0].query(queries, 0)
    with pytest.raises(ValueError, match="mlx3d_knn_build: leaf_size must be >= 1, got 0"):
        kernel_library.KDTree(means, 0)


def test_linux_build_exports_the_api_alone(builds):
    """The library carries its C++ runtime inside (static libstdc++) and exports nothing of it."""
    nm = shutil.which("nm")
    if nm is None:
        pytest.skip("nm (binutils) is not installed")
    lib = builds("linux-x64") / kernel_build.library_name("linux-x64")
    out = subprocess.run([nm, "-D", "--defined-only", str(lib)], capture_output=True, text=True, check=True).stdout
    exported = {line.split()[-1] for line in out.splitlines() if line.split()[1] in "TWDBVR"}
    header = (ROOT / "mlx3d" / "csrc" / "kernels" / "mlx3d_kernels.h").read_text()
    import re

    assert exported == set(re.findall(r"MLX3D_API \w[\w\s\*]*?\b(mlx3d_\w+)\(", header))
    needed = subprocess.run(["ldd", str(lib)], capture_output=True, text=True).stdout if shutil.which("ldd") else ""
    assert "libstdc++" not in needed


@pytest.mark.parametrize("platform", ["windows-x64", "linux-arm64"])
def test_other_platforms_builds_give_the_linux_builds_results(builds, platform, tmp_path, monkeypatch):
    runner = wine_command() if platform == "windows-x64" else qemu_command()
    if runner is None:
        pytest.skip(f"{'wine' if platform == 'windows-x64' else 'qemu-user and the arm64 C library'} not installed "
                    "(`make test-kernel-platforms` installs them)")
    base = sh_calls() + statistics_calls() + knn_calls()  # with oracles of their own below
    use_library(monkeypatch, builds("linux-x64") / kernel_build.library_name("linux-x64"))  # for the calls' inputs
    calls = base + [] + raster_calls() + projection_calls() + binning_calls() + photometric_calls() + optim_calls()  # the other areas' calls (add yours here): compared with the linux-x64 build's bits
    reference = run_driver(builds("linux-x64"), "linux-x64", [], calls, tmp_path)
    bad = len(sh_calls()) - 1
    assert reference[bad][0] == 2 and "degree must be 0..3, got 4" in reference[bad][1]  # 2: an invalid argument
    assert all(rc == 0 and np.isfinite(np.concatenate(outs)).all() for rc, _, outs in reference[:bad])
    for (name, args), (rc, _, outs) in zip(base[bad + 1:], reference[bad + 1:len(base)]):
        assert rc == 0
        if name == "mlx3d_add_screen_statistics":  # numpy's float64 expression
            expected = numpy_statistics(*(a[1] for a in args[:3]), args[4][1], args[5][1], *(a[1] for a in args[6:9]))
            assert all(o.tobytes() == e.tobytes() for o, e in zip(outs, expected))
        else:  # the numpy k-d tree's neighbours and distances (mlx3d.kdtree, the same float32 arithmetic)
            from mlx3d.kdtree import KDTree

            tree, queries, k, output = KDTree(args[0][1], args[2][1]), args[3][1], args[5][1], args[6][1]
            if output == 0:
                index, dist = tree.query(queries, k)
                assert np.array_equal(outs[1].reshape(-1, k), index) and outs[0].tobytes() == dist.astype(np.float32).tobytes()
            else:
                expected = (tree.query_mean if output == 1 else tree.query_kth)(queries, k)
                assert outs[0].tobytes() == expected.astype(np.float32).tobytes()
    check_same(run_driver(builds(platform), platform, runner, calls, tmp_path), reference, calls)


# ---- rasterizer tests ----
def test_rasterizer_in_process_is_cores(builds, monkeypatch):
    """The library's forward pass (plain, with a background, over a surface layer) and gradients (means2d, conics,
    features, opacities, background) are _core's bit for bit, at several thread counts and both lane widths."""
    import mlx.core as mx

    from mlx3d import kernel_library, native

    if not native.available():
        pytest.skip("compares with mlx3d._core")
    use_library(monkeypatch, builds("linux-x64") / kernel_build.library_name("linux-x64"))
    width, height, tile = RASTER_SIZE
    means2d, conics, features, opac, offsets, ids, depths = (mx.array(a) for a in raster_inputs())
    background = mx.array([0.2, 0.5, 0.9])
    rng = np.random.default_rng(2)
    cot = [mx.array(rng.normal(size=s).astype(np.float32)) for s in ((height, width, 3), (height, width))]
    surface = (depths, mx.array(rng.random((height, width, 3)).astype(np.float32) * 0.5),
               mx.array(rng.random((height, width)).astype(np.float32) * 0.5),
               mx.array(np.where(rng.random((height, width)) < 0.3, np.inf, np.median(np.array(depths)))
                        .astype(np.float32)))
    assert kernel_library.rasterizer_simd_lanes() == native.core().rasterizer_simd_lanes()

    def loss(fn, threads):
        def f(m, c, ft, o, bg):
            accum, alpha, _, _ = fn(m, c, ft, o, offsets, ids, width, height, tile, threads, bg)
            return (accum * cot[0]).sum() + (alpha * cot[1]).sum()
        return f

    for isa in ("", "baseline"):
        monkeypatch.setenv("MLX3D_RASTER_ISA", isa)
        for threads in THREADS:
            for bg in (None, background):
                got = kernel_library.rasterize_forward(means2d, conics, features, opac, offsets, ids, width, height, tile, threads, bg)
                want = native.core().rasterize_forward(means2d, conics, features, opac, offsets, ids, width, height, tile, threads, bg)
                assert all(np.array(g).tobytes() == np.array(w).tobytes() for g, w in zip(got, want))
            grads = [mx.grad(loss(fn, threads), argnums=(0, 1, 2, 3, 4))(means2d, conics, features, opac, background)
                     for fn in (kernel_library.rasterize_forward, native.core().rasterize_forward)]
            assert all(np.array(g).tobytes() == np.array(w).tobytes() for g, w in zip(*grads))
            assert float(mx.abs(grads[0][0]).max()) > 0 and float(mx.abs(grads[0][4]).max()) > 0
            got = kernel_library.rasterize_forward_surface(means2d, conics, features, opac, offsets, ids, *surface, width, height, tile,
                                                           threads)
            want = native.core().rasterize_forward_surface(means2d, conics, features, opac, offsets, ids, *surface, width, height, tile,
                                                           threads)
            assert all(np.array(g).tobytes() == np.array(w).tobytes() for g, w in zip(got, want))
    with pytest.raises(ValueError, match=r"rasterize: conics must have shape \(\d+, 3\), got"):
        kernel_library.rasterize_forward(means2d, conics[:, :2], features, opac, offsets, ids, width, height, tile)
    with pytest.raises(ValueError, match=r"rasterize: tile_offsets must have shape \(21,\), got \(20,\)"):
        kernel_library.rasterize_forward(means2d, conics, features, opac, offsets[1:], ids, width, height, tile)
    with pytest.raises(TypeError, match="flatten_ids must be int32, got mlx.core.float32"):
        kernel_library.rasterize_forward(means2d, conics, features, opac, offsets, ids.astype(mx.float32), width, height, tile)


# ---- projection and tile binning tests ----
def test_binning_in_process_is_cores(builds, monkeypatch):
    """The library's tile binning and extents are _core's, entry for entry, at several thread counts; bad inputs
    are errors that name them."""
    import mlx.core as mx

    from mlx3d import kernel_library, native

    if not native.available():
        pytest.skip("compares with mlx3d._core")
    use_library(monkeypatch, builds("linux-x64") / kernel_build.library_name("linux-x64"))
    width, height, tile = RASTER_SIZE
    means2d, conics, _, opac, _, _, depths = raster_inputs()
    radii = np.full(len(means2d), 9.0, np.float32)
    radii[::7] = 0.0
    for extents in ((None, None), (conics, opac)):
        want_ext = native.core().tile_extents(radii, *extents)
        assert kernel_library.tile_extents(radii, *extents).tobytes() == want_ext.tobytes()
        for threads in THREADS:
            got = kernel_library.bin_tiles(means2d, radii, depths, width, height, tile, threads, *extents)
            want = native.core().bin_tiles(means2d, radii, depths, width, height, tile, threads, *extents)
            assert all(g.dtype == mx.int32 and np.array_equal(np.array(g), np.array(w)) for g, w in zip(got, want))
            assert len(got[1]) > len(means2d)
    empty = kernel_library.bin_tiles(means2d, np.zeros_like(radii), depths, width, height, tile)
    assert len(empty[1]) == 0 and not np.array(empty[0]).any()
    with pytest.raises(ValueError, match="give conics and opacities together"):
        kernel_library.bin_tiles(means2d, radii, depths, width, height, tile, 0, conics)
    with pytest.raises(ValueError, match=r"depths \(one per Gaussian\) must hold 500 elements, got 499"):
        kernel_library.bin_tiles(means2d, radii, depths[1:], width, height, tile)


def test_projection_in_process_is_cores(builds, monkeypatch):
    """The library's projection and its gradients (means, quats, scales) are _core's bit for bit at several thread
    counts, with and without antialiasing; bad inputs are named."""
    import mlx.core as mx

    from mlx3d import kernel_library, native

    if not native.available():
        pytest.skip("compares with mlx3d._core")
    use_library(monkeypatch, builds("linux-x64") / kernel_build.library_name("linux-x64"))
    means, quats, scales, camera = projection_inputs()
    means, quats, scales = mx.array(means), mx.array(quats), mx.array(scales)
    n = means.shape[0]
    rng = np.random.default_rng(4)
    cot = [mx.array(rng.normal(size=shape).astype(np.float32)) for shape in ((n, 2), (n, 3), (n,), (n,))]
    viewmat = [float(v) for v in np.asarray(camera.viewmat, np.float64).reshape(-1)]
    for antialias in (False, True):
        for threads in THREADS:
            def call(fn, m, q, s):
                return fn(m, q, s, viewmat, camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height, camera.near,
                          camera.far, 0.3, antialias, threads)

            def loss(fn):
                def f(m, q, s):
                    m2, conics, _, depths, comp = call(fn, m, q, s)
                    return (m2 * cot[0]).sum() + (conics * cot[1]).sum() + (depths * cot[2]).sum() + (comp * cot[3]).sum()
                return f

            got, want = call(kernel_library.project_ewa, means, quats, scales), call(native.core().project_ewa, means, quats, scales)
            assert all(np.array(g).tobytes() == np.array(w).tobytes() for g, w in zip(got, want))
            assert int((np.array(got[2]) > 0).sum()) > n // 2  # most of the file is in view
            grads = [mx.grad(loss(fn), argnums=(0, 1, 2))(means, quats, scales)
                     for fn in (kernel_library.project_ewa, native.core().project_ewa)]
            assert all(np.array(g).tobytes() == np.array(w).tobytes() for g, w in zip(*grads))
    with pytest.raises(ValueError, match=r"project_ewa: quats must have shape \(500, 4\), got \(500, 3\)"):
        kernel_library.project_ewa(means, quats[:, :3], scales, viewmat, 100, 100, 36, 26, 72, 52, 0.01, 100)
    with pytest.raises(ValueError, match="viewmat must have 16 entries"):
        kernel_library.project_ewa(means, quats, scales, viewmat[:12], 100, 100, 36, 26, 72, 52, 0.01, 100)


# ---- photometric loss tests ----
def photometric_value_and_grads(fn, x, y, weights, lam, taps, threads):
    """(loss, dloss/dimg, dloss/dref) as numpy of a photometric_loss with _core's signature."""
    import mlx.core as mx

    value, grads = mx.value_and_grad(lambda a, b: fn(a, b, weights, lam, taps, threads), argnums=(0, 1))(x, y)
    return np.array(value), np.array(grads[0]), np.array(grads[1])


def test_photometric_in_process_is_cores_and_the_reference(builds, monkeypatch):
    """The loss and both gradients, and the MSE, bit for bit _core's at 1, 2 and 4 threads, with and without weights;
    close to mlx3d.training.metrics' pure MLX expression evaluated in float64 (its float32 graph, whose means are
    float32 sums, is 10 times further from it on the render), and the MSE to numpy's float64 mean."""
    import mlx.core as mx

    from mlx3d import kernel_library, native
    from mlx3d.training import metrics

    use_library(monkeypatch, builds("linux-x64") / kernel_build.library_name("linux-x64"))
    core = native.core() if native.available() else None
    taps = [float(t) for t in photometric_taps()]
    for name, x, y, w in photometric_cases():
        x, y, w = mx.array(x), mx.array(y), mx.array(w)
        for weights in (None, w):
            w64 = None if weights is None else weights.astype(mx.float64)
            for lam in (0.2, 1.0) if name == "render" else (0.2,):
                ref = mx.value_and_grad(lambda a, b: metrics.photometric_loss(a, b, lam, w64, backend="reference", compiled=False),
                                        argnums=(0, 1))(x.astype(mx.float64), y.astype(mx.float64))
                ref = [np.array(ref[0]), *(np.array(g) for g in ref[1])]
                for threads in THREADS:
                    got = photometric_value_and_grads(kernel_library.photometric_loss, x, y, weights, lam, taps, threads)
                    where = f"{name}, weights {weights is not None}, lambda {lam}, {threads} threads"
                    assert float(got[0]) == pytest.approx(float(ref[0]), rel=5e-5), where  # float32 per pixel
                    for g, r in zip(got[1:], ref[1:]):
                        np.testing.assert_allclose(g, r, rtol=0, atol=5e-5 * np.abs(r).max(), err_msg=where)
                    if core is not None:
                        want = photometric_value_and_grads(core.photometric_loss, x, y, weights, lam, taps, threads)
                        assert all(g.tobytes() == c.tobytes() for g, c in zip(got, want)), where
            for clip in (False, True):
                img = x * 1.4 - 0.2
                shown = np.clip(np.array(img, np.float64), 0, 1) if clip else np.array(img, np.float64)
                per_pixel = ((shown - np.array(y, np.float64)) ** 2).mean(-1)
                wp = np.ones(per_pixel.shape) if weights is None else np.array(weights, np.float64)
                for threads in THREADS:
                    got = np.array(kernel_library.mse(img, y, weights, clip, threads))
                    pure = metrics.mse(img.astype(mx.float64), y.astype(mx.float64), w64, clip=clip, backend="reference")
                    assert float(got) == pytest.approx(float(pure), rel=1e-6)
                    assert float(got) == pytest.approx((per_pixel * wp).sum() / wp.sum(), rel=1e-6)
                    if core is not None:
                        assert got.tobytes() == np.array(core.mse(img, y, weights, clip, threads)).tobytes()


def test_photometric_gradients_run_only_what_is_differentiated(builds, monkeypatch):
    """The render's gradient is the loss pass's own (one kernel call); the photo's runs the kernel again only when
    asked for; the weights and the MSE have no gradient (errors, as _core's)."""
    import mlx.core as mx

    from mlx3d import kernel_library, native
    from mlx3d.kernel_library import photometric

    use_library(monkeypatch, builds("linux-x64") / kernel_build.library_name("linux-x64"))
    _, x, y, w = (a if isinstance(a, str) else mx.array(a) for a in photometric_cases()[1])
    taps = [float(t) for t in photometric_taps()]
    calls = []

    def counting(name, *args):
        calls.append(name)
        return kernel_library._call(name, *args)

    monkeypatch.setattr(photometric, "_call", counting)
    loss = kernel_library.photometric_loss
    value, grad = mx.value_and_grad(lambda a: loss(a, y, w, 0.2, taps))(x)
    assert calls == ["mlx3d_photometric_loss"]
    both = mx.value_and_grad(lambda a, b: loss(a, b, w, 0.2, taps), argnums=(0, 1))(x, y)
    assert calls == ["mlx3d_photometric_loss"] * 3
    assert np.array(value).tobytes() == np.array(both[0]).tobytes() and np.array(grad).tobytes() == np.array(both[1][0]).tobytes()
    cores = [native.core()] if native.available() else []
    for fn in [loss] + [c.photometric_loss for c in cores]:
        with pytest.raises(RuntimeError, match="photometric_loss: the gradient with respect to the mask is not implemented"):
            mx.eval(mx.grad(lambda m: fn(x, y, m, 0.2, taps), argnums=0)(w))
    for fn in [kernel_library.mse] + [c.mse for c in cores]:
        with pytest.raises(RuntimeError, match="mse on the CPU kernel is a metric and has no gradient"):
            mx.eval(mx.grad(lambda a: fn(a, y, None))(x))


def test_photometric_bad_calls_are_errors_that_name_the_problem(builds, monkeypatch):
    import mlx.core as mx

    from mlx3d import kernel_library
    from mlx3d.kernel_library import _call, _ptr

    use_library(monkeypatch, builds("linux-x64") / kernel_build.library_name("linux-x64"))
    _, x, y, w = (a if isinstance(a, str) else mx.array(a) for a in photometric_cases()[1])
    taps = [float(t) for t in photometric_taps()]
    loss, mse = kernel_library.photometric_loss, kernel_library.mse
    for fn, extra in ((loss, (0.2, taps)), (mse, ())):
        op = "photometric_loss" if fn is loss else "mse"
        with pytest.raises(ValueError, match=rf"{op}: img and ref must be \(H, W, C\) of one shape, got \(37, 53, 3\) and \(37, 52, 3\)"):
            fn(x, y[:, 1:], None, *extra)
        with pytest.raises(ValueError, match=rf"{op}: img and ref must be \(H, W, C\) of one shape, got \(37, 53\) and \(37, 53\)"):
            fn(x[..., 0], y[..., 0], None, *extra)
        with pytest.raises(TypeError, match=f"{op}: images must be float32 .* got mlx.core.float16 and mlx.core.float32"):
            fn(x.astype(mx.float16), y, None, *extra)
        with pytest.raises(ValueError, match=rf"{op}: weights must be float32 \(H, W\) = \(37, 53\), got mlx.core.float32 \(53, 37\)"):
            fn(x, y, w.T, *extra)
        with pytest.raises(ValueError, match=rf"{op}: the images must not be empty, got \(0, 53, 3\)"):
            fn(x[:0], y[:0], None, *extra)
        with pytest.raises(ValueError, match="num_threads must be >= 0"):
            fn(x, y, None, *(extra or (False,)), -1)
    with pytest.raises(ValueError, match="photometric_loss: taps must have an odd, positive length"):
        loss(x, y, None, 0.2, taps[:10])
    with pytest.raises(ValueError, match=r"photometric_loss: lambda_dssim must be in \[0, 1\]"):
        loss(x, y, None, 1.5, taps)
    # strided inputs are read through a copy: the same bits
    xt, yt = mx.swapaxes(mx.swapaxes(x, 0, 1) * 1, 0, 1), mx.swapaxes(mx.swapaxes(y, 0, 1) * 1, 0, 1)
    assert np.array(loss(xt, yt, w, 0.2, taps)).tobytes() == np.array(loss(x, y, w, 0.2, taps)).tobytes()
    # the C functions check their arguments themselves
    a, out = np.zeros((4, 5, 3), np.float32), np.zeros(60, np.float32)
    t = photometric_taps()
    with pytest.raises(ValueError, match=r"mlx3d_photometric_loss: lambda must be in \[0, 1\], got 1.500000"):
        _call("mlx3d_photometric_loss", _ptr(a), _ptr(a), None, 4, 5, 3, 1.5, _ptr(t), 11, 1, None, _ptr(out), _ptr(out))
    with pytest.raises(ValueError, match=r"mlx3d_photometric_loss: taps must have an odd, positive length, got 0"):
        _call("mlx3d_photometric_loss", _ptr(a), _ptr(a), None, 4, 5, 3, 0.2, _ptr(t), 0, 1, None, _ptr(out), _ptr(out))
    with pytest.raises(ValueError, match=r"mlx3d_mse: the image must be \(H, W, C\) with H, W, C >= 1, got \(0, 5, 3\)"):
        _call("mlx3d_mse", _ptr(a), _ptr(a), None, 0, 5, 3, 0, 1, _ptr(out))
    with pytest.raises(ValueError, match=r"mlx3d_mse: a null pointer \(only weights may be NULL\)"):
        _call("mlx3d_mse", _ptr(a), None, None, 4, 5, 3, 0, 1, _ptr(out))


def test_photometric_driver_calls_are_cores(builds, monkeypatch, tmp_path):
    """The calls the other platforms' builds run (photometric_calls), run by the linux-x64 driver: bit for bit _core's
    losses, gradients and MSEs (the in-process library's where _core is missing), and the two bad calls' errors."""
    import mlx.core as mx

    from mlx3d import kernel_library, native

    use_library(monkeypatch, builds("linux-x64") / kernel_build.library_name("linux-x64"))
    api = native.core() if native.available() else kernel_library
    calls = photometric_calls()
    results = run_driver(builds("linux-x64"), "linux-x64", [], calls, tmp_path)
    for (name, args), (rc, error, outs) in zip(calls[:-2], results[:-2]):
        x, y, w = (mx.array(a[1]) if a[1].size else None for a in args[:3])
        if name == "mlx3d_mse":
            assert rc == 0 and outs[0].tobytes() == np.array(api.mse(x, y, w, bool(args[6][1]), args[7][1])).tobytes()
            continue
        lam, taps, threads = args[6][1], [float(t) for t in args[7][1]], args[9][1]
        value, grad = mx.value_and_grad(lambda a: api.photometric_loss(a, y, w, lam, taps, threads))(x)
        assert rc == 0 and outs[1].tobytes() == np.array(value).reshape(1).tobytes() and outs[2].tobytes() == np.array(grad).ravel().tobytes()
    assert [r[:2] for r in results[-2:]] == [(2, "mlx3d_photometric_loss: lambda must be in [0, 1], got 1.500000"),
                                             (2, "mlx3d_photometric_loss: taps must have an odd, positive length, got 10")]


# ---- optimizer and activations tests ----
def optim_library(builds, monkeypatch):
    """(mlx3d.kernel_library on the linux-x64 build, mlx3d._core or None)."""
    from mlx3d import kernel_library, native

    use_library(monkeypatch, builds("linux-x64") / kernel_build.library_name("linux-x64"))
    assert kernel_library.available(), kernel_library.failure()
    return kernel_library, native.core() if native.available() else None


def same_bits(a, b) -> bool:
    return np.asarray(a).tobytes() == np.asarray(b).tobytes()


def test_adam_in_process_is_numpys_and_cores(builds, monkeypatch):
    """Three steps of four parameters (the SH rest coefficients 270000 floats: four threads' work) at 1, 2 and 4
    threads: p', m', v' bit for bit numpy's float32 expression and _core's; the arrays passed in keep their values."""
    import mlx.core as mx

    lib, core = optim_library(builds, monkeypatch)
    for p, g, m, v, lr, c1, c2, want in adam_steps(sh_rows=6000):
        args = [mx.array(a) for a in (p, g, m, v)]
        for threads in THREADS:
            got = lib.adam_step(*args, lr, *ADAM_BETAS, ADAM_EPS, c1, c2, threads)
            assert [a.shape for a in got] == [args[0].shape] * 3 and all(a.dtype == mx.float32 for a in got)
            assert all(same_bits(a, w) for a, w in zip(got, want)), (p.shape, threads)
            if core is not None:
                assert all(same_bits(a, c) for a, c in zip(got, core.adam_step(*args, lr, *ADAM_BETAS, ADAM_EPS, c1, c2, threads)))
        assert all(same_bits(a, b) for a, b in zip(args, (p, g, m, v)))
    p, g, _, _, lr, c1, c2, want = adam_steps(sh_rows=1)[0]  # as Adam.update's first step (zeros_like moments); p transposed
    zeros = mx.zeros_like(mx.array(g))
    got = lib.adam_step(mx.array(p.T.copy()).T, mx.array(g), zeros, zeros, lr, *ADAM_BETAS, ADAM_EPS, c1, c2)
    assert all(same_bits(a, w) for a, w in zip(got, want))
    empty = mx.zeros((0, 3))
    assert [a.shape for a in lib.adam_step(empty, empty, empty, empty, 1e-3, *ADAM_BETAS, ADAM_EPS, 0.1, 0.001)] == [(0, 3)] * 3


def test_all_finite_in_process_is_cores(builds, monkeypatch):
    """Arrays of every finite magnitude, then NaN, inf or -inf first, in the middle or last of the first or the last
    array (300000 floats: four threads' work), other dtypes (read as float32) and no arrays, at 1, 2 and 4 threads."""
    import mlx.core as mx

    lib, core = optim_library(builds, monkeypatch)
    x = finite_inputs(300_000)
    small = finite_inputs(1000, seed=3).reshape(10, 100)
    cases = [([x, small], True), ([], True)]
    for which in (0, 1):
        for at in (0, "middle", -1):
            for bad in (np.nan, np.inf, -np.inf):
                arrays = [x.copy(), small.copy()]
                flat = arrays[which].reshape(-1)
                flat[flat.size // 2 if at == "middle" else at] = bad
                cases.append((arrays, False))
    cases = [([mx.array(a) for a in arrays], want) for arrays, want in cases]
    cases += [([mx.array([1.0, np.inf], mx.float16)], False), ([mx.array([65504.0], mx.float16), mx.array([1, 2])], True),
              ([mx.array(x)[::3], mx.array(small).T], True)]
    for arrays, want in cases:
        for threads in THREADS:
            got = lib.all_finite(arrays, threads)
            assert got.dtype == mx.bool_ and got.shape == () and bool(got) == want
            if core is not None:
                assert bool(core.all_finite(arrays, threads)) == want


def test_activation_in_process_is_mlxs_and_cores(builds, monkeypatch):
    """exp and sigmoid over the float range (every 1024th float32 bit pattern, the edges and the floats around them,
    typical values; 4.2 million, all threads busy) at 1, 2 and 4 threads: values and gradients bit for bit mx.exp /
    mx.sigmoid's and _core's, NaN payloads included."""
    import mlx.core as mx

    lib, core = optim_library(builds, monkeypatch)
    x = mx.array(activation_inputs(stride=1024))
    cot = mx.array(np.random.default_rng(37).normal(size=x.shape).astype(np.float32))
    for kind in ("exp", "sigmoid"):
        def run(fn):
            (y,), (g,) = mx.vjp(fn, [x], [cot])
            return np.array(y), np.array(g)

        want = run(getattr(mx, kind))
        for threads in THREADS:
            got = run(lambda a: lib.activation(a, kind, threads))
            assert same_bits(got[0], want[0]) and same_bits(got[1], want[1]), (kind, threads)
            if core is not None:
                assert same_bits(got[0], np.array(core.activation(x, kind, threads)))
        shaped = x[: 3 * 1000 * 4].reshape(3, 1000, 4)[:, ::2]  # a strided 3-D view: read through a copy
        assert same_bits(lib.activation(shaped, kind), getattr(mx, kind)(shaped))


def test_affine_in_process_is_cores_and_near_numpys(builds, monkeypatch):
    """The hard maps of test_transforms over 20000 Gaussians (five threads' blocks) at 1, 2 and 4 threads: bit for bit
    _core's, the same bits at every thread count, and the covariances of numpy's reference (mlx3d.transforms) to 1e-5."""
    from mlx3d.transforms import _covariances_numpy, covariances

    lib, core = optim_library(builds, monkeypatch)
    for name, linear, quats, log_scales in affine_problem(20000):
        outs = []
        for threads in THREADS:
            q, s = np.empty_like(quats), np.empty_like(log_scales)
            lib.affine_covariances(linear, quats, log_scales, q, s, threads)
            outs.append((q, s))
            if core is not None:
                qc, sc = np.empty_like(quats), np.empty_like(log_scales)
                core.affine_covariances(linear, quats, log_scales, qc, sc, threads)
                assert same_bits(q, qc) and same_bits(s, sc), (name, threads)
        assert all(same_bits(q, outs[0][0]) and same_bits(s, outs[0][1]) for q, s in outs)
        q, s = outs[0]
        q_ref, s_ref = _covariances_numpy(linear, quats, log_scales)
        assert np.isfinite(q).all() and np.isfinite(s).all() and (q[:, 0] >= 0).all()
        np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-6)
        c, c_ref = covariances(q, s), covariances(q_ref, s_ref)
        assert (np.linalg.norm(c - c_ref, axis=(1, 2)) / np.linalg.norm(c_ref, axis=(1, 2))).max() < 1e-5, name
        assert (np.diff(s, axis=1) <= 0).all()
        np.testing.assert_allclose(s, np.sort(s_ref, axis=1)[:, ::-1], atol=1e-5)


def test_optim_bad_calls_are_errors_that_name_the_problem(builds, monkeypatch):
    import mlx.core as mx

    lib, _ = optim_library(builds, monkeypatch)
    p = mx.zeros((5, 3))
    scalars = (1e-3, *ADAM_BETAS, ADAM_EPS, 0.1, 0.001)
    with pytest.raises(ValueError, match=r"adam_step: p, g, m and v must have the same shape, got \(5, 3\) and \(4, 3\)"):
        lib.adam_step(p, p, p[:4], p, *scalars)
    with pytest.raises(TypeError, match="adam_step: g must be float32, got mlx.core.float16"):
        lib.adam_step(p, p.astype(mx.float16), p, p, *scalars)
    with pytest.raises(ValueError, match="adam_step: the bias corrections c1, c2 must be > 0, got 0.1, 0.0"):
        lib.adam_step(p, p, p, p, *scalars[:-1], 0.0)
    with pytest.raises(ValueError, match="num_threads must be >= 0"):
        lib.adam_step(p, p, p, p, *scalars, -1)
    with pytest.raises(ValueError, match="num_threads must be >= 0"):
        lib.all_finite([p], -2)
    with pytest.raises(ValueError, match="activation: kind must be 'exp' or 'sigmoid', got 'tanh'"):
        lib.activation(p, "tanh")
    with pytest.raises(TypeError, match="activation: x must be float32, got mlx.core.float16"):
        lib.activation(p.astype(mx.float16), "exp")
    q, s = np.zeros((5, 4), np.float32), np.zeros((5, 3), np.float32)
    with pytest.raises(ValueError, match=r"affine_covariances: linear must have shape \(3, 3\), got \(2, 2\)"):
        lib.affine_covariances(np.eye(2), q, s, q.copy(), s.copy())
    with pytest.raises(ValueError, match=r"affine_covariances: log_scales must have shape \(5, 3\) as quats, got \(4, 3\)"):
        lib.affine_covariances(np.eye(3), q, s[1:], q.copy(), s.copy())
    with pytest.raises(ValueError, match=r"affine_covariances: quats_out must be a writable C-contiguous float32 \(5, 4\)"):
        lib.affine_covariances(np.eye(3), q, s, q.astype(np.float64), s.copy())
    # the C functions' own checks, with their names
    from mlx3d.kernel_library import _call, _ptr

    x = np.zeros(10, np.float32)
    with pytest.raises(ValueError, match=r"mlx3d_adam_moment: squared must be 0 \(first moment\) or 1 \(second moment\), got 2"):
        _call("mlx3d_adam_moment", _ptr(x), _ptr(x), 10, 0.9, 2, 1, _ptr(np.zeros(10, np.float32)))
    with pytest.raises(ValueError, match=r"mlx3d_adam_moment: out must be x \(in place\) or not overlap it"):
        _call("mlx3d_adam_moment", _ptr(np.zeros(9, np.float32)), _ptr(x[:9]), 9, 0.9, 0, 1, _ptr(x[1:]))
    with pytest.raises(ValueError, match="mlx3d_adam_param: p_out must not overlap m or v"):
        _call("mlx3d_adam_param", _ptr(x[:5]), _ptr(x[5:]), _ptr(x[5:]), 5, 1e-3, 1e-15, 0.1, 0.001, 1, _ptr(x[5:]))
    with pytest.raises(ValueError, match="mlx3d_exp: the element count must be >= 0, got -1"):
        _call("mlx3d_exp", _ptr(x), -1, 1, _ptr(x))
    with pytest.raises(ValueError, match=r"mlx3d_affine_covariances: threads must be >= 0 \(0 = every hardware thread\), got -1"):
        _call("mlx3d_affine_covariances", _ptr(np.eye(3)), _ptr(q), _ptr(s), 5, -1, _ptr(q.copy()), _ptr(s.copy()))


def test_optim_driver_calls_are_numpys_mlxs_and_the_in_process_librarys(builds, monkeypatch, tmp_path):
    """The linux-x64 driver's results of optim_calls (what the other platforms' builds are held to): Adam numpy's
    float32 expression, into fresh outputs and in place; all_finite right; exp and sigmoid mx.exp's and mx.sigmoid's;
    the affine re-decomposition the in-process library's; the bad calls' errors."""
    import mlx.core as mx

    lib, _ = optim_library(builds, monkeypatch)
    calls = optim_calls()
    results = run_driver(builds("linux-x64"), "linux-x64", [], calls, tmp_path)
    for (name, args), (rc, error, outs) in zip(calls[:-2], results[:-2]):
        assert rc == 0 and error == "", name
        a = [value for _, value in args]
        if name == "mlx3d_adam_moment":
            assert same_bits(outs[0], numpy_moment(a[0], a[1], a[3], a[4]))
        elif name == "mlx3d_adam_param":
            assert same_bits(outs[0], numpy_param(a[0], a[1], a[2], *a[4:8]))
        elif name == "mlx3d_all_finite":
            assert list(outs[0]) == [int(np.isfinite(a[0]).all())]
        elif name in ("mlx3d_exp", "mlx3d_sigmoid"):
            assert same_bits(outs[0], getattr(mx, name[6:])(mx.array(a[0])))
        else:
            q, s = np.empty_like(a[1]), np.empty_like(a[2])
            lib.affine_covariances(a[0], a[1], a[2], q, s)
            assert same_bits(outs[0], q) and same_bits(outs[1], s)
    (rc0, error0, _), (rc1, error1, _) = results[-2:]
    assert rc0 == 2 and error0 == "mlx3d_adam_moment: squared must be 0 (first moment) or 1 (second moment), got 2"
    assert rc1 == 2 and error1.startswith("mlx3d_adam_param: the bias corrections c1, c2 must be > 0")


def test_windows_build_picks_avx2_where_the_cpu_has_it(builds, tmp_path, monkeypatch):
    """The Windows DLL (clang, zig) checks the CPU itself and runs the rasterizer's 8-lane AVX2 variant where it can,
    with the Linux build's bits at that width, forward and backward."""
    runner = wine_command()
    if runner is None:
        pytest.skip("wine not installed (`make test-kernel-platforms` installs it)")
    use_library(monkeypatch, builds("linux-x64") / kernel_build.library_name("linux-x64"))  # for the calls' inputs
    calls = [("mlx3d_rasterizer_lanes", [])] + raster_calls()
    reference = run_driver(builds("linux-x64"), "linux-x64", [], calls, tmp_path, baseline=False)
    if reference[0][0] != 8:
        pytest.skip("this CPU has no AVX2")
    got = run_driver(builds("windows-x64"), "windows-x64", runner, calls, tmp_path, baseline=False)
    assert got[0][0] == 8
    check_same(got, reference, calls)


def test_macos_build_is_an_arm64_library_exporting_the_api(builds):
    """Built and inspected only: the Mach-O header says 64-bit arm64 dylib, and every function of the API is in
    its symbol table. Never run here (no macOS)."""
    lib = builds("macos-arm64") / kernel_build.library_name("macos-arm64")
    data = lib.read_bytes()
    magic, cputype, _, filetype = struct.unpack_from("<IiiI", data, 0)
    assert (magic, cputype, filetype) == (0xFEEDFACF, 0x0100000C, 6)  # MH_MAGIC_64, CPU_TYPE_ARM64, MH_DYLIB
    header = (ROOT / "mlx3d" / "csrc" / "kernels" / "mlx3d_kernels.h").read_text()
    import re

    api = set(re.findall(r"MLX3D_API \w[\w\s\*]*?\b(mlx3d_\w+)\(", header))
    assert {"mlx3d_sh_forward", "mlx3d_sh_backward", "mlx3d_last_error"} <= api
    for name in api:
        assert b"_" + name.encode() + b"\0" in data, f"{name} is not exported"
