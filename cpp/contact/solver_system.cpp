// The contact solver's Newton matrix on a kept block pattern (solver_system.h).
#include "contact/solver_system.h"

#include <Eigen/OrderingMethods>
#include <Eigen/SparseCore>
#include <algorithm>
#include <stdexcept>

namespace kinema::contact {

NewtonSystem::NewtonSystem(const Model& model) {
  const Index n = model.vertex_count;
  dof_.assign(static_cast<size_t>(n), -1);
  for (Index v = 0; v < n; ++v)
    if (!model.fixed[static_cast<size_t>(v)] || model.driven[static_cast<size_t>(v)]) {
      dof_[static_cast<size_t>(v)] = static_cast<Index>(vertex_of_.size());
      vertex_of_.push_back(v);
    }
  std::vector<std::pair<Index, Index>> blocks;
  for (Index d = 0; d < dof_count(); ++d) blocks.emplace_back(d, d);
  auto element = [&](const Index* verts, int count) {
    for (int a = 0; a < count; ++a)
      for (int b = 0; b < count; ++b) {
        const Index i = dof(verts[a]), j = dof(verts[b]);
        if (i >= 0 && j >= 0) blocks.emplace_back(i, j);
      }
  };
  for (size_t t = 0; t < model.tets.size(); t += 4) element(&model.tets[t], 4);
  for (size_t s = 0; s < model.springs.size(); s += 2) element(&model.springs[s], 2);
  // Dofs numbered in the approximate-minimum-degree order of the elastic pattern (vertex
  // graph): the factorisation runs in this fixed order whatever contact blocks are reserved,
  // so its values do not depend on the pattern's history (reserved blocks are exact zeros) and
  // a restored state continues bit for bit.
  const Index nd = dof_count();
  {
    std::vector<Eigen::Triplet<Scalar, Index>> t;
    for (const auto& [i, j] : blocks) t.emplace_back(i, j, 1);
    Eigen::SparseMatrix<Scalar, Eigen::ColMajor, Index> graph(nd, nd);
    graph.setFromTriplets(t.begin(), t.end());
    Eigen::PermutationMatrix<Eigen::Dynamic, Eigen::Dynamic, Index> order;  // new -> old
    Eigen::AMDOrdering<Index>()(graph, order);
    std::vector<Index> renumber(static_cast<size_t>(nd));
    const std::vector<Index> old_vertex = vertex_of_;
    for (Index k = 0; k < nd; ++k) {
      const Index old = order.indices()[k];
      renumber[static_cast<size_t>(old)] = k;
      vertex_of_[static_cast<size_t>(k)] = old_vertex[static_cast<size_t>(old)];
      dof_[static_cast<size_t>(vertex_of_[static_cast<size_t>(k)])] = k;
    }
    for (auto& [i, j] : blocks) i = renumber[static_cast<size_t>(i)], j = renumber[static_cast<size_t>(j)];
  }
  std::sort(blocks.begin(), blocks.end());
  blocks.erase(std::unique(blocks.begin(), blocks.end()), blocks.end());
  elastic_ = blocks;
  rebuild(blocks);
}

Index NewtonSystem::find(Index i, Index j) const {
  const auto first = bcol_.begin() + bptr_[static_cast<size_t>(i)];
  const auto last = bcol_.begin() + bptr_[static_cast<size_t>(i) + 1];
  const auto it = std::lower_bound(first, last, j);
  return it != last && *it == j ? static_cast<Index>(it - bcol_.begin()) : -1;
}

void NewtonSystem::slots(const Index* verts, int count, Slot* out) const {
  for (int a = 0; a < count; ++a)
    for (int b = 0; b < count; ++b) {
      Slot& slot = out[a * count + b];
      const Index i = dof(verts[a]), j = dof(verts[b]);
      if (i < 0 || j < 0) {
        slot = Slot{};
        continue;
      }
      const Index k = find(i, j);
      if (k < 0) throw std::logic_error("NewtonSystem::slots: a block outside the pattern");
      const Index start = bptr_[static_cast<size_t>(i)], len = bptr_[static_cast<size_t>(i) + 1] - start;
      slot = Slot{9 * start + 3 * (k - start), 3 * len};
    }
}

void NewtonSystem::add_block(Index i, Index j, const Scalar* m) {
  const Index k = find(i, j);
  if (k < 0) {
    missing_.emplace_back(i, j);
    missing_values_.insert(missing_values_.end(), m, m + 9);
    return;
  }
  const Index start = bptr_[static_cast<size_t>(i)], len = bptr_[static_cast<size_t>(i) + 1] - start;
  Scalar* out = values_.data() + 9 * start + 3 * (k - start);
  for (int r = 0; r < 3; ++r)
    for (int s = 0; s < 3; ++s) out[r * 3 * len + s] += m[3 * r + s];
}

void NewtonSystem::rebuild(const std::vector<std::pair<Index, Index>>& blocks) {
  const Index rows = dof_count();
  ++layout_;
  // Old pattern and values, to carry over.
  const std::vector<Index> old_ptr = std::move(bptr_), old_col = std::move(bcol_);
  const std::vector<Scalar> old_values = std::move(values_);
  bptr_.assign(static_cast<size_t>(rows) + 1, 0);
  bcol_.resize(blocks.size());
  for (size_t k = 0; k < blocks.size(); ++k) {
    ++bptr_[static_cast<size_t>(blocks[k].first) + 1];
    bcol_[k] = blocks[k].second;
  }
  for (Index i = 0; i < rows; ++i) bptr_[static_cast<size_t>(i) + 1] += bptr_[static_cast<size_t>(i)];
  values_.assign(9 * blocks.size(), 0);
  row_ptr_.resize(static_cast<size_t>(3 * rows) + 1);
  col_.resize(9 * blocks.size());
  row_ptr_[0] = 0;
  for (Index i = 0; i < rows; ++i) {
    const Index start = bptr_[static_cast<size_t>(i)], len = bptr_[static_cast<size_t>(i) + 1] - start;
    for (int r = 0; r < 3; ++r) {
      row_ptr_[static_cast<size_t>(3 * i + r) + 1] = 9 * start + (r + 1) * 3 * len;
      for (Index k = 0; k < len; ++k)
        for (int s = 0; s < 3; ++s)
          col_[static_cast<size_t>(9 * start + r * 3 * len + 3 * k + s)] = 3 * bcol_[static_cast<size_t>(start + k)] + s;
    }
  }
  if (old_ptr.empty()) return;
  for (Index i = 0; i < rows; ++i) {
    const Index os = old_ptr[static_cast<size_t>(i)], olen = old_ptr[static_cast<size_t>(i) + 1] - os;
    const Index ns = bptr_[static_cast<size_t>(i)], nlen = bptr_[static_cast<size_t>(i) + 1] - ns;
    for (Index k = os; k < os + olen; ++k) {
      const Index slot = find(i, old_col[static_cast<size_t>(k)]);
      if (slot < 0) continue;  // dropped
      for (int r = 0; r < 3; ++r)
        for (int s = 0; s < 3; ++s)
          values_[static_cast<size_t>(9 * ns + r * 3 * nlen + 3 * (slot - ns) + s)] =
              old_values[static_cast<size_t>(9 * os + r * 3 * olen + 3 * (k - os) + s)];
    }
  }
}

void NewtonSystem::begin_step(const std::vector<std::vector<Index>>& stencils) {
  std::vector<std::pair<Index, Index>> blocks = elastic_;
  for (const std::vector<Index>& v : stencils)
    for (Index a : v)
      for (Index b : v) {
        const Index i = dof(a), j = dof(b);
        if (i >= 0 && j >= 0 && i != j) blocks.emplace_back(i, j);
      }
  std::sort(blocks.begin(), blocks.end());
  blocks.erase(std::unique(blocks.begin(), blocks.end()), blocks.end());
  // Unchanged when the current pattern is exactly these blocks.
  bool same = static_cast<Index>(blocks.size()) == block_count();
  for (Index i = 0; same && i < dof_count(); ++i)
    for (Index k = bptr_[static_cast<size_t>(i)]; same && k < bptr_[static_cast<size_t>(i) + 1]; ++k)
      same = blocks[static_cast<size_t>(k)] == std::make_pair(i, bcol_[static_cast<size_t>(k)]);
  if (same) return;
  rebuild(blocks);
  changed_ = true;
}

void NewtonSystem::clear() {
  std::fill(values_.begin(), values_.end(), Scalar(0));
  missing_.clear();
  missing_values_.clear();
}

bool NewtonSystem::finish() {
  if (!missing_.empty()) {
    std::vector<std::pair<Index, Index>> blocks;
    blocks.reserve(bcol_.size() + missing_.size());
    for (Index i = 0; i < dof_count(); ++i)
      for (Index k = bptr_[static_cast<size_t>(i)]; k < bptr_[static_cast<size_t>(i) + 1]; ++k)
        blocks.emplace_back(i, bcol_[static_cast<size_t>(k)]);
    blocks.insert(blocks.end(), missing_.begin(), missing_.end());
    std::sort(blocks.begin(), blocks.end());
    blocks.erase(std::unique(blocks.begin(), blocks.end()), blocks.end());
    const std::vector<std::pair<Index, Index>> missing = std::move(missing_);
    const std::vector<Scalar> values = std::move(missing_values_);
    missing_.clear();
    missing_values_.clear();
    rebuild(blocks);
    for (size_t m = 0; m < missing.size(); ++m) add_block(missing[m].first, missing[m].second, &values[9 * m]);
    changed_ = true;
  }
  if (!changed_) return false;
  changed_ = false;
  ++version_;
  return true;
}

}  // namespace kinema::contact
