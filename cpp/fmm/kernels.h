// The translation operators of the 2D Laplace fast multipole method in complex form
// (Greengard & Rokhlin 1987, J. Comput. Phys. 73:325):
//   phi(z) = Re f(z),  f(z) = sum_j q_j log(z - z_j),  grad phi = (Re f', -Im f') = conj(f'(z)).
// Expansions are stored scaled by their box's half-width h, so that every coefficient is O(1)
// whatever the depth of the tree:
//   multipole about c:  f(z) = a_0 log(z - c) + sum_{k>=1} a_k (h / (z - c))^k,  a_0 = sum_j q_j;
//   local about c:      f(z) = sum_{l>=0} b_l ((z - c) / h)^l.
// Only Re f is physical, so the branches of the logarithms never matter: constant terms keep
// just their real part. Coefficient k of an expansion of order p sits at re[k], im[k], k <= p.
#pragma once

#include <cmath>
#include <cstdint>
#include <vector>

#include "core/types.h"

namespace kinema::fmm {

// Natural logarithm of a positive normal double, in branch-free arithmetic so that loops over
// it vectorise (libm's log does not). x = 2^e m with m in [1, 2), and
// log x = (e + 1/2) log 2 + 2 atanh(s),  s = (m - sqrt2)/(m + sqrt2),  |s| < 0.172,
// the series summed to s^23 (below 1e-17); the absolute error is a few 1e-16.
inline Scalar fast_log(Scalar x) {
  const auto bits = __builtin_bit_cast(std::uint64_t, x);
  // The biased exponent converted to double by the 2^52 trick (packed int64 -> double
  // conversion does not exist before AVX-512, and would stop the loop from vectorising).
  const std::uint64_t biased = (bits >> 52) | 0x4330000000000000ULL;
  const Scalar e = __builtin_bit_cast(Scalar, biased) - (4503599627370496.0 + 1023.0);
  const std::uint64_t mantissa = (bits & 0x000fffffffffffffULL) | 0x3ff0000000000000ULL;
  const Scalar m = __builtin_bit_cast(Scalar, mantissa);
  const Scalar sqrt2 = 1.4142135623730951;
  const Scalar s = (m - sqrt2) / (m + sqrt2);
  const Scalar s2 = s * s;
  Scalar poly = 1.0 / 23;
  poly = poly * s2 + 1.0 / 21;
  poly = poly * s2 + 1.0 / 19;
  poly = poly * s2 + 1.0 / 17;
  poly = poly * s2 + 1.0 / 15;
  poly = poly * s2 + 1.0 / 13;
  poly = poly * s2 + 1.0 / 11;
  poly = poly * s2 + 1.0 / 9;
  poly = poly * s2 + 1.0 / 7;
  poly = poly * s2 + 1.0 / 5;
  poly = poly * s2 + 1.0 / 3;
  const Scalar ln2_hi = 6.93147180369123816490e-01, ln2_lo = 1.90821492927058770002e-10;
  const Scalar k = e + 0.5;
  return k * ln2_hi + (k * ln2_lo + 2.0 * s + 2.0 * s * s2 * poly);
}

// Smallest r^2 handed to fast_log; closer pairs (subnormal r^2) take the libm path.
constexpr Scalar kMinNormal = 2.2250738585072014e-308;

// Accumulates, at target (x, y), the fields of sources [0, n) (coordinates sx, sy, charges q):
// phi += sum q log r, grad += sum q (x - y_j) / r^2. Pairs at distance 0 are left out (the
// self term, and duplicates of it). Returns false if some pair was too close for fast_log, in
// which case the caller redoes the target with p2p_exact.
template <bool Gradient>
inline bool p2p(Scalar x, Scalar y, const Scalar* sx, const Scalar* sy, const Scalar* q, Index n,
                Scalar& phi, Scalar& gx, Scalar& gy) {
  Scalar sum_log = 0, sum_x = 0, sum_y = 0, tiny = 0;
#pragma omp simd reduction(+ : sum_log, sum_x, sum_y, tiny)
  for (Index j = 0; j < n; ++j) {
    const Scalar dx = x - sx[j], dy = y - sy[j];
    const Scalar r2 = dx * dx + dy * dy;
    const Scalar ok = static_cast<Scalar>(r2 >= kMinNormal);
    // distinct points whose r^2 is subnormal or underflows to 0 need the exact path
    tiny += (1.0 - ok) * (std::abs(dx) + std::abs(dy));
    const Scalar safe = r2 + (1.0 - ok);  // 1 where the pair is left out
    const Scalar w = ok * q[j];
    sum_log += w * fast_log(safe);
    if constexpr (Gradient) {
      const Scalar inv = w / safe;
      sum_x += inv * dx;
      sum_y += inv * dy;
    }
  }
  phi += 0.5 * sum_log;
  if constexpr (Gradient) {
    gx += sum_x;
    gy += sum_y;
  }
  return tiny == 0;
}

// The same sum with libm's log, correct for any nonzero distance.
template <bool Gradient>
inline void p2p_exact(Scalar x, Scalar y, const Scalar* sx, const Scalar* sy, const Scalar* q,
                      Index n, Scalar& phi, Scalar& gx, Scalar& gy) {
  for (Index j = 0; j < n; ++j) {
    const Scalar dx = x - sx[j], dy = y - sy[j];
    const Scalar r = std::hypot(dx, dy);
    if (r == 0) continue;
    phi += q[j] * std::log(r);
    if constexpr (Gradient) {
      gx += q[j] * (dx / r) / r;
      gy += q[j] * (dy / r) / r;
    }
  }
}

// Tables shared by the translations of one expansion order p.
struct Operators {
  explicit Operators(int p);
  int p;
  // m2l[(l-1)*p + (k-1)] = C(k+l-1, l), for l, k in 1..p (multipole k -> local l).
  std::vector<Scalar> m2l;
  // m2m[l*(p+1) + k] = C(l-1, k-1), for 1 <= k <= l <= p.
  std::vector<Scalar> m2m;
  // 1/l for l in 1..p (entry 0 unused).
  std::vector<Scalar> inverse;
};

// P2M: a_0 = sum q, a_k = -sum q ((z_j - c)/h)^k / k.
void p2m(const Operators& op, Scalar cx, Scalar cy, Scalar h, const Scalar* sx, const Scalar* sy,
         const Scalar* q, Index n, Scalar* re, Scalar* im);

// M2M: adds the child's multipole (centre c1, half-width h1) to the parent's (c0, h0).
void m2m(const Operators& op, const Scalar* re1, const Scalar* im1, Scalar c1x, Scalar c1y,
         Scalar h1, Scalar* re0, Scalar* im0, Scalar c0x, Scalar c0y, Scalar h0);

// M2L: adds the local expansion about (ct, ht) of a multipole about (cs, hs); needs
// |ct - cs| > (hs + ht) sqrt(2) for convergence, and twice that for speed.
void m2l(const Operators& op, const Scalar* re_s, const Scalar* im_s, Scalar csx, Scalar csy,
         Scalar hs, Scalar* re_t, Scalar* im_t, Scalar ctx, Scalar cty, Scalar ht);

// L2L: adds the parent's local expansion (c0, h0) re-centred on the child (c1, h1).
void l2l(const Operators& op, const Scalar* re0, const Scalar* im0, Scalar c0x, Scalar c0y,
         Scalar h0, Scalar* re1, Scalar* im1, Scalar c1x, Scalar c1y, Scalar h1);

// P2L: adds the local expansion about (c, h) of the sources (all outside the box's disc).
void p2l(const Operators& op, Scalar cx, Scalar cy, Scalar h, const Scalar* sx, const Scalar* sy,
         const Scalar* q, Index n, Scalar* re, Scalar* im);

// L2P: evaluates the local expansion at target (x, y), adding to phi (and the gradient).
template <bool Gradient>
inline void l2p(int p, const Scalar* re, const Scalar* im, Scalar cx, Scalar cy, Scalar h,
                Scalar x, Scalar y, Scalar& phi, Scalar& gx, Scalar& gy) {
  const Scalar inv_h = 1.0 / h;
  const Scalar vr = (x - cx) * inv_h, vi = (y - cy) * inv_h;
  Scalar fr = re[p], fi = im[p];  // Horner for f(v)
  Scalar dr = p * re[p], di = p * im[p];  // and for sum l b_l v^(l-1)
  for (int l = p - 1; l >= 0; --l) {
    const Scalar tr = fr * vr - fi * vi + re[l];
    fi = fr * vi + fi * vr + im[l];
    fr = tr;
    if (Gradient && l >= 1) {
      const Scalar ur = dr * vr - di * vi + l * re[l];
      di = dr * vi + di * vr + l * im[l];
      dr = ur;
    }
  }
  phi += fr;
  if constexpr (Gradient) {
    // f'(z) = (1/h) sum l b_l v^(l-1); grad = (Re f', -Im f').
    gx += dr * inv_h;
    gy -= di * inv_h;
  }
}

// M2P: evaluates the multipole about (c, h) at a target (x, y) outside its box's disc.
template <bool Gradient>
inline void m2p(int p, const Scalar* re, const Scalar* im, Scalar cx, Scalar cy, Scalar h,
                Scalar x, Scalar y, Scalar& phi, Scalar& gx, Scalar& gy) {
  const Scalar zr = x - cx, zi = y - cy;
  const Scalar r2 = zr * zr + zi * zi;
  // w = h / (z - c)
  const Scalar wr = h * zr / r2, wi = -h * zi / r2;
  Scalar sr = 0, si = 0, kr = 0, ki = 0;  // S = sum a_k w^k, K = sum k a_k w^k (Horner, then * w)
  for (int k = p; k >= 1; --k) {
    const Scalar tr = sr * wr - si * wi + re[k];
    si = sr * wi + si * wr + im[k];
    sr = tr;
    if constexpr (Gradient) {
      const Scalar ur = kr * wr - ki * wi + k * re[k];
      ki = kr * wi + ki * wr + k * im[k];
      kr = ur;
    }
  }
  phi += re[0] * 0.5 * std::log(r2) + (sr * wr - si * wi);
  if constexpr (Gradient) {
    // f' = (a_0 - sum k a_k w^k) / (z - c)
    const Scalar Kr = kr * wr - ki * wi, Ki = kr * wi + ki * wr;
    const Scalar nr = re[0] - Kr, ni = -Ki;
    const Scalar fr = (nr * zr + ni * zi) / r2, fi = (ni * zr - nr * zi) / r2;
    gx += fr;
    gy -= fi;
  }
}

}  // namespace kinema::fmm
