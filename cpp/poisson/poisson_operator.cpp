#include "poisson/poisson_operator.h"

#include <algorithm>
#include <array>
#include <cstdint>
#include <string>

#include "core/parallel.h"
#include "core/simd.h"
#include "poisson/poisson_rows.h"

namespace kinema {

PoissonOperator::PoissonOperator(const GridShape& shape, Scalar h, Boundary bc,
                                 const std::uint8_t* solid, Scalar shift, int dirichlet_walls)
    : shape_(shape), h_(h), inv_h2_(1 / (h * h)), shift_(shift),
      inv_plain_(1 / (shift + inv_h2_ * (shape.dim == 3 ? 6 : 4))), bc_(bc), avx2_(use_avx2()),
      stream_stores_(avx2_ && shape.size() * static_cast<Index>(sizeof(Scalar)) >= kStreamBytes) {
  int walls = bc == Boundary::Periodic ? 0 : dirichlet_walls >= 0 ? dirichlet_walls
                                                                   : (bc == Boundary::Dirichlet ? kAllWalls : 0);
  for (int axis = 0; axis < 3; ++axis)
    if (!shape.active(axis)) walls &= ~(3 << (2 * axis));
  dirichlet_ = static_cast<std::uint8_t>(walls);
  // The end cells of plain rows share one diagonal when both walls of the row's axis agree.
  ends_plain_ = bc != Boundary::Periodic && ((dirichlet_ >> 4) & 1) == ((dirichlet_ >> 5) & 1);
  if (!(h > 0)) throw InvalidArgument("h: expected a grid spacing > 0");
  if (!(shift >= 0)) throw InvalidArgument("shift: expected a diagonal shift >= 0");
  const Index n = shape_.size();
  const auto& s = shape_.n;
  mask_.assign(n, 0);
  diag_.assign(n, 0);
  parallel_for(n, [&](Index c) {
    if (!solid || !solid[c]) mask_[c] = kFluidBit;
  });
  fluid_count_ = static_cast<Index>(parallel_sum(n, [&](Index c) { return fluid(c) ? 1.0 : 0.0; }));

  // Couplings and diagonal counts, from each fluid cell's six faces (written to a copy, since
  // neighbours read the fluid bits concurrently).
  std::vector<std::uint8_t> mask = mask_;
  const bool periodic = bc_ == Boundary::Periodic;
  if (periodic) wrap_.assign(n, 0);
  parallel_for(shape_.rows(), [&](Index row) {
    const Index i = row / s[1], j = row % s[1];
    for (Index k = 0; k < s[2]; ++k) {
      const Index c = shape_.index(i, j, k);
      if (!fluid(c)) continue;
      const Index idx[3] = {i, j, k};
      std::uint8_t bits = kFluidBit, count = 0;
      for (int axis = 0; axis < 3; ++axis) {
        if (!shape_.active(axis)) continue;
        const Index stride = shape_.stride(axis);
        for (int side = 0; side < 2; ++side) {
          const bool inside = side == 0 ? idx[axis] > 0 : idx[axis] + 1 < s[axis];
          if (inside) {
            const Index nb = side == 0 ? c - stride : c + stride;
            if (mask_[nb] & kFluidBit) {
              bits |= static_cast<std::uint8_t>(1u << (2 * axis + side));
              ++count;
            }
          } else if ((dirichlet_ >> (2 * axis + side)) & 1) {
            count += 2;  // ghost value -u_c: (u_c - (-u_c)) / h^2
          } else if (periodic && s[axis] > 1) {
            const Index nb = side == 0 ? c + (s[axis] - 1) * stride : c - (s[axis] - 1) * stride;
            if (mask_[nb] & kFluidBit) {
              bits |= static_cast<std::uint8_t>(1u << (2 * axis + side));
              wrap_[c] |= static_cast<std::uint8_t>(1u << (2 * axis + side));
              ++count;
            }
          }
        }
      }
      mask[c] = bits;
      diag_[c] = count;
    }
  });
  mask_.swap(mask);

  // A row takes the plain stencil on its inner cells when it and its four (2D: two)
  // neighbouring rows are all fluid and inside the domain.
  const bool three_d = shape_.dim == 3;
  row_fast_.assign(shape_.rows(), 0);
  auto row_all_fluid = [&](Index i, Index j) {
    const Index base = shape_.index(i, j, 0);
    for (Index k = 0; k < s[2]; ++k)
      if (!(mask_[base + k] & kFluidBit)) return false;
    return true;
  };
  if (s[2] >= 3) {
    parallel_for(shape_.rows(), [&](Index row) {
      const Index i = row / s[1], j = row % s[1];
      if (j == 0 || j + 1 == s[1]) return;
      if (three_d && (i == 0 || i + 1 == s[0])) return;
      bool ok = row_all_fluid(i, j) && row_all_fluid(i, j - 1) && row_all_fluid(i, j + 1);
      if (ok && three_d) ok = row_all_fluid(i - 1, j) && row_all_fluid(i + 1, j);
      row_fast_[row] = ok;
    });
  }

  // The other rows whose inner cells all see the same stencil: fluid, coupled along the row,
  // with one set of couplings to the next rows and planes and one diagonal (the rows along the
  // domain's faces, most of all), and no periodic wrap. The AVX2 passes run them by vectors.
  row_dirs_.assign(shape_.rows(), kMixedRow);
  if (s[2] >= 3) {
    parallel_for(shape_.rows(), [&](Index row) {
      if (row_fast_[row]) return;
      const Index first = row * s[2] + 1, end = (row + 1) * s[2] - 1;
      const std::uint8_t m = mask_[first], count = diag_[first];
      if (!(m & kFluidBit) || (m & 0x30) != 0x30) return;
      for (Index c = first; c < end; ++c)
        if (mask_[c] != m || diag_[c] != count || (periodic && wrap_[c])) return;
      row_dirs_[row] = m & 0x0F;
    });
  }

  // Row flags: all fluid; clear of solids in the 3^d neighbourhood of every cell.
  row_clear_.assign(shape_.rows(), 0);
  row_fluid_.assign(shape_.rows(), 0);
  parallel_for(shape_.rows(), [&](Index row) {
    const Index i = row / s[1], j = row % s[1];
    bool all_fluid = true, clear = true;
    for (Index k = 0; k < s[2]; ++k) all_fluid = all_fluid && (mask_[row * s[2] + k] & kFluidBit);
    for (Index a = (three_d ? i - 1 : i); a <= (three_d ? i + 1 : i) && clear; ++a)
      for (Index b = j - 1; b <= j + 1 && clear; ++b) {
        if (a < 0 || a >= s[0] || b < 0 || b >= s[1]) continue;
        const Index base = shape_.index(a, b, 0);
        for (Index k = 0; k < s[2] && clear; ++k) clear = mask_[base + k] & kFluidBit;
      }
    row_fluid_[row] = all_fluid;
    row_clear_[row] = clear;
  });

  label_components();
}

// Connected components of the fluid cells through coupled faces; a component is singular when
// none of its cells has a Dirichlet face and there is no shift.
void PoissonOperator::label_components() {
  singular_components_.clear();
  component_.clear();
  component_size_.clear();
  if (shift_ > 0) return;
  const Index n = size();
  if (fluid_count_ == n) {
    // Without solids the fluid is one component, singular exactly without Dirichlet faces.
    if (dirichlet_ == 0 && n > 0) {
      component_.assign(n, 0);
      component_size_.push_back(n);
      singular_components_.push_back(0);
    }
    return;
  }
  component_.assign(n, -1);
  std::vector<Index> stack;
  std::int32_t next = 0;
  for (Index seed = 0; seed < n; ++seed) {
    if (!fluid(seed) || component_[seed] >= 0) continue;
    const std::int32_t id = next++;
    bool has_dirichlet = false;
    Index count = 0;
    component_[seed] = id;
    stack.push_back(seed);
    while (!stack.empty()) {
      const Index c = stack.back();
      stack.pop_back();
      ++count;
      const std::uint8_t m = mask_[c];
      int couplings = 0;
      for (int dir = 0; dir < kDirections; ++dir) {
        if (!(m & (1u << dir))) continue;
        ++couplings;
        const Index nb = neighbour(c, dir);
        if (component_[nb] < 0) {
          component_[nb] = id;
          stack.push_back(nb);
        }
      }
      if (diag_[c] != couplings) has_dirichlet = true;
    }
    component_size_.push_back(count);
    if (!has_dirichlet) singular_components_.push_back(id);
  }
  if (singular_components_.empty()) component_.clear();
}

std::vector<Index> PoissonOperator::singular_anchor_cells() const {
  std::vector<Index> anchors;
  if (!singular()) return anchors;
  std::vector<char> seen(component_size_.size(), 0);
  std::vector<char> is_singular(component_size_.size(), 0);
  for (auto id : singular_components_) is_singular[id] = 1;
  for (Index c = 0; c < size(); ++c) {
    const auto id = component_[c];
    if (id >= 0 && is_singular[id] && !seen[id]) {
      seen[id] = 1;
      anchors.push_back(c);
    }
  }
  return anchors;
}

void PoissonOperator::project(Scalar* x) const {
  const Index n = size();
  if (!singular()) {
    if (fluid_count_ < n) parallel_for(n, [&](Index c) { if (!fluid(c)) x[c] = 0; });
    return;
  }
  if (singular_components_.size() == 1 && component_size_.size() == 1) {
    // One component holding every fluid cell (pure Neumann): a parallel reproducible mean.
    const Scalar mean = parallel_sum(n, [&](Index c) { return fluid(c) ? x[c] : 0.0; }) /
                        static_cast<Scalar>(fluid_count_);
    parallel_for(n, [&](Index c) { x[c] = fluid(c) ? x[c] - mean : 0; });
    return;
  }
  std::vector<Scalar> sum(component_size_.size(), 0);
  for (Index c = 0; c < n; ++c)
    if (component_[c] >= 0) sum[component_[c]] += x[c];
  std::vector<Scalar> mean(component_size_.size(), 0);
  for (auto id : singular_components_) mean[id] = sum[id] / static_cast<Scalar>(component_size_[id]);
  parallel_for(n, [&](Index c) { x[c] = component_[c] >= 0 ? x[c] - mean[component_[c]] : 0; });
}

Scalar PoissonOperator::wrapped_neighbour_sum(const Scalar* x, Index c) const {
  Scalar sum = 0;
  for (int dir = 0; dir < kDirections; ++dir)
    if ((mask_[c] >> dir) & 1) sum += x[neighbour(c, dir)];
  return sum;
}

inline Scalar PoissonOperator::neighbour_sum(const Scalar* x, Index c) const {
  if (!wrap_.empty() && wrap_[c]) return wrapped_neighbour_sum(x, c);
  const std::uint8_t m = mask_[c];
  const Index s0 = shape_.stride(0), s1 = shape_.stride(1);
  Scalar sum = 0;
  if (m & 0x01) sum += x[c - s0];
  if (m & 0x02) sum += x[c + s0];
  if (m & 0x04) sum += x[c - s1];
  if (m & 0x08) sum += x[c + s1];
  if (m & 0x10) sum += x[c - 1];
  if (m & 0x20) sum += x[c + 1];
  return sum;
}

using poisson_rows::Avx2RowKernels;
using poisson_rows::avx2_row_kernels;
using poisson_rows::end_cell_update;
using poisson_rows::plain_row_body;
using poisson_rows::PlainRow;
using poisson_rows::RowEnds;

namespace {

// A whole plain row [base, base + n2): its end cells as `ends` says, the cells between take
// the plain stencil.
template <bool ThreeD, bool Residual>
void plain_row_baseline(const Scalar* x, Scalar* y, const Scalar* b, Index base, Index n2, Index s0,
                        Index s1, Scalar d, Scalar ih2, const RowEnds& ends) {
  y[base] = ends.value<ThreeD, Residual>(x, b, base, 1, s0, s1, ih2);
  plain_row_body<ThreeD, Residual>(x, y, b, base + 1, base + n2 - 1, s0, s1, d, ih2);
  y[base + n2 - 1] = ends.value<ThreeD, Residual>(x, b, base + n2 - 1, -1, s0, s1, ih2);
}

template <bool ThreeD>
PlainRow pick_plain_row(const Avx2RowKernels* avx2, bool residual, bool stream) {
  if (avx2) return ThreeD ? avx2->plain_row3[residual][stream] : avx2->plain_row2[residual];
  return residual ? plain_row_baseline<ThreeD, true> : plain_row_baseline<ThreeD, false>;
}

}  // namespace

// y = A x, or y = b - A x when b is given. Rows flagged fast run the plain (2d+1)-point
// stencil on their inner cells (vectorised, AVX2 where the CPU has it); every other cell reads
// its mask.
template <bool ThreeD>
void PoissonOperator::apply_impl(const Scalar* x, Scalar* y, const Scalar* b) const {
  const Index n2 = shape_.n[2], s0 = shape_.stride(0), s1 = shape_.stride(1);
  const Scalar ih2 = inv_h2_;
  const Scalar d_plain = shift_ + ih2 * (ThreeD ? 6 : 4);
  const Scalar d_end = end_diagonal<ThreeD>();
  const Avx2RowKernels* avx2 = avx2_ ? avx2_row_kernels() : nullptr;
  const PlainRow plain_row = pick_plain_row<ThreeD>(avx2, b != nullptr, stream_stores_);
  auto masked = [&](Index c) -> Scalar {
    if (!fluid(c)) return 0;
    return diagonal(c) * x[c] - ih2 * neighbour_sum(x, c);
  };
  auto row_kernel = [&](Index row) {
    const Index base = row * n2;
    if (row_fast_[row]) {
      RowEnds ends;
      ends.plain = ends_plain_;
      ends.d_end = d_end;
      if (!ends_plain_) {
        const Index last = base + n2 - 1;
        const Scalar first_ax = masked(base), last_ax = masked(last);
        ends.y_first = b ? b[base] - first_ax : first_ax;
        ends.y_last = b ? b[last] - last_ax : last_ax;
      }
      plain_row(x, y, b, base, n2, s0, s1, d_plain, ih2, ends);
    } else {
      auto masked_cells = [&](Index from, Index to) {
        for (Index c = from; c < to; ++c) {
          const Scalar ax = masked(c);
          y[c] = b ? (fluid(c) ? b[c] - ax : 0) : ax;
        }
      };
      Index c = base;
      if (avx2 && row_dirs_[row] != kMixedRow) {
        masked_cells(base, base + 1);
        const Scalar d = diagonal(base + 1);
        c = avx2->off_row_apply[b != nullptr](x, y, b, base, n2, row_dirs_[row], s0, s1, d, ih2);
      }
      masked_cells(c, base + n2);
    }
  };
#pragma omp parallel if (parallel())
  {
#pragma omp for schedule(static) nowait
    for (Index row = 0; row < shape_.rows(); ++row) row_kernel(row);
    // Each thread orders its own non-temporal stores before the team's closing barrier, after
    // which y is read: one fence per pass, where there was one per row.
    if (stream_stores_ && avx2) avx2->stream_fence();
  }
}

void PoissonOperator::apply(const Scalar* x, Scalar* y) const {
  if (shape_.dim == 3) apply_impl<true>(x, y, nullptr);
  else apply_impl<false>(x, y, nullptr);
}

void PoissonOperator::residual(const Scalar* b, const Scalar* x, Scalar* r) const {
  if (shape_.dim == 3) apply_impl<true>(x, r, b);
  else apply_impl<false>(x, r, b);
}

// Gauss-Seidel on the cells of one colour in one row: x_c = (b_c + sum_nb x_nb / h^2) / diag_c.
// Cells of one colour only couple to the other colour, so every update of a colour reads the
// same values whatever the order: the sweeps below are parallel and thread-count independent.
// k0 is the first k of the colour in the row, (i + j + colour) % 2, from the caller: an integer
// division here, and the division for inv_plain_, sat on every row's critical path.
template <bool ThreeD>
void PoissonOperator::smooth_row(const Scalar* b, Scalar* x, Index row, Index k0) const {
  const Index n2 = shape_.n[2], s0 = shape_.stride(0), s1 = shape_.stride(1);
  const Scalar ih2 = inv_h2_;
  const Index base = row * n2;
  auto masked = [&](Index c) {
    if (!fluid(c)) return;
    const Scalar d = diagonal(c);
    x[c] = d > 0 ? (b[c] + ih2 * neighbour_sum(x, c)) / d : 0;
  };
  const Avx2RowKernels* avx2 = avx2_ ? avx2_row_kernels() : nullptr;
  if (!row_fast_[row]) {
    Index k = k0;
    if (avx2 && row_dirs_[row] != kMixedRow) {
      if (k0 == 0) masked(base);
      k = avx2->off_row_colour(b, x, base, n2, k0, row_dirs_[row], s0, s1, diagonal(base + 1), ih2);
      k += (k & 1) != k0;
    }
    for (; k < n2; k += 2) masked(base + k);
    return;
  }
  const Scalar inv_plain = inv_plain_;
  const Scalar d_end = end_diagonal<ThreeD>();
  auto end_cell = [&](Index c, Index inward) {
    if (!ends_plain_) return masked(c);
    end_cell_update<ThreeD>(b, x, c, inward, s0, s1, ih2, d_end);
  };
  if (avx2 && ends_plain_ && n2 % 4 == 0 && n2 >= 8) {
    avx2->colour_row_whole[ThreeD](b, x, base, n2, k0, s0, s1, ih2, inv_plain, d_end);
    return;
  }
  if (k0 == 0) end_cell(base, 1);
  if (avx2) {
    avx2->colour_row[ThreeD](b, x, base, n2, k0, s0, s1, ih2, inv_plain);
  } else {
    const Index first = k0 == 0 ? 2 : 1;
#pragma omp simd
    for (Index k = first; k < n2 - 1; k += 2) {
      const Index c = base + k;
      Scalar nb = x[c - s1] + x[c + s1] + x[c - 1] + x[c + 1];
      if (ThreeD) nb += x[c - s0] + x[c + s0];
      x[c] = (b[c] + ih2 * nb) * inv_plain;
    }
  }
  if (((n2 - 1) & 1) == k0) end_cell(base + n2 - 1, -1);
}

// The first colour on row `row` (plane p) and the second on the row below it (plane p - 1):
// fused when both rows are plain (colour_row_pair_avx2), else the two row updates in turn.
// Both rows' cells of their colour start at the same k0.
template <bool ThreeD>
void PoissonOperator::smooth_row_pair(const Scalar* b, Scalar* x, Index row, Index k0) const {
  const Index below = row - shape_.n[1];
  const Avx2RowKernels* avx2 = avx2_ ? avx2_row_kernels() : nullptr;
  if (ThreeD && avx2 && ends_plain_ && row_fast_[row] && row_fast_[below]) {
    const Index n2 = shape_.n[2], s0 = shape_.stride(0), s1 = shape_.stride(1);
    const Scalar ih2 = inv_h2_, inv_plain = inv_plain_, d_end = end_diagonal<ThreeD>();
    const Index base = row * n2;
    auto end_cells = [&](Index k, Index inward) {
      for (Index c : {base + k, base + k - s0}) end_cell_update<ThreeD>(b, x, c, inward, s0, s1, ih2, d_end);
    };
    if (n2 % 4 == 0 && n2 >= 8) {
      avx2->colour_row_pair_whole(b, x, base, n2, k0, s0, s1, ih2, inv_plain, d_end);
      return;
    }
    if (k0 == 0) end_cells(0, 1);
    avx2->colour_row_pair(b, x, base, n2, k0, s0, s1, ih2, inv_plain);
    if (((n2 - 1) & 1) == k0) end_cells(n2 - 1, -1);
    return;
  }
  smooth_row<ThreeD>(b, x, row, k0);
  smooth_row<ThreeD>(b, x, below, k0);
}

// Both colours in one pass over memory: slabs (planes i in 3D, rows j in 2D) are swept in
// order, the second colour trailing one slab behind the first, whose neighbours are then final.
// Each thread takes a contiguous block of slabs; the second colour on a block's first and last
// slab waits for the neighbouring blocks behind a barrier.
template <bool ThreeD>
void PoissonOperator::sweep_impl(const Scalar* b, Scalar* x, int first_color) const {
  const int second_color = 1 - first_color;
  const Index slabs = ThreeD ? shape_.n[0] : shape_.n[1];
  const Index rows_per_slab = ThreeD ? shape_.n[1] : 1;
  // Row j of slab p is row p * rows_per_slab + j, (i, j) = (p, j) in 3D and (0, p) in 2D: its
  // cells of a colour start at k0 = (p + j + colour) % 2.
  auto slab = [&](Index p, int color) {
    for (Index j = 0; j < rows_per_slab; ++j) smooth_row<ThreeD>(b, x, p * rows_per_slab + j, (p + j + color) & 1);
  };
#pragma omp parallel if (parallel())
  {
    const Index team = omp_get_num_threads(), t = omp_get_thread_num();
    const Index lo = slabs * t / team, hi = slabs * (t + 1) / team;
    for (Index p = lo; p < hi; ++p) {
      if (ThreeD && p - 1 > lo) {
        // Row by row, the first colour on row j of plane p, then the second on row j of plane
        // p - 1: the latter reads the first colour at (p, j), just done, and at (p - 2, j),
        // (p - 1, j +- 1) and along its row, all final since the previous plane; the first
        // colour on later rows of plane p reads the second only at (p - 1, j' > j), still old.
        for (Index j = 0; j < rows_per_slab; ++j)
          smooth_row_pair<ThreeD>(b, x, p * rows_per_slab + j, (p + j + first_color) & 1);
        continue;
      }
      slab(p, first_color);
      if (p - 1 > lo) slab(p - 1, second_color);
    }
#pragma omp barrier
    if (hi > lo) slab(lo, second_color);
    if (hi - 1 > lo) slab(hi - 1, second_color);
  }
}

void PoissonOperator::sweep(const Scalar* b, Scalar* x, int first_color) const {
  if (shape_.dim == 3) sweep_impl<true>(b, x, first_color);
  else sweep_impl<false>(b, x, first_color);
}

void PoissonOperator::jacobi(const Scalar* b, const Scalar* x, Scalar* x_new, Scalar omega) const {
  residual(b, x, x_new);
  parallel_for(size(), [&](Index c) {
    const Scalar d = fluid(c) ? diagonal(c) : 0;
    x_new[c] = d > 0 ? x[c] + omega * x_new[c] / d : 0;
  });
}

CsrArrays PoissonOperator::assemble() const {
  const Index n = size();
  CsrArrays A;
  A.rows = n;
  A.row_ptr.assign(n + 1, 0);
  for (Index c = 0; c < n; ++c) {
    Index count = 0;
    if (fluid(c)) {
      count = 1;
      for (int dir = 0; dir < kDirections; ++dir) count += (mask_[c] >> dir) & 1;
    }
    A.row_ptr[c + 1] = A.row_ptr[c] + count;
  }
  A.col_index.resize(A.row_ptr[n]);
  A.values.resize(A.row_ptr[n]);
  // Columns in increasing order (a periodic wrap puts a neighbour at the other end of the row).
  parallel_for(n, [&](Index c) {
    if (!fluid(c)) return;
    std::array<std::pair<Index, Scalar>, kDirections + 1> entries;
    int count = 0;
    entries[count++] = {c, diagonal(c)};
    const std::uint8_t m = mask_[c];
    for (int dir = 0; dir < kDirections; ++dir)
      if (m & (1u << dir)) entries[count++] = {neighbour(c, dir), -inv_h2_};
    std::sort(entries.begin(), entries.begin() + count,
              [](const auto& a, const auto& b) { return a.first < b.first; });
    Index p = A.row_ptr[c];
    for (int e = 0; e < count; ++e, ++p) {
      A.col_index[p] = entries[e].first;
      A.values[p] = entries[e].second;
    }
  });
  return A;
}

PoissonOperator PoissonOperator::coarsened() const {
  GridShape coarse = shape_;
  for (int axis = 0; axis < 3; ++axis)
    if (shape_.active(axis)) coarse.n[axis] = (shape_.n[axis] + 1) / 2;
  std::vector<std::uint8_t> solid(coarse.size(), 1);
  const auto& s = shape_.n;
  // A coarse cell is fluid when any child is (children 2I and 2I+1 per active axis).
  parallel_for(coarse.rows(), [&](Index row) {
    const Index I = row / coarse.n[1], J = row % coarse.n[1];
    const Index i0 = shape_.active(0) ? 2 * I : I;
    const Index i1 = shape_.active(0) ? std::min(2 * I + 1, s[0] - 1) : I;
    for (Index K = 0; K < coarse.n[2]; ++K) {
      bool any = false;
      for (Index i = i0; i <= i1; ++i)
        for (Index j = 2 * J; j <= std::min(2 * J + 1, s[1] - 1); ++j)
          for (Index k = 2 * K; k <= std::min(2 * K + 1, s[2] - 1); ++k)
            any = any || fluid(shape_.index(i, j, k));
      solid[coarse.index(I, J, K)] = !any;
    }
  });
  return PoissonOperator(coarse, 2 * h_, bc_, solid.data(), shift_, dirichlet_);
}

}  // namespace kinema
