// The 3DGS training loss (1 - λ) L1 + λ (1 - SSIM) of an (H,W,C) render against a photo with its gradient,
// and the per-step MSE, as CPU MLX primitives: the kernel library's mlx3d_photometric_loss / mlx3d_mse
// (kernels/photometric.cpp, mlx3d_kernels.h) run on MLX arrays.
//
// The loss primitive's forward pass writes the gradient with respect to the render too (training always
// needs it); its vjp scales it by the cotangent. The loss is symmetric in (x, y), so the gradient with
// respect to the photo is the same primitive with the two swapped. The ops check every argument the
// kernels check, so the calls inside encoder.dispatch do not fail.
#include <nanobind/nanobind.h>
#include <nanobind/stl/optional.h>
#include <nanobind/stl/vector.h>

#include <cstdint>
#include <memory>
#include <optional>
#include <stdexcept>
#include <string>
#include <vector>

#include "bindings.h"
#include "kernels/mlx3d_kernels.h"
#include "mlx/array.h"
#include "mlx/ops.h"
#include "mlx/primitives.h"
#include "primitive_util.h"

namespace nb = nanobind;
namespace mx = mlx::core;
using namespace nb::literals;

namespace mlx3d {
namespace {

class PhotometricLoss : public CpuPrimitive {
 public:
  PhotometricLoss(mx::Stream stream, float lambda, std::vector<float> taps, int num_threads)
      : CpuPrimitive(stream, "Apple GPUs use mlx3d.training.metrics' MLX graph"), lambda_(lambda), taps_(std::move(taps)), num_threads_(num_threads) {}

  // inputs: img (H,W,C), ref (H,W,C)[, weights (H,W)]; outputs: loss (), dloss/dimg (H,W,C)
  void eval_cpu(const std::vector<mx::array>& inputs, std::vector<mx::array>& outputs) override {
    auto& encoder = prepare_outputs(*this, inputs, outputs);
    const int64_t h = inputs[0].shape(0), w = inputs[0].shape(1), c = inputs[0].shape(2);
    const float *x = inputs[0].data<float>(), *y = inputs[1].data<float>();
    const float* weights = inputs.size() > 2 ? inputs[2].data<float>() : nullptr;
    float *loss = outputs[0].data<float>(), *grad = outputs[1].data<float>();
    encoder.dispatch([=, lambda = lambda_, taps = taps_, threads = num_threads_]() {
      ScratchFloats scratch(8 * size_t(h) * w * c);  // from MLX's buffer cache: no fresh pages per call
      check_call(mlx3d_photometric_loss(x, y, weights, h, w, c, lambda, taps.data(), int64_t(taps.size()), threads, scratch.data(), loss,
                                        grad));
    });
  }

  std::vector<mx::array> vjp(const std::vector<mx::array>& primals, const std::vector<mx::array>& cotangents,
                             const std::vector<int>& argnums, const std::vector<mx::array>& outputs) override {
    auto s = stream();
    std::vector<mx::array> result;
    for (int a : argnums) {
      if (a == 0) {
        result.push_back(mx::multiply(cotangents[0], outputs[1], s));
      } else if (a == 1) {  // symmetric loss: d/dref L(img, ref) = d/dfirst L(ref, img)
        std::vector<mx::array> swapped = {primals[1], primals[0]};
        if (primals.size() > 2) swapped.push_back(primals[2]);
        auto other = mx::array::make_arrays({mx::Shape{}, primals[0].shape()}, {mx::float32, mx::float32},
                                            std::make_shared<PhotometricLoss>(s, lambda_, taps_, num_threads_), swapped);
        result.push_back(mx::multiply(cotangents[0], other[1], s));
      } else {
        throw std::runtime_error("photometric_loss: the gradient with respect to the mask is not implemented.");
      }
    }
    return result;
  }

  std::vector<mx::Shape> output_shapes(const std::vector<mx::array>& inputs) override { return {mx::Shape{}, inputs[0].shape()}; }

  const char* name() const override { return "PhotometricLoss"; }

  bool is_equivalent(const mx::Primitive& other) const override {
    const auto* o = dynamic_cast<const PhotometricLoss*>(&other);
    return o && o->lambda_ == lambda_ && o->taps_ == taps_ && o->num_threads_ == num_threads_;
  }

 private:
  float lambda_;
  std::vector<float> taps_;
  int num_threads_;
};

// inputs: img (H,W,C), ref (H,W,C)[, weights (H,W)]; output: the MSE (), clipping img first when `clip`.
// A metric: no gradient.
class MeanSquaredError : public CpuPrimitive {
 public:
  MeanSquaredError(mx::Stream stream, bool clip, int num_threads)
      : CpuPrimitive(stream, "Apple GPUs use mlx3d.training.metrics' MLX graph"), clip_(clip), num_threads_(num_threads) {}

  void eval_cpu(const std::vector<mx::array>& inputs, std::vector<mx::array>& outputs) override {
    auto& encoder = prepare_outputs(*this, inputs, outputs);
    const int64_t h = inputs[0].shape(0), w = inputs[0].shape(1), c = inputs[0].shape(2);
    const float *x = inputs[0].data<float>(), *y = inputs[1].data<float>();
    const float* weights = inputs.size() > 2 ? inputs[2].data<float>() : nullptr;
    float* out = outputs[0].data<float>();
    encoder.dispatch([=, clip = clip_, threads = num_threads_]() {
      check_call(mlx3d_mse(x, y, weights, h, w, c, clip ? 1 : 0, threads, out));
    });
  }

  std::vector<mx::array> vjp(const std::vector<mx::array>&, const std::vector<mx::array>&, const std::vector<int>&,
                             const std::vector<mx::array>&) override {
    throw std::runtime_error("mse on the CPU kernel is a metric and has no gradient; use backend='reference' to differentiate it.");
  }

  std::vector<mx::Shape> output_shapes(const std::vector<mx::array>&) override { return {mx::Shape{}}; }

  const char* name() const override { return "MeanSquaredError"; }

  bool is_equivalent(const mx::Primitive& other) const override {
    const auto* o = dynamic_cast<const MeanSquaredError*>(&other);
    return o && o->clip_ == clip_ && o->num_threads_ == num_threads_;
  }

 private:
  bool clip_;
  int num_threads_;
};

// float32 (H, W, C) images with H, W, C >= 1 and fewer than 2^31 values (as the kernels require them),
// optional (H, W) weights, and num_threads >= 0, as photometric_loss checks them.
std::vector<mx::array> image_inputs(const char* op, const mx::array& img, const mx::array& ref, const std::optional<mx::array>& weights,
                                    int num_threads) {
  auto fail = [op](const std::string& msg) { throw std::invalid_argument(std::string(op) + ": " + msg); };
  if (img.ndim() != 3 || img.shape() != ref.shape())
    fail("img and ref must be (H, W, C) of one shape, got " + shape_str(img) + " and " + shape_str(ref));
  if (img.size() == 0) fail("the images must not be empty, got " + shape_str(img));
  if (img.size() > size_t(INT32_MAX)) fail("the images must hold fewer than 2^31 values, got " + shape_str(img));
  if (img.dtype() != mx::float32 || ref.dtype() != mx::float32) fail("images must be float32 (the Python wrapper casts them)");
  if (weights && (weights->shape() != mx::Shape{img.shape(0), img.shape(1)} || weights->dtype() != mx::float32))
    fail("weights must be float32 (H, W), got " + shape_str(*weights));
  if (num_threads < 0) fail("num_threads must be >= 0 (0 = all cores), got " + std::to_string(num_threads));
  auto s = mx::default_stream(mx::Device::cpu);
  std::vector<mx::array> inputs = {mx::contiguous(img, false, s), mx::contiguous(ref, false, s)};
  if (weights) inputs.push_back(mx::contiguous(*weights, false, s));
  return inputs;
}

mx::array mean_squared_error(const mx::array& img, const mx::array& ref, std::optional<mx::array> weights, bool clip, int num_threads) {
  std::vector<mx::array> inputs = image_inputs("mse", img, ref, weights, num_threads);
  return mx::array(mx::Shape{}, mx::float32, std::make_shared<MeanSquaredError>(mx::default_stream(mx::Device::cpu), clip, num_threads),
                   std::move(inputs));
}

mx::array photometric_loss(const mx::array& img, const mx::array& ref, std::optional<mx::array> weights, float lambda,
                           const std::vector<float>& taps, int num_threads) {
  auto fail = [](const std::string& msg) { throw std::invalid_argument("photometric_loss: " + msg); };
  if (taps.empty() || taps.size() % 2 == 0) fail("taps must have an odd, positive length");
  if (!(lambda >= 0.0f && lambda <= 1.0f)) fail("lambda_dssim must be in [0, 1]");
  std::vector<mx::array> inputs = image_inputs("photometric_loss", img, ref, weights, num_threads);
  if (int64_t(taps.size()) - 1 > (INT32_MAX - int64_t(img.shape(1)) * img.shape(2)) / img.shape(2))
    fail("too many taps (" + std::to_string(taps.size()) + ") for rows of " + std::to_string(int64_t(img.shape(1)) * img.shape(2)) +
         " values");
  auto s = mx::default_stream(mx::Device::cpu);
  return mx::array::make_arrays({mx::Shape{}, img.shape()}, {mx::float32, mx::float32},
                                std::make_shared<PhotometricLoss>(s, lambda, taps, num_threads), inputs)[0];
}

}  // namespace

void bind_photometric(nb::module_& m) {
  m.def("photometric_loss", &photometric_loss, "img"_a, "ref"_a, "weights"_a.none(), "lambda_dssim"_a, "taps"_a, "num_threads"_a = 0,
        "(1 - λ) L1 + λ (1 - SSIM) of float32 (H,W,C) images, optionally weighted per pixel (MLX primitive, CPU,\n"
        "threaded; differentiable w.r.t. img and ref). Use mlx3d.training.metrics.photometric_loss(backend='cpu').");
  m.def("mse", &mean_squared_error, "img"_a, "ref"_a, "weights"_a.none(), "clip"_a = false, "num_threads"_a = 0,
        "Mean squared error of float32 (H,W,C) images (img clipped to [0, 1] first with clip), optionally weighted per\n"
        "pixel (MLX primitive, CPU, threaded; no gradient). Use mlx3d.training.metrics.psnr(backend='cpu').");
}

}  // namespace mlx3d
