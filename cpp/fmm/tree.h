// Adaptive 2^D-tree (quadtree D = 2, octree D = 3) over sources and targets with the
// interaction lists of the adaptive FMM (Carrier, Greengard & Rokhlin 1988, SIAM J. Sci. Stat.
// Comput. 9:669; in 3D Cheng, Greengard & Rokhlin 1999, J. Comput. Phys. 155:468):
//   U (leaf B): leaves adjacent to B                                            -> P2P
//   V (box B):  children of the parent's neighbours, not adjacent to B          -> M2L
//   W (leaf B): boxes below B's neighbours, not adjacent to B                   -> M2P
//   X (box B):  leaves not adjacent to B but adjacent to its parent (dual of W) -> P2L
// A box splits while it holds more than `leaf_size` sources or targets (and is wider than
// `min_width`), so clustered points get a deep tree only where they are (no level restriction
// is needed). Adjacency is decided on integer box coordinates, exactly, at any depth.
#pragma once

#include <array>
#include <vector>

#include "core/interrupt.h"
#include "core/types.h"

namespace kinema::fmm {

template <int D>
struct TreeBox {
  static constexpr int kChildren = 1 << D;
  Scalar c[D] = {};  // centre
  Scalar h = 0;      // half-width
  int level = 0;
  Index i[D] = {};  // integer position among the 2^level boxes per axis of its level
  Index parent = -1;
  std::array<Index, kChildren> child = filled();
  Index src_begin = 0, src_end = 0, tgt_begin = 0, tgt_end = 0;  // ranges in tree order
  bool leaf = true;
  Index source_count() const { return src_end - src_begin; }
  Index target_count() const { return tgt_end - tgt_begin; }

 private:
  static std::array<Index, kChildren> filled() {
    std::array<Index, kChildren> a{};
    a.fill(-1);
    return a;
  }
};

// One V-list entry: the source box and its offset in units of the box width, as an index
// into the 7^D cube of same-level offsets: sum_d (delta_d + 3) 7^(D-1-d) (target minus source).
struct M2lEntry {
  Index source;
  int offset;
};

// Interaction lists of one box (only boxes holding targets have them).
struct Lists {
  std::vector<M2lEntry> m2l;  // V
  std::vector<Index> p2l;     // X
  std::vector<Index> m2p;     // W
  // U list (and W boxes too small for a multipole to pay) as source ranges in tree order,
  // neighbours in memory merged (begin, end, begin, end, ...), so that direct sums run over
  // long contiguous loops.
  std::vector<Index> p2p_ranges;
  // The same boxes split: the adjacent leaves (B itself included) and the small W boxes, each
  // by ascending src_begin, for near fields that visit each pair of leaves once.
  std::vector<Index> u, w_direct;
};

template <int D>
struct Tree {
  using Box = TreeBox<D>;
  // points: n sources and m targets as D coordinate arrays; sorted copies and permutations
  // live in the tree. `p2p_below`: W boxes with at most this many sources are summed directly
  // (a multipole of order p costs ~p^(D-1) per target). `root_scale` >= 1: the root is the
  // points' bounding cube enlarged by this factor about its centre (which moves every level's
  // box width, so the leaves of evenly spread points can hold any count, not only n / 2^(D L)).
  Tree(const Scalar* const source_xyz[D], Index n, const Scalar* const target_xyz[D], Index m,
       Index leaf_size, Scalar min_width, Index p2p_below, Interrupt& interrupt,
       Scalar root_scale = 1);

  std::vector<Box> boxes;                  // boxes[0] is the root; children follow their level
  std::vector<std::vector<Index>> levels;  // box ids per level
  std::vector<Lists> lists;                // per box
  std::vector<Index> leaves;               // leaves holding targets
  std::vector<Index> src_perm, tgt_perm;   // tree order -> input index
  std::vector<Scalar> s[D], t[D];          // coordinates in tree order

  bool adjacent(const Box& a, const Box& b) const;

 private:
  void build(Index leaf_size, Scalar min_width, Scalar root_scale, Interrupt& interrupt);
  void build_lists(Index p2p_below, Interrupt& interrupt);
};

extern template struct Tree<2>;
extern template struct Tree<3>;

using Quadtree = Tree<2>;
using Octree = Tree<3>;
using Box = TreeBox<2>;
using Box3 = TreeBox<3>;

}  // namespace kinema::fmm
