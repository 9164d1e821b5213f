// Fixed-radius neighbour lists in CSR form: the neighbours of query point i are
// list[start[i] .. start[i+1]), in the order the candidates were offered (deterministic).
// Ways to fill them, all allocation-free once the buffers have grown:
// - build(): from a NeighborGrid, all binned points within `radius` of each query point
//   (neighbor_lists.cpp);
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
#include <memory>
#include <vector>

#include "core/parallel.h"
#include "core/simd.h"
#include "core/types.h"
#include "particles/neighbor_grid.h"

namespace kinema {

struct NeighborLists {
  std::vector<Index> start;
  std::vector<std::int32_t> list;

  Index size() const { return static_cast<Index>(list.size()); }

  // Neighbours within radius (at most the grid's build radius) of each query point xq (nq rows
  // of D) among the points the grid binned; a query point is its own neighbour only if !self.
  // Each row lists its neighbours in the grid's sorted order (cell order). The distance test
  // runs over the grid's contiguous runs of coordinates, 4 candidates at a time with AVX2 where
  // the CPU has it (avx2 = use_avx2()); both paths give identical lists (neighbor_lists.cpp).
  template <int D>
  void build(const NeighborGrid<D>& grid, const Scalar* xq, Index nq, Scalar radius, bool self) {
    build<D>(grid, xq, nq, radius, self, use_avx2());
  }
  template <int D>
  void build(const NeighborGrid<D>& grid, const Scalar* xq, Index nq, Scalar radius, bool self, bool avx2);

  // The entries of `wider` (lists of the same query points) within radius at the current
  // coordinates xs (listed points) and xq (query points).
  template <int D>
  void filter(const NeighborLists& wider, const Scalar* xs, const Scalar* xq, Index nq, Scalar radius) {
    using Vec = Eigen::Matrix<Scalar, D, 1>;
    const Scalar r2 = radius * radius;
    fill_rows(nq, nullptr, [&](Index i, Buffer<std::int32_t>& out, Buffer<Scalar>*) {
      const Vec xi = Eigen::Map<const Vec>(xq + i * D);
      const Index begin = wider.start[i], end = wider.start[i + 1];
      std::int32_t* kept = out.room(static_cast<size_t>(end - begin));
      Index count = 0;
      for (Index k = begin; k < end; ++k) {
        const std::int32_t j = wider.list[k];
        kept[count] = j;
        count += (Eigen::Map<const Vec>(xs + Index{j} * D) - xi).squaredNorm() < r2;
      }
      out.size += static_cast<size_t>(count);
    });
  }

  // The lists of nq query points from candidates(i, push), which calls push(j, value) for each
  // neighbour j of query point i in order; values[k] is the value pushed with entry k. Each
  // query point is visited once, by one thread, in increasing order within a thread.
  template <class Candidates>
  void fill_with_values(Index nq, std::vector<Scalar>& values, Candidates&& candidates) {
    fill_rows(nq, &values, [&](Index i, Buffer<std::int32_t>& out, Buffer<Scalar>* vout) {
      // The two buffers grow together; their ends are kept in locals (registers) over the row.
      size_t size = out.size, capacity = std::min(out.capacity, vout->capacity);
      std::int32_t* ids = out.data.get();
      Scalar* vals = vout->data.get();
      candidates(i, [&](Index j, Scalar value) {
        if (size == capacity) {
          out.size = vout->size = size;
          ids = out.room(1) - size;
          vals = vout->room(1) - size;
          capacity = std::min(out.capacity, vout->capacity);
        }
        ids[size] = static_cast<std::int32_t>(j);
        vals[size] = value;
        ++size;
      });
      out.size = vout->size = size;
    });
  }

  // A growable array whose new room is left uninitialised: one thread's rows before they are
  // concatenated (a row reserves room for all its candidates, then keeps a prefix).
  template <class T>
  struct Buffer {
    std::unique_ptr<T[]> data;
    size_t size = 0, capacity = 0;
    // Room for `extra` more entries past size (size is left to the caller to advance).
    T* room(size_t extra) {
      if (size + extra > capacity) {
        capacity = std::max(size + extra, 2 * capacity);
        std::unique_ptr<T[]> grown(new T[capacity]);
        std::copy(data.get(), data.get() + size, grown.get());
        data = std::move(grown);
      }
      return data.get() + size;
    }
  };

 private:
  std::vector<Buffer<std::int32_t>> per_thread_;
  std::vector<Buffer<Scalar>> per_thread_values_;

  // row(i, out, vout) appends the neighbours of query point i to out (and, with values, one
  // value each to vout).
  template <class Row>
  void fill_rows(Index nq, std::vector<Scalar>* values, Row&& row) {
    fill_chunks(nq, values, [&](Index begin, Index end, Buffer<std::int32_t>& out, Buffer<Scalar>* vout, Index* sizes) {
      for (Index i = begin; i < end; ++i) {
        const size_t before = out.size;
        row(i, out, vout);
        sizes[i] = static_cast<Index>(out.size - before);
      }
    });
  }

  // rows(begin, end, out, vout, sizes) appends the rows of the query points [begin, end) to out
  // (and vout) and sets sizes[i] to the length of row i.
  template <class Rows>
  void fill_chunks(Index nq, std::vector<Scalar>* values, Rows&& rows) {
    start.assign(static_cast<size_t>(nq) + 1, 0);
    const int threads = nq > kParallelGrain ? num_threads() : 1;
    per_thread_.resize(static_cast<size_t>(std::max(threads, 1)));
    if (values != nullptr) per_thread_values_.resize(per_thread_.size());
    // Each thread fills the lists of one contiguous chunk of points; concatenating the chunks
    // in order gives the same CSR arrays for any thread count.
#pragma omp parallel num_threads(threads)
    {
      const int t = omp_get_thread_num();
      const int nt = omp_get_num_threads();
      const Index begin = nq * t / nt, end = nq * (t + 1) / nt;
      auto& buf = per_thread_[static_cast<size_t>(t)];
      buf.size = 0;
      Buffer<Scalar>* vbuf = values != nullptr ? &per_thread_values_[static_cast<size_t>(t)] : nullptr;
      if (vbuf != nullptr) vbuf->size = 0;
      if (begin < end) rows(begin, end, buf, vbuf, start.data() + 1);
#pragma omp barrier
#pragma omp single
      {
        for (Index i = 0; i < nq; ++i) start[i + 1] += start[i];
        list.resize(static_cast<size_t>(start[nq]));
        if (values != nullptr) values->resize(static_cast<size_t>(start[nq]));
      }
      std::copy(buf.data.get(), buf.data.get() + buf.size, list.begin() + start[begin]);
      if (vbuf != nullptr) std::copy(vbuf->data.get(), vbuf->data.get() + vbuf->size, values->begin() + start[begin]);
    }
  }
};

}  // namespace kinema
