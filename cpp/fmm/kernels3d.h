// Solid harmonics and the translation operators of the 3D Laplace fast multipole method
// (Greengard & Rokhlin 1997, Acta Numerica 6:229; scaled solid harmonics as in Helgaker,
// Jorgensen & Olsen, "Molecular Electronic-Structure Theory", 2000, sec. 9.13):
//   R_l^m(r) = r^l P_l^m(cos t) e^{i m f} / (l + m)!,   I_l^m(r) = (l - m)! P_l^m(cos t) e^{i m f} / r^{l+1},
//   1/|x - y| = sum_{l, m} conj(R_l^m(y - c)) I_l^m(x - c)          (|y - c| < |x - c|).
// Expansions of a box of half-width h are stored scaled so that every coefficient is O(1):
//   multipole  phi(x) = (1/h) sum M_lm I_lm((x - c)/h),   M_lm = sum_j q_j conj(R_lm((y_j - c)/h)),
//   local      phi(x) = sum L_lm conj(R_lm((x - c)/h)).
// Charges are real, so X_{l,-m} = (-1)^m conj(X_lm) and only m >= 0 is stored, as (p+1)^2
// reals per expansion: for each l, Re X_l0, then Re X_lm, Im X_lm for m = 1..l.
#pragma once

#include <complex>
#include <vector>

#include "core/types.h"

namespace kinema::fmm3 {

using Complex = std::complex<Scalar>;

inline int coefficient_count(int p) { return (p + 1) * (p + 1); }
// Index of X_lm (m >= 0) among the (p+1)(p+2)/2 complex coefficients.
inline int cidx(int l, int m) { return l * (l + 1) / 2 + m; }
inline int complex_count(int p) { return (p + 1) * (p + 2) / 2; }

// R_lm(v) and I_lm(v) for 0 <= m <= l <= p into out[cidx(l, m)].
void regular(Scalar x, Scalar y, Scalar z, int p, Complex* out);
void irregular(Scalar x, Scalar y, Scalar z, int p, Complex* out);

// Between the compact real layout and complex coefficients (m >= 0).
void to_complex(const Scalar* real, int p, Complex* out);
void add_real(const Complex* c, int p, Scalar scale, Scalar* real);

// X_lm for any m, from the stored m >= 0 (0 outside |m| <= l <= p).
inline Complex coefficient(const Complex* c, int p, int l, int m) {
  if (l < 0 || l > p || m > l || m < -l) return 0;
  if (m >= 0) return c[cidx(l, m)];
  return (m & 1) ? -std::conj(c[cidx(l, -m)]) : std::conj(c[cidx(l, -m)]);
}

// P2M: M += sum_j q_j conj(R((y_j - c)/h)) (sources as x, y, z arrays).
void p2m(int p, const Scalar* c, Scalar h, const Scalar* const xyz[3], const Scalar* q, Index n,
         Index stride, Scalar* multipole);
// M2M: adds the multipole of a child (centre cc, half-width h/2) to its parent's (cp, h).
void m2m(int p, const Scalar* child, const Scalar* cc, const Scalar* cp, Scalar h, Scalar* parent);
// L2L: adds the parent's local expansion (centre cp, half-width h) to its child's (cc, h/2).
void l2l(int p, const Scalar* parent, const Scalar* cp, Scalar h, const Scalar* cc, Scalar* child);
// P2L: L += local expansion about c (half-width h) of the sources (all far from the box).
void p2l(int p, const Scalar* c, Scalar h, const Scalar* const xyz[3], const Scalar* q, Index n,
         Index stride, Scalar* local);

// The dense M2L matrix (real layout, row-major (p+1)^2 x (p+1)^2) taking a scaled multipole
// to the scaled local expansion of a same-level box displaced by `offset` box widths
// (target centre minus source centre); the result still has to be divided by h.
void m2l_matrix(int p, const int offset[3], Scalar* matrix);

// Derivatives of expansions as expansions: d/du of a local of order p (order p - 1) and of a
// multipole of order p (order p + 1), u = (x - c)/h, axis 0, 1, 2.
void local_derivative(const Complex* local, int p, int axis, Complex* out);
void multipole_derivative(const Complex* multipole, int p, int axis, Complex* out);

// Re sum_lm L_lm conj(R_lm) over the full m range, from m >= 0 coefficients.
Scalar local_sum(const Complex* local, const Complex* regular_values, int p);
// Re sum_lm M_lm I_lm over the full m range.
Scalar multipole_sum(const Complex* multipole, const Complex* irregular_values, int p);

}  // namespace kinema::fmm3
