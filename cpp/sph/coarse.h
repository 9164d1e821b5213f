// The coarse space of DFSPH's density solve (a two-level correction, issue 15): hat functions of
// the height, nodes every `width` along the gravity axis, so one stiffness per layer of the
// fluid, linearly interpolated in between (the prolongation P); the Galerkin operator
// A_c = P^T A P of the solve's matrix A restricted to the particles that are compressed or hold
// pressure; one exact coarse solve per density solve.
//
// Why: a column at rest is held by a pressure that grows linearly with depth, the longest mode
// of the solve, which a Jacobi iteration rebuilds by about 1% per iteration (bench/sph/
// sph_column_cycle.py, sph_dfsph_iterations.py). Under a loose tolerance the solve stopped
// before it had, the column sank while the mean compression stayed inside the tolerance, and
// the step that finally reached tol kicked it back up (12,900 Pa against rho0 g H / 2 = 2,450).
// The coarse correction removes the layer-averaged compression rate at the start of each solve.
//
// The matrix: the solve changes the stiffnesses by kappa and the velocities by -dt M kappa,
// (M kappa)_i = kappa_i (G_i + B_i) + m sum_j kappa_j grad_i W_ij, and reads its residual through
// the density rate (R v)_i = G_i . v_i - m sum_j grad_i W_ij . v_j, so A = R M. With symmetric
// neighbour lists and grad_i W_ij = -grad_j W_ji,
//   (A_c)_cd = sum_i u_i^c . z_i^d,  S_i^c = m sum_{j in N(i), j active} N_c(x_j) grad_i W_ij,
//   u_i^c = S_i^c + [i active] N_c(x_i) G_i,  z_i^d = S_i^d + [i active] N_d(x_i) (G_i + B_i),
// one pass over the neighbour lists; nodes at least h apart make it pentadiagonal. The sums run
// in a fixed order (particles grouped by layer, fixed chunks of each layer), so the operator is
// the same bit for bit whatever the thread count.
#pragma once

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#include "core/parallel.h"
#include "core/types.h"

namespace kinema::sph {

template <int D>
class CoarseSpace {
 public:
  using Vec = Eigen::Matrix<Scalar, D, 1>;

  // Builds P and factors A_c for the particles x (n, d) with the step's exact neighbour lists
  // (start, list and the stored kernel gradients grads, D floats per entry), particle mass m,
  // the gradient sums G (fluid and boundary) and B (boundary); `active` (n,) marks the particles
  // in the coarse problem. Returns false (the space then unused) when the fluid spans more
  // than kMaxNodes layers or no node holds enough particles.
  bool build(const Scalar* x, Index n, Scalar width, int axis, const Index* start, const std::int32_t* list,
             const float* grads, Scalar m, const Scalar* G, const Scalar* B, const char* active) {
    ready_ = false;
    if (n == 0) return false;
    Scalar lo = x[axis];
    for (Index i = 1; i < n; ++i) lo = std::min(lo, x[i * D + axis]);
    layer_.resize(static_cast<size_t>(n));
    t_.resize(static_cast<size_t>(n));
    std::int32_t layers = 1;
    for (Index i = 0; i < n; ++i) {
      const Scalar u = (x[i * D + axis] - lo) / width;
      const Scalar f = std::floor(u);
      if (!(f < kMaxNodes)) return false;
      layer_[i] = static_cast<std::int32_t>(f);
      t_[i] = std::min<Scalar>(std::max<Scalar>(u - f, 0), 1);
      layers = std::max(layers, layer_[i] + 1);
    }
    const std::int32_t nodes = layers + 1;
    nodes_ = nodes;
    // Particles grouped by layer (counting sort, stable), cut into chunks of at most kChunk.
    layer_start_.assign(static_cast<size_t>(layers) + 1, 0);
    for (Index i = 0; i < n; ++i) ++layer_start_[layer_[i] + 1];
    for (std::int32_t l = 0; l < layers; ++l) layer_start_[l + 1] += layer_start_[l];
    members_.resize(static_cast<size_t>(n));
    {
      std::vector<Index> fill(layer_start_.begin(), layer_start_.end() - 1);
      for (Index i = 0; i < n; ++i) members_[fill[layer_[i]]++] = i;
    }
    chunks_.clear();
    for (std::int32_t l = 0; l < layers; ++l)
      for (Index b = layer_start_[l]; b < layer_start_[l + 1]; b += kChunk)
        chunks_.push_back({l, b, std::min(layer_start_[l + 1], b + kChunk)});
    // Each chunk's contributions to (A_c)_{l+a, l+b}, a and b node offsets -1..2 from its
    // layer l, and to the nodes' shares (the active particles' weights).
    const Index nchunks = static_cast<Index>(chunks_.size());
    partial_.assign(static_cast<size_t>(nchunks) * 20, 0);
#pragma omp parallel for schedule(dynamic, 1)
    for (Index q = 0; q < nchunks; ++q) {
      Scalar* block = partial_.data() + q * 20;
      const std::int32_t l = chunks_[q].layer;
      for (Index e = chunks_[q].begin; e < chunks_[q].end; ++e) {
        const Index i = members_[e];
        Vec S[4] = {Vec::Zero(), Vec::Zero(), Vec::Zero(), Vec::Zero()};
        for (Index k = start[i]; k < start[i + 1]; ++k) {
          const Index j = list[k];
          if (!active[j]) continue;
          const Vec g = m * Eigen::Map<const Eigen::Matrix<float, D, 1>>(grads + k * D).template cast<Scalar>();
          const int d = layer_[j] - l + 1;  // 0..2: neighbours lie within h < width
          S[d] += (1 - t_[j]) * g;
          S[d + 1] += t_[j] * g;
        }
        Vec u[4] = {S[0], S[1], S[2], S[3]}, z[4] = {S[0], S[1], S[2], S[3]};
        if (active[i]) {
          const Vec Gi = Eigen::Map<const Vec>(G + i * D);
          const Vec GBi = Gi + Eigen::Map<const Vec>(B + i * D);
          u[1] += (1 - t_[i]) * Gi;
          u[2] += t_[i] * Gi;
          z[1] += (1 - t_[i]) * GBi;
          z[2] += t_[i] * GBi;
          block[16 + 1] += 1 - t_[i];
          block[16 + 2] += t_[i];
        }
        for (int a = 0; a < 4; ++a)
          for (int b = 0; b < 4; ++b) block[a * 4 + b] += u[a].dot(z[b]);
      }
    }
    // A_c and the shares, the chunks added in order.
    Eigen::MatrixXd Ac = Eigen::MatrixXd::Zero(nodes, nodes);
    std::vector<Scalar> share(static_cast<size_t>(nodes), 0);
    for (Index q = 0; q < nchunks; ++q) {
      const Scalar* block = partial_.data() + q * 20;
      const std::int32_t l = chunks_[q].layer;
      for (int a = 0; a < 4; ++a) {
        const std::int32_t c = l + a - 1;
        if (c < 0 || c >= nodes) continue;
        share[c] += block[16 + a];
        for (int b = 0; b < 4; ++b) {
          const std::int32_t d = l + b - 1;
          if (d >= 0 && d < nodes) Ac(c, d) += block[a * 4 + b];
        }
      }
    }
    // A node holding less than kMinShare of the fullest node's active particles (the surface,
    // a splash) is left out (K = 0 there): the coarse space would otherwise fit a few
    // particles' errors with large, poorly determined stiffnesses.
    const Scalar full = *std::max_element(share.begin(), share.end());
    if (!(full > 0)) return false;
    dead_.assign(static_cast<size_t>(nodes), 0);
    const Scalar scale = Ac.diagonal().cwiseAbs().maxCoeff();  // of the identity rows (for rcond)
    for (std::int32_t c = 0; c < nodes; ++c)
      if (share[c] < kMinShare * full || !(Ac(c, c) > 0)) {
        dead_[c] = 1;
        Ac.row(c).setZero();
        Ac.col(c).setZero();
        Ac(c, c) = scale > 0 ? scale : 1;
      }
    lu_.compute(Ac);
    // (Near-)singular: a fluid whose pressed layers barely couple (a splash, a jet around an
    // obstacle). Measured on a column falling onto a circle: rcond 7e-3 to 0.3 or below 2e-6
    // (down to 0, which gave non-finite K and a blown-up step), nothing in between.
    if (!(lu_.rcond() > kMinRcond)) return false;
    rhs_.resize(nodes);
    ready_ = true;
    return true;
  }

  bool ready() const { return ready_; }

  // K = A_c^{-1} P^T r / scale: the nodes' stiffness corrections for the residual r (n,) of
  // the active particles.
  void solve(const Scalar* r, const char* active, Scalar scale) {
    rhs_.setZero();
    for (Index e = 0; e < static_cast<Index>(members_.size()); ++e) {
      const Index i = members_[e];
      if (!active[i]) continue;
      rhs_[layer_[i]] += (1 - t_[i]) * r[i];
      rhs_[layer_[i] + 1] += t_[i] * r[i];
    }
    for (std::int32_t c = 0; c < nodes_; ++c) rhs_[c] = dead_[c] ? 0 : rhs_[c] / scale;
    K_ = lu_.solve(rhs_);
    if (!K_.allFinite()) K_.setZero();
  }

  // (P K)_i, the correction at particle i (0 for a particle outside the coarse problem).
  Scalar at(Index i, const char* active) const {
    return active[i] ? (1 - t_[i]) * K_[layer_[i]] + t_[i] * K_[layer_[i] + 1] : 0;
  }

  static constexpr std::int32_t kMaxNodes = 256;
  static constexpr Index kChunk = 2048;
  static constexpr Scalar kMinShare = 0.25;
  static constexpr Scalar kMinRcond = 1e-4;  // of A_c, its identity rows at its largest diagonal

 private:
  struct Chunk {
    std::int32_t layer;
    Index begin, end;
  };
  bool ready_ = false;
  std::int32_t nodes_ = 0;
  std::vector<std::int32_t> layer_;  // (n,) layer of each particle
  std::vector<Scalar> t_;            // (n,) position within the layer, [0, 1]
  std::vector<Index> layer_start_, members_;
  std::vector<Chunk> chunks_;
  std::vector<Scalar> partial_;      // (chunks, 20): 4 x 4 block and 4 shares
  std::vector<char> dead_;
  Eigen::PartialPivLU<Eigen::MatrixXd> lu_;
  Eigen::VectorXd rhs_, K_;
};

}  // namespace kinema::sph
