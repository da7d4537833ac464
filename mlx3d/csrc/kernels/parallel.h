// What the CPU kernels share, free of MLX and Python (the kernel library's and mlx3d._core's): vector
// lanes, the worker threads and the ways work is cut between them, and page-aligned scratch arrays.
#pragma once

#include <algorithm>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdlib>
#include <cstring>
#include <exception>
#include <functional>
#include <memory>
#include <mutex>
#include <new>
#include <sstream>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

#if defined(__unix__) || defined(__APPLE__)
#include <pthread.h>
#endif
#if defined(__x86_64__) || defined(__i386__)
#include <immintrin.h>
#endif

#if defined(__linux__)
#include <sys/mman.h>
#endif
#if defined(_WIN32)
#include <malloc.h>
#endif

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

#if defined(__GNUC__) && !defined(MLX3D_SCALAR_LANES)
// Lane values only cross always-inlined functions, so GCC's note that passing AVX vectors by value
// changes the calling convention does not apply.
#pragma GCC diagnostic ignored "-Wpsabi"
#define MLX3D_VECTOR_LANES 1
#endif

namespace mlx3d {

// Lanes: elements computed together by the per-Gaussian kernels (sh_color.cpp, projection.cpp), one
// per lane of a GCC vector of floats (GCC and clang): 8, one AVX register in the MLX3D_AVX2_CLONES
// variant (GCC) and two SSE or NEON registers otherwise; one float with other compilers (MSVC; as the
// rasterizer's lanes, rasterize.cpp) or with -DMLX3D_SCALAR_LANES. Each lane runs the float operations
// of one element alone, so the results do not depend on the batching.
#if defined(MLX3D_VECTOR_LANES)
constexpr int kLanes = 8;
typedef float Lanes __attribute__((vector_size(4 * kLanes)));
#define MLX3D_LANES_INLINE inline __attribute__((always_inline))
#else
constexpr int kLanes = 1;
typedef float Lanes;
#define MLX3D_LANES_INLINE inline
#endif

// kLanes floats from p (any alignment) as lanes, and back; with F = float, one float (for the tails of
// lane loops written once for both).
template <class F = Lanes>
MLX3D_LANES_INLINE F lanes_at(const float* p) {
  F v;
  std::memcpy(&v, p, sizeof(v));
  return v;
}

template <class F>
MLX3D_LANES_INLINE void put_lanes(float* p, F v) {
  std::memcpy(p, &v, sizeof(v));
}

// Threads to use for `work_items` items: num_threads (0: all hardware threads), at most one per item.
inline int resolve_threads(int num_threads, int work_items) {
  int threads = num_threads > 0 ? num_threads : static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
  return std::max(1, std::min(threads, work_items));
}

// A spin-wait hint to the core (lets the other hardware thread run).
inline void cpu_relax() {
#if defined(__x86_64__) || defined(__i386__)
  _mm_pause();
#elif defined(__aarch64__)
  asm volatile("yield");
#endif
}

// Worker threads kept for the whole process, which run the kernels' threaded passes. Starting a
// std::thread per pass cost its clone on the calling thread and left the caller working alone until the
// new thread ran: a training step runs about 64 passes. A worker waits for the next job spinning for a
// while (50 us), then sleeps on a condition variable. One job at a time: a concurrent or nested
// call gets false from run() and starts its own threads. A forked child gets a fresh pool (the parent's
// workers do not exist there).
class WorkerPool {
 public:
  static WorkerPool& instance() {
    static std::once_flag once;
    std::call_once(once, [] {
      current() = new WorkerPool();  // never deleted: parked workers end with the process
#if defined(__unix__) || defined(__APPLE__)
      pthread_atfork(nullptr, nullptr, [] { current() = new WorkerPool(); });
#endif
    });
    return *current();
  }

  // Runs task(i) for i in [0, n): 0 on the calling thread, the others on workers; returns when all are
  // done (an exception from task(0) is rethrown after them). False, with nothing run, while the pool is
  // running another job.
  bool run(int n, const std::function<void(int)>& task) {
    std::unique_lock<std::mutex> busy(busy_, std::try_to_lock);
    if (!busy.owns_lock()) return false;
    for (; workers_ < n - 1; ++workers_) std::thread([this, index = workers_ + 1] { work(index); }).detach();
    task_.store(&task, std::memory_order_relaxed);
    remaining_.store(n - 1, std::memory_order_relaxed);
    {
      std::lock_guard<std::mutex> lock(wake_mutex_);
      const uint64_t next = (job_.load(std::memory_order_relaxed) >> 32) + 1;
      job_.store(next << 32 | static_cast<uint32_t>(n), std::memory_order_release);
    }
    wake_.notify_all();
    std::exception_ptr error;
    try {
      task(0);
    } catch (...) {
      error = std::current_exception();
    }
    for (Spin spin; remaining_.load(std::memory_order_acquire) > 0;)
      if (!spin.more()) std::this_thread::yield();
    if (error) std::rethrow_exception(error);
    return true;
  }

 private:
  // A spin-wait of at most kSpin: more() pauses the core briefly while it lasts.
  struct Spin {
    static constexpr std::chrono::microseconds kSpin{50};
    std::chrono::steady_clock::time_point end = std::chrono::steady_clock::now() + kSpin;
    int count = 0;
    bool more() {
      cpu_relax();
      return (++count & 63) != 0 || std::chrono::steady_clock::now() < end;
    }
  };

  static WorkerPool*& current() {
    static WorkerPool* pool = nullptr;
    return pool;
  }

  // Worker `index` (>= 1): runs its task of each job with more than `index` threads. A job is its number
  // and thread count in one word (job_), so a worker never pairs one job's number with another's count.
  void work(int index) {
    uint64_t seen = 0;  // the last job number handled
    for (;;) {
      uint64_t job = job_.load(std::memory_order_acquire);
      for (Spin spin; job >> 32 == seen && spin.more();) job = job_.load(std::memory_order_acquire);
      if (job >> 32 == seen) {
        std::unique_lock<std::mutex> lock(wake_mutex_);
        wake_.wait(lock, [&] { return job_.load(std::memory_order_acquire) >> 32 != seen; });
        job = job_.load(std::memory_order_acquire);
      }
      seen = job >> 32;
      if (index < static_cast<int>(job & 0xffffffffu)) {
        (*task_.load(std::memory_order_relaxed))(index);
        remaining_.fetch_sub(1, std::memory_order_release);
      }
    }
  }

  std::mutex busy_;  // held by run() for a whole job
  std::mutex wake_mutex_;
  std::condition_variable wake_;
  std::atomic<uint64_t> job_{0};  // job number << 32 | its thread count
  std::atomic<int> remaining_{0};  // workers' tasks of the current job not yet done
  std::atomic<const std::function<void(int)>*> task_{nullptr};
  int workers_ = 0;  // started (detached; they run for the process's life), indices 1 .. workers_
};

// Runs task(i) for i in [0, n) at once, one thread each (the caller runs i = 0): on the worker pool, or
// on threads started for this call while the pool is busy.
inline void run_threads(int n, const std::function<void(int)>& task) {
  if (n <= 1) {
    task(0);
    return;
  }
  if (WorkerPool::instance().run(n, task)) return;
  std::vector<std::thread> pool;
  pool.reserve(n - 1);
  for (int i = 1; i < n; ++i) pool.emplace_back(task, i);
  task(0);
  for (auto& th : pool) th.join();
}

// Runs fn(item, thread id) for items [t0, t1) on `threads` threads, taking items from a shared counter.
template <typename Fn>
void parallel_items(int t0, int t1, int threads, Fn&& fn) {
  std::atomic<int> next(t0);
  threads = std::max(1, std::min(threads, t1 - t0));
  run_threads(threads, [&](int id) {
    for (int t = next.fetch_add(1); t < t1; t = next.fetch_add(1)) fn(t, id);
  });
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
  const int64_t step = split.step;
  run_threads(split.threads, [&](int t) {
    Fn own = fn;
    own(std::min(n, t * step), std::min(n, (t + 1) * step));
  });
}

// Runs fn(lo, hi) on blocks covering [0, n), each thread with its own copy of fn: for per-element work
// where which thread does an element does not matter. Each thread works through its own contiguous range
// (as parallel_ranges) a block at a time, then helps with the others' remaining blocks. With fixed
// ranges alone, a thread that started late (a pool worker woken from its sleep) or got the costlier
// elements (culled Gaussians cost little) left the other core idle at the end of each pass; blocks dealt
// out in turn from one counter instead measured slower (both threads then touch the pages of the same
// fresh output together). Blocks hold a multiple of 64 elements, about 8 per range.
template <typename Fn>
void parallel_blocks(int64_t n, int num_threads, int64_t min_per_thread, const Fn& fn) {
  const RangeSplit split = split_ranges(n, num_threads, min_per_thread);
  const int threads = split.threads;
  if (threads <= 1) {
    if (n > 0) fn(0, n);
    return;
  }
  constexpr int64_t kBlocksPerRange = 8;
  const int64_t block = ((split.step + kBlocksPerRange - 1) / kBlocksPerRange + 63) / 64 * 64;
  std::unique_ptr<std::atomic<int64_t>[]> next(new std::atomic<int64_t>[threads]);  // each range's next block
  for (int t = 0; t < threads; ++t) next[t].store(t * split.step, std::memory_order_relaxed);
  run_threads(threads, [&](int id) {
    Fn own = fn;
    for (int k = 0; k < threads; ++k) {
      const int t = (id + k) % threads;
      const int64_t end = std::min(n, (t + 1) * split.step);
      for (int64_t lo = next[t].fetch_add(block, std::memory_order_relaxed); lo < end; lo = next[t].fetch_add(block, std::memory_order_relaxed))
        own(lo, std::min(end, lo + block));
    }
  });
}

// `bytes` (a multiple of `align`, a power of two) aligned to `align`; nullptr when out of memory. Free
// with aligned_free (Windows' C runtime has no std::aligned_alloc, and its blocks need their own free).
inline void* aligned_malloc(size_t align, size_t bytes) {
#if defined(_WIN32)
  return _aligned_malloc(bytes, align);
#else
  return std::aligned_alloc(align, bytes);
#endif
}

inline void aligned_free(void* p) {
#if defined(_WIN32)
  _aligned_free(p);
#else
  std::free(p);
#endif
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
    void* p = aligned_malloc(align, rounded);
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
  // Gives up ownership: free the pointer with aligned_free.
  T* release() { return data_.release(); }

 private:
  struct Free {
    void operator()(T* p) const { aligned_free(p); }
  };
  std::unique_ptr<T, Free> data_;
};

}  // namespace mlx3d
