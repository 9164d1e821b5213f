// The MAC-grid advection kernels (grid/kernels.h), tested without Python: interpolation is
// exact for linear fields, an integer-cell shift in a periodic domain is exact for every
// scheme, the clamped schemes stay within the initial range, and higher-order back-traces
// follow a circular streamline more closely; the node-wise and the row-wise (baseline and AVX2)
// implementations give the same bits.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <random>
#include <string>
#include <vector>

#include "core/errors.h"
#include "core/simd.h"
#include "grid/advect_rows.h"
#include "grid/kernels.h"

namespace kinema::grid {
namespace {

TEST(GridKernels, InterpolationExactForLinearFields) {
  for (const auto& dims : {std::vector<Index>{7, 5}, std::vector<Index>{4, 6, 5}}) {
    const GridShape shape(dims);
    for (int axis = 3 - shape.dim; axis < 3; ++axis) {
      const FieldLayout L = face_layout(shape, axis, false);
      std::vector<Scalar> f(L.size());
      auto linear = [](const Vec3& x) { return 0.3 + 1.5 * x[0] - 2.0 * x[1] + 0.7 * x[2]; };
      for_each_node(L, [&](Index i, Index j, Index k, Index c) {
        f[c] = linear({i + L.offset[0], j + L.offset[1], k + L.offset[2]});
      });
      // interior points (inside the node hull, where no clamping happens)
      for (const Vec3& x : {Vec3{0.7, 1.3, 2.2}, Vec3{0.5, 2.9, 1.01}, Vec3{0.6, 1.5, 3.4}}) {
        Vec3 p = x;
        if (shape.dim == 2) p[0] = L.offset[0];
        EXPECT_NEAR(sample(f.data(), L, p), linear(p), 1e-12) << "axis " << axis << " dim " << shape.dim;
      }
    }
  }
}

TEST(GridKernels, PeriodicIntegerShiftIsExactForEveryScheme) {
  const GridShape shape(std::vector<Index>{16, 12});
  const FieldLayout C = cell_layout(shape, true);
  std::vector<Scalar> u(face_layout(shape, 1, true).size(), 3.0);  // 3 cells per unit time in x
  std::vector<Scalar> v(face_layout(shape, 2, true).size(), -2.0);
  MacVelocity vel;
  for (int a = 0; a < 3; ++a) vel.layout[a] = face_layout(shape, a, true);
  vel.comp[1] = u.data();
  vel.comp[2] = v.data();
  std::vector<Scalar> q(C.size()), out(C.size());
  for_each_node(C, [&](Index, Index j, Index k, Index c) { q[c] = std::sin(0.7 * j) + std::cos(1.3 * k + 0.2 * j); });
  for (auto scheme : {AdvectionScheme::SemiLagrangian, AdvectionScheme::MacCormack, AdvectionScheme::BFECC}) {
    for (int rk = 1; rk <= 3; ++rk) {
      AdvectionScratch scratch;
      advect(scheme, vel, C, q.data(), out.data(), 1.0, rk, scratch);
      for_each_node(C, [&](Index, Index j, Index k, Index c) {
        const Index js = ((j - 3) % 16 + 16) % 16, ks = ((k + 2) % 12 + 12) % 12;
        EXPECT_NEAR(out[c], q[C.index(0, js, ks)], 1e-12)
            << "scheme " << static_cast<int>(scheme) << " rk " << rk << " at " << j << "," << k;
      });
    }
  }
}

// Solid-body rotation about the domain centre, on a closed grid.
struct Rotation {
  GridShape shape{std::vector<Index>{48, 48}};
  std::vector<Scalar> u, v;
  MacVelocity vel;
  Rotation() {
    for (int a = 0; a < 3; ++a) vel.layout[a] = face_layout(shape, a, false);
    u.resize(vel.layout[1].size());
    v.resize(vel.layout[2].size());
    const Scalar c = 24, omega = 0.1;  // grid units, rad per unit time
    for_each_node(vel.layout[1], [&](Index, Index j, Index k, Index f) { u[f] = -omega * (k + 0.5 - c); (void)j; });
    for_each_node(vel.layout[2], [&](Index, Index j, Index k, Index f) { v[f] = omega * (j + 0.5 - c); (void)k; });
    vel.comp[1] = u.data();
    vel.comp[2] = v.data();
  }
};

TEST(GridKernels, ClampedSchemesStayInRange) {
  Rotation r;
  const FieldLayout C = cell_layout(r.shape, false);
  std::vector<Scalar> q(C.size()), out(C.size());
  // a discontinuous square: the case where unclamped MacCormack and BFECC overshoot
  for_each_node(C, [&](Index, Index j, Index k, Index c) { q[c] = (j >= 14 && j < 24 && k >= 20 && k < 30) ? 1 : 0; });
  for (auto scheme : {AdvectionScheme::MacCormack, AdvectionScheme::BFECC}) {
    std::vector<Scalar> a = q;
    AdvectionScratch scratch;
    for (int s = 0; s < 30; ++s) {
      advect(scheme, r.vel, C, a.data(), out.data(), 0.5, 2, scratch);
      a = out;
    }
    EXPECT_GE(*std::min_element(a.begin(), a.end()), 0.0);
    EXPECT_LE(*std::max_element(a.begin(), a.end()), 1.0);
  }
}

TEST(GridKernels, HigherOrderBackTraceFollowsTheCircle) {
  Rotation r;
  const Vec3 x{0.5, 34.0, 24.0};  // radius 10 from the centre
  Scalar err[4];
  for (int rk = 1; rk <= 3; ++rk) {
    const Vec3 y = back_trace(r.vel, x, 5.0, rk);  // 0.5 rad in one step
    const Scalar radius = std::hypot(y[1] - 24, y[2] - 24);
    err[rk] = std::fabs(radius - 10);
  }
  EXPECT_LT(err[2], err[1]);
  EXPECT_LT(err[3], err[2]);
  EXPECT_LT(err[3], 0.05);
}

// Random velocities up to 3 cells per unit time (departure points beyond the walls, where the
// clamping and wrapping act), every field layout, scheme and back-trace order: the row kernels
// must reproduce the node-wise passes exactly, and so the results cannot depend on the CPU.
TEST(GridKernels, RowKernelsGiveTheSameBitsAsTheNodeWisePasses) {
  std::vector<AdvectionKernel> kernels{AdvectionKernel::Rows};
  if (cpu_has_avx2()) kernels.push_back(AdvectionKernel::RowsAvx2);
  std::mt19937 rng(7);
  std::uniform_real_distribution<Scalar> uniform(-1, 1);
  for (const auto& dims : {std::vector<Index>{13, 10}, std::vector<Index>{9, 6, 11}}) {
    const GridShape shape(dims);
    for (bool periodic : {false, true}) {
      std::array<std::vector<Scalar>, 3> comp;
      MacVelocity vel;
      for (int a = 0; a < 3; ++a) {
        vel.layout[a] = face_layout(shape, a, periodic);
        if (!shape.active(a)) continue;
        comp[a].resize(vel.layout[a].size());
        for (Scalar& x : comp[a]) x = 3 * uniform(rng);
        vel.comp[a] = comp[a].data();
      }
      std::vector<FieldLayout> layouts{cell_layout(shape, periodic)};
      for (int a = 3 - shape.dim; a < 3; ++a) layouts.push_back(face_layout(shape, a, periodic));
      for (const FieldLayout& L : layouts) {
        ASSERT_TRUE(rows_apply(vel, L));
        std::vector<Scalar> q0(L.size()), q1(L.size());
        for (Index c = 0; c < L.size(); ++c) q0[c] = uniform(rng), q1[c] = uniform(rng);
        const Scalar* q[2] = {q0.data(), q1.data()};
        for (auto scheme : {AdvectionScheme::SemiLagrangian, AdvectionScheme::MacCormack, AdvectionScheme::BFECC}) {
          for (int rk = 1; rk <= 3; ++rk) {
            auto run = [&](AdvectionKernel kernel) {
              std::vector<Scalar> o0(L.size()), o1(L.size());
              Scalar* out[2] = {o0.data(), o1.data()};
              AdvectionScratch scratch;
              advect_fields(scheme, vel, L, 2, q, out, 0.9, rk, scratch, -1, kernel);
              o0.insert(o0.end(), o1.begin(), o1.end());
              return o0;
            };
            const std::vector<Scalar> reference = run(AdvectionKernel::Nodes);
            for (AdvectionKernel kernel : kernels) {
              const std::vector<Scalar> result = run(kernel);
              Index differ = 0;
              for (size_t c = 0; c < result.size(); ++c) differ += result[c] != reference[c];
              EXPECT_EQ(differ, 0) << "kernel " << static_cast<int>(kernel) << " dim " << shape.dim
                                   << (periodic ? " periodic" : " closed") << " layout offset " << L.offset[0]
                                   << "," << L.offset[1] << "," << L.offset[2] << " scheme "
                                   << static_cast<int>(scheme) << " rk " << rk;
            }
          }
        }
      }
    }
  }
}

TEST(GridKernels, RowKernelsRefuseNoSlipWalls) {
  const GridShape shape(std::vector<Index>{8, 8});
  std::vector<Scalar> u(face_layout(shape, 1, false).size(), 1.0), v(face_layout(shape, 2, false).size(), 0.0);
  MacVelocity vel;
  for (int a = 0; a < 3; ++a) vel.layout[a] = face_layout(shape, a, false);
  vel.comp[1] = u.data();
  vel.comp[2] = v.data();
  WallVelocities walls;
  walls.no_slip.fill(true);
  vel.walls = &walls;
  const FieldLayout C = cell_layout(shape, false);
  std::vector<Scalar> q(C.size(), 1.0), out(C.size());
  const Scalar* in[1] = {q.data()};
  Scalar* res[1] = {out.data()};
  AdvectionScratch scratch;
  EXPECT_FALSE(rows_apply(vel, C));
  EXPECT_THROW(advect_fields(AdvectionScheme::MacCormack, vel, C, 1, in, res, 0.5, 2, scratch, -1, AdvectionKernel::Rows),
               InvalidArgument);
  advect_fields(AdvectionScheme::MacCormack, vel, C, 1, in, res, 0.5, 2, scratch);  // Auto: node-wise
  for (Scalar x : out) EXPECT_EQ(x, 1.0);  // a constant field stays constant
}

}  // namespace
}  // namespace kinema::grid
