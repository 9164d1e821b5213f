#include "poisson/multigrid.h"

#include <Eigen/SparseCholesky>
#include <algorithm>
#include <array>

#include "core/parallel.h"

namespace kinema {

struct Multigrid::Coarse {
  Eigen::SimplicialLDLT<Eigen::SparseMatrix<Scalar>> ldlt;
  std::vector<Index> pinned;  // solid cells and one anchor per singular component
  Eigen::VectorXd rhs, sol;
};

namespace {

bool can_coarsen(const PoissonOperator& op, Index coarsest_cells) {
  if (op.size() <= coarsest_cells) return false;
  for (int axis = 0; axis < 3; ++axis) {
    if (!op.shape().active(axis)) continue;
    if (op.shape().n[axis] < 4) return false;
    // a periodic axis halves exactly, so that the coarse grid wraps where the fine one does
    if (op.bc() == Boundary::Periodic && op.shape().n[axis] % 2 != 0) return false;
  }
  return true;
}

// Calls emit(coarse_index, weight) for the terms of (P x_c) at fine cell (i, j, k): the 2^d
// coarse cells nearest to the fine cell centre with the (3/4, 1/4) weights per axis; a coarse
// cell across the domain boundary is replaced by the in-range one with the sign of the ghost
// value (-1 Dirichlet, +1 Neumann) or, on a periodic grid, wrapped around; a solid coarse cell
// is replaced by the parent.
template <class Emit>
void prolongation_stencil(const PoissonOperator& fine, const PoissonOperator& coarse, Index i,
                          Index j, Index k, Emit&& emit) {
  const GridShape& cs = coarse.shape();
  const Index f[3] = {i, j, k};
  Index parent[3], partner[3];
  for (int a = 0; a < 3; ++a) {
    if (fine.shape().active(a)) {
      parent[a] = f[a] / 2;
      partner[a] = (f[a] & 1) ? parent[a] + 1 : parent[a] - 1;
    } else {
      parent[a] = partner[a] = 0;
    }
  }
  const Index parent_index = cs.index(parent[0], parent[1], parent[2]);
  const bool periodic = coarse.bc() == Boundary::Periodic;
  for (int subset = 0; subset < 8; ++subset) {
    Index c[3];
    Scalar w = 1, sign = 1;
    bool skip = false;
    for (int a = 0; a < 3; ++a) {
      const bool use_partner = subset & (1 << a);
      if (!fine.shape().active(a)) {
        if (use_partner) skip = true;
        c[a] = 0;
        continue;
      }
      c[a] = use_partner ? partner[a] : parent[a];
      w *= use_partner ? 0.25 : 0.75;
      if (c[a] < 0 || c[a] >= cs.n[a]) {
        if (periodic) {
          c[a] = c[a] < 0 ? c[a] + cs.n[a] : c[a] - cs.n[a];
        } else {
          sign *= coarse.ghost_sign(2 * a + (c[a] < 0 ? 0 : 1));
          c[a] = parent[a];
        }
      }
    }
    if (skip) continue;
    const Index ci = cs.index(c[0], c[1], c[2]);
    emit(coarse.fluid(ci) ? ci : parent_index, w * sign);
  }
}

}  // namespace

Multigrid::Multigrid(const PoissonOperator& fine, const MultigridOptions& options)
    : fine_(&fine), options_(options), coarse_(std::make_unique<Coarse>()) {
  const PoissonOperator* current = &fine;
  while (can_coarsen(*current, options_.coarsest_cells)) {
    ops_.push_back(current->coarsened());
    current = &ops_.back();
  }
  const int L = levels();
  b_.resize(L);
  x_.resize(L);
  r_.resize(L);
  for (int l = 0; l < L; ++l) {
    const Index n = level(l).size();
    if (l > 0) {
      b_[l].assign(n, 0);
      x_[l].assign(n, 0);
    }
    if (l + 1 < L) r_[l].assign(n, 0);
  }

  // Coarsest level: exact sparse LDL^T with solid cells and one cell per singular component
  // pinned to zero (rows and columns replaced by the identity).
  const PoissonOperator& last = level(L - 1);
  const CsrArrays csr = last.assemble();
  const Index n = last.size();
  std::vector<char> pinned(n, 0);
  for (Index c = 0; c < n; ++c)
    if (!last.fluid(c)) pinned[c] = 1;
  for (Index c : last.singular_anchor_cells()) pinned[c] = 1;
  std::vector<Eigen::Triplet<Scalar>> triplets;
  for (Index r = 0; r < n; ++r) {
    if (pinned[r]) {
      triplets.emplace_back(r, r, 1.0);
      coarse_->pinned.push_back(r);
      continue;
    }
    for (Index p = csr.row_ptr[r]; p < csr.row_ptr[r + 1]; ++p)
      if (!pinned[csr.col_index[p]]) triplets.emplace_back(r, csr.col_index[p], csr.values[p]);
  }
  Eigen::SparseMatrix<Scalar> A(n, n);
  A.setFromTriplets(triplets.begin(), triplets.end());
  coarse_->ldlt.compute(A);
  if (coarse_->ldlt.info() != Eigen::Success)
    throw KinemaError("multigrid: the coarsest-grid factorisation failed");
  coarse_->rhs.resize(n);
  coarse_->sol.resize(n);
}

Multigrid::~Multigrid() = default;
Multigrid::Multigrid(Multigrid&&) noexcept = default;
Multigrid& Multigrid::operator=(Multigrid&&) noexcept = default;

void Multigrid::vcycle(const Scalar* b, Scalar* x) { cycle(0, b, x); }

void Multigrid::cycle(int l, const Scalar* b, Scalar* x) {
  const PoissonOperator& A = level(l);
  if (l == levels() - 1) {
    coarse_solve(b, x);
    return;
  }
  parallel_for(A.size(), [&](Index c) { x[c] = 0; });
  for (int s = 0; s < options_.pre_smooth; ++s) {
    A.sweep(b, x, 0);
  }
  A.residual(b, x, r_[l].data());
  restrict_residual(l, r_[l].data(), b_[l + 1].data());
  cycle(l + 1, b_[l + 1].data(), x_[l + 1].data());
  prolong_add(l, x_[l + 1].data(), x);
  for (int s = 0; s < options_.post_smooth; ++s) {
    A.sweep(b, x, 1);
  }
}

void Multigrid::coarse_solve(const Scalar* b, Scalar* x) {
  const PoissonOperator& A = level(levels() - 1);
  const Index n = A.size();
  std::copy(b, b + n, coarse_->rhs.data());
  A.project(coarse_->rhs.data());
  for (Index c : coarse_->pinned) coarse_->rhs[c] = 0;
  coarse_->sol = coarse_->ldlt.solve(coarse_->rhs);
  std::copy(coarse_->sol.data(), coarse_->sol.data() + n, x);
  A.project(x);
}

namespace {

// The 1D prolongation weights of the fine cells 2I-1, 2I, 2I+1, 2I+2 onto coarse cell I along
// an axis with nf fine and nc coarse cells: (1/4, 3/4, 3/4, 1/4), where a fine cell whose other
// coarse neighbour lies across the domain boundary adds that neighbour's ghost value sigma*x_I
// (sigma = -1 Dirichlet, +1 Neumann), and cells outside the fine grid weigh nothing.
// Sigma is per wall: lower and upper end of the axis.
struct Sigma {
  Scalar lo = 1, hi = 1;
};

Sigma axis_sigma(const PoissonOperator& C, int axis) { return {C.ghost_sign(2 * axis), C.ghost_sign(2 * axis + 1)}; }

std::array<Scalar, 4> window_weights(Index nf, Index nc, Index I, Sigma sigma) {
  std::array<Scalar, 4> w{0.25, 0.75, 0.75, 0.25};
  if (I == 0) w[1] += 0.25 * sigma.lo;         // fine 2I reaches coarse -1: reflected
  if (I + 1 == nc) w[2] += 0.25 * sigma.hi;    // fine 2I+1 reaches coarse nc: reflected
  for (int c = 0; c < 4; ++c) {
    const Index f = 2 * I - 1 + c;
    if (f < 0 || f >= nf) w[c] = 0;
  }
  return w;
}

// For fine index f along an axis: (parent weight, partner weight, partner index), the partner
// reflected onto the parent across the domain boundary.
struct AxisTerm {
  Scalar parent_weight, partner_weight;
  Index parent, partner;
};

AxisTerm axis_term(Index f, Index nc, Sigma sigma) {
  const Index parent = f / 2;
  const Index partner = (f & 1) ? parent + 1 : parent - 1;
  if (partner < 0) return {0.75 + 0.25 * sigma.lo, 0, parent, parent};
  if (partner >= nc) return {0.75 + 0.25 * sigma.hi, 0, parent, parent};
  return {0.75, 0.25, parent, partner};
}

}  // namespace

void Multigrid::prolong_add(int l, const Scalar* coarse, Scalar* fine) const {
  const PoissonOperator& F = level(l);
  const PoissonOperator& C = level(l + 1);
  const GridShape& fs = F.shape();
  const GridShape& cs = C.shape();
  const bool three_d = fs.dim == 3;
  const Index nf2 = fs.n[2], nc2 = cs.n[2];
  const Sigma s0 = axis_sigma(C, 0), s1 = axis_sigma(C, 1), s2 = axis_sigma(C, 2);
  const bool periodic = C.bc() == Boundary::Periodic;  // wraps: the general stencil throughout
#pragma omp parallel if (F.parallel())
  {
    std::vector<Scalar> m(nc2);  // the coarse lines combined with their plane weights
#pragma omp for schedule(static)
    for (Index row = 0; row < fs.rows(); ++row) {
      const Index i = row / fs.n[1], j = row % fs.n[1];
      Scalar* out = fine + row * nf2;
      const AxisTerm ti = three_d ? axis_term(i, cs.n[0], s0) : AxisTerm{1, 0, 0, 0};
      const AxisTerm tj = axis_term(j, cs.n[1], s1);
      const Index prow = ti.parent * cs.n[1] + tj.parent;
      if (periodic || !(C.row_clear(prow) && F.row_fluid(row))) {
        for (Index k = 0; k < nf2; ++k) {
          if (!F.fluid(row * nf2 + k)) continue;
          Scalar sum = 0;
          prolongation_stencil(F, C, i, j, k, [&](Index ci, Scalar w) { sum += w * coarse[ci]; });
          out[k] += sum;
        }
        continue;
      }
      // Separable: combine the coarse lines of the (i, j) plane, then interpolate along k.
      const Scalar* l00 = coarse + (ti.parent * cs.n[1] + tj.parent) * nc2;
      const Scalar* l01 = coarse + (ti.parent * cs.n[1] + tj.partner) * nc2;
      const Scalar* l10 = coarse + (ti.partner * cs.n[1] + tj.parent) * nc2;
      const Scalar* l11 = coarse + (ti.partner * cs.n[1] + tj.partner) * nc2;
      const Scalar w00 = ti.parent_weight * tj.parent_weight, w01 = ti.parent_weight * tj.partner_weight;
      const Scalar w10 = ti.partner_weight * tj.parent_weight, w11 = ti.partner_weight * tj.partner_weight;
#pragma omp simd
      for (Index K = 0; K < nc2; ++K) m[K] = w00 * l00[K] + w01 * l01[K] + w10 * l10[K] + w11 * l11[K];
      for (Index k : {Index(0), nf2 - 1}) {
        const AxisTerm tk = axis_term(k, nc2, s2);
        out[k] += tk.parent_weight * m[tk.parent] + tk.partner_weight * m[tk.partner];
      }
      for (Index k = 1; k + 1 < nf2; ++k) {
        const Index K = k >> 1;
        out[k] += 0.75 * m[K] + 0.25 * m[(k & 1) ? K + 1 : K - 1];
      }
    }
  }
}

void Multigrid::restrict_residual(int l, const Scalar* fine, Scalar* coarse) const {
  const PoissonOperator& F = level(l);
  const PoissonOperator& C = level(l + 1);
  const GridShape& fs = F.shape();
  const GridShape& cs = C.shape();
  const bool three_d = fs.dim == 3;
  const Scalar scale = three_d ? 1.0 / 8 : 1.0 / 4;  // R = P^T / 2^d
  const Sigma s0 = axis_sigma(C, 0), s1 = axis_sigma(C, 1), s2 = axis_sigma(C, 2);
  const Index nf2 = fs.n[2], nc2 = cs.n[2];
  const bool periodic = C.bc() == Boundary::Periodic;
#pragma omp parallel if (F.parallel())
  {
    std::vector<Scalar> t(nf2);  // the fine lines of the window, plane-weighted
#pragma omp for schedule(static)
    for (Index row = 0; row < cs.rows(); ++row) {
      const Index I = row / cs.n[1], J = row % cs.n[1];
      Scalar* out = coarse + row * nc2;
      if (periodic) {
        for (Index K = 0; K < nc2; ++K) out[K] = scale * restrict_general(l, fine, I, J, K);
        continue;
      }
      if (!C.row_clear(row)) {
        for (Index K = 0; K < nc2; ++K) out[K] = scale * restrict_general(l, fine, I, J, K);
        continue;
      }
      // Separable: the transpose of prolong_add's clear-row path.
      const auto wi = three_d ? window_weights(fs.n[0], cs.n[0], I, s0)
                              : std::array<Scalar, 4>{0, 1, 0, 0};
      const auto wj = window_weights(fs.n[1], cs.n[1], J, s1);
      std::fill(t.begin(), t.end(), 0.0);
      for (int a = 0; a < 4; ++a) {
        if (wi[a] == 0) continue;
        const Index fi = three_d ? 2 * I - 1 + a : 0;
        for (int b = 0; b < 4; ++b) {
          if (wj[b] == 0) continue;
          const Scalar w = wi[a] * wj[b];
          const Scalar* line = fine + fs.index(fi, 2 * J - 1 + b, 0);
#pragma omp simd
          for (Index k = 0; k < nf2; ++k) t[k] += w * line[k];
        }
      }
      for (Index K : {Index(0), nc2 - 1}) {
        const auto wk = window_weights(nf2, nc2, K, s2);
        Scalar sum = 0;
        for (int c = 0; c < 4; ++c)
          if (wk[c] != 0) sum += wk[c] * t[2 * K - 1 + c];
        out[K] = scale * sum;
      }
      for (Index K = 1; K + 1 < nc2; ++K)
        out[K] = scale * (0.25 * (t[2 * K - 1] + t[2 * K + 2]) + 0.75 * (t[2 * K] + t[2 * K + 1]));
    }
  }
}

// Row I of P^T near solids (or anywhere on a periodic grid). A fine cell of the 4^d window
// 2I-1 .. 2I+2 per axis that is not a child of I reaches I only through the separable weights
// (I is fluid and in range; ghost reflections included); a child of I may also reach it through
// solid substitutions, so it takes the general stencil. A periodic window wraps (the fine grid
// has at least 4 cells per axis, so it never meets itself).
Scalar Multigrid::restrict_general(int l, const Scalar* fine, Index I, Index J, Index K) const {
  const PoissonOperator& F = level(l);
  const PoissonOperator& C = level(l + 1);
  const GridShape& fs = F.shape();
  const bool three_d = fs.dim == 3;
  const Index c = C.shape().index(I, J, K);
  if (!C.fluid(c)) return 0;
  const bool periodic = C.bc() == Boundary::Periodic;
  const Index centre[3] = {three_d ? I : 0, J, K};
  std::array<std::array<Scalar, 4>, 3> window{};
  window[0] = {0, 1, 0, 0};  // inactive axis 0 of a 2D grid: the one plane, a "child"
  for (int a = 0; a < 3; ++a)
    if (fs.active(a))
      window[a] = periodic ? std::array<Scalar, 4>{0.25, 0.75, 0.75, 0.25}
                           : window_weights(fs.n[a], C.shape().n[a], centre[a], axis_sigma(C, a));
  // fine index of window offset o along axis a, or -1 outside a closed grid
  auto fine_index = [&](int a, int o) -> Index {
    if (!fs.active(a)) return 0;
    Index f = 2 * centre[a] - 1 + o;
    if (periodic) return f < 0 ? f + fs.n[a] : (f >= fs.n[a] ? f - fs.n[a] : f);
    return f >= 0 && f < fs.n[a] ? f : -1;
  };
  Scalar sum = 0;
  for (int oi = 0; oi < 4; ++oi) {
    const Index i = fine_index(0, oi);
    if (i < 0 || window[0][oi] == 0) continue;
    for (int oj = 0; oj < 4; ++oj) {
      const Index j = fine_index(1, oj);
      if (j < 0) continue;
      for (int ok = 0; ok < 4; ++ok) {
        const Index k = fine_index(2, ok);
        if (k < 0) continue;
        const Index f = fs.index(i, j, k);
        const Scalar rf = fine[f];
        if (rf == 0 || !F.fluid(f)) continue;
        const bool child = (oi == 1 || oi == 2) && (oj == 1 || oj == 2) && (ok == 1 || ok == 2);
        if (!child) {
          sum += window[0][oi] * window[1][oj] * window[2][ok] * rf;
          continue;
        }
        prolongation_stencil(F, C, i, j, k, [&](Index ci, Scalar wc) {
          if (ci == c) sum += wc * rf;
        });
      }
    }
  }
  return sum;
}

}  // namespace kinema
