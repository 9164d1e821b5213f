// The cell-centred finite-volume operator A = shift*I - lap_h of kinema's Poisson and diffusion
// solvers, on a 2D or 3D grid with spacing h:
//   (A u)_c = shift*u_c + sum over the faces f of c of (u_c - u_nb(f)) / h^2,
// where a face to a fluid neighbour couples the two cells, a Dirichlet boundary face uses the
// ghost value u_nb = -u_c (u = 0 on the face), a Neumann boundary face or a face to a solid
// cell carries no flux, and on a periodic grid a boundary face couples to the cell at the other
// end of the axis. Solid cells are excluded: (A u)_c = 0 there. The operator is symmetric
// and positive semi-definite; it is singular (constants per component) only for a fluid
// component that touches no Dirichlet face while shift == 0. McAdams, Sifakis & Teran,
// "A parallel multigrid Poisson solver for fluids simulation on large grids", SCA 2010, Sec. 3.
#pragma once

#include <algorithm>
#include <cstdint>
#include <vector>

#include "core/parallel.h"
#include "poisson/grid.h"

namespace kinema {

// CSR arrays of an assembled operator (rows of solid cells are empty).
struct CsrArrays {
  Index rows = 0;
  std::vector<Index> row_ptr, col_index;
  std::vector<Scalar> values;
};

// Walls of a grid: bit 2*axis + side (internal axis, side 0 = lower).
constexpr int kAllWalls = 0x3F;

class PoissonOperator {
 public:
  // `solid` (nullable) has one byte per cell, nonzero = solid. `dirichlet_walls` (bits
  // 2*axis + side) chooses per wall between Dirichlet and Neumann under bc = Neumann or
  // Dirichlet; -1 takes them from bc (all Dirichlet or all Neumann).
  PoissonOperator(const GridShape& shape, Scalar h, Boundary bc, const std::uint8_t* solid,
                  Scalar shift = 0, int dirichlet_walls = -1);

  // The operator of the grid coarsened by two per active axis (ceil), spacing 2h; a coarse
  // cell is fluid when any of its children is.
  PoissonOperator coarsened() const;

  void apply(const Scalar* x, Scalar* y) const;                         // y = A x
  void residual(const Scalar* b, const Scalar* x, Scalar* r) const;     // r = b - A x
  // One red-black Gauss-Seidel sweep: all cells of colour first_color ((i+j+k) % 2), then
  // all of the other colour, fused into one pass over memory. Reversing first_color gives the
  // adjoint sweep, so pre- and post-smoothing in opposite orders keep a V-cycle symmetric.
  void sweep(const Scalar* b, Scalar* x, int first_color) const;
  // Weighted Jacobi: x_new = x + omega D^-1 (b - A x).
  void jacobi(const Scalar* b, const Scalar* x, Scalar* x_new, Scalar omega) const;

  // Removes from x, per singular component, its mean over that component (the A-null space);
  // a no-op for a nonsingular operator. Solid entries are set to zero.
  void project(Scalar* x) const;
  bool singular() const { return !singular_components_.empty(); }
  // One representative cell per singular component (the first in index order).
  std::vector<Index> singular_anchor_cells() const;

  CsrArrays assemble() const;

  const GridShape& shape() const { return shape_; }
  Index size() const { return shape_.size(); }
  Scalar h() const { return h_; }
  Scalar shift() const { return shift_; }
  Boundary bc() const { return bc_; }
  // Sign of the ghost value beyond a boundary face of `wall`: -1 Dirichlet, +1 Neumann.
  Scalar ghost_sign(int wall) const { return (dirichlet_ >> wall) & 1 ? -1 : 1; }
  int dirichlet_walls() const { return dirichlet_; }
  bool fluid(Index c) const { return mask_[c] & kFluidBit; }
  // True when no cell of the row (i, j) has a solid cell in its 3^d neighbourhood, so that the
  // multigrid transfers there only meet domain boundaries and stay separable.
  bool row_clear(Index row) const { return row_clear_[row] != 0; }
  // True when every cell of the row (i, j) is fluid.
  bool row_fluid(Index row) const { return row_fluid_[row] != 0; }
  // Whether a pass over this grid is worth an OpenMP team.
  bool parallel() const { return shape_.size() > 8 * kParallelGrain; }
  Index fluid_count() const { return fluid_count_; }
  // Whether the plain-stencil rows run with AVX2 (chosen at construction, core/simd.h); the
  // results are bitwise the same either way.
  bool avx2() const { return avx2_; }
  // Whether the 3D apply and residual write their result with non-temporal stores (AVX2 rows
  // on grids of at least kStreamBytes per array); bitwise the same results either way. Tests
  // and benchmarks may switch it.
  bool stream_stores() const { return stream_stores_; }
  void set_stream_stores(bool on) { stream_stores_ = on && avx2_; }
  static constexpr Index kStreamBytes = Index(64) << 20;
  // A_cc for a fluid cell.
  Scalar diagonal(Index c) const { return shift_ + inv_h2_ * diag_[c]; }

 private:
  template <bool ThreeD>
  void apply_impl(const Scalar* x, Scalar* y, const Scalar* b) const;
  template <bool ThreeD>
  void smooth_row(const Scalar* b, Scalar* x, Index row, Index k0) const;
  template <bool ThreeD>
  void smooth_row_pair(const Scalar* b, Scalar* x, Index row, Index k0) const;
  template <bool ThreeD>
  void sweep_impl(const Scalar* b, Scalar* x, int first_color) const;
  void label_components();

  Scalar neighbour_sum(const Scalar* x, Index c) const;
  // A_cc of an end cell (k = 0 or n2 - 1) of a plain row without periodic wrap: 2d - 1
  // couplings, plus the ghost's 2 under Dirichlet. Computed as diagonal() computes it.
  template <bool ThreeD>
  Scalar end_diagonal() const {
    const int count = (ThreeD ? 5 : 3) + ((dirichlet_ >> 4) & 1 ? 2 : 0);  // both ends alike
    return shift_ + inv_h2_ * static_cast<std::uint8_t>(count);
  }
  Scalar wrapped_neighbour_sum(const Scalar* x, Index c) const;

 public:
  // Index of the neighbour of c in direction dir (bit of mask), across the periodic wrap if
  // that is where it lies. Only meaningful for a coupled direction.
  Index neighbour(Index c, int dir) const {
    const int axis = dir / 2;
    const Index stride = shape_.stride(axis);
    if (!wrap_.empty() && (wrap_[c] >> dir) & 1)
      return dir % 2 ? c - (shape_.n[axis] - 1) * stride : c + (shape_.n[axis] - 1) * stride;
    return dir % 2 ? c + stride : c - stride;
  }

 private:

  GridShape shape_;
  Scalar h_ = 1, inv_h2_ = 1, shift_ = 0;
  Scalar inv_plain_ = 1;                // 1 / A_cc of a plain cell, for the smoother
  Boundary bc_ = Boundary::Dirichlet;
  std::uint8_t dirichlet_ = kAllWalls;  // Dirichlet walls (active axes only; none when periodic)
  bool avx2_ = false;                   // run the plain-stencil rows with AVX2 (core/simd.h)
  bool stream_stores_ = false;          // 3D apply: non-temporal stores of the result
  bool ends_plain_ = false;             // end cells of plain rows: no periodic wrap (end_diagonal)
  std::vector<std::uint8_t> mask_;      // neighbour-coupling bits 0-5 and kFluidBit
  std::vector<std::uint8_t> diag_;      // couplings + 2 per Dirichlet face (fluid cells)
  std::vector<std::uint8_t> wrap_;      // periodic: directions whose neighbour wraps around
  std::vector<std::uint8_t> row_fast_;  // row whose inner cells see the plain stencil
  // Other rows whose inner cells share one stencil: its couplings off the row (mask bits 0-3),
  // or kMixedRow.
  std::vector<std::uint8_t> row_dirs_;
  static constexpr std::uint8_t kMixedRow = 0xFF;
  std::vector<std::uint8_t> row_clear_, row_fluid_;
  Index fluid_count_ = 0;
  std::vector<std::int32_t> component_;          // per cell; -1 for solid
  std::vector<std::int32_t> singular_components_;
  std::vector<Index> component_size_;
};

}  // namespace kinema
