// Solid harmonics of blocks of points (see block3d.h): the recurrences of kernels3d.cpp's
// regular() run on kLanes points side by side, one degree at a time, in two rolling arrays
// (degree l, and degree l - 1 overwritten in place by degree l + 1), and each degree is summed
// into the outputs (L2P) or the expansion (P2M) at once.
#include "fmm/block3d.h"

#include <algorithm>
#include <cstring>
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

// The regular solid harmonics R_lm (m >= 0) of kLanes points (u: scaled positions), degree by
// degree, in vectors of W doubles (NB = kLanes / W of them per value): visit(l, re, im) sees
// the NB vectors of R_lm at re[m * NB], im[m * NB], m <= l. Degree l + 1 overwrites degree
// l - 1 in place (zero at m = l):
// R_{l+1,m} = ((2l+1) z R_lm - r^2 R_{l-1,m}) / ((l+1)^2 - m^2), R_{l+1,l+1} = -w R_ll / (2l+2).
template <int W, class Visit>
KINEMA_ALWAYS_INLINE void regular_block(int p, const Scalar* ux, const Scalar* uy, const Scalar* uz, Visit&& visit) {
  typedef Scalar V __attribute__((vector_size(W * sizeof(Scalar))));
  constexpr int NB = B / W;
  const Reciprocals& rec = reciprocals();
  V x[NB], y[NB], z[NB], r2[NB];
  V ar_[(kMaxDegree + 2) * NB], ai_[(kMaxDegree + 2) * NB];
  V br_[(kMaxDegree + 2) * NB], bi_[(kMaxDegree + 2) * NB];
  V *ar = ar_, *ai = ai_, *br = br_, *bi = bi_;
  for (int v = 0; v < NB; ++v) {
    std::memcpy(&x[v], ux + v * W, sizeof(V));
    std::memcpy(&y[v], uy + v * W, sizeof(V));
    std::memcpy(&z[v], uz + v * W, sizeof(V));
    r2[v] = x[v] * x[v] + y[v] * y[v] + z[v] * z[v];
  }
  for (int k = 0; k < (p + 2) * NB; ++k) ar[k] = ai[k] = br[k] = bi[k] = V{};
  for (int v = 0; v < NB; ++v) ar[v] = V{} + 1;
  for (int l = 0;; ++l) {
    visit(l, static_cast<const V*>(ar), static_cast<const V*>(ai));
    if (l == p) break;
    const Scalar two_l1 = Scalar(2 * l + 1);
    const Scalar* inv = rec.step + cidx(l, 0);
    V zz[NB];
    for (int v = 0; v < NB; ++v) zz[v] = two_l1 * z[v];
    for (int m = 0; m <= l; ++m) {
      const Scalar f = inv[m];
      for (int v = 0; v < NB; ++v) {
        const int k = m * NB + v;
        br[k] = (zz[v] * ar[k] - r2[v] * br[k]) * f;
        bi[k] = (zz[v] * ai[k] - r2[v] * bi[k]) * f;
      }
    }
    const Scalar s = rec.diagonal[l];
    for (int v = 0; v < NB; ++v) {
      const int k = l * NB + v;
      const V cr = ar[k], ci = ai[k];
      br[k + NB] = -(x[v] * cr - y[v] * ci) * s;
      bi[k + NB] = -(x[v] * ci + y[v] * cr) * s;
    }
    V* t = ar;
    ar = br, br = t;
    t = ai;
    ai = bi, bi = t;
  }
}

template <int W, int O>
KINEMA_ALWAYS_INLINE void evaluate_body(int p, int outputs, const Scalar* table, const Scalar* ux,
                                        const Scalar* uy, const Scalar* uz, Scalar* result) {
  typedef Scalar V __attribute__((vector_size(W * sizeof(Scalar))));
  constexpr int NB = B / W;
  const int no = O > 0 ? O : outputs;
  constexpr int kAcc = O > 0 ? O : kMaxOutputs;
  V acc[kAcc][NB];
  for (int o = 0; o < no; ++o)
    for (int v = 0; v < NB; ++v) acc[o][v] = V{};
  regular_block<W>(p, ux, uy, uz, [&](int l, const V* ar, const V* ai) {
    const Scalar* c = table + 2 * cidx(l, 0) * no;
    for (int m = 0; m <= l; ++m) {
      for (int o = 0; o < no; ++o) {
        const Scalar cr = c[2 * (m * no + o)], ci = c[2 * (m * no + o) + 1];
        for (int v = 0; v < NB; ++v) acc[o][v] += cr * ar[m * NB + v] + ci * ai[m * NB + v];
      }
    }
  });
  for (int o = 0; o < no; ++o)
    for (int v = 0; v < NB; ++v) std::memcpy(result + o * B + v * W, &acc[o][v], sizeof(V));
}

// sums[2 k * B + t] (real) and sums[(2 k + 1) * B + t] (imaginary) += w_t conj(R_k(u_t)).
template <int W>
KINEMA_ALWAYS_INLINE void accumulate_body(int p, const Scalar* ux, const Scalar* uy, const Scalar* uz,
                                          const Scalar* w, Scalar* sums) {
  typedef Scalar V __attribute__((vector_size(W * sizeof(Scalar))));
  typedef Scalar U __attribute__((vector_size(W * sizeof(Scalar)), aligned(sizeof(Scalar))));
  constexpr int NB = B / W;
  V wv[NB];
  for (int v = 0; v < NB; ++v) std::memcpy(&wv[v], w + v * W, sizeof(V));
  regular_block<W>(p, ux, uy, uz, [&](int l, const V* ar, const V* ai) {
    U* s = reinterpret_cast<U*>(sums + 2 * cidx(l, 0) * B);
    for (int m = 0; m <= l; ++m)
      for (int v = 0; v < NB; ++v) {
        s[2 * m * NB + v] += wv[v] * ar[m * NB + v];
        s[(2 * m + 1) * NB + v] -= wv[v] * ai[m * NB + v];
      }
  });
}

using Accumulate = void (*)(int, const Scalar*, const Scalar*, const Scalar*, const Scalar*, Scalar*);

void accumulate_portable(int p, const Scalar* ux, const Scalar* uy, const Scalar* uz, const Scalar* w, Scalar* sums) {
  accumulate_body<2>(p, ux, uy, uz, w, sums);
}

#if KINEMA_HAVE_AVX2_CLONES
__attribute__((target("avx2,fma"))) void accumulate_avx2(int p, const Scalar* ux, const Scalar* uy,
                                                         const Scalar* uz, const Scalar* w, Scalar* sums) {
  accumulate_body<4>(p, ux, uy, uz, w, sums);
}
__attribute__((target("avx512f,avx2,fma"))) void accumulate_avx512(int p, const Scalar* ux, const Scalar* uy,
                                                                   const Scalar* uz, const Scalar* w, Scalar* sums) {
  accumulate_body<8>(p, ux, uy, uz, w, sums);
}
#endif

using Evaluate = void (*)(int, int, const Scalar*, const Scalar*, const Scalar*, const Scalar*, Scalar*);

template <int O>
void evaluate_portable(int p, int outputs, const Scalar* table, const Scalar* ux, const Scalar* uy,
                       const Scalar* uz, Scalar* result) {
  evaluate_body<2, O>(p, outputs, table, ux, uy, uz, result);
}

#if KINEMA_HAVE_AVX2_CLONES
template <int O>
__attribute__((target("avx2,fma"))) void evaluate_avx2(int p, int outputs, const Scalar* table,
                                                       const Scalar* ux, const Scalar* uy,
                                                       const Scalar* uz, Scalar* result) {
  evaluate_body<4, O>(p, outputs, table, ux, uy, uz, result);
}
template <int O>
__attribute__((target("avx512f,avx2,fma"))) void evaluate_avx512(int p, int outputs, const Scalar* table,
                                                                 const Scalar* ux, const Scalar* uy,
                                                                 const Scalar* uz, Scalar* result) {
  evaluate_body<8, O>(p, outputs, table, ux, uy, uz, result);
}
#endif

// Kernels for 1, 4 and any number of outputs, for the widest instruction set of this CPU.
struct Kernels {
  Evaluate one, four, any;
  Accumulate accumulate;
  Kernels()
      : one(evaluate_portable<1>), four(evaluate_portable<4>), any(evaluate_portable<0>),
        accumulate(accumulate_portable) {
#if KINEMA_HAVE_AVX2_CLONES
    if (use_avx512_kernels()) {
      one = evaluate_avx512<1>, four = evaluate_avx512<4>, any = evaluate_avx512<0>;
      accumulate = accumulate_avx512;
    } else if (use_avx2()) {
      one = evaluate_avx2<1>, four = evaluate_avx2<4>, any = evaluate_avx2<0>;
      accumulate = accumulate_avx2;
    }
#endif
  }
};
const Kernels& kernels() {
  static const Kernels k;
  return k;
}

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
  const Kernels& k = kernels();
  const Evaluate f = table.outputs() == 1 ? k.one : table.outputs() == 4 ? k.four : k.any;
  f(table.order(), table.outputs(), table.data(), ux, uy, uz, result);
}

void multipole_accumulate(int p, const Scalar* c, Scalar h, const Scalar* const xyz[3], const Scalar* q,
                          Index n, Index stride, Scalar* multipole) {
  if (p > kMaxDegree) throw std::logic_error("multipole_accumulate: order beyond the scratch bounds");
  const Accumulate f = kernels().accumulate;
  std::vector<Scalar> sums(static_cast<size_t>(2 * complex_count(p) * B), 0.0);
  const Scalar inv_h = 1 / h;
  for (Index start = 0; start < n; start += B) {
    alignas(64) Scalar u[3][B], w[B];
    for (int t = 0; t < B; ++t) {
      const Index j = start + t < n ? start + t : start;  // padding: zero charge
      for (int a = 0; a < 3; ++a) u[a][t] = (xyz[a][j] - c[a]) * inv_h;
      w[t] = start + t < n ? q[j * stride] : 0;
    }
    f(p, u[0], u[1], u[2], w, sums.data());
  }
  for (int l = 0; l <= p; ++l)
    for (int m = 0; m <= l; ++m) {
      Scalar re = 0, im = 0;
      const Scalar* s = &sums[static_cast<size_t>(2 * cidx(l, m) * B)];
      for (int t = 0; t < B; ++t) re += s[t], im += s[B + t];
      if (m == 0) {
        multipole[l * l] += re;
      } else {
        multipole[l * l + 2 * m - 1] += re;
        multipole[l * l + 2 * m] += im;
      }
    }
}

}  // namespace kinema::fmm3
