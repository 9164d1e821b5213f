// The neighbour-row sums of the SPH light passes (sph/kernels.h: row_dot, row_weighted, and
// row_dot over padded velocities): the AVX2 versions equal the baseline bit for bit (same operations in the same order, no FMA), and
// both agree with a long-double reference within the rounding bound of their summation. Also the
// kernel pass's kernel values (kernel_values_avx2 against CubicSpline::values).
#include <gtest/gtest.h>

#include <cmath>
#include <cstdint>
#include <limits>
#include <random>
#include <vector>

#include "sph/kernels.h"

namespace kinema {

namespace {

// Random CSR rows over n particles with every length from 0 to 45 (so every remainder mod 4
// and rows shorter than one group of four), random neighbours, gradients, velocities and
// weights of mixed signs and magnitudes.
struct RandomRows {
  Index n = 300;
  std::vector<Index> start{0};
  std::vector<std::int32_t> list;
  std::vector<float> grads;
  std::vector<Scalar> v, c;

  RandomRows() {
    std::mt19937 rng(11);
    std::uniform_real_distribution<Scalar> u(-1, 1);
    std::uniform_int_distribution<std::int32_t> pick(0, static_cast<std::int32_t>(n - 1));
    for (Index i = 0; i < n; ++i) {
      const Index length = i % 46;
      for (Index e = 0; e < length; ++e) {
        list.push_back(pick(rng));
        for (int a = 0; a < 3; ++a) grads.push_back(static_cast<float>(1e4 * u(rng)));
      }
      start.push_back(static_cast<Index>(list.size()));
    }
    // The padding float the row sums may read (kernels.h): a NaN, so that a result that used
    // it would show.
    grads.push_back(std::numeric_limits<float>::quiet_NaN());
    for (Index i = 0; i < 3 * n; ++i) v.push_back(3 * u(rng) * std::exp(2 * u(rng)));
    for (Index i = 0; i < n; ++i) c.push_back(1e-6 * u(rng));
  }
};

// gamma_k = k u / (1 - k u): each term of a row of `length` entries passes through one
// multiplication and at most length / 4 + 4 additions (its partial sum's chain, the
// combination of the partials and of the components). The reference forms row_weighted's
// c_i + c_j in double, as the sums do.
Scalar gamma_bound(Index length) {
  const Scalar k = static_cast<Scalar>(length / 4 + 5);
  const Scalar u = std::numeric_limits<Scalar>::epsilon() / 2;
  return k * u / (1 - k * u);
}

}  // namespace

TEST(SphRows, BaselineSumsAgreeWithLongDoubleReference) {
  const RandomRows r;
  for (Index i = 0; i < r.n; ++i) {
    long double dot = 0, dot_abs = 0, weighted[3] = {}, weighted_abs[3] = {};
    const Scalar ci = r.c[i];
    for (Index k = r.start[i]; k < r.start[i + 1]; ++k) {
      const Index j = r.list[k];
      for (int a = 0; a < 3; ++a) {
        const long double g = r.grads[k * 3 + a];
        dot += r.v[j * 3 + a] * g;
        dot_abs += std::fabs(r.v[j * 3 + a] * g);
        weighted[a] += (ci + r.c[j]) * g;
        weighted_abs[a] += std::fabs((ci + r.c[j]) * g);
      }
    }
    const Scalar bound = gamma_bound(r.start[i + 1] - r.start[i]);
    const Scalar got = sph::row_dot<3>(r.list.data(), r.grads.data(), r.start[i], r.start[i + 1], r.v.data());
    EXPECT_LE(std::fabs(got - static_cast<Scalar>(dot)), bound * dot_abs) << "row_dot, row " << i;
    Scalar out[3];
    sph::row_weighted<3>(r.list.data(), r.grads.data(), r.start[i], r.start[i + 1], ci, r.c.data(), out);
    for (int a = 0; a < 3; ++a)
      EXPECT_LE(std::fabs(out[a] - static_cast<Scalar>(weighted[a])), bound * weighted_abs[a])
          << "row_weighted, row " << i << ", component " << a;
  }
}

TEST(SphRows, Avx2EqualsBaselineBitwise) {
  if (!cpu_has_avx2()) GTEST_SKIP() << "this CPU has no AVX2";
#if defined(__FMA__)
  GTEST_SKIP() << "built with FMA (-march=native): the baseline may contract its multiply-adds";
#endif
  const auto baseline = sph::RowSums<3>::choose(false);
  const auto wide = sph::RowSums<3>::choose(true);
  ASSERT_FALSE(baseline.avx2);
  ASSERT_TRUE(wide.avx2);
  const RandomRows r;
  // The rate sums of DFSPH read the velocities padded to 4 doubles per particle (the fourth 0).
  ASSERT_EQ(baseline.dot4, nullptr);
  ASSERT_NE(wide.dot4, nullptr);
  std::vector<Scalar> v4(static_cast<size_t>(4 * r.n), 0);
  for (Index j = 0; j < r.n; ++j)
    for (int a = 0; a < 3; ++a) v4[static_cast<size_t>(4 * j + a)] = r.v[static_cast<size_t>(3 * j + a)];
  for (Index i = 0; i < r.n; ++i) {
    const Index b = r.start[i], e = r.start[i + 1];
    ASSERT_EQ(baseline.dot(r.list.data(), r.grads.data(), b, e, r.v.data()),
              wide.dot(r.list.data(), r.grads.data(), b, e, r.v.data()))
        << "row_dot, row " << i;
    ASSERT_EQ(baseline.dot(r.list.data(), r.grads.data(), b, e, r.v.data()),
              wide.dot4(r.list.data(), r.grads.data(), b, e, v4.data()))
        << "row_dot over padded velocities, row " << i;
    Scalar out0[3], out1[3];
    baseline.weighted(r.list.data(), r.grads.data(), b, e, r.c[i], r.c.data(), out0);
    wide.weighted(r.list.data(), r.grads.data(), b, e, r.c[i], r.c.data(), out1);
    for (int a = 0; a < 3; ++a) ASSERT_EQ(out0[a], out1[a]) << "row_weighted, row " << i << ", component " << a;
  }
}

// The kernel pass's kernel values (sph/kernels.h): kernel_values_avx2 gives CubicSpline::values'
// r, W and dW/dr / r bit for bit, over distances that cover both pieces of the spline, the
// join q = 1/2, the edge q = 1 and beyond, r = 0 (grad_factor 0) and every tail length (count
// mod 4), in 2D and 3D; and the values are the spline's (kernel_w, kernel_dw / r).
template <int D>
void check_kernel_values() {
  const Scalar h = 0.037;
  const sph::CubicSpline<D> W(h);
  std::mt19937 rng(5);
  std::uniform_real_distribution<Scalar> u(0, 1.1);
  std::vector<Scalar> r2;
  for (const Scalar q : {0.0, 0.5, 1.0, 1e-300, 0.25, 0.75, 0.9999999, 1.0000001})
    r2.push_back(q * h * q * h);
  while (r2.size() < 67) {
    const Scalar q = u(rng);
    r2.push_back(q * h * q * h);
  }
  for (int count = 0; count <= static_cast<int>(r2.size()); ++count) {
    std::vector<Scalar> r0(count), w0(count), g0(count), r1(count), w1(count), g1(count);
    W.values(r2.data(), count, r0.data(), w0.data(), g0.data());
#if KINEMA_HAVE_AVX2_CLONES
    sph::kernel_values_avx2<D>(W, r2.data(), count, r1.data(), w1.data(), g1.data());
#else
    W.values(r2.data(), count, r1.data(), w1.data(), g1.data());
#endif
    for (int e = 0; e < count; ++e) {
      ASSERT_EQ(r0[e], r1[e]) << D << "D, count " << count << ", entry " << e;
      ASSERT_EQ(w0[e], w1[e]) << D << "D, count " << count << ", entry " << e;
      ASSERT_EQ(g0[e], g1[e]) << D << "D, count " << count << ", entry " << e;
    }
  }
  std::vector<Scalar> r(r2.size()), w(r2.size()), g(r2.size());
  W.values(r2.data(), static_cast<int>(r2.size()), r.data(), w.data(), g.data());
  for (size_t e = 0; e < r2.size(); ++e) {
    const Scalar want_w = sph::kernel_w(r[e], h, D);
    const Scalar want_g = r[e] > 0 ? sph::kernel_dw(r[e], h, D) / r[e] : 0;
    EXPECT_NEAR(w[e], want_w, 1e-12 * W.w0()) << "entry " << e;
    EXPECT_NEAR(g[e], want_g, 1e-12 * 12 * W.w0() / (h * h)) << "entry " << e;  // |dW/dr / r| <= 12 sigma / h^2
  }
}

TEST(SphKernelValues, Avx2EqualsBaselineBitwise) {
  if (!cpu_has_avx2()) GTEST_SKIP() << "this CPU has no AVX2";
#if defined(__FMA__)
  GTEST_SKIP() << "built with FMA (-march=native): the baseline may contract its multiply-adds";
#endif
  check_kernel_values<2>();
  check_kernel_values<3>();
}

}  // namespace kinema
