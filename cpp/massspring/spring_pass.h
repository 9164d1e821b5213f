// The per-spring passes of the explicit and symplectic steps and of their adjoints, each spring
// evaluated once; its terms go, signed, to its two ends' slots of the vertices' incidence lists,
// and a vertex then sums its slots in sequence (its springs in the model's spring order, as
// ElementAssembly::gather_vector does). The 2D passes have an AVX2 version
// (spring_pass_avx2.h) that evaluates four springs per instruction; it performs the same IEEE
// operations in the same order as the scalar loop (no FMA), so both give the same bits
// (core/simd.h).
//
// Forward (kernels.h's spring_force): with d = x_j - x_i, l = |d|, n = d (1 / l) (one division
// per spring), dv = v_j - v_i,
//   f_i = (k (l - L) + c dv.n) n               -> out[slot(i) D + r], its negative at slot(j)
// Adjoint of psi = -mu . f_i (mu = lambda_j - lambda_i, adjoint.cpp's header):
//   gd = -((k n + c dv_perp / l) (mu.n) + F mu_perp / l),  gdv = -c (mu.n) n
//     (dL/dx_j, dL/dv_j)  -> out[slot(j) 2D + ..], their negatives at slot(i)
//   and, when wanted, dk += -(l - L) mu.n, dL += k mu.n, dc += -(dv.n) mu.n.
// A zero-length spring has no direction: its terms are 0.
//
// Why the passes stay in cache (SpringPasses): the springs run in "pass order", sorted by their
// lower end, in blocks of vertices; once the springs whose lower end lies in a block are done,
// every term of the block's vertices is written (a spring reaches a vertex only from a lower end
// at or below it), so the block's sums follow at once, while their terms are in L1/L2. The terms
// then live only from the spring's block to its higher end's block: a ring of slots as long as
// that window (a few hundred vertices' worth on a grid-numbered cloth; the whole list when the
// numbering scatters neighbours) replaces a buffer of every slot. Each thread takes a range of
// vertices with its own ring and first evaluates the springs from below its range that reach into
// it (evaluated twice, once per side: the same bits): no thread writes what another reads, and
// the whole step is one parallel region. A vertex's sum is the same whatever the blocks and
// threads, so results are bitwise independent of the thread count.
#pragma once

#include <omp.h>

#include <Eigen/Core>
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#include "core/errors.h"
#include "core/parallel.h"
#include "core/simd.h"
#include "core/types.h"

namespace kinema::massspring {

// Vertex and slot indices in the passes: 32 bits halve their memory traffic.
using PassIndex = std::int32_t;

// Indices are element offsets (a vertex i's row of an (n, D) array starts at D i; a ring slot p
// at D p), so that a pass adds them to a base pointer as they are.
struct SpringInputs {
  const PassIndex* springs;  // (m, 2), pass order, ends as in the model: D i
  const Scalar *x, *v;       // (n, D)
  const Scalar *k, *L, *c;   // (m,), pass order
  // slot[2 s + a]: where the term of end a of spring s goes in the ring (the header): D p.
  const PassIndex* slot;
  const PassIndex* order;  // pass position -> the model's spring index (parameter gradients)
  Index plane;             // the adjoint's second plane (its gdv) starts this far after the first
};

// f_i of springs [begin, end) into out (ring of D-vectors), by slot.
template <int D>
inline void spring_forces_scalar(const SpringInputs in, Index begin, Index end, Scalar* out) {
  for (Index s = begin; s < end; ++s) {
    const Index a = in.springs[2 * s], b = in.springs[2 * s + 1];
    Scalar d[D], dv[D];
    for (int r = 0; r < D; ++r) {
      d[r] = in.x[b + r] - in.x[a + r];
      dv[r] = in.v[b + r] - in.v[a + r];
    }
    Scalar l2 = d[0] * d[0];
    for (int r = 1; r < D; ++r) l2 += d[r] * d[r];
    const Scalar l = std::sqrt(l2);
    Scalar* oa = out + in.slot[2 * s];
    Scalar* ob = out + in.slot[2 * s + 1];
    if (l == 0) {
      for (int r = 0; r < D; ++r) oa[r] = ob[r] = 0;
      continue;
    }
    const Scalar inv = 1 / l;
    Scalar n[D];
    for (int r = 0; r < D; ++r) n[r] = d[r] * inv;
    Scalar vn = dv[0] * n[0];
    for (int r = 1; r < D; ++r) vn += dv[r] * n[r];
    const Scalar F = in.k[s] * (l - in.L[s]) + in.c[s] * vn;
    for (int r = 0; r < D; ++r) {
      oa[r] = F * n[r];
      ob[r] = -oa[r];
    }
  }
}

// gd, gdv of springs [begin, end) into out's two planes (rings of D-vectors), by slot; the
// parameter terms added to dk, dL, dc (model order) when dk is not null.
template <int D>
inline void spring_adjoint_scalar(const SpringInputs in, const Scalar* lambda, Index begin,
                                  Index end, Scalar* out, Scalar* dk, Scalar* dL, Scalar* dc) {
  for (Index s = begin; s < end; ++s) {
    const Index a = in.springs[2 * s], b = in.springs[2 * s + 1];
    Scalar d[D], dv[D], mu[D];
    for (int r = 0; r < D; ++r) {
      d[r] = in.x[b + r] - in.x[a + r];
      dv[r] = in.v[b + r] - in.v[a + r];
      mu[r] = lambda[b + r] - lambda[a + r];
    }
    Scalar l2 = d[0] * d[0];
    for (int r = 1; r < D; ++r) l2 += d[r] * d[r];
    const Scalar l = std::sqrt(l2);
    Scalar* oa = out + in.slot[2 * s];
    Scalar* ob = out + in.slot[2 * s + 1];
    Scalar* va = oa + in.plane;
    Scalar* vb = ob + in.plane;
    if (l == 0) {
      for (int r = 0; r < D; ++r) oa[r] = ob[r] = va[r] = vb[r] = 0;
      continue;
    }
    const Scalar k = in.k[s], L = in.L[s], c = in.c[s], inv = 1 / l;
    Scalar n[D];
    for (int r = 0; r < D; ++r) n[r] = d[r] * inv;
    Scalar mn = mu[0] * n[0], vn = dv[0] * n[0];
    for (int r = 1; r < D; ++r) {
      mn += mu[r] * n[r];
      vn += dv[r] * n[r];
    }
    const Scalar F = k * (l - L) + c * vn;
    const Scalar cm = -c * mn;
    for (int r = 0; r < D; ++r) {
      const Scalar dvp = dv[r] - vn * n[r], mup = mu[r] - mn * n[r];
      // d = x_j - x_i: dL/dx_i = -gd, dL/dx_j = +gd (the same for v).
      ob[r] = -((k * n[r] + c * dvp * inv) * mn + F * mup * inv);
      vb[r] = cm * n[r];
      oa[r] = -ob[r];
      va[r] = -vb[r];
    }
    if (dk) {
      const Index q = in.order[s];
      dk[q] += -(l - L) * mn;
      dL[q] += k * mn;
      dc[q] += -vn * mn;
    }
  }
}

}  // namespace kinema::massspring

#include "massspring/spring_pass_avx2.h"

namespace kinema::massspring {

template <int D>
void spring_forces(const SpringInputs& in, Index begin, Index end, bool avx2, Scalar* out) {
#if KINEMA_HAVE_AVX2_CLONES
  if (D == 2 && avx2) return avx2::spring_forces_2d(in, begin, end, out);
#endif
  (void)avx2;
  spring_forces_scalar<D>(in, begin, end, out);
}

template <int D>
void spring_adjoint(const SpringInputs& in, const Scalar* lambda, Index begin, Index end, bool avx2,
                    Scalar* out, Scalar* dk, Scalar* dL, Scalar* dc) {
#if KINEMA_HAVE_AVX2_CLONES
  if (D == 2 && avx2) return avx2::spring_adjoint_2d(in, lambda, begin, end, out, dk, dL, dc);
#endif
  (void)avx2;
  spring_adjoint_scalar<D>(in, lambda, begin, end, out, dk, dL, dc);
}

// The springs in pass order, their ends' ring slots and the vertex ranges of the threads
// (the header's scheme); one per Solver.
class SpringPasses {
 public:
  // springs (m, 2) over n vertices of dimension dim, in the model's order. Throws
  // InvalidArgument when the counts exceed the passes' 32-bit indices.
  void build(const Index* springs, Index spring_count, Index vertex_count, int dim);
  // The model's per-spring parameters (model order) into pass order.
  void set_parameters(const Scalar* k, const Scalar* L, const Scalar* c);

  SpringInputs inputs(const Scalar* x, const Scalar* v) const {
    return {ends_.data(), x,           v,
            k_.data(),    L_.data(),   c_.data(),
            slot_.data(), order_.data(), ring_size_ * dim_};
  }

  // One parallel region: each thread, over its range [a, b) of vertices, calls before(a, b);
  // then (after a barrier, when `barrier`: before's writes are read by other threads' springs)
  // springs(begin, end, ring, owned) for the pass-order springs [begin, end) (owned: false for
  // those evaluated only for the terms they bring into the range from below, whose parameter
  // terms belong to another range), block by block, and after(u, w, sums) once the springs of
  // the block [u, w) are done, sums (w - u, Planes D) holding each vertex's sum of its terms in
  // slot order, plane by plane (a ring of Planes planes of D-vectors).
  template <int D, int Planes, class Springs, class Before, class After>
  void run(bool barrier, Springs&& springs, Before&& before, After&& after) {
    using Term = Eigen::Matrix<Scalar, D, 1>;
    constexpr int W = Planes * D;
    const int threads = spring_count_ > kParallelSprings ? num_threads() : 1;
    if (static_cast<int>(rings_.size()) < threads) rings_.resize(static_cast<std::size_t>(threads));
#pragma omp parallel num_threads(threads) if (threads > 1)
    {
      const int team = omp_get_num_threads(), t = omp_get_thread_num();
      const Index a = split(t, team), b = split(t + 1, team);
      before(a, b);
      if (barrier) {
#pragma omp barrier
      }
      std::vector<Scalar>& ring = rings_[static_cast<std::size_t>(t)];
      const Index plane = ring_size_ * D;
      ring.resize(static_cast<std::size_t>(Planes * plane + kBlock * W));
      Scalar* out = ring.data();
      Scalar* sums = out + Planes * plane;
      const Index* ptr = incidence_ptr_.data();
      const Index mask = ring_mask_;
      if (a < b) springs(first_[reach_[a]], first_[a], out, false);
      for (Index u = a; u < b; u += kBlock) {
        const Index w = std::min(b, u + kBlock);
        springs(first_[u], first_[w], out, true);
        for (Index i = u; i < w; ++i) {
          Term sum[Planes];
          for (int k = 0; k < Planes; ++k) sum[k].setZero();
          for (Index p = ptr[i]; p < ptr[i + 1]; ++p)
            for (int k = 0; k < Planes; ++k)
              sum[k] += Eigen::Map<const Term>(out + k * plane + (p & mask) * D);
          for (int k = 0; k < Planes; ++k) Eigen::Map<Term>(sums + (i - u) * W + k * D) = sum[k];
        }
        after(u, w, static_cast<const Scalar*>(sums));
      }
    }
  }

 private:
  // Vertices per block: the ring spans a block plus the springs' reach around it.
  static constexpr Index kBlock = 64;
  // Below this many springs one thread does the pass (waking a team costs more).
  static constexpr Index kParallelSprings = 2048;

  // The first vertex of thread t's range of `team`: ranges of about equal slot counts.
  Index split(int t, int team) const {
    if (t == 0) return 0;
    if (t == team) return vertex_count_;
    const Index target = 2 * spring_count_ * t / team;
    return std::lower_bound(incidence_ptr_.begin(), incidence_ptr_.end(), target) -
           incidence_ptr_.begin();
  }

  Index vertex_count_ = 0, spring_count_ = 0;
  int dim_ = 0;
  std::vector<PassIndex> ends_, slot_, order_;
  std::vector<Scalar> k_, L_, c_;
  std::vector<Index> first_;          // (n + 1): pass-order springs whose lower end is below v
  std::vector<Index> reach_;          // (n,): the lowest lower end of the springs reaching v or above
  std::vector<Index> incidence_ptr_;  // (n + 1): vertex i's slots [ptr[i], ptr[i + 1])
  Index ring_size_ = 0, ring_mask_ = 0;
  std::vector<std::vector<Scalar>> rings_;  // per thread
};

inline void SpringPasses::build(const Index* springs, Index spring_count, Index vertex_count,
                                int dim) {
  constexpr Index kMax = INT32_MAX;
  if (dim * vertex_count > kMax || 2 * dim * spring_count > kMax)
    throw InvalidArgument("springs: the explicit passes index vertices and spring ends with 32 bits; "
                          "got " + std::to_string(vertex_count) + " vertices and " +
                          std::to_string(spring_count) + " springs");
  const Index n = vertex_count, m = spring_count;
  vertex_count_ = n;
  spring_count_ = m;
  dim_ = dim;
  // Slots: each vertex's spring ends in the model's spring order (CSR).
  incidence_ptr_.assign(static_cast<std::size_t>(n + 1), 0);
  for (Index q = 0; q < 2 * m; ++q) ++incidence_ptr_[springs[q] + 1];
  for (Index i = 0; i < n; ++i) incidence_ptr_[i + 1] += incidence_ptr_[i];
  std::vector<Index> slot(static_cast<std::size_t>(2 * m));
  {
    std::vector<Index> next(incidence_ptr_.begin(), incidence_ptr_.end() - 1);
    for (Index q = 0; q < 2 * m; ++q) slot[q] = next[springs[q]]++;
  }
  // Pass order: by lower end, then by model order (a counting sort).
  const auto lower = [&](Index s) { return std::min(springs[2 * s], springs[2 * s + 1]); };
  const auto upper = [&](Index s) { return std::max(springs[2 * s], springs[2 * s + 1]); };
  first_.assign(static_cast<std::size_t>(n + 1), 0);
  for (Index s = 0; s < m; ++s) ++first_[lower(s) + 1];
  for (Index i = 0; i < n; ++i) first_[i + 1] += first_[i];
  order_.resize(static_cast<std::size_t>(m));
  {
    std::vector<Index> next(first_.begin(), first_.end() - 1);
    for (Index s = 0; s < m; ++s) order_[next[lower(s)]++] = static_cast<PassIndex>(s);
  }
  // The window of live slots around a block of vertices [u, u + kBlock): from the lowest lower
  // end of a spring reaching u (reach_[u], the prologue's springs start there) to the highest
  // upper end of a spring starting in the block.
  std::vector<Index> high(static_cast<std::size_t>(n));
  reach_.resize(static_cast<std::size_t>(n));
  for (Index i = 0; i < n; ++i) high[i] = reach_[i] = i;
  for (Index s = 0; s < m; ++s) {
    high[lower(s)] = std::max(high[lower(s)], upper(s));
    reach_[upper(s)] = std::min(reach_[upper(s)], lower(s));
  }
  for (Index i = 1; i < n; ++i) high[i] = std::max(high[i], high[i - 1]);
  for (Index i = n - 2; i >= 0; --i) reach_[i] = std::min(reach_[i], reach_[i + 1]);
  Index window = 1;
  for (Index u = 0; u < n; ++u) {
    const Index top = high[std::min(u + kBlock, n) - 1];
    window = std::max(window, incidence_ptr_[top + 1] - incidence_ptr_[reach_[u]]);
  }
  // A ring of 2^k slots when that is shorter than the list; else the whole list, unmasked.
  Index ring = 1;
  while (ring < window) ring *= 2;
  if (ring < 2 * m) {
    ring_size_ = ring;
    ring_mask_ = ring - 1;
  } else {
    ring_size_ = std::max<Index>(2 * m, 1);
    ring_mask_ = ~Index{0};
  }
  ends_.resize(static_cast<std::size_t>(2 * m));
  slot_.resize(static_cast<std::size_t>(2 * m));
  for (Index p = 0; p < m; ++p) {
    const Index s = order_[p];
    for (int e = 0; e < 2; ++e) {
      ends_[2 * p + e] = static_cast<PassIndex>(dim * springs[2 * s + e]);
      slot_[2 * p + e] = static_cast<PassIndex>(dim * (slot[2 * s + e] & ring_mask_));
    }
  }
}

inline void SpringPasses::set_parameters(const Scalar* k, const Scalar* L, const Scalar* c) {
  const std::size_t m = order_.size();
  k_.resize(m);
  L_.resize(m);
  c_.resize(m);
  for (std::size_t p = 0; p < m; ++p) {
    k_[p] = k[order_[p]];
    L_[p] = L[order_[p]];
    c_[p] = c[order_[p]];
  }
}

}  // namespace kinema::massspring
