// Per-particle SPH math: the cubic spline kernel of the course notes (Koschier, Bender,
// Solenthaler and Teschner, "Smoothed Particle Hydrodynamics Techniques for the Physics Based
// Simulation of Fluids and Solids", Eurographics tutorial 2019, eq. 4), with support radius h:
//   W(q) = sigma_d * { 6 (q^3 - q^2) + 1  (0 <= q <= 1/2);  2 (1 - q)^3  (1/2 < q <= 1);  0 },
//   q = r / h,  sigma_2 = 40 / (7 pi h^2),  sigma_3 = 8 / (pi h^3),
// its radial derivatives and gradient, and the symmetric pair terms the solvers share.
#pragma once

#include <Eigen/Core>
#include <cmath>
#include <cstdint>

#include "core/simd.h"
#include "core/types.h"

#if KINEMA_HAVE_AVX2_CLONES
#include <immintrin.h>
#endif

namespace kinema::sph {

constexpr Scalar kPi = 3.14159265358979323846;

// Normalisation sigma_d of the cubic spline in d dimensions for support radius h.
inline Scalar kernel_sigma(int d, Scalar h) {
  return d == 2 ? 40.0 / (7.0 * kPi * h * h) : 8.0 / (kPi * h * h * h);
}

// W(r, h) for d = 2 or 3.
inline Scalar kernel_w(Scalar r, Scalar h, int d) {
  const Scalar q = r / h;
  if (q >= 1 || q < 0) return 0;
  const Scalar s = kernel_sigma(d, h);
  if (q <= 0.5) return s * (6 * (q * q * q - q * q) + 1);
  const Scalar t = 1 - q;
  return s * 2 * t * t * t;
}

// dW/dr.
inline Scalar kernel_dw(Scalar r, Scalar h, int d) {
  const Scalar q = r / h;
  if (q >= 1 || q < 0) return 0;
  const Scalar s = kernel_sigma(d, h) / h;
  if (q <= 0.5) return s * 6 * (3 * q * q - 2 * q);
  const Scalar t = 1 - q;
  return -s * 6 * t * t;
}

// d^2W/dr^2.
inline Scalar kernel_d2w(Scalar r, Scalar h, int d) {
  const Scalar q = r / h;
  if (q >= 1 || q < 0) return 0;
  const Scalar s = kernel_sigma(d, h) / (h * h);
  if (q <= 0.5) return s * 6 * (6 * q - 2);
  return s * 12 * (1 - q);
}

// The kernel with its constants precomputed, as the solvers' inner loops use it.
template <int D>
struct CubicSpline {
  using Vec = Eigen::Matrix<Scalar, D, 1>;

  explicit CubicSpline(Scalar h_) : h(h_), inv_h(1 / h_), sigma(kernel_sigma(D, h_)) {}

  // Both pieces are evaluated and one is selected, so that the inner loops do not branch on
  // q <= 1/2.
  Scalar w(Scalar r) const {
    const Scalar q = r * inv_h;
    const Scalar t = 1 - q;
    const Scalar inner = sigma * (6 * (q * q * q - q * q) + 1);
    const Scalar outer = sigma * 2 * t * t * t;
    return q >= 1 ? 0 : q <= 0.5 ? inner : outer;
  }
  Scalar w0() const { return sigma; }

  // (dW/dr) / r at distance r, so that grad_i W(x_i - x_j) = grad_factor(r) (x_i - x_j); zero
  // at r = 0, where the direction is undefined, and outside the support.
  Scalar grad_factor(Scalar r) const {
    if (r <= 0) return 0;
    const Scalar q = r * inv_h;
    const Scalar inner = sigma * inv_h * 6 * (3 * q * q - 2 * q);
    const Scalar outer = -sigma * inv_h * 6 * (1 - q) * (1 - q);
    return q >= 1 ? 0 : (q <= 0.5 ? inner : outer) / r;
  }

  // grad_i W(x_i - x_j) for xij = x_i - x_j.
  Vec grad(const Vec& xij) const { return grad_factor(std::sqrt(xij.squaredNorm())) * xij; }

  // r = sqrt(r2), w(r) and grad_factor(r) of `count` squared distances (the kernel pass's
  // chunks of entries), one at a time; kernel_values_avx2 below gives the same bits.
  void values(const Scalar* r2, int count, Scalar* r, Scalar* w_out, Scalar* dw_out) const {
    for (int e = 0; e < count; ++e) {
      r[e] = std::sqrt(r2[e]);
      w_out[e] = w(r[e]);
      dw_out[e] = grad_factor(r[e]);
    }
  }

  Scalar h, inv_h, sigma;
};

#if KINEMA_HAVE_AVX2_CLONES
// CubicSpline::values four distances at a time: each lane does CubicSpline::w's and
// grad_factor's multiplications, additions, square root and division in their order (no FMA),
// and selects as they branch, so the results are bitwise theirs. The square root and the
// division, one per entry each, were the kernel pass's costliest instructions as scalars.
template <int D>
KINEMA_TARGET_AVX2 void kernel_values_avx2(const CubicSpline<D>& W, const Scalar* r2, int count, Scalar* r, Scalar* w_out,
                                           Scalar* dw_out) {
  const Scalar inv_h = W.inv_h, sigma = W.sigma;
  const __m256d one = _mm256_set1_pd(1), half = _mm256_set1_pd(0.5), zero = _mm256_setzero_pd();
  const __m256d six = _mm256_set1_pd(6), two = _mm256_set1_pd(2), three = _mm256_set1_pd(3);
  const __m256d vinv_h = _mm256_set1_pd(inv_h), vsigma = _mm256_set1_pd(sigma);
  const __m256d sigma2 = _mm256_set1_pd(sigma * 2);
  const __m256d c_inner = _mm256_set1_pd(sigma * inv_h * 6), c_outer = _mm256_set1_pd(-sigma * inv_h * 6);
  int e = 0;
  for (; e + 4 <= count; e += 4) {
    const __m256d re = _mm256_sqrt_pd(_mm256_loadu_pd(r2 + e));
    const __m256d q = _mm256_mul_pd(re, vinv_h);
    const __m256d t = _mm256_sub_pd(one, q);
    const __m256d qq = _mm256_mul_pd(q, q);
    // w: sigma (6 (q^3 - q^2) + 1) or sigma 2 t^3.
    const __m256d w_in =
        _mm256_mul_pd(vsigma, _mm256_add_pd(_mm256_mul_pd(six, _mm256_sub_pd(_mm256_mul_pd(qq, q), qq)), one));
    const __m256d w_out4 = _mm256_mul_pd(_mm256_mul_pd(_mm256_mul_pd(sigma2, t), t), t);
    const __m256d inner_mask = _mm256_cmp_pd(q, half, _CMP_LE_OQ);
    const __m256d outside = _mm256_cmp_pd(q, one, _CMP_GE_OQ);
    const __m256d w = _mm256_blendv_pd(_mm256_blendv_pd(w_out4, w_in, inner_mask), zero, outside);
    // grad_factor: (sigma / h) 6 (3 q^2 - 2 q) or -(sigma / h) 6 (1 - q)^2, over r.
    const __m256d g_in = _mm256_mul_pd(c_inner, _mm256_sub_pd(_mm256_mul_pd(_mm256_mul_pd(three, q), q), _mm256_mul_pd(two, q)));
    const __m256d g_out = _mm256_mul_pd(_mm256_mul_pd(c_outer, t), t);
    const __m256d g = _mm256_div_pd(_mm256_blendv_pd(g_out, g_in, inner_mask), re);
    const __m256d none = _mm256_or_pd(outside, _mm256_cmp_pd(re, zero, _CMP_LE_OQ));
    _mm256_storeu_pd(r + e, re);
    _mm256_storeu_pd(w_out + e, w);
    _mm256_storeu_pd(dw_out + e, _mm256_blendv_pd(g, zero, none));
  }
  for (; e < count; ++e) {
    r[e] = std::sqrt(r2[e]);
    w_out[e] = W.w(r[e]);
    dw_out[e] = W.grad_factor(r[e]);
  }
}
#endif

// Tait's equation of state (Becker and Teschner 2007, eq. 6), p = B ((rho/rho0)^gamma - 1),
// with negative pressures clamped to zero: they would pull free-surface particles into
// clumps (tensile instability).
inline Scalar tait_pressure(Scalar rho, Scalar rho0, Scalar B, Scalar gamma) {
  const Scalar ratio = rho / rho0;
  if (ratio <= 1) return 0;
  return B * (std::pow(ratio, gamma) - 1);
}

// Laminar viscosity term of Morris et al. 1997 in the form of Monaghan 2005 / Koschier et al.
// 2019 eq. 33: the acceleration of i from j for kinematic viscosity nu,
//   2 (d + 2) nu (m_j / rho_j) (v_ij . x_ij) / (|x_ij|^2 + 0.01 h^2) grad W_ij.
template <int D>
inline Eigen::Matrix<Scalar, D, 1> viscosity_term(const Eigen::Matrix<Scalar, D, 1>& xij,
                                                 const Eigen::Matrix<Scalar, D, 1>& vij,
                                                 const Eigen::Matrix<Scalar, D, 1>& grad_w,
                                                 Scalar volume_j, Scalar nu, Scalar h) {
  const Scalar c = 2 * (D + 2) * nu * volume_j * vij.dot(xij) / (xij.squaredNorm() + 0.01 * h * h);
  return c * grad_w;
}

// Sums over one row of a neighbour list, the solvers' light passes (DFSPH's density rates and
// velocity corrections, WCSPH's pressure force). A row is the entries k in [begin, end) of a list
// (list[k] = j) whose kernel gradients g_k = grad_i W_ij are stored as D floats at grads + D k,
// and one float more must be readable after the list's last gradient (the AVX2 versions load an
// entry's gradient as 4 floats and drop the fourth):
//   row_dot:      sum_k v_j . g_k            (v: D doubles per particle)
//   row_weighted: sum_k (c_i + c_j) g_k      (c: one double per particle, c_i one for the row;
//                                             D results into out)
// Entry e of the row goes into partial sum e mod 4 (four independent add chains), the partials
// are combined as (p0 + p1) + (p2 + p3) per component, and row_dot's components as (x + y) + z.
// The AVX2 versions (3D) hold an entry's components in the lanes of a 4-double vector and do the
// same multiplications and additions in the same order, without FMA: their results are bitwise
// equal to these.
template <int D, class Term>
KINEMA_ALWAYS_INLINE void row_partials(Index begin, Index end, Term&& term, Scalar* sum) {
  Scalar p0[D] = {}, p1[D] = {}, p2[D] = {}, p3[D] = {};
  Index k = begin;
  for (; k + 4 <= end; k += 4) {
    term(k, p0);
    term(k + 1, p1);
    term(k + 2, p2);
    term(k + 3, p3);
  }
  if (k < end) term(k, p0);
  if (k + 1 < end) term(k + 1, p1);
  if (k + 2 < end) term(k + 2, p2);
  for (int a = 0; a < D; ++a) sum[a] = (p0[a] + p1[a]) + (p2[a] + p3[a]);
}

template <int D>
inline Scalar row_dot(const std::int32_t* list, const float* grads, Index begin, Index end, const Scalar* v) {
  Scalar sum[D];
  row_partials<D>(begin, end, [&](Index k, Scalar* p) {
    const Scalar* vj = v + Index{list[k]} * D;
    for (int a = 0; a < D; ++a) p[a] += vj[a] * static_cast<Scalar>(grads[k * D + a]);
  }, sum);
  return D == 3 ? (sum[0] + sum[1]) + sum[D - 1] : sum[0] + sum[1];
}

template <int D>
inline void row_weighted(const std::int32_t* list, const float* grads, Index begin, Index end, Scalar ci,
                         const Scalar* c, Scalar* out) {
  row_partials<D>(begin, end, [&](Index k, Scalar* p) {
    const Scalar cj = ci + c[list[k]];
    for (int a = 0; a < D; ++a) p[a] += cj * static_cast<Scalar>(grads[k * D + a]);
  }, out);
}

#if KINEMA_HAVE_AVX2_CLONES
namespace detail {

// (Masked loads would spare the padding float but run at half the speed on AMD Zen 3.)
KINEMA_TARGET_AVX2 KINEMA_ALWAYS_INLINE __m256d load_grad3(const float* grads, Index k) {
  return _mm256_cvtps_pd(_mm_loadu_ps(grads + 3 * k));
}
// (v_j, v_j + 1, v_j + 2, 0) without reading past v_j.
KINEMA_TARGET_AVX2 KINEMA_ALWAYS_INLINE __m256d load_vec3(const Scalar* v, Index j) {
  return _mm256_insertf128_pd(_mm256_castpd128_pd256(_mm_loadu_pd(v + 3 * j)), _mm_load_sd(v + 3 * j + 2), 1);
}
// One entry's term: p += a * g_k, lane-wise.
KINEMA_TARGET_AVX2 KINEMA_ALWAYS_INLINE __m256d add_term(__m256d p, __m256d a, const float* grads, Index k) {
  return _mm256_add_pd(p, _mm256_mul_pd(a, load_grad3(grads, k)));
}

// row_partials of 4-lane terms: term(k) is entry k's vector.
template <class Term>
KINEMA_TARGET_AVX2 KINEMA_ALWAYS_INLINE void row_partials_avx2(const float* grads, Index begin, Index end,
                                                              Term&& term, Scalar* sum4) {
  __m256d p0 = _mm256_setzero_pd(), p1 = p0, p2 = p0, p3 = p0;
  Index k = begin;
  for (; k + 4 <= end; k += 4) {
    p0 = add_term(p0, term(k), grads, k);
    p1 = add_term(p1, term(k + 1), grads, k + 1);
    p2 = add_term(p2, term(k + 2), grads, k + 2);
    p3 = add_term(p3, term(k + 3), grads, k + 3);
  }
  if (k < end) p0 = add_term(p0, term(k), grads, k);
  if (k + 1 < end) p1 = add_term(p1, term(k + 1), grads, k + 1);
  if (k + 2 < end) p2 = add_term(p2, term(k + 2), grads, k + 2);
  _mm256_storeu_pd(sum4, _mm256_add_pd(_mm256_add_pd(p0, p1), _mm256_add_pd(p2, p3)));
}

// Entry k's factor: v_j (row_dot) or c_j broadcast (row_weighted). (Function objects, not
// lambdas: a lambda would not inherit the AVX2 target.)
struct VelocityOf {
  const std::int32_t* list;
  const Scalar* v;
  KINEMA_TARGET_AVX2 KINEMA_ALWAYS_INLINE __m256d operator()(Index k) const { return load_vec3(v, list[k]); }
};
// v_j from velocities stored 4 doubles per particle, the fourth 0: one load.
struct Velocity4Of {
  const std::int32_t* list;
  const Scalar* v4;
  KINEMA_TARGET_AVX2 KINEMA_ALWAYS_INLINE __m256d operator()(Index k) const { return _mm256_loadu_pd(v4 + 4 * Index{list[k]}); }
};
struct WeightOf {
  const std::int32_t* list;
  Scalar ci;
  const Scalar* c;
  KINEMA_TARGET_AVX2 KINEMA_ALWAYS_INLINE __m256d operator()(Index k) const { return _mm256_set1_pd(ci + c[list[k]]); }
};

}  // namespace detail

KINEMA_TARGET_AVX2 inline Scalar row_dot_avx2(const std::int32_t* list, const float* grads, Index begin, Index end,
                                              const Scalar* v) {
  alignas(32) Scalar sum[4];
  detail::row_partials_avx2(grads, begin, end, detail::VelocityOf{list, v}, sum);
  return (sum[0] + sum[1]) + sum[2];
}

// row_dot_avx2 over velocities stored 4 doubles per particle with the fourth 0 (v4): the same
// lanes as load_vec3 gives, in one load instead of three operations (the light passes are bound
// by the instructions around their gathers), so the same result bit for bit.
KINEMA_TARGET_AVX2 inline Scalar row_dot4_avx2(const std::int32_t* list, const float* grads, Index begin, Index end,
                                               const Scalar* v4) {
  alignas(32) Scalar sum[4];
  detail::row_partials_avx2(grads, begin, end, detail::Velocity4Of{list, v4}, sum);
  return (sum[0] + sum[1]) + sum[2];
}

KINEMA_TARGET_AVX2 inline void row_weighted_avx2(const std::int32_t* list, const float* grads, Index begin,
                                                 Index end, Scalar ci, const Scalar* c, Scalar* out) {
  alignas(32) Scalar sum[4];
  detail::row_partials_avx2(grads, begin, end, detail::WeightOf{list, ci, c}, sum);
  for (int a = 0; a < 3; ++a) out[a] = sum[a];
}
#endif

// The row sums of one dimension, AVX2 (3D, where the CPU has it and KINEMA_SIMD is not
// "baseline", see core/simd.h) or the baseline.
template <int D>
struct RowSums {
  Scalar (*dot)(const std::int32_t*, const float*, Index, Index, const Scalar*) = row_dot<D>;
  void (*weighted)(const std::int32_t*, const float*, Index, Index, Scalar, const Scalar*, Scalar*) = row_weighted<D>;
  // row_dot over velocities padded to 4 doubles per particle (AVX2, 3D), else null.
  Scalar (*dot4)(const std::int32_t*, const float*, Index, Index, const Scalar*) = nullptr;
  bool avx2 = false;

  static RowSums choose(bool avx2) {
    RowSums rows;
#if KINEMA_HAVE_AVX2_CLONES
    if constexpr (D == 3) {
      if (avx2 && cpu_has_avx2()) {
        rows.dot = row_dot_avx2;
        rows.weighted = row_weighted_avx2;
        rows.dot4 = row_dot4_avx2;
        rows.avx2 = true;
      }
    }
#endif
    return rows;
  }
};

}  // namespace kinema::sph
