// Assembly of per-element vectors and matrices into global ones with a sparsity pattern fixed at
// construction, so that Newton iterations and time steps never re-allocate: the element loop
// writes into a per-element buffer in parallel, and every global entry then gathers its
// contributions in a fixed order (deterministic for any thread count, no atomics, no colouring).
//   f_i = sum_{(e, a): elements[e][a] = i} f^e_a,    K_ij = sum_{(e, a, b)} K^e_ab
// Elements are any fixed-size vertex tuples: springs (k = 2), triangles (3), tetrahedra (4).
#pragma once

#include <vector>

#include "core/types.h"

namespace kinema {

class ElementAssembly {
 public:
  // elements: element_count * k vertex indices in [0, vertex_count); d: dofs per vertex.
  // Throws InvalidArgument for an out-of-range or repeated vertex inside one element.
  ElementAssembly(Index vertex_count, int d, int k, const Index* elements, Index element_count);

  Index vertex_count() const { return vertex_count_; }
  Index element_count() const { return element_count_; }
  int dim() const { return d_; }
  int nodes() const { return k_; }
  Index dof_count() const { return vertex_count_ * d_; }
  // Entries of one element vector (k d) and one element matrix ((k d)^2, row-major).
  Index element_vector_size() const { return Index(k_) * d_; }
  Index element_matrix_size() const { return element_vector_size() * element_vector_size(); }

  // The global matrix's pattern: full (both triangles), CSR with sorted columns, dof-level.
  // Being symmetric, it is also its own CSC pattern (CHOLMOD reads it as such).
  const std::vector<Index>& row_ptr() const { return row_ptr_; }
  const std::vector<Index>& col_index() const { return col_index_; }
  Index nonzeros() const { return static_cast<Index>(col_index_.size()); }
  // Position of the diagonal entry of each dof row.
  const std::vector<Index>& diagonal() const { return diagonal_; }

  // out (dof_count) = sum of element vectors (element_count * k d, element e at e * k d).
  void gather_vector(const Scalar* element_vectors, Scalar* out) const;
  // values (nonzeros) = sum of element matrices (element_count * (k d)^2, row-major each).
  void gather_matrix(const Scalar* element_matrices, Scalar* values) const;

 private:
  Index vertex_count_, element_count_;
  int d_, k_;
  std::vector<Index> row_ptr_, col_index_, diagonal_;
  // Vertex-level incidence: the (e * k + a) slots of every vertex, in element order.
  std::vector<Index> vertex_ptr_, vertex_slot_;
  // Vertex-level block pattern: block_ptr_ per vertex row, block_col_ the neighbour vertex,
  // and for each block the element blocks that add into it, as offsets of their first entry.
  std::vector<Index> block_ptr_, block_col_, source_ptr_, source_;
};

}  // namespace kinema
