// The two element passes of the symplectic step and its adjoint for the stable neo-Hookean
// tetrahedron (the benchmark body's and most users' model), four elements side by side: the
// elements' inputs are gathered into lanes, then one straight-line body runs on every lane at
// once (one vector instruction per operation: SSE2 halves, AVX2 whole), then each element's
// vertex terms are written out as the generic pass writes them (fem/element_pass.h).
// Lanes is a GCC/Clang vector type: the pass is built where core/simd.h's clones are.
//   force term  vol P(F) Dm^-T,   P = mu (H - (cof F - I)) + lam' (J - 1) cof F,  H = F - I,
//   K w term    vol dP[dF] Dm^-T, dP = mu dF + lam' (cof F : dF) cof F + (lam' (J - 1) - mu) dcof F[dF],
// lam' = lam + mu, F = Ds(x) Dm^-1, dF = Ds(w) Dm^-1, J - 1 and cof F - I written without
// cancellation (fem/kernels.h, Smith, de Goes & Kim 2018). The same operations as kernels.h's
// in a different order, so the terms agree with the generic pass's to rounding, not bitwise.
// The baseline and AVX2 versions are one always-inline body compiled twice (core/simd.h): no
// FMA, the same operations in the same order, so they agree bit for bit.
#pragma once

#include <algorithm>
#include <vector>

#include "core/parallel.h"
#include "core/simd.h"
#include "fem/model.h"

namespace kinema::fem::lanes {

#if defined(__GNUC__)
constexpr bool kAvailable = true;
constexpr int W = 4;  // elements per block

// Four doubles operated on together (GCC/Clang vector extension: one AVX2 instruction, or two
// SSE2 ones in the baseline build); scalars combine with them lane by lane.
typedef Scalar Lanes __attribute__((vector_size(W * sizeof(Scalar))));
// The same held in memory that is only Scalar-aligned (a std::vector's storage need not be
// aligned beyond the allocator's default).
typedef Scalar StoredLanes __attribute__((vector_size(W * sizeof(Scalar)), aligned(alignof(Scalar))));

// The model's per-element constants of W elements, one Lanes per value: Dm^-1 (column-major),
// the rest volume and the Lame parameters; a short last block repeats its last element in the
// spare lanes (their results are not written). Built once per model (pack), so that a block
// loads them as whole vectors.
struct Constants {
  StoredLanes dinv[9], vol, mu, lam;
};

inline std::vector<Constants> pack(const Model& m) {
  std::vector<Constants> packed(static_cast<std::size_t>((m.element_count + W - 1) / W));
  for (Index e = 0; e < static_cast<Index>(packed.size()) * W; ++e) {
    Constants& c = packed[static_cast<std::size_t>(e / W)];
    const Index s = std::min(e, m.element_count - 1);
    const int l = static_cast<int>(e % W);
    for (int k = 0; k < 9; ++k) c.dinv[k][l] = m.Dm_inv[s * 9 + k];
    c.vol[l] = m.volume[s];
    c.mu[l] = m.mu[s];
    c.lam[l] = m.lam[s];
  }
  return packed;
}

// One block's inputs (with its constants) and outputs.
struct Block {
  Lanes ds[9], dw[9];
  const StoredLanes *dinv, *vol, *mu, *lam;
  Lanes g[12];
};

// Ds(a) of the block's elements, a = x or w: Ds(r, c) = a[v_{c+1}, r] - a[v_0, r]. Each value is
// built from the four elements' scalars in registers (not stored lane by lane and reloaded).
KINEMA_ALWAYS_INLINE void edge_matrices(const Scalar* a, const Index* const* el, Lanes* ds) {
  for (int c = 0; c < 3; ++c)
    for (int r = 0; r < 3; ++r)
      ds[r + 3 * c] = Lanes{a[el[0][c + 1] * 3 + r] - a[el[0][0] * 3 + r],
                            a[el[1][c + 1] * 3 + r] - a[el[1][0] * 3 + r],
                            a[el[2][c + 1] * 3 + r] - a[el[2][0] * 3 + r],
                            a[el[3][c + 1] * 3 + r] - a[el[3][0] * 3 + r]};
}

KINEMA_ALWAYS_INLINE void gather(const Model& m, const Constants& k, const Scalar* x, const Scalar* w,
                                 Index e0, Index count, Block& b) {
  const Index* el[W];
  for (int l = 0; l < W; ++l) el[l] = m.elements.data() + (e0 + std::min<Index>(l, count - 1)) * 4;
  edge_matrices(x, el, b.ds);
  if (w) edge_matrices(w, el, b.dw);
  b.dinv = k.dinv;
  b.vol = &k.vol;
  b.mu = &k.mu;
  b.lam = &k.lam;
}

KINEMA_ALWAYS_INLINE void scatter(const Block& b, Index e0, Index count, Scalar* out) {
  for (int l = 0; l < count; ++l)
    for (int k = 0; k < 12; ++k) out[(e0 + l) * 12 + k] = b.g[k][l];
}

// A = B C for column-major 3 x 3 matrices.
KINEMA_ALWAYS_INLINE void product(const Lanes* B, const StoredLanes* C, Lanes* A) {
  for (int c = 0; c < 3; ++c)
    for (int r = 0; r < 3; ++r)
      A[r + 3 * c] = B[r] * C[3 * c] + B[r + 3] * C[1 + 3 * c] + B[r + 6] * C[2 + 3 * c];
}

// u x v, u and v three consecutive values.
KINEMA_ALWAYS_INLINE void cross(const Lanes* u, const Lanes* v, Lanes* out) {
  out[0] = u[1] * v[2] - u[2] * v[1];
  out[1] = u[2] * v[0] - u[0] * v[2];
  out[2] = u[0] * v[1] - u[1] * v[0];
}

// cof A (column-major): columns a1 x a2, a2 x a0, a0 x a1.
KINEMA_ALWAYS_INLINE void cofactor3(const Lanes* A, Lanes* C) {
  cross(A + 3, A + 6, C);
  cross(A + 6, A, C + 3);
  cross(A, A + 3, C + 6);
}

// det(I + H) - 1 = tr H + (tr(H)^2 - tr(H^2)) / 2 + det H, with cof H given (an out
// argument: a vector returned by value would change the ABI between the two builds).
KINEMA_ALWAYS_INLINE void det_minus_one3(const Lanes* H, const Lanes* cofH, Lanes& out) {
  const Lanes t = H[0] + H[4] + H[8];
  const Lanes t2 = H[0] * H[0] + H[4] * H[4] + H[8] * H[8] +
                   2 * (H[3] * H[1] + H[6] * H[2] + H[7] * H[5]);
  const Lanes det = H[0] * cofH[0] + H[1] * cofH[1] + H[2] * cofH[2];
  out = t + (t * t - t2) / 2 + det;
}

// The elements' vertex terms from P: vol P Dm^-T (columns: vertices 1..3; vertex 0 minus
// their sum).
KINEMA_ALWAYS_INLINE void vertex_terms(const Lanes* P, Block& b) {
  const StoredLanes* Dinv = b.dinv;
  for (int a = 0; a < 3; ++a)
    for (int r = 0; r < 3; ++r)  // (vol P Dm^-T)(r, a) = vol sum_k P(r, k) Dm^-1(a, k)
      b.g[3 * (a + 1) + r] =
          *b.vol * (P[r] * Dinv[a] + P[r + 3] * Dinv[a + 3] + P[r + 6] * Dinv[a + 6]);
  for (int r = 0; r < 3; ++r) b.g[r] = -(b.g[3 + r] + b.g[6 + r] + b.g[9 + r]);
}

KINEMA_ALWAYS_INLINE void force_lanes(Block& b) {
  Lanes F[9], H[9], C[9], cofH[9], P[9];
  product(b.ds, b.dinv, F);
  for (int k = 0; k < 9; ++k) H[k] = k % 4 == 0 ? F[k] - 1 : F[k];
  cofactor3(F, C);
  cofactor3(H, cofH);
  const Lanes mu = *b.mu, lp = *b.lam + *b.mu;
  Lanes Jm1;
  det_minus_one3(H, cofH, Jm1);
  const Lanes t = H[0] + H[4] + H[8];
  const Lanes s = lp * Jm1;
  for (int c = 0; c < 3; ++c)
    for (int r = 0; r < 3; ++r) {
      // cof F - I = tr(H) I - H^T + cof H
      const Lanes cof_minus_i = r == c ? t - H[c + 3 * r] + cofH[r + 3 * c] : cofH[r + 3 * c] - H[c + 3 * r];
      P[r + 3 * c] = mu * (H[r + 3 * c] - cof_minus_i) + s * C[r + 3 * c];
    }
  vertex_terms(P, b);
}

KINEMA_ALWAYS_INLINE void hessian_product_lanes(Block& b) {
  Lanes F[9], dF[9], H[9], C[9], cofH[9], dC[9], t1[3], t2[3], dP[9];
  product(b.ds, b.dinv, F);
  product(b.dw, b.dinv, dF);
  for (int k = 0; k < 9; ++k) H[k] = k % 4 == 0 ? F[k] - 1 : F[k];
  cofactor3(F, C);
  cofactor3(H, cofH);
  // d(cof F)[dF], column by column: d(f_p x f_q) = df_p x f_q + f_p x df_q.
  for (int a = 0; a < 3; ++a) {
    const int p = 3 * ((a + 1) % 3), q = 3 * ((a + 2) % 3);
    cross(dF + p, F + q, t1);
    cross(F + p, dF + q, t2);
    for (int r = 0; r < 3; ++r) dC[3 * a + r] = t1[r] + t2[r];
  }
  const Lanes mu = *b.mu, lp = *b.lam + *b.mu;
  Lanes Jm1;
  det_minus_one3(H, cofH, Jm1);
  Lanes CdF = C[0] * dF[0];
  for (int k = 1; k < 9; ++k) CdF += C[k] * dF[k];
  const Lanes sC = lp * CdF, sdC = lp * Jm1 - mu;
  for (int k = 0; k < 9; ++k) dP[k] = mu * dF[k] + sC * C[k] + sdC * dC[k];
  vertex_terms(dP, b);
}

// Elements [begin, end) (begin a multiple of W): the force terms (w null) or the K w terms,
// into out (12 per element).
KINEMA_ALWAYS_INLINE void run_blocks(const Model& m, const Constants* k, const Scalar* x,
                                     const Scalar* w, Index begin, Index end, Scalar* out) {
  Block b;
  for (Index e0 = begin; e0 < end; e0 += W) {
    const Index count = std::min<Index>(W, end - e0);
    gather(m, k[e0 / W], x, w, e0, count, b);
    if (w) hessian_product_lanes(b);
    else force_lanes(b);
    scatter(b, e0, count, out);
  }
}

inline void run_baseline(const Model& m, const Constants* k, const Scalar* x, const Scalar* w,
                         Index begin, Index end, Scalar* out) {
  run_blocks(m, k, x, w, begin, end, out);
}

#if KINEMA_HAVE_AVX2_CLONES
KINEMA_TARGET_AVX2 inline void run_avx2(const Model& m, const Constants* k, const Scalar* x,
                                        const Scalar* w, Index begin, Index end, Scalar* out) {
  run_blocks(m, k, x, w, begin, end, out);
}
#endif

// Every element of the model (3D, neo-Hookean; k = pack(m)), over the threads in chunks of
// whole blocks: the force terms at x (w null) or the K(x) w terms.
inline void neohookean_terms(const Model& m, const std::vector<Constants>& k, const Scalar* x,
                             const Scalar* w, bool avx2, Scalar* out) {
  constexpr Index chunk = 64 * W;
  const Index count = m.element_count, chunks = (count + chunk - 1) / chunk;
#pragma omp parallel for schedule(static) if (count > kParallelGrain)
  for (Index c = 0; c < chunks; ++c) {
    const Index begin = c * chunk, end = std::min(count, begin + chunk);
#if KINEMA_HAVE_AVX2_CLONES
    if (avx2) {
      run_avx2(m, k.data(), x, w, begin, end, out);
      continue;
    }
#endif
    (void)avx2;
    run_baseline(m, k.data(), x, w, begin, end, out);
  }
}

#else
constexpr bool kAvailable = false;  // callers take the generic element pass
struct Constants {};
inline std::vector<Constants> pack(const Model&) { return {}; }
inline void neohookean_terms(const Model&, const std::vector<Constants>&, const Scalar*,
                             const Scalar*, bool, Scalar*) {}
#endif

}  // namespace kinema::fem::lanes
