// Python bindings of the k-d tree (numpy in, numpy out).
#include <nanobind/nanobind.h>
#include <nanobind/ndarray.h>
#include <nanobind/stl/optional.h>
#include <nanobind/stl/pair.h>

#include <cstdint>
#include <memory>
#include <optional>
#include <string>

#include "bindings.h"
#include "kernels/knn.h"

namespace nb = nanobind;
using namespace nb::literals;

namespace mlx3d {

namespace {

using Points = nb::ndarray<const float, nb::shape<-1, 3>, nb::c_contig, nb::device::cpu>;
using SelfIndex = nb::ndarray<const int64_t, nb::shape<-1>, nb::c_contig, nb::device::cpu>;
using IndexOut = nb::ndarray<nb::numpy, int64_t, nb::ndim<2>>;
using DistOut2 = nb::ndarray<nb::numpy, float, nb::ndim<2>>;
using DistOut1 = nb::ndarray<nb::numpy, float, nb::ndim<1>>;

template <typename T>
std::pair<T*, nb::capsule> new_buffer(size_t count) {
  std::unique_ptr<T[]> buf(new T[count == 0 ? 1 : count]);
  T* ptr = buf.get();
  nb::capsule owner(ptr, [](void* p) noexcept { delete[] static_cast<T*>(p); });
  buf.release();
  return {ptr, std::move(owner)};
}

knn::QueryArgs make_args(const Points& queries, int k,
                         const std::optional<SelfIndex>& self_index, int num_threads,
                         knn::Output output) {
  knn::QueryArgs args;
  args.queries = queries.data();
  args.m = static_cast<int64_t>(queries.shape(0));
  args.k = k;
  args.num_threads = num_threads;
  args.output = output;
  if (self_index) {
    if (static_cast<int64_t>(self_index->shape(0)) != args.m) {
      throw nb::value_error(("self_index has " + std::to_string(self_index->shape(0)) +
                             " entries but queries has " + std::to_string(args.m) + " rows")
                                .c_str());
    }
    args.self_index = self_index->data();
  }
  if (num_threads < 0) {
    throw nb::value_error(
        ("num_threads must be >= 0 (0 = all), got " + std::to_string(num_threads)).c_str());
  }
  return args;
}

std::pair<IndexOut, DistOut2> tree_query(const knn::KDTree& tree, const Points& queries, int k,
                                         const std::optional<SelfIndex>& self_index,
                                         int num_threads) {
  knn::QueryArgs args =
      make_args(queries, k, self_index, num_threads, knn::Output::kNeighbours);
  const size_t m = static_cast<size_t>(args.m);
  const size_t kk = static_cast<size_t>(k < 0 ? 0 : k);
  auto [idx, idx_owner] = new_buffer<int64_t>(m * kk);
  auto [dist, dist_owner] = new_buffer<float>(m * kk);
  args.out_index = idx;
  args.out_dist = dist;
  {
    nb::gil_scoped_release release;
    tree.query(args);
  }
  return {IndexOut(idx, {m, kk}, idx_owner), DistOut2(dist, {m, kk}, dist_owner)};
}

DistOut1 tree_query_reduce(const knn::KDTree& tree, const Points& queries, int k,
                           const std::optional<SelfIndex>& self_index, int num_threads,
                           knn::Output output) {
  knn::QueryArgs args = make_args(queries, k, self_index, num_threads, output);
  const size_t m = static_cast<size_t>(args.m);
  auto [dist, owner] = new_buffer<float>(m);
  args.out_dist = dist;
  {
    nb::gil_scoped_release release;
    tree.query(args);
  }
  return DistOut1(dist, {m}, owner);
}

}  // namespace

void bind_knn(nb::module_& m) {
  nb::class_<knn::KDTree>(
      m, "KDTree",
      "k-d tree over (N, 3) float32 points (median split on the widest axis).\n\n"
      "Low-level; use mlx3d.neighbors for the validated numpy API.")
      .def(
          "__init__",
          [](knn::KDTree* self, Points points, int leaf_size) {
            const float* data = points.data();
            const int64_t n = static_cast<int64_t>(points.shape(0));
            nb::gil_scoped_release release;
            new (self) knn::KDTree(data, n, leaf_size);
          },
          "points"_a, "leaf_size"_a = 16,
          "Builds the tree from C-contiguous float32 points of shape (N, 3).")
      .def_prop_ro("size", &knn::KDTree::size, "Number of points N.")
      .def_prop_ro("leaf_size", &knn::KDTree::leaf_size)
      .def_prop_ro("depth", &knn::KDTree::depth, "Number of tree levels.")
      .def_prop_ro("node_count", &knn::KDTree::node_count)
      .def(
          "order",
          [](const knn::KDTree& tree) {
            std::vector<int64_t> order = tree.order();
            auto [buf, owner] = new_buffer<int64_t>(order.size());
            std::copy(order.begin(), order.end(), buf);
            return nb::ndarray<nb::numpy, int64_t, nb::ndim<1>>(buf, {order.size()}, owner);
          },
          "Original point indices in tree order (spatially coherent), int64 (N,).")
      .def("query", &tree_query, "queries"_a, "k"_a, "self_index"_a = nb::none(),
           "num_threads"_a = 0,
           "k nearest points of each query.\n\n"
           "Returns (indices int64 (M, k), squared distances float32 (M, k)) sorted\n"
           "by increasing distance (ties by index). self_index (int64 (M,), -1 =\n"
           "none) names each query's own point, which is skipped.")
      .def(
          "query_mean",
          [](const knn::KDTree& tree, const Points& queries, int k,
             const std::optional<SelfIndex>& self_index, int num_threads) {
            return tree_query_reduce(tree, queries, k, self_index, num_threads,
                                     knn::Output::kMean);
          },
          "queries"_a, "k"_a, "self_index"_a = nb::none(), "num_threads"_a = 0,
          "Mean Euclidean distance to the k nearest points, float32 (M,).")
      .def(
          "query_kth",
          [](const knn::KDTree& tree, const Points& queries, int k,
             const std::optional<SelfIndex>& self_index, int num_threads) {
            return tree_query_reduce(tree, queries, k, self_index, num_threads,
                                     knn::Output::kKth);
          },
          "queries"_a, "k"_a, "self_index"_a = nb::none(), "num_threads"_a = 0,
          "Euclidean distance to the k-th nearest point, float32 (M,).");
}

}  // namespace mlx3d
