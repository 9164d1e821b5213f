// The neighbour-row sums of the SPH light passes (sph/kernels.h: row_dot, row_weighted, and
// row_dot over padded velocities): the AVX2 versions equal the baseline bit for bit (same operations in the same order, no FMA), and
// both agree with a long-double reference within the rounding bound of their summation.
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

}  // namespace kinema
