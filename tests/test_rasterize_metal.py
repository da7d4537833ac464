"""The Metal rasterizer (mlx3d.render.raster_metal).

Everywhere: the module imports without Metal, its kernels' header is the
raster_math.h the CPU kernels compile, and rasterize_metal with its kernels'
sources compiled as C++ (tests/metal_emulator.py: one thread at a time,
atomics as plain adds) reproduces the MLX rasterizer's outputs and gradients,
and the CPU kernel's bit for bit where the compiled module is built. With
Metal (Apple GPUs) the real kernels are compared with the CPU rasterizer.
"""

from __future__ import annotations

from pathlib import Path

import mlx.core as mx
import numpy as np
import pytest

import metal_emulator
from mlx3d import native
from mlx3d.render import raster_metal
from mlx3d.render.raster_cpu import rasterize_cpu, rasterize_cpu_surface
from mlx3d.render.raster_metal import (
    backward_source,
    forward_source,
    kernel_header,
    metal_available,
    rasterize_metal,
    rasterize_metal_surface,
)
from mlx3d.render.raster_mlx import rasterize_mlx, rasterize_mlx_surface

try:  # the scene builder and oracle binning of the CPU tests
    from test_rasterize_cpu import random_scene
except ImportError:  # pragma: no cover - run from another directory
    from tests.test_rasterize_cpu import random_scene

HEADER_FILE = Path(__file__).resolve().parents[1] / "mlx3d" / "csrc" / "raster_math.h"
needs_metal = pytest.mark.skipif(not metal_available(), reason="Metal is not available (no Apple GPU)")


def test_module_imports_and_kernel_source_uses_the_shared_math():
    assert isinstance(metal_available(), bool)
    assert metal_available() == bool(mx.metal.is_available())
    header = kernel_header()
    assert header == HEADER_FILE.read_text(encoding="utf-8")
    for name in ("rm_power", "rm_exp", "rm_alpha", "rm_next_T", "RM_T_MIN"):
        assert name in header and name in forward_source()
    for name in ("rm_T_before", "rm_behind", "rm_dl_dalpha", "rm_gaussian_grad", "atomic_fetch_add_explicit"):
        assert name in header or name == "atomic_fetch_add_explicit"
        assert name in backward_source()
    # no kernel was built by importing or by reading the sources
    assert not raster_metal.kernels()._built


@pytest.mark.skipif(metal_available(), reason="checks the error raised without Metal")
def test_clear_error_without_metal():
    means, conics, feats, opac, off, ids = random_scene(0, 5, 16, 16, 3)
    with pytest.raises(RuntimeError, match="Metal"):
        rasterize_metal(means, conics, feats, opac, off, ids, 16, 16)
    with pytest.raises(ValueError, match="tile_size"):
        rasterize_metal(means, conics, feats, opac, np.zeros(2, np.int32), ids[:0], 16, 16, tile_size=64)
    with pytest.raises(ValueError, match="means2d"):
        rasterize_metal(means[:, :1], conics, feats, opac, off, ids, 16, 16)


# --------------------------------------------------------------------------- #
# the kernels' sources compiled as C++, launched through rasterize_metal
# --------------------------------------------------------------------------- #
needs_cxx = pytest.mark.skipif(metal_emulator.compiler() is None, reason="no C++ compiler to compile the kernel sources on the CPU")


@pytest.fixture
def emulated(monkeypatch):
    """rasterize_metal's own Python with its kernels' sources compiled as C++ (tests/metal_emulator.py)."""
    monkeypatch.setattr(raster_metal, "metal_available", lambda: True)
    with raster_metal.use_builder(metal_emulator.metal_kernel) as kernels:
        yield kernels


def scene_depths(seed, n, width, height):
    """The depths random_scene(seed, n, width, height, ...) binned its Gaussians by (it draws them last)."""
    rng = np.random.default_rng(seed)
    for shape in (n, n, (n, 2), n, (n, 3), n):
        rng.uniform(size=shape)
    return rng.uniform(1, 10, n).astype(np.float32)


def surface_layer(seed, width, height, opaque):
    rng = np.random.default_rng(100 + seed)
    alpha = np.ones((height, width), np.float32) if opaque else rng.uniform(0, 1, (height, width)).astype(np.float32)
    color = rng.uniform(0, 1, (height, width, 3)).astype(np.float32) * alpha[..., None]
    depth = rng.uniform(0, 12, (height, width)).astype(np.float32)
    depth[rng.uniform(size=(height, width)) < 0.2] = np.inf
    return color, alpha, depth


@needs_cxx
@pytest.mark.parametrize("channels,tile", [(3, 16), (1, 8), (5, 16)])
def test_emulated_kernels_match_the_cpu_and_mlx_rasterizers(emulated, channels, tile):
    width, height = 45, 29
    scene = random_scene(channels, 200, width, height, channels, tile=tile, opacity=(0.3, 1.5))
    rng = np.random.default_rng(channels)
    cots = [mx.array(rng.normal(size=(height, width, channels)).astype(np.float32)),
            mx.array(rng.normal(size=(height, width)).astype(np.float32))]
    primals = [mx.array(x) for x in scene[:4]]

    def run(fn):
        def f(m, c, fe, o):
            return fn(m, c, fe, o, scene[4], scene[5], width, height, tile)[:2]

        outputs = fn(*scene, width, height, tile)
        return [np.array(o) for o in outputs], [np.array(g) for g in mx.vjp(f, primals, cots)[1]]

    (gpu, g_gpu), (pure, g_pure) = run(rasterize_metal), run(rasterize_mlx)
    assert emulated._built.keys() == {"forward", "backward"}
    np.testing.assert_allclose(gpu[0], pure[0], atol=1e-6)
    np.testing.assert_allclose(gpu[1], pure[1], atol=1e-6)
    np.testing.assert_array_equal(gpu[2], pure[2])
    for a, b in zip(g_gpu, g_pure):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5 * np.abs(b).max())
    if native.available():  # the same per-pixel code as the CPU kernel: the forward bit for bit
        cpu, g_cpu = run(rasterize_cpu)
        for a, b in zip(gpu, cpu):
            np.testing.assert_array_equal(a, b)
        for a, b in zip(g_gpu, g_cpu):
            np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5 * np.abs(b).max())


@needs_cxx
@pytest.mark.parametrize("seed", range(4))
def test_emulated_surface_kernel_matches_the_cpu_and_mlx_rasterizers(emulated, seed):
    width, height = 70, 50
    scene = random_scene(seed, 300, width, height, 3, opacity=(0.3, 1.5))
    layer = (scene_depths(seed, 300, width, height), *surface_layer(seed, width, height, opaque=seed % 2 == 1))
    gpu = [np.array(a) for a in rasterize_metal_surface(*scene, *layer, width, height)]
    pure = [np.array(a) for a in rasterize_mlx_surface(*scene, *layer, width, height)]
    assert "surface" in emulated._built
    np.testing.assert_allclose(gpu[0], pure[0], atol=1e-6)
    np.testing.assert_allclose(gpu[1], pure[1], atol=1e-6)
    np.testing.assert_array_equal(gpu[2], pure[2])
    if native.available():
        for a, b in zip(gpu, rasterize_cpu_surface(*scene, *layer, width, height)):
            np.testing.assert_array_equal(a, np.array(b))

    def loss(means):
        return rasterize_metal_surface(means, *scene[1:], *layer, width, height)[0].sum()

    with pytest.raises(RuntimeError, match="forward-only"):
        mx.grad(loss)(mx.array(scene[0]))


@needs_cxx
def test_emulated_kernels_with_nothing_to_draw(emulated):
    width, height = 20, 12
    off, ids = np.zeros(3, np.int32), np.zeros(0, np.int32)
    for n in (0, 4):
        m, c, f, o = np.ones((n, 2)), np.ones((n, 3)), np.ones((n, 2)), np.ones(n)
        accum, alpha, last = rasterize_metal(m, c, f, o, off, ids, width, height)
        assert accum.shape == (height, width, 2) and not np.array(accum).any()
        assert not np.array(alpha).any() and not np.array(last).any()
    assert not emulated._built  # no kernel is launched for an empty scene


# --------------------------------------------------------------------------- #
# the real kernels (Apple GPUs)
# --------------------------------------------------------------------------- #
@needs_metal
@pytest.mark.parametrize("channels,tile", [(3, 16), (1, 8), (5, 16)])
def test_metal_matches_cpu(channels, tile):
    width, height = 45, 29
    scene = random_scene(channels, 200, width, height, channels, tile=tile)
    means, conics, feats, opac, off, ids = scene
    cpu = rasterize_cpu(*scene, width, height, tile)
    gpu = rasterize_metal(*scene, width, height, tile)
    np.testing.assert_allclose(np.array(gpu[0]), np.array(cpu[0]), atol=1e-5)
    np.testing.assert_allclose(np.array(gpu[1]), np.array(cpu[1]), atol=1e-5)
    np.testing.assert_array_equal(np.array(gpu[2]), np.array(cpu[2]))

    rng = np.random.default_rng(channels)
    cots = [mx.array(rng.normal(size=(height, width, channels)).astype(np.float32)),
            mx.array(rng.normal(size=(height, width)).astype(np.float32))]
    primals = [mx.array(x) for x in (means, conics, feats, opac)]

    def wrap(fn):
        def f(m, c, fe, o):
            out = fn(m, c, fe, o, off, ids, width, height, tile)
            return out[0], out[1]

        return f

    _, g_cpu = mx.vjp(wrap(rasterize_cpu), primals, cots)
    _, g_gpu = mx.vjp(wrap(rasterize_metal), primals, cots)
    for a, b in zip(g_gpu, g_cpu):
        b = np.array(b)
        np.testing.assert_allclose(np.array(a), b, rtol=1e-4, atol=1e-5 * np.abs(b).max())


@needs_metal
def test_metal_empty_inputs():
    width, height = 20, 12
    off = np.zeros(3, np.int32)
    ids = np.zeros(0, np.int32)
    for n in (0, 4):
        m, c, f, o = np.ones((n, 2)), np.ones((n, 3)), np.ones((n, 2)), np.ones(n)
        accum, alpha, last = rasterize_metal(m, c, f, o, off, ids, width, height)
        assert accum.shape == (height, width, 2) and not np.array(accum).any()
        assert not np.array(alpha).any() and not np.array(last).any()

        def loss(m_, c_, f_, o_):
            a, al, _ = rasterize_metal(m_, c_, f_, o_, off, ids, width, height)
            return a.sum() + al.sum()

        grads = mx.grad(loss, argnums=(0, 1, 2, 3))(*[mx.array(x, dtype=mx.float32) for x in (m, c, f, o)])
        for g, x in zip(grads, (m, c, f, o)):
            assert g.shape == x.shape and not np.array(g).any()
