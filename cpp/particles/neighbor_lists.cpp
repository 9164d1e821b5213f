// The grid search of NeighborLists::build: for each query point, the runs of the grid's sorted
// coordinates (one per line of cells within reach) are streamed through the distance test
// |x_j - x_i|^2 < r^2, and the indices that pass are compacted into the row. About 80% of the
// candidates of the 3^3 cells fail the test, at random, so the test is branch-free: every
// candidate is written and the row's end advances by the test's outcome (baseline), or 4
// candidates are tested at once and the passing lanes packed by a shuffle (AVX2). Both compute
// ((dx dx + dy dy) + dz dz) in the same order without FMA, so they keep the same entries.
#include "particles/neighbor_lists.h"

#if KINEMA_HAVE_AVX2_CLONES
#include <immintrin.h>
#endif

namespace kinema {

namespace {

using IdBuffer = NeighborLists::Buffer<std::int32_t>;

// The runs of a group of queries (see search_rows) and the coordinates they index.
template <int D>
struct Candidates {
  typename NeighborGrid<D>::Span spans[NeighborGrid<D>::kMaxSpans];
  int count = 0;
  const Scalar* xs[D];
  const std::int32_t* ids;
};

// Writes to row the candidates within radius (r2 = radius^2) of p, except the point `skip`
// (-1: none), in order, and returns how many. Room: all candidates (+ 3 for AVX2).
template <int D>
Index test_candidates(const Candidates<D>& cand, const Scalar* p, Scalar r2, std::int32_t skip, std::int32_t* row) {
  Index kept = 0;
  for (int s = 0; s < cand.count; ++s)
    for (Index k = cand.spans[s].begin; k < cand.spans[s].end; ++k) {
      Scalar d2 = 0;
      for (int a = 0; a < D; ++a) {
        const Scalar d = cand.xs[a][k] - p[a];
        d2 += d * d;
      }
      row[kept] = cand.ids[k];
      kept += (d2 < r2) & (cand.ids[k] != skip);
    }
  return kept;
}

#if KINEMA_HAVE_AVX2_CLONES
// _mm_shuffle_epi8 controls that move the 32-bit lanes set in a 4-bit mask to the front.
struct PackTable {
  alignas(16) std::uint8_t control[16][16];
  std::uint8_t popcount[16];
  constexpr PackTable() : control(), popcount() {
    for (int m = 0; m < 16; ++m) {
      int out = 0;
      for (int lane = 0; lane < 4; ++lane)
        if (m >> lane & 1) {
          for (int b = 0; b < 4; ++b) control[m][4 * out + b] = static_cast<std::uint8_t>(4 * lane + b);
          ++out;
        }
      for (int b = 4 * out; b < 16; ++b) control[m][b] = 0x80;  // zero
      popcount[m] = static_cast<std::uint8_t>(out);
    }
  }
};
constexpr PackTable kPack;

// test_candidates, 4 candidates at a time. A run's last group reads up to 3 entries past it
// (the grid pads its arrays) and masks them out; the 16-byte stores need 3 entries of slack.
// One group of 4 candidates at k: appends those of the lanes in `valid` within the radius
// (r2 broadcast), except `skipped`, to row[kept..].
template <int D>
KINEMA_TARGET_AVX2 KINEMA_ALWAYS_INLINE void test_group_avx2(const Scalar* const* xs, const std::int32_t* ids,
                                                             const __m256d* px, __m256d r2, __m128i skipped, Index k,
                                                             int valid, std::int32_t* row, Index& kept) {
  __m256d d2 = _mm256_setzero_pd();
  for (int a = 0; a < D; ++a) {
    const __m256d d = _mm256_sub_pd(_mm256_loadu_pd(xs[a] + k), px[a]);
    d2 = _mm256_add_pd(d2, _mm256_mul_pd(d, d));
  }
  const __m128i id = _mm_loadu_si128(reinterpret_cast<const __m128i*>(ids + k));
  const int mask = _mm256_movemask_pd(_mm256_cmp_pd(d2, r2, _CMP_LT_OQ)) &
                   ~_mm_movemask_ps(_mm_castsi128_ps(_mm_cmpeq_epi32(id, skipped))) & valid;
  const __m128i control = _mm_load_si128(reinterpret_cast<const __m128i*>(kPack.control[mask]));
  _mm_storeu_si128(reinterpret_cast<__m128i*>(row + kept), _mm_shuffle_epi8(id, control));
  kept += kPack.popcount[mask];
}

// test_candidates, 4 candidates at a time. A run's last group reads up to 3 entries past it
// (the grid pads its arrays) and masks them out; the 16-byte stores need 3 entries of slack.
template <int D>
KINEMA_TARGET_AVX2 Index test_candidates_avx2(const Candidates<D>& cand, const Scalar* p, Scalar radius2,
                                              std::int32_t skip, std::int32_t* row) {
  const __m256d r2 = _mm256_set1_pd(radius2);
  const __m128i skipped = _mm_set1_epi32(skip);
  // Local copies: the stores into the row may alias anything, the compiler would reload these.
  const Scalar* xs[D];
  __m256d px[D];
  for (int a = 0; a < D; ++a) {
    xs[a] = cand.xs[a];
    px[a] = _mm256_set1_pd(p[a]);
  }
  const std::int32_t* ids = cand.ids;
  Index kept = 0;
  for (int s = 0; s < cand.count; ++s) {
    const Index end = cand.spans[s].end;
    Index k = cand.spans[s].begin;
    for (; k + 4 <= end; k += 4) test_group_avx2<D>(xs, ids, px, r2, skipped, k, 0xf, row, kept);
    if (k < end) test_group_avx2<D>(xs, ids, px, r2, skipped, k, 0xf >> (4 - (end - k)), row, kept);
  }
  return kept;
}
#endif

// The rows of the queries [begin, end) (sizes[i]: the size of row i). Consecutive queries in
// one cell (most of them once the points are sorted along a space-filling curve) share the
// runs of the cells within radius of their bounding box: the lookups of the runs and the
// branches of the loops over them are paid once per group.
template <int D>
void search_rows(const NeighborGrid<D>& grid, const Scalar* xq, Index begin, Index end, Scalar radius, bool self,
                 bool avx2, IdBuffer& out, Index* sizes) {
  using Vec = typename NeighborGrid<D>::Vec;
  auto test = &test_candidates<D>;
#if KINEMA_HAVE_AVX2_CLONES
  if (avx2) test = &test_candidates_avx2<D>;
#else
  (void)avx2;
#endif
  constexpr Index kMaxGroup = 32;
  Candidates<D> cand;
  for (int a = 0; a < D; ++a) cand.xs[a] = grid.sorted_coordinates(a);
  cand.ids = grid.sorted();
  const Scalar r2 = radius * radius;
  Index i = begin;
  typename NeighborGrid<D>::Cell cell = grid.cell_of(Eigen::Map<const Vec>(xq + i * D));
  while (i < end) {
    Vec lo = Eigen::Map<const Vec>(xq + i * D), hi = lo;
    Index j = i + 1;
    typename NeighborGrid<D>::Cell next = cell;
    for (; j < end && j - i < kMaxGroup; ++j) {
      const Eigen::Map<const Vec> p(xq + j * D);
      next = grid.cell_of(p);
      if (next != cell) break;
      lo = lo.cwiseMin(p);
      hi = hi.cwiseMax(p);
    }
    cand.count = grid.spans_of_box(cell, lo, hi, radius, cand.spans);
    Index room = 3;
    for (int s = 0; s < cand.count; ++s) room += cand.spans[s].end - cand.spans[s].begin;
    for (Index q = i; q < j; ++q) {
      const Index kept = test(cand, xq + q * D, r2, self ? static_cast<std::int32_t>(q) : -1,
                              out.room(static_cast<size_t>(room)));
      out.size += static_cast<size_t>(kept);
      sizes[q] = kept;
    }
    if (j < end && j - i == kMaxGroup) next = grid.cell_of(Eigen::Map<const Vec>(xq + j * D));
    cell = next;
    i = j;
  }
}

}  // namespace

template <int D>
void NeighborLists::build(const NeighborGrid<D>& grid, const Scalar* xq, Index nq, Scalar radius, bool self,
                          bool avx2) {
  fill_chunks(nq, nullptr, [&](Index begin, Index end, Buffer<std::int32_t>& out, Buffer<Scalar>*, Index* sizes) {
    search_rows<D>(grid, xq, begin, end, radius, self, avx2, out, sizes);
  });
}

template void NeighborLists::build<2>(const NeighborGrid<2>&, const Scalar*, Index, Scalar, bool, bool);
template void NeighborLists::build<3>(const NeighborGrid<3>&, const Scalar*, Index, Scalar, bool, bool);

}  // namespace kinema
