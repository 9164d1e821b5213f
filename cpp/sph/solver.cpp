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
#include "sph/fluid.h"
#include "sph/kernels.h"

namespace kinema::sph {

namespace {

// Fixed-radius neighbour lists in CSR form: the neighbours of query point i are
// list[start[i] .. start[i+1]). Rebuilt every step without reallocating once grown.
struct NeighborLists {
  std::vector<Index> start;
  std::vector<std::int32_t> list;
  std::vector<std::vector<std::int32_t>> per_thread;

  Index size() const { return static_cast<Index>(list.size()); }

  // Neighbours within radius of each query point xq (nq rows) among the points the grid binned
  // (coordinates xs); a query point is its own neighbour only if !self.
  template <int D>
  void build(const NeighborGrid<D>& grid, const Scalar* xs, const Scalar* xq, Index nq,
             Scalar radius, bool self) {
    using Vec = Eigen::Matrix<Scalar, D, 1>;
    const Scalar r2 = radius * radius;
    start.assign(static_cast<size_t>(nq) + 1, 0);
    const int threads = nq > kParallelGrain ? num_threads() : 1;
    per_thread.resize(static_cast<size_t>(std::max(threads, 1)));
    // Each thread fills the lists of one contiguous chunk of points; concatenating the chunks
    // in order gives the same CSR arrays for any thread count.
#pragma omp parallel num_threads(threads)
    {
      const int t = omp_get_thread_num();
      const int nt = omp_get_num_threads();
      const Index begin = nq * t / nt, end = nq * (t + 1) / nt;
      auto& buf = per_thread[static_cast<size_t>(t)];
      buf.clear();
      for (Index i = begin; i < end; ++i) {
        const Vec xi = Eigen::Map<const Vec>(xq + i * D);
        const size_t before = buf.size();
        grid.for_each_candidate(xi, [&](Index j) {
          if (self && j == i) return;
          if ((Eigen::Map<const Vec>(xs + j * D) - xi).squaredNorm() < r2)
            buf.push_back(static_cast<std::int32_t>(j));
        });
        start[static_cast<size_t>(i) + 1] = static_cast<Index>(buf.size() - before);
      }
#pragma omp barrier
#pragma omp single
      {
        for (Index i = 0; i < nq; ++i) start[i + 1] += start[i];
        list.resize(static_cast<size_t>(start[nq]));
      }
      std::copy(buf.begin(), buf.end(), list.begin() + start[begin]);
    }
  }
};

template <int D>
class SolverD final : public Solver {
 public:
  using Vec = Eigen::Matrix<Scalar, D, 1>;
  using Map = Eigen::Map<Vec>;
  using CMap = Eigen::Map<const Vec>;

  SolverD(const Model& model, const Config& config, const State& state)
      : Solver(model, config), W_(model.h) {
    for (int a = 0; a < D; ++a) g_[a] = config.gravity[a];
    c_ = config.speed_of_sound > 0 ? config.speed_of_sound : default_speed_of_sound(state);
    B_ = config.rho0 * c_ * c_ / config.gamma;
    if (model.boundary_count() > 0)
      boundary_grid_.build(model.boundary_x.data(), model.boundary_count(), model.h);
    const auto n = static_cast<size_t>(state.n);
    accel_.assign(n * D, 0);
    aux_.assign(n, 0);
    kappa_.assign(n, 0);
    kappa_sum_.assign(n, 0);
    factor_.assign(n, 0);
  }

  StepStats step(State& s, Scalar dt, Interrupt& interrupt) override {
    if (!(dt > 0) || !std::isfinite(dt))
      throw InvalidArgument("dt: expected a finite number > 0, got " + std::to_string(dt));
    Stopwatch watch;
    StepStats stats;
    stats.dt = dt;
    if (config_.method == Method::WCSPH) step_wcsph(s, dt, stats);
    else step_dfsph(s, dt, stats, interrupt);
    s.time += dt;
    ++s.steps;
    stats.max_speed = check_state(s, dt);
    stats.neighbor_count = fluid_.size();
    stats.seconds = watch.seconds();
    return stats;
  }

  Scalar stable_dt(const State& s, Scalar cfl) const override {
    const Scalar vmax = max_speed(s);
    const Scalar signal = config_.method == Method::WCSPH ? c_ + vmax : vmax;
    Scalar dt = kMaxDt;
    if (signal > 0) dt = std::min(dt, cfl * model_.spacing / signal);
    // Explicit viscosity: dt <= 0.125 spacing^2 / nu (Morris et al. 1997, eq. 24 with the
    // particle spacing; the support radius there would leave the step at the edge of stability).
    if (config_.viscosity > 0) dt = std::min(dt, 0.125 * model_.spacing * model_.spacing / config_.viscosity);
    // At rest the fluid first accelerates under gravity: keep g dt^2 below cfl * spacing.
    const Scalar g = g_.norm();
    if (g > 0) dt = std::min(dt, std::sqrt(cfl * model_.spacing / g));
    return dt;
  }

  Scalar density_error(State& s) override {
    check_finite(s, "x", s.x);
    neighborhoods(s, false);
    densities(s);
    if (config_.method == Method::WCSPH) pressures(s);
    return mean_compression(s.density.data(), s.n);
  }

 private:
  // ------------------------------------------------------------------ time steps

  // Becker and Teschner 2007, section 3, with symplectic Euler.
  void step_wcsph(State& s, Scalar dt, StepStats& stats) {
    // Neighbourhoods of the current positions (Morton reordering every few steps).
    neighborhoods(s, true);
    // Density: rho_i = sum_j m W_ij + sum_b psi_b W_ib (Akinci et al. 2012, eq. 5).
    densities(s);
    // Pressure from Tait's equation of state (Becker and Teschner 2007, eq. 6).
    pressures(s);
    // Accelerations: gravity, viscosity (course notes eq. 33) and the symmetric pressure force
    // a_i = -sum_j m (p_i/rho_i^2 + p_j/rho_j^2) grad W_ij (eq. 5), the boundary mirroring p_i.
    non_pressure_accelerations(s);
    pressure_accelerations(s);
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
    // Neighbourhoods of the current positions (Morton reordering every few steps).
    neighborhoods(s, true);
    // Densities and the factors alpha_i (eq. 11) of the current positions.
    densities(s);
    dfsph_factors(s);
    std::fill(kappa_sum_.begin(), kappa_sum_.end(), 0);
    // Divergence-free solver (Algorithm 2): make D rho / Dt = 0 with the current velocities.
    if (config_.divergence_solve) stats.divergence_iterations = divergence_solve(s, dt, stats, interrupt);
    // Non-pressure accelerations (gravity, viscosity) and the predicted velocity v* (eq. 2).
    non_pressure_accelerations(s);
    parallel_for(n, [&](Index i) { Map(s.v.data() + i * D) += dt * CMap(accel_.data() + i * D); });
    // Constant-density solver (Algorithm 3): correct v* so that rho* = rho0.
    stats.iterations = density_solve(s, dt, stats, interrupt);
    // Positions: x += dt v*.
    parallel_for(n, [&](Index i) { Map(s.x.data() + i * D) += dt * CMap(s.v.data() + i * D); });
    enforce_domain(s);
    // The pressure that the solves applied: p_i = kappa_i rho_i = rho_i^2 (kappa_i / rho_i).
    parallel_for(n, [&](Index i) { s.pressure[i] = s.density[i] * s.density[i] * kappa_sum_[i]; });
  }

  // ------------------------------------------------------------------ DFSPH solvers

  // alpha_i = rho_i / (|sum_j m grad W_ij + sum_b psi_b grad W_ib|^2 + sum_j |m grad W_ij|^2)
  // (eq. 11; the static boundary enters only the first sum). Zero without neighbours.
  void dfsph_factors(const State& s) {
    const Scalar m = model_.mass;
    parallel_for(s.n, [&](Index i) {
      const Vec xi = CMap(s.x.data() + i * D);
      Vec sum = Vec::Zero();
      Scalar sum_sq = 0;
      for (Index k = fluid_.start[i]; k < fluid_.start[i + 1]; ++k) {
        const Vec gw = m * W_.grad(xi - CMap(s.x.data() + fluid_.list[k] * D));
        sum += gw;
        sum_sq += gw.squaredNorm();
      }
      for (Index k = boundary_.start[i]; k < boundary_.start[i + 1]; ++k) {
        const Index b = boundary_.list[k];
        sum += model_.boundary_psi[b] * W_.grad(xi - CMap(model_.boundary_x.data() + b * D));
      }
      const Scalar denom = sum.squaredNorm() + sum_sq;
      // Below this a particle has (almost) no neighbours and no pressure to apply.
      factor_[i] = denom > 1e-6 * m * m / std::pow(model_.h, 2 * D + 2) ? s.density[i] / denom : 0;
    });
  }

  // Rate of density change of i under the current velocities, D rho_i / Dt =
  // sum_j m (v_i - v_j) . grad W_ij + sum_b psi_b v_i . grad W_ib (eq. 9).
  Scalar density_rate(const State& s, Index i) const {
    const Vec xi = CMap(s.x.data() + i * D);
    const Vec vi = CMap(s.v.data() + i * D);
    Scalar rate = 0;
    for (Index k = fluid_.start[i]; k < fluid_.start[i + 1]; ++k) {
      const Index j = fluid_.list[k];
      rate += model_.mass * (vi - CMap(s.v.data() + j * D)).dot(W_.grad(xi - CMap(s.x.data() + j * D)));
    }
    for (Index k = boundary_.start[i]; k < boundary_.start[i + 1]; ++k) {
      const Index b = boundary_.list[k];
      rate += model_.boundary_psi[b] * vi.dot(W_.grad(xi - CMap(model_.boundary_x.data() + b * D)));
    }
    return rate;
  }

  // v_i -= dt sum_j m (k_i + k_j) grad W_ij + dt k_i sum_b psi_b grad W_ib, with
  // k_i = kappa_i / rho_i in kappa_ (eqs. 6 and 12).
  void apply_kappa(State& s, Scalar dt) {
    parallel_for(s.n, [&](Index i) {
      const Vec xi = CMap(s.x.data() + i * D);
      const Scalar ki = kappa_[i];
      Vec dv = Vec::Zero();
      for (Index k = fluid_.start[i]; k < fluid_.start[i + 1]; ++k) {
        const Index j = fluid_.list[k];
        const Scalar kij = ki + kappa_[j];
        if (kij != 0) dv += (model_.mass * kij) * W_.grad(xi - CMap(s.x.data() + j * D));
      }
      if (ki != 0)
        for (Index k = boundary_.start[i]; k < boundary_.start[i + 1]; ++k) {
          const Index b = boundary_.list[k];
          dv += (model_.boundary_psi[b] * ki) * W_.grad(xi - CMap(model_.boundary_x.data() + b * D));
        }
      // Staged in accel_ so that every particle reads the velocities of the same iterate.
      Map(accel_.data() + i * D) = dv;
    });
    parallel_for(s.n, [&](Index i) { Map(s.v.data() + i * D) -= dt * CMap(accel_.data() + i * D); });
  }

  // Algorithm 2. Only compression is corrected (D rho/Dt clamped to >= 0), and particles with
  // fewer neighbours than a filled kernel support (free surface) are skipped, as SPlisHSPlasH does.
  int divergence_solve(State& s, Scalar dt, StepStats& stats, Interrupt& interrupt) {
    const Index n = s.n;
    const Index min_neighbors = D == 3 ? 20 : 7;
    const Scalar rho0 = config_.rho0;
    auto update_rates = [&] {
      parallel_for(n, [&](Index i) {
        const bool full = fluid_.start[i + 1] - fluid_.start[i] + boundary_.start[i + 1] - boundary_.start[i] >= min_neighbors;
        aux_[i] = full ? std::max<Scalar>(density_rate(s, i), 0) : 0;
      });
      return parallel_sum(n, [&](Index i) { return aux_[i]; }) / std::max<Index>(n, 1) * dt / rho0;
    };
    Scalar error = update_rates();
    int it = 0;
    while ((error > config_.divergence_tol || it < 1) && it < config_.max_iter) {
      interrupt.check();
      // kappa^v_i = (1/dt) (D rho_i/Dt) alpha_i (eq. 12), stored divided by rho_i.
      parallel_for(n, [&](Index i) {
        kappa_[i] = s.density[i] > 0 ? aux_[i] * factor_[i] / (dt * s.density[i]) : 0;
        kappa_sum_[i] += kappa_[i];
      });
      apply_kappa(s, dt);
      error = update_rates();
      ++it;
    }
    stats.divergence_error = error;
    return it;
  }

  // Algorithm 3: predicted density rho*_i = rho_i + dt D rho_i/Dt (eq. 4), clamped below at
  // rho0 (a free surface is not pulled together); kappa_i = (rho*_i - rho0) alpha_i / dt^2 (eq. 6).
  int density_solve(State& s, Scalar dt, StepStats& stats, Interrupt& interrupt) {
    const Index n = s.n;
    const Scalar rho0 = config_.rho0;
    auto update_predictions = [&] {
      parallel_for(n, [&](Index i) { aux_[i] = std::max(s.density[i] + dt * density_rate(s, i), rho0); });
      return mean_compression(aux_.data(), n);
    };
    Scalar error = update_predictions();
    int it = 0;
    while ((error > config_.tol || it < 2) && it < config_.max_iter) {
      interrupt.check();
      parallel_for(n, [&](Index i) {
        kappa_[i] = s.density[i] > 0 ? (aux_[i] - rho0) * factor_[i] / (dt * dt * s.density[i]) : 0;
        kappa_sum_[i] += kappa_[i];
      });
      apply_kappa(s, dt);
      error = update_predictions();
      ++it;
    }
    stats.density_error = error;
    return it;
  }

  // ------------------------------------------------------------------ shared passes

  void neighborhoods(State& s, bool may_reorder) {
    if (may_reorder && config_.reorder_every > 0 && s.steps % config_.reorder_every == 0) reorder(s);
    fluid_grid_.build(s.x.data(), s.n, model_.h);
    fluid_.build<D>(fluid_grid_, s.x.data(), s.x.data(), s.n, model_.h, true);
    if (model_.boundary_count() > 0)
      boundary_.build<D>(boundary_grid_, model_.boundary_x.data(), s.x.data(), s.n, model_.h, false);
    else
      boundary_.start.assign(static_cast<size_t>(s.n) + 1, 0);
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
  }

  void densities(State& s) {
    const Scalar m = model_.mass;
    parallel_for(s.n, [&](Index i) {
      const Vec xi = CMap(s.x.data() + i * D);
      Scalar rho = m * W_.w0();
      for (Index k = fluid_.start[i]; k < fluid_.start[i + 1]; ++k)
        rho += m * W_.w((xi - CMap(s.x.data() + fluid_.list[k] * D)).norm());
      for (Index k = boundary_.start[i]; k < boundary_.start[i + 1]; ++k) {
        const Index b = boundary_.list[k];
        rho += model_.boundary_psi[b] * W_.w((xi - CMap(model_.boundary_x.data() + b * D)).norm());
      }
      s.density[i] = rho;
    });
  }

  void pressures(State& s) {
    parallel_for(s.n, [&](Index i) { s.pressure[i] = tait_pressure(s.density[i], config_.rho0, B_, config_.gamma); });
  }

  // accel_ = g + viscosity (fluid-fluid; walls are free-slip).
  void non_pressure_accelerations(const State& s) {
    const Scalar nu = config_.viscosity;
    parallel_for(s.n, [&](Index i) {
      Vec a = g_;
      if (nu > 0) {
        const Vec xi = CMap(s.x.data() + i * D);
        const Vec vi = CMap(s.v.data() + i * D);
        for (Index k = fluid_.start[i]; k < fluid_.start[i + 1]; ++k) {
          const Index j = fluid_.list[k];
          const Vec xij = xi - CMap(s.x.data() + j * D);
          a += viscosity_term<D>(xij, vi - CMap(s.v.data() + j * D), W_.grad(xij),
                                 model_.mass / s.density[j], nu, model_.h);
        }
      }
      Map(accel_.data() + i * D) = a;
    });
  }

  void pressure_accelerations(const State& s) {
    const Scalar m = model_.mass;
    parallel_for(s.n, [&](Index i) {
      const Scalar pi = s.pressure[i] / (s.density[i] * s.density[i]);
      const Vec xi = CMap(s.x.data() + i * D);
      Vec a = Vec::Zero();
      for (Index k = fluid_.start[i]; k < fluid_.start[i + 1]; ++k) {
        const Index j = fluid_.list[k];
        const Scalar pij = pi + s.pressure[j] / (s.density[j] * s.density[j]);
        if (pij != 0) a -= (m * pij) * W_.grad(xi - CMap(s.x.data() + j * D));
      }
      // Pressure mirroring at the boundary: p_b / rho_b^2 = p_i / rho_i^2.
      if (pi != 0)
        for (Index k = boundary_.start[i]; k < boundary_.start[i + 1]; ++k) {
          const Index b = boundary_.list[k];
          a -= (2 * model_.boundary_psi[b] * pi) * W_.grad(xi - CMap(model_.boundary_x.data() + b * D));
        }
      Map(accel_.data() + i * D) += a;
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
    for (Index i = 0; i < s.n; ++i) vmax2 = std::max(vmax2, CMap(s.v.data() + i * D).squaredNorm());
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

  // c = 10 sqrt(2 |g| H) for the fluid's initial height H along gravity, so that the flow stays
  // below Mach 0.1 and compression near 1% (Monaghan 1994); never below 10 x the initial speeds.
  Scalar default_speed_of_sound(const State& s) const {
    const Scalar g = g_.norm();
    Scalar height = 0;
    if (g > 0 && s.n > 0) {
      const Vec up = -g_ / g;
      Scalar lo = INFINITY, hi = -INFINITY;
      for (Index i = 0; i < s.n; ++i) {
        const Scalar y = up.dot(CMap(s.x.data() + i * D));
        lo = std::min(lo, y);
        hi = std::max(hi, y);
      }
      height = std::max(hi - lo, model_.h);
    }
    Scalar c = 10 * std::sqrt(2 * g * height);
    c = std::max(c, 10 * max_speed(s));
    return c > 0 ? c : 1.0;
  }

  CubicSpline<D> W_;
  Vec g_ = Vec::Zero();
  Scalar B_ = 0;
  NeighborGrid<D> fluid_grid_, boundary_grid_;
  NeighborLists fluid_, boundary_;
  std::vector<Scalar> accel_;      // (n, d) accelerations, or velocity corrections in DFSPH
  std::vector<Scalar> aux_;        // DFSPH: predicted densities or density rates
  std::vector<Scalar> kappa_;      // DFSPH: kappa_i / rho_i of the current iteration
  std::vector<Scalar> kappa_sum_;  // DFSPH: kappa_i / rho_i summed over the step's solves
  std::vector<Scalar> factor_;     // DFSPH: alpha_i
};

}  // namespace

std::unique_ptr<Solver> Solver::create(const Model& model, const Config& config, const State& state) {
  if (state.dim != model.dim) throw InvalidArgument("positions: dimension differs from the model's");
  if (state.n >= (Index{1} << 31)) throw InvalidArgument("positions: at most 2^31 - 1 particles");
  if (!(config.rho0 > 0)) throw InvalidArgument("rho0: expected a number > 0");
  if (config.viscosity < 0) throw InvalidArgument("viscosity: expected a number >= 0");
  if (!(config.gamma > 0)) throw InvalidArgument("gamma: expected a number > 0");
  if (config.speed_of_sound < 0) throw InvalidArgument("speed_of_sound: expected a number > 0");
  if (!(config.tol > 0)) throw InvalidArgument("tol: expected a number > 0");
  if (!(config.divergence_tol > 0)) throw InvalidArgument("divergence_tol: expected a number > 0");
  if (config.max_iter < 1) throw InvalidArgument("max_iter: expected an integer >= 1");
  if (config.reorder_every < 0) throw InvalidArgument("reorder_every: expected an integer >= 0");
  if (model.dim == 2) return std::make_unique<SolverD<2>>(model, config, state);
  return std::make_unique<SolverD<3>>(model, config, state);
}

}  // namespace kinema::sph
