// k-nearest-neighbour search over 3D float32 points with a k-d tree.
//
// The tree is built once (median split on the widest axis of each node's tight
// bounding box) and queried with a bounded max-heap per query. Distances are
// accumulated in double precision, so results do not depend on the magnitude
// of the coordinates. Queries are spread over the kernels' worker threads (run_threads, parallel.h).
#pragma once

#include <cstdint>
#include <vector>

namespace mlx3d::knn {

// Point stored in tree order together with its original index.
struct TreePoint {
  float x, y, z;
  int32_t index;
};

// Node of the k-d tree. Children of an inner node are stored next to each
// other (`left`, `left + 1`); `left == -1` marks a leaf.
struct Node {
  float lo[3];
  float hi[3];
  int32_t begin;
  int32_t end;
  int32_t left;
  int32_t depth;
};

// What a query writes per query row.
enum class Output {
  kNeighbours,  // k indices (int64) and k squared distances (float32), sorted
  kMean,        // mean Euclidean distance to the k neighbours (float32)
  kKth,         // Euclidean distance to the k-th neighbour (float32)
};

struct QueryArgs {
  const float* queries = nullptr;      // (m, 3) row-major
  int64_t m = 0;
  int k = 1;
  const int64_t* self_index = nullptr; // (m,) or nullptr; -1 = no self
  int num_threads = 0;                 // 0 = all hardware threads
  Output output = Output::kNeighbours;
  int64_t* out_index = nullptr;        // (m, k) for kNeighbours
  float* out_dist = nullptr;           // (m, k) squared or (m,) reduced
};

class KDTree {
 public:
  // `xyz` is (n, 3) row-major float32; all coordinates must be finite.
  KDTree(const float* xyz, int64_t n, int leaf_size);

  int64_t size() const { return static_cast<int64_t>(points_.size()); }
  int leaf_size() const { return leaf_size_; }
  int depth() const { return max_depth_ + 1; }
  int64_t node_count() const { return static_cast<int64_t>(nodes_.size()); }

  // Original point indices in tree (spatially coherent) order.
  std::vector<int64_t> order() const;

  // Runs the queries described by `args`; validates k / self_index and throws
  // std::invalid_argument on bad input. Thread-safe (the tree is read-only).
  void query(const QueryArgs& args) const;

  static int hardware_threads();

 private:
  void build(int32_t begin, int32_t end, int32_t depth);
  void query_range(const QueryArgs& args, int64_t q0, int64_t q1,
                   double* heap_d, int32_t* heap_i,
                   std::vector<std::pair<int32_t, double>>& stack) const;

  std::vector<TreePoint> points_;
  std::vector<Node> nodes_;
  int leaf_size_ = 16;
  int max_depth_ = 0;
};

}  // namespace mlx3d::knn
