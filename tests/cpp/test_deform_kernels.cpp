// Element kernels of km.fem and km.massspring against central finite differences, the
// structural properties of the energies (rigid invariance, symmetric Hessians, projection to
// PSD) and the fixed-pattern assembly against a dense scatter.
#include <gtest/gtest.h>

#include <Eigen/Eigenvalues>
#include <cmath>
#include <random>
#include <vector>

#include "fem/kernels.h"
#include "massspring/kernels.h"
#include "mesh/element_assembly.h"

namespace kinema {
namespace {

using fem::Material;
constexpr Material kMaterials[] = {Material::Linear, Material::StVK, Material::Corotated,
                                   Material::NeoHookean};
constexpr Scalar kMu = 3.0, kLam = 7.0;

template <int D>
fem::Mat<D> random_F(std::mt19937& rng, Scalar spread) {
  std::uniform_real_distribution<Scalar> u(-spread, spread);
  fem::Mat<D> F = fem::Mat<D>::Identity();
  for (int i = 0; i < D * D; ++i) F.data()[i] += u(rng);
  return F;
}

template <int D>
fem::Mat<D> rotation(std::mt19937& rng) {
  Eigen::HouseholderQR<fem::Mat<D>> qr(random_F<D>(rng, 1.0));
  fem::Mat<D> Q = qr.householderQ();
  if (Q.determinant() < 0) Q.col(0) *= -1;
  return Q;
}

// P against d psi / dF and dP/dF against dP, by central differences (step 1e-6: error ~1e-9).
template <int D>
void check_derivatives(Material m, Scalar spread, unsigned seed) {
  std::mt19937 rng(seed);
  for (int trial = 0; trial < 20; ++trial) {
    const fem::Mat<D> F = random_F<D>(rng, spread);
    const fem::Mat<D> P = fem::piola<D>(F, m, kMu, kLam);
    const fem::HessF<D> H = fem::piola_derivative<D>(F, m, kMu, kLam);
    const Scalar h = 1e-6;
    for (int k = 0; k < D * D; ++k) {
      fem::Mat<D> Fp = F, Fm = F;
      Fp.data()[k] += h;
      Fm.data()[k] -= h;
      const Scalar dpsi = (fem::psi<D>(Fp, m, kMu, kLam) - fem::psi<D>(Fm, m, kMu, kLam)) / (2 * h);
      EXPECT_NEAR(P.data()[k], dpsi, 1e-6 * (1 + std::abs(dpsi)))
          << "material " << int(m) << " d " << D << " entry " << k;
      const fem::Mat<D> dP = (fem::piola<D>(Fp, m, kMu, kLam) - fem::piola<D>(Fm, m, kMu, kLam)) / (2 * h);
      for (int l = 0; l < D * D; ++l)
        EXPECT_NEAR(H(l, k), dP.data()[l], 1e-5 * (1 + H.cwiseAbs().maxCoeff()))
            << "material " << int(m) << " d " << D << " dP/dF(" << l << ", " << k << ")";
    }
    EXPECT_LE((H - H.transpose()).cwiseAbs().maxCoeff(), 1e-12 * (1 + H.cwiseAbs().maxCoeff()));
  }
}

TEST(FemKernels, PiolaAndHessianMatchFiniteDifferences2D) {
  for (Material m : kMaterials) check_derivatives<2>(m, 0.3, 1);
}

TEST(FemKernels, PiolaAndHessianMatchFiniteDifferences3D) {
  for (Material m : kMaterials) check_derivatives<3>(m, 0.3, 2);
}

TEST(FemKernels, InvertedElementsStayDefined) {
  // Neo-Hookean and corotated are finite with finite-difference-consistent stress for J < 0.
  std::mt19937 rng(3);
  for (Material m : {Material::Corotated, Material::NeoHookean}) {
    fem::Mat<3> F = random_F<3>(rng, 0.2);
    F.col(0) *= -1;  // reflect: J < 0
    ASSERT_LT(F.determinant(), 0);
    EXPECT_TRUE(std::isfinite(fem::psi<3>(F, m, kMu, kLam)));
    EXPECT_TRUE(fem::piola<3>(F, m, kMu, kLam).allFinite());
    EXPECT_TRUE(fem::piola_derivative<3>(F, m, kMu, kLam).allFinite());
  }
}

template <int D>
void check_rigid(unsigned seed) {
  std::mt19937 rng(seed);
  for (Material m : kMaterials) {
    if (m == Material::Linear) continue;  // linear elasticity is not rotation invariant
    const fem::Mat<D> R = rotation<D>(rng);
    EXPECT_NEAR(fem::psi<D>(R, m, kMu, kLam), 0, 1e-12) << "material " << int(m);
    EXPECT_LE(fem::piola<D>(R, m, kMu, kLam).cwiseAbs().maxCoeff(), 1e-12) << "material " << int(m);
  }
  const fem::Mat<D> I = fem::Mat<D>::Identity();
  for (Material m : kMaterials) {
    EXPECT_NEAR(fem::psi<D>(I, m, kMu, kLam), 0, 1e-14);
    // All four linearise to the same small-strain tensor at F = I.
    const fem::HessF<D> H = fem::piola_derivative<D>(I, m, kMu, kLam);
    const fem::HessF<D> H0 = fem::piola_derivative<D>(I, Material::Linear, kMu, kLam);
    EXPECT_LE((H - H0).cwiseAbs().maxCoeff(), 1e-12) << "material " << int(m);
  }
}

TEST(FemKernels, RigidRotationsCostNothing2D) { check_rigid<2>(4); }
TEST(FemKernels, RigidRotationsCostNothing3D) { check_rigid<3>(5); }

TEST(FemKernels, ProjectionGivesNearestPsd) {
  std::mt19937 rng(6);
  for (Material m : kMaterials) {
    fem::Mat<3> F = random_F<3>(rng, 0.6);
    F *= 0.5;  // strong compression makes StVK and neo-Hookean indefinite
    fem::HessF<3> H = fem::piola_derivative<3>(F, m, kMu, kLam);
    const fem::HessF<3> H0 = H;
    fem::project_psd<3>(H);
    Eigen::SelfAdjointEigenSolver<fem::HessF<3>> eig(H);
    EXPECT_GE(eig.eigenvalues().minCoeff(), -1e-10 * H.cwiseAbs().maxCoeff());
    Eigen::SelfAdjointEigenSolver<fem::HessF<3>> eig0(H0);
    if (eig0.eigenvalues().minCoeff() > 0) EXPECT_EQ(H, H0);  // PD input is left alone
  }
}

TEST(FemKernels, ElementForcesAreEnergyGradient) {
  std::mt19937 rng(7);
  const Index elem[4] = {0, 1, 2, 3};
  const Scalar X[12] = {0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1};
  fem::Mat<3> Dinv;
  const Scalar vol = fem::rest_shape<3>(X, elem, Dinv);
  EXPECT_NEAR(vol, 1.0 / 6, 1e-15);
  std::uniform_real_distribution<Scalar> u(-0.2, 0.2);
  Scalar x[12];
  for (int i = 0; i < 12; ++i) x[i] = X[i] + u(rng);
  for (Material m : kMaterials) {
    auto W = [&](const Scalar* xx) {
      return vol * fem::psi<3>(fem::deformation_gradient<3>(xx, elem, Dinv), m, kMu, kLam);
    };
    const fem::Mat<3> F = fem::deformation_gradient<3>(x, elem, Dinv);
    const auto g = fem::element_gradient<3>(fem::piola<3>(F, m, kMu, kLam), Dinv, vol);
    const auto K = fem::element_hessian<3>(fem::piola_derivative<3>(F, m, kMu, kLam), Dinv, vol);
    for (int k = 0; k < 12; ++k) {
      Scalar xp[12], xm[12];
      std::copy(x, x + 12, xp);
      std::copy(x, x + 12, xm);
      xp[k] += 1e-6;
      xm[k] -= 1e-6;
      EXPECT_NEAR(g(k), (W(xp) - W(xm)) / 2e-6, 1e-6);
      const fem::Mat<3> Fp = fem::deformation_gradient<3>(xp, elem, Dinv);
      const fem::Mat<3> Fm = fem::deformation_gradient<3>(xm, elem, Dinv);
      const fem::ElementVec<3> dg = (fem::element_gradient<3>(fem::piola<3>(Fp, m, kMu, kLam), Dinv, vol) -
                       fem::element_gradient<3>(fem::piola<3>(Fm, m, kMu, kLam), Dinv, vol)) / 2e-6;
      for (int l = 0; l < 12; ++l) EXPECT_NEAR(K(l, k), dg(l), 1e-5);
    }
    // Translations are in the null space of the element stiffness.
    for (int r = 0; r < 3; ++r) {
      Eigen::Matrix<Scalar, 12, 1> t = Eigen::Matrix<Scalar, 12, 1>::Zero();
      for (int a = 0; a < 4; ++a) t(a * 3 + r) = 1;
      EXPECT_LE((K * t).cwiseAbs().maxCoeff(), 1e-12 * (1 + K.cwiseAbs().maxCoeff()));
    }
  }
}

// The structured element stiffness equals the dense triple product vol B^T (dP/dF) B.
template <int D>
void check_structured_hessian() {
  std::mt19937 rng(11);
  const fem::Mat<D> Dinv = random_F<D>(rng, 0.5);
  const auto H = fem::piola_derivative<D>(random_F<D>(rng, 0.3), Material::NeoHookean, kMu, kLam);
  const auto B = fem::gradient_operator<D>(Dinv);
  const Eigen::Matrix<Scalar, (D + 1) * D, (D + 1) * D> dense = 0.7 * B.transpose() * H * B;
  const auto K = fem::element_hessian<D>(H, Dinv, 0.7);
  EXPECT_LE((K - dense).cwiseAbs().maxCoeff(), 1e-13 * dense.cwiseAbs().maxCoeff());
}

TEST(FemKernels, StructuredHessianEqualsDenseProduct2D) { check_structured_hessian<2>(); }
TEST(FemKernels, StructuredHessianEqualsDenseProduct3D) { check_structured_hessian<3>(); }

TEST(MassSpringKernels, ForceAndJacobianMatchFiniteDifferences) {
  std::mt19937 rng(8);
  std::uniform_real_distribution<Scalar> u(-1, 1);
  const Scalar k = 5, L = 1.3;
  for (int trial = 0; trial < 10; ++trial) {
    massspring::Vec<3> d(u(rng), u(rng), u(rng));
    const massspring::Vec<3> zero = massspring::Vec<3>::Zero();
    // f_i = -dU/dx_i = dU/dd
    const auto f = massspring::spring_force<3>(d, zero, k, L, 0);
    const auto S = massspring::spring_jacobian<3>(d, L, false);
    for (int r = 0; r < 3; ++r) {
      massspring::Vec<3> dp = d, dm = d;
      dp(r) += 1e-6;
      dm(r) -= 1e-6;
      EXPECT_NEAR(f(r), (massspring::spring_energy<3>(dp, k, L) - massspring::spring_energy<3>(dm, k, L)) / 2e-6, 1e-6);
      const massspring::Vec<3> df = (massspring::spring_force<3>(dp, zero, k, L, 0) -
                       massspring::spring_force<3>(dm, zero, k, L, 0)) / 2e-6;
      for (int q = 0; q < 3; ++q) EXPECT_NEAR(k * S(q, r), df(q), 1e-6);  // df_i/dx_j = k S
    }
    const auto Sc = massspring::spring_jacobian<3>(d, L, true);
    EXPECT_GE(Eigen::SelfAdjointEigenSolver<massspring::Mat<3>>(Sc).eigenvalues().minCoeff(), -1e-14);
  }
}

TEST(ElementAssembly, GatherEqualsDenseScatter) {
  // Two triangles sharing an edge plus one isolated vertex, d = 2.
  const std::vector<Index> elements = {0, 1, 2, 2, 1, 3};
  ElementAssembly A(5, 2, 3, elements.data(), 2);
  const Index n = A.dof_count(), kd = A.element_vector_size();
  std::mt19937 rng(9);
  std::uniform_real_distribution<Scalar> u(-1, 1);
  std::vector<Scalar> ev(2 * kd), em(2 * kd * kd);
  for (auto& v : ev) v = u(rng);
  for (auto& v : em) v = u(rng);
  std::vector<Scalar> f(n), values(A.nonzeros());
  A.gather_vector(ev.data(), f.data());
  A.gather_matrix(em.data(), values.data());
  Eigen::VectorXd f_ref = Eigen::VectorXd::Zero(n);
  Eigen::MatrixXd K_ref = Eigen::MatrixXd::Zero(n, n);
  for (int e = 0; e < 2; ++e)
    for (int a = 0; a < 3; ++a)
      for (int r = 0; r < 2; ++r) {
        const Index q = elements[e * 3 + a] * 2 + r;
        f_ref(q) += ev[e * kd + a * 2 + r];
        for (int b = 0; b < 3; ++b)
          for (int c = 0; c < 2; ++c)
            K_ref(q, elements[e * 3 + b] * 2 + c) += em[e * kd * kd + (a * 2 + r) * kd + b * 2 + c];
      }
  Eigen::MatrixXd K = Eigen::MatrixXd::Zero(n, n);
  for (Index q = 0; q < n; ++q)
    for (Index p = A.row_ptr()[q]; p < A.row_ptr()[q + 1]; ++p) K(q, A.col_index()[p]) += values[p];
  for (Index q = 0; q < n; ++q) EXPECT_DOUBLE_EQ(f[q], f_ref(q));
  EXPECT_LE((K - K_ref).cwiseAbs().maxCoeff(), 1e-15);
  // Vertex 4 is in no element: its diagonal block is present (and zero).
  EXPECT_EQ(A.row_ptr()[9] - A.row_ptr()[8], 2);
  EXPECT_EQ(values[A.diagonal()[8]], 0);
}

}  // namespace
}  // namespace kinema
