// Fixed-radius neighbour lists in CSR form: the neighbours of query point i are
// list[start[i] .. start[i+1]), in the order the candidates were offered (deterministic).
// Ways to fill them, all allocation-free once the buffers have grown:
// - build(): from a NeighborGrid, all binned points within `radius` of each query point;
// - filter(): from wider lists (a Verlet list with a skin, Verlet 1967), only the entries
//   within `radius` at the current positions. A Verlet list built with radius h (1 + skin)
//   holds every pair closer than h as long as no point has moved more than skin h / 2 since
//   the build, so filtering it each step gives exactly the pairs a fresh search would;
// - fill_with_values(): from any source of candidates, with one value per entry kept in a
//   parallel array (a caller's filter that computes something per pair on the way).
#pragma once

#include <omp.h>

#include <Eigen/Core>
#include <algorithm>
#include <cstdint>
#include <vector>

#include "core/parallel.h"
#include "core/types.h"
#include "particles/neighbor_grid.h"

namespace kinema {

struct NeighborLists {
  std::vector<Index> start;
  std::vector<std::int32_t> list;

  Index size() const { return static_cast<Index>(list.size()); }

  // Neighbours within radius of each query point xq (nq rows of D) among the points the grid
  // binned (coordinates xs); a query point is its own neighbour only if !self.
  template <int D>
  void build(const NeighborGrid<D>& grid, const Scalar* xs, const Scalar* xq, Index nq, Scalar radius,
             bool self) {
    using Vec = Eigen::Matrix<Scalar, D, 1>;
    const Scalar r2 = radius * radius;
    fill(nq, [&](Index i, auto&& push) {
      const Vec xi = Eigen::Map<const Vec>(xq + i * D);
      // Most candidates of the 3^D cells fail the test, at random: the test is done branch-free
      // into a small buffer that is handed on when full.
      constexpr int kChunk = 64;
      Index kept[kChunk];
      int count = 0;
      grid.for_each_candidate(xi, radius, [&](Index j) {
        kept[count] = j;
        count += (Eigen::Map<const Vec>(xs + j * D) - xi).squaredNorm() < r2 && !(self && j == i);
        if (count == kChunk) {
          for (int e = 0; e < count; ++e) push(kept[e]);
          count = 0;
        }
      });
      for (int e = 0; e < count; ++e) push(kept[e]);
    });
  }

  // The entries of `wider` (lists of the same query points) within radius at the current
  // coordinates xs (listed points) and xq (query points).
  template <int D>
  void filter(const NeighborLists& wider, const Scalar* xs, const Scalar* xq, Index nq, Scalar radius) {
    using Vec = Eigen::Matrix<Scalar, D, 1>;
    const Scalar r2 = radius * radius;
    fill(nq, [&](Index i, auto&& push) {
      const Vec xi = Eigen::Map<const Vec>(xq + i * D);
      for (Index k = wider.start[i]; k < wider.start[i + 1]; ++k) {
        const Index j = wider.list[k];
        if ((Eigen::Map<const Vec>(xs + j * D) - xi).squaredNorm() < r2) push(j);
      }
    });
  }

  // The lists of nq query points from candidates(i, push), which calls push(j, value) for each
  // neighbour j of query point i in order; values[k] is the value pushed with entry k. Each
  // query point is visited once, by one thread, in increasing order within a thread.
  template <class Candidates>
  void fill_with_values(Index nq, std::vector<Scalar>& values, Candidates&& candidates) {
    fill_impl<true>(nq, &values, candidates);
  }

 private:
  std::vector<std::vector<std::int32_t>> per_thread_;
  std::vector<std::vector<Scalar>> per_thread_values_;

  // candidates(i, push) calls push(j) for each neighbour j of query point i, in order.
  template <class Candidates>
  void fill(Index nq, Candidates&& candidates) {
    fill_impl<false>(nq, nullptr, [&](Index i, auto&& push) {
      candidates(i, [&](Index j) { push(j, Scalar(0)); });
    });
  }

  template <bool kValues, class Candidates>
  void fill_impl(Index nq, std::vector<Scalar>* values, Candidates&& candidates) {
    start.assign(static_cast<size_t>(nq) + 1, 0);
    const int threads = nq > kParallelGrain ? num_threads() : 1;
    per_thread_.resize(static_cast<size_t>(std::max(threads, 1)));
    if constexpr (kValues) per_thread_values_.resize(per_thread_.size());
    // Each thread fills the lists of one contiguous chunk of points; concatenating the chunks
    // in order gives the same CSR arrays for any thread count.
#pragma omp parallel num_threads(threads)
    {
      const int t = omp_get_thread_num();
      const int nt = omp_get_num_threads();
      const Index begin = nq * t / nt, end = nq * (t + 1) / nt;
      auto& buf = per_thread_[static_cast<size_t>(t)];
      buf.clear();
      std::vector<Scalar>* vbuf = kValues ? &per_thread_values_[static_cast<size_t>(t)] : nullptr;
      if constexpr (kValues) vbuf->clear();
      for (Index i = begin; i < end; ++i) {
        const size_t before = buf.size();
        candidates(i, [&](Index j, Scalar value) {
          buf.push_back(static_cast<std::int32_t>(j));
          if constexpr (kValues) vbuf->push_back(value);
        });
        start[static_cast<size_t>(i) + 1] = static_cast<Index>(buf.size() - before);
      }
#pragma omp barrier
#pragma omp single
      {
        for (Index i = 0; i < nq; ++i) start[i + 1] += start[i];
        list.resize(static_cast<size_t>(start[nq]));
        if constexpr (kValues) values->resize(static_cast<size_t>(start[nq]));
      }
      std::copy(buf.begin(), buf.end(), list.begin() + start[begin]);
      if constexpr (kValues) std::copy(vbuf->begin(), vbuf->end(), values->begin() + start[begin]);
    }
  }
};

}  // namespace kinema
