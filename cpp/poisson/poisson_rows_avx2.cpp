// AVX2 versions of the Poisson operator's row kernels (poisson_rows.h): the same operations in
// the same order as the portable rows, four cells per instruction, with the prefetches and
// store orders that the 3D passes need to reach the memory bandwidth. Reached only through
// avx2_row_kernels(), which the operator calls when the CPU has AVX2 (core/simd.h).
#include "poisson/poisson_rows.h"

#include <cstdint>

#if KINEMA_HAVE_AVX2_CLONES
#include <immintrin.h>
#endif

namespace kinema::poisson_rows {

#if KINEMA_HAVE_AVX2_CLONES
namespace {

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


constexpr Avx2RowKernels kKernels = {
    {plain_row2_avx2<false>, plain_row2_avx2<true>},
    {{plain_row3_avx2<false, false>, plain_row3_avx2<false, true>},
     {plain_row3_avx2<true, false>, plain_row3_avx2<true, true>}},
    {off_row_apply_avx2<false>, off_row_apply_avx2<true>},
    {colour_row_avx2<false>, colour_row_avx2<true>},
    {colour_row_whole_avx2<false>, colour_row_whole_avx2<true>},
    colour_row_pair_avx2,
    colour_row_pair_whole_avx2,
    off_row_colour_avx2,
    stream_fence,
};

}  // namespace

const Avx2RowKernels* avx2_row_kernels() { return &kKernels; }
#else
const Avx2RowKernels* avx2_row_kernels() { return nullptr; }
#endif

}  // namespace kinema::poisson_rows
