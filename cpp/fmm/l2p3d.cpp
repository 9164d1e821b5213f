// Block L2P (see l2p3d.h): the recurrences of kernels3d.cpp's regular() run on kLanes targets
// side by side, one degree at a time, in two rolling arrays (degree l, and degree l - 1
// overwritten in place by degree l + 1), and each degree is summed into the outputs at once.
#include "fmm/l2p3d.h"

#include <algorithm>
#include <stdexcept>
#include <utility>

#include "core/simd.h"
#include "fmm/p2p3d.h"

namespace kinema::fmm3 {

namespace {

constexpr int B = kLanes;
constexpr int kMaxDegree = 63;  // scratch bound (the 3D FMM's orders are <= 40)
constexpr int kMaxOutputs = 40; // 4 components x 10 values

// 1 / ((l+1)^2 - m^2) at cidx(l, m) and 1 / (2 l + 2) at index l, l < kMaxDegree.
struct Reciprocals {
  Scalar step[(kMaxDegree + 1) * (kMaxDegree + 2) / 2];
  Scalar diagonal[kMaxDegree + 1];
  Reciprocals() {
    for (int l = 0; l <= kMaxDegree; ++l) {
      diagonal[l] = Scalar(1) / Scalar(2 * l + 2);
      for (int m = 0; m <= l; ++m) step[cidx(l, m)] = Scalar(1) / Scalar((l + 1) * (l + 1) - m * m);
    }
  }
};
const Reciprocals& reciprocals() {
  static const Reciprocals r;
  return r;
}

template <int O>
KINEMA_ALWAYS_INLINE void evaluate_body(int p, int outputs, const Scalar* table, const Scalar* ux,
                                        const Scalar* uy, const Scalar* uz, Scalar* result) {
  const int no = O > 0 ? O : outputs;
  constexpr int kAcc = O > 0 ? O : kMaxOutputs;
  const Reciprocals& rec = reciprocals();
  alignas(64) Scalar acc[kAcc * B] = {};
  alignas(64) Scalar x[B], y[B], z[B], r2[B];
  alignas(64) Scalar ar_[(kMaxDegree + 2) * B], ai_[(kMaxDegree + 2) * B];
  alignas(64) Scalar br_[(kMaxDegree + 2) * B], bi_[(kMaxDegree + 2) * B];
  Scalar *ar = ar_, *ai = ai_, *br = br_, *bi = bi_;
  for (int t = 0; t < B; ++t) {
    x[t] = ux[t], y[t] = uy[t], z[t] = uz[t];
    r2[t] = x[t] * x[t] + y[t] * y[t] + z[t] * z[t];
  }
  for (int k = 0; k < (p + 2) * B; ++k) ar[k] = ai[k] = br[k] = bi[k] = 0;
  for (int t = 0; t < B; ++t) ar[t] = 1;
  for (int l = 0;; ++l) {
    // Degree l (in a) into the outputs.
    const Scalar* c = table + 2 * cidx(l, 0) * no;
    for (int m = 0; m <= l; ++m) {
      const Scalar* re = ar + m * B;
      const Scalar* im = ai + m * B;
      for (int o = 0; o < no; ++o) {
        const Scalar cr = c[2 * (m * no + o)], ci = c[2 * (m * no + o) + 1];
        Scalar* a = acc + o * B;
        for (int t = 0; t < B; ++t) a[t] += cr * re[t] + ci * im[t];
      }
    }
    if (l == p) break;
    // Degree l + 1 into b (which holds degree l - 1, zero at m = l):
    // R_{l+1,m} = ((2l+1) z R_lm - r^2 R_{l-1,m}) / ((l+1)^2 - m^2), R_{l+1,l+1} = -w R_ll / (2l+2).
    const Scalar two_l1 = Scalar(2 * l + 1);
    const Scalar* inv = rec.step + cidx(l, 0);
    for (int m = 0; m <= l; ++m) {
      const Scalar f = inv[m];
      Scalar* pr = br + m * B;
      Scalar* pi = bi + m * B;
      const Scalar* cr = ar + m * B;
      const Scalar* ci = ai + m * B;
      for (int t = 0; t < B; ++t) {
        const Scalar zz = two_l1 * z[t];
        pr[t] = (zz * cr[t] - r2[t] * pr[t]) * f;
        pi[t] = (zz * ci[t] - r2[t] * pi[t]) * f;
      }
    }
    const Scalar s = rec.diagonal[l];
    const Scalar* cr = ar + l * B;
    const Scalar* ci = ai + l * B;
    Scalar* nr = br + (l + 1) * B;
    Scalar* ni = bi + (l + 1) * B;
    for (int t = 0; t < B; ++t) {
      nr[t] = -(x[t] * cr[t] - y[t] * ci[t]) * s;
      ni[t] = -(x[t] * ci[t] + y[t] * cr[t]) * s;
    }
    std::swap(ar, br);
    std::swap(ai, bi);
  }
  for (int k = 0; k < no * B; ++k) result[k] = acc[k];
}

using Evaluate = void (*)(int, int, const Scalar*, const Scalar*, const Scalar*, const Scalar*, Scalar*);

template <int O>
void evaluate_portable(int p, int outputs, const Scalar* table, const Scalar* ux, const Scalar* uy,
                       const Scalar* uz, Scalar* result) {
  evaluate_body<O>(p, outputs, table, ux, uy, uz, result);
}

#if KINEMA_HAVE_AVX2_CLONES
template <int O>
__attribute__((target("avx2,fma"))) void evaluate_avx2(int p, int outputs, const Scalar* table,
                                                       const Scalar* ux, const Scalar* uy,
                                                       const Scalar* uz, Scalar* result) {
  evaluate_body<O>(p, outputs, table, ux, uy, uz, result);
}
template <int O>
__attribute__((target("avx512f,avx2,fma"))) void evaluate_avx512(int p, int outputs, const Scalar* table,
                                                                 const Scalar* ux, const Scalar* uy,
                                                                 const Scalar* uz, Scalar* result) {
  evaluate_body<O>(p, outputs, table, ux, uy, uz, result);
}
#endif

// Kernels for 1, 4 and any number of outputs, for the widest instruction set of this CPU.
struct Kernels {
  Evaluate one, four, any;
  Kernels() : one(evaluate_portable<1>), four(evaluate_portable<4>), any(evaluate_portable<0>) {
#if KINEMA_HAVE_AVX2_CLONES
    if (use_avx512_kernels()) one = evaluate_avx512<1>, four = evaluate_avx512<4>, any = evaluate_avx512<0>;
    else if (use_avx2()) one = evaluate_avx2<1>, four = evaluate_avx2<4>, any = evaluate_avx2<0>;
#endif
  }
};

}  // namespace

void LocalTable::set(int o, const Complex* local, int order, Scalar scale) {
  for (int l = 0; l <= std::min(order, p_); ++l)
    for (int m = 0; m <= l; ++m) {
      const Scalar f = m == 0 ? scale : 2 * scale;
      Scalar* v = &values_[static_cast<size_t>(2 * (cidx(l, m) * outputs_ + o))];
      v[0] = f * local[cidx(l, m)].real();
      v[1] = f * local[cidx(l, m)].imag();
    }
}

void local_evaluate(const LocalTable& table, const Scalar* ux, const Scalar* uy, const Scalar* uz,
                    Scalar* result) {
  if (table.order() > kMaxDegree || table.outputs() > kMaxOutputs)
    throw std::logic_error("local_evaluate: order or outputs beyond the scratch bounds");
  static const Kernels kernels;
  const Evaluate f = table.outputs() == 1 ? kernels.one : table.outputs() == 4 ? kernels.four : kernels.any;
  f(table.order(), table.outputs(), table.data(), ux, uy, uz, result);
}

}  // namespace kinema::fmm3
