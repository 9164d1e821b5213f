// Adaptive quadtree construction (level by level, boxes of a level partitioned in parallel)
// and the U, V, W, X lists of Carrier, Greengard & Rokhlin 1988, built top-down from each
// box's "near" list: the same-level or coarser-leaf boxes adjacent to it.
#include "fmm/quadtree.h"

#include <algorithm>
#include <numeric>

namespace kinema::fmm {

namespace {

// Deeper than this, integer box coordinates would overflow; double coordinates stop splitting
// long before (a box narrower than a few ulps of its centre is not split).
constexpr int kMaxLevel = 60;

int quadrant(Scalar x, Scalar y, Scalar cx, Scalar cy) { return (x >= cx) + 2 * (y >= cy); }

// Stable counting sort of [begin, end) of (perm, x, y) by quadrant; counts[q] receives sizes.
void partition(Index begin, Index end, Scalar cx, Scalar cy, Index* perm, Scalar* x, Scalar* y,
               Index* perm_tmp, Scalar* x_tmp, Scalar* y_tmp, std::array<Index, 4>& counts) {
  counts = {0, 0, 0, 0};
  for (Index i = begin; i < end; ++i) ++counts[quadrant(x[i], y[i], cx, cy)];
  std::array<Index, 4> at{begin, 0, 0, 0};
  for (int q = 1; q < 4; ++q) at[q] = at[q - 1] + counts[q - 1];
  for (Index i = begin; i < end; ++i) {
    const Index k = at[quadrant(x[i], y[i], cx, cy)]++;
    perm_tmp[k] = perm[i];
    x_tmp[k] = x[i];
    y_tmp[k] = y[i];
  }
  std::copy(perm_tmp + begin, perm_tmp + end, perm + begin);
  std::copy(x_tmp + begin, x_tmp + end, x + begin);
  std::copy(y_tmp + begin, y_tmp + end, y + begin);
}

}  // namespace

Quadtree::Quadtree(const Scalar* sx_, const Scalar* sy_, Index n, const Scalar* tx_,
                   const Scalar* ty_, Index m, Index leaf_size, Index p2p_below,
                   Interrupt& interrupt)
    : src_perm(n), tgt_perm(m), sx(sx_, sx_ + n), sy(sy_, sy_ + n), tx(tx_, tx_ + m),
      ty(ty_, ty_ + m) {
  std::iota(src_perm.begin(), src_perm.end(), Index{0});
  std::iota(tgt_perm.begin(), tgt_perm.end(), Index{0});
  build(leaf_size, interrupt);
  build_lists(p2p_below, interrupt);
}

bool Quadtree::adjacent(const Box& a, const Box& b) const {
  // Both boxes in units of the finer level; closed boxes that touch or overlap are adjacent.
  const int level = std::max(a.level, b.level);
  const int sa = level - a.level, sb = level - b.level;
  const Index ax0 = a.ix << sa, ax1 = (a.ix + 1) << sa, ay0 = a.iy << sa, ay1 = (a.iy + 1) << sa;
  const Index bx0 = b.ix << sb, bx1 = (b.ix + 1) << sb, by0 = b.iy << sb, by1 = (b.iy + 1) << sb;
  return ax0 <= bx1 && bx0 <= ax1 && ay0 <= by1 && by0 <= ay1;
}

void Quadtree::build(Index leaf_size, Interrupt& interrupt) {
  const Index n = static_cast<Index>(sx.size()), m = static_cast<Index>(tx.size());
  Scalar lo_x = INFINITY, lo_y = INFINITY, hi_x = -INFINITY, hi_y = -INFINITY;
  for (Index i = 0; i < n; ++i) {
    lo_x = std::min(lo_x, sx[i]), hi_x = std::max(hi_x, sx[i]);
    lo_y = std::min(lo_y, sy[i]), hi_y = std::max(hi_y, sy[i]);
  }
  for (Index i = 0; i < m; ++i) {
    lo_x = std::min(lo_x, tx[i]), hi_x = std::max(hi_x, tx[i]);
    lo_y = std::min(lo_y, ty[i]), hi_y = std::max(hi_y, ty[i]);
  }
  Box root;
  if (n + m > 0) {
    root.cx = 0.5 * (lo_x + hi_x);
    root.cy = 0.5 * (lo_y + hi_y);
    // A margin keeps points on the far edges inside despite the rounding of the centre.
    root.h = 0.5 * std::max(hi_x - lo_x, hi_y - lo_y) * (1 + 1e-12);
    const Scalar floor = 1e-300 + 1e-15 * std::max(std::abs(root.cx), std::abs(root.cy));
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
  std::vector<Scalar> sx_tmp(src_tmp.size()), sy_tmp(src_tmp.size());
  std::vector<Scalar> tx_tmp(tgt_tmp.size()), ty_tmp(tgt_tmp.size());
  for (int level = 0;; ++level) {
    interrupt.check();
    const std::vector<Index>& current = levels[static_cast<size_t>(level)];
    const Index count = static_cast<Index>(current.size());
    std::vector<std::array<Index, 4>> src_counts(current.size()), tgt_counts(current.size());
    std::vector<char> split(current.size(), 0);
#pragma omp parallel for schedule(dynamic, 1) if (count > 1)
    for (Index b = 0; b < count; ++b) {
      Box& box = boxes[static_cast<size_t>(current[static_cast<size_t>(b)])];
      if (box.source_count() <= leaf_size && box.target_count() <= leaf_size) continue;
      if (level >= kMaxLevel) continue;
      // Stop where halving the box no longer changes its centre's last bits.
      const Scalar quarter = 0.25 * box.h;
      if (box.cx + quarter == box.cx || box.cy + quarter == box.cy) continue;
      // Coincident points cannot be separated by any depth: keep them in one leaf.
      Scalar ex0 = INFINITY, ex1 = -INFINITY, ey0 = INFINITY, ey1 = -INFINITY;
      for (Index i = box.src_begin; i < box.src_end; ++i) {
        ex0 = std::min(ex0, sx[i]), ex1 = std::max(ex1, sx[i]);
        ey0 = std::min(ey0, sy[i]), ey1 = std::max(ey1, sy[i]);
      }
      for (Index i = box.tgt_begin; i < box.tgt_end; ++i) {
        ex0 = std::min(ex0, tx[i]), ex1 = std::max(ex1, tx[i]);
        ey0 = std::min(ey0, ty[i]), ey1 = std::max(ey1, ty[i]);
      }
      if (ex1 <= ex0 && ey1 <= ey0) continue;
      split[static_cast<size_t>(b)] = 1;
      partition(box.src_begin, box.src_end, box.cx, box.cy, src_perm.data(), sx.data(),
                sy.data(), src_tmp.data(), sx_tmp.data(), sy_tmp.data(),
                src_counts[static_cast<size_t>(b)]);
      partition(box.tgt_begin, box.tgt_end, box.cx, box.cy, tgt_perm.data(), tx.data(),
                ty.data(), tgt_tmp.data(), tx_tmp.data(), ty_tmp.data(),
                tgt_counts[static_cast<size_t>(b)]);
    }
    std::vector<Index> next;
    for (Index b = 0; b < count; ++b) {
      if (!split[static_cast<size_t>(b)]) continue;
      const Index id = current[static_cast<size_t>(b)];
      Index src_at = boxes[static_cast<size_t>(id)].src_begin;
      Index tgt_at = boxes[static_cast<size_t>(id)].tgt_begin;
      boxes[static_cast<size_t>(id)].leaf = false;
      for (int q = 0; q < 4; ++q) {
        const Index ns = src_counts[static_cast<size_t>(b)][q];
        const Index nt = tgt_counts[static_cast<size_t>(b)][q];
        if (ns + nt == 0) continue;
        const Box& parent = boxes[static_cast<size_t>(id)];
        Box c;
        c.h = 0.5 * parent.h;
        c.cx = parent.cx + ((q & 1) ? c.h : -c.h);
        c.cy = parent.cy + ((q & 2) ? c.h : -c.h);
        c.level = level + 1;
        c.ix = 2 * parent.ix + (q & 1);
        c.iy = 2 * parent.iy + ((q >> 1) & 1);
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

void Quadtree::build_lists(Index p2p_below, Interrupt& interrupt) {
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
        if (adjacent(box, other)) mine.push_back(e);
        else if (other.level == box.level) out.m2l.push_back(e);
        else out.p2l.push_back(e);  // a coarser leaf adjacent to the parent only
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
        if (boxes[static_cast<size_t>(e)].leaf) out.p2p.push_back(e);
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
            if (fb.leaf) out.p2p.push_back(f);
            else stack.push_back(f);
          } else if (fb.source_count() <= p2p_below) {
            out.p2p.push_back(f);
          } else {
            out.m2p.push_back(f);
          }
        }
      }
      std::sort(out.p2p.begin(), out.p2p.end(), [&](Index a, Index b) {
        return boxes[static_cast<size_t>(a)].src_begin < boxes[static_cast<size_t>(b)].src_begin;
      });
      for (Index e : out.p2p) {
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

}  // namespace kinema::fmm
