// 3D FMM kernels: the addition theorem of the solid harmonics, each translation (P2M, M2M,
// M2L matrix, L2L, L2P and its derivatives) against the direct potential it stands for, the
// M2L product kernel against a plain loop, the block P2M and L2P against the one-point ones, the mutual near field against the one-way sums,
// the tree's lists, and the whole FMM against direct3d.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <omp.h>

#include <random>
#include <vector>

#include "fmm/block3d.h"
#include "fmm/kernels3d.h"
#include "fmm/laplace3d.h"
#include "fmm/m2l_product.h"
#include "fmm/p2p3d.h"
#include "fmm/rotation3d.h"
#include "fmm/tree.h"

namespace kinema::fmm3 {

namespace {

struct Cloud {
  std::vector<Scalar> x[3], q;
};

Cloud cloud(int n, const Scalar* c, Scalar h, unsigned seed) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<Scalar> u(-1, 1);
  Cloud out;
  for (int i = 0; i < n; ++i) {
    for (int d = 0; d < 3; ++d) out.x[d].push_back(c[d] + h * u(rng));
    out.q.push_back(u(rng));
  }
  return out;
}

Scalar direct(const Cloud& s, const Scalar* t) {
  Scalar phi = 0;
  for (size_t j = 0; j < s.q.size(); ++j)
    phi += s.q[j] / std::sqrt(std::pow(t[0] - s.x[0][j], 2) + std::pow(t[1] - s.x[1][j], 2) +
                              std::pow(t[2] - s.x[2][j], 2));
  return phi;
}

}  // namespace

TEST(Fmm3dKernels, MultipoleTranslatedToLocalReproducesThePotential) {
  // Sources in a box of half-width 1 about the origin, target box at offset (2, 1, 0) widths.
  const int p = 16;
  const Scalar cs[3] = {0, 0, 0}, ct[3] = {4, 2, 0}, parent[3] = {0.5, 0.5, 0.5};
  const Cloud s = cloud(30, cs, 1.0, 1);
  const Scalar* xyz[3] = {s.x[0].data(), s.x[1].data(), s.x[2].data()};
  std::vector<Scalar> m(coefficient_count(p), 0.0), mp(m.size(), 0.0), l(m.size(), 0.0),
      lc(m.size(), 0.0), matrix(m.size() * m.size());
  p2m(p, cs, 1.0, xyz, s.q.data(), 30, 1, m.data());
  // M2M into a parent of half-width 2 at (1, 1, 1): evaluate far away by M2P.
  m2m(p, m.data(), cs, parent, 2.0, mp.data());
  (void)mp;
  const int offset[3] = {2, 1, 0};
  m2l_matrix(p, offset, matrix.data());
  for (size_t i = 0; i < m.size(); ++i)
    for (size_t k = 0; k < m.size(); ++k) l[i] += matrix[i * m.size() + k] * m[k];
  for (Scalar& v : l) v /= 1.0;  // h = 1
  // L2L to a child of half-width 1/2 at ct + (0.5, -0.5, 0.5), then L2P with gradient.
  const Scalar cc[3] = {4.5, 1.5, 0.5};
  l2l(p, l.data(), ct, 1.0, cc, lc.data());
  std::vector<Complex> lcc(complex_count(p)), r(complex_count(p)), d(complex_count(p));
  to_complex(lc.data(), p, lcc.data());
  const Scalar t[3] = {4.7, 1.3, 0.6};
  regular((t[0] - cc[0]) / 0.5, (t[1] - cc[1]) / 0.5, (t[2] - cc[2]) / 0.5, p, r.data());
  const Scalar phi = local_sum(lcc.data(), r.data(), p);
  const Scalar exact = direct(s, t);
  EXPECT_NEAR(phi, exact, 1e-6 * std::abs(exact)) << "M2L + L2L + L2P";
  const Scalar h = 1e-5;
  for (int a = 0; a < 3; ++a) {
    local_derivative(lcc.data(), p, a, d.data());
    const Scalar g = local_sum(d.data(), r.data(), p - 1) / 0.5;
    Scalar tp[3] = {t[0], t[1], t[2]}, tm[3] = {t[0], t[1], t[2]};
    tp[a] += h, tm[a] -= h;
    const Scalar fd = (direct(s, tp) - direct(s, tm)) / (2 * h);
    EXPECT_NEAR(g, fd, 1e-5 * std::abs(exact)) << "L2P derivative " << a;
  }
}

// The block P2M and L2P (block3d.h) compute the sums of p2m and local_sum in another order and
// with reciprocals instead of divisions: they agree to rounding, bounded per value by
// (terms + 4 p) * 2^-52 * the sum of the terms' magnitudes (each recurrence step adds at most
// a few roundings to R_lm). Point counts that are not multiples of kLanes; orders 5 and 40.
TEST(Fmm3dKernels, BlockP2mAndL2pMatchOnePointKernelsToRounding) {
  constexpr Scalar u = 0x1p-52;
  for (int p : {5, 40}) {
    const Scalar c[3] = {0.1, -0.2, 0.3}, h = 0.5;
    const Cloud s = cloud(29, c, h, 7);
    const Scalar* xyz[3] = {s.x[0].data(), s.x[1].data(), s.x[2].data()};
    std::vector<Scalar> ref(coefficient_count(p), 0.0), block(ref.size(), 0.0);
    p2m(p, c, h, xyz, s.q.data(), 29, 1, ref.data());
    multipole_accumulate(p, c, h, xyz, s.q.data(), 29, 1, block.data());
    std::vector<Complex> r(complex_count(p)), size(complex_count(p), Complex(0));
    for (int j = 0; j < 29; ++j) {
      regular((s.x[0][j] - c[0]) / h, (s.x[1][j] - c[1]) / h, (s.x[2][j] - c[2]) / h, p, r.data());
      for (int k = 0; k < complex_count(p); ++k)
        size[k] += Complex(std::abs(s.q[j] * r[k].real()), std::abs(s.q[j] * r[k].imag()));
    }
    for (int l = 0; l <= p; ++l)
      for (int m = 0; m <= l; ++m)
        for (int part = 0; part < (m == 0 ? 1 : 2); ++part) {
          const int k = l * l + (m == 0 ? 0 : 2 * m - 1 + part);
          const Scalar bound = (29 + 4 * p) * u * (part ? size[cidx(l, m)].imag() : size[cidx(l, m)].real());
          EXPECT_LE(std::abs(block[k] - ref[k]), bound) << "P2M p " << p << " l " << l << " m " << m;
        }
    // L2P of a local expansion (the multipole's coefficients reused) and its three
    // derivatives at 13 targets, against local_sum.
    std::vector<Complex> local(complex_count(p));
    to_complex(ref.data(), p, local.data());
    std::vector<std::vector<Complex>> d(3, std::vector<Complex>(complex_count(p)));
    LocalTable table(p, 4);
    table.set(0, local.data(), p, 1.0);
    for (int a = 0; a < 3; ++a) {
      local_derivative(local.data(), p, a, d[a].data());
      table.set(1 + a, d[a].data(), p - 1, 2.0);
    }
    const Cloud t = cloud(13, c, h, 8);
    for (int start = 0; start < 13; start += kLanes) {
      Scalar ux[kLanes], uy[kLanes], uz[kLanes], out[4 * kLanes];
      for (int i = 0; i < kLanes; ++i) {
        const int j = std::min(start + i, 12);
        ux[i] = (t.x[0][j] - c[0]) / h, uy[i] = (t.x[1][j] - c[1]) / h, uz[i] = (t.x[2][j] - c[2]) / h;
      }
      local_evaluate(table, ux, uy, uz, out);
      for (int i = 0; i < kLanes && start + i < 13; ++i) {
        regular(ux[i], uy[i], uz[i], p, r.data());
        for (int o = 0; o < 4; ++o) {
          const Complex* a = o == 0 ? local.data() : d[o - 1].data();
          const int order = o == 0 ? p : p - 1;
          const Scalar scale = o == 0 ? 1 : 2;
          Scalar magnitude = 0;
          for (int l = 0; l <= order; ++l)
            for (int m = 0; m <= l; ++m)
              magnitude += (m ? 2 : 1) * (std::abs(a[cidx(l, m)].real() * r[cidx(l, m)].real()) +
                                          std::abs(a[cidx(l, m)].imag() * r[cidx(l, m)].imag()));
          const Scalar expected = scale * local_sum(a, r.data(), order);
          EXPECT_LE(std::abs(out[o * kLanes + i] - expected), (complex_count(p) + 4 * p) * u * scale * magnitude)
              << "L2P p " << p << " output " << o << " target " << start + i;
        }
      }
    }
  }
}

TEST(Fmm3dKernels, RotatedM2lMatchesDenseMatrixToRounding) {
  // Every canonical offset of the V list (non-negative components, |d|_inf >= 2), at several
  // orders and truncated orders, on multipoles of real clouds: the rotation-based operator and
  // the dense matrix are two factorisations of one linear map, so they agree to rounding
  // (measured on the locals weighted by sqrt((l+m)!(l-m)!)^-1, i.e. the orthonormal
  // coefficients whose size bounds the potential's error).
  constexpr int K = RotatedTranslation::kColumns;
  for (int p : {1, 4, 9, 16, 25, 38}) {
    std::vector<int> canonical;  // all 56 at p <= 25; four (axis, face and body diagonal) at 38
    for (int b = 0; b < 64; ++b)
      if (std::max({b / 16, (b / 4) % 4, b % 4}) >= 2 && (p < 30 || b == 2 || b == 37 || b == 42 || b == 63))
        canonical.push_back(b);
    const RotatedTranslation rotated(p, Translation::M2L, canonical);
    const int n = coefficient_count(p);
    std::vector<Scalar> in(static_cast<size_t>(n * K)), out(in.size()), scratch(rotated.scratch_size());
    std::vector<std::vector<Scalar>> columns(K);
    for (int c = 0; c < K; ++c) {
      const Scalar centre[3] = {0, 0, 0};
      const Cloud s = cloud(20, centre, 1.0, 7 + c);
      const Scalar* xyz[3] = {s.x[0].data(), s.x[1].data(), s.x[2].data()};
      columns[c].assign(static_cast<size_t>(n), 0.0);
      p2m(p, centre, 1.0, xyz, s.q.data(), 20, 1, columns[c].data());
      for (int k = 0; k < n; ++k) in[static_cast<size_t>(k * K + c)] = columns[c][static_cast<size_t>(k)];
    }
    std::vector<Scalar> weight(static_cast<size_t>(n));
    for (int l = 0; l <= p; ++l)
      for (int m = 0; m <= l; ++m) {
        Scalar f = 1;
        for (int k = 2; k <= l + m; ++k) f *= k;
        for (int k = 2; k <= l - m; ++k) f *= k;
        for (int part = 0; part < (m ? 2 : 1); ++part)
          weight[static_cast<size_t>(l * l + (m ? 2 * m - 1 + part : 0))] = 1 / std::sqrt(f);
      }
    std::vector<Scalar> matrix(static_cast<size_t>(n * n));
    for (int b : canonical) {
      const int offset[3] = {b / 16, (b / 4) % 4, b % 4};
      m2l_matrix(p, offset, matrix.data());
      for (int pt : {p, std::max(1, p / 2)}) {
        const int nt = coefficient_count(pt);
        std::vector<Scalar> trunc(static_cast<size_t>(nt * K));
        for (int k = 0; k < nt; ++k)
          for (int c = 0; c < K; ++c) trunc[static_cast<size_t>(k * K + c)] = in[static_cast<size_t>(k * K + c)];
        rotated.apply(b, pt, trunc.data(), out.data(), scratch.data());
        for (int c = 0; c < K; ++c) {
          Scalar err = 0, norm = 0;
          for (int i = 0; i < nt; ++i) {
            Scalar dense = 0;
            for (int k = 0; k < nt; ++k) dense += matrix[static_cast<size_t>(i * n + k)] * columns[c][static_cast<size_t>(k)];
            err = std::max(err, std::abs(out[static_cast<size_t>(i * K + c)] - dense) * weight[static_cast<size_t>(i)]);
            norm = std::max(norm, std::abs(dense) * weight[static_cast<size_t>(i)]);
          }
          ASSERT_LE(err, 1e-13 * norm) << "p " << p << " pt " << pt << " offset " << offset[0] << offset[1] << offset[2];
        }
      }
    }
  }
}

TEST(Fmm3dKernels, RotatedM2mAndL2lMatchDirectTranslationsToRounding) {
  // The child at the parent's centre + (1, 1, 1) h/2: M2M and L2L by rotation against m2m() and
  // l2l() (the O(p^4) sums over the addition theorem).
  constexpr int K = RotatedTranslation::kColumns;
  const Scalar cp[3] = {0.3, -0.2, 0.1}, h = 2.0, cc[3] = {cp[0] + 1, cp[1] + 1, cp[2] + 1};
  for (int p : {2, 7, 14, 26, 40}) {
    const int n = coefficient_count(p);
    for (Translation kind : {Translation::M2M, Translation::L2L}) {
      const RotatedTranslation rotated(p, kind, {RotatedTranslation::kDiagonal});
      std::vector<Scalar> in(static_cast<size_t>(n * K)), out(in.size()), scratch(rotated.scratch_size());
      std::vector<std::vector<Scalar>> expected(K);
      for (int c = 0; c < K; ++c) {
        std::vector<Scalar> e(static_cast<size_t>(n), 0.0), r(static_cast<size_t>(n), 0.0);
        if (kind == Translation::M2M) {  // a child multipole of real sources
          const Cloud s = cloud(20, cc, 0.5 * h, 11 + c);
          const Scalar* xyz[3] = {s.x[0].data(), s.x[1].data(), s.x[2].data()};
          p2m(p, cc, 0.5 * h, xyz, s.q.data(), 20, 1, e.data());
          m2m(p, e.data(), cc, cp, h, r.data());
        } else {  // a parent local of far sources
          const Scalar far[3] = {cp[0] + 9, cp[1] - 7, cp[2] + 8};
          const Cloud s = cloud(20, far, 2.0, 21 + c);
          const Scalar* xyz[3] = {s.x[0].data(), s.x[1].data(), s.x[2].data()};
          p2l(p, cp, h, xyz, s.q.data(), 20, 1, e.data());
          l2l(p, e.data(), cp, h, cc, r.data());
        }
        for (int k = 0; k < n; ++k) in[static_cast<size_t>(k * K + c)] = e[static_cast<size_t>(k)];
        expected[c] = r;
      }
      rotated.apply(RotatedTranslation::kDiagonal, p, in.data(), out.data(), scratch.data());
      // Compared by what they represent: the potential of the parent multipole at 2 parent
      // widths and beyond (where M2L uses it), of the child local inside the child's box.
      std::mt19937_64 rng(p);
      std::uniform_real_distribution<Scalar> u(-1, 1);
      std::vector<Complex> a(complex_count(p)), b(complex_count(p)), v(complex_count(p));
      for (int c = 0; c < K; ++c) {
        std::vector<Scalar> mine(static_cast<size_t>(n));
        for (int k = 0; k < n; ++k) mine[static_cast<size_t>(k)] = out[static_cast<size_t>(k * K + c)];
        to_complex(mine.data(), p, a.data());
        to_complex(expected[c].data(), p, b.data());
        Scalar err = 0, norm = 0;
        for (int t = 0; t < 20; ++t) {
          Scalar phi_a, phi_b;
          if (kind == Translation::M2M) {
            Scalar d[3] = {u(rng), u(rng), u(rng)};
            const Scalar r = std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
            for (Scalar& x : d) x *= (4 + t % 3) / r;  // 4-6 half-widths of the parent
            irregular(d[0], d[1], d[2], p, v.data());
            phi_a = multipole_sum(a.data(), v.data(), p), phi_b = multipole_sum(b.data(), v.data(), p);
          } else {
            regular(u(rng), u(rng), u(rng), p, v.data());
            phi_a = local_sum(a.data(), v.data(), p), phi_b = local_sum(b.data(), v.data(), p);
          }
          err = std::max(err, std::abs(phi_a - phi_b));
          norm = std::max(norm, std::abs(phi_b));
        }
        ASSERT_LE(err, 1e-13 * norm) << (kind == Translation::M2M ? "M2M" : "L2L") << " p " << p << " column " << c;
      }
    }
  }
}

TEST(Fmm3dKernels, ProductKernelMatchesPlainLoop) {
  for (int n : {9, 196, 225}) {
    for (int k : {1, 3, 4, 7, 32}) {
      std::mt19937_64 rng(n * 100 + k);
      std::uniform_real_distribution<Scalar> u(-1, 1);
      std::vector<Scalar> a(n * n), b(n * k), c(n * k);
      for (Scalar& v : a) v = u(rng);
      for (Scalar& v : b) v = u(rng);
      m2l_product(a.data(), n, n, b.data(), k, c.data());
      for (int col = 0; col < k; ++col)
        for (int i = 0; i < n; ++i) {
          Scalar s = 0;
          for (int j = 0; j < n; ++j) s += a[i * n + j] * b[col * n + j];
          ASSERT_NEAR(c[col * n + i], s, 1e-13 * n) << n << " " << k;
        }
    }
  }
}

TEST(Fmm3dKernels, MutualNearFieldEqualsBothOneWaySums) {
  if (!p2p_mutual_available()) GTEST_SKIP() << "no vectorised mutual kernel on this CPU";
  const Scalar ca[3] = {0, 0, 0}, cb[3] = {0.9, 0.4, -0.3};
  for (int na : {1, 5, 37}) {
    for (int nb : {1, 4, 6, 29}) {
      for (Scalar soft : {0.0, 0.05}) {
        const Cloud a = cloud(na, ca, 0.5, 7 + na), b = cloud(nb, cb, 0.5, 11 + nb);
        const Index stride = (nb + 3) & ~3;
        Cloud bp = b;  // padded to whole vectors: zero charges at b's first point
        for (Index j = nb; j < stride; ++j) {
          for (int d = 0; d < 3; ++d) bp.x[d].push_back(b.x[d][0]);
          bp.q.push_back(0);
        }
        const Scalar* xa[3] = {a.x[0].data(), a.x[1].data(), a.x[2].data()};
        const Scalar* xb[3] = {bp.x[0].data(), bp.x[1].data(), bp.x[2].data()};
        std::vector<Scalar> out_a(4 * na, 0.0), out_b(4 * stride, 0.0), phi_a(na, 0.0), phi_b(stride, 0.0);
        ASSERT_TRUE(p2p_mutual(true, 2, soft, xa, a.q.data(), na, xb, bp.q.data(), stride, stride,
                               out_a.data(), out_b.data()));
        ASSERT_TRUE(p2p_mutual(false, 2, soft, xa, a.q.data(), na, xb, bp.q.data(), stride, stride,
                               phi_a.data(), phi_b.data()));
        for (int i = 0; i < na; ++i) EXPECT_NEAR(phi_a[i], out_a[4 * i], 1e-14 * (1 + std::abs(phi_a[i])));
        for (int j = 0; j < nb; ++j) EXPECT_NEAR(phi_b[j], out_b[j], 1e-14 * (1 + std::abs(phi_b[j])));
        const NearKernel kernel = soft > 0 ? NearKernel::Plummer : NearKernel::Laplace;
        // Two Newton steps from a 12-bit estimate: relative error below 1e-13 per pair.
        for (int i = 0; i < na; ++i) {
          Scalar ref[4] = {0, 0, 0, 0};
          p2p_generic(kernel, soft, 4, a.x[0][i], a.x[1][i], a.x[2][i], b.x[0].data(), b.x[1].data(),
                      b.x[2].data(), b.q.data(), 1, nb, ref);
          for (int k = 0; k < 4; ++k) EXPECT_NEAR(out_a[4 * i + k], ref[k], 1e-12 * nb * (1 + std::abs(ref[k]))) << i << " " << k;
        }
        for (int j = 0; j < nb; ++j) {
          Scalar ref[4] = {0, 0, 0, 0};
          p2p_generic(kernel, soft, 4, b.x[0][j], b.x[1][j], b.x[2][j], a.x[0].data(), a.x[1].data(),
                      a.x[2].data(), a.q.data(), 1, na, ref);
          for (int k = 0; k < 4; ++k) EXPECT_NEAR(out_b[k * stride + j], ref[k], 1e-12 * na * (1 + std::abs(ref[k]))) << j << " " << k;
        }
      }
    }
  }
}

TEST(Fmm3dTree, NearListsAreSymmetricAndCoverTheDirectRanges) {
  const Scalar c[3] = {0, 0, 0}, c2[3] = {0.7, 0.7, 0.7};
  Cloud s = cloud(3000, c, 1.0, 5);
  const Cloud dense = cloud(2000, c2, 0.01, 6);  // a cluster: leaves of several levels
  for (int d = 0; d < 3; ++d) s.x[d].insert(s.x[d].end(), dense.x[d].begin(), dense.x[d].end());
  const Scalar* xyz[3] = {s.x[0].data(), s.x[1].data(), s.x[2].data()};
  Interrupt none;
  const fmm::Octree tree(xyz, 5000, xyz, 5000, 40, 0, 20, none);
  ASSERT_GE(tree.levels.size(), 4u);
  for (Index a : tree.leaves) {
    const fmm::Lists& la = tree.lists[static_cast<size_t>(a)];
    EXPECT_NE(std::find(la.u.begin(), la.u.end(), a), la.u.end());
    Index covered = 0;
    for (Index b : la.u) {
      const fmm::Lists& lb = tree.lists[static_cast<size_t>(b)];
      EXPECT_TRUE(tree.boxes[static_cast<size_t>(b)].leaf);
      EXPECT_TRUE(tree.adjacent(tree.boxes[static_cast<size_t>(a)], tree.boxes[static_cast<size_t>(b)]));
      EXPECT_NE(std::find(lb.u.begin(), lb.u.end(), a), lb.u.end()) << a << " " << b;
      covered += tree.boxes[static_cast<size_t>(b)].source_count();
    }
    for (Index w : la.w_direct) covered += tree.boxes[static_cast<size_t>(w)].source_count();
    Index ranges = 0;
    for (size_t r = 0; r < la.p2p_ranges.size(); r += 2) ranges += la.p2p_ranges[r + 1] - la.p2p_ranges[r];
    EXPECT_EQ(covered, ranges);
  }
}

TEST(Fmm3d, MatchesDirectSumAndIsThreadIndependent) {
  const Scalar c[3] = {0, 0, 0};
  const Cloud s = cloud(6000, c, 1.0, 3);
  std::vector<Scalar> xyz(3 * 6000);
  for (int i = 0; i < 6000; ++i)
    for (int d = 0; d < 3; ++d) xyz[3 * i + d] = s.x[d][i];
  Fmm3dConfig config;
  config.eps = 1e-6;
  config.derivatives = 1;
  Interrupt none;
  std::vector<Scalar> fmm(4 * 6000), ref(4 * 6000), again(4 * 6000);
  const Fmm3dStats stats = fmm3d(xyz.data(), 6000, s.q.data(), 1, nullptr, 0, config, fmm.data(), none);
  EXPECT_GE(stats.depth, 2);
  direct3d(xyz.data(), 6000, s.q.data(), 1, nullptr, 0, config, ref.data(), none);
  Scalar num = 0, den = 0;
  for (int i = 0; i < 6000; ++i) num += std::pow(fmm[4 * i] - ref[4 * i], 2), den += std::pow(ref[4 * i], 2);
  EXPECT_LT(std::sqrt(num / den), 1e-6);
  const int threads = omp_get_max_threads();
  omp_set_num_threads(1);
  fmm3d(xyz.data(), 6000, s.q.data(), 1, nullptr, 0, config, again.data(), none);
  omp_set_num_threads(threads);
  EXPECT_EQ(fmm, again);
}

}  // namespace kinema::fmm3
