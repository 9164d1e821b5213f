// Adaptive quadtree over sources and targets with the interaction lists of the adaptive FMM
// (Carrier, Greengard & Rokhlin 1988, SIAM J. Sci. Stat. Comput. 9:669):
//   U (leaf B): leaves adjacent to B                        -> direct sum (P2P)
//   V (box B):  children of the parent's neighbours, not adjacent to B  -> M2L
//   W (leaf B): boxes below B's neighbours, not adjacent to B but with an adjacent parent -> M2P
//   X (box B):  leaves not adjacent to B but adjacent to its parent (dual of W)  -> P2L
// A box splits while it holds more than `leaf_size` sources or targets, so clustered points
// get a deep tree where they are and a shallow one elsewhere (no level restriction needed).
// Adjacency is decided on integer box coordinates, exactly, at any depth.
#pragma once

#include <array>
#include <vector>

#include "core/interrupt.h"
#include "core/types.h"

namespace kinema::fmm {

struct Box {
  Scalar cx = 0, cy = 0, h = 0;  // centre and half-width
  int level = 0;
  Index ix = 0, iy = 0;  // integer position among the 2^level x 2^level boxes of its level
  Index parent = -1;
  std::array<Index, 4> child{-1, -1, -1, -1};
  Index src_begin = 0, src_end = 0, tgt_begin = 0, tgt_end = 0;  // ranges in tree order
  bool leaf = true;
  Index source_count() const { return src_end - src_begin; }
  Index target_count() const { return tgt_end - tgt_begin; }
};

// Interaction lists of one box (only boxes holding targets have them).
struct Lists {
  std::vector<Index> m2l;  // V
  std::vector<Index> p2l;  // X
  std::vector<Index> p2p;  // U, and W boxes too small for a multipole to pay
  // The sources of the p2p boxes as ranges in tree order, neighbours in memory merged
  // (begin, end, begin, end, ...), so that direct sums run over long contiguous loops.
  std::vector<Index> p2p_ranges;
  std::vector<Index> m2p;  // W
};

struct Quadtree {
  // Builds the tree of the points (sx, sy) (n sources) and (tx, ty) (m targets); the sorted
  // copies and the permutations live in the tree. `p2p_below`: W-list boxes with at most this
  // many sources are summed directly instead (a multipole of order p costs ~p per target).
  Quadtree(const Scalar* sx, const Scalar* sy, Index n, const Scalar* tx, const Scalar* ty,
           Index m, Index leaf_size, Index p2p_below, Interrupt& interrupt);

  std::vector<Box> boxes;                 // boxes[0] is the root; children follow their level
  std::vector<std::vector<Index>> levels;  // box ids per level
  std::vector<Lists> lists;               // per box
  std::vector<Index> leaves;              // leaves holding targets
  std::vector<Index> src_perm, tgt_perm;  // tree order -> input index
  std::vector<Scalar> sx, sy, tx, ty;     // coordinates in tree order

  bool adjacent(const Box& a, const Box& b) const;

 private:
  void build(Index leaf_size, Interrupt& interrupt);
  void build_lists(Index p2p_below, Interrupt& interrupt);
};

}  // namespace kinema::fmm
