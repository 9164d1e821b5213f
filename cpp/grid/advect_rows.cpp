#include "grid/advect_rows.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <memory>
#include <utility>
#include <vector>

#include "core/simd.h"

namespace kinema::grid {

namespace {

// The brackets (kernels.h: Bracket) of a row of coordinates along one axis.
struct RowAxis {
  int* i0 = nullptr;
  int* i1 = nullptr;
  Scalar* w = nullptr;
};

// One thread's arrays for a row of n nodes: the Runge-Kutta stages k1..k3, the point being
// evaluated, the face- and cell-offset brackets per axis, a sampled row, and the positions
// k + offset of the nodes along the row.
struct RowScratch {
  std::vector<Scalar> reals;
  std::vector<int> ints;
  Scalar *k1[3], *k2[3], *k3[3], *p[3];
  RowAxis face[3], cell[3];
  Scalar *sampled, *x2;

  RowScratch(Index n, Scalar offset) : reals(static_cast<size_t>(20 * n)), ints(static_cast<size_t>(12 * n)) {
    Scalar* r = reals.data();
    int* q = ints.data();
    auto take = [&]() { return std::exchange(r, r + n); };
    for (int b = 0; b < 3; ++b) {
      k1[b] = take(), k2[b] = take(), k3[b] = take(), p[b] = take();
      face[b] = RowAxis{q, q + n, take()};
      cell[b] = RowAxis{q + 2 * n, q + 3 * n, take()};
      q += 4 * n;
    }
    sampled = take();
    x2 = take();
    for (Index k = 0; k < n; ++k) x2[k] = static_cast<Scalar>(k) + offset;
  }
};

// bracket() of kernels.h element-wise on x[k] - offset, `nodes` nodes, with the same
// operations (so the same bits); int indices, which vectorise.
template <bool Periodic>
[[gnu::always_inline]] inline void bracket_row(const Scalar* __restrict x, Index n, Scalar offset, int nodes,
                                               int period, const RowAxis& out) {
  int* __restrict i0 = out.i0;
  int* __restrict i1 = out.i1;
  Scalar* __restrict w = out.w;
  if constexpr (Periodic) {
    const Scalar p = static_cast<Scalar>(period);
    for (Index k = 0; k < n; ++k) {
      Scalar s = x[k] - offset;
      s -= p * std::floor(s / p);
      s = (s > -1 && s <= p) ? s : 0;  // NaN or garbage (see bracket in kernels.h)
      int i = static_cast<int>(s);
      i = i > period - 1 ? period - 1 : (i < 0 ? 0 : i);  // s rounded up to p (or garbage in)
      w[k] = s - static_cast<Scalar>(i);
      i0[k] = i;
      i1[k] = i + 1 >= nodes ? i + 1 - period : i + 1;  // cell axes wrap, face axes hold the duplicate
    }
  } else {
    const Scalar hi = static_cast<Scalar>(nodes - 1);
    const int top = nodes - 2;
    for (Index k = 0; k < n; ++k) {
      Scalar s = x[k] - offset;
      s = s < 0 ? 0 : (s > hi ? hi : s);
      s = s == s ? s : 0;
      int i = static_cast<int>(s);
      i = i > top ? top : i;
      w[k] = s - static_cast<Scalar>(i);
      i0[k] = i;
      i1[k] = i + 1;
    }
  }
}

// detail::interpolate of kernels.h element-wise: out[k] = f at the row's brackets (strides s0,
// s1 of f's layout); with Bounds, lo/hi[k] = the extrema of the nodes used.
template <bool ThreeD, bool Bounds>
[[gnu::always_inline]] inline void interpolate_row(const Scalar* __restrict f, int s0, int s1, const RowAxis& a0,
                                                   const RowAxis& a1, const RowAxis& a2, Index n,
                                                   Scalar* __restrict out, Scalar* __restrict lo,
                                                   Scalar* __restrict hi) {
  const int *__restrict i0 = a0.i0, *__restrict i1 = a0.i1;
  const int *__restrict j0 = a1.i0, *__restrict j1 = a1.i1;
  const int *__restrict k0 = a2.i0, *__restrict k1 = a2.i1;
  const Scalar *__restrict wi = a0.w, *__restrict wj = a1.w, *__restrict wk = a2.w;
  for (Index k = 0; k < n; ++k) {
    const int r0 = j0[k] * s1, r1 = j1[k] * s1, c0 = k0[k], c1 = k1[k];
    int o = ThreeD ? i0[k] * s0 : 0;
    Scalar f00 = f[o + r0 + c0], f01 = f[o + r0 + c1], f10 = f[o + r1 + c0], f11 = f[o + r1 + c1];
    Scalar mn = 0, mx = 0;
    if constexpr (Bounds) {
      mn = std::min(std::min(f00, f01), std::min(f10, f11));
      mx = std::max(std::max(f00, f01), std::max(f10, f11));
    }
    Scalar a = f00 + wk[k] * (f01 - f00), b = f10 + wk[k] * (f11 - f10);
    Scalar v = a + wj[k] * (b - a);
    if constexpr (ThreeD) {
      o = i1[k] * s0;
      f00 = f[o + r0 + c0], f01 = f[o + r0 + c1], f10 = f[o + r1 + c0], f11 = f[o + r1 + c1];
      if constexpr (Bounds) {
        mn = std::min(mn, std::min(std::min(f00, f01), std::min(f10, f11)));
        mx = std::max(mx, std::max(std::max(f00, f01), std::max(f10, f11)));
      }
      a = f00 + wk[k] * (f01 - f00), b = f10 + wk[k] * (f11 - f10);
      const Scalar v1 = a + wj[k] * (b - a);
      v = v + wi[k] * (v1 - v);
    }
    out[k] = v;
    if constexpr (Bounds) {
      lo[k] = mn;
      hi[k] = mx;
    }
  }
}

// interpolate_row<ThreeD, false> (the same bits in out) plus the interpolant's partial
// derivatives along each axis in grid units, d[b][k] (d[0] untouched in 2D): the adjoint's
// d u(y) / d y at the Runge-Kutta stages, from the values the trace gathers anyway.
template <bool ThreeD>
[[gnu::always_inline]] inline void interpolate_row_grad(const Scalar* __restrict f, int s0, int s1,
                                                        const RowAxis& a0, const RowAxis& a1, const RowAxis& a2,
                                                        Index n, Scalar* __restrict out, Scalar* const* d) {
  const int *__restrict i0 = a0.i0, *__restrict i1 = a0.i1;
  const int *__restrict j0 = a1.i0, *__restrict j1 = a1.i1;
  const int *__restrict k0 = a2.i0, *__restrict k1 = a2.i1;
  const Scalar *__restrict wi = a0.w, *__restrict wj = a1.w, *__restrict wk = a2.w;
  Scalar *__restrict d0 = d[0], *__restrict d1 = d[1], *__restrict d2 = d[2];
  for (Index k = 0; k < n; ++k) {
    const int r0 = j0[k] * s1, r1 = j1[k] * s1, c0 = k0[k], c1 = k1[k];
    int o = ThreeD ? i0[k] * s0 : 0;
    Scalar f00 = f[o + r0 + c0], f01 = f[o + r0 + c1], f10 = f[o + r1 + c0], f11 = f[o + r1 + c1];
    Scalar a = f00 + wk[k] * (f01 - f00), b = f10 + wk[k] * (f11 - f10);
    Scalar v = a + wj[k] * (b - a);
    Scalar dj = b - a, dk = (f01 - f00) + wj[k] * ((f11 - f10) - (f01 - f00));
    if constexpr (ThreeD) {
      o = i1[k] * s0;
      f00 = f[o + r0 + c0], f01 = f[o + r0 + c1], f10 = f[o + r1 + c0], f11 = f[o + r1 + c1];
      a = f00 + wk[k] * (f01 - f00), b = f10 + wk[k] * (f11 - f10);
      const Scalar v1 = a + wj[k] * (b - a);
      const Scalar dj1 = b - a, dk1 = (f01 - f00) + wj[k] * ((f11 - f10) - (f01 - f00));
      d0[k] = v1 - v;
      dj = dj + wi[k] * (dj1 - dj);
      dk = dk + wi[k] * (dk1 - dk);
      v = v + wi[k] * (v1 - v);
    }
    out[k] = v;
    d1[k] = dj;
    d2[k] = dk;
  }
}

// What one pass over the rows writes.
enum class RowPass {
  Forward,     // out = src at the departure points, lo/hi = the stencil bounds
  Plain,       // out = src at the departure points
  MacCormack,  // out = clamp(q^ + (q - q~)/2, lo, hi), src = q^ traced back (q~)
  BFECC,       // out = q + (q - q~)/2, src = q^ traced back (q~)
};

struct RowJob {
  RowPass kind;
  Scalar dt;  // signed: the second pass traces back over -dt
  const Scalar* const* src;
  const Scalar* const* q;
  Scalar* const* out;
  Scalar* const* lo;
  Scalar* const* hi;
  Scalar* const* trace = nullptr;  // kTraceSlots arrays over L (advect_rows' trace), or null
};

// The passes of kernels.cpp (Passes<ThreeD, false>) over rows; every member function that runs
// per row is always_inline, so the AVX2 entry point compiles all of it for AVX2.
template <bool ThreeD, bool Periodic>
struct RowPasses {
  static constexpr int first = ThreeD ? 0 : 1;  // first active axis
  const MacVelocity& u;
  const FieldLayout& L;
  int count, rk;
  int face_axis;           // the axis L's nodes are faces of, or -1 for cells
  int cells[3], period[3];  // per axis of the velocity's grid
  int us0[3], us1[3];       // strides of u's components

  RowPasses(const MacVelocity& vel, const FieldLayout& layout, int fields, int rk_order)
      : u(vel), L(layout), count(fields), rk(rk_order) {
    face_axis = L.offset[0] == 0 ? 0 : L.offset[1] == 0 ? 1 : L.offset[2] == 0 ? 2 : -1;
    for (int b = 0; b < 3; ++b) {
      const FieldLayout& F = u.layout[b];
      cells[b] = static_cast<int>(F.n[b] - 1);
      period[b] = static_cast<int>(F.period[b]);
      us0[b] = static_cast<int>(F.stride(0));
      us1[b] = static_cast<int>(F.stride(1));
    }
  }

  // v = u at the row's points p (MacVelocity::at_lean element-wise): the brackets of each axis
  // for the face and the cell offset, shared by the components. jac (nullable, 9 arrays):
  // jac[3 a + b] = d u_a / d p_b (interpolate_row_grad; no clamping factor).
  [[gnu::always_inline]] inline void velocity_row(Scalar* const* p, Index n, Scalar* const* v, RowScratch& s,
                                                  Scalar* const* jac = nullptr) const {
    for (int b = first; b < 3; ++b) {
      bracket_row<Periodic>(p[b], n, 0, cells[b] + 1, period[b], s.face[b]);
      bracket_row<Periodic>(p[b], n, 0.5, cells[b], period[b], s.cell[b]);
    }
    for (int a = first; a < 3; ++a) {
      const RowAxis &x0 = a == 0 ? s.face[0] : s.cell[0], &x1 = a == 1 ? s.face[1] : s.cell[1],
                    &x2 = a == 2 ? s.face[2] : s.cell[2];
      if (jac) interpolate_row_grad<ThreeD>(u.comp[a], us0[a], us1[a], x0, x1, x2, n, v[a], jac + 3 * a);
      else interpolate_row<ThreeD, false>(u.comp[a], us0[a], us1[a], x0, x1, x2, n, v[a], nullptr, nullptr);
    }
  }

  // u at node k of row (i, j) by the general interpolation (clamping, periodic wrap).
  [[gnu::always_inline]] inline void outer_node(Index i, Index j, Index k, Scalar* const* v, const Scalar* x2) const {
    const Vec3 x{static_cast<Scalar>(i) + L.offset[0], static_cast<Scalar>(j) + L.offset[1], x2[k]};
    const Vec3 w = u.template at_lean<ThreeD>(x);
    for (int b = first; b < 3; ++b) v[b][k] = w[b];
  }

  // k1 = u at the nodes of row (i, j) (Passes::node_velocity element-wise): 2- and 4-point
  // averages inside, the general interpolation on the domain's outer layer.
  [[gnu::always_inline]] inline void node_velocity_row(Index i, Index j, Index n, Scalar* const* v,
                                                       const Scalar* x2) const {
    const Index edge[3] = {cells[0] - 1, cells[1] - 1, cells[2] - 1};  // nodes idx >= edge are outer
    bool outer_row = j == 0 || j >= edge[1];
    if (ThreeD) outer_row = outer_row || i == 0 || i >= edge[0];
    const Index begin = outer_row ? n : 1, end = outer_row ? n : std::max(begin, std::min(n, edge[2]));
    for (Index k = 0; k < begin; ++k) outer_node(i, j, k, v, x2);
    for (Index k = end; k < n; ++k) outer_node(i, j, k, v, x2);
    if (begin >= end) return;
    for (int b = first; b < 3; ++b) {
      const FieldLayout& F = u.layout[b];
      const Scalar* __restrict ub = u.comp[b] + F.index(i, j, 0);
      Scalar* __restrict vb = v[b];
      if (face_axis < 0) {  // cell centre: between faces idx_b and idx_b + 1
        const Index sb = F.stride(b);
        for (Index k = begin; k < end; ++k) vb[k] = 0.5 * (ub[k] + ub[k + sb]);
      } else if (face_axis == b) {
        for (Index k = begin; k < end; ++k) vb[k] = ub[k];
      } else {  // faces idx_b, idx_b + 1 of the cells idx_a - 1 and idx_a
        const Index sa = F.stride(face_axis), sb = F.stride(b);
        for (Index k = begin; k < end; ++k) vb[k] = 0.25 * (ub[k - sa] + ub[k - sa + sb] + ub[k] + ub[k + sb]);
      }
    }
  }

  // p = x - c kv for the row's nodes x.
  [[gnu::always_inline]] inline void shift_row(Index i, Index j, Index n, Scalar c, Scalar* const* kv,
                                               RowScratch& s) const {
    const Scalar x[2] = {static_cast<Scalar>(i) + L.offset[0], static_cast<Scalar>(j) + L.offset[1]};
    for (int b = first; b < 2; ++b) {
      Scalar* __restrict pb = s.p[b];
      const Scalar* __restrict kb = kv[b];
      for (Index k = 0; k < n; ++k) pb[k] = x[b] - c * kb[k];
    }
    Scalar* __restrict p2 = s.p[2];
    const Scalar *__restrict k2 = kv[2], *__restrict x2 = s.x2;
    for (Index k = 0; k < n; ++k) p2[k] = x2[k] - c * k2[k];
  }

  // kept[b] = s.p[b] for the active axes.
  [[gnu::always_inline]] inline void keep(const RowScratch& s, Index n, Scalar* const* kept) const {
    for (int b = first; b < 3; ++b) std::copy_n(s.p[b], n, kept[b]);
  }

  // s.p = the departure points of row (i, j) over dt (back_trace_from element-wise); y1, y2
  // (nullable) receive the points the second and third stages sample the velocity at, j1, j2
  // (nullable) the velocity's derivatives there (velocity_row's jac).
  [[gnu::always_inline]] inline void trace_row(Index i, Index j, Index n, Scalar dt, RowScratch& s,
                                               Scalar* const* y1 = nullptr, Scalar* const* y2 = nullptr,
                                               Scalar* const* j1 = nullptr, Scalar* const* j2 = nullptr) const {
    node_velocity_row(i, j, n, s.k1, s.x2);
    if (rk == 1) return shift_row(i, j, n, dt, s.k1, s);
    shift_row(i, j, n, 0.5 * dt, s.k1, s);
    if (y1) keep(s, n, y1);
    velocity_row(s.p, n, s.k2, s, j1);
    if (rk == 2) return shift_row(i, j, n, dt, s.k2, s);
    shift_row(i, j, n, 0.75 * dt, s.k2, s);
    if (y2) keep(s, n, y2);
    velocity_row(s.p, n, s.k3, s, j2);
    for (int b = first; b < 3; ++b) {
      Scalar* __restrict k3 = s.k3[b];
      const Scalar *__restrict k1 = s.k1[b], *__restrict k2 = s.k2[b];
      for (Index k = 0; k < n; ++k) k3[k] = (2 * k1[k] + 3 * k2[k] + 4 * k3[k]) / 9;
    }
    shift_row(i, j, n, dt, s.k3, s);
  }

  // One row of a pass.
  [[gnu::always_inline]] inline void row(const RowJob& job, Index i, Index j, RowScratch& s) const {
    const Index n = L.n[2], c = L.index(i, j, 0);
    if (job.trace) {
      Scalar* st[kTraceSlots];
      for (int e = 0; e < kTraceSlots; ++e) st[e] = job.trace[e] ? job.trace[e] + c : nullptr;
      // the stages' arrays where given (axis 2 always is); interpolate_row_grad gives the same bits
      trace_row(i, j, n, job.dt, s, st[2] ? st : nullptr, st[5] ? st + 3 : nullptr, st[17] ? st + 9 : nullptr,
                st[26] ? st + 18 : nullptr);
      keep(s, n, st + 6);
    } else {
      trace_row(i, j, n, job.dt, s);
    }
    RowAxis* at = s.face;  // the velocity's brackets are spent: reuse their storage
    for (int b = first; b < 3; ++b)
      bracket_row<Periodic>(s.p[b], n, L.offset[b], static_cast<int>(L.n[b]), static_cast<int>(L.period[b]), at[b]);
    const int s0 = static_cast<int>(L.stride(0)), s1 = static_cast<int>(L.stride(1));
    for (int f = 0; f < count; ++f) {
      switch (job.kind) {
        case RowPass::Forward:
          interpolate_row<ThreeD, true>(job.src[f], s0, s1, at[0], at[1], at[2], n, job.out[f] + c, job.lo[f] + c,
                                        job.hi[f] + c);
          break;
        case RowPass::Plain:
          interpolate_row<ThreeD, false>(job.src[f], s0, s1, at[0], at[1], at[2], n, job.out[f] + c, nullptr,
                                         nullptr);
          break;
        case RowPass::MacCormack: {
          interpolate_row<ThreeD, false>(job.src[f], s0, s1, at[0], at[1], at[2], n, s.sampled, nullptr, nullptr);
          const Scalar *__restrict fwd = job.src[f] + c, *__restrict q = job.q[f] + c, *__restrict back = s.sampled;
          const Scalar *__restrict lo = job.lo[f] + c, *__restrict hi = job.hi[f] + c;
          Scalar* __restrict out = job.out[f] + c;
          for (Index k = 0; k < n; ++k) out[k] = std::clamp(fwd[k] + 0.5 * (q[k] - back[k]), lo[k], hi[k]);
          break;
        }
        case RowPass::BFECC: {
          interpolate_row<ThreeD, false>(job.src[f], s0, s1, at[0], at[1], at[2], n, s.sampled, nullptr, nullptr);
          const Scalar *__restrict q = job.q[f] + c, *__restrict back = s.sampled;
          Scalar* __restrict out = job.out[f] + c;
          for (Index k = 0; k < n; ++k) out[k] = q[k] + 0.5 * (q[k] - back[k]);
          break;
        }
      }
    }
  }

  // The stages of row (i, j)'s back-traces over dt: st[0..2] = y1, st[3..5] = y2, st[6..8] = p,
  // st[9..17] and st[18..26] the velocity's derivatives at y1 and y2 (velocity_row's jac).
  [[gnu::always_inline]] inline void stages(Index i, Index j, Scalar dt, RowScratch& s, Scalar* const* st) const {
    const Index n = L.n[2];
    trace_row(i, j, n, dt, s, st, st + 3, st + 9, st + 18);
    keep(s, n, st + 6);
  }
  static void stages_baseline(const RowPasses& p, Index i, Index j, Scalar dt, RowScratch& s, Scalar* const* st) {
    p.stages(i, j, dt, s, st);
  }
#if KINEMA_HAVE_AVX2_CLONES
  KINEMA_TARGET_AVX2 static void stages_avx2(const RowPasses& p, Index i, Index j, Scalar dt, RowScratch& s,
                                             Scalar* const* st) {
    p.stages(i, j, dt, s, st);
  }
#endif

  using RowFunction = void (*)(const RowPasses&, const RowJob&, Index, Index, RowScratch&);

  static void row_baseline(const RowPasses& p, const RowJob& job, Index i, Index j, RowScratch& s) {
    p.row(job, i, j, s);
  }
#if KINEMA_HAVE_AVX2_CLONES
  // "avx2" without "fma": no contraction, so the same bits as the baseline.
  KINEMA_TARGET_AVX2 static void row_avx2(const RowPasses& p, const RowJob& job, Index i, Index j,
                                               RowScratch& s) {
    p.row(job, i, j, s);
  }
#endif

  // Every row of L, handed out in small blocks on demand (for_each_node's schedule).
  void pass(const RowJob& job, bool avx2) const {
    RowFunction fn = &row_baseline;
#if KINEMA_HAVE_AVX2_CLONES
    if (avx2) fn = &row_avx2;
#else
    (void)avx2;
#endif
    const Index rows = L.rows(), n1 = L.n[1];
#pragma omp parallel if (L.size() > 8 * kParallelGrain)
    {
      RowScratch s(L.n[2], L.offset[2]);
#pragma omp for schedule(dynamic, 8)
      for (Index row = 0; row < rows; ++row) fn(*this, job, row / n1, row % n1, s);
    }
  }

  void run(AdvectionScheme scheme, const Scalar* const* q, Scalar* const* out, Scalar dt, AdvectionScratch& scratch,
           bool avx2, bool scratch_only, Scalar* const* trace) const {
    if (scheme == AdvectionScheme::SemiLagrangian) {
      pass(RowJob{RowPass::Plain, dt, q, q, out, nullptr, nullptr, trace}, avx2);
      return;
    }
    AdvectionScratch::Fields s = scratch.fields(count, scheme);
    Scalar *const *fwd = s.forward, *const *lo = s.lo, *const *hi = s.hi, *const *bar = s.corrected;
    // q^ = SL(q, dt) with the clamping bounds of Selle et al.
    pass(RowJob{RowPass::Forward, dt, q, q, fwd, lo, hi, trace}, avx2);
    if (scratch_only && scheme == AdvectionScheme::MacCormack) return;
    if (scheme == AdvectionScheme::MacCormack) {
      pass(RowJob{RowPass::MacCormack, -dt, fwd, q, out, lo, hi}, avx2);
      return;
    }
    // BFECC: the error-compensated field advected forward once more, clamped to q^'s bounds.
    pass(RowJob{RowPass::BFECC, -dt, fwd, q, bar, nullptr, nullptr}, avx2);
    if (scratch_only) return;
    pass(RowJob{RowPass::Plain, dt, bar, q, out, nullptr, nullptr}, avx2);
    clamp_fields(L, count, out, lo, hi);
  }
};

}  // namespace

struct RowTrace::Impl {
  RowScratch scratch;
  std::vector<Scalar> store;
  Impl(Index n, Scalar offset) : scratch(n, offset), store(static_cast<size_t>(27 * n)) {}
};

RowTrace::RowTrace(const MacVelocity& u, const FieldLayout& L, int rk_order, bool avx2)
    : u_(u), L_(L), rk_(rk_order), avx2_(avx2), impl_(std::make_unique<Impl>(L.n[2], L.offset[2])) {
  const Index n = L.n[2];
  Scalar* r = impl_->store.data();
  for (int b = 0; b < 3; ++b) y1[b] = r + b * n, y2[b] = r + (3 + b) * n, p[b] = r + (6 + b) * n;
  for (int m = 0; m < 2; ++m)
    for (int e = 0; e < 9; ++e) jac[m][e] = r + (9 + 9 * m + e) * n;
  if (!u.comp[0])  // 2D: axis 0 is the nodes' own coordinate
    for (Scalar* a : {y1[0], y2[0], p[0]}) std::fill(a, a + n, L.offset[0]);
}

RowTrace::~RowTrace() = default;

namespace {
template <bool Periodic>
[[gnu::always_inline]] inline void brackets_row(const Scalar* __restrict x, Index n, Scalar offset, int nodes,
                                                int period, const RowAxis& out, Scalar* __restrict d) {
  bracket_row<Periodic>(x, n, offset, nodes, period, out);
  const Scalar hi = static_cast<Scalar>(nodes - 1);
  for (Index k = 0; k < n; ++k) {
    const Scalar s = x[k] - offset;
    d[k] = Periodic || (s >= 0 && s <= hi) ? Scalar(1) : Scalar(0);
  }
}
template <bool Periodic>
[[gnu::always_inline]] inline void inside_row(const Scalar* __restrict x, Index n, Scalar offset, int nodes,
                                              Scalar* __restrict d) {
  const Scalar hi = static_cast<Scalar>(nodes - 1);
  for (Index k = 0; k < n; ++k) {
    const Scalar s = x[k] - offset;
    d[k] = Periodic || (s >= 0 && s <= hi) ? Scalar(1) : Scalar(0);
  }
}
void inside_baseline(const Scalar* x, Index n, Scalar offset, int nodes, Scalar* d) {
  inside_row<false>(x, n, offset, nodes, d);
}
#if KINEMA_HAVE_AVX2_CLONES
KINEMA_TARGET_AVX2 void inside_avx2(const Scalar* x, Index n, Scalar offset, int nodes, Scalar* d) {
  inside_row<false>(x, n, offset, nodes, d);
}
#endif

template <bool Periodic>
void brackets_baseline(const Scalar* x, Index n, Scalar offset, int nodes, int period, const RowAxis& out,
                       Scalar* d) {
  brackets_row<Periodic>(x, n, offset, nodes, period, out, d);
}
#if KINEMA_HAVE_AVX2_CLONES
template <bool Periodic>
KINEMA_TARGET_AVX2 void brackets_avx2(const Scalar* x, Index n, Scalar offset, int nodes, int period,
                                      const RowAxis& out, Scalar* d) {
  brackets_row<Periodic>(x, n, offset, nodes, period, out, d);
}
#endif

template <bool ThreeD, bool Periodic>
void trace_stages(const MacVelocity& u, const FieldLayout& L, int rk, bool avx2, Index i, Index j, Scalar dt,
                  RowScratch& s, Scalar* const* st) {
  const RowPasses<ThreeD, Periodic> passes(u, L, 1, rk);
#if KINEMA_HAVE_AVX2_CLONES
  if (avx2) return RowPasses<ThreeD, Periodic>::stages_avx2(passes, i, j, dt, s, st);
#else
  (void)avx2;
#endif
  RowPasses<ThreeD, Periodic>::stages_baseline(passes, i, j, dt, s, st);
}
}  // namespace

void RowTrace::trace(Index i, Index j, Scalar dt) {
  Scalar* st[27] = {y1[0], y1[1], y1[2], y2[0], y2[1], y2[2], p[0], p[1], p[2]};
  for (int m = 0; m < 2; ++m) std::copy_n(jac[m], 9, st + 9 + 9 * m);
  RowScratch& s = impl_->scratch;
  const bool periodic = L_.period[2] > 0;
  if (u_.comp[0]) {
    if (periodic) trace_stages<true, true>(u_, L_, rk_, avx2_, i, j, dt, s, st);
    else trace_stages<true, false>(u_, L_, rk_, avx2_, i, j, dt, s, st);
  } else {
    if (periodic) trace_stages<false, true>(u_, L_, rk_, avx2_, i, j, dt, s, st);
    else trace_stages<false, false>(u_, L_, rk_, avx2_, i, j, dt, s, st);
  }
}

void RowTrace::brackets(const Scalar* x, Scalar offset, Index nodes, Index period, int* i0, int* i1, Scalar* w,
                        Scalar* d) const {
  const RowAxis out{i0, i1, w};
  const Index n = L_.n[2];
  const int nn = static_cast<int>(nodes), pp = static_cast<int>(period);
#if KINEMA_HAVE_AVX2_CLONES
  if (avx2_) {
    if (period > 0) brackets_avx2<true>(x, n, offset, nn, pp, out, d);
    else brackets_avx2<false>(x, n, offset, nn, pp, out, d);
    return;
  }
#endif
  if (period > 0) brackets_baseline<true>(x, n, offset, nn, pp, out, d);
  else brackets_baseline<false>(x, n, offset, nn, pp, out, d);
}

void RowTrace::stage_brackets(int b, bool cell, const int*& i0, const int*& i1, const Scalar*& w) const {
  const RowAxis& a = cell ? impl_->scratch.cell[b] : impl_->scratch.face[b];
  i0 = a.i0, i1 = a.i1, w = a.w;
}

void RowTrace::inside(const Scalar* x, Scalar offset, Index nodes, Index period, Scalar* d) const {
  const Index n = L_.n[2];
  if (period > 0) {
    std::fill(d, d + n, Scalar(1));
    return;
  }
  const int nn = static_cast<int>(nodes);
#if KINEMA_HAVE_AVX2_CLONES
  if (avx2_) return inside_avx2(x, n, offset, nn, d);
#endif
  inside_baseline(x, n, offset, nn, d);
}

bool rows_apply(const MacVelocity& u, const FieldLayout& L) {
  if (u.walls) return false;
  constexpr Index kMaxNodes = std::numeric_limits<int>::max();
  const int first = u.comp[0] ? 0 : 1;
  const bool periodic = L.period[2] > 0;
  if (L.size() >= kMaxNodes) return false;
  for (int b = first; b < 3; ++b) {
    const FieldLayout& F = u.layout[b];
    if (!u.comp[b] || F.n[b] < 3 || L.n[b] < 2 || F.size() >= kMaxNodes) return false;
    if ((L.period[b] > 0) != periodic || (F.period[b] > 0) != periodic) return false;
  }
  return true;
}


void advect_rows(AdvectionScheme scheme, const MacVelocity& u, const FieldLayout& L, int count,
                 const Scalar* const* q, Scalar* const* out, Scalar dt, int rk_order, AdvectionScratch& scratch,
                 bool avx2, bool scratch_only, Scalar* const* trace) {
  const bool periodic = L.period[2] > 0;
  const bool s = scratch_only;
  if (u.comp[0]) {
    if (periodic) RowPasses<true, true>(u, L, count, rk_order).run(scheme, q, out, dt, scratch, avx2, s, trace);
    else RowPasses<true, false>(u, L, count, rk_order).run(scheme, q, out, dt, scratch, avx2, s, trace);
  } else {
    if (periodic) RowPasses<false, true>(u, L, count, rk_order).run(scheme, q, out, dt, scratch, avx2, s, trace);
    else RowPasses<false, false>(u, L, count, rk_order).run(scheme, q, out, dt, scratch, avx2, s, trace);
  }
}

bool trace_slot_used(int s, int rk_order, bool three_d) {
  if (s < 0 || s >= kTraceSlots) return false;
  const int first = three_d ? 0 : 1;
  if (s < 9) {  // y1, y2, p
    const int stage = s / 3;
    return s % 3 >= first && (stage == 2 || rk_order > stage + 1);
  }
  const int m = (s - 9) / 9, e = (s - 9) % 9;  // jac at y1 (rk >= 2) or y2 (rk 3)
  return rk_order > m + 1 && e / 3 >= first && e % 3 >= first;
}

}  // namespace kinema::grid
