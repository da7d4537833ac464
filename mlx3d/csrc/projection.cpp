// EWA projection of 3D Gaussians as CPU MLX primitives, threaded over Gaussians.
//
// Forward: means (N,3), quats (N,4), scales (N,3) -> means2d (N,2), conics (N,3), radii (N,)
// int32, depths (N,), compensation (N,). Backward: the gradients of means, quats and scales
// from those of means2d, conics, depths and compensation (radii have none). The per-Gaussian
// math is projection_math.h; each Gaussian is computed by one thread from its own inputs, several
// at a time (one per vector lane, each lane the float operations of one Gaussian alone), so
// results are bitwise identical for any thread count. The pure-MLX reference is
// mlx3d.render.projection.project_ewa(backend='reference').
#include <nanobind/nanobind.h>
#include <nanobind/stl/vector.h>

#include <algorithm>
#include <cmath>
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

// Lane-wise sqrt and ceil for projection_math.h (declared before it, as its templates look them up);
// both correctly rounded in every variant, and the file is built without FMA contraction, so the
// results do not depend on the lanes.
#if defined(MLX3D_VECTOR_LANES)
MLX3D_LANES_INLINE mlx3d::Lanes pm_sqrt(mlx3d::Lanes x) {
  for (int j = 0; j < mlx3d::kLanes; ++j) x[j] = __builtin_sqrtf(x[j]);
  return x;
}
MLX3D_LANES_INLINE mlx3d::Lanes pm_ceil(mlx3d::Lanes x) {
  for (int j = 0; j < mlx3d::kLanes; ++j) x[j] = __builtin_ceilf(x[j]);
  return x;
}
#endif
#include "projection_math.h"

namespace nb = nanobind;
namespace mx = mlx::core;
using namespace nb::literals;

namespace mlx3d {
namespace {

constexpr int kBlock = 4096;  // at least this many Gaussians per thread

// Field f of `width` floats per Gaussian, of Gaussians [i0, i0 + count) and the last one repeated, as lanes.
MLX3D_LANES_INLINE Lanes gather(const float* a, int width, int f, int64_t i0, int count) {
  alignas(32) float t[kLanes];
  for (int j = 0; j < kLanes; ++j) t[j] = a[(i0 + std::min(j, count - 1)) * width + f];
  return lanes_at(t);
}

// Writes the first `count` lanes of v to field f of Gaussians [i0, i0 + count).
MLX3D_LANES_INLINE void scatter(float* a, int width, int f, int64_t i0, int count, Lanes v) {
  alignas(32) float t[kLanes];
  put_lanes(t, v);
  for (int j = 0; j < count; ++j) a[(i0 + j) * width + f] = t[j];
}

MLX3D_LANES_INLINE PmGaussianOf<Lanes> gaussians_at(const float* means, const float* quats, const float* scales, int64_t i0, int count) {
  PmGaussianOf<Lanes> g;
  for (int k = 0; k < 3; ++k) g.mean[k] = gather(means, 3, k, i0, count), g.scale[k] = gather(scales, 3, k, i0, count);
  for (int k = 0; k < 4; ++k) g.quat[k] = gather(quats, 4, k, i0, count);
  return g;
}

struct ForwardArrays {
  const float *means, *quats, *scales;
  float *means2d, *conics, *depths, *compensation;
  int32_t* radii;
};

struct BackwardArrays {
  const float *means, *quats, *scales;
  const float *d_means2d, *d_conics, *d_depths, *d_compensation;  // (N,2), (N,3), (N,), (N,)
  float *d_means, *d_quats, *d_scales;
};

MLX3D_AVX2_CLONES void forward_range(const PmCamera& cam, const ForwardArrays& a, int64_t lo, int64_t hi) {
  for (int64_t i0 = lo; i0 < hi; i0 += kLanes) {
    const int count = static_cast<int>(std::min<int64_t>(kLanes, hi - i0));
    const PmStateOf<Lanes> s = pm_forward(cam, gaussians_at(a.means, a.quats, a.scales, i0, count));
    for (int k = 0; k < 2; ++k) scatter(a.means2d, 2, k, i0, count, s.means2d[k]);
    for (int k = 0; k < 3; ++k) scatter(a.conics, 3, k, i0, count, s.conic[k]);
    scatter(a.depths, 1, 0, i0, count, s.depth);
    scatter(a.compensation, 1, 0, i0, count, s.compensation);
    alignas(32) float radius[kLanes];
    put_lanes(radius, s.radius);
    for (int j = 0; j < count; ++j) a.radii[i0 + j] = static_cast<int32_t>(radius[j]);
  }
}

MLX3D_AVX2_CLONES void backward_range(const PmCamera& cam, const BackwardArrays& a, int64_t lo, int64_t hi) {
  for (int64_t i0 = lo; i0 < hi; i0 += kLanes) {
    const int count = static_cast<int>(std::min<int64_t>(kLanes, hi - i0));
    const PmGaussianOf<Lanes> g = gaussians_at(a.means, a.quats, a.scales, i0, count);
    const PmStateOf<Lanes> s = pm_forward(cam, g);
    const PmGradOf<Lanes> d = pm_backward(cam, g, s, gather(a.d_means2d, 2, 0, i0, count), gather(a.d_means2d, 2, 1, i0, count),
                                          gather(a.d_conics, 3, 0, i0, count), gather(a.d_conics, 3, 1, i0, count),
                                          gather(a.d_conics, 3, 2, i0, count), gather(a.d_depths, 1, 0, i0, count),
                                          gather(a.d_compensation, 1, 0, i0, count));
    for (int k = 0; k < 3; ++k) scatter(a.d_means, 3, k, i0, count, d.mean[k]), scatter(a.d_scales, 3, k, i0, count, d.scale[k]);
    for (int k = 0; k < 4; ++k) scatter(a.d_quats, 4, k, i0, count, d.quat[k]);
  }
}

class ProjectBase : public CpuPrimitive {
 public:
  ProjectBase(mx::Stream stream, PmCamera cam, int num_threads)
      : CpuPrimitive(stream, "Apple GPUs use the MLX reference projection"), cam_(cam), num_threads_(num_threads) {}

  bool is_equivalent(const mx::Primitive& other) const override {
    const auto* o = dynamic_cast<const ProjectBase*>(&other);
    if (!o || std::string(o->name()) != name() || o->num_threads_ != num_threads_ || o->cam_.antialias != cam_.antialias) return false;
    const float* a = &cam_.rot[0];
    const float* b = &o->cam_.rot[0];
    for (int i = 0; i < 9; ++i)
      if (a[i] != b[i]) return false;
    for (int i = 0; i < 3; ++i)
      if (cam_.trans[i] != o->cam_.trans[i]) return false;
    return cam_.fx == o->cam_.fx && cam_.fy == o->cam_.fy && cam_.cx == o->cam_.cx && cam_.cy == o->cam_.cy &&
           cam_.width == o->cam_.width && cam_.height == o->cam_.height && cam_.near_z == o->cam_.near_z &&
           cam_.far_z == o->cam_.far_z && cam_.blur == o->cam_.blur;
  }

 protected:
  PmCamera cam_;
  int num_threads_;
};

class ProjectEwaBackward : public ProjectBase {
 public:
  using ProjectBase::ProjectBase;

  // inputs: means, quats, scales, dL/dmeans2d (N,2), dL/dconics (N,3), dL/ddepths (N,), dL/dcompensation (N,)
  // outputs: dL/dmeans, dL/dquats, dL/dscales
  void eval_cpu(const std::vector<mx::array>& inputs, std::vector<mx::array>& outputs) override {
    auto& encoder = prepare_outputs(*this, inputs, outputs);
    const BackwardArrays a{inputs[0].data<float>(),  inputs[1].data<float>(),  inputs[2].data<float>(),  inputs[3].data<float>(),
                           inputs[4].data<float>(),  inputs[5].data<float>(),  inputs[6].data<float>(),  outputs[0].data<float>(),
                           outputs[1].data<float>(), outputs[2].data<float>()};
    const int64_t n = inputs[0].shape(0);
    encoder.dispatch([a, n, cam = cam_, threads = num_threads_]() {
      parallel_blocks(n, threads, kBlock, [a, cam](int64_t lo, int64_t hi) { backward_range(cam, a, lo, hi); });
    });
  }

  std::vector<mx::array> vjp(const std::vector<mx::array>&, const std::vector<mx::array>&, const std::vector<int>&,
                             const std::vector<mx::array>&) override {
    throw std::runtime_error("ProjectEwaBackward: second-order gradients are not implemented.");
  }

  std::vector<mx::Shape> output_shapes(const std::vector<mx::array>& inputs) override {
    return {inputs[0].shape(), inputs[1].shape(), inputs[2].shape()};
  }

  const char* name() const override { return "ProjectEwaBackward"; }
};

class ProjectEwaForward : public ProjectBase {
 public:
  using ProjectBase::ProjectBase;

  void eval_cpu(const std::vector<mx::array>& inputs, std::vector<mx::array>& outputs) override {
    auto& encoder = prepare_outputs(*this, inputs, outputs);
    const ForwardArrays a{inputs[0].data<float>(),  inputs[1].data<float>(),  inputs[2].data<float>(),
                          outputs[0].data<float>(), outputs[1].data<float>(), outputs[3].data<float>(),
                          outputs[4].data<float>(), outputs[2].data<int32_t>()};
    const int64_t n = inputs[0].shape(0);
    encoder.dispatch([a, n, cam = cam_, threads = num_threads_]() {
      parallel_blocks(n, threads, kBlock, [a, cam](int64_t lo, int64_t hi) { forward_range(cam, a, lo, hi); });
    });
  }

  // Cotangents: one per output (means2d, conics, radii, depths, compensation); radii's is ignored.
  std::vector<mx::array> vjp(const std::vector<mx::array>& primals, const std::vector<mx::array>& cotangents,
                             const std::vector<int>& argnums, const std::vector<mx::array>&) override {
    auto s = stream();
    auto prep = [&](const mx::array& x) { return mx::contiguous(mx::astype(x, mx::float32, s), false, s); };
    auto grads = mx::array::make_arrays({primals[0].shape(), primals[1].shape(), primals[2].shape()}, {mx::float32, mx::float32, mx::float32},
                                        std::make_shared<ProjectEwaBackward>(s, cam_, num_threads_),
                                        {primals[0], primals[1], primals[2], prep(cotangents[0]), prep(cotangents[1]),
                                         prep(cotangents[3]), prep(cotangents[4])});
    std::vector<mx::array> result;
    for (int a : argnums) result.push_back(grads[a]);
    return result;
  }

  std::vector<mx::Shape> output_shapes(const std::vector<mx::array>& inputs) override {
    const int n = inputs[0].shape(0);
    return {{n, 2}, {n, 3}, {n}, {n}, {n}};
  }

  const char* name() const override { return "ProjectEwaForward"; }
};

void check(bool ok, const std::string& msg) {
  if (!ok) throw std::invalid_argument("project_ewa: " + msg);
}

std::vector<mx::array> project_ewa(const mx::array& means, const mx::array& quats, const mx::array& scales, const std::vector<float>& viewmat,
                                   float fx, float fy, float cx, float cy, int width, int height, float near_z, float far_z,
                                   float blur, bool antialias, int num_threads) {
  check(means.ndim() == 2 && means.shape(1) == 3, "means must have shape (N, 3), got " + shape_str(means));
  const int n = means.shape(0);
  check(quats.ndim() == 2 && quats.shape(0) == n && quats.shape(1) == 4,
        "quats must have shape (N, 4) = (" + std::to_string(n) + ", 4), got " + shape_str(quats));
  check(scales.ndim() == 2 && scales.shape(0) == n && scales.shape(1) == 3,
        "scales must have shape (N, 3) = (" + std::to_string(n) + ", 3), got " + shape_str(scales));
  for (const auto* a : {&means, &quats, &scales}) check(a->dtype() == mx::float32, "inputs must be float32 (the Python wrapper casts them)");
  check(viewmat.size() == 16, "viewmat must have 16 entries (4x4 row-major)");
  check(width >= 1 && height >= 1, "width and height must be >= 1");
  check(num_threads >= 0, "num_threads must be >= 0 (0 = all cores)");
  PmCamera cam;
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) cam.rot[3 * i + j] = viewmat[4 * i + j];
    cam.trans[i] = viewmat[4 * i + 3];
  }
  cam.fx = fx, cam.fy = fy, cam.cx = cx, cam.cy = cy;
  cam.width = float(width), cam.height = float(height), cam.near_z = near_z, cam.far_z = far_z, cam.blur = blur;
  cam.antialias = antialias ? 1 : 0;
  auto s = mx::default_stream(mx::Device::cpu);
  std::vector<mx::array> inputs;
  for (const auto* a : {&means, &quats, &scales}) inputs.push_back(mx::contiguous(*a, false, s));
  return mx::array::make_arrays({{n, 2}, {n, 3}, {n}, {n}, {n}}, {mx::float32, mx::float32, mx::int32, mx::float32, mx::float32},
                                std::make_shared<ProjectEwaForward>(s, cam, num_threads), inputs);
}

}  // namespace

void bind_projection(nb::module_& m) {
  m.def("project_ewa", &project_ewa, "means"_a, "quats"_a, "scales"_a, "viewmat"_a, "fx"_a, "fy"_a, "cx"_a, "cy"_a, "width"_a,
        "height"_a, "near"_a, "far"_a, "blur"_a = 0.3f, "antialias"_a = false, "num_threads"_a = 0,
        "EWA projection (MLX primitive, CPU, threaded; differentiable w.r.t. means, quats, scales):\n"
        "returns [means2d (N,2), conics (N,3), radii (N,) int32, depths (N,), compensation (N,)].\n"
        "Use mlx3d.render.projection.project_ewa, which validates and casts its inputs.");
}

}  // namespace mlx3d
