// One Adam step on a parameter array as CPU MLX primitives, and the finiteness check the trainer runs
// before it: the kernel library's mlx3d_adam_moment, mlx3d_adam_param and mlx3d_all_finite
// (kernels/adam.cpp, mlx3d_kernels.h) run on MLX arrays.
//
//   m' = b1 m + (1 - b1) g;  v' = b2 v + (1 - b2) g²;  p' = p - lr (m' / c1) / (sqrt(v' / c2) + eps)
//
// with the bias corrections c1 = 1 - b1^t, c2 = 1 - b2^t given by the caller: AdamMoment (m', then v')
// and AdamParam (p'). AllFinite checks a step's loss and gradients first (the trainer updates only when
// they are finite).
//
// Each is a single-output primitive, so MLX's own donation rule applies: its output is written over its
// first input when nothing else holds that array (then m' over m, v' over v, p' over p; the library's
// functions may update in place). A fresh buffer costs a page fault and zeroing per 4 KB page on first
// touch (writing 236 MB of fresh pages took 170-210 ms here, against 40 ms for memory already touched),
// and the old and new arrays then coexist (3 x 236 MB at 1M Gaussians). mlx3d.training.adam.Adam drops
// its old moments for the new ones, and the trainer drops its parameters before evaluating the update
// (after the step's gradients, whose graph holds them).
#include <nanobind/nanobind.h>
#include <nanobind/stl/vector.h>

#include <cstdint>
#include <memory>
#include <stdexcept>
#include <string>
#include <utility>
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

// The step's scalars as the caller gave them (the library rounds them to float32).
struct AdamScalars {
  double lr, b1, b2, eps, c1, c2;
};

// `out` over input k's buffer where MLX may donate it (nothing else holds it; MLX's rule) and no other input
// shares it, else a fresh buffer.
void output_over(const std::vector<mx::array>& inputs, int k, mx::array& out) {
  const mx::array& a = inputs[k];
  bool donate = a.is_donatable() && a.flags().row_contiguous && a.data_size() == a.size();
  for (int j = 0; j < static_cast<int>(inputs.size()); ++j) donate = donate && (j == k || inputs[j].data_shared_ptr() != a.data_shared_ptr());
  if (donate)
    out.copy_shared_buffer(a);
  else
    out.set_data(mx::allocator::malloc(out.nbytes()));
}

class AdamBase : public CpuPrimitive {
 public:
  AdamBase(mx::Stream stream, AdamScalars s, int num_threads)
      : CpuPrimitive(stream, "Apple GPUs use the MLX expression in mlx3d.training.adam"), s_(s), num_threads_(num_threads) {}

  std::vector<mx::array> vjp(const std::vector<mx::array>&, const std::vector<mx::array>&, const std::vector<int>&,
                             const std::vector<mx::array>&) override {
    throw std::runtime_error(std::string(name()) + " is an optimizer update and has no gradient.");
  }

  bool is_equivalent(const mx::Primitive& other) const override {
    const auto* o = dynamic_cast<const AdamBase*>(&other);
    return o && std::string(o->name()) == name() && o->num_threads_ == num_threads_ && o->s_.lr == s_.lr &&
           o->s_.b1 == s_.b1 && o->s_.b2 == s_.b2 && o->s_.eps == s_.eps && o->s_.c1 == s_.c1 && o->s_.c2 == s_.c2;
  }

 protected:
  AdamScalars s_;
  int num_threads_;
};

// inputs: g, x (the moment); output: x' (the first moment, or with `squared` the second), over x when donated.
class AdamMoment : public AdamBase {
 public:
  AdamMoment(mx::Stream stream, AdamScalars s, int num_threads, bool squared) : AdamBase(stream, s, num_threads), squared_(squared) {}

  void eval_cpu(const std::vector<mx::array>& inputs, std::vector<mx::array>& outputs) override {
    output_over(inputs, 1, outputs[0]);
    auto& encoder = register_arrays(*this, inputs, outputs);
    const float *g = inputs[0].data<float>(), *x = inputs[1].data<float>();
    float* out = outputs[0].data<float>();
    const int64_t n = inputs[0].size();
    const double beta = squared_ ? s_.b2 : s_.b1;
    encoder.dispatch([=, squared = int(squared_), threads = num_threads_]() {
      check_call(mlx3d_adam_moment(g, x, n, beta, squared, threads, out));
    });
  }

  std::vector<mx::Shape> output_shapes(const std::vector<mx::array>& inputs) override { return {inputs[0].shape()}; }

  const char* name() const override { return squared_ ? "AdamSecondMoment" : "AdamFirstMoment"; }

 private:
  bool squared_;
};

// inputs: p, m', v'; output: p', over p when MLX may donate it (nothing else holds p).
class AdamParam : public AdamBase {
 public:
  using AdamBase::AdamBase;

  void eval_cpu(const std::vector<mx::array>& inputs, std::vector<mx::array>& outputs) override {
    output_over(inputs, 0, outputs[0]);
    auto& encoder = register_arrays(*this, inputs, outputs);
    const float *p = inputs[0].data<float>(), *m = inputs[1].data<float>(), *v = inputs[2].data<float>();
    float* p_out = outputs[0].data<float>();
    const int64_t n = inputs[0].size();
    encoder.dispatch([=, s = s_, threads = num_threads_]() {
      check_call(mlx3d_adam_param(p, m, v, n, s.lr, s.eps, s.c1, s.c2, threads, p_out));
    });
  }

  std::vector<mx::Shape> output_shapes(const std::vector<mx::array>& inputs) override { return {inputs[0].shape()}; }

  const char* name() const override { return "AdamParam"; }
};

// A bool scalar: true when no element of any (float32) input is NaN or infinite (mlx3d_all_finite on each
// input in turn, one threaded pass reading it once).
class AllFinite : public CpuPrimitive {
 public:
  AllFinite(mx::Stream stream, int num_threads)
      : CpuPrimitive(stream, "Apple GPUs use the MLX expression in mlx3d.training.adam"), num_threads_(num_threads) {}

  void eval_cpu(const std::vector<mx::array>& inputs, std::vector<mx::array>& outputs) override {
    auto& encoder = prepare_outputs(*this, inputs, outputs);
    std::vector<std::pair<const float*, int64_t>> arrays;
    for (const auto& a : inputs) arrays.emplace_back(a.data<float>(), static_cast<int64_t>(a.size()));
    bool* out = outputs[0].data<bool>();
    encoder.dispatch([arrays, out, threads = num_threads_]() {
      uint8_t finite = 1;
      for (size_t i = 0; i < arrays.size() && finite; ++i)
        check_call(mlx3d_all_finite(arrays[i].first, arrays[i].second, threads, &finite));
      *out = finite != 0;
    });
  }

  std::vector<mx::array> vjp(const std::vector<mx::array>&, const std::vector<mx::array>&, const std::vector<int>&,
                             const std::vector<mx::array>&) override {
    throw std::runtime_error("AllFinite has no gradient.");
  }

  std::vector<mx::Shape> output_shapes(const std::vector<mx::array>&) override { return {{}}; }

  const char* name() const override { return "AllFinite"; }

  bool is_equivalent(const mx::Primitive& other) const override {
    const auto* o = dynamic_cast<const AllFinite*>(&other);
    return o && o->num_threads_ == num_threads_;
  }

 private:
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
  const AdamScalars s{lr, b1, b2, eps, c1, c2};
  auto st = mx::default_stream(mx::Device::cpu);
  auto c = [&](const mx::array& a) { return mx::contiguous(a, false, st); };
  const mx::array gc = c(g);
  mx::array m_new(p.shape(), mx::float32, std::make_shared<AdamMoment>(st, s, num_threads, false), {gc, c(m)});
  mx::array v_new(p.shape(), mx::float32, std::make_shared<AdamMoment>(st, s, num_threads, true), {gc, c(v)});
  mx::array p_new(p.shape(), mx::float32, std::make_shared<AdamParam>(st, s, num_threads), {c(p), m_new, v_new});
  return {p_new, m_new, v_new};
}

mx::array all_finite(const std::vector<mx::array>& arrays, int num_threads) {
  if (num_threads < 0) throw std::invalid_argument("all_finite: num_threads must be >= 0 (0 = all cores)");
  auto st = mx::default_stream(mx::Device::cpu);
  std::vector<mx::array> inputs;
  for (const auto& a : arrays) inputs.push_back(mx::contiguous(mx::astype(a, mx::float32, st), false, st));
  if (inputs.empty()) return mx::array(true);
  return mx::array(mx::Shape{}, mx::bool_, std::make_shared<AllFinite>(st, num_threads), inputs);
}

}  // namespace

void bind_adam(nb::module_& m) {
  m.def("adam_step", &adam_step, "p"_a, "g"_a, "m"_a, "v"_a, "lr"_a, "b1"_a, "b2"_a, "eps"_a, "c1"_a, "c2"_a,
        "num_threads"_a = 0,
        "One Adam step on float32 arrays of one shape: returns [p', m', v'] (MLX primitives, CPU, threaded).\n"
        "Each takes over the buffer of m, v or p where nothing else holds that array (MLX's donation).\n"
        "c1, c2: the bias corrections 1 - b1^t, 1 - b2^t. Used by mlx3d.training.adam.Adam.");
  m.def("all_finite", &all_finite, "arrays"_a, "num_threads"_a = 0,
        "A bool scalar (MLX primitive, CPU, threaded): True when no element of any array is NaN or infinite.");
}

}  // namespace mlx3d
