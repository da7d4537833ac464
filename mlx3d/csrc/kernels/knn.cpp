#include "knn.h"

#include "parallel.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <string>
#include <thread>
#include <utility>

namespace mlx3d::knn {

namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();
// Queries handed to a thread at a time (dynamic scheduling: queries near far
// outliers cost more than queries inside dense regions).
constexpr int64_t kBlock = 512;

inline double box_dist2(const Node& n, double qx, double qy, double qz) {
  double d2 = 0.0;
  double t;
  t = std::max({static_cast<double>(n.lo[0]) - qx, qx - static_cast<double>(n.hi[0]), 0.0});
  d2 += t * t;
  t = std::max({static_cast<double>(n.lo[1]) - qy, qy - static_cast<double>(n.hi[1]), 0.0});
  d2 += t * t;
  t = std::max({static_cast<double>(n.lo[2]) - qz, qz - static_cast<double>(n.hi[2]), 0.0});
  d2 += t * t;
  return d2;
}

// Bounded max-heap of (squared distance, index); the root is the worst kept.
struct Heap {
  double* d;
  int32_t* i;
  int k;
  int size;

  double worst() const { return size < k ? kInf : d[0]; }

  void push(double dist, int32_t idx) {
    if (size < k) {
      int c = size++;
      while (c > 0) {
        int p = (c - 1) >> 1;
        if (d[p] >= dist) break;
        d[c] = d[p];
        i[c] = i[p];
        c = p;
      }
      d[c] = dist;
      i[c] = idx;
    } else {
      // Replace the root (caller checked dist < d[0]) and sift down.
      int c = 0;
      for (;;) {
        int l = 2 * c + 1;
        if (l >= k) break;
        int r = l + 1;
        int m = (r < k && d[r] > d[l]) ? r : l;
        if (d[m] <= dist) break;
        d[c] = d[m];
        i[c] = i[m];
        c = m;
      }
      d[c] = dist;
      i[c] = idx;
    }
  }

  // Sorts the kept entries by (distance, index) in place.
  void sort() {
    // Insertion sort: k is small and the heap is partially ordered.
    for (int a = 1; a < size; ++a) {
      double dv = d[a];
      int32_t iv = i[a];
      int b = a - 1;
      while (b >= 0 && (d[b] > dv || (d[b] == dv && i[b] > iv))) {
        d[b + 1] = d[b];
        i[b + 1] = i[b];
        --b;
      }
      d[b + 1] = dv;
      i[b + 1] = iv;
    }
  }
};

}  // namespace

int KDTree::hardware_threads() {
  unsigned h = std::thread::hardware_concurrency();
  return h == 0 ? 1 : static_cast<int>(h);
}

KDTree::KDTree(const float* xyz, int64_t n, int leaf_size) {
  if (n <= 0) {
    throw std::invalid_argument("points is empty: at least one point is required");
  }
  if (n > std::numeric_limits<int32_t>::max() - 1) {
    throw std::invalid_argument("points has " + std::to_string(n) +
                                " rows; at most 2^31 - 2 are supported");
  }
  if (leaf_size < 1) {
    throw std::invalid_argument("leaf_size must be >= 1, got " + std::to_string(leaf_size));
  }
  leaf_size_ = leaf_size;
  points_.resize(static_cast<size_t>(n));
  for (int64_t j = 0; j < n; ++j) {
    points_[j] = {xyz[3 * j], xyz[3 * j + 1], xyz[3 * j + 2], static_cast<int32_t>(j)};
  }
  nodes_.reserve(static_cast<size_t>(4 * (n / leaf_size_ + 1)));
  nodes_.push_back(Node{});
  build(0, static_cast<int32_t>(n), 0);
}

void KDTree::build(int32_t begin, int32_t end, int32_t depth) {
  // Iterative over an explicit work list to keep the stack shallow and the
  // node layout deterministic: each entry is (node id, begin, end, depth).
  struct Work {
    int32_t id, begin, end, depth;
  };
  std::vector<Work> work;
  work.push_back({0, begin, end, depth});
  while (!work.empty()) {
    Work w = work.back();
    work.pop_back();
    float lo[3] = {points_[w.begin].x, points_[w.begin].y, points_[w.begin].z};
    float hi[3] = {lo[0], lo[1], lo[2]};
    for (int32_t j = w.begin + 1; j < w.end; ++j) {
      const TreePoint& p = points_[j];
      lo[0] = std::min(lo[0], p.x);
      hi[0] = std::max(hi[0], p.x);
      lo[1] = std::min(lo[1], p.y);
      hi[1] = std::max(hi[1], p.y);
      lo[2] = std::min(lo[2], p.z);
      hi[2] = std::max(hi[2], p.z);
    }
    Node node{};
    for (int a = 0; a < 3; ++a) {
      node.lo[a] = lo[a];
      node.hi[a] = hi[a];
    }
    node.begin = w.begin;
    node.end = w.end;
    node.depth = w.depth;
    node.left = -1;
    max_depth_ = std::max(max_depth_, static_cast<int>(w.depth));

    if (w.end - w.begin > leaf_size_) {
      // Median split on the widest axis. Ranges of identical coordinates are
      // still split by position, which keeps the tree balanced (and queries
      // fast) for duplicated or degenerate clouds.
      double ext[3];
      for (int a = 0; a < 3; ++a) ext[a] = static_cast<double>(hi[a]) - lo[a];
      int axis = 0;
      if (ext[1] > ext[axis]) axis = 1;
      if (ext[2] > ext[axis]) axis = 2;
      int32_t mid = w.begin + (w.end - w.begin) / 2;
      auto first = points_.begin() + w.begin;
      auto nth = points_.begin() + mid;
      auto last = points_.begin() + w.end;
      switch (axis) {
        case 0:
          std::nth_element(first, nth, last,
                           [](const TreePoint& a, const TreePoint& b) { return a.x < b.x; });
          break;
        case 1:
          std::nth_element(first, nth, last,
                           [](const TreePoint& a, const TreePoint& b) { return a.y < b.y; });
          break;
        default:
          std::nth_element(first, nth, last,
                           [](const TreePoint& a, const TreePoint& b) { return a.z < b.z; });
          break;
      }
      int32_t left = static_cast<int32_t>(nodes_.size());
      nodes_.push_back(Node{});
      nodes_.push_back(Node{});
      node.left = left;
      work.push_back({left + 1, mid, w.end, w.depth + 1});
      work.push_back({left, w.begin, mid, w.depth + 1});
    }
    nodes_[w.id] = node;
  }
}

std::vector<int64_t> KDTree::order() const {
  std::vector<int64_t> out(points_.size());
  for (size_t j = 0; j < points_.size(); ++j) out[j] = points_[j].index;
  return out;
}

void KDTree::query_range(const QueryArgs& args, int64_t q0, int64_t q1, double* heap_d,
                         int32_t* heap_i,
                         std::vector<std::pair<int32_t, double>>& stack) const {
  const int k = args.k;
  const Node* nodes = nodes_.data();
  const TreePoint* pts = points_.data();
  for (int64_t q = q0; q < q1; ++q) {
    const double qx = args.queries[3 * q];
    const double qy = args.queries[3 * q + 1];
    const double qz = args.queries[3 * q + 2];
    const int32_t self =
        args.self_index ? static_cast<int32_t>(args.self_index[q]) : int32_t{-1};
    Heap heap{heap_d, heap_i, k, 0};

    stack.clear();
    stack.emplace_back(0, box_dist2(nodes[0], qx, qy, qz));
    while (!stack.empty()) {
      auto [id, dist] = stack.back();
      stack.pop_back();
      if (!(dist < heap.worst())) continue;
      // Descend to the nearer child, remembering the farther one.
      while (nodes[id].left >= 0) {
        const int32_t l = nodes[id].left;
        double dl = box_dist2(nodes[l], qx, qy, qz);
        double dr = box_dist2(nodes[l + 1], qx, qy, qz);
        int32_t near = l, far = l + 1;
        if (dr < dl) {
          std::swap(near, far);
          std::swap(dl, dr);
        }
        const double worst = heap.worst();
        if (dr < worst) stack.emplace_back(far, dr);
        if (!(dl < worst)) {
          id = -1;
          break;
        }
        id = near;
      }
      if (id < 0) continue;
      const Node& leaf = nodes[id];
      double worst = heap.worst();
      for (int32_t j = leaf.begin; j < leaf.end; ++j) {
        const TreePoint& p = pts[j];
        const double dx = static_cast<double>(p.x) - qx;
        const double dy = static_cast<double>(p.y) - qy;
        const double dz = static_cast<double>(p.z) - qz;
        const double d2 = dx * dx + dy * dy + dz * dz;
        if (d2 < worst && p.index != self) {
          heap.push(d2, p.index);
          worst = heap.worst();
        }
      }
    }

    heap.sort();
    switch (args.output) {
      case Output::kNeighbours: {
        int64_t* oi = args.out_index + q * k;
        float* od = args.out_dist + q * k;
        for (int j = 0; j < k; ++j) {
          oi[j] = heap_i[j];
          od[j] = static_cast<float>(heap_d[j]);
        }
        break;
      }
      case Output::kMean: {
        double s = 0.0;
        for (int j = 0; j < k; ++j) s += std::sqrt(heap_d[j]);
        args.out_dist[q] = static_cast<float>(s / k);
        break;
      }
      case Output::kKth:
        args.out_dist[q] = static_cast<float>(std::sqrt(heap_d[k - 1]));
        break;
    }
  }
}

void KDTree::query(const QueryArgs& args) const {
  const int64_t n = size();
  if (args.m < 0) throw std::invalid_argument("queries: negative row count");
  if (args.k < 1) {
    throw std::invalid_argument("k must be >= 1, got " + std::to_string(args.k));
  }
  bool any_self = false;
  if (args.self_index) {
    for (int64_t q = 0; q < args.m; ++q) {
      const int64_t s = args.self_index[q];
      if (s < -1 || s >= n) {
        throw std::invalid_argument("self_index[" + std::to_string(q) + "] = " +
                                    std::to_string(s) + " is outside [-1, " +
                                    std::to_string(n) + ")");
      }
      any_self = any_self || s >= 0;
    }
  }
  const int64_t available = any_self ? n - 1 : n;
  if (args.k > available) {
    throw std::invalid_argument("k = " + std::to_string(args.k) + " exceeds the " +
                                std::to_string(available) + " available neighbours");
  }
  if (args.m == 0) return;
  if (args.output == Output::kNeighbours && !args.out_index) {
    throw std::invalid_argument("out_index is required");
  }
  if (!args.out_dist || !args.queries) throw std::invalid_argument("null buffer");

  const int64_t blocks = (args.m + kBlock - 1) / kBlock;
  int threads = args.num_threads > 0 ? args.num_threads : hardware_threads();
  threads = static_cast<int>(std::min<int64_t>(threads, blocks));
  threads = std::max(threads, 1);

  // Per-thread scratch, allocated here so that workers never allocate. The
  // traversal stack holds at most one entry per tree level plus the root.
  struct Scratch {
    std::vector<double> heap_d;
    std::vector<int32_t> heap_i;
    std::vector<std::pair<int32_t, double>> stack;
  };
  std::vector<Scratch> scratch(static_cast<size_t>(threads));
  for (auto& s : scratch) {
    s.heap_d.resize(static_cast<size_t>(args.k));
    s.heap_i.resize(static_cast<size_t>(args.k));
    s.stack.reserve(static_cast<size_t>(max_depth_ + 4));
  }

  std::atomic<int64_t> next{0};
  auto worker = [&](Scratch* s) {
    for (;;) {
      const int64_t b = next.fetch_add(1, std::memory_order_relaxed);
      if (b >= blocks) break;
      const int64_t q0 = b * kBlock;
      const int64_t q1 = std::min(args.m, q0 + kBlock);
      query_range(args, q0, q1, s->heap_d.data(), s->heap_i.data(), s->stack);
    }
  };

  run_threads(threads, [&](int t) { worker(&scratch[t]); });
}

}  // namespace mlx3d::knn
