// The adjoint of one MAC-grid fluid step (Solver::step_adjoint) and of the advection schemes
// (adjoint.h). The step is recomputed from the state before it up to the viscosity (what the
// adjoint reads: the velocity the back-traces used and the viscous solution), then its phases
// are reversed: projection (one solve of the same pressure operator), viscosity (one solve of
// the same symmetric operator per component), forces, advection, sources.
#include "grid/adjoint.h"

#include <algorithm>
#include <cstring>
#include <string>

#include "core/errors.h"
#include "core/parallel.h"
#include "grid/solver.h"
#include "linalg/cg.h"

namespace kinema::grid {

namespace {

// The trilinear (bilinear in 2D) stencil of point x in layout L: nodes, weights and the weights'
// derivatives with respect to x (grid units), with bracket()'s clamping and wrapping.
struct Stencil {
  int count = 0;  // 4 in 2D, 8 in 3D
  Index node[8];
  Scalar w[8];
  Vec3 dw[8];

  Scalar value(const Scalar* f) const {
    Scalar v = 0;
    for (int n = 0; n < count; ++n) v += w[n] * f[node[n]];
    return v;
  }
  Vec3 gradient(const Scalar* f) const {
    Vec3 g{0, 0, 0};
    for (int n = 0; n < count; ++n)
      for (int b = 0; b < 3; ++b) g[b] += dw[n][b] * f[node[n]];
    return g;
  }
  // The node holding the smallest (largest) value, first in stencil order on ties.
  Index argmin(const Scalar* f) const {
    Index best = node[0];
    for (int n = 1; n < count; ++n)
      if (f[node[n]] < f[best]) best = node[n];
    return best;
  }
  Index argmax(const Scalar* f) const {
    Index best = node[0];
    for (int n = 1; n < count; ++n)
      if (f[node[n]] > f[best]) best = node[n];
    return best;
  }
};

// One axis of a stencil: the bracketing nodes, the weight of i1 and d w / d x (1 inside; 0 where
// bracket() clamped the coordinate to the domain, or read a NaN as 0).
struct AxisWeight {
  Index i0 = 0, i1 = 0;
  Scalar w = 0, d = 0;
};

inline AxisWeight axis_weight(Scalar s, Index n, Index period) {
  const Bracket br = bracket(s, n, period);
  return AxisWeight{br.i0, br.i1, br.w,
                    period > 0 || (n > 1 && s >= 0 && s <= static_cast<Scalar>(n - 1)) ? Scalar(1) : Scalar(0)};
}

template <bool ThreeD>
Stencil stencil_of(const FieldLayout& L, const AxisWeight& x0, const AxisWeight& x1, const AxisWeight& x2) {
  Stencil st;
  st.count = ThreeD ? 8 : 4;
  const Index s0 = L.stride(0), s1 = L.stride(1);
  int m = 0;
  for (int a0 = 0; a0 < (ThreeD ? 2 : 1); ++a0) {
    const Scalar f0 = ThreeD ? (a0 ? x0.w : 1 - x0.w) : 1;
    const Scalar d0 = ThreeD ? (a0 ? x0.d : -x0.d) : 0;
    const Index n0 = ThreeD ? (a0 ? x0.i1 : x0.i0) * s0 : 0;
    for (int a1 = 0; a1 < 2; ++a1) {
      const Scalar f1 = a1 ? x1.w : 1 - x1.w, d1 = a1 ? x1.d : -x1.d;
      const Index n1 = n0 + (a1 ? x1.i1 : x1.i0) * s1;
      for (int a2 = 0; a2 < 2; ++a2, ++m) {
        const Scalar f2 = a2 ? x2.w : 1 - x2.w, d2 = a2 ? x2.d : -x2.d;
        st.node[m] = n1 + (a2 ? x2.i1 : x2.i0);
        st.w[m] = f0 * f1 * f2;
        st.dw[m] = Vec3{d0 * f1 * f2, f0 * d1 * f2, f0 * f1 * d2};
      }
    }
  }
  return st;
}

// The stencil of point x (grid units) in layout L.
template <bool ThreeD>
Stencil stencil(const FieldLayout& L, const Vec3& x) {
  AxisWeight a[3];
  for (int b = ThreeD ? 0 : 1; b < 3; ++b) a[b] = axis_weight(x[b] - L.offset[b], L.n[b], L.period[b]);
  return stencil_of<ThreeD>(L, a[0], a[1], a[2]);
}

// Deterministic scatter-add into a set of target arrays over the nodes of a layout: each thread
// takes a fixed contiguous range of rows and adds into its own zeroed copy of the targets; the
// copies are then added into the targets in thread order (thread 0 adds into the targets
// themselves).
class Scatter {
 public:
  // The id of target `data` (n values); the same pointer twice is one target.
  static constexpr int kMaxTargets = 3 + 2 * kMaxAdvectedFields;

  int target(Scalar* data, Index n) {
    for (size_t t = 0; t < data_.size(); ++t)
      if (data_[t] == data) return static_cast<int>(t);
    data_.push_back(data);
    size_.push_back(n);
    return static_cast<int>(data_.size()) - 1;
  }

  // body(i, j, k, c, acc) for every node of L; acc[id] is the calling thread's copy of target id.
  template <class Body>
  void run(const FieldLayout& L, Body&& body) {
    const int targets = static_cast<int>(data_.size());
    const int threads = L.size() > 8 * kParallelGrain ? omp_get_max_threads() : 1;
    // thread 0 adds into the targets themselves, the others into zeroed copies
    copies_.resize(static_cast<size_t>(threads) * targets);
    for (int t = 1; t < threads; ++t)
      for (int id = 0; id < targets; ++id) copies_[t * targets + id].assign(static_cast<size_t>(size_[id]), 0);
    int used = 1;
    const Index rows = L.rows(), n1 = L.n[1], nk = L.n[2];
#pragma omp parallel num_threads(threads) if (threads > 1)
    {
      const int team = omp_get_num_threads(), t = omp_get_thread_num();
#pragma omp single
      used = team;
      Scalar* acc[kMaxTargets];
      for (int id = 0; id < targets; ++id) acc[id] = t == 0 ? data_[id] : copies_[t * targets + id].data();
      const Index first = rows * t / team, last = rows * (t + 1) / team;
      for (Index row = first; row < last; ++row) {
        const Index i = row / n1, j = row % n1;
        Index flat = row * nk;
        for (Index k = 0; k < nk; ++k, ++flat) body(i, j, k, flat, acc);
      }
    }
    for (int id = 0; id < targets && used > 1; ++id) {
      Scalar* out = data_[id];
      parallel_for(size_[id], [&](Index e) {
        Scalar s = out[e];
        for (int t = 1; t < used; ++t) s += copies_[t * targets + id][e];
        out[e] = s;
      });
    }
  }

 private:
  std::vector<Scalar*> data_;
  std::vector<Index> size_;
  std::vector<std::vector<Scalar>> copies_;
};

// The back-trace of kernels.h with its Runge-Kutta stages kept, and its adjoint.
template <bool ThreeD>
struct Tracer {
  const MacVelocity& u;
  int rk;
  int u_id[3];  // Scatter ids of dL/du per component (-1 inactive)

  struct Stages {
    Vec3 x, y1, y2, p;
  };

  Vec3 velocity(const Vec3& x) const { return u.template at_lean<ThreeD>(x); }

  Stages trace(const Vec3& x, Scalar dt) const {
    Stages s;
    s.x = x;
    const Vec3 k1 = velocity(x);
    auto shifted = [&](const Vec3& k, Scalar c) { return Vec3{x[0] - c * k[0], x[1] - c * k[1], x[2] - c * k[2]}; };
    if (rk == 1) {
      s.p = shifted(k1, dt);
      return s;
    }
    s.y1 = shifted(k1, 0.5 * dt);
    const Vec3 k2 = velocity(s.y1);
    if (rk == 2) {
      s.p = shifted(k2, dt);
      return s;
    }
    s.y2 = shifted(k2, 0.75 * dt);
    const Vec3 k3 = velocity(s.y2);
    Vec3 k;
    for (int a = 0; a < 3; ++a) k[a] = (2 * k1[a] + 3 * k2[a] + 4 * k3[a]) / 9;
    s.p = shifted(k, dt);
    return s;
  }

  // dL/du += (d u(y) / d u)^T g; returns (d u(y) / d y)^T g when `moves` (else 0: y is fixed).
  Vec3 velocity_adjoint(const Vec3& y, const Vec3& g, Scalar* const* acc, bool moves = true) const {
    Vec3 gy{0, 0, 0};
    // the face brackets along axis b serve component b, the cell brackets the others
    AxisWeight face[3], cell[3];
    for (int b = ThreeD ? 0 : 1; b < 3; ++b) {
      const Index n = u.layout[b].n[b] - 1, p = u.layout[b].period[b];
      face[b] = axis_weight(y[b], n + 1, p);
      cell[b] = axis_weight(y[b] - 0.5, n, p);
    }
    for (int a = ThreeD ? 0 : 1; a < 3; ++a) {
      if (g[a] == 0) continue;
      const Stencil st = stencil_of<ThreeD>(u.layout[a], a == 0 ? face[0] : cell[0], a == 1 ? face[1] : cell[1],
                                            a == 2 ? face[2] : cell[2]);
      Scalar* gu = acc[u_id[a]];
      for (int n = 0; n < st.count; ++n) gu[st.node[n]] += g[a] * st.w[n];
      if (!moves) continue;
      const Vec3 d = st.gradient(u.comp[a]);
      for (int b = 0; b < 3; ++b) gy[b] += g[a] * d[b];
    }
    return gy;
  }

  // dL/du += (dp/du)^T gp through the stages of p = x - dt k.
  void trace_adjoint(const Stages& s, Scalar dt, const Vec3& gp, Scalar* const* acc) const {
    Vec3 g1{0, 0, 0}, g2{0, 0, 0}, g3{0, 0, 0};
    const Scalar c1 = rk == 1 ? 1 : rk == 2 ? 0 : 2.0 / 9, c2 = rk == 2 ? 1 : rk == 3 ? 3.0 / 9 : 0,
                 c3 = rk == 3 ? 4.0 / 9 : 0;
    for (int b = 0; b < 3; ++b) {
      g1[b] = -dt * c1 * gp[b];
      g2[b] = -dt * c2 * gp[b];
      g3[b] = -dt * c3 * gp[b];
    }
    if (rk == 3) {
      const Vec3 gy2 = velocity_adjoint(s.y2, g3, acc);
      for (int b = 0; b < 3; ++b) g2[b] -= 0.75 * dt * gy2[b];
    }
    if (rk >= 2) {
      const Vec3 gy1 = velocity_adjoint(s.y1, g2, acc);
      for (int b = 0; b < 3; ++b) g1[b] -= 0.5 * dt * gy1[b];
    }
    velocity_adjoint(s.x, g1, acc, false);  // the node itself does not move
  }
};

template <bool ThreeD>
void advect_adjoint_impl(AdvectionScheme scheme, const MacVelocity& u, const FieldLayout& L, int count,
                         const Scalar* const* q, const Scalar* const* g_out, Scalar* const* g_q,
                         const std::array<Scalar*, 3>& g_u, Scalar dt, int rk) {
  const Index n = L.size();
  auto node = [&](Index i, Index j, Index k) {
    return Vec3{static_cast<Scalar>(i) + L.offset[0], static_cast<Scalar>(j) + L.offset[1],
                static_cast<Scalar>(k) + L.offset[2]};
  };
  // A scatter with dL/du and the given per-field targets; returns the tracer and the ids.
  auto make = [&](Scatter& sc, Scalar* const* fields, int* ids) {
    Tracer<ThreeD> tr{u, rk, {-1, -1, -1}};
    for (int a = ThreeD ? 0 : 1; a < 3; ++a) tr.u_id[a] = sc.target(g_u[a], u.layout[a].size());
    for (int f = 0; f < count; ++f) ids[f] = sc.target(fields[f], n);
    return tr;
  };
  // out[f] = SL(src[f]) adjoint: dL/dsrc[f] += W^T g[f] (ids), positions through the trace.
  auto semi_lagrangian = [&](const Scalar* const* src, const Scalar* const* g, Scalar* const* dst, Scalar step) {
    Scatter sc;
    int ids[kMaxAdvectedFields];
    const Tracer<ThreeD> tr = make(sc, dst, ids);
    sc.run(L, [&](Index i, Index j, Index k, Index c, Scalar* const* acc) {
      const auto s = tr.trace(node(i, j, k), step);
      const Stencil st = stencil<ThreeD>(L, s.p);
      Vec3 gp{0, 0, 0};
      for (int f = 0; f < count; ++f) {
        const Scalar gf = g[f][c];
        if (gf == 0) continue;
        Scalar* out = acc[ids[f]];
        for (int m = 0; m < st.count; ++m) out[st.node[m]] += gf * st.w[m];
        const Vec3 d = st.gradient(src[f]);
        for (int b = 0; b < 3; ++b) gp[b] += gf * d[b];
      }
      if (gp != Vec3{0, 0, 0}) tr.trace_adjoint(s, step, gp, acc);
    });
  };
  if (scheme == AdvectionScheme::SemiLagrangian) {
    semi_lagrangian(q, g_out, g_q, dt);
    return;
  }
  // Recompute the forward pass q^ = SL(q, dt) and its stencil's extreme nodes (the clamp bounds).
  std::vector<std::vector<Scalar>> fwd(count, std::vector<Scalar>(n)), g_fwd(count, std::vector<Scalar>(n, 0));
  std::vector<std::vector<Index>> lo(count, std::vector<Index>(n)), hi(count, std::vector<Index>(n));
  const Tracer<ThreeD> plain{u, rk, {-1, -1, -1}};
  for_each_node(L, [&](Index i, Index j, Index k, Index c) {
    const Stencil st = stencil<ThreeD>(L, plain.trace(node(i, j, k), dt).p);
    for (int f = 0; f < count; ++f) {
      fwd[f][c] = st.value(q[f]);
      lo[f][c] = st.argmin(q[f]);
      hi[f][c] = st.argmax(q[f]);
    }
  });
  Scalar* fwd_p[kMaxAdvectedFields];
  Scalar* g_fwd_p[kMaxAdvectedFields];
  for (int f = 0; f < count; ++f) fwd_p[f] = fwd[f].data(), g_fwd_p[f] = g_fwd[f].data();
  // Where the clamp took a bound, the node value itself is the result.
  auto clamped = [&](int f, Index c, Scalar v, Scalar g, Scalar* gq) {
    const Index l = lo[f][c], h = hi[f][c];
    if (v < q[f][l]) gq[l] += g;
    else if (q[f][h] < v) gq[h] += g;
    else return false;
    return true;
  };
  // The adjoint of the round trip q~ = SL(q^, -dt) of both schemes: direct(f, c, st, acc, q_id,
  // fwd_id) adds the terms that do not go through q~ and returns dL/dq~[f][c] (st: the stencil of
  // q~'s departure point).
  auto round_trip = [&](auto&& direct) {
    Scatter sc;
    int q_ids[kMaxAdvectedFields], fwd_ids[kMaxAdvectedFields];
    const Tracer<ThreeD> tr = make(sc, g_q, q_ids);
    for (int f = 0; f < count; ++f) fwd_ids[f] = sc.target(g_fwd_p[f], n);
    sc.run(L, [&](Index i, Index j, Index k, Index c, Scalar* const* acc) {
      const auto s = tr.trace(node(i, j, k), -dt);
      const Stencil st = stencil<ThreeD>(L, s.p);
      Vec3 gp{0, 0, 0};
      for (int f = 0; f < count; ++f) {
        const Scalar g_back = direct(f, c, st, acc, q_ids[f], fwd_ids[f]);
        if (g_back == 0) continue;
        Scalar* gf = acc[fwd_ids[f]];
        for (int m = 0; m < st.count; ++m) gf[st.node[m]] += g_back * st.w[m];
        const Vec3 d = st.gradient(fwd_p[f]);
        for (int b = 0; b < 3; ++b) gp[b] += g_back * d[b];
      }
      if (gp != Vec3{0, 0, 0}) tr.trace_adjoint(s, -dt, gp, acc);
    });
  };
  if (scheme == AdvectionScheme::MacCormack) {
    // out = clamp(q^ + (q - q~)/2)
    round_trip([&](int f, Index c, const Stencil& st, Scalar* const* acc, int q_id, int fwd_id) -> Scalar {
      const Scalar g = g_out[f][c];
      if (g == 0) return 0;
      const Scalar v = fwd_p[f][c] + 0.5 * (q[f][c] - st.value(fwd_p[f]));
      if (clamped(f, c, v, g, acc[q_id])) return 0;
      acc[fwd_id][c] += g;
      acc[q_id][c] += 0.5 * g;
      return -0.5 * g;
    });
    semi_lagrangian(q, g_fwd_p, g_q, dt);
    return;
  }
  // BFECC: q_bar = q + (q - SL(q^, -dt))/2, out = clamp(SL(q_bar, dt)).
  std::vector<std::vector<Scalar>> bar(count, std::vector<Scalar>(n)), g_bar(count, std::vector<Scalar>(n, 0));
  for_each_node(L, [&](Index i, Index j, Index k, Index c) {
    const Stencil st = stencil<ThreeD>(L, plain.trace(node(i, j, k), -dt).p);
    for (int f = 0; f < count; ++f) bar[f][c] = q[f][c] + 0.5 * (q[f][c] - st.value(fwd_p[f]));
  });
  Scalar* bar_p[kMaxAdvectedFields];
  Scalar* g_bar_p[kMaxAdvectedFields];
  for (int f = 0; f < count; ++f) bar_p[f] = bar[f].data(), g_bar_p[f] = g_bar[f].data();
  {
    Scatter sc;
    int q_ids[kMaxAdvectedFields], bar_ids[kMaxAdvectedFields];
    const Tracer<ThreeD> tr = make(sc, g_q, q_ids);
    for (int f = 0; f < count; ++f) bar_ids[f] = sc.target(g_bar_p[f], n);
    sc.run(L, [&](Index i, Index j, Index k, Index c, Scalar* const* acc) {
      const auto s = tr.trace(node(i, j, k), dt);
      const Stencil st = stencil<ThreeD>(L, s.p);
      Vec3 gp{0, 0, 0};
      for (int f = 0; f < count; ++f) {
        const Scalar g = g_out[f][c];
        if (g == 0 || clamped(f, c, st.value(bar_p[f]), g, acc[q_ids[f]])) continue;
        Scalar* gb = acc[bar_ids[f]];
        for (int m = 0; m < st.count; ++m) gb[st.node[m]] += g * st.w[m];
        const Vec3 d = st.gradient(bar_p[f]);
        for (int b = 0; b < 3; ++b) gp[b] += g * d[b];
      }
      if (gp != Vec3{0, 0, 0}) tr.trace_adjoint(s, dt, gp, acc);
    });
  }
  // q_bar = 1.5 q - 0.5 q~
  round_trip([&](int f, Index c, const Stencil&, Scalar* const* acc, int q_id, int) -> Scalar {
    const Scalar g = g_bar_p[f][c];
    acc[q_id][c] += 1.5 * g;
    return -0.5 * g;
  });
  semi_lagrangian(q, g_fwd_p, g_q, dt);
}

}  // namespace

void advect_adjoint(AdvectionScheme scheme, const MacVelocity& u, const FieldLayout& L, int count,
                    const Scalar* const* q, const Scalar* const* g_out, Scalar* const* g_q,
                    const std::array<Scalar*, 3>& g_u, Scalar dt, int rk_order) {
  if (count <= 0) return;
  if (count > kMaxAdvectedFields) throw InvalidArgument("advect_adjoint: at most 8 fields per call");
  if (u.walls) throw InvalidArgument("walls: the advection adjoint does not handle no-slip walls");
  if (u.comp[0]) advect_adjoint_impl<true>(scheme, u, L, count, q, g_out, g_q, g_u, dt, rk_order);
  else advect_adjoint_impl<false>(scheme, u, L, count, q, g_out, g_q, g_u, dt, rk_order);
}

// --------------------------------------------------------------------------- the step

void Solver::check_differentiable() const {
  if (config_.vorticity_confinement > 0)
    throw InvalidArgument("vorticity_confinement: the adjoint of vorticity confinement is not implemented; "
                          "use vorticity_confinement=0 under km.diff");
  if (walls_.no_slip != std::array<bool, 6>{})
    throw InvalidArgument("walls: no-slip and moving walls are not differentiable (their interpolation "
                          "blend has no adjoint); use walls='free_slip' under km.diff");
}

void Solver::set_viscosity(Scalar viscosity) {
  if (!(viscosity >= 0 && std::isfinite(viscosity)))
    throw InvalidArgument("viscosity: expected a finite value >= 0, got " + format_real(viscosity));
  config_.viscosity = viscosity;
  if (viscosity > 0 && rhs_face_.empty()) {
    Index largest_face = 0;
    for (int a = 0; a < 3; ++a)
      if (active_[a]) largest_face = std::max(largest_face, faces_[a].size());
    rhs_face_.assign(largest_face, 0);
    solution_face_.assign(largest_face, 0);
  }
}

void Solver::enforce_boundary_adjoint(std::array<std::vector<Scalar>, 3>& grad) const {
  for (int a = 0; a < 3; ++a) {
    if (!active_[a]) continue;
    Scalar* g = grad[a].data();
    const Index back = model_.shape.n[a] * faces_[a].stride(a);
    for (Index f : pinned_faces_[a]) g[f] = 0;
    for (Index f : duplicate_faces_[a]) {
      g[f - back] += g[f];
      g[f] = 0;
    }
  }
}

void Solver::cell_force_adjoint(int axis, const Scalar* g, Scalar* out, Index stride) const {
  // A free face gets 0.5 (f[lo] + f[hi]), or f of its one cell on an open side: gathered per cell
  // over its lower face (idx) and upper face (idx + 1, or face 0 across a periodic seam).
  const FieldLayout& F = faces_[axis];
  const std::vector<std::uint8_t>& fixed = fixed_[axis];
  const Index n_axis = model_.shape.n[axis], fs = F.stride(axis);
  const bool periodic = config_.periodic;
  for_each_node(cells_, [&](Index i, Index j, Index k, Index c) {
    const Index ia = axis == 0 ? i : axis == 1 ? j : k;
    const Index lower = F.index(i, j, k);
    const Index upper = periodic && ia == n_axis - 1 ? lower - ia * fs : lower + fs;
    Scalar s = 0;
    if (!fixed[lower]) s += (!periodic && ia == 0 ? 1 : 0.5) * g[lower];
    if (!fixed[upper]) s += (!periodic && ia == n_axis - 1 ? 1 : 0.5) * g[upper];
    out[c * stride] = s;
  });
}

void Solver::projection_adjoint(std::array<std::vector<Scalar>, 3>& grad, Scalar dt, Interrupt& interrupt) {
  // u' = u - (dt/h) G p with A p = -div(u) / dt. The transpose: dL/dp = -(dt/h) G^T g, then one
  // solve w = A^-1 dL/dp (A is symmetric; dL/dp sums to zero on every singular component, as the
  // forward right-hand side does), then g += div^T w * (-1/dt); the divergence is 0 in solid cells.
  enforce_boundary_adjoint(grad);  // project() ends with enforce_boundary
  const Index n = cells_.size();
  std::vector<Scalar> gp(static_cast<size_t>(n), 0), w(static_cast<size_t>(n), 0);
  const Scalar scale = dt / model_.h;
  const bool periodic = config_.periodic;
  for (int a = 0; a < 3; ++a) {
    if (!active_[a]) continue;
    // grad p on a free face is p[hi] - p[lo], or -+2 p of the one cell of an open side (ghost -p);
    // cell c is the hi cell of its lower face and the lo cell of its upper face.
    const FieldLayout& F = faces_[a];
    const std::vector<std::uint8_t>& fixed = fixed_[a];
    const Index n_axis = model_.shape.n[a], fs = F.stride(a);
    const Scalar* g = grad[a].data();
    for_each_node(cells_, [&](Index i, Index j, Index k, Index c) {
      const Index ia = a == 0 ? i : a == 1 ? j : k;
      const Index lower = F.index(i, j, k);
      const Index upper = periodic && ia == n_axis - 1 ? lower - ia * fs : lower + fs;
      Scalar s = 0;
      if (!fixed[lower]) s -= (!periodic && ia == 0 ? 2 : 1) * g[lower];
      if (!fixed[upper]) s += (!periodic && ia == n_axis - 1 ? 2 : 1) * g[upper];
      gp[c] += scale * s;
    });
  }
  const Scalar norm2 = parallel_sum(n, [&](Index c) { return gp[c] * gp[c]; });
  if (norm2 > 0) {
    IterativeOptions options{config_.tol, config_.max_iter};
    const SolveInfo info = pressure_solver_->solve(gp.data(), w.data(), options, interrupt);
    if (!info.converged)
      throw ConvergenceError("pressure: the adjoint projection did not reach tol=" + format_real(config_.tol) +
                             " (relative residual " + format_real(info.residual) + ")");
  }
  // Cell c's divergence reads its faces idx (-) and idx + 1 (+), never across a periodic seam.
  const Scalar inv = -1 / (dt * model_.h);
  for (int a = 0; a < 3; ++a) {
    if (!active_[a]) continue;
    const Index n_axis = model_.shape.n[a];
    Scalar* g = grad[a].data();
    for_each_node(faces_[a], [&](Index i, Index j, Index k, Index f) {
      std::array<Index, 3> idx{i, j, k};
      Scalar s = 0;
      if (idx[a] < n_axis) {
        const Index hi = cells_.index(i, j, k);
        if (fluid_cell(hi)) s -= w[hi];
      }
      if (idx[a] > 0) {
        --idx[a];
        const Index lo = cells_.index(idx[0], idx[1], idx[2]);
        if (fluid_cell(lo)) s += w[lo];
      }
      g[f] += inv * s;
    });
  }
}

void Solver::step_adjoint(const State& before, Scalar dt, const Scalar* control, State& adjoint,
                          Scalar& grad_viscosity, Scalar* grad_control, Interrupt& interrupt) {
  if (!(dt > 0) || !std::isfinite(dt)) throw InvalidArgument("dt: expected a finite time step > 0, got " + format_real(dt));
  check_differentiable();
  check_state(before);
  check_state(adjoint);
  const int dim = model_.shape.dim;
  const Index cells = cells_.size();
  // Recompute the step up to the viscosity: s0 is what advection reads, s what the viscosity made.
  State s = before;
  refresh_solids(s);
  apply_sources(s);
  enforce_boundary(s);
  const State s0 = s;
  advect(s, dt);
  add_forces(s, dt, control);
  diffuse(s, dt, interrupt);
  interrupt.check();

  std::array<std::vector<Scalar>, 3>& g = adjoint.velocity;
  // 4. Projection.
  projection_adjoint(g, dt, interrupt);
  // 3. Viscosity: (I + c L) x = u*, c = nu dt / h^2: lambda = (I + c L)^-1 g, dL/du* = lambda,
  // dL/dc = -lambda . L x (also at nu = 0, where the forward pass skips the solve).
  enforce_boundary_adjoint(g);
  const Scalar c = config_.viscosity * dt / (model_.h * model_.h);
  grad_viscosity = 0;
  {
    std::vector<Scalar> lambda, lx;
    for (int a = 0; a < 3; ++a) {
      if (!active_[a]) continue;
      const Index nf = faces_[a].size();
      lambda = g[a];
      if (c > 0) {
        IterativeOptions options{config_.tol * 1e-2, config_.max_iter};
        const SolveInfo info = pcg(
            nf, [&](const Scalar* in, Scalar* out) { apply_viscosity_operator(a, c, in, out); }, {}, g[a].data(),
            lambda.data(), options, interrupt, {}, &viscosity_cg_);
        if (!info.converged)
          throw ConvergenceError("viscosity: the adjoint CG did not reach tol for component " +
                                 std::string(1, "uvw"[a - (3 - dim)]));
      }
      lx.assign(static_cast<size_t>(nf), 0);
      apply_viscosity_operator(a, 1, s.velocity[a].data(), lx.data());  // (I + L) x
      const Scalar* x = s.velocity[a].data();
      const Scalar* l = lambda.data();
      const Scalar* y = lx.data();
      grad_viscosity -= parallel_sum(nf, [&](Index f) { return l[f] * (y[f] - x[f]); });
      g[a] = lambda;
    }
    grad_viscosity *= dt / (model_.h * model_.h);
  }
  // 2. Forces: controls and buoyancy are cell values averaged to the free faces.
  if (config_.periodic) enforce_boundary_adjoint(g);
  std::vector<Scalar> g_force(static_cast<size_t>(cells));
  const bool rho = config_.density && config_.alpha != 0, temp = config_.temperature && config_.beta != 0;
  for (int a = 0; a < 3; ++a) {
    if (!active_[a]) continue;
    if (grad_control) {
      const int user = a - (3 - dim);
      cell_force_adjoint(a, g[a].data(), grad_control + user, dim);
      parallel_for(cells, [&](Index cc) { grad_control[cc * dim + user] *= dt; });
    }
    if ((rho || temp) && config_.up[a] != 0) {
      cell_force_adjoint(a, g[a].data(), g_force.data(), 1);
      const Scalar up = config_.up[a] * dt;
      if (rho) parallel_for(cells, [&](Index cc) { adjoint.density[cc] -= config_.alpha * up * g_force[cc]; });
      if (temp) parallel_for(cells, [&](Index cc) { adjoint.temperature[cc] += config_.beta * up * g_force[cc]; });
    }
  }
  // 1. Advection: velocity through itself, scalars (zeroed in solids and at inflows) through it.
  enforce_boundary_adjoint(g);
  const MacVelocity u0 = mac_velocity(s0.velocity);
  const Scalar dt_grid = dt / model_.h;
  std::array<std::vector<Scalar>, 3> g0;
  std::array<Scalar*, 3> g0_p{nullptr, nullptr, nullptr};
  for (int a = 0; a < 3; ++a)
    if (active_[a]) g0[a].assign(faces_[a].size(), 0), g0_p[a] = g0[a].data();
  for (int a = 0; a < 3; ++a) {
    if (!active_[a]) continue;
    const Scalar* qa = s0.velocity[a].data();
    const Scalar* ga = g[a].data();
    advect_adjoint(config_.advection, u0, faces_[a], 1, &qa, &ga, &g0_p[a], g0_p, dt_grid, config_.rk_order);
  }
  const Scalar* q[2];
  const Scalar* g_out[2];
  Scalar* g_in[2];
  Scalar* g_scalars[2];
  std::array<std::vector<Scalar>, 2> g_scalar0;
  int count = 0;
  for (auto [field, grad] : {std::pair{&s0.density, &adjoint.density}, std::pair{&s0.temperature, &adjoint.temperature}}) {
    if (field->empty()) continue;
    Scalar* gq = grad->data();
    if (has_solid_) parallel_for(cells, [&](Index cc) { if (model_.solid[cc]) gq[cc] = 0; });
    g_scalars[count] = gq;
    q[count] = field->data();
    g_out[count] = gq;
    g_scalar0[count].assign(static_cast<size_t>(cells), 0);
    g_in[count] = g_scalar0[count].data();
    ++count;
  }
  if (count > 0 && any_open()) inflow_ambient(s0, g_scalars, count);
  advect_adjoint(config_.advection, u0, cells_, count, q, g_out, g_in, g0_p, dt_grid, config_.rk_order);
  // 0. Boundary values and sources imposed before the step.
  enforce_boundary_adjoint(g0);
  for (int f = 0; f < count; ++f) std::copy(g_scalar0[f].begin(), g_scalar0[f].end(), g_scalars[f]);
  for (const Model::Source& src : model_.sources) {
    for (Index cc : src.cells) {
      if (!fluid_cell(cc)) continue;
      if (src.set_density) adjoint.density[cc] = 0;
      if (src.set_temperature) adjoint.temperature[cc] = 0;
    }
    if (!src.set_velocity) continue;
    for (int a = 0; a < 3; ++a)
      if (active_[a])
        for (Index f : src.faces[a])
          if (fixed_[a][f] != 1) g0[a][f] = 0;
  }
  for (int a = 0; a < 3; ++a) g[a] = std::move(g0[a]);
  std::fill(adjoint.pressure.begin(), adjoint.pressure.end(), Scalar(0));
}

}  // namespace kinema::grid
