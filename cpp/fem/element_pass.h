// The per-element bodies of the element passes a symplectic step and its adjoint make every
// step (fem/solver.cpp's elastic gradient, fem/adjoint.cpp's K w): one element's
//   force term    vol P(F) Dm^-T split over its vertices (dW/dx_e, kernels.h),
//   adjoint term  vol dP(F)[dF] Dm^-T with dF = Ds(w) Dm^-1 (the element's K w), and when asked
//                 the Lame products vol dP/dmu : dF, vol dP/dlam : dF and the work vol P : dF.
// The formulas are kernels.h's; each body is compiled flat (every helper inlined into it, with
// the model's material chosen once per element), which the compiler does not do on its own for
// these Eigen expressions, and the hot loops are nothing but these calls.
#pragma once

#include "core/simd.h"
#include "fem/kernels.h"
#include "fem/model.h"

#if defined(__GNUC__)
#define KINEMA_FLATTEN __attribute__((flatten))
#else
#define KINEMA_FLATTEN
#endif

namespace kinema::fem {

// dP/dF applied to dF without forming the D^2 x D^2 matrix (piola_derivative<D>(F) vec(dF), as
// fem/kernels.h writes it, term by term); the corotated model's rotation derivative goes
// through the matrix.
template <int D>
Mat<D> piola_differential(const Mat<D>& F, const Mat<D>& dF, Material m, Scalar mu, Scalar lam) {
  const Mat<D> I = Mat<D>::Identity();
  switch (m) {
    case Material::Linear:
      return mu * (dF + dF.transpose()) + lam * dF.trace() * I;
    case Material::StVK: {
      const Mat<D> E = (F.transpose() * F - I) / 2;
      const Mat<D> S = 2 * mu * E + lam * E.trace() * I;
      const Mat<D> dE = (dF.transpose() * F + F.transpose() * dF) / 2;
      return dF * S + F * (2 * mu * dE + lam * dE.trace() * I);
    }
    case Material::NeoHookean: {
      // mu dF + lam' (cof F : dF) cof F + (lam' (J - 1) - mu) d(cof F)[dF], lam' = lam + mu.
      const Scalar l = lam + mu;
      const Mat<D> C = cofactor<D>(F);
      Mat<D> dC;
      if constexpr (D == 2) {
        dC = cofactor<D>(dF);  // linear in F
      } else {
        dC.col(0) = dF.col(1).cross(F.col(2)) + F.col(1).cross(dF.col(2));
        dC.col(1) = dF.col(2).cross(F.col(0)) + F.col(2).cross(dF.col(0));
        dC.col(2) = dF.col(0).cross(F.col(1)) + F.col(0).cross(dF.col(1));
      }
      return mu * dF + (l * C.cwiseProduct(dF).sum()) * C + (l * det_minus_one<D>(F - I) - mu) * dC;
    }
    case Material::Corotated:
      break;
  }
  Mat<D> dP;
  Eigen::Map<Eigen::Matrix<Scalar, D * D, 1>>(dP.data()) = piola_derivative<D>(F, m, mu, lam) * vec<D>(dF);
  return dP;
}

// Element e's force term (dW/dx_e) into out + e (D + 1) D.
template <int D>
KINEMA_FLATTEN void element_force_term(const Model& m, const Scalar* x, Index e, Scalar* out) {
  constexpr int K = (D + 1) * D;
  const Mat<D> Dinv = Eigen::Map<const Mat<D>>(m.Dm_inv.data() + e * D * D);
  const Mat<D> F = deformation_gradient<D>(x, m.elements.data() + e * (D + 1), Dinv);
  const Mat<D> P = piola<D>(F, m.material(), m.mu[e], m.lam[e]);
  Eigen::Map<ElementVec<D>>(out + e * K) = element_gradient<D>(P, Dinv, m.volume[e]);
}

// Element e's Lame products g_mu[e] = vol dP/dmu : dF, g_lam[e] = vol dP/dlam : dF (when g_mu is
// non-null), given F and dF; returns the work vol P : dF when `work` (else 0).
template <int D>
KINEMA_ALWAYS_INLINE Scalar element_parameter_terms(const Model& m, const Mat<D>& F, const Mat<D>& dF,
                                                    Index e, Scalar* g_mu, Scalar* g_lam, bool work) {
  if (g_mu) {
    Mat<D> A, B;
    piola_lame_derivatives<D>(F, m.material(), A, B);
    g_mu[e] = m.volume[e] * A.cwiseProduct(dF).sum();
    g_lam[e] = m.volume[e] * B.cwiseProduct(dF).sum();
  }
  return work ? m.volume[e] * piola<D>(F, m.material(), m.mu[e], m.lam[e]).cwiseProduct(dF).sum() : 0;
}

// Element e's K w term into out + e (D + 1) D (when out is non-null) and its parameter terms
// (element_parameter_terms).
template <int D>
KINEMA_FLATTEN Scalar element_adjoint_term(const Model& m, const Scalar* x, const Scalar* w, Index e,
                                           Scalar* out, Scalar* g_mu, Scalar* g_lam, bool work) {
  constexpr int K = (D + 1) * D;
  const Index* el = m.elements.data() + e * (D + 1);
  const Mat<D> Dinv = Eigen::Map<const Mat<D>>(m.Dm_inv.data() + e * D * D);
  const Mat<D> F = deformation_gradient<D>(x, el, Dinv);
  const Mat<D> dF = deformation_gradient<D>(w, el, Dinv);  // linear in w: Ds(w) Dm^-1
  if (out) {
    const Mat<D> dP = piola_differential<D>(F, dF, m.material(), m.mu[e], m.lam[e]);
    Eigen::Map<ElementVec<D>>(out + e * K) = element_gradient<D>(dP, Dinv, m.volume[e]);
  }
  return element_parameter_terms<D>(m, F, dF, e, g_mu, g_lam, work);
}

}  // namespace kinema::fem
