// kinema._core.mpm: the material point method behind km.mpm.Simulation.
// State arrays are zero-copy views whose owner is the C++ State itself (held by a shared
// pointer in the view's capsule): adding particles builds a new State, so a view taken before
// add_particles stays valid memory but is detached from the simulation.
//
// Views show the rows in user order (the order particles were added). While no view is alive
// and none was taken for a while, the solver may store the rows in grid-block order
// (mpm::Solver::sort_rows; the transfers then read memory sequentially): all views share one
// capsule, whose reference count says whether any view (or a slice of one) is alive, and
// taking a view, or any call that reads the particles, first puts the rows back in user order.
// Likewise the solver keeps a step's binning of the particles for the next step only while no
// view can have written them (mpm::State::binning is cleared when a view is taken, and after a
// step during which one was alive). Results are bitwise the same either way (solver.h).
#include <memory>
#include <optional>

#include "bindings/common.h"
#include "core/advance.h"
#include "core/errors.h"
#include "mpm/kernels.h"
#include "mpm/solver.h"

namespace kinema::bind {

namespace {

// A State from a dict of km.mpm.Simulation.state() (a copy; shapes checked against n, d).
mpm::State state_from(const py::dict& dict, int d, const char* which) {
  mpm::State state(d);
  auto array = [&](const char* key) {
    if (!dict.contains(key)) throw InvalidArgument(std::string(which) + ": missing '" + key + "'");
    return py::array_t<Scalar, py::array::c_style | py::array::forcecast>::ensure(dict[key]);
  };
  auto copy = [&](const char* key, std::vector<Scalar>& out, Index per_particle) {
    auto a = array(key);
    if (!a || a.size() != state.n * per_particle)
      throw InvalidArgument(std::string(which) + "['" + key + "']: expected " + std::to_string(state.n * per_particle) +
                            " values for " + std::to_string(state.n) + " particles");
    out.assign(a.data(), a.data() + a.size());
  };
  auto x = array("x");
  if (!x || x.ndim() != 2 || x.shape(1) != d)
    throw InvalidArgument(std::string(which) + "['x']: expected shape (n, " + std::to_string(d) + ")");
  state.n = x.shape(0);
  copy("x", state.x, d);
  copy("v", state.v, d);
  copy("F", state.F, d * d);
  copy("C", state.C, d * d);
  copy("mass", state.mass, 1);
  copy("volume", state.volume, 1);
  copy("Jp", state.Jp, 1);
  copy("youngs_modulus", state.youngs_modulus, 1);
  copy("poisson_ratio", state.poisson_ratio, 1);
  if (!dict.contains("material")) throw InvalidArgument(std::string(which) + ": missing 'material'");
  auto codes = py::array_t<Index, py::array::c_style | py::array::forcecast>::ensure(dict["material"]);
  if (!codes || codes.size() != state.n)
    throw InvalidArgument(std::string(which) + "['material']: expected " + std::to_string(state.n) + " codes");
  state.material.assign(codes.data(), codes.data() + codes.size());
  return state;
}

struct PySimulation {
  PySimulation(std::vector<Index> shape, Scalar h, const mpm::Config& config_, mpm::Boundary boundary,
               std::vector<Scalar> origin, Scalar friction)
      : config(config_) {
    model = mpm::make_model(static_cast<int>(shape.size()), shape, h, origin, boundary, friction);
    state = std::make_shared<mpm::State>(model.dim);
    solver = std::make_unique<mpm::Solver>(model, config);
  }

  int dim() const { return model.dim; }

  py::tuple add_particles(py::array positions, mpm::MaterialKind kind, Scalar density, Scalar youngs_modulus,
                          Scalar poisson_ratio, py::array velocity, py::array volume, Scalar friction_angle,
                          Scalar cohesion, const std::string& friction_law, Scalar mu_s, Scalar mu_2, Scalar I0,
                          Scalar grain_diameter, Scalar grain_density) {
    const int d = model.dim;
    if (positions.ndim() != 2 || positions.shape(1) != d)
      throw InvalidArgument("positions: expected shape (n, " + std::to_string(d) + ")");
    const Index m = positions.shape(0);
    const Scalar* x = checked_data(positions, "positions", m * d, false);
    const Scalar* v = checked_data(velocity, "velocity", m * d, false);
    const Scalar* vol = checked_data(volume, "volume", m, false);
    for (Index p = 0; p < m; ++p) {
      for (int a = 0; a < d; ++a) {
        const Scalar xa = x[p * d + a];
        if (!(xa >= model.origin[a] && xa <= model.upper(a)))
          throw InvalidArgument("positions: particle " + std::to_string(p) + " lies outside the domain [" +
                                format_real(model.origin[a]) + ", " + format_real(model.upper(a)) +
                                "] on axis " + std::to_string(a) + " (x = " + format_real(xa) + ")");
        if (!std::isfinite(v[p * d + a])) throw InvalidArgument("velocity: contains non-finite values");
      }
      if (!(std::isfinite(vol[p]) && vol[p] > 0)) throw InvalidArgument("volume: expected finite values > 0");
    }
    mpm::Material mat = mpm::make_material(d, kind, density, youngs_modulus, poisson_ratio, friction_angle, cohesion);
    if (friction_law == "mu_i")
      mpm::use_mu_i(mat, d, mu_s, mu_2, I0, grain_diameter, grain_density);
    else if (friction_law != "constant")
      throw InvalidArgument("friction_law: expected 'constant' or 'mu_i', got '" + friction_law + "'");
    std::vector<Scalar> mass(vol, vol + m);
    for (Scalar& w : mass) w *= density;
    user_order();
    // A new State (old views keep the old one alive) and a new solver for the new material table.
    auto next = std::make_shared<mpm::State>(*state);
    mpm::Model next_model = model;
    next_model.materials.push_back(mat);
    next->append(x, v, m, mass.data(), vol, static_cast<Index>(next_model.materials.size() - 1), mat.youngs_modulus,
                 mat.poisson_ratio);
    solver = std::make_unique<mpm::Solver>(next_model, config);
    model = std::move(next_model);
    const Index start = state->n;
    state = std::move(next);
    owner = py::object();  // views of the old State keep it
    return py::make_tuple(start, state->n);
  }

  void add_collider(const std::string& shape, std::vector<Scalar> lower, std::vector<Scalar> upper,
                    std::vector<Scalar> center, Scalar radius, mpm::Boundary boundary, Scalar friction) {
    mpm::Collider c;
    const size_t d = static_cast<size_t>(model.dim);
    if (shape == "box") {
      c.shape = mpm::Collider::Shape::Box;
      if (lower.size() != d || upper.size() != d)
        throw InvalidArgument("region: a box needs 'lower' and 'upper' with " + std::to_string(d) + " coordinates");
      std::copy(lower.begin(), lower.end(), c.lower.begin());
      std::copy(upper.begin(), upper.end(), c.upper.begin());
    } else if (shape == "sphere") {
      c.shape = mpm::Collider::Shape::Sphere;
      if (center.size() != d)
        throw InvalidArgument("region: a sphere needs a 'center' with " + std::to_string(d) + " coordinates");
      std::copy(center.begin(), center.end(), c.center.begin());
      c.radius = radius;
    } else {
      throw InvalidArgument("region: 'shape' must be 'box' or 'sphere', got '" + shape + "'");
    }
    c.boundary = boundary;
    c.friction = friction;
    mpm::Model next = model;
    mpm::add_collider(next, c);
    solver = std::make_unique<mpm::Solver>(next, config);
    model = std::move(next);
  }

  // (n, d) forces [N] or None.
  const Scalar* forces_of(py::object forces) const {
    if (forces.is_none()) return nullptr;
    py::array a = forces.cast<py::array>();
    if (a.ndim() != 2 || a.shape(0) != state->n || a.shape(1) != model.dim)
      throw InvalidArgument("control: expected forces of shape (" + std::to_string(state->n) + ", " +
                            std::to_string(model.dim) + ") [N]");
    return checked_data(a, "control", state->n * model.dim, false);
  }

  mpm::StepStats step(Scalar dt, py::object forces) {
    const Scalar* f = forces_of(forces);
    const bool may_sort = !views_alive();
    mpm::StepStats stats;
    {
      Interrupt interrupt = python_interrupt();
      ReleaseGil release;
      stats = solver->step(*state, dt, interrupt, f);  // transactional by itself (solver.h)
      after_step(may_sort);
    }
    drop_binning_if_viewed();
    return stats;
  }

  // Rows are sorted into block order once kQuietSteps steps have passed with no view alive and
  // no particle read, then every kResortSteps steps (particles move under a cell per step, so
  // the order decays slowly; a sort costs about a third of a 2D step of 8,192 particles). A
  // caller that reads the particles after every step never pays for a sort it cannot use.
  static constexpr Index kQuietSteps = 8, kResortSteps = 32;
  void after_step(bool may_sort) {
    if (!may_sort) {
      quiet_steps = 0;
      state->binning = 0;  // a view alive during the step may have been written
      return;
    }
    ++quiet_steps;
    if (quiet_steps >= kQuietSteps && (quiet_steps - kQuietSteps) % kResortSteps == 0) solver->sort_rows(*state);
  }

  bool views_alive() const { return owner && owner.ref_count() > 1; }

  // The solver keeps a step's binning for the next only while nothing can have written the
  // particles (mpm::State::binning): not across a view alive after the step.
  void drop_binning_if_viewed() {
    if (views_alive()) state->binning = 0;
  }

  // Before anything reads or writes the particles from Python: rows back in user order (and the
  // binning kept for the next step dropped).
  void user_order() {
    quiet_steps = 0;
    state->binning = 0;
    if (state->user_ordered()) return;
    ReleaseGil release;
    solver->user_order(*state);
  }

  // Steps of stable_dt(cfl) until `duration` has passed (core/advance.h); returns the step
  // count and the last step's statistics with the stage and wall seconds summed over all.
  py::tuple advance(Scalar duration, Scalar cfl) {
    if (!(std::isfinite(cfl) && cfl > 0)) throw InvalidArgument("cfl: expected a number > 0, got " + format_real(cfl));
    mpm::StepStats last, sum;
    AdvanceResult result;
    const bool may_sort = !views_alive();
    {
      Interrupt interrupt = python_interrupt();
      ReleaseGil release;
      result = advance_to(
          *state, duration, [&](const mpm::State& s) { return solver->stable_dt(s, cfl); },
          [&](mpm::State& s, Scalar dt) {
            mpm::StepStats stats = solver->step(s, dt, interrupt);
            after_step(may_sort);
            return stats;
          },
          [&](const mpm::StepStats& stats) {
            last = stats;
            sum.sort_seconds += stats.sort_seconds;
            sum.p2g_seconds += stats.p2g_seconds;
            sum.grid_seconds += stats.grid_seconds;
            sum.g2p_seconds += stats.g2p_seconds;
            sum.seconds += stats.seconds;
          },
          interrupt);
    }
    drop_binning_if_viewed();
    last.time = state->time;
    last.sort_seconds = sum.sort_seconds;
    last.p2g_seconds = sum.p2g_seconds;
    last.grid_seconds = sum.grid_seconds;
    last.g2p_seconds = sum.g2p_seconds;
    last.seconds = sum.seconds;
    return py::make_tuple(result.steps, last);
  }

  // The vector-Jacobian product of one step (Solver::step_adjoint): `before`/`after` are state()
  // dicts around step(dt, forces); `grads` maps x, v, F, C to dL/d(after). Returns
  // (dL/d(before) as a dict of x, v, F, C; dL/dE (n,); dL/dnu (n,); dL/dforces (n, d) or None).
  py::tuple step_adjoint(Scalar dt, const py::dict& before_dict, const py::dict& after_dict, py::object forces,
                         const py::dict& grads) {
    const int d = model.dim;
    const mpm::State before = state_from(before_dict, d, "before");
    const mpm::State after = state_from(after_dict, d, "after");
    if (after.n != before.n) throw InvalidArgument("after: particle count differs from before's");
    const Index n = before.n;
    const Scalar* f = nullptr;
    if (!forces.is_none()) {
      py::array a = forces.cast<py::array>();
      if (a.ndim() != 2 || a.shape(0) != n || a.shape(1) != d)
        throw InvalidArgument("control: expected forces of shape (" + std::to_string(n) + ", " + std::to_string(d) + ")");
      f = checked_data(a, "control", n * d, false);
    }
    mpm::State adjoint(d);
    adjoint.n = n;
    const std::pair<const char*, std::vector<Scalar>*> fields[] = {
        {"x", &adjoint.x}, {"v", &adjoint.v}, {"F", &adjoint.F}, {"C", &adjoint.C}};
    for (const auto& [key, out] : fields) {
      const Index size = n * d * (key[0] == 'F' || key[0] == 'C' ? d : 1);
      if (!grads.contains(key)) {
        out->assign(static_cast<size_t>(size), 0.0);
        continue;
      }
      auto a = py::array_t<Scalar, py::array::c_style | py::array::forcecast>::ensure(grads[key]);
      if (!a || a.size() != size)
        throw InvalidArgument(std::string("grads['") + key + "']: expected " + std::to_string(size) + " values");
      out->assign(a.data(), a.data() + size);
    }
    mpm::ParamsAdjoint params;
    std::vector<Scalar> forces_bar(f ? static_cast<size_t>(n * d) : 0);
    {
      Interrupt interrupt = python_interrupt();
      ReleaseGil release;
      solver->step_adjoint(before, after, dt, f, adjoint, params, f ? forces_bar.data() : nullptr, interrupt);
    }
    py::dict out;
    out["x"] = to_numpy(std::move(adjoint.x), {n, d});
    out["v"] = to_numpy(std::move(adjoint.v), {n, d});
    out["F"] = to_numpy(std::move(adjoint.F), {n, d, d});
    out["C"] = to_numpy(std::move(adjoint.C), {n, d, d});
    py::object fb = py::none();
    if (f) fb = to_numpy(std::move(forces_bar), {n, d});
    return py::make_tuple(out, to_numpy(std::move(params.youngs_modulus), {n}),
                          to_numpy(std::move(params.poisson_ratio), {n}), fb);
  }

  // A writable view of one State buffer (rows in user order), owned by the State through the
  // capsule all views share.
  template <class T>
  py::array view(std::vector<T>& buffer, std::vector<py::ssize_t> shape) {
    user_order();
    if (!owner) {
      auto* held = new std::shared_ptr<mpm::State>(state);
      owner = py::capsule(held, [](void* p) { delete static_cast<std::shared_ptr<mpm::State>*>(p); });
    }
    return py::array_t<T>(shape, buffer.data(), owner);
  }

  mpm::Model model;
  mpm::Config config;
  std::shared_ptr<mpm::State> state;
  std::unique_ptr<mpm::Solver> solver;
  py::object owner;       // the capsule of every view of `state` (null until one is taken)
  Index quiet_steps = 0;  // steps since a view was alive or the particles were read
};

}  // namespace

void bind_mpm(py::module_& m) {
  py::enum_<mpm::Boundary>(m, "Boundary", "Velocity condition at a wall or collider.")
      .value("sticky", mpm::Boundary::Sticky)
      .value("slip", mpm::Boundary::Slip)
      .value("separate", mpm::Boundary::Separate);
  py::enum_<mpm::MaterialKind>(m, "MaterialKind")
      .value("elastic", mpm::MaterialKind::Elastic)
      .value("neohookean", mpm::MaterialKind::NeoHookean)
      .value("snow", mpm::MaterialKind::Snow)
      .value("sand", mpm::MaterialKind::Sand)
      .value("water", mpm::MaterialKind::Water);

  py::class_<mpm::Config>(m, "Config", "How the MPM solver steps (cpp/mpm/config.h).")
      .def(py::init<>())
      .def_readwrite("gravity", &mpm::Config::gravity, "[m/s^2], 3 entries, the first d used")
      .def_readwrite("max_cells_per_step", &mpm::Config::max_cells_per_step,
                     "cells a particle may cross in one step before DivergenceError")
      .def_readwrite("max_dt", &mpm::Config::max_dt, "largest step stable_dt returns [s]")
      .def_readwrite("adapt_threads", &mpm::Config::adapt_threads,
                     "small steps may run on one thread when it measures clearly faster than the team");

  py::class_<mpm::StepStats, StepStatsBase>(m, "StepStats", "Statistics of one MPM step.")
      .def_readonly("max_speed", &mpm::StepStats::max_speed, "largest particle speed after the step [m/s]")
      .def_readonly("particle_blocks", &mpm::StepStats::particle_blocks, "grid blocks holding particles")
      .def_readonly("active_blocks", &mpm::StepStats::active_blocks, "blocks the transfers touch")
      .def_readonly("rebinned", &mpm::StepStats::rebinned,
                    "particles binned anew: all after a full sort, else those that left their block")
      .def_readonly("sort_seconds", &mpm::StepStats::sort_seconds, "binning and block activation [s]")
      .def_readonly("p2g_seconds", &mpm::StepStats::p2g_seconds, "stress and particle-to-grid transfer [s]")
      .def_readonly("grid_seconds", &mpm::StepStats::grid_seconds, "grid update and boundary conditions [s]")
      .def_readonly("g2p_seconds", &mpm::StepStats::g2p_seconds, "grid-to-particle transfer and plasticity [s]")
      .def_readonly("threads", &mpm::StepStats::threads, "threads the step ran on")
      .def("__repr__", [](const mpm::StepStats& s) {
        return "kinema.mpm.StepStats(time=" + format_real(s.time) + ", dt=" + format_real(s.dt) +
               ", max_speed=" + format_real(s.max_speed) + ", seconds=" + format_real(s.seconds) + ")";
      });

  py::class_<mpm::Material>(m, "Material", "One entry of the material table (model.h).")
      .def_property_readonly("kind", [](const mpm::Material& mat) { return std::string(mpm::material_name(mat.kind)); })
      .def_readonly("density", &mpm::Material::density, "[kg/m^d]")
      .def_readonly("youngs_modulus", &mpm::Material::youngs_modulus, "[Pa] (water: bulk modulus)")
      .def_readonly("poisson_ratio", &mpm::Material::poisson_ratio)
      .def_readonly("mu", &mpm::Material::mu, "[Pa]")
      .def_readonly("lambda_", &mpm::Material::lambda, "[Pa]")
      .def_readonly("friction_angle", &mpm::Material::friction_angle, "[deg]")
      .def_readonly("cohesion", &mpm::Material::cohesion, "[Pa]")
      .def_property_readonly("friction_law", [](const mpm::Material& mat) {
        return std::string(mat.friction_law == mpm::Material::FrictionLaw::MuI ? "mu_i" : "constant");
      })
      .def_readonly("mu_s", &mpm::Material::mu_s, "static friction coefficient of mu(I) [-]")
      .def_readonly("mu_2", &mpm::Material::mu_2, "limiting friction coefficient of mu(I) [-]")
      .def_readonly("I0", &mpm::Material::inertial_number0, "inertial number scale of mu(I) [-]")
      .def_readonly("grain_diameter", &mpm::Material::grain_diameter, "[m]")
      .def_readonly("grain_density", &mpm::Material::grain_density, "[kg/m^d]")
      .def_readonly("wave_speed", &mpm::Material::wave_speed, "fastest elastic wave at rest [m/s]");

  py::class_<PySimulation>(m, "Simulation")
      .def(py::init<std::vector<Index>, Scalar, const mpm::Config&, mpm::Boundary, std::vector<Scalar>, Scalar>(),
           py::arg("shape"), py::arg("h"), py::arg("config"), py::arg("boundary"), py::arg("origin"),
           py::arg("friction"))
      .def("add_particles", &PySimulation::add_particles, py::arg("positions"), py::arg("material"),
           py::arg("density"), py::arg("youngs_modulus"), py::arg("poisson_ratio"), py::arg("velocity"),
           py::arg("volume"), py::arg("friction_angle"), py::arg("cohesion"), py::arg("friction_law") = "constant",
           py::arg("mu_s") = 0.0, py::arg("mu_2") = 0.0, py::arg("I0") = 0.0, py::arg("grain_diameter") = 0.0,
           py::arg("grain_density") = 0.0)
      .def("add_collider", &PySimulation::add_collider, py::arg("shape"), py::arg("lower"), py::arg("upper"),
           py::arg("center"), py::arg("radius"), py::arg("boundary"), py::arg("friction"))
      .def("step", &PySimulation::step, py::arg("dt"), py::arg("forces") = py::none())
      .def("step_adjoint", &PySimulation::step_adjoint, py::arg("dt"), py::arg("before"), py::arg("after"),
           py::arg("forces"), py::arg("grads"))
      .def("advance", &PySimulation::advance, py::arg("duration"), py::arg("cfl"))
      .def("stable_dt", [](const PySimulation& s, Scalar cfl) { return s.solver->stable_dt(*s.state, cfl); },
           py::arg("cfl"))
      .def("cfl_dt", [](const PySimulation& s) { return s.solver->cfl_dt(*s.state); })
      .def_property_readonly("speed_measured", [](const PySimulation& s) { return s.solver->speed_measured(*s.state); },
                             "whether cfl_dt and stable_dt read the last step's measurement (no pass over the particles)")
      .def("kinetic_energy", [](const PySimulation& s) { return s.solver->kinetic_energy(*s.state); })
      .def("momentum", [](const PySimulation& s) { return s.solver->momentum(*s.state); })
      .def("angular_momentum", [](const PySimulation& s) { return s.solver->angular_momentum(*s.state); })
      .def_property_readonly("config", [](const PySimulation& s) { return s.config; })
      .def_property_readonly("dim", &PySimulation::dim)
      .def_property_readonly("count", [](const PySimulation& s) { return s.state->n; })
      .def_property_readonly("rows_in_block_order", [](const PySimulation& s) { return !s.state->user_ordered(); },
                             "whether the rows are stored sorted into grid blocks (views show user order either way)")
      .def_property_readonly("x", [](PySimulation& s) { return s.view(s.state->x, {s.state->n, s.dim()}); })
      .def_property_readonly("v", [](PySimulation& s) { return s.view(s.state->v, {s.state->n, s.dim()}); })
      .def_property_readonly("F", [](PySimulation& s) {
        return s.view(s.state->F, {s.state->n, s.dim(), s.dim()});
      })
      .def_property_readonly("C", [](PySimulation& s) {
        return s.view(s.state->C, {s.state->n, s.dim(), s.dim()});
      })
      .def_property_readonly("mass", [](PySimulation& s) { return s.view(s.state->mass, {s.state->n}); })
      .def_property_readonly("volume", [](PySimulation& s) { return s.view(s.state->volume, {s.state->n}); })
      .def_property_readonly("material", [](PySimulation& s) { return s.view(s.state->material, {s.state->n}); })
      .def_property_readonly("Jp", [](PySimulation& s) { return s.view(s.state->Jp, {s.state->n}); })
      .def_property_readonly("youngs_modulus",
                             [](PySimulation& s) { return s.view(s.state->youngs_modulus, {s.state->n}); })
      .def_property_readonly("poisson_ratio",
                             [](PySimulation& s) { return s.view(s.state->poisson_ratio, {s.state->n}); })
      .def_property("time", [](const PySimulation& s) { return s.state->time; },
                    [](PySimulation& s, Scalar t) { s.state->time = t; })
      .def_property("steps", [](const PySimulation& s) { return s.state->steps; },
                    [](PySimulation& s, Index n) { s.state->steps = n; })
      .def_property_readonly("materials", [](const PySimulation& s) { return s.model.materials; });
}

}  // namespace kinema::bind
