// MPM kernels: the signed SVD reconstructs F with rotations (also for inverted and degenerate
// F), every stress vanishes at rest and is symmetric, the Hencky stress's first Piola-Kirchhoff
// tensor matches central finite differences of its energy, the snow projection clamps, the
// Drucker-Prager return lands on the cone, the mu(I) return lands on the cone of mu(I) at the
// plastic shear rate it implies, and a solver step conserves momentum exactly.
#include <gtest/gtest.h>

#include <cmath>
#include <random>

#include "mpm/adjoint_kernels.h"
#include "mpm/kernels.h"
#include "mpm/solver.h"

namespace kinema::mpm {

namespace {

template <int D>
Mat<D> random_F(std::mt19937& rng, Scalar spread) {
  std::normal_distribution<Scalar> n(0, spread);
  Mat<D> F = Mat<D>::Identity();
  for (int r = 0; r < D; ++r)
    for (int c = 0; c < D; ++c) F(r, c) += n(rng);
  return F;
}

template <int D>
void check_svd(const Mat<D>& F) {
  const Svd<D> s = svd(F);
  const Mat<D> back = s.U * s.sigma.asDiagonal() * s.V.transpose();
  EXPECT_LT((back - F).norm(), 1e-12 * (1 + F.norm())) << F;
  EXPECT_LT((s.U.transpose() * s.U - Mat<D>::Identity()).norm(), 1e-12);
  EXPECT_LT((s.V.transpose() * s.V - Mat<D>::Identity()).norm(), 1e-12);
  EXPECT_NEAR(s.U.determinant(), 1, 1e-12);
  EXPECT_NEAR(s.V.determinant(), 1, 1e-12);
}

template <int D>
void svd_cases() {
  std::mt19937 rng(3);
  for (int k = 0; k < 200; ++k) check_svd<D>(random_F<D>(rng, k < 100 ? 0.2 : 1.5));
  Mat<D> reflect = Mat<D>::Identity();
  reflect(0, 0) = -1;
  check_svd<D>(reflect);
  check_svd<D>(Mat<D>::Identity());
  Mat<D> rank1 = Mat<D>::Zero();
  rank1(0, 1) = 2;
  check_svd<D>(rank1);
}

template <int D>
void stresses_symmetric_and_zero_at_rest() {
  Material m = make_material(D, MaterialKind::Elastic, 1000, 1e5, 0.3, 0, 0);
  const Mat<D> I = Mat<D>::Identity();
  EXPECT_LT(corotated_tau<D>(I, svd(I), m.mu, m.lambda).norm(), 1e-9);
  EXPECT_LT(neohookean_tau<D>(I, m.mu, m.lambda).norm(), 1e-9);
  EXPECT_LT(hencky_tau<D>(svd(I), m.mu, m.lambda).norm(), 1e-9);
  EXPECT_LT(water_tau<D>(1.0, 1e5, 7).norm(), 1e-9);
  std::mt19937 rng(5);
  for (int k = 0; k < 50; ++k) {
    const Mat<D> F = random_F<D>(rng, 0.3);
    for (const Mat<D>& t : {corotated_tau<D>(F, svd(F), m.mu, m.lambda), neohookean_tau<D>(F, m.mu, m.lambda),
                            hencky_tau<D>(svd(F), m.mu, m.lambda)})
      EXPECT_LT((t - t.transpose()).norm(), 1e-9 * t.norm());
  }
}

// Hencky energy psi = mu |log S|^2 + lambda/2 tr(log S)^2; P = tau F^-T must be dpsi/dF.
template <int D>
void hencky_matches_finite_differences() {
  const Scalar mu = 3.0, lambda = 2.0;
  auto psi = [&](const Mat<D>& F) {
    const Svd<D> s = svd(F);
    const Vec<D> e = s.sigma.array().log().matrix();
    return mu * e.squaredNorm() + 0.5 * lambda * e.sum() * e.sum();
  };
  std::mt19937 rng(7);
  const Mat<D> F = random_F<D>(rng, 0.15);
  const Mat<D> P = hencky_tau<D>(svd(F), mu, lambda) * F.inverse().transpose();
  const Scalar eps = 1e-6;
  for (int r = 0; r < D; ++r)
    for (int c = 0; c < D; ++c) {
      Mat<D> Fp = F, Fm = F;
      Fp(r, c) += eps;
      Fm(r, c) -= eps;
      EXPECT_NEAR((psi(Fp) - psi(Fm)) / (2 * eps), P(r, c), 1e-7) << r << "," << c;
    }
}

template <int D>
void plastic_projections() {
  Material snow = make_material(D, MaterialKind::Snow, 400, 1.4e5, 0.2, 0, 0);
  Mat<D> F = Mat<D>::Identity() * 0.9;  // compressed beyond theta_c
  Scalar Jp = 1;
  Svd<D> s;
  const Mat<D> Fe = snow_project<D>(F, snow, Jp, s);
  EXPECT_NEAR(Fe(0, 0), 1 - snow.theta_c, 1e-12);
  EXPECT_NEAR(Jp * Fe.determinant(), F.determinant(), 1e-12);  // F = Fe Fp, Jp = det Fp

  Material sand = make_material(D, MaterialKind::Sand, 1600, 3.5e5, 0.3, 30, 0);
  std::mt19937 rng(11);
  for (int k = 0; k < 100; ++k) {
    const Mat<D> Ft = random_F<D>(rng, 0.1);
    Scalar J = 1;
    Svd<D> t;
    const Mat<D> Fs = sand_project<D>(Ft, sand, J, t, 1e-3);
    const Svd<D> r = svd(Fs);
    const Vec<D> e = r.sigma.array().abs().log().matrix();
    const Vec<D> dev = e - Vec<D>::Constant(e.sum() / D);
    // On or inside the cone: |dev| + (d lambda + 2 mu)/(2 mu) alpha tr <= 0 (and tr <= 0).
    const Scalar yield = dev.norm() + (D * sand.lambda + 2 * sand.mu) / (2 * sand.mu) * e.sum() * sand.alpha;
    EXPECT_LE(e.sum(), 1e-12);
    EXPECT_LE(yield, 1e-10);
  }
}

// The mu(I) return mapping (kernels.h, sand_project): a trial state outside the static cone
// lands on the cone of mu(I) with I from the plastic shear rate it implies, i.e. Jop et al.'s
// |tau| / p = mu_s + (mu_2 - mu_s) / (I0 / I + 1), |tau| = sqrt(tau':tau' / 2), computed here
// from the stress itself; inside the static cone nothing changes; mu_2 = mu_s is the constant
// law with alpha = sqrt(2) mu_s / d.
template <int D>
void mu_i_projection() {
  const Scalar mu_s = 0.5, mu_2 = 0.8, I0 = 0.3, d_g = 1e-3, rho_s = 2650, dt = 1e-4;
  Material sand = make_material(D, MaterialKind::Sand, 1600, 1e5, 0.3, std::atan(mu_s) * 180 / 3.14159265358979323846, 0);
  use_mu_i(sand, D, mu_s, mu_2, I0, d_g, rho_s);
  std::mt19937 rng(17);
  int flowed = 0;
  for (int k = 0; k < 200; ++k) {
    // Compressed (tr eps < 0) trial states with random shear.
    const Mat<D> Ft = random_F<D>(rng, 0.05) * 0.97;
    Scalar Jp = 1;
    Svd<D> t;
    const Mat<D> Fs = sand_project<D>(Ft, sand, Jp, t, dt);
    const Svd<D> trial = svd(Ft), out = svd(Fs);
    const Vec<D> e0 = trial.sigma.array().abs().log().matrix(), e1 = out.sigma.array().abs().log().matrix();
    if (e0.sum() >= 0) continue;
    const Mat<D> tau = hencky_tau<D>(out, sand.mu, sand.lambda);
    const Scalar p = -tau.trace() / D / out.sigma.prod();  // Cauchy pressure
    const Mat<D> dev_tau = tau - Mat<D>::Identity() * (tau.trace() / D);
    const Scalar ratio = std::sqrt(0.5 * dev_tau.squaredNorm()) / (-tau.trace() / D);
    const Vec<D> d0 = e0 - Vec<D>::Constant(e0.sum() / D), d1 = e1 - Vec<D>::Constant(e1.sum() / D);
    EXPECT_NEAR(e1.sum(), e0.sum(), 1e-12);  // the projection keeps the volume
    EXPECT_NEAR(Jp, 1, 1e-12);
    if (Fs == Ft) {
      EXPECT_LE(ratio, mu_s + 1e-12);  // inside the static cone
      continue;
    }
    ++flowed;
    const Scalar gamma_dot = std::sqrt(2.0) * (d0.norm() - d1.norm()) / dt;
    const Scalar I = gamma_dot * d_g / std::sqrt(p / rho_s);
    EXPECT_NEAR(ratio, mu_s + (mu_2 - mu_s) / (I0 / I + 1), 1e-9) << "I = " << I;
    EXPECT_GT(ratio, mu_s);
  }
  EXPECT_GT(flowed, 20);
  // mu_2 = mu_s: the constant law's cone with alpha = sqrt(2) mu_s / d.
  Material flat = sand;
  flat.mu_2 = mu_s;
  Material constant = sand;
  constant.friction_law = Material::FrictionLaw::Constant;
  constant.alpha = std::sqrt(2.0) * mu_s / D;
  for (int k = 0; k < 50; ++k) {
    const Mat<D> Ft = random_F<D>(rng, 0.05) * 0.97;
    Scalar J1 = 1, J2 = 1;
    Svd<D> t1, t2;
    EXPECT_LT((sand_project<D>(Ft, flat, J1, t1, dt) - sand_project<D>(Ft, constant, J2, t2, dt)).norm(), 1e-12);
  }
}

template <int D>
void step_conserves_momentum() {
  Model model = make_model(D, std::vector<Index>(D, 16), 1.0 / 16, std::vector<Scalar>(D, 0.0), Boundary::Slip);
  model.materials.push_back(make_material(D, MaterialKind::NeoHookean, 1000, 1e4, 0.3, 0, 0));
  Config config;
  config.gravity = {0, 0, 0};
  State state(D);
  std::mt19937 rng(13);
  std::uniform_real_distribution<Scalar> u(0.3, 0.7);
  std::normal_distribution<Scalar> n(0, 0.1);
  const Index count = 500;
  std::vector<Scalar> x(count * D), v(count * D), mass(count, 1e-3), vol(count, 1e-6);
  for (auto& xi : x) xi = u(rng);
  for (auto& vi : v) vi = n(rng);
  state.append(x.data(), v.data(), count, mass.data(), vol.data(), 0, 1e4, 0.3);
  for (auto& f : state.F) f += 0.05 * n(rng);
  Solver solver(model, config);
  const std::vector<Scalar> p0 = solver.momentum(state);
  Interrupt interrupt;
  for (int k = 0; k < 10; ++k) solver.step(state, 1e-3, interrupt);
  const std::vector<Scalar> p1 = solver.momentum(state);
  for (int a = 0; a < D; ++a) EXPECT_NEAR(p0[a], p1[a], 1e-15);
}

}  // namespace

// The stress adjoints against central differences of tau along random directions, for random F
// and at F = I (repeated singular values, where the corotated adjoint must stay regular).
// With mu, lambda = O(1) and step e = 1e-6 the difference's truncation is O(e^2) = 1e-12 and its
// rounding O(u / e) = 1e-10 relative, so 1e-7 relative leaves a wide margin.
template <int D>
void stress_adjoints_match_finite_differences() {
  const Scalar mu = 3.0, lambda = 2.0, e = 1e-6;
  std::mt19937 rng(17);
  std::normal_distribution<Scalar> normal(0, 1);
  auto random_mat = [&] {
    Mat<D> m;
    for (int i = 0; i < D * D; ++i) m(i) = normal(rng);
    return m;
  };
  for (int k = 0; k < 40; ++k) {
    const Mat<D> F = k == 0 ? Mat<D>::Identity() : random_F<D>(rng, 0.3);
    const Mat<D> W = random_mat(), dF = random_mat();
    for (int corotated = 0; corotated < 2; ++corotated) {
      auto tau = [&](const Mat<D>& G, Scalar m, Scalar l) {
        return corotated ? corotated_tau<D>(G, svd(G), m, l) : neohookean_tau<D>(G, m, l);
      };
      Mat<D> F_bar = Mat<D>::Zero();
      Scalar mu_bar = 0, lambda_bar = 0;
      if (corotated)
        corotated_tau_vjp<D>(F, svd(F), mu, lambda, W, F_bar, mu_bar, lambda_bar);
      else
        neohookean_tau_vjp<D>(F, mu, lambda, W, F_bar, mu_bar, lambda_bar);
      const Scalar fd_F = W.cwiseProduct(tau(F + e * dF, mu, lambda) - tau(F - e * dF, mu, lambda)).sum() / (2 * e);
      const Scalar fd_mu = W.cwiseProduct(tau(F, mu + e, lambda) - tau(F, mu - e, lambda)).sum() / (2 * e);
      const Scalar fd_lambda = W.cwiseProduct(tau(F, mu, lambda + e) - tau(F, mu, lambda - e)).sum() / (2 * e);
      const Scalar scale = 1 + std::abs(fd_F);
      EXPECT_NEAR(F_bar.cwiseProduct(dF).sum(), fd_F, 1e-7 * scale) << "corotated " << corotated << " case " << k;
      EXPECT_NEAR(mu_bar, fd_mu, 1e-7 * (1 + std::abs(fd_mu))) << "corotated " << corotated << " case " << k;
      EXPECT_NEAR(lambda_bar, fd_lambda, 1e-7 * (1 + std::abs(fd_lambda))) << "corotated " << corotated;
    }
  }
  // Water: the Tait stress's and the projection's adjoints (functions of J alone).
  for (int k = 0; k < 20; ++k) {
    const Mat<D> F = random_F<D>(rng, 0.1), W = random_mat(), dF = random_mat();
    const Scalar K = 5.0, gamma = 7.0;
    auto tau = [&](const Mat<D>& G, Scalar bulk) { return water_tau<D>(G.determinant(), bulk, gamma); };
    auto project = [&](const Mat<D>& G) {
      const Scalar J = G.determinant();
      return Mat<D>(Mat<D>::Identity() * (D == 2 ? std::sqrt(J) : std::cbrt(J)));
    };
    Mat<D> F_bar = Mat<D>::Zero();
    const Scalar K_bar = water_tau_vjp<D>(F, K, gamma, W, F_bar);
    const Scalar fd_F = W.cwiseProduct(tau(F + e * dF, K) - tau(F - e * dF, K)).sum() / (2 * e);
    const Scalar fd_K = W.cwiseProduct(tau(F, K + e) - tau(F, K - e)).sum() / (2 * e);
    EXPECT_NEAR(F_bar.cwiseProduct(dF).sum(), fd_F, 1e-7 * (1 + std::abs(fd_F))) << "water stress, case " << k;
    EXPECT_NEAR(K_bar, fd_K, 1e-7 * (1 + std::abs(fd_K))) << "water bulk modulus, case " << k;
    const Scalar fd_P = W.cwiseProduct(project(F + e * dF) - project(F - e * dF)).sum() / (2 * e);
    EXPECT_NEAR(water_projection_vjp<D>(F, W).cwiseProduct(dF).sum(), fd_P, 1e-7 * (1 + std::abs(fd_P)))
        << "water projection, case " << k;
  }
  // lame_parameters_vjp against differences of lame_parameters.
  const Scalar E = 1e3, nu = 0.3, mb = 0.7, lb = -1.3;
  Scalar E_bar, nu_bar, mp, lp, mm, lm;
  lame_parameters_vjp(E, nu, mb, lb, E_bar, nu_bar);
  lame_parameters(E, nu + e, mp, lp);
  lame_parameters(E, nu - e, mm, lm);
  EXPECT_NEAR(nu_bar, (mb * (mp - mm) + lb * (lp - lm)) / (2 * e), 1e-6 * std::abs(nu_bar));
  lame_parameters(E + 1e-3, nu, mp, lp);
  lame_parameters(E - 1e-3, nu, mm, lm);
  EXPECT_NEAR(E_bar, (mb * (mp - mm) + lb * (lp - lm)) / 2e-3, 1e-6 * std::abs(E_bar));
}

// The 2D snow projection without an SVD (kernels.h) against the projection through the signed
// SVD and against Eigen's JacobiSVD (singular values clamped, F = U Sigma V^T rebuilt), on random
// F and on degenerate ones: repeated singular values (scaled rotations, both inside and outside
// the clamp), reflections, rank one and zero. The three are the same map; the differences are
// rounding, a few ulps of |F| (the tolerance 1e-13 |F| covers the sqrt and product chains).
void snow_projection_without_svd() {
  const Material snow = make_material(2, MaterialKind::Snow, 400, 1.4e5, 0.2, 0, 0);
  std::mt19937 rng(11);
  std::vector<Mat<2>> cases;
  for (int k = 0; k < 300; ++k) cases.push_back(random_F<2>(rng, k < 100 ? 0.01 : k < 200 ? 0.2 : 1.5));
  for (Scalar scale : {0.0, 0.5, 0.98, 1.0, 1.005, 1.2}) {
    for (Scalar angle : {0.0, 0.3, 2.0, M_PI}) {
      Mat<2> R;
      R << std::cos(angle), -std::sin(angle), std::sin(angle), std::cos(angle);
      cases.push_back(scale * R);
      Mat<2> reflect = scale * R;
      reflect.col(0) *= -1;
      cases.push_back(reflect);
      cases.push_back(R * Eigen::Vector2d(scale, 0).asDiagonal() * R.transpose());  // rank one (or zero)
    }
  }
  for (const Mat<2>& F : cases) {
    Scalar Jp_fast = 1.3, Jp_svd = 1.3;
    Svd<2> s;
    const Mat<2> fast = snow_project(F, snow, Jp_fast);
    const Mat<2> ref = snow_project<2>(F, snow, Jp_svd, s);
    const Scalar tol = 1e-13 * (1 + F.norm());
    EXPECT_LT((fast - ref).norm(), tol) << F;
    // Eigen's SVD: unsigned singular values; the signed convention moves det's sign onto the
    // smaller one (clamped to 1 - theta_c when negative, as the signed clamp does).
    Eigen::JacobiSVD<Mat<2>> jac(F, Eigen::ComputeFullU | Eigen::ComputeFullV);
    Mat<2> U = jac.matrixU(), V = jac.matrixV();
    Eigen::Vector2d sigma = jac.singularValues();
    if (U.determinant() < 0) U.col(1) *= -1, sigma(1) *= -1;
    if (V.determinant() < 0) V.col(1) *= -1, sigma(1) *= -1;
    Eigen::Vector2d clamped = sigma;
    for (int a = 0; a < 2; ++a) clamped(a) = std::clamp(sigma(a), 1 - snow.theta_c, 1 + snow.theta_s);
    // A scaled reflection (sigma = s, -s) has no unique signed SVD: U V^T is any rotation, and
    // the clamped F with it; there only the two forms of kernels.h are compared (above).
    if (!(sigma(1) < 0 && sigma(0) + sigma(1) <= 1e-12 * sigma(0)))
      EXPECT_LT((fast - U * clamped.asDiagonal() * V.transpose()).norm(), tol) << F;
    // Jp = 1.3 s1 s2 / (c1 c2): s2 carries an absolute rounding of a few ulps of s1.
    const Scalar Jp_ref = 1.3 * sigma.prod() / clamped.prod();
    EXPECT_NEAR(Jp_fast, Jp_ref, 1e-12 * std::abs(Jp_ref) + 1e-13 * 1.3 * sigma(0) * sigma(0) / std::abs(clamped.prod()))
        << F;
  }
  // Inside the clamp the elastic F is kept bit for bit and Jp is untouched.
  Mat<2> inside;
  inside << 1.001, 0.002, -0.001, 0.999;
  Scalar Jp = 1.3;
  EXPECT_EQ(snow_project(inside, snow, Jp), inside);
  EXPECT_EQ(Jp, 1.3);
}

TEST(MpmKernels, SnowProjectionWithoutSvd2D) { snow_projection_without_svd(); }
TEST(MpmKernels, StressAdjoints2D) { stress_adjoints_match_finite_differences<2>(); }
TEST(MpmKernels, StressAdjoints3D) { stress_adjoints_match_finite_differences<3>(); }
TEST(MpmKernels, SignedSvd2D) { svd_cases<2>(); }
TEST(MpmKernels, SignedSvd3D) { svd_cases<3>(); }
TEST(MpmKernels, StressesSymmetricAndZeroAtRest2D) { stresses_symmetric_and_zero_at_rest<2>(); }
TEST(MpmKernels, StressesSymmetricAndZeroAtRest3D) { stresses_symmetric_and_zero_at_rest<3>(); }
TEST(MpmKernels, HenckyFiniteDifferences2D) { hencky_matches_finite_differences<2>(); }
TEST(MpmKernels, HenckyFiniteDifferences3D) { hencky_matches_finite_differences<3>(); }
TEST(MpmKernels, PlasticProjections2D) { plastic_projections<2>(); }
TEST(MpmKernels, PlasticProjections3D) { plastic_projections<3>(); }
TEST(MpmKernels, MuIProjection2D) { mu_i_projection<2>(); }
TEST(MpmKernels, MuIProjection3D) { mu_i_projection<3>(); }
TEST(MpmSolver, StepConservesMomentum2D) { step_conserves_momentum<2>(); }
TEST(MpmSolver, StepConservesMomentum3D) { step_conserves_momentum<3>(); }

}  // namespace kinema::mpm
