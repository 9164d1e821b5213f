#include "particles/neighbor_grid.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <string>

#include "core/errors.h"
#include "core/parallel.h"
#include "particles/neighbor_lists.h"

namespace kinema {

namespace {

// A dense grid is kept below this many cells per point (plus a floor for tiny point sets):
// scattered points then still cost O(n) memory, at the price of coarser cells.
constexpr Index kCellsPerPoint = 8;
constexpr Index kMinCellBudget = 1 << 12;

}  // namespace

template <int D>
void NeighborGrid<D>::build(const Scalar* x, Index n, Scalar radius, int subdivision) {
  if (!(radius > 0) || !std::isfinite(radius) || !std::isfinite(1 / radius))
    throw InvalidArgument("radius: expected a finite number > 0 with a finite inverse, got " + format_real(radius));
  if (subdivision < 1 || subdivision > kMaxSubdivision)
    throw InvalidArgument("subdivision: expected 1 to " + std::to_string(kMaxSubdivision) + ", got " +
                          std::to_string(subdivision));
  if (n > std::numeric_limits<std::int32_t>::max())
    throw InvalidArgument("points: at most 2^31 - 1 points, got " + std::to_string(n));
  Vec lo = Vec::Constant(0), hi = Vec::Constant(0);
  if (n > 0) {
    lo = hi = Eigen::Map<const Vec>(x);
    for (Index i = 1; i < n; ++i) {
      const Eigen::Map<const Vec> p(x + i * D);
      lo = lo.cwiseMin(p);
      hi = hi.cwiseMax(p);
    }
    if (!lo.allFinite() || !hi.allFinite())
      throw InvalidArgument("points: coordinates must be finite");
    if (!(hi - lo).allFinite())
      throw InvalidArgument("points: the coordinates span more than the largest float64 (from " +
                            format_real(lo.minCoeff()) + " to " + format_real(hi.maxCoeff()) +
                            "); shift or scale them");
  }
  // Cell edge: radius / subdivision, enlarged until the bounding box needs at most `budget`
  // cells; the reach then shrinks to the cells the radius still spans.
  const Scalar budget = static_cast<Scalar>(std::max(kCellsPerPoint * n, kMinCellBudget));
  cell_ = radius / subdivision;
  reach_ = subdivision;
  for (;;) {
    Scalar cells = 1;
    for (int a = 0; a < D; ++a) cells *= std::floor((hi[a] - lo[a]) / cell_) + 1;
    // cell_ grows by at least 1.25 per pass; an infinite cell (a denormal radius over a wide
    // box) holds every point
    if (cells <= budget || !std::isfinite(cell_)) break;
    cell_ *= std::max<Scalar>(1.25, std::pow(cells / budget, 1.0 / D));
    reach_ = std::max<Index>(1, static_cast<Index>(std::ceil(radius / cell_)));
  }
  inv_cell_ = 1 / cell_;
  origin_ = lo;
  Index cells = 1;
  for (int a = 0; a < D; ++a) {
    dims_[a] = static_cast<Index>(std::floor((hi[a] - lo[a]) * inv_cell_)) + 1;
    cells *= dims_[a];
  }

  // Counting sort: cell of each point, histogram, prefix sum, stable scatter.
  point_cell_.resize(static_cast<size_t>(n));
  parallel_for(n, [&](Index i) {
    const Cell c = cell_of(Eigen::Map<const Vec>(x + i * D));
    Index flat = 0;
    for (int a = 0; a < D; ++a) flat = flat * dims_[a] + std::min(std::max<Index>(c[a], 0), dims_[a] - 1);
    point_cell_[static_cast<size_t>(i)] = flat;
  });
  cell_start_.assign(static_cast<size_t>(cells + 1), 0);
  for (Index i = 0; i < n; ++i) ++cell_start_[static_cast<size_t>(point_cell_[i] + 1)];
  for (Index c = 0; c < cells; ++c) cell_start_[c + 1] += cell_start_[c];
  count_ = n;
  sorted_.resize(static_cast<size_t>(n + kPadding));
  // Scatter through a moving cursor per cell; cell_start_ is restored afterwards.
  for (Index i = 0; i < n; ++i) sorted_[static_cast<size_t>(cell_start_[point_cell_[i]]++)] = static_cast<std::int32_t>(i);
  for (Index c = cells; c > 0; --c) cell_start_[c] = cell_start_[c - 1];
  cell_start_[0] = 0;

  // near_: the cells with a point within reach, the occupied cells dilated by reach_ cells along
  // each axis in turn (a separable maximum filter).
  near_.resize(static_cast<size_t>(cells));
  dilated_.resize(static_cast<size_t>(cells));
  for (Index c = 0; c < cells; ++c) near_[c] = cell_start_[c + 1] > cell_start_[c];
  Index stride = cells;
  for (int a = 0; a < D; ++a) {
    stride /= dims_[a];
    const Index span = stride * dims_[a];
    parallel_for(cells, [&](Index c) {
      const Index along = c % span / stride;
      std::uint8_t any = 0;
      for (Index o = std::max(-reach_, -along); o <= std::min(reach_, dims_[a] - 1 - along); ++o) any |= near_[c + o * stride];
      dilated_[c] = any;
    });
    near_.swap(dilated_);
  }

  // The coordinates in sorted order, one array per axis; the padding is never a candidate.
  std::fill_n(sorted_.begin() + n, kPadding, -1);
  stride_ = n + kPadding;
  coords_.resize(static_cast<size_t>(D * stride_));
  parallel_for(n, [&](Index k) {
    for (int a = 0; a < D; ++a) coords_[a * stride_ + k] = x[Index{sorted_[k]} * D + a];
  });
  for (int a = 0; a < D; ++a) std::fill_n(coords_.begin() + a * stride_ + n, kPadding, Scalar(0));
}

template <int D>
std::vector<Index> neighbor_pairs(const Scalar* x, Index n, Scalar radius) {
  NeighborGrid<D> grid;
  grid.build(x, n, radius);
  NeighborLists lists;
  lists.build<D>(grid, x, n, radius, true);
  // Each row sorted, its partners j > i kept: two passes (count, then fill at known offsets)
  // keep the output independent of the thread count.
  std::vector<Index> count(static_cast<size_t>(n) + 1, 0);
  parallel_for(n, [&](Index i) {
    std::sort(lists.list.begin() + lists.start[i], lists.list.begin() + lists.start[i + 1]);
    Index c = 0;
    for (Index k = lists.start[i]; k < lists.start[i + 1]; ++k) c += lists.list[k] > i;
    count[static_cast<size_t>(i) + 1] = c;
  });
  for (Index i = 0; i < n; ++i) count[i + 1] += count[i];
  std::vector<Index> pairs(static_cast<size_t>(2 * count[n]));
  parallel_for(n, [&](Index i) {
    Index* out = pairs.data() + 2 * count[i];
    for (Index k = lists.start[i + 1] - (count[i + 1] - count[i]); k < lists.start[i + 1]; ++k) {
      *out++ = i;
      *out++ = lists.list[k];
    }
  });
  return pairs;
}

namespace {

// Spreads the low bits of v so that D - 1 zero bits separate consecutive bits.
inline std::uint64_t spread_bits(std::uint64_t v, int D) {
  std::uint64_t out = 0;
  const int bits = 64 / D;
  for (int b = 0; b < bits; ++b) out |= ((v >> b) & 1u) << (b * D);
  return out;
}

}  // namespace

template <int D>
std::vector<Index> morton_order(const Scalar* x, Index n, Scalar cell_size) {
  using Vec = typename NeighborGrid<D>::Vec;
  std::vector<std::pair<std::uint64_t, Index>> keys(static_cast<size_t>(n));
  Vec lo = Vec::Zero();
  if (n > 0) {
    lo = Eigen::Map<const Vec>(x);
    for (Index i = 1; i < n; ++i) lo = lo.cwiseMin(Eigen::Map<const Vec>(x + i * D));
  }
  const std::uint64_t max_coord = (std::uint64_t{1} << (64 / D)) - 1;
  parallel_for(n, [&](Index i) {
    std::uint64_t key = 0;
    for (int a = 0; a < D; ++a) {
      const Scalar c = std::floor((x[i * D + a] - lo[a]) / cell_size);
      const std::uint64_t ci = c > 0 ? std::min<std::uint64_t>(static_cast<std::uint64_t>(std::min<Scalar>(c, 1e18)), max_coord) : 0;
      key |= spread_bits(ci, D) << a;
    }
    keys[static_cast<size_t>(i)] = {key, i};
  });
  std::sort(keys.begin(), keys.end());
  std::vector<Index> order(static_cast<size_t>(n));
  for (Index k = 0; k < n; ++k) order[k] = keys[k].second;
  return order;
}

template class NeighborGrid<2>;
template class NeighborGrid<3>;
template std::vector<Index> neighbor_pairs<2>(const Scalar*, Index, Scalar);
template std::vector<Index> neighbor_pairs<3>(const Scalar*, Index, Scalar);
template std::vector<Index> morton_order<2>(const Scalar*, Index, Scalar);
template std::vector<Index> morton_order<3>(const Scalar*, Index, Scalar);

}  // namespace kinema
