// The advection passes of kernels.h reorganised along rows of the contiguous axis, for speed:
// every stage of a back-trace (node velocity, brackets, trilinear interpolation, the MacCormack
// correction) runs over one row of nodes into short arrays, which the compiler vectorises, and
// each row is compiled twice, for the baseline x86-64 ISA and for AVX2, picked at run time
// (core/simd.h).
// The arithmetic is that of the node-wise passes operation by operation, and the AVX2 version
// is built without FMA contraction, so every path gives the same bits (tests/cpp compares them).
// Same schemes and equations as kernels.h (Stam 1999; Selle et al. 2008; Kim et al. 2005).
#pragma once

#include <memory>

#include "grid/kernels.h"

namespace kinema::grid {

// Whether the row passes handle this problem: no no-slip wall enters the interpolation, every
// active axis has at least 2 cells, and every field has fewer than 2^31 nodes (the rows index
// nodes with 32-bit integers, which AVX2 converts and multiplies in one instruction).
bool rows_apply(const MacVelocity& u, const FieldLayout& L);

// The arrays of a stored back-trace (advect_rows' `trace`): per node of L, in RowTrace's order,
// y1 (slots 0-2), y2 (3-5), p (6-8), and d u_a / d y_b at y1 (9 + 3 a + b) and y2 (18 + 3 a + b).
constexpr int kTraceSlots = 27;
// Whether slot s holds anything for this order and dimension (2D: none along axis 0).
bool trace_slot_used(int s, int rk_order, bool three_d);

// advect_fields by rows; requires rows_apply(u, L), and cpu_has_avx2() (core/simd.h) when avx2.
// trace (nullable, kTraceSlots arrays of L.size(), any of them null, those of a stage all or
// none): receives the first pass's back-trace over dt (RowTrace's values, the same bits), which
// the adjoint's passes over the same trace then read instead of tracing again.
void advect_rows(AdvectionScheme scheme, const MacVelocity& u, const FieldLayout& L, int count,
                 const Scalar* const* q, Scalar* const* out, Scalar dt, int rk_order,
                 AdvectionScratch& scratch, bool avx2, bool scratch_only = false, Scalar* const* trace = nullptr);

// The back-traces of advect_rows along one row of L's nodes at a time, with their Runge-Kutta
// stages kept (for the adjoint): y1 = x - dt/2 k1 (rk >= 2), y2 = x - 3 dt/4 k2 (rk 3) and the
// departure point p, per axis, for the L.n[2] nodes of the row (in 2D, axis 0 holds the nodes'
// own coordinate). The same bits as advect_rows' traces. Requires rows_apply(u, L), and
// cpu_has_avx2() when avx2; one per thread.
class RowTrace {
 public:
  RowTrace(const MacVelocity& u, const FieldLayout& L, int rk_order, bool avx2);
  ~RowTrace();
  RowTrace(const RowTrace&) = delete;
  RowTrace& operator=(const RowTrace&) = delete;

  void trace(Index i, Index j, Scalar dt);  // fills y1, y2, p and jac for row (i, j)

  // The brackets (kernels.h: bracket) of x[k] - offset, k < L.n[2], on `nodes` nodes of period
  // `period` (0: none; the row passes require every axis periodic or none), and d[k] = d w / d x:
  // 1 inside the domain or when periodic, 0 where the coordinate was clamped.
  void brackets(const Scalar* x, Scalar offset, Index nodes, Index period, int* i0, int* i1, Scalar* w,
                Scalar* d) const;

  // The brackets of the last Runge-Kutta stage trace() sampled the velocity at (y1 at rk 2, y2 at
  // rk 3; none at rk 1), for axis b's face (cell = false) or cell offset: the brackets() of that
  // stage's coordinates for u's layouts, the same bits; valid until the next trace().
  void stage_brackets(int b, bool cell, const int*& i0, const int*& i1, const Scalar*& w) const;
  // brackets()' d alone.
  void inside(const Scalar* x, Scalar offset, Index nodes, Index period, Scalar* d) const;

  Scalar* y1[3];
  Scalar* y2[3];
  Scalar* p[3];
  // jac[m][3 a + b] = d u_a / d y_b at stage m + 1 (y1, y2) in grid units, from the brackets
  // as computed (no factor for a clamped coordinate; 2D: b = 0 unset).
  Scalar* jac[2][9];

 private:
  struct Impl;
  const MacVelocity& u_;
  const FieldLayout& L_;
  int rk_;
  bool avx2_;
  std::unique_ptr<Impl> impl_;
};

}  // namespace kinema::grid
