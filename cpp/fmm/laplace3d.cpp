// The FMM passes over the adaptive octree: upward (P2M, M2M), downward (M2L from the V list
// as dense matrix products batched by offset, P2L from the X list, L2L), then per leaf L2P +
// M2P (W list) + P2P (U list); when the targets are the sources, the U-list P2P instead runs
// once per pair of adjacent leaves for both ends, in groups of leaves whose tasks write
// disjoint leaves. Every output is written by one task at a time, and each expansion and
// target receives its terms in a fixed order, so results are bitwise identical run to run
// and for any thread count.
#include "fmm/laplace3d.h"

#include <Eigen/Core>
#include <algorithm>
#include <cmath>
#include <memory>
#include <string>
#include <vector>

#include "core/errors.h"
#include "core/timer.h"
#include "fmm/kernels3d.h"
#include "fmm/block3d.h"
#include "fmm/m2l_product.h"
#include "fmm/rotation3d.h"
#include "fmm/tree.h"

namespace kinema::fmm3 {

namespace {

using fmm::Box3;
using fmm::Lists;
using fmm::Octree;
using ColMatrix = Eigen::Matrix<Scalar, Eigen::Dynamic, Eigen::Dynamic>;

constexpr int kOffsets = 343;
// From this order on the rotated M2L beats the dense products (bench/fmm/fmm3d_bench.py --m2l).
constexpr int kRotationOrder = 6;  // the 7^3 cube of same-level offsets, (dx+3)*49 + (dy+3)*7 + dz+3

// M2L matrices for the offsets with dx, dy, dz >= 0 only (56 of the 316): a reflection of the
// offset is a diagonal +-1 map on both expansions, A(d) = T A(|d|) T (Helgaker's harmonics:
// x -> -x maps I_lm to (-1)^m conj(I_lm), y -> -y to conj(I_lm), z -> -z to (-1)^(l+m) I_lm).
struct M2lOperators {
  M2lOperators(int p_, const std::vector<char>& used, bool rotate)
      : p(p_), n(coefficient_count(p_)), index(64, -1) {
    std::vector<int> wanted;
    for (int o = 0; o < kOffsets; ++o) {
      if (!used[static_cast<size_t>(o)]) continue;
      const int base = canonical(o);
      if (index[static_cast<size_t>(base)] < 0) {
        index[static_cast<size_t>(base)] = static_cast<int>(wanted.size());
        wanted.push_back(base);
      }
    }
    if (rotate) {
      rotated = std::make_unique<RotatedTranslation>(p, Translation::M2L, wanted);
      m2m = std::make_unique<RotatedTranslation>(p, Translation::M2M, std::vector<int>{RotatedTranslation::kDiagonal});
      l2l = std::make_unique<RotatedTranslation>(p, Translation::L2L, std::vector<int>{RotatedTranslation::kDiagonal});
    } else {
      build_dense(wanted);
    }
    // signs[pattern][k]: pattern bit 0/1/2 set when dx/dy/dz < 0.
    signs.assign(8, std::vector<Scalar>(static_cast<size_t>(n), 1.0));
    for (int pattern = 0; pattern < 8; ++pattern)
      for (int l = 0; l <= p; ++l)
        for (int m = 0; m <= l; ++m)
          for (int part = 0; part < (m == 0 ? 1 : 2); ++part) {  // part 1: imaginary
            Scalar s = 1;
            if (pattern & 1) s *= ((m & 1) ? -1 : 1) * (part ? -1 : 1);
            if (pattern & 2) s *= part ? -1 : 1;
            if (pattern & 4) s *= ((l + m) & 1) ? -1 : 1;
            const int k = l * l + (m == 0 ? 0 : 2 * m - 1 + part);
            signs[static_cast<size_t>(pattern)][static_cast<size_t>(k)] = s;
          }
  }
  void build_dense(const std::vector<int>& wanted) {
    matrices.resize(wanted.size() * static_cast<size_t>(n) * static_cast<size_t>(n));
    const int count = static_cast<int>(wanted.size());
#pragma omp parallel for schedule(dynamic, 1)
    for (int i = 0; i < count; ++i) {
      const int b = wanted[static_cast<size_t>(i)];
      const int d[3] = {b / 16, (b / 4) % 4, b % 4};
      m2l_matrix(p, d, &matrices[static_cast<size_t>(i) * n * n]);
    }
  }
  static int canonical(int o) {
    const int dx = o / 49 - 3, dy = (o / 7) % 7 - 3, dz = o % 7 - 3;
    return std::abs(dx) * 16 + std::abs(dy) * 4 + std::abs(dz);
  }
  // Order used for offset o: the expansions of boxes |d| widths apart converge as (sqrt3/|d|)^p
  // (radii sqrt3 h each, centres 2 h |d| apart), so the farther offsets reach the nearest
  // ones' (|d| = 2) accuracy with fewer terms: the order scaled by log(sqrt3/2)/log(sqrt3/|d|),
  // with a factor 3 of margin (the bound is loose at the nearest offsets).
  static int truncated_order(int o, int p) {
    const int dx = o / 49 - 3, dy = (o / 7) % 7 - 3, dz = o % 7 - 3;
    const Scalar d = std::sqrt(Scalar(dx * dx + dy * dy + dz * dz));
    const Scalar ratio = std::log(std::sqrt(3.0) / 2) / std::log(std::sqrt(3.0) / d);
    return std::clamp(static_cast<int>(std::ceil(3 * ratio * (p + 1))) - 1, std::min(p, 3), p);
  }
  static int pattern(int o) {
    return (o / 49 - 3 < 0) + 2 * ((o / 7) % 7 - 3 < 0) + 4 * (o % 7 - 3 < 0);
  }
  const Scalar* matrix(int offset) const {
    return &matrices[static_cast<size_t>(index[static_cast<size_t>(canonical(offset))]) * n * n];
  }
  int p, n;
  std::vector<int> index;
  std::vector<Scalar> matrices;          // dense operators (when not rotating)
  std::unique_ptr<RotatedTranslation> rotated, m2m, l2l;  // O(p^3) operators (when rotating)
  std::vector<std::vector<Scalar>> signs;
};

// Newton steps after the float reciprocal square root (relative error e0 <= 1.5 2^-12) of the
// near field: each squares it, e_{k+1} = 1.5 e_k^2, so one step leaves 2e-7 (6e-7 on 1/r^3),
// far below eps >= 1e-5 (the FMM's own error there is above 1e-6); two leave 6e-14, three
// reach rounding.
Index direct_below_for(int p) { return 2 * coefficient_count(p); }

int newton_steps(Scalar eps) { return eps >= 1e-5 ? 1 : eps >= 1e-9 ? 2 : 3; }

struct Engine {
  const Octree& tree;
  const Fmm3dConfig& config;
  int p, n, nc, width;
  const std::vector<Scalar>& q;  // tree order, n_sources x nc
  std::vector<Scalar> multipole, local;
  Scalar* mul(Index box, int c) { return &multipole[(static_cast<size_t>(box) * nc + c) * n]; }
  Scalar* loc(Index box, int c) { return &local[(static_cast<size_t>(box) * nc + c) * n]; }
  const Scalar* src[3];

  // Boxes with at most this many sources (W list) or targets (X list) meet the leaves across
  // the list directly: an expansion of order p costs ~(p+1)^2 complex terms per point.
  Index direct_below;
  bool direct_p2l(const Box3& box) const { return box.target_count() <= direct_below; }

  Engine(const Octree& t, const Fmm3dConfig& cfg, int order, int components, const std::vector<Scalar>& charges)
      : tree(t), config(cfg), p(order), n(coefficient_count(order)), nc(components),
        width(output_width(cfg.derivatives)), q(charges), direct_below(direct_below_for(order)) {
    multipole.assign(tree.boxes.size() * static_cast<size_t>(nc * n), 0.0);
    local.assign(multipole.size(), 0.0);
    for (int d = 0; d < 3; ++d) src[d] = tree.s[d].data();
  }

  void upward(const M2lOperators& ops, Interrupt& interrupt) {
    const bool rotate = ops.m2m != nullptr;
    constexpr Index kBlock = 1024;  // boxes between interrupt checks (P2M of ~1e5 points)
    for (size_t level = tree.levels.size(); level-- > 0;) {
      const std::vector<Index>& ids = tree.levels[level];
      const Index count = static_cast<Index>(ids.size());
      for (Index start = 0; start < count; start += kBlock) {
        interrupt.check();
        const Index stop = std::min(count, start + kBlock);
#pragma omp parallel for schedule(dynamic, 4)
        for (Index i = start; i < stop; ++i) {
          const Index id = ids[static_cast<size_t>(i)];
          const Box3& box = tree.boxes[static_cast<size_t>(id)];
          if (box.source_count() == 0) continue;
          for (int c = 0; c < nc; ++c) {
            if (box.leaf) {
              const Scalar* xyz[3] = {src[0] + box.src_begin, src[1] + box.src_begin, src[2] + box.src_begin};
              multipole_accumulate(p, box.c, box.h, xyz, &q[static_cast<size_t>(box.src_begin) * nc + c],
                                   box.source_count(), nc, mul(id, c));
              continue;
            }
            if (rotate) continue;
            for (Index ch : box.child) {
              if (ch < 0 || tree.boxes[static_cast<size_t>(ch)].source_count() == 0) continue;
              m2m(p, mul(ch, c), tree.boxes[static_cast<size_t>(ch)].c, box.c, box.h, mul(id, c));
            }
          }
        }
      }
      if (rotate) translate_children(ids, ops, true);
    }
  }

  // dst += scale T (T op (T src)) for the (dst box, src box) pairs of one offset, kColumns
  // expansions (pairs x components) at a time; T: the reflection signs mapping the offset to
  // its canonical one b. src and dst read and write multipoles or locals (M2L: multipoles to
  // locals, M2M: multipoles, L2L: locals). Each dst box appears once per call.
  void translate(const RotatedTranslation& op, int b, int pt, const Scalar* sign,
                 const std::vector<std::pair<Index, Index>>& list, bool from_multipoles,
                 bool to_multipoles, Scalar scale) {
    constexpr int K = RotatedTranslation::kColumns;
    const int ne = coefficient_count(pt);
    const Index columns = static_cast<Index>(list.size()) * nc, blocks = (columns + K - 1) / K;
#pragma omp parallel if (blocks > 1)
    {
      // Per thread: the buffers (~0.9 MB at p = 40) are reused from block to block.
      std::vector<Scalar> in(static_cast<size_t>(ne * K), 0.0), out(in.size()), scratch(op.scratch_size());
#pragma omp for schedule(dynamic, 4)
      for (Index bk = 0; bk < blocks; ++bk) {
        const Index begin = bk * K, end = std::min(columns, begin + K);
        if (end - begin < K) std::fill(in.begin(), in.end(), 0.0);
        const Scalar* from[K];
        Scalar* to[K];
        for (Index col = begin; col < end; ++col) {
          const std::pair<Index, Index>& pr = list[static_cast<size_t>(col / nc)];
          const int c = static_cast<int>(col % nc);
          from[col - begin] = from_multipoles ? mul(pr.second, c) : loc(pr.second, c);
          to[col - begin] = to_multipoles ? mul(pr.first, c) : loc(pr.first, c);
        }
        // Transposed in slices of kSlice coefficients, so that the slice of `in` or `out`
        // being written or read stays in the first-level cache.
        constexpr int kSlice = 32;
        const int used = static_cast<int>(end - begin);
        for (int k0 = 0; k0 < ne; k0 += kSlice) {
          const int k1 = std::min(ne, k0 + kSlice);
          for (int col = 0; col < used; ++col)
            for (int k = k0; k < k1; ++k) in[static_cast<size_t>(k * K + col)] = sign[k] * from[col][k];
        }
        op.apply(b, pt, in.data(), out.data(), scratch.data());
        for (int k0 = 0; k0 < ne; k0 += kSlice) {
          const int k1 = std::min(ne, k0 + kSlice);
          for (int col = 0; col < used; ++col)
            for (int k = k0; k < k1; ++k) to[col][k] += sign[k] * scale * out[static_cast<size_t>(k * K + col)];
        }
      }
    }
  }

  // M2M (upward) or L2L (downward) of one level by rotation, octant by octant.
  void translate_children(const std::vector<Index>& ids, const M2lOperators& ops, bool upward) {
    for (int q = 0; q < 8; ++q) {
      std::vector<std::pair<Index, Index>> list;
      for (Index id : ids) {
        const Box3& box = tree.boxes[static_cast<size_t>(id)];
        if (upward) {
          if (box.leaf || box.source_count() == 0) continue;
          const Index ch = box.child[static_cast<size_t>(q)];
          if (ch >= 0 && tree.boxes[static_cast<size_t>(ch)].source_count() > 0) list.push_back({id, ch});
        } else if (box.target_count() > 0 && box.parent > 0 &&
                   tree.boxes[static_cast<size_t>(box.parent)].child[static_cast<size_t>(q)] == id) {
          list.push_back({id, box.parent});
        }
      }
      if (list.empty()) continue;
      translate(upward ? *ops.m2m : *ops.l2l, RotatedTranslation::kDiagonal, p,
                ops.signs[static_cast<size_t>(~q & 7)].data(), list, upward, upward, 1.0);
    }
  }

  // All V-list interactions of one level, one offset at a time: C = A [M_s1 M_s2 ...] as a
  // matrix product, added to the targets' locals (each target has one source per offset).
  void m2l_level(const std::vector<Index>& ids, const M2lOperators& ops, Interrupt& interrupt) {
    std::vector<std::vector<std::pair<Index, Index>>> pairs(kOffsets);
    for (Index id : ids)
      for (const fmm::M2lEntry& e : tree.lists[static_cast<size_t>(id)].m2l)
        pairs[static_cast<size_t>(e.offset)].push_back({id, e.source});
    const Scalar inv_h = 1 / tree.boxes[static_cast<size_t>(ids.front())].h;
    constexpr Index kChunk = 32;
    for (int o = 0; o < kOffsets; ++o) {
      const auto& list = pairs[static_cast<size_t>(o)];
      if (list.empty()) continue;
      interrupt.check();
      const Scalar* a = ops.matrix(o);
      const int pattern = M2lOperators::pattern(o);
      const Scalar* sign = ops.signs[static_cast<size_t>(pattern)].data();
      const bool flip = pattern != 0;
      const Index count = static_cast<Index>(list.size());
      const Index chunks = (count + kChunk - 1) / kChunk;
      const int pt = M2lOperators::truncated_order(o, p);
      const int ne = coefficient_count(pt);
      if (ops.rotated) {
        translate(*ops.rotated, M2lOperators::canonical(o), pt, sign, list, true, false, inv_h);
        continue;
      }
#pragma omp parallel for schedule(dynamic, 1) if (chunks > 1)
      for (Index ck = 0; ck < chunks; ++ck) {
        const Index begin = ck * kChunk, end = std::min(count, begin + kChunk);
        ColMatrix b(ne, (end - begin) * nc), result(ne, (end - begin) * nc);
        for (Index i = begin; i < end; ++i)
          for (int c = 0; c < nc; ++c) {
            const Scalar* m = mul(list[static_cast<size_t>(i)].second, c);
            Scalar* col = b.col((i - begin) * nc + c).data();
            if (flip) for (int k = 0; k < ne; ++k) col[k] = sign[k] * m[k];
            else std::copy(m, m + ne, col);
          }
        m2l_product(a, n, ne, b.data(), static_cast<int>(b.cols()), result.data());
        for (Index i = begin; i < end; ++i)
          for (int c = 0; c < nc; ++c) {
            Scalar* l = loc(list[static_cast<size_t>(i)].first, c);
            const Scalar* r = result.col((i - begin) * nc + c).data();
            if (flip) for (int k = 0; k < ne; ++k) l[k] += sign[k] * inv_h * r[k];
            else for (int k = 0; k < ne; ++k) l[k] += inv_h * r[k];
          }
      }
    }
  }

  void downward(const M2lOperators& ops, Fmm3dStats& stats, Interrupt& interrupt) {
    for (size_t level = 1; level < tree.levels.size(); ++level) {
      interrupt.check();
      const std::vector<Index>& ids = tree.levels[level];
      const Index count = static_cast<Index>(ids.size());
      Stopwatch watch;
      m2l_level(ids, ops, interrupt);
      stats.seconds_m2l += watch.seconds();
      const bool rotate = ops.l2l != nullptr;
      if (rotate) translate_children(ids, ops, false);
#pragma omp parallel for schedule(dynamic, 8)
      for (Index i = 0; i < count; ++i) {
        const Index id = ids[static_cast<size_t>(i)];
        const Box3& box = tree.boxes[static_cast<size_t>(id)];
        if (box.target_count() == 0) continue;
        const Box3& parent = tree.boxes[static_cast<size_t>(box.parent)];
        const Lists& lists = tree.lists[static_cast<size_t>(id)];
        for (int c = 0; c < nc; ++c) {
          if (box.parent > 0 && !rotate) l2l(p, loc(box.parent, c), parent.c, parent.h, box.c, loc(id, c));
          if (direct_p2l(box)) continue;
          for (Index s : lists.p2l) {
            const Box3& sb = tree.boxes[static_cast<size_t>(s)];
            const Scalar* xyz[3] = {src[0] + sb.src_begin, src[1] + sb.src_begin, src[2] + sb.src_begin};
            p2l(p, box.c, box.h, xyz, &q[static_cast<size_t>(sb.src_begin) * nc + c],
                sb.source_count(), nc, loc(id, c));
          }
        }
      }
    }
  }

  // Derivative expansions of one expansion: index 0 the expansion itself, then d/dx, d/dy,
  // d/dz, then xx xy xz yy yz zz (orders shifted by one per derivative).
  template <bool Local>
  void derived(const Complex* base, std::vector<std::vector<Complex>>& out) const {
    out.resize(static_cast<size_t>(width));
    const int step = Local ? -1 : 1;
    out[0].assign(base, base + complex_count(p));
    if (width == 1) return;
    for (int a = 0; a < 3; ++a) {
      out[static_cast<size_t>(1 + a)].resize(static_cast<size_t>(complex_count(p + step)));
      if (Local) local_derivative(base, p, a, out[static_cast<size_t>(1 + a)].data());
      else multipole_derivative(base, p, a, out[static_cast<size_t>(1 + a)].data());
    }
    if (width == 4) return;
    const int first[6] = {0, 0, 0, 1, 1, 2}, second[6] = {0, 1, 2, 1, 2, 2};
    for (int k = 0; k < 6; ++k) {
      std::vector<Complex>& dst = out[static_cast<size_t>(4 + k)];
      dst.resize(static_cast<size_t>(complex_count(std::max(0, p + 2 * step))));
      const Complex* d1 = out[static_cast<size_t>(1 + first[k])].data();
      if (Local) {
        if (p >= 2) local_derivative(d1, p - 1, second[k], dst.data());
        else std::fill(dst.begin(), dst.end(), Complex(0));
      } else {
        multipole_derivative(d1, p + 1, second[k], dst.data());
      }
    }
  }

  // `self`: the targets are the sources (target t is source t in tree order: a smooth near
  // kernel leaves out that pair only). `mutual` (self only): the near field of adjacent leaves
  // is summed once per pair of leaves (near_mutual) instead of here. Returns the count of
  // coincident pairs the Laplace near field left out (p2p_generic).
  Index leaves(std::vector<Scalar>& result, bool self, bool mutual, Interrupt& interrupt) {
    const Index leaf_count = static_cast<Index>(tree.leaves.size());
    const bool fast = config.kernel != NearKernel::Gaussian && nc == 1 && width <= 4;
    const Scalar softening = config.kernel == NearKernel::Plummer ? config.length : 0.0;
    const int newton = newton_steps(config.eps);
    const Scalar* tgt[3] = {tree.t[0].data(), tree.t[1].data(), tree.t[2].data()};
    constexpr Index kBlock = 256;
    Index coincident = 0;
    for (Index start = 0; start < leaf_count; start += kBlock) {
      interrupt.check();
      const Index stop = std::min(leaf_count, start + kBlock);
#pragma omp parallel for schedule(dynamic, 1) reduction(+ : coincident)
      for (Index i = start; i < stop; ++i) {
        const Index id = tree.leaves[static_cast<size_t>(i)];
        const Box3& box = tree.boxes[static_cast<size_t>(id)];
        const Lists& lists = tree.lists[static_cast<size_t>(id)];
        const int extra = width == 1 ? 0 : width == 4 ? 1 : 2;
        std::vector<Index> small_w;  // source ranges of the W boxes summed directly
        if (mutual)
          for (Index w : lists.w_direct)
            small_w.insert(small_w.end(), {tree.boxes[static_cast<size_t>(w)].src_begin, tree.boxes[static_cast<size_t>(w)].src_end});
        std::vector<Index> ranges = mutual ? small_w : lists.p2p_ranges;
        // X lists of the leaf and its ancestors that are summed directly (direct_p2l).
        for (Index up = id; up > 0; up = tree.boxes[static_cast<size_t>(up)].parent) {
          if (!direct_p2l(tree.boxes[static_cast<size_t>(up)])) continue;
          for (Index s : tree.lists[static_cast<size_t>(up)].p2l)
            ranges.insert(ranges.end(), {tree.boxes[static_cast<size_t>(s)].src_begin, tree.boxes[static_cast<size_t>(s)].src_end});
        }
        std::vector<Complex> coeffs(static_cast<size_t>(complex_count(p)));
        std::vector<Complex> values(static_cast<size_t>(complex_count(p + extra)));
        std::vector<std::vector<Complex>> local_d;
        const Scalar inv_h = 1 / box.h;
        // L2P: output (c, k), a derivative of order d, is the derived local of order p - d
        // scaled by h^-d.
        LocalTable table(p, nc * width);
        for (int c = 0; c < nc; ++c) {
          to_complex(loc(id, c), p, coeffs.data());
          derived<true>(coeffs.data(), local_d);
          for (int k = 0; k < width; ++k) {
            const int d = k == 0 ? 0 : k < 4 ? 1 : 2;
            table.set(c * width + k, local_d[static_cast<size_t>(k)].data(), p - d, d == 0 ? 1 : d == 1 ? inv_h : inv_h * inv_h);
          }
        }
        // W list: derivative multipoles of each box, per component.
        std::vector<std::vector<std::vector<Complex>>> far_d(lists.m2p.size() * static_cast<size_t>(nc));
        for (size_t w = 0; w < lists.m2p.size(); ++w)
          for (int c = 0; c < nc; ++c) {
            to_complex(mul(lists.m2p[w], c), p, coeffs.data());
            derived<false>(coeffs.data(), far_d[w * nc + c]);
          }
        std::vector<Scalar> block(static_cast<size_t>(nc * width * kLanes));
        for (Index t = box.tgt_begin; t < box.tgt_end; ++t) {
          const Scalar x = tgt[0][t], y = tgt[1][t], z = tgt[2][t];
          Scalar* out = &result[static_cast<size_t>(t) * nc * width];
          const Index lane = (t - box.tgt_begin) % kLanes;
          if (lane == 0) {  // L2P of the next kLanes targets (the last block padded with t)
            Scalar u[3][kLanes];
            for (Index j = 0; j < kLanes; ++j) {
              const Index s = t + j < box.tgt_end ? t + j : t;
              for (int a = 0; a < 3; ++a) u[a][j] = (tgt[a][s] - box.c[a]) * inv_h;
            }
            local_evaluate(table, u[0], u[1], u[2], block.data());
          }
          for (int o = 0; o < nc * width; ++o) out[o] = block[static_cast<size_t>(o * kLanes + lane)];
          // M2P: (1/h) sum M I((x - c)/h), derivative of order d scales as h^-(d+1).
          for (size_t w = 0; w < lists.m2p.size(); ++w) {
            const Box3& sb = tree.boxes[static_cast<size_t>(lists.m2p[w])];
            const Scalar ih = 1 / sb.h;
            irregular((x - sb.c[0]) * ih, (y - sb.c[1]) * ih, (z - sb.c[2]) * ih, p + extra, values.data());
            for (int c = 0; c < nc; ++c)
              for (int k = 0; k < width; ++k) {
                const int d = k == 0 ? 0 : k < 4 ? 1 : 2;
                const Scalar scale = d == 0 ? ih : d == 1 ? ih * ih : ih * ih * ih;
                out[c * width + k] += scale * multipole_sum(far_d[w * nc + c][static_cast<size_t>(k)].data(), values.data(), p + d);
              }
          }
          // P2P: the near field with the near kernel.
          for (size_t r = 0; r < ranges.size(); r += 2) {
            const Index b = ranges[r], e = ranges[r + 1];
            const Index own = self && b <= t && t < e ? t - b : -1;
            if (fast && p2p_fast(width == 4, newton, softening, x, y, z, src[0] + b, src[1] + b,
                                 src[2] + b, &q[static_cast<size_t>(b)], e - b, out, own))
              continue;
            coincident += p2p_generic(config.kernel, config.length, width, x, y, z, src[0] + b, src[1] + b,
                                      src[2] + b, &q[static_cast<size_t>(b) * nc], nc, e - b, out, own);
          }
        }
      }
    }
    return coincident;
  }

  // Leaves grouped so that the tasks of one group write disjoint leaves: leaf A's task sums
  // the pairs of A with itself and with its adjacent leaves B > A, writing A and those B.
  // Greedy colouring in leaf order; every target then receives its terms group by group in a
  // fixed order, whatever the thread count.
  std::vector<std::vector<Index>> mutual_groups() const {
    std::vector<int> colour(tree.boxes.size(), -1);
    std::vector<Index> seen;  // seen[c] == a: colour c is taken by a task in conflict with a
    std::vector<std::vector<Index>> groups;
    for (Index a : tree.leaves) {
      for (Index x : tree.lists[static_cast<size_t>(a)].u) {
        if (x < a) continue;  // x in A's write set
        for (Index w : tree.lists[static_cast<size_t>(x)].u) {
          if (w > x) continue;  // w writes x
          const int c = colour[static_cast<size_t>(w)];
          if (c >= 0) seen[static_cast<size_t>(c)] = a;
        }
      }
      int c = 0;
      while (c < static_cast<int>(seen.size()) && seen[static_cast<size_t>(c)] == a) ++c;
      if (c == static_cast<int>(seen.size())) {
        seen.push_back(-1);
        groups.emplace_back();
      }
      colour[static_cast<size_t>(a)] = c;
      groups[static_cast<size_t>(c)].push_back(a);
    }
    return groups;
  }

  // The near field of adjacent leaves when the targets are the sources, each pair of leaves
  // visited once (p2p_mutual), A with itself by p2p_fast.
  Index near_mutual(std::vector<Scalar>& result, Interrupt& interrupt) {
    const Scalar softening = config.kernel == NearKernel::Plummer ? config.length : 0.0;
    const int newton = newton_steps(config.eps);
    const bool gradient = width == 4;
    constexpr Index kBlock = 256;  // tasks between interrupt checks
    Index coincident = 0;
    for (const std::vector<Index>& group : mutual_groups())
      for (Index start = 0; start < static_cast<Index>(group.size()); start += kBlock) {
        interrupt.check();
        const Index count = std::min(static_cast<Index>(group.size()), start + kBlock);
#pragma omp parallel for schedule(dynamic, 1) if (count - start > 1) reduction(+ : coincident)
        for (Index g = start; g < count; ++g) {
          const Index a = group[static_cast<size_t>(g)];
          const Box3& ab = tree.boxes[static_cast<size_t>(a)];
          const Index na = ab.source_count(), a0 = ab.src_begin;
          const Scalar* xa[3] = {src[0] + a0, src[1] + a0, src[2] + a0};
          for (Index t = a0; t < ab.src_end; ++t) {
            Scalar* out = &result[static_cast<size_t>(t) * width];
            if (!p2p_fast(gradient, newton, softening, src[0][t], src[1][t], src[2][t], xa[0], xa[1], xa[2],
                          &q[static_cast<size_t>(a0)], na, out, t - a0))
              coincident += p2p_generic(config.kernel, config.length, width, src[0][t], src[1][t], src[2][t],
                                        xa[0], xa[1], xa[2], &q[static_cast<size_t>(a0)], 1, na, out, t - a0);
          }
          std::vector<Scalar> out_a, out_b, xb[3], qb;
          for (Index b : tree.lists[static_cast<size_t>(a)].u) {
            if (b <= a) continue;
            const Box3& bb = tree.boxes[static_cast<size_t>(b)];
            const Index nb = bb.source_count(), b0 = bb.src_begin, stride = (nb + 3) & ~Index{3};
            // b padded to whole vectors with zero charges at its first point.
            for (int d = 0; d < 3; ++d) {
              xb[d].assign(src[d] + b0, src[d] + bb.src_end);
              xb[d].resize(static_cast<size_t>(stride), src[d][b0]);
            }
            qb.assign(q.begin() + b0, q.begin() + bb.src_end);
            qb.resize(static_cast<size_t>(stride), 0.0);
            out_a.assign(static_cast<size_t>(na * width), 0.0);
            out_b.assign(static_cast<size_t>(stride * width), 0.0);
            const Scalar* xbp[3] = {xb[0].data(), xb[1].data(), xb[2].data()};
            if (p2p_mutual(gradient, newton, softening, xa, &q[static_cast<size_t>(a0)], na, xbp,
                           qb.data(), stride, stride, out_a.data(), out_b.data())) {
              for (Index i = 0; i < na; ++i)
                for (int k = 0; k < width; ++k)
                  result[static_cast<size_t>((a0 + i) * width + k)] += out_a[static_cast<size_t>(i * width + k)];
              for (Index j = 0; j < nb; ++j)
                for (int k = 0; k < width; ++k)
                  result[static_cast<size_t>((b0 + j) * width + k)] += out_b[static_cast<size_t>(k * stride + j)];
              continue;
            }
            for (Index t = a0; t < ab.src_end; ++t)
              coincident += p2p_generic(config.kernel, config.length, width, src[0][t], src[1][t], src[2][t], src[0] + b0,
                          src[1] + b0, src[2] + b0, &q[static_cast<size_t>(b0)], 1, nb,
                          &result[static_cast<size_t>(t) * width]);
            for (Index t = b0; t < bb.src_end; ++t)
              coincident += p2p_generic(config.kernel, config.length, width, src[0][t], src[1][t], src[2][t], xa[0],
                          xa[1], xa[2], &q[static_cast<size_t>(a0)], 1, na, &result[static_cast<size_t>(t) * width]);
          }
        }
      }
    return coincident;
  }
};

}  // namespace

int order_for(Scalar eps) {
  // Measured at N = 6e3..2e4 with random-sign charges (the hardest case for phi): phi's
  // relative error is ~1.2e-3 at p = 4 (Plummer sphere) and falls by about 0.33 decades per
  // order up to p = 14, ~0.25 beyond.
  const Scalar digits = -std::log10(std::clamp(eps, 1e-15, 0.5));
  const Scalar p = digits <= 6 ? 5 + 3 * std::max(0.0, digits - 3) : 14 + 3.9 * (digits - 6);
  return std::clamp(static_cast<int>(std::ceil(p)), 3, kMaxOrder3d);
}

bool rotate_m2l(int order, const Fmm3dConfig& config) {
  if (config.m2l != M2lMethod::Auto) return config.m2l == M2lMethod::Rotation;
  return order >= kRotationOrder;
}

// With s points per leaf a target costs ~27 s / 2 near-field pairs (each pair once for both
// ends) and a leaf ~189 M2L translations: the work per point A s + B(p) / s is least at
// s* = sqrt(B / A). Measured on whole runs at N = 1e6 (uniform, the leaf level's occupancy set
// by root_scale_for, one thread, CPU seconds): the best s is ~60 at p = 5, 80..130 at p = 8,
// ~140 at p = 14 and >= 270 at p = 26 (12% cheaper than 180), each within 10% of the cost over
// a factor 1.5 of s; B grows about as (p + 1)^2 over this range (the rotated M2L's O(p^3)
// terms do not dominate yet), so s* ~ 10 (p + 1).
Scalar occupancy_for(int order) { return std::clamp(10.0 * (order + 1), 40.0, 400.0); }

// Boxes split above this count: sqrt(8) s*, at most 512, so that a box of an even region
// holding s* stays a leaf (its count's spread is ~sqrt(s*) < (512 - 400) / 4) while its parent,
// holding 8 s*, splits; in a graded region leaves hold up to the threshold.
Index leaf_size_for(int order) {
  return std::min<Index>(512, static_cast<Index>(std::ceil(std::sqrt(8.0) * occupancy_for(order))));
}

// The boxes of level L of a uniform tree hold n / 8^L points: only one level in eight
// multiples of the best occupancy s* is open to them. Enlarging the root by f in [1, 2)
// scales every box's count by f^3, so some level holds s* exactly. The counts are measured,
// not assumed: the point-weighted mean count of the cells of a coarse level L0 (the count a
// point sees in its own cell) is n0, and f^3 = s* 8^k / n0 for the k that puts it in [1, 8).
// Only evenly spread points are rescaled (the bench problem's leaves then hold s*).
Scalar root_scale_for(const Scalar* const sxyz[3], Index n, const Scalar* const txyz[3], Index m,
                      Scalar occupancy) {
  const Index most = std::max(n, m);
  if (most < 8 * occupancy) return 1;
  Scalar lo[3], hi[3], width = 0;
  for (int d = 0; d < 3; ++d) {
    lo[d] = INFINITY, hi[d] = -INFINITY;
    for (Index i = 0; i < n; ++i) lo[d] = std::min(lo[d], sxyz[d][i]), hi[d] = std::max(hi[d], sxyz[d][i]);
    for (Index i = 0; i < m; ++i) lo[d] = std::min(lo[d], txyz[d][i]), hi[d] = std::max(hi[d], txyz[d][i]);
    width = std::max(width, hi[d] - lo[d]);
  }
  if (!(width > 0) || !std::isfinite(width)) return 1;
  int level = 1;  // the finest level whose boxes hold >= s* points on average
  while (level < 7 && std::pow(8.0, level + 1) * occupancy <= most) ++level;
  const Index cells = Index{1} << level;
  const Scalar scale = cells / (width * (1 + 1e-12));
  Scalar n0 = 0;
  std::vector<Index> count(static_cast<size_t>(cells * cells * cells));
  for (int set = 0; set < 2; ++set) {
    const Scalar* const* xyz = set == 0 ? sxyz : txyz;
    const Index k = set == 0 ? n : m;
    if (k == 0 || (set == 1 && xyz == sxyz)) continue;
    std::fill(count.begin(), count.end(), 0);
    for (Index i = 0; i < k; ++i) {
      Index cell = 0;
      for (int d = 0; d < 3; ++d) {
        const Scalar mid = 0.5 * (lo[d] + hi[d]);
        const Index c = static_cast<Index>((xyz[d][i] - mid) * scale + 0.5 * cells);
        cell = cell * cells + std::clamp<Index>(c, 0, cells - 1);
      }
      ++count[static_cast<size_t>(cell)];
    }
    Scalar sum = 0;
    Index occupied = 0;
    for (Index c : count) sum += static_cast<Scalar>(c) * c, occupied += c > 0;
    // Clustered points (a point's cell holds far more than the occupied cells' mean) keep the
    // bounding cube: their leaves lie on many levels, and their trees are the ones the order
    // rule was measured on (a Plummer sphere's W-list error at p = 38 moved from 7e-14 to
    // 2e-12 with f = 1.25: the M2P's convergence ratio depends on where the levels fall).
    if (sum / k > 1.5 * static_cast<Scalar>(k) / static_cast<Scalar>(occupied)) return 1;
    n0 = std::max(n0, sum / k);
  }
  if (!(n0 > occupancy)) return 1;
  Scalar f3 = occupancy / n0;
  int leaf_level = level;
  for (; f3 < 1; f3 *= 8) ++leaf_level;
  // Leaves on level 1 are all adjacent (a direct sum): then the tree keeps its own depth.
  if (leaf_level < 2) return 1;
  return std::clamp(std::cbrt(f3), 1.0, 2.0);
}

Fmm3dStats fmm3d(const Scalar* sources, Index n, const Scalar* charges, int components,
                 const Scalar* targets, Index m, const Fmm3dConfig& config, Scalar* out,
                 Interrupt& interrupt) {
  if (!(config.eps > 0 && config.eps < 1))
    throw InvalidArgument("eps: expected a number in (0, 1), got " + format_real(config.eps));
  if (config.order < 0 || config.order > kMaxOrder3d)
    throw InvalidArgument("order: expected 0 (automatic) or 1.." + std::to_string(kMaxOrder3d) +
                          ", got " + std::to_string(config.order));
  if (config.leaf_size < 0) throw InvalidArgument("leaf_size: expected 0 (automatic) or a positive count");
  if (static_cast<int>(config.m2l) < 0 || static_cast<int>(config.m2l) > 2)
    throw InvalidArgument("m2l: expected auto, dense or rotation");
  if (config.derivatives < 0 || config.derivatives > 2)
    throw InvalidArgument("derivatives: expected 0, 1 or 2");
  if (components < 1 || components > 4)
    throw InvalidArgument("charges: expected 1 to 4 components, got " + std::to_string(components));
  if (config.kernel != NearKernel::Laplace && !(config.length > 0 && std::isfinite(config.length)))
    throw InvalidArgument("length: expected a positive softening or core length, got " + format_real(config.length));
  const bool self = targets == nullptr;
  if (self) {
    targets = sources;
    m = n;
  }
  Fmm3dStats stats;
  stats.order = config.order > 0 ? config.order : order_for(config.eps);
  stats.leaf_size = config.leaf_size > 0 ? config.leaf_size : leaf_size_for(stats.order);
  const int width = output_width(config.derivatives);
  if (m == 0) return stats;
  if (n == 0) {
    std::fill(out, out + m * components * width, 0.0);
    return stats;
  }

  Stopwatch watch;
  std::vector<Scalar> sxyz[3], txyz[3];
  for (int d = 0; d < 3; ++d) {
    sxyz[d].resize(static_cast<size_t>(n));
    txyz[d].resize(static_cast<size_t>(m));
    for (Index i = 0; i < n; ++i) sxyz[d][static_cast<size_t>(i)] = sources[3 * i + d];
    for (Index i = 0; i < m; ++i) txyz[d][static_cast<size_t>(i)] = targets[3 * i + d];
  }
  const Scalar* sp[3] = {sxyz[0].data(), sxyz[1].data(), sxyz[2].data()};
  const Scalar* tp[3] = {txyz[0].data(), txyz[1].data(), txyz[2].data()};
  const int p = stats.order;
  stats.root_scale = config.leaf_size > 0 ? 1 : root_scale_for(sp, n, tp, self ? 0 : m, occupancy_for(p));
  const Octree tree(sp, n, tp, m, stats.leaf_size, config.min_width, direct_below_for(p),
                    interrupt, stats.root_scale);
  std::vector<Scalar> q(static_cast<size_t>(n) * components);
  for (Index i = 0; i < n; ++i)
    for (int c = 0; c < components; ++c)
      q[static_cast<size_t>(i * components + c)] = charges[tree.src_perm[static_cast<size_t>(i)] * components + c];
  stats.box_count = static_cast<Index>(tree.boxes.size());
  stats.depth = static_cast<int>(tree.levels.size()) - 1;
  std::vector<char> used(kOffsets, 0);
  for (const Lists& l : tree.lists)
    for (const fmm::M2lEntry& e : l.m2l) used[static_cast<size_t>(e.offset)] = 1;
  stats.rotation = rotate_m2l(p, config);
  const M2lOperators ops(p, used, stats.rotation);
  stats.seconds_tree = watch.seconds();

  Engine engine(tree, config, p, components, q);
  watch.restart();
  engine.upward(ops, interrupt);
  stats.seconds_upward = watch.seconds();
  watch.restart();
  engine.downward(ops, stats, interrupt);
  stats.seconds_downward = watch.seconds() - stats.seconds_m2l;
  watch.restart();
  std::vector<Scalar> result(static_cast<size_t>(m) * components * width);
  // In the self case the two trees' orders coincide (the same points partitioned alike), so a
  // leaf's targets are its sources.
  const bool mutual = self && config.kernel != NearKernel::Gaussian && components == 1 &&
                      width <= 4 && p2p_mutual_available();
  stats.coincident = engine.leaves(result, self, mutual, interrupt);
  if (mutual) stats.coincident += engine.near_mutual(result, interrupt);
  stats.seconds_leaves = watch.seconds();

  const size_t row = static_cast<size_t>(components * width);
  for (Index t = 0; t < m; ++t)
    std::copy(&result[static_cast<size_t>(t) * row], &result[static_cast<size_t>(t) * row] + row,
              out + static_cast<size_t>(tree.tgt_perm[static_cast<size_t>(t)]) * row);
  return stats;
}

Index direct3d(const Scalar* sources, Index n, const Scalar* charges, int components,
               const Scalar* targets, Index m, const Fmm3dConfig& config, Scalar* out,
               Interrupt& interrupt) {
  const bool self = targets == nullptr;
  if (self) {
    targets = sources;
    m = n;
  }
  const int width = output_width(config.derivatives);
  std::vector<Scalar> xyz[3];
  for (int d = 0; d < 3; ++d) {
    xyz[d].resize(static_cast<size_t>(n));
    for (Index i = 0; i < n; ++i) xyz[d][static_cast<size_t>(i)] = sources[3 * i + d];
  }
  const Index block = std::max<Index>(16, (Index{1} << 22) / std::max<Index>(n, 1));
  Index coincident = 0;
  for (Index start = 0; start < m; start += block) {
    interrupt.check();
    const Index stop = std::min(m, start + block);
#pragma omp parallel for schedule(static) reduction(+ : coincident)
    for (Index t = start; t < stop; ++t) {
      Scalar* o = out + static_cast<size_t>(t) * components * width;
      std::fill(o, o + components * width, 0.0);
      coincident += p2p_generic(config.kernel, config.length, width, targets[3 * t], targets[3 * t + 1],
                  targets[3 * t + 2], xyz[0].data(), xyz[1].data(), xyz[2].data(), charges,
                  components, n, o, self ? t : -1);
    }
  }
  return coincident;
}

}  // namespace kinema::fmm3
