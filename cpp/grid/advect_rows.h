// The advection passes of kernels.h reorganised along rows of the contiguous axis, for speed:
// every stage of a back-trace (node velocity, brackets, trilinear interpolation, the MacCormack
// correction) runs over one row of nodes into short arrays, which the compiler vectorises, and
// each row is compiled twice, for the baseline x86-64 ISA and for AVX2, picked at run time
// (core/simd.h).
// The arithmetic is that of the node-wise passes operation by operation, and the AVX2 version
// is built without FMA contraction, so every path gives the same bits (tests/cpp compares them).
// Same schemes and equations as kernels.h (Stam 1999; Selle et al. 2008; Kim et al. 2005).
#pragma once

#include "grid/kernels.h"

namespace kinema::grid {

// Whether the row passes handle this problem: no no-slip wall enters the interpolation, every
// active axis has at least 2 cells, and every field has fewer than 2^31 nodes (the rows index
// nodes with 32-bit integers, which AVX2 converts and multiplies in one instruction).
bool rows_apply(const MacVelocity& u, const FieldLayout& L);

// advect_fields by rows; requires rows_apply(u, L), and cpu_has_avx2() (core/simd.h) when avx2.
void advect_rows(AdvectionScheme scheme, const MacVelocity& u, const FieldLayout& L, int count,
                 const Scalar* const* q, Scalar* const* out, Scalar dt, int rk_order,
                 AdvectionScratch& scratch, bool avx2);

}  // namespace kinema::grid
