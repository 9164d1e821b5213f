// The DFSPH solves' pairs stored once per pair (sph/pair_blocks.h): the sums over every
// neighbour of a row (weighted: sum_j (c_i + c_j) g_ij; dot: sum_j v_j . g_ij) agree with a
// long-double reference over the full lists within the rounding bound of their summation, on
// symmetric lists (g_ji = -g_ij) spanning several blocks; they do not depend on the thread
// count; and the AVX2 version equals the baseline bit for bit.
#include <gtest/gtest.h>

#include <omp.h>

#include <cmath>
#include <cstdint>
#include <limits>
#include <random>
#include <vector>

#include "sph/pair_blocks.h"

namespace kinema {

namespace {

// Symmetric full lists over n particles: pairs within one block and across blocks (near and
// far in index), random lengths (some rows empty), antisymmetric float gradients of mixed
// magnitudes, velocities and weights of mixed signs.
template <int D>
struct SymmetricRows {
  Index n;
  std::vector<Index> start{0};
  std::vector<std::int32_t> list;
  std::vector<float> grads;
  std::vector<Scalar> v, c;

  explicit SymmetricRows(Index n_) : n(n_) {
    std::mt19937 rng(7);
    std::uniform_real_distribution<Scalar> u(-1, 1);
    std::vector<std::vector<std::pair<std::int32_t, std::vector<float>>>> rows(static_cast<size_t>(n));
    for (Index i = 0; i < n; ++i) {
      const int extra = static_cast<int>(i % 17);
      for (int e = 0; e < extra; ++e) {
        // Mostly nearby indices (a Morton order's neighbours), some anywhere.
        Index j = e % 5 == 0 ? static_cast<Index>((u(rng) + 1) / 2 * (n - 1)) : i + 1 + static_cast<Index>(e * 37 % 300);
        if (j >= n || j == i) continue;
        std::vector<float> g(D);
        for (int a = 0; a < D; ++a) g[a] = static_cast<float>(1e4 * u(rng) * std::exp(2 * u(rng)));
        std::vector<float> minus(D);
        for (int a = 0; a < D; ++a) minus[a] = -g[a];
        rows[static_cast<size_t>(i)].push_back({static_cast<std::int32_t>(j), g});
        rows[static_cast<size_t>(j)].push_back({static_cast<std::int32_t>(i), minus});
      }
    }
    for (Index i = 0; i < n; ++i) {
      for (const auto& [j, g] : rows[static_cast<size_t>(i)]) {
        list.push_back(j);
        grads.insert(grads.end(), g.begin(), g.end());
      }
      start.push_back(static_cast<Index>(list.size()));
    }
    for (Index i = 0; i < D * n; ++i) v.push_back(3 * u(rng) * std::exp(2 * u(rng)));
    for (Index i = 0; i < n; ++i) c.push_back(1e-6 * u(rng));
  }
};

// gamma_k = k u / (1 - k u) for a row of `length` entries: each term passes through one
// multiplication and at most length + 5 additions (the row's accumulator of its lower in-block
// neighbours is one chain of up to `length` terms; then the partial sums, their combination, the
// accumulator's addition and the components').
Scalar gamma_bound(Index length) {
  const Scalar k = static_cast<Scalar>(length + 6);
  const Scalar u = std::numeric_limits<Scalar>::epsilon() / 2;
  return k * u / (1 - k * u);
}

template <int D>
struct Sums {
  std::vector<Scalar> weighted, dot;
};

template <int D>
Sums<D> sums(sph::PairBlocks<D>& p, const SymmetricRows<D>& r, bool avx2) {
  Sums<D> out;
  out.weighted.assign(static_cast<size_t>(D * r.n), std::nan(""));
  out.dot.assign(static_cast<size_t>(r.n), std::nan(""));
  p.weighted(r.c.data(), avx2, [&](Index i, const auto& s) {
    for (int a = 0; a < D; ++a) out.weighted[static_cast<size_t>(i * D + a)] = s[a];
  });
  p.dot(r.v.data(), avx2, [&](Index i, Scalar s) { out.dot[static_cast<size_t>(i)] = s; });
  return out;
}

template <int D>
void expect_sums_agree_with_reference() {
  const Index n = 3 * sph::PairBlocks<D>::kBlock + 123;
  const SymmetricRows<D> r(n);
  sph::PairBlocks<D> p;
  p.build(n, r.start.data(), r.list.data(), r.grads.data());
  // Fewer entries than the full lists: the in-block pairs are stored once.
  EXPECT_LT(static_cast<Index>(p.entries.size()), static_cast<Index>(r.list.size()));
  const Sums<D> got = sums(p, r, false);
  for (Index i = 0; i < n; ++i) {
    long double dot = 0, dot_abs = 0, w[D] = {}, w_abs[D] = {};
    for (Index k = r.start[i]; k < r.start[i + 1]; ++k) {
      const Index j = r.list[k];
      for (int a = 0; a < D; ++a) {
        const long double g = r.grads[k * D + a];
        dot += r.v[j * D + a] * g;
        dot_abs += std::fabs(r.v[j * D + a] * g);
        w[a] += (r.c[i] + r.c[j]) * g;
        w_abs[a] += std::fabs((r.c[i] + r.c[j]) * g);
      }
    }
    const Scalar bound = gamma_bound(r.start[i + 1] - r.start[i]);
    EXPECT_LE(std::fabs(got.dot[i] - static_cast<Scalar>(dot)), bound * dot_abs) << "dot, row " << i;
    for (int a = 0; a < D; ++a)
      EXPECT_LE(std::fabs(got.weighted[i * D + a] - static_cast<Scalar>(w[a])), bound * w_abs[a])
          << "weighted, row " << i << ", component " << a;
  }
}

}  // namespace

TEST(SphPairBlocks, SumsAgreeWithLongDoubleReference2D) { expect_sums_agree_with_reference<2>(); }
TEST(SphPairBlocks, SumsAgreeWithLongDoubleReference3D) { expect_sums_agree_with_reference<3>(); }

TEST(SphPairBlocks, SumsDoNotDependOnThreadCount) {
  const Index n = 5 * sph::PairBlocks<3>::kBlock + 7;
  const SymmetricRows<3> r(n);
  sph::PairBlocks<3> p;
  const int threads = omp_get_max_threads();
  omp_set_num_threads(1);
  p.build(n, r.start.data(), r.list.data(), r.grads.data());
  const Sums<3> one = sums(p, r, false);
  omp_set_num_threads(2);
  sph::PairBlocks<3> q;
  q.build(n, r.start.data(), r.list.data(), r.grads.data());
  const Sums<3> two = sums(q, r, false);
  omp_set_num_threads(threads);
  for (size_t k = 0; k < one.dot.size(); ++k) ASSERT_EQ(one.dot[k], two.dot[k]) << "dot, row " << k;
  for (size_t k = 0; k < one.weighted.size(); ++k) ASSERT_EQ(one.weighted[k], two.weighted[k]) << "weighted, entry " << k;
}

TEST(SphPairBlocks, Avx2EqualsBaselineBitwise) {
  if (!cpu_has_avx2()) GTEST_SKIP() << "this CPU has no AVX2";
#if defined(__FMA__)
  GTEST_SKIP() << "built with FMA (-march=native): the baseline may contract its multiply-adds";
#endif
  const Index n = 2 * sph::PairBlocks<3>::kBlock + 555;
  const SymmetricRows<3> r(n);
  sph::PairBlocks<3> p;
  p.build(n, r.start.data(), r.list.data(), r.grads.data());
  const Sums<3> base = sums(p, r, false), wide = sums(p, r, true);
  for (size_t k = 0; k < base.dot.size(); ++k) ASSERT_EQ(base.dot[k], wide.dot[k]) << "dot, row " << k;
  for (size_t k = 0; k < base.weighted.size(); ++k)
    ASSERT_EQ(base.weighted[k], wide.weighted[k]) << "weighted, entry " << k;
}

}  // namespace kinema
