// Adaptive octree over sources and targets with the interaction lists of the adaptive FMM
// (Carrier, Greengard & Rokhlin 1988; in 3D Cheng, Greengard & Rokhlin 1999, J. Comput. Phys.
// 155:468):
//   U (leaf B): leaves adjacent to B                                         -> P2P
//   V (box B):  children of the parent's neighbours, not adjacent to B       -> M2L
//   W (leaf B): boxes below B's neighbours, not adjacent to B               -> M2P
//   X (box B):  leaves not adjacent to B but adjacent to its parent (dual of W) -> P2L
// A box splits while it holds more than `leaf_size` sources or targets (and is wider than
// `min_width`), so clustered points get a deep tree only where they are. Adjacency is decided
// on integer box coordinates, exactly, at any depth.
#pragma once

#include <array>
#include <cstdint>
#include <vector>

#include "core/interrupt.h"
#include "core/types.h"

namespace kinema::fmm {

struct Box3 {
  Scalar c[3] = {0, 0, 0};  // centre
  Scalar h = 0;             // half-width
  int level = 0;
  Index i[3] = {0, 0, 0};  // integer position among the 2^level boxes per axis of its level
  Index parent = -1;
  std::array<Index, 8> child{-1, -1, -1, -1, -1, -1, -1, -1};
  Index src_begin = 0, src_end = 0, tgt_begin = 0, tgt_end = 0;  // ranges in tree order
  bool leaf = true;
  Index source_count() const { return src_end - src_begin; }
  Index target_count() const { return tgt_end - tgt_begin; }
};

// One V-list entry: the source box and its offset (index into the 7^3 cube of offsets
// (dx + 3) * 49 + (dy + 3) * 7 + (dz + 3), in units of the box width).
struct M2lEntry {
  Index source;
  int offset;
};

struct Lists3 {
  std::vector<M2lEntry> m2l;  // V
  std::vector<Index> p2l;     // X
  std::vector<Index> m2p;     // W
  // U list (and W boxes too small for a multipole to pay) as source ranges in tree order,
  // neighbours in memory merged: begin, end, begin, end, ...
  std::vector<Index> p2p_ranges;
};

struct Octree {
  // points: n sources and m targets as x, y, z arrays; sorted copies and permutations live in
  // the tree. `p2p_below`: W boxes with at most this many sources are summed directly.
  Octree(const Scalar* const source_xyz[3], Index n, const Scalar* const target_xyz[3], Index m,
         Index leaf_size, Scalar min_width, Index p2p_below, Interrupt& interrupt);

  std::vector<Box3> boxes;                 // boxes[0] is the root
  std::vector<std::vector<Index>> levels;  // box ids per level
  std::vector<Lists3> lists;               // per box
  std::vector<Index> leaves;               // leaves holding targets
  std::vector<Index> src_perm, tgt_perm;   // tree order -> input index
  std::vector<Scalar> s[3], t[3];          // coordinates in tree order

  bool adjacent(const Box3& a, const Box3& b) const;

 private:
  void build(Index leaf_size, Scalar min_width, Interrupt& interrupt);
  void build_lists(Index p2p_below, Interrupt& interrupt);
};

}  // namespace kinema::fmm
