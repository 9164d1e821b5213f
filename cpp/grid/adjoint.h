// Reverse-mode derivative (vector-Jacobian product) of the advection schemes of kernels.h.
// A semi-Lagrangian step out(x) = q(p(x; u)), p the Runge-Kutta back-trace, has the adjoint
//   dL/dq += W^T g          (the transpose of the interpolation: a scatter onto the stencil),
//   dL/du += (dp/du)^T (grad q)(p) g   (the trace moves with the velocity it reads),
// where dp/du follows the Runge-Kutta stages back (each stage's velocity is read at a point that
// depends on the previous stages). MacCormack and BFECC are differentiated on the branch their
// clamp took at each node (Selle et al. 2008): a clamped node's value is a stencil node of q,
// so its gradient goes to that node only. Interpolation weights are differentiated where the
// back-trace stays inside the domain; a clamped (outside) coordinate has zero derivative.
//
// The scatters are deterministic for any thread count: the nodes are cut into blocks of slabs
// wider than twice the reach of a node's writes (max |u| |dt| plus the stencil), the even
// blocks run in parallel, then the odd ones, so no two threads write one node at once (no
// atomics, no per-thread copies) and every node receives its terms in one fixed order.
//
// Where the row passes apply (advect_rows.h: rows_apply), a row's back-traces and the brackets
// of its departure points and Runge-Kutta stages are computed at once, vectorised (RowTrace);
// the nodes then only gather and scatter, in the same order.
//
// No-slip walls in the interpolation (MacVelocity::walls) are not handled; the Solver refuses to
// differentiate them (Solver::check_differentiable).
#pragma once

#include <cstdint>
#include <vector>

#include "grid/kernels.h"

namespace kinema::grid {

// Zeroed buffers of an adjoint, kept from call to call: a fresh vector of a few MB costs a page
// fault and the kernel's zeroing per 4 KiB on first touch (serial, in the allocating thread),
// about a tenth of a 64^3 step's adjoint; a kept one is only refilled, in parallel.
struct AdjointScratch {
  std::vector<std::vector<Scalar>> buffers;
  std::vector<std::vector<std::uint8_t>> flags;
  AdvectionScratch forward;  // the forward's first passes where the caller kept none
  // Buffer `slot`, resized to n values (its capacity kept), all 0.
  Scalar* zeros(int slot, Index n);
  // The same, its values unspecified (every one is written before it is read).
  Scalar* raw(int slot, Index n);
  std::uint8_t* zero_flags(int slot, Index n);
};

// The adjoint of advect_fields(scheme, u, L, count, q, out, dt, rk_order): given
// g_out[f] = dL/d(out[f]), adds dL/d(q[f]) into g_q[f] and dL/du into g_u[a] (one array per
// active component of u, on u.layout[a]). g_q[f] may alias g_u[a] (a velocity component advected
// through itself). u.walls must be null. forward (nullable): the scratch of that advect_fields
// call (MacCormack and BFECC read its forward pass, bounds and corrected field; recomputed when
// null, by rows; BFECC's then with their departure points kept for the adjoint's first pass).
// work (nullable): buffers kept between calls (a local one when null).
void advect_adjoint(AdvectionScheme scheme, const MacVelocity& u, const FieldLayout& L, int count,
                    const Scalar* const* q, const Scalar* const* g_out, Scalar* const* g_q,
                    const std::array<Scalar*, 3>& g_u, Scalar dt, int rk_order,
                    const AdvectionScratch* forward = nullptr, AdjointScratch* work = nullptr);

}  // namespace kinema::grid
