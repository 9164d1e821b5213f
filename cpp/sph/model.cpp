// Config checks, Model and State construction and the scene helpers (lattice blocks, box walls).
#include "sph/model.h"

#include <algorithm>
#include <cmath>
#include <string>

#include "core/errors.h"
#include "core/parallel.h"
#include "particles/neighbor_grid.h"
#include "sph/kernels.h"

namespace kinema::sph {

Method parse_method(const std::string& name) {
  if (name == "wcsph") return Method::WCSPH;
  if (name == "dfsph") return Method::DFSPH;
  throw InvalidArgument("method: expected 'wcsph' or 'dfsph', got '" + name + "'");
}

const char* method_name(Method method) { return method == Method::WCSPH ? "wcsph" : "dfsph"; }

void check(const Config& c) {
  auto positive = [](Scalar v, const char* name) {
    if (!(v > 0) || !std::isfinite(v))
      throw InvalidArgument(std::string(name) + ": expected a finite number > 0, got " + format_real(v));
  };
  auto fraction = [](Scalar v, const char* name) {
    if (!(v >= 0) || !(v <= 1))
      throw InvalidArgument(std::string(name) + ": expected a number in [0, 1], got " + format_real(v));
  };
  if (c.method != Method::WCSPH && c.method != Method::DFSPH) throw InvalidArgument("method: unknown");
  positive(c.rho0, "rho0");
  if (!(c.viscosity >= 0) || !std::isfinite(c.viscosity))
    throw InvalidArgument("viscosity: expected a finite number >= 0, got " + format_real(c.viscosity));
  for (Scalar g : c.gravity)
    if (!std::isfinite(g)) throw InvalidArgument("gravity: expected finite components, got " + format_real(g));
  if (c.speed_of_sound != 0) positive(c.speed_of_sound, "speed_of_sound");
  positive(c.gamma, "gamma");
  positive(c.tol, "tol");
  positive(c.divergence_tol, "divergence_tol");
  if (c.max_iter < 1) throw InvalidArgument("max_iter: expected an integer >= 1, got " + std::to_string(c.max_iter));
  if (c.reorder_every < 0)
    throw InvalidArgument("reorder_every: expected an integer >= 0, got " + std::to_string(c.reorder_every));
  fraction(c.neighbor_skin, "neighbor_skin");
  fraction(c.warm_start, "warm_start");
  if (c.coarse_correction < -1 || c.coarse_correction > 1)
    throw InvalidArgument("coarse_correction: expected -1 (auto), 0 or 1, got " + std::to_string(c.coarse_correction));
}

State::State(int dim_, Index n_)
    : dim(dim_), n(n_), x(static_cast<size_t>(n_ * dim_), 0), v(static_cast<size_t>(n_ * dim_), 0),
      density(static_cast<size_t>(n_), 0), pressure(static_cast<size_t>(n_), 0),
      ids(static_cast<size_t>(n_)) {
  if (dim != 2 && dim != 3) throw InvalidArgument("positions: expected d = 2 or 3 columns");
  for (Index i = 0; i < n; ++i) ids[i] = i;
}

namespace {

// c = 10 sqrt(2 |g| H) for the fluid's initial height H along gravity, so that the flow stays
// below Mach 0.1 and compression near 1% (Monaghan 1994); never below 10 x the initial speeds.
Scalar default_speed_of_sound(const Config& config, const State& s, Scalar h) {
  const int d = s.dim;
  Scalar g = 0;
  for (int a = 0; a < d; ++a) g += config.gravity[a] * config.gravity[a];
  g = std::sqrt(g);
  Scalar height = 0;
  if (g > 0 && s.n > 0) {
    Scalar lo = INFINITY, hi = -INFINITY;
    for (Index i = 0; i < s.n; ++i) {
      Scalar y = 0;  // the height along -g
      for (int a = 0; a < d; ++a) y += (-config.gravity[a] / g) * s.x[i * d + a];
      lo = std::min(lo, y);
      hi = std::max(hi, y);
    }
    height = std::max(hi - lo, h);
  }
  Scalar vmax2 = 0;
  for (Index i = 0; i < s.n; ++i) {
    Scalar v2 = 0;
    for (int a = 0; a < d; ++a) v2 += s.v[i * d + a] * s.v[i * d + a];
    vmax2 = std::max(vmax2, v2);
  }
  const Scalar c = std::max(10 * std::sqrt(2 * g * height), 10 * std::sqrt(vmax2));
  return c > 0 ? c : 1.0;
}

template <int D>
std::vector<Scalar> akinci_psi(const std::vector<Scalar>& xb, Scalar h, Scalar rho0) {
  using Vec = Eigen::Matrix<Scalar, D, 1>;
  const Index m = static_cast<Index>(xb.size()) / D;
  NeighborGrid<D> grid;
  grid.build(xb.data(), m, h);
  const CubicSpline<D> W(h);
  std::vector<Scalar> psi(static_cast<size_t>(m));
  parallel_for(m, [&](Index b) {
    const Vec xi = Eigen::Map<const Vec>(xb.data() + b * D);
    Scalar sum = 0;  // includes the sample itself
    grid.for_each_candidate(xi, [&](Index k) {
      sum += W.w((Eigen::Map<const Vec>(xb.data() + k * D) - xi).norm());
    });
    // psi_b = rho0 V_b with V_b = 1 / sum_k W_bk (Akinci et al. 2012, eq. 4).
    psi[static_cast<size_t>(b)] = rho0 / sum;
  });
  return psi;
}

// The boundary's own density at each sample, sum_k psi_k W_bk (itself included).
template <int D>
std::vector<Scalar> wall_density(const std::vector<Scalar>& xb, const std::vector<Scalar>& psi, Scalar h) {
  using Vec = Eigen::Matrix<Scalar, D, 1>;
  const Index m = static_cast<Index>(psi.size());
  std::vector<Scalar> rho(static_cast<size_t>(m), 0);
  if (m == 0) return rho;
  NeighborGrid<D> grid;
  grid.build(xb.data(), m, h);
  const CubicSpline<D> W(h);
  parallel_for(m, [&](Index b) {
    const Vec xi = Eigen::Map<const Vec>(xb.data() + b * D);
    Scalar sum = 0;
    grid.for_each_candidate(xi, [&](Index k) {
      sum += psi[static_cast<size_t>(k)] * W.w((Eigen::Map<const Vec>(xb.data() + k * D) - xi).norm());
    });
    rho[static_cast<size_t>(b)] = sum;
  });
  return rho;
}

}  // namespace

Model make_model(const Config& config, const State& initial, Scalar spacing, std::vector<Scalar> boundary,
                 const Scalar* lower, const Scalar* upper) {
  check(config);
  const int dim = initial.dim;
  const Scalar rho0 = config.rho0;
  if (dim != 2 && dim != 3) throw InvalidArgument("positions: expected d = 2 or 3 columns");
  if (initial.n >= (Index{1} << 31)) throw InvalidArgument("positions: at most 2^31 - 1 particles");
  for (const std::vector<Scalar>* a : {&initial.x, &initial.v})
    for (Scalar c : *a)
      if (!std::isfinite(c))
        throw InvalidArgument(std::string(a == &initial.x ? "positions" : "velocity") + ": expected finite values");
  if (!(spacing > 0) || !std::isfinite(spacing))
    throw InvalidArgument("spacing: expected a finite number > 0, got " + format_real(spacing));
  if (boundary.size() % static_cast<size_t>(dim) != 0)
    throw InvalidArgument("boundary: expected shape (M, " + std::to_string(dim) + ")");
  for (Scalar c : boundary)
    if (!std::isfinite(c)) throw InvalidArgument("boundary: expected finite values");
  Model model;
  model.dim = dim;
  model.spacing = spacing;
  model.h = 2 * spacing;
  model.mass = rho0 * std::pow(spacing, dim);
  model.speed_of_sound =
      config.speed_of_sound > 0 ? config.speed_of_sound : default_speed_of_sound(config, initial, model.h);
  model.boundary_x = std::move(boundary);
  model.boundary_psi = dim == 2 ? akinci_psi<2>(model.boundary_x, model.h, rho0)
                                : akinci_psi<3>(model.boundary_x, model.h, rho0);
  model.wall_begin = model.boundary_count();
  if (lower && upper) {
    model.has_domain = true;
    for (int a = 0; a < dim; ++a) {
      if (!(upper[a] > lower[a]) || !std::isfinite(lower[a]) || !std::isfinite(upper[a]))
        throw InvalidArgument("domain: expected finite lower < upper on every axis");
      model.lower[a] = lower[a];
      model.upper[a] = upper[a];
    }
    // The walls are two lattice layers whose volume is known exactly: Akinci's estimate
    // 1 / sum_k W_bk would see only the wall side of a wall sample's support and overstate
    // it, leaving a few percent of spurious compression at the walls.
    const std::vector<Scalar> walls = box_boundary(dim, lower, upper, spacing, 2);
    Scalar volume = 1;
    for (int a = 0; a < dim; ++a) {
      const Scalar length = upper[a] - lower[a];
      volume *= length / static_cast<Scalar>(std::max<Index>(1, std::llround(length / spacing)));
    }
    model.boundary_x.insert(model.boundary_x.end(), walls.begin(), walls.end());
    model.boundary_psi.resize(model.boundary_x.size() / static_cast<size_t>(dim), rho0 * volume);
  }
  model.wall_rho = dim == 2 ? wall_density<2>(model.boundary_x, model.boundary_psi, model.h)
                            : wall_density<3>(model.boundary_x, model.boundary_psi, model.h);
  return model;
}

std::vector<Scalar> block(int dim, const Scalar* lower, const Scalar* upper, Scalar spacing) {
  std::array<Index, 3> count{1, 1, 1};
  Index total = 1;
  for (int a = 0; a < dim; ++a) {
    // Points whose centre lies in the box: lower + (k + 1/2) spacing <= upper.
    count[a] = std::max<Index>(0, static_cast<Index>(std::floor((upper[a] - lower[a]) / spacing + 0.5 + 1e-9)));
    total *= count[a];
  }
  std::vector<Scalar> x(static_cast<size_t>(total * dim));
  Index p = 0;
  for (Index i = 0; i < count[0]; ++i)
    for (Index j = 0; j < count[1]; ++j)
      for (Index k = 0; k < (dim == 3 ? count[2] : 1); ++k, ++p) {
        const Index idx[3] = {i, j, k};
        for (int a = 0; a < dim; ++a) x[p * dim + a] = lower[a] + (idx[a] + 0.5) * spacing;
      }
  return x;
}

std::vector<Scalar> box_boundary(int dim, const Scalar* lower, const Scalar* upper, Scalar spacing,
                                 int layers) {
  // Per axis: the wall-parallel coordinates inside (spacing stretched to fit the box exactly,
  // so the samples of opposite walls line up) and `layers` coordinates beyond each wall.
  std::array<std::vector<Scalar>, 3> coords;
  std::array<std::vector<bool>, 3> outside;
  for (int a = 0; a < dim; ++a) {
    const Scalar length = upper[a] - lower[a];
    const Index n = std::max<Index>(1, static_cast<Index>(std::llround(length / spacing)));
    const Scalar s = length / static_cast<Scalar>(n);
    for (int k = layers - 1; k >= 0; --k) {
      coords[a].push_back(lower[a] - (k + 0.5) * s);
      outside[a].push_back(true);
    }
    for (Index k = 0; k < n; ++k) {
      coords[a].push_back(lower[a] + (k + 0.5) * s);
      outside[a].push_back(false);
    }
    for (int k = 0; k < layers; ++k) {
      coords[a].push_back(upper[a] + (k + 0.5) * s);
      outside[a].push_back(true);
    }
  }
  if (dim == 2) {
    coords[2] = {0};
    outside[2] = {false};
  }
  std::vector<Scalar> x;
  for (size_t i = 0; i < coords[0].size(); ++i)
    for (size_t j = 0; j < coords[1].size(); ++j)
      for (size_t k = 0; k < coords[2].size(); ++k) {
        if (!(outside[0][i] || outside[1][j] || outside[2][k])) continue;
        x.push_back(coords[0][i]);
        x.push_back(coords[1][j]);
        if (dim == 3) x.push_back(coords[2][k]);
      }
  return x;
}

}  // namespace kinema::sph
