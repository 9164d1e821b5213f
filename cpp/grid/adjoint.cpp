// The adjoint of one MAC-grid fluid step (Solver::step_adjoint) and of the advection schemes
// (adjoint.h). The step is recomputed from the state before it up to the viscosity (what the
// adjoint reads: the velocity the back-traces used and the viscous solution), then its phases
// are reversed: projection (one solve of the same pressure operator), viscosity (one solve of
// the same symmetric operator per component), forces, advection, sources.
#include "grid/adjoint.h"

#include <algorithm>
#include <cstring>
#include <memory>
#include <string>

#include "core/errors.h"
#include "core/parallel.h"
#include "core/simd.h"
#include "grid/advect_rows.h"
#include "grid/solver.h"
#include "linalg/cg.h"

namespace kinema::grid {

namespace {

// v resized to n values (its capacity kept), all 0.
Scalar* zero_filled(std::vector<Scalar>& v, Index n) {
  v.resize(static_cast<size_t>(n));
  Scalar* p = v.data();
  parallel_for(n, [&](Index i) { p[i] = 0; });
  return p;
}

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

// The trilinear (bilinear in 2D) stencil of a point in layout L, from its axis brackets (with
// bracket()'s clamping and wrapping): nodes in the order (a0, a1, a2) = 000, 001, 010, ...,
// weights, and the interpolant's value and gradient in grid units.
template <bool ThreeD>
struct Stencil {
  static constexpr int count = ThreeD ? 8 : 4;
  Index node[8];
  Scalar w[8];
  Scalar d[3];   // d w / d x per axis (0 along a clamped axis)
  Scalar wa[3];  // the weight of the upper node per axis

  Stencil(const FieldLayout& L, const AxisWeight& x0, const AxisWeight& x1, const AxisWeight& x2) {
    const Index s0 = L.stride(0), s1 = L.stride(1);
    d[0] = ThreeD ? x0.d : 0, d[1] = x1.d, d[2] = x2.d;
    wa[0] = ThreeD ? x0.w : 0, wa[1] = x1.w, wa[2] = x2.w;
    int m = 0;
    for (int a0 = 0; a0 < (ThreeD ? 2 : 1); ++a0) {
      const Scalar f0 = ThreeD ? (a0 ? x0.w : 1 - x0.w) : 1;
      const Index n0 = ThreeD ? (a0 ? x0.i1 : x0.i0) * s0 : 0;
      for (int a1 = 0; a1 < 2; ++a1) {
        const Scalar f1 = f0 * (a1 ? x1.w : 1 - x1.w);
        const Index n1 = n0 + (a1 ? x1.i1 : x1.i0) * s1;
        node[m] = n1 + x2.i0, w[m++] = f1 * (1 - x2.w);
        node[m] = n1 + x2.i1, w[m++] = f1 * x2.w;
      }
    }
  }

  // v[n] = f at node n.
  void gather(const Scalar* f, Scalar* v) const {
    for (int n = 0; n < count; ++n) v[n] = f[node[n]];
  }
  // The interpolant from the gathered values v.
  Scalar value(const Scalar* v) const {
    Scalar s = 0;
    for (int n = 0; n < count; ++n) s += w[n] * v[n];
    return s;
  }
  // target[node] += g * w for every node.
  void scatter(Scalar g, Scalar* target) const {
    for (int n = 0; n < count; ++n) target[node[n]] += g * w[n];
  }
  // The same for the nodes of nonzero weight only.
  void scatter_nonzero(Scalar g, Scalar* target) const {
    for (int n = 0; n < count; ++n)
      if (w[n] != 0) target[node[n]] += g * w[n];
  }
  // g times the gradient of the interpolant of the gathered values v, added to out: the
  // differences along each axis, weighted by the other axes' weights.
  void add_gradient(const Scalar* v, Scalar g, Vec3& out) const {
    const Scalar u1 = 1 - wa[1], u2 = 1 - wa[2];
    if constexpr (ThreeD) {
      const Scalar u0 = 1 - wa[0];
      // planes a0 = 0 (v0..v3) and 1 (v4..v7)
      const Scalar p0 = u1 * (u2 * v[0] + wa[2] * v[1]) + wa[1] * (u2 * v[2] + wa[2] * v[3]);
      const Scalar p1 = u1 * (u2 * v[4] + wa[2] * v[5]) + wa[1] * (u2 * v[6] + wa[2] * v[7]);
      out[0] += g * d[0] * (p1 - p0);
      const Scalar e1 = u0 * (u2 * (v[2] - v[0]) + wa[2] * (v[3] - v[1])) +
                        wa[0] * (u2 * (v[6] - v[4]) + wa[2] * (v[7] - v[5]));
      const Scalar e2 = u0 * (u1 * (v[1] - v[0]) + wa[1] * (v[3] - v[2])) +
                        wa[0] * (u1 * (v[5] - v[4]) + wa[1] * (v[7] - v[6]));
      out[1] += g * d[1] * e1;
      out[2] += g * d[2] * e2;
    } else {
      out[1] += g * d[1] * (u2 * (v[2] - v[0]) + wa[2] * (v[3] - v[1]));
      out[2] += g * d[2] * (u1 * (v[1] - v[0]) + wa[1] * (v[3] - v[2]));
    }
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

// target[node] += g * w over the nodes of nonzero weight of Stencil(L, x0, x1, x2): its weights,
// products and order, without forming the nodes behind a zero factor (a stencil centred on a
// node of its own layout, or half-way between two, has 4-6 of its 8 weights exactly 0; weights
// are finite, so a zero factor makes a zero weight).
template <bool ThreeD>
void scatter_sparse(const FieldLayout& L, const AxisWeight& x0, const AxisWeight& x1, const AxisWeight& x2, Scalar g,
                    Scalar* target) {
  const Index s0 = L.stride(0), s1 = L.stride(1);
  for (int a0 = 0; a0 < (ThreeD ? 2 : 1); ++a0) {
    const Scalar f0 = ThreeD ? (a0 ? x0.w : 1 - x0.w) : 1;
    if (f0 == 0) continue;
    const Index n0 = ThreeD ? (a0 ? x0.i1 : x0.i0) * s0 : 0;
    for (int a1 = 0; a1 < 2; ++a1) {
      const Scalar f1 = f0 * (a1 ? x1.w : 1 - x1.w);
      if (f1 == 0) continue;
      const Index n1 = n0 + (a1 ? x1.i1 : x1.i0) * s1;
      const Scalar lo = f1 * (1 - x2.w), hi = f1 * x2.w;
      if (lo != 0) target[n1 + x2.i0] += g * lo;
      if (hi != 0) target[n1 + x2.i1] += g * hi;
    }
  }
}

// The stencil of point x (grid units) in layout L.
template <bool ThreeD>
Stencil<ThreeD> stencil(const FieldLayout& L, const Vec3& x) {
  AxisWeight a[3];
  for (int b = ThreeD ? 0 : 1; b < 3; ++b) a[b] = axis_weight(x[b] - L.offset[b], L.n[b], L.period[b]);
  return Stencil<ThreeD>(L, a[0], a[1], a[2]);
}

// Scatter-add over the nodes of a layout, without atomics or per-thread copies, and with a
// result that does not depend on the thread count. The nodes are cut into blocks of whole
// slabs along the outermost axis (axis 0 in 3D, 1 in 2D), each at least twice as wide as the
// reach of a node's writes (how far along that axis from the node its stencils can lie); the
// even blocks run in parallel, then the odd ones (then, across a periodic seam with an odd
// block count, the last one alone). No two blocks that run together write the same node, so
// every node receives its terms in one fixed order: the blocks' and, inside a block, the rows'.
class Scatter {
 public:
  // row(scratch, i, j, c) for every row (i, j) of L, c its first node, with scratch = make()
  // per block; a node's writes lie within `reach` slabs of it (reach < 0: unknown, run serially).
  template <class Make, class Row>
  static void run(const FieldLayout& L, Index reach, Make&& make, Row&& row_body) {
    const int axis = L.n[0] > 1 ? 0 : 1;
    const Index n = L.n[axis], n1 = L.n[1], nk = L.n[2];
    const Index width = reach < 0 ? n : std::max<Index>(1, 2 * reach);
    // a multiple of 4 blocks where there are that many: each colour's share divides evenly
    // among 1, 2 or 4 threads (the cut depends on the grid and the reach only, never on them)
    const Index most = std::max<Index>(1, n / width);
    const Index blocks = most >= 4 ? most / 4 * 4 : most;
    const bool seam = L.period[axis] > 0 && blocks % 2 == 1 && blocks > 1;
    const Index slab_rows = axis == 0 ? n1 : 1;  // rows per slab
    auto block = [&](Index b) {
      const Index first = n * b / blocks * slab_rows, last = n * (b + 1) / blocks * slab_rows;
      auto scratch = make();
      for (Index row = first; row < last; ++row) row_body(scratch, row / n1, row % n1, row * nk);
    };
    // a node's adjoint costs tens of nanoseconds: a few thousand of them outweigh a parallel region
    const bool parallel = blocks > 1 && L.size() > kParallelGrain;
    for (int colour = 0; colour < 2; ++colour) {
      const Index end = seam ? blocks - 1 : blocks;
#pragma omp parallel for schedule(dynamic, 1) if (parallel)
      for (Index b = colour; b < end; b += 2) block(b);
    }
    if (seam) block(blocks - 1);
  }
};

// How many slabs along the blocking axis of L a node's scatter can reach when its back-traces
// read u over |dt| (Runge-Kutta stages are convex combinations of sampled velocities, so no
// stage leaves |dt| max|u| of the node), plus the stencil, the half-cell offset between faces
// and cells, and rounding; -1 where u is not finite or the reach spans the domain.
inline Index scatter_reach(const MacVelocity& u, const FieldLayout& L, Scalar dt) {
  const int axis = L.n[0] > 1 ? 0 : 1;
  const Scalar* c = u.comp[axis];
  const Index n = u.layout[axis].size();
  Scalar top = 0;
  for (Index e = 0; e < n; ++e) {
    const Scalar a = std::fabs(c[e]);
    if (!(a <= top)) top = a;  // NaN propagates
  }
  const Scalar reach = std::ceil(top * std::fabs(dt)) + 3;
  if (!(reach < static_cast<Scalar>(L.n[axis]))) return -1;
  return static_cast<Index>(reach);
}

// The back-trace of kernels.h with its Runge-Kutta stages kept, and its adjoint.
template <bool ThreeD>
struct Tracer {
  const MacVelocity& u;
  int rk;
  Scalar* g_u[3];  // dL/du per component (nullptr inactive)

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

  // The brackets of a point for u's components: the face brackets along axis b serve
  // component b, the cell brackets the others.
  struct Brackets {
    AxisWeight face[3], cell[3];
    const Scalar* const* jac = nullptr;  // nullable: jac[3 a + b][k] = d u_a / d y_b (RowTrace::jac)
    Index k = 0;
  };
  Brackets brackets(const Vec3& y) const {
    Brackets br;
    for (int b = ThreeD ? 0 : 1; b < 3; ++b) {
      const Index n = u.layout[b].n[b] - 1, p = u.layout[b].period[b];
      br.face[b] = axis_weight(y[b], n + 1, p);
      br.cell[b] = axis_weight(y[b] - 0.5, n, p);
    }
    return br;
  }

  // dL/du += (d u(y) / d u)^T g; returns (d u(y) / d y)^T g when `moves` (else 0: y is a node,
  // whose stencils have many zero weights, skipped).
  Vec3 velocity_adjoint(const Brackets& br, const Vec3& g, bool moves = true) const {
    Vec3 gy{0, 0, 0};
    const AxisWeight *face = br.face, *cell = br.cell;
    for (int a = ThreeD ? 0 : 1; a < 3; ++a) {
      if (g[a] == 0) continue;
      if (!moves && ThreeD) {
        scatter_sparse<ThreeD>(u.layout[a], a == 0 ? face[0] : cell[0], a == 1 ? face[1] : cell[1],
                               a == 2 ? face[2] : cell[2], g[a], g_u[a]);
        continue;
      }
      const Stencil<ThreeD> st(u.layout[a], a == 0 ? face[0] : cell[0], a == 1 ? face[1] : cell[1],
                               a == 2 ? face[2] : cell[2]);
      if (!moves) {  // 2D: 2-3 of 4 weights exactly 0
        st.scatter_nonzero(g[a], g_u[a]);
        continue;
      }
      st.scatter(g[a], g_u[a]);
      if (br.jac) {  // the trace's derivatives, times 0 along a clamped axis (as add_gradient)
        for (int b = ThreeD ? 0 : 1; b < 3; ++b) gy[b] += g[a] * st.d[b] * br.jac[3 * a + b][br.k];
      } else {
        Scalar v[8];
        st.gather(u.comp[a], v);
        st.add_gradient(v, g[a], gy);
      }
    }
    return gy;
  }

  // dL/du += (dp/du)^T gp through the stages of p = x - dt k after the first; at(m) = the
  // brackets of stage m (1: s.y1, 2: s.y2). Returns g1, the gradient of the first stage's
  // velocity u(x) at the node x itself, which the caller scatters (advect_adjoint_impl's
  // stage0): every pass and field of a call reads u at the same nodes, so their g1 are summed
  // and scattered once.
  template <class At>
  Vec3 trace_adjoint(Scalar dt, const Vec3& gp, At&& at) const {
    Vec3 g1{0, 0, 0}, g2{0, 0, 0}, g3{0, 0, 0};
    const Scalar c1 = rk == 1 ? 1 : rk == 2 ? 0 : 2.0 / 9, c2 = rk == 2 ? 1 : rk == 3 ? 3.0 / 9 : 0,
                 c3 = rk == 3 ? 4.0 / 9 : 0;
    for (int b = 0; b < 3; ++b) {
      g1[b] = -dt * c1 * gp[b];
      g2[b] = -dt * c2 * gp[b];
      g3[b] = -dt * c3 * gp[b];
    }
    if (rk == 3) {
      const Vec3 gy2 = velocity_adjoint(at(2), g3);
      for (int b = 0; b < 3; ++b) g2[b] -= 0.75 * dt * gy2[b];
    }
    if (rk >= 2) {
      const Vec3 gy1 = velocity_adjoint(at(1), g2);
      for (int b = 0; b < 3; ++b) g1[b] -= 0.5 * dt * gy1[b];
    }
    return g1;
  }
};

template <bool ThreeD>
void advect_adjoint_impl(AdvectionScheme scheme, const MacVelocity& u, const FieldLayout& L, int count,
                         const Scalar* const* q, const Scalar* const* g_out, Scalar* const* g_q,
                         const std::array<Scalar*, 3>& g_u, Scalar dt, int rk, const AdvectionScratch* forward,
                         AdjointScratch& work) {
  // work's slots: g_node per axis (0-2), the kept gp per axis (3-5), g_fwd and g_bar per field,
  // the stored back-trace over dt (advect_rows' trace)
  constexpr int kGp = 3, kFwd = 6, kBar = kFwd + kMaxAdvectedFields, kTrace = kBar + kMaxAdvectedFields;
  const Index n = L.size();
  const Index reach = scatter_reach(u, L, dt);
  auto node = [&](Index i, Index j, Index k) {
    return Vec3{static_cast<Scalar>(i) + L.offset[0], static_cast<Scalar>(j) + L.offset[1],
                static_cast<Scalar>(k) + L.offset[2]};
  };
  const Tracer<ThreeD> tr{u, rk, {g_u[0], g_u[1], g_u[2]}};
  // Where the row passes apply, a row's back-traces run at once (advect_rows' vectorised
  // traces), and so do the brackets of its departure points (in L) and of its Runge-Kutta
  // stages (for u); the nodes then only gather and scatter.
  const bool rows = rows_apply(u, L);
  const Index nk = L.n[2];
  const int first = ThreeD ? 0 : 1;
  // Per node of L and active axis b: the gradient of u_b read at the node (the first
  // Runge-Kutta stage) summed over the passes and fields of this call.
  Scalar* g_node[3] = {nullptr, nullptr, nullptr};
  for (int b = first; b < 3; ++b) g_node[b] = work.zeros(b, n);
  // slots: (stage m, face 0 / cell 1, axis b) at 6 m + 3 o + b, the departure point in L at 18 + b
  constexpr int kSlots = 21;
  struct RowData {
    std::unique_ptr<RowTrace> trace;
    std::vector<int> ints;      // per slot: i0, i1
    std::vector<Scalar> reals;  // per slot: w, d; then the nodes' coordinates
    // per slot, where its i0, i1, w and d are read: its own arrays, or (i0, i1, w of the last
    // Runge-Kutta stage) the brackets the trace computed for it (RowTrace::stage_brackets)
    const int* i0[kSlots];
    const int* i1[kSlots];
    const Scalar* w[kSlots];
    Scalar* d[kSlots];
    bool traced = false;  // the last stage's slots read the trace's brackets
  };
  // The slots of the last stage the trace samples the velocity at (none at rk 1): the trace leaves
  // their brackets behind, so only their d is computed.
  const int last_stage = rk - 1;
  auto own = [&](RowData& rd, int sl) {
    rd.i0[sl] = rd.ints.data() + 2 * sl * nk, rd.i1[sl] = rd.i0[sl] + nk;
    rd.w[sl] = rd.reals.data() + 2 * sl * nk, rd.d[sl] = rd.reals.data() + (2 * sl + 1) * nk;
  };
  // The last stage's slots read the trace's brackets (on) or their own arrays.
  auto use_trace = [&](RowData& rd, bool on) {
    if (rd.traced == on || last_stage < 1) return;
    rd.traced = on;
    for (int b = first; b < 3; ++b)
      for (int o = 0; o < 2; ++o) {
        const int sl = 6 * last_stage + 3 * o + b;
        own(rd, sl);
        if (on) rd.trace->stage_brackets(b, o == 1, rd.i0[sl], rd.i1[sl], rd.w[sl]);
      }
  };
  auto fill = [&](RowData& rd, int sl, const Scalar* x, Scalar offset, Index nodes, Index period) {
    int* i = rd.ints.data() + 2 * sl * nk;
    Scalar* r = rd.reals.data() + 2 * sl * nk;
    rd.trace->brackets(x, offset, nodes, period, i, i + nk, r, r + nk);
  };
  auto make = [&] {
    RowData rd;
    if (rows) {
      rd.trace = std::make_unique<RowTrace>(u, L, rk, use_avx2());
      rd.ints.resize(static_cast<size_t>(2 * kSlots * nk));
      rd.reals.resize(static_cast<size_t>((2 * kSlots + 3) * nk));
      for (int sl = 0; sl < kSlots; ++sl) own(rd, sl);
      use_trace(rd, true);
      Scalar* x2 = rd.reals.data() + (2 * kSlots + 2) * nk;
      for (Index k = 0; k < nk; ++k) x2[k] = static_cast<Scalar>(k) + L.offset[2];
      // stage 0 along the row (stage0()): the nodes' own brackets, the same for every row
      const Index cells = u.layout[2].n[2] - 1, period = u.layout[2].period[2];
      fill(rd, 2, x2, 0, cells + 1, period);
      fill(rd, 5, x2, 0.5, cells, period);
    }
    return rd;
  };
  auto slot = [&](const RowData& rd, int sl, Index k) {
    return AxisWeight{rd.i0[sl][k], rd.i1[sl][k], rd.w[sl][k], rd.d[sl][k]};
  };
  // The back-trace over dt stored per node (advect_rows' trace; rows only): the slots in use, and
  // RowTrace's array of each.
  int used[kTraceSlots], n_used = 0;
  for (int e = 0; e < kTraceSlots; ++e)
    if (trace_slot_used(e, rk, ThreeD)) used[n_used++] = e;
  auto trace_array = [](RowTrace& rt, int e) -> Scalar* {
    return e < 3 ? rt.y1[e] : e < 6 ? rt.y2[e - 3] : e < 9 ? rt.p[e - 6] : rt.jac[(e - 9) / 9][(e - 9) % 9];
  };
  Scalar* stored[kTraceSlots] = {};  // the departure points' arrays once allocated (slots 6-8)
  auto store_departures = [&]() -> Scalar** {
    for (int s = 0; s < n_used; ++s)
      if (used[s] >= 6 && used[s] < 9) stored[used[s]] = work.raw(kTrace + used[s], n);
    return stored;
  };
  // One node of a pass: its terms at the departure point (stencil st), their scatter, and the
  // trace's adjoint (at(m): the brackets of stage m).
  // Two passes over the same trace (BFECC's first and last) carry their departure points'
  // gradients through it once: the first keeps gp per node (gp_keep), the last adds it (gp_add).
  Scalar* gp_keep[3] = {nullptr, nullptr, nullptr};
  const Scalar* gp_add[3] = {nullptr, nullptr, nullptr};
  auto node_adjoint = [&](const Stencil<ThreeD>& st, Index c, Scalar step, const Scalar* const* src,
                          Scalar* const* dst, auto&& term, auto&& at) {
    Vec3 gp{0, 0, 0};
    for (int f = 0; f < count; ++f) {
      Scalar v[8];  // src[f] on the stencil, gathered once for the term and the gradient
      st.gather(src[f], v);
      const Scalar g = term(f, c, st, v);
      if (g == 0) continue;
      st.scatter(g, dst[f]);
      st.add_gradient(v, g, gp);
    }
    if (gp_add[first])
      for (int b = first; b < 3; ++b) gp[b] += gp_add[b][c];
    if (gp_keep[first]) {
      for (int b = first; b < 3; ++b) gp_keep[b][c] = gp[b];
      return;
    }
    if (gp == Vec3{0, 0, 0}) return;
    const Vec3 g1 = tr.trace_adjoint(step, gp, at);
    for (int b = first; b < 3; ++b) g_node[b][c] += g1[b];  // node c is this row's: no other writer
  };
  // One pass traced over `step`: for each node, term(f, c, st, at) (at: src[f] on st) returns dL/d(src[f] at the
  // departure point) after adding the terms that do not go through it; the pass scatters that
  // into dst[f] (W^T) and carries (grad src[f]) through the trace into dL/du. load (nullable):
  // the trace stored per node (advect_rows' trace), read instead of traced: its non-null arrays
  // must hold all the pass reads (the departure points alone where gp_keep skips the trace's
  // adjoint).
  auto pass = [&](Scalar step, const Scalar* const* src, Scalar* const* dst, auto&& term,
                  const Scalar* const* load = nullptr) {
    Scatter::run(L, reach, make, [&](RowData& rd, Index i, Index j, Index c0) {
      if (!rd.trace) {
        for (Index k = 0; k < nk; ++k) {
          const auto s = tr.trace(node(i, j, k), step);
          node_adjoint(stencil<ThreeD>(L, s.p), c0 + k, step, src, dst, term,
                       [&](int m) { return tr.brackets(m == 0 ? s.x : m == 1 ? s.y1 : s.y2); });
        }
        return;
      }
      RowTrace& rt = *rd.trace;
      if (load) {
        for (int s = 0; s < n_used; ++s)
          if (load[used[s]]) std::copy_n(load[used[s]] + c0, nk, trace_array(rt, used[s]));
      } else {
        rt.trace(i, j, step);
      }
      use_trace(rd, !load);  // a loaded trace left no brackets behind
      const Scalar* stage[3][3] = {{nullptr, nullptr, nullptr}, {rt.y1[0], rt.y1[1], rt.y1[2]},
                                   {rt.y2[0], rt.y2[1], rt.y2[2]}};
      for (int b = first; b < 3; ++b) {
        fill(rd, 18 + b, rt.p[b], L.offset[b], L.n[b], L.period[b]);
        const Index cells = u.layout[b].n[b] - 1, period = u.layout[b].period[b];
        for (int m = 1; m < rk && !gp_keep[first]; ++m) {  // stage 0 (the node) is stage0()'s
          if (m == last_stage && rd.traced) {
            rt.inside(stage[m][b], 0, cells + 1, period, rd.d[6 * m + b]);
            rt.inside(stage[m][b], 0.5, cells, period, rd.d[6 * m + 3 + b]);
            continue;
          }
          fill(rd, 6 * m + b, stage[m][b], 0, cells + 1, period);
          fill(rd, 6 * m + 3 + b, stage[m][b], 0.5, cells, period);
        }
      }
      for (Index k = 0; k < nk; ++k) {
        const Stencil<ThreeD> st(L, slot(rd, 18, k), slot(rd, 19, k), slot(rd, 20, k));
        node_adjoint(st, c0 + k, step, src, dst, term, [&](int m) {
          typename Tracer<ThreeD>::Brackets br;
          for (int b = first; b < 3; ++b) br.face[b] = slot(rd, 6 * m + b, k), br.cell[b] = slot(rd, 6 * m + 3 + b, k);
          br.jac = rt.jac[m - 1];
          br.k = k;
          return br;
        });
      }
    });
  };
  // out[f] = SL(src[f]) adjoint: dL/dsrc[f] += W^T g[f], positions through the trace.
  auto semi_lagrangian = [&](const Scalar* const* src, const Scalar* const* g, Scalar* const* dst) {
    pass(dt, src, dst, [&](int f, Index c, const Stencil<ThreeD>&, const Scalar*) { return g[f][c]; });
  };
  // The first stage of every trace reads u at the node itself: dL/du_a += W_a(x)^T g_node[a]
  // for every node x of L, once per call (its stencils reach a slab or two).
  auto stage0 = [&] {
    const Index reach0 = 3 < L.n[L.n[0] > 1 ? 0 : 1] ? 3 : -1;
    Scatter::run(L, reach0, make, [&](RowData& rd, Index i, Index j, Index c0) {
      auto at_node = [&](Index k) {
        Vec3 g{0, 0, 0};
        for (int b = first; b < 3; ++b) g[b] = g_node[b][c0 + k];
        return g;
      };
      if (!rd.trace) {
        for (Index k = 0; k < nk; ++k) {
          const Vec3 g = at_node(k);
          if (g != Vec3{0, 0, 0}) tr.velocity_adjoint(tr.brackets(node(i, j, k)), g, false);
        }
        return;
      }
      // the nodes' brackets: constant along the row on axes 0 and 1, the row's (make()) on axis 2
      typename Tracer<ThreeD>::Brackets br;
      for (int b = first; b < 2; ++b) {
        const Scalar x = static_cast<Scalar>(b == 0 ? i : j) + L.offset[b];
        const Index cells = u.layout[b].n[b] - 1, period = u.layout[b].period[b];
        br.face[b] = axis_weight(x, cells + 1, period);
        br.cell[b] = axis_weight(x - 0.5, cells, period);
      }
      if constexpr (ThreeD) {
        // velocity_adjoint(moves = false), i.e. scatter_sparse per component, with the factors of
        // axes 0 and 1 (constant along the row) formed once per row: the same products, the same
        // order of writes into each g_u[a] (components write distinct arrays)
        for (int a = 0; a < 3; ++a) {
          const FieldLayout& F = u.layout[a];
          const AxisWeight &x0 = a == 0 ? br.face[0] : br.cell[0], &x1 = a == 1 ? br.face[1] : br.cell[1];
          Scalar f1s[4];
          Index n1s[4];
          int pairs = 0;
          for (int a0 = 0; a0 < 2; ++a0) {
            const Scalar f0 = a0 ? x0.w : 1 - x0.w;
            if (f0 == 0) continue;
            const Index n0 = (a0 ? x0.i1 : x0.i0) * F.stride(0);
            for (int a1 = 0; a1 < 2; ++a1) {
              const Scalar f1 = f0 * (a1 ? x1.w : 1 - x1.w);
              if (f1 == 0) continue;
              f1s[pairs] = f1, n1s[pairs++] = n0 + (a1 ? x1.i1 : x1.i0) * F.stride(1);
            }
          }
          const Scalar* ga = g_node[a] + c0;
          Scalar* target = g_u[a];
          const int sl = a == 2 ? 2 : 5;
          for (Index k = 0; k < nk; ++k) {
            const Scalar g = ga[k];
            if (g == 0) continue;
            const AxisWeight x2 = slot(rd, sl, k);
            for (int e = 0; e < pairs; ++e) {
              const Scalar lo = f1s[e] * (1 - x2.w), hi = f1s[e] * x2.w;
              if (lo != 0) target[n1s[e] + x2.i0] += g * lo;
              if (hi != 0) target[n1s[e] + x2.i1] += g * hi;
            }
          }
        }
      } else {
        for (Index k = 0; k < nk; ++k) {
          const Vec3 g = at_node(k);
          if (g == Vec3{0, 0, 0}) continue;
          br.face[2] = slot(rd, 2, k), br.cell[2] = slot(rd, 5, k);
          tr.velocity_adjoint(br, g, false);
        }
      }
    });
  };
  if (scheme == AdvectionScheme::SemiLagrangian) {
    semi_lagrangian(q, g_out, g_q);
    stage0();
    return;
  }
  // The forward pass as run: q^ = SL(q, dt), the clamp bounds lo/hi (values), BFECC's q_bar.
  // Recomputed by rows for BFECC, its departure points are stored for the adjoint's first pass,
  // which traces the same and reads only them (it carries its gradients through the last pass's
  // trace). Not the whole trace (15 arrays per node at RK2): storing and reading it costs about
  // as much as tracing again.
  const Scalar* const* departures = nullptr;
  if (!forward) {
    AdvectionScratch& own = work.forward;
    if (rows) {
      Scalar** store = scheme == AdvectionScheme::BFECC ? store_departures() : nullptr;
      Scalar* unused[kMaxAdvectedFields] = {};  // scratch_only: the row passes stop before out
      own.reserve(n, scheme, count);
      advect_rows(scheme, u, L, count, q, unused, dt, rk, own, use_avx2(), true, store);
      departures = store;
    } else {
      std::vector<std::vector<Scalar>> out(count, std::vector<Scalar>(n));
      Scalar* out_p[kMaxAdvectedFields];
      for (int f = 0; f < count; ++f) out_p[f] = out[f].data();
      advect_fields(scheme, u, L, count, q, out_p, dt, rk, own);
    }
    forward = &own;
  }
  const Scalar *fwd[kMaxAdvectedFields], *lo[kMaxAdvectedFields], *hi[kMaxAdvectedFields],
      *bar[kMaxAdvectedFields];
  Scalar* g_fwd_p[kMaxAdvectedFields];
  for (int f = 0; f < count; ++f) {
    fwd[f] = forward->forward[f].data(), lo[f] = forward->lo[f].data(), hi[f] = forward->hi[f].data();
    if (scheme == AdvectionScheme::BFECC) bar[f] = forward->corrected[f].data();
    g_fwd_p[f] = work.zeros(kFwd + f, n);
  }
  if (scheme == AdvectionScheme::MacCormack) {
    // out = clamp(q^ + (q - q~)/2), q~ = SL(q^, -dt). The bounds are those of q over the
    // stencil of the forward departure point, which the last pass traces again: where the clamp
    // took a bound, this pass only notes which (1: lo, 2: hi), and the last one sends the
    // node's gradient to that extreme node of its stencil.
    std::uint8_t* branch[kMaxAdvectedFields];
    for (int f = 0; f < count; ++f) branch[f] = work.zero_flags(f, n);
    pass(-dt, fwd, g_fwd_p, [&](int f, Index c, const Stencil<ThreeD>& st, const Scalar* at) -> Scalar {
      const Scalar g = g_out[f][c];
      if (g == 0) return 0;
      const Scalar v = fwd[f][c] + 0.5 * (q[f][c] - st.value(at));
      if (v < lo[f][c] || hi[f][c] < v) {
        branch[f][c] = v < lo[f][c] ? 1 : 2;
        return 0;
      }
      g_fwd_p[f][c] += g;
      g_q[f][c] += 0.5 * g;
      return -0.5 * g;
    });
    pass(dt, q, g_q, [&](int f, Index c, const Stencil<ThreeD>& st, const Scalar*) -> Scalar {
      if (branch[f][c]) g_q[f][branch[f][c] == 1 ? st.argmin(q[f]) : st.argmax(q[f])] += g_out[f][c];
      return g_fwd_p[f][c];
    });
    stage0();
    return;
  }
  // BFECC: q_bar = q + (q - SL(q^, -dt))/2, out = clamp(SL(q_bar, dt)).
  Scalar* g_bar_p[kMaxAdvectedFields];
  for (int f = 0; f < count; ++f) g_bar_p[f] = work.zeros(kBar + f, n);
  Scalar* gp_store[3] = {nullptr, nullptr, nullptr};  // this pass's gp, carried by the last one's trace
  for (int b = first; b < 3; ++b) gp_store[b] = gp_keep[b] = work.zeros(kGp + b, n);
  // Where the clamp took a bound, the result is that extreme node of q on the stencil of the
  // departure point (the same as the forward's: the same trace).
  pass(dt, bar, g_bar_p, [&](int f, Index c, const Stencil<ThreeD>& st, const Scalar* at) -> Scalar {
    const Scalar g = g_out[f][c];
    if (g == 0) return 0;
    const Scalar v = st.value(at);
    if (v < lo[f][c]) g_q[f][st.argmin(q[f])] += g;
    else if (hi[f][c] < v) g_q[f][st.argmax(q[f])] += g;
    else return g;
    return 0;
  }, departures);
  for (int b = first; b < 3; ++b) gp_keep[b] = nullptr;
  // q_bar = 1.5 q - 0.5 q~
  pass(-dt, fwd, g_fwd_p, [&](int f, Index c, const Stencil<ThreeD>&, const Scalar*) -> Scalar {
    const Scalar g = g_bar_p[f][c];
    g_q[f][c] += 1.5 * g;
    return -0.5 * g;
  });
  for (int b = first; b < 3; ++b) gp_add[b] = gp_store[b];
  semi_lagrangian(q, g_fwd_p, g_q);  // the same trace as the first pass
  stage0();
}

}  // namespace

Scalar* AdjointScratch::raw(int slot, Index n) {
  if (static_cast<int>(buffers.size()) <= slot) buffers.resize(static_cast<size_t>(slot) + 1);
  std::vector<Scalar>& v = buffers[static_cast<size_t>(slot)];
  v.resize(static_cast<size_t>(n));
  return v.data();
}

Scalar* AdjointScratch::zeros(int slot, Index n) {
  if (static_cast<int>(buffers.size()) <= slot) buffers.resize(static_cast<size_t>(slot) + 1);
  return zero_filled(buffers[static_cast<size_t>(slot)], n);
}

std::uint8_t* AdjointScratch::zero_flags(int slot, Index n) {
  if (static_cast<int>(flags.size()) <= slot) flags.resize(static_cast<size_t>(slot) + 1);
  std::vector<std::uint8_t>& v = flags[static_cast<size_t>(slot)];
  v.resize(static_cast<size_t>(n));
  std::uint8_t* p = v.data();
  parallel_for(n, [&](Index i) { p[i] = 0; });
  return p;
}

void advect_adjoint(AdvectionScheme scheme, const MacVelocity& u, const FieldLayout& L, int count,
                    const Scalar* const* q, const Scalar* const* g_out, Scalar* const* g_q,
                    const std::array<Scalar*, 3>& g_u, Scalar dt, int rk_order, const AdvectionScratch* forward,
                    AdjointScratch* work) {
  if (count <= 0) return;
  if (count > kMaxAdvectedFields) throw InvalidArgument("advect_adjoint: at most 8 fields per call");
  if (u.walls) throw InvalidArgument("walls: the advection adjoint does not handle no-slip walls");
  AdjointScratch local;
  AdjointScratch& w = work ? *work : local;
  if (u.comp[0]) advect_adjoint_impl<true>(scheme, u, L, count, q, g_out, g_q, g_u, dt, rk_order, forward, w);
  else advect_adjoint_impl<false>(scheme, u, L, count, q, g_out, g_q, g_u, dt, rk_order, forward, w);
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

void Solver::cell_force_adjoint(int axis, const Scalar* g, Scalar* out, Index stride, Scalar scale) const {
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
    out[c * stride] = s * scale;
  });
}

void Solver::projection_adjoint(std::array<std::vector<Scalar>, 3>& grad, Scalar dt, Interrupt& interrupt,
                                Index warm_step) {
  // u' = u - (dt/h) G p with A p = -div(u) / dt. The transpose: dL/dp = -(dt/h) G^T g, then one
  // solve w = A^-1 dL/dp (A is symmetric; dL/dp sums to zero on every singular component, as the
  // forward right-hand side does), then g += div^T w * (-1/dt); the divergence is 0 in solid cells.
  enforce_boundary_adjoint(grad);  // project() ends with enforce_boundary
  const Index n = cells_.size();
  std::vector<Scalar>& gp = adjoint_gp_;
  std::vector<Scalar>& w = adjoint_w_;
  gp.resize(static_cast<size_t>(n));
  w.resize(static_cast<size_t>(n));
  parallel_for(n, [&](Index c) { gp[c] = 0, w[c] = 0; });
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
  const bool fixed = config_.pressure_vcycles > 0;
  if (norm2 > 0 && fixed) {
    // The forward map b -> p is k V-cycles from zero: Q sum_j (I - B A)^j B with B = Q V Q
    // symmetric (V is a symmetric cycle, Q the projection off solids and the null space), so
    // it is symmetric and its transpose is the same k cycles from zero.
    IterativeOptions options{0, config_.pressure_vcycles};
    pressure_solver_->solve(gp.data(), w.data(), options, interrupt);
  } else if (norm2 > 0) {
    // Warm start (as project() does) only when it beats zero.
    if (warm_step >= 0 && adjoint_pressure_step_ == warm_step + 1 &&
        static_cast<Index>(adjoint_pressure_.size()) == n) {
      std::vector<Scalar>& r = adjoint_r_;
      r.resize(static_cast<size_t>(n));
      pressure_solver_->op().residual(gp.data(), adjoint_pressure_.data(), r.data());
      if (parallel_sum(n, [&](Index c) { return r[c] * r[c]; }) < norm2) w = adjoint_pressure_;
    }
    IterativeOptions options{config_.tol, config_.max_iter};
    const SolveInfo info = pressure_solver_->solve(gp.data(), w.data(), options, interrupt);
    if (!info.converged)
      throw ConvergenceError("pressure: the adjoint projection did not reach tol=" + format_real(config_.tol) +
                             " (relative residual " + format_real(info.residual) + ")");
  }
  if (warm_step >= 0) {
    adjoint_pressure_ = w;
    adjoint_pressure_step_ = warm_step;
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
                          Scalar* grad_viscosity, Scalar* grad_control, Interrupt& interrupt,
                          const std::array<AdvectionScratch, 4>* forward) {
  if (!(dt > 0) || !std::isfinite(dt)) throw InvalidArgument("dt: expected a finite time step > 0, got " + format_real(dt));
  check_differentiable();
  check_state(before);
  check_state(adjoint);
  const int dim = model_.shape.dim;
  const Index cells = cells_.size();
  // Recompute the step up to the viscosity: s0 is what advection reads, s what the viscosity
  // made (only dL/dnu reads it: without it, s0 and the advection's scratch are enough).
  State& s0 = adjoint_s0_;
  const Index before_steps = before.steps;  // before may be s0 itself (adjoint_before)
  if (&before != &s0) s0 = before;  // into the kept arrays
  refresh_solids(s0);
  apply_sources(s0);
  enforce_boundary(s0);
  // The advection's forward passes, for its adjoint: the forward step's when it kept them, the
  // recomputed step's with the viscosity; else advect_adjoint recomputes them (BFECC's with
  // their departure points, which its first pass then reads).
  const std::array<AdvectionScratch, 4>* kept = forward ? forward : grad_viscosity ? &adjoint_kept_ : nullptr;
  State s;
  if (grad_viscosity) {
    s = s0;
    advect(s, dt, forward ? nullptr : &adjoint_kept_);
    add_forces(s, dt, control);
    diffuse(s, dt, interrupt);
  }
  interrupt.check();
  std::array<std::vector<Scalar>, 3>& g = adjoint.velocity;
  // 4. Projection.
  projection_adjoint(g, dt, interrupt, before_steps);
  // 3. Viscosity: (I + c L) x = u*, c = nu dt / h^2: lambda = (I + c L)^-1 g, dL/du* = lambda,
  // dL/dc = -lambda . L x (also at nu = 0, where the forward pass skips the solve).
  enforce_boundary_adjoint(g);
  const Scalar c = config_.viscosity * dt / (model_.h * model_.h);
  Scalar grad_nu = 0;
  {
    std::vector<Scalar> lambda, lx;
    for (int a = 0; a < 3; ++a) {
      if (!active_[a] || (c == 0 && !grad_viscosity)) continue;  // at nu = 0 the step is the identity
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
      if (grad_viscosity) {
        lx.assign(static_cast<size_t>(nf), 0);
        apply_viscosity_operator(a, 1, s.velocity[a].data(), lx.data());  // (I + L) x
        const Scalar* x = s.velocity[a].data();
        const Scalar* l = lambda.data();
        const Scalar* y = lx.data();
        grad_nu -= parallel_sum(nf, [&](Index f) { return l[f] * (y[f] - x[f]); });
      }
      if (c > 0) g[a].swap(lambda);
    }
    if (grad_viscosity) *grad_viscosity = grad_nu * dt / (model_.h * model_.h);
  }
  // 2. Forces: controls and buoyancy are cell values averaged to the free faces.
  if (config_.periodic) enforce_boundary_adjoint(g);
  std::vector<Scalar>& g_force = adjoint_force_;
  g_force.resize(static_cast<size_t>(cells));
  const bool rho = config_.density && config_.alpha != 0, temp = config_.temperature && config_.beta != 0;
  for (int a = 0; a < 3; ++a) {
    if (!active_[a]) continue;
    if (grad_control) {
      const int user = a - (3 - dim);
      cell_force_adjoint(a, g[a].data(), grad_control + user, dim, dt);
    }
    if ((rho || temp) && config_.up[a] != 0) {
      cell_force_adjoint(a, g[a].data(), g_force.data(), 1, 1);
      const Scalar up = config_.up[a] * dt;
      if (rho) parallel_for(cells, [&](Index cc) { adjoint.density[cc] -= config_.alpha * up * g_force[cc]; });
      if (temp) parallel_for(cells, [&](Index cc) { adjoint.temperature[cc] += config_.beta * up * g_force[cc]; });
    }
  }
  // 1. Advection: velocity through itself, scalars (zeroed in solids and at inflows) through it.
  enforce_boundary_adjoint(g);
  const MacVelocity u0 = mac_velocity(s0.velocity);
  const Scalar dt_grid = dt / model_.h;
  std::array<std::vector<Scalar>, 3>& g0 = adjoint_g0_;
  std::array<Scalar*, 3> g0_p{nullptr, nullptr, nullptr};
  for (int a = 0; a < 3; ++a)
    if (active_[a]) g0_p[a] = zero_filled(g0[a], faces_[a].size());
  for (int a = 0; a < 3; ++a) {
    if (!active_[a]) continue;
    const Scalar* qa = s0.velocity[a].data();
    const Scalar* ga = g[a].data();
    advect_adjoint(config_.advection, u0, faces_[a], 1, &qa, &ga, &g0_p[a], g0_p, dt_grid, config_.rk_order,
                   kept ? &(*kept)[1 + a] : nullptr, &adjoint_work_);
  }
  const Scalar* q[2];
  const Scalar* g_out[2];
  Scalar* g_in[2];
  Scalar* g_scalars[2];
  std::array<std::vector<Scalar>, 2>& g_scalar0 = adjoint_scalar0_;
  int count = 0;
  for (auto [field, grad] : {std::pair{&s0.density, &adjoint.density}, std::pair{&s0.temperature, &adjoint.temperature}}) {
    if (field->empty()) continue;
    Scalar* gq = grad->data();
    if (has_solid_) parallel_for(cells, [&](Index cc) { if (model_.solid[cc]) gq[cc] = 0; });
    g_scalars[count] = gq;
    q[count] = field->data();
    g_out[count] = gq;
    g_in[count] = zero_filled(g_scalar0[count], cells);
    ++count;
  }
  if (count > 0 && any_open()) inflow_ambient(s0, g_scalars, count);
  advect_adjoint(config_.advection, u0, cells_, count, q, g_out, g_in, g0_p, dt_grid, config_.rk_order,
                 kept ? &(*kept)[0] : nullptr, &adjoint_work_);
  // 0. Boundary values and sources imposed before the step.
  enforce_boundary_adjoint(g0);
  // the result moves into the returned arrays; the solver keeps the spent ones (no copy)
  int moved = 0;
  for (auto [field, grad] : {std::pair{&s0.density, &adjoint.density}, std::pair{&s0.temperature, &adjoint.temperature}})
    if (!field->empty()) grad->swap(g_scalar0[moved++]);
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
  for (int a = 0; a < 3; ++a) g[a].swap(g0[a]);  // g0 keeps g's old arrays for the next call
  std::fill(adjoint.pressure.begin(), adjoint.pressure.end(), Scalar(0));
}

}  // namespace kinema::grid
