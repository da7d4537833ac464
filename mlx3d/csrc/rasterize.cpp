// The 3DGS tile rasterizer as MLX primitives on the CPU: RasterizeForward (composite, also with a surface
// layer) and RasterizeBackward (its vector-Jacobian product), which run the kernel library's
// mlx3d_rasterize_forward / _forward_surface / _backward (kernels/raster.cpp, mlx3d_kernels.h) on MLX
// arrays; the ops check the inputs' shapes and dtypes and make them row-contiguous.
//
// Inputs: means2d (N,2) f32, conics (N,3) f32 (a, b, c of [[a,b],[b,c]]), features (N,C) f32,
// opacities (N,) f32, tile_offsets (T+1,) i32, flatten_ids (M,) i32[, background (C,) f32].
// Outputs of RasterizeForward: accum (H,W,C) f32, alpha (H,W) f32 = 1 - T_final, last (H,W) i32,
// final_T (H,W) f32 (kept for the backward pass).
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
#include "primitive_util.h"
#include "mlx/array.h"
#include "mlx/ops.h"
#include "mlx/primitives.h"
#include "mlx/stream.h"

namespace nb = nanobind;
namespace mx = mlx::core;
using namespace nb::literals;

namespace mlx3d {
namespace {

void check(bool ok, const std::string& msg) {
  if (!ok) throw std::invalid_argument("rasterize: " + msg);
}

int simd_lanes() { return mlx3d_rasterizer_lanes(); }

// The Gaussians' and the binning's inputs of a primitive (the first six), and their sizes.
struct Args {
  const float *means, *conics, *features, *opacities;
  const int32_t *offsets, *ids;
  int64_t n, m;
  int channels;
};

Args args_of(const std::vector<mx::array>& inputs) {
  return {inputs[0].data<float>(),   inputs[1].data<float>(), inputs[2].data<float>(),
          inputs[3].data<float>(),   inputs[4].data<int32_t>(), inputs[5].data<int32_t>(),
          int64_t(inputs[0].shape(0)), int64_t(inputs[5].size()), int(inputs[2].shape(1))};
}

// ---------------------------------------------------------------- primitives

class RasterizeBackward : public mx::Primitive {
 public:
  RasterizeBackward(mx::Stream stream, int width, int height, int tile, int num_threads)
      : mx::Primitive(stream), width_(width), height_(height), tile_(tile), num_threads_(num_threads) {}

  // inputs: means2d, conics, features, opacities, tile_offsets, flatten_ids,
  //         last, final_T, dL/daccum (H,W,C), dL/dalpha (H,W)[, the forward's background (C,)]
  // outputs: dL/dmeans2d, dL/dconics, dL/dfeatures, dL/dopacities
  void eval_cpu(const std::vector<mx::array>& inputs, std::vector<mx::array>& outputs) override {
    auto& encoder = prepare_outputs(*this, inputs, outputs);
    const Args a = args_of(inputs);
    const int32_t* last = inputs[6].data<int32_t>();
    const float *final_T = inputs[7].data<float>(), *d_accum = inputs[8].data<float>(), *d_alpha = inputs[9].data<float>();
    const float* bg = inputs.size() > 10 ? inputs[10].data<float>() : nullptr;
    float *d_means = outputs[0].data<float>(), *d_conics = outputs[1].data<float>(), *d_features = outputs[2].data<float>(),
          *d_opacities = outputs[3].data<float>();
    encoder.dispatch([=, w = width_, h = height_, tile = tile_, threads = num_threads_]() {
      check_call(mlx3d_rasterize_backward(a.means, a.conics, a.features, a.opacities, a.offsets, a.ids, a.n, a.channels, a.m, w,
                                          h, tile, last, final_T, d_accum, d_alpha, bg, threads, d_means, d_conics, d_features,
                                          d_opacities));
    });
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

// With `surface`, the forward-only variant that composites a surface layer
// (extra inputs: depths (N,), surface colour (H,W,C), alpha (H,W), depth (H,W)). Otherwise an optional
// seventh input, the background (C,), is composited behind accum (add_background).
class RasterizeForward : public mx::Primitive {
 public:
  RasterizeForward(mx::Stream stream, int width, int height, int tile, int num_threads, bool surface = false)
      : mx::Primitive(stream), width_(width), height_(height), tile_(tile), num_threads_(num_threads), surface_(surface) {}

  void eval_cpu(const std::vector<mx::array>& inputs, std::vector<mx::array>& outputs) override {
    auto& encoder = prepare_outputs(*this, inputs, outputs);
    const Args a = args_of(inputs);
    const float* bg = !surface_ && inputs.size() > 6 ? inputs[6].data<float>() : nullptr;
    const float* sf[4] = {nullptr, nullptr, nullptr, nullptr};  // depths, surface colour, alpha, depth
    if (surface_)
      for (int k = 0; k < 4; ++k) sf[k] = inputs[6 + k].data<float>();
    float *accum = outputs[0].data<float>(), *alpha = outputs[1].data<float>(), *final_T = outputs[3].data<float>();
    int32_t* last = outputs[2].data<int32_t>();
    encoder.dispatch([=, w = width_, h = height_, tile = tile_, threads = num_threads_, surface = surface_]() {
      check_call(surface ? mlx3d_rasterize_forward_surface(a.means, a.conics, a.features, a.opacities, a.offsets, a.ids, a.n,
                                                           a.channels, a.m, w, h, tile, sf[0], sf[1], sf[2], sf[3], threads,
                                                           accum, alpha, last, final_T)
                         : mlx3d_rasterize_forward(a.means, a.conics, a.features, a.opacities, a.offsets, a.ids, a.n, a.channels,
                                                   a.m, w, h, tile, bg, threads, accum, alpha, last, final_T));
    });
  }

  void eval_gpu(const std::vector<mx::array>&, std::vector<mx::array>&) override {
    throw std::runtime_error("RasterizeForward runs on the CPU only; use mlx3d.render.raster_metal on Apple GPUs.");
  }

  // Cotangents: one per output (accum, alpha, last, final_T); those of `last`
  // (integer) and `final_T` (internal) are ignored. tile_offsets and
  // flatten_ids are integer inputs and get zero cotangents; the background's
  // (when asked for) comes from an MLX expression.
  std::vector<mx::array> vjp(const std::vector<mx::array>& primals, const std::vector<mx::array>& cotangents,
                             const std::vector<int>& argnums, const std::vector<mx::array>& outputs) override {
    if (surface_)
      throw std::runtime_error(
          "RasterizeSurfaceForward: compositing over a surface is forward-only (no gradients); render without "
          "`surface` to differentiate.");
    auto s = stream();
    bool need = false;
    for (int a : argnums) need |= a < 4;
    std::vector<mx::array> grads;
    if (need) {
      auto prep = [&](const mx::array& x) { return mx::contiguous(mx::astype(x, mx::float32, s), false, s); };
      std::vector<mx::array> inputs = {primals[0], primals[1], primals[2],  primals[3],       primals[4],
                                       primals[5], outputs[2], outputs[3], prep(cotangents[0]), prep(cotangents[1])};
      if (primals.size() > 6) inputs.push_back(primals[6]);  // the background
      grads = mx::array::make_arrays(
          {primals[0].shape(), primals[1].shape(), primals[2].shape(), primals[3].shape()},
          {mx::float32, mx::float32, mx::float32, mx::float32},
          std::make_shared<RasterizeBackward>(s, width_, height_, tile_, num_threads_), inputs);
    }
    std::vector<mx::array> result;
    for (int a : argnums) {
      if (a < 4) {
        result.push_back(grads[a]);
      } else if (a == 6) {  // the background: the sum over pixels of dL/daccum (1 - alpha)
        const mx::array uncovered = mx::expand_dims(mx::subtract(mx::array(1.0f), outputs[1], s), -1, s);
        result.push_back(mx::sum(mx::multiply(cotangents[0], uncovered, s), std::vector<int>{0, 1}, false, s));
      } else {
        result.push_back(mx::zeros_like(primals[a], s));
      }
    }
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

  const char* name() const override { return surface_ ? "RasterizeSurfaceForward" : "RasterizeForward"; }

  bool is_equivalent(const mx::Primitive& other) const override {
    const auto* o = dynamic_cast<const RasterizeForward*>(&other);
    return o && o->width_ == width_ && o->height_ == height_ && o->tile_ == tile_ && o->num_threads_ == num_threads_ &&
           o->surface_ == surface_;
  }

 private:
  int width_, height_, tile_, num_threads_;
  bool surface_;
};

// Checks the plain rasterizer inputs' shapes, dtypes and sizes.
void check_forward_inputs(const mx::array& means2d, const mx::array& conics, const mx::array& features,
                          const mx::array& opacities, const mx::array& tile_offsets, const mx::array& flatten_ids,
                          int width, int height, int tile_size, int num_threads) {
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
}

// The forward primitive's lazily evaluated outputs (accum, alpha, last, final_T) on row-contiguous copies of `args`.
std::vector<mx::array> make_forward(const std::vector<const mx::array*>& args, int width, int height, int tile_size,
                                    int num_threads, bool surface) {
  auto s = mx::default_stream(mx::Device::cpu);
  std::vector<mx::array> inputs;
  for (const auto* a : args) inputs.push_back(mx::contiguous(*a, false, s));
  const int C = args[2]->shape(1);
  return mx::array::make_arrays({{height, width, C}, {height, width}, {height, width}, {height, width}},
                                {mx::float32, mx::float32, mx::int32, mx::float32},
                                std::make_shared<RasterizeForward>(s, width, height, tile_size, num_threads, surface),
                                inputs);
}

// The op: validates shapes/dtypes, makes the inputs row-contiguous and returns
// the four lazily evaluated outputs (accum, alpha, last, final_T).
std::vector<mx::array> rasterize_forward(const mx::array& means2d, const mx::array& conics, const mx::array& features,
                                         const mx::array& opacities, const mx::array& tile_offsets,
                                         const mx::array& flatten_ids, int width, int height, int tile_size,
                                         int num_threads, std::optional<mx::array> background) {
  check_forward_inputs(means2d, conics, features, opacities, tile_offsets, flatten_ids, width, height, tile_size,
                       num_threads);
  std::vector<const mx::array*> args = {&means2d, &conics, &features, &opacities, &tile_offsets, &flatten_ids};
  if (background) {
    check(background->ndim() == 1 && background->shape(0) == features.shape(1) && background->dtype() == mx::float32,
          "background must be float32 (C,) with C = " + std::to_string(features.shape(1)) + ", got " + shape_str(*background));
    args.push_back(&*background);
  }
  return make_forward(args, width, height, tile_size, num_threads, false);
}

// The surface variant's op (forward-only): the plain inputs, then the
// Gaussians' depths (N,) and the surface colour (H,W,C), alpha (H,W), depth (H,W).
std::vector<mx::array> rasterize_forward_surface(const mx::array& means2d, const mx::array& conics,
                                                 const mx::array& features, const mx::array& opacities,
                                                 const mx::array& tile_offsets, const mx::array& flatten_ids,
                                                 const mx::array& depths, const mx::array& surface_color,
                                                 const mx::array& surface_alpha, const mx::array& surface_depth,
                                                 int width, int height, int tile_size, int num_threads) {
  check_forward_inputs(means2d, conics, features, opacities, tile_offsets, flatten_ids, width, height, tile_size,
                       num_threads);
  const std::string hw = "(" + std::to_string(height) + ", " + std::to_string(width);
  check(depths.ndim() == 1 && depths.shape(0) == means2d.shape(0),
        "depths must have shape (N,) = (" + std::to_string(means2d.shape(0)) + ",), got " + shape_str(depths));
  check(surface_color.ndim() == 3 && surface_color.shape(0) == height && surface_color.shape(1) == width &&
            surface_color.shape(2) == features.shape(1),
        "surface_color must have shape (H, W, C) = " + hw + ", " + std::to_string(features.shape(1)) + "), got " +
            shape_str(surface_color));
  for (const auto* a : {&surface_alpha, &surface_depth})
    check(a->ndim() == 2 && a->shape(0) == height && a->shape(1) == width,
          "surface_alpha and surface_depth must have shape (H, W) = " + hw + "), got " + shape_str(*a));
  for (const auto* a : {&depths, &surface_color, &surface_alpha, &surface_depth})
    check(a->dtype() == mx::float32, "float inputs must be float32 (the Python wrapper casts them)");
  return make_forward({&means2d, &conics, &features, &opacities, &tile_offsets, &flatten_ids, &depths, &surface_color,
                       &surface_alpha, &surface_depth},
                      width, height, tile_size, num_threads, true);
}

}  // namespace

void bind_rasterize(nb::module_& m) {
  m.def("rasterizer_simd_lanes", &simd_lanes,
        "Pixels per SIMD step of the CPU rasterizer on this machine (8: AVX2, 4: SSE2/NEON, 1: scalar);\n"
        "MLX3D_RASTER_ISA=baseline forces the baseline variant.");
  m.def("rasterize_forward", &rasterize_forward, "means2d"_a, "conics"_a, "features"_a, "opacities"_a,
        "tile_offsets"_a, "flatten_ids"_a, "width"_a, "height"_a, "tile_size"_a = 16, "num_threads"_a = 0,
        "background"_a = nb::none(),
        "3DGS tile rasterizer (MLX primitive, CPU, threaded over tiles; differentiable w.r.t. the first four\n"
        "inputs and the background). float32 means2d (N,2), conics (N,3), features (N,C), opacities (N,); int32\n"
        "tile_offsets (tiles+1,), flatten_ids (M,); background: None or float32 (C,), composited behind accum as\n"
        "(1 - alpha) * background. Returns [accum (H,W,C), alpha (H,W), last (H,W) int32, final_T (H,W)].\n"
        "Use mlx3d.render.raster_cpu.rasterize_cpu, which validates and casts its inputs.");
  m.def("rasterize_forward_surface", &rasterize_forward_surface, "means2d"_a, "conics"_a, "features"_a, "opacities"_a,
        "tile_offsets"_a, "flatten_ids"_a, "depths"_a, "surface_color"_a, "surface_alpha"_a, "surface_depth"_a,
        "width"_a, "height"_a, "tile_size"_a = 16, "num_threads"_a = 0,
        "rasterize_forward composited in depth order with a per-pixel surface layer (forward-only): float32 depths\n"
        "(N,) the Gaussians' camera z (the binning's sort key), surface_color (H,W,C) premultiplied, surface_alpha\n"
        "(H,W), surface_depth (H,W) camera z (+inf: behind every Gaussian). Returns [accum, alpha, last, final_T].\n"
        "Use mlx3d.render.raster_cpu.rasterize_cpu_surface.");
}

}  // namespace mlx3d
