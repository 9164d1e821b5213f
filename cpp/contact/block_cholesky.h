// Sparse Cholesky factorisation A = L L^T of a symmetric positive definite matrix made of
// 3x3 blocks (the contact solver's Newton matrix: one block per pair of coupled vertices), in
// the matrix's own block order (no permutation: the Newton system numbers its dofs in a
// fill-reducing order already).
//
// Why not a scalar factorisation: the Newton matrix's pattern is a block pattern, so every
// scalar column of L shares its structure with two others. A scalar simplicial factorisation
// (Eigen's SimplicialLLT, CHOLMOD's simplicial) walks the indices of each of the three and
// updates one scalar at a time; here every index step moves a 3x3 block (27 multiply-adds with
// fixed-size, unrolled arithmetic), and the supernodal CHOLMOD alternative spends its time in
// BLAS calls on supernodes a few columns wide (at 1k-2k unknowns: measured 1.5-2x slower than
// the scalar simplicial one, which this one beats in turn; bench/RESULTS.md, contact section).
//
// Left-looking by block columns (Davis, "Direct Methods for Sparse Linear Systems", SIAM 2006,
// ch. 4): the symbolic analysis (elimination tree and the block pattern of L by row subtrees)
// runs once per pattern; each numeric factorisation visits, for block column j, the earlier
// columns k with L(j,k) != 0 through linked lists ordered by each column's next row. The
// operation order depends on the pattern only, so results are deterministic.
//
// Blocks are stored by columns padded to four values (the fourth zero), so a block update
// W -= A B^T is nine products of four-wide columns by broadcast scalars: written once with
// four-wide vectors, compiled for the baseline (two SSE2 halves) and for AVX2 (core/simd.h),
// the same operations in the same order either way (no FMA), so both give the same bits.
#pragma once

#include <Eigen/Core>
#include <vector>

#include "core/types.h"
#include "linalg/csr.h"

namespace kinema::contact {

class BlockCholesky {
 public:
  // Symbolic analysis of A's block pattern. A: full symmetric scalar CSR whose block row i
  // occupies scalar rows 3i..3i+2 with the same block columns (each block's 3 columns
  // contiguous and sorted), as NewtonSystem::view() gives.
  void analyze(const CsrView& A);
  // Numeric factorisation of A (same pattern as analysed). Returns false when A is not
  // positive definite (a pivot block fails its 3x3 Cholesky).
  bool factorize(const CsrView& A);
  // x = A^-1 b (x may alias b).
  void solve(const Scalar* b, Scalar* x) const;

  // A 3x3 block by columns, each padded to four values (v[4 c + r] = B(r, c), v[4 c + 3] = 0).
  struct alignas(32) Block {
    Scalar v[12];
  };

 private:
  template <bool Avx2>
  bool factorize_with(const CsrView& A);

  Index n_ = 0;  // block rows
  bool avx2_ = false;
  // A's block rows: block columns and the offset of each block's first scalar in row 3i.
  std::vector<Index> a_ptr_, a_col_, a_offset_;
  // L below the diagonal, by block columns: rows (sorted) and 3x3 blocks; the inverses of the
  // diagonal blocks (lower triangular).
  std::vector<Index> l_ptr_, l_row_;
  std::vector<Block> l_, diag_inv_;
  // Numeric scratch: dense block column, linked lists of columns by next row.
  std::vector<Block> work_;
  std::vector<Index> head_, next_, position_;
};

}  // namespace kinema::contact
