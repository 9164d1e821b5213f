// The per-spring passes of the explicit and symplectic steps and of their adjoints, each spring
// evaluated once; its terms go, signed, to its two ends' slots of the vertices' incidence lists,
// and a vertex then sums its slots in sequence (its springs in spring order, as
// ElementAssembly::gather_vector does). The 2D passes have an AVX2 version that evaluates four
// springs per instruction; it performs the same IEEE operations in the same order as the scalar
// loop (no FMA), so both give the same bits (core/simd.h).
//
// Forward (kernels.h's spring_force): with d = x_j - x_i, l = |d|, n = d / l, dv = v_j - v_i,
//   f_i = (k (l - L) + c dv.n) n               -> out[slot(i) D + r], its negative at slot(j)
// Adjoint of psi = -mu . f_i (mu = lambda_j - lambda_i, adjoint.cpp's header; n = d (1 / l) here,
// one division per spring, within rounding of the forward's d / l):
//   gd = -((k n + c dv_perp / l) (mu.n) + F mu_perp / l),  gdv = -c (mu.n) n
//     (dL/dx_j, dL/dv_j)  -> out[slot(j) 2D + ..], their negatives at slot(i)
//   and, when wanted, dk += -(l - L) mu.n, dL += k mu.n, dc += -(dv.n) mu.n.
// A zero-length spring has no direction: its terms are 0.
#pragma once

#include <algorithm>
#include <cmath>

#include "core/simd.h"
#include "core/types.h"

#if KINEMA_HAVE_AVX2_CLONES
#include <immintrin.h>
#endif

namespace kinema::massspring {

struct SpringInputs {
  const Index* springs;  // (m, 2)
  const Scalar *x, *v;   // (n, D)
  const Scalar *k, *L, *c;
  // slot[2 s + a]: where end a of spring s is in the vertices' incidence lists (CSR order, each
  // vertex's springs in spring order). A pass writes each end's term there, signed, so that a
  // vertex's sum reads its terms in sequence.
  const Index* slot;
};

// f_i of springs [begin, end) into out (2 m, D), by slot.
template <int D>
inline void spring_forces_scalar(const SpringInputs& in, Index begin, Index end, Scalar* out) {
  for (Index s = begin; s < end; ++s) {
    const Index a = in.springs[2 * s], b = in.springs[2 * s + 1];
    Scalar d[D], dv[D];
    for (int r = 0; r < D; ++r) {
      d[r] = in.x[b * D + r] - in.x[a * D + r];
      dv[r] = in.v[b * D + r] - in.v[a * D + r];
    }
    Scalar l2 = d[0] * d[0];
    for (int r = 1; r < D; ++r) l2 += d[r] * d[r];
    const Scalar l = std::sqrt(l2);
    Scalar* oa = out + in.slot[2 * s] * D;
    Scalar* ob = out + in.slot[2 * s + 1] * D;
    if (l == 0) {
      for (int r = 0; r < D; ++r) oa[r] = ob[r] = 0;
      continue;
    }
    Scalar n[D];
    for (int r = 0; r < D; ++r) n[r] = d[r] / l;
    Scalar vn = dv[0] * n[0];
    for (int r = 1; r < D; ++r) vn += dv[r] * n[r];
    const Scalar F = in.k[s] * (l - in.L[s]) + in.c[s] * vn;
    for (int r = 0; r < D; ++r) {
      oa[r] = F * n[r];
      ob[r] = -oa[r];
    }
  }
}

// gd, gdv of springs [begin, end) into out (2 m, 2 D), by slot; the parameter terms added to dk, dL, dc
// when dk is not null.
template <int D>
inline void spring_adjoint_scalar(const SpringInputs& in, const Scalar* lambda, Index begin,
                                  Index end, Scalar* out, Scalar* dk, Scalar* dL, Scalar* dc) {
  for (Index s = begin; s < end; ++s) {
    const Index a = in.springs[2 * s], b = in.springs[2 * s + 1];
    Scalar d[D], dv[D], mu[D];
    for (int r = 0; r < D; ++r) {
      d[r] = in.x[b * D + r] - in.x[a * D + r];
      dv[r] = in.v[b * D + r] - in.v[a * D + r];
      mu[r] = lambda[b * D + r] - lambda[a * D + r];
    }
    Scalar l2 = d[0] * d[0];
    for (int r = 1; r < D; ++r) l2 += d[r] * d[r];
    const Scalar l = std::sqrt(l2);
    Scalar* oa = out + in.slot[2 * s] * 2 * D;
    Scalar* ob = out + in.slot[2 * s + 1] * 2 * D;
    if (l == 0) {
      for (int r = 0; r < 2 * D; ++r) oa[r] = ob[r] = 0;
      continue;
    }
    const Scalar k = in.k[s], L = in.L[s], c = in.c[s], inv = 1 / l;
    Scalar n[D];
    for (int r = 0; r < D; ++r) n[r] = d[r] * inv;
    Scalar mn = mu[0] * n[0], vn = dv[0] * n[0];
    for (int r = 1; r < D; ++r) {
      mn += mu[r] * n[r];
      vn += dv[r] * n[r];
    }
    const Scalar F = k * (l - L) + c * vn;
    const Scalar cm = -c * mn;
    for (int r = 0; r < D; ++r) {
      const Scalar dvp = dv[r] - vn * n[r], mup = mu[r] - mn * n[r];
      // d = x_j - x_i: dL/dx_i = -gd, dL/dx_j = +gd (the same for v).
      ob[r] = -((k * n[r] + c * dvp * inv) * mn + F * mup * inv);
      ob[D + r] = cm * n[r];
      oa[r] = -ob[r];
      oa[D + r] = -ob[D + r];
    }
    if (dk) {
      dk[s] += -(l - L) * mn;
      dL[s] += k * mn;
      dc[s] += -vn * mn;
    }
  }
}

#if KINEMA_HAVE_AVX2_CLONES
namespace avx2 {

// (x, y) of vertices i0..i3 of an (n, 2) array, as the vectors (x0..x3), (y0..y3).
KINEMA_TARGET_AVX2 KINEMA_ALWAYS_INLINE void load4(const Scalar* a, const Index* i, __m256d& X,
                                                   __m256d& Y) {
  const __m256d lo = _mm256_insertf128_pd(_mm256_castpd128_pd256(_mm_loadu_pd(a + 2 * i[0])),
                                          _mm_loadu_pd(a + 2 * i[2]), 1);
  const __m256d hi = _mm256_insertf128_pd(_mm256_castpd128_pd256(_mm_loadu_pd(a + 2 * i[1])),
                                          _mm_loadu_pd(a + 2 * i[3]), 1);
  X = _mm256_unpacklo_pd(lo, hi);
  Y = _mm256_unpackhi_pd(lo, hi);
}

// Stores (X[q], Y[q]) at out + stride slot[2 q] (end a = 0) and its negative at
// out + stride slot[2 q + 1] (end 1), q = 0..3 (the four springs' slots, spring_pass.h's header);
// `flip` swaps the ends.
KINEMA_TARGET_AVX2 KINEMA_ALWAYS_INLINE void store4(Scalar* out, Index stride, const Index* slot,
                                                    __m256d X, __m256d Y, bool flip) {
  const __m256d sign = _mm256_set1_pd(-0.0);
  const __m256d lo = _mm256_unpacklo_pd(X, Y);  // (x0, y0, x2, y2)
  const __m256d hi = _mm256_unpackhi_pd(X, Y);  // (x1, y1, x3, y3)
  const __m256d nlo = _mm256_xor_pd(lo, sign), nhi = _mm256_xor_pd(hi, sign);
  const int a = flip ? 1 : 0, b = 1 - a;
  _mm_storeu_pd(out + stride * slot[a], _mm256_castpd256_pd128(lo));
  _mm_storeu_pd(out + stride * slot[2 + a], _mm256_castpd256_pd128(hi));
  _mm_storeu_pd(out + stride * slot[4 + a], _mm256_extractf128_pd(lo, 1));
  _mm_storeu_pd(out + stride * slot[6 + a], _mm256_extractf128_pd(hi, 1));
  _mm_storeu_pd(out + stride * slot[b], _mm256_castpd256_pd128(nlo));
  _mm_storeu_pd(out + stride * slot[2 + b], _mm256_castpd256_pd128(nhi));
  _mm_storeu_pd(out + stride * slot[4 + b], _mm256_extractf128_pd(nlo, 1));
  _mm_storeu_pd(out + stride * slot[6 + b], _mm256_extractf128_pd(nhi, 1));
}

struct Four {
  Index a[4], b[4];
};

KINEMA_TARGET_AVX2 KINEMA_ALWAYS_INLINE Four ends(const Index* springs, Index s) {
  Four e;
  for (int q = 0; q < 4; ++q) {
    e.a[q] = springs[2 * (s + q)];
    e.b[q] = springs[2 * (s + q) + 1];
  }
  return e;
}

KINEMA_TARGET_AVX2 inline void spring_forces_2d(const SpringInputs& in, Index begin, Index end,
                                                Scalar* out) {
  Index s = begin;
  const __m256d zero = _mm256_setzero_pd();
  for (; s + 4 <= end; s += 4) {
    const Four e = ends(in.springs, s);
    __m256d xa, ya, xb, yb, vxa, vya, vxb, vyb;
    load4(in.x, e.a, xa, ya);
    load4(in.x, e.b, xb, yb);
    load4(in.v, e.a, vxa, vya);
    load4(in.v, e.b, vxb, vyb);
    const __m256d dx = _mm256_sub_pd(xb, xa), dy = _mm256_sub_pd(yb, ya);
    const __m256d dvx = _mm256_sub_pd(vxb, vxa), dvy = _mm256_sub_pd(vyb, vya);
    const __m256d l = _mm256_sqrt_pd(_mm256_add_pd(_mm256_mul_pd(dx, dx), _mm256_mul_pd(dy, dy)));
    const __m256d nx = _mm256_div_pd(dx, l), ny = _mm256_div_pd(dy, l);
    const __m256d vn = _mm256_add_pd(_mm256_mul_pd(dvx, nx), _mm256_mul_pd(dvy, ny));
    const __m256d F = _mm256_add_pd(
        _mm256_mul_pd(_mm256_loadu_pd(in.k + s), _mm256_sub_pd(l, _mm256_loadu_pd(in.L + s))),
        _mm256_mul_pd(_mm256_loadu_pd(in.c + s), vn));
    const __m256d none = _mm256_cmp_pd(l, zero, _CMP_EQ_OQ);
    store4(out, 2, in.slot + 2 * s, _mm256_andnot_pd(none, _mm256_mul_pd(F, nx)),
           _mm256_andnot_pd(none, _mm256_mul_pd(F, ny)), false);
  }
  spring_forces_scalar<2>(in, s, end, out);
}

// One component of gd (the header): -((k n + c dv_perp / l) mn + F mu_perp / l), inv = 1 / l.
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

// p[0..3] += t, lanes of `none` (zero-length springs, whose t is NaN) left alone.
KINEMA_TARGET_AVX2 KINEMA_ALWAYS_INLINE void add4(Scalar* p, __m256d none, __m256d t) {
  _mm256_storeu_pd(p, _mm256_add_pd(_mm256_loadu_pd(p), _mm256_andnot_pd(none, t)));
}

KINEMA_TARGET_AVX2 inline void spring_adjoint_2d(const SpringInputs& in, const Scalar* lambda,
                                                 Index begin, Index end, Scalar* out, Scalar* dk,
                                                 Scalar* dL, Scalar* dc) {
  Index s = begin;
  const __m256d zero = _mm256_setzero_pd();
  for (; s + 4 <= end; s += 4) {
    const Four e = ends(in.springs, s);
    __m256d xa, ya, xb, yb, pa, qa, pb, qb;
    load4(in.x, e.a, xa, ya);
    load4(in.x, e.b, xb, yb);
    const __m256d dx = _mm256_sub_pd(xb, xa), dy = _mm256_sub_pd(yb, ya);
    load4(in.v, e.a, pa, qa);
    load4(in.v, e.b, pb, qb);
    const __m256d dvx = _mm256_sub_pd(pb, pa), dvy = _mm256_sub_pd(qb, qa);
    load4(lambda, e.a, pa, qa);
    load4(lambda, e.b, pb, qb);
    const __m256d mux = _mm256_sub_pd(pb, pa), muy = _mm256_sub_pd(qb, qa);
    const __m256d l = _mm256_sqrt_pd(_mm256_add_pd(_mm256_mul_pd(dx, dx), _mm256_mul_pd(dy, dy)));
    const __m256d k = _mm256_loadu_pd(in.k + s), L = _mm256_loadu_pd(in.L + s),
                  c = _mm256_loadu_pd(in.c + s);
    const __m256d inv = _mm256_div_pd(_mm256_set1_pd(1.0), l);
    const __m256d nx = _mm256_mul_pd(dx, inv), ny = _mm256_mul_pd(dy, inv);
    const __m256d mn = _mm256_add_pd(_mm256_mul_pd(mux, nx), _mm256_mul_pd(muy, ny));
    const __m256d vn = _mm256_add_pd(_mm256_mul_pd(dvx, nx), _mm256_mul_pd(dvy, ny));
    const __m256d lL = _mm256_sub_pd(l, L);
    const __m256d F = _mm256_add_pd(_mm256_mul_pd(k, lL), _mm256_mul_pd(c, vn));
    const __m256d sign = _mm256_set1_pd(-0.0);
    const __m256d cm = _mm256_mul_pd(_mm256_xor_pd(c, sign), mn);
    const __m256d none = _mm256_cmp_pd(l, zero, _CMP_EQ_OQ);
    // gd belongs to end j (+) and i (-), as the scalar loop's.
    store4(out, 4, in.slot + 2 * s, _mm256_andnot_pd(none, adjoint_gd(k, c, inv, F, mn, vn, nx, dvx, mux)),
           _mm256_andnot_pd(none, adjoint_gd(k, c, inv, F, mn, vn, ny, dvy, muy)), true);
    store4(out + 2, 4, in.slot + 2 * s, _mm256_andnot_pd(none, _mm256_mul_pd(cm, nx)),
           _mm256_andnot_pd(none, _mm256_mul_pd(cm, ny)), true);
    if (dk) {
      add4(dk + s, none, _mm256_mul_pd(_mm256_xor_pd(lL, sign), mn));
      add4(dL + s, none, _mm256_mul_pd(k, mn));
      add4(dc + s, none, _mm256_mul_pd(_mm256_xor_pd(vn, sign), mn));
    }
  }
  spring_adjoint_scalar<2>(in, lambda, s, end, out, dk, dL, dc);
}

}  // namespace avx2
#endif

// Blocks of springs, four-aligned, over the threads.
constexpr Index kSpringBlock = 512;

template <int D, class Pass>
void for_spring_blocks(Index m, Pass&& pass) {
  const Index blocks = (m + kSpringBlock - 1) / kSpringBlock;
#pragma omp parallel for schedule(static) if (m > 4 * kSpringBlock)
  for (Index b = 0; b < blocks; ++b) pass(b * kSpringBlock, std::min(m, (b + 1) * kSpringBlock));
}

template <int D>
void spring_forces(const SpringInputs& in, Index m, bool avx2, Scalar* out) {
  for_spring_blocks<D>(m, [&](Index begin, Index end) {
#if KINEMA_HAVE_AVX2_CLONES
    if (D == 2 && avx2) return avx2::spring_forces_2d(in, begin, end, out);
#endif
    (void)avx2;
    spring_forces_scalar<D>(in, begin, end, out);
  });
}

template <int D>
void spring_adjoint(const SpringInputs& in, const Scalar* lambda, Index m, bool avx2, Scalar* out,
                    Scalar* dk, Scalar* dL, Scalar* dc) {
  for_spring_blocks<D>(m, [&](Index begin, Index end) {
#if KINEMA_HAVE_AVX2_CLONES
    if (D == 2 && avx2) return avx2::spring_adjoint_2d(in, lambda, begin, end, out, dk, dL, dc);
#endif
    (void)avx2;
    spring_adjoint_scalar<D>(in, lambda, begin, end, out, dk, dL, dc);
  });
}

}  // namespace kinema::massspring
