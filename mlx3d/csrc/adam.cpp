// One Adam step on a parameter array as a CPU MLX primitive: one threaded pass that reads
// p, g, m, v and writes p', m', v' (the MLX expression of mlx3d.training.adam.Adam makes a
// pass per operation). Elementwise, so results do not depend on the thread count.
//
//   m' = b1 m + (1 - b1) g;  v' = b2 v + (1 - b2) g²;  p' = p - lr (m' / c1) / (sqrt(v' / c2) + eps)
//
// with the bias corrections c1 = 1 - b1^t, c2 = 1 - b2^t given by the caller. A fourth output says
// whether every gradient entry is finite, found in the same pass (the trainer keeps the old
// parameters when one is not, instead of making another pass over all gradients first).
#include <nanobind/nanobind.h>
#include <nanobind/stl/vector.h>

#include <atomic>
#include <cmath>
#include <cstring>
#include <cstdint>
#include <memory>
#include <stdexcept>
#include <string>
#include <vector>

#include "bindings.h"
#include "mlx/array.h"
#include "mlx/ops.h"
#include "mlx/primitives.h"
#include "primitive_util.h"

namespace nb = nanobind;
namespace mx = mlx::core;
using namespace nb::literals;

namespace mlx3d {
namespace {

constexpr int64_t kBlock = 1 << 16;  // at least this many floats per thread

struct AdamScalars {
  float lr, b1, one_minus_b1, b2, one_minus_b2, eps, c1, c2;
};

// Returns true when every g[i] is finite.
bool run_adam(const float* p, const float* g, const float* m, const float* v, float* p_out, float* m_out, float* v_out,
              int64_t n, AdamScalars s, int num_threads) {
  std::atomic<bool> finite(true);
  parallel_ranges(n, num_threads, kBlock, [=, &finite](int64_t lo, int64_t hi) {
    uint32_t exponent_ones = 0;  // non-zero when some g[i] has an all-ones exponent (inf or NaN)
    for (int64_t i = lo; i < hi; ++i) {
      const float gi = g[i];
      uint32_t bits;
      std::memcpy(&bits, &gi, 4);
      exponent_ones |= uint32_t((bits & 0x7f800000u) == 0x7f800000u);
      const float mi = s.b1 * m[i] + s.one_minus_b1 * gi;
      const float vi = s.b2 * v[i] + s.one_minus_b2 * (gi * gi);
      m_out[i] = mi;
      v_out[i] = vi;
      p_out[i] = p[i] - (s.lr * (mi / s.c1)) / (std::sqrt(vi / s.c2) + s.eps);
    }
    if (exponent_ones) finite.store(false, std::memory_order_relaxed);
  });
  return finite.load();
}

class AdamStep : public CpuPrimitive {
 public:
  AdamStep(mx::Stream stream, AdamScalars s, int num_threads)
      : CpuPrimitive(stream, "Apple GPUs use the MLX expression in mlx3d.training.adam"), s_(s), num_threads_(num_threads) {}

  void eval_cpu(const std::vector<mx::array>& inputs, std::vector<mx::array>& outputs) override {
    auto& encoder = prepare_outputs(*this, inputs, outputs);
    const float *p = inputs[0].data<float>(), *g = inputs[1].data<float>(), *m = inputs[2].data<float>(), *v = inputs[3].data<float>();
    float *po = outputs[0].data<float>(), *mo = outputs[1].data<float>(), *vo = outputs[2].data<float>();
    bool* finite = outputs[3].data<bool>();
    const int64_t n = inputs[0].size();
    encoder.dispatch([=, s = s_, threads = num_threads_]() { *finite = run_adam(p, g, m, v, po, mo, vo, n, s, threads); });
  }

  std::vector<mx::array> vjp(const std::vector<mx::array>&, const std::vector<mx::array>&, const std::vector<int>&,
                             const std::vector<mx::array>&) override {
    throw std::runtime_error("AdamStep is an optimizer update and has no gradient.");
  }

  std::vector<mx::array> jvp(const std::vector<mx::array>&, const std::vector<mx::array>&, const std::vector<int>&) override {
    throw std::runtime_error("AdamStep is an optimizer update and has no gradient.");
  }

  std::vector<mx::Shape> output_shapes(const std::vector<mx::array>& inputs) override {
    return {inputs[0].shape(), inputs[0].shape(), inputs[0].shape(), {}};
  }

  const char* name() const override { return "AdamStep"; }

  bool is_equivalent(const mx::Primitive& other) const override {
    const auto* o = dynamic_cast<const AdamStep*>(&other);
    return o && o->num_threads_ == num_threads_ && o->s_.lr == s_.lr && o->s_.b1 == s_.b1 && o->s_.b2 == s_.b2 &&
           o->s_.eps == s_.eps && o->s_.c1 == s_.c1 && o->s_.c2 == s_.c2;
  }

 private:
  AdamScalars s_;
  int num_threads_;
};

std::vector<mx::array> adam_step(const mx::array& p, const mx::array& g, const mx::array& m, const mx::array& v, double lr,
                                 double b1, double b2, double eps, double c1, double c2, int num_threads) {
  for (const auto* a : {&g, &m, &v})
    if (a->shape() != p.shape())
      throw std::invalid_argument("adam_step: p, g, m and v must have the same shape, got " + shape_str(p) + " and " + shape_str(*a));
  for (const auto* a : {&p, &g, &m, &v})
    if (a->dtype() != mx::float32) throw std::invalid_argument("adam_step: arrays must be float32");
  if (!(c1 > 0) || !(c2 > 0)) throw std::invalid_argument("adam_step: bias corrections c1, c2 must be > 0");
  if (num_threads < 0) throw std::invalid_argument("adam_step: num_threads must be >= 0 (0 = all cores)");
  // the scalars as float32, as MLX rounds Python scalars that meet a float32 array
  const AdamScalars s{float(lr), float(b1), float(1.0 - b1), float(b2), float(1.0 - b2), float(eps), float(c1), float(c2)};
  auto st = mx::default_stream(mx::Device::cpu);
  std::vector<mx::array> inputs;
  for (const auto* a : {&p, &g, &m, &v}) inputs.push_back(mx::contiguous(*a, false, st));
  return mx::array::make_arrays({p.shape(), p.shape(), p.shape(), {}}, {mx::float32, mx::float32, mx::float32, mx::bool_},
                                std::make_shared<AdamStep>(st, s, num_threads), inputs);
}

}  // namespace

void bind_adam(nb::module_& m) {
  m.def("adam_step", &adam_step, "p"_a, "g"_a, "m"_a, "v"_a, "lr"_a, "b1"_a, "b2"_a, "eps"_a, "c1"_a, "c2"_a,
        "num_threads"_a = 0,
        "One Adam step on float32 arrays of one shape: returns [p', m', v', finite] (MLX primitive, CPU,\n"
        "threaded); finite: a bool scalar, True when every entry of g is finite.\n"
        "c1, c2: the bias corrections 1 - b1^t, 1 - b2^t. Used by mlx3d.training.adam.Adam.");
}

}  // namespace mlx3d
