#include "fmm/m2l_product.h"

#include "core/simd.h"

#if KINEMA_HAVE_AVX2_CLONES
#include <immintrin.h>
#endif

namespace kinema::fmm3 {

namespace {

void product_portable(const Scalar* a, int lda, int n, const Scalar* b, int k, Scalar* c) {
  for (int col = 0; col < k; ++col) {
    const Scalar* bc = b + static_cast<size_t>(col) * n;
    Scalar* cc = c + static_cast<size_t>(col) * n;
    for (int i = 0; i < n; ++i) {
      const Scalar* row = a + static_cast<size_t>(i) * lda;
      Scalar s = 0;
      for (int j = 0; j < n; ++j) s += row[j] * bc[j];
      cc[i] = s;
    }
  }
}

#if KINEMA_HAVE_AVX2_CLONES
#define KINEMA_AVX2_FMA __attribute__((target("avx2,fma")))

KINEMA_AVX2_FMA inline Scalar reduce(__m256d v) {
  const __m128d lo = _mm256_castpd256_pd128(v), hi = _mm256_extractf128_pd(v, 1);
  const __m128d s = _mm_add_pd(lo, hi);
  return _mm_cvtsd_f64(_mm_add_sd(s, _mm_unpackhi_pd(s, s)));
}

// Rows i0, i0 + 1 of A against columns c0 .. c0 + cols - 1 (cols <= 4) of B.
template <int Cols>
KINEMA_AVX2_FMA void block(const Scalar* a, int lda, int n, int rows, const Scalar* b, Scalar* c) {
  const int vec_end = n & ~3;
  __m256d acc[2][Cols];
  for (int r = 0; r < 2; ++r)
    for (int q = 0; q < Cols; ++q) acc[r][q] = _mm256_setzero_pd();
  const Scalar* a0 = a;
  const Scalar* a1 = rows > 1 ? a + lda : a;
  for (int j = 0; j < vec_end; j += 4) {
    const __m256d x0 = _mm256_loadu_pd(a0 + j), x1 = _mm256_loadu_pd(a1 + j);
    for (int q = 0; q < Cols; ++q) {
      const __m256d y = _mm256_loadu_pd(b + static_cast<size_t>(q) * n + j);
      acc[0][q] = _mm256_fmadd_pd(x0, y, acc[0][q]);
      acc[1][q] = _mm256_fmadd_pd(x1, y, acc[1][q]);
    }
  }
  for (int q = 0; q < Cols; ++q) {
    const Scalar* bq = b + static_cast<size_t>(q) * n;
    Scalar s0 = reduce(acc[0][q]), s1 = reduce(acc[1][q]);
    for (int j = vec_end; j < n; ++j) s0 += a0[j] * bq[j], s1 += a1[j] * bq[j];
    c[static_cast<size_t>(q) * n] = s0;
    if (rows > 1) c[static_cast<size_t>(q) * n + 1] = s1;
  }
}

KINEMA_AVX2_FMA void product_avx2(const Scalar* a, int lda, int n, const Scalar* b, int k, Scalar* c) {
  for (int c0 = 0; c0 < k; c0 += 4) {
    const int cols = k - c0 < 4 ? k - c0 : 4;
    const Scalar* bc = b + static_cast<size_t>(c0) * n;
    Scalar* cc = c + static_cast<size_t>(c0) * n;
    for (int i = 0; i < n; i += 2) {
      const int rows = n - i < 2 ? 1 : 2;
      const Scalar* ai = a + static_cast<size_t>(i) * lda;
      switch (cols) {
        case 4: block<4>(ai, lda, n, rows, bc, cc + i); break;
        case 3: block<3>(ai, lda, n, rows, bc, cc + i); break;
        case 2: block<2>(ai, lda, n, rows, bc, cc + i); break;
        default: block<1>(ai, lda, n, rows, bc, cc + i); break;
      }
    }
  }
}
#endif

}  // namespace

void m2l_product(const Scalar* a, int lda, int n, const Scalar* b, int k, Scalar* c) {
#if KINEMA_HAVE_AVX2_CLONES
  static const bool avx2 = use_avx2();
  if (avx2) {
    product_avx2(a, lda, n, b, k, c);
    return;
  }
#endif
  product_portable(a, lda, n, b, k, c);
}

}  // namespace kinema::fmm3
