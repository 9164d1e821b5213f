// Bounding volume hierarchy over boxed primitives (spheres and triangles), built top-down with
// the binned surface area heuristic and traversed iteratively, near child first.
//
//   SAH cost of a split: C = C_trav + (A_L / A) N_L C_isect + (A_R / A) N_R C_isect
// evaluated at the boundaries of 16 centroid bins along the widest centroid axis (Wald, "On fast
// construction of SAH-based bounding volume hierarchies", IEEE RT 2007; PBRT 3rd ed., sec. 4.3).
// Nodes are stored depth-first: a node's first child follows it, the second is at `second`.
#pragma once

#include <cstdint>
#include <vector>

#include "render/kernels.h"

namespace kinema::render {

struct BvhNode {
  Scalar lo[3], hi[3];
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

  // lo, hi: 3n values, the bounds of primitive i at [3i, 3i + 3).
  Bvh(const std::vector<Scalar>& lo, const std::vector<Scalar>& hi);

  const std::vector<BvhNode>& nodes() const { return nodes_; }
  const std::vector<Index>& order() const { return order_; }
  int depth() const { return depth_; }

  // Visits the leaves whose boxes the ray meets within (t_min, t_max), near first; `leaf(first,
  // count, t_max)` tests those primitives and returns the (possibly shrunk) t_max.
  template <class Leaf>
  Scalar traverse(const Vec3& origin, const Vec3& direction, Scalar t_min, Scalar t_max,
                  Leaf&& leaf) const {
    if (nodes_.empty()) return t_max;
    const Vec3 inv_dir = direction.cwiseInverse();
    std::int32_t stack[kStackSize];
    int top = 0;
    std::int32_t node = 0;
    for (;;) {
      const BvhNode& n = nodes_[static_cast<size_t>(node)];
      if (hit_box(n.lo, n.hi, origin, inv_dir, t_min, t_max)) {
        if (n.count > 0) {
          t_max = leaf(n.first, n.count, t_max);
        } else if (direction[n.axis] < 0) {
          stack[top++] = node + 1;
          node = n.second;
          continue;
        } else {
          stack[top++] = n.second;
          node = node + 1;
          continue;
        }
      }
      if (top == 0) break;
      node = stack[--top];
    }
    return t_max;
  }

 private:
  std::int32_t build(Index begin, Index end, int depth, const std::vector<Scalar>& lo,
                     const std::vector<Scalar>& hi, const std::vector<Scalar>& centroid);

  std::vector<BvhNode> nodes_;
  std::vector<Index> order_;
  int depth_ = 0;
};

}  // namespace kinema::render
