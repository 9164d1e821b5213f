// The Newton matrix of the contact solver on a kept sparsity pattern (issue 20: "barrier and
// friction terms assembled into the Newton system on the fixed pattern plus contact blocks").
//
// Unknowns are the degrees of freedom only (free body vertices and driven collider vertices;
// static collider and pinned vertices leave the system, where they used to be identity rows).
// The matrix is stored as 3x3 blocks over those vertices: the elastic blocks (tets, springs,
// diagonal) form the fixed part of the pattern; contact blocks (barrier and friction stencils
// joining two different dofs) are added into it. A block missing from the pattern is added on
// the spot (values kept), which changes the pattern and needs a new symbolic analysis; blocks
// stay reserved for the rest of the step, so Newton iterations whose contact set returns to
// pairs seen reuse the analysis (numeric refactorisation only). Each step starts from the
// elastic blocks plus those of the pairs active at x_n: a pattern that is a function of the
// state (so a restored state continues bit for bit), the same as the last step's whenever no
// pair appeared or vanished in between (then nothing is re-analysed), and bounded fill on long
// runs.
//
// Dofs are numbered in the AMD order of the elastic pattern, kept for the model's life, so a
// factorisation in this natural order does not depend on which contact blocks are reserved.
//
// Layout: block row i holds blocks k in [bptr[i], bptr[i+1]) with sorted block columns; its
// three scalar rows are contiguous in the CSR arrays, so a scalar CSR view (full symmetric
// matrix, sorted columns) is what the linear solvers read, without copies.
#pragma once

#include <cstdint>
#include <vector>

#include "contact/model.h"
#include "linalg/csr.h"

namespace kinema::contact {

class NewtonSystem {
 public:
  explicit NewtonSystem(const Model& model);

  Index dof_count() const { return static_cast<Index>(vertex_of_.size()); }
  Index size() const { return 3 * dof_count(); }
  // Dof of vertex v, or -1 when v is not a degree of freedom.
  Index dof(Index v) const { return dof_[static_cast<size_t>(v)]; }
  Index vertex(Index d) const { return vertex_of_[static_cast<size_t>(d)]; }

  // A new step: the pattern becomes the elastic blocks plus the blocks of these contact
  // stencils (the pairs active at the step's start), unchanged if it is that already.
  void begin_step(const std::vector<std::vector<Index>>& stencils);
  // Zeroes the values before an assembly.
  void clear();
  // Adds the element matrix H (3 count x 3 count) over vertices verts[0..count); entries of
  // vertices that are not dofs are skipped; blocks missing from the pattern are added.
  template <class Matrix>
  void add(const Index* verts, int count, const Matrix& H);
  // After an assembly: folds in the blocks that were missing (a pattern change). Returns true
  // when the pattern changed since the last call.
  bool finish();

  // Where the blocks of an element whose blocks are all in the pattern live (the elastic
  // elements': they are part of every pattern), so that repeated assemblies add into them
  // without searching: valid until layout() changes. offset < 0: a vertex that is no dof.
  struct Slot {
    Index offset = -1, stride = 0;  // first value of the block; distance between its rows
  };
  void slots(const Index* verts, int count, Slot* out) const;  // count x count slots, row-major
  template <class Matrix>
  void add(const Slot* slots, int count, const Matrix& H);
  // Counts the changes of the storage layout (every rebuild of the pattern).
  std::int64_t layout() const { return layout_; }

  CsrView view() const { return {size(), size(), row_ptr_.data(), col_.data(), values_.data()}; }
  // Number of pattern changes so far (each one a new symbolic analysis for the factorisation).
  std::int64_t version() const { return version_; }
  Index block_count() const { return static_cast<Index>(bcol_.size()); }

 private:
  // Slot of block (i, j), or -1.
  Index find(Index i, Index j) const;
  // Adds the row-major 3x3 block m at dofs (i, j).
  void add_block(Index i, Index j, const Scalar* m);
  // Rebuilds the pattern from blocks (sorted unique (i, j) pairs), keeping the values of
  // blocks present before.
  void rebuild(const std::vector<std::pair<Index, Index>>& blocks);

  std::vector<Index> dof_, vertex_of_;
  std::vector<Index> bptr_, bcol_;
  std::vector<std::pair<Index, Index>> elastic_;  // the fixed (elastic and diagonal) blocks, sorted
  std::vector<Index> row_ptr_, col_;
  std::vector<Scalar> values_;
  // Blocks an assembly found missing: (i, j) and 9 values each (row-major).
  std::vector<std::pair<Index, Index>> missing_;
  std::vector<Scalar> missing_values_;
  std::int64_t version_ = 0, layout_ = 0;
  bool changed_ = true;
};

template <class Matrix>
void NewtonSystem::add(const Index* verts, int count, const Matrix& H) {
  for (int a = 0; a < count; ++a) {
    const Index i = dof(verts[a]);
    if (i < 0) continue;
    for (int b = 0; b < count; ++b) {
      const Index j = dof(verts[b]);
      if (j < 0) continue;
      Scalar m[9];
      for (int r = 0; r < 3; ++r)
        for (int s = 0; s < 3; ++s) m[3 * r + s] = H(3 * a + r, 3 * b + s);
      add_block(i, j, m);
    }
  }
}

template <class Matrix>
void NewtonSystem::add(const Slot* slots, int count, const Matrix& H) {
  for (int a = 0; a < count; ++a)
    for (int b = 0; b < count; ++b) {
      const Slot& slot = slots[a * count + b];
      if (slot.offset < 0) continue;
      Scalar* out = values_.data() + slot.offset;
      for (int r = 0; r < 3; ++r)
        for (int s = 0; s < 3; ++s) out[r * slot.stride + s] += H(3 * a + r, 3 * b + s);
    }
}

}  // namespace kinema::contact
