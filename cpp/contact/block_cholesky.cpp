// Left-looking block Cholesky of a 3x3-block SPD matrix (block_cholesky.h).
#include "contact/block_cholesky.h"

#include <algorithm>
#include <cmath>
#include <cstring>

#include "core/simd.h"

namespace kinema::contact {

namespace {

using Block = BlockCholesky::Block;

// Inverse of the lower Cholesky factor of the 3x3 SPD block D; false when D is not positive
// definite (a pivot <= 0 or not finite).
bool chol3_inverse(const Block& Db, Block& inv) {
  auto D = [&](int r, int c) { return Db.v[4 * c + r]; };
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
  inv = Block{{i00, i10, i20, 0, 0, i11, i21, 0, 0, 0, i22, 0}};
  return true;
}

#if defined(__GNUC__)
// Four doubles (GCC/Clang vector extension): AVX registers in the AVX2 build, two SSE2 halves
// in the baseline one.
typedef Scalar V4 __attribute__((vector_size(32)));
#else
struct V4 {
  Scalar e[4];
  V4 operator*(Scalar s) const { return {{e[0] * s, e[1] * s, e[2] * s, e[3] * s}}; }
  V4 operator+(const V4& o) const { return {{e[0] + o.e[0], e[1] + o.e[1], e[2] + o.e[2], e[3] + o.e[3]}}; }
  V4 operator-(const V4& o) const { return {{e[0] - o.e[0], e[1] - o.e[1], e[2] - o.e[2], e[3] - o.e[3]}}; }
};
#endif

// (By reference: a vector returned by value would change the baseline's ABI, -Wpsabi.)
KINEMA_ALWAYS_INLINE void load(V4& v, const Scalar* p) { std::memcpy(&v, p, sizeof v); }
KINEMA_ALWAYS_INLINE void store(Scalar* p, const V4& v) { std::memcpy(p, &v, sizeof v); }

// B's entries by (column c, term t) = B(c, t), the factors of the columns of A in A B^T.
struct Transposed {
  Scalar b[3][3];
  explicit Transposed(const Block& B) {
    for (int c = 0; c < 3; ++c)
      for (int t = 0; t < 3; ++t) b[c][t] = B.v[4 * t + c];
  }
};

// W -= A B^T, column by column: W(:, c) -= A(:, 0) B(c, 0) + A(:, 1) B(c, 1) + A(:, 2) B(c, 2).
KINEMA_ALWAYS_INLINE void subtract_product(Block& W, const Block& A, const Transposed& B) {
  V4 a0, a1, a2, w;
  load(a0, A.v), load(a1, A.v + 4), load(a2, A.v + 8);
  for (int c = 0; c < 3; ++c) {
    load(w, W.v + 4 * c);
    store(W.v + 4 * c, w - (a0 * B.b[c][0] + a1 * B.b[c][1] + a2 * B.b[c][2]));
  }
}

// W = A B^T.
KINEMA_ALWAYS_INLINE void set_product(Block& W, const Block& A, const Transposed& B) {
  V4 a0, a1, a2;
  load(a0, A.v), load(a1, A.v + 4), load(a2, A.v + 8);
  for (int c = 0; c < 3; ++c) store(W.v + 4 * c, a0 * B.b[c][0] + a1 * B.b[c][1] + a2 * B.b[c][2]);
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
  l_.assign(l_row_.size(), Block{});
  diag_inv_.assign(static_cast<size_t>(n_), Block{});
  work_.assign(static_cast<size_t>(n_), Block{});
  avx2_ = use_avx2();
  head_.assign(static_cast<size_t>(n_), -1);
  next_.assign(static_cast<size_t>(n_), -1);
  position_.assign(static_cast<size_t>(n_), 0);
}

// The numeric factorisation, inlined into a baseline and an AVX2 version.
KINEMA_ALWAYS_INLINE bool factorize_body(const CsrView& A, Index n, const std::vector<Index>& a_ptr,
                                         const std::vector<Index>& a_col, const std::vector<Index>& a_offset,
                                         const std::vector<Index>& l_ptr, const std::vector<Index>& l_row,
                                         std::vector<Block>& l, std::vector<Block>& diag_inv, std::vector<Block>& work,
                                         std::vector<Index>& head, std::vector<Index>& next,
                                         std::vector<Index>& position) {
  std::fill(head.begin(), head.end(), Index(-1));
  bool ok = true;
  for (Index j = 0; j < n; ++j) {
    // Column j of A's lower triangle into the work blocks: A(i, j) = A(j, i)^T for i > j, so
    // column c of work block i is row 3j + c of A over block column i.
    Block D{};
    for (Index e = a_ptr[static_cast<size_t>(j)]; e < a_ptr[static_cast<size_t>(j) + 1]; ++e) {
      const Index i = a_col[static_cast<size_t>(e)];
      if (i < j) continue;
      const Index off = a_offset[static_cast<size_t>(e)];
      Block& out = i == j ? D : work[static_cast<size_t>(i)];
      for (int c = 0; c < 3; ++c) {
        const Scalar* row = A.values + A.row_ptr[3 * j + c] + off;
        // The diagonal block is symmetric: its rows are its columns.
        out.v[4 * c] = row[0], out.v[4 * c + 1] = row[1], out.v[4 * c + 2] = row[2], out.v[4 * c + 3] = 0;
      }
    }
    // Updates from the earlier columns k with L(j, k) != 0 (those whose next row is j).
    Index k = head[static_cast<size_t>(j)];
    head[static_cast<size_t>(j)] = -1;
    while (k >= 0) {
      const Index following = next[static_cast<size_t>(k)];
      const Index p = position[static_cast<size_t>(k)], end = l_ptr[static_cast<size_t>(k) + 1];
      const Transposed Ljk(l[static_cast<size_t>(p)]);
      subtract_product(D, l[static_cast<size_t>(p)], Ljk);
      for (Index q = p + 1; q < end; ++q)
        subtract_product(work[static_cast<size_t>(l_row[static_cast<size_t>(q)])], l[static_cast<size_t>(q)], Ljk);
      position[static_cast<size_t>(k)] = p + 1;
      if (p + 1 < end) {
        const Index r = l_row[static_cast<size_t>(p) + 1];
        next[static_cast<size_t>(k)] = head[static_cast<size_t>(r)];
        head[static_cast<size_t>(r)] = k;
      }
      k = following;
    }
    Block& inv = diag_inv[static_cast<size_t>(j)];
    if (!chol3_inverse(D, inv)) {
      ok = false;
      inv = Block{};
    }
    const Transposed inv_t(inv);
    const Index begin = l_ptr[static_cast<size_t>(j)], end = l_ptr[static_cast<size_t>(j) + 1];
    for (Index q = begin; q < end; ++q) {
      Block& w = work[static_cast<size_t>(l_row[static_cast<size_t>(q)])];
      set_product(l[static_cast<size_t>(q)], w, inv_t);  // L(q, j) = W D^-T
      w = Block{};
    }
    position[static_cast<size_t>(j)] = begin;
    if (begin < end) {
      const Index r = l_row[static_cast<size_t>(begin)];
      next[static_cast<size_t>(j)] = head[static_cast<size_t>(r)];
      head[static_cast<size_t>(r)] = j;
    }
  }
  return ok;
}

template <>
KINEMA_TARGET_AVX2 bool BlockCholesky::factorize_with<true>(const CsrView& A) {
  return factorize_body(A, n_, a_ptr_, a_col_, a_offset_, l_ptr_, l_row_, l_, diag_inv_, work_, head_, next_,
                              position_);
}

template <>
bool BlockCholesky::factorize_with<false>(const CsrView& A) {
  return factorize_body(A, n_, a_ptr_, a_col_, a_offset_, l_ptr_, l_row_, l_, diag_inv_, work_, head_, next_,
                               position_);
}

bool BlockCholesky::factorize(const CsrView& A) {
  return avx2_ ? factorize_with<true>(A) : factorize_with<false>(A);
}

void BlockCholesky::solve(const Scalar* b, Scalar* x) const {
  if (x != b) std::copy(b, b + 3 * n_, x);
  // L y = b, column by column.
  for (Index j = 0; j < n_; ++j) {
    Scalar* xj = x + 3 * j;
    const Scalar* inv = diag_inv_[static_cast<size_t>(j)].v;
    Scalar y[3];
    for (int r = 0; r < 3; ++r) y[r] = inv[r] * xj[0] + inv[4 + r] * xj[1] + inv[8 + r] * xj[2];
    xj[0] = y[0], xj[1] = y[1], xj[2] = y[2];
    for (Index q = l_ptr_[static_cast<size_t>(j)]; q < l_ptr_[static_cast<size_t>(j) + 1]; ++q) {
      const Scalar* L = l_[static_cast<size_t>(q)].v;
      Scalar* xr = x + 3 * l_row_[static_cast<size_t>(q)];
      for (int r = 0; r < 3; ++r) xr[r] -= L[r] * y[0] + L[4 + r] * y[1] + L[8 + r] * y[2];
    }
  }
  // L^T x = y, backwards.
  for (Index j = n_ - 1; j >= 0; --j) {
    Scalar* xj = x + 3 * j;
    Scalar s[3] = {xj[0], xj[1], xj[2]};
    for (Index q = l_ptr_[static_cast<size_t>(j)]; q < l_ptr_[static_cast<size_t>(j) + 1]; ++q) {
      const Scalar* L = l_[static_cast<size_t>(q)].v;
      const Scalar* xr = x + 3 * l_row_[static_cast<size_t>(q)];
      for (int c = 0; c < 3; ++c) s[c] -= L[4 * c] * xr[0] + L[4 * c + 1] * xr[1] + L[4 * c + 2] * xr[2];
    }
    const Scalar* inv = diag_inv_[static_cast<size_t>(j)].v;
    for (int c = 0; c < 3; ++c) xj[c] = inv[4 * c] * s[0] + inv[4 * c + 1] * s[1] + inv[4 * c + 2] * s[2];
  }
}

}  // namespace kinema::contact
