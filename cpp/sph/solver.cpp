// The WCSPH and DFSPH time steps. One implementation serves 2D and 3D (templated on D).
// Equation numbers: Becker and Teschner 2007 (WCSPH), Bender and Koschier 2017 (DFSPH,
// "Divergence-Free SPH for Incompressible and Viscous Fluids", IEEE TVCG), Akinci et al. 2012
// (boundary), Koschier et al. 2019 (the course notes: kernel, viscosity, CFL).
#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <sstream>

#include "core/errors.h"
#include "core/parallel.h"
#include "core/timer.h"
#include "particles/neighbor_grid.h"
#include "particles/neighbor_lists.h"
#include "sph/coarse.h"
#include "sph/kernels.h"
#include "sph/solver.h"
#include "sph/walls.h"

namespace kinema::sph {

// The solver of one dimension behind Solver (SolverD<2> or SolverD<3>).
struct Solver::Impl {
  Impl(const Model& model, const Config& config) : model_(model), config_(config) {}
  virtual ~Impl() = default;
  virtual StepStats step(State& state, Scalar dt, Interrupt& interrupt, const Scalar* forces) = 0;
  virtual Scalar stable_dt(const State& state, Scalar cfl) const = 0;
  virtual Scalar density_error(State& state) = 0;
  virtual std::vector<Index> neighbor_pairs_in_use(State& state, std::vector<Index>& boundary_pairs) = 0;
  virtual void restore_lists(State& state, const std::vector<Scalar>& x, Scalar skin) = 0;
  const Model model_;
  const Config config_;
};

namespace {

template <int D>
class SolverD final : public Solver::Impl {
 public:
  using Vec = Eigen::Matrix<Scalar, D, 1>;
  using Map = Eigen::Map<Vec>;
  using CMap = Eigen::Map<const Vec>;

  SolverD(const Model& model, const Config& config)
      : Impl(model, config), W_(model.h), c_(model.speed_of_sound), rows_(RowSums<D>::choose(use_avx2())) {
    values_avx2_ = use_avx2() && cpu_has_avx2();
    for (int a = 0; a < D; ++a) g_[a] = config.gravity[a];
    const bool coarse = config.coarse_correction > 0 || (config.coarse_correction < 0 && config.tol > Config::kCoarseAutoTol);
    if (coarse && g_.norm() > 0) g_.cwiseAbs().maxCoeff(&coarse_axis_);
    B_ = config.rho0 * c_ * c_ / config.gamma;
  }

  StepStats step(State& s, Scalar dt, Interrupt& interrupt, const Scalar* forces) override {
    if (!(dt > 0) || !std::isfinite(dt))
      throw InvalidArgument("dt: expected a finite number > 0, got " + format_real(dt));
    prepare(s);
    forces_ = forces;
    Stopwatch watch;
    StepStats stats;
    stats.dt = dt;
    if (config_.method == Method::WCSPH) step_wcsph(s, dt, stats);
    else step_dfsph(s, dt, stats, interrupt);
    s.time += dt;
    ++s.steps;
    s.last_dt = dt;
    stats.time = s.time;
    stats.max_speed = check_state(s, dt);
    stats.neighbor_count = fluid().size();
    stats.neighbor_rebuild = rebuilt_;
    stats.search_seconds = search_seconds_;
    stats.kernel_seconds = kernel_seconds_;
    stats.seconds = watch.seconds();
    return stats;
  }

  Scalar stable_dt(const State& s, Scalar cfl) const override {
    if (s.dim != D || s.v.size() != static_cast<size_t>(s.n * D))
      throw InvalidArgument("state: expected the velocities of " + std::to_string(s.n) + " particles in " +
                            std::to_string(D) + "D");
    if (!(cfl > 0) || !std::isfinite(cfl)) throw InvalidArgument("cfl: expected a finite number > 0, got " + format_real(cfl));
    const Scalar vmax = max_speed(s);
    const Scalar signal = config_.method == Method::WCSPH ? c_ + vmax : vmax;
    Scalar dt = Solver::kMaxDt;
    if (signal > 0) dt = std::min(dt, cfl * model_.spacing / signal);
    // Explicit viscosity: dt <= kViscousDt spacing^2 / nu. The viscosity term's largest
    // eigenvalue is 13.1 nu / spacing^2 on a 2D lattice (14.2 in 3D) and 19.3 (21.4) once the
    // particles are displaced by 0.2 spacing at random, as settled fluid is (computed by
    // bench/sph/sph_dam_front_and_rest.py --viscous-spectrum), so forward Euler's bound 2 / lambda falls from
    // 0.15 to 0.10 spacing^2 / nu. The 0.125 used before (Morris et al. 1997, eq. 24) was past
    // it: a viscous column at rest at that step kept ~2 J of noise (issue 15). 0.05 keeps
    // dt lambda <= 1, where no mode changes sign.
    if (config_.viscosity > 0) dt = std::min(dt, kViscousDt * model_.spacing * model_.spacing / config_.viscosity);
    // At rest the fluid first accelerates under gravity: keep g dt^2 below 0.1 cfl * spacing.
    // (cfl * spacing before: a column of 2.5 mm spacing released at 5 ms steps threw particles
    // out at 2 m/s, 15 m/s once DFSPH could give back warm-started pressure; tests/test_sph.py
    // test_coarse_and_fine_spacing.)
    const Scalar g = g_.norm();
    if (g > 0) dt = std::min(dt, std::sqrt(0.1 * cfl * model_.spacing / g));
    return dt;
  }

  Scalar density_error(State& s) override {
    prepare(s);
    check_finite(s, "x", s.x);
    neighborhoods(s, false, false, s.density.data());
    if (config_.method == Method::WCSPH) pressures(s);
    return mean_compression(s.density.data(), s.n);
  }

 private:
  // ------------------------------------------------------------------ time steps

  // Becker and Teschner 2007, section 3, with symplectic Euler.
  void step_wcsph(State& s, Scalar dt, StepStats& stats) {
    // Neighbourhoods of the current positions (Morton reordering every few steps), the step's
    // kernel gradients and the densities rho_i = sum_j m W_ij + sum_b psi_b W_ib (Akinci et al. 2012, eq. 5).
    neighborhoods(s, true, false, s.density.data());
    // Pressure from Tait's equation of state (Becker and Teschner 2007, eq. 6).
    pressures(s);
    // Accelerations: gravity, viscosity (course notes eq. 33) and the symmetric pressure force
    // a_i = -sum_j m (p_i/rho_i^2 + p_j/rho_j^2) grad W_ij (eq. 5) with the walls' terms
    // (pressure_accelerations).
    non_pressure_accelerations(s);
    Stopwatch solve;
    pressure_accelerations(s);
    stats.solve_seconds = solve.seconds();
    // Symplectic Euler: v += dt a, then x += dt v.
    const Index n = s.n;
    parallel_for(n, [&](Index i) {
      Map v(s.v.data() + i * D);
      v += dt * CMap(accel_.data() + i * D);
      Map(s.x.data() + i * D) += dt * v;
    });
    enforce_domain(s);
    stats.density_error = mean_compression(s.density.data(), n);
  }

  // Bender and Koschier 2017, Algorithm 1 (rotated so that a step starts from the positions
  // it is given, as SPlisHSPlasH's TimeStepDFSPH::step does).
  void step_dfsph(State& s, Scalar dt, StepStats& stats, Interrupt& interrupt) {
    const Index n = s.n;
    pending_apply_ = false;
    // Neighbourhoods of the current positions (Verlet lists; Morton reordering every few steps),
    // the step's kernel gradients, densities and the factors alpha_i (eq. 11).
    neighborhoods(s, true, true, s.density.data());
    // Divergence-free solver (Algorithm 2): make D rho / Dt = 0 with the current velocities.
    Stopwatch solve;
    if (config_.divergence_solve) {
      stats.divergence_iterations = divergence_solve(s, dt, stats, interrupt);
      stats.divergence_converged = stats.divergence_error <= config_.divergence_tol;
    }
    stats.solve_seconds = solve.seconds();
    // Non-pressure accelerations (gravity, viscosity) and the predicted velocity v* (eq. 2).
    non_pressure_accelerations(s);
    parallel_for(n, [&](Index i) { Map(s.v.data() + i * D) += dt * CMap(accel_.data() + i * D); });
    // Constant-density solver (Algorithm 3): correct v* so that rho* = rho0.
    solve.restart();
    stats.iterations = density_solve(s, dt, stats, interrupt);
    stats.density_converged = stats.density_error <= config_.tol;
    stats.solve_seconds += solve.seconds();
    // Positions: x += dt v*.
    parallel_for(n, [&](Index i) { Map(s.x.data() + i * D) += dt * CMap(s.v.data() + i * D); });
    enforce_domain(s);
    // The step's pressure: both solvers change velocities as the force -(m_i / rho_i) grad p_i
    // with p_i = kappa_i rho_i would over dt (Bender and Koschier 2017, eqs. 5-6), at the same
    // positions, and s.kappa_density and s.kappa_divergence hold their kappa_i / rho_i (warm start
    // and iterations). Both count: in a column at rest the divergence solve's warm start carries
    // part of the weight, and the density solve's share alone read 0.2-1.5 rho0 g (H - y).
    parallel_for(n, [&](Index i) {
      s.pressure[i] = s.density[i] * s.density[i] * (s.kappa_density[i] + s.kappa_divergence[i]);
    });
  }

  // ------------------------------------------------------------------ DFSPH solvers

  // The step's fluid neighbour list with its kernel gradients, as raw pointers for the inner
  // loops (valid from the step's kernel_pass until its positions move).
  struct Pairs {
    const Index* start;
    const std::int32_t* list;
    const float* grads;  // grad_i W_ij of each entry at the step's positions, D floats
    // grad_i W_ij of entry k = j.
    Vec grad(Index k) const { return Eigen::Map<const Eigen::Matrix<float, D, 1>>(grads + k * D).template cast<Scalar>(); }
  };
  Pairs fluid_pairs() const { return {fluid().start.data(), fluid().list.data(), fluid_grad_.data()}; }

  // sum_j (c_i + c_j) grad W_ij over the fluid neighbours j of i (c: one value per particle).
  Vec symmetric_gradient_sum(const Pairs& f, const Scalar* c, Index i) const {
    Vec sum;
    rows_.weighted(f.list, f.grads, f.start[i], f.start[i + 1], c[i], c, sum.data());
    return sum;
  }

  // The light passes below rest on the step's gradient sums (kernel_pass) G_i = sum_j m grad
  // W_ij + sum_b psi_b grad W_ib and B_i = sum_b psi_b grad W_ib, which take the boundary
  // lists and every term in v_i out of the loops over neighbours: what is left is one gather
  // (v_j or k_j) and D multiply-adds per fluid entry.

  // Rate of density change of i under the velocities v (eq. 9),
  //   D rho_i / Dt = sum_j m (v_i - v_j) . grad W_ij + sum_b psi_b v_i . grad W_ib
  //                = v_i . G_i - m sum_j v_j . grad W_ij.
  // With rows_.dot4 the sum reads v_j from v4_, which mirrors v padded to 4 doubles (sync_v4).
  Scalar density_rate(const Pairs& f, const Scalar* v, Index i) const {
    const Scalar sum = rows_.dot4 ? rows_.dot4(f.list, f.grads, f.start[i], f.start[i + 1], v4_.data())
                                  : rows_.dot(f.list, f.grads, f.start[i], f.start[i + 1], v);
    return CMap(v + i * D).dot(CMap(grad_sum_.data() + i * D)) - model_.mass * sum;
  }

  // v4_ := the velocities v_i padded to 4 doubles, (v_i, 0), where rows_.dot4 reads them.
  void sync_v4(const State& s) {
    if (!rows_.dot4) return;
    parallel_for(s.n, [&](Index i) { store_v4(s, i); });
  }
  void store_v4(const State& s, Index i) {
    for (int a = 0; a < D; ++a) v4_[4 * i + a] = s.v[i * D + a];
    for (int a = D; a < 4; ++a) v4_[4 * i + a] = 0;
  }

  // The velocity change of one iteration's stiffness increments k_i = kappa_i / rho_i (in
  // kappa_), eqs. 6 and 12, with the static boundary's samples b carrying a stiffness k_b:
  //   v_i -= dt (m sum_j (k_i + k_j) grad W_ij + sum_b psi_b (k_i + k_b) grad W_ib).
  // With Config::shepard_walls (the default since issue 15) the domain's walls (Model::wall_begin
  // on) carry one stiffness per sample, the Shepard average of their fluid neighbours',
  //   k_b = sum_i W_ib k_i / sum_i W_ib                         (dfsph_wall_pass),
  // so that the wall force has the form of a constraint force, J^T k with one multiplier per
  // wall sample on the wall's density rho_b (the form of WCSPH's walls below): a column at rest
  // filling its tank keeps its energy (2D 5 mm -0.0%, 3D 5 mm -0.1%, 2D 2.5 mm +0.8% of the
  // available energy; tests/test_sph.py, the filled tank), and beside a wall at rest k_b is
  // about k_i, so the wall holds what the symmetric fluid term pushes (3D column at rest: slope
  // 0.98-1.03 rho0 g; at tol 1e-3 its rms speed 0.062 m/s is at the test's bound 0.063;
  // bench/sph/sph_column_cycle.py). The coarse 3D dam break's front runs 8% ahead of WCSPH's at
  // T = 2, as far as WCSPH's own front moves from 8 to 16 across (docs/guide/sph.md).
  // Without it every sample mirrors the particle it pushes, k_b = k_i (Akinci et al. 2012's
  // pressure mirroring, the term 2 k_i B_i): hydrostatic beside a wall too, but twice the
  // walls' share of the energy gradient, not a constraint force: the filled tank gained 1.9%
  // (2D 5 mm), 5.6% (3D), 37% (2D 2.5 mm). With k_i B_i alone (Akinci et al. 2012's single
  // term, as SPlisHSPlasH's DFSPH) a wall held only half of what the symmetric fluid term
  // pushes against it: particles next to a wall needed twice the stiffness for the same force,
  // and a 3D column at rest (whose narrow tank puts 3/4 of the particles within h of a side
  // wall) read a pressure slope of 1.25 rho0 g (1.32 within h of a side wall, 1.02-1.03 away
  // from it, where WCSPH reads 1.02), its bottom row 1.7 (2D) and 2.1 (3D) rho0 g (H - y).
  // alpha_i (kernel_pass) keeps the mirror's Jacobi diagonal either way; the boundary samples a
  // user gives always mirror (their own density has no rest value).
  // Written in place: the pass reads no velocity; both branches keep v4_ current.
  void apply_kappa(State& s, Scalar dt) {
    const Pairs f = fluid_pairs();
    const Scalar m = model_.mass;
    if (walls_.size() > 0 && config_.method == Method::DFSPH) {
      parallel_for(walls_.rows(), [&](Index c) {
        Scalar k = 0;
        for (Index e = walls_.start[c]; e < walls_.start[c + 1]; ++e) k += wall_weight_[e] * kappa_[walls_.particle[e]];
        wall_k_[c] = k;
      });
      const std::int32_t* list = boundary().list.data();
      parallel_for(s.n, [&](Index i) {
        Vec dv = m * symmetric_gradient_sum(f, kappa_.data(), i) + kappa_[i] * CMap(boundary_grad_sum_.data() + i * D);
        for (Index k = boundary().start[i]; k < boundary().start[i + 1]; ++k) {
          const Index b = list[k];
          dv += (b < walls_.begin ? kappa_[i] : wall_k_[b - walls_.begin]) * CMap(wall_entry_grad_.data() + k * D);
        }
        Map(s.v.data() + i * D) -= dt * dv;
        if (rows_.dot4) store_v4(s, i);
      });
      return;
    }
    parallel_for(s.n, [&](Index i) {
      const Vec dv = m * symmetric_gradient_sum(f, kappa_.data(), i) + (2 * kappa_[i]) * CMap(boundary_grad_sum_.data() + i * D);
      Map(s.v.data() + i * D) -= dt * dv;
      if (rows_.dot4) store_v4(s, i);
    });
  }

  // ------------------------------------------------------------------ WCSPH's walls
  //
  // The closed box's walls (Model::wall_begin on) are lattice layers of known volume psi_b /
  // rho0 that continue the fluid's lattice. Under WCSPH they carry a pressure of their own, as
  // frozen fluid particles of mass psi_b would: the density of wall sample b is
  //   rho_b = sum_k psi_k W_bk + sum_i m W_ib        (rho0 beside a fluid lattice at rest),
  // P_b = p(rho_b) / rho_b^2 by Tait's equation of state (the dynamic boundary particles of
  // Crespo et al. 2007, with a summation density), and the fluid's energy
  //   E = sum_i m v_i^2 / 2 + sum_i m U(rho_i) + sum_b psi_b U(rho_b),  U'(rho) = p / rho^2,
  // has the force
  //   a_i = -m sum_j (P_i + P_j) grad W_ij - sum_b psi_b (P_i + P_b) grad W_ib = -dE/dx_i / m
  // exactly: the walls neither give nor take energy, and beside a wall the pressure is the
  // fluid's. The mirrored term 2 P_i B_i used before (Akinci et al. 2012: p_b = p_i) is not a
  // gradient and fed a WCSPH column at rest filling its tank: +188% of its available energy in
  // 0.3 s at 2.5 mm (issue 15). Akinci's single term P_i B_i (p_b = 0) is the gradient without
  // the walls' own energy, but holds only half of what the fluid pushes against a wall: a 3D
  // column at rest read a pressure slope of 1.25 rho0 g. The boundary samples a user gives
  // (Akinci volumes, whose own density is already about rho0, so that rho_b has no rest value
  // to compare with) take the single term: conservative, with the pressure of the particles
  // beside them about twice the hydrostatic one.

  // sum_b psi_b c_b grad W_ib over the wall samples near particle i at x_i (c: one value per
  // sample), in double precision as B_i.
  Vec wall_force(Index i, const Vec& xi, const Scalar* c) const {
    Vec sum = Vec::Zero();
    const std::int32_t* list = boundary().list.data();
    const Scalar* psi = model_.boundary_psi.data();
    for (Index k = boundary().start[i]; k < boundary().start[i + 1]; ++k) {
      const Index b = list[k];
      if (b < model_.wall_begin) continue;
      const Vec xib = xi - CMap(model_.boundary_x.data() + b * D);
      sum += (psi[b] * c[b] * W_.grad_factor(std::sqrt(xib.squaredNorm()))) * xib;
    }
    return sum;
  }

  // After kernel_pass, DFSPH with walls: the walls' rows, the Shepard weights W_ib / sum_i W_ib
  // of their entries (apply_kappa's k_b) and psi_b grad W_ib of every boundary entry.
  void dfsph_wall_pass(const State& s) {
    const Index begin = model_.wall_begin, count = model_.boundary_count();
    walls_.build(boundary(), s.n, begin, count);
    wall_weight_.resize(static_cast<size_t>(walls_.size()));
    wall_k_.assign(static_cast<size_t>(walls_.rows()), 0);
    parallel_for(walls_.rows(), [&](Index c) {
      const Vec xb = CMap(model_.boundary_x.data() + (begin + c) * D);
      Scalar sum = 0;
      for (Index e = walls_.start[c]; e < walls_.start[c + 1]; ++e)
        sum += wall_weight_[e] = W_.w((CMap(s.x.data() + Index{walls_.particle[e]} * D) - xb).norm());
      for (Index e = walls_.start[c]; e < walls_.start[c + 1]; ++e) wall_weight_[e] = sum > 0 ? wall_weight_[e] / sum : 0;
    });
    const NeighborLists& lists = boundary();
    wall_entry_grad_.resize(lists.list.size() * D);
    parallel_for(s.n, [&](Index i) {
      const Vec xi = CMap(s.x.data() + i * D);
      for (Index k = lists.start[i]; k < lists.start[i + 1]; ++k) {
        const Index b = lists.list[k];
        const Vec xib = xi - CMap(model_.boundary_x.data() + b * D);
        Map(wall_entry_grad_.data() + k * D) = (model_.boundary_psi[b] * W_.grad_factor(std::sqrt(xib.squaredNorm()))) * xib;
      }
    });
  }

  // After kernel_pass: the walls' rows and densities rho_b.
  void wall_pass(const State& s) {
    const Index begin = model_.wall_begin, count = model_.boundary_count();
    walls_.build(boundary(), s.n, begin, count);
    wall_rho_.resize(static_cast<size_t>(count));
    wall_P_.resize(static_cast<size_t>(count));
    const Scalar m = model_.mass;
    parallel_for(walls_.rows(), [&](Index c) {
      const Index b = begin + c;
      const Vec xb = CMap(model_.boundary_x.data() + b * D);
      Scalar rho = model_.wall_rho[b];
      for (Index e = walls_.start[c]; e < walls_.start[c + 1]; ++e)
        rho += m * W_.w((CMap(s.x.data() + Index{walls_.particle[e]} * D) - xb).norm());
      wall_rho_[b] = rho;
    });
  }

  // Algorithms 2 and 3 as one Jacobi iteration on the stiffnesses k_i = kappa_i / rho_i (stored
  // in k): each iteration adds residual_i alpha_i / (scale rho_i) (eqs. 6 and 12: the residual
  // is rho*_i - rho0 with scale dt^2, or D rho_i / Dt with scale dt) and applies the velocity
  // change of the increments. A compressed particle (residual > 0) takes compression_weight x
  // the increment: the full one in the divergence solve, as in the paper and SPlisHSPlasH, 0.8
  // in the density solve (kCompressionWeight). Since alpha_i only approximates the inverse
  // diagonal (below), the full increment overshoots on the short modes and leaves particles
  // moving apart, which neither one-sided solve pulls back; warm-started, the density solve
  // iterates about a nearly converged state every step and the overshoot recurs. A 3D column at
  // rest (issue 15, tests/test_sph.py) bounced as a whole: mean vertical speed +-0.028 m/s, its
  // kinetic energy growing 3x over 0.5 s, rms 0.070-0.084 m/s against WCSPH's 0.048. Told
  // apart: both solves cold (warm_start 0) 0.051 m/s but 14 iterations per step, warm_start
  // 0.25 0.063; the divergence solve off still 0.078, its warm start off 0.094; the carried
  // stiffness of particles that end a solve expanded trimmed off 0.084 (so the feed is the
  // overshoot within the step, not the pressure carried over). At 0.8 the bounce is gone (mean
  // vertical speed <= 0.008 m/s, rms 0.046 m/s at 9.1 iterations per step; 0.9: 0.070; 0.7:
  // 0.044 at 10.7). The price is slower convergence at tight tolerances: a 3D dam break of 60k
  // particles at tol 1e-4 takes 17.8 density iterations per step against 5.6 at the full rate.
  // In the density solve an expanded one gives back stiffness at
  // expansion_weight x the rate, but only what the warm start gave it (warm_left_): the warm
  // start can start a particle above the pressure it needs (a free-surface particle, a splash),
  // and with increments >= 0 only, as before, that excess stayed for the whole step and pushed
  // the fluid apart (issue 15: a 2D dam break's surge front 60% ahead of Martin and Moyce at
  // T = 0.83, within 5% after). From a cold start the iteration is the paper's: monotone. An
  // unlimited give-back (k_i down to 0) or the full rate made Jacobi diverge: alpha_i only
  // approximates the inverse diagonal (the iteration matrix's eigenvalues reach 2.1 on a 2D
  // lattice, 2.8 in 3D, more once disordered). The divergence solve gives nothing back
  // (expansion_weight 0): its give-back made a collapsing column's divergence solve diverge.
  // Warm start (Bender and Koschier 2017, sec. 4.5): the solve begins from warm_start x the
  // stiffnesses of the last step, times warm_scale. The density solve's k_i is a pressure over
  // rho_i^2, which does not scale with dt (warm_scale 1); the divergence solve's corrects a
  // velocity divergence in one step, so its dt k^v_i carries over (warm_scale = last dt / dt,
  // as SPlisHSPlasH does): reused as is, a step 20x longer than the last one started 20x above
  // its stiffness. residual() fills aux_ and returns the solver's error; iterations continue
  // until it is below tol.
  // With two_level (the density solve, config.coarse_correction, gravity), the first iteration
  // may instead be the coarse correction of build_coarse (coarse.h): k += P K, its increments
  // limited as the Jacobi ones (a particle gives back at most what the warm start gave it).
  template <class Residual>
  int projected_jacobi(State& s, Scalar dt, Scalar scale, std::vector<Scalar>& k, Scalar tol, int min_iter,
                       Residual&& residual, Scalar& error, Interrupt& interrupt, Scalar warm_scale,
                       Scalar compression_weight, Scalar expansion_weight, bool two_level = false,
                       bool defer_last = false) {
    const Index n = s.n;
    const Scalar w = s.last_dt > 0 ? config_.warm_start * warm_scale : 0;
    // The increments a solve before this one left to apply (defer_last below) go with the warm
    // start's: apply_kappa is linear in the stiffnesses, so one pass applies both.
    const bool pending = pending_apply_;
    pending_apply_ = false;
    if (w > 0 || pending) {
      parallel_for(n, [&](Index i) {
        k[i] = warm_left_[i] = w * k[i];
        kappa_[i] = pending ? k[i] + pending_[i] : k[i];
      });
      apply_kappa(s, dt);
    } else {
      sync_v4(s);  // (with a warm start apply_kappa does, and every iteration after)
    }
    if (!(w > 0)) {
      std::fill(k.begin(), k.end(), 0);
      std::fill(warm_left_.begin(), warm_left_.end(), 0);
    }
    error = residual();
    // The coarse correction runs when the warm start already ends within tol: that is where a
    // Jacobi solve stops after its minimum iterations with the long mode unbuilt (the column at
    // rest's sinking). From above tol, the iterations run anyway, and a coarse step first gave a
    // fine (2.5 mm) collapsing column no fewer iterations and a final compression of 1.1e-2
    // against 0.8e-2 (tests/test_sph.py test_coarse_and_fine_spacing).
    two_level = two_level && error <= tol && build_coarse(s, k);
    int it = 0;
    // The coarse step is not one of the minimum iterations: with it in their place a 2D column
    // at rest at tol 5e-3 (2 iterations a step: the coarse step and one Jacobi iteration, which
    // did not smooth what the coarse step left within the layers) jittered at 0.091 m/s rms
    // (one-level 0.021); after it, 0.021 (3D 0.040, one-level 0.097).
    if (two_level) ++min_iter;
    // Momentum (the density solve where tol < kMomentumTol, one-level): each Jacobi increment adds
    // kMomentum x the particle's last one (Polyak's heavy ball), restarted after an iteration
    // whose error rose. Jacobi's slow error here is smooth and spread (a few % of it removed per
    // iteration at tol 1e-4, issue 15), and on a smooth mode the increments repeat, so the
    // momentum multiplies the step there by up to 1 / (1 - kMomentum) = 2, while on the short
    // modes, whose increments alternate, it damps (stable while the relaxed iteration matrix's
    // eigenvalues, up to 0.8 x 2.8 in 3D, stay below 2 (1 + kMomentum)). Measured (60k-particle
    // 3D dam break, tol 1e-4, bench/sph/sph_dfsph_iterations.py): 15.8 density iterations per
    // step without, 12.0 at 0.3, 9.1 at 0.5, 6.8 at 0.7, with the same compression at the end
    // (1.00e-4); 0.7 lets the columns at rest bounce (2D 0.078, 3D 0.067 m/s, bound 0.063). Off
    // at tol >= 1e-3: the fine (2.5 mm) collapsing column of tests/test_sph.py then ends at a
    // compression of 0.0121 against 0.0080 without (its bound 0.01), while at tol 3e-4 and 1e-4
    // it ends lower with it (0.0086 against 0.0096, 0.0039 against 0.0054); with the coarse
    // correction (tol > 1e-3) the loose-tolerance columns bounced (0.08-0.13 m/s).
    const Scalar beta = compression_weight < 1 && !two_level && coarse_axis_ < 0 && tol < kMomentumTol ? kMomentum : 0;
    prev_.assign(n, 0);
    Scalar last_error = error, b = beta;
    while ((error > tol || it < min_iter) && it < config_.max_iter) {
      interrupt.check();
      const bool coarse = two_level && it == 0;
      // The last of the minimum iterations from a residual already within tol: the solve stops
      // after it without recomputing the residual (see below).
      const bool last = !coarse && it + 1 == min_iter && error <= tol;
      if (coarse) coarse_solve(s, scale);
      parallel_for(n, [&](Index i) {
        Scalar increment;
        if (coarse) {
          increment = coarse_.at(i, active_.data());
        } else {
          const Scalar r = (aux_[i] > 0 ? compression_weight : expansion_weight) * aux_[i];
          increment = s.density[i] > 0 ? r * factor_[i] / (scale * s.density[i]) : 0;
          increment += b * prev_[i];
        }
        kappa_[i] = std::max(increment, -warm_left_[i]);
        prev_[i] = kappa_[i];
        if (kappa_[i] < 0) warm_left_[i] += kappa_[i];
        k[i] += kappa_[i];
      });
      // With defer_last that last iteration's velocity change is left to the next solve's warm
      // start (pending_): one neighbour pass fewer (the divergence solve, where nothing in
      // between reads the velocities but the gravity update, which commutes with it).
      if (last && defer_last) {
        pending_.assign(kappa_.begin(), kappa_.end());
        pending_apply_ = true;
        ++it;
        break;
      }
      apply_kappa(s, dt);
      // The last of the minimum iterations from a residual already within tol: the solve stops
      // after it without recomputing the residual (one light pass of the ten a step makes at
      // tol 1e-3; the divergence solve's usual exit there, its one minimum iteration from a
      // warm start within tol), and `error` stays the one before it. Presumed within tol: an
      // iteration from a converged state lowers the compression almost always. Measured on
      // the 150k dam break at tol 1e-3 / 5e-4 / 3e-4 / 1e-4 (bench/sph/sph_dfsph_iterations.py
      // start), 1 of 19 such residuals ended above tol (5.06e-4 at tol 5e-4, from 4.98e-4),
      // none in the columns at rest and dam breaks of tests/test_sph.py.
      if (last) {
        ++it;
        break;
      }
      error = residual();
      b = error > last_error ? 0 : beta;  // restart where the error rose
      last_error = error;
      ++it;
    }
    return it;
  }

  // The coarse space of the density solve (coarse.h) for the stiffnesses k after the warm
  // start, whose residual is in aux_: its problem holds the particles that are compressed or
  // hold stiffness (the one-sided solve leaves the others free; with the compressed ones alone
  // a 3D column at rest still bounced at tol 2e-3, 0.098 m/s rms: it sinks while expanded, with
  // its pressure low). Returns false where there is none (see CoarseSpace::build).
  bool build_coarse(const State& s, const std::vector<Scalar>& k) {
    const Index n = s.n;
    active_.resize(n);
    parallel_for(n, [&](Index i) { active_[i] = aux_[i] > 0 || k[i] > 0; });
    const Pairs f = fluid_pairs();
    return coarse_.build(s.x.data(), n, kCoarseWidth * model_.h, coarse_axis_, f.start, f.list, f.grads, model_.mass,
                         grad_sum_.data(), boundary_grad_sum_.data(), active_.data());
  }

  // Solves the coarse problem for the density solve's residual in aux_, on its compression rate
  // alone: dt D rho_i / Dt = aux_i - (rho_i - rho0), the part the step's velocities make, with
  // its sign. Posed on the whole residual, the correction removed the density error the fluid
  // has accumulated (within tol) in one step: a 2D lattice column at rest was thrown up at
  // 0.2 m/s in its first step, which the one-sided solves never took back.
  void coarse_solve(const State& s, Scalar scale) {
    coarse_r_.resize(s.n);
    parallel_for(s.n, [&](Index i) { coarse_r_[i] = aux_[i] - (s.density[i] - config_.rho0); });
    coarse_.solve(coarse_r_.data(), active_.data(), scale);
  }

  static constexpr Scalar kCompressionWeight = 0.8;
  static constexpr Scalar kExpansionWeight = 0.5;
  static constexpr Scalar kViscousDt = 0.05;
  static constexpr Scalar kCoarseWidth = 3;  // distance of the coarse nodes, in h
  static constexpr Scalar kMomentum = 0.5;      // density solve: share of the last increment added
  static constexpr Scalar kMomentumTol = 1e-3;  // momentum where tol < this

  // Algorithm 2 on D rho_i / Dt. The error is the mean compression rate (D rho/Dt clamped to
  // >= 0) times dt / rho0. Particles with fewer neighbours than a filled kernel support (free
  // surface) are skipped, as SPlisHSPlasH does.
  int divergence_solve(State& s, Scalar dt, StepStats& stats, Interrupt& interrupt) {
    const Index n = s.n;
    const Index min_neighbors = D == 3 ? 20 : 7;
    auto residual = [&] {
      const Pairs f = fluid_pairs();
      const Index* b = boundary().start.data();
      parallel_for(n, [&](Index i) {
        const bool full = f.start[i + 1] - f.start[i] + b[i + 1] - b[i] >= min_neighbors;
        aux_[i] = full ? density_rate(f, s.v.data(), i) : 0;
      });
      return parallel_sum(n, [&](Index i) { return std::max<Scalar>(aux_[i], 0); }) / std::max<Index>(n, 1) * dt /
             config_.rho0;
    };
    const int it = projected_jacobi(s, dt, dt, s.kappa_divergence, config_.divergence_tol, 1, residual,
                                    stats.divergence_error, interrupt, s.last_dt > 0 ? s.last_dt / dt : 1, 1, 0, false,
                                    config_.viscosity == 0);
    return it;
  }

  // Algorithm 3 on the predicted density rho*_i = rho_i + dt D rho_i/Dt (eq. 4). The error is
  // the mean compression max(rho*_i / rho0 - 1, 0) over all particles (Bender and Koschier
  // 2017, sec. 4.3). (A second rule, the wall contacts' mean held to tol too, once kept a 2D
  // column at rest from sagging and bouncing, 0.09 -> 0.031 m/s rms, but it doubled the
  // iterations of a 3D dam break at tol 1e-4, 6.6 -> 16.2 per step; the under-relaxed
  // increments above hold both columns without it: 2D 0.026 m/s at 7.7 iterations per step,
  // 3D 0.046 m/s at 9.1; with both rules 0.026 / 0.047 m/s at 9.0 / 9.1.)
  int density_solve(State& s, Scalar dt, StepStats& stats, Interrupt& interrupt) {
    const Index n = s.n;
    const Scalar rho0 = config_.rho0;
    auto residual = [&] {
      const Pairs f = fluid_pairs();
      parallel_for(n, [&](Index i) { aux_[i] = s.density[i] + dt * density_rate(f, s.v.data(), i) - rho0; });
      return parallel_sum(n, [&](Index i) { return std::max<Scalar>(aux_[i], 0); }) / std::max<Index>(n, 1) / rho0;
    };
    // Warm start: k_i = p_i / rho_i^2 holds up a fluid at rest whatever dt, but the part that
    // corrected last step's density errors scales as 1 / dt^2: after a step 50x shorter (a run
    // started with small fixed steps) it is 2500x too large, so a longer step takes the last
    // stiffnesses times (last dt / dt)^2, as SPlisHSPlasH carries kappa dt^2, and a shorter one
    // takes them as they are.
    const Scalar ratio = s.last_dt > 0 ? std::min<Scalar>(1, s.last_dt / dt) : 1;
    return projected_jacobi(s, dt, dt * dt, s.kappa_density, config_.tol, 2, residual, stats.density_error,
                            interrupt, ratio * ratio, kCompressionWeight, kExpansionWeight, coarse_axis_ >= 0);
  }

  // ------------------------------------------------------------------ shared passes

  // The step's neighbour lists: the entries within h at the current positions (without a
  // skin, the lists of the grid search are these already).
  const NeighborLists& fluid() const { return lists_->skin > 0 ? fluid_exact_ : lists_->fluid; }
  const NeighborLists& boundary() const { return lists_->skin > 0 ? boundary_exact_ : lists_->boundary; }

  // Calls keep(k, j, x_i - x_j, W_ij, dW/dr / r) for the entries k (list[k] = j) of row i of
  // the list `wide` (listed points xs), in list order: those within h if Filter (about 40% of a
  // Verlet list's entries fail the test, at random), else all; then emit(j, value) with the
  // value each keep returned. A chunk of entries at a time: the distances and the test
  // branch-free, then the kernel values of the chunk's entries kept at once (kernel_values: four
  // wide with AVX2; the square root and division per entry were the kernel pass's costliest
  // instructions as scalars), then keep over the chunk, then emit (a caller's sums in keep stay
  // in registers: with the list's stores in the same loop they went through memory).
  template <bool Filter, class Keep, class Emit>
  void row_entries(const NeighborLists& wide, const Scalar* xs, const Vec& xi, Index i, Keep&& keep, Emit&& emit) const {
    constexpr Index kChunk = 64;
    const Scalar h2 = model_.h * model_.h;
    const std::int32_t* list = wide.list.data();
    const Index end = wide.start[i + 1];
    for (Index k0 = wide.start[i]; k0 < end; k0 += kChunk) {
      const Index k1 = std::min(end, k0 + kChunk);
      std::int32_t kept[kChunk];
      Scalar r2[kChunk], r[kChunk], w[kChunk], dw[kChunk];
      int count = 0;
      for (Index k = k0; k < k1; ++k) {
        const std::int32_t j = list[k];
        const Scalar d2 = (xi - CMap(xs + Index{j} * D)).squaredNorm();
        kept[count] = static_cast<std::int32_t>(k - k0);
        r2[count] = d2;
        count += Filter ? d2 < h2 : 1;
      }
      kernel_values(r2, count, r, w, dw);
      for (int e = 0; e < count; ++e) {
        const Index k = k0 + kept[e], j = list[k];
        r[e] = keep(k, j, Vec(xi - CMap(xs + j * D)), w[e], dw[e]);  // (r[] reused for the values)
      }
      for (int e = 0; e < count; ++e) emit(list[k0 + kept[e]], r[e]);
    }
  }

  // r = sqrt(r2), W(r) and dW/dr / r of count distances (CubicSpline::values, or its AVX2
  // version where the CPU has it: the same bits).
  void kernel_values(const Scalar* r2, int count, Scalar* r, Scalar* w, Scalar* dw) const {
#if KINEMA_HAVE_AVX2_CLONES
    if (values_avx2_) return kernel_values_avx2<D>(W_, r2, count, r, w, dw);
#endif
    W_.values(r2, count, r, w, dw);
  }

  // One pass over the Verlet lists at the step's positions that keeps their entries within h
  // (the exact lists fluid() and boundary()) and computes on the way: the densities
  // rho_i = sum_j m W_ij + sum_b psi_b W_ib (Akinci et al. 2012, eq. 5) into `density`; the
  // kernel gradients grad_i W_ij of every fluid entry kept, which the step's later passes read
  // instead of evaluating the kernel again (the positions do not move until the step's end;
  // a DFSPH step makes about 13 passes); and, with `factors`, DFSPH's alpha_i (eq. 11) for the
  // mirrored boundary of apply_kappa, whose k_i moves v_i by -dt k_i (G_i + B_i):
  //   alpha_i = rho_i / ((G_i + B_i) . G_i + sum_j |m grad W_ij|^2),
  //   G_i = sum_j m grad W_ij + B_i, B_i = sum_b psi_b grad W_ib,
  // the exact Jacobi diagonal, with B_i . G_i taken as >= 0 (a smaller step where it is
  // negative, at a wall beside a free surface); zero without neighbours.
  // For every particle i (at x): row(i, x_i, entries), where entries(entry) calls
  // entry(j, x_i - x_j, W_ij, dW/dr / r) for each neighbour j within h (listed points xs) in
  // list order (row_entries); with the dW/dr / r it returns, grad_i W_ij = (dW/dr / r)(x_i - x_j) goes into
  // grads (D floats per entry, parallel to the step's list, and one float of padding that the
  // row sums of kernels.h read; nothing stored if grads is null). The later passes then stream
  // the gradients instead of gathering x_j: 12 bytes per entry, and single precision perturbs a
  // gradient by ~1e-7 relative, far below the solvers' tolerances. With a skin the Verlet list
  // `wide` is filtered into `exact` on the way (fill_with_gradients; without grads the factors
  // are staged in kept_dw), without it is exact already.
  template <class Row>
  void kernel_rows(const NeighborLists& wide, NeighborLists& exact, std::vector<Scalar>& kept_dw,
                   std::vector<float>* grads, const Scalar* xs, const Scalar* x, Index n, Row&& row) {
    auto store = [&](Index k, Scalar dw, const Vec& xij) {
      if (grads) Eigen::Map<Eigen::Matrix<float, D, 1>>(grads->data() + k * D) = stored_gradient(dw, xij);
    };
    if (lists_->skin > 0 && grads) return fill_with_gradients(wide, exact, *grads, xs, x, n, row);
    if (lists_->skin > 0) {
      exact.fill_with_values(n, kept_dw, [&](Index i, auto&& push) {
        const Vec xi = CMap(x + i * D);
        row(i, xi, [&](auto&& entry) {
          row_entries<true>(
              wide, xs, xi, i, [&](Index, Index j, const Vec& xij, Scalar w, Scalar dw) { return entry(j, xij, w, dw); },
              push);
        });
      });
      if (!grads) return;
      grads->resize(exact.list.size() * D + 1);
      parallel_for(n, [&](Index i) {
        const Vec xi = CMap(x + i * D);
        for (Index k = exact.start[i]; k < exact.start[i + 1]; ++k) store(k, kept_dw[k], xi - CMap(xs + Index{exact.list[k]} * D));
      });
      return;
    }
    if (grads) grads->resize(wide.list.size() * D + 1);
    parallel_for(n, [&](Index i) {
      const Vec xi = CMap(x + i * D);
      row(i, xi, [&](auto&& entry) {
        row_entries<false>(
            wide, xs, xi, i,
            [&](Index k, Index j, const Vec& xij, Scalar w, Scalar dw) {
              const Scalar value = entry(j, xij, w, dw);
              store(k, value, xij);
              return value;
            },
            [](Index, Scalar) {});
      });
    });
  }

  // kernel_rows with a skin and gradients: exact := the entries of the Verlet list `wide` within
  // h, their gradients into grads, in one pass over the rows (staging dW/dr / r per entry and a
  // second pass gathering x_j again to form the gradients cost about 15% of the kernel pass at
  // 150k particles). Each thread fills the rows of one contiguous chunk into its own buffers,
  // concatenated in order: the same arrays for any thread count, bitwise those of the two passes.
  template <class Row>
  void fill_with_gradients(const NeighborLists& wide, NeighborLists& exact, std::vector<float>& grads,
                           const Scalar* xs, const Scalar* x, Index n, Row&& row) {
    exact.start.assign(static_cast<size_t>(n) + 1, 0);
    const int threads = n > kParallelGrain ? num_threads() : 1;
    fill_ids_.resize(static_cast<size_t>(threads));
    fill_grads_.resize(static_cast<size_t>(threads));
#pragma omp parallel num_threads(threads)
    {
      const int t = omp_get_thread_num(), nt = omp_get_num_threads();
      const Index begin = n * t / nt, end = n * (t + 1) / nt;
      auto& ids = fill_ids_[static_cast<size_t>(t)];
      auto& gs = fill_grads_[static_cast<size_t>(t)];
      ids.size = gs.size = 0;
      for (Index i = begin; i < end; ++i) {
        const auto most = static_cast<size_t>(wide.start[i + 1] - wide.start[i]);
        std::int32_t* id = ids.room(most);
        float* g = gs.room(most * D);
        Index count = 0;
        const Vec xi = CMap(x + i * D);
        row(i, xi, [&](auto&& entry) {
          row_entries<true>(
              wide, xs, xi, i,
              [&](Index, Index j, const Vec& xij, Scalar w, Scalar dw) {
                const Scalar value = entry(j, xij, w, dw);
                id[count] = static_cast<std::int32_t>(j);
                Eigen::Map<Eigen::Matrix<float, D, 1>>(g + count * D) = stored_gradient(value, xij);
                ++count;
                return value;
              },
              [](Index, Scalar) {});
        });
        exact.start[i + 1] = count;
        ids.size += static_cast<size_t>(count);
        gs.size += static_cast<size_t>(count * D);
      }
#pragma omp barrier
#pragma omp single
      {
        for (Index i = 0; i < n; ++i) exact.start[i + 1] += exact.start[i];
        exact.list.resize(static_cast<size_t>(exact.start[n]));
        grads.resize(exact.list.size() * D + 1);
      }
      std::copy(ids.data.get(), ids.data.get() + ids.size, exact.list.begin() + exact.start[begin]);
      std::copy(gs.data.get(), gs.data.get() + gs.size, grads.begin() + exact.start[begin] * D);
    }
  }

  // grad_i W_ij = (dW/dr / r) x_ij as the light passes read it (rounded to float).
  static Eigen::Matrix<float, D, 1> stored_gradient(Scalar dw, const Vec& xij) {
    return (dw * xij).template cast<float>();
  }

  // Also forms the gradient sums of the light passes: boundary_grad_sum_ = B_i = sum_b psi_b
  // grad W_ib and, with factors, grad_sum_ = G_i = sum_j m grad W_ij + B_i, the fluid part from
  // the gradients as stored, so that density_rate's algebra is exact up to double rounding.
  // The boundary gradients themselves are not stored: no later pass reads them.
  void kernel_pass(State& s, bool factors, Scalar* density) {
    const Scalar m = model_.mass;
    const Scalar* x = s.x.data();
    // With factors, sum_j |m grad W_ij|^2 goes from the fluid pass to the boundary pass in factor_.
    Scalar* sum_sq = factor_.data();
    kernel_rows(lists_->fluid, fluid_exact_, fluid_dw_, &fluid_grad_, x, x, s.n, [&](Index i, const Vec&, auto&& entries) {
      Scalar rho = m * W_.w0();
      Vec gsum = Vec::Zero();
      Scalar gsq = 0;
      entries([&](Index, const Vec& xij, Scalar w, Scalar dw) {
        rho += m * w;
        if (factors) {
          const Vec gw = m * stored_gradient(dw, xij).template cast<Scalar>();
          gsum += gw;
          gsq += gw.squaredNorm();
        }
        return dw;
      });
      density[i] = rho;
      if (factors) {
        Map(grad_sum_.data() + i * D) = gsum;
        sum_sq[i] = gsq;
      }
    });
    const Scalar* xb = model_.boundary_x.data();
    const Scalar* psi = model_.boundary_psi.data();
    // Below this a particle has (almost) no neighbours and no pressure to apply.
    const Scalar min_denom = 1e-6 * m * m / std::pow(model_.h, 2 * D + 2);
    const bool walls = config_.method == Method::WCSPH && model_.wall_begin < model_.boundary_count();
    kernel_rows(lists_->boundary, boundary_exact_, boundary_dw_, nullptr, xb, x, s.n, [&](Index i, const Vec&, auto&& entries) {
      Scalar rho = density[i];
      Vec bsum = Vec::Zero();
      entries([&](Index b, const Vec& xib, Scalar w, Scalar dw) {
        rho += psi[b] * w;
        bsum += psi[b] * (dw * xib);
        return dw;
      });
      density[i] = rho;
      Map(boundary_grad_sum_.data() + i * D) = bsum;
      if (factors) {
        const Vec gsum = Map(grad_sum_.data() + i * D) += bsum;
        const Scalar denom = gsum.squaredNorm() + std::max<Scalar>(bsum.dot(gsum), 0) + sum_sq[i];
        factor_[i] = denom > min_denom ? rho / denom : 0;
      }
    });
    if (walls) wall_pass(s);
    else if (config_.method == Method::DFSPH && model_.wall_begin < model_.boundary_count() &&
             config_.shepard_walls)
      dfsph_wall_pass(s);
    else walls_.clear();
  }

  // Neighbour lists of the current positions. The cell-grid search runs only when the Verlet
  // lists (radius h (1 + skin)) may have lost a pair: when some particle has moved skin h / 2
  // or more since they were built. Each call then filters them to the exact pairs within h in
  // kernel_pass (which see). The skin pays when the lists live a few steps; when the fastest
  // particle would cross it in under two steps (DFSPH's large steps), the search runs with no
  // skin. Morton reordering happens at a rebuild, at most every reorder_every steps.
  void neighborhoods(State& s, bool may_reorder, bool factors, Scalar* density) {
    const Scalar h = model_.h;
    Stopwatch watch;
    const VerletLists* lists = s.lists.get();
    rebuilt_ = !lists || lists->skin == 0 || lists->x.size() != s.x.size() ||
               2 * max_displacement(s, lists->x) >= 0.999 * lists->skin * h;
    if (rebuilt_) {
      if (may_reorder && config_.reorder_every > 0 &&
          (s.reorder_step < 0 || s.steps - s.reorder_step >= config_.reorder_every)) {
        reorder(s);
        s.reorder_step = s.steps;
      }
      const Scalar travel = s.last_dt * max_speed(s);  // expected distance per step
      build_lists(s, s.x, config_.neighbor_skin * h >= 4 * travel ? config_.neighbor_skin : 0);
    }
    lists_ = s.lists.get();
    search_seconds_ = watch.seconds();
    watch.restart();
    kernel_pass(s, factors, density);
    kernel_seconds_ = watch.seconds();
  }

  // s.lists := the Verlet lists of radius h (1 + skin) at the positions x, in lists the
  // solver alone holds (the last ones, when no State copy shares them any more: a rebuild
  // then allocates nothing).
  void build_lists(State& s, const std::vector<Scalar>& x, Scalar skin) {
    std::shared_ptr<VerletLists> fresh =
        spare_ && spare_.use_count() == 1 ? std::move(spare_) : std::make_shared<VerletLists>();
    fresh->x = x;
    fresh->skin = skin;
    const Scalar radius = model_.h * (1 + skin);
    fluid_grid_.build(fresh->x.data(), s.n, radius);
    fresh->fluid.build<D>(fluid_grid_, fresh->x.data(), s.n, radius, true);
    if (model_.boundary_count() > 0) {
      if (boundary_grid_radius_ != radius) {
        boundary_grid_.build(model_.boundary_x.data(), model_.boundary_count(), radius);
        boundary_grid_radius_ = radius;
      }
      fresh->boundary.build<D>(boundary_grid_, fresh->x.data(), s.n, radius, false);
    } else {
      fresh->boundary.start.assign(static_cast<size_t>(s.n) + 1, 0);
      fresh->boundary.list.clear();
    }
    spare_ = std::const_pointer_cast<VerletLists>(std::move(s.lists));
    s.lists = std::move(fresh);
  }

  void restore_lists(State& s, const std::vector<Scalar>& x, Scalar skin) override {
    prepare(s);
    if (x.size() != s.x.size())
      throw InvalidArgument("neighbor_x: expected shape (" + std::to_string(s.n) + ", " + std::to_string(D) + ")");
    check_finite(s, "neighbor_x", x);
    if (!(skin >= 0) || !(skin <= 1)) throw InvalidArgument("neighbor_skin: expected a number in [0, 1], got " + format_real(skin));
    build_lists(s, x, skin);
  }

  // Largest distance a particle has moved since the positions x0 [m].
  Scalar max_displacement(const State& s, const std::vector<Scalar>& built) const {
    Scalar d2 = 0;
    const Scalar* x = s.x.data();
    const Scalar* x0 = built.data();
#pragma omp parallel for schedule(static) reduction(max : d2) if (s.n > kParallelGrain)
    for (Index i = 0; i < s.n; ++i) d2 = std::max(d2, (CMap(x + i * D) - CMap(x0 + i * D)).squaredNorm());
    return std::sqrt(d2);
  }

  // Checks that the state is one of this model's and sizes the scratch (and DFSPH's
  // stiffnesses, zero in a new state) for it. The values left in the scratch do not matter:
  // every pass writes before it reads.
  void prepare(State& s) {
    if (s.dim != D || s.x.size() != static_cast<size_t>(s.n * D) || s.v.size() != s.x.size() ||
        s.density.size() != static_cast<size_t>(s.n) || s.pressure.size() != static_cast<size_t>(s.n) ||
        s.ids.size() != static_cast<size_t>(s.n))
      throw InvalidArgument("state: expected the arrays of " + std::to_string(s.n) + " particles in " +
                            std::to_string(D) + "D");
    if (s.n >= (Index{1} << 31)) throw InvalidArgument("state: at most 2^31 - 1 particles");
    const auto n = static_cast<size_t>(s.n);
    if (config_.method == Method::DFSPH) {
      if (s.kappa_density.size() != n) s.kappa_density.assign(n, 0);
      if (s.kappa_divergence.size() != n) s.kappa_divergence.assign(n, 0);
      grad_sum_.resize(n * D);
      if (rows_.dot4) v4_.resize(4 * n);
    }
    accel_.resize(n * D);
    aux_.resize(n);
    kappa_.resize(n);
    warm_left_.resize(n);
    factor_.resize(n);
    boundary_grad_sum_.resize(n * D);
  }

  std::vector<Index> neighbor_pairs_in_use(State& s, std::vector<Index>& boundary_pairs) override {
    prepare(s);
    check_finite(s, "x", s.x);
    neighborhoods(s, true, false, aux_.data());  // the densities only as a by-product
    std::vector<Index> pairs;
    boundary_pairs.clear();
    for (Index i = 0; i < s.n; ++i) {
      for (Index k = fluid().start[i]; k < fluid().start[i + 1]; ++k)
        if (fluid().list[k] > i) {
          pairs.push_back(i);
          pairs.push_back(fluid().list[k]);
        }
      for (Index k = boundary().start[i]; k < boundary().start[i + 1]; ++k) {
        boundary_pairs.push_back(i);
        boundary_pairs.push_back(boundary().list[k]);
      }
    }
    return pairs;
  }

  // Permutes every per-particle array in place along the Morton curve (buffers keep their
  // addresses, so numpy views stay valid; ids records who is where).
  void reorder(State& s) {
    const std::vector<Index> order = morton_order<D>(s.x.data(), s.n, model_.h);
    bool identity = true;
    for (Index k = 0; k < s.n && identity; ++k) identity = order[k] == k;
    if (identity) return;
    auto permute = [&](auto& a, int width) {
      auto copy = a;
      parallel_for(s.n, [&](Index k) {
        for (int c = 0; c < width; ++c) a[k * width + c] = copy[order[k] * width + c];
      });
    };
    permute(s.x, D);
    permute(s.v, D);
    permute(s.density, 1);
    permute(s.pressure, 1);
    permute(s.ids, 1);
    if (!s.kappa_density.empty()) {
      permute(s.kappa_density, 1);
      permute(s.kappa_divergence, 1);
    }
  }

  void pressures(State& s) {
    parallel_for(s.n, [&](Index i) { s.pressure[i] = tait_pressure(s.density[i], config_.rho0, B_, config_.gamma); });
    // The walls' P_b, where a particle is near (no other is read).
    if (walls_.size() > 0)
      parallel_for(walls_.rows(), [&](Index c) {
        if (walls_.start[c] == walls_.start[c + 1]) return;
        const Index b = walls_.begin + c;
        const Scalar rho = wall_rho_[b];
        wall_P_[b] = tait_pressure(rho, config_.rho0, B_, config_.gamma) / (rho * rho);
      });
  }

  // accel_ = g + external forces / m + viscosity (fluid-fluid; walls are free-slip).
  void non_pressure_accelerations(const State& s) {
    const Scalar nu = config_.viscosity;
    const Pairs f = fluid_pairs();
    parallel_for(s.n, [&](Index i) {
      Vec a = g_;
      if (forces_) a += CMap(forces_ + s.ids[i] * D) / model_.mass;
      if (nu > 0) {
        const Vec xi = CMap(s.x.data() + i * D);
        const Vec vi = CMap(s.v.data() + i * D);
        for (Index k = f.start[i]; k < f.start[i + 1]; ++k) {
          const Index j = f.list[k];
          const Vec xij = xi - CMap(s.x.data() + j * D);
          a += viscosity_term<D>(xij, vi - CMap(s.v.data() + j * D), f.grad(k),
                                 model_.mass / s.density[j], nu, model_.h);
        }
      }
      Map(accel_.data() + i * D) = a;
    });
  }

  // The symmetric pressure force (Becker and Teschner 2007, eq. 5) with the walls' (see
  // "WCSPH's walls"), for P_i = p_i / rho_i^2 and the walls' P_b = p_b / rho_b^2 (pressures()):
  //   a_i = -m sum_j (P_i + P_j) grad W_ij - P_i B_i - sum_b psi_b P_b grad W_ib,
  // with the step's boundary gradient sums B_i (kernel_pass): -dE/dx_i / m. P is staged in aux_.
  void pressure_accelerations(const State& s) {
    const Scalar m = model_.mass;
    const Pairs f = fluid_pairs();
    const bool walls = walls_.size() > 0;
    parallel_for(s.n, [&](Index i) { aux_[i] = s.pressure[i] / (s.density[i] * s.density[i]); });
    parallel_for(s.n, [&](Index i) {
      Vec a = m * symmetric_gradient_sum(f, aux_.data(), i) + aux_[i] * CMap(boundary_grad_sum_.data() + i * D);
      if (walls) a += wall_force(i, CMap(s.x.data() + i * D), wall_P_.data());
      Map(accel_.data() + i * D) -= a;
    });
  }

  // The domain's walls: positions are clamped into the box and the outward velocity removed,
  // so nothing leaks whatever dt (the wall samples do the physics, this is the guarantee).
  void enforce_domain(State& s) const {
    if (!model_.has_domain) return;
    parallel_for(s.n, [&](Index i) {
      for (int a = 0; a < D; ++a) {
        Scalar& x = s.x[i * D + a];
        Scalar& v = s.v[i * D + a];
        if (x < model_.lower[a]) {
          x = model_.lower[a];
          v = std::max<Scalar>(v, 0);
        } else if (x > model_.upper[a]) {
          x = model_.upper[a];
          v = std::min<Scalar>(v, 0);
        }
      }
    });
  }

  // ------------------------------------------------------------------ checks and measures

  Scalar mean_compression(const Scalar* rho, Index n) const {
    if (n == 0) return 0;
    const Scalar rho0 = config_.rho0;
    return parallel_sum(n, [&](Index i) { return std::max<Scalar>(rho[i] / rho0 - 1, 0); }) / n;
  }

  static Scalar max_speed(const State& s) {
    Scalar vmax2 = 0;
    const Scalar* v = s.v.data();
#pragma omp parallel for schedule(static) reduction(max : vmax2) if (s.n > kParallelGrain)
    for (Index i = 0; i < s.n; ++i) vmax2 = std::max(vmax2, CMap(v + i * D).squaredNorm());
    return std::sqrt(vmax2);
  }

  void check_finite(const State& s, const char* name, const std::vector<Scalar>& a) const {
    for (size_t k = 0; k < a.size(); ++k)
      if (!std::isfinite(a[k])) {
        std::ostringstream msg;
        msg << "sph: particle " << s.ids[k / D] << " has a non-finite " << name << " at step "
            << s.steps << "; the time step was probably too large (stable_dt(0.4) = "
            << stable_dt(s, 0.4) << " s)";
        throw DivergenceError(msg.str());
      }
  }

  // Throws DivergenceError on NaN/Inf or on runaway speeds: beyond c for WCSPH (whose c is ten
  // times the fastest expected flow), beyond 10 c for DFSPH. Returns the max speed.
  Scalar check_state(const State& s, Scalar dt) const {
    check_finite(s, "position", s.x);
    check_finite(s, "velocity", s.v);
    const Scalar vmax = max_speed(s);
    // WCSPH is built for Mach ~0.1: a supersonic particle means the explicit step diverged.
    const Scalar limit = config_.method == Method::WCSPH ? c_ : 10 * c_;
    if (vmax > limit) {
      std::ostringstream msg;
      msg << "sph (" << (config_.method == Method::WCSPH ? "wcsph" : "dfsph") << "): particle speed "
          << vmax << " m/s exceeds " << (config_.method == Method::WCSPH ? "the speed of sound " : "10 x the reference speed ")
          << c_ << " m/s at step " << s.steps
          << " (dt = " << dt << " s): the simulation blew up; use advance() or a dt below about "
          << cfl_dt_at_rest() << " s";
      throw DivergenceError(msg.str());
    }
    return vmax;
  }

  Scalar cfl_dt_at_rest() const {
    return config_.method == Method::WCSPH ? 0.4 * model_.spacing / c_ : 0.4 * model_.spacing / (0.1 * c_);
  }

  // DFSPH's two-level density solve: the coarse space, the axis of its layers (gravity's
  // largest component; -1: none), the particles in its problem and its residual.
  CoarseSpace<D> coarse_;
  int coarse_axis_ = -1;
  std::vector<char> active_;
  std::vector<Scalar> coarse_r_;
  CubicSpline<D> W_;
  Scalar c_;  // speed of sound (WCSPH) or reference speed (DFSPH) [m/s]
  Vec g_ = Vec::Zero();
  Scalar B_ = 0;
  NeighborGrid<D> fluid_grid_, boundary_grid_;
  Scalar boundary_grid_radius_ = 0;             // cell size boundary_grid_ was built for
  std::shared_ptr<VerletLists> spare_;          // the lists before the state's last ones, for reuse
  const VerletLists* lists_ = nullptr;          // the step's Verlet lists (the state's)
  NeighborLists fluid_exact_, boundary_exact_;  // their entries within h (kernel_pass; with a skin)
  RowSums<D> rows_;                             // the light passes' row sums (AVX2 or baseline)
  bool values_avx2_ = false;                    // kernel_values four wide (AVX2)
  bool rebuilt_ = false;                        // the step rebuilt the lists
  double search_seconds_ = 0, kernel_seconds_ = 0;  // the last neighborhoods() call's split
  const Scalar* forces_ = nullptr;              // the step's external forces (n, d) by particle id, or null
  std::vector<Scalar> accel_;      // (n, d) accelerations
  std::vector<Scalar> aux_;        // DFSPH: predicted densities or density rates; WCSPH: p_i / rho_i^2
  std::vector<Scalar> prev_;       // DFSPH: the last iteration's increments (momentum)
  std::vector<Scalar> pending_;    // DFSPH: increments the divergence solve left to apply (defer_last)
  bool pending_apply_ = false;
  std::vector<Scalar> v4_;         // DFSPH with rows_.dot4: the velocities padded to (n, 4)
  std::vector<Scalar> warm_left_;  // DFSPH: warm-start stiffness a solve may still give back
  std::vector<Scalar> kappa_;      // DFSPH: increment of kappa_i / rho_i in the current iteration
  std::vector<Scalar> factor_;     // DFSPH: alpha_i
  // The step's kernel gradients grad_i W_ij of each entry of fluid() (D floats) and their sums,
  // set by kernel_pass (step-local: every step recomputes them before use).
  std::vector<float> fluid_grad_;
  std::vector<Scalar> grad_sum_;           // (n, d) DFSPH: G_i = sum_j m grad W_ij + sum_b psi_b grad W_ib
  // DFSPH's walls (dfsph_wall_pass): Shepard weights of the walls' entries, k_b of each wall
  // row, psi_b grad W_ib of each boundary entry.
  std::vector<Scalar> wall_weight_, wall_k_, wall_entry_grad_;
  std::vector<Scalar> boundary_grad_sum_;  // (n, d) sum_b psi_b grad W_ib
  // kernel_pass with a skin: dW/dr / r of the entries kept, one buffer per list so that each
  // grows to its list's size once (shared, every fluid pass after a boundary pass regrew it).
  std::vector<Scalar> fluid_dw_, boundary_dw_;
  // fill_with_gradients' per-thread buffers (kept: a step allocates nothing once they have grown).
  std::vector<NeighborLists::Buffer<std::int32_t>> fill_ids_;
  std::vector<NeighborLists::Buffer<float>> fill_grads_;
  // WCSPH's walls ("WCSPH's walls"): their rows and, per boundary sample (M,), the density
  // rho_b and P_b = p_b / rho_b^2.
  WallRows walls_;
  std::vector<Scalar> wall_rho_, wall_P_;
};

}  // namespace

Solver::Solver(const Model& model, const Config& config) {
  check(config);
  if (model.dim == 2) impl_ = std::make_unique<SolverD<2>>(model, config);
  else if (model.dim == 3) impl_ = std::make_unique<SolverD<3>>(model, config);
  else throw InvalidArgument("model: expected d = 2 or 3");
}

Solver::~Solver() = default;
Solver::Solver(Solver&&) noexcept = default;
Solver& Solver::operator=(Solver&&) noexcept = default;

StepStats Solver::step(State& state, Scalar dt, Interrupt& interrupt, const Scalar* forces) {
  return impl_->step(state, dt, interrupt, forces);
}
Scalar Solver::stable_dt(const State& state, Scalar cfl) const { return impl_->stable_dt(state, cfl); }
Scalar Solver::density_error(State& state) { return impl_->density_error(state); }
std::vector<Index> Solver::neighbor_pairs_in_use(State& state, std::vector<Index>& boundary_pairs) {
  return impl_->neighbor_pairs_in_use(state, boundary_pairs);
}
void Solver::restore_lists(State& state, const std::vector<Scalar>& x, Scalar skin) { impl_->restore_lists(state, x, skin); }
const Model& Solver::model() const { return impl_->model_; }
const Config& Solver::config() const { return impl_->config_; }

}  // namespace kinema::sph
