"""Writes raster_frozen.npz: inputs and outputs of the C++ rasterizer for a few
seeded scenes, used by tests/test_rasterize_cpu.py::test_frozen_outputs_are_bit_identical.

The outputs (accum, alpha, last, final_T and the four gradients, for the
AVX2 and the baseline kernel variants) were produced once by the kernel
before its sub-tile culling existed; the test checks that the current kernel
still reproduces them bit for bit. The gradients of means, conics and
opacities were written again, with culling off, when the backward pass began
to run its colour recurrence on colours dotted with dL/daccum (a different
rounding): they moved by at most 4.7e-7 of each array's largest magnitude,
with the same non-finite entries. Rerunning this script overwrites the
outputs with the current kernel's, so only do that on purpose, with culling
off:

    MLX3D_RASTER_CULL=0 .venv/bin/python tests/data/make_raster_frozen.py
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def _bin(means, ext_x, ext_y, depths, width, height, tile):
    """Tile lists by the tile rule (docs/guides/rendering.md) with per-axis half-extents (0 = culled)."""
    tiles_x, tiles_y = -(-width // tile), -(-height // tile)
    lists = [[] for _ in range(tiles_x * tiles_y)]
    for g in range(len(means)):
        ex, ey = float(ext_x[g]), float(ext_y[g])
        if not (ex > 0 and ey > 0):
            continue
        mx_, my_ = float(means[g][0]), float(means[g][1])
        if not (np.isfinite(mx_) and np.isfinite(my_)):
            continue
        x0, x1 = max(int(np.floor((mx_ - ex) / tile)), 0), min(int(np.floor((mx_ + ex) / tile)), tiles_x - 1)
        y0, y1 = max(int(np.floor((my_ - ey) / tile)), 0), min(int(np.floor((my_ + ey) / tile)), tiles_y - 1)
        for ty in range(y0, y1 + 1):
            for tx in range(x0, x1 + 1):
                lists[ty * tiles_x + tx].append(g)
    offsets, ids = [0], []
    for lst in lists:
        lst.sort(key=lambda g: (float(np.float32(depths[g])), g))
        ids.extend(lst)
        offsets.append(len(ids))
    return np.array(offsets, np.int32), np.array(ids, np.int32)


def _gaussians(rng, n, width, height, sigma, aniso, opacity):
    means = np.stack([rng.uniform(-6, width + 6, n), rng.uniform(-6, height + 6, n)], 1)
    s_major = rng.uniform(*sigma, n)
    s_minor = s_major / np.exp(rng.uniform(0, np.log(aniso), n))
    theta = rng.uniform(0, np.pi, n)
    cos, sin = np.cos(theta), np.sin(theta)
    rot = np.stack([np.stack([cos, -sin], -1), np.stack([sin, cos], -1)], -2)
    s = np.stack([s_major, s_minor], 1)
    cov = rot @ (s[:, :, None] ** 2 * np.swapaxes(rot, -1, -2))
    inv = np.linalg.inv(cov)
    conics = np.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], 1)
    opac = rng.uniform(*opacity, n)
    return means, conics, opac, np.ceil(3.5 * s_major)


def cases():
    """name -> dict(means, conics, feats, opac, offsets, ids, width, height, tile)."""
    out = {}

    def add(name, means, conics, feats, opac, offsets, ids, width, height, tile):
        f32 = lambda x: np.ascontiguousarray(x, np.float32)  # noqa: E731
        out[name] = dict(means=f32(means), conics=f32(conics), feats=f32(feats), opac=f32(opac),
                         offsets=np.asarray(offsets, np.int32), ids=np.asarray(ids, np.int32),
                         width=width, height=height, tile=tile)

    # 1. ordinary translucent scene, 3 channels, partial tiles
    rng = np.random.default_rng(101)
    w, h, n = 61, 45, 400
    m, c, o, r = _gaussians(rng, n, w, h, (0.8, 7.0), 4.0, (0.02, 0.95))
    off, ids = _bin(m, r, r, rng.uniform(1, 10, n), w, h, 16)
    add("translucent_c3_t16", m, c, rng.uniform(-1, 1, (n, 3)), o, off, ids, w, h, 16)

    # 2. dense and opaque (many stopped pixels, clamped pairs), 4 channels, tile 8
    rng = np.random.default_rng(102)
    w, h, n = 40, 33, 900
    m, c, o, r = _gaussians(rng, n, w, h, (1.0, 9.0), 3.0, (0.3, 1.3))
    o = np.minimum(o, 1.0)
    off, ids = _bin(m, r, r, rng.uniform(1, 10, n), w, h, 8)
    add("opaque_c4_t8", m, c, rng.uniform(0, 1, (n, 4)), o, off, ids, w, h, 8)

    # 3. very anisotropic, opacities near 1/255 and above 1, tile 12 (lane blocks straddle rows)
    rng = np.random.default_rng(103)
    w, h, n = 50, 38, 500
    m, c, o, r = _gaussians(rng, n, w, h, (0.5, 14.0), 3000.0, (0.0035, 0.02))
    o[::3] = rng.uniform(0.5, 3.0, len(o[::3]))
    o[1::7] = np.float32(1.0 / 255.0) * rng.uniform(0.999, 1.001, len(o[1::7]))
    off, ids = _bin(m, r, r, rng.uniform(1, 10, n), w, h, 12)
    add("aniso_faint_c1_t12", m, c, rng.uniform(-1, 1, (n, 1)), o, off, ids, w, h, 12)

    # 4. degenerate and non-finite parameters, tile 16 and 5 channels
    rng = np.random.default_rng(104)
    w, h, n = 36, 20, 120
    m, c, o, r = _gaussians(rng, n, w, h, (0.5, 5.0), 10.0, (0.1, 1.0))
    bad_c = [[np.nan, 0, 1], [np.inf, 0, 1], [0, 0, 0], [-1, 0, -1], [1, 2, 1], [1e30, 0, 1e30], [1e38, -1e38, 1e38],
             [3e-8, 0, 3e-8], [1e-40, 0, 1.0], [1.0, 0.999999, 1.0], [4.0, 0, -0.5], [1e-3, 0, 1e-3]]
    for i, cc in enumerate(bad_c):
        c[i] = cc
    bad_o = [np.nan, np.inf, -0.5, 0.0, 1e-30, 1e30, 0.003921568, 0.0039215689, 0.00392157, 0.99, 1.0, 0.5]
    o[len(bad_c):len(bad_c) + len(bad_o)] = bad_o
    m[30] = [np.nan, 5.0]
    m[31] = [1e20, -1e20]
    m[32] = [18.5, 10.5]
    r = np.full(n, 12.0)
    r[31] = 0.0
    off, ids = _bin(np.nan_to_num(m), r, r, rng.uniform(1, 10, n), w, h, 16)
    add("degenerate_c5_t16", m, c, rng.uniform(-2, 2, (n, 5)), o, off, ids, w, h, 16)

    # 5. one Gaussian per tile list, placed anywhere around its tile: every
    #    (pixel, Gaussian) decision shows in `last`
    rng = np.random.default_rng(105)
    w, h, tile = 96, 80, 16
    tiles_x, tiles_y = w // tile, h // tile
    n = tiles_x * tiles_y * 3
    m, c, o, _ = _gaussians(rng, n, tile, tile, (0.3, 12.0), 500.0, (0.003, 1.2))
    for g in range(n):
        t = g % (tiles_x * tiles_y)
        m[g] += [(t % tiles_x) * tile, (t // tiles_x) * tile]
    ids = np.arange(n, dtype=np.int32).reshape(3, -1).T.reshape(-1)  # 3 per tile
    off = np.arange(0, n + 1, 3, dtype=np.int32)
    add("isolated_c2_t16", m, c, rng.uniform(-1, 1, (n, 2)), o, off, ids, w, h, tile)

    # 6. alpha of 1/255 within a hair of a pixel centre: one Gaussian per tile
    #    list, its mean placed so that a chosen pixel sits on the skip boundary
    rng = np.random.default_rng(106)
    w, h, tile = 160, 128, 16
    tiles_x, tiles_y = w // tile, h // tile
    n = tiles_x * tiles_y
    _, c, o, _ = _gaussians(rng, n, tile, tile, (0.4, 16.0), 100.0, (0.005, 1.0))
    c32, o32 = c.astype(np.float32).astype(np.float64), o.astype(np.float32).astype(np.float64)
    m = np.zeros((n, 2))
    for g in range(n):
        t = g
        pix = np.array([(t % tiles_x) * tile + rng.integers(tile) + 0.5, (t // tiles_x) * tile + rng.integers(tile) + 0.5])
        ang = rng.uniform(0, 2 * np.pi)
        u = np.array([np.cos(ang), np.sin(ang)])
        q = c32[g, 0] * u[0] ** 2 + 2 * c32[g, 1] * u[0] * u[1] + c32[g, 2] * u[1] ** 2
        dist = np.sqrt(2 * np.log(o32[g] / np.float64(np.float32(1) / np.float32(255))) / q)
        m[g] = pix + u * dist * (1 + rng.uniform(-2e-6, 2e-6))
    ids = np.arange(n, dtype=np.int32)
    off = np.arange(0, n + 1, dtype=np.int32)
    add("threshold_c1_t16", m, c, rng.uniform(0.5, 1, (n, 1)), o, off, ids, w, h, tile)

    # 7. signed zeros (-0.0 conic entries and opacities), 3 channels
    rng = np.random.default_rng(107)
    w, h, n = 32, 32, 60
    m, c, o, r = _gaussians(rng, n, w, h, (1.0, 5.0), 2.0, (0.2, 0.9))
    c[::2, 1] = -0.0
    c[1::5] = [-0.0, -0.0, -0.0]
    o[3::7] = -0.0
    c[5::9, 0] = -0.0
    off, ids = _bin(m, r, r, rng.uniform(1, 10, n), w, h, 16)
    add("signed_zero_c3_t16", m, c, rng.uniform(-1, 1, (n, 3)), o, off, ids, w, h, 16)
    return out


def cotangents(height, width, channels):
    """Deterministic cotangents in [-1, 1) (integer hash, no RNG): dL/daccum, dL/dalpha."""

    def hashed(count, salt):
        i = np.arange(count, dtype=np.uint64) + np.uint64(salt)
        v = (i * np.uint64(2654435761) + np.uint64(12345)) % np.uint64(2**32)
        v = (v ^ (v >> np.uint64(13))) % np.uint64(4096)
        return (v.astype(np.float32) / np.float32(2048.0) - np.float32(1.0)).astype(np.float32)

    return (hashed(height * width * channels, 1).reshape(height, width, channels),
            hashed(height * width, 7).reshape(height, width))


def outputs(case, num_threads=2):
    """Forward outputs (with final_T) and the gradients for the cotangents above,
    from the kernel variant the environment selects (MLX3D_RASTER_ISA)."""
    import mlx.core as mx

    from mlx3d import native
    from mlx3d.render.raster_cpu import rasterize_cpu

    args = [mx.array(case[k]) for k in ("means", "conics", "feats", "opac", "offsets", "ids")]
    w, h, tile = int(case["width"]), int(case["height"]), int(case["tile"])
    fwd = native.core().rasterize_forward(*args, w, h, tile, num_threads)
    mx.eval(fwd)
    cot = [mx.array(a) for a in cotangents(h, w, case["feats"].shape[1])]

    def f(m, c, fe, o):
        accum, alpha, _ = rasterize_cpu(m, c, fe, o, args[4], args[5], w, h, tile, num_threads=num_threads)
        return accum, alpha

    _, grads = mx.vjp(f, args[:4], cot)
    mx.eval(grads)
    names = ("accum", "alpha", "last", "final_T", "g_means", "g_conics", "g_feats", "g_opac")
    return {k: np.array(v) for k, v in zip(names, list(fwd) + list(grads))}


def main():
    from mlx3d import native

    data = {}
    for name, case in cases().items():
        for k, v in case.items():
            data[f"{name}/{k}"] = np.asarray(v)
        for isa in ("best", "baseline"):
            if isa == "baseline":
                os.environ["MLX3D_RASTER_ISA"] = "baseline"
            else:
                os.environ.pop("MLX3D_RASTER_ISA", None)
            data[f"{isa}_lanes"] = np.int32(native.core().rasterizer_simd_lanes())
            for k, v in outputs(case).items():
                if isa == "baseline" and not k.startswith("g_"):
                    continue  # forward outputs do not depend on the variant
                data[f"{name}/{isa}/{k}"] = v
    os.environ.pop("MLX3D_RASTER_ISA", None)
    np.savez_compressed(HERE / "raster_frozen.npz", **data)
    print(f"wrote {HERE / 'raster_frozen.npz'} ({(HERE / 'raster_frozen.npz').stat().st_size} bytes)", file=sys.stderr)


if __name__ == "__main__":
    main()
