// Adaptive tree construction (level by level, the boxes of a level partitioned in parallel)
// and the U, V, W, X lists, built top-down from each box's "near" list: the same-level or
// coarser-leaf boxes adjacent to it. One template serves the quadtree and the octree.
#include "fmm/tree.h"

#include <algorithm>
#include <cmath>
#include <numeric>

namespace kinema::fmm {

namespace {

// Deeper than this, integer box coordinates would overflow; double coordinates stop splitting
// long before (a box narrower than a few ulps of its centre is not split).
constexpr int kMaxLevel = 60;

template <int D>
int orthant(const std::vector<Scalar>* xyz, Index i, const Scalar* c) {
  int k = 0;
  for (int d = 0; d < D; ++d) k += (xyz[d][static_cast<size_t>(i)] >= c[d]) << d;
  return k;
}

// Stable counting sort of [begin, end) of (perm, coordinates) by orthant; counts receives sizes.
template <int D>
void partition(Index begin, Index end, const Scalar* c, Index* perm, std::vector<Scalar>* xyz,
               Index* perm_tmp, std::vector<Scalar>* tmp, std::array<Index, (1 << D)>& counts) {
  counts.fill(0);
  for (Index i = begin; i < end; ++i) ++counts[static_cast<size_t>(orthant<D>(xyz, i, c))];
  std::array<Index, (1 << D)> at{};
  at[0] = begin;
  for (int q = 1; q < (1 << D); ++q) at[static_cast<size_t>(q)] = at[static_cast<size_t>(q - 1)] + counts[static_cast<size_t>(q - 1)];
  for (Index i = begin; i < end; ++i) {
    const Index k = at[static_cast<size_t>(orthant<D>(xyz, i, c))]++;
    perm_tmp[k] = perm[i];
    for (int d = 0; d < D; ++d) tmp[d][static_cast<size_t>(k)] = xyz[d][static_cast<size_t>(i)];
  }
  std::copy(perm_tmp + begin, perm_tmp + end, perm + begin);
  for (int d = 0; d < D; ++d) std::copy(tmp[d].begin() + begin, tmp[d].begin() + end, xyz[d].begin() + begin);
}

}  // namespace

template <int D>
Tree<D>::Tree(const Scalar* const sxyz[D], Index n, const Scalar* const txyz[D], Index m,
              Index leaf_size, Scalar min_width, Index p2p_below, Interrupt& interrupt,
              Scalar root_scale)
    : src_perm(static_cast<size_t>(n)), tgt_perm(static_cast<size_t>(m)) {
  for (int d = 0; d < D; ++d) {
    s[d].assign(sxyz[d], sxyz[d] + n);
    t[d].assign(txyz[d], txyz[d] + m);
  }
  std::iota(src_perm.begin(), src_perm.end(), Index{0});
  std::iota(tgt_perm.begin(), tgt_perm.end(), Index{0});
  build(leaf_size, min_width, root_scale, interrupt);
  build_lists(p2p_below, interrupt);
}

template <int D>
bool Tree<D>::adjacent(const Box& a, const Box& b) const {
  // Both boxes in units of the finer level; closed boxes that touch or overlap are adjacent.
  const int level = std::max(a.level, b.level);
  const int sa = level - a.level, sb = level - b.level;
  for (int d = 0; d < D; ++d) {
    const Index a0 = a.i[d] << sa, a1 = (a.i[d] + 1) << sa;
    const Index b0 = b.i[d] << sb, b1 = (b.i[d] + 1) << sb;
    if (!(a0 <= b1 && b0 <= a1)) return false;
  }
  return true;
}

template <int D>
void Tree<D>::build(Index leaf_size, Scalar min_width, Scalar root_scale, Interrupt& interrupt) {
  constexpr int kChildren = Box::kChildren;
  const Index n = static_cast<Index>(s[0].size()), m = static_cast<Index>(t[0].size());
  Box root;
  if (n + m > 0) {
    Scalar width = 0, scale = 0, extent[D];
    for (int d = 0; d < D; ++d) {
      Scalar lo = INFINITY, hi = -INFINITY;
      for (Scalar v : s[d]) lo = std::min(lo, v), hi = std::max(hi, v);
      for (Scalar v : t[d]) lo = std::min(lo, v), hi = std::max(hi, v);
      root.c[d] = 0.5 * (lo + hi);
      extent[d] = hi - lo;
      width = std::max(width, hi - lo);
      scale = std::max(scale, std::abs(root.c[d]));
    }
    // A margin keeps points on the far faces inside despite the rounding of the centre.
    root.h = 0.5 * width * (1 + 1e-12) * std::max<Scalar>(1, root_scale);
    // Along an axis where the points span at most half the root (a plane z = const in 3D, a
    // line in 2D), centred they would lie on the faces between the children at every level,
    // each box's points at its worst distance from its centre: a 3D plane's error then fell
    // ~0.16 decades per order instead of ~0.3 (3x the asked eps at 1e-10, 18x at 1e-12).
    // The root is shifted by h/3 there, so that they lie at 1/3 or 2/3 of every box (1/3 has
    // no finite binary expansion) and stay inside ([mid - h/2, mid + h/2] in [c - h, c + h]).
    for (int d = 0; d < D; ++d)
      if (extent[d] <= root.h) root.c[d] += root.h / 3;
    const Scalar floor = 1e-300 + 1e-15 * scale;
    if (!(root.h > floor)) root.h = std::max(floor, 1.0);
  } else {
    root.h = 1;
  }
  root.src_end = n;
  root.tgt_end = m;
  boxes.push_back(root);
  levels.push_back({0});

  // Scratch for the partitions; boxes of one level own disjoint ranges of each.
  std::vector<Index> src_tmp(static_cast<size_t>(n)), tgt_tmp(static_cast<size_t>(m));
  std::vector<Scalar> s_tmp[D], t_tmp[D];
  for (int d = 0; d < D; ++d) s_tmp[d].resize(src_tmp.size()), t_tmp[d].resize(tgt_tmp.size());
  for (int level = 0;; ++level) {
    interrupt.check();
    const std::vector<Index>& current = levels[static_cast<size_t>(level)];
    const Index count = static_cast<Index>(current.size());
    std::vector<std::array<Index, kChildren>> src_counts(current.size()), tgt_counts(current.size());
    std::vector<char> split(current.size(), 0);
#pragma omp parallel for schedule(dynamic, 1) if (count > 1)
    for (Index b = 0; b < count; ++b) {
      Box& box = boxes[static_cast<size_t>(current[static_cast<size_t>(b)])];
      if (box.source_count() <= leaf_size && box.target_count() <= leaf_size) continue;
      if (level >= kMaxLevel || box.h < min_width) continue;  // children would be narrower
      // Stop where halving the box no longer changes its centre's last bits.
      const Scalar quarter = 0.25 * box.h;
      bool resolvable = true;
      for (int d = 0; d < D; ++d) resolvable = resolvable && box.c[d] + quarter != box.c[d];
      if (!resolvable) continue;
      // Coincident points cannot be separated by any depth: keep them in one leaf.
      bool distinct = false;
      for (int d = 0; d < D && !distinct; ++d) {
        Scalar e0 = INFINITY, e1 = -INFINITY;
        for (Index i = box.src_begin; i < box.src_end; ++i) e0 = std::min(e0, s[d][static_cast<size_t>(i)]), e1 = std::max(e1, s[d][static_cast<size_t>(i)]);
        for (Index i = box.tgt_begin; i < box.tgt_end; ++i) e0 = std::min(e0, t[d][static_cast<size_t>(i)]), e1 = std::max(e1, t[d][static_cast<size_t>(i)]);
        distinct = e1 > e0;
      }
      if (!distinct) continue;
      split[static_cast<size_t>(b)] = 1;
      partition<D>(box.src_begin, box.src_end, box.c, src_perm.data(), s, src_tmp.data(), s_tmp,
                   src_counts[static_cast<size_t>(b)]);
      partition<D>(box.tgt_begin, box.tgt_end, box.c, tgt_perm.data(), t, tgt_tmp.data(), t_tmp,
                   tgt_counts[static_cast<size_t>(b)]);
    }
    std::vector<Index> next;
    for (Index b = 0; b < count; ++b) {
      if (!split[static_cast<size_t>(b)]) continue;
      const Index id = current[static_cast<size_t>(b)];
      Index src_at = boxes[static_cast<size_t>(id)].src_begin;
      Index tgt_at = boxes[static_cast<size_t>(id)].tgt_begin;
      boxes[static_cast<size_t>(id)].leaf = false;
      for (int q = 0; q < kChildren; ++q) {
        const Index ns = src_counts[static_cast<size_t>(b)][static_cast<size_t>(q)];
        const Index nt = tgt_counts[static_cast<size_t>(b)][static_cast<size_t>(q)];
        if (ns + nt == 0) continue;
        const Box& parent = boxes[static_cast<size_t>(id)];
        Box c;
        c.h = 0.5 * parent.h;
        for (int d = 0; d < D; ++d) {
          const int bit = (q >> d) & 1;
          c.c[d] = parent.c[d] + (bit ? c.h : -c.h);
          c.i[d] = 2 * parent.i[d] + bit;
        }
        c.level = level + 1;
        c.parent = id;
        c.src_begin = src_at;
        c.src_end = src_at + ns;
        c.tgt_begin = tgt_at;
        c.tgt_end = tgt_at + nt;
        src_at += ns;
        tgt_at += nt;
        const Index cid = static_cast<Index>(boxes.size());
        boxes[static_cast<size_t>(id)].child[static_cast<size_t>(q)] = cid;
        boxes.push_back(c);
        next.push_back(cid);
      }
    }
    if (next.empty()) break;
    levels.push_back(std::move(next));
  }
}

template <int D>
void Tree<D>::build_lists(Index p2p_below, Interrupt& interrupt) {
  lists.resize(boxes.size());
  std::vector<std::vector<Index>> near(boxes.size());
  if (boxes[0].source_count() > 0) near[0].push_back(0);
  for (size_t level = 0; level < levels.size(); ++level) {
    interrupt.check();
    const std::vector<Index>& current = levels[level];
    const Index count = static_cast<Index>(current.size());
#pragma omp parallel for schedule(dynamic, 16) if (count > 64)
    for (Index b = 0; b < count; ++b) {
      const Index id = current[static_cast<size_t>(b)];
      const Box& box = boxes[static_cast<size_t>(id)];
      if (box.target_count() == 0) continue;
      Lists& out = lists[static_cast<size_t>(id)];
      std::vector<Index>& mine = near[static_cast<size_t>(id)];
      auto consider = [&](Index e) {
        const Box& other = boxes[static_cast<size_t>(e)];
        if (other.source_count() == 0) return;
        if (adjacent(box, other)) {
          mine.push_back(e);
        } else if (other.level == box.level) {
          int offset = 0;
          for (int d = 0; d < D; ++d) offset = 7 * offset + static_cast<int>(box.i[d] - other.i[d]) + 3;
          out.m2l.push_back({e, offset});
        } else {
          out.p2l.push_back(e);  // a coarser leaf adjacent to the parent only
        }
      };
      if (box.parent >= 0) {
        for (Index d : near[static_cast<size_t>(box.parent)]) {
          const Box& other = boxes[static_cast<size_t>(d)];
          if (other.leaf) consider(d);
          else
            for (Index e : other.child)
              if (e >= 0) consider(e);
        }
      }
      if (!box.leaf) continue;
      // Leaf: adjacent leaves are summed directly; below adjacent non-leaves, the first boxes
      // that are not adjacent are evaluated from their multipoles (W list).
      std::vector<Index> stack;
      for (Index e : mine) {
        if (boxes[static_cast<size_t>(e)].leaf) out.u.push_back(e);
        else stack.push_back(e);
      }
      while (!stack.empty()) {
        const Box& other = boxes[static_cast<size_t>(stack.back())];
        stack.pop_back();
        for (Index f : other.child) {
          if (f < 0) continue;
          const Box& fb = boxes[static_cast<size_t>(f)];
          if (fb.source_count() == 0) continue;
          if (adjacent(box, fb)) {
            if (fb.leaf) out.u.push_back(f);
            else stack.push_back(f);
          } else if (fb.source_count() <= p2p_below) {
            out.w_direct.push_back(f);
          } else {
            out.m2p.push_back(f);
          }
        }
      }
      const auto by_memory = [&](Index a, Index c) {
        return boxes[static_cast<size_t>(a)].src_begin < boxes[static_cast<size_t>(c)].src_begin;
      };
      std::sort(out.u.begin(), out.u.end(), by_memory);
      std::sort(out.w_direct.begin(), out.w_direct.end(), by_memory);
      std::vector<Index> all(out.u.size() + out.w_direct.size());
      std::merge(out.u.begin(), out.u.end(), out.w_direct.begin(), out.w_direct.end(), all.begin(), by_memory);
      for (Index e : all) {
        const Box& eb = boxes[static_cast<size_t>(e)];
        if (!out.p2p_ranges.empty() && out.p2p_ranges.back() == eb.src_begin) out.p2p_ranges.back() = eb.src_end;
        else out.p2p_ranges.insert(out.p2p_ranges.end(), {eb.src_begin, eb.src_end});
      }
    }
    // Parents' near lists are no longer needed once their children have theirs.
    if (level > 0)
      for (Index id : levels[level - 1]) std::vector<Index>().swap(near[static_cast<size_t>(id)]);
  }
  for (size_t id = 0; id < boxes.size(); ++id)
    if (boxes[id].leaf && boxes[id].target_count() > 0) leaves.push_back(static_cast<Index>(id));
}

template struct Tree<2>;
template struct Tree<3>;

}  // namespace kinema::fmm
