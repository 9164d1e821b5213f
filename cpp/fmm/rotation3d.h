// The translations of the 3D Laplace FMM in O(p^3) by rotation ("point and shoot";
// White & Head-Gordon 1994, J. Chem. Phys. 101:6593; Greengard & Rokhlin 1997, sec. 5.2):
//   L = Rz(a)^T Ry(b)^T T_z(rho) Ry(b) Rz(a) M,
// rotate the multipole so that the offset points along +z (about z by the azimuth a, O(p^2);
// about y by the polar angle b with the Wigner d-matrices d^l_{m'm}(b), O(p^3)), translate
// along z, where only I_{n,0}(0, 0, rho) = n!/rho^{n+1} survives (L_jm = (-1)^{j+m}
// sum_l I_{l+j,0} conj(M_lm): one (p+1-m)^2 matrix per m, O(p^3)), rotate back.
// The d-matrices are exp(-b (J+ - J-)/2) on the 2l+1 orthonormal harmonics of degree l,
// computed by diagonalising the Hermitian generator once per degree; they are rescaled to the
// scaled solid harmonics of kernels3d.h and split, as the charges are real, into a real block
// acting on Re X_lm and another on Im X_lm (each degree couples only within itself).
// Operators are built for the offsets with non-negative components only (laplace3d.cpp maps
// the others by reflection), one d-matrix set per distinct polar angle and one translation
// per distinct distance. They are applied to kColumns expansions at a time stored
// coefficient-major (value k of column c at k * kColumns + c), so that every product is a
// vectorised loop over the columns. M2M and L2L (parent and child centres along a body
// diagonal, one direction up to reflections) use the same rotations with the translations
// along z M_lm <- sum_j 2^-j M_jm t^(l-j)/(l-j)! and L_jm <- 2^-j sum_l L_lm t^(l-j)/(l-j)!,
// t = sqrt(3)/2 (multipoles and locals rotate with the scaled harmonics' two scalings).
#pragma once

#include <vector>

#include "core/types.h"

namespace kinema::fmm3 {

enum class Translation { M2L, M2M, L2L };

class RotatedTranslation {
 public:
  static constexpr int kColumns = 16;
  static constexpr int kDiagonal = 21;  // canonical code of the offset (1, 1, 1)

  // p: the expansion order; canonical: the offsets b = dx * 16 + dy * 4 + dz
  // (0 <= dx, dy, dz <= 3, not all zero) that apply() will be called with. M2M and L2L take
  // only kDiagonal: the child's centre minus the parent's is (1, 1, 1) h/2 up to reflections.
  RotatedTranslation(int p, Translation kind, const std::vector<int>& canonical);

  // out = A(b) in for kColumns scaled expansions of order pt <= p (the leading (pt+1)^2
  // coefficients in the real layout of kernels3d.h). M2L: multipoles to the locals of the
  // same order (still to be divided by h, as m2l_matrix's); M2M: child multipoles (box h/2) to
  // their parent's (h) scaling, as m2m(); L2L: parent locals to their child's, as l2l().
  // scratch: scratch_size() values.
  void apply(int b, int pt, const Scalar* in, Scalar* out, Scalar* scratch) const;
  size_t scratch_size() const { return static_cast<size_t>(2 * (p_ + 1) * (p_ + 1) * kColumns); }
  int order() const { return p_; }

 private:
  struct Offset {
    int angle = -1, distance = -1;  // indices of the d-matrix set and of the translation
    std::vector<Scalar> cos_ma, sin_ma;  // cos(m a), sin(m a), m = 0..p
  };
  int p_;
  Translation kind_;
  std::vector<Offset> offsets_;  // by canonical offset (64 slots)
  // Per angle, per degree l: forward real block (l+1)^2, forward imaginary block l^2, then the
  // backward blocks likewise (each block row-major, output index by input index); start of degree l within a set at block_start_[l].
  std::vector<std::vector<Scalar>> rotations_;
  std::vector<size_t> block_start_;
  // Per distance, per m: (p+1-m)^2 row-major, rows j = m..p, columns l = m..p.
  std::vector<std::vector<Scalar>> translations_;
  std::vector<size_t> translation_start_;
};

}  // namespace kinema::fmm3
