// FMM kernels: the vectorisable log against libm, each translation operator against the
// direct sum it stands for, and the whole FMM against direct2d at several orders.
#include <gtest/gtest.h>

#include <cmath>
#include <complex>
#include <random>
#include <vector>

#include "fmm/kernels.h"
#include "fmm/laplace2d.h"

namespace kinema::fmm {

namespace {

struct Cloud {
  std::vector<Scalar> x, y, q;
};

// n charges uniform in the square of half-width h about (cx, cy).
Cloud cloud(Index n, Scalar cx, Scalar cy, Scalar h, unsigned seed) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<Scalar> u(-1, 1);
  Cloud c;
  for (Index i = 0; i < n; ++i) {
    c.x.push_back(cx + h * u(rng));
    c.y.push_back(cy + h * u(rng));
    c.q.push_back(u(rng));
  }
  return c;
}

Scalar direct_phi(const Cloud& c, Scalar x, Scalar y) {
  Scalar phi = 0;
  for (size_t j = 0; j < c.x.size(); ++j) phi += c.q[j] * std::log(std::hypot(x - c.x[j], y - c.y[j]));
  return phi;
}

}  // namespace

TEST(FastLog, MatchesLibmToAFewUlps) {
  std::mt19937_64 rng(1);
  std::uniform_real_distribution<Scalar> e(-300, 300);
  Scalar worst = 0;
  for (int i = 0; i < 200000; ++i) {
    const Scalar x = std::pow(10.0, e(rng));
    const Scalar exact = std::log(x);
    worst = std::max(worst, std::abs(fast_log(x) - exact) / std::max(1.0, std::abs(exact)));
  }
  EXPECT_LT(worst, 1e-15) << "worst error of fast_log, relative to max(1, |log x|)";
  EXPECT_NEAR(fast_log(1.0), 0.0, 4e-16);
}

TEST(Translations, EveryOperatorReproducesTheDirectSum) {
  const int p = 30;
  const Operators op(p);
  const size_t n = static_cast<size_t>(p + 1);
  // Sources in a child box (half-width 0.25) of the parent box about the origin (half-width
  // 0.5); the target box is 3 parent widths away, as in a V list.
  const Cloud src = cloud(50, 0.25, -0.25, 0.25, 2);
  std::vector<Scalar> child(2 * n, 0.0), parent(2 * n, 0.0), local(2 * n, 0.0), sub(2 * n, 0.0),
      p2l_local(2 * n, 0.0);
  p2m(op, 0.25, -0.25, 0.25, src.x.data(), src.y.data(), src.q.data(), 50, child.data(), child.data() + n);
  m2m(op, child.data(), child.data() + n, 0.25, -0.25, 0.25, parent.data(), parent.data() + n, 0, 0, 0.5);
  m2l(op, parent.data(), parent.data() + n, 0, 0, 0.5, local.data(), local.data() + n, 3.0, 1.0, 0.5);
  l2l(op, local.data(), local.data() + n, 3.0, 1.0, 0.5, sub.data(), sub.data() + n, 2.75, 1.25, 0.25);
  p2l(op, 2.75, 1.25, 0.25, src.x.data(), src.y.data(), src.q.data(), 50, p2l_local.data(), p2l_local.data() + n);
  const Scalar tx = 2.9, ty = 1.1;
  const Scalar exact = direct_phi(src, tx, ty);
  Scalar f[4] = {0, 0, 0, 0}, gx = 0, gy = 0;
  m2p<false>(p, child.data(), child.data() + n, 0.25, -0.25, 0.25, tx, ty, f[0], gx, gy);
  m2p<false>(p, parent.data(), parent.data() + n, 0, 0, 0.5, tx, ty, f[1], gx, gy);
  l2p<false>(p, sub.data(), sub.data() + n, 2.75, 1.25, 0.25, tx, ty, f[2], gx, gy);
  l2p<false>(p, p2l_local.data(), p2l_local.data() + n, 2.75, 1.25, 0.25, tx, ty, f[3], gx, gy);
  const char* names[4] = {"P2M+M2P", "M2M+M2P", "M2M+M2L+L2L+L2P", "P2L+L2P"};
  for (int i = 0; i < 4; ++i) EXPECT_NEAR(f[i], exact, 1e-12 * std::abs(exact)) << names[i];
}

TEST(Translations, GradientsMatchTheDirectSum) {
  const int p = 30;
  const Operators op(p);
  const size_t n = static_cast<size_t>(p + 1);
  const Cloud src = cloud(40, 0, 0, 0.5, 3);
  std::vector<Scalar> mp(2 * n, 0.0), loc(2 * n, 0.0);
  p2m(op, 0, 0, 0.5, src.x.data(), src.y.data(), src.q.data(), 40, mp.data(), mp.data() + n);
  m2l(op, mp.data(), mp.data() + n, 0, 0, 0.5, loc.data(), loc.data() + n, -2.0, 1.0, 0.5);
  const Scalar tx = -1.8, ty = 1.3;
  Scalar ex = 0, ey = 0, phi = 0, ex_phi = 0, ey_phi = 0, tmp = 0;
  p2p_exact<true>(tx, ty, src.x.data(), src.y.data(), src.q.data(), 40, tmp, ex, ey);
  Scalar gx = 0, gy = 0, lx = 0, ly = 0;
  m2p<true>(p, mp.data(), mp.data() + n, 0, 0, 0.5, tx, ty, phi, gx, gy);
  l2p<true>(p, loc.data(), loc.data() + n, -2.0, 1.0, 0.5, tx, ty, ex_phi, lx, ly);
  (void)ey_phi;
  const Scalar scale = std::hypot(ex, ey);
  EXPECT_NEAR(gx, ex, 1e-12 * scale);
  EXPECT_NEAR(gy, ey, 1e-12 * scale);
  EXPECT_NEAR(lx, ex, 1e-12 * scale);
  EXPECT_NEAR(ly, ey, 1e-12 * scale);
}

TEST(P2P, VectorisedSumEqualsLibmSumAndSkipsCoincidentPoints) {
  Cloud src = cloud(1000, 0, 0, 1, 4);
  src.x[7] = 0.125;  // a source exactly at the target: left out
  src.y[7] = -0.5;
  Scalar a = 0, ax = 0, ay = 0, b = 0, bx = 0, by = 0;
  EXPECT_TRUE(p2p<true>(0.125, -0.5, src.x.data(), src.y.data(), src.q.data(), 1000, a, ax, ay));
  p2p_exact<true>(0.125, -0.5, src.x.data(), src.y.data(), src.q.data(), 1000, b, bx, by);
  EXPECT_NEAR(a, b, 1e-13 * std::abs(b));
  EXPECT_NEAR(ax, bx, 1e-12 * std::abs(bx));
  EXPECT_NEAR(ay, by, 1e-12 * std::abs(by));
  // A pair closer than sqrt(DBL_MIN) is flagged for the exact path.
  const Scalar sx = 1e-200, sy = 0, q = 1;
  EXPECT_FALSE(p2p<false>(0, 0, &sx, &sy, &q, 1, a, ax, ay));
}

TEST(Laplace2d, ErrorFallsWithTheOrderAndMeetsEps) {
  const Index n = 3000;
  const Cloud c = cloud(n, 0.3, 0.7, 2.0, 5);
  std::vector<Scalar> pts(2 * n);
  for (Index i = 0; i < n; ++i) pts[2 * i] = c.x[i], pts[2 * i + 1] = c.y[i];
  Interrupt interrupt;
  std::vector<Scalar> ref(n), gref(2 * n), phi(n), grad(2 * n);
  direct2d(pts.data(), c.q.data(), n, nullptr, n, true, ref.data(), gref.data(), interrupt);
  auto error = [&](const std::vector<Scalar>& a, const std::vector<Scalar>& b) {
    Scalar e = 0, s = 0;
    for (size_t i = 0; i < a.size(); ++i) e += (a[i] - b[i]) * (a[i] - b[i]), s += b[i] * b[i];
    return std::sqrt(e / s);
  };
  Scalar previous = 1;
  for (int order : {6, 12, 24}) {
    Laplace2dConfig config;
    config.order = order;
    config.gradient = true;
    laplace2d(pts.data(), c.q.data(), n, nullptr, n, config, phi.data(), grad.data(), interrupt);
    const Scalar e = error(phi, ref);
    EXPECT_LT(e, previous / 10) << "order " << order;
    previous = e;
  }
  for (Scalar eps : {1e-4, 1e-9, 1e-13}) {
    Laplace2dConfig config;
    config.eps = eps;
    config.gradient = true;
    laplace2d(pts.data(), c.q.data(), n, nullptr, n, config, phi.data(), grad.data(), interrupt);
    EXPECT_LT(error(phi, ref), eps) << "phi, eps " << eps;
    EXPECT_LT(error(grad, gref), eps) << "gradient, eps " << eps;
  }
}

}  // namespace kinema::fmm
