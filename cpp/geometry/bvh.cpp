// Binned-SAH BVH construction (Wald 2007; PBRT 3rd ed., sec. 4.3.2).
#include "geometry/bvh.h"

#include <algorithm>
#include <array>

#include "core/errors.h"

namespace kinema::geometry {

namespace {

struct Box {
  Scalar lo[3] = {kInfinity, kInfinity, kInfinity};
  Scalar hi[3] = {-kInfinity, -kInfinity, -kInfinity};
  void grow(const Scalar* l, const Scalar* h) {
    for (int a = 0; a < 3; ++a) {
      lo[a] = std::min(lo[a], l[a]);
      hi[a] = std::max(hi[a], h[a]);
    }
  }
  void grow(const Box& b) { grow(b.lo, b.hi); }
  Scalar area() const {
    const Scalar dx = hi[0] - lo[0], dy = hi[1] - lo[1], dz = hi[2] - lo[2];
    return dx < 0 ? 0 : 2 * (dx * dy + dy * dz + dz * dx);
  }
};

Scalar node_area(const BvhNode& n) {
  Box b;
  b.grow(n.lo, n.hi);
  return b.area();
}

// Relative cost of a traversal step against one primitive test (PBRT's 1/8).
constexpr Scalar kTraversalCost = 0.125;

}  // namespace

Bvh::Bvh(const std::vector<Scalar>& lo, const std::vector<Scalar>& hi, int max_leaf_size)
    : max_leaf_size_(std::max(max_leaf_size, 1)) {
  const Index n = static_cast<Index>(lo.size() / 3);
  if (n == 0) return;
  if (n > (Index(1) << 29)) throw InvalidArgument("bvh: more than 2^29 primitives");
  std::vector<Scalar> centroid(lo.size());
  for (size_t i = 0; i < lo.size(); ++i) centroid[i] = 0.5 * (lo[i] + hi[i]);
  order_.resize(static_cast<size_t>(n));
  for (Index i = 0; i < n; ++i) order_[static_cast<size_t>(i)] = i;
  nodes_.reserve(static_cast<size_t>(2 * n));
  build(0, n, 0, lo, hi, centroid);
  keep_leaf_boxes(lo, hi);
  area_sum_ = 0;
  for (size_t k = nodes_.size(); k-- > 0;) area_sum_ += node_area(nodes_[k]);
}

void Bvh::keep_leaf_boxes(const std::vector<Scalar>& lo, const std::vector<Scalar>& hi) {
  leaf_box_.resize(2 * lo.size());
  for (size_t j = 0; j < order_.size(); ++j) {
    const size_t p = 3 * static_cast<size_t>(order_[j]);
    for (int c = 0; c < 3; ++c) {
      leaf_box_[6 * j + c] = lo[p + c];
      leaf_box_[6 * j + 3 + c] = hi[p + c];
    }
  }
}

std::int32_t Bvh::build(Index begin, Index end, int depth, const std::vector<Scalar>& lo,
                        const std::vector<Scalar>& hi, const std::vector<Scalar>& centroid) {
  depth_ = std::max(depth_, depth + 1);
  const auto self = static_cast<std::int32_t>(nodes_.size());
  nodes_.emplace_back();
  Box bounds, cbounds;
  for (Index i = begin; i < end; ++i) {
    const size_t p = 3 * static_cast<size_t>(order_[static_cast<size_t>(i)]);
    bounds.grow(&lo[p], &hi[p]);
    cbounds.grow(&centroid[p], &centroid[p]);
  }
  auto make_leaf = [&] {
    BvhNode& node = nodes_[static_cast<size_t>(self)];
    std::copy(bounds.lo, bounds.lo + 3, node.lo);
    std::copy(bounds.hi, bounds.hi + 3, node.hi);
    node.second = -1;
    node.axis = 0;
    node.first = static_cast<std::int32_t>(begin);
    node.count = static_cast<std::int32_t>(end - begin);
    return self;
  };
  const Index n = end - begin;
  if (n <= max_leaf_size_) return make_leaf();

  int axis = 0;
  for (int a = 1; a < 3; ++a)
    if (cbounds.hi[a] - cbounds.lo[a] > cbounds.hi[axis] - cbounds.lo[axis]) axis = a;
  const Scalar c_lo = cbounds.lo[axis], extent = cbounds.hi[axis] - cbounds.lo[axis];
  auto key = [&](Index prim) { return centroid[3 * static_cast<size_t>(prim) + axis]; };

  Index mid = begin + n / 2;
  bool median = extent <= 0 || depth >= kMaxSahDepth;
  if (!median) {
    auto bin_of = [&](Index prim) {
      const auto b = static_cast<int>(kBins * ((key(prim) - c_lo) / extent));
      return std::min(std::max(b, 0), kBins - 1);
    };
    std::array<Index, kBins> count{};
    std::array<Box, kBins> box;
    for (Index i = begin; i < end; ++i) {
      const Index prim = order_[static_cast<size_t>(i)];
      const int b = bin_of(prim);
      ++count[b];
      box[b].grow(&lo[3 * static_cast<size_t>(prim)], &hi[3 * static_cast<size_t>(prim)]);
    }
    // Sweep from the right for the right-hand areas, then from the left for the costs.
    std::array<Scalar, kBins> right_area{};
    std::array<Index, kBins> right_count{};
    Box acc;
    Index cnt = 0;
    for (int b = kBins - 1; b > 0; --b) {
      acc.grow(box[b]);
      cnt += count[b];
      right_area[b] = acc.area();
      right_count[b] = cnt;
    }
    Box left;
    Index left_count = 0;
    Scalar best_cost = kInfinity;
    int best = -1;
    const Scalar inv_area = bounds.area() > 0 ? 1 / bounds.area() : 0;
    for (int b = 1; b < kBins; ++b) {
      left.grow(box[b - 1]);
      left_count += count[b - 1];
      if (left_count == 0 || right_count[b] == 0) continue;
      const Scalar cost = kTraversalCost + inv_area * (static_cast<Scalar>(left_count) * left.area() +
                                                       static_cast<Scalar>(right_count[b]) * right_area[b]);
      if (cost < best_cost) {
        best_cost = cost;
        best = b;
      }
    }
    if (best < 0) {
      median = true;
    } else {
      if (n <= max_leaf_size_ * 4 && best_cost >= static_cast<Scalar>(n)) return make_leaf();
      auto split = std::partition(order_.begin() + begin, order_.begin() + end,
                                  [&](Index prim) { return bin_of(prim) < best; });
      mid = split - order_.begin();
    }
  }
  if (median) {
    // Ties broken by primitive id, so the tree does not depend on the library's nth_element.
    std::nth_element(order_.begin() + begin, order_.begin() + mid, order_.begin() + end,
                     [&](Index a, Index b) { return key(a) < key(b) || (key(a) == key(b) && a < b); });
  }

  {
    BvhNode& node = nodes_[static_cast<size_t>(self)];
    std::copy(bounds.lo, bounds.lo + 3, node.lo);
    std::copy(bounds.hi, bounds.hi + 3, node.hi);
    node.axis = axis;
    node.first = 0;
    node.count = 0;
  }
  build(begin, mid, depth + 1, lo, hi, centroid);
  const std::int32_t second = build(mid, end, depth + 1, lo, hi, centroid);
  nodes_[static_cast<size_t>(self)].second = second;
  return self;
}

void Bvh::refit(const std::vector<Scalar>& lo, const std::vector<Scalar>& hi) {
  if (lo.size() != 3 * order_.size() || hi.size() != lo.size())
    throw InvalidArgument("bvh: refit needs the bounds of the same primitives");
  keep_leaf_boxes(lo, hi);
  // Children follow their parent in the depth-first layout, so a reverse sweep sees them first;
  // a leaf's primitives are contiguous in the leaf-ordered bounds.
  Scalar sum = 0;
  for (size_t k = nodes_.size(); k-- > 0;) {
    BvhNode& node = nodes_[k];
    Box b;
    if (node.count > 0) {
      for (std::int32_t i = 0; i < node.count; ++i) {
        const size_t p = 6 * static_cast<size_t>(node.first + i);
        b.grow(&leaf_box_[p], &leaf_box_[p + 3]);
      }
    } else {
      const BvhNode& left = nodes_[k + 1];
      const BvhNode& right = nodes_[static_cast<size_t>(node.second)];
      b.grow(left.lo, left.hi);
      b.grow(right.lo, right.hi);
    }
    std::copy(b.lo, b.lo + 3, node.lo);
    std::copy(b.hi, b.hi + 3, node.hi);
    sum += b.area();
  }
  area_sum_ = sum;
}

Scalar Bvh::area_ratio() const {
  if (nodes_.empty()) return 0;
  const Scalar root = node_area(nodes_[0]);
  return root > 0 ? area_sum_ / root : 0;
}

}  // namespace kinema::geometry
