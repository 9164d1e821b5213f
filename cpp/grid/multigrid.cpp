#include "grid/multigrid.h"

#include <Eigen/SparseCholesky>
#include <algorithm>

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
  for (int axis = 0; axis < 3; ++axis)
    if (op.shape().active(axis) && op.shape().n[axis] < 4) return false;
  return true;
}

// Calls emit(coarse_index, weight) for the terms of (P x_c) at fine cell (i, j, k): the 2^d
// coarse cells nearest to the fine cell centre with the (3/4, 1/4) weights per axis; a coarse
// cell across the domain boundary is replaced by the in-range one with the sign of the ghost
// value (-1 Dirichlet, +1 Neumann), and a solid coarse cell by the parent.
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
  const Scalar ghost_sign = coarse.bc() == Boundary::Dirichlet ? -1 : 1;
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
        c[a] = parent[a];
        sign *= ghost_sign;
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
    A.smooth_color(b, x, 0);
    A.smooth_color(b, x, 1);
  }
  A.residual(b, x, r_[l].data());
  restrict_residual(l, r_[l].data(), b_[l + 1].data());
  cycle(l + 1, b_[l + 1].data(), x_[l + 1].data());
  prolong_add(l, x_[l + 1].data(), x);
  for (int s = 0; s < options_.post_smooth; ++s) {
    A.smooth_color(b, x, 1);
    A.smooth_color(b, x, 0);
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

void Multigrid::prolong_add(int l, const Scalar* coarse, Scalar* fine) const {
  const PoissonOperator& F = level(l);
  const PoissonOperator& C = level(l + 1);
  const GridShape& fs = F.shape();
  const GridShape& cs = C.shape();
  const bool three_d = fs.dim == 3;
  const Index cs0 = cs.stride(0), cs1 = cs.stride(1);
#pragma omp parallel for schedule(static)
  for (Index row = 0; row < fs.rows(); ++row) {
    const Index i = row / fs.n[1], j = row % fs.n[1];
    const Index I = three_d ? i / 2 : 0, J = j / 2;
    const Index di = three_d ? ((i & 1) ? cs0 : -cs0) : 0;
    const Index dj = (j & 1) ? cs1 : -cs1;
    for (Index k = 0; k < fs.n[2]; ++k) {
      const Index f = row * fs.n[2] + k;
      if (!F.fluid(f)) continue;
      const Index p = cs.index(I, J, k / 2);
      if (C.interior(p)) {
        const Index dk = (k & 1) ? 1 : -1;
        if (three_d) {
          fine[f] += (27.0 / 64) * coarse[p] +
                     (9.0 / 64) * (coarse[p + di] + coarse[p + dj] + coarse[p + dk]) +
                     (3.0 / 64) * (coarse[p + di + dj] + coarse[p + di + dk] + coarse[p + dj + dk]) +
                     (1.0 / 64) * coarse[p + di + dj + dk];
        } else {
          fine[f] += (9.0 / 16) * coarse[p] + (3.0 / 16) * (coarse[p + dj] + coarse[p + dk]) +
                     (1.0 / 16) * coarse[p + dj + dk];
        }
      } else {
        Scalar sum = 0;
        prolongation_stencil(F, C, i, j, k, [&](Index ci, Scalar w) { sum += w * coarse[ci]; });
        fine[f] += sum;
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
  static constexpr Scalar kW[4] = {0.25, 0.75, 0.75, 0.25};
  const Index fs0 = fs.stride(0), fs1 = fs.stride(1);
#pragma omp parallel for schedule(static)
  for (Index row = 0; row < cs.rows(); ++row) {
    const Index I = row / cs.n[1], J = row % cs.n[1];
    for (Index K = 0; K < cs.n[2]; ++K) {
      const Index c = row * cs.n[2] + K;
      if (!C.fluid(c)) {
        coarse[c] = 0;
        continue;
      }
      Scalar sum = 0;
      if (C.interior(c)) {
        // The 4^d fine window 2I-1 .. 2I+2 per axis with the tensor weights (1,3,3,1)/4.
        const Index i0 = three_d ? 2 * I - 1 : 0, j0 = 2 * J - 1, k0 = 2 * K - 1;
        const int ni = three_d ? 4 : 1;
        for (int a = 0; a < ni; ++a) {
          const Scalar wa = three_d ? kW[a] : 1.0;
          for (int b = 0; b < 4; ++b) {
            const Scalar* line = fine + (i0 + a) * fs0 + (j0 + b) * fs1 + k0;
            sum += wa * kW[b] *
                   (0.25 * (line[0] + line[3]) + 0.75 * (line[1] + line[2]));
          }
        }
      } else {
        // Gather the transpose of the general prolongation stencil over the fine window.
        const Index lo[3] = {three_d ? std::max<Index>(2 * I - 1, 0) : 0, std::max<Index>(2 * J - 1, 0),
                             std::max<Index>(2 * K - 1, 0)};
        const Index hi[3] = {three_d ? std::min<Index>(2 * I + 2, fs.n[0] - 1) : 0,
                             std::min<Index>(2 * J + 2, fs.n[1] - 1),
                             std::min<Index>(2 * K + 2, fs.n[2] - 1)};
        for (Index i = lo[0]; i <= hi[0]; ++i)
          for (Index j = lo[1]; j <= hi[1]; ++j)
            for (Index k = lo[2]; k <= hi[2]; ++k) {
              const Index f = fs.index(i, j, k);
              if (!F.fluid(f)) continue;
              const Scalar rf = fine[f];
              prolongation_stencil(F, C, i, j, k, [&](Index ci, Scalar w) {
                if (ci == c) sum += w * rf;
              });
            }
      }
      coarse[c] = scale * sum;
    }
  }
}

}  // namespace kinema
