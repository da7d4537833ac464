// Helpers shared by the CPU MLX primitives: threads, vector lanes, output allocation, shape strings.
#pragma once

#include <algorithm>
#include <atomic>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <new>
#include <sstream>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

#if defined(__linux__)
#include <sys/mman.h>
#endif

#include "mlx/allocator.h"
#include "mlx/array.h"
#include "mlx/backend/cpu/encoder.h"
#include "mlx/primitives.h"

// x86-64 with GCC on Linux: a function so marked is also compiled for AVX2 and picked at load time
// (ifunc). Each output element is the same sequence of float operations (no FMA contraction without
// -mfma), so the results do not depend on the variant.
// MLX3D_FMA_CLONES: the same with an FMA variant, for code that calls std::fma itself (MLX's scalar
// exp): there it is one instruction instead of a call into libm, with the same, exactly rounded result.
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__) && defined(__linux__)
#define MLX3D_AVX2_CLONES __attribute__((target_clones("avx2", "default")))
#define MLX3D_FMA_CLONES __attribute__((target_clones("fma", "default")))
#else
#define MLX3D_AVX2_CLONES
#define MLX3D_FMA_CLONES
#endif

#if defined(__GNUC__) && !defined(__clang__) && !defined(MLX3D_SCALAR_LANES)
// Lane values only cross always-inlined functions, so GCC's note that passing AVX vectors by value
// changes the calling convention does not apply.
#pragma GCC diagnostic ignored "-Wpsabi"
#define MLX3D_VECTOR_LANES 1
#endif

namespace mlx3d {

// Lanes: elements computed together by the per-Gaussian kernels (sh_color.cpp, projection.cpp), one
// per lane of a GCC vector of floats: 8, one AVX register in the MLX3D_AVX2_CLONES variant and two SSE
// registers otherwise; one float with other compilers (as the rasterizer's lanes, rasterize.cpp) or
// with -DMLX3D_SCALAR_LANES. Each lane runs the float operations of one element alone, so the results
// do not depend on the batching.
#if defined(MLX3D_VECTOR_LANES)
constexpr int kLanes = 8;
typedef float Lanes __attribute__((vector_size(4 * kLanes)));
#define MLX3D_LANES_INLINE inline __attribute__((always_inline))
#else
constexpr int kLanes = 1;
typedef float Lanes;
#define MLX3D_LANES_INLINE inline
#endif

// kLanes floats from p (any alignment) as lanes, and back.
MLX3D_LANES_INLINE Lanes lanes_at(const float* p) {
  Lanes v;
  std::memcpy(&v, p, sizeof(v));
  return v;
}

MLX3D_LANES_INLINE void put_lanes(float* p, Lanes v) { std::memcpy(p, &v, sizeof(v)); }

// Threads to use for `work_items` items: num_threads (0: all hardware threads), at most one per item.
inline int resolve_threads(int num_threads, int work_items) {
  int threads = num_threads > 0 ? num_threads : static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
  return std::max(1, std::min(threads, work_items));
}

// Runs fn(item, thread id) for items [t0, t1) on `threads` threads, taking items from a shared counter.
template <typename Fn>
void parallel_items(int t0, int t1, int threads, Fn&& fn) {
  std::atomic<int> next(t0);
  auto worker = [&](int id) {
    for (int t = next.fetch_add(1); t < t1; t = next.fetch_add(1)) fn(t, id);
  };
  threads = std::max(1, std::min(threads, t1 - t0));
  std::vector<std::thread> pool;
  pool.reserve(threads - 1);
  for (int i = 1; i < threads; ++i) pool.emplace_back(worker, i);
  worker(0);
  for (auto& th : pool) th.join();
}

// How parallel_ranges cuts [0, n): `threads` contiguous ranges of `step` items (the last ones shorter,
// possibly empty). index(lo) is the thread whose non-empty range starts at lo.
struct RangeSplit {
  int threads;
  int64_t step;
  int index(int64_t lo) const { return step ? static_cast<int>(lo / step) : 0; }
};

inline RangeSplit split_ranges(int64_t n, int num_threads, int64_t min_per_thread) {
  const int threads = resolve_threads(num_threads, static_cast<int>(std::max<int64_t>(1, (n + min_per_thread - 1) / min_per_thread)));
  return {threads, (n + threads - 1) / threads};
}

// Runs fn(lo, hi) on contiguous ranges covering [0, n), one per thread (num_threads, 0: all hardware
// threads, at most one per min_per_thread items), each thread with its own copy of fn (capture by
// value): for per-element work. Sharing the callable's captures between threads through
// references, as parallel_items does, measured 1.5x slower per thread here than one thread alone on the
// SH and projection kernels; copies scale.
template <typename Fn>
void parallel_ranges(int64_t n, int num_threads, int64_t min_per_thread, const Fn& fn) {
  const RangeSplit split = split_ranges(n, num_threads, min_per_thread);
  const int threads = split.threads;
  const int64_t step = split.step;
  std::vector<std::thread> pool;
  pool.reserve(threads - 1);
  for (int t = 1; t < threads; ++t) pool.emplace_back(fn, std::min(n, t * step), std::min(n, (t + 1) * step));
  Fn own = fn;
  own(int64_t(0), std::min(n, step));
  for (auto& th : pool) th.join();
}

// An uninitialised array of n T, on 2 MB pages where the OS offers them (Linux transparent huge
// pages): for per-Gaussian buffers that kernels read and update in random order, where 4 KB pages
// would miss the TLB on nearly every access. Freed on scope exit.
template <class T>
class HugePageArray {
 public:
  explicit HugePageArray(size_t n) {
    constexpr size_t kHuge = size_t(2) << 20;
    const size_t bytes = std::max<size_t>(n, 1) * sizeof(T);
    const size_t align = bytes >= kHuge ? kHuge : 64;  // a cache line at least (T may ask for it)
    static_assert(alignof(T) <= 64, "HugePageArray aligns to 64 bytes");
    const size_t rounded = (bytes + align - 1) / align * align;
    void* p = std::aligned_alloc(align, rounded);
    if (!p) throw std::bad_alloc();
#if defined(__linux__) && defined(MADV_HUGEPAGE)
    if (bytes >= kHuge) madvise(p, rounded, MADV_HUGEPAGE);  // advice only: 4 KB pages if refused
#endif
    data_.reset(static_cast<T*>(p));
  }
  T* data() { return data_.get(); }
  const T* data() const { return data_.get(); }
  T& operator[](size_t i) { return data_.get()[i]; }
  const T& operator[](size_t i) const { return data_.get()[i]; }
  // Gives up ownership: free the pointer with std::free.
  T* release() { return data_.release(); }

 private:
  struct Free {
    void operator()(T* p) const { std::free(p); }
  };
  std::unique_ptr<T, Free> data_;
};

// Uninitialised float scratch from MLX's buffer cache, returned to it on scope exit: reused across
// evaluations, so a kernel's temporaries cost neither fresh pages (faults) nor zeroing per call.
class ScratchFloats {
 public:
  explicit ScratchFloats(size_t n) : data_(mlx::core::allocator::malloc(std::max<size_t>(n, 1) * sizeof(float))) {}
  float* data() { return static_cast<float*>(data_.buffer().raw_ptr()); }

 private:
  mlx::core::allocator::Data data_;
};

// Checks that every input is row-contiguous (the ops make them so before building a primitive, and the
// kernels index them as plain arrays) and registers every array, outputs given their buffers, with the
// primitive's CPU command encoder, which it returns.
inline mlx::core::cpu::CommandEncoder& register_arrays(mlx::core::Primitive& primitive, const std::vector<mlx::core::array>& inputs,
                                                       std::vector<mlx::core::array>& outputs) {
  for (const auto& a : inputs)
    if (!a.flags().row_contiguous) throw std::runtime_error(std::string(primitive.name()) + ": internal error: non-contiguous input");
  auto& encoder = mlx::core::cpu::get_command_encoder(primitive.stream());
  for (const auto& a : inputs) encoder.set_input_array(a);
  for (auto& o : outputs) encoder.set_output_array(o);
  return encoder;
}

// register_arrays, with a fresh buffer for every output.
inline mlx::core::cpu::CommandEncoder& prepare_outputs(mlx::core::Primitive& primitive, const std::vector<mlx::core::array>& inputs,
                                                       std::vector<mlx::core::array>& outputs) {
  for (auto& o : outputs) o.set_data(mlx::core::allocator::malloc(o.nbytes()));
  return register_arrays(primitive, inputs, outputs);
}

// Base of the CPU-only primitives: GPU evaluation, forward-mode differentiation and vmap are refused
// with the primitive's name. `gpu_hint` says what Apple GPUs run instead.
class CpuPrimitive : public mlx::core::Primitive {
 public:
  CpuPrimitive(mlx::core::Stream stream, const char* gpu_hint) : mlx::core::Primitive(stream), gpu_hint_(gpu_hint) {}

  void eval_gpu(const std::vector<mlx::core::array>&, std::vector<mlx::core::array>&) override {
    throw std::runtime_error(std::string(name()) + " runs on the CPU only (" + gpu_hint_ + ").");
  }

  std::vector<mlx::core::array> jvp(const std::vector<mlx::core::array>&, const std::vector<mlx::core::array>&,
                                    const std::vector<int>&) override {
    throw std::runtime_error(std::string(name()) + ": forward-mode differentiation (jvp) is not implemented; use mx.grad / mx.vjp.");
  }

  std::pair<std::vector<mlx::core::array>, std::vector<int>> vmap(const std::vector<mlx::core::array>&,
                                                                  const std::vector<int>&) override {
    throw std::runtime_error(std::string(name()) + ": vmap is not implemented.");
  }

 private:
  const char* gpu_hint_;
};

// "(2, 3)" for a 2x3 array, "(5,)" for a vector.
inline std::string shape_str(const mlx::core::array& a) {
  std::ostringstream os;
  os << "(";
  for (int i = 0; i < static_cast<int>(a.ndim()); ++i) os << (i ? ", " : "") << a.shape(i);
  if (a.ndim() == 1) os << ",";
  os << ")";
  return os.str();
}

}  // namespace mlx3d
