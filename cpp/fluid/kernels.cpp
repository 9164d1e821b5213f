#include "fluid/kernels.h"

#include <algorithm>

namespace kinema::fluid {

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

void advect_semi_lagrangian(const MacVelocity& u, const FieldLayout& L, const Scalar* q, Scalar* out,
                            Scalar dt, int rk_order, Scalar* lo, Scalar* hi) {
  for_each_node(L, [&](Index i, Index j, Index k, Index c) {
    const Vec3 x{static_cast<Scalar>(i) + L.offset[0], static_cast<Scalar>(j) + L.offset[1],
                 static_cast<Scalar>(k) + L.offset[2]};
    const Vec3 from = back_trace(u, x, dt, rk_order);
    if (lo) out[c] = sample(q, L, from, lo + c, hi + c);
    else out[c] = sample(q, L, from);
  });
}

void AdvectionScratch::reserve(Index n, AdvectionScheme scheme) {
  if (scheme == AdvectionScheme::SemiLagrangian) return;
  for (auto* v : {&forward, &backward, &lo, &hi})
    if (static_cast<Index>(v->size()) < n) v->resize(static_cast<size_t>(n));
}

void advect(AdvectionScheme scheme, const MacVelocity& u, const FieldLayout& L, const Scalar* q,
            Scalar* out, Scalar dt, int rk_order, AdvectionScratch& s) {
  if (scheme == AdvectionScheme::SemiLagrangian) {
    advect_semi_lagrangian(u, L, q, out, dt, rk_order, nullptr, nullptr);
    return;
  }
  const Index n = L.size();
  s.reserve(n, scheme);
  Scalar *fwd = s.forward.data(), *bwd = s.backward.data(), *lo = s.lo.data(), *hi = s.hi.data();
  // q^ = SL(q, dt) with the clamping bounds; q~ = SL(q^, -dt) estimates q's round-trip error.
  advect_semi_lagrangian(u, L, q, fwd, dt, rk_order, lo, hi);
  advect_semi_lagrangian(u, L, fwd, bwd, -dt, rk_order, nullptr, nullptr);
  if (scheme == AdvectionScheme::MacCormack) {
    parallel_for(n, [&](Index c) {
      out[c] = std::clamp(fwd[c] + 0.5 * (q[c] - bwd[c]), lo[c], hi[c]);
    });
    return;
  }
  // BFECC: advect the error-compensated field q + (q - q~)/2 forward once more; the back-trace
  // is the first pass's, so its stencil bounds still apply.
  parallel_for(n, [&](Index c) { bwd[c] = q[c] + 0.5 * (q[c] - bwd[c]); });
  advect_semi_lagrangian(u, L, bwd, out, dt, rk_order, nullptr, nullptr);
  parallel_for(n, [&](Index c) { out[c] = std::clamp(out[c], lo[c], hi[c]); });
}

}  // namespace kinema::fluid
