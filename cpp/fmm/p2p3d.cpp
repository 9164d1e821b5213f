// The vectorised Laplace/Plummer P2P: an AVX2 version (behind a run-time CPU check, as
// core/simd.h describes) and a portable one with an exact square root.
#include "fmm/p2p3d.h"

#include "core/simd.h"

#include <algorithm>
#include <cstdlib>
#include <cstring>

#if KINEMA_HAVE_AVX2_CLONES
#include <immintrin.h>
#endif

namespace kinema::fmm3 {

namespace {

#if KINEMA_HAVE_AVX2_CLONES
#define KINEMA_AVX2_FMA __attribute__((target("avx2,fma")))

struct Sums {
  __m256d phi, gx, gy, gz, bad;
};

// One vector of four sources: the inverse distance by a float estimate and Newton steps
// y <- y (3/2 - s^2 y^2 / 2); left out: without softening the pairs at distance 0, with it the
// lanes of `self_lane` (the target itself; s^2 >= a^2 > 0 there). r^2 + a^2 outside float's
// normal range is flagged, and so, without softening, is a charged source other than the
// target itself at distance 0 (p2p_generic then counts it or, if r^2 underflowed, sums it).
template <bool Gradient, bool Softened>
KINEMA_AVX2_FMA inline void p2p_vector(__m256d dx, __m256d dy, __m256d dz, __m256d w, __m256d a2,
                                       int newton_steps, __m256d self_lane, Sums& acc) {
  const __m256d zero = _mm256_setzero_pd();
  const __m256d r2 = _mm256_fmadd_pd(dx, dx, _mm256_fmadd_pd(dy, dy, _mm256_mul_pd(dz, dz)));
  const __m256d s2 = _mm256_add_pd(r2, a2);
  __m256d live, safe;
  if constexpr (Softened) {
    live = _mm256_andnot_pd(self_lane, _mm256_castsi256_pd(_mm256_set1_epi64x(-1)));
    safe = s2;
  } else {
    live = _mm256_cmp_pd(r2, zero, _CMP_GT_OQ);
    safe = _mm256_blendv_pd(_mm256_set1_pd(1.0), s2, live);
  }
  const __m256d out_of_range = _mm256_or_pd(_mm256_cmp_pd(s2, _mm256_set1_pd(1e-36), _CMP_LT_OQ),
                                            _mm256_cmp_pd(s2, _mm256_set1_pd(1e36), _CMP_GT_OQ));
  if constexpr (Softened) {
    acc.bad = _mm256_or_pd(acc.bad, _mm256_and_pd(live, out_of_range));
  } else {
    const __m256d charged = _mm256_andnot_pd(self_lane, _mm256_cmp_pd(w, zero, _CMP_NEQ_UQ));
    acc.bad = _mm256_or_pd(acc.bad, _mm256_and_pd(_mm256_or_pd(live, charged), out_of_range));
  }
  __m256d inv = _mm256_cvtps_pd(_mm_rsqrt_ps(_mm256_cvtpd_ps(safe)));
  const __m256d hs = _mm256_mul_pd(_mm256_set1_pd(0.5), safe);
  for (int k = 0; k < newton_steps; ++k)
    inv = _mm256_mul_pd(inv, _mm256_fnmadd_pd(hs, _mm256_mul_pd(inv, inv), _mm256_set1_pd(1.5)));
  const __m256d wi = _mm256_and_pd(live, _mm256_mul_pd(w, inv));
  acc.phi = _mm256_add_pd(acc.phi, wi);
  if constexpr (Gradient) {
    const __m256d wi3 = _mm256_mul_pd(wi, _mm256_mul_pd(inv, inv));
    acc.gx = _mm256_fnmadd_pd(wi3, dx, acc.gx);
    acc.gy = _mm256_fnmadd_pd(wi3, dy, acc.gy);
    acc.gz = _mm256_fnmadd_pd(wi3, dz, acc.gz);
  }
}

// All ones in lane k of four (k = 0..3), zeros elsewhere (none for any other k).
KINEMA_AVX2_FMA inline __m256d lane_is(Index k) {
  return _mm256_castsi256_pd(_mm256_cmpeq_epi64(_mm256_set_epi64x(3, 2, 1, 0), _mm256_set1_epi64x(k)));
}

KINEMA_AVX2_FMA inline Scalar horizontal_sum(__m256d v) {
  alignas(32) Scalar t[4];
  _mm256_store_pd(t, v);
  return (t[0] + t[1]) + (t[2] + t[3]);
}

template <bool Gradient, bool Softened>
KINEMA_AVX2_FMA bool p2p_avx2(int newton_steps, Scalar a, Scalar x, Scalar y, Scalar z,
                              const Scalar* sx, const Scalar* sy, const Scalar* sz,
                              const Scalar* q, Index n, Scalar* out, Index self) {
  const __m256d vx = _mm256_set1_pd(x), vy = _mm256_set1_pd(y), vz = _mm256_set1_pd(z);
  const __m256d a2 = _mm256_set1_pd(a * a);
  Sums acc{_mm256_setzero_pd(), _mm256_setzero_pd(), _mm256_setzero_pd(), _mm256_setzero_pd(),
           _mm256_setzero_pd()};
  Index j = 0;
  for (; j + 4 <= n; j += 4) {
    p2p_vector<Gradient, Softened>(_mm256_sub_pd(vx, _mm256_loadu_pd(sx + j)),
                                   _mm256_sub_pd(vy, _mm256_loadu_pd(sy + j)),
                                   _mm256_sub_pd(vz, _mm256_loadu_pd(sz + j)), _mm256_loadu_pd(q + j),
                                   a2, newton_steps, lane_is(self - j), acc);
  }
  if (j < n) {
    // The tail padded with copies of the target (distance 0: masked out without softening) and
    // zero charges.
    alignas(32) Scalar bx[4] = {x, x, x, x}, by[4] = {y, y, y, y}, bz[4] = {z, z, z, z},
                       bq[4] = {0, 0, 0, 0};
    for (Index k = 0; j + k < n; ++k) bx[k] = sx[j + k], by[k] = sy[j + k], bz[k] = sz[j + k], bq[k] = q[j + k];
    p2p_vector<Gradient, Softened>(_mm256_sub_pd(vx, _mm256_load_pd(bx)), _mm256_sub_pd(vy, _mm256_load_pd(by)),
                                   _mm256_sub_pd(vz, _mm256_load_pd(bz)), _mm256_load_pd(bq), a2,
                                   newton_steps, lane_is(self - j), acc);
  }
  if (_mm256_movemask_pd(acc.bad) != 0) return false;
  out[0] += horizontal_sum(acc.phi);
  if constexpr (Gradient) {
    out[1] += horizontal_sum(acc.gx);
    out[2] += horizontal_sum(acc.gy);
    out[3] += horizontal_sum(acc.gz);
  }
  return true;
}

// Target i of block a against all of block b, four b points per vector: the inverse distance
// as in p2p_vector, q_b/r into i's sums and q_i/r into b's sums in memory. (Two targets per
// pass, sharing b's loads and stores, measured slower: the sixteen AVX2 registers spill.)
template <bool Gradient, int NewtonSteps>
KINEMA_AVX2_FMA inline void mutual_row(__m256d a2, const Scalar* const xa[3],
                                       const Scalar* qa, Index i, const Scalar* const xb[3],
                                       const Scalar* qb, Index nb, Scalar* const bout[4],
                                       Scalar* out_a, __m256d& smallest, __m256d& largest) {
  const __m256d zero = _mm256_setzero_pd(), three_halves = _mm256_set1_pd(1.5), half = _mm256_set1_pd(0.5);
  const __m256d vx = _mm256_set1_pd(xa[0][i]), vy = _mm256_set1_pd(xa[1][i]),
                vz = _mm256_set1_pd(xa[2][i]), qi = _mm256_set1_pd(qa[i]);
  __m256d phi = zero, gx = zero, gy = zero, gz = zero;
  for (Index j = 0; j < nb; j += 4) {
    const __m256d dx = _mm256_sub_pd(vx, _mm256_loadu_pd(xb[0] + j));
    const __m256d dy = _mm256_sub_pd(vy, _mm256_loadu_pd(xb[1] + j));
    const __m256d dz = _mm256_sub_pd(vz, _mm256_loadu_pd(xb[2] + j));
    const __m256d s2 = _mm256_add_pd(
        _mm256_fmadd_pd(dx, dx, _mm256_fmadd_pd(dy, dy, _mm256_mul_pd(dz, dz))), a2);
    smallest = _mm256_min_pd(smallest, s2);
    largest = _mm256_max_pd(largest, s2);
    __m256d inv = _mm256_cvtps_pd(_mm_rsqrt_ps(_mm256_cvtpd_ps(s2)));
    const __m256d hs = _mm256_mul_pd(half, s2);
    for (int k = 0; k < NewtonSteps; ++k)
      inv = _mm256_mul_pd(inv, _mm256_fnmadd_pd(hs, _mm256_mul_pd(inv, inv), three_halves));
    const __m256d qj = _mm256_loadu_pd(qb + j);
    phi = _mm256_fmadd_pd(qj, inv, phi);
    _mm256_storeu_pd(bout[0] + j, _mm256_fmadd_pd(qi, inv, _mm256_loadu_pd(bout[0] + j)));
    if constexpr (Gradient) {
      const __m256d inv3 = _mm256_mul_pd(inv, _mm256_mul_pd(inv, inv));
      const __m256d wj = _mm256_mul_pd(qj, inv3), wi = _mm256_mul_pd(qi, inv3);
      // grad at i of q_j / |x_i - x_j| is -q_j d / r^3 (d = x_i - x_j); at j, +q_i d / r^3.
      gx = _mm256_fnmadd_pd(wj, dx, gx);
      gy = _mm256_fnmadd_pd(wj, dy, gy);
      gz = _mm256_fnmadd_pd(wj, dz, gz);
      _mm256_storeu_pd(bout[1] + j, _mm256_fmadd_pd(wi, dx, _mm256_loadu_pd(bout[1] + j)));
      _mm256_storeu_pd(bout[2] + j, _mm256_fmadd_pd(wi, dy, _mm256_loadu_pd(bout[2] + j)));
      _mm256_storeu_pd(bout[3] + j, _mm256_fmadd_pd(wi, dz, _mm256_loadu_pd(bout[3] + j)));
    }
  }
  Scalar* o = out_a + i * (Gradient ? 4 : 1);
  o[0] += horizontal_sum(phi);
  if constexpr (Gradient) {
    o[1] += horizontal_sum(gx);
    o[2] += horizontal_sum(gy);
    o[3] += horizontal_sum(gz);
  }
}

template <bool Gradient, int NewtonSteps>
KINEMA_AVX2_FMA bool p2p_mutual_avx2(Scalar a, const Scalar* const xa[3],
                                     const Scalar* qa, Index na, const Scalar* const xb[3],
                                     const Scalar* qb, Index nb, Index stride_b, Scalar* out_a,
                                     Scalar* out_b) {
  const __m256d a2 = _mm256_set1_pd(a * a);
  // Points of disjoint leaves are distinct, so no pair is masked: the extremes of r^2 + a^2
  // are tracked instead (a coincident pair shows as a minimum of 0 and falls back).
  __m256d smallest = _mm256_set1_pd(1.0), largest = smallest;
  const Index g = Gradient ? stride_b : 0;  // without the gradient out_b holds phi only
  Scalar* const bout[4] = {out_b, out_b + g, out_b + 2 * g, out_b + 3 * g};
  for (Index i = 0; i < na; ++i)
    mutual_row<Gradient, NewtonSteps>(a2, xa, qa, i, xb, qb, nb, bout, out_a, smallest, largest);
  const __m256d bad = _mm256_or_pd(_mm256_cmp_pd(smallest, _mm256_set1_pd(1e-36), _CMP_LT_OQ),
                                   _mm256_cmp_pd(largest, _mm256_set1_pd(1e36), _CMP_GT_OQ));
  return _mm256_movemask_pd(bad) == 0;
}

// AVX-512 versions (eight sources per vector) where the CPU has AVX-512F: the inverse distance
// from the double-precision estimate rsqrt14 (relative error below 2^-14) refined by Newton
// steps, 1.5 e^2 each: one leaves 5.6e-9, two reach rounding. So `newton_steps` k (the float
// path's count, whose accuracy is 2e-7, 6e-14, rounding) maps to min(k, 2) steps here, at least
// as accurate. The last partial vector runs masked; r^2 + a^2 is range-checked as in AVX2 (the
// estimate itself covers the double range), so both paths hand the same leaves to the fallback.
#define KINEMA_AVX512 __attribute__((target("avx512f,avx2,fma")))

KINEMA_AVX512 inline __m512d inverse_sqrt512(__m512d s2, int steps) {
  __m512d inv = _mm512_rsqrt14_pd(s2);
  const __m512d hs = _mm512_mul_pd(_mm512_set1_pd(0.5), s2);
  for (int k = 0; k < steps; ++k)
    inv = _mm512_mul_pd(inv, _mm512_fnmadd_pd(hs, _mm512_mul_pd(inv, inv), _mm512_set1_pd(1.5)));
  return inv;
}

KINEMA_AVX512 inline __mmask8 tail_mask(Index left) {
  return left >= 8 ? __mmask8(0xFF) : __mmask8((1u << left) - 1);
}

template <bool Gradient, bool Softened>
KINEMA_AVX512 bool p2p_avx512(int steps, Scalar a, Scalar x, Scalar y, Scalar z,
                              const Scalar* sx, const Scalar* sy, const Scalar* sz,
                              const Scalar* q, Index n, Scalar* out, Index self) {
  const __m512d vx = _mm512_set1_pd(x), vy = _mm512_set1_pd(y), vz = _mm512_set1_pd(z);
  const __m512d a2 = _mm512_set1_pd(a * a), zero = _mm512_setzero_pd(), one = _mm512_set1_pd(1.0);
  __m512d phi = zero, gx = zero, gy = zero, gz = zero;
  __mmask8 bad = 0;
  for (Index j = 0; j < n; j += 8) {
    const __mmask8 m = tail_mask(n - j);
    // Masked-off lanes load the target itself: distance 0 and a zero charge.
    const __m512d dx = _mm512_sub_pd(vx, _mm512_mask_loadu_pd(vx, m, sx + j));
    const __m512d dy = _mm512_sub_pd(vy, _mm512_mask_loadu_pd(vy, m, sy + j));
    const __m512d dz = _mm512_sub_pd(vz, _mm512_mask_loadu_pd(vz, m, sz + j));
    const __m512d r2 = _mm512_fmadd_pd(dx, dx, _mm512_fmadd_pd(dy, dy, _mm512_mul_pd(dz, dz)));
    const __mmask8 live =
        Softened ? _mm512_cmpneq_epi64_mask(_mm512_set_epi64(7, 6, 5, 4, 3, 2, 1, 0), _mm512_set1_epi64(self - j))
                 : _mm512_cmp_pd_mask(r2, zero, _CMP_GT_OQ);
    const __m512d s2 = _mm512_add_pd(r2, a2);
    const __m512d qj = _mm512_maskz_loadu_pd(m, q + j);
    // Without softening a charged source other than the target at distance 0 is flagged too.
    const __mmask8 checked =
        Softened ? live
                 : __mmask8(live | (_mm512_cmp_pd_mask(qj, zero, _CMP_NEQ_UQ) &
                                    _mm512_cmpneq_epi64_mask(_mm512_set_epi64(7, 6, 5, 4, 3, 2, 1, 0),
                                                             _mm512_set1_epi64(self - j))));
    bad |= checked & (_mm512_cmp_pd_mask(s2, _mm512_set1_pd(1e-36), _CMP_LT_OQ) |
                      _mm512_cmp_pd_mask(s2, _mm512_set1_pd(1e36), _CMP_GT_OQ));
    const __m512d inv = inverse_sqrt512(_mm512_mask_blend_pd(live, one, s2), steps);
    const __m512d wi = _mm512_maskz_mul_pd(live, qj, inv);
    phi = _mm512_add_pd(phi, wi);
    if constexpr (Gradient) {
      const __m512d wi3 = _mm512_mul_pd(wi, _mm512_mul_pd(inv, inv));
      gx = _mm512_fnmadd_pd(wi3, dx, gx);
      gy = _mm512_fnmadd_pd(wi3, dy, gy);
      gz = _mm512_fnmadd_pd(wi3, dz, gz);
    }
  }
  if (bad) return false;
  out[0] += _mm512_reduce_add_pd(phi);
  if constexpr (Gradient) {
    out[1] += _mm512_reduce_add_pd(gx);
    out[2] += _mm512_reduce_add_pd(gy);
    out[3] += _mm512_reduce_add_pd(gz);
  }
  return true;
}

template <bool Gradient, int Steps>
KINEMA_AVX512 bool p2p_mutual_avx512(Scalar a, const Scalar* const xa[3], const Scalar* qa, Index na,
                                     const Scalar* const xb[3], const Scalar* qb, Index nb,
                                     Index stride_b, Scalar* out_a, Scalar* out_b) {
  const __m512d a2 = _mm512_set1_pd(a * a), zero = _mm512_setzero_pd();
  __m512d smallest = _mm512_set1_pd(1.0), largest = smallest;
  const Index g = Gradient ? stride_b : 0;
  Scalar* const bout[4] = {out_b, out_b + g, out_b + 2 * g, out_b + 3 * g};
  for (Index i = 0; i < na; ++i) {
    const __m512d vx = _mm512_set1_pd(xa[0][i]), vy = _mm512_set1_pd(xa[1][i]),
                  vz = _mm512_set1_pd(xa[2][i]), qi = _mm512_set1_pd(qa[i]);
    __m512d phi = zero, gx = zero, gy = zero, gz = zero;
    for (Index j = 0; j < nb; j += 8) {
      const __mmask8 m = tail_mask(nb - j);
      const __m512d dx = _mm512_sub_pd(vx, _mm512_maskz_loadu_pd(m, xb[0] + j));
      const __m512d dy = _mm512_sub_pd(vy, _mm512_maskz_loadu_pd(m, xb[1] + j));
      const __m512d dz = _mm512_sub_pd(vz, _mm512_maskz_loadu_pd(m, xb[2] + j));
      const __m512d s2 = _mm512_add_pd(
          _mm512_fmadd_pd(dx, dx, _mm512_fmadd_pd(dy, dy, _mm512_mul_pd(dz, dz))), a2);
      smallest = _mm512_mask_min_pd(smallest, m, smallest, s2);
      largest = _mm512_mask_max_pd(largest, m, largest, s2);
      const __m512d inv = inverse_sqrt512(_mm512_mask_blend_pd(m, _mm512_set1_pd(1.0), s2), Steps);
      const __m512d qj = _mm512_maskz_loadu_pd(m, qb + j);
      phi = _mm512_fmadd_pd(qj, inv, phi);
      _mm512_mask_storeu_pd(bout[0] + j, m, _mm512_fmadd_pd(qi, inv, _mm512_maskz_loadu_pd(m, bout[0] + j)));
      if constexpr (Gradient) {
        const __m512d inv3 = _mm512_mul_pd(inv, _mm512_mul_pd(inv, inv));
        const __m512d wj = _mm512_mul_pd(qj, inv3), wi = _mm512_mul_pd(qi, inv3);
        gx = _mm512_fnmadd_pd(wj, dx, gx);
        gy = _mm512_fnmadd_pd(wj, dy, gy);
        gz = _mm512_fnmadd_pd(wj, dz, gz);
        _mm512_mask_storeu_pd(bout[1] + j, m, _mm512_fmadd_pd(wi, dx, _mm512_maskz_loadu_pd(m, bout[1] + j)));
        _mm512_mask_storeu_pd(bout[2] + j, m, _mm512_fmadd_pd(wi, dy, _mm512_maskz_loadu_pd(m, bout[2] + j)));
        _mm512_mask_storeu_pd(bout[3] + j, m, _mm512_fmadd_pd(wi, dz, _mm512_maskz_loadu_pd(m, bout[3] + j)));
      }
    }
    Scalar* o = out_a + i * (Gradient ? 4 : 1);
    o[0] += _mm512_reduce_add_pd(phi);
    if constexpr (Gradient) {
      o[1] += _mm512_reduce_add_pd(gx);
      o[2] += _mm512_reduce_add_pd(gy);
      o[3] += _mm512_reduce_add_pd(gz);
    }
  }
  const __mmask8 bad = _mm512_cmp_pd_mask(smallest, _mm512_set1_pd(1e-36), _CMP_LT_OQ) |
                       _mm512_cmp_pd_mask(largest, _mm512_set1_pd(1e36), _CMP_GT_OQ);
  return bad == 0;
}

bool use_avx512() {
  const char* choice = std::getenv("KINEMA_SIMD");
  if (choice != nullptr && (std::strcmp(choice, "baseline") == 0 || std::strcmp(choice, "avx2") == 0)) return false;
  return __builtin_cpu_supports("avx512f");
}
#endif

}  // namespace

bool use_avx512_kernels() {
#if KINEMA_HAVE_AVX2_CLONES
  return use_avx2() && use_avx512();
#else
  return false;
#endif
}

bool p2p_mutual_available() {
#if KINEMA_HAVE_AVX2_CLONES
  return use_avx2();
#else
  return false;
#endif
}

bool p2p_mutual(bool gradient, int newton_steps, Scalar a, const Scalar* const xa[3],
                const Scalar* qa, Index na, const Scalar* const xb[3], const Scalar* qb, Index nb,
                Index stride_b, Scalar* out_a, Scalar* out_b) {
#if KINEMA_HAVE_AVX2_CLONES
  static const bool avx2 = use_avx2(), avx512 = avx2 && use_avx512();
  if (avx512) {
    using Kernel = bool (*)(Scalar, const Scalar* const*, const Scalar*, Index, const Scalar* const*,
                            const Scalar*, Index, Index, Scalar*, Scalar*);
    static constexpr Kernel kernels[2][2] = {
        {p2p_mutual_avx512<false, 1>, p2p_mutual_avx512<false, 2>},
        {p2p_mutual_avx512<true, 1>, p2p_mutual_avx512<true, 2>}};
    return kernels[gradient][std::clamp(newton_steps, 1, 2) - 1](a, xa, qa, na, xb, qb, nb, stride_b, out_a, out_b);
  }
  // The Newton steps as a template argument: the inner loop unrolled (1 to 3 steps).
  if (avx2) {
    using Kernel = bool (*)(Scalar, const Scalar* const*, const Scalar*, Index, const Scalar* const*,
                            const Scalar*, Index, Index, Scalar*, Scalar*);
    static constexpr Kernel kernels[2][3] = {
        {p2p_mutual_avx2<false, 1>, p2p_mutual_avx2<false, 2>, p2p_mutual_avx2<false, 3>},
        {p2p_mutual_avx2<true, 1>, p2p_mutual_avx2<true, 2>, p2p_mutual_avx2<true, 3>}};
    return kernels[gradient][std::clamp(newton_steps, 1, 3) - 1](a, xa, qa, na, xb, qb, nb, stride_b, out_a, out_b);
  }
#endif
  (void)gradient, (void)newton_steps, (void)a, (void)xa, (void)qa, (void)na, (void)xb, (void)qb,
      (void)nb, (void)stride_b, (void)out_a, (void)out_b;
  return false;
}

bool p2p_fast(bool gradient, int newton_steps, Scalar a, Scalar x, Scalar y, Scalar z,
              const Scalar* sx, const Scalar* sy, const Scalar* sz, const Scalar* q, Index n,
              Scalar* out, Index self) {
#if KINEMA_HAVE_AVX2_CLONES
  static const bool avx2 = use_avx2(), avx512 = avx2 && use_avx512();
  using Kernel = bool (*)(int, Scalar, Scalar, Scalar, Scalar, const Scalar*, const Scalar*,
                          const Scalar*, const Scalar*, Index, Scalar*, Index);
  if (avx512) {
    static constexpr Kernel kernels[2][2] = {{p2p_avx512<false, false>, p2p_avx512<false, true>},
                                             {p2p_avx512<true, false>, p2p_avx512<true, true>}};
    return kernels[gradient][a > 0](std::clamp(newton_steps, 1, 2), a, x, y, z, sx, sy, sz, q, n, out, self);
  }
  if (avx2) {
    static constexpr Kernel kernels[2][2] = {{p2p_avx2<false, false>, p2p_avx2<false, true>},
                                             {p2p_avx2<true, false>, p2p_avx2<true, true>}};
    return kernels[gradient][a > 0](newton_steps, a, x, y, z, sx, sy, sz, q, n, out, self);
  }
#endif
  // Portable build: the caller's p2p_generic (which also counts coincident pairs).
  (void)gradient, (void)newton_steps, (void)a, (void)x, (void)y, (void)z, (void)sx, (void)sy,
      (void)sz, (void)q, (void)n, (void)out, (void)self;
  return false;
}

}  // namespace kinema::fmm3
