"""The Metal rasterizer (mlx3d.render.raster_metal).

Everywhere: the module imports without Metal, its kernels' header is the
raster_math.h the CPU kernels compile, and the kernel bodies, compiled as C++
with a thin shim for the Metal built-ins (one thread at a time, atomics as
plain adds), reproduce the CPU rasterizer's outputs and gradients. With Metal
(Apple GPUs) the real kernels are compared with the CPU rasterizer.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import mlx.core as mx
import numpy as np
import pytest

from mlx3d.render import raster_metal
from mlx3d.render.raster_cpu import rasterize_cpu
from mlx3d.render.raster_metal import (
    backward_source,
    forward_source,
    kernel_header,
    metal_available,
    rasterize_metal,
)

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
    assert not raster_metal._kernel_cache


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
# the kernel bodies as C++ (a shim for the Metal built-ins)
# --------------------------------------------------------------------------- #
SHIM = r"""
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <vector>
#define device
#define thread
struct uint3 { unsigned x, y, z; };
enum ShimMemoryOrder { memory_order_relaxed };
template <class T> using atomic = T;
inline void atomic_fetch_add_explicit(float* p, float v, ShimMemoryOrder) { *p += v; }
"""

SHIM_MAIN = r"""
template <int WIDTH, int HEIGHT, int TILE, int TILES_X, int CH>
void forward_kernel(const device float* means2d, const device float* conics, const device float* features,
                    const device float* opacities, const device int32_t* tile_offsets,
                    const device int32_t* flatten_ids, device float* out_accum, device float* out_alpha,
                    device int32_t* out_last, device float* out_final_T, uint3 threadgroup_position_in_grid,
                    uint3 thread_position_in_threadgroup) {
FORWARD_BODY
}

template <int WIDTH, int HEIGHT, int TILE, int TILES_X, int CH>
void backward_kernel(const device float* means2d, const device float* conics, const device float* features,
                     const device float* opacities, const device int32_t* tile_offsets,
                     const device int32_t* flatten_ids, const device int32_t* last, const device float* final_T,
                     const device float* cot_accum, const device float* cot_alpha,
                     device atomic<float>* g_means2d, device atomic<float>* g_conics,
                     device atomic<float>* g_features, device atomic<float>* g_opacities,
                     uint3 threadgroup_position_in_grid, uint3 thread_position_in_threadgroup) {
BACKWARD_BODY
}

template <class T>
std::vector<T> load(const char* dir, const char* name, size_t count) {
  std::vector<T> v(count + 1);
  std::string path = std::string(dir) + "/" + name;
  FILE* f = std::fopen(path.c_str(), "rb");
  if (!f) { std::perror(path.c_str()); std::exit(2); }
  if (count && std::fread(v.data(), sizeof(T), count, f) != count) { std::exit(3); }
  std::fclose(f);
  return v;
}
template <class T>
void save(const char* dir, const char* name, const std::vector<T>& v, size_t count) {
  std::string path = std::string(dir) + "/" + name;
  FILE* f = std::fopen(path.c_str(), "wb");
  std::fwrite(v.data(), sizeof(T), count, f);
  std::fclose(f);
}

int main(int argc, char** argv) {
  const char* d = argv[1];
  const size_t n = SHIM_N, m = SHIM_M, hw = size_t(SHIM_H) * SHIM_W, tiles = size_t(SHIM_TX) * SHIM_TY;
  auto means = load<float>(d, "means", 2 * n);
  auto conics = load<float>(d, "conics", 3 * n);
  auto feats = load<float>(d, "feats", SHIM_C * n);
  auto opac = load<float>(d, "opac", n);
  auto off = load<int32_t>(d, "off", tiles + 1);
  auto ids = load<int32_t>(d, "ids", m);
  auto cot_accum = load<float>(d, "cot_accum", hw * SHIM_C);
  auto cot_alpha = load<float>(d, "cot_alpha", hw);
  std::vector<float> accum(hw * SHIM_C), alpha(hw), final_T(hw);
  std::vector<int32_t> last(hw);
  std::vector<float> gm(2 * n + 1), gc(3 * n + 1), gf(SHIM_C * n + 1), go(n + 1);
  for (unsigned ty = 0; ty < SHIM_TY; ++ty)
    for (unsigned tx = 0; tx < SHIM_TX; ++tx)
      for (unsigned y = 0; y < SHIM_TILE; ++y)
        for (unsigned x = 0; x < SHIM_TILE; ++x)
          forward_kernel<SHIM_W, SHIM_H, SHIM_TILE, SHIM_TX, SHIM_C>(
              means.data(), conics.data(), feats.data(), opac.data(), off.data(), ids.data(), accum.data(),
              alpha.data(), last.data(), final_T.data(), uint3{tx, ty, 0}, uint3{x, y, 0});
  for (unsigned ty = 0; ty < SHIM_TY; ++ty)
    for (unsigned tx = 0; tx < SHIM_TX; ++tx)
      for (unsigned y = 0; y < SHIM_TILE; ++y)
        for (unsigned x = 0; x < SHIM_TILE; ++x)
          backward_kernel<SHIM_W, SHIM_H, SHIM_TILE, SHIM_TX, SHIM_C>(
              means.data(), conics.data(), feats.data(), opac.data(), off.data(), ids.data(), last.data(),
              final_T.data(), cot_accum.data(), cot_alpha.data(), gm.data(), gc.data(), gf.data(), go.data(),
              uint3{tx, ty, 0}, uint3{x, y, 0});
  save(d, "accum", accum, hw * SHIM_C);
  save(d, "alpha", alpha, hw);
  save(d, "last", last, hw);
  save(d, "g_means", gm, 2 * n);
  save(d, "g_conics", gc, 3 * n);
  save(d, "g_feats", gf, SHIM_C * n);
  save(d, "g_opac", go, n);
  return 0;
}
"""


def _cxx():
    for name in ("c++", "g++", "clang++"):
        path = shutil.which(name)
        if path:
            return path
    return None


@pytest.mark.skipif(_cxx() is None, reason="no C++ compiler to compile the kernel bodies on the CPU")
def test_kernel_bodies_compiled_as_cpp_match_the_cpu_rasterizer(tmp_path):
    width, height, tile, channels = 37, 23, 16, 3
    scene = random_scene(4, 150, width, height, channels, tile=tile)
    means, conics, feats, opac, off, ids = scene
    rng = np.random.default_rng(1)
    cot_accum = rng.normal(size=(height, width, channels)).astype(np.float32)
    cot_alpha = rng.normal(size=(height, width)).astype(np.float32)
    for name, arr in dict(means=means, conics=conics, feats=feats, opac=opac, off=off, ids=ids,
                          cot_accum=cot_accum, cot_alpha=cot_alpha).items():
        np.ascontiguousarray(arr).tofile(tmp_path / name)
    tiles_x, tiles_y = -(-width // tile), -(-height // tile)
    source = SHIM + kernel_header() + SHIM_MAIN.replace("FORWARD_BODY", forward_source()).replace(
        "BACKWARD_BODY", backward_source()
    )
    (tmp_path / "kernels.cpp").write_text("#include <string>\n" + source)
    defines = dict(SHIM_N=len(means), SHIM_M=len(ids), SHIM_W=width, SHIM_H=height, SHIM_TILE=tile,
                   SHIM_TX=tiles_x, SHIM_TY=tiles_y, SHIM_C=channels)
    exe = tmp_path / "kernels"
    cmd = [_cxx(), "-std=c++17", "-O1", "-ffp-contract=off", "-o", str(exe), str(tmp_path / "kernels.cpp")]
    cmd += [f"-D{k}={v}" for k, v in defines.items()]
    build = subprocess.run(cmd, capture_output=True, text=True)
    assert build.returncode == 0, build.stderr[-4000:]
    run = subprocess.run([str(exe), str(tmp_path)], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr

    def read(name, dtype, shape):
        return np.fromfile(tmp_path / name, dtype=dtype).reshape(shape)

    accum, alpha, last = rasterize_cpu(*scene, width, height, tile)
    np.testing.assert_allclose(read("accum", np.float32, (height, width, channels)), np.array(accum), atol=1e-6)
    np.testing.assert_allclose(read("alpha", np.float32, (height, width)), np.array(alpha), atol=1e-6)
    np.testing.assert_array_equal(read("last", np.int32, (height, width)), np.array(last))

    def f(m, c, fe, o):
        out = rasterize_cpu(m, c, fe, o, off, ids, width, height, tile)
        return out[0], out[1]

    _, grads = mx.vjp(f, [mx.array(x) for x in (means, conics, feats, opac)], [mx.array(cot_accum), mx.array(cot_alpha)])
    n = len(means)
    for name, shape, g in zip(("g_means", "g_conics", "g_feats", "g_opac"),
                              ((n, 2), (n, 3), (n, channels), (n,)), grads):
        want = np.array(g)
        got = read(name, np.float32, shape)
        scale = np.abs(want).max()
        assert scale > 0
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-5 * scale, err_msg=name)


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
