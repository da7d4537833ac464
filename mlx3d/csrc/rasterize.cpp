// The 3DGS tile rasterizer as MLX primitives on the CPU: RasterizeForward
// (composite) and RasterizeBackward (its vector-Jacobian product), both
// threaded over tiles. The per-pixel math lives in raster_math.h, which the
// Metal kernels (mlx3d/render/raster_metal.py) compile too.
//
// Inputs (row-contiguous; the op below makes them so):
//   means2d (N,2) f32, conics (N,3) f32 (a, b, c of [[a,b],[b,c]]), features (N,C) f32,
//   opacities (N,) f32, tile_offsets (T+1,) i32, flatten_ids (M,) i32
// Outputs of RasterizeForward:
//   accum (H,W,C) f32 (no background), alpha (H,W) f32 = 1 - T_final,
//   last (H,W) i32, final_T (H,W) f32 (T_final, kept for the backward pass).
// `last` is 3DGS's n_contrib: 1 + the position, inside the pixel's tile range,
// of the last Gaussian that contributed (0 when none did). The backward pass
// walks entries [0, last) of the tile range back to front.
//
// Work layout. Each thread takes the next tile from an atomic counter. A tile
// first gathers its Gaussians into contiguous arrays (entries with an id
// outside [0, N) get opacity 0 and are skipped), then processes its pixels in
// blocks of one SIMD vector of pixels (8 with AVX2, 4 with SSE2/NEON, see
// "variants" below), row-major: the Gaussian loop is outside, each step runs
// the per-pixel math on all lanes at once, and a block stops when all of its
// pixels have stopped. Forward results do not depend on the vector width:
// each lane runs exactly the scalar per-pixel recurrence.
//
// Determinism of the backward pass. Gradients are first accumulated per
// *tile entry* (one slot per flatten_ids position) by the single thread that
// owns the tile, in a fixed order (pixel blocks in order; lanes summed
// in lane order at the end of the tile). The per-Gaussian gradients are then the
// sums of their entries' slots in flatten_ids order, done sequentially. No
// floating-point sum depends on the thread count or on scheduling, so 1 and
// many threads give bitwise-identical results. Tiles are processed in chunks
// of consecutive tiles to bound the slot buffer (same summation order).
#include <nanobind/nanobind.h>
#include <nanobind/stl/vector.h>

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <sstream>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

#include "bindings.h"
#include "mlx/allocator.h"
#include "mlx/array.h"
#include "mlx/backend/cpu/encoder.h"
#include "mlx/ops.h"
#include "mlx/primitives.h"
#include "mlx/stream.h"

// Lane types: the tile kernels run several pixels at once, one per lane. With
// GCC they are vectors of floats / int32 (GCC vector extensions): 8 lanes in
// the AVX2 variant (x86-64, picked at run time), 4 otherwise (SSE2, NEON);
// other compilers (or -DMLX3D_RASTER_SCALAR_LANES) get one pixel per lane.
// Each lane runs exactly the scalar per-pixel recurrence, so forward results
// do not depend on the lane width. The rm_* templates of raster_math.h are
// instantiated with the lane type; comparisons give lane masks (-1 / 0 per
// lane; bool for scalar lanes) and `?:` selects per lane.
#if defined(__GNUC__) && !defined(__clang__) && !defined(MLX3D_RASTER_SCALAR_LANES)
#define MLX3D_RASTER_VECTOR_LANES 1
#pragma GCC diagnostic ignored "-Wpsabi"
typedef float LaneF4 __attribute__((vector_size(16)));
typedef int32_t LaneI4 __attribute__((vector_size(16)));
typedef float LaneF8 __attribute__((vector_size(32)));
typedef int32_t LaneI8 __attribute__((vector_size(32)));
// 2^n for integral-valued lanes n in [-126, 127] (used by rm_exp).
inline __attribute__((always_inline)) LaneF4 rm_pow2i(LaneF4 n) {
  LaneI4 bits = (__builtin_convertvector(n, LaneI4) + 127) << 23;
  return (LaneF4)bits;
}
inline __attribute__((always_inline)) LaneF8 rm_pow2i(LaneF8 n) {
  LaneI8 bits = (__builtin_convertvector(n, LaneI8) + 127) << 23;
  return (LaneF8)bits;
}
#if defined(__x86_64__) && defined(__ELF__)
#define MLX3D_RASTER_AVX2 1
#endif
#endif
#include "raster_math.h"

namespace nb = nanobind;
namespace mx = mlx::core;
using namespace nb::literals;

namespace mlx3d {
namespace {

constexpr int kGradFixed = 6;  // mean_x, mean_y, conic_a, conic_b, conic_c, opacity

// Helpers used inside the tile kernels are always inlined (see RM_INLINE), so
// that they are compiled for the instruction set of the kernel variant.
template <class V>
constexpr int lanes_of() {
  return static_cast<int>(sizeof(V) / sizeof(float));
}
template <class V>
RM_INLINE V load_lanes(const void* p) {
  V v;
  std::memcpy(&v, p, sizeof(V));
  return v;
}
template <class V>
RM_INLINE void store_lanes(void* p, const V& v) {
  std::memcpy(p, &v, sizeof(V));
}
template <class LI>
RM_INLINE bool any_lane(const LI& m) {
  int32_t a[lanes_of<LI>()];
  store_lanes(a, m);
  int32_t any = 0;
  for (int l = 0; l < lanes_of<LI>(); ++l) any |= a[l];
  return any != 0;
}

struct Geometry {
  int width = 0, height = 0, tile = 16, tiles_x = 0, tiles_y = 0, channels = 1;
  int64_t num_gaussians = 0, num_entries = 0;
  int num_tiles() const { return tiles_x * tiles_y; }
};

Geometry make_geometry(int width, int height, int tile, int64_t n, int channels, int64_t m) {
  Geometry g;
  g.width = width;
  g.height = height;
  g.tile = tile;
  g.tiles_x = (width + tile - 1) / tile;
  g.tiles_y = (height + tile - 1) / tile;
  g.channels = channels;
  g.num_gaussians = n;
  g.num_entries = m;
  return g;
}

struct Inputs {
  const float* means = nullptr;
  const float* conics = nullptr;
  const float* features = nullptr;
  const float* opacities = nullptr;
  const int32_t* offsets = nullptr;
  const int32_t* ids = nullptr;
  const int64_t* ranges = nullptr;  // sanitised tile_offsets (see sanitise_offsets)
};

// tile_offsets clamped to [0, M] and made non-decreasing, so that tile ranges
// never overlap or leave the entry array whatever the input holds (the Python
// wrapper rejects such inputs; this only keeps the kernels memory-safe).
std::vector<int64_t> sanitise_offsets(const int32_t* offsets, const Geometry& geo) {
  std::vector<int64_t> r(static_cast<size_t>(geo.num_tiles()) + 1);
  int64_t prev = 0;
  for (size_t t = 0; t < r.size(); ++t) {
    prev = std::min<int64_t>(std::max<int64_t>(offsets[t], prev), geo.num_entries);
    r[t] = prev;
  }
  return r;
}

// Entries [lo, hi) of tile t.
inline void tile_range(const Inputs& in, const Geometry&, int t, int64_t& lo, int64_t& hi) {
  lo = in.ranges[t];
  hi = in.ranges[t + 1];
}

// Per-thread scratch: the tile's Gaussians gathered contiguously, and lane buffers.
struct Scratch {
  std::vector<float> x, y, a, b, c, op, feat;  // gathered, one row per tile entry
  std::vector<float> lane;                      // per-channel lane state
  std::vector<float> entry_lanes;               // backward: per-entry, per-field lane sums

  // `count` zeroed lane vectors in `buf`, 32-byte aligned. (alignof of a
  // 32-byte vector type is 16 outside AVX code, so std::vector<LF> would not do.)
  template <class LF>
  static LF* lanes(std::vector<float>& buf, size_t count) {
    constexpr size_t kAlign = 32;
    buf.assign(count * lanes_of<LF>() + kAlign / sizeof(float), 0.0f);
    const uintptr_t p = reinterpret_cast<uintptr_t>(buf.data());
    return reinterpret_cast<LF*>((p + kAlign - 1) / kAlign * kAlign);
  }

  void gather(const Inputs& in, const Geometry& geo, int64_t lo, int64_t hi) {
    const int64_t n = hi - lo;
    const int C = geo.channels;
    x.resize(n), y.resize(n), a.resize(n), b.resize(n), c.resize(n), op.resize(n);
    feat.resize(static_cast<size_t>(n) * C);
    for (int64_t j = 0; j < n; ++j) {
      const int64_t g = in.ids[lo + j];
      if (g < 0 || g >= geo.num_gaussians) {
        x[j] = y[j] = a[j] = b[j] = c[j] = op[j] = 0.0f;
        std::fill_n(&feat[j * C], C, 0.0f);
        continue;
      }
      x[j] = in.means[2 * g];
      y[j] = in.means[2 * g + 1];
      a[j] = in.conics[3 * g];
      b[j] = in.conics[3 * g + 1];
      c[j] = in.conics[3 * g + 2];
      op[j] = in.opacities[g];
      std::memcpy(&feat[j * C], &in.features[g * C], sizeof(float) * C);
    }
  }
};

struct TileBox {
  int x0, y0, w, h;
};

inline TileBox tile_box(const Geometry& geo, int t) {
  TileBox box;
  box.x0 = (t % geo.tiles_x) * geo.tile;
  box.y0 = (t / geo.tiles_x) * geo.tile;
  box.w = std::min(geo.tile, geo.width - box.x0);
  box.h = std::min(geo.tile, geo.height - box.y0);
  return box;
}

struct ForwardOut {
  float* accum;
  float* alpha;
  int32_t* last;
  float* final_T;
};

// Pixel centres of block q0 (kLanes pixels, row-major in the tile) and which
// lanes are inside the image tile (a mask: nonzero = valid).
template <class LF, class LI>
RM_INLINE void block_pixels(const TileBox& box, int q0, LF& px, LF& py, LI& valid, int64_t* pix, const Geometry& geo) {
  constexpr int kLanes = lanes_of<LF>();
  float fx[kLanes], fy[kLanes];
  int32_t v[kLanes];
  const int npix = box.w * box.h;
  for (int l = 0; l < kLanes; ++l) {
    const int q = q0 + l;
    const bool in = q < npix;
    const int qx = in ? q % box.w : 0, qy = in ? q / box.w : 0;
    fx[l] = static_cast<float>(box.x0 + qx) + 0.5f;
    fy[l] = static_cast<float>(box.y0 + qy) + 0.5f;
    v[l] = in ? -1 : 0;
    pix[l] = in ? static_cast<int64_t>(box.y0 + qy) * geo.width + (box.x0 + qx) : -1;
  }
  px = load_lanes<LF>(fx);
  py = load_lanes<LF>(fy);
  valid = load_lanes<LI>(v);
}

template <class LF, class LI>
RM_INLINE void forward_tile_impl(const Inputs& in, const Geometry& geo, int t, Scratch& s, const ForwardOut& out) {
  constexpr int kLanes = lanes_of<LF>();
  int64_t lo, hi;
  tile_range(in, geo, t, lo, hi);
  const int n = static_cast<int>(hi - lo);
  s.gather(in, geo, lo, hi);
  const int C = geo.channels;
  const TileBox box = tile_box(geo, t);
  const int npix = box.w * box.h;
  LF* acc = Scratch::lanes<LF>(s.lane, C);  // per channel
  const LF zero{};
  const LI izero{};

  for (int q0 = 0; q0 < npix; q0 += kLanes) {
    LF px, py;
    LI active;
    int64_t pix[kLanes];
    block_pixels(box, q0, px, py, active, pix, geo);
    LF T = zero + 1.0f;
    LI nlast = izero;
    for (int ch = 0; ch < C; ++ch) acc[ch] = zero;
    for (int k = 0; k < n; ++k) {
      const LF dx = s.x[k] - px;
      const LF dy = s.y[k] - py;
      const LF power = rm_power(zero + s.a[k], zero + s.b[k], zero + s.c[k], dx, dy);
      const LF g = rm_exp(power);
      const LF alpha = rm_alpha(zero + s.op[k], g, power);
      const LF next_T = rm_next_T(T, alpha);
      const LI goes_on = (next_T < RM_T_MIN) == 0;  // a skipped Gaussian keeps T >= RM_T_MIN
      const LI use = active & (alpha > 0.0f) & goes_on;
      const LF w = use ? alpha * T : 0.0f;
      T = use ? next_T : T;
      nlast = use ? izero + (k + 1) : nlast;
      active = active & goes_on;
      const float* f = &s.feat[static_cast<size_t>(k) * C];
      for (int ch = 0; ch < C; ++ch) acc[ch] = use ? acc[ch] + f[ch] * w : acc[ch];
      if (!any_lane(active)) break;
    }
    float Ta[kLanes], ca[kLanes];
    int32_t la[kLanes];
    store_lanes(Ta, T);
    store_lanes(la, nlast);
    for (int l = 0; l < kLanes; ++l) {
      if (pix[l] < 0) continue;
      out.alpha[pix[l]] = 1.0f - Ta[l];
      out.last[pix[l]] = la[l];
      out.final_T[pix[l]] = Ta[l];
    }
    for (int ch = 0; ch < C; ++ch) {
      store_lanes(ca, acc[ch]);
      for (int l = 0; l < kLanes; ++l)
        if (pix[l] >= 0) out.accum[pix[l] * C + ch] = ca[l];
    }
  }
}

struct BackwardIn {
  const int32_t* last;
  const float* final_T;
  const float* g_accum;
  const float* g_alpha;
};

// Accumulates the tile's gradients into entry_grad[(e - lo) * K + field]
// (K = 6 + C fields: mean_x, mean_y, conic a, b, c, opacity, features), which
// the caller zeroed.
template <class LF, class LI>
RM_INLINE void backward_tile_impl(const Inputs& in, const Geometry& geo, int t, Scratch& s, const BackwardIn& bw,
                                  float* entry_grad) {
  constexpr int kLanes = lanes_of<LF>();
  int64_t lo, hi;
  tile_range(in, geo, t, lo, hi);
  const int n = static_cast<int>(hi - lo);
  if (n == 0) return;
  s.gather(in, geo, lo, hi);
  const int C = geo.channels;
  const int K = kGradFixed + C;
  const TileBox box = tile_box(geo, t);
  const int npix = box.w * box.h;
  const LF zero{};
  const LI izero{};
  LF* behind = Scratch::lanes<LF>(s.lane, static_cast<size_t>(3) * C);  // per channel
  LF* prev_feat = behind + C;  // feature of the kept Gaussian behind
  LF* gacc = prev_feat + C;    // dL/daccum of the lanes' pixels
  LF* sums = Scratch::lanes<LF>(s.entry_lanes, static_cast<size_t>(n) * K);  // [entry][field]

  for (int q0 = 0; q0 < npix; q0 += kLanes) {
    LF px, py;
    LI valid;
    int64_t pix[kLanes];
    block_pixels(box, q0, px, py, valid, pix, geo);
    float tf[kLanes], ga[kLanes], gc[kLanes];
    int32_t nl[kLanes];
    int kmax = 0;
    for (int l = 0; l < kLanes; ++l) {
      const bool ok = pix[l] >= 0;
      nl[l] = ok ? std::min(std::max(static_cast<int>(bw.last[pix[l]]), 0), n) : 0;
      tf[l] = ok ? bw.final_T[pix[l]] : 1.0f;
      ga[l] = ok ? bw.g_alpha[pix[l]] : 0.0f;
      kmax = std::max(kmax, static_cast<int>(nl[l]));
    }
    for (int ch = 0; ch < C; ++ch) {
      for (int l = 0; l < kLanes; ++l) gc[l] = pix[l] >= 0 ? bw.g_accum[pix[l] * C + ch] : 0.0f;
      gacc[ch] = load_lanes<LF>(gc);
      behind[ch] = zero;
      prev_feat[ch] = zero;
    }
    const LI nlast = load_lanes<LI>(nl);
    const LF T_final = load_lanes<LF>(tf);
    const LF g_alpha = load_lanes<LF>(ga);
    LF T = T_final;
    LF prev_alpha = zero;
    for (int k = kmax - 1; k >= 0; --k) {
      const LF ca = zero + s.a[k], cb = zero + s.b[k], cc = zero + s.c[k], o = zero + s.op[k];
      const LF dx = s.x[k] - px;
      const LF dy = s.y[k] - py;
      const LF power = rm_power(ca, cb, cc, dx, dy);
      const LF g = rm_exp(power);
      const LF alpha_k = rm_alpha(o, g, power);
      const LI use = ((izero + k) < nlast) & (alpha_k > 0.0f);
      if (!any_lane(use)) continue;
      const LF alpha = use ? alpha_k : 0.0f;
      T = rm_T_before(T, alpha);  // unchanged (T / 1) where not used
      const LF w = alpha * T;
      const LF pa = prev_alpha;
      prev_alpha = use ? alpha : prev_alpha;
      LF* ek = sums + static_cast<size_t>(k) * K;
      const float* f = &s.feat[static_cast<size_t>(k) * C];
      LF dot = zero;
      for (int ch = 0; ch < C; ++ch) {
        const LF nb = rm_behind(behind[ch], pa, prev_feat[ch]);
        behind[ch] = use ? nb : behind[ch];
        dot += use ? (f[ch] - nb) * gacc[ch] : 0.0f;
        prev_feat[ch] = use ? zero + f[ch] : prev_feat[ch];
        ek[kGradFixed + ch] += use ? w * gacc[ch] : 0.0f;
      }
      const LF dl_dalpha = rm_dl_dalpha(T, dot, T_final, g_alpha, alpha);
      const RmGaussGrad<LF> gg = rm_gaussian_grad(ca, cb, cc, dx, dy, o, g, dl_dalpha);
      ek[0] += use ? gg.mean_x : 0.0f;
      ek[1] += use ? gg.mean_y : 0.0f;
      ek[2] += use ? gg.conic_a : 0.0f;
      ek[3] += use ? gg.conic_b : 0.0f;
      ek[4] += use ? gg.conic_c : 0.0f;
      ek[5] += use ? gg.opacity : 0.0f;
    }
  }
  // Lane sums in a fixed order.
  float v[kLanes];
  for (size_t j = 0; j < static_cast<size_t>(n) * K; ++j) {
    store_lanes(v, sums[j]);
    float total = 0.0f;
    for (int l = 0; l < kLanes; ++l) total += v[l];
    entry_grad[j] += total;
  }
}

// ------------------------------------------------------------- variants
// The tile kernels are compiled for the baseline ISA (4 lanes with GCC: SSE2
// on x86-64, NEON on arm64; 1 lane otherwise) and, on x86-64 with GCC, for
// AVX2 (8 lanes), picked at run time from the CPU. MLX3D_RASTER_ISA=baseline
// in the environment forces the baseline variant (read at each evaluation).
// Forward outputs are identical across variants; backward lane sums group
// pixels differently, so gradients may differ in the last bits.
using ForwardTileFn = void (*)(const Inputs&, const Geometry&, int, Scratch&, const ForwardOut&);
using BackwardTileFn = void (*)(const Inputs&, const Geometry&, int, Scratch&, const BackwardIn&, float*);

#if defined(MLX3D_RASTER_VECTOR_LANES)
using BaseF = LaneF4;
using BaseI = LaneI4;
#else
using BaseF = float;
using BaseI = int32_t;
#endif

void forward_tile_base(const Inputs& in, const Geometry& geo, int t, Scratch& s, const ForwardOut& out) {
  forward_tile_impl<BaseF, BaseI>(in, geo, t, s, out);
}
void backward_tile_base(const Inputs& in, const Geometry& geo, int t, Scratch& s, const BackwardIn& bw, float* eg) {
  backward_tile_impl<BaseF, BaseI>(in, geo, t, s, bw, eg);
}

#if defined(MLX3D_RASTER_AVX2)
__attribute__((target("avx2"))) void forward_tile_avx2(const Inputs& in, const Geometry& geo, int t, Scratch& s,
                                                       const ForwardOut& out) {
  forward_tile_impl<LaneF8, LaneI8>(in, geo, t, s, out);
}
__attribute__((target("avx2"))) void backward_tile_avx2(const Inputs& in, const Geometry& geo, int t, Scratch& s,
                                                        const BackwardIn& bw, float* eg) {
  backward_tile_impl<LaneF8, LaneI8>(in, geo, t, s, bw, eg);
}
#endif

bool use_avx2() {
#if defined(MLX3D_RASTER_AVX2)
  static const bool has_avx2 = [] {
    __builtin_cpu_init();
    return __builtin_cpu_supports("avx2") != 0;
  }();
  const char* isa = std::getenv("MLX3D_RASTER_ISA");
  return has_avx2 && !(isa && std::strcmp(isa, "baseline") == 0);
#else
  return false;
#endif
}

int simd_lanes() {
  return use_avx2() ? 8 : lanes_of<BaseF>();
}

ForwardTileFn pick_forward() {
#if defined(MLX3D_RASTER_AVX2)
  if (use_avx2()) return forward_tile_avx2;
#endif
  return forward_tile_base;
}

BackwardTileFn pick_backward() {
#if defined(MLX3D_RASTER_AVX2)
  if (use_avx2()) return backward_tile_avx2;
#endif
  return backward_tile_base;
}

int resolve_threads(int num_threads, int work_items) {
  int threads = num_threads > 0 ? num_threads : static_cast<int>(std::max(1u, std::thread::hardware_concurrency()));
  return std::max(1, std::min(threads, work_items));
}

// Runs fn(tile, scratch) for tiles [t0, t1) on `threads` threads, taking tiles
// from a shared counter.
template <typename Fn>
void parallel_tiles(int t0, int t1, int threads, std::vector<Scratch>& scratch, Fn&& fn) {
  std::atomic<int> next(t0);
  auto worker = [&](int id) {
    for (int t = next.fetch_add(1); t < t1; t = next.fetch_add(1)) fn(t, scratch[id]);
  };
  threads = std::max(1, std::min(threads, t1 - t0));
  std::vector<std::thread> pool;
  pool.reserve(threads - 1);
  for (int i = 1; i < threads; ++i) pool.emplace_back(worker, i);
  worker(0);
  for (auto& th : pool) th.join();
}

void run_forward(Inputs in, const Geometry& geo, int num_threads, const ForwardOut& out) {
  const std::vector<int64_t> ranges = sanitise_offsets(in.offsets, geo);
  in.ranges = ranges.data();
  const int tiles = geo.num_tiles();
  const int threads = resolve_threads(num_threads, tiles);
  std::vector<Scratch> scratch(threads);
  const ForwardTileFn forward_tile = pick_forward();
  parallel_tiles(0, tiles, threads, scratch,
                 [&](int t, Scratch& s) { forward_tile(in, geo, t, s, out); });
}

struct GradOut {
  float* means;
  float* conics;
  float* features;
  float* opacities;
};

void run_backward(Inputs in, const Geometry& geo, int num_threads, const BackwardIn& bw, const GradOut& out) {
  const int C = geo.channels;
  const int K = kGradFixed + C;
  const int64_t N = geo.num_gaussians;
  std::fill_n(out.means, N * 2, 0.0f);
  std::fill_n(out.conics, N * 3, 0.0f);
  std::fill_n(out.features, N * C, 0.0f);
  std::fill_n(out.opacities, N, 0.0f);
  const int tiles = geo.num_tiles();
  if (N == 0 || geo.num_entries == 0 || tiles == 0) return;
  const std::vector<int64_t> ranges = sanitise_offsets(in.offsets, geo);
  in.ranges = ranges.data();
  const int threads = resolve_threads(num_threads, tiles);
  std::vector<Scratch> scratch(threads);
  const BackwardTileFn backward_tile = pick_backward();
  // Chunks of consecutive tiles holding at most ~4M slot floats (or one tile).
  const int64_t budget = std::max<int64_t>(1, (int64_t(1) << 22) / K);
  std::vector<float> entry_grad;
  for (int t0 = 0; t0 < tiles;) {
    int t1 = t0 + 1;
    while (t1 < tiles && ranges[t1 + 1] - ranges[t0] <= budget) ++t1;
    const int64_t lo0 = ranges[t0], hi1 = ranges[t1];
    entry_grad.assign(static_cast<size_t>(hi1 - lo0) * K, 0.0f);
    parallel_tiles(t0, t1, threads, scratch, [&](int t, Scratch& s) {
      backward_tile(in, geo, t, s, bw, entry_grad.data() + (ranges[t] - lo0) * K);
    });
    // Per-Gaussian sums over its entries, in flatten_ids order.
    for (int64_t e = lo0; e < hi1; ++e) {
      const int64_t g = in.ids[e];
      if (g < 0 || g >= N) continue;
      const float* v = entry_grad.data() + (e - lo0) * K;
      out.means[2 * g] += v[0];
      out.means[2 * g + 1] += v[1];
      out.conics[3 * g] += v[2];
      out.conics[3 * g + 1] += v[3];
      out.conics[3 * g + 2] += v[4];
      out.opacities[g] += v[5];
      float* fo = out.features + g * C;
      for (int ch = 0; ch < C; ++ch) fo[ch] += v[kGradFixed + ch];
    }
    t0 = t1;
  }
}

// ------------------------------------------------------------------ checks

std::string shape_str(const mx::array& a) {
  std::ostringstream os;
  os << "(";
  for (int i = 0; i < static_cast<int>(a.ndim()); ++i) os << (i ? ", " : "") << a.shape(i);
  if (a.ndim() == 1) os << ",";
  os << ")";
  return os.str();
}

void check(bool ok, const std::string& msg) {
  if (!ok) throw std::invalid_argument("rasterize: " + msg);
}

Inputs input_pointers(const std::vector<mx::array>& inputs) {
  for (const auto& a : inputs)
    if (!a.flags().row_contiguous) throw std::runtime_error("rasterize: internal error: non-contiguous input");
  Inputs in;
  in.means = inputs[0].data<float>();
  in.conics = inputs[1].data<float>();
  in.features = inputs[2].data<float>();
  in.opacities = inputs[3].data<float>();
  in.offsets = inputs[4].data<int32_t>();
  in.ids = inputs[5].data<int32_t>();
  return in;
}

void allocate(mx::array& out) {
  out.set_data(mx::allocator::malloc(out.nbytes()));
}

// ---------------------------------------------------------------- primitives

class RasterizeBackward : public mx::Primitive {
 public:
  RasterizeBackward(mx::Stream stream, int width, int height, int tile, int num_threads)
      : mx::Primitive(stream), width_(width), height_(height), tile_(tile), num_threads_(num_threads) {}

  // inputs: means2d, conics, features, opacities, tile_offsets, flatten_ids,
  //         last, final_T, dL/daccum (H,W,C), dL/dalpha (H,W)
  // outputs: dL/dmeans2d, dL/dconics, dL/dfeatures, dL/dopacities
  void eval_cpu(const std::vector<mx::array>& inputs, std::vector<mx::array>& outputs) override {
    for (auto& o : outputs) allocate(o);
    auto& encoder = mx::cpu::get_command_encoder(stream());
    for (const auto& a : inputs) encoder.set_input_array(a);
    for (auto& o : outputs) encoder.set_output_array(o);
    Inputs in = input_pointers(inputs);
    for (int i = 6; i < 10; ++i)
      if (!inputs[i].flags().row_contiguous) throw std::runtime_error("rasterize: internal error: non-contiguous input");
    const Geometry geo = make_geometry(width_, height_, tile_, inputs[0].shape(0), inputs[2].shape(1), inputs[5].size());
    BackwardIn bw{inputs[6].data<int32_t>(), inputs[7].data<float>(), inputs[8].data<float>(), inputs[9].data<float>()};
    GradOut out{outputs[0].data<float>(), outputs[1].data<float>(), outputs[2].data<float>(), outputs[3].data<float>()};
    encoder.dispatch([in, geo, bw, out, threads = num_threads_]() { run_backward(in, geo, threads, bw, out); });
  }

  void eval_gpu(const std::vector<mx::array>&, std::vector<mx::array>&) override {
    throw std::runtime_error("RasterizeBackward runs on the CPU only; use mlx3d.render.raster_metal on Apple GPUs.");
  }

  std::vector<mx::array> vjp(const std::vector<mx::array>&, const std::vector<mx::array>&, const std::vector<int>&,
                             const std::vector<mx::array>&) override {
    throw std::runtime_error("RasterizeBackward: second-order gradients of the rasterizer are not implemented.");
  }

  std::vector<mx::array> jvp(const std::vector<mx::array>&, const std::vector<mx::array>&,
                             const std::vector<int>&) override {
    throw std::runtime_error("RasterizeBackward: forward-mode differentiation (jvp) is not implemented.");
  }

  std::pair<std::vector<mx::array>, std::vector<int>> vmap(const std::vector<mx::array>&,
                                                           const std::vector<int>&) override {
    throw std::runtime_error("RasterizeBackward: vmap is not implemented.");
  }

  std::vector<mx::Shape> output_shapes(const std::vector<mx::array>& inputs) override {
    return {inputs[0].shape(), inputs[1].shape(), inputs[2].shape(), inputs[3].shape()};
  }

  const char* name() const override { return "RasterizeBackward"; }

  bool is_equivalent(const mx::Primitive& other) const override {
    const auto* o = dynamic_cast<const RasterizeBackward*>(&other);
    return o && o->width_ == width_ && o->height_ == height_ && o->tile_ == tile_ && o->num_threads_ == num_threads_;
  }

 private:
  int width_, height_, tile_, num_threads_;
};

class RasterizeForward : public mx::Primitive {
 public:
  RasterizeForward(mx::Stream stream, int width, int height, int tile, int num_threads)
      : mx::Primitive(stream), width_(width), height_(height), tile_(tile), num_threads_(num_threads) {}

  void eval_cpu(const std::vector<mx::array>& inputs, std::vector<mx::array>& outputs) override {
    for (auto& o : outputs) allocate(o);
    auto& encoder = mx::cpu::get_command_encoder(stream());
    for (const auto& a : inputs) encoder.set_input_array(a);
    for (auto& o : outputs) encoder.set_output_array(o);
    Inputs in = input_pointers(inputs);
    const Geometry geo = make_geometry(width_, height_, tile_, inputs[0].shape(0), inputs[2].shape(1), inputs[5].size());
    ForwardOut out{outputs[0].data<float>(), outputs[1].data<float>(), outputs[2].data<int32_t>(),
                   outputs[3].data<float>()};
    encoder.dispatch([in, geo, out, threads = num_threads_]() { run_forward(in, geo, threads, out); });
  }

  void eval_gpu(const std::vector<mx::array>&, std::vector<mx::array>&) override {
    throw std::runtime_error("RasterizeForward runs on the CPU only; use mlx3d.render.raster_metal on Apple GPUs.");
  }

  // Cotangents: one per output (accum, alpha, last, final_T); those of `last`
  // (integer) and `final_T` (internal) are ignored. tile_offsets and
  // flatten_ids are integer inputs and get zero cotangents.
  std::vector<mx::array> vjp(const std::vector<mx::array>& primals, const std::vector<mx::array>& cotangents,
                             const std::vector<int>& argnums, const std::vector<mx::array>& outputs) override {
    auto s = stream();
    bool need = false;
    for (int a : argnums) need |= a < 4;
    std::vector<mx::array> grads;
    if (need) {
      auto prep = [&](const mx::array& x) { return mx::contiguous(mx::astype(x, mx::float32, s), false, s); };
      std::vector<mx::array> inputs = {primals[0], primals[1], primals[2],  primals[3],       primals[4],
                                       primals[5], outputs[2], outputs[3], prep(cotangents[0]), prep(cotangents[1])};
      grads = mx::array::make_arrays(
          {primals[0].shape(), primals[1].shape(), primals[2].shape(), primals[3].shape()},
          {mx::float32, mx::float32, mx::float32, mx::float32},
          std::make_shared<RasterizeBackward>(s, width_, height_, tile_, num_threads_), inputs);
    }
    std::vector<mx::array> result;
    for (int a : argnums) result.push_back(a < 4 ? grads[a] : mx::zeros_like(primals[a], s));
    return result;
  }

  std::vector<mx::array> jvp(const std::vector<mx::array>&, const std::vector<mx::array>&,
                             const std::vector<int>&) override {
    throw std::runtime_error(
        "RasterizeForward: forward-mode differentiation (jvp) is not implemented; use mx.grad / mx.vjp.");
  }

  std::pair<std::vector<mx::array>, std::vector<int>> vmap(const std::vector<mx::array>&,
                                                           const std::vector<int>&) override {
    throw std::runtime_error("RasterizeForward: vmap is not implemented; render images one at a time.");
  }

  std::vector<mx::Shape> output_shapes(const std::vector<mx::array>& inputs) override {
    const int C = inputs[2].shape(1);
    return {{height_, width_, C}, {height_, width_}, {height_, width_}, {height_, width_}};
  }

  const char* name() const override { return "RasterizeForward"; }

  bool is_equivalent(const mx::Primitive& other) const override {
    const auto* o = dynamic_cast<const RasterizeForward*>(&other);
    return o && o->width_ == width_ && o->height_ == height_ && o->tile_ == tile_ && o->num_threads_ == num_threads_;
  }

 private:
  int width_, height_, tile_, num_threads_;
};

// The op: validates shapes/dtypes, makes the inputs row-contiguous and returns
// the four lazily evaluated outputs (accum, alpha, last, final_T).
std::vector<mx::array> rasterize_forward(const mx::array& means2d, const mx::array& conics, const mx::array& features,
                                         const mx::array& opacities, const mx::array& tile_offsets,
                                         const mx::array& flatten_ids, int width, int height, int tile_size,
                                         int num_threads) {
  check(width >= 1 && height >= 1,
        "width and height must be >= 1, got " + std::to_string(width) + " x " + std::to_string(height));
  check(tile_size >= 1, "tile_size must be >= 1, got " + std::to_string(tile_size));
  check(num_threads >= 0, "num_threads must be >= 0 (0 = all cores), got " + std::to_string(num_threads));
  check(means2d.ndim() == 2 && means2d.shape(1) == 2, "means2d must have shape (N, 2), got " + shape_str(means2d));
  const int n = means2d.shape(0);
  check(conics.ndim() == 2 && conics.shape(0) == n && conics.shape(1) == 3,
        "conics must have shape (N, 3) = (" + std::to_string(n) + ", 3), got " + shape_str(conics));
  check(features.ndim() == 2 && features.shape(0) == n && features.shape(1) >= 1,
        "features must have shape (N, C) with N = " + std::to_string(n) + " and C >= 1, got " + shape_str(features));
  check(opacities.ndim() == 1 && opacities.shape(0) == n,
        "opacities must have shape (N,) = (" + std::to_string(n) + ",), got " + shape_str(opacities));
  const int64_t tiles = int64_t((width + tile_size - 1) / tile_size) * ((height + tile_size - 1) / tile_size);
  check(tile_offsets.ndim() == 1 && tile_offsets.shape(0) == tiles + 1,
        "tile_offsets must have shape (tiles + 1,) = (" + std::to_string(tiles + 1) + ",), got " +
            shape_str(tile_offsets));
  check(flatten_ids.ndim() == 1, "flatten_ids must have shape (M,), got " + shape_str(flatten_ids));
  for (const auto* a : {&means2d, &conics, &features, &opacities})
    check(a->dtype() == mx::float32, "float inputs must be float32 (the Python wrapper casts them)");
  check(tile_offsets.dtype() == mx::int32, "tile_offsets must be int32");
  check(flatten_ids.dtype() == mx::int32, "flatten_ids must be int32");

  auto s = mx::default_stream(mx::Device::cpu);
  std::vector<mx::array> inputs;
  for (const auto* a : {&means2d, &conics, &features, &opacities, &tile_offsets, &flatten_ids})
    inputs.push_back(mx::contiguous(*a, false, s));
  const int C = features.shape(1);
  return mx::array::make_arrays({{height, width, C}, {height, width}, {height, width}, {height, width}},
                                {mx::float32, mx::float32, mx::int32, mx::float32},
                                std::make_shared<RasterizeForward>(s, width, height, tile_size, num_threads), inputs);
}

}  // namespace

void bind_rasterize(nb::module_& m) {
  m.def("rasterizer_simd_lanes", &simd_lanes,
        "Pixels per SIMD step of the CPU rasterizer on this machine (8: AVX2, 4: SSE2/NEON, 1: scalar);\n"
        "MLX3D_RASTER_ISA=baseline forces the baseline variant.");
  m.def("rasterize_forward", &rasterize_forward, "means2d"_a, "conics"_a, "features"_a, "opacities"_a,
        "tile_offsets"_a, "flatten_ids"_a, "width"_a, "height"_a, "tile_size"_a = 16, "num_threads"_a = 0,
        "3DGS tile rasterizer (MLX primitive, CPU, threaded over tiles; differentiable w.r.t. the first four\n"
        "inputs). float32 means2d (N,2), conics (N,3), features (N,C), opacities (N,); int32 tile_offsets\n"
        "(tiles+1,), flatten_ids (M,). Returns [accum (H,W,C), alpha (H,W), last (H,W) int32, final_T (H,W)].\n"
        "Use mlx3d.render.raster_cpu.rasterize_cpu, which validates and casts its inputs.");
}

}  // namespace mlx3d
