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

// Candidates in the runs: the room a row needs (reserved at once: a buffer that grows keeps
// only the entries before its size).
template <class Span>
size_t candidate_count(const Span* spans, int count) {
  Index total = 0;
  for (int s = 0; s < count; ++s) total += spans[s].end - spans[s].begin;
  return static_cast<size_t>(total);
}

// Appends to `out` the points of grid.spans(p, radius) within radius of p, except the point
// `skip` (-1: none), and returns how many.
template <int D>
Index search_row(const NeighborGrid<D>& grid, const Scalar* p, Scalar radius, std::int32_t skip, IdBuffer& out) {
  using Span = typename NeighborGrid<D>::Span;
  Span spans[NeighborGrid<D>::kMaxSpans];
  const int count = grid.spans(Eigen::Map<const typename NeighborGrid<D>::Vec>(p), radius, spans);
  const Scalar r2 = radius * radius;
  const std::int32_t* ids = grid.sorted();
  const Scalar* xs[D];
  for (int a = 0; a < D; ++a) xs[a] = grid.sorted_coordinates(a);
  std::int32_t* row = out.room(candidate_count(spans, count));
  Index kept = 0;
  for (int s = 0; s < count; ++s)
    for (Index k = spans[s].begin; k < spans[s].end; ++k) {
      Scalar d2 = 0;
      for (int a = 0; a < D; ++a) {
        const Scalar d = xs[a][k] - p[a];
        d2 += d * d;
      }
      row[kept] = ids[k];
      kept += (d2 < r2) & (ids[k] != skip);
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

// search_row, 4 candidates at a time. A run's last group reads up to 3 entries past it (the
// grid pads its arrays) and masks them out; the row keeps 3 entries of slack for the 16-byte
// stores.
template <int D>
KINEMA_TARGET_AVX2 Index search_row_avx2(const NeighborGrid<D>& grid, const Scalar* p, Scalar radius,
                                         std::int32_t skip, IdBuffer& out) {
  using Span = typename NeighborGrid<D>::Span;
  Span spans[NeighborGrid<D>::kMaxSpans];
  const int count = grid.spans(Eigen::Map<const typename NeighborGrid<D>::Vec>(p), radius, spans);
  const __m256d r2 = _mm256_set1_pd(radius * radius);
  const __m128i skipped = _mm_set1_epi32(skip);
  const std::int32_t* ids = grid.sorted();
  const Scalar* xs[D];
  __m256d px[D];
  for (int a = 0; a < D; ++a) {
    xs[a] = grid.sorted_coordinates(a);
    px[a] = _mm256_set1_pd(p[a]);
  }
  std::int32_t* row = out.room(candidate_count(spans, count) + 3);
  Index kept = 0;
  for (int s = 0; s < count; ++s) {
    const Index begin = spans[s].begin, end = spans[s].end;
    for (Index k = begin; k < end; k += 4) {
      __m256d d2 = _mm256_setzero_pd();
      for (int a = 0; a < D; ++a) {
        const __m256d d = _mm256_sub_pd(_mm256_loadu_pd(xs[a] + k), px[a]);
        d2 = _mm256_add_pd(d2, _mm256_mul_pd(d, d));
      }
      const __m128i id = _mm_loadu_si128(reinterpret_cast<const __m128i*>(ids + k));
      int mask = _mm256_movemask_pd(_mm256_cmp_pd(d2, r2, _CMP_LT_OQ));
      mask &= ~_mm_movemask_ps(_mm_castsi128_ps(_mm_cmpeq_epi32(id, skipped)));
      if (end - k < 4) mask &= (1 << (end - k)) - 1;
      const __m128i control = _mm_load_si128(reinterpret_cast<const __m128i*>(kPack.control[mask]));
      _mm_storeu_si128(reinterpret_cast<__m128i*>(row + kept), _mm_shuffle_epi8(id, control));
      kept += kPack.popcount[mask];
    }
  }
  return kept;
}
#endif

}  // namespace

template <int D>
void NeighborLists::build(const NeighborGrid<D>& grid, const Scalar* xq, Index nq, Scalar radius, bool self,
                          bool avx2) {
  auto row = &search_row<D>;
#if KINEMA_HAVE_AVX2_CLONES
  if (avx2) row = &search_row_avx2<D>;
#else
  (void)avx2;
#endif
  fill_rows(nq, nullptr, [&](Index i, Buffer<std::int32_t>& out, Buffer<Scalar>*) {
    out.size += static_cast<size_t>(row(grid, xq + i * D, radius, self ? static_cast<std::int32_t>(i) : -1, out));
  });
}

template void NeighborLists::build<2>(const NeighborGrid<2>&, const Scalar*, Index, Scalar, bool, bool);
template void NeighborLists::build<3>(const NeighborGrid<3>&, const Scalar*, Index, Scalar, bool, bool);

}  // namespace kinema
