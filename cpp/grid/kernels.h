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
// "Fluid Simulation for Computer Graphics", 2nd ed., Sec. 3.1. Fields on one layout (the
// cell-centred scalars) share their departure points, and each pass of a scheme traces every
// node once.
// Positions are in grid units (metres / h); a field's node (i, j, k) sits at (i, j, k) + offset.
#pragma once

#include <array>
#include <cmath>
#include <vector>

#include "core/parallel.h"
#include "core/types.h"
#include "poisson/grid.h"

namespace kinema::grid {

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

// A NaN coordinate (a NaN velocity written into a state view while a step runs), or one whose
// periodic wrap lost every digit (a huge dt), is read as 0: converting it to an integer would be
// undefined and index out of bounds. The step's blow-up check then reports any NaN.
inline Bracket bracket(Scalar s, Index n, Index period) {
  Bracket b;
  if (period > 0) {
    const Scalar p = static_cast<Scalar>(period);
    s -= p * std::floor(s / p);
    if (!(s > -1 && s <= p)) s = 0;  // NaN, or the rounding garbage of a huge s (dt far too large)
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
  if (s != s) s = 0;
  b.i0 = static_cast<Index>(s);
  if (b.i0 > n - 2) b.i0 = n - 2;
  b.w = s - static_cast<Scalar>(b.i0);
  b.i1 = b.i0 + 1;
  return b;
}

// What interpolation of a velocity component sees beyond its last node next to a no-slip wall:
// the half cell between the node and the wall is filled linearly up to the wall's velocity,
// as with the ghost value 2 U_wall - u of Bridson Sec. 10.1 (without it the nearest value is
// extended, which is a free-slip wall). A moving lid thus drags the fluid in the advection too,
// not only through the viscosity.
struct WallVelocities {
  std::array<bool, 6> no_slip{};   // wall 2*axis + side (internal axis)
  std::array<Vec3, 6> velocity{};  // its velocity (internal axes; tangential)
};

namespace detail {

// A bracket along one axis plus, next to a no-slip wall, the share `keep` of the interpolated
// value that stays (the rest is the wall's velocity).
struct Axis {
  Index i0 = 0, i1 = 0;
  Scalar w = 0;
  Scalar keep = 1;
  int wall = -1;
};

// Brackets coordinate x (grid units) on nodes at offset + i, i < n. `walls` (nullable) applies
// the no-slip half cell on a tangential axis (offset 0.5) of a closed domain.
inline Axis locate(Scalar x, Scalar offset, Index n, Index period, int axis, const WallVelocities* walls) {
  const Scalar s = x - offset;
  const Bracket b = bracket(s, n, period);
  Axis a;
  a.i0 = b.i0;
  a.i1 = b.i1;
  a.w = b.w;
  if (walls && period == 0) {
    if (s < 0 && walls->no_slip[2 * axis]) {
      a.keep = std::fmax(0.0, 1 + 2 * s);
      a.wall = 2 * axis;
    } else if (s > static_cast<Scalar>(n - 1) && walls->no_slip[2 * axis + 1]) {
      a.keep = std::fmax(0.0, 1 - 2 * (s - static_cast<Scalar>(n - 1)));
      a.wall = 2 * axis + 1;
    }
  }
  return a;
}

// Trilinear (ThreeD) or bilinear (axes 1, 2) interpolation of f with node strides s0, s1;
// Bounds: lo/hi receive the extrema of the nodes used.
template <bool ThreeD, bool Bounds>
inline Scalar interpolate(const Scalar* f, Index s0, Index s1, const Axis& a0, const Axis& a1,
                          const Axis& a2, Scalar& lo, Scalar& hi) {
  auto plane = [&](const Scalar* p, Scalar& mn, Scalar& mx) {
    const Scalar* r0 = p + a1.i0 * s1;
    const Scalar* r1 = p + a1.i1 * s1;
    const Scalar f00 = r0[a2.i0], f01 = r0[a2.i1], f10 = r1[a2.i0], f11 = r1[a2.i1];
    if (Bounds) {  // std::min/max compile to single instructions; the inputs are finite
      mn = std::min(std::min(f00, f01), std::min(f10, f11));
      mx = std::max(std::max(f00, f01), std::max(f10, f11));
    }
    const Scalar a = f00 + a2.w * (f01 - f00), b = f10 + a2.w * (f11 - f10);
    return a + a1.w * (b - a);
  };
  if constexpr (ThreeD) {
    Scalar mn1 = 0, mx1 = 0;
    const Scalar a = plane(f + a0.i0 * s0, lo, hi), b = plane(f + a0.i1 * s0, mn1, mx1);
    if (Bounds) {
      lo = std::min(lo, mn1);
      hi = std::max(hi, mx1);
    }
    return a + a0.w * (b - a);
  } else {
    return plane(f, lo, hi);
  }
}

// Blends an interpolated value of component `comp` towards the velocity of the no-slip walls
// its brackets reach past.
template <bool ThreeD, bool Bounds>
inline Scalar wall_blend(Scalar v, const WallVelocities& walls, int comp, const Axis& a0, const Axis& a1,
                         const Axis& a2, Scalar& lo, Scalar& hi) {
  for (const Axis* a : {&a0, &a1, &a2}) {
    if (a->wall < 0 || (!ThreeD && a == &a0)) continue;
    const Scalar W = walls.velocity[a->wall][comp];
    v = W + a->keep * (v - W);
    if (Bounds) {
      lo = std::min(lo, W);
      hi = std::max(hi, W);
    }
  }
  return v;
}

}  // namespace detail

// Trilinear (bilinear in 2D) interpolation of f at x. When lo/hi are given they receive the
// smallest and largest of the nodes that carry weight: the clamping bounds of Selle et al.
inline Scalar sample(const Scalar* f, const FieldLayout& L, const Vec3& x, Scalar* lo = nullptr,
                     Scalar* hi = nullptr) {
  const bool three_d = L.n[0] > 1;
  detail::Axis a[3];
  for (int b = three_d ? 0 : 1; b < 3; ++b)
    a[b] = detail::locate(x[b], L.offset[b], L.n[b], L.period[b], b, nullptr);
  Scalar mn = 0, mx = 0;
  const Scalar v = three_d ? detail::interpolate<true, true>(f, L.stride(0), L.stride(1), a[0], a[1], a[2], mn, mx)
                           : detail::interpolate<false, true>(f, L.stride(0), L.stride(1), a[0], a[1], a[2], mn, mx);
  if (lo) *lo = mn;
  if (hi) *hi = mx;
  return v;
}

// A read-only MAC velocity field: component a (internal axis) on face_layout(shape, a).
struct MacVelocity {
  std::array<const Scalar*, 3> comp{nullptr, nullptr, nullptr};  // nullptr: inactive axis
  std::array<FieldLayout, 3> layout;
  const WallVelocities* walls = nullptr;  // no-slip walls seen by interpolation (nullable)

  // Velocity at x in grid units per unit time (cells / s when the caller scales by 1/h).
  Vec3 at(const Vec3& x) const {
    if (comp[0]) return at_impl<true>(x, walls);
    return at_impl<false>(x, walls);
  }

  // The same, with the dimension fixed at compile time. The brackets of each axis are found
  // once for the face-offset and once for the cell-offset position and shared by the
  // components: component a uses the face brackets along axis a and cell ones elsewhere.
  template <bool ThreeD>
  [[gnu::always_inline]] inline Vec3 at_impl(const Vec3& x, const WallVelocities* w) const {
    if (!w) return at_lean<ThreeD>(x);
    detail::Axis face[3], cell[3];
    for (int b = ThreeD ? 0 : 1; b < 3; ++b) {
      const FieldLayout& L = layout[b];  // faces normal to b: cells + 1 along b
      const Index n = L.n[b] - 1, p = L.period[b];
      face[b] = detail::locate(x[b], 0, n + 1, p, b, nullptr);
      cell[b] = detail::locate(x[b], 0.5, n, p, b, w);
    }
    Vec3 v{0, 0, 0};
    for (int a = ThreeD ? 0 : 1; a < 3; ++a) {
      const FieldLayout& L = layout[a];
      const detail::Axis& a0 = a == 0 ? face[0] : cell[0];
      const detail::Axis& a1 = a == 1 ? face[1] : cell[1];
      const detail::Axis& a2 = a == 2 ? face[2] : cell[2];
      Scalar lo, hi;
      v[a] = detail::interpolate<ThreeD, false>(comp[a], L.stride(0), L.stride(1), a0, a1, a2, lo, hi);
      if (w) v[a] = detail::wall_blend<ThreeD, false>(v[a], *w, a, a0, a1, a2, lo, hi);
    }
    return v;
  }

  // at_impl without walls: the same arithmetic on plain brackets, which the compiler keeps in
  // registers (about half the instructions of the general path).
  template <bool ThreeD>
  [[gnu::always_inline]] inline Vec3 at_lean(const Vec3& x) const {
    Index fi[3] = {0, 0, 0}, ci[3] = {0, 0, 0};
    Scalar fw[3] = {0, 0, 0}, cw[3] = {0, 0, 0};
    Index fj[3] = {0, 0, 0}, cj[3] = {0, 0, 0};
    for (int b = ThreeD ? 0 : 1; b < 3; ++b) {
      const Index n = layout[b].n[b] - 1, p = layout[b].period[b];
      const Bracket f = bracket(x[b], n + 1, p), c = bracket(x[b] - 0.5, n, p);
      fi[b] = f.i0, fj[b] = f.i1, fw[b] = f.w;
      ci[b] = c.i0, cj[b] = c.i1, cw[b] = c.w;
    }
    Vec3 v{0, 0, 0};
    for (int a = ThreeD ? 0 : 1; a < 3; ++a) {
      const FieldLayout& L = layout[a];
      const Index s1 = L.n[2], s0 = L.n[1] * s1;
      const Index i0 = a == 0 ? fi[0] : ci[0], i1 = a == 0 ? fj[0] : cj[0];
      const Index j0 = a == 1 ? fi[1] : ci[1], j1 = a == 1 ? fj[1] : cj[1];
      const Index k0 = a == 2 ? fi[2] : ci[2], k1 = a == 2 ? fj[2] : cj[2];
      const Scalar wi = a == 0 ? fw[0] : cw[0], wj = a == 1 ? fw[1] : cw[1], wk = a == 2 ? fw[2] : cw[2];
      const Scalar* f = comp[a];
      auto plane = [&](const Scalar* p) {
        const Scalar* r0 = p + j0 * s1;
        const Scalar* r1 = p + j1 * s1;
        const Scalar lo = r0[k0] + wk * (r0[k1] - r0[k0]), hi = r1[k0] + wk * (r1[k1] - r1[k0]);
        return lo + wj * (hi - lo);
      };
      if constexpr (ThreeD) {
        const Scalar p0 = plane(f + i0 * s0), p1 = plane(f + i1 * s0);
        v[a] = p0 + wi * (p1 - p0);
      } else {
        v[a] = plane(f);
      }
    }
    return v;
  }
};

// The point that reaches x after time dt (grid units: dt already divided by h), by explicit
// Runge-Kutta of order rk_order on dx/dt = u(x) integrated backwards; k1 = u(x) given.
template <class Velocity>
[[gnu::always_inline]] inline Vec3 back_trace_from(const Velocity& u, const Vec3& x, const Vec3& k1, Scalar dt, int rk_order) {
  auto shifted = [&](const Vec3& k, Scalar c) {
    return Vec3{x[0] - c * k[0], x[1] - c * k[1], x[2] - c * k[2]};
  };
  if (rk_order == 1) return shifted(k1, dt);
  const Vec3 k2 = u(shifted(k1, 0.5 * dt));
  if (rk_order == 2) return shifted(k2, dt);
  const Vec3 k3 = u(shifted(k2, 0.75 * dt));
  Vec3 k;
  for (int a = 0; a < 3; ++a) k[a] = (2 * k1[a] + 3 * k2[a] + 4 * k3[a]) / 9;
  return shifted(k, dt);
}

inline Vec3 back_trace(const MacVelocity& u, const Vec3& x, Scalar dt, int rk_order) {
  return back_trace_from([&](const Vec3& y) { return u.at(y); }, x, u.at(x), dt, rk_order);
}

// body(i, j, k, flat) for every node of L, rows in parallel when the field is large. The rows
// are handed out in small blocks on demand: every node is written independently, so the result
// does not depend on the schedule, and on a shared machine a thread that was descheduled no
// longer holds the others at the closing barrier (with static halves it did: at 128^3 a third of
// the step's samples were threads spinning there).
template <class Body>
void for_each_node(const FieldLayout& L, Body&& body) {
  const Index rows = L.rows(), nk = L.n[2], n1 = L.n[1];
#pragma omp parallel for schedule(dynamic, 8) if (L.size() > 8 * kParallelGrain)
  for (Index row = 0; row < rows; ++row) {
    const Index i = row / n1, j = row % n1;
    Index flat = row * nk;
    for (Index k = 0; k < nk; ++k, ++flat) body(i, j, k, flat);
  }
}

enum class AdvectionScheme { SemiLagrangian, MacCormack, BFECC };

// Which implementation advects; all give the same bits (tests/cpp compares them). Nodes: one
// node at a time, for every case. Rows, RowsAvx2: along rows of the contiguous axis with the
// baseline ISA or AVX2 (advect_rows.h; not with no-slip walls). Auto: the fastest that applies.
enum class AdvectionKernel { Auto, Nodes, Rows, RowsAvx2 };

constexpr int kMaxAdvectedFields = 8;  // fields per advect_fields call

// Scratch of the advection schemes, sized once for the largest field set: per field the
// forward pass and its stencil bounds, and the BFECC-corrected field.
struct AdvectionScratch {
  std::vector<std::vector<Scalar>> forward, lo, hi, corrected;
  void reserve(Index n, AdvectionScheme scheme, int fields = 1);

  // The arrays of fields 0..count-1 (corrected only for BFECC), as the passes take them.
  struct Fields {
    Scalar *forward[kMaxAdvectedFields], *lo[kMaxAdvectedFields], *hi[kMaxAdvectedFields],
        *corrected[kMaxAdvectedFields];
  };
  Fields fields(int count, AdvectionScheme scheme);
};

// BFECC's last step: out[f] clamped to [lo[f], hi[f]] on every node of L.
void clamp_fields(const FieldLayout& L, int count, Scalar* const* out, Scalar* const* lo, Scalar* const* hi);

// One advection step of `count` fields sharing the layout L: q[f] into out[f] (out[f] must not
// alias any q) by the chosen scheme. The back-traces are computed once per node and pass and
// serve every field. `wall_component` >= 0 marks the fields as that velocity component, which
// then see u.walls next to no-slip walls; -1 for scalars (extended to the walls). A kernel
// other than Auto or Nodes throws InvalidArgument where it does not apply. scratch_only: only
// the scratch is wanted (for the adjoint: q^, the bounds, BFECC's corrected field); the row
// kernels then skip the passes after it and leave out unspecified.
void advect_fields(AdvectionScheme scheme, const MacVelocity& u, const FieldLayout& L, int count,
                   const Scalar* const* q, Scalar* const* out, Scalar dt, int rk_order,
                   AdvectionScratch& scratch, int wall_component = -1,
                   AdvectionKernel kernel = AdvectionKernel::Auto, bool scratch_only = false);

// One advection step of q into out (out must not alias q) by the chosen scheme.
void advect(AdvectionScheme scheme, const MacVelocity& u, const FieldLayout& L, const Scalar* q,
            Scalar* out, Scalar dt, int rk_order, AdvectionScratch& scratch);

}  // namespace kinema::grid
