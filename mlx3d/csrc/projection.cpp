// EWA projection of 3D Gaussians as CPU MLX primitives, threaded over Gaussians.
//
// Forward: means (N,3), quats (N,4), scales (N,3) -> means2d (N,2), conics (N,3), radii (N,)
// int32, depths (N,), compensation (N,). Backward: the gradients of means, quats and scales
// from those of means2d, conics, depths and compensation (radii have none). The per-Gaussian
// math is projection_math.h; each Gaussian is computed by one thread from its own inputs, so
// results are bitwise identical for any thread count. The pure-MLX reference is
// mlx3d.render.projection.project_ewa(backend='reference').
#include <nanobind/nanobind.h>
#include <nanobind/stl/vector.h>

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
#include "projection_math.h"

namespace nb = nanobind;
namespace mx = mlx::core;
using namespace nb::literals;

namespace mlx3d {
namespace {

constexpr int kBlock = 4096;  // at least this many Gaussians per thread

inline PmGaussian gaussian_at(const float* means, const float* quats, const float* scales, int64_t i) {
  PmGaussian g;
  for (int k = 0; k < 3; ++k) g.mean[k] = means[3 * i + k], g.scale[k] = scales[3 * i + k];
  for (int k = 0; k < 4; ++k) g.quat[k] = quats[4 * i + k];
  return g;
}

template <typename Fn>
void for_each_gaussian(int64_t n, int num_threads, const Fn& fn) {
  parallel_ranges(n, num_threads, kBlock, [fn](int64_t lo, int64_t hi) {
    for (int64_t i = lo; i < hi; ++i) fn(i);
  });
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
    const float *means = inputs[0].data<float>(), *quats = inputs[1].data<float>(), *scales = inputs[2].data<float>();
    const float *g2 = inputs[3].data<float>(), *gc = inputs[4].data<float>(), *gd = inputs[5].data<float>(), *gk = inputs[6].data<float>();
    float *dm = outputs[0].data<float>(), *dq = outputs[1].data<float>(), *ds = outputs[2].data<float>();
    const int64_t n = inputs[0].shape(0);
    encoder.dispatch([=, cam = cam_, threads = num_threads_]() {
      for_each_gaussian(n, threads, [=](int64_t i) {
        const PmGaussian g = gaussian_at(means, quats, scales, i);
        const PmState s = pm_forward(cam, g);
        const PmGrad d = pm_backward(cam, g, s, g2[2 * i], g2[2 * i + 1], gc[3 * i], gc[3 * i + 1], gc[3 * i + 2], gd[i], gk[i]);
        for (int k = 0; k < 3; ++k) dm[3 * i + k] = d.mean[k], ds[3 * i + k] = d.scale[k];
        for (int k = 0; k < 4; ++k) dq[4 * i + k] = d.quat[k];
      });
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
    const float *means = inputs[0].data<float>(), *quats = inputs[1].data<float>(), *scales = inputs[2].data<float>();
    float *m2 = outputs[0].data<float>(), *con = outputs[1].data<float>(), *dep = outputs[3].data<float>(), *comp = outputs[4].data<float>();
    int32_t* radii = outputs[2].data<int32_t>();
    const int64_t n = inputs[0].shape(0);
    encoder.dispatch([=, cam = cam_, threads = num_threads_]() {
      for_each_gaussian(n, threads, [=](int64_t i) {
        const PmState s = pm_forward(cam, gaussian_at(means, quats, scales, i));
        m2[2 * i] = s.means2d[0];
        m2[2 * i + 1] = s.means2d[1];
        for (int k = 0; k < 3; ++k) con[3 * i + k] = s.conic[k];
        radii[i] = static_cast<int32_t>(s.radius);
        dep[i] = s.depth;
        comp[i] = s.compensation;
      });
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
