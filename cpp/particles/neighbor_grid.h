// Fixed-radius neighbour search on a uniform cell grid stored as flat CSR arrays: points are
// binned by counting sort (cell_start[c] .. cell_start[c+1] index `sorted`), so a rebuild
// allocates nothing once the buffers have grown, and a query visits the cells within reach of
// a point (3^d at the default cell edge = radius). This is the compact, allocation-free grid of
// Ihmsen et al. 2011 ("A parallel SPH implementation on multi-core CPUs") without the hash:
// the grid covers the points' bounding box densely and its cell size grows when that box would
// need too many cells. The grid keeps a copy of the coordinates in cell order, so a query
// streams each line of cells as one contiguous run instead of gathering point by point.
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
  // A run [begin, end) of positions in the grid's sorted order (see sorted()).
  struct Span {
    Index begin, end;
  };
  static constexpr int kMaxSubdivision = 3;
  // Most spans a query yields: one per line of cells along the last axis.
  static constexpr int kMaxSpans = D == 2 ? 2 * kMaxSubdivision + 1 : (2 * kMaxSubdivision + 1) * (2 * kMaxSubdivision + 1);

  // Bins the n points x (n rows of D coordinates) into cells of edge >= radius / subdivision
  // (radius > 0, subdivision 1 .. kMaxSubdivision): a query of radius <= `radius` then visits
  // the (2 subdivision + 1)^D cells around a point, less those beyond the radius. Finer cells
  // offer fewer candidates outside the radius at the price of more, shorter runs. Throws
  // InvalidArgument for non-finite coordinates or more than 2^31 - 1 points.
  void build(const Scalar* x, Index n, Scalar radius, int subdivision = 1);

  Index point_count() const { return count_; }
  Index cell_count() const { return static_cast<Index>(cell_start_.size()) - 1; }
  Scalar cell_size() const { return cell_; }
  // Cells a query reaches on each side of its own.
  Index reach() const { return reach_; }

  // sorted()[k] is the index of the point at sorted position k: points grouped by cell (cells
  // in row-major order, the last axis fastest), in index order within a cell (readable up to
  // kPadding entries past point_count()).
  const std::int32_t* sorted() const { return sorted_.data(); }
  // The coordinates on axis a of the points in sorted order (structure of arrays; readable up
  // to kPadding entries past point_count()).
  const Scalar* sorted_coordinates(int a) const { return coords_.data() + a * stride_; }
  static constexpr Index kPadding = 4;

  // Integer cell coordinates of p (may lie outside [0, dims) for points outside the grid).
  Cell cell_of(const Vec& p) const {
    Cell c;
    for (int a = 0; a < D; ++a) {
      // Clamped before the cast: a far-away point must not overflow the integer. The floor of
      // the clamped value by truncation (std::floor is a library call on baseline x86-64).
      const Scalar f = std::min<Scalar>(std::max<Scalar>((p[a] - origin_[a]) * inv_cell_, -2),
                                        static_cast<Scalar>(dims_[a] + 1));
      const Index t = static_cast<Index>(f);
      c[a] = t - (f < static_cast<Scalar>(t));
    }
    return c;
  }

  // Writes to `spans` the runs of sorted positions of the non-empty lines of cells around p
  // that come within `radius` (at most the build radius) of p and returns their count (at most
  // kMaxSpans): a superset of the points within radius, in cell order (deterministic). Along
  // the last axis a line is trimmed to the cells within reach, which are contiguous.
  int spans(const Vec& p, Scalar radius, Span* spans) const { return spans_of_box(cell_of(p), p, p, radius, spans); }

  // The same for all points of the box [lo, hi] inside cell c (= cell_of of its points): the
  // runs of the cells that come within radius of some point of the box.
  int spans_of_box(const Cell& c, const Vec& box_lo, const Vec& box_hi, Scalar radius, Span* spans) const {
    if (count_ == 0) return 0;
    // Most queries far from all points (a fluid particle away from the walls) stop here.
    bool inside = true;
    Index flat = 0;
    for (int a = 0; a < D; ++a) {
      inside = inside && c[a] >= 0 && c[a] < dims_[a];
      flat = flat * dims_[a] + c[a];
    }
    if (inside && !near_[static_cast<size_t>(flat)]) return 0;
    const Index R = reach_;
    Index lo[D], hi[D];
    // gap[a][R + o]: squared distance from the box to the cells at offset o on axis a, less a
    // margin for the rounding of the binning.
    Scalar gap[D][2 * kMaxSubdivision + 1];
    for (int a = 0; a < D; ++a) {
      lo[a] = std::max<Index>(c[a] - R, 0);
      hi[a] = std::min<Index>(c[a] + R, dims_[a] - 1);
      if (lo[a] > hi[a]) return 0;
      const Scalar margin = 1e-9 * (cell_ + std::max(std::abs(box_lo[a]), std::abs(box_hi[a])) + std::abs(origin_[a]));
      gap[a][R] = 0;
      for (Index o = 1; o <= R; ++o) {
        const Scalar below = std::max<Scalar>(box_lo[a] - (origin_[a] + (c[a] - o + 1) * cell_) - margin, 0);
        const Scalar above = std::max<Scalar>(origin_[a] + (c[a] + o) * cell_ - box_hi[a] - margin, 0);
        gap[a][R - o] = below * below;
        gap[a][R + o] = above * above;
      }
    }
    const Scalar r2 = radius * radius;
    auto dist2 = [&](int a, Index i) { return gap[a][i - c[a] + R]; };
    int count = 0;
    // The line of cells `row` + [first, last] along the last axis, trimmed to those within
    // reach given the squared distance d across the other axes.
    auto line = [&](Index row, Scalar d) {
      constexpr int L = D - 1;
      Index first = lo[L], last = hi[L];
      while (first < c[L] && first <= last && d + dist2(L, first) >= r2) ++first;
      while (last > c[L] && last >= first && d + dist2(L, last) >= r2) --last;
      if (first > last) return;
      const Index begin = cell_start_[row + first], end = cell_start_[row + last + 1];
      if (begin < end) spans[count++] = Span{begin, end};
    };
    if constexpr (D == 2) {
      for (Index i = lo[0]; i <= hi[0]; ++i)
        if (dist2(0, i) < r2) line(i * dims_[1], dist2(0, i));
    } else {
      for (Index i = lo[0]; i <= hi[0]; ++i) {
        if (dist2(0, i) >= r2) continue;
        for (Index j = lo[1]; j <= hi[1]; ++j) {
          const Scalar d01 = dist2(0, i) + dist2(1, j);
          if (d01 < r2) line((i * dims_[1] + j) * dims_[2], d01);
        }
      }
    }
    return count;
  }

  // Calls visit(j) for every binned point j of spans(p, radius), in order; without a radius,
  // for the whole block of cells within reach (a superset of the points within the build
  // radius of p).
  template <class Visit>
  void for_each_candidate(const Vec& p, Visit&& visit) const {
    for_each_candidate(p, std::numeric_limits<Scalar>::infinity(), visit);
  }
  template <class Visit>
  void for_each_candidate(const Vec& p, Scalar radius, Visit&& visit) const {
    Span runs[kMaxSpans];
    const int count = spans(p, radius, runs);
    for (int s = 0; s < count; ++s)
      for (Index k = runs[s].begin; k < runs[s].end; ++k) visit(Index{sorted_[k]});
  }

 private:
  Vec origin_ = Vec::Zero();
  Scalar cell_ = 1, inv_cell_ = 1;
  Index reach_ = 1;
  Cell dims_{};
  Index count_ = 0;                  // points binned
  Index stride_ = 0;                 // coords_ holds axis a at [a stride_, a stride_ + n)
  std::vector<Index> cell_start_;    // CSR row pointer over cells, size cell_count + 1
  std::vector<std::int32_t> sorted_; // point indices grouped by cell, in index order within a cell
  std::vector<Scalar> coords_;       // the points' coordinates in sorted order, per axis
  std::vector<std::uint8_t> near_;   // per cell: 1 if a point lies in a cell within reach
  std::vector<std::uint8_t> dilated_;  // scratch of near_
  std::vector<Index> point_cell_;    // scratch: the cell of each point
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
