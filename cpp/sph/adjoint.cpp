// The vector-Jacobian product of one WCSPH step (adjoint.h gives the step's equations). With
// lambda_i = dL/da_i = dt (dL/dv'_i + dt dL/dx'_i), grad W_ij = F(r) x_ij (F = W'(r) / r) and
// its Jacobian H_ij = d(grad W_ij)/dx_i = F I + (F'(r) / r) x_ij x_ij^T (symmetric in i, j):
//   pressure:  dL/dP_i = -m sum_j (lambda_i - lambda_j) . grad W_ij - lambda_i . B_i,
//              dL/dx_i += -m sum_j (P_i + P_j) H_ij (lambda_i - lambda_j) - sum_b psi_b (P_i + P_b) H_ib lambda_i,
//   walls:     (the samples that carry pressure, solver.cpp "The walls"; P_b = 0 for the others)
//              dL/dP_b = -psi_b sum_i lambda_i . grad W_ib, dL/drho_b = dL/dP_b dP_b/drho_b,
//              dL/dx_i += m sum_b dL/drho_b grad W_ib (rho_b = wall_rho_b + sum_i m W_ib),
//   viscosity: each ordered pair (i, j) with c_ij = K nu V_j s_ij (K = 2 (d + 2), V_j = m / rho_j,
//              s_ij = v_ij . x_ij / (|x_ij|^2 + 0.01 h^2)) and mu_ij = lambda_i . grad W_ij gives
//              dL/dv_ij = K nu V_j mu_ij x_ij / den, dL/dx_ij = K nu V_j mu_ij ds/dx_ij + c_ij H_ij lambda_i,
//              dL/drho_j = -c_ij mu_ij / rho_j and dL/dnu = K V_j s_ij mu_ij,
//   density:   dL/dx_i += m sum_j (dL/drho_i + dL/drho_j) grad W_ij + dL/drho_i B_i,
// with dL/drho_i = dL/dP_i dP_i/drho_i + the viscosity's share. Every pair term is gathered by
// both of its particles (each evaluates the pair from its own side), so the passes run in
// parallel without atomics and the result does not depend on the thread count. The neighbour
// set is the step's: the pairs closer than h at before's positions, searched afresh (the same
// set as the forward's Verlet lists filtered to h), in the step's row order (Morton reordering
// at the start of the step is undone through the ids). Branches are those the forward took:
// Tait's clamp p = 0 for rho <= rho0 (kernels.h) and the domain clamp, read off `after` (a
// clamped coordinate equals the wall's exactly; its velocity is 0 when it was cut).
#include "sph/adjoint.h"

#include <Eigen/Core>
#include <cmath>
#include <string>
#include <vector>

#include "core/errors.h"
#include "core/parallel.h"
#include "particles/neighbor_grid.h"
#include "particles/neighbor_lists.h"
#include "sph/kernels.h"
#include "sph/solver.h"
#include "sph/walls.h"

namespace kinema::sph {

// step_adjoint's buffers, sized once and overwritten by every call, and its neighbour search.
struct AdjointScratch {
  std::vector<Scalar> x, v, rho, P, dP, B, lambda, grho, gx, gv, gnu;
  std::vector<Scalar> wall_P, wall_dP, wall_grho;  // (M,) the walls' P_b, dP_b/drho_b, dL/drho_b
  WallRows walls;
  std::vector<Index> order, row_of;
  NeighborGrid<2> grid2, boundary_grid2;
  NeighborGrid<3> grid3, boundary_grid3;
  NeighborLists fluid, boundary;
};

namespace {

// F(r) = W'(r) / r and F'(r) / r of the cubic spline (kernels.h), as grad_factor evaluates F;
// both zero at r = 0 and beyond the support.
template <int D>
struct KernelJacobian {
  explicit KernelJacobian(Scalar h) : W(h) {}
  void operator()(Scalar r, Scalar& F, Scalar& dF_over_r) const {
    F = W.grad_factor(r);
    const Scalar q = r * W.inv_h;
    if (r <= 0 || q >= 1) {
      dF_over_r = 0;
    } else if (q <= 0.5) {
      // F = (6 sigma / h^2) (3 q - 2): F' = 18 sigma / h^3.
      dF_over_r = 18 * W.sigma * W.inv_h * W.inv_h * W.inv_h / r;
    } else {
      // F = -(6 sigma / h) (1 - q)^2 / r: F' = (6 sigma / h) (1 - q) (2 / (h r) + (1 - q) / r^2).
      const Scalar t = 1 - q;
      dF_over_r = 6 * W.sigma * W.inv_h * t * (2 * W.inv_h / r + t / (r * r)) / r;
    }
  }
  CubicSpline<D> W;
};

template <int D>
void adjoint_d(const Model& model, const Config& config, AdjointScratch& s, const State& before, const State& after,
               Scalar dt, State& adjoint, ParamsAdjoint& params, Scalar* adjoint_forces) {
  using Vec = Eigen::Matrix<Scalar, D, 1>;
  using CMap = Eigen::Map<const Vec>;
  using Map = Eigen::Map<Vec>;
  const Index n = before.n;
  const auto nd = static_cast<size_t>(n * D);
  const Scalar m = model.mass, h = model.h, nu = config.viscosity, rho0 = config.rho0, gamma = config.gamma;
  const Scalar c = model.speed_of_sound;
  const Scalar Bt = rho0 * c * c / gamma;  // Tait's B
  const Scalar K = 2 * (D + 2), eps = 0.01 * h * h;
  const KernelJacobian<D> kernel(h);

  // The step's rows: row k of the step (and of after) is row order[k] of before.
  s.row_of.assign(static_cast<size_t>(n), -1);
  for (Index r = 0; r < n; ++r) {
    if (s.row_of[before.ids[r]] >= 0) throw InvalidArgument("before: ids must be a permutation of 0.." + std::to_string(n - 1));
    s.row_of[before.ids[r]] = r;
  }
  s.order.resize(static_cast<size_t>(n));
  for (Index k = 0; k < n; ++k) {
    const Index id = after.ids[k];
    if (id < 0 || id >= n || s.row_of[id] < 0) throw InvalidArgument("after: its ids are not a permutation of before's");
    s.order[k] = s.row_of[id];
    s.row_of[id] = -1;  // taken: a repeated id is refused
  }
  s.x.resize(nd);
  s.v.resize(nd);
  parallel_for(n, [&](Index k) {
    Map(s.x.data() + k * D) = CMap(before.x.data() + s.order[k] * D);
    Map(s.v.data() + k * D) = CMap(before.v.data() + s.order[k] * D);
  });
  const Scalar* x = s.x.data();
  const Scalar* v = s.v.data();

  // The step's neighbour set: pairs closer than h at its positions.
  NeighborGrid<D>& grid = [&]() -> NeighborGrid<D>& {
    if constexpr (D == 2) return s.grid2; else return s.grid3;
  }();
  NeighborGrid<D>& boundary_grid = [&]() -> NeighborGrid<D>& {
    if constexpr (D == 2) return s.boundary_grid2; else return s.boundary_grid3;
  }();
  grid.build(x, n, h);
  s.fluid.build<D>(grid, x, n, h, true);
  const Index nb = model.boundary_count();
  if (nb > 0) {
    boundary_grid.build(model.boundary_x.data(), nb, h);
    s.boundary.build<D>(boundary_grid, x, n, h, false);
  } else {
    s.boundary.start.assign(static_cast<size_t>(n) + 1, 0);
    s.boundary.list.clear();
  }
  const Index* fs = s.fluid.start.data();
  const std::int32_t* fl = s.fluid.list.data();
  const Index* bs = s.boundary.start.data();
  const std::int32_t* bl = s.boundary.list.data();
  const Scalar* xb = model.boundary_x.data();
  const Scalar* psi = model.boundary_psi.data();

  // Densities, boundary gradient sums B_i, P_i = p_i / rho_i^2 and dP_i / drho_i.
  s.rho.resize(static_cast<size_t>(n));
  s.P.resize(static_cast<size_t>(n));
  s.dP.resize(static_cast<size_t>(n));
  s.B.resize(nd);
  parallel_for(n, [&](Index i) {
    const Vec xi = CMap(x + i * D);
    Scalar rho = m * kernel.W.w0();
    for (Index k = fs[i]; k < fs[i + 1]; ++k) rho += m * kernel.W.w((xi - CMap(x + Index{fl[k]} * D)).norm());
    Vec Bi = Vec::Zero();
    for (Index k = bs[i]; k < bs[i + 1]; ++k) {
      const Vec xib = xi - CMap(xb + Index{bl[k]} * D);
      const Scalar r = xib.norm();
      rho += psi[bl[k]] * kernel.W.w(r);
      Bi += psi[bl[k]] * kernel.W.grad_factor(r) * xib;
    }
    Map(s.B.data() + i * D) = Bi;
    const Scalar p = tait_pressure(rho, rho0, Bt, gamma);
    // The branch taken: p = 0 (and dp/drho = 0) at rho <= rho0.
    const Scalar dp = rho > rho0 ? Bt * gamma * std::pow(rho / rho0, gamma - 1) / rho0 : 0;
    s.rho[i] = rho;
    s.P[i] = p / (rho * rho);
    s.dP[i] = dp / (rho * rho) - 2 * p / (rho * rho * rho);
  });

  // The walls' P_b = p_b / rho_b^2 and dP_b / drho_b (zero for the samples without pressure).
  const Index wall_begin = model.wall_begin;
  const bool has_walls = wall_begin < nb;
  s.wall_P.assign(static_cast<size_t>(nb), 0);
  s.wall_dP.assign(static_cast<size_t>(nb), 0);
  s.wall_grho.assign(static_cast<size_t>(nb), 0);
  if (has_walls) {
    s.walls.build(s.boundary, n, wall_begin, nb);
    parallel_for(s.walls.rows(), [&](Index c) {
      const Index b = wall_begin + c;
      const Vec xbb = CMap(xb + b * D);
      Scalar rho = model.wall_rho[b];
      for (Index e = s.walls.start[c]; e < s.walls.start[c + 1]; ++e)
        rho += m * kernel.W.w((CMap(x + Index{s.walls.particle[e]} * D) - xbb).norm());
      const Scalar p = tait_pressure(rho, rho0, Bt, gamma);
      const Scalar dp = rho > rho0 ? Bt * gamma * std::pow(rho / rho0, gamma - 1) / rho0 : 0;
      s.wall_P[b] = p / (rho * rho);
      s.wall_dP[b] = dp / (rho * rho) - 2 * p / (rho * rho * rho);
    });
  }

  // Through the domain clamp and the integrator: x' = x + dt v*, v* = v + dt a.
  s.lambda.resize(nd);
  s.gx.resize(nd);
  s.gv.resize(nd);
  parallel_for(n, [&](Index k) {
    for (int a = 0; a < D; ++a) {
      const size_t e = static_cast<size_t>(k * D + a);
      Scalar gxa = adjoint.x[e], gva = adjoint.v[e];
      if (model.has_domain && (after.x[e] == model.lower[a] || after.x[e] == model.upper[a])) {
        gxa = 0;  // x' = the wall
        if (after.v[e] == 0) gva = 0;  // v' = max(v*, 0) (min at the upper wall) was cut
      }
      const Scalar gvs = gva + dt * gxa;  // dL/dv*
      s.gx[e] = gxa;
      s.gv[e] = gvs;
      s.lambda[e] = dt * gvs;
    }
  });
  const Scalar* lambda = s.lambda.data();
  if (adjoint_forces)
    parallel_for(n, [&](Index k) { Map(adjoint_forces + after.ids[k] * D) = CMap(lambda + k * D) / m; });

  // Pressure and viscosity, gathered per particle: dL/dx, dL/dv, dL/drho, dL/dnu.
  s.grho.resize(static_cast<size_t>(n));
  s.gnu.resize(static_cast<size_t>(n));
  parallel_for(n, [&](Index i) {
    const Vec xi = CMap(x + i * D), vi = CMap(v + i * D), li = CMap(lambda + i * D);
    const Scalar Vi = m / s.rho[i];
    Vec gxi = Vec::Zero(), gvi = Vec::Zero();
    Scalar gP = 0, grho = 0, gnu = 0;
    for (Index k = fs[i]; k < fs[i + 1]; ++k) {
      const Index j = fl[k];
      const Vec xij = xi - CMap(x + j * D), vij = vi - CMap(v + j * D), lj = CMap(lambda + j * D);
      const Scalar r = xij.norm();
      Scalar F, dF;
      kernel(r, F, dF);
      const Vec g = F * xij;
      auto H = [&](const Vec& u) -> Vec { return F * u + (dF * xij.dot(u)) * xij; };
      // pressure
      const Vec dl = li - lj;
      gP -= m * dl.dot(g);
      gxi -= m * (s.P[i] + s.P[j]) * H(dl);
      // viscosity: the pair (i, j) of i's row ...
      const Scalar den = 1 / (xij.squaredNorm() + eps);
      const Scalar sij = vij.dot(xij) * den;
      const Vec ds = (vij - 2 * sij * xij) * den;  // ds_ij / dx_ij
      const Scalar Vj = m / s.rho[j];
      const Scalar mu = li.dot(g);
      gnu += K * Vj * sij * mu;
      gvi += (K * nu * Vj * mu * den) * xij;
      gxi += (K * nu * Vj * mu) * ds + (K * nu * Vj * sij) * H(li);
      // ... and the pair (j, i) of j's row (x_ji = -x_ij, v_ji = -v_ij, grad W_ji = -g).
      const Scalar mu_ji = -lj.dot(g);
      const Scalar c_ji = K * nu * Vi * sij;
      gvi += (K * nu * Vi * mu_ji * den) * xij;
      gxi += (K * nu * Vi * mu_ji) * ds - c_ji * H(lj);
      grho -= c_ji * mu_ji / s.rho[i];
    }
    // the boundary's pressure -P_i B_i - sum_b psi_b P_b grad W_ib
    const Vec Bi = CMap(s.B.data() + i * D);
    gP -= li.dot(Bi);
    for (Index k = bs[i]; k < bs[i + 1]; ++k) {
      const Index b = bl[k];
      const Vec xib = xi - CMap(xb + b * D);
      Scalar F, dF;
      kernel(xib.norm(), F, dF);
      gxi -= (s.P[i] + s.wall_P[b]) * psi[b] * (F * li + (dF * xib.dot(li)) * xib);
    }
    s.grho[i] = grho + gP * s.dP[i];
    s.gnu[i] = gnu;
    Map(s.gx.data() + i * D) += gxi;
    Map(s.gv.data() + i * D) += gvi;
  });

  // The walls' dL/drho_b = -psi_b sum_i lambda_i . grad W_ib dP_b/drho_b.
  if (has_walls)
    parallel_for(s.walls.rows(), [&](Index c) {
      const Index b = wall_begin + c;
      const Vec xbb = CMap(xb + b * D);
      Scalar gP = 0;
      for (Index e = s.walls.start[c]; e < s.walls.start[c + 1]; ++e) {
        const Index i = s.walls.particle[e];
        const Vec xib = CMap(x + i * D) - xbb;
        gP -= CMap(lambda + i * D).dot(kernel.W.grad_factor(xib.norm()) * xib);
      }
      s.wall_grho[b] = psi[b] * gP * s.wall_dP[b];
    });

  // Densities: dL/dx_i += m sum_j (dL/drho_i + dL/drho_j) grad W_ij + dL/drho_i B_i
  //                      + m sum_b dL/drho_b grad W_ib.
  parallel_for(n, [&](Index i) {
    const Vec xi = CMap(x + i * D);
    Vec gxi = s.grho[i] * CMap(s.B.data() + i * D);
    if (has_walls)
      for (Index k = bs[i]; k < bs[i + 1]; ++k) {
        const Index b = bl[k];
        if (b < wall_begin) continue;
        const Vec xib = xi - CMap(xb + b * D);
        gxi += (m * s.wall_grho[b] * kernel.W.grad_factor(xib.norm())) * xib;
      }
    for (Index k = fs[i]; k < fs[i + 1]; ++k) {
      const Index j = fl[k];
      const Vec xij = xi - CMap(x + j * D);
      gxi += (m * (s.grho[i] + s.grho[j]) * kernel.W.grad_factor(xij.norm())) * xij;
    }
    Map(s.gx.data() + i * D) += gxi;
  });

  // Back to before's rows.
  parallel_for(n, [&](Index k) {
    Map(adjoint.x.data() + s.order[k] * D) = CMap(s.gx.data() + k * D);
    Map(adjoint.v.data() + s.order[k] * D) = CMap(s.gv.data() + k * D);
  });
  params.viscosity += parallel_sum(n, [&](Index i) { return s.gnu[i]; });
}

}  // namespace

void Solver::step_adjoint(const State& before, const State& after, Scalar dt, State& adjoint,
                          ParamsAdjoint& adjoint_params, Scalar* adjoint_forces, Interrupt& interrupt) {
  const Model& model = this->model();
  const Config& config = this->config();
  if (config.method != Method::WCSPH)
    throw InvalidArgument("method: gradients need method=\"wcsph\"; DFSPH's pressure solves are projected "
                          "Jacobi iterations stopped at a tolerance, not differentiable as run");
  if (!(dt > 0) || !std::isfinite(dt)) throw InvalidArgument("dt: expected a finite number > 0, got " + format_real(dt));
  const int d = model.dim;
  const Index n = before.n;
  const auto nd = static_cast<size_t>(n * d);
  for (const State* s : {&before, &after, static_cast<const State*>(&adjoint)})
    if (s->dim != d || s->n != n || s->x.size() != nd || s->v.size() != nd)
      throw InvalidArgument("before, after, adjoint: expected states of " + std::to_string(n) + " particles in " +
                            std::to_string(d) + "D");
  if (before.ids.size() != static_cast<size_t>(n) || after.ids.size() != static_cast<size_t>(n))
    throw InvalidArgument("before, after: expected the ids of " + std::to_string(n) + " particles");
  for (Index k = 0; k < n; ++k)
    if (before.ids[k] < 0 || before.ids[k] >= n)
      throw InvalidArgument("before: ids must be a permutation of 0.." + std::to_string(n - 1));
  interrupt.check();
  if (!adjoint_) adjoint_ = std::make_shared<AdjointScratch>();
  if (d == 2) adjoint_d<2>(model, config, *adjoint_, before, after, dt, adjoint, adjoint_params, adjoint_forces);
  else adjoint_d<3>(model, config, *adjoint_, before, after, dt, adjoint, adjoint_params, adjoint_forces);
}

}  // namespace kinema::sph
