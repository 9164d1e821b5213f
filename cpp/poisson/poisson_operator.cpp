#include "poisson/poisson_operator.h"

#include <algorithm>
#include <array>
#include <cstdint>
#include <string>

#include "core/parallel.h"
#include "core/simd.h"

#if KINEMA_HAVE_AVX2_CLONES
#include <immintrin.h>
#endif

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

// The neighbour sum of an end cell (k = 0 or n2 - 1) of a plain row on a grid without periodic
// wrap, from the row's geometry rather than its mask: such a cell couples to its four
// neighbours in the next rows and planes and to the one cell along the row (`inward`), as
// row_fast_ guarantees, so neither the mask nor the diagonal count needs to be read (for the
// 3D passes they would be two more streams from memory, one byte used per row). The terms are
// added in neighbour_sum's order, so the result is bitwise the same.
template <bool ThreeD>
KINEMA_ALWAYS_INLINE Scalar end_cell_sum(const Scalar* x, Index c, Index inward, Index s0, Index s1) {
  Scalar sum = 0;
  if (ThreeD) {
    sum += x[c - s0];
    sum += x[c + s0];
  }
  sum += x[c - s1];
  sum += x[c + s1];
  sum += x[c + inward];
  return sum;
}

// The Gauss-Seidel update of such an end cell, with its diagonal d_end (end_diagonal).
template <bool ThreeD>
KINEMA_ALWAYS_INLINE void end_cell_update(const Scalar* b, Scalar* x, Index c, Index inward, Index s0,
                                          Index s1, Scalar ih2, Scalar d_end) {
  x[c] = (b[c] + ih2 * end_cell_sum<ThreeD>(x, c, inward, s0, s1)) / d_end;
}

namespace {

// The plain (2d+1)-point stencil on cells [begin, end) of a row: y = A x, or y = b - A x.
template <bool ThreeD, bool Residual>
KINEMA_ALWAYS_INLINE void plain_row_body(const Scalar* x, Scalar* y, const Scalar* b, Index begin,
                                         Index end, Index s0, Index s1, Scalar d, Scalar ih2) {
#pragma omp simd
  for (Index c = begin; c < end; ++c) {
    Scalar nb = x[c - s1] + x[c + s1] + x[c - 1] + x[c + 1];
    if (ThreeD) nb += x[c - s0] + x[c + s0];
    const Scalar ax = d * x[c] - ih2 * nb;
    y[c] = Residual ? b[c] - ax : ax;
  }
}

// The results of the two end cells of a plain row (k = 0 and n2 - 1), which see the domain
// face or the periodic wrap. With plain ends (no wrap) the row computes them from its geometry
// (end_cell_sum, diagonal d_end), once it has reached them; otherwise the caller has computed
// them through the mask, y_first and y_last.
struct RowEnds {
  bool plain = false;
  Scalar d_end = 0;
  Scalar y_first = 0, y_last = 0;

  // The end cell c, whose one neighbour along the row is at c + inward.
  template <bool ThreeD, bool Residual>
  KINEMA_ALWAYS_INLINE Scalar value(const Scalar* x, const Scalar* b, Index c, Index inward, Index s0,
                                    Index s1, Scalar ih2) const {
    if (!plain) return inward > 0 ? y_first : y_last;
    const Scalar ax = d_end * x[c] - ih2 * end_cell_sum<ThreeD>(x, c, inward, s0, s1);
    return Residual ? b[c] - ax : ax;
  }
};

// A whole plain row [base, base + n2): its end cells as `ends` says, the cells between take
// the plain stencil.
template <bool ThreeD, bool Residual>
void plain_row_baseline(const Scalar* x, Scalar* y, const Scalar* b, Index base, Index n2, Index s0,
                        Index s1, Scalar d, Scalar ih2, const RowEnds& ends) {
  y[base] = ends.value<ThreeD, Residual>(x, b, base, 1, s0, s1, ih2);
  plain_row_body<ThreeD, Residual>(x, y, b, base + 1, base + n2 - 1, s0, s1, d, ih2);
  y[base + n2 - 1] = ends.value<ThreeD, Residual>(x, b, base + n2 - 1, -1, s0, s1, ih2);
}

#if KINEMA_HAVE_AVX2_CLONES
// Cells ahead of the current one that the 3D rows prefetch: the next plane, read there for the
// first time, is what they wait on; the hardware prefetcher alone keeps too few lines in flight
// for a core to reach the memory bandwidth. 64 cells (512 B) was the best of 16 to 256 in
// bench_grid on 128^3 and 256^3 (bench/RESULTS.md). Through an integer, so that no pointer is
// formed past the end of an array.
constexpr Index kPrefetchAhead = 64;

KINEMA_ALWAYS_INLINE void prefetch_ahead(const Scalar* p, bool for_write = false) {
  const auto address = reinterpret_cast<std::uintptr_t>(p) + kPrefetchAhead * sizeof(Scalar);
  if (for_write) __builtin_prefetch(reinterpret_cast<const void*>(address), 1, 3);
  else __builtin_prefetch(reinterpret_cast<const void*>(address), 0, 3);
}

// Orders the calling thread's non-temporal stores before its later stores.
inline void stream_fence() { _mm_sfence(); }

// The prefetches of a 3D row at cell c, once per 64-byte line: the next plane, b for the
// residual, and y when it is written through the cache. A function, not a lambda: GCC judged
// a lambda holding only prefetches free of side effects and dropped its calls (the assembly
// showed no prefetch at all).
template <bool Residual>
KINEMA_ALWAYS_INLINE void prefetch_row3(const Scalar* x, const Scalar* b, const Scalar* y, Index c, Index s0,
                                        bool write_y) {
  if ((c & 7) < 4) {
    prefetch_ahead(x + c + s0);
    if (Residual) prefetch_ahead(b + c);
    if (write_y) prefetch_ahead(y + c, true);
  }
}

// The plain stencil's result on the four cells from c (plain_row_body's operations and order).
template <bool Residual>
KINEMA_TARGET_AVX2 KINEMA_ALWAYS_INLINE __m256d plain_vector3(const Scalar* x, const Scalar* b, Index c,
                                                              Index s0, Index s1, __m256d vd, __m256d vih2) {
  __m256d nb = _mm256_add_pd(_mm256_add_pd(_mm256_add_pd(_mm256_loadu_pd(x + c - s1),
                                                         _mm256_loadu_pd(x + c + s1)),
                                           _mm256_loadu_pd(x + c - 1)),
                             _mm256_loadu_pd(x + c + 1));
  nb = _mm256_add_pd(nb, _mm256_add_pd(_mm256_loadu_pd(x + c - s0), _mm256_loadu_pd(x + c + s0)));
  const __m256d ax = _mm256_sub_pd(_mm256_mul_pd(vd, _mm256_loadu_pd(x + c)), _mm256_mul_pd(vih2, nb));
  return Residual ? _mm256_sub_pd(_mm256_loadu_pd(b + c), ax) : ax;
}

// The four cells from c computed as end cells of a plain row (end_cell_sum, with diagonal
// d_end and the one neighbour along the row at `inward`): the lane of the row's actual end cell
// is kept, the others are discarded. The loads are plain_vector3's, so they come from cache.
template <bool Residual>
KINEMA_TARGET_AVX2 KINEMA_ALWAYS_INLINE __m256d end_vector3(const Scalar* x, const Scalar* b, Index c,
                                                            Index inward, Index s0, Index s1, __m256d vd_end,
                                                            __m256d vih2) {
  __m256d sum = _mm256_add_pd(_mm256_setzero_pd(), _mm256_loadu_pd(x + c - s0));
  sum = _mm256_add_pd(sum, _mm256_loadu_pd(x + c + s0));
  sum = _mm256_add_pd(sum, _mm256_loadu_pd(x + c - s1));
  sum = _mm256_add_pd(sum, _mm256_loadu_pd(x + c + s1));
  sum = _mm256_add_pd(sum, _mm256_loadu_pd(x + c + inward));
  const __m256d ax = _mm256_sub_pd(_mm256_mul_pd(vd_end, _mm256_loadu_pd(x + c)), _mm256_mul_pd(vih2, sum));
  return Residual ? _mm256_sub_pd(_mm256_loadu_pd(b + c), ax) : ax;
}

// A 3D plain row with AVX2: the operations of plain_row_body in the same order (no FMA), so the
// results are bitwise those of the baseline. The 3D stencil makes seven loads per cell: with
// SSE2's two lanes it is bound by the load ports rather than by memory, with AVX2's four it is
// not. When the row is a whole number of vectors, the end cells are blended into the first and
// last vector, so that the row is written by whole vectors only; with plain ends they are
// computed there too, from the same loads (end_vector3). Computed ahead of the row, the last
// end cell's load from the next plane missed in every cache and stalled the core once per row.
// With Stream the vectors are non-temporal stores that bypass the cache: no read of y's old
// contents, a third less memory traffic, for grids too large for y to be read back from cache
// anyway (kStreamBytes); a row that is not 32-byte aligned is written through the cache.
template <bool Residual, bool Stream>
KINEMA_TARGET_AVX2 void plain_row3_avx2(const Scalar* x, Scalar* y, const Scalar* b, Index base,
                                        Index n2, Index s0, Index s1, Scalar d, Scalar ih2,
                                        const RowEnds& ends) {
  const __m256d vd = _mm256_set1_pd(d), vih2 = _mm256_set1_pd(ih2);
  const Index end = base + n2;
  if (n2 % 4 == 0 && n2 >= 8) {
    const bool stream = Stream && (reinterpret_cast<std::uintptr_t>(y + base) & 31) == 0;
    const __m256d vd_end = _mm256_set1_pd(ends.d_end);
    auto put = [&](Index c, __m256d v) KINEMA_TARGET_AVX2 {
      if (stream) _mm256_stream_pd(y + c, v);
      else _mm256_storeu_pd(y + c, v);
    };
    // The first and last vector, with the end cells blended in, outside the loop.
    const __m256d first = ends.plain ? end_vector3<Residual>(x, b, base, 1, s0, s1, vd_end, vih2)
                                     : _mm256_set1_pd(ends.y_first);
    put(base, _mm256_blend_pd(plain_vector3<Residual>(x, b, base, s0, s1, vd, vih2), first, 0b0001));
    if (stream) {
      for (Index c = base + 4; c < end - 4; c += 4) {
        prefetch_row3<Residual>(x, b, y, c, s0, false);
        _mm256_stream_pd(y + c, plain_vector3<Residual>(x, b, c, s0, s1, vd, vih2));
      }
    } else {
      for (Index c = base + 4; c < end - 4; c += 4) {
        prefetch_row3<Residual>(x, b, y, c, s0, true);
        _mm256_storeu_pd(y + c, plain_vector3<Residual>(x, b, c, s0, s1, vd, vih2));
      }
    }
    const Index c = end - 4;
    const __m256d last = ends.plain ? end_vector3<Residual>(x, b, c, -1, s0, s1, vd_end, vih2)
                                    : _mm256_set1_pd(ends.y_last);
    put(c, _mm256_blend_pd(plain_vector3<Residual>(x, b, c, s0, s1, vd, vih2), last, 0b1000));
    return;  // a non-temporal store is ordered by the caller's stream_fence
  }
  y[base] = ends.value<true, Residual>(x, b, base, 1, s0, s1, ih2);
  Index c = base + 1;
  for (; c + 4 <= end - 1; c += 4) {
    prefetch_row3<Residual>(x, b, y, c, s0, true);
    _mm256_storeu_pd(y + c, plain_vector3<Residual>(x, b, c, s0, s1, vd, vih2));
  }
  plain_row_body<true, Residual>(x, y, b, c, end - 1, s0, s1, d, ih2);
  y[end - 1] = ends.value<true, Residual>(x, b, end - 1, -1, s0, s1, ih2);
}

// The couplings of a row whose inner cells share one stencil (row_dirs_) to the rows and
// planes next to it, in neighbour_sum's order (-s0, +s0, -s1, +s1): the offset of each, 0 where
// the row has no such coupling, and a lane mask set there. An absent term is added as -0.0,
// which leaves every sum bitwise as it is (x + -0.0 == x, also for x = +-0), so the vector sum
// is bitwise neighbour_sum's, and no load leaves the grid.
struct OffRowTerms {
  Index offset[4];
  __m256d absent[4];
};

KINEMA_TARGET_AVX2 KINEMA_ALWAYS_INLINE OffRowTerms off_row_terms(std::uint8_t dirs, Index s0, Index s1) {
  const Index strides[4] = {-s0, s0, -s1, s1};
  OffRowTerms t;
  for (int q = 0; q < 4; ++q) {
    const bool present = (dirs >> q) & 1;
    t.offset[q] = present ? strides[q] : 0;
    t.absent[q] = _mm256_castsi256_pd(_mm256_set1_epi64x(present ? 0 : -1));
  }
  return t;
}

// neighbour_sum on the four cells from c of such a row.
KINEMA_TARGET_AVX2 KINEMA_ALWAYS_INLINE __m256d off_row_sum(const Scalar* x, Index c, const OffRowTerms& t) {
  const __m256d neg_zero = _mm256_set1_pd(-0.0);
  __m256d sum = _mm256_setzero_pd();
  for (int q = 0; q < 4; ++q)
    sum = _mm256_add_pd(sum, _mm256_blendv_pd(_mm256_loadu_pd(x + c + t.offset[q]), neg_zero, t.absent[q]));
  sum = _mm256_add_pd(sum, _mm256_loadu_pd(x + c - 1));
  return _mm256_add_pd(sum, _mm256_loadu_pd(x + c + 1));
}

// The inner cells of such a row from base + 1 by whole vectors, with the masked path's
// operations (diagonal d); returns where they stop, for the caller's scalar cells.
template <bool Residual>
KINEMA_TARGET_AVX2 Index off_row_apply_avx2(const Scalar* x, Scalar* y, const Scalar* b, Index base, Index n2,
                                            std::uint8_t dirs, Index s0, Index s1, Scalar d, Scalar ih2) {
  const OffRowTerms t = off_row_terms(dirs, s0, s1);
  const __m256d vd = _mm256_set1_pd(d), vih2 = _mm256_set1_pd(ih2);
  Index c = base + 1;
  for (; c + 4 <= base + n2 - 1; c += 4) {
    if ((c & 7) < 4) {  // once per 64-byte line
      prefetch_ahead(x + c + t.offset[1]);
      if (Residual) prefetch_ahead(b + c);
    }
    const __m256d ax = _mm256_sub_pd(_mm256_mul_pd(vd, _mm256_loadu_pd(x + c)), _mm256_mul_pd(vih2, off_row_sum(x, c, t)));
    _mm256_storeu_pd(y + c, Residual ? _mm256_sub_pd(_mm256_loadu_pd(b + c), ax) : ax);
  }
  return c;
}

// 2D rows stay in cache (a 1024^2 grid's rows are 8 KB): the plain body, compiled for AVX2.
template <bool Residual>
KINEMA_TARGET_AVX2 void plain_row2_avx2(const Scalar* x, Scalar* y, const Scalar* b, Index base,
                                        Index n2, Index s0, Index s1, Scalar d, Scalar ih2,
                                        const RowEnds& ends) {
  y[base] = ends.value<false, Residual>(x, b, base, 1, s0, s1, ih2);
  plain_row_body<false, Residual>(x, y, b, base + 1, base + n2 - 1, s0, s1, d, ih2);
  y[base + n2 - 1] = ends.value<false, Residual>(x, b, base + n2 - 1, -1, s0, s1, ih2);
}
#endif

using PlainRow = void (*)(const Scalar*, Scalar*, const Scalar*, Index, Index, Index, Index, Scalar,
                          Scalar, const RowEnds&);

template <bool ThreeD>
PlainRow pick_plain_row(bool residual, bool avx2, bool stream) {
#if KINEMA_HAVE_AVX2_CLONES
  if (avx2) {
    if (!ThreeD) return residual ? plain_row2_avx2<true> : plain_row2_avx2<false>;
    if (stream) return residual ? plain_row3_avx2<true, true> : plain_row3_avx2<false, true>;
    return residual ? plain_row3_avx2<true, false> : plain_row3_avx2<false, false>;
  }
#endif
  (void)avx2;
  (void)stream;
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
  const PlainRow plain_row = pick_plain_row<ThreeD>(b != nullptr, avx2_, stream_stores_);
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
#if KINEMA_HAVE_AVX2_CLONES
      if (avx2_ && row_dirs_[row] != kMixedRow) {
        masked_cells(base, base + 1);
        const Scalar d = diagonal(base + 1);
        c = b ? off_row_apply_avx2<true>(x, y, b, base, n2, row_dirs_[row], s0, s1, d, ih2)
              : off_row_apply_avx2<false>(x, y, b, base, n2, row_dirs_[row], s0, s1, d, ih2);
      }
#endif
      masked_cells(c, base + n2);
    }
  };
#pragma omp parallel if (parallel())
  {
#pragma omp for schedule(static) nowait
    for (Index row = 0; row < shape_.rows(); ++row) row_kernel(row);
    // Each thread orders its own non-temporal stores before the team's closing barrier, after
    // which y is read: one fence per pass, where there was one per row.
#if KINEMA_HAVE_AVX2_CLONES
    if (stream_stores_) stream_fence();
#endif
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

#if KINEMA_HAVE_AVX2_CLONES
namespace {

// One colour on the inner cells [1, n2 - 1) of a plain row starting at `base`: the cells with
// k % 2 == k0. The update runs on whole AVX2 vectors and keeps the other colour's lanes by a
// blend, so that every load is contiguous. Each vector's store waits until the next vector's
// loads are issued: those at c - 1 and c + 1 overlap the previous store by one cell, and a load
// from a store still in flight would stall on the failed store forwarding (the lanes read there
// belong to the other colour, which this pass does not change). In 3D the next plane and b are
// prefetched (kPrefetchAhead). Same operations in the same order as the scalar body in
// smooth_row, so the results are bitwise those of the baseline.
// The Gauss-Seidel update of the four cells from c, kept where take_new is set (one colour)
// and `own` elsewhere; `below` and `above` are the cells at c -+ s0 (3D only). The scalar body's
// operations in its order.
template <bool ThreeD>
KINEMA_TARGET_AVX2 KINEMA_ALWAYS_INLINE __m256d colour_vector(const Scalar* b, const Scalar* x, Index c, Index s1,
                                                              __m256d own, __m256d below, __m256d above,
                                                              __m256d vih2, __m256d vinv, __m256d take_new) {
  __m256d nb = _mm256_add_pd(_mm256_add_pd(_mm256_add_pd(_mm256_loadu_pd(x + c - s1),
                                                         _mm256_loadu_pd(x + c + s1)),
                                           _mm256_loadu_pd(x + c - 1)),
                             _mm256_loadu_pd(x + c + 1));
  if (ThreeD) nb = _mm256_add_pd(nb, _mm256_add_pd(below, above));
  const __m256d updated = _mm256_mul_pd(_mm256_add_pd(_mm256_loadu_pd(b + c), _mm256_mul_pd(vih2, nb)), vinv);
  return _mm256_blendv_pd(own, updated, take_new);
}

// Lanes of the colour whose cells have k % 2 == k0, in vectors that start at odd k.
KINEMA_TARGET_AVX2 KINEMA_ALWAYS_INLINE __m256d colour_lanes(Index k0) {
  return k0 == 1 ? _mm256_castsi256_pd(_mm256_setr_epi64x(-1, 0, -1, 0))
                 : _mm256_castsi256_pd(_mm256_setr_epi64x(0, -1, 0, -1));
}

// The whole vectors of a row from k = 1 up to its last cell, each stored one vector later as
// described above: `merged(c)` is the vector at cell c, its colour updated and the other colour
// as it was. Returns the k where the vectors stop.
template <class Merged>
KINEMA_TARGET_AVX2 KINEMA_ALWAYS_INLINE Index delayed_colour_vectors(Scalar* x, Index base, Index n2,
                                                                     Merged&& merged) {
  Index k = 1;
  __m256d pending = _mm256_setzero_pd();
  Scalar* pending_at = nullptr;
  for (; k + 4 <= n2 - 1; k += 4) {
    const __m256d v = merged(base + k);
    if (pending_at) _mm256_storeu_pd(pending_at, pending);
    pending = v;
    pending_at = x + base + k;
  }
  if (pending_at) _mm256_storeu_pd(pending_at, pending);
  return k;
}

template <bool ThreeD>
KINEMA_TARGET_AVX2 void colour_row_avx2(const Scalar* b, Scalar* x, Index base, Index n2, Index k0,
                                        Index s0, Index s1, Scalar ih2, Scalar inv) {
  const __m256d vih2 = _mm256_set1_pd(ih2), vinv = _mm256_set1_pd(inv), take_new = colour_lanes(k0);
  Index k = delayed_colour_vectors(x, base, n2, [&](Index c) KINEMA_TARGET_AVX2 {
    if (ThreeD && (c & 7) < 4) {  // once per 64-byte line
      prefetch_ahead(x + c + s0);
      prefetch_ahead(b + c);
    }
    const __m256d below = ThreeD ? _mm256_loadu_pd(x + c - s0) : _mm256_setzero_pd();
    const __m256d above = ThreeD ? _mm256_loadu_pd(x + c + s0) : _mm256_setzero_pd();
    return colour_vector<ThreeD>(b, x, c, s1, _mm256_loadu_pd(x + c), below, above, vih2, vinv, take_new);
  });
  for (k += (k & 1) != k0; k < n2 - 1; k += 2) {
    const Index c = base + k;
    Scalar nb = x[c - s1] + x[c + s1] + x[c - 1] + x[c + 1];
    if (ThreeD) nb += x[c - s0] + x[c + s0];
    x[c] = (b[c] + ih2 * nb) * inv;
  }
}

// The two colours of a sweep on a pair of plain rows at once: the first colour on the row at
// `base` (plane p) and the second colour on the row below it at base - s0 (plane p - 1), whose
// first-colour cells are already final. The second colour of a cell reads the first colour's new
// value of the cell above it, which this vector has just computed, and the cell above reads
// the old value of the cell below, loaded once for both: one pass over the rows where two
// would load them twice. Both rows' cells of their colour have the same k parity k0. Stores
// are delayed by one vector as in colour_row_avx2, and the operations are those of the scalar
// body in the same order: bitwise the result of the two colour passes.
KINEMA_TARGET_AVX2 void colour_row_pair_avx2(const Scalar* b, Scalar* x, Index base, Index n2, Index k0,
                                             Index s0, Index s1, Scalar ih2, Scalar inv) {
  const __m256d vih2 = _mm256_set1_pd(ih2), vinv = _mm256_set1_pd(inv), take_new = colour_lanes(k0);
  auto update = [&](Index c, __m256d own, __m256d below, __m256d above) KINEMA_TARGET_AVX2 {
    return colour_vector<true>(b, x, c, s1, own, below, above, vih2, vinv, take_new);
  };
  // Both rows' updates of the four cells from c: (first row, second row).
  auto pair = [&](Index c, __m256d& first, __m256d& second) KINEMA_TARGET_AVX2 {
    const Index d = c - s0;
    const __m256d middle = _mm256_loadu_pd(x + d);  // plane p - 1: below the first row, the second row's own
    first = update(c, _mm256_loadu_pd(x + c), middle, _mm256_loadu_pd(x + c + s0));
    second = update(d, middle, _mm256_loadu_pd(x + d - s0), first);
  };
  Index k = 1;
  if (k + 4 <= n2 - 1) {
    // The first vector outside the loop, so that the loop stores the previous one unconditionally.
    __m256d pending_first, pending_second;
    pair(base + k, pending_first, pending_second);
    for (k += 4; k + 4 <= n2 - 1; k += 4) {
      const Index c = base + k;
      if ((c & 7) < 4) {  // once per 64-byte line
        prefetch_ahead(x + c + s0);
        prefetch_ahead(b + c);
        prefetch_ahead(b + c - s0);
      }
      __m256d first, second;
      pair(c, first, second);
      _mm256_storeu_pd(x + c - 4, pending_first);
      _mm256_storeu_pd(x + c - 4 - s0, pending_second);
      pending_first = first;
      pending_second = second;
    }
    _mm256_storeu_pd(x + base + k - 4, pending_first);
    _mm256_storeu_pd(x + base + k - 4 - s0, pending_second);
  }
  const Index tail = k + ((k & 1) != k0);
  for (Index row_base : {base, base - s0})
    for (Index t = tail; t < n2 - 1; t += 2) {
      const Index c = row_base + t;
      Scalar nb = x[c - s1] + x[c + s1] + x[c - 1] + x[c + 1];
      nb += x[c - s0] + x[c + s0];
      x[c] = (b[c] + ih2 * nb) * inv;
    }
}

// One colour on the inner cells of a row whose inner cells share one stencil (row_dirs_),
// by whole vectors from k = 1 as in colour_row_avx2, with the masked path's operations
// (x_c = (b_c + ih2 neighbour_sum) / d, d > 0 as the row couples along itself); returns the k
// where the vectors stop, for the caller's scalar cells.
KINEMA_TARGET_AVX2 Index off_row_colour_avx2(const Scalar* b, Scalar* x, Index base, Index n2, Index k0,
                                             std::uint8_t dirs, Index s0, Index s1, Scalar d, Scalar ih2) {
  const OffRowTerms t = off_row_terms(dirs, s0, s1);
  const __m256d vd = _mm256_set1_pd(d), vih2 = _mm256_set1_pd(ih2), take_new = colour_lanes(k0);
  return delayed_colour_vectors(x, base, n2, [&](Index c) KINEMA_TARGET_AVX2 {
    if ((c & 7) < 4) {  // once per 64-byte line
      prefetch_ahead(x + c + t.offset[1]);
      prefetch_ahead(b + c);
    }
    const __m256d updated =
        _mm256_div_pd(_mm256_add_pd(_mm256_loadu_pd(b + c), _mm256_mul_pd(vih2, off_row_sum(x, c, t))), vd);
    return _mm256_blendv_pd(_mm256_loadu_pd(x + c), updated, take_new);
  });
}

// The Gauss-Seidel updates of the four cells from c computed as end cells of a plain row
// (end_cell_update's operations and order; `inward` is the one neighbour along the row, `below`
// and `above` the cells at c -+ s0): the lane of the row's actual end cell is kept.
template <bool ThreeD>
KINEMA_TARGET_AVX2 KINEMA_ALWAYS_INLINE __m256d end_colour_vector(const Scalar* b, const Scalar* x, Index c,
                                                                  Index inward, Index s1, __m256d below,
                                                                  __m256d above, __m256d vih2, __m256d vd_end) {
  __m256d sum = _mm256_setzero_pd();
  if (ThreeD) sum = _mm256_add_pd(_mm256_add_pd(sum, below), above);
  sum = _mm256_add_pd(sum, _mm256_loadu_pd(x + c - s1));
  sum = _mm256_add_pd(sum, _mm256_loadu_pd(x + c + s1));
  sum = _mm256_add_pd(sum, _mm256_loadu_pd(x + c + inward));
  return _mm256_div_pd(_mm256_add_pd(_mm256_loadu_pd(b + c), _mm256_mul_pd(vih2, sum)), vd_end);
}

// colour_row_avx2 on a row of whole vectors (n2 % 4 == 0, n2 >= 8) with plain ends, the end
// cells blended in as in colour_row_pair_whole_avx2.
template <bool ThreeD>
KINEMA_TARGET_AVX2 void colour_row_whole_avx2(const Scalar* b, Scalar* x, Index base, Index n2, Index k0,
                                              Index s0, Index s1, Scalar ih2, Scalar inv, Scalar d_end) {
  const __m256d vih2 = _mm256_set1_pd(ih2), vinv = _mm256_set1_pd(inv), vd_end = _mm256_set1_pd(d_end),
                take_new = colour_lanes(1 - k0);
  auto row_vector = [&](Index c, int end_lane) KINEMA_TARGET_AVX2 {
    const __m256d below = ThreeD ? _mm256_loadu_pd(x + c - s0) : _mm256_setzero_pd();
    const __m256d above = ThreeD ? _mm256_loadu_pd(x + c + s0) : _mm256_setzero_pd();
    __m256d v = colour_vector<ThreeD>(b, x, c, s1, _mm256_loadu_pd(x + c), below, above, vih2, vinv, take_new);
    if (end_lane == 0)
      v = _mm256_blend_pd(v, end_colour_vector<ThreeD>(b, x, c, 1, s1, below, above, vih2, vd_end), 0b0001);
    if (end_lane == 3)
      v = _mm256_blend_pd(v, end_colour_vector<ThreeD>(b, x, c, -1, s1, below, above, vih2, vd_end), 0b1000);
    return v;
  };
  const Index end = base + n2;
  __m256d pending = row_vector(base, k0 == 0 ? 0 : -1);
  for (Index c = base + 4; c < end - 4; c += 4) {
    if (ThreeD && (c & 7) < 4) {  // once per 64-byte line
      prefetch_ahead(x + c + s0);
      prefetch_ahead(b + c);
    }
    const __m256d v = row_vector(c, -1);
    _mm256_storeu_pd(x + c - 4, pending);
    pending = v;
  }
  const __m256d last = row_vector(end - 4, ((n2 - 1) & 1) == k0 ? 3 : -1);
  _mm256_storeu_pd(x + end - 8, pending);
  _mm256_storeu_pd(x + end - 4, last);
}

// colour_row_pair_avx2 on rows of whole vectors (n2 % 4 == 0, n2 >= 8) with plain ends: the
// vectors start at k = 0 and the end cells' updates are blended into the first and last vector
// (end_colour_vector), from the same loads. The scalar end cells these replace stood on every
// row pair's critical path, their stores right before the vector loads of the same line.
KINEMA_TARGET_AVX2 void colour_row_pair_whole_avx2(const Scalar* b, Scalar* x, Index base, Index n2, Index k0,
                                                   Index s0, Index s1, Scalar ih2, Scalar inv, Scalar d_end) {
  // Vectors starting at even k: the colour's lanes are those colour_lanes gives the other
  // parity for vectors starting at odd k.
  const __m256d vih2 = _mm256_set1_pd(ih2), vinv = _mm256_set1_pd(inv), vd_end = _mm256_set1_pd(d_end),
                take_new = colour_lanes(1 - k0);
  // Both rows' updates of the four cells from c: (first row, second row); the end lane
  // `end_lane` (0 or 3, -1 for none) is of this colour and takes the end-cell update.
  auto pair = [&](Index c, int end_lane, __m256d& first, __m256d& second) KINEMA_TARGET_AVX2 {
    const Index d = c - s0;
    const __m256d middle = _mm256_loadu_pd(x + d), above = _mm256_loadu_pd(x + c + s0),
                  bottom = _mm256_loadu_pd(x + d - s0);
    first = colour_vector<true>(b, x, c, s1, _mm256_loadu_pd(x + c), middle, above, vih2, vinv, take_new);
    if (end_lane == 0)
      first = _mm256_blend_pd(first, end_colour_vector<true>(b, x, c, 1, s1, middle, above, vih2, vd_end), 0b0001);
    if (end_lane == 3)
      first = _mm256_blend_pd(first, end_colour_vector<true>(b, x, c, -1, s1, middle, above, vih2, vd_end), 0b1000);
    second = colour_vector<true>(b, x, d, s1, middle, bottom, first, vih2, vinv, take_new);
    if (end_lane == 0)
      second = _mm256_blend_pd(second, end_colour_vector<true>(b, x, d, 1, s1, bottom, first, vih2, vd_end), 0b0001);
    if (end_lane == 3)
      second = _mm256_blend_pd(second, end_colour_vector<true>(b, x, d, -1, s1, bottom, first, vih2, vd_end), 0b1000);
  };
  const Index end = base + n2;
  __m256d pending_first, pending_second;
  pair(base, k0 == 0 ? 0 : -1, pending_first, pending_second);
  for (Index c = base + 4; c < end - 4; c += 4) {
    if ((c & 7) < 4) {  // once per 64-byte line
      prefetch_ahead(x + c + s0);
      prefetch_ahead(b + c);
      prefetch_ahead(b + c - s0);
    }
    __m256d first, second;
    pair(c, -1, first, second);
    _mm256_storeu_pd(x + c - 4, pending_first);
    _mm256_storeu_pd(x + c - 4 - s0, pending_second);
    pending_first = first;
    pending_second = second;
  }
  __m256d first, second;
  pair(end - 4, ((n2 - 1) & 1) == k0 ? 3 : -1, first, second);
  _mm256_storeu_pd(x + end - 8, pending_first);
  _mm256_storeu_pd(x + end - 8 - s0, pending_second);
  _mm256_storeu_pd(x + end - 4, first);
  _mm256_storeu_pd(x + end - 4 - s0, second);
}

}  // namespace
#endif

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
  if (!row_fast_[row]) {
    Index k = k0;
#if KINEMA_HAVE_AVX2_CLONES
    if (avx2_ && row_dirs_[row] != kMixedRow) {
      if (k0 == 0) masked(base);
      k = off_row_colour_avx2(b, x, base, n2, k0, row_dirs_[row], s0, s1, diagonal(base + 1), ih2);
      k += (k & 1) != k0;
    }
#endif
    for (; k < n2; k += 2) masked(base + k);
    return;
  }
  const Scalar inv_plain = inv_plain_;
  const Scalar d_end = end_diagonal<ThreeD>();
  auto end_cell = [&](Index c, Index inward) {
    if (!ends_plain_) return masked(c);
    end_cell_update<ThreeD>(b, x, c, inward, s0, s1, ih2, d_end);
  };
#if KINEMA_HAVE_AVX2_CLONES
  if (avx2_ && ends_plain_ && n2 % 4 == 0 && n2 >= 8) {
    colour_row_whole_avx2<ThreeD>(b, x, base, n2, k0, s0, s1, ih2, inv_plain, d_end);
    return;
  }
#endif
  if (k0 == 0) end_cell(base, 1);
#if KINEMA_HAVE_AVX2_CLONES
  if (avx2_) {
    colour_row_avx2<ThreeD>(b, x, base, n2, k0, s0, s1, ih2, inv_plain);
  } else
#endif
  {
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
#if KINEMA_HAVE_AVX2_CLONES
  if (ThreeD && avx2_ && ends_plain_ && row_fast_[row] && row_fast_[below]) {
    const Index n2 = shape_.n[2], s0 = shape_.stride(0), s1 = shape_.stride(1);
    const Scalar ih2 = inv_h2_, inv_plain = inv_plain_, d_end = end_diagonal<ThreeD>();
    const Index base = row * n2;
    auto end_cells = [&](Index k, Index inward) {
      for (Index c : {base + k, base + k - s0}) end_cell_update<ThreeD>(b, x, c, inward, s0, s1, ih2, d_end);
    };
    if (n2 % 4 == 0 && n2 >= 8) {
      colour_row_pair_whole_avx2(b, x, base, n2, k0, s0, s1, ih2, inv_plain, d_end);
      return;
    }
    if (k0 == 0) end_cells(0, 1);
    colour_row_pair_avx2(b, x, base, n2, k0, s0, s1, ih2, inv_plain);
    if (((n2 - 1) & 1) == k0) end_cells(n2 - 1, -1);
    return;
  }
#endif
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
