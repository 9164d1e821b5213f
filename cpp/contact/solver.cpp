// Projected Newton on the incremental potential with barrier, lagged friction and a
// CCD-clamped backtracking line search (Li et al. 2020, algorithm 1).
#include "contact/solver.h"

#include <Eigen/Eigenvalues>
#include <Eigen/SparseCore>
#include <algorithm>
#include <cmath>
#include <limits>

#include "contact/barrier.h"
#include "core/errors.h"
#include "core/timer.h"
#include "massspring/kernels.h"

namespace kinema::contact {

namespace {

Vec3 at(const Scalar* x, Index i) { return Eigen::Map<const Vec3>(x + 3 * i); }

Eigen::Matrix<Scalar, 3, 2> tangent_basis(const Vec3& n) {
  const Vec3 a = std::abs(n.x()) < 0.9 ? Vec3::UnitX() : Vec3::UnitY();
  const Vec3 t1 = n.cross(a).normalized();
  Eigen::Matrix<Scalar, 3, 2> P;
  P.col(0) = t1;
  P.col(1) = n.cross(t1);
  return P;
}

// Least-squares coordinates (u, v) of r in the span of e1 and e2 (the 2x2 normal equations).
Eigen::Matrix<Scalar, 2, 1> span_coordinates(const Vec3& e1, const Vec3& e2, const Vec3& r) {
  const Scalar a11 = e1.dot(e1), a12 = e1.dot(e2), a22 = e2.dot(e2), b1 = e1.dot(r), b2 = e2.dot(r);
  const Scalar det = a11 * a22 - a12 * a12;
  return {(a22 * b1 - a12 * b2) / det, (a11 * b2 - a12 * b1) / det};
}

// Weights w of the closest points of a constraint at x (relative position r = sum w_a x_a)
// and the contact normal.
void closest_weights(const Model& model, const Constraint& c, const Scalar* x, FrictionContact& f, Vec3& n) {
  f.v = c.v;
  if (c.plane >= 0) {
    // Relative to a moving plane's point: its tangential motion drags what rests on it.
    f.count = c.v[1] >= 0 ? 2 : 1;
    f.w[0] = 1;
    f.w[1] = -1;
    n = model.planes[static_cast<size_t>(c.plane)].normal;
    return;
  }
  const int k = vertex_count(c.kind);
  f.count = k;
  Vec3 y[4];
  for (int a = 0; a < k; ++a) y[a] = at(x, c.v[static_cast<size_t>(a)]);
  switch (c.kind) {
    case PairKind::PP:
      f.w[0] = 1, f.w[1] = -1;
      break;
    case PairKind::PE: {
      const Scalar s = segment_parameter(y[0], y[1], y[2]);
      f.w[0] = 1, f.w[1] = -(1 - s), f.w[2] = -s;
      break;
    }
    case PairKind::PT: {
      // Closest point y1 + u (y2 - y1) + v (y3 - y1) on the triangle's plane.
      const Eigen::Matrix<Scalar, 2, 1> uv = span_coordinates(y[2] - y[1], y[3] - y[1], y[0] - y[1]);
      f.w[0] = 1, f.w[1] = -(1 - uv[0] - uv[1]), f.w[2] = -uv[0], f.w[3] = -uv[1];
      break;
    }
    case PairKind::EE: {
      // Closest points y0 + s (y1 - y0) and y2 + t (y3 - y2): s (y1 - y0) + t (y2 - y3) = y2 - y0.
      const Eigen::Matrix<Scalar, 2, 1> st = span_coordinates(y[1] - y[0], y[2] - y[3], y[2] - y[0]);
      f.w[0] = 1 - st[0], f.w[1] = st[0], f.w[2] = -(1 - st[1]), f.w[3] = -st[1];
      break;
    }
  }
  Vec3 r = Vec3::Zero();
  for (int a = 0; a < k; ++a) r += f.w[a] * y[a];
  n = r.normalized();
}

// Sliding displacement u = P^T sum_a w_a (x_a - x_n,a) of a lagged friction contact.
Eigen::Matrix<Scalar, 2, 1> sliding(const FrictionContact& f, const Scalar* x, const Scalar* xn) {
  Vec3 rel = Vec3::Zero();
  for (int a = 0; a < f.count; ++a) {
    const Index v = f.v[static_cast<size_t>(a)];
    rel += f.w[a] * (at(x, v) - at(xn, v));
  }
  return f.P.transpose() * rel;
}

}  // namespace

Solver::Solver(const Model& model, const Config& config) : model_(model), config_(config) {
  if (!(std::isfinite(config.dhat) && config.dhat > 0))
    throw InvalidArgument("dhat: expected a finite value > 0, got " + format_real(config.dhat));
  if (!(std::isfinite(config.friction) && config.friction >= 0))
    throw InvalidArgument("friction: expected a finite value >= 0, got " + format_real(config.friction));
  if (!(std::isfinite(config.friction_velocity) && config.friction_velocity > 0))
    throw InvalidArgument("friction_velocity: expected a finite value > 0, got " +
                          format_real(config.friction_velocity));
  if (!(std::isfinite(config.barrier_stiffness) && config.barrier_stiffness >= 0))
    throw InvalidArgument("barrier_stiffness: expected a finite value >= 0, got " +
                          format_real(config.barrier_stiffness));
  if (!(std::isfinite(config.tol) && config.tol > 0))
    throw InvalidArgument("tol: expected a finite value > 0, got " + format_real(config.tol));
  if (config.max_newton < 1) throw InvalidArgument("max_newton: expected >= 1");
  if (!config.gravity.allFinite()) throw InvalidArgument("gravity: contains non-finite values");
  dhat2_ = config.dhat * config.dhat;
}

void Solver::check_intersection_free(const Scalar* x, const char* name) const {
  const std::vector<std::string> hits = find_intersections(model_, x, 5);
  if (hits.empty()) {
    const Scalar d = min_distance(model_, x, config_.dhat);
    if (d > 0) return;
    throw InvalidArgument(std::string(name) + ": two non-adjacent primitives touch (distance " + format_real(d) +
                          "); contact needs a start that is strictly free of intersections");
  }
  std::string msg = std::string(name) + ": the configuration intersects (vertex indices are global): ";
  for (size_t k = 0; k < hits.size(); ++k) msg += (k ? "; " : "") + hits[k];
  throw InvalidArgument(msg + "; contact needs a start that is free of intersections");
}

Scalar Solver::elastic_energy(const Scalar* x) const {
  Scalar e = 0;
  const Index tet_count = static_cast<Index>(model_.tet_volume.size());
  for (Index t = 0; t < tet_count; ++t) {
    const fem::Mat<3> F = fem::deformation_gradient<3>(x, &model_.tets[4 * t], model_.tet_dm_inv[t]);
    e += model_.tet_volume[t] * fem::psi<3>(F, model_.tet_material[t], model_.tet_mu[t], model_.tet_lambda[t]);
  }
  const Index spring_count = static_cast<Index>(model_.spring_rest.size());
  for (Index s = 0; s < spring_count; ++s) {
    const Vec3 d = at(x, model_.springs[2 * s + 1]) - at(x, model_.springs[2 * s]);
    e += massspring::spring_energy<3>(d, model_.spring_stiffness[s], model_.spring_rest[s]);
  }
  return e;
}

Scalar Solver::barrier_energy(const Scalar* x) const {
  return evaluate_barriers(model_, find_constraints(model_, broad_phase_, x, dhat2_), x, dhat2_, nullptr, nullptr,
                           Projection::None);
}

void Solver::barrier_gradient(const Scalar* x, Scalar* g) const {
  std::fill(g, g + 3 * model_.vertex_count, Scalar(0));
  const std::vector<Constraint> constraints = find_constraints(model_, broad_phase_, x, dhat2_);
  std::vector<Vec<12>>& gb = barrier_gradients_;
  evaluate_barriers(model_, constraints, x, dhat2_, &gb, nullptr, Projection::None);
  for (size_t k = 0; k < constraints.size(); ++k) {
    const Constraint& c = constraints[k];
    for (int a = 0; a < c.stencil_size(); ++a)
      for (int r = 0; r < 3; ++r) g[3 * c.stencil()[a] + r] += gb[k][3 * a + r];
  }
}

template <class I>
void Solver::barrier_hessian(const Scalar* x, Projection projection, std::vector<I>& ptr, std::vector<I>& col,
                             std::vector<Scalar>& val) const {
  const std::vector<Constraint> constraints = find_constraints(model_, broad_phase_, x, dhat2_);
  std::vector<Vec<12>>& gb = barrier_gradients_;
  std::vector<Mat<12>>& Hb = barrier_hessians_;
  evaluate_barriers(model_, constraints, x, dhat2_, &gb, &Hb, projection);
  // CSR straight from the contact blocks (no triplets): the 3x3 blocks (v_a, v_b) of every
  // contact, bucketed by row vertex in contact order (counting sort), each row's entries
  // stably sorted by column vertex; equal blocks are summed in contact order, as
  // setFromTriplets sums duplicates, so the values are those of the triplet assembly.
  const Index n = model_.vertex_count;
  std::vector<Index>& start = hessian_row_start_;
  std::vector<HessianEntry>& entries = hessian_entries_;
  start.assign(static_cast<size_t>(n) + 1, 0);
  size_t total = 0;
  for (const Constraint& c : constraints) {
    const int k = c.stencil_size();
    for (int a = 0; a < k; ++a) start[static_cast<size_t>(c.stencil()[a]) + 1] += k;
    total += static_cast<size_t>(k * k);
  }
  for (Index v = 0; v < n; ++v) start[static_cast<size_t>(v) + 1] += start[static_cast<size_t>(v)];
  entries.resize(total);
  {
    std::vector<Index>& next = hessian_row_next_;
    next.assign(start.begin(), start.end() - 1);
    for (size_t i = 0; i < constraints.size(); ++i) {
      const int k = constraints[i].stencil_size();
      const Index* v = constraints[i].stencil();
      for (int a = 0; a < k; ++a)
        for (int b = 0; b < k; ++b)
          entries[static_cast<size_t>(next[static_cast<size_t>(v[a])]++)] =
              HessianEntry{v[b], static_cast<Index>(i), static_cast<int>(a), static_cast<int>(b)};
    }
  }
  // Distinct column vertices per row vertex; scalar rows 3v..3v+2 each hold 3 per block.
  std::vector<Index>& blocks = hessian_row_blocks_;
  blocks.assign(static_cast<size_t>(n), 0);
  for (Index v = 0; v < n; ++v) {
    auto first = entries.begin() + start[static_cast<size_t>(v)], last = entries.begin() + start[static_cast<size_t>(v) + 1];
    if (first == last) continue;
    // Stable sort by column: insertion sort for the usual rows of a few dozen entries
    // (std::stable_sort allocates a buffer per call), std::stable_sort for long ones.
    if (last - first > 64) {
      std::stable_sort(first, last, [](const HessianEntry& p, const HessianEntry& q) { return p.col < q.col; });
    } else {
      for (auto it = first + 1; it < last; ++it) {
        const HessianEntry h = *it;
        auto hole = it;
        for (; hole != first && h.col < (hole - 1)->col; --hole) *hole = *(hole - 1);
        *hole = h;
      }
    }
    Index m = 1;
    for (auto it = first + 1; it != last; ++it) m += it->col != (it - 1)->col;
    blocks[static_cast<size_t>(v)] = m;
  }
  ptr.assign(static_cast<size_t>(3 * n) + 1, 0);
  for (Index v = 0; v < n; ++v)
    for (int r = 0; r < 3; ++r)
      ptr[static_cast<size_t>(3 * v + r) + 1] = ptr[static_cast<size_t>(3 * v + r)] + static_cast<I>(3 * blocks[static_cast<size_t>(v)]);
  const size_t nnz = static_cast<size_t>(ptr.back());
  col.resize(nnz);
  val.assign(nnz, Scalar(0));
  for (Index v = 0; v < n; ++v) {
    Index slot = -1, last_col = -1;
    for (Index e = start[static_cast<size_t>(v)]; e < start[static_cast<size_t>(v) + 1]; ++e) {
      const HessianEntry& h = entries[static_cast<size_t>(e)];
      if (h.col != last_col) {
        ++slot;
        last_col = h.col;
        for (int r = 0; r < 3; ++r)
          for (int c = 0; c < 3; ++c)
            col[static_cast<size_t>(ptr[static_cast<size_t>(3 * v + r)] + 3 * slot + c)] = static_cast<I>(3 * h.col + c);
      }
      const Mat<12>& H = Hb[static_cast<size_t>(h.contact)];
      for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c)
          val[static_cast<size_t>(ptr[static_cast<size_t>(3 * v + r)] + 3 * slot + c)] += H(3 * h.a + r, 3 * h.b + c);
    }
  }
}

template void Solver::barrier_hessian<int32_t>(const Scalar*, Projection, std::vector<int32_t>&,
                                               std::vector<int32_t>&, std::vector<Scalar>&) const;
template void Solver::barrier_hessian<int64_t>(const Scalar*, Projection, std::vector<int64_t>&,
                                               std::vector<int64_t>&, std::vector<Scalar>&) const;

std::vector<Constraint> Solver::constraints(const Scalar* x) const {
  return find_constraints(model_, broad_phase_, x, dhat2_);
}

Scalar Solver::max_safe_step(const Scalar* x, const Scalar* dx) const {
  return contact::max_safe_step(model_, broad_phase_, x, dx, CcdOptions{});
}

Scalar Solver::initial_kappa(Scalar h) const {
  if (config_.barrier_stiffness > 0) return config_.barrier_stiffness * h * h;
  // Li et al. 2020 sec. 4.3 (as in the IPC toolkit): the stiffness at which the barrier's
  // curvature at a gap of 1e-8 of the scene size matches 1e11 times the average vertex mass.
  Index dynamic = 0;
  for (Index i = 0; i < model_.vertex_count; ++i) dynamic += model_.fixed[static_cast<size_t>(i)] ? 0 : 1;
  const Scalar average_mass = dynamic > 0 ? model_.total_mass() / static_cast<Scalar>(dynamic) : 1;
  const Scalar diag = std::max(model_.bbox_diagonal(model_.rest.data()), config_.dhat);
  Scalar d0 = 1e-8 * diag;
  d0 *= d0;
  if (d0 >= dhat2_) d0 = 0.5 * dhat2_;
  return 1e11 * average_mass / (4 * d0 * barrier_second(d0, dhat2_));
}

void Solver::lag_friction(const std::vector<Scalar>& x, const std::vector<Constraint>& constraints, Scalar kappa,
                          Scalar h) {
  friction_.clear();
  bool any = config_.friction > 0;
  for (Scalar mu : model_.body_friction) any |= mu > 0;
  for (const Plane& plane : model_.planes) any |= plane.friction > 0;
  if (!any) return;
  for (const Constraint& c : constraints) {
    FrictionContact f;
    // The pair's coefficient: its collider's own, else the scene's.
    f.mu = config_.friction;
    if (c.plane >= 0) {
      const Scalar own = model_.planes[static_cast<size_t>(c.plane)].friction;
      if (own >= 0) f.mu = own;
    } else {
      for (int a = 0; a < c.stencil_size(); ++a) {
        const Scalar own = model_.body_friction[static_cast<size_t>(model_.body[static_cast<size_t>(c.stencil()[a])])];
        if (own >= 0) {
          f.mu = own;
          break;
        }
      }
    }
    if (!(f.mu > 0)) continue;
    Vec3 n;
    closest_weights(model_, c, x.data(), f, n);
    // Normal force of the barrier: -d(kappa b)/d(distance) / h^2 (kappa carries the h^2 of Phi).
    f.normal_force = -kappa / (h * h) * barrier_first(c.d, dhat2_) * 2 * std::sqrt(c.d);
    if (!(f.normal_force > 0)) continue;
    f.P = tangent_basis(n);
    friction_.push_back(f);
  }
}

Scalar Solver::potential(const std::vector<Scalar>& x, Scalar h, Scalar kappa, std::vector<Constraint>& constraints,
                         bool known) const {
  Scalar inertia = 0;
  for (Index i = 0; i < model_.vertex_count; ++i) {
    const size_t k = static_cast<size_t>(i);
    if (model_.driven[k]) {
      // Augmented Lagrangian hold of a driven vertex on its target.
      const Vec3 c = at(x.data(), i) - at(target_.data(), i);
      inertia += 0.5 * driven_stiffness_ * c.squaredNorm() - Eigen::Map<const Vec3>(&driven_lambda_[3 * k]).dot(c);
      continue;
    }
    if (model_.fixed[k]) continue;
    const Scalar m = model_.mass[k];
    inertia += 0.5 * m * (at(x.data(), i) - at(xhat_.data(), i)).squaredNorm();
    // Mass-proportional damping c m v as the dissipation h c/2 |x - x_n|_M^2.
    if (model_.damping[k] > 0) inertia += 0.5 * h * model_.damping[k] * m * (at(x.data(), i) - at(xn_.data(), i)).squaredNorm();
  }
  // Spring damping c (v_rel . d)^2 / 2 along the direction d lagged at x_n, as a dissipation h c/2 (du . d)^2.
  const Index spring_count = static_cast<Index>(model_.spring_rest.size());
  for (Index s = 0; s < spring_count; ++s) {
    if (model_.spring_damping[static_cast<size_t>(s)] <= 0) continue;
    const Index i = model_.springs[2 * s], j = model_.springs[2 * s + 1];
    const Scalar du = spring_direction_[static_cast<size_t>(s)].dot((at(x.data(), j) - at(xn_.data(), j)) -
                                                                    (at(x.data(), i) - at(xn_.data(), i)));
    inertia += 0.5 * h * model_.spring_damping[static_cast<size_t>(s)] * du * du;
  }
  if (!known) constraints = find_constraints(model_, candidates_, x.data(), dhat2_);
  const Scalar b = evaluate_barriers(model_, constraints, x.data(), dhat2_, nullptr, nullptr, Projection::None);
  Scalar friction = 0;
  const Scalar eps_v = config_.friction_velocity;
  for (const FrictionContact& f : friction_) {
    const Eigen::Matrix<Scalar, 2, 1> u = sliding(f, x.data(), xn_.data());
    friction += f.mu * f.normal_force * h * friction_f0(u.norm() / h, eps_v);
  }
  return inertia + h * h * (elastic_energy(x.data()) + friction) + kappa * b;
}

void Solver::assemble(const std::vector<Scalar>& x, Scalar h, Scalar kappa, const std::vector<Constraint>& constraints,
                      std::vector<Scalar>& g, NewtonSystem& system) const {
  const Index n = model_.vertex_count;
  g.assign(static_cast<size_t>(3 * n), 0);
  system.clear();
  const Scalar h2 = h * h;
  // (Generic: an element's gradient expression is read in place, not copied into a heap vector.)
  auto add_grad = [&](const Index* verts, int count, const auto& ge) {
    for (int a = 0; a < count; ++a)
      for (int r = 0; r < 3; ++r) g[static_cast<size_t>(3 * verts[a] + r)] += ge[3 * a + r];
  };
  // Inertia: M (x - xhat), mass-proportional damping h c M (x - x_n); driven obstacle vertices:
  // the augmented-Lagrangian spring k (x - target) - lambda.
  for (Index i = 0; i < n; ++i) {
    const size_t iv = static_cast<size_t>(i);
    if (model_.driven[iv]) {
      for (int r = 0; r < 3; ++r) {
        const size_t k = static_cast<size_t>(3 * i + r);
        g[k] += driven_stiffness_ * (x[k] - target_[k]) - driven_lambda_[k];
      }
      system.add(&elastic_slots_[iv], 1, (driven_stiffness_ * Mat3::Identity()).eval());
      continue;
    }
    if (model_.fixed[iv]) continue;
    const Scalar m = model_.mass[iv], mc = h * model_.damping[iv] * m;
    for (int r = 0; r < 3; ++r) {
      const size_t k = static_cast<size_t>(3 * i + r);
      g[k] += m * (x[k] - xhat_[k]) + mc * (x[k] - xn_[k]);
    }
    system.add(&elastic_slots_[iv], 1, ((m + mc) * Mat3::Identity()).eval());
  }
  // Elasticity: h^2 grad Psi, h^2 (projected) Hessian per element.
  const Index tet_count = static_cast<Index>(model_.tet_volume.size());
  for (Index e = 0; e < tet_count; ++e) {
    const Index* tet = &model_.tets[4 * e];
    const fem::Mat<3>& dm_inv = model_.tet_dm_inv[e];
    const fem::Mat<3> F = fem::deformation_gradient<3>(x.data(), tet, dm_inv);
    const fem::Material mat = model_.tet_material[e];
    const Scalar mu = model_.tet_mu[e], lam = model_.tet_lambda[e], vol = model_.tet_volume[e];
    add_grad(tet, 4, h2 * fem::element_gradient<3>(fem::piola<3>(F, mat, mu, lam), dm_inv, vol));
    fem::HessF<3> dPdF = fem::piola_derivative<3>(F, mat, mu, lam);
    fem::project_psd<3>(dPdF);
    system.add(&elastic_slots_[static_cast<size_t>(n + 16 * e)], 4, (h2 * fem::element_hessian<3>(dPdF, dm_inv, vol)).eval());
  }
  const Index spring_count = static_cast<Index>(model_.spring_rest.size());
  for (Index s = 0; s < spring_count; ++s) {
    const Index* ij = &model_.springs[2 * s];
    const Vec3 d = at(x.data(), ij[1]) - at(x.data(), ij[0]);
    const Scalar k = model_.spring_stiffness[s], L = model_.spring_rest[s];
    const Vec3 f = massspring::spring_force<3>(d, Vec3::Zero(), k, L, 0);  // force on ij[0]
    Eigen::Matrix<Scalar, 6, 1> ge;
    ge << -h2 * f, h2 * f;
    add_grad(ij, 2, ge);
    Mat3 S = h2 * k * massspring::spring_jacobian<3>(d, L, true);
    const Scalar c = model_.spring_damping[static_cast<size_t>(s)];
    if (c > 0) {
      const Vec3& dir = spring_direction_[static_cast<size_t>(s)];
      const Scalar du = dir.dot((at(x.data(), ij[1]) - at(xn_.data(), ij[1])) - (at(x.data(), ij[0]) - at(xn_.data(), ij[0])));
      Eigen::Matrix<Scalar, 6, 1> gd;
      gd << -h * c * du * dir, h * c * du * dir;
      add_grad(ij, 2, gd);
      S += h * c * dir * dir.transpose();
    }
    Eigen::Matrix<Scalar, 6, 6> He;
    He << S, -S, -S, S;
    system.add(&elastic_slots_[static_cast<size_t>(n + 16 * tet_count + 4 * s)], 2, He);
  }
  // Barrier: kappa (b' grad d, b'' grad d grad d^T + b' Hess d), made PSD per contact.
  std::vector<Vec<12>>& gb = barrier_gradients_;
  std::vector<Mat<12>>& Hb = barrier_hessians_;
  evaluate_barriers(model_, constraints, x.data(), dhat2_, &gb, &Hb, config_.barrier_projection);
  for (size_t i = 0; i < constraints.size(); ++i) {
    const Constraint& c = constraints[i];
    const int k = c.stencil_size();
    add_grad(c.stencil(), k, kappa * gb[i].head(3 * k));
    system.add(c.stencil(), k, kappa * Hb[i]);
  }
  // Friction: h^2 mu lambda (f1(y)/y u/h through T, and the PSD tangent Hessian).
  const Scalar eps_v = config_.friction_velocity;
  for (const FrictionContact& f : friction_) {
    const Eigen::Matrix<Scalar, 2, 1> u = sliding(f, x.data(), xn_.data());
    const Scalar y = u.norm() / h;
    const Scalar scale = h2 * f.mu * f.normal_force;
    const Scalar phi = friction_f1_over_y(y, eps_v);
    const Eigen::Matrix<Scalar, 2, 1> gu = scale * phi * u / h;
    Eigen::Matrix<Scalar, 2, 2> Hu = scale / h * phi * Eigen::Matrix<Scalar, 2, 2>::Identity();
    if (y > 0) {
      const Eigen::Matrix<Scalar, 2, 1> uh = u / u.norm();
      Hu += scale / h * (friction_f1_derivative(y, eps_v) - phi) * uh * uh.transpose();
    }
    const Eigen::Matrix<Scalar, 3, 1> g3 = f.P * gu;
    const Mat3 H3 = f.P * Hu * f.P.transpose();
    Vec<12> ge;
    Mat<12> He;
    for (int a = 0; a < f.count; ++a) {
      ge.segment<3>(3 * a) = f.w[a] * g3;
      for (int b = 0; b < f.count; ++b) He.block<3, 3>(3 * a, 3 * b) = f.w[a] * f.w[b] * H3;
    }
    add_grad(f.v.data(), f.count, ge);
    system.add(f.v.data(), f.count, He);
  }
}

void Solver::refresh_slots(const NewtonSystem& system) {
  if (&system == slots_system_ && system.layout() == slots_layout_) return;  // (reset when system_ is replaced)
  const Index n = model_.vertex_count;
  const Index tet_count = static_cast<Index>(model_.tet_volume.size());
  const Index spring_count = static_cast<Index>(model_.spring_rest.size());
  elastic_slots_.resize(static_cast<size_t>(n + 16 * tet_count + 4 * spring_count));
  for (Index i = 0; i < n; ++i) system.slots(&i, 1, &elastic_slots_[static_cast<size_t>(i)]);
  for (Index e = 0; e < tet_count; ++e) system.slots(&model_.tets[4 * e], 4, &elastic_slots_[static_cast<size_t>(n + 16 * e)]);
  for (Index s = 0; s < spring_count; ++s)
    system.slots(&model_.springs[2 * s], 2, &elastic_slots_[static_cast<size_t>(n + 16 * tet_count + 4 * s)]);
  slots_system_ = &system;
  slots_layout_ = system.layout();
}

bool Solver::keep_candidates(const Scalar* x, const Scalar* p, Scalar reach, bool force, StepStats& stats) {
  const size_t k = static_cast<size_t>(3 * model_.vertex_count);
  if (!force && cover_lo_.size() == k) {
    bool covered = true;
    for (size_t i = 0; covered && i < k; ++i) {
      const Scalar a = x[i], b = p ? x[i] + p[i] : a;
      covered = std::min(a, b) >= cover_lo_[i] && std::max(a, b) <= cover_hi_[i];
    }
    if (covered) return false;
  }
  // Boxes swept over x -> x + p, every vertex's grown by the margin delta: a later sweep whose
  // vertices stay inside their grown boxes meets only pairs whose boxes, grown by dhat + 2 delta
  // (delta from each side), met here.
  // delta = dhat: on the 16x16 cloth the broad phase then runs 3-5 times per step instead of
  // once per Newton iteration (7.6), while the larger candidate set costs the narrow phase
  // little (larger margins cost more than they save).
  const Scalar delta = config_.dhat;
  // The region covers the sweep x -> x + reach p: inside the Newton loop reach = 2, since the
  // iterates that follow mostly go on in p's direction (in Newton's linear phase every full
  // step falls short, and the next ones continue along much the same path):
  // on the 16x16 cloth 1.6 broad phases per step instead of 3.0 at reach 1 (reach 3: 1.4, but
  // the larger candidate set then costs about what it saves; a uniformly larger delta more).
  if (p && reach != 1) {
    reach_.resize(k);
    for (size_t i = 0; i < k; ++i) reach_[i] = reach * p[i];
    p = reach_.data();
  }
  Stopwatch timer;
  cover_lo_.clear();  // (no cover while the candidates are being replaced)
  broad_phase_.find(model_, x, p, config_.dhat + 2 * delta, candidates_);
  cover_lo_.resize(k);
  cover_hi_.resize(k);
  for (size_t i = 0; i < k; ++i) {
    const Scalar a = x[i], b = p ? x[i] + p[i] : a;
    cover_lo_[i] = std::min(a, b) - delta;
    cover_hi_[i] = std::max(a, b) + delta;
  }
  stats.broad_phase_seconds += timer.seconds();
  ++stats.broad_phases;
  return true;
}

StepStats Solver::step(State& state, Scalar dt, Interrupt& interrupt) {
  Stopwatch timer;
  // The incremental potential weighs the elastic and barrier energies by dt^2: that must be finite.
  if (!(std::isfinite(dt) && dt > 0 && std::isfinite(dt * dt)))
    throw InvalidArgument("dt: expected a finite value > 0 with a finite square, got " + format_real(dt));
  const Index n = model_.vertex_count;
  if (static_cast<Index>(state.x.size()) != 3 * n || static_cast<Index>(state.v.size()) != 3 * n)
    throw InvalidArgument("state: expected " + std::to_string(n) + " vertices");
  StepStats stats;
  const Scalar h = dt;
  if (state.kappa <= 0) {
    check_intersection_free(state.x.data(), "x");
    state.kappa = initial_kappa(h);
  }
  const Scalar diag = std::max(model_.bbox_diagonal(state.x.data()), config_.dhat);

  // Inertia target xhat = x_n + h v_n + h^2 g and friction lagged at x_n (Li et al. 2020, eq. 17).
  xn_ = state.x;
  xhat_.resize(xn_.size());
  sweep_.resize(xn_.size());
  for (Index i = 0; i < n; ++i)
    for (int r = 0; r < 3; ++r) {
      const size_t k = static_cast<size_t>(3 * i + r);
      xhat_[k] = model_.fixed[static_cast<size_t>(i)] ? xn_[k] : xn_[k] + h * state.v[k] + h * h * config_.gravity[r];
    }
  // A step that would carry vertices over many scene diagonals is a diverged state (or a dt far
  // too long): CCD would crawl along such a path in tiny increments for hours. Refused. The
  // scale is at least 1 m, so that a scene whose bodies span nothing (a single vertex above a
  // plane) is not refused for an ordinary step.
  {
    Scalar reach = 0;
    for (size_t k = 0; k < xhat_.size(); ++k) reach = std::max(reach, std::abs(xhat_[k] - xn_[k]));
    if (!(reach <= 1e3 * std::max(diag, Scalar(1))))
      throw DivergenceError("v: a step of dt = " + format_real(h) + " would move vertices by " + format_real(reach) +
                            " m, more than 1000 scene diagonals (" + format_real(std::max(diag, Scalar(1))) +
                            " m): the state has diverged or dt is far too long");
  }
  Scalar kappa = state.kappa;
  // The active pairs at the current iterate (kept: the assembly, the line search's Phi at x
  // and the kappa update all read them). At x_n: those the last step ended with when the state
  // is still where it left it (bitwise; the pairs are a function of x), and then no broad phase
  // here: the kept candidates serve until a Newton sweep leaves the region they cover (on the
  // 16x16 cloth 1.6 broad phases per step instead of 2.5 with one covering x_n -> xhat first).
  // Else the candidates cover the sweep x_n -> xhat, where the first Newton step heads. Pairs
  // are sorted, so a larger candidate set finds the same pairs.
  std::vector<Constraint> current, next;
  if (!end_x_.empty() && end_x_ == xn_) {
    current = end_constraints_;
  } else {
    for (size_t k = 0; k < xhat_.size(); ++k) sweep_[k] = xhat_[k] - xn_[k];
    keep_candidates(xn_.data(), sweep_.data(), 1, true, stats);
    current = find_constraints(model_, candidates_, xn_.data(), dhat2_);
  }
  lag_friction(xn_, current, kappa, h);
  // Spring damping acts along the spring directions at x_n.
  const Index spring_count = static_cast<Index>(model_.spring_rest.size());
  spring_direction_.assign(static_cast<size_t>(spring_count), Vec3::Zero());
  for (Index s = 0; s < spring_count; ++s) {
    const Vec3 d = at(xn_.data(), model_.springs[2 * s + 1]) - at(xn_.data(), model_.springs[2 * s]);
    if (d.norm() > 0) spring_direction_[static_cast<size_t>(s)] = d.normalized();
  }
  // Driven obstacle vertices: held to their targets by k/2 |x - target|^2 - lambda . (x - target)
  // (augmented Lagrangian, as IPC holds Dirichlet conditions, Li et al. 2020 sec. 5), with
  // lambda updated whenever Newton converges short of the target.
  bool any_driven = false;
  for (Index i = 0; i < n; ++i) any_driven |= model_.driven[static_cast<size_t>(i)] != 0;
  if (any_driven && static_cast<Index>(state.target.size()) != 3 * n)
    throw InvalidArgument("target: expected " + std::to_string(n) + " positions");
  target_ = any_driven ? state.target : xn_;
  driven_lambda_.assign(static_cast<size_t>(3 * n), 0);
  {
    Index dynamic = 0;
    for (Index i = 0; i < n; ++i) dynamic += model_.fixed[static_cast<size_t>(i)] ? 0 : 1;
    driven_stiffness_ = 1e8 * (dynamic > 0 ? model_.total_mass() / static_cast<Scalar>(dynamic) : 1);
  }
  const Scalar track_tol = config_.tol * diag * h;
  auto driven_gap = [&](const std::vector<Scalar>& y) {
    Scalar worst = 0;
    for (Index i = 0; i < n; ++i)
      if (model_.driven[static_cast<size_t>(i)]) worst = std::max(worst, (at(y.data(), i) - at(target_.data(), i)).norm());
    return worst;
  };

  std::vector<Scalar> x = xn_, g, p(static_cast<size_t>(3 * n)), trial(static_cast<size_t>(3 * n));
  if (!system_ || !config_.reuse_pattern) {
    system_ = std::make_unique<NewtonSystem>(model_);
    slots_system_ = nullptr;
  }
  {
    std::vector<std::vector<Index>> stencils;
    for (const Constraint& c : current) stencils.emplace_back(c.stencil(), c.stencil() + c.stencil_size());
    system_->begin_step(stencils);
  }
  const Index m = system_->size();
  std::vector<Scalar> rhs(static_cast<size_t>(m)), pd(static_cast<size_t>(m));
  stats.unknowns = m;
  Scalar prev_min = std::numeric_limits<Scalar>::infinity();
  bool converged = false;
  // Phi at the current iterate, known after an accepted line search (the trial's value: same x,
  // same pairs, so the same bits) until kappa or a driven multiplier changes.
  Scalar phi_x = 0;
  bool phi_known = false;
  for (Index it = 0; it < config_.max_newton; ++it) {
    interrupt.check();
    // Projected Newton direction: H p = -grad Phi over the degrees of freedom.
    Stopwatch phase;
    if (!config_.reuse_pattern && it > 0) {
      system_ = std::make_unique<NewtonSystem>(model_);
      slots_system_ = nullptr;
    }
    refresh_slots(*system_);
    assemble(x, h, kappa, current, g, *system_);
    system_->finish();
    const bool simplicial = config_.simplicial && config_.linear_solver == LinearSolver::CholmodDirect;
    const CsrView view = system_->view();
    if (!linear_ || system_->version() != linear_version_ || !config_.reuse_pattern) {
      // A new pattern: a new symbolic analysis.
      linear_ = std::make_unique<SpdSolver>();
      linear_version_ = system_->version();
      ++stats.pattern_changes;
      if (simplicial) block_llt_.analyze(view);
    }
    stats.assemble_seconds += phase.seconds();
    phase.restart();
    for (Index d = 0; d < system_->dof_count(); ++d)
      for (int r = 0; r < 3; ++r) rhs[static_cast<size_t>(3 * d + r)] = -g[static_cast<size_t>(3 * system_->vertex(d) + r)];
    std::fill(pd.begin(), pd.end(), Scalar(0));
    bool definite = true;
    if (simplicial) {
      Stopwatch factor_timer;
      definite = block_llt_.factorize(view);
      stats.factor_seconds += factor_timer.seconds();
      if (definite) block_llt_.solve(rhs.data(), pd.data());
    } else {
      // cholmod-pcg: PCG preconditioned by the last factor (refactorised when it stalls) to a
      // relative residual of 1e-8; the direct and CG kinds solve to rounding / 1e-10.
      SpdSolveStats solve_stats;
      const bool lagged = config_.linear_solver == LinearSolver::Cholmod;
      definite = linear_->solve(config_.linear_solver, view, rhs.data(), pd.data(), lagged ? 1e-8 : 1e-10, lagged,
                                interrupt, solve_stats);
    }
    if (!definite) throw NotPositiveDefinite("contact: the projected Newton matrix is not positive definite", -1);
    std::fill(p.begin(), p.end(), Scalar(0));
    for (Index d = 0; d < system_->dof_count(); ++d)
      for (int r = 0; r < 3; ++r) p[static_cast<size_t>(3 * system_->vertex(d) + r)] = pd[static_cast<size_t>(3 * d + r)];
    stats.solve_seconds += phase.seconds();
    stats.newton_iterations = it + 1;
    Scalar p_max = 0;
    for (Scalar v : p) p_max = std::max(p_max, std::abs(v));
    stats.newton_history.push_back(p_max / (h * diag));
    if (!std::isfinite(p_max)) throw DivergenceError("contact: non-finite Newton step at time " + format_real(state.time));
    if (p_max < config_.tol * diag * h) {
      if (!any_driven || driven_gap(x) <= track_tol) {
        converged = true;
        break;
      }
      // Short of a driven target: move the multipliers towards the reaction and go on.
      for (Index i = 0; i < n; ++i)
        if (model_.driven[static_cast<size_t>(i)])
          for (int r = 0; r < 3; ++r) {
            const size_t k = static_cast<size_t>(3 * i + r);
            driven_lambda_[k] -= driven_stiffness_ * (x[k] - target_[k]);
          }
      phi_known = false;
      continue;
    }
    // Largest intersection-free step by CCD, then backtracking until Phi decreases.
    Stopwatch ccd_timer;
    CcdOptions ccd;
    // Candidates covering the sweep x -> x + p hold the CCD pairs, every line-search trial's
    // active pairs and the next iteration's; the broad phase runs only when the sweep leaves
    // the region the kept ones cover.
    keep_candidates(x.data(), p.data(), 2, false, stats);
    Scalar alpha = contact::max_safe_step(model_, candidates_, x.data(), p.data(), ccd);
    stats.ccd_seconds += ccd_timer.seconds();
    stats.min_step_fraction = std::min(stats.min_step_fraction, alpha);
    phase.restart();
    const Scalar phi0 = phi_known ? phi_x : potential(x, h, kappa, current, true);
    bool accepted = false;
    for (int ls = 0; ls < 60; ++ls) {
      for (size_t k = 0; k < x.size(); ++k) trial[k] = x[k] + alpha * p[k];
      const Scalar phi = potential(trial, h, kappa, next, false);
      if (phi <= phi0) {
        accepted = true;
        phi_x = phi;
        phi_known = true;
        break;
      }
      alpha /= 2;
      ++stats.line_search_halvings;
    }
    stats.line_search_seconds += phase.seconds();
    stats.step_history.push_back(accepted ? alpha : 0);
    if (!accepted) {
      // No decrease along a descent direction: Phi is at its minimum to rounding.
      converged = !any_driven || driven_gap(x) <= track_tol;
      break;
    }
    x.swap(trial);
    current.swap(next);
    // Raise kappa when contacts keep closing in below 1e-9 of the scene size (Li et al. 2020,
    // sec. 4.3), so the gap stays resolvable in floating point.
    Scalar dmin = std::numeric_limits<Scalar>::infinity();
    for (const Constraint& c : current) dmin = std::min(dmin, std::sqrt(c.d));
    const Scalar eps_d = 1e-9 * diag;
    if (prev_min < eps_d && dmin < eps_d && dmin < prev_min) {
      kappa *= 2;
      phi_known = false;
    }
    prev_min = dmin;
  }
  if (!converged) {
    std::string last;
    const size_t k = stats.newton_history.size();
    for (size_t i = k > 4 ? k - 4 : 0; i < k; ++i)
      last += (last.empty() ? "" : ", ") + format_real(stats.newton_history[i]) + " (step " +
              format_real(stats.step_history[std::min(i, stats.step_history.size() - 1)]) + ")";
    if (any_driven && driven_gap(x) > track_tol)
      throw ConvergenceError("contact: a moving collider could not reach its scripted position at time " +
                             format_real(state.time + h) + " (off by " + format_real(driven_gap(x)) +
                             " m): something is squeezed between colliders; try a smaller dt");
    throw ConvergenceError("contact: Newton did not reach tol = " + format_real(config_.tol) + " in " +
                           std::to_string(config_.max_newton) + " iterations at time " + format_real(state.time) +
                           " (last max|dx|/(dt diag): " + last + "); try a smaller dt or a larger max_newton");
  }

  // Driven vertices land exactly on their targets where that last move is intersection-free.
  if (any_driven) {
    std::vector<Scalar> rest_move(x.size(), 0);
    for (Index i = 0; i < n; ++i)
      if (model_.driven[static_cast<size_t>(i)])
        for (int r = 0; r < 3; ++r) rest_move[static_cast<size_t>(3 * i + r)] = target_[static_cast<size_t>(3 * i + r)] - x[static_cast<size_t>(3 * i + r)];
    if (max_safe_step(x.data(), rest_move.data()) >= 1) {
      keep_candidates(x.data(), rest_move.data(), 1, false, stats);
      for (size_t k = 0; k < x.size(); ++k) x[k] += rest_move[k];
      current = find_constraints(model_, candidates_, x.data(), dhat2_);
    }
  }
  // Kept for the next step's start (x_n is then this x unless the user moved it).
  end_x_ = x;
  end_constraints_ = current;
  // Velocities from the displacement (implicit Euler).
  for (size_t k = 0; k < x.size(); ++k) state.v[k] = (x[k] - xn_[k]) / h;
  state.x = x;
  state.time += h;
  state.kappa = kappa;

  const std::vector<Constraint>& final_set = current;
  stats.contact_count = static_cast<Index>(final_set.size());
  stats.min_distance = std::numeric_limits<Scalar>::infinity();
  for (const Constraint& c : final_set) stats.min_distance = std::min(stats.min_distance, std::sqrt(c.d));
  for (const FrictionContact& f : friction_) {
    if (sliding(f, x.data(), xn_.data()).norm() / h < config_.friction_velocity)
      ++stats.sticking_count;
    else
      ++stats.sliding_count;
  }
  stats.barrier_stiffness = kappa;
  stats.time = state.time;
  stats.dt = h;
  stats.seconds = timer.seconds();
  stats.ccd_share = stats.seconds > 0 ? stats.ccd_seconds / stats.seconds : 0;
  return stats;
}

}  // namespace kinema::contact
