// P2M and L2P of the 3D Laplace FMM for blocks of points: the regular solid harmonics of
// kernels3d.h by their recurrence, vectorised across kLanes points (AVX-512 or AVX2 where the
// CPU has it, as core/simd.h describes), each degree summed into the outputs as soon as it is
// computed. A target is evaluated by the same operations in the same order whatever block it
// is in; a multipole's sums depend only on its sources' order.
#pragma once

#include <vector>

#include "core/types.h"
#include "fmm/kernels3d.h"

namespace kinema::fmm3 {

constexpr int kLanes = 8;  // targets per block

// Coefficients of `outputs` local expansions (of orders <= p, zero-padded to p) laid out for
// local_evaluate: value (l, m) of output o at table[2 * (cidx(l, m) * outputs + o)] (real,
// imaginary part), doubled for m > 0, so that output o = sum_lm Re(a_lm conj R_lm) over m >= 0.
class LocalTable {
 public:
  LocalTable(int p, int outputs)
      : p_(p), outputs_(outputs), values_(static_cast<size_t>(2 * complex_count(p) * outputs), 0.0) {}
  // Output o = scale * Re sum L_lm conj(R_lm) over l <= order (as local_sum).
  void set(int o, const Complex* local, int order, Scalar scale);
  int order() const { return p_; }
  int outputs() const { return outputs_; }
  const Scalar* data() const { return values_.data(); }

 private:
  int p_, outputs_;
  std::vector<Scalar> values_;
};

// result[o * kLanes + t] = output o of the table at the scaled position (ux[t], uy[t], uz[t]),
// t < kLanes (pad a short block with any finite position).
void local_evaluate(const LocalTable& table, const Scalar* ux, const Scalar* uy, const Scalar* uz,
                    Scalar* result);

// P2M: multipole += sum_j q_j conj(R((y_j - c)/h)), the sources [0, n) as x, y, z arrays and
// charges q[j * stride] (kernels3d.h's p2m, kLanes sources at a time: lane sums, then added
// up lane by lane).
void multipole_accumulate(int p, const Scalar* c, Scalar h, const Scalar* const xyz[3], const Scalar* q,
                          Index n, Index stride, Scalar* multipole);

}  // namespace kinema::fmm3
