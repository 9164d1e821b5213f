// Contact kernels in C++: the BVH box query against brute force, the closest-point distance
// derivatives against central differences, and ACCD's conservativeness.
#include <gtest/gtest.h>

#include <algorithm>
#include <random>
#include <vector>

#include "contact/ccd.h"
#include "contact/distance.h"
#include "geometry/bvh.h"

namespace kinema::contact {

// A random query box, the primitives the BVH reports for it (sorted) and those whose boxes
// overlap it by brute force.
template <class Rng>
void query_and_brute_force(const geometry::Bvh& bvh, const std::vector<Scalar>& lo, const std::vector<Scalar>& hi,
                           Rng& rng, std::vector<Index>& found, std::vector<Index>& expected) {
  std::uniform_real_distribution<Scalar> u(0, 1);
  Scalar qlo[3], qhi[3];
  for (int a = 0; a < 3; ++a) {
    qlo[a] = u(rng);
    qhi[a] = qlo[a] + 0.1 * u(rng);
  }
  found.clear();
  expected.clear();
  bvh.query(qlo, qhi, [&](Index i) { found.push_back(i); });
  std::sort(found.begin(), found.end());
  for (size_t i = 0; i < lo.size() / 3; ++i) {
    bool overlap = true;
    for (size_t a = 0; a < 3; ++a) overlap = overlap && lo[3 * i + a] <= qhi[a] && qlo[a] <= hi[3 * i + a];
    if (overlap) expected.push_back(static_cast<Index>(i));
  }
}

TEST(GeometryBvh, BoxQueryFindsEveryOverlappingBoxAndPrunesTheRest) {
  std::mt19937 rng(3);
  std::uniform_real_distribution<Scalar> u(0, 1), w(0, 0.05);
  const int n = 2000;
  std::vector<Scalar> lo(3 * n), hi(3 * n);
  for (int i = 0; i < 3 * n; ++i) {
    lo[i] = u(rng);
    hi[i] = lo[i] + w(rng);
  }
  const geometry::Bvh bvh(lo, hi);
  std::vector<Index> found, expected;
  for (int q = 0; q < 50; ++q) {
    query_and_brute_force(bvh, lo, hi, rng, found, expected);
    // Every overlapping box is found (the leaves' other primitives may come along), and the
    // tree prunes: a leaf holds at most kMaxLeafSize primitives.
    EXPECT_TRUE(std::includes(found.begin(), found.end(), expected.begin(), expected.end())) << "query " << q;
    EXPECT_LE(found.size(), static_cast<size_t>(geometry::Bvh::kMaxLeafSize) * (expected.size() + 8)) << "query " << q;
  }
}

TEST(ContactDistance, PointTriangleAndEdgeEdgeDerivativesMatchCentralDifferences) {
  std::mt19937 rng(5);
  std::normal_distribution<Scalar> g(0, 1);
  for (PairKind kind : {PairKind::PE, PairKind::PT, PairKind::EE}) {
    const int k = vertex_count(kind);
    Vec3 v[4];
    for (int a = 0; a < k; ++a) v[a] = Vec3(g(rng), g(rng), g(rng));
    Vec<12> grad;
    Mat<12> H;
    reduced_derivatives(kind, v, grad, H);
    const Scalar eps = 1e-6;
    for (int i = 0; i < 3 * k; ++i) {
      Vec3 p[4], m[4];
      std::copy(v, v + 4, p);
      std::copy(v, v + 4, m);
      p[i / 3][i % 3] += eps;
      m[i / 3][i % 3] -= eps;
      const Scalar fd = (reduced_distance(kind, p) - reduced_distance(kind, m)) / (2 * eps);
      EXPECT_NEAR(fd, grad[i], 1e-6 * grad.cwiseAbs().maxCoeff()) << "kind " << k << " entry " << i;
      Vec<12> gp, gm;
      Mat<12> Hp;
      reduced_derivatives(kind, p, gp, Hp);
      reduced_derivatives(kind, m, gm, Hp);
      for (int j = 0; j < 3 * k; ++j)
        EXPECT_NEAR((gp[j] - gm[j]) / (2 * eps), H(j, i), 1e-5 * H.cwiseAbs().maxCoeff());
    }
  }
}

TEST(GeometryBvh, RefitQueriesStayExactAfterTheBoxesMove) {
  std::mt19937 rng(5);
  std::uniform_real_distribution<Scalar> u(0, 1), w(0, 0.05), step(-0.2, 0.2);
  const int n = 1500;
  std::vector<Scalar> lo(3 * n), hi(3 * n);
  for (int i = 0; i < 3 * n; ++i) {
    lo[i] = u(rng);
    hi[i] = lo[i] + w(rng);
  }
  geometry::Bvh bvh(lo, hi);
  const std::vector<geometry::BvhNode> built = bvh.nodes();
  const Scalar built_ratio = bvh.area_ratio();
  // Refitting to the boxes it was built from reproduces every node box exactly.
  bvh.refit(lo, hi);
  for (size_t k = 0; k < built.size(); ++k)
    for (int a = 0; a < 3; ++a) {
      ASSERT_EQ(bvh.nodes()[k].lo[a], built[k].lo[a]) << "node " << k;
      ASSERT_EQ(bvh.nodes()[k].hi[a], built[k].hi[a]) << "node " << k;
    }
  EXPECT_EQ(bvh.area_ratio(), built_ratio);
  // Move every box at random: the refit tree still finds every overlapping box.
  for (int i = 0; i < n; ++i)
    for (int a = 0; a < 3; ++a) {
      const Scalar d = step(rng);
      lo[3 * i + a] += d;
      hi[3 * i + a] += d;
    }
  bvh.refit(lo, hi);
  EXPECT_GT(bvh.area_ratio(), built_ratio);  // the old grouping fits the moved boxes worse
  std::vector<Index> found, expected;
  for (int q = 0; q < 50; ++q) {
    query_and_brute_force(bvh, lo, hi, rng, found, expected);
    EXPECT_TRUE(std::includes(found.begin(), found.end(), expected.begin(), expected.end())) << "query " << q;
  }
}

TEST(ContactCcd, PointThroughTriangleStopsBeforeThePlane) {
  const Vec3 t0(-1, -1, 0), t1(2, -1, 0), t2(-1, 2, 0), zero = Vec3::Zero();
  const Scalar t = point_triangle_ccd(Vec3(0.1, 0.1, 1), t0, t1, t2, Vec3(0, 0, -2), zero, zero, zero, 1.0);
  EXPECT_GT(t, 0.4);
  EXPECT_LT(t, 0.5);  // the plane is reached at t = 0.5
}

}  // namespace kinema::contact
