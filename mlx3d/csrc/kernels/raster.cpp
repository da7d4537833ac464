// The 3DGS tile rasterizer on the CPU: mlx3d_rasterize_forward (composite), its surface variant and
// mlx3d_rasterize_backward (its vector-Jacobian product), threaded over tiles (mlx3d_kernels.h). The per-pixel math lives in raster_math.h, which the
// Metal kernels (mlx3d/render/raster_metal.py) compile too.
//
// Inputs (row-contiguous):
//   means2d (N,2) f32, conics (N,3) f32 (a, b, c of [[a,b],[b,c]]), features (N,C) f32,
//   opacities (N,) f32, tile_offsets (T+1,) i32, flatten_ids (M,) i32
// Outputs of the forward pass:
//   accum (H,W,C) f32 (no background), alpha (H,W) f32 = 1 - T_final,
//   last (H,W) i32, final_T (H,W) f32 (T_final, kept for the backward pass).
// `last` is 3DGS's n_contrib: 1 + the position, inside the pixel's tile range,
// of the last Gaussian that contributed (0 when none did). The backward pass
// walks entries [0, last) of the tile range back to front.
// The forward-only surface variant also composites a per-pixel surface layer in
// depth order (see "surface layer"); same outputs.
//
// Work layout. Each Gaussian is first packed into a 64-byte Splat record
// (mean, conic, opacity, up to 4 features and its "reach", see "sub-tile
// culling"), in parallel. Each thread then takes the next tile from an atomic
// counter. A tile gathers its entries' records contiguously (entries with an
// id outside [0, N) get opacity 0 and are skipped) and processes its pixels in
// blocks of one SIMD vector of pixels (8 with AVX2, 4 with SSE2/NEON, see
// "variants" below). Each block runs only the entries whose reach holds one of
// its pixels, in tile order: the Gaussian loop is outside, each step runs the
// per-pixel math on all lanes at once, and a block stops when all of its
// pixels have stopped. The forward pass lists entries per block in chunks
// (a tile whose pixels all stop early lists no more) and uses rectangular
// blocks (4x2 pixels for 8 lanes); the backward pass uses row-major runs of
// pixels, which fix its lane sums (below). Forward results depend neither on
// the vector width nor on the block shape: each lane runs exactly the scalar
// per-pixel recurrence.
//
// Determinism of the backward pass. Gradients are first accumulated per
// *tile entry* (one slot per flatten_ids position) by the single thread that
// owns the tile, in a fixed order (pixel blocks in order; lanes summed
// in lane order at the end of the tile). The per-Gaussian gradients are then the
// sums of their entries' slots in flatten_ids order, done on one thread into
// one record of 6 + C floats per Gaussian (split into the four outputs at the
// end). No floating-point sum depends on the thread count or on scheduling,
// so 1 and many threads give bitwise-identical results. Tiles are processed
// in chunks of consecutive tiles to bound the slot buffer (same summation
// order).
#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <memory>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

#include "api.h"
#include "mlx3d_kernels.h"
#include "parallel.h"

// Lane types: the tile kernels run several pixels at once, one per lane. With
// GCC and clang (which has GCC's vector extensions and defines __GNUC__ too)
// they are vectors of floats / int32: 8 lanes in the AVX2 variant (x86-64,
// picked at run time), 4 otherwise (SSE2, NEON); other compilers (MSVC)
// or -DMLX3D_RASTER_SCALAR_LANES get one pixel per lane.
// Each lane runs exactly the scalar per-pixel recurrence, so forward results
// do not depend on the lane width. The rm_* templates of raster_math.h are
// instantiated with the lane type; comparisons give lane masks (-1 / 0 per
// lane; bool for scalar lanes) and `?:` selects per lane.
#if defined(__GNUC__) && !defined(MLX3D_RASTER_SCALAR_LANES)
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
// The AVX2 variant: x86-64 ELF (GCC or clang), and Windows with clang (zig's builds; GCC's MinGW does not
// keep the 32-byte stack alignment AVX locals need).
#if defined(__x86_64__) && (defined(__ELF__) || (defined(_WIN32) && defined(__clang__)))
#define MLX3D_RASTER_AVX2 1
#endif
#if defined(__x86_64__)
#include <cpuid.h>
#include <immintrin.h>
#endif
#endif
#include "../raster_math.h"

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
// All lanes = v, bit for bit (-0.0f stays -0.0f): the bits are broadcast as
// integers, which compiles to one broadcast load (writing the lanes one by one
// compiled to a chain of five shuffles on the port the kernels' blends use).
template <class LF>
RM_INLINE LF splat(float v) {
#if defined(MLX3D_RASTER_VECTOR_LANES)
  int32_t bits;
  std::memcpy(&bits, &v, sizeof(bits));
  if constexpr (sizeof(LF) == sizeof(LaneF8)) {
    return (LaneF8)(LaneI8{} + bits);
  } else {
    static_assert(sizeof(LF) == sizeof(LaneF4), "lane type");
    return (LaneF4)(LaneI4{} + bits);
  }
#else
  return v;
#endif
}
template <class LI>
RM_INLINE bool any_lane(const LI& m) {
  int32_t a[lanes_of<LI>()];
  store_lanes(a, m);
  int32_t any = 0;
  for (int l = 0; l < lanes_of<LI>(); ++l) any |= a[l];
  return any != 0;
}
#if defined(MLX3D_RASTER_AVX2)
// One vptest instead of eight lane extractions (only called from AVX2 code;
// plain inline, as always_inline would be refused inside the generic
// templates before they are inlined into the AVX2 kernels).
__attribute__((target("avx2"))) inline bool any_lane(const LaneI8& m) {
  const __m256i v = (__m256i)m;
  return !_mm256_testz_si256(v, v);
}
#endif
#if defined(MLX3D_RASTER_VECTOR_LANES) && defined(__x86_64__)
// SSE (x86-64 baseline): the lanes' sign bits.
RM_INLINE bool any_lane(const LaneI4& m) {
  return _mm_movemask_ps((__m128)m) != 0;
}
#endif

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

// Features held in each Splat record (more channels are gathered separately).
constexpr int kMaxFixedChannels = 4;

// A Gaussian as the tile kernels read it: one 64-byte record per Gaussian,
// built once per evaluation (make_splat), so that gathering a tile entry is
// one cache line.
struct alignas(64) Splat {
  float x, y;         // mean
  float a, b, c, op;  // 0.0f + conic and opacity: the operands the per-pixel math has always used
                      // (the sum maps -0.0f to +0.0f)
  float hx, hy;       // reach box half-extents (pixels); +inf: no bound; < 0: reaches no pixel
  float slope, p, r;  // reach row spans (see "sub-tile culling")
  int32_t pad;
  float f[kMaxFixedChannels];  // features, when there are at most kMaxFixedChannels
};
static_assert(sizeof(Splat) == 64, "one cache line per Splat");

// The surface layer of RasterizeForward's surface variant (see "surface layer").
struct SurfaceIn {
  const float* depths = nullptr;  // (N,) the Gaussians' camera z, the binning's sort key
  const float* color = nullptr;   // (H,W,C) premultiplied
  const float* alpha = nullptr;   // (H,W)
  const float* depth = nullptr;   // (H,W) camera z; +inf: after every entry
};

struct Inputs {
  const float* means = nullptr;
  const float* conics = nullptr;
  const float* features = nullptr;
  const float* opacities = nullptr;
  const int32_t* offsets = nullptr;
  const int32_t* ids = nullptr;
  const int64_t* ranges = nullptr;  // sanitised tile_offsets (see sanitise_offsets)
  const Splat* splats = nullptr;    // (N,) see make_splat
  SurfaceIn surface;                // the surface variant only
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

// ------------------------------------------------------------ sub-tile culling
// A Gaussian's reach is a set of pixels outside which its alpha is certainly
// skipped: at every other pixel centre the kernels' float32 arithmetic
// (rm_power, rm_exp, rm_alpha) gives power > 0 or alpha < 1/255. It is a box
// (half-extents hx, hy around the mean) and, inside the box, one column span
// per pixel row (the row's chord of a slightly enlarged ellipse). A block of
// pixels is only run against the tile entries whose reach holds one of its
// pixels. A pair left out is one that every lane would have skipped, which
// changes no state (T, accum, last, which lanes go on; in the backward pass,
// a Gaussian no lane uses), so the results are bitwise those of evaluating
// every pair. MLX3D_RASTER_CULL=0 in the environment turns culling off (read
// at each evaluation; for tests).
//
// Why pixels outside the reach skip (u = 2^-24; a, b, c, o: the float inputs;
// d = (dx, dy) = mean - pixel centre, exact; d' = the kernel's float offsets):
// - Let L = ln(o / (1/255f)) + 1e-5. rm_exp(x) <= exp(x) (1 + 1e-7) for every
//   float x in [-88, 0] (checked over all of them), so a computed power
//   p <= 0 with p < -L gives o * rm_exp(p) < (1/255f)(1 - 9.9e-6), whose float
//   product is below 1/255f: skipped. When L <= 0 (o <= (1/255f) e^-1e-5,
//   including o <= 0), o * rm_exp(p) < 1/255f for every p <= 0: the Gaussian
//   reaches nothing.
// - rm_power evaluated as written (this file is compiled with
//   -ffp-contract=off; a fused multiply-add would only lower the error) is at
//   most (1 - u)(-Q/2 + 1.6 u S) with Q = a dx'² + 2b dx'dy' + c dy'² and
//   S = a dx'² + c dy'² + 2|b dx'dy'|. For a positive definite conic,
//   S <= 2 (a dx'² + c dy'²) <= 2 rho Q with rho = max(a, c) / lambda_min; with
//   rho <= 1e4 the power is at most -0.498 Q. So Q(d') > K = 2 (L + 1e-6) / 0.99
//   gives power < -L.
// - Box: Q(d') >= dx'² / Sxx with Sxx = c / det (Sigma = conic^-1), and |dx'| >=
//   |dx| (1 - u), so |dx| > hx = sqrt(K Sxx) (1 + 1e-4) + 0.01 gives Q(d') > K
//   (likewise dy with Syy = a / det). The margins also cover the rounding of
//   the box arithmetic, done in double.
// - Row spans: |Q(d') - Q(d)| <= 2.01 u S(d) <= 2.5e-3 Q(d) (rho <= 1e4), so
//   Q(d) > 1.01 K gives Q(d') > K. With K' = 1.01 K,
//   Q(d) = a (dx + (b/a) dy)² + (det/a) dy², so in row dy the pixels with
//   Q(d) <= K' have |dx + slope dy| <= sqrt(p - r dy²), slope = b/a, p = K'/a,
//   r = det/a². p is stored rounded up and r rounded down (float), slope
//   rounded to nearest (|slope dy| <= hx inside the box, so that costs at most
//   u hx); the span is computed in double and widened by 1e-4 hx + 0.01
//   pixels, far above those errors (cancellation near the ellipse's top and
//   bottom rows costs at most ~1.5e-8 hx).
// Anything else gets no bound (evaluated everywhere in its tiles): non-finite
// inputs, a or c below 1e-30 (keeps rm_power clear of underflow), det <= 0,
// rho > 1e4, a half-extent above 1e6 or a mean farther than 1e7 pixels from
// the origin.
constexpr double kReachCondMax = 1e4;
constexpr double kReachMinDiag = 1e-30;
constexpr double kReachMaxHalf = 1e6;
constexpr double kReachMaxCoord = 1e7;

float float_up(double v) {
  const float f = static_cast<float>(v);
  return static_cast<double>(f) < v ? std::nextafter(f, std::numeric_limits<float>::infinity()) : f;
}
float float_down(double v) {
  const float f = static_cast<float>(v);
  return static_cast<double>(f) > v ? std::nextafter(f, -std::numeric_limits<float>::infinity()) : f;
}

// The reach fields of a Splat (see above) from a Gaussian's float conic and opacity.
void set_reach(float a_, float b_, float c_, float o_, Splat& s) {
  s.hx = s.hy = std::numeric_limits<float>::infinity();
  s.slope = s.p = s.r = 0.0f;
  const double a = a_, b = b_, c = c_, o = o_;
  if (!std::isfinite(o)) return;
  const double L = o > 0.0 ? std::log(o / static_cast<double>(RM_ALPHA_MIN)) + 1e-5 : -1.0;
  if (L <= 0.0) {
    s.hx = s.hy = -1.0f;
    return;
  }
  if (!(std::isfinite(a) && std::isfinite(b) && std::isfinite(c))) return;
  if (!(a >= kReachMinDiag && c >= kReachMinDiag)) return;
  const double det = a * c - b * b;
  if (!(det > 0.0)) return;
  const double half = 0.5 * (a - c);
  const double lambda_max = 0.5 * (a + c) + std::sqrt(half * half + b * b);
  const double lambda_min = det / lambda_max;
  if (!(std::max(a, c) <= kReachCondMax * lambda_min)) return;
  const double k = 2.0 * (L + 1e-6) / 0.99;
  const double ex = std::sqrt(k * c / det) * (1.0 + 1e-4) + 0.01;
  const double ey = std::sqrt(k * a / det) * (1.0 + 1e-4) + 0.01;
  if (!(ex <= kReachMaxHalf && ey <= kReachMaxHalf)) return;
  s.hx = float_up(ex);
  s.hy = float_up(ey);
  s.slope = static_cast<float>(b / a);
  s.p = float_up(1.01 * k / a);
  s.r = float_down(det / (a * a));
}

// Splat g (culling off: no reach bound).
void make_splat(const Inputs& in, const Geometry& geo, int64_t g, bool cull, Splat& s) {
  s.x = in.means[2 * g];
  s.y = in.means[2 * g + 1];
  s.a = 0.0f + in.conics[3 * g];
  s.b = 0.0f + in.conics[3 * g + 1];
  s.c = 0.0f + in.conics[3 * g + 2];
  s.op = 0.0f + in.opacities[g];
  s.pad = 0;
  if (cull) {
    set_reach(in.conics[3 * g], in.conics[3 * g + 1], in.conics[3 * g + 2], in.opacities[g], s);
  } else {
    s.hx = s.hy = std::numeric_limits<float>::infinity();
    s.slope = s.p = s.r = 0.0f;
  }
  const int C = geo.channels;
  for (int ch = 0; ch < kMaxFixedChannels; ++ch) s.f[ch] = ch < C ? in.features[g * C + ch] : 0.0f;
}

bool culling_enabled() {
  const char* v = std::getenv("MLX3D_RASTER_CULL");
  return !(v && std::strcmp(v, "0") == 0);
}

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

// Column spans of rows [r0, r1] (see "sub-tile culling"): lo[r], hi[r] =
// ceil(centre - half), floor(centre + half), clamped to [c0, c1], with
// centre = cx + slope dy, half = sqrt(max(p - r dy², 0)) + margin, dy = cy - r.
void row_spans_scalar(double cx, double cy, double slope, double p, double rc, double margin, int r0, int r1, int c0,
                      int c1, int* lo, int* hi) {
  for (int r = r0; r <= r1; ++r) {
    const double dy = cy - r;
    const double centre = cx + slope * dy;
    const double half = std::sqrt(std::max(p - rc * dy * dy, 0.0)) + margin;
    lo[r] = std::max(c0, static_cast<int>(std::ceil(centre - half)));
    hi[r] = std::min(c1, static_cast<int>(std::floor(centre + half)));
  }
}

#if defined(MLX3D_RASTER_AVX2)
// The spans of rows r .. r + 3 (as row_spans_scalar, the same double arithmetic), unclamped.
struct Spans4 {
  __m256d cx, cy, slope, p, rc, margin;
};
__attribute__((target("avx2"))) inline void spans4(const Spans4& v, int r, __m128i& lo, __m128i& hi) {
  const __m256d step = _mm256_set_pd(3.0, 2.0, 1.0, 0.0);
  const __m256d dy = _mm256_sub_pd(v.cy, _mm256_add_pd(_mm256_set1_pd(static_cast<double>(r)), step));
  const __m256d centre = _mm256_add_pd(v.cx, _mm256_mul_pd(v.slope, dy));
  const __m256d arg = _mm256_max_pd(_mm256_sub_pd(v.p, _mm256_mul_pd(_mm256_mul_pd(v.rc, dy), dy)), _mm256_setzero_pd());
  const __m256d half = _mm256_add_pd(_mm256_sqrt_pd(arg), v.margin);
  lo = _mm256_cvttpd_epi32(_mm256_ceil_pd(_mm256_sub_pd(centre, half)));
  hi = _mm256_cvttpd_epi32(_mm256_floor_pd(_mm256_add_pd(centre, half)));
}

__attribute__((target("avx2"))) inline Spans4 spans4_setup(double cx, double cy, double slope, double p, double rc,
                                                           double margin) {
  return {_mm256_set1_pd(cx), _mm256_set1_pd(cy), _mm256_set1_pd(slope), _mm256_set1_pd(p), _mm256_set1_pd(rc),
          _mm256_set1_pd(margin)};
}

// row_spans_scalar four rows at a time; may write up to 3 entries past r1.
__attribute__((target("avx2"))) void row_spans_avx2(double cx, double cy, double slope, double p, double rc,
                                                    double margin, int r0, int r1, int c0, int c1, int* lo, int* hi) {
  const Spans4 v = spans4_setup(cx, cy, slope, p, rc, margin);
  const __m128i vc0 = _mm_set1_epi32(c0), vc1 = _mm_set1_epi32(c1);
  for (int r = r0; r <= r1; r += 4) {
    __m128i l, h;
    spans4(v, r, l, h);
    _mm_storeu_si128(reinterpret_cast<__m128i*>(lo + r), _mm_max_epi32(l, vc0));
    _mm_storeu_si128(reinterpret_cast<__m128i*>(hi + r), _mm_min_epi32(h, vc1));
  }
}
#endif

// Whether the point (q, row) (tile-local pixel indices) lies in the ellipse
// of the row spans, |q - (cx + slope dy)| <= sqrt(p - r dy²) with dy = cy - row,
// with no margin (so the spans, which add one, hold q in that row).
RM_INLINE bool in_span_ellipse(const Splat& e, double cx, double cy, int q, int row) {
  const double dy = cy - row;
  const double u = q - (cx + static_cast<double>(e.slope) * dy);
  return u * u <= static_cast<double>(e.p) - static_cast<double>(e.r) * dy * dy;
}

// Block lists. Each entry's reach is turned into a bitset of the pixel
// blocks it holds a pixel of (one bit per block, 64 per word); the bitsets of
// each 64 entries are transposed into one word per block, and a block's list
// is then read off its words. These steps are free of data-dependent
// branches: the spans' shapes vary from entry to entry, and loops and
// branches shaped by them mispredicted (building the lists took about 30% of
// each kernel's time; docs/design/training-step-history.md, "The tile kernels, per core").

// Sets bits [b0, b1] of `bits` (`words` words) when `any` (else nothing; b0
// and b1 are then ignored, so they may be anything).
RM_INLINE void set_block_range(uint64_t* bits, int words, int b0, int b1, bool any) {
  if (words == 1) {  // tiles of up to 64 blocks (16x16 pixels with 4 or 8 lanes): no loop
    const uint64_t range = (uint64_t(2) << (b1 & 63)) - (uint64_t(1) << (b0 & 63));
    bits[0] |= any ? range : 0;
    return;
  }
  b0 = any ? b0 : 0;
  b1 = any ? std::max(b0, b1) : 0;
  for (int word = b0 >> 6; word <= b1 >> 6; ++word) {
    const int first = std::max(b0, word << 6) & 63, last = std::min(b1, (word << 6) + 63) & 63;
    bits[word] |= any ? (~uint64_t(0) >> (63 - (last - first))) << first : 0;
  }
}

// Pixel blocks of a tile: pixel (row r, column q) is in block ((r * row_mul + q) >> q_shift) + (r >> row_shift)
// * row_blocks.
struct BlockMap {
  int row_mul, q_shift, row_shift, row_blocks;
};

// Backward blocks: kLanes consecutive pixels in row-major order of a tile of width w (a block may span two rows).
template <int kLanes>
constexpr BlockMap run_blocks(int w) {
  static_assert((kLanes & (kLanes - 1)) == 0, "lanes: a power of two");
  int shift = 0;
  while ((1 << shift) < kLanes) ++shift;
  return {w, shift, 0, 0};
}

// Forward blocks: kW x kH rectangles (powers of two) numbered row by row, bw per row.
template <int kW, int kH>
constexpr BlockMap rect_blocks(int bw) {
  static_assert((kW & (kW - 1)) == 0 && (kH & (kH - 1)) == 0, "block sides: powers of two");
  int ws = 0, hs = 0;
  while ((1 << ws) < kW) ++ws;
  while ((1 << hs) < kH) ++hs;
  return {0, ws, hs, bw};
}

// Sets the bits of the blocks holding a pixel of the spans (rows [r0, r1], columns [lo[r], hi[r]]; lo > hi:
// none): each row's pixels lie in one run of block numbers.
RM_INLINE void set_span_blocks(int r0, int r1, const int* lo, const int* hi, const BlockMap& map, int words,
                               uint64_t* bits) {
  for (int r = r0; r <= r1; ++r) {
    const int row = (r >> map.row_shift) * map.row_blocks;
    set_block_range(bits, words, row + ((r * map.row_mul + lo[r]) >> map.q_shift),
                    row + ((r * map.row_mul + hi[r]) >> map.q_shift), lo[r] <= hi[r]);
  }
}

#if defined(MLX3D_RASTER_AVX2)
// The same for tiles of at most 64 blocks (one word), with the spans computed here (as row_spans_avx2),
// four rows at a time in 64-bit lanes, with no branch on the spans: each row's run of blocks is
// (2 << b1) - (1 << b0), and rows past r1 or with no pixel add nothing.
__attribute__((target("avx2"))) inline uint64_t span_blocks_word(const Spans4& v, int r0, int r1, int c0, int c1,
                                                                 const BlockMap& map) {
  const __m128i vc0 = _mm_set1_epi32(c0), vc1 = _mm_set1_epi32(c1);
  const __m256i row_mul = _mm256_set1_epi64x(map.row_mul), row_blocks = _mm256_set1_epi64x(map.row_blocks);
  const __m256i q_shift = _mm256_set1_epi64x(map.q_shift), row_shift = _mm256_set1_epi64x(map.row_shift);
  const __m256i one = _mm256_set1_epi64x(1), two = _mm256_set1_epi64x(2), last = _mm256_set1_epi64x(r1);
  __m256i acc = _mm256_setzero_si256();
  for (int r = r0; r <= r1; r += 4) {
    __m128i l, h;
    spans4(v, r, l, h);
    const __m256i lo = _mm256_cvtepi32_epi64(_mm_max_epi32(l, vc0)), hi = _mm256_cvtepi32_epi64(_mm_min_epi32(h, vc1));
    const __m256i rows = _mm256_add_epi64(_mm256_set1_epi64x(r), _mm256_set_epi64x(3, 2, 1, 0));
    const __m256i base = _mm256_mul_epu32(rows, row_mul);  // small non-negative values: 32-bit products
    const __m256i row = _mm256_mul_epu32(_mm256_srlv_epi64(rows, row_shift), row_blocks);
    const __m256i b0 = _mm256_add_epi64(row, _mm256_srlv_epi64(_mm256_add_epi64(base, lo), q_shift));
    const __m256i b1 = _mm256_add_epi64(row, _mm256_srlv_epi64(_mm256_add_epi64(base, hi), q_shift));
    const __m256i run = _mm256_sub_epi64(_mm256_sllv_epi64(two, b1), _mm256_sllv_epi64(one, b0));
    const __m256i none = _mm256_or_si256(_mm256_cmpgt_epi64(rows, last), _mm256_cmpgt_epi64(lo, hi));
    acc = _mm256_or_si256(acc, _mm256_andnot_si256(none, run));
  }
  const __m128i pair = _mm_or_si128(_mm256_castsi256_si128(acc), _mm256_extracti128_si256(acc, 1));
  return static_cast<uint64_t>(_mm_cvtsi128_si64(pair) | _mm_extract_epi64(pair, 1));
}
#endif

// The blocks (`map`; nb blocks, `words` words of bits) holding a pixel of Splat e's reach in the tile, ORed
// into bits. The reach's pixels are rows [r0, r1] and, in each, tile-local columns [lo[r], hi[r]] (its
// spans, see "sub-tile culling"). When the reach box holds the whole tile and the tile's four corner pixels
// lie in the spans' ellipse, which is convex, every block is held, without computing the spans.
// lo and hi: scratch of box.h + 3 entries.
template <bool kAvx2>
RM_INLINE void reach_blocks(const Splat& e, const TileBox& box, const BlockMap& map, int nb, int words, int* lo, int* hi,
                            uint64_t* bits) {
  int r0 = 0, r1 = box.h - 1, c0 = 0, c1 = box.w - 1;
  if (e.hx < 0.0f || e.hy < 0.0f) return;
  const bool bounded = e.hx <= kReachMaxHalf && e.hy <= kReachMaxHalf && std::fabs(e.x) <= kReachMaxCoord &&
                       std::fabs(e.y) <= kReachMaxCoord;  // false for NaN too
  if (!bounded) {
    set_block_range(bits, words, 0, nb - 1, true);
    return;
  }
  // tile-local pixel column q has its centre at x0 + q + 0.5
  const double cx = static_cast<double>(e.x) - 0.5 - box.x0, cy = static_cast<double>(e.y) - 0.5 - box.y0;
  c0 = std::max(c0, static_cast<int>(std::ceil(cx - e.hx)));
  c1 = std::min(c1, static_cast<int>(std::floor(cx + e.hx)));
  r0 = std::max(r0, static_cast<int>(std::ceil(cy - e.hy)));
  r1 = std::min(r1, static_cast<int>(std::floor(cy + e.hy)));
  if (c0 > c1 || r0 > r1) return;
  const int w1 = box.w - 1, h1 = box.h - 1;
  if (c0 == 0 && r0 == 0 && c1 == w1 && r1 == h1 && in_span_ellipse(e, cx, cy, 0, 0) &&
      in_span_ellipse(e, cx, cy, w1, 0) && in_span_ellipse(e, cx, cy, 0, h1) && in_span_ellipse(e, cx, cy, w1, h1)) {
    set_block_range(bits, words, 0, nb - 1, true);
    return;
  }
  const double margin = 1e-4 * e.hx + 0.01;
#if defined(MLX3D_RASTER_AVX2)
  if constexpr (kAvx2) {
    if (words == 1) {
      bits[0] |= span_blocks_word(spans4_setup(cx, cy, e.slope, e.p, e.r, margin), r0, r1, c0, c1, map);
      return;
    }
    row_spans_avx2(cx, cy, e.slope, e.p, e.r, margin, r0, r1, c0, c1, lo, hi);
    set_span_blocks(r0, r1, lo, hi, map, words, bits);
    return;
  }
#endif
  row_spans_scalar(cx, cy, e.slope, e.p, e.r, margin, r0, r1, c0, c1, lo, hi);
  set_span_blocks(r0, r1, lo, hi, map, words, bits);
}

// Transposes the 64x64 bit matrix a (a[i] bit j becomes a[j] bit i): six rounds of block swaps.
RM_INLINE void transpose_bits64(uint64_t* a) {
  uint64_t m = 0x00000000FFFFFFFFull;
  for (int j = 32; j != 0; j >>= 1, m ^= m << j) {
    for (int k = 0; k < 64; k = ((k | j) + 1) & ~j) {
      const uint64_t t = ((a[k] >> j) ^ a[k | j]) & m;
      a[k] ^= t << j;
      a[k | j] ^= t;
    }
  }
}

// The entries' bitsets by block: cols[b * G + g] bit i is bit b of entry 64 g + i's bitset (`words` words
// per entry at bits), for blocks b < nb and the G = ceil(n / 64) groups of entries (0 past entry n).
// Returns G. One 64x64 transpose per group and word, instead of one test per entry and block.
RM_INLINE int block_columns(const uint64_t* bits, int words, int n, int nb, std::vector<uint64_t>& cols) {
  const int groups = (n + 63) / 64;
  if (cols.size() < static_cast<size_t>(nb) * groups) cols.resize(static_cast<size_t>(nb) * groups);
  uint64_t a[64];
  for (int g = 0; g < groups; ++g)
    for (int w = 0; w < words; ++w) {
      for (int i = 0; i < 64; ++i) {
        const int k = 64 * g + i;
        a[i] = k < n ? bits[static_cast<size_t>(k) * words + w] : 0;
      }
      transpose_bits64(a);
      for (int b = 64 * w; b < std::min(nb, 64 * w + 64); ++b) cols[static_cast<size_t>(b) * groups + g] = a[b - 64 * w];
    }
  return groups;
}

// Positions of the set bits of each byte value, in increasing order (the rest zero), and their count.
struct BytePositions {
  uint8_t pos[256][8];
  uint8_t count[256];
};
constexpr BytePositions make_byte_positions() {
  BytePositions t{};
  for (int v = 0; v < 256; ++v) {
    int c = 0;
    for (int bit = 0; bit < 8; ++bit)
      if (v & (1 << bit)) t.pos[v][c++] = static_cast<uint8_t>(bit);
    t.count[v] = static_cast<uint8_t>(c);
  }
  return t;
}
constexpr BytePositions kBytePositions = make_byte_positions();

// Spare room `list` needs past the entries block_list writes.
constexpr int kListSlack = 8;

// Writes to `list` the entries k0 + j, j in [0, n), whose bits in `col` (one word per group of 64 entries,
// as block_columns gives a block's) are set, in increasing order; returns how many. Eight candidates are
// written per byte of bits and the count advanced by the byte's set bits (no branch on the bits), so
// `list` needs kListSlack spare entries.
RM_INLINE int block_list(const uint64_t* col, int n, int k0, int32_t* list) {
  int count = 0;
  for (int g = 0; 64 * g < n; ++g) {
    const int rest = n - 64 * g;
    const uint64_t m = rest >= 64 ? col[g] : col[g] & ((uint64_t(1) << rest) - 1);
    for (int byte = 0; byte < 8; ++byte) {
      const unsigned v = static_cast<unsigned>(m >> (8 * byte)) & 0xff;
      const int base = k0 + 64 * g + 8 * byte;
      for (int i = 0; i < 8; ++i) list[count + i] = base + kBytePositions.pos[v][i];
      count += kBytePositions.count[v];
    }
  }
  return count;
}

// Asks for the cache line at p ahead of a read (kWrite = false) or a write.
template <bool kWrite>
inline void prefetch(const void* p) {
#if defined(__GNUC__) || defined(__clang__)
  __builtin_prefetch(p, kWrite ? 1 : 0);
#else
  (void)p;
#endif
}

// Per-thread scratch: the tile's Gaussians gathered contiguously, and lane buffers.
struct Scratch {
  std::vector<Splat> entries;                   // gathered, one per tile entry
  std::vector<float> feat;                      // gathered features (more than kMaxFixedChannels)
  std::vector<float> lane;                      // per-block lane state
  std::vector<float> entry_lanes;               // backward: per-entry, per-field lane sums
  std::vector<int32_t> list;                    // one block's entry list
  std::vector<uint64_t> block_bits;             // per entry, the blocks its reach holds (see "block lists")
  std::vector<uint64_t> block_cols;             // the same by block (block_columns)
  std::vector<int32_t> block_kmax;              // backward: entries each block walks
  std::vector<uint8_t> done;                    // forward: blocks whose pixels all stopped
  std::vector<int32_t> span_lo, span_hi;        // one entry's column spans, per tile row
  std::vector<float> entry_depth;               // forward with a surface: the tile's entries' depths

  // `count` zeroed lane vectors in `buf`, 32-byte aligned. (alignof of a
  // 32-byte vector type is 16 outside AVX code, so std::vector<LF> would not do.)
  template <class LF>
  static LF* lanes(std::vector<float>& buf, size_t count) {
    constexpr size_t kAlign = 32;
    buf.assign(count * lanes_of<LF>() + kAlign / sizeof(float), 0.0f);
    const uintptr_t p = reinterpret_cast<uintptr_t>(buf.data());
    return reinterpret_cast<LF*>((p + kAlign - 1) / kAlign * kAlign);
  }

  void reserve(int64_t n, int C, int rows) {
    if (entries.size() < static_cast<size_t>(n)) entries.resize(n);
    if (C > kMaxFixedChannels && feat.size() < static_cast<size_t>(n) * C) feat.resize(static_cast<size_t>(n) * C);
    if (span_lo.size() < static_cast<size_t>(rows) + 4) span_lo.resize(rows + 4), span_hi.resize(rows + 4);
  }

  // Asks for the Splats of entries [k0, k1) of the tile whose range starts at lo (random places in
  // in.splats), so that their misses overlap other work before gather() reads them.
  void prefetch_splats(const Inputs& in, const Geometry& geo, int64_t lo, int k0, int k1) const {
    for (int j = k0; j < k1; ++j) {
      const int64_t g = in.ids[lo + j];
      if (g >= 0 && g < geo.num_gaussians) prefetch<false>(&in.splats[g]);
    }
  }

  // Entries [k0, k1) of the tile whose range starts at lo; reserve() first.
  // An id outside [0, N) gets opacity 0 and no reach (it never contributes).
  void gather(const Inputs& in, const Geometry& geo, int64_t lo, int k0, int k1) {
    const int C = geo.channels;
    for (int j = k0; j < k1; ++j) {
      const int64_t g = in.ids[lo + j];
      Splat& e = entries[j];
      const bool ok = g >= 0 && g < geo.num_gaussians;
      if (ok) {
        e = in.splats[g];
      } else {
        std::memset(&e, 0, sizeof(e));
        e.hx = e.hy = -1.0f;
      }
      if (C > kMaxFixedChannels) {
        float* f = &feat[static_cast<size_t>(j) * C];
        if (ok)
          std::memcpy(f, &in.features[g * C], sizeof(float) * C);
        else
          std::fill_n(f, C, 0.0f);
      }
    }
  }

  // Features of gathered entry k.
  template <int CC>
  RM_INLINE const float* features(int k, int C) const {
    if constexpr (CC > 0) {
      return entries[k].f;
    } else {
      return C > kMaxFixedChannels ? &feat[static_cast<size_t>(k) * C] : entries[k].f;
    }
  }
};

struct ForwardOut {
  float* accum;
  float* alpha;
  int32_t* last;
  float* final_T;
};

// Pixel centres of the backward block q0 (kLanes pixels, row-major in the
// tile) and which lanes are inside the image tile (a mask: nonzero = valid).
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

// Forward pixel blocks are kW x kH rectangles (4x2 pixels for 8 lanes, 2x2
// for 4), which meet fewer small Gaussians than a row of pixels; each lane
// runs its own pixel's recurrence, so the layout does not change any result.
template <int kLanes>
constexpr int block_h() {
  return kLanes >= 4 ? 2 : 1;
}

// Pixel centres of forward block (bx, by) and which lanes are inside the tile.
template <class LF, class LI>
RM_INLINE void rect_pixels(const TileBox& box, int bx, int by, LF& px, LF& py, LI& valid, int64_t* pix,
                           const Geometry& geo) {
  constexpr int kLanes = lanes_of<LF>();
  constexpr int kH = block_h<kLanes>(), kW = kLanes / kH;
  float fx[kLanes], fy[kLanes];
  int32_t v[kLanes];
  for (int l = 0; l < kLanes; ++l) {
    const int qx = bx * kW + l % kW, qy = by * kH + l / kW;
    const bool in = qx < box.w && qy < box.h;
    fx[l] = static_cast<float>(box.x0 + qx) + 0.5f;
    fy[l] = static_cast<float>(box.y0 + qy) + 0.5f;
    v[l] = in ? -1 : 0;
    pix[l] = in ? static_cast<int64_t>(box.y0 + qy) * geo.width + (box.x0 + qx) : -1;
  }
  px = load_lanes<LF>(fx);
  py = load_lanes<LF>(fy);
  valid = load_lanes<LI>(v);
}

// Forward state of one pixel block in Scratch::lane: px, py, T, active (mask),
// nlast (int lanes), then accum per channel; with a surface then sidx (int
// lanes), surface alpha, passed (mask) and the surface colour per channel.
constexpr int kBlockFixed = 5;
constexpr int kSurfaceFixed = 3;
template <bool kSurface>
constexpr int block_stride(int C) {
  return kBlockFixed + C + (kSurface ? kSurfaceFixed + C : 0);
}

// ---------------------------------------------------------- surface layer
// The surface variant composites a per-pixel layer (premultiplied colour s_c,
// alpha s_a, camera depth d) with the Gaussians, in depth order. A tile's
// entries are sorted by the Gaussians' depths, so each pixel's surface sits
// just before tile position sidx = the first entry with depth >= d (n: after
// the last). Before entry sidx (or at the end of the tile), a pixel that has
// not stopped takes
//   accum += T * s_c;  T = T * (1 - s_a);  stop if T < RM_T_MIN,
// and goes on over the entries behind it with the reduced T. Entries left out
// of a block's lists (culling) are ones every lane skips, so the surface is
// taken before the next listed entry at or after sidx, with the same result.
// sidx comes from a binary search per pixel, which gives the same result for
// every lane width and thread count.

// The surface event on lanes `at` (masks), as above.
template <class LF, class LI>
RM_INLINE void surface_event(const LI& at, const LF* color, const LF& s_alpha, int C, LF& T, LI& active, LI& passed,
                             LF* acc) {
  for (int ch = 0; ch < C; ++ch) acc[ch] = at ? acc[ch] + T * color[ch] : acc[ch];
  T = at ? rm_next_T(T, s_alpha) : T;
  passed = passed | at;
  active = active & ((at == 0) | ((T < RM_T_MIN) == 0));
}

// Surface fields of a block whose lanes cover pixels pix (-1: outside the
// image, never active): sidx by binary search over the tile's n sorted entry
// depths, alpha and colour. `passed` stays 0 (the state is zeroed).
template <class LF, class LI>
RM_INLINE void init_surface(const SurfaceIn& sf, int C, const float* entry_depth, int n, const int64_t* pix,
                            LF* surf) {
  constexpr int kLanes = lanes_of<LF>();
  int32_t sidx[kLanes];
  float v[kLanes];
  for (int l = 0; l < kLanes; ++l) {
    const float d = pix[l] >= 0 ? sf.depth[pix[l]] : std::numeric_limits<float>::infinity();
    sidx[l] = static_cast<int32_t>(
        std::partition_point(entry_depth, entry_depth + n, [d](float z) { return z < d; }) - entry_depth);
    v[l] = pix[l] >= 0 ? sf.alpha[pix[l]] : 0.0f;
  }
  store_lanes(&surf[0], load_lanes<LI>(sidx));
  surf[1] = load_lanes<LF>(v);
  for (int ch = 0; ch < C; ++ch) {
    for (int l = 0; l < kLanes; ++l) v[l] = pix[l] >= 0 ? sf.color[pix[l] * C + ch] : 0.0f;
    surf[kSurfaceFixed + ch] = load_lanes<LF>(v);
  }
}

// The surface event of the lanes that are still active after every entry.
template <class LF, class LI>
RM_INLINE void finish_surface(LF* sb, int C) {
  LF* surf = sb + kBlockFixed + C;
  LF T = sb[2];
  LI active = load_lanes<LI>(&sb[3]);
  LI passed = load_lanes<LI>(&surf[2]);
  surface_event(active & (passed == 0), surf + kSurfaceFixed, surf[1], C, T, active, passed, sb + kBlockFixed);
  sb[2] = T;
  store_lanes(&sb[3], active);
  store_lanes(&surf[2], passed);
}

// Pair batches. Both kernels compute the exp and alpha of kPairBatch
// (block, entry) pairs before running the recurrence over them. These are
// independent of each other, but each is a long chain of dependent
// operations (rm_exp's polynomial). A batch is always kPairBatch pairs (a
// short one repeats its last entry; those alphas are never used) and its loop
// is unrolled, so that GCC's scheduling before register allocation
// (-fschedule-insns, CMakeLists.txt) interleaves the chains instruction by
// instruction instead of leaving it to the core's out-of-order window: about
// 10% off the forward and backward passes (docs/design/training-step-history.md, "Pair batches"). Each
// pair runs the same operations, so results are bitwise the same.
constexpr int kPairBatch = 8;
static_assert(kPairBatch == 8, "the kernels' '#pragma GCC unroll 8' unrolls one pair batch");

// Tile entries are listed per block in chunks of this many, so that a tile
// whose pixels all stop early does not list the rest.
constexpr int kForwardChunk = 64;

// Runs block state `sb` over tile entries list[0..count) (in order); returns
// false when all of the block's pixels have stopped.
template <class LF, class LI, int CC, bool kSurface>
RM_INLINE bool composite_block(const Scratch& s, LF* sb, int C, const int32_t* list, int count) {
  const LI izero{};
  const LF px = sb[0], py = sb[1];
  LF T = sb[2];
  LI active = load_lanes<LI>(&sb[3]);
  LI nlast = load_lanes<LI>(&sb[4]);
  LF* const surf = sb + kBlockFixed + C;
  const LI sidx = kSurface ? load_lanes<LI>(&surf[0]) : izero;
  LI passed = kSurface ? load_lanes<LI>(&surf[2]) : izero;
  LF acc_reg[CC > 0 ? CC : 1];
  LF* acc = sb + kBlockFixed;
  if constexpr (CC > 0) {
    for (int ch = 0; ch < CC; ++ch) acc_reg[ch] = acc[ch];
    acc = acc_reg;
    C = CC;
  }
  // Alphas of a batch of entries first (see "pair batches"), then the
  // front-to-back recurrence over them.
  constexpr int kBatch = kPairBatch;
  LF alphas[kBatch];
  bool live = true;
  for (int i0 = 0; i0 < count && live; i0 += kBatch) {
    const int nb = std::min(kBatch, count - i0);
#pragma GCC unroll 8
    for (int j = 0; j < kBatch; ++j) {
      const Splat& e = s.entries[list[i0 + std::min(j, nb - 1)]];
      const LF dx = e.x - px;
      const LF dy = e.y - py;
      const LF power = rm_power(splat<LF>(e.a), splat<LF>(e.b), splat<LF>(e.c), dx, dy);
      alphas[j] = rm_alpha(splat<LF>(e.op), rm_exp(power), power);
    }
    for (int j = 0; j < nb; ++j) {
      const int k = list[i0 + j];
      if constexpr (kSurface) {
        const LI at = active & (passed == 0) & ((izero + k) >= sidx);
        if (any_lane(at)) surface_event(at, surf + kSurfaceFixed, surf[1], C, T, active, passed, acc);
      }
      const LF alpha = alphas[j];
      const LF next_T = rm_next_T(T, alpha);
      const LI goes_on = (next_T < RM_T_MIN) == 0;  // a skipped Gaussian keeps T >= RM_T_MIN
      const LI use = active & (alpha > 0.0f) & goes_on;
      const LF w = use ? alpha * T : 0.0f;
      T = use ? next_T : T;
      nlast = use ? izero + (k + 1) : nlast;
      active = active & goes_on;
      const float* f = s.template features<CC>(k, C);
      for (int ch = 0; ch < C; ++ch) acc[ch] = use ? acc[ch] + f[ch] * w : acc[ch];
      if (!any_lane(active)) {
        live = false;
        break;
      }
    }
  }
  sb[2] = T;
  store_lanes(&sb[3], active);
  store_lanes(&sb[4], nlast);
  if constexpr (kSurface) store_lanes(&surf[2], passed);
  if constexpr (CC > 0)
    for (int ch = 0; ch < CC; ++ch) sb[kBlockFixed + ch] = acc_reg[ch];
  return live;
}

template <class LF, class LI, int CC, bool kSurface>
RM_INLINE void forward_tile_impl(const Inputs& in, const Geometry& geo, int t, Scratch& s, const ForwardOut& out) {
  constexpr int kLanes = lanes_of<LF>();
  constexpr int kH = block_h<kLanes>(), kW = kLanes / kH;
  int64_t lo, hi;
  tile_range(in, geo, t, lo, hi);
  const int n = static_cast<int>(hi - lo);
  const int C = geo.channels;
  const TileBox box = tile_box(geo, t);
  const int bw = (box.w + kW - 1) / kW, bh = (box.h + kH - 1) / kH;
  const int nb = bw * bh;  // block (bx, by) is number by * bw + bx
  const int S = block_stride<kSurface>(C);
  LF* st = Scratch::lanes<LF>(s.lane, static_cast<size_t>(nb) * S);  // zeroed: accum = 0
  const LF zero{};
  const LI izero{};
  int64_t pix[kLanes];
  if constexpr (kSurface) {
    s.entry_depth.resize(n);
    for (int j = 0; j < n; ++j) {
      const int64_t g = in.ids[lo + j];
      s.entry_depth[j] = g >= 0 && g < geo.num_gaussians ? in.surface.depths[g] : std::numeric_limits<float>::infinity();
    }
  }
  for (int b = 0; b < nb; ++b) {
    LF* sb = st + static_cast<size_t>(b) * S;
    LI valid;
    rect_pixels(box, b % bw, b / bw, sb[0], sb[1], valid, pix, geo);
    sb[2] = zero + 1.0f;
    store_lanes(&sb[3], valid);  // lanes outside the image never start
    store_lanes(&sb[4], izero);
    if constexpr (kSurface) init_surface<LF, LI>(in.surface, C, s.entry_depth.data(), n, pix, sb + kBlockFixed + C);
  }
  s.reserve(n, C, box.h);
  s.done.assign(nb, 0);
  const int words = (nb + 63) / 64;
  const BlockMap map = rect_blocks<kW, kH>(bw);
  if (s.list.size() < static_cast<size_t>(kForwardChunk) + kListSlack) s.list.resize(kForwardChunk + kListSlack);
  int32_t* list = s.list.data();
  uint8_t* done = s.done.data();
  int* span_lo = s.span_lo.data();
  int* span_hi = s.span_hi.data();
  int alive = nb;
  for (int k0 = 0; k0 < n && alive > 0; k0 += kForwardChunk) {
    const int k1 = std::min(n, k0 + kForwardChunk);
    s.gather(in, geo, lo, k0, k1);
    s.prefetch_splats(in, geo, lo, k1, std::min(n, k1 + kForwardChunk));  // the next chunk's, during this one
    s.block_bits.assign(static_cast<size_t>(k1 - k0) * words, 0);
    for (int k = k0; k < k1; ++k)
      reach_blocks<kLanes == 8>(s.entries[k], box, map, nb, words, span_lo, span_hi,
                                &s.block_bits[static_cast<size_t>(k - k0) * words]);
    const int groups = block_columns(s.block_bits.data(), words, k1 - k0, nb, s.block_cols);  // 1 while kForwardChunk <= 64
    for (int b = 0; b < nb; ++b) {
      if (done[b]) continue;
      const int count = block_list(&s.block_cols[static_cast<size_t>(b) * groups], k1 - k0, k0, list);
      if (count == 0) continue;
      LF* sb = st + static_cast<size_t>(b) * S;
      if (!composite_block<LF, LI, CC, kSurface>(s, sb, C, list, count)) {
        done[b] = 1;
        --alive;
      }
    }
  }
  if constexpr (kSurface)
    for (int b = 0; b < nb; ++b) finish_surface<LF, LI>(st + static_cast<size_t>(b) * S, C);
  for (int b = 0; b < nb; ++b) {
    const LF* sb = st + static_cast<size_t>(b) * S;
    LF px, py;
    LI valid;
    rect_pixels(box, b % bw, b / bw, px, py, valid, pix, geo);
    float Ta[kLanes], ca[kLanes];
    int32_t la[kLanes];
    store_lanes(Ta, sb[2]);
    store_lanes(la, load_lanes<LI>(&sb[4]));
    for (int l = 0; l < kLanes; ++l) {
      if (pix[l] < 0) continue;
      out.alpha[pix[l]] = 1.0f - Ta[l];
      out.last[pix[l]] = la[l];
      out.final_T[pix[l]] = Ta[l];
    }
    for (int ch = 0; ch < C; ++ch) {
      store_lanes(ca, sb[kBlockFixed + ch]);
      for (int l = 0; l < kLanes; ++l)
        if (pix[l] >= 0) out.accum[pix[l] * C + ch] = ca[l];
    }
  }
}

// Lanes l of vectors r[0..L) as vector l, for l < L (L = 4 or 8 lanes).
template <class LF>
RM_INLINE void transpose_lanes(const LF* r, LF* c) {
#if defined(MLX3D_RASTER_VECTOR_LANES)
  if constexpr (lanes_of<LF>() == 8) {
    LF t[8], u[8];
    for (int i = 0; i < 8; i += 2) {
      t[i] = __builtin_shufflevector(r[i], r[i + 1], 0, 8, 1, 9, 4, 12, 5, 13);
      t[i + 1] = __builtin_shufflevector(r[i], r[i + 1], 2, 10, 3, 11, 6, 14, 7, 15);
    }
    for (int i = 0; i < 8; i += 4)
      for (int h = 0; h < 2; ++h) {
        u[i + 2 * h] = __builtin_shufflevector(t[i + h], t[i + h + 2], 0, 1, 8, 9, 4, 5, 12, 13);
        u[i + 2 * h + 1] = __builtin_shufflevector(t[i + h], t[i + h + 2], 2, 3, 10, 11, 6, 7, 14, 15);
      }
    // u[0..4): lanes 0-3 of r[0..4) in their low halves (lane l of u[l']: l' = l % 4), lanes 4-7 in
    // their high halves; u[4..8) the same for r[4..8).
    for (int l = 0; l < 4; ++l) {
      c[l] = __builtin_shufflevector(u[l], u[l + 4], 0, 1, 2, 3, 8, 9, 10, 11);
      c[l + 4] = __builtin_shufflevector(u[l], u[l + 4], 4, 5, 6, 7, 12, 13, 14, 15);
    }
    return;
  } else if constexpr (lanes_of<LF>() == 4) {
    const LF t0 = __builtin_shufflevector(r[0], r[1], 0, 4, 1, 5), t1 = __builtin_shufflevector(r[0], r[1], 2, 6, 3, 7);
    const LF t2 = __builtin_shufflevector(r[2], r[3], 0, 4, 1, 5), t3 = __builtin_shufflevector(r[2], r[3], 2, 6, 3, 7);
    c[0] = __builtin_shufflevector(t0, t2, 0, 1, 4, 5);
    c[1] = __builtin_shufflevector(t0, t2, 2, 3, 6, 7);
    c[2] = __builtin_shufflevector(t1, t3, 0, 1, 4, 5);
    c[3] = __builtin_shufflevector(t1, t3, 2, 3, 6, 7);
    return;
  }
#endif
  c[0] = r[0];
}

// out[j] = sum of the lanes of v[j] in lane order, from +0 (((0 + lane 0) + lane 1) + ...), for
// j < count. Groups of L vectors are transposed, so that their L sums run side by side, one per lane,
// each with the same additions in the same order: the bits do not depend on the grouping.
template <class LF>
RM_INLINE void lane_totals(const LF* v, size_t count, float* out) {
  constexpr int L = lanes_of<LF>();
  size_t j = 0;
  for (; j + L <= count; j += L) {
    LF c[L];
    transpose_lanes(v + j, c);
    LF total{};
    for (int l = 0; l < L; ++l) total += c[l];
    store_lanes(out + j, total);
  }
  for (; j < count; ++j) {
    float lanes[L];
    store_lanes(lanes, v[j]);
    float total = 0.0f;
    for (int l = 0; l < L; ++l) total += lanes[l];
    out[j] = total;
  }
}

struct BackwardIn {
  const int32_t* last;
  const float* final_T;
  const float* g_accum;
  const float* g_alpha;
};

// Writes the tile's gradients to entry_grad[(e - lo) * K + field] for its
// entries e before the last one any pixel uses (K = 6 + C fields: mean_x,
// mean_y, conic a, b, c, opacity, features; zero for an entry no pixel uses)
// and returns how many that is: the entries after them have zero gradients,
// left unwritten. Pixel blocks are kLanes consecutive pixels in row-major order
// (the lane sums, and so the gradients' last bits, depend on this grouping);
// each walks back from the largest `last` of its pixels, over the entries that
// reach it.
template <class LF, class LI, int CC>
RM_INLINE int backward_tile_impl(const Inputs& in, const Geometry& geo, int t, Scratch& s, const BackwardIn& bw,
                                 float* entry_grad) {
  constexpr int kLanes = lanes_of<LF>();
  int64_t lo, hi;
  tile_range(in, geo, t, lo, hi);
  const int n = static_cast<int>(hi - lo);
  if (n == 0) return 0;
  const int C = CC > 0 ? CC : geo.channels;
  const int K = kGradFixed + C;
  const TileBox box = tile_box(geo, t);
  const int npix = box.w * box.h;
  const int nb = (npix + kLanes - 1) / kLanes;
  const LF zero{};
  const LI izero{};

  // Entries each block walks: [0, max of its pixels' `last`).
  s.block_kmax.assign(nb, 0);
  int kmax = 0;
  for (int b = 0; b < nb; ++b) {
    int km = 0;
    for (int q = b * kLanes; q < std::min(npix, (b + 1) * kLanes); ++q) {
      const int64_t p = static_cast<int64_t>(box.y0 + q / box.w) * geo.width + (box.x0 + q % box.w);
      km = std::max(km, std::min(std::max(static_cast<int>(bw.last[p]), 0), n));
    }
    s.block_kmax[b] = km;
    kmax = std::max(kmax, km);
  }
  if (kmax == 0) return 0;  // entries from kmax on contribute to no pixel
  s.reserve(kmax, C, box.h);
  s.gather(in, geo, lo, 0, kmax);

  // The blocks each entry reaches (see "block lists").
  int* span_lo = s.span_lo.data();
  int* span_hi = s.span_hi.data();
  const int words = (nb + 63) / 64;
  s.block_bits.assign(static_cast<size_t>(kmax) * words, 0);
  const BlockMap map = run_blocks<kLanes>(box.w);
  for (int k = 0; k < kmax; ++k)
    reach_blocks<kLanes == 8>(s.entries[k], box, map, nb, words, span_lo, span_hi,
                              &s.block_bits[static_cast<size_t>(k) * words]);
  const int groups = block_columns(s.block_bits.data(), words, kmax, nb, s.block_cols);
  if (s.list.size() < static_cast<size_t>(kmax) + kListSlack) s.list.resize(kmax + kListSlack);
  int32_t* list = s.list.data();

  LF* gacc = Scratch::lanes<LF>(s.lane, C);  // dL/daccum of the lanes' pixels, per channel
  LF gacc_reg[CC > 0 ? CC : 1];
  if constexpr (CC > 0) gacc = gacc_reg;
  LF* sums = Scratch::lanes<LF>(s.entry_lanes, static_cast<size_t>(kmax) * K);  // [entry][field]

  for (int blk = 0; blk < nb; ++blk) {
    // The entries before the block's last contributor that reach it, in order.
    const int count = block_list(&s.block_cols[static_cast<size_t>(blk) * groups], s.block_kmax[blk], 0, list);
    if (count == 0) continue;  // no entry reaches it: it adds nothing
    LF px, py;
    LI valid;
    int64_t pix[kLanes];
    block_pixels(box, blk * kLanes, px, py, valid, pix, geo);
    float tf[kLanes], ga[kLanes], gc[kLanes];
    int32_t nl[kLanes];
    for (int l = 0; l < kLanes; ++l) {
      const bool ok = pix[l] >= 0;
      nl[l] = ok ? std::min(std::max(static_cast<int>(bw.last[pix[l]]), 0), n) : 0;
      tf[l] = ok ? bw.final_T[pix[l]] : 1.0f;
      ga[l] = ok ? bw.g_alpha[pix[l]] : 0.0f;
    }
    for (int ch = 0; ch < C; ++ch) {
      for (int l = 0; l < kLanes; ++l) gc[l] = pix[l] >= 0 ? bw.g_accum[pix[l] * C + ch] : 0.0f;
      gacc[ch] = load_lanes<LF>(gc);
    }
    const LI nlast = load_lanes<LI>(nl);
    const LF T_final = load_lanes<LF>(tf);
    const LF g_alpha = load_lanes<LF>(ga);
    LF T = T_final;
    LF prev_alpha = zero;
    // dL/dα needs the colour behind each Gaussian, B (see rm_behind), only
    // through B · dL/daccum, which is linear in B: so the recurrence runs on
    // the dotted colours, one lane vector instead of one per channel.
    LF behind = zero;     // B · dL/daccum
    LF prev_dot = zero;   // f · dL/daccum of the kept Gaussian behind
    // Back to front over the block's entries, in batches: exp and alpha of
    // a batch first (see "pair batches"), then the recurrence.
    constexpr int kBatch = kPairBatch;
    LF gs[kBatch], alphas[kBatch];
    for (int i1 = count; i1 > 0; i1 -= kBatch) {
      const int nbatch = std::min(kBatch, i1);
#pragma GCC unroll 8
      for (int j = 0; j < kBatch; ++j) {
        const Splat& e = s.entries[list[i1 - 1 - std::min(j, nbatch - 1)]];
        const LF dx = e.x - px;
        const LF dy = e.y - py;
        const LF power = rm_power(splat<LF>(e.a), splat<LF>(e.b), splat<LF>(e.c), dx, dy);
        gs[j] = rm_exp(power);
        alphas[j] = rm_alpha(splat<LF>(e.op), gs[j], power);
      }
      for (int j = 0; j < nbatch; ++j) {
        const int k = list[i1 - 1 - j];
        const LI use = ((izero + k) < nlast) & (alphas[j] > 0.0f);
        if (!any_lane(use)) continue;
        const Splat& e = s.entries[k];
        const LF ca = splat<LF>(e.a), cb = splat<LF>(e.b), cc = splat<LF>(e.c), o = splat<LF>(e.op);
        const LF dx = e.x - px;
        const LF dy = e.y - py;
        const LF g = gs[j];
        const LF alpha_k = alphas[j];
        const LF alpha = use ? alpha_k : 0.0f;
        T = rm_T_before(T, alpha);  // unchanged (T / 1) where not used
        const LF w = alpha * T;
        const LF pa = prev_alpha;
        prev_alpha = use ? alpha : prev_alpha;
        LF* ek = sums + static_cast<size_t>(k) * K;
        const float* f = s.template features<CC>(k, C);
        LF f_dot = zero;  // f · dL/daccum
        for (int ch = 0; ch < C; ++ch) {
          f_dot += splat<LF>(f[ch]) * gacc[ch];
          ek[kGradFixed + ch] += use ? w * gacc[ch] : 0.0f;
        }
        const LF nbh = rm_behind(behind, pa, prev_dot);
        behind = use ? nbh : behind;
        prev_dot = use ? f_dot : prev_dot;
        const LF dl_dalpha = rm_dl_dalpha(T, f_dot - nbh, T_final, g_alpha, alpha);  // used lanes only
        const RmGaussGrad<LF> gg = rm_gaussian_grad(ca, cb, cc, dx, dy, o, g, dl_dalpha);
        ek[0] += use ? gg.mean_x : 0.0f;
        ek[1] += use ? gg.mean_y : 0.0f;
        ek[2] += use ? gg.conic_a : 0.0f;
        ek[3] += use ? gg.conic_b : 0.0f;
        ek[4] += use ? gg.conic_c : 0.0f;
        ek[5] += use ? gg.opacity : 0.0f;
      }
    }
  }
  lane_totals(sums, static_cast<size_t>(kmax) * K, entry_grad);
  return kmax;
}

// ------------------------------------------------------------- variants
// The tile kernels are compiled for the baseline ISA (4 lanes with GCC: SSE2
// on x86-64, NEON on arm64; 1 lane otherwise) and, on x86-64 with GCC, for
// AVX2 (8 lanes), picked at run time from the CPU. MLX3D_RASTER_ISA=baseline
// in the environment forces the baseline variant (read at each evaluation).
// Forward outputs are identical across variants; backward lane sums group
// pixels differently, so gradients may differ in the last bits. Each variant
// is also instantiated for 1 to 4 channels (features held in registers) and
// for any number of channels; these give identical results.
using ForwardTileFn = void (*)(const Inputs&, const Geometry&, int, Scratch&, const ForwardOut&);
using BackwardTileFn = int (*)(const Inputs&, const Geometry&, int, Scratch&, const BackwardIn&, float*);

#if defined(MLX3D_RASTER_VECTOR_LANES)
using BaseF = LaneF4;
using BaseI = LaneI4;
#else
using BaseF = float;
using BaseI = int32_t;
#endif

template <int CC, bool kSurface>
void forward_tile_base(const Inputs& in, const Geometry& geo, int t, Scratch& s, const ForwardOut& out) {
  forward_tile_impl<BaseF, BaseI, CC, kSurface>(in, geo, t, s, out);
}
template <int CC>
int backward_tile_base(const Inputs& in, const Geometry& geo, int t, Scratch& s, const BackwardIn& bw, float* eg) {
  return backward_tile_impl<BaseF, BaseI, CC>(in, geo, t, s, bw, eg);
}

#if defined(MLX3D_RASTER_AVX2)
template <int CC, bool kSurface>
__attribute__((target("avx2"))) void forward_tile_avx2(const Inputs& in, const Geometry& geo, int t, Scratch& s,
                                                       const ForwardOut& out) {
  forward_tile_impl<LaneF8, LaneI8, CC, kSurface>(in, geo, t, s, out);
}
template <int CC>
__attribute__((target("avx2"))) int backward_tile_avx2(const Inputs& in, const Geometry& geo, int t, Scratch& s,
                                                       const BackwardIn& bw, float* eg) {
  return backward_tile_impl<LaneF8, LaneI8, CC>(in, geo, t, s, bw, eg);
}
#endif

#if defined(MLX3D_RASTER_AVX2)
// Whether the CPU has AVX2 and the OS saves the AVX registers (CPUID and XGETBV, as compiler runtimes check it:
// zig's has no __builtin_cpu_supports).
bool cpu_has_avx2() {
  unsigned a, b, c, d;
  if (!__get_cpuid(1, &a, &b, &c, &d) || !(c & (1u << 27)) || !(c & (1u << 28))) return false;  // OSXSAVE, AVX
  unsigned lo, hi;
  __asm__ volatile("xgetbv" : "=a"(lo), "=d"(hi) : "c"(0));
  if ((lo & 6u) != 6u) return false;  // the OS saves XMM and YMM state
  if (__get_cpuid_max(0, nullptr) < 7) return false;
  __cpuid_count(7, 0, a, b, c, d);
  return (b & (1u << 5)) != 0;  // AVX2
}
#endif

bool use_avx2() {
#if defined(MLX3D_RASTER_AVX2)
  static const bool has_avx2 = cpu_has_avx2();
  const char* isa = std::getenv("MLX3D_RASTER_ISA");
  return has_avx2 && !(isa && std::strcmp(isa, "baseline") == 0);
#else
  return false;
#endif
}

int simd_lanes() {
  return use_avx2() ? 8 : lanes_of<BaseF>();
}

// fns[0]: any channel count; fns[c]: c channels.
template <class Fn>
Fn pick_channels(const Fn (&fns)[kMaxFixedChannels + 1], int channels) {
  return channels >= 1 && channels <= kMaxFixedChannels ? fns[channels] : fns[0];
}

// The forward tile kernel for `channels`, plain or with a surface layer.
ForwardTileFn pick_forward(int channels, bool surface) {
#if defined(MLX3D_RASTER_AVX2)
  static const ForwardTileFn avx2[2][kMaxFixedChannels + 1] = {
      {forward_tile_avx2<0, false>, forward_tile_avx2<1, false>, forward_tile_avx2<2, false>,
       forward_tile_avx2<3, false>, forward_tile_avx2<4, false>},
      {forward_tile_avx2<0, true>, forward_tile_avx2<1, true>, forward_tile_avx2<2, true>, forward_tile_avx2<3, true>,
       forward_tile_avx2<4, true>}};
  if (use_avx2()) return pick_channels(avx2[surface], channels);
#endif
  static const ForwardTileFn base[2][kMaxFixedChannels + 1] = {
      {forward_tile_base<0, false>, forward_tile_base<1, false>, forward_tile_base<2, false>,
       forward_tile_base<3, false>, forward_tile_base<4, false>},
      {forward_tile_base<0, true>, forward_tile_base<1, true>, forward_tile_base<2, true>, forward_tile_base<3, true>,
       forward_tile_base<4, true>}};
  return pick_channels(base[surface], channels);
}

BackwardTileFn pick_backward(int channels) {
#if defined(MLX3D_RASTER_AVX2)
  static const BackwardTileFn avx2[] = {backward_tile_avx2<0>, backward_tile_avx2<1>, backward_tile_avx2<2>,
                                        backward_tile_avx2<3>, backward_tile_avx2<4>};
  if (use_avx2()) return pick_channels(avx2, channels);
#endif
  static const BackwardTileFn base[] = {backward_tile_base<0>, backward_tile_base<1>, backward_tile_base<2>,
                                        backward_tile_base<3>, backward_tile_base<4>};
  return pick_channels(base, channels);
}

// Runs fn(tile, scratch) for tiles [t0, t1) on `threads` threads.
template <typename Fn>
void parallel_tiles(int t0, int t1, int threads, std::vector<Scratch>& scratch, Fn&& fn) {
  parallel_items(t0, t1, threads, [&](int t, int id) { fn(t, scratch[id]); });
}

// The Splat records of all Gaussians (with reach bounds unless culling is off).
HugePageArray<Splat> make_splats(const Inputs& in, const Geometry& geo, int threads) {
  const int64_t n = geo.num_gaussians;
  HugePageArray<Splat> splats(static_cast<size_t>(n));  // tiles gather them in random order
  // Pixel centres are exact floats (as the bounds assume) up to 2^23.
  const bool cull = culling_enabled() && geo.width <= (1 << 22) && geo.height <= (1 << 22);
  constexpr int64_t kBlock = 4096;
  const int blocks = static_cast<int>((n + kBlock - 1) / kBlock);
  parallel_items(0, blocks, threads, [&](int blk, int) {
    for (int64_t g = blk * kBlock; g < std::min(n, (blk + 1) * kBlock); ++g) make_splat(in, geo, g, cull, splats[g]);
  });
  return splats;
}

void run_forward(Inputs in, const Geometry& geo, int num_threads, const ForwardOut& out, bool surface) {
  const std::vector<int64_t> ranges = sanitise_offsets(in.offsets, geo);
  in.ranges = ranges.data();
  const int tiles = geo.num_tiles();
  const int threads = resolve_threads(num_threads, tiles);
  const HugePageArray<Splat> splats = make_splats(in, geo, threads);
  in.splats = splats.data();
  std::vector<Scratch> scratch(threads);
  const ForwardTileFn forward_tile = pick_forward(geo.channels, surface);
  parallel_tiles(0, tiles, threads, scratch,
                 [&](int t, Scratch& s) { forward_tile(in, geo, t, s, out); });
}

struct GradOut {
  float* means;
  float* conics;
  float* features;
  float* opacities;
};

// Per-Gaussian ranges of at least this many Gaussians per thread for the output passes.
constexpr int64_t kMinGaussiansPerThread = 4096;

// Adds the slots of entries [lo0, hi1) (slots[(e - lo0) * K + field]) to acc[g * K + field] of
// their Gaussians g, in flatten_ids order. Bound by memory latency (the Gaussians come in random
// order), so the next Gaussians' sums are prefetched.
void add_slots(const Inputs& in, int64_t N, int K, int64_t lo0, int64_t hi1, const float* slots, float* acc) {
  constexpr int64_t kAhead = 16;
  for (int64_t e = lo0; e < hi1; ++e) {
    if (e + kAhead < hi1) {
      const int64_t ga = in.ids[e + kAhead];
      if (ga >= 0 && ga < N) prefetch<true>(acc + ga * K);
    }
    const int64_t g = in.ids[e];
    if (g < 0 || g >= N) continue;
    const float* v = slots + (e - lo0) * K;
    float* a = acc + g * K;
    for (int j = 0; j < K; ++j) a[j] += v[j];
  }
}

// Slot floats per chunk of tiles in the backward pass: the two chunk buffers take 8 MB, which glibc
// serves from memory it already holds once the first pass has freed them. Buffers of 16 MB each came
// from fresh pages every pass (a page fault and a zeroed page per 4 KB: 30-40 ms of CPU per step at
// 138,766 Gaussians, 648x420); smaller chunks are not slower (docs/design/training-step-history.md, "A training step at
// real-capture sizes").
constexpr int64_t kSlotBudget = int64_t(1) << 20;

// Adds every tile entry's gradient slots to acc[g * K + field] of its Gaussian g, in flatten_ids order.
//
// Tiles are taken in chunks of consecutive tiles holding at most kSlotBudget slot floats (or one
// tile), each chunk's slots in one of two buffers. A chunk's slots are added to the per-Gaussian sums by
// thread 0 alone, in order, so the sums do not depend on the thread count. Summing one thread
// measured faster than splitting it among threads (docs/design/training-step-history.md, "A training step at real-capture
// sizes"), so instead it overlaps the other threads' tiles: thread 0 sums chunk c as soon as all of
// its tiles are done, while the others go on with chunk c + 1 (a tile of chunk c + 2 waits until
// chunk c is summed, whose buffer it reuses). The slot buffers are left uninitialised: each tile
// writes the slots of its entries up to its last used one, and only those are summed (the others'
// gradients are zero, and adding +0 changes no sum: a sum from +0 is never -0).
void accumulate_entries(Inputs in, const Geometry& geo, int num_threads, const BackwardIn& bw, float* acc) {
  const int C = geo.channels;
  const int K = kGradFixed + C;
  const int64_t N = geo.num_gaussians;
  const int tiles = geo.num_tiles();
  const std::vector<int64_t> ranges = sanitise_offsets(in.offsets, geo);
  in.ranges = ranges.data();
  const int threads = resolve_threads(num_threads, tiles);
  const HugePageArray<Splat> splats = make_splats(in, geo, threads);
  in.splats = splats.data();
  std::vector<Scratch> scratch(threads);
  const BackwardTileFn backward_tile = pick_backward(C);
  const int64_t budget = std::max<int64_t>(1, kSlotBudget / K);
  std::vector<int> chunk_start{0};  // first tile of each chunk, then `tiles`
  std::vector<int> chunk_of(tiles);
  int64_t largest = 0;
  while (chunk_start.back() < tiles) {
    const int t0 = chunk_start.back();
    int t1 = t0 + 1;
    while (t1 < tiles && ranges[t1 + 1] - ranges[t0] <= budget) ++t1;
    largest = std::max(largest, ranges[t1] - ranges[t0]);
    for (int t = t0; t < t1; ++t) chunk_of[t] = static_cast<int>(chunk_start.size()) - 1;
    chunk_start.push_back(t1);
  }
  const int chunks = static_cast<int>(chunk_start.size()) - 1;
  const size_t buffer_floats = static_cast<size_t>(largest) * K;
  std::unique_ptr<float[]> buffers(new float[(chunks > 1 ? 2 : 1) * buffer_floats]);
  // Tile t's slots: in its chunk's buffer (chunks alternate between the two), after the chunk's earlier tiles.
  auto slots_of = [&](int t) {
    const int c = chunk_of[t];
    return buffers.get() + static_cast<size_t>(c % 2) * buffer_floats + (ranges[t] - ranges[chunk_start[c]]) * K;
  };

  std::vector<int> used(tiles);  // entries with slots written, per tile
  std::atomic<int> summed(0);   // chunks [0, summed) are in acc
  std::unique_ptr<std::atomic<int>[]> tiles_left(new std::atomic<int>[chunks]);
  for (int c = 0; c < chunks; ++c) tiles_left[c].store(chunk_start[c + 1] - chunk_start[c]);
  // Thread 0: sums every chunk whose tiles are all done, in order; returns whether it summed one.
  auto sum_ready = [&]() {
    bool any = false;
    for (int c = summed.load(std::memory_order_relaxed); c < chunks && tiles_left[c].load(std::memory_order_acquire) == 0; ++c) {
      for (int t = chunk_start[c]; t < chunk_start[c + 1]; ++t) add_slots(in, N, K, ranges[t], ranges[t] + used[t], slots_of(t), acc);
      summed.store(c + 1, std::memory_order_release);
      any = true;
    }
    return any;
  };
  parallel_items(0, tiles, threads, [&](int t, int id) {
    const int c = chunk_of[t];
    while (summed.load(std::memory_order_acquire) < c - 1)  // chunk c - 2 still holds the buffer
      if (id != 0 || !sum_ready()) std::this_thread::yield();
    used[t] = backward_tile(in, geo, t, scratch[id], bw, slots_of(t));
    tiles_left[c].fetch_sub(1, std::memory_order_acq_rel);
    if (id == 0) sum_ready();
  });
  sum_ready();  // the chunks whose tiles finished last (every tile is done now)
}

void run_backward(Inputs in, const Geometry& geo, int num_threads, const BackwardIn& bw, const GradOut& out) {
  const int C = geo.channels;
  const int K = kGradFixed + C;
  const int64_t N = geo.num_gaussians;
  const int tiles = geo.num_tiles();
  // Per-Gaussian sums, K interleaved fields per Gaussian (one or two cache lines per update), split
  // into the four outputs at the end.
  HugePageArray<float> sums(static_cast<size_t>(N) * K);  // updated in random Gaussian order
  float* acc = sums.data();
  parallel_blocks(N, num_threads, kMinGaussiansPerThread, [acc, K](int64_t g0, int64_t g1) {
    std::fill(acc + g0 * K, acc + g1 * K, 0.0f);
  });
  if (N > 0 && geo.num_entries > 0 && tiles > 0) accumulate_entries(in, geo, num_threads, bw, acc);
  parallel_blocks(N, num_threads, kMinGaussiansPerThread, [out, acc, C, K](int64_t g0, int64_t g1) {
    for (int64_t g = g0; g < g1; ++g) {
      const float* v = acc + g * K;
      out.means[2 * g] = v[0];
      out.means[2 * g + 1] = v[1];
      out.conics[3 * g] = v[2];
      out.conics[3 * g + 1] = v[3];
      out.conics[3 * g + 2] = v[4];
      out.opacities[g] = v[5];
      std::copy(v + kGradFixed, v + K, out.features + g * C);
    }
  });
}

// The background composite of the CPU path, on threads over the pixels: accum += (1 - alpha) bg (C
// channels per pixel), and its gradient with respect to alpha, g_alpha - sum_c g_accum[c] bg[c] (the
// channel sum in channel order). Each is the float32 arithmetic of the MLX expression it replaces,
// accum + (1 - alpha)[..., None] * bg (mlx3d.render.rasterize.composite), so results keep their bits.
void add_background(float* accum, const float* alpha, const float* bg, int C, int64_t pixels, int num_threads) {
  parallel_blocks(pixels, num_threads, 16384, [=](int64_t lo, int64_t hi) {
    for (int64_t p = lo; p < hi; ++p) {
      const float t = 1.0f - alpha[p];
      for (int c = 0; c < C; ++c) accum[p * C + c] = accum[p * C + c] + t * bg[c];
    }
  });
}

void background_alpha_grad(const float* g_accum, const float* g_alpha, const float* bg, int C, int64_t pixels,
                           int num_threads, float* out) {
  parallel_blocks(pixels, num_threads, 16384, [=](int64_t lo, int64_t hi) {
    for (int64_t p = lo; p < hi; ++p) {
      float along = 0.0f;
      for (int c = 0; c < C; ++c) along = along + g_accum[p * C + c] * bg[c];
      out[p] = g_alpha[p] + -along;
    }
  });
}

void check_sizes(int64_t n, int channels, int64_t m, int width, int height, int tile_size, int threads) {
  require(width >= 1 && height >= 1, "width and height must be >= 1, got " + std::to_string(width) + " x " + std::to_string(height));
  require(tile_size >= 1, "tile_size must be >= 1, got " + std::to_string(tile_size));
  require(n >= 0 && n <= INT32_MAX, "the count of Gaussians must be in [0, 2^31), got " + std::to_string(n));
  require(m >= 0 && m <= INT32_MAX, "the count of tile entries must be in [0, 2^31), got " + std::to_string(m));
  require(channels >= 1, "channels must be >= 1, got " + std::to_string(channels));
  require(threads >= 0, "threads must be >= 0 (0 = every hardware thread), got " + std::to_string(threads));
}

Inputs input_pointers(const float* means2d, const float* conics, const float* features, const float* opacities,
                      const int32_t* tile_offsets, const int32_t* flatten_ids, int64_t n, int64_t m) {
  require(tile_offsets != nullptr, "tile_offsets is a null pointer");
  require(n == 0 || (means2d && conics && features && opacities), "a null Gaussian array");
  require(m == 0 || flatten_ids, "flatten_ids is a null pointer");
  Inputs in;
  in.means = means2d;
  in.conics = conics;
  in.features = features;
  in.opacities = opacities;
  in.offsets = tile_offsets;
  in.ids = flatten_ids;
  return in;
}

}  // namespace
}  // namespace mlx3d

using namespace mlx3d;

extern "C" {

MLX3D_API int mlx3d_rasterizer_lanes(void) { return simd_lanes(); }

MLX3D_API int mlx3d_rasterize_forward(const float* means2d, const float* conics, const float* features, const float* opacities,
                                      const int32_t* tile_offsets, const int32_t* flatten_ids, int64_t n, int channels, int64_t m,
                                      int width, int height, int tile_size, const float* background, int threads, float* accum,
                                      float* alpha, int32_t* last, float* final_T) {
  return guarded("mlx3d_rasterize_forward", [&] {
    check_sizes(n, channels, m, width, height, tile_size, threads);
    const Inputs in = input_pointers(means2d, conics, features, opacities, tile_offsets, flatten_ids, n, m);
    require(accum && alpha && last && final_T, "an output is a null pointer");
    const Geometry geo = make_geometry(width, height, tile_size, n, channels, m);
    const ForwardOut out{accum, alpha, last, final_T};
    run_forward(in, geo, threads, out, false);
    if (background) add_background(accum, alpha, background, channels, int64_t(width) * height, threads);
  });
}

MLX3D_API int mlx3d_rasterize_forward_surface(const float* means2d, const float* conics, const float* features,
                                              const float* opacities, const int32_t* tile_offsets, const int32_t* flatten_ids,
                                              int64_t n, int channels, int64_t m, int width, int height, int tile_size,
                                              const float* depths, const float* surface_color, const float* surface_alpha,
                                              const float* surface_depth, int threads, float* accum, float* alpha, int32_t* last,
                                              float* final_T) {
  return guarded("mlx3d_rasterize_forward_surface", [&] {
    check_sizes(n, channels, m, width, height, tile_size, threads);
    Inputs in = input_pointers(means2d, conics, features, opacities, tile_offsets, flatten_ids, n, m);
    require((n == 0 || depths) && surface_color && surface_alpha && surface_depth, "a surface input is a null pointer");
    require(accum && alpha && last && final_T, "an output is a null pointer");
    in.surface = {depths, surface_color, surface_alpha, surface_depth};
    const Geometry geo = make_geometry(width, height, tile_size, n, channels, m);
    run_forward(in, geo, threads, ForwardOut{accum, alpha, last, final_T}, true);
  });
}

MLX3D_API int mlx3d_rasterize_backward(const float* means2d, const float* conics, const float* features, const float* opacities,
                                       const int32_t* tile_offsets, const int32_t* flatten_ids, int64_t n, int channels, int64_t m,
                                       int width, int height, int tile_size, const int32_t* last, const float* final_T,
                                       const float* d_accum, const float* d_alpha, const float* background, int threads,
                                       float* d_means2d, float* d_conics, float* d_features, float* d_opacities) {
  return guarded("mlx3d_rasterize_backward", [&] {
    check_sizes(n, channels, m, width, height, tile_size, threads);
    const Inputs in = input_pointers(means2d, conics, features, opacities, tile_offsets, flatten_ids, n, m);
    require(last && final_T && d_accum && d_alpha, "a forward output or a cotangent is a null pointer");
    require(n == 0 || (d_means2d && d_conics && d_features && d_opacities), "an output is a null pointer");
    const Geometry geo = make_geometry(width, height, tile_size, n, channels, m);
    BackwardIn bw{last, final_T, d_accum, d_alpha};
    std::vector<float> g_alpha;  // dL/dalpha with the background's term
    if (background) {
      g_alpha.resize(static_cast<size_t>(width) * height);
      background_alpha_grad(d_accum, d_alpha, background, channels, static_cast<int64_t>(g_alpha.size()), threads, g_alpha.data());
      bw.g_alpha = g_alpha.data();
    }
    run_backward(in, geo, threads, bw, GradOut{d_means2d, d_conics, d_features, d_opacities});
  });
}

}  // extern "C"
