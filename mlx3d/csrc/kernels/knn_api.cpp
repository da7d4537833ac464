// The k-d tree k-NN (knn.h, knn.cpp) behind the C API: a tree is an opaque handle from mlx3d_knn_build,
// queried any number of times (from any threads: the tree is read-only) and released by mlx3d_knn_free.
#include <algorithm>
#include <cstdint>
#include <string>
#include <vector>

#include "api.h"
#include "knn.h"
#include "mlx3d_kernels.h"

namespace {

const mlx3d::knn::KDTree& tree_of(const void* tree) {
  mlx3d::require(tree != nullptr, "a null tree");
  return *static_cast<const mlx3d::knn::KDTree*>(tree);
}

}  // namespace

extern "C" {

MLX3D_API int mlx3d_knn_build(const float* xyz, int64_t n, int leaf_size, void** tree) {
  return mlx3d::guarded("mlx3d_knn_build", [&] {
    mlx3d::require(tree != nullptr, "a null output pointer");
    *tree = nullptr;
    mlx3d::require(n <= 0 || xyz != nullptr, "a null points pointer");
    *tree = new mlx3d::knn::KDTree(xyz, n, leaf_size);  // checks the count and the leaf size
  });
}

MLX3D_API int mlx3d_knn_free(void* tree) {
  return mlx3d::guarded("mlx3d_knn_free", [&] { delete static_cast<mlx3d::knn::KDTree*>(tree); });
}

MLX3D_API int mlx3d_knn_info(const void* tree, int64_t* size, int* leaf_size, int* depth, int64_t* node_count) {
  return mlx3d::guarded("mlx3d_knn_info", [&] {
    const auto& t = tree_of(tree);
    mlx3d::require(size && leaf_size && depth && node_count, "a null output pointer");
    *size = t.size();
    *leaf_size = t.leaf_size();
    *depth = t.depth();
    *node_count = t.node_count();
  });
}

MLX3D_API int mlx3d_knn_order(const void* tree, int64_t* order) {
  return mlx3d::guarded("mlx3d_knn_order", [&] {
    const auto& t = tree_of(tree);
    mlx3d::require(order != nullptr, "a null output pointer");
    const std::vector<int64_t> o = t.order();
    std::copy(o.begin(), o.end(), order);
  });
}

MLX3D_API int mlx3d_knn_query(const void* tree, const float* queries, int64_t m, int k, const int64_t* self_index, int output,
                              int threads, int64_t* out_index, float* out_dist) {
  return mlx3d::guarded("mlx3d_knn_query", [&] {
    const auto& t = tree_of(tree);
    mlx3d::require(output >= 0 && output <= 2, "output must be 0 (neighbours), 1 (mean) or 2 (k-th), got " + std::to_string(output));
    mlx3d::require(threads >= 0, "threads must be >= 0 (0 = every hardware thread), got " + std::to_string(threads));
    mlx3d::knn::QueryArgs args;  // query() checks k, self_index and the buffers
    args.queries = queries;
    args.m = m;
    args.k = k;
    args.self_index = self_index;
    args.num_threads = threads;
    args.output = output == 0 ? mlx3d::knn::Output::kNeighbours : output == 1 ? mlx3d::knn::Output::kMean : mlx3d::knn::Output::kKth;
    args.out_index = out_index;
    args.out_dist = out_dist;
    t.query(args);
  });
}

}  // extern "C"
