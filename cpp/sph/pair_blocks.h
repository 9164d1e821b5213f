// The DFSPH solves' neighbour pairs stored once per pair, for the two light passes every Jacobi
// iteration makes (sph/solver.cpp: the velocity change of the stiffness increments and the rate
// of density change). Both passes are bound by the bytes they stream (an int32 index and a float
// gradient per entry, 16 bytes in 3D, ~64 MB a pass at 150k particles, far past the caches), and
// the full lists hold every pair twice with grad_j W_ji = -grad_i W_ij. Here the rows are cut
// into blocks of kBlock consecutive rows (Morton-ordered particles, so a block is a compact
// region): a pair within one block is stored once, in the row of its lower index, and its term
// is added to both ends (the upper end's share kept in a per-row accumulator until its row comes);
// a pair across blocks stays in both rows, as before, so that blocks are independent and run in
// parallel. Each row's sum is final when its row has been read, so the caller's per-particle
// update runs right there. About 55-60% of a 3D dam break's entries remain.
//
// The results do not depend on the thread count (a block's sums are formed in a fixed order) and
// the AVX2 version (3D) performs the same lane-wise multiplications and additions in the same
// order as the baseline (one body, GCC vector extensions, no FMA): bitwise equal.
#pragma once

#include <omp.h>

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <vector>

#include "core/parallel.h"
#include "core/simd.h"
#include "core/types.h"

namespace kinema::sph {

namespace pair_lanes {

// Aligned as their elements: std::vector does not honour a vector type's natural alignment (GCC
// drops the attribute from the template argument), so every access is an unaligned one.
typedef double V4 __attribute__((vector_size(32), aligned(8)));
typedef double V2 __attribute__((vector_size(16), aligned(8)));
typedef float F4 __attribute__((vector_size(16), aligned(4)));
typedef float F2 __attribute__((vector_size(8), aligned(4)));
typedef std::int32_t I4 __attribute__((vector_size(16), aligned(4)));

// The D components of a gradient or a velocity as a vector of lanes (3D: 4 lanes, the fourth 0).
template <int D>
struct Lanes;

template <>
struct Lanes<3> {
  using V = V4;
  // An entry's gradient (3 floats, then its index, masked off: an index read as a float would be
  // a denormal).
  static KINEMA_ALWAYS_INLINE V grad(const void* entry) {
    I4 bits;
    std::memcpy(&bits, entry, sizeof bits);
    bits &= I4{-1, -1, -1, 0};
    return __builtin_convertvector(reinterpret_cast<F4&>(bits), V4);
  }
  static KINEMA_ALWAYS_INLINE V load(const Scalar* v, Index j) { return V{v[3 * j], v[3 * j + 1], v[3 * j + 2], 0}; }
  static KINEMA_ALWAYS_INLINE Scalar sum(const V& a) { return (a[0] + a[1]) + a[2]; }
};

template <>
struct Lanes<2> {
  using V = V2;
  static KINEMA_ALWAYS_INLINE V grad(const void* entry) {
    F2 g;
    std::memcpy(&g, entry, sizeof g);
    return __builtin_convertvector(g, V2);
  }
  static KINEMA_ALWAYS_INLINE V load(const Scalar* v, Index j) { return V{v[2 * j], v[2 * j + 1]}; }
  static KINEMA_ALWAYS_INLINE Scalar sum(const V& a) { return a[0] + a[1]; }
};

}  // namespace pair_lanes

template <int D>
struct PairBlocks {
  static constexpr Index kBlock = 2048;  // rows per block
  using V = typename pair_lanes::Lanes<D>::V;
  struct Entry {
    float g[D];  // grad_i W_ij as the full list stores it
    std::int32_t j;
  };

  Index n = 0;
  std::vector<Index> start;      // (n + 1) row i: entries [start[i], start[i + 1])
  std::vector<Index> local_end;  // (n) of which [start[i], local_end[i]) are in-block with j > i
  std::vector<Entry> entries;
  std::vector<V> acc;            // (n) the upper ends' shares, per pass

  Index blocks() const { return (n + kBlock - 1) / kBlock; }

  // From the full lists (CSR fstart, flist; D float gradients per entry), keeping each row's
  // order.
  void build(Index rows, const Index* fstart, const std::int32_t* flist, const float* fgrads) {
    n = rows;
    start.resize(static_cast<size_t>(n) + 1);
    local_end.resize(static_cast<size_t>(n));
    acc.resize(static_cast<size_t>(n));
    start[0] = 0;
    parallel_for(n, [&](Index i) {
      const Index b0 = i / kBlock * kBlock, b1 = b0 + kBlock;
      Index local = 0, cross = 0;
      for (Index k = fstart[i]; k < fstart[i + 1]; ++k) {
        const Index j = flist[k];
        local += j > i && j < b1;
        cross += j < b0 || j >= b1;
      }
      local_end[i] = local;
      start[i + 1] = local + cross;
    });
    for (Index i = 0; i < n; ++i) start[i + 1] += start[i];
    entries.resize(static_cast<size_t>(start[n]));
    parallel_for(n, [&](Index i) {
      const Index b0 = i / kBlock * kBlock, b1 = b0 + kBlock;
      Index a = start[i], c = start[i] + local_end[i];
      local_end[i] = c;
      for (Index k = fstart[i]; k < fstart[i + 1]; ++k) {
        const Index j = flist[k];
        const bool local = j >= b0 && j < b1;
        if (local && j < i) continue;
        Entry& e = entries[static_cast<size_t>(local ? a++ : c++)];
        for (int d = 0; d < D; ++d) e.g[d] = fgrads[k * D + d];
        e.j = static_cast<std::int32_t>(j);
      }
    });
  }

  // out(i, s) for every row i with the lanes s of sum_j (c_i + c_j) grad_i W_ij over all the
  // fluid neighbours j of i.
  template <class Out>
  void weighted(const Scalar* c, bool avx2, Out&& out) {
    run(avx2, [&](Index b) { weighted_block(b, c, out); }, [&](Index b) { weighted_block_avx2(b, c, out); });
  }

  // out(i, s) for every row i with s = sum_j v_j . grad_i W_ij over all the fluid neighbours j
  // of i (v: D values per particle).
  template <class Out>
  void dot(const Scalar* v, bool avx2, Out&& out) {
    run(avx2, [&](Index b) { dot_block(b, v, out); }, [&](Index b) { dot_block_avx2(b, v, out); });
  }

 private:
  template <class Base, class Wide>
  void run(bool avx2, Base&& base, Wide&& wide) {
    const Index nb = blocks();
#pragma omp parallel for schedule(dynamic, 1) if (n > kParallelGrain)
    for (Index b = 0; b < nb; ++b) {
#if KINEMA_HAVE_AVX2_CLONES
      if (D == 3 && avx2) {
        wide(b);
        continue;
      }
#endif
      (void)avx2;
      (void)wide;
      base(b);
    }
  }

  // Entries [begin, end) into four partial sums (entry e into e mod 4), as the full lists' row
  // sums do.
  template <class Term>
  static KINEMA_ALWAYS_INLINE void partials(Index begin, Index end, Term&& term, V* p) {
    Index k = begin;
    for (; k + 4 <= end; k += 4) {
      term(k, p[0]);
      term(k + 1, p[1]);
      term(k + 2, p[2]);
      term(k + 3, p[3]);
    }
    if (k < end) term(k, p[0]);
    if (k + 1 < end) term(k + 1, p[1]);
    if (k + 2 < end) term(k + 2, p[2]);
  }

  template <class Out>
  KINEMA_ALWAYS_INLINE void weighted_body(Index b, const Scalar* c, Out& out) {
    using L = pair_lanes::Lanes<D>;
    const Index b0 = b * kBlock, b1 = std::min(n, b0 + kBlock);
    const Entry* e = entries.data();
    V* a = acc.data();
    for (Index i = b0; i < b1; ++i) a[i] = V{};
    for (Index i = b0; i < b1; ++i) {
      const Scalar ci = c[i];
      V p[4] = {};
      partials(start[i], local_end[i], [&](Index k, V& s) {
        const V t = (ci + c[e[k].j]) * L::grad(e + k);
        s += t;
        a[e[k].j] -= t;
      }, p);
      partials(local_end[i], start[i + 1], [&](Index k, V& s) { s += (ci + c[e[k].j]) * L::grad(e + k); }, p);
      const V sum = ((p[0] + p[1]) + (p[2] + p[3])) + a[i];
      out(i, sum);
    }
  }

  template <class Out>
  KINEMA_ALWAYS_INLINE void dot_body(Index b, const Scalar* v, Out& out) {
    using L = pair_lanes::Lanes<D>;
    const Index b0 = b * kBlock, b1 = std::min(n, b0 + kBlock);
    const Entry* e = entries.data();
    V* a = acc.data();
    for (Index i = b0; i < b1; ++i) a[i] = V{};
    for (Index i = b0; i < b1; ++i) {
      const V vi = L::load(v, i);
      V p[4] = {};
      partials(start[i], local_end[i], [&](Index k, V& s) {
        const V g = L::grad(e + k);
        s += L::load(v, e[k].j) * g;
        a[e[k].j] -= vi * g;
      }, p);
      partials(local_end[i], start[i + 1], [&](Index k, V& s) { s += L::load(v, e[k].j) * L::grad(e + k); }, p);
      out(i, L::sum(((p[0] + p[1]) + (p[2] + p[3])) + a[i]));
    }
  }

  template <class Out>
  void weighted_block(Index b, const Scalar* c, Out& out) { weighted_body(b, c, out); }
  template <class Out>
  void dot_block(Index b, const Scalar* v, Out& out) { dot_body(b, v, out); }
#if KINEMA_HAVE_AVX2_CLONES
  template <class Out>
  KINEMA_TARGET_AVX2 void weighted_block_avx2(Index b, const Scalar* c, Out& out) { weighted_body(b, c, out); }
  template <class Out>
  KINEMA_TARGET_AVX2 void dot_block_avx2(Index b, const Scalar* v, Out& out) { dot_body(b, v, out); }
#else
  template <class Out>
  void weighted_block_avx2(Index b, const Scalar* c, Out& out) { weighted_body(b, c, out); }
  template <class Out>
  void dot_block_avx2(Index b, const Scalar* v, Out& out) { dot_body(b, v, out); }
#endif
};

}  // namespace kinema::sph
