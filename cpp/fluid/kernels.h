// Interpolation and advection kernels on MAC (staggered) grids, 2D and 3D from one code path.
// Advection solves dq/dt + (u . grad) q = 0 for a cell-centred scalar or one staggered velocity
// component by tracing each node back through the velocity field:
//   semi-Lagrangian  q^{n+1}(x) = q^n(x - int u dt)                      (Stam, SIGGRAPH 1999),
//   MacCormack       q^ = SL(q, dt), q~ = SL(q^, -dt), q^{n+1} = q^ + (q - q~)/2
//                    (Selle, Fedkiw, Kim, Liu & Rossignac, J. Sci. Comput. 35, 2008),
//   BFECC            q_bar = q + (q - SL(SL(q, dt), -dt))/2, q^{n+1} = SL(q_bar, dt)
//                    (Kim, Liu, Llamas & Rossignac, 2005),
// where the two error-correcting schemes are clamped to the extrema of the interpolation
// stencil at the back-traced point, which removes their overshoots (Selle et al. 2008, Sec. 3).
// Back-traces use explicit Runge-Kutta of order 1, 2 (midpoint) or 3 (Ralston), as in Bridson,
// "Fluid Simulation for Computer Graphics", 2nd ed., Sec. 3.1.
// Positions are in grid units (metres / h); a field's node (i, j, k) sits at (i, j, k) + offset.
#pragma once

#include <array>
#include <cmath>
#include <vector>

#include "core/parallel.h"
#include "core/types.h"
#include "grid/grid.h"

namespace kinema::fluid {

using Vec3 = std::array<Scalar, 3>;

// Where a field's nodes sit and what happens beyond its ends.
struct FieldLayout {
  std::array<Index, 3> n{1, 1, 1};      // nodes per axis (internal 3D axes; axis 0 is 1 in 2D)
  Vec3 offset{0.5, 0.5, 0.5};           // position of node 0 in grid units
  std::array<Index, 3> period{0, 0, 0};  // wrap length in nodes, 0 = clamp (closed domain)

  Index size() const { return n[0] * n[1] * n[2]; }
  Index rows() const { return n[0] * n[1]; }
  Index index(Index i, Index j, Index k) const { return (i * n[1] + j) * n[2] + k; }
  Index stride(int axis) const { return axis == 0 ? n[1] * n[2] : axis == 1 ? n[2] : 1; }
};

// Cell centres of `shape`.
FieldLayout cell_layout(const GridShape& shape, bool periodic);
// Faces normal to internal axis `axis`: one more node along it, offset 0 there. In a periodic
// domain the last face duplicates the first (same value, kept in sync by the solver).
FieldLayout face_layout(const GridShape& shape, int axis, bool periodic);

// Index and weight of the two nodes bracketing coordinate s (grid units) along one axis.
struct Bracket {
  Index i0 = 0, i1 = 0;
  Scalar w = 0;  // weight of i1
};

inline Bracket bracket(Scalar s, Index n, Index period) {
  Bracket b;
  if (period > 0) {
    const Scalar p = static_cast<Scalar>(period);
    s -= p * std::floor(s / p);
    b.i0 = static_cast<Index>(s);
    if (b.i0 >= period) b.i0 = period - 1;  // s rounded up to p
    b.w = s - static_cast<Scalar>(b.i0);
    b.i1 = b.i0 + 1;
    if (b.i1 >= n) b.i1 -= period;  // cell-centred axes wrap; face axes hold the duplicate
    return b;
  }
  if (n == 1) return b;
  const Scalar hi = static_cast<Scalar>(n - 1);
  s = s < 0 ? 0 : (s > hi ? hi : s);
  b.i0 = static_cast<Index>(s);
  if (b.i0 > n - 2) b.i0 = n - 2;
  b.w = s - static_cast<Scalar>(b.i0);
  b.i1 = b.i0 + 1;
  return b;
}

// Trilinear (bilinear in 2D) interpolation of f at x. When lo/hi are given they receive the
// smallest and largest of the nodes that carry weight: the clamping bounds of Selle et al.
inline Scalar sample(const Scalar* f, const FieldLayout& L, const Vec3& x, Scalar* lo = nullptr,
                     Scalar* hi = nullptr) {
  const Bracket by = bracket(x[1] - L.offset[1], L.n[1], L.period[1]);
  const Bracket bz = bracket(x[2] - L.offset[2], L.n[2], L.period[2]);
  auto plane = [&](Index i, Scalar& mn, Scalar& mx) {
    const Scalar f00 = f[L.index(i, by.i0, bz.i0)], f01 = f[L.index(i, by.i0, bz.i1)];
    const Scalar f10 = f[L.index(i, by.i1, bz.i0)], f11 = f[L.index(i, by.i1, bz.i1)];
    mn = std::fmin(std::fmin(f00, f01), std::fmin(f10, f11));
    mx = std::fmax(std::fmax(f00, f01), std::fmax(f10, f11));
    const Scalar a = f00 + bz.w * (f01 - f00), b = f10 + bz.w * (f11 - f10);
    return a + by.w * (b - a);
  };
  Scalar mn, mx, value;
  if (L.n[0] == 1) {
    value = plane(0, mn, mx);
  } else {
    const Bracket bx = bracket(x[0] - L.offset[0], L.n[0], L.period[0]);
    Scalar mn1, mx1;
    const Scalar a = plane(bx.i0, mn, mx), b = plane(bx.i1, mn1, mx1);
    mn = std::fmin(mn, mn1);
    mx = std::fmax(mx, mx1);
    value = a + bx.w * (b - a);
  }
  if (lo) *lo = mn;
  if (hi) *hi = mx;
  return value;
}

// A read-only MAC velocity field: component a (internal axis) on face_layout(shape, a).
struct MacVelocity {
  std::array<const Scalar*, 3> comp{nullptr, nullptr, nullptr};  // nullptr: inactive axis
  std::array<FieldLayout, 3> layout;

  // Velocity at x in grid units per unit time (cells / s when the caller scales by 1/h).
  Vec3 at(const Vec3& x) const {
    Vec3 v{0, 0, 0};
    for (int a = 0; a < 3; ++a)
      if (comp[a]) v[a] = sample(comp[a], layout[a], x);
    return v;
  }
};

// The point that reaches x after time dt (grid units: dt already divided by h), by explicit
// Runge-Kutta of order rk_order on dx/dt = u(x) integrated backwards.
inline Vec3 back_trace(const MacVelocity& u, const Vec3& x, Scalar dt, int rk_order) {
  const Vec3 k1 = u.at(x);
  auto shifted = [&](const Vec3& k, Scalar c) {
    return Vec3{x[0] - c * k[0], x[1] - c * k[1], x[2] - c * k[2]};
  };
  if (rk_order == 1) return shifted(k1, dt);
  const Vec3 k2 = u.at(shifted(k1, 0.5 * dt));
  if (rk_order == 2) return shifted(k2, dt);
  const Vec3 k3 = u.at(shifted(k2, 0.75 * dt));
  Vec3 k;
  for (int a = 0; a < 3; ++a) k[a] = (2 * k1[a] + 3 * k2[a] + 4 * k3[a]) / 9;
  return shifted(k, dt);
}

// body(i, j, k, flat) for every node of L, rows in parallel when the field is large.
template <class Body>
void for_each_node(const FieldLayout& L, Body&& body) {
  const Index rows = L.rows(), nk = L.n[2], n1 = L.n[1];
#pragma omp parallel for schedule(static) if (L.size() > 8 * kParallelGrain)
  for (Index row = 0; row < rows; ++row) {
    const Index i = row / n1, j = row % n1;
    Index flat = row * nk;
    for (Index k = 0; k < nk; ++k, ++flat) body(i, j, k, flat);
  }
}

enum class AdvectionScheme { SemiLagrangian, MacCormack, BFECC };

// out = q traced back through u over dt (grid units); lo/hi (nullable) receive each node's
// stencil extrema. out must not alias q.
void advect_semi_lagrangian(const MacVelocity& u, const FieldLayout& L, const Scalar* q, Scalar* out,
                            Scalar dt, int rk_order, Scalar* lo, Scalar* hi);

// Scratch of the error-correcting schemes, sized once for the largest field.
struct AdvectionScratch {
  std::vector<Scalar> forward, backward, lo, hi;
  void reserve(Index n, AdvectionScheme scheme);
};

// One advection step of q into out (out must not alias q) by the chosen scheme.
void advect(AdvectionScheme scheme, const MacVelocity& u, const FieldLayout& L, const Scalar* q,
            Scalar* out, Scalar dt, int rk_order, AdvectionScratch& scratch);

}  // namespace kinema::fluid
