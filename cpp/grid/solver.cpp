#include "grid/solver.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <string>

#include "core/errors.h"
#include "core/parallel.h"
#include "core/rollback.h"
#include "core/simd.h"
#include "core/timer.h"
#include "grid/advect_rows.h"
#include "linalg/cg.h"

namespace kinema::grid {

namespace {

constexpr const char* kComponentNames3[3] = {"u", "v", "w"};

// The user's name of internal velocity component `axis`.
std::string component_name(int dim, int axis) { return kComponentNames3[axis - (3 - dim)]; }

Scalar max_abs(const std::vector<Scalar>& v) {
  Scalar m = 0;
  const Index n = static_cast<Index>(v.size());
  const Scalar* p = v.data();
#pragma omp parallel for schedule(static) reduction(max : m) if (n > 8 * kParallelGrain)
  for (Index i = 0; i < n; ++i) {
    const Scalar a = std::fabs(p[i]);
    // a non-finite entry must win the reduction: NaN compares false everywhere
    m = a <= std::numeric_limits<Scalar>::max() ? std::max(m, a)
                                                 : std::numeric_limits<Scalar>::infinity();
  }
  return m;
}

// body(i, j, first node of the row, scratch) for every row of L, handed out in small blocks on
// demand as for_each_node does, with `arrays` scratch rows of L.n[2] values per thread.
template <class Body>
void for_each_row(const FieldLayout& L, int arrays, Body&& body) {
  const Index rows = L.rows(), n1 = L.n[1], nk = L.n[2];
#pragma omp parallel if (L.size() > 8 * kParallelGrain)
  {
    std::vector<Scalar> scratch(static_cast<size_t>(arrays * nk));
#pragma omp for schedule(dynamic, 8)
    for (Index row = 0; row < rows; ++row) body(row / n1, row % n1, row * nk, scratch.data());
  }
}

// Runs the enclosing scope on one thread when the grid is small: the shared kernels (CG, vector
// updates) open a parallel region per operation above kParallelGrain entries, which on a few
// thousand cells costs more than it saves (and far more on a loaded machine). Results do not change:
// the reductions are deterministic for any thread count (core/parallel.h).
class SerialBelow {
 public:
  explicit SerialBelow(Index n) : saved_(omp_get_max_threads()), active_(n <= 8 * kParallelGrain) {
    if (active_) omp_set_num_threads(1);
  }
  ~SerialBelow() {
    if (active_) omp_set_num_threads(saved_);
  }
  SerialBelow(const SerialBelow&) = delete;
  SerialBelow& operator=(const SerialBelow&) = delete;

 private:
  int saved_;
  bool active_;
};

}  // namespace

Model make_model(const GridShape& shape, Scalar h) {
  if (!(h > 0) || !std::isfinite(h)) throw InvalidArgument("h: expected a finite cell size > 0");
  Model model;
  model.shape = shape;
  model.h = h;
  model.solid.assign(shape.size(), 0);
  return model;
}

void Solver::check_config() const {
  const Config& c = config_;
  if (c.rk_order < 1 || c.rk_order > 3)
    throw InvalidArgument("rk_order: expected 1, 2 or 3, got " + std::to_string(c.rk_order));
  if (!(c.tol > 0 && c.tol < 1))
    throw InvalidArgument("tol: expected a relative tolerance in (0, 1), got " + format_real(c.tol));
  if (c.max_iter < 0) throw InvalidArgument("max_iter: expected a count >= 0 (0: the default)");
  if (c.pressure_vcycles < 0)
    throw InvalidArgument("pressure_vcycles: expected a count >= 0 (0: solve to tol), got " +
                          std::to_string(c.pressure_vcycles));
  if (c.pressure_vcycles > 0 && c.periodic)
    for (int a = 0; a < 3; ++a)
      if (model_.shape.active(a) && model_.shape.n[a] % 2 != 0)
        throw InvalidArgument("pressure_vcycles: multigrid on a periodic grid needs an even number of cells "
                              "along every axis");
  if (!(c.viscosity >= 0 && std::isfinite(c.viscosity)))
    throw InvalidArgument("viscosity: expected a finite value >= 0, got " + format_real(c.viscosity));
  if (!(c.vorticity_confinement >= 0 && std::isfinite(c.vorticity_confinement)))
    throw InvalidArgument("vorticity_confinement: expected a finite value >= 0, got " +
                          format_real(c.vorticity_confinement));
  if (!std::isfinite(c.alpha) || !std::isfinite(c.beta))
    throw InvalidArgument("buoyancy: expected finite (alpha, beta)");
  for (int a = 0; a < 3; ++a) {
    if (!std::isfinite(c.gravity[a])) throw InvalidArgument("gravity: expected finite components");
    if (!std::isfinite(c.up[a])) throw InvalidArgument("up: expected finite components");
  }
  for (int w = 0; w < 6; ++w) {
    if (!c.open[w]) continue;
    if (c.periodic) throw InvalidArgument("open: a periodic domain has no open sides (boundary='periodic')");
    if (!model_.shape.active(w / 2)) throw InvalidArgument("open: a 2D domain has no z sides");
  }
  if (static_cast<Index>(model_.solid.size()) != model_.shape.size())
    throw InvalidArgument("solid: expected one entry per cell (" + std::to_string(model_.shape.size()) +
                          "), got " + std::to_string(model_.solid.size()));
}

Solver::Solver(const Model& model, const Config& config) : model_(model), config_(config) {
  check_config();
  const GridShape& shape = model_.shape;
  // Buoyancy acts against gravity, or along +y without it.
  if (config_.up == Vec3{0, 0, 0}) {
    const Vec3& g = config_.gravity;
    const Scalar norm = std::sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2]);
    if (norm > 0) config_.up = Vec3{-g[0] / norm, -g[1] / norm, -g[2] / norm};
    else config_.up[3 - shape.dim + 1] = 1;
  }
  cells_ = cell_layout(shape, config.periodic);
  for (int a = 0; a < 3; ++a) {
    active_[a] = shape.active(a);
    faces_[a] = face_layout(shape, a, config.periodic);
    if (!active_[a]) continue;
    velocity_new_[a].assign(faces_[a].size(), 0);
    fixed_[a].assign(faces_[a].size(), 0);
  }
  rhs_.assign(shape.size(), 0);
  residual_.assign(shape.size(), 0);
  const int scalars = int(config.density) + int(config.temperature);
  for (int f = 0; f < scalars; ++f) scalar_new_[f].assign(shape.size(), 0);
  Index largest_face = 0;
  for (int a = 0; a < 3; ++a)
    if (active_[a]) largest_face = std::max(largest_face, faces_[a].size());
  advection_scratch_.reserve(largest_face, config.advection, std::max(scalars, 1));
  if (config.viscosity > 0) {
    rhs_face_.assign(largest_face, 0);
    solution_face_.assign(largest_face, 0);
  }
  const bool buoyant = (config.density && config.alpha != 0) || (config.temperature && config.beta != 0);
  if (config.vorticity_confinement > 0 || buoyant)
    for (int a = 0; a < 3; ++a)
      if (active_[a]) force_[a].assign(shape.size(), 0);
  if (config.vorticity_confinement > 0) {
    for (int a = 0; a < 3; ++a) {
      if (active_[a]) cell_velocity_[a].assign(shape.size(), 0);
      // 2D vorticity is a scalar along the inactive axis 0.
      if (shape.dim == 3 || a == 0) vorticity_[a].assign(shape.size(), 0);
    }
    vorticity_norm_.assign(shape.size(), 0);
  }
  for (int w = 0; w < 6; ++w) {
    // Open sides extend the nearest value, as free-slip walls do (zero normal gradient).
    walls_.no_slip[w] = !config.open[w] && !config.periodic && (config.no_slip || model_.wall_moving[w]);
    walls_.velocity[w] = model_.wall_velocity[w];
  }
  check_kernel();
  build_solids();
}

State Solver::make_state() const {
  State state;
  const Index n = model_.shape.size();
  for (int a = 0; a < 3; ++a)
    if (active_[a]) state.velocity[a].assign(faces_[a].size(), 0);
  state.pressure.assign(n, 0);
  if (config_.density) state.density.assign(n, 0);
  if (config_.temperature) state.temperature.assign(n, 0);
  return state;
}

void Solver::check_kernel() const {
  const AdvectionKernel k = config_.advection_kernel;
  if (k == AdvectionKernel::Auto || k == AdvectionKernel::Nodes) return;
  if (k == AdvectionKernel::RowsAvx2 && !cpu_has_avx2())
    throw InvalidArgument("advection_kernel: 'rows_avx2' needs a CPU with AVX2");
  // The row kernels' conditions depend on the layouts and walls only, not on the values.
  const MacVelocity u = mac_velocity(velocity_new_);
  bool apply = rows_apply(u, cells_);
  for (int a = 0; a < 3; ++a) apply = apply && (!active_[a] || rows_apply(u, faces_[a]));
  if (!apply)
    throw InvalidArgument("advection_kernel: the row kernels need at least 2 cells per axis and no no-slip or "
                          "moving walls; use 'auto' or 'nodes'");
}

Index Solver::neighbour(const FieldLayout& L, const std::array<Index, 3>& idx, int axis,
                             int step) {
  Index m = idx[axis] + step;
  if (L.period[axis] > 0) {
    const Index p = L.period[axis];
    m = (m % p + p) % p;
  } else if (m < 0 || m >= L.n[axis]) {
    return -1;
  }
  std::array<Index, 3> j = idx;
  j[axis] = m;
  return L.index(j[0], j[1], j[2]);
}

void Solver::refresh_solids(State& state) {
  if (model_.solid == solid_used_) return;
  build_solids();
  for (Index c = 0; c < model_.shape.size(); ++c)
    if (!fluid_cell(c)) state.pressure[c] = 0;
  enforce_boundary(state);
}

void Solver::build_solids() {
  solid_used_ = model_.solid;
  has_solid_ = std::any_of(solid_used_.begin(), solid_used_.end(), [](std::uint8_t s) { return s != 0; });
  const GridShape& s = model_.shape;
  for (int a = 0; a < 3; ++a) {
    if (!active_[a]) continue;
    const FieldLayout& L = faces_[a];
    for_each_node(L, [&](Index i, Index j, Index k, Index f) {
      const std::array<Index, 3> idx{i, j, k};
      std::uint8_t flag = 0;
      const bool first = idx[a] == 0, last = idx[a] == s.n[a];
      if (config_.periodic) {
        if (last) flag = 2;
      } else if ((first && !config_.open[2 * a]) || (last && !config_.open[2 * a + 1])) {
        flag = 1;
      }
      if (flag != 1 && has_solid_) {
        // the cells on either side: c - e_a (wrapping) and c; an open side's face has one
        std::array<Index, 3> lo = idx, hi = idx;
        lo[a] = first ? s.n[a] - 1 : idx[a] - 1;
        hi[a] = last ? 0 : idx[a];
        if (!config_.periodic && first) lo = hi;
        if (!config_.periodic && last) hi = lo;
        if (solid_used_[s.index(lo[0], lo[1], lo[2])] || solid_used_[s.index(hi[0], hi[1], hi[2])])
          flag = flag == 2 ? 2 : 1;
      }
      fixed_[a][f] = flag;
    });
    pinned_faces_[a].clear();
    duplicate_faces_[a].clear();
    for (Index f = 0; f < L.size(); ++f) {
      if (fixed_[a][f] == 1) pinned_faces_[a].push_back(f);
      else if (fixed_[a][f] == 2) duplicate_faces_[a].push_back(f);
    }
  }
  PoissonConfig pc;
  pc.method = config_.pressure_vcycles > 0 ? PoissonMethod::Multigrid : config_.projection;
  if (config_.periodic) {
    // red-black smoothing needs an even number of cells along every periodic axis
    for (int a = 0; a < 3; ++a)
      if (active_[a] && s.n[a] % 2 != 0) pc.method = PoissonMethod::CG;
  }
  // Closed walls are zero-flux (Neumann); open sides hold p = 0 (Dirichlet, ghost -p).
  int open_walls = 0;
  for (int w = 0; w < 6; ++w)
    if (config_.open[w]) open_walls |= 1 << w;
  pressure_solver_ = std::make_unique<PoissonSolver>(
      s, model_.h, config_.periodic ? Boundary::Periodic : Boundary::Neumann,
      has_solid_ ? solid_used_.data() : nullptr, 0, pc, open_walls);
}

void Solver::set_wall_velocity(int wall, const Vec3& velocity) {
  if (config_.periodic)
    throw InvalidArgument("side: a periodic domain has no walls (boundary='periodic')");
  if (wall < 0 || wall >= 6) throw InvalidArgument("side: expected a wall 0-5, got " + std::to_string(wall));
  const int axis = wall / 2;
  if (!active_[axis]) throw InvalidArgument("side: no such wall in a 2D domain");
  if (config_.open[wall]) throw InvalidArgument("side: an open side is not a wall and cannot move");
  if (velocity[axis] != 0)
    throw InvalidArgument("velocity: a wall can only move tangentially (its normal component must be 0)");
  for (Scalar x : velocity)
    if (!std::isfinite(x)) throw InvalidArgument("velocity: expected finite values");
  const bool moving = velocity[0] != 0 || velocity[1] != 0 || velocity[2] != 0;
  const AdvectionKernel k = config_.advection_kernel;
  if (moving && (k == AdvectionKernel::Rows || k == AdvectionKernel::RowsAvx2))
    throw InvalidArgument("velocity: the row advection kernels do not handle moving walls; use "
                          "advection_kernel='auto' or 'nodes'");
  model_.wall_velocity[wall] = velocity;
  model_.wall_moving[wall] = moving;
  walls_.no_slip[wall] = config_.no_slip || moving;
  walls_.velocity[wall] = velocity;
}

Index Solver::add_source(const std::uint8_t* mask, bool set_density, Scalar density, bool set_temperature,
                         Scalar temperature, bool set_velocity, const Vec3& velocity) {
  if (set_density && !config_.density)
    throw InvalidArgument("density: the fluid carries no density field (create it with density=True)");
  if (set_temperature && !config_.temperature)
    throw InvalidArgument("temperature: the fluid carries no temperature field (create it with temperature=True)");
  if (!set_density && !set_temperature && !set_velocity)
    throw InvalidArgument("add_source: give at least one of density, temperature, velocity");
  if (!std::isfinite(density)) throw InvalidArgument("density: expected a finite value, got " + format_real(density));
  if (!std::isfinite(temperature))
    throw InvalidArgument("temperature: expected a finite value, got " + format_real(temperature));
  for (int a = 0; a < 3; ++a)
    if (!std::isfinite(velocity[a])) throw InvalidArgument("velocity: expected finite values");
  Model::Source src;
  src.set_density = set_density;
  src.set_temperature = set_temperature;
  src.density = density;
  src.temperature = temperature;
  src.set_velocity = set_velocity;
  src.velocity = velocity;
  std::array<std::vector<std::uint8_t>, 3> on;
  for (int a = 0; a < 3; ++a)
    if (active_[a]) on[a].assign(faces_[a].size(), 0);
  const GridShape& s = model_.shape;
  for (Index i = 0; i < s.n[0]; ++i)
    for (Index j = 0; j < s.n[1]; ++j)
      for (Index k = 0; k < s.n[2]; ++k) {
        const Index c = s.index(i, j, k);
        if (!mask[c]) continue;
        src.cells.push_back(c);
        for (int a = 0; a < 3; ++a) {
          if (!active_[a]) continue;
          std::array<Index, 3> idx{i, j, k};
          on[a][faces_[a].index(idx[0], idx[1], idx[2])] = 1;
          ++idx[a];
          if (config_.periodic && idx[a] == s.n[a]) idx[a] = 0;  // the duplicate follows face 0
          on[a][faces_[a].index(idx[0], idx[1], idx[2])] = 1;
        }
      }
  for (int a = 0; a < 3; ++a)
    for (Index f = 0; f < static_cast<Index>(on[a].size()); ++f)
      if (on[a][f]) src.faces[a].push_back(f);
  model_.sources.push_back(std::move(src));
  return static_cast<Index>(model_.sources.size()) - 1;
}

void Solver::apply_sources(State& state) const {
  for (const Model::Source& src : model_.sources) {
    for (Index c : src.cells) {
      if (!fluid_cell(c)) continue;
      if (src.set_density) state.density[c] = src.density;
      if (src.set_temperature) state.temperature[c] = src.temperature;
    }
    if (!src.set_velocity) continue;
    for (int a = 0; a < 3; ++a) {
      if (!active_[a]) continue;
      Scalar* u = state.velocity[a].data();
      for (Index f : src.faces[a])
        if (fixed_[a][f] != 1) u[f] = src.velocity[a];
    }
  }
}

// ------------------------------------------------------------------------------------ step

void Solver::check_state(const State& state) const {
  bool fits = state.pressure.size() == static_cast<size_t>(cells_.size()) &&
              state.density.size() == (config_.density ? state.pressure.size() : 0) &&
              state.temperature.size() == (config_.temperature ? state.pressure.size() : 0);
  for (int a = 0; a < 3; ++a)
    fits = fits && state.velocity[a].size() == static_cast<size_t>(active_[a] ? faces_[a].size() : 0);
  if (!fits)
    throw InvalidArgument("state: its arrays do not fit this grid and configuration (make it with make_state)");
}

StepStats Solver::step(State& state, Scalar dt, Interrupt& interrupt, const Scalar* control,
                       std::array<AdvectionScratch, 4>* kept) {
  if (!(dt > 0) || !std::isfinite(dt)) throw InvalidArgument("dt: expected a finite time step > 0, got " + format_real(dt));
  check_state(state);
  return with_rollback(state, [&] { return step_phases(state, dt, interrupt, control, kept); });
}

StepStats Solver::step_phases(State& state, Scalar dt, Interrupt& interrupt, const Scalar* control,
                              std::array<AdvectionScratch, 4>* kept) {
  SerialBelow serial(cells_.size());
  Stopwatch total, clock;
  StepStats stats;
  stats.dt = dt;
  stats.cfl = max_speed(state) * dt / model_.h;
  if (!std::isfinite(stats.cfl)) check(state, dt, state.steps + 1);  // the caller wrote a NaN or Inf
  refresh_solids(state);
  apply_sources(state);
  enforce_boundary(state);

  // 1. Advection of velocity and scalars (kernels.h; Stam 1999, Selle et al. 2008).
  advect(state, dt, kept);
  stats.advect_seconds = clock.seconds();
  clock.restart();
  // 2. Body forces: gravity, buoyancy, vorticity confinement (Fedkiw et al. 2001, Sec. 3-4),
  // and the caller's control accelerations.
  add_forces(state, dt, control);
  stats.forces_seconds = clock.seconds();
  clock.restart();
  interrupt.check();
  // 3. Viscosity, backward Euler: (I - nu dt lap) u^{n+1} = u* (Stam 1999, Sec. 3).
  stats.viscosity_iterations = diffuse(state, dt, interrupt);
  stats.viscosity_seconds = clock.seconds();
  clock.restart();
  // 4. Projection: -lap p = -div(u*)/dt, u = u* - dt grad p (Chorin 1968; Bridson Ch. 5).
  stats.pressure = project(state, dt, interrupt);
  stats.projection_seconds = clock.seconds();
  // 5. Blow-up detection.
  state.time += dt;
  ++state.steps;
  check(state, dt, state.steps);
  stats.time = state.time;
  stats.seconds = total.seconds();
  return stats;
}

Scalar Solver::stable_dt(const State& state, Scalar cfl, Scalar max_dt) const {
  if (!(cfl > 0) || !std::isfinite(cfl)) throw InvalidArgument("cfl: expected a finite number > 0, got " + format_real(cfl));
  if (!(max_dt > 0)) throw InvalidArgument("max_dt: expected a step > 0 [s], got " + format_real(max_dt));
  check_state(state);
  Scalar speed = max_speed(state);
  if (!std::isfinite(speed)) check(state, 0, state.steps + 1);
  for (const Vec3& w : model_.wall_velocity)
    speed = std::max(speed, std::sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2]));
  for (const Model::Source& src : model_.sources)  // imposed before the step
    if (src.set_velocity)
      for (Scalar c : src.velocity) speed = std::max(speed, std::fabs(c));
  const Vec3& g = config_.gravity;
  speed += std::sqrt(5 * model_.h * std::sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2]));
  return speed > 0 ? std::min(max_dt, cfl * model_.h / speed) : max_dt;
}

AdvanceResult Solver::advance(State& state, Scalar duration, Scalar cfl, Scalar max_dt, Interrupt& interrupt,
                              StepStats* last) {
  stable_dt(state, cfl, max_dt);  // the argument checks, before any step
  const Scalar end = state.time + duration;
  return advance_to(
      state, duration,
      [&](const State& s) {
        const Scalar dt = stable_dt(s, cfl, max_dt);
        return std::isinf(dt) ? end - s.time : dt;  // nothing moves: one step to the end
      },
      [&](State& s, Scalar dt) { return step(s, dt, interrupt); },
      [&](const StepStats& stats) {
        if (last) *last = stats;
      },
      interrupt);
}

// ------------------------------------------------------------------------------ advection

MacVelocity Solver::mac_velocity(const std::array<std::vector<Scalar>, 3>& velocity) const {
  MacVelocity u;
  for (int a = 0; a < 3; ++a) {
    u.layout[a] = faces_[a];
    if (active_[a]) u.comp[a] = velocity[a].data();
  }
  if (walls_.no_slip != std::array<bool, 6>{}) u.walls = &walls_;
  return u;
}

void Solver::advect(State& state, Scalar dt, std::array<AdvectionScratch, 4>* kept) {
  const MacVelocity u = mac_velocity(state.velocity);
  const Scalar dt_grid = dt / model_.h;
  const int rk = config_.rk_order;
  // The scalars share their departure points: one call advects both.
  Scalar* fields[2];
  const Scalar* q[2];
  Scalar* out[2];
  int count = 0;
  for (std::vector<Scalar>* s : {&state.density, &state.temperature}) {
    if (s->empty()) continue;
    q[count] = fields[count] = s->data();
    out[count] = scalar_new_[count].data();
    ++count;
  }
  grid::advect_fields(config_.advection, u, cells_, count, q, out, dt_grid, rk,
                       kept ? (*kept)[0] : advection_scratch_, -1, config_.advection_kernel);
  const std::vector<std::uint8_t>& solid = model_.solid;
  for (int f = 0; f < count; ++f) {
    Scalar* dst = fields[f];
    const Scalar* src = out[f];
    parallel_for(cells_.size(), [&](Index c) { dst[c] = has_solid_ && solid[c] ? 0 : src[c]; });
  }
  if (count > 0 && any_open()) inflow_ambient(state, fields, count);
  // Velocity last: every component is traced through the old field.
  for (int a = 0; a < 3; ++a) {
    if (!active_[a]) continue;
    const Scalar* qa = state.velocity[a].data();
    Scalar* oa = velocity_new_[a].data();
    grid::advect_fields(config_.advection, u, faces_[a], 1, &qa, &oa, dt_grid, rk,
                         kept ? (*kept)[1 + a] : advection_scratch_, a, config_.advection_kernel);
  }
  for (int a = 0; a < 3; ++a) {
    if (!active_[a]) continue;
    Scalar* dst = state.velocity[a].data();
    const Scalar* src = velocity_new_[a].data();
    parallel_for(faces_[a].size(), [&](Index f) { dst[f] = src[f]; });
  }
  enforce_boundary(state);
}

// Where fluid enters through an open side it brings ambient air: the scalars of the cells whose
// open face has an inward velocity become 0 (Dirichlet at inflow; outflow keeps the
// zero-gradient extension of the clamped back-trace).
void Solver::inflow_ambient(const State& state, Scalar* const* fields, int count) const {
  const GridShape& s = model_.shape;
  for (int w = 0; w < 6; ++w) {
    if (!config_.open[w]) continue;
    const int a = w / 2, side = w % 2;
    const Index layer = side ? s.n[a] - 1 : 0, face_layer = side ? s.n[a] : 0;
    const FieldLayout& F = faces_[a];
    const Scalar* u = state.velocity[a].data();
    const int b = (a + 1) % 3, c = (a + 2) % 3;
    for (Index ib = 0; ib < s.n[b]; ++ib)
      for (Index ic = 0; ic < s.n[c]; ++ic) {
        std::array<Index, 3> idx{};
        idx[a] = face_layer;
        idx[b] = ib;
        idx[c] = ic;
        const Scalar un = u[F.index(idx[0], idx[1], idx[2])];
        if (!(side ? un < 0 : un > 0)) continue;
        idx[a] = layer;
        const Index cell = s.index(idx[0], idx[1], idx[2]);
        for (int f = 0; f < count; ++f) fields[f][cell] = 0;
      }
  }
}

// --------------------------------------------------------------------------------- forces

void Solver::add_cell_force(State& state, int axis, const Scalar* f, Index fs, Scalar dt, Scalar du) const {
  const FieldLayout& L = faces_[axis];
  Scalar* u = state.velocity[axis].data();
  const std::vector<std::uint8_t>& fixed = fixed_[axis];
  const Index n_axis = model_.shape.n[axis];
  const Index stride = cells_.stride(axis);
  const bool periodic = config_.periodic;
  for_each_node(L, [&](Index i, Index j, Index k, Index face) {
    if (fixed[face]) return;
    const Index ia = axis == 0 ? i : axis == 1 ? j : k;
    if (!periodic && (ia == 0 || ia == n_axis)) {  // a face of an open side: the one cell inside
      std::array<Index, 3> c{i, j, k};
      if (ia == n_axis) --c[axis];
      u[face] += dt * f[cells_.index(c[0], c[1], c[2]) * fs] + du;
      return;
    }
    // other free faces are interior (or a periodic face 0): cell (i, j, k) is the upper neighbour
    const Index hi = cells_.index(i, j, k);
    const Index lo = ia == 0 ? hi + (n_axis - 1) * stride : hi - stride;
    u[face] += dt * 0.5 * (f[lo * fs] + f[hi * fs]) + du;
  });
}

void Solver::add_forces(State& state, Scalar dt, const Scalar* control) {
  // One pass per component: the cell-centred forces (buoyancy and vorticity confinement, summed
  // per cell into force_) averaged to the faces, plus gravity, uniform on every free face.
  const bool rho = !state.density.empty() && config_.alpha != 0;
  const bool temp = !state.temperature.empty() && config_.beta != 0;
  const bool buoyant = rho || temp;
  const bool confined = config_.vorticity_confinement > 0;
  if (confined) {
    confinement_force(state, buoyant);
  } else if (buoyant) {
    const Scalar* density = state.density.data();
    const Scalar* temperature = state.temperature.data();
    const Scalar alpha = config_.alpha, beta = config_.beta;
    for (int a = 0; a < 3; ++a) {
      if (!active_[a] || config_.up[a] == 0) continue;
      Scalar* f = force_[a].data();
      const Scalar up = config_.up[a];
      parallel_for(cells_.size(), [&](Index c) {
        f[c] = up * ((rho ? -alpha * density[c] : 0) + (temp ? beta * temperature[c] : 0));
      });
    }
  }
  for (int a = 0; a < 3; ++a) {
    if (!active_[a]) continue;
    const Scalar du = dt * config_.gravity[a];
    if (confined || (buoyant && config_.up[a] != 0)) {
      add_cell_force(state, a, force_[a].data(), 1, dt, du);
    } else if (du != 0) {
      Scalar* u = state.velocity[a].data();
      const std::uint8_t* fixed = fixed_[a].data();
      parallel_for(faces_[a].size(), [&](Index f) {
        if (!fixed[f]) u[f] += du;
      });
    }
    if (control) add_cell_force(state, a, control + (a - (3 - model_.shape.dim)), model_.shape.dim, dt, 0);
  }
  // Prescribed and duplicate faces were skipped above; a periodic duplicate must follow its face
  // 0, or the seam carries a spurious divergence that the projection cannot remove.
  if (config_.periodic) enforce_boundary(state);
}

void Solver::confinement_force(const State& state, bool buoyant) {
  const GridShape& s = model_.shape;
  const FieldLayout& C = cells_;
  const Scalar h = model_.h;
  // Cell-centred velocity.
  for (int a = 0; a < 3; ++a) {
    if (!active_[a]) continue;
    const Scalar* u = state.velocity[a].data();
    const Index fs = faces_[a].stride(a);
    Scalar* cu = cell_velocity_[a].data();
    const FieldLayout& F = faces_[a];
    for_each_node(C, [&](Index i, Index j, Index k, Index c) {
      const Index f = F.index(i, j, k);
      cu[c] = 0.5 * (u[f] + u[f + fs]);
    });
  }
  // Central difference of a cell field along an axis, one-sided at closed walls.
  const bool periodic = config_.periodic;
  auto diff = [&](const Scalar* q, Index c, Index ib, int axis) -> Scalar {
    if (!active_[axis] || !q) return 0;
    const Index n = s.n[axis], stride = C.stride(axis);
    Index up = c + stride, dn = c - stride;
    Scalar span = 2;
    if (ib + 1 >= n) {
      if (periodic) up = c - (n - 1) * stride;
      else up = c, span -= 1;
    }
    if (ib == 0) {
      if (periodic) dn = c + (n - 1) * stride;
      else dn = c, span -= 1;
    }
    return span > 0 ? (q[up] - q[dn]) / (span * h) : 0;
  };
  // diff over the cells of row (i, j) starting at c0 into out: the neighbours along axes 0 and 1
  // are the same for the whole row, along axis 2 only the row's two end cells differ, so the
  // loops run without branches and vectorise.
  const Index nk = C.n[2];
  auto diff_row = [&](const Scalar* q, Index i, Index j, Index c0, int axis, Scalar* out) {
    if (!active_[axis] || !q) {
      std::fill(out, out + nk, Scalar(0));
    } else if (axis < 2) {
      const Index ib = axis == 0 ? i : j, n = s.n[axis], stride = C.stride(axis);
      Index up = stride, dn = -stride;
      Scalar span = 2;
      if (ib + 1 >= n) {
        if (periodic) up = -(n - 1) * stride;
        else up = 0, span -= 1;
      }
      if (ib == 0) {
        if (periodic) dn = (n - 1) * stride;
        else dn = 0, span -= 1;
      }
      if (span > 0) {
        const Scalar d = span * h;
        const Scalar *hi = q + c0 + up, *lo = q + c0 + dn;
        for (Index k = 0; k < nk; ++k) out[k] = (hi[k] - lo[k]) / d;
      } else {
        std::fill(out, out + nk, Scalar(0));
      }
    } else {
      const Scalar d = 2 * h;
      const Scalar* r = q + c0;
      for (Index k = 1; k + 1 < nk; ++k) out[k] = (r[k + 1] - r[k - 1]) / d;
      out[0] = diff(q, c0, 0, 2);
      if (nk > 1) out[nk - 1] = diff(q, c0 + nk - 1, nk - 1, 2);
    }
  };
  auto comp = [&](int a) -> const Scalar* { return active_[a] ? cell_velocity_[a].data() : nullptr; };
  const Scalar *u0 = comp(0), *u1 = comp(1), *u2 = comp(2);
  const bool three_d = s.dim == 3;
  // omega = curl u; in 2D only the component along the inactive axis 0 exists.
  for_each_row(C, 6, [&](Index i, Index j, Index c0, Scalar* d) {
    Scalar *d0 = d, *d1 = d + nk, *d2 = d + 2 * nk, *d3 = d + 3 * nk, *d4 = d + 4 * nk, *d5 = d + 5 * nk;
    diff_row(u2, i, j, c0, 1, d0);
    diff_row(u1, i, j, c0, 2, d1);
    if (three_d) {
      diff_row(u0, i, j, c0, 2, d2);
      diff_row(u2, i, j, c0, 0, d3);
      diff_row(u1, i, j, c0, 0, d4);
      diff_row(u0, i, j, c0, 1, d5);
    }
    Scalar *v0 = vorticity_[0].data() + c0, *norm = vorticity_norm_.data() + c0;
    if (!three_d) {
      for (Index k = 0; k < nk; ++k) {
        const Scalar w0 = d0[k] - d1[k];
        v0[k] = w0;
        norm[k] = std::sqrt(w0 * w0);
      }
      return;
    }
    Scalar *v1 = vorticity_[1].data() + c0, *v2 = vorticity_[2].data() + c0;
    for (Index k = 0; k < nk; ++k) {
      const Scalar w0 = d0[k] - d1[k], w1 = d2[k] - d3[k], w2 = d4[k] - d5[k];
      v0[k] = w0;
      v1[k] = w1;
      v2[k] = w2;
      norm[k] = std::sqrt(w0 * w0 + (w1 * w1 + w2 * w2));
    }
  });
  // f = eps h (N x omega), N = grad|omega| / |grad|omega||, plus buoyancy (-alpha rho + beta T) up.
  const Scalar eps = config_.vorticity_confinement;
  const Scalar* wn = vorticity_norm_.data();
  const bool rho = buoyant && !state.density.empty() && config_.alpha != 0;
  const bool temp = buoyant && !state.temperature.empty() && config_.beta != 0;
  const Scalar* density = state.density.data();
  const Scalar* temperature = state.temperature.data();
  const Scalar alpha = config_.alpha, beta = config_.beta;
  const Vec3 up = config_.up;
  for_each_row(C, 3, [&](Index i, Index j, Index c0, Scalar* grad) {
    diff_row(wn, i, j, c0, 0, grad);
    diff_row(wn, i, j, c0, 1, grad + nk);
    diff_row(wn, i, j, c0, 2, grad + 2 * nk);
    for (Index k = 0; k < nk; ++k) {
      const Index c = c0 + k;
      const Scalar b = (rho ? -alpha * density[c] : 0) + (temp ? beta * temperature[c] : 0);
      Vec3 N{grad[k], grad[nk + k], grad[2 * nk + k]};
      const Scalar len = std::sqrt(N[0] * N[0] + N[1] * N[1] + N[2] * N[2]);
      Vec3 w{vorticity_[0][c], three_d ? vorticity_[1][c] : 0, three_d ? vorticity_[2][c] : 0};
      Vec3 f{0, 0, 0};
      if (len > 1e-12 * (wn[c] + 1e-300) / h && fluid_cell(c)) {
        for (Scalar& x : N) x /= len;
        f = Vec3{N[1] * w[2] - N[2] * w[1], N[2] * w[0] - N[0] * w[2], N[0] * w[1] - N[1] * w[0]};
      }
      for (int a = 0; a < 3; ++a)
        if (active_[a]) force_[a][c] = eps * h * f[a] + up[a] * b;
    }
  });
}

// ------------------------------------------------------------------------------ viscosity

// y = (I + c L) x on the free faces of component `axis`, L = -h^2 lap with the wall ghosts of
// Bridson Sec. 10.1 (no slip: ghost = 2 U_wall - u; free slip: ghost = u); prescribed faces
// are identity rows. The operator is symmetric positive definite for any c >= 0.
void Solver::apply_viscosity_operator(int axis, Scalar c, const Scalar* x, Scalar* y) const {
  const FieldLayout& L = faces_[axis];
  const std::vector<std::uint8_t>& fixed = fixed_[axis];
  // Neighbours by stride, as neighbour() finds them: across a periodic seam node idx -+ 1 wraps
  // by the period (a face axis's duplicate node is never a neighbour), else it must exist.
  Index stride[3], count[3], period[3];
  for (int b = 0; b < 3; ++b) stride[b] = L.stride(b), count[b] = L.n[b], period[b] = L.period[b];
  for_each_node(L, [&](Index i, Index j, Index k, Index f) {
    if (fixed[f]) {
      y[f] = x[f];
      return;
    }
    const Index idx[3] = {i, j, k};
    Scalar diag = 1, off = 0;
    for (int b = 0; b < 3; ++b) {
      if (!active_[b]) continue;
      for (int side = 0; side < 2; ++side) {
        Index m = idx[b] + (side ? 1 : -1);
        if (period[b] > 0) {
          m = m < 0 ? m + period[b] : (m >= period[b] ? m - period[b] : m);
        } else if (m < 0 || m >= count[b]) {
          if (walls_.no_slip[2 * b + side]) diag += 2 * c;  // no slip or moving; not open
          continue;
        }
        const Index g = f + (m - idx[b]) * stride[b];
        diag += c;
        if (!fixed[g]) off += x[g];
      }
    }
    y[f] = diag * x[f] - c * off;
  });
}

Index Solver::diffuse(State& state, Scalar dt, Interrupt& interrupt) {
  if (config_.viscosity == 0) return 0;
  const Scalar c = config_.viscosity * dt / (model_.h * model_.h);
  Index iterations = 0;
  for (int a = 0; a < 3; ++a) {
    if (!active_[a]) continue;
    const FieldLayout& L = faces_[a];
    const std::vector<std::uint8_t>& fixed = fixed_[a];
    Scalar* u = state.velocity[a].data();
    Scalar* b = rhs_face_.data();
    // Right-hand side: u* plus the known neighbours (prescribed faces, moving walls).
    for_each_node(L, [&](Index i, Index j, Index k, Index f) {
      b[f] = u[f];
      if (fixed[f]) return;
      const std::array<Index, 3> idx{i, j, k};
      for (int bx = 0; bx < 3; ++bx) {
        if (!active_[bx]) continue;
        for (int side = 0; side < 2; ++side) {
          const Index g = neighbour(L, idx, bx, side ? 1 : -1);
          const int wall = 2 * bx + side;
          if (g >= 0) {
            if (fixed[g]) b[f] += c * u[g];
          } else if (walls_.no_slip[wall]) {
            b[f] += 2 * c * model_.wall_velocity[wall][a];
          }
        }
      }
    });
    Scalar* x = solution_face_.data();
    std::memcpy(x, u, sizeof(Scalar) * L.size());
    IterativeOptions options{config_.tol * 1e-2, config_.max_iter};
    const SolveInfo info = pcg(
        L.size(), [&](const Scalar* in, Scalar* out) { apply_viscosity_operator(a, c, in, out); },
        {}, b, x, options, interrupt, {}, &viscosity_cg_);
    if (!info.converged)
      throw ConvergenceError("viscosity: CG did not reach tol for component " +
                             component_name(model_.shape.dim, a) + " at step " +
                             std::to_string(state.steps + 1));
    iterations += info.iterations;
    std::memcpy(u, x, sizeof(Scalar) * L.size());
  }
  enforce_boundary(state);
  return iterations;
}

// ----------------------------------------------------------------------------- projection

void Solver::divergence(const State& state, Scalar* out, Scalar scale) const {
  const Scalar inv_h = 1 / model_.h;
  for_each_node(cells_, [&](Index i, Index j, Index k, Index c) {
    if (!fluid_cell(c)) {
      out[c] = 0;
      return;
    }
    Scalar d = 0;
    for (int a = 0; a < 3; ++a) {
      if (!active_[a]) continue;
      const FieldLayout& F = faces_[a];
      const Index f = F.index(i, j, k);
      d += state.velocity[a][f + F.stride(a)] - state.velocity[a][f];
    }
    out[c] = d * inv_h * scale;
  });
}

SolveInfo Solver::project(State& state, Scalar dt, Interrupt& interrupt) {
  const Index n = cells_.size();
  Scalar* b = rhs_.data();
  divergence(state, b, -1 / dt);
  Scalar* p = state.pressure.data();
  const bool fixed = config_.pressure_vcycles > 0;
  IterativeOptions options =
      fixed ? IterativeOptions{0, config_.pressure_vcycles} : IterativeOptions{config_.tol, config_.max_iter};
  SolveInfo info;
  // Warm start from the last pressure only when it beats zero: when the flow nearly stops,
  // b shrinks by orders of magnitude and the rounding error of A p_old alone would exceed
  // tol ||b||, which no iteration can reach.
  // Fixed V-cycles always start from zero, so the map b -> p is linear (and symmetric).
  bool zero = fixed;
  if (!fixed) {
    Scalar* r = residual_.data();
    pressure_solver_->op().residual(b, p, r);
    const Scalar r_norm2 = parallel_sum(n, [&](Index c) { return r[c] * r[c]; });
    const Scalar b_norm2 = parallel_sum(n, [&](Index c) { return b[c] * b[c]; });
    zero = !(r_norm2 < b_norm2);
  }
  if (zero) parallel_for(n, [&](Index c) { p[c] = 0; });
  try {
    info = pressure_solver_->solve(b, p, options, interrupt);
  } catch (const DivergenceError& e) {
    throw DivergenceError(std::string("pressure: ") + e.what() + " at step " + std::to_string(state.steps + 1));
  } catch (const InvalidArgument& e) {
    // CG broke down on rounding (p^T A p <= 0 on a semi-definite operator)
    throw ConvergenceError(std::string("pressure: ") + e.what() + " at step " + std::to_string(state.steps + 1) +
                           "; hint: a larger tol");
  }
  if (!info.converged && !fixed)
    throw ConvergenceError("pressure: the projection did not reach tol=" + std::to_string(config_.tol) +
                           " (relative residual " + std::to_string(info.residual) + " after " +
                           std::to_string(info.iterations) + " iterations) at step " +
                           std::to_string(state.steps + 1));
  // u -= dt grad p on every free face.
  const Scalar scale = dt / model_.h;
  const bool periodic = config_.periodic;
  for (int a = 0; a < 3; ++a) {
    if (!active_[a]) continue;
    const FieldLayout& F = faces_[a];
    Scalar* u = state.velocity[a].data();
    const std::vector<std::uint8_t>& fixed = fixed_[a];
    const Index n_axis = model_.shape.n[a], stride = cells_.stride(a);
    for_each_node(F, [&](Index i, Index j, Index k, Index f) {
      if (fixed[f]) return;
      const Index ia = a == 0 ? i : a == 1 ? j : k;
      if (!periodic && (ia == 0 || ia == n_axis)) {
        // a face of an open side, p = 0 on it: the ghost cell beyond holds -p
        std::array<Index, 3> c{i, j, k};
        if (ia == n_axis) --c[a];
        const Scalar pc = p[cells_.index(c[0], c[1], c[2])];
        u[f] -= scale * (ia == 0 ? 2 * pc : -2 * pc);
        return;
      }
      const Index hi = cells_.index(i, j, k);
      const Index lo = ia == 0 ? hi + (n_axis - 1) * stride : hi - stride;
      u[f] -= scale * (p[hi] - p[lo]);
    });
  }
  enforce_boundary(state);
  return info;
}

// ------------------------------------------------------------------------- bookkeeping

void Solver::enforce_boundary(State& state) const {
  for (int a = 0; a < 3; ++a) {
    if (!active_[a]) continue;
    Scalar* u = state.velocity[a].data();
    const Index back = model_.shape.n[a] * faces_[a].stride(a);  // from the duplicate to face 0
    const Index* pinned = pinned_faces_[a].data();
    const Index* duplicate = duplicate_faces_[a].data();
    parallel_for(static_cast<Index>(pinned_faces_[a].size()), [&](Index e) { u[pinned[e]] = 0; });
    parallel_for(static_cast<Index>(duplicate_faces_[a].size()), [&](Index e) {
      u[duplicate[e]] = u[duplicate[e] - back];
    });
  }
}

void Solver::check(const State& state, Scalar dt, Index step) const {
  for (int a = 0; a < 3; ++a) {
    if (!active_[a]) continue;
    const Scalar m = max_abs(state.velocity[a]);
    if (!std::isfinite(m))
      throw DivergenceError("velocity " + component_name(model_.shape.dim, a) +
                            ": non-finite value at step " + std::to_string(step) +
                            " (t = " + std::to_string(state.time) + " s, dt = " + std::to_string(dt) +
                            " s); hint: check the forces and inputs, or use a smaller dt");
  }
  const std::pair<const char*, const std::vector<Scalar>*> scalars[] = {
      {"density", &state.density}, {"temperature", &state.temperature}, {"pressure", &state.pressure}};
  for (const auto& [name, q] : scalars)
    if (!q->empty() && !std::isfinite(max_abs(*q)))
      throw DivergenceError(std::string(name) + ": non-finite value at step " + std::to_string(step) +
                            " (t = " + std::to_string(state.time) + " s); hint: use a smaller dt");
}

Scalar Solver::max_speed(const State& state) const {
  Scalar m = 0;
  for (int a = 0; a < 3; ++a)
    if (active_[a]) m = std::max(m, max_abs(state.velocity[a]));
  return m;
}

Vec3 Solver::velocity_at(const State& state, const Vec3& x) const {
  const Scalar inv_h = 1 / model_.h;
  return mac_velocity(state.velocity).at(Vec3{active_[0] ? x[0] * inv_h : 0.5, x[1] * inv_h, x[2] * inv_h});
}

Scalar Solver::kinetic_energy(const State& state) const {
  // Trapezoid rule per component: closed-wall faces carry half weight, a periodic duplicate none.
  Scalar e = 0;
  for (int a = 0; a < 3; ++a) {
    if (!active_[a]) continue;
    const FieldLayout& F = faces_[a];
    const Scalar* u = state.velocity[a].data();
    const Index n_axis = model_.shape.n[a], stride = F.stride(a);
    e += parallel_sum(F.size(), [&](Index f) {
      const Index ia = (f / stride) % (n_axis + 1);
      Scalar w = 1;
      if (ia == n_axis) w = config_.periodic ? 0 : 0.5;
      else if (ia == 0 && !config_.periodic) w = 0.5;
      return w * u[f] * u[f];
    });
  }
  return 0.5 * e * std::pow(model_.h, model_.shape.dim);
}

}  // namespace kinema::grid
