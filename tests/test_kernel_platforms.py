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
# ---- projection and tile binning calls ----
# ---- photometric loss calls ----
# ---- optimizer and activations calls ----


ARRAY_TYPES = {"f": "<f4", "u": "u1", "n": "<i4", "D": "<f8"}


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
            if kind in ("o", "l", "D"):
                (count,) = struct.unpack_from("<Q", data, at)
                dtype = np.dtype({"o": "<f4", "l": "<i8", "D": "<f8"}[kind])
                outs.append(np.frombuffer(data, dtype, count, at + 8).copy())
                at += 8 + dtype.itemsize * count
        results.append((rc, error, outs))
    assert at == len(data), "the driver wrote more than the calls asked for"
    return results


def run_driver(folder: Path, platform: str, runner: list[str], calls, tmp_path: Path) -> list:
    calls_file, out_file = tmp_path / f"calls_{platform}.bin", tmp_path / f"out_{platform}.bin"
    write_calls(calls_file, calls)
    env = dict(os.environ)
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
    with pytest.raises(RuntimeError, match="mlx3d_sh_forward: degree 3 needs at least 16 coefficients, got 1"):
        kernel_library.sh_colors([dc], means, centre, 3)
    with pytest.raises(TypeError, match="means must be float32, got mlx.core.float16"):
        kernel_library.sh_colors([dc, rest], means.astype(mx.float16), centre, 3)
    with pytest.raises(ValueError, match=r"means must have shape \(500, 3\), got \(499, 3\)"):
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
    with pytest.raises(ValueError, match="radii must hold 500 elements, got 499"):
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
    with pytest.raises(RuntimeError, match="mlx3d_knn_query: k must be >= 1, got 0"):
        trees[0].query(queries, 0)
    with pytest.raises(RuntimeError, match="mlx3d_knn_build: leaf_size must be >= 1, got 0"):
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
def test_other_platforms_builds_give_the_linux_builds_results(builds, platform, tmp_path):
    runner = wine_command() if platform == "windows-x64" else qemu_command()
    if runner is None:
        pytest.skip(f"{'wine' if platform == 'windows-x64' else 'qemu-user and the arm64 C library'} not installed "
                    "(`make test-kernel-platforms` installs them)")
    base = sh_calls() + statistics_calls() + knn_calls()  # with oracles of their own below
    calls = base + []  # the other areas' calls (add yours here): compared with the linux-x64 build's bits
    reference = run_driver(builds("linux-x64"), "linux-x64", [], calls, tmp_path)
    bad = len(sh_calls()) - 1
    assert reference[bad][0] == 1 and "degree must be 0..3, got 4" in reference[bad][1]
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
# ---- projection and tile binning tests ----
# ---- photometric loss tests ----
# ---- optimizer and activations tests ----


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
