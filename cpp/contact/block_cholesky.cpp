// Left-looking block Cholesky of a 3x3-block SPD matrix (block_cholesky.h).
#include "contact/block_cholesky.h"

#include <cmath>

namespace kinema::contact {

namespace {

using Mat3 = Eigen::Matrix<Scalar, 3, 3>;

// Inverse of the lower Cholesky factor of the 3x3 SPD block D; false when D is not positive
// definite (a pivot <= 0 or not finite).
bool chol3_inverse(const Mat3& D, Mat3& inv) {
  const Scalar p0 = D(0, 0);
  if (!(p0 > 0 && std::isfinite(p0))) return false;
  const Scalar l00 = std::sqrt(p0), l10 = D(1, 0) / l00, l20 = D(2, 0) / l00;
  const Scalar p1 = D(1, 1) - l10 * l10;
  if (!(p1 > 0 && std::isfinite(p1))) return false;
  const Scalar l11 = std::sqrt(p1), l21 = (D(2, 1) - l20 * l10) / l11;
  const Scalar p2 = D(2, 2) - l20 * l20 - l21 * l21;
  if (!(p2 > 0 && std::isfinite(p2))) return false;
  const Scalar l22 = std::sqrt(p2);
  // Forward substitution on the identity.
  const Scalar i00 = 1 / l00, i11 = 1 / l11, i22 = 1 / l22;
  const Scalar i10 = -l10 * i00 * i11;
  const Scalar i21 = -l21 * i11 * i22;
  const Scalar i20 = -(l20 * i00 + l21 * i10) * i22;
  inv << i00, 0, 0, i10, i11, 0, i20, i21, i22;
  return true;
}

}  // namespace

void BlockCholesky::analyze(const CsrView& A) {
  n_ = A.rows / 3;
  a_ptr_.assign(static_cast<size_t>(n_) + 1, 0);
  a_col_.clear();
  a_offset_.clear();
  for (Index i = 0; i < n_; ++i) {
    const Index begin = A.row_ptr[3 * i], end = A.row_ptr[3 * i + 1];
    for (Index p = begin; p < end; p += 3) {
      a_col_.push_back(A.col_index[p] / 3);
      a_offset_.push_back(p - begin);
    }
    a_ptr_[static_cast<size_t>(i) + 1] = static_cast<Index>(a_col_.size());
  }
  // Elimination tree and the pattern of L by row subtrees: row i of L holds the nodes met
  // walking up the tree from each k < i with A(i, k) != 0 until a node already marked for i.
  // Rows come in increasing order, so every column's row list is sorted.
  std::vector<Index> parent(static_cast<size_t>(n_), -1), mark(static_cast<size_t>(n_), -1);
  std::vector<std::vector<Index>> rows(static_cast<size_t>(n_));
  for (Index i = 0; i < n_; ++i) {
    mark[static_cast<size_t>(i)] = i;
    for (Index e = a_ptr_[static_cast<size_t>(i)]; e < a_ptr_[static_cast<size_t>(i) + 1]; ++e) {
      Index p = a_col_[static_cast<size_t>(e)];
      if (p >= i) break;  // sorted block columns: the rest is the upper triangle
      while (mark[static_cast<size_t>(p)] != i) {
        rows[static_cast<size_t>(p)].push_back(i);
        mark[static_cast<size_t>(p)] = i;
        if (parent[static_cast<size_t>(p)] < 0) parent[static_cast<size_t>(p)] = i;
        p = parent[static_cast<size_t>(p)];
      }
    }
  }
  l_ptr_.assign(static_cast<size_t>(n_) + 1, 0);
  l_row_.clear();
  for (Index j = 0; j < n_; ++j) {
    l_row_.insert(l_row_.end(), rows[static_cast<size_t>(j)].begin(), rows[static_cast<size_t>(j)].end());
    l_ptr_[static_cast<size_t>(j) + 1] = static_cast<Index>(l_row_.size());
  }
  l_.assign(l_row_.size(), Mat3::Zero());
  diag_inv_.assign(static_cast<size_t>(n_), Mat3::Zero());
  work_.assign(static_cast<size_t>(n_), Mat3::Zero());
  head_.assign(static_cast<size_t>(n_), -1);
  next_.assign(static_cast<size_t>(n_), -1);
  position_.assign(static_cast<size_t>(n_), 0);
}

bool BlockCholesky::factorize(const CsrView& A) {
  std::fill(head_.begin(), head_.end(), Index(-1));
  bool ok = true;
  for (Index j = 0; j < n_; ++j) {
    // Column j of A's lower triangle into the work blocks: A(i, j) = A(j, i)^T for i > j.
    Mat3 D = Mat3::Zero();
    for (Index e = a_ptr_[static_cast<size_t>(j)]; e < a_ptr_[static_cast<size_t>(j) + 1]; ++e) {
      const Index i = a_col_[static_cast<size_t>(e)];
      if (i < j) continue;
      const Index off = a_offset_[static_cast<size_t>(e)];
      Mat3 block;
      for (int r = 0; r < 3; ++r)
        for (int s = 0; s < 3; ++s) block(r, s) = A.values[A.row_ptr[3 * j + r] + off + s];
      if (i == j)
        D = block;
      else
        work_[static_cast<size_t>(i)] = block.transpose();
    }
    // Updates from the earlier columns k with L(j, k) != 0 (those whose next row is j).
    Index k = head_[static_cast<size_t>(j)];
    head_[static_cast<size_t>(j)] = -1;
    while (k >= 0) {
      const Index following = next_[static_cast<size_t>(k)];
      const Index p = position_[static_cast<size_t>(k)], end = l_ptr_[static_cast<size_t>(k) + 1];
      const Mat3 Ljk_t = l_[static_cast<size_t>(p)].transpose();
      D.noalias() -= l_[static_cast<size_t>(p)] * Ljk_t;
      for (Index q = p + 1; q < end; ++q)
        work_[static_cast<size_t>(l_row_[static_cast<size_t>(q)])].noalias() -= l_[static_cast<size_t>(q)] * Ljk_t;
      position_[static_cast<size_t>(k)] = p + 1;
      if (p + 1 < end) {
        const Index r = l_row_[static_cast<size_t>(p) + 1];
        next_[static_cast<size_t>(k)] = head_[static_cast<size_t>(r)];
        head_[static_cast<size_t>(r)] = k;
      }
      k = following;
    }
    Mat3& inv = diag_inv_[static_cast<size_t>(j)];
    if (!chol3_inverse(D, inv)) {
      ok = false;
      inv.setZero();
    }
    const Mat3 inv_t = inv.transpose();
    const Index begin = l_ptr_[static_cast<size_t>(j)], end = l_ptr_[static_cast<size_t>(j) + 1];
    for (Index q = begin; q < end; ++q) {
      Mat3& w = work_[static_cast<size_t>(l_row_[static_cast<size_t>(q)])];
      l_[static_cast<size_t>(q)].noalias() = w * inv_t;
      w.setZero();
    }
    position_[static_cast<size_t>(j)] = begin;
    if (begin < end) {
      const Index r = l_row_[static_cast<size_t>(begin)];
      next_[static_cast<size_t>(j)] = head_[static_cast<size_t>(r)];
      head_[static_cast<size_t>(r)] = j;
    }
  }
  return ok;
}

void BlockCholesky::solve(const Scalar* b, Scalar* x) const {
  using Vec3 = Eigen::Matrix<Scalar, 3, 1>;
  if (x != b) std::copy(b, b + 3 * n_, x);
  // L y = b, column by column.
  for (Index j = 0; j < n_; ++j) {
    Eigen::Map<Vec3> xj(x + 3 * j);
    const Vec3 y = diag_inv_[static_cast<size_t>(j)] * xj;
    xj = y;
    for (Index q = l_ptr_[static_cast<size_t>(j)]; q < l_ptr_[static_cast<size_t>(j) + 1]; ++q)
      Eigen::Map<Vec3>(x + 3 * l_row_[static_cast<size_t>(q)]).noalias() -= l_[static_cast<size_t>(q)] * y;
  }
  // L^T x = y, backwards.
  for (Index j = n_ - 1; j >= 0; --j) {
    Eigen::Map<Vec3> xj(x + 3 * j);
    Vec3 s = xj;
    for (Index q = l_ptr_[static_cast<size_t>(j)]; q < l_ptr_[static_cast<size_t>(j) + 1]; ++q)
      s.noalias() -= l_[static_cast<size_t>(q)].transpose() * Eigen::Map<const Vec3>(x + 3 * l_row_[static_cast<size_t>(q)]);
    xj = diag_inv_[static_cast<size_t>(j)].transpose() * s;
  }
}

}  // namespace kinema::contact
