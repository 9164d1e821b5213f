// Fixed-radius neighbour search on a uniform cell grid stored as flat CSR arrays: points are
// binned by counting sort (cell_start[c] .. cell_start[c+1] index `sorted`), so a rebuild
// allocates nothing once the buffers have grown, and a query visits the 3^d cells around a
// point. This is the compact, allocation-free grid of Ihmsen et al. 2011 ("A parallel SPH
// implementation on multi-core CPUs") without the hash: the grid covers the points' bounding
// box densely and its cell size grows when that box would need too many cells.
// Points are rows of d = 2 or 3 coordinates (row-major, numpy's (n, d) layout).
#pragma once

#include <Eigen/Core>
#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <limits>
#include <vector>

#include "core/types.h"

namespace kinema {

template <int D>
class NeighborGrid {
 public:
  using Vec = Eigen::Matrix<Scalar, D, 1>;
  using Cell = std::array<Index, D>;

  // Bins the n points x (n rows of D coordinates) into cells of edge >= cell_size > 0.
  // Throws InvalidArgument for non-finite coordinates.
  void build(const Scalar* x, Index n, Scalar cell_size);

  Index point_count() const { return static_cast<Index>(sorted_.size()); }
  Index cell_count() const { return static_cast<Index>(cell_start_.size()) - 1; }
  Scalar cell_size() const { return cell_; }

  // Integer cell coordinates of p (may lie outside [0, dims) for points outside the grid).
  Cell cell_of(const Vec& p) const {
    Cell c;
    for (int a = 0; a < D; ++a) {
      // Clamped before the cast: a far-away point must not overflow the integer.
      const Scalar f = std::floor((p[a] - origin_[a]) * inv_cell_);
      c[a] = static_cast<Index>(std::min<Scalar>(std::max<Scalar>(f, -2), static_cast<Scalar>(dims_[a] + 1)));
    }
    return c;
  }

  // Calls visit(j) for every binned point j in the 3^D cells around p: a superset of the points
  // within cell_size of p, in cell order (deterministic). With a radius (at most cell_size),
  // the cells that lie radius or farther from p are skipped (same order for the others).
  template <class Visit>
  void for_each_candidate(const Vec& p, Visit&& visit) const {
    for_each_candidate(p, std::numeric_limits<Scalar>::infinity(), visit);
  }
  template <class Visit>
  void for_each_candidate(const Vec& p, Scalar radius, Visit&& visit) const {
    if (sorted_.empty()) return;
    const Cell c = cell_of(p);
    Cell lo, hi;
    // Squared distances from p to the neighbouring cells on each axis: gap[a][0] below (cell
    // c - 1), gap[a][1] above (c + 1); less a margin for the rounding of the binning.
    Scalar gap[D][2];
    for (int a = 0; a < D; ++a) {
      lo[a] = std::max<Index>(c[a] - 1, 0);
      hi[a] = std::min<Index>(c[a] + 1, dims_[a] - 1);
      if (lo[a] > hi[a]) return;
      const Scalar margin = 1e-9 * (cell_ + std::abs(p[a]) + std::abs(origin_[a]));
      const Scalar below = std::max<Scalar>(p[a] - (origin_[a] + c[a] * cell_) - margin, 0);
      const Scalar above = std::max<Scalar>(origin_[a] + (c[a] + 1) * cell_ - p[a] - margin, 0);
      gap[a][0] = below * below;
      gap[a][1] = above * above;
    }
    const Scalar r2 = radius * radius;
    // Squared distance from p to the cells at offset i - c[a] on axis a.
    auto dist2 = [&](int a, Index i) { return i < c[a] ? gap[a][0] : i > c[a] ? gap[a][1] : Scalar(0); };
    if constexpr (D == 2) {
      for (Index i = lo[0]; i <= hi[0]; ++i) {
        const Scalar d0 = dist2(0, i);
        if (d0 >= r2) continue;
        // Cells of one row are contiguous: visit the run of those within reach at once.
        const Index first = lo[1] < c[1] && d0 + gap[1][0] >= r2 ? c[1] : lo[1];
        const Index last = hi[1] > c[1] && d0 + gap[1][1] >= r2 ? c[1] : hi[1];
        const Index row = i * dims_[1];
        for (Index k = cell_start_[row + first]; k < cell_start_[row + last + 1]; ++k) visit(sorted_[k]);
      }
    } else {
      for (Index i = lo[0]; i <= hi[0]; ++i)
        for (Index j = lo[1]; j <= hi[1]; ++j) {
          const Scalar d01 = dist2(0, i) + dist2(1, j);
          if (d01 >= r2) continue;
          const Index first = lo[2] < c[2] && d01 + gap[2][0] >= r2 ? c[2] : lo[2];
          const Index last = hi[2] > c[2] && d01 + gap[2][1] >= r2 ? c[2] : hi[2];
          const Index row = (i * dims_[1] + j) * dims_[2];
          for (Index k = cell_start_[row + first]; k < cell_start_[row + last + 1]; ++k) visit(sorted_[k]);
        }
    }
  }

 private:
  Vec origin_ = Vec::Zero();
  Scalar cell_ = 1, inv_cell_ = 1;
  Cell dims_{};
  std::vector<Index> cell_start_;   // CSR row pointer over cells, size cell_count + 1
  std::vector<Index> sorted_;       // point indices grouped by cell, in index order within a cell
  std::vector<Index> point_cell_;   // scratch: the cell of each point
};

// All pairs i < j of the n points with |x_i - x_j| < radius, sorted lexicographically, as a
// flat array [i0, j0, i1, j1, ...].
template <int D>
std::vector<Index> neighbor_pairs(const Scalar* x, Index n, Scalar radius);

// A permutation ordering the points along the Morton (Z-order) curve of cells of edge
// cell_size: order[k] is the index of the point that goes to position k. Neighbours in space
// become neighbours in memory, which is what makes the neighbour loops cache friendly.
template <int D>
std::vector<Index> morton_order(const Scalar* x, Index n, Scalar cell_size);

}  // namespace kinema
