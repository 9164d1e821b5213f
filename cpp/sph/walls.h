// The rows of the walls that carry pressure (Model::wall_begin on): the (fluid -> boundary)
// neighbour lists read the other way round, so that a wall sample can sum over its fluid
// neighbours without atomics. Shared by the step (solver.cpp) and its adjoint (adjoint.cpp).
#pragma once

#include <cstdint>
#include <vector>

#include "core/types.h"
#include "particles/neighbor_lists.h"

namespace kinema::sph {

struct WallRows {
  Index begin = 0;                      // first boundary sample with a row
  std::vector<Index> start;             // (M - begin + 1,) row c = sample begin + c
  std::vector<std::int32_t> particle;   // the fluid rows i of each row's entries

  Index rows() const { return static_cast<Index>(start.size()) - 1; }
  Index size() const { return static_cast<Index>(particle.size()); }

  void clear() {
    start.assign(1, 0);
    particle.clear();
  }

  // Transposes the rows of samples [begin_, m) out of `lists` (n fluid rows), each row in the
  // order of the fluid rows (a serial counting sort: the same whatever the thread count; one
  // pass over the boundary entries, a few percent of a WCSPH step).
  void build(const NeighborLists& lists, Index n, Index begin_, Index m) {
    begin = begin_;
    const Index rows_count = m > begin ? m - begin : 0;
    start.assign(static_cast<size_t>(rows_count) + 1, 0);
    const std::int32_t* list = lists.list.data();
    for (Index i = 0; i < n; ++i)
      for (Index k = lists.start[i]; k < lists.start[i + 1]; ++k)
        if (list[k] >= begin) ++start[static_cast<size_t>(list[k] - begin) + 1];
    for (Index c = 0; c < rows_count; ++c) start[c + 1] += start[c];
    particle.resize(static_cast<size_t>(start[rows_count]));
    std::vector<Index>& cursor = cursor_;
    cursor.assign(start.begin(), start.end() - 1);
    for (Index i = 0; i < n; ++i)
      for (Index k = lists.start[i]; k < lists.start[i + 1]; ++k)
        if (list[k] >= begin) {
          particle[cursor[static_cast<size_t>(list[k] - begin)]++] = static_cast<std::int32_t>(i);
        }
  }

 private:
  std::vector<Index> cursor_;
};

}  // namespace kinema::sph
