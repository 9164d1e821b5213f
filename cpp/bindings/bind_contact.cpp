// kinema._core.contact: the IPC contact solver behind km.contact.Scene, plus its kernels
// (distances, barrier, CCD) for tests and benchmarks. State arrays are zero-copy views whose
// owner is the C++ State (a shared pointer in the view's capsule); adding a body builds a new
// State, so views taken before an add stay valid memory but are detached from the scene.
#include <cstdint>
#include <limits>
#include <memory>

#include "bindings/common.h"
#include "bindings/fem_material.h"
#include "contact/barrier.h"
#include "contact/solver.h"
#include "core/errors.h"
#include "core/rollback.h"

namespace kinema::bind {

namespace {

using contact::Vec3;

LinearSolver contact_linear_solver(const std::string& name) {
  if (name == "cholmod") return LinearSolver::CholmodDirect;
  if (name == "cholmod-pcg") return LinearSolver::Cholmod;
  if (name == "cg") return LinearSolver::CG;
  throw InvalidArgument("linear_solver: expected 'simplicial', 'cholmod', 'cholmod-pcg' or 'cg', got '" + name + "'");
}

contact::Projection contact_projection(const std::string& name) {
  if (name == "none") return contact::Projection::None;
  if (name == "clamp") return contact::Projection::Clamp;
  if (name == "rank-one") return contact::Projection::RankOne;
  throw InvalidArgument("projection: expected 'rank-one', 'clamp' or 'none', got '" + name + "'");
}

const char* projection_name(contact::Projection p) {
  return p == contact::Projection::None ? "none" : p == contact::Projection::Clamp ? "clamp" : "rank-one";
}

Index rows_of(const py::array& a, Index cols, const char* name) {
  if (a.ndim() != 2 || a.shape(1) != cols)
    throw InvalidArgument(std::string(name) + ": expected shape (n, " + std::to_string(cols) + "), got " +
                          std::to_string(a.ndim()) + " dimensions");
  return a.shape(0);
}

const Index* index_data(const IndexArray& a) { return a.data(); }

struct PyScene {
  explicit PyScene(const contact::Config& c) : config(c), model(std::make_shared<contact::Model>()) {
    state = std::make_shared<contact::State>(contact::make_state(*model));
  }

  // Grows the state by the vertices just added (at their given positions, at rest).
  Index grown(Index start) {
    auto next = std::make_shared<contact::State>(*state);
    next->x.insert(next->x.end(), model->rest.begin() + 3 * start, model->rest.end());
    next->v.resize(next->x.size(), 0);
    next->target.insert(next->target.end(), model->rest.begin() + 3 * start, model->rest.end());
    next->kappa = 0;
    state = std::move(next);
    solver.reset();
    return start;
  }

  Index add_solid(py::array vertices, const IndexArray& tets, const std::string& material, const ScalarArray& E,
                  const ScalarArray& nu, Scalar density, Scalar damping, const IndexArray& fixed) {
    const Index n = rows_of(vertices, 3, "vertices");
    const Index m = rows_of(tets, 4, "tets");
    const Scalar* x = checked_data(vertices, "vertices", 3 * n, false);
    if (nu.size() != E.size())
      throw InvalidArgument("poisson_ratio: expected as many values as youngs_modulus (" + std::to_string(E.size()) + ")");
    return grown(model->add_solid(x, n, index_data(tets), m, parse_material(material), E.data(), nu.data(),
                                  E.size(), density, damping, index_data(fixed), fixed.size()));
  }

  Index add_springs(py::array vertices, const IndexArray& springs, const ScalarArray& stiffness,
                    const ScalarArray& rest_length, const ScalarArray& damping, const ScalarArray& mass,
                    const IndexArray& triangles, const IndexArray& fixed) {
    const Index n = rows_of(vertices, 3, "vertices");
    const Index s = rows_of(springs, 2, "springs");
    const Index m = triangles.size() ? rows_of(triangles, 3, "triangles") : 0;
    const Scalar* x = checked_data(vertices, "vertices", 3 * n, false);
    auto per_spring = [&](const ScalarArray& a, const char* name) {
      if (a.size() != s) throw InvalidArgument(std::string(name) + ": expected " + std::to_string(s) + " values");
      return a.data();
    };
    if (mass.size() != n) throw InvalidArgument("mass: expected " + std::to_string(n) + " values");
    return grown(model->add_springs(x, n, index_data(springs), s, per_spring(stiffness, "stiffness"),
                                    per_spring(rest_length, "rest_length"), per_spring(damping, "damping"), mass.data(),
                                    index_data(triangles), m, index_data(fixed), fixed.size()));
  }

  Index add_cloth(py::array vertices, const IndexArray& triangles, const IndexArray& springs, Scalar stiffness,
                  Scalar density, const IndexArray& fixed) {
    const Index n = rows_of(vertices, 3, "vertices");
    const Index m = rows_of(triangles, 3, "triangles");
    const Index s = rows_of(springs, 2, "springs");
    const Scalar* x = checked_data(vertices, "vertices", 3 * n, false);
    return grown(model->add_cloth(x, n, index_data(triangles), m, index_data(springs), s, stiffness, density,
                                  index_data(fixed), fixed.size()));
  }

  Index add_obstacle(py::array vertices, const IndexArray& triangles, bool moving, Scalar friction) {
    const Index n = rows_of(vertices, 3, "vertices");
    const Index m = rows_of(triangles, 3, "triangles");
    const Scalar* x = checked_data(vertices, "vertices", 3 * n, false);
    return grown(model->add_obstacle(x, n, index_data(triangles), m, moving, friction));
  }

  // A moving plane's driven vertex (its point) is appended to the state; returns it, or -1.
  Index add_plane(const std::array<Scalar, 3>& point, const std::array<Scalar, 3>& normal, Scalar friction,
                  bool moving) {
    const Index vertex =
        model->add_plane(Vec3(point[0], point[1], point[2]), Vec3(normal[0], normal[1], normal[2]), friction, moving);
    if (vertex >= 0) return grown(vertex);
    state->kappa = 0;
    solver.reset();
    return -1;
  }

  contact::Solver& ready() {
    if (model->vertex_count == 0) throw InvalidArgument("scene: add a body before stepping");
    if (!solver) solver = std::make_unique<contact::Solver>(*model, config);
    return *solver;
  }

  contact::StepStats step(Scalar dt) {
    contact::Solver& s = ready();
    Interrupt interrupt = python_interrupt();
    ReleaseGil release;
    return with_rollback(*state, [&] { return s.step(*state, dt, interrupt); });
  }

  py::array_t<Scalar> view(std::vector<Scalar>& buffer) {
    auto* owner = new std::shared_ptr<contact::State>(state);
    py::capsule capsule(owner, [](void* p) { delete static_cast<std::shared_ptr<contact::State>*>(p); });
    return py::array_t<Scalar>({static_cast<py::ssize_t>(buffer.size() / 3), py::ssize_t(3)}, buffer.data(), capsule);
  }

  const Scalar* positions(py::array& x) {
    return checked_data(x, "x", 3 * model->vertex_count, false);
  }

  contact::Config config;
  std::shared_ptr<contact::Model> model;
  std::shared_ptr<contact::State> state;
  std::unique_ptr<contact::Solver> solver;
};

}  // namespace

void bind_contact(py::module_& m) {
  py::class_<contact::Config>(m, "Config")
      .def(py::init<>())
      .def_property(
          "gravity", [](const contact::Config& c) { return std::array<Scalar, 3>{c.gravity[0], c.gravity[1], c.gravity[2]}; },
          [](contact::Config& c, const std::array<Scalar, 3>& g) { c.gravity = Vec3(g[0], g[1], g[2]); })
      .def_readwrite("dhat", &contact::Config::dhat)
      .def_readwrite("reuse_pattern", &contact::Config::reuse_pattern)
      .def_readwrite("barrier_stiffness", &contact::Config::barrier_stiffness)
      .def_readwrite("friction", &contact::Config::friction)
      .def_readwrite("friction_velocity", &contact::Config::friction_velocity)
      .def_readwrite("tol", &contact::Config::tol)
      .def_readwrite("max_newton", &contact::Config::max_newton)
      .def_property(
          "barrier_projection", [](const contact::Config& c) { return projection_name(c.barrier_projection); },
          [](contact::Config& c, const std::string& s) { c.barrier_projection = contact_projection(s); })
      .def_property(
          "linear_solver",
          [](const contact::Config& c) {
            return c.linear_solver == LinearSolver::CG        ? "cg"
                   : c.linear_solver == LinearSolver::Cholmod ? "cholmod-pcg"
                   : c.simplicial                             ? "simplicial"
                                                              : "cholmod";
          },
          [](contact::Config& c, const std::string& s) {
            c.simplicial = s == "simplicial";
            c.linear_solver = contact_linear_solver(c.simplicial ? "cholmod" : s);
          });

  py::class_<contact::StepStats, StepStatsBase>(m, "StepStats")
      .def_readonly("newton_iterations", &contact::StepStats::newton_iterations)
      .def_readonly("line_search_halvings", &contact::StepStats::line_search_halvings)
      .def_readonly("contact_count", &contact::StepStats::contact_count)
      .def_readonly("min_distance", &contact::StepStats::min_distance)
      .def_readonly("sticking_count", &contact::StepStats::sticking_count)
      .def_readonly("sliding_count", &contact::StepStats::sliding_count)
      .def_readonly("min_step_fraction", &contact::StepStats::min_step_fraction)
      .def_readonly("ccd_seconds", &contact::StepStats::ccd_seconds)
      .def_readonly("ccd_share", &contact::StepStats::ccd_share)
      .def_readonly("barrier_stiffness", &contact::StepStats::barrier_stiffness)
      .def_readonly("assemble_seconds", &contact::StepStats::assemble_seconds)
      .def_readonly("solve_seconds", &contact::StepStats::solve_seconds)
      .def_readonly("line_search_seconds", &contact::StepStats::line_search_seconds)
      .def_readonly("factor_seconds", &contact::StepStats::factor_seconds)
      .def_readonly("broad_phase_seconds", &contact::StepStats::broad_phase_seconds)
      .def_readonly("broad_phases", &contact::StepStats::broad_phases)
      .def_readonly("pattern_changes", &contact::StepStats::pattern_changes)
      .def_readonly("unknowns", &contact::StepStats::unknowns)
      .def_readonly("newton_history", &contact::StepStats::newton_history)
      .def_readonly("step_history", &contact::StepStats::step_history)
      .def("__repr__", [](const contact::StepStats& s) {
        return "StepStats(time=" + format_real(s.time) + ", newton_iterations=" + std::to_string(s.newton_iterations) +
               ", contact_count=" + std::to_string(s.contact_count) + ", min_distance=" + format_real(s.min_distance) +
               ", sticking_count=" + std::to_string(s.sticking_count) + ", sliding_count=" + std::to_string(s.sliding_count) +
               ", ccd_share=" + format_real(s.ccd_share) + ")";
      });

  py::class_<PyScene>(m, "Scene")
      .def(py::init<const contact::Config&>())
      .def("add_solid", &PyScene::add_solid)
      .def("add_cloth", &PyScene::add_cloth)
      .def("add_springs", &PyScene::add_springs)
      .def("add_obstacle", &PyScene::add_obstacle, py::arg("vertices"), py::arg("triangles"), py::arg("moving"),
           py::arg("friction") = -1.0)
      .def("add_plane", &PyScene::add_plane, py::arg("point"), py::arg("normal"), py::arg("friction") = -1.0, py::arg("moving") = false)
      .def("step", &PyScene::step)
      .def_property_readonly("vertex_count", [](const PyScene& s) { return s.model->vertex_count; })
      .def_property_readonly("x", [](PyScene& s) { return s.view(s.state->x); })
      .def_property_readonly("v", [](PyScene& s) { return s.view(s.state->v); })
      .def_property_readonly("target", [](PyScene& s) { return s.view(s.state->target); })
      .def_property("time", [](const PyScene& s) { return s.state->time; },
                    [](PyScene& s, Scalar t) { s.state->time = t; })
      .def_property("kappa", [](const PyScene& s) { return s.state->kappa; },
                    [](PyScene& s, Scalar k) { s.state->kappa = k; })
      .def_property_readonly("mass", [](const PyScene& s) { return s.model->mass; })
      .def_property_readonly("fixed", [](const PyScene& s) { return std::vector<bool>(s.model->fixed.begin(), s.model->fixed.end()); })
      .def_property_readonly("faces", [](const PyScene& s) {
        return to_numpy(std::vector<Index>(s.model->faces), {static_cast<Index>(s.model->faces.size() / 3), 3});
      })
      .def_property_readonly("edges", [](const PyScene& s) {
        return to_numpy(std::vector<Index>(s.model->edges), {static_cast<Index>(s.model->edges.size() / 2), 2});
      })
      .def_property_readonly("body", [](const PyScene& s) { return s.model->body; })
      .def("check_intersection_free", [](PyScene& s, py::array x) {
        s.ready().check_intersection_free(s.positions(x), "x");
      })
      .def("min_distance", [](PyScene& s, py::array x, Scalar radius) {
        return contact::min_distance(*s.model, s.positions(x), radius);
      })
      .def("intersections", [](PyScene& s, py::array x, Index limit) {
        return contact::find_intersections(*s.model, s.positions(x), limit);
      })
      .def("constraint_count", [](PyScene& s, py::array x) {
        const Scalar* p = s.positions(x);
        contact::Solver& solver = s.ready();
        ReleaseGil release;
        return static_cast<Index>(solver.constraints(p).size());
      })
      .def("elastic_energy", [](PyScene& s, py::array x) { return s.ready().elastic_energy(s.positions(x)); })
      .def("barrier_energy", [](PyScene& s, py::array x) {
        const Scalar* p = s.positions(x);
        contact::Solver& solver = s.ready();
        ReleaseGil release;
        return solver.barrier_energy(p);
      })
      .def("barrier_gradient", [](PyScene& s, py::array x) {
        const Scalar* p = s.positions(x);
        contact::Solver& solver = s.ready();
        std::vector<Scalar> g(static_cast<size_t>(3 * s.model->vertex_count));
        {
          ReleaseGil release;
          solver.barrier_gradient(p, g.data());
        }
        return to_numpy(std::move(g), {s.model->vertex_count, 3});
      })
      .def("barrier_hessian", [](PyScene& s, py::array x, const std::string& projection) {
        const Scalar* p = s.positions(x);
        const contact::Projection how = contact_projection(projection);
        contact::Solver& solver = s.ready();
        // CSR arrays assembled in place and handed to numpy without a copy; 32-bit indices
        // (scipy's own choice, so it does not convert them) while the entries fit.
        auto build = [&](auto index) -> py::tuple {
          using I = decltype(index);
          std::vector<I> ptr, col;
          std::vector<Scalar> val;
          {
            ReleaseGil release;
            solver.barrier_hessian(p, how, ptr, col, val);
          }
          const Index nnz = static_cast<Index>(val.size()), rows = static_cast<Index>(ptr.size());
          return py::make_tuple(to_numpy(std::move(val), {nnz}), to_numpy(std::move(col), {nnz}),
                                to_numpy(std::move(ptr), {rows}));
        };
        // int32 surely holds every index when even the dense matrix's (3n)^2 entries fit.
        const Index rows = 3 * s.model->vertex_count;
        const bool small = rows < 46340 && rows * rows < std::numeric_limits<int32_t>::max();
        return small ? build(int32_t(0)) : build(int64_t(0));
      })
      .def("max_safe_step", [](PyScene& s, py::array x, py::array dx) {
        const Scalar* p = s.positions(x);
        const Scalar* d = checked_data(dx, "dx", 3 * s.model->vertex_count, false);
        contact::Solver& solver = s.ready();
        ReleaseGil release;
        return solver.max_safe_step(p, d);
      });

  // Kernels of one pair, for gradient tests.
  m.def("pair_distance", [](const std::string& kind, const ScalarArray& v) {
    contact::PairKind pk;
    if (kind == "pp") pk = contact::PairKind::PP;
    else if (kind == "pe") pk = contact::PairKind::PE;
    else if (kind == "pt") pk = contact::PairKind::PT;
    else if (kind == "ee") pk = contact::PairKind::EE;
    else throw InvalidArgument("kind: expected 'pp', 'pe', 'pt' or 'ee', got '" + kind + "'");
    const int k = contact::vertex_count(pk);
    if (v.size() != 3 * k) throw InvalidArgument("vertices: expected " + std::to_string(k) + " points");
    contact::Vec3 y[4];
    for (int a = 0; a < k; ++a) y[a] = contact::Vec3(v.data()[3 * a], v.data()[3 * a + 1], v.data()[3 * a + 2]);
    contact::Vec<12> g;
    contact::Mat<12> H;
    contact::reduced_derivatives(pk, y, g, H);
    const Scalar d = contact::reduced_distance(pk, y);
    std::vector<Scalar> gv(g.data(), g.data() + 3 * k), Hv(static_cast<size_t>(9 * k * k));
    for (int a = 0; a < 3 * k; ++a)
      for (int b = 0; b < 3 * k; ++b) Hv[static_cast<size_t>(a * 3 * k + b)] = H(a, b);
    return py::make_tuple(d, to_numpy(std::move(gv), {3 * k}), to_numpy(std::move(Hv), {3 * k, 3 * k}));
  });
  m.def("point_triangle_distance", [](const ScalarArray& p, const ScalarArray& t0, const ScalarArray& t1,
                                      const ScalarArray& t2) {
    const Index n = p.size() / 3;
    if (t0.size() != 3 * n || t1.size() != 3 * n || t2.size() != 3 * n)
      throw InvalidArgument("t0, t1, t2: expected the shape of p");
    std::vector<Scalar> out(static_cast<size_t>(n));
    auto v = [](const ScalarArray& a, Index i) { return Eigen::Map<const Vec3>(a.data() + 3 * i); };
    for (Index i = 0; i < n; ++i) out[static_cast<size_t>(i)] = contact::point_triangle_distance(v(p, i), v(t0, i), v(t1, i), v(t2, i));
    return to_numpy(std::move(out), {n});
  });
  m.def("edge_edge_distance", [](const ScalarArray& a0, const ScalarArray& a1, const ScalarArray& b0,
                                 const ScalarArray& b1) {
    const Index n = a0.size() / 3;
    if (a1.size() != 3 * n || b0.size() != 3 * n || b1.size() != 3 * n)
      throw InvalidArgument("a1, b0, b1: expected the shape of a0");
    std::vector<Scalar> out(static_cast<size_t>(n));
    auto v = [](const ScalarArray& a, Index i) { return Eigen::Map<const Vec3>(a.data() + 3 * i); };
    for (Index i = 0; i < n; ++i) out[static_cast<size_t>(i)] = contact::edge_edge_distance(v(a0, i), v(a1, i), v(b0, i), v(b1, i));
    return to_numpy(std::move(out), {n});
  });
  m.def("ccd", [](const std::string& kind, const ScalarArray& x0, const ScalarArray& x1, Scalar t_max) {
    // x0, x1: (4, 3) positions at t = 0 and t = 1.
    if (x0.size() != 12 || x1.size() != 12) throw InvalidArgument("x0, x1: expected shape (4, 3)");
    Vec3 y[4], d[4];
    for (int a = 0; a < 4; ++a) {
      y[a] = Eigen::Map<const Vec3>(x0.data() + 3 * a);
      d[a] = Eigen::Map<const Vec3>(x1.data() + 3 * a) - y[a];
    }
    if (kind == "pt") return contact::point_triangle_ccd(y[0], y[1], y[2], y[3], d[0], d[1], d[2], d[3], t_max);
    if (kind == "ee") return contact::edge_edge_ccd(y[0], y[1], y[2], y[3], d[0], d[1], d[2], d[3], t_max);
    throw InvalidArgument("kind: expected 'pt' or 'ee', got '" + kind + "'");
  });
  m.def("edge_edge_barrier", [](const ScalarArray& v, Scalar eps_x, Scalar dhat2, bool project) {
    // v: (4, 3) = a0, a1, b0, b1; the mollified barrier term with its gradient and Hessian.
    if (v.size() != 12) throw InvalidArgument("vertices: expected shape (4, 3)");
    contact::Vec3 y[4];
    for (int a = 0; a < 4; ++a) y[a] = Eigen::Map<const contact::Vec3>(v.data() + 3 * a);
    contact::Vec<12> g;
    contact::Mat<12> H;
    const contact::Reduced r = contact::edge_edge_region(y[0], y[1], y[2], y[3]);
    const Scalar e = contact::pair_barrier(r, y, eps_x, dhat2, &g, &H);
    if (project) contact::project_psd_translation_free<4>(H);
    std::vector<Scalar> gv(g.data(), g.data() + 12), Hv(144);
    for (int a = 0; a < 12; ++a)
      for (int b = 0; b < 12; ++b) Hv[static_cast<size_t>(12 * a + b)] = H(a, b);
    return py::make_tuple(e, to_numpy(std::move(gv), {12}), to_numpy(std::move(Hv), {12, 12}));
  }, py::arg("vertices"), py::arg("eps_x"), py::arg("dhat2"), py::arg("project") = false);
  m.def("barrier", [](Scalar d, Scalar dhat2) {
    return py::make_tuple(contact::barrier(d, dhat2), contact::barrier_first(d, dhat2), contact::barrier_second(d, dhat2));
  });
}

}  // namespace kinema::bind
