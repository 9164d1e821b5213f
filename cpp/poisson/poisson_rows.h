// The row kernels of the Poisson operator (poisson_operator.h) that its portable code and its
// AVX2 versions (poisson_rows_avx2.cpp) share: the plain (2d+1)-point stencil on a row and the
// end cells of plain rows. The AVX2 kernels perform the same operations in the same order (no
// FMA), so their results are bitwise those of the portable ones; the operator reaches them
// through one table, avx2_row_kernels(), chosen at run time (core/simd.h, KINEMA_SIMD).
#pragma once

#include <cstdint>

#include "core/simd.h"
#include "core/types.h"

namespace kinema::poisson_rows {

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

// A whole plain row [base, base + n2): y = A x (or b - A x) on its cells, its ends as `ends` says.
using PlainRow = void (*)(const Scalar* x, Scalar* y, const Scalar* b, Index base, Index n2, Index s0,
                          Index s1, Scalar d, Scalar ih2, const RowEnds& ends);

// The AVX2 row kernels, indexed by [residual], [stream] (non-temporal stores) and [three_d].
struct Avx2RowKernels {
  PlainRow plain_row2[2];
  PlainRow plain_row3[2][2];
  // The inner cells of a row whose inner cells share one stencil (dirs), by whole vectors from
  // base + 1 with diagonal d; returns where they stop, for the caller's scalar cells.
  Index (*off_row_apply[2])(const Scalar* x, Scalar* y, const Scalar* b, Index base, Index n2,
                            std::uint8_t dirs, Index s0, Index s1, Scalar d, Scalar ih2);
  // One Gauss-Seidel colour (cells k % 2 == k0) on the inner cells of a plain row.
  void (*colour_row[2])(const Scalar* b, Scalar* x, Index base, Index n2, Index k0, Index s0, Index s1,
                        Scalar ih2, Scalar inv);
  // The same on a row of whole vectors (n2 % 4 == 0, n2 >= 8) with plain ends, end cells included.
  void (*colour_row_whole[2])(const Scalar* b, Scalar* x, Index base, Index n2, Index k0, Index s0, Index s1,
                              Scalar ih2, Scalar inv, Scalar d_end);
  // 3D: the first colour on the row at base and the second on the row below it (base - s0).
  void (*colour_row_pair)(const Scalar* b, Scalar* x, Index base, Index n2, Index k0, Index s0, Index s1,
                          Scalar ih2, Scalar inv);
  void (*colour_row_pair_whole)(const Scalar* b, Scalar* x, Index base, Index n2, Index k0, Index s0,
                                Index s1, Scalar ih2, Scalar inv, Scalar d_end);
  // off_row_apply's counterpart for one colour; returns the k where the vectors stop.
  Index (*off_row_colour)(const Scalar* b, Scalar* x, Index base, Index n2, Index k0, std::uint8_t dirs,
                          Index s0, Index s1, Scalar d, Scalar ih2);
  // Orders the calling thread's non-temporal stores before its later stores.
  void (*stream_fence)();
};

// The AVX2 kernels, or nullptr when this build has none (a compiler or CPU family without them).
const Avx2RowKernels* avx2_row_kernels();

}  // namespace kinema::poisson_rows
