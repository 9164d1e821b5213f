// The contact solver's Newton matrix on a kept block pattern (contact/solver_system.h): its CSR
// view holds exactly the dense sum of the element matrices over the degrees of freedom; a
// contact block missing from the pattern is added with every value kept; a pattern that holds
// is not changed; each step starts from the elastic blocks plus the given stencils' blocks.
#include <gtest/gtest.h>

#include <random>
#include <vector>

#include "contact/solver_system.h"

namespace kinema::contact {

namespace {

// A cloth strip of n x 2 vertices (springs along the triangle edges) and a fixed triangle.
Model strip(int n) {
  std::vector<Scalar> x;
  for (int i = 0; i < n; ++i)
    for (int j = 0; j < 2; ++j) x.insert(x.end(), {Scalar(i), Scalar(j), 0});
  std::vector<Index> tris, springs;
  for (int i = 0; i + 1 < n; ++i) {
    const Index a = 2 * i, b = 2 * i + 1, c = 2 * i + 2, d = 2 * i + 3;
    tris.insert(tris.end(), {a, c, b, b, c, d});
    springs.insert(springs.end(), {a, b, a, c, b, c, b, d, c, d});
  }
  Model model;
  model.add_cloth(x.data(), 2 * n, tris.data(), static_cast<Index>(tris.size() / 3), springs.data(),
                  static_cast<Index>(springs.size() / 2), 1.0, 1.0, nullptr, 0);
  const Scalar ob[9] = {0, 0, 5, 1, 0, 5, 0, 1, 5};
  const Index tri[3] = {0, 1, 2};
  model.add_obstacle(ob, 3, tri, 1);
  return model;
}

using Dense = Eigen::Matrix<Scalar, Eigen::Dynamic, Eigen::Dynamic>;

Dense dense_of(const NewtonSystem& s) {
  const CsrView v = s.view();
  Dense A = Dense::Zero(v.rows, v.cols);
  for (Index r = 0; r < v.rows; ++r)
    for (Index k = v.row_ptr[r]; k < v.row_ptr[r + 1]; ++k) {
      if (k > v.row_ptr[r]) {
        EXPECT_LT(v.col_index[k - 1], v.col_index[k]);  // sorted, unique
      }
      A(r, v.col_index[k]) = v.values[k];
    }
  return A;
}

// Adds the element H over verts into the dense reference (dofs only).
void add_dense(const NewtonSystem& s, Dense& A, const std::vector<Index>& verts, const Dense& H) {
  for (size_t a = 0; a < verts.size(); ++a)
    for (size_t b = 0; b < verts.size(); ++b) {
      const Index i = s.dof(verts[a]), j = s.dof(verts[b]);
      if (i >= 0 && j >= 0) A.block<3, 3>(3 * i, 3 * j) += H.block<3, 3>(3 * a, 3 * b);
    }
}

}  // namespace

TEST(ContactNewtonSystem, HoldsTheDenseSumAndGrowsOnlyForNewContactBlocks) {
  const Model model = strip(6);
  NewtonSystem s(model);
  EXPECT_EQ(s.dof_count(), 12);  // the obstacle's 3 vertices are not unknowns
  EXPECT_EQ(s.dof(12), -1);
  std::mt19937 rng(5);
  std::normal_distribution<Scalar> normal;
  auto random = [&](int k) {
    Dense H(3 * k, 3 * k);
    for (Index e = 0; e < H.size(); ++e) H.data()[e] = normal(rng);
    return H;
  };
  auto assemble = [&](const std::vector<std::vector<Index>>& contacts, Dense& ref) {
    s.clear();
    ref = Dense::Zero(s.size(), s.size());
    for (size_t sp = 0; sp < model.springs.size(); sp += 2) {
      const std::vector<Index> v{model.springs[sp], model.springs[sp + 1]};
      const Dense H = random(2);
      s.add(v.data(), 2, H);
      add_dense(s, ref, v, H);
    }
    for (const auto& v : contacts) {
      const Dense H = random(static_cast<int>(v.size()));
      s.add(v.data(), static_cast<int>(v.size()), H);
      add_dense(s, ref, v, H);
    }
    return s.finish();
  };
  Dense ref;
  s.begin_step({});
  EXPECT_TRUE(assemble({}, ref));  // the first pattern
  EXPECT_EQ(dense_of(s), ref);
  const Index elastic_blocks = s.block_count();
  // A vertex against the obstacle: only its own (diagonal) block, already in the pattern.
  EXPECT_FALSE(assemble({{0, 12, 13, 14}}, ref));
  EXPECT_EQ(dense_of(s), ref);
  // Self-contact of far vertices (0 against edge 10-11): new blocks, every value kept.
  const std::vector<std::vector<Index>> self{{0, 10, 11}, {1, 9, 10, 11}};
  EXPECT_TRUE(assemble(self, ref));
  EXPECT_EQ(dense_of(s), ref);
  EXPECT_GT(s.block_count(), elastic_blocks);
  const std::int64_t version = s.version();
  // The same contacts again, or fewer: the pattern holds.
  EXPECT_FALSE(assemble(self, ref));
  EXPECT_FALSE(assemble({self[0]}, ref));
  EXPECT_EQ(dense_of(s), ref);
  EXPECT_EQ(s.version(), version);
  // A step starting with the same pairs active: the pattern holds.
  s.begin_step(self);
  EXPECT_FALSE(assemble(self, ref));
  EXPECT_EQ(dense_of(s), ref);
  EXPECT_EQ(s.version(), version);
}

TEST(ContactNewtonSystem, EachStepStartsFromTheElasticBlocksAndTheActivePairs) {
  const Model model = strip(40);
  NewtonSystem s(model);
  const Index elastic_blocks = s.block_count();
  // One step meeting many far pairs (vertex a against vertex a + 40): 2 x 40 blocks added.
  s.begin_step({});
  s.clear();
  const Eigen::Matrix<Scalar, 6, 6> H = Eigen::Matrix<Scalar, 6, 6>::Identity();
  for (Index a = 0; a < 40; ++a) {
    const Index v[2] = {a, a + 40};
    s.add(v, 2, H);
  }
  EXPECT_TRUE(s.finish());
  EXPECT_EQ(s.block_count(), elastic_blocks + 80);
  // The next step starts with two of those pairs active: only their 4 blocks stay reserved.
  s.begin_step({{0, 40}, {1, 41}});
  EXPECT_EQ(s.block_count(), elastic_blocks + 4);
  s.clear();
  EXPECT_TRUE(s.finish());  // a new pattern: a new analysis
  s.begin_step({{1, 41}, {0, 40}});
  s.clear();
  EXPECT_FALSE(s.finish());  // the same pairs: the pattern holds
  // Obstacle vertices and pairs within the elastic pattern add nothing.
  s.begin_step({{0, 40}, {1, 41}, {0, 80, 81}, {0, 1}});
  s.clear();
  EXPECT_FALSE(s.finish());
}

}  // namespace kinema::contact
