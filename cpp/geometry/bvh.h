// Bounding volume hierarchy over axis-aligned boxes of primitives (the renderer's spheres and
// triangles, the contact solver's points, edges and faces), built top-down with the binned
// surface area heuristic. Queries: a ray walk, near child first (rendering), all boxes
// overlapping a given box, and simultaneous descents of two trees (or of one against itself)
// for exactly the overlapping primitive pairs (contact broad phase: the tree keeps the primitive
// boxes in leaf order).
//
//   SAH cost of a split: C = C_trav + (A_L / A) N_L C_isect + (A_R / A) N_R C_isect
// evaluated at the boundaries of 16 centroid bins along the widest centroid axis (Wald, "On fast
// construction of SAH-based bounding volume hierarchies", IEEE RT 2007; PBRT 3rd ed., sec. 4.3).
// Nodes are stored depth-first: a node's first child follows it, the second is at `second`.
#pragma once

#include <Eigen/Core>
#include <algorithm>
#include <array>
#include <cstdint>
#include <limits>
#include <vector>

#if defined(__SSE2__)
#include <emmintrin.h>
#endif

#include "core/types.h"

namespace kinema::geometry {

using Vec3 = Eigen::Matrix<Scalar, 3, 1>;
constexpr Scalar kInfinity = std::numeric_limits<Scalar>::infinity();

// 1 + 2 gamma_3 with gamma_n = n u / (1 - n u): widening the far slab distance by this factor
// makes the slab test conservative under rounding (PBRT 3rd ed., sec. 3.9.2), so a BVH never
// misses a hit that the brute-force loop finds.
constexpr Scalar kSlabWiden = 1 + 2 * (3 * 0x1p-53 / (1 - 3 * 0x1p-53));

// Slab test of the box [lo, hi] against a ray given by its origin and inverse direction; true
// when the ray meets the box for some t in (t_min, t_max). NaNs (0 * inf when the origin lies
// on a slab plane) fail every comparison and leave the interval unchanged, as in PBRT.
inline bool hit_box(const Scalar lo[3], const Scalar hi[3], const Vec3& origin, const Vec3& inv_dir,
                    Scalar t_min, Scalar t_max) {
  for (int a = 0; a < 3; ++a) {
    Scalar t_near = (lo[a] - origin[a]) * inv_dir[a];
    Scalar t_far = (hi[a] - origin[a]) * inv_dir[a];
    if (t_near > t_far) std::swap(t_near, t_far);
    t_far *= kSlabWiden;
    t_min = t_near > t_min ? t_near : t_min;
    t_max = t_far < t_max ? t_far : t_max;
    if (t_min > t_max) return false;
  }
  return true;
}


struct BvhNode {
  Scalar lo[3], hi[3];  // contiguous: Bvh::overlap6 reads the six as one box
  std::int32_t second;  // interior: index of the second child; leaf: -1
  std::int32_t axis;    // interior: split axis (the near child is chosen by the ray's sign)
  std::int32_t first;   // leaf: first entry in Bvh::order
  std::int32_t count;   // leaf: number of primitives (0 for interior nodes)
};

class Bvh {
 public:
  static constexpr int kMaxLeafSize = 4;
  static constexpr int kBins = 16;
  // Beyond this depth a node is split at the median: bounds the depth (and the traversal stack)
  // even for adversarial inputs where the SAH peels off one primitive at a time.
  static constexpr int kMaxSahDepth = 40;
  static constexpr int kStackSize = 128;

  Bvh() = default;
  // lo, hi: 3n values, the bounds of primitive i at [3i, 3i + 3). max_leaf_size: a node of at
  // most this many primitives is a leaf (the SAH may stop at up to 4x as many); pair descents
  // (contact) run faster with larger leaves than ray walks do.
  Bvh(const std::vector<Scalar>& lo, const std::vector<Scalar>& hi, int max_leaf_size = kMaxLeafSize);

  // Recomputes every node's box from new bounds of the same primitives, keeping the tree: O(n),
  // and every query stays exact (only its speed depends on how well the old grouping fits).
  void refit(const std::vector<Scalar>& lo, const std::vector<Scalar>& hi);
  // Sum of the nodes' surface areas over the root's: the SAH's expected number of nodes a query
  // visits, up to constants. A refit tree whose ratio has grown well past its build's is worth
  // rebuilding.
  Scalar area_ratio() const;

  const std::vector<BvhNode>& nodes() const { return nodes_; }
  static bool overlap(const BvhNode& a, const BvhNode& b) {
    return (a.lo[0] <= b.hi[0]) & (b.lo[0] <= a.hi[0]) & (a.lo[1] <= b.hi[1]) & (b.lo[1] <= a.hi[1]) &
           (a.lo[2] <= b.hi[2]) & (b.lo[2] <= a.hi[2]);
  }
  static Scalar extent(const BvhNode& a) { return (a.hi[0] - a.lo[0]) + (a.hi[1] - a.lo[1]) + (a.hi[2] - a.lo[2]); }
  const std::vector<Index>& order() const { return order_; }
  int depth() const { return depth_; }

  // Depth-first walk over the nodes that `enter(node)` accepts, calling `leaf(node)` on each
  // accepted leaf; `second_first(node)` says whether an interior node's second child is
  // visited before its first. The one stack loop under both queries below.
  template <class Enter, class Leaf, class SecondFirst>
  void walk(Enter&& enter, Leaf&& leaf, SecondFirst&& second_first) const {
    if (nodes_.empty()) return;
    std::int32_t stack[kStackSize];
    int top = 0;
    std::int32_t node = 0;
    for (;;) {
      const BvhNode& n = nodes_[static_cast<size_t>(node)];
      if (enter(n)) {
        if (n.count > 0) {
          leaf(n);
        } else {
          const bool swap = second_first(n);
          stack[top++] = swap ? node + 1 : n.second;
          node = swap ? n.second : node + 1;
          continue;
        }
      }
      if (top == 0) break;
      node = stack[--top];
    }
  }

  // Calls `visit(i, j)` for every primitive i of this tree and j of `other` whose own boxes (the
  // bounds last given to the constructor or to refit) overlap, closed boxes: exactly the
  // overlapping pairs, by one simultaneous descent of both trees (far fewer box tests than a
  // query per primitive). The tree keeps those bounds in leaf order, so a leaf pair is tested in
  // contiguous memory, each primitive first against the other leaf's box.
  template <class Visit>
  void query_box_pairs(const Bvh& other, Visit&& visit) const {
    pair_descent(other, 0, visit);
  }
  // The same of the tree against itself: `visit(i, j)` once for every unordered pair of
  // different primitives whose boxes overlap (i and j in either order).
  template <class Visit>
  void query_box_self(Visit&& visit) const {
    pair_descent(*this, 1, visit);
  }

  // Visits the leaves whose boxes the ray meets within (t_min, t_max), near first; `leaf(first,
  // count, t_max)` tests those primitives and returns the (possibly shrunk) t_max.
  template <class Leaf>
  Scalar traverse(const Vec3& origin, const Vec3& direction, Scalar t_min, Scalar t_max,
                  Leaf&& leaf) const {
    const Vec3 inv_dir = direction.cwiseInverse();
    walk([&](const BvhNode& n) { return hit_box(n.lo, n.hi, origin, inv_dir, t_min, t_max); },
         [&](const BvhNode& n) { t_max = leaf(n.first, n.count, t_max); },
         [&](const BvhNode& n) { return direction[n.axis] < 0; });
    return t_max;
  }

  // Calls `visit(primitive)` for every primitive of every leaf whose box overlaps [lo, hi]
  // (closed boxes, so touching boxes count: the contact broad phase must never drop a pair at
  // the threshold). A superset of the primitives whose own boxes overlap: the tree keeps no
  // per-primitive boxes, so callers test their primitives themselves.
  template <class Visit>
  void query(const Scalar lo[3], const Scalar hi[3], Visit&& visit) const {
    walk(
        [&](const BvhNode& n) {
          // Non-short-circuit: six comparisons without branches.
          return (n.lo[0] <= hi[0]) & (lo[0] <= n.hi[0]) & (n.lo[1] <= hi[1]) & (lo[1] <= n.hi[1]) &
                 (n.lo[2] <= hi[2]) & (lo[2] <= n.hi[2]);
        },
        [&](const BvhNode& n) {
          for (std::int32_t i = 0; i < n.count; ++i) visit(order_[static_cast<size_t>(n.first + i)]);
        },
        [](const BvhNode&) { return false; });
  }

 private:
  // Closed-box overlap of boxes stored as (lo[3], hi[3]): lo_a <= hi_b and lo_b <= hi_a in
  // every axis. With SSE2 two axes per comparison; the same six comparisons either way.
  static bool overlap6(const Scalar* a, const Scalar* b) {
#if defined(__SSE2__)
    const __m128d x = _mm_cmple_pd(_mm_loadu_pd(a), _mm_loadu_pd(b + 3));
    const __m128d y = _mm_cmple_pd(_mm_loadu_pd(b), _mm_loadu_pd(a + 3));
    const __m128d z = _mm_cmple_pd(_mm_unpacklo_pd(_mm_load_sd(a + 2), _mm_load_sd(b + 2)),
                                   _mm_unpacklo_pd(_mm_load_sd(b + 5), _mm_load_sd(a + 5)));
    return _mm_movemask_pd(_mm_and_pd(_mm_and_pd(x, y), z)) == 3;
#else
    return (a[0] <= b[3]) & (b[0] <= a[3]) & (a[1] <= b[4]) & (b[1] <= a[4]) & (a[2] <= b[5]) & (b[2] <= a[5]);
#endif
  }

  // The primitive pairs of leaves A (of this tree) and B (of `other`) whose primitive boxes
  // overlap, j > i only when `upper` (a leaf against itself).
  template <class Visit>
  void leaf_pairs(const Bvh& other, const BvhNode& A, const BvhNode& B, bool upper, Visit& visit) const {
    for (std::int32_t i = 0; i < A.count; ++i) {
      const size_t a = static_cast<size_t>(A.first + i);
      if (!upper && !overlap6(&leaf_box_[6 * a], B.lo)) continue;
      for (std::int32_t j = upper ? i + 1 : 0; j < B.count; ++j) {
        const size_t b = static_cast<size_t>(B.first + j);
        if (!overlap6(&leaf_box_[6 * a], &other.leaf_box_[6 * b])) continue;
        visit(order_[a], other.order_[b]);
      }
    }
  }

  // Simultaneous descent from the roots (self: of the tree against itself, each unordered
  // pair of leaves once). The stack holds at most the two depths' sum per level of the self
  // descent: 4 * kStackSize covers the deepest trees the builder makes (bvh.cpp bounds the
  // depth by kMaxSahDepth plus the median splits of at most 2^29 primitives).
  template <class Visit>
  void pair_descent(const Bvh& other, int self, Visit& visit) const {
    if (nodes_.empty() || other.nodes_.empty()) return;
    std::array<std::int32_t, 2> stack[4 * kStackSize];
    int top = 0;
    stack[top++] = {0, 0};
    while (top > 0) {
      const auto [a, b] = stack[--top];
      const BvhNode& A = nodes_[static_cast<size_t>(a)];
      if (self && a == b) {
        if (A.count > 0) {
          leaf_pairs(*this, A, A, true, visit);
        } else {
          stack[top++] = {a + 1, A.second};
          stack[top++] = {A.second, A.second};
          stack[top++] = {a + 1, a + 1};
        }
        continue;
      }
      const BvhNode& B = other.nodes_[static_cast<size_t>(b)];
      if (!overlap6(A.lo, B.lo)) continue;
      if (A.count > 0 && B.count > 0) {
        leaf_pairs(other, A, B, false, visit);
      } else if (B.count > 0 || (A.count == 0 && extent(A) >= extent(B))) {
        stack[top++] = {A.second, b};
        stack[top++] = {a + 1, b};
      } else {
        stack[top++] = {a, B.second};
        stack[top++] = {a, b + 1};
      }
    }
  }

  std::int32_t build(Index begin, Index end, int depth, const std::vector<Scalar>& lo,
                     const std::vector<Scalar>& hi, const std::vector<Scalar>& centroid);

  void keep_leaf_boxes(const std::vector<Scalar>& lo, const std::vector<Scalar>& hi);

  std::vector<BvhNode> nodes_;
  std::vector<Index> order_;
  std::vector<Scalar> leaf_box_;  // primitive order_[j]'s bounds (lo[3], hi[3]) at 6 j (leaf order)
  Scalar area_sum_ = 0;                    // sum of the nodes' surface areas (area_ratio)
  int max_leaf_size_ = kMaxLeafSize;
  int depth_ = 0;
};

}  // namespace kinema::geometry
