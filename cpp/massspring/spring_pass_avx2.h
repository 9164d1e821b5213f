// AVX2 versions of spring_pass.h's 2D spring loops: four springs per instruction, the scalar
// loop's IEEE operations in its order (no FMA), so the same bits (core/simd.h). Included by
// spring_pass.h after the scalar loops, which finish each range's tail of fewer than four.
#pragma once

#include <algorithm>

#include "core/simd.h"

#if KINEMA_HAVE_AVX2_CLONES
#include <immintrin.h>

namespace kinema::massspring::avx2 {

// (x, y) of the rows at element offsets i0..i3 of an (n, 2) array, as the vectors (x0..x3),
// (y0..y3).
KINEMA_TARGET_AVX2 KINEMA_ALWAYS_INLINE void load4(const Scalar* a, const PassIndex* i, __m256d& X,
                                                   __m256d& Y) {
  const __m256d lo = _mm256_insertf128_pd(_mm256_castpd128_pd256(_mm_loadu_pd(a + i[0])),
                                          _mm_loadu_pd(a + i[2]), 1);
  const __m256d hi = _mm256_insertf128_pd(_mm256_castpd128_pd256(_mm_loadu_pd(a + i[1])),
                                          _mm_loadu_pd(a + i[3]), 1);
  X = _mm256_unpacklo_pd(lo, hi);
  Y = _mm256_unpackhi_pd(lo, hi);
}

// Stores (X[q], Y[q]) at out + slot[2 q] (end a = 0) and its negative at out + slot[2 q + 1]
// (end 1), q = 0..3 (the four springs' slots, spring_pass.h's header); `flip` swaps the ends.
KINEMA_TARGET_AVX2 KINEMA_ALWAYS_INLINE void store4(Scalar* out, const PassIndex* slot, __m256d X,
                                                    __m256d Y, bool flip) {
  const __m256d sign = _mm256_set1_pd(-0.0);
  const __m256d lo = _mm256_unpacklo_pd(X, Y);  // (x0, y0, x2, y2)
  const __m256d hi = _mm256_unpackhi_pd(X, Y);  // (x1, y1, x3, y3)
  const __m256d nlo = _mm256_xor_pd(lo, sign), nhi = _mm256_xor_pd(hi, sign);
  const int a = flip ? 1 : 0, b = 1 - a;
  _mm_storeu_pd(out + slot[a], _mm256_castpd256_pd128(lo));
  _mm_storeu_pd(out + slot[2 + a], _mm256_castpd256_pd128(hi));
  _mm_storeu_pd(out + slot[4 + a], _mm256_extractf128_pd(lo, 1));
  _mm_storeu_pd(out + slot[6 + a], _mm256_extractf128_pd(hi, 1));
  _mm_storeu_pd(out + slot[b], _mm256_castpd256_pd128(nlo));
  _mm_storeu_pd(out + slot[2 + b], _mm256_castpd256_pd128(nhi));
  _mm_storeu_pd(out + slot[4 + b], _mm256_extractf128_pd(nlo, 1));
  _mm_storeu_pd(out + slot[6 + b], _mm256_extractf128_pd(nhi, 1));
}

// Springs per batch: the square roots and divisions of a batch run first, in a loop of their
// own, so that many are in flight at once (in the loop that uses them, each spring's long chain
// sqrt -> div -> everything else would leave the divider idle between springs).
constexpr Index kBatch = 64;

// The ends of springs s..s+3.
struct Ends {
  PassIndex a[4], b[4];
};

KINEMA_TARGET_AVX2 KINEMA_ALWAYS_INLINE Ends ends(const SpringInputs& in, Index s) {
  Ends e;
  for (int q = 0; q < 4; ++q) {
    e.a[q] = in.springs[2 * (s + q)];
    e.b[q] = in.springs[2 * (s + q) + 1];
  }
  return e;
}

// End b minus end a of an (n, 2) array for the four springs of e.
KINEMA_TARGET_AVX2 KINEMA_ALWAYS_INLINE void difference4(const Scalar* a, const Ends& e, __m256d& X,
                                                         __m256d& Y) {
  __m256d xa, ya, xb, yb;
  load4(a, e.a, xa, ya);
  load4(a, e.b, xb, yb);
  X = _mm256_sub_pd(xb, xa);
  Y = _mm256_sub_pd(yb, ya);
}

// The geometry of springs [s, s + 4 count): l, 1 / l and n = d (1 / l), lane by lane, into
// geo[0..3][0, 4 count).
KINEMA_TARGET_AVX2 KINEMA_ALWAYS_INLINE void geometry(const SpringInputs& in, Index s, Index count,
                                                      Scalar (*geo)[kBatch]) {
  const __m256d one = _mm256_set1_pd(1.0);
  for (Index g = 0; g < 4 * count; g += 4) {
    __m256d dx, dy;
    difference4(in.x, ends(in, s + g), dx, dy);
    const __m256d l = _mm256_sqrt_pd(_mm256_add_pd(_mm256_mul_pd(dx, dx), _mm256_mul_pd(dy, dy)));
    const __m256d inv = _mm256_div_pd(one, l);
    _mm256_store_pd(geo[0] + g, l);
    _mm256_store_pd(geo[1] + g, inv);
    _mm256_store_pd(geo[2] + g, _mm256_mul_pd(dx, inv));
    _mm256_store_pd(geo[3] + g, _mm256_mul_pd(dy, inv));
  }
}

KINEMA_TARGET_AVX2 inline void spring_forces_2d(const SpringInputs in, Index begin, Index end,
                                                Scalar* out) {
  Index s = begin;
  const __m256d zero = _mm256_setzero_pd();
  alignas(32) Scalar geo[4][kBatch];
  while (end - s >= 4) {
    const Index count = std::min(kBatch, end - s) / 4;
    geometry(in, s, count, geo);
    for (Index g = 0; g < 4 * count; g += 4, s += 4) {
      __m256d dvx, dvy;
      difference4(in.v, ends(in, s), dvx, dvy);
      const __m256d l = _mm256_load_pd(geo[0] + g);
      const __m256d nx = _mm256_load_pd(geo[2] + g), ny = _mm256_load_pd(geo[3] + g);
      const __m256d vn = _mm256_add_pd(_mm256_mul_pd(dvx, nx), _mm256_mul_pd(dvy, ny));
      const __m256d F = _mm256_add_pd(
          _mm256_mul_pd(_mm256_loadu_pd(in.k + s), _mm256_sub_pd(l, _mm256_loadu_pd(in.L + s))),
          _mm256_mul_pd(_mm256_loadu_pd(in.c + s), vn));
      const __m256d none = _mm256_cmp_pd(l, zero, _CMP_EQ_OQ);
      store4(out, in.slot + 2 * s, _mm256_andnot_pd(none, _mm256_mul_pd(F, nx)),
             _mm256_andnot_pd(none, _mm256_mul_pd(F, ny)), false);
    }
  }
  spring_forces_scalar<2>(in, s, end, out);
}

// One component of gd (spring_pass.h's header): -((k n + c dv_perp / l) mn + F mu_perp / l),
// inv = 1 / l.
KINEMA_TARGET_AVX2 KINEMA_ALWAYS_INLINE __m256d adjoint_gd(__m256d k, __m256d c, __m256d inv, __m256d F,
                                                           __m256d mn, __m256d vn, __m256d n,
                                                           __m256d dvr, __m256d mur) {
  const __m256d dvp = _mm256_sub_pd(dvr, _mm256_mul_pd(vn, n));
  const __m256d mup = _mm256_sub_pd(mur, _mm256_mul_pd(mn, n));
  const __m256d t = _mm256_add_pd(
      _mm256_mul_pd(_mm256_add_pd(_mm256_mul_pd(k, n), _mm256_mul_pd(_mm256_mul_pd(c, dvp), inv)), mn),
      _mm256_mul_pd(_mm256_mul_pd(F, mup), inv));
  return _mm256_xor_pd(t, _mm256_set1_pd(-0.0));
}

// p[order[s + q]] += t[q], q = 0..3, lanes of `none` (zero-length springs, whose t is NaN)
// adding 0.
KINEMA_TARGET_AVX2 KINEMA_ALWAYS_INLINE void add4(Scalar* p, const PassIndex* order, __m256d none,
                                                  __m256d t) {
  alignas(32) Scalar lanes[4];
  _mm256_store_pd(lanes, _mm256_andnot_pd(none, t));
  for (int q = 0; q < 4; ++q) p[order[q]] += lanes[q];
}

KINEMA_TARGET_AVX2 inline void spring_adjoint_2d(const SpringInputs in, const Scalar* lambda,
                                                 Index begin, Index end, Scalar* out, Scalar* dk,
                                                 Scalar* dL, Scalar* dc) {
  Index s = begin;
  const __m256d zero = _mm256_setzero_pd();
  const __m256d sign = _mm256_set1_pd(-0.0);
  alignas(32) Scalar geo[4][kBatch];
  while (end - s >= 4) {
    const Index count = std::min(kBatch, end - s) / 4;
    geometry(in, s, count, geo);
    for (Index g = 0; g < 4 * count; g += 4, s += 4) {
      const Ends e = ends(in, s);
      __m256d dvx, dvy, mux, muy;
      difference4(in.v, e, dvx, dvy);
      difference4(lambda, e, mux, muy);
      const __m256d l = _mm256_load_pd(geo[0] + g), inv = _mm256_load_pd(geo[1] + g);
      const __m256d nx = _mm256_load_pd(geo[2] + g), ny = _mm256_load_pd(geo[3] + g);
      const __m256d k = _mm256_loadu_pd(in.k + s), L = _mm256_loadu_pd(in.L + s),
                    c = _mm256_loadu_pd(in.c + s);
      const __m256d mn = _mm256_add_pd(_mm256_mul_pd(mux, nx), _mm256_mul_pd(muy, ny));
      const __m256d vn = _mm256_add_pd(_mm256_mul_pd(dvx, nx), _mm256_mul_pd(dvy, ny));
      const __m256d lL = _mm256_sub_pd(l, L);
      const __m256d F = _mm256_add_pd(_mm256_mul_pd(k, lL), _mm256_mul_pd(c, vn));
      const __m256d cm = _mm256_mul_pd(_mm256_xor_pd(c, sign), mn);
      const __m256d none = _mm256_cmp_pd(l, zero, _CMP_EQ_OQ);
      // gd belongs to end j (+) and i (-), as the scalar loop's.
      store4(out, in.slot + 2 * s,
             _mm256_andnot_pd(none, adjoint_gd(k, c, inv, F, mn, vn, nx, dvx, mux)),
             _mm256_andnot_pd(none, adjoint_gd(k, c, inv, F, mn, vn, ny, dvy, muy)), true);
      store4(out + in.plane, in.slot + 2 * s, _mm256_andnot_pd(none, _mm256_mul_pd(cm, nx)),
             _mm256_andnot_pd(none, _mm256_mul_pd(cm, ny)), true);
      if (dk) {
        add4(dk, in.order + s, none, _mm256_mul_pd(_mm256_xor_pd(lL, sign), mn));
        add4(dL, in.order + s, none, _mm256_mul_pd(k, mn));
        add4(dc, in.order + s, none, _mm256_mul_pd(_mm256_xor_pd(vn, sign), mn));
      }
    }
  }
  spring_adjoint_scalar<2>(in, lambda, s, end, out, dk, dL, dc);
}

}  // namespace kinema::massspring::avx2
#endif
