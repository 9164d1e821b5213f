// Direct (P2P) sums of the 3D kernels, near field of the FMM and the exact reference:
//   phi(x) = sum_j q_j f(|x - y_j|),  grad phi = sum_j q_j f'(r)/r (x - y_j),
//   hess phi = sum_j q_j [f'/r I + (f'' - f'/r)/r^2 (x - y_j)(x - y_j)^T],
// for f = 1/r (Laplace), 1/sqrt(r^2 + a^2) (Plummer softening) and erf(r/a)/r (the potential
// of a Gaussian blob exp(-r^2/a^2)/(pi^{3/2} a^3), Beale & Majda 1985). What is left out:
// for Laplace every pair at distance 0 (the self pair, and coincident points, whose
// interaction is infinite); for the smooth kernels (finite at r = 0) only the self pair, named
// by its index (`self`, the source that is the target itself, or -1): a distinct source at
// the target's position adds its finite q_j f(0). The Laplace and Plummer potential and
// gradient also have a vectorised path.
#pragma once

#include <algorithm>
#include <cmath>

#include "core/types.h"

namespace kinema::fmm3 {

enum class NearKernel { Laplace = 0, Plummer = 1, Gaussian = 2 };

// f, f'/r and (f'' - f'/r)/r^2 of the kernel at r^2 > 0, for a length a.
struct Radial {
  Scalar f, g, h;
};

inline Radial radial(NearKernel kernel, Scalar r2, Scalar a) {
  if (kernel == NearKernel::Laplace) {
    const Scalar inv = 1 / std::sqrt(r2), inv2 = inv * inv;
    return {inv, -inv * inv2, 3 * inv * inv2 * inv2};
  }
  if (kernel == NearKernel::Plummer) {
    const Scalar s2 = r2 + a * a, inv = 1 / std::sqrt(s2), inv2 = inv * inv;
    return {inv, -inv * inv2, 3 * inv * inv2 * inv2};
  }
  // Gaussian blob: erf(rho)/r, rho = r/a; its series below rho = 0.02 (next term < 2e-16).
  constexpr Scalar two_over_sqrt_pi = 1.1283791670955126;
  const Scalar inv_a = 1 / a, a2 = 1 / (inv_a * inv_a);
  const Scalar rho2 = r2 * inv_a * inv_a;
  const Scalar c = two_over_sqrt_pi * inv_a;
  if (rho2 < 4e-4) {
    const Scalar f = c * (1 - rho2 / 3 + rho2 * rho2 / 10 - rho2 * rho2 * rho2 / 42);
    const Scalar g = c / a2 * (-2.0 / 3 + 0.4 * rho2 - rho2 * rho2 / 7);
    const Scalar h = c / (a2 * a2) * (0.8 - rho2 * 4.0 / 7);
    return {f, g, h};
  }
  const Scalar r = std::sqrt(r2), inv_r = 1 / r, inv_r2 = inv_r * inv_r;
  const Scalar e = std::erf(r * inv_a), gauss = c * std::exp(-rho2);
  const Scalar f = e * inv_r;
  const Scalar d1 = gauss * inv_r - e * inv_r2;                        // f'
  const Scalar d2 = -2 * gauss / a2 - 2 * gauss * inv_r2 + 2 * e * inv_r2 * inv_r;  // f''
  const Scalar g = d1 * inv_r;
  return {f, g, (d2 - g) * inv_r2};
}

// The Laplace kernel 1/r where r^2 leaves double's comfortable range (r < 1e-50 or r > 1e50,
// down to distances whose squares underflow to 0): from the unit vector e = d / r and 1/r,
// phi += w / r, grad += -w e / r^2, hess += w (3 e e^T - I) / r^3, each as accurate as its
// value is representable (an unrepresentable one overflows to inf, never to a silent 0).
inline void laplace_scaled(Scalar dx, Scalar dy, Scalar dz, const Scalar* w, int components,
                           int width, Scalar (*acc)[10]) {
  const Scalar big = std::max({std::abs(dx), std::abs(dy), std::abs(dz)});
  const Scalar ux = dx / big, uy = dy / big, uz = dz / big;
  const Scalar norm = std::sqrt(ux * ux + uy * uy + uz * uz);
  const Scalar inv = 1 / (big * norm), ex = ux / norm, ey = uy / norm, ez = uz / norm;
  for (int c = 0; c < components; ++c) {
    Scalar* o = acc[c];
    const Scalar f = w[c] * inv;
    o[0] += f;
    if (width > 1) {
      const Scalar g = -f * inv;
      o[1] += g * ex, o[2] += g * ey, o[3] += g * ez;
    }
    if (width > 4) {
      const Scalar h = f * inv * inv;
      o[4] += h * (3 * ex * ex - 1), o[5] += 3 * h * ex * ey, o[6] += 3 * h * ex * ez;
      o[7] += h * (3 * ey * ey - 1), o[8] += 3 * h * ey * ez, o[9] += h * (3 * ez * ez - 1);
    }
  }
}

// Adds to out[c * width + ...] (phi, grad[3], hess[6] = xx xy xz yy yz zz; the first `width`
// of them, width 1, 4 or 10) the sum over sources [0, n) with charge components
// q[j * components + c], c < components (the kernel evaluated once per pair). Source `self`
// (in [0, n), or -1 for none) is the target itself and skipped; Laplace skips every source at
// the target's position (equal coordinates, distance exactly 0) instead and returns how many
// of them, other than `self`, carry a nonzero charge while the target (source `self`, when
// there is one) does too: coincident pairs whose interaction is infinite, which callers
// report. Distinct points are summed however close: a distance whose square underflows is
// not 0.
inline Index p2p_generic(NearKernel kernel, Scalar a, int width, Scalar x, Scalar y, Scalar z,
                         const Scalar* sx, const Scalar* sy, const Scalar* sz, const Scalar* q,
                         int components, Index n, Scalar* out, Index self = -1) {
  const bool laplace = kernel == NearKernel::Laplace;
  constexpr int kMaxComponents = 4;
  Scalar acc[kMaxComponents][10] = {};
  Index coincident = 0;
  const auto charged = [components](const Scalar* w) {
    return std::any_of(w, w + components, [](Scalar v) { return v != 0; });
  };
  const bool target_charged = self < 0 || charged(q + self * components);
  for (Index j = 0; j < n; ++j) {
    const Scalar dx = x - sx[j], dy = y - sy[j], dz = z - sz[j];
    const Scalar r2 = dx * dx + dy * dy + dz * dz;
    const Scalar* w = q + j * components;
    if (laplace) {
      if (dx == 0 && dy == 0 && dz == 0) {
        if (j != self && target_charged && charged(w)) ++coincident;
        continue;
      }
      if (!(r2 >= 1e-100 && r2 <= 1e100)) {
        laplace_scaled(dx, dy, dz, w, components, width, acc);
        continue;
      }
    } else if (j == self) {
      continue;
    }
    const Radial k = radial(kernel, r2, a);
    for (int c = 0; c < components; ++c) {
      Scalar* o = acc[c];
      o[0] += w[c] * k.f;
      if (width > 1) {
        const Scalar wg = w[c] * k.g;
        o[1] += wg * dx, o[2] += wg * dy, o[3] += wg * dz;
      }
      if (width > 4) {
        const Scalar wg = w[c] * k.g, wh = w[c] * k.h;
        o[4] += wg + wh * dx * dx, o[5] += wh * dx * dy, o[6] += wh * dx * dz;
        o[7] += wg + wh * dy * dy, o[8] += wh * dy * dz, o[9] += wg + wh * dz * dz;
      }
    }
  }
  for (int c = 0; c < components; ++c)
    for (int i = 0; i < width; ++i) out[c * width + i] += acc[c][i];
  return coincident;
}

// The Laplace (softening a = 0) or Plummer potential and gradient of sources [0, n) with unit
// stride charges, AVX2 where the CPU has it (a float reciprocal square root refined by Newton
// steps: one leaves 2e-7, two a relative error below 1e-13, three reach rounding; the
// mutual kernel takes 1 to 3). Adds to out[0..3]. Left out as in p2p_generic: with a = 0
// every pair at distance 0, with a > 0 source `self` (or none for -1).
// Returns false, leaving out untouched, when a pair's r^2 is outside the range where the float
// estimate is valid, when (a = 0) a charged source other than `self` lies at the target, and
// always in a build without the vectorised kernels; the caller then uses p2p_generic.
bool p2p_fast(bool gradient, int newton_steps, Scalar a, Scalar x, Scalar y, Scalar z,
              const Scalar* sx, const Scalar* sy, const Scalar* sz, const Scalar* q, Index n,
              Scalar* out, Index self = -1);

// True when this CPU runs AVX-512F and the AVX-512 kernels are not switched off
// (KINEMA_SIMD=baseline or avx2, as core/simd.h describes).
bool use_avx512_kernels();

// True when p2p_mutual has its vectorised form on this CPU (otherwise near fields use
// p2p_fast in both directions).
bool p2p_mutual_available();

// The Laplace or Plummer near field between two disjoint blocks of points that are sources and
// targets at once (Newton's third law: each pair's kernel is evaluated once for both ends).
// No pair is a self pair: Plummer counts coincident points; for Laplace they fail the range
// check below.
// Block a: coordinates xa[3][na], charges qa; block b likewise, its arrays readable up to nb
// rounded up to a multiple of 4 (padding: zero charges at one of b's points). Adds the field
// of b at a's points to out_a (na x width rows, width 1 or 4: phi[, grad]) and the field of a
// at b's points to out_b (width arrays of stride `stride_b`). Returns false when a pair is
// outside the range of the float estimate (as p2p_fast): the outputs are then partial, so
// they are scratch that the caller adds to its results only on success.
bool p2p_mutual(bool gradient, int newton_steps, Scalar a, const Scalar* const xa[3],
                const Scalar* qa, Index na, const Scalar* const xb[3], const Scalar* qb, Index nb,
                Index stride_b, Scalar* out_a, Scalar* out_b);

}  // namespace kinema::fmm3
