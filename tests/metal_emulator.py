"""``mx.fast.metal_kernel`` emulated on the CPU: the kernel source compiled as C++.

``metal_kernel(name, input_names, output_names, source, header, atomic_outputs)``
has MLX's signature and returns a launch callable with MLX's keywords
(``inputs``, ``template``, ``grid``, ``threadgroup``, ``output_shapes``,
``output_dtypes``, ``init_value``). The kernel body and header are compiled,
unchanged, as C++17 with a shim for the Metal words they use (``device``,
``thread``, ``uint3``, ``atomic<float>``, ``atomic_fetch_add_explicit``) into
a shared library (cached per source in the temporary directory) and called
through ctypes. The launch runs every thread of the grid one after another,
threadgroup by threadgroup, so atomics are plain additions. Template
constants become run-time ``int``s (arrays sized by them are variable-length
arrays, which GCC and Clang accept in C++). Outputs without ``init_value``
start as NaN (Metal leaves them uninitialised), so a kernel that forgets to
write one shows it.

Used by ``mlx3d.render.raster_metal.use_builder(metal_kernel)`` to run the Mac
path's Python and kernels on Linux.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import tempfile
import threading
from pathlib import Path

import mlx.core as mx
import numpy as np

__all__ = ["metal_kernel", "compiler", "launches"]

SHIM = r"""
#include <cstdint>
#include <cmath>
#define device
#define thread
#define constant const
struct uint3 { unsigned x, y, z; };
enum ShimMemoryOrder { memory_order_relaxed };
template <class T> using atomic = T;
template <class T> inline void atomic_fetch_add_explicit(T* p, T v, ShimMemoryOrder) { *p += v; }
"""

_C_TYPES = {mx.float32: "float", mx.int32: "int32_t", mx.uint32: "uint32_t", mx.bool_: "bool", mx.int64: "int64_t"}
_NP_TYPES = {mx.float32: np.float32, mx.int32: np.int32, mx.uint32: np.uint32, mx.bool_: np.bool_, mx.int64: np.int64}
_lock = threading.Lock()
_libraries: dict = {}
launches: dict = {}  # kernel name -> number of launches (tests read it to see which kernels ran)


def compiler() -> str | None:
    """The C++ compiler the emulator uses (CXX, else c++, g++, clang++ on PATH), or None."""
    for name in (os.environ.get("CXX"), "c++", "g++", "clang++"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


def _library(text: str) -> ctypes.CDLL:
    key = hashlib.sha256(text.encode()).hexdigest()[:20]
    with _lock:
        if key in _libraries:
            return _libraries[key]
        folder = Path(tempfile.gettempdir()) / "mlx3d-metal-emulator"
        folder.mkdir(exist_ok=True)
        lib = folder / f"kernel-{key}.so"
        if not lib.exists():
            src = folder / f"kernel-{key}.cpp"
            src.write_text(text)
            tmp = folder / f"kernel-{key}.{os.getpid()}.so"
            cmd = [compiler(), "-std=c++17", "-O2", "-ffp-contract=off", "-fPIC", "-shared", "-Wno-vla", "-o", str(tmp), str(src)]
            build = subprocess.run(cmd, capture_output=True, text=True)
            if build.returncode != 0:
                raise RuntimeError(f"the kernel did not compile as C++:\n{build.stderr[-4000:]}")
            os.replace(tmp, lib)
        _libraries[key] = ctypes.CDLL(str(lib))
        return _libraries[key]


def _source(name, input_names, output_names, in_types, out_types, atomic, template_names, body, header) -> str:
    params = [f"const device {t}* {n}" for n, t in zip(input_names, in_types)]
    params += [f"device {'atomic<' + t + '>' if atomic else t}* {n}" for n, t in zip(output_names, out_types)]
    params += ["uint3 threadgroup_position_in_grid", "uint3 thread_position_in_threadgroup", "uint3 thread_position_in_grid",
               "uint3 threads_per_threadgroup"]
    params += [f"const int {t}" for t in template_names]
    args = [f"({'const ' if i < len(input_names) else ''}{t}*)buffers[{i}]" for i, t in enumerate(list(in_types) + list(out_types))]
    args += ["uint3{bx, by, bz}", "uint3{x, y, z}", "uint3{bx * tg[0] + x, by * tg[1] + y, bz * tg[2] + z}", "uint3{tg[0], tg[1], tg[2]}"]
    args += [f"(int)tmpl[{i}]" for i in range(len(template_names))]
    return f"""{SHIM}
{header}
static void {name}_body({", ".join(params)}) {{
{body}
}}
extern "C" void launch(void** buffers, const long long* tmpl, const unsigned* grid, const unsigned* tg) {{
  const unsigned nx = (grid[0] + tg[0] - 1) / tg[0], ny = (grid[1] + tg[1] - 1) / tg[1], nz = (grid[2] + tg[2] - 1) / tg[2];
  for (unsigned bz = 0; bz < nz; ++bz) for (unsigned by = 0; by < ny; ++by) for (unsigned bx = 0; bx < nx; ++bx)
    for (unsigned z = 0; z < tg[2]; ++z) for (unsigned y = 0; y < tg[1]; ++y) for (unsigned x = 0; x < tg[0]; ++x) {{
      if (bx * tg[0] + x >= grid[0] || by * tg[1] + y >= grid[1] || bz * tg[2] + z >= grid[2]) continue;
      {name}_body({", ".join(args)});
    }}
}}
"""


def metal_kernel(name, input_names, output_names, source, header="", ensure_row_contiguous=True, atomic_outputs=False, **_options):
    """A launch callable running ``source`` as C++ (see the module docstring)."""
    if compiler() is None:
        raise RuntimeError("the Metal kernel emulator needs a C++ compiler (c++, g++ or clang++ on PATH)")

    def launch(*, inputs, output_shapes, output_dtypes, grid, threadgroup, template=(), init_value=None, verbose=False, stream=None):
        arrays = [np.ascontiguousarray(np.asarray(a)) for a in inputs]
        in_types = [_C_TYPES[(i if isinstance(i, mx.array) else mx.array(i)).dtype] for i in inputs]
        out_types = [_C_TYPES[d] for d in output_dtypes]
        names = [t for t, _ in template]
        lib = _library(_source(name, input_names, output_names, in_types, out_types, atomic_outputs, names, source, header))
        outputs = []
        for shape, dtype in zip(output_shapes, output_dtypes):
            out = np.empty(tuple(shape), _NP_TYPES[dtype])
            if init_value is not None:
                out.fill(init_value)
            elif out.dtype.kind == "f":
                out.fill(np.nan)
            outputs.append(out)
        buffers = (ctypes.c_void_p * (len(arrays) + len(outputs)))(*[a.ctypes.data for a in arrays + outputs])
        values = (ctypes.c_longlong * max(1, len(template)))(*[int(v) for _, v in template])
        lib.launch(buffers, values, (ctypes.c_uint * 3)(*grid), (ctypes.c_uint * 3)(*threadgroup))
        launches[name] = launches.get(name, 0) + 1
        return [mx.array(o) for o in outputs]

    return launch
