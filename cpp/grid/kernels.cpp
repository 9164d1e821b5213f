#include "grid/kernels.h"

#include <algorithm>

#include "core/simd.h"
#include "grid/advect_rows.h"

namespace kinema::grid {

FieldLayout cell_layout(const GridShape& shape, bool periodic) {
  FieldLayout L;
  L.n = shape.n;
  for (int a = 0; a < 3; ++a) L.period[a] = periodic && shape.active(a) ? shape.n[a] : 0;
  return L;
}

FieldLayout face_layout(const GridShape& shape, int axis, bool periodic) {
  FieldLayout L = cell_layout(shape, periodic);
  L.n[axis] += 1;
  L.offset[axis] = 0;
  return L;
}

namespace {

// The advection passes over the nodes of L, with the dimension and whether no-slip walls enter
// the interpolation fixed at compile time. Every pass traces each node once (k1 = u(node), then the Runge-Kutta stages)
// and samples all fields at the departure point with one set of brackets.
template <bool ThreeD, bool Walls>
struct Passes {
  const MacVelocity& u;
  const FieldLayout& L;
  int count, rk;
  int comp;  // velocity component of the fields (walls apply), or -1
  Index s0, s1;

  [[gnu::always_inline]] inline Vec3 velocity(const Vec3& x) const { return u.template at_impl<ThreeD>(x, Walls ? u.walls : nullptr); }

  // The Runge-Kutta stages' velocity: the pass itself is the functor, so that the evaluation is
  // inlined into the trace (a lambda there stayed an out-of-line call: a quarter of the step's
  // profile at 128^3, returning its 3-vector through memory).
  [[gnu::always_inline]] inline Vec3 operator()(const Vec3& x) const { return velocity(x); }

  // The departure point of node (i, j, k) over dt. (Recomputing k1 = u(node) per pass measured
  // no slower than keeping it in three arrays between the passes.)
  [[gnu::always_inline]] inline Vec3 departure(Index i, Index j, Index k, Scalar dt) const {
    const Vec3 x{static_cast<Scalar>(i) + L.offset[0], static_cast<Scalar>(j) + L.offset[1],
                 static_cast<Scalar>(k) + L.offset[2]};
    return back_trace_from(*this, x, node_velocity(i, j, k, x), dt, rk);
  }

  // u at node (i, j, k) of L (position x): away from the domain's ends it is the node value or
  // a 2- or 4-point average of the other components (what interpolation gives there, cheaper);
  // nodes on the outer layer take the general path (clamping, walls, periodic wrap).
  [[gnu::always_inline]] inline Vec3 node_velocity(Index i, Index j, Index k, const Vec3& x) const {
    const Index idx[3] = {i, j, k};
    const int face_axis = L.offset[0] == 0 ? 0 : L.offset[1] == 0 ? 1 : L.offset[2] == 0 ? 2 : -1;
    for (int b = ThreeD ? 0 : 1; b < 3; ++b)
      if (idx[b] == 0 || idx[b] >= u.layout[b].n[b] - 2) return velocity(x);
    Vec3 v{0, 0, 0};
    for (int b = ThreeD ? 0 : 1; b < 3; ++b) {
      const FieldLayout& F = u.layout[b];
      const Scalar* ub = u.comp[b];
      if (face_axis < 0) {  // cell centre: between faces idx_b and idx_b + 1
        const Index f = F.index(i, j, k);
        v[b] = 0.5 * (ub[f] + ub[f + F.stride(b)]);
      } else if (face_axis == b) {
        v[b] = ub[F.index(i, j, k)];
      } else {  // faces idx_b, idx_b + 1 of the cells idx_a - 1 and idx_a
        const Index f = F.index(i, j, k), sa = F.stride(face_axis), sb = F.stride(b);
        v[b] = 0.25 * (ub[f - sa] + ub[f - sa + sb] + ub[f] + ub[f + sb]);
      }
    }
    return v;
  }

  // The brackets of point x in L; only the tangential axes of a wall-aware field see walls.
  void locate(const Vec3& x, detail::Axis (&a)[3]) const {
    for (int b = ThreeD ? 0 : 1; b < 3; ++b) {
      const bool tangential = Walls && comp >= 0 && b != comp;  // scalars extend to the walls
      a[b] = detail::locate(x[b], L.offset[b], L.n[b], L.period[b], b, tangential ? u.walls : nullptr);
    }
  }

  template <bool Bounds>
  Scalar sample(const Scalar* f, const detail::Axis (&a)[3], Scalar& lo, Scalar& hi) const {
    Scalar v = detail::interpolate<ThreeD, Bounds>(f, s0, s1, a[0], a[1], a[2], lo, hi);
    if (Walls && comp >= 0) v = detail::wall_blend<ThreeD, Bounds>(v, *u.walls, comp, a[0], a[1], a[2], lo, hi);
    return v;
  }

  // out[f] = q[f] at the departure points over dt; with lo/hi, also the stencil bounds.
  void semi_lagrangian(const Scalar* const* q, Scalar* const* out, Scalar dt, Scalar* const* lo,
                       Scalar* const* hi) const {
    for_each_node(L, [&](Index i, Index j, Index k, Index c) {
      detail::Axis a[3];
      locate(departure(i, j, k, dt), a);
      for (int f = 0; f < count; ++f) {
        if (lo) out[f][c] = sample<true>(q[f], a, lo[f][c], hi[f][c]);
        else {
          Scalar l, h;
          out[f][c] = sample<false>(q[f], a, l, h);
        }
      }
    });
  }

  // The second pass of both schemes: the forward field traced back over -dt gives fwd~, whose
  // difference to q estimates the round-trip error; combine(f, c, fwd~) writes the result.
  template <class Combine>
  void round_trip(const Scalar* const* fwd, Scalar dt, Combine&& combine) const {
    for_each_node(L, [&](Index i, Index j, Index k, Index c) {
      detail::Axis a[3];
      locate(departure(i, j, k, -dt), a);
      for (int f = 0; f < count; ++f) {
        Scalar l, h;
        combine(f, c, sample<false>(fwd[f], a, l, h));
      }
    });
  }

  void run(AdvectionScheme scheme, const Scalar* const* q, Scalar* const* out, Scalar dt,
           AdvectionScratch& s) const {
    if (scheme == AdvectionScheme::SemiLagrangian) {
      semi_lagrangian(q, out, dt, nullptr, nullptr);
      return;
    }
    AdvectionScratch::Fields scratch = s.fields(count, scheme);
    Scalar *const *fwd = scratch.forward, *const *lo = scratch.lo, *const *hi = scratch.hi, *const *bar = scratch.corrected;
    // q^ = SL(q, dt) with the clamping bounds of Selle et al.
    semi_lagrangian(q, fwd, dt, lo, hi);
    if (scheme == AdvectionScheme::MacCormack) {
      // MacCormack: out = clamp(q^ + (q - q~)/2, lo, hi), fused with the second pass.
      round_trip(fwd, dt, [&](int f, Index c, Scalar back) {
        out[f][c] = std::clamp(fwd[f][c] + 0.5 * (q[f][c] - back), lo[f][c], hi[f][c]);
      });
      return;
    }
    // BFECC: advect the error-compensated field forward once more, through the first pass's
    // departure points, so its stencil bounds still apply.
    round_trip(fwd, dt, [&](int f, Index c, Scalar back) { bar[f][c] = q[f][c] + 0.5 * (q[f][c] - back); });
    semi_lagrangian(bar, out, dt, nullptr, nullptr);
    clamp_fields(L, count, out, lo, hi);
  }
};

template <bool ThreeD>
void dispatch_walls(AdvectionScheme scheme, const MacVelocity& u, const FieldLayout& L, int count,
                    const Scalar* const* q, Scalar* const* out, Scalar dt, int rk, AdvectionScratch& s,
                    int comp) {
  if (u.walls) {
    Passes<ThreeD, true>{u, L, count, rk, comp, L.stride(0), L.stride(1)}.run(scheme, q, out, dt, s);
  } else {
    Passes<ThreeD, false>{u, L, count, rk, comp, L.stride(0), L.stride(1)}.run(scheme, q, out, dt, s);
  }
}

}  // namespace

void AdvectionScratch::reserve(Index n, AdvectionScheme scheme, int fields) {
  if (scheme == AdvectionScheme::SemiLagrangian) return;
  auto grow = [&](std::vector<std::vector<Scalar>>& set) {
    if (static_cast<int>(set.size()) < fields) set.resize(static_cast<size_t>(fields));
    for (int f = 0; f < fields; ++f)
      if (static_cast<Index>(set[f].size()) < n) set[f].resize(static_cast<size_t>(n));
  };
  grow(forward);
  grow(lo);
  grow(hi);
  if (scheme == AdvectionScheme::BFECC) grow(corrected);
}

AdvectionScratch::Fields AdvectionScratch::fields(int count, AdvectionScheme scheme) {
  Fields f{};
  for (int i = 0; i < count; ++i) {
    f.forward[i] = forward[i].data();
    f.lo[i] = lo[i].data();
    f.hi[i] = hi[i].data();
    if (scheme == AdvectionScheme::BFECC) f.corrected[i] = corrected[i].data();
  }
  return f;
}

void clamp_fields(const FieldLayout& L, int count, Scalar* const* out, Scalar* const* lo, Scalar* const* hi) {
  for (int f = 0; f < count; ++f) {
    Scalar *o = out[f], *l = lo[f], *h = hi[f];
    parallel_for(L.size(), [&](Index c) { o[c] = std::clamp(o[c], l[c], h[c]); });
  }
}

void advect_fields(AdvectionScheme scheme, const MacVelocity& u, const FieldLayout& L, int count,
                   const Scalar* const* q, Scalar* const* out, Scalar dt, int rk_order,
                   AdvectionScratch& scratch, int wall_component, AdvectionKernel kernel, bool scratch_only) {
  if (count <= 0) return;
  if (count > kMaxAdvectedFields) throw InvalidArgument("advect: at most 8 fields per call");
  scratch.reserve(L.size(), scheme, count);  // a no-op when the solver reserved enough
  if (kernel != AdvectionKernel::Nodes) {
    const bool rows = rows_apply(u, L);
    if (kernel == AdvectionKernel::Auto && rows) {
      advect_rows(scheme, u, L, count, q, out, dt, rk_order, scratch, use_avx2(), scratch_only);
      return;
    }
    if (kernel != AdvectionKernel::Auto) {
      if (!rows) throw InvalidArgument("advect: the row kernels do not apply to this problem");
      if (kernel == AdvectionKernel::RowsAvx2 && !cpu_has_avx2())
        throw InvalidArgument("advect: this CPU has no AVX2");
      advect_rows(scheme, u, L, count, q, out, dt, rk_order, scratch, kernel == AdvectionKernel::RowsAvx2,
                  scratch_only);
      return;
    }
  }
  // the velocity's layouts fix the dimension: 2D fields have one node along axis 0
  if (u.comp[0]) dispatch_walls<true>(scheme, u, L, count, q, out, dt, rk_order, scratch, wall_component);
  else dispatch_walls<false>(scheme, u, L, count, q, out, dt, rk_order, scratch, wall_component);
}

void advect(AdvectionScheme scheme, const MacVelocity& u, const FieldLayout& L, const Scalar* q,
            Scalar* out, Scalar dt, int rk_order, AdvectionScratch& scratch) {
  advect_fields(scheme, u, L, 1, &q, &out, dt, rk_order, scratch);
}

}  // namespace kinema::grid
