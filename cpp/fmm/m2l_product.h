// The dense M2L product of the 3D FMM, C = A B for the leading n x n block of a row-major
// operator A with row stride lda, and k column vectors B (each n contiguous values; C likewise): the row-times-column dot products are
// vectorised along the rows of A, two rows and four columns at a time, with AVX2/FMA where
// the CPU has it (core/simd.h) and a portable loop otherwise. The order of the operations
// depends only on n and k, so results do not depend on the thread count.
#pragma once

#include "core/types.h"

namespace kinema::fmm3 {

void m2l_product(const Scalar* a, int lda, int n, const Scalar* b, int k, Scalar* c);

}  // namespace kinema::fmm3
