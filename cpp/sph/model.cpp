// Model and State construction, scene helpers (lattice blocks, box walls) and the solver factory.
#include <cmath>
#include <string>

#include "core/errors.h"
#include "core/parallel.h"
#include "particles/neighbor_grid.h"
#include "sph/fluid.h"
#include "sph/kernels.h"

namespace kinema::sph {

Method parse_method(const std::string& name) {
  if (name == "wcsph") return Method::WCSPH;
  if (name == "dfsph") return Method::DFSPH;
  throw InvalidArgument("method: expected 'wcsph' or 'dfsph', got '" + name + "'");
}

State::State(int dim_, Index n_)
    : dim(dim_), n(n_), x(static_cast<size_t>(n_ * dim_), 0), v(static_cast<size_t>(n_ * dim_), 0),
      density(static_cast<size_t>(n_), 0), pressure(static_cast<size_t>(n_), 0),
      ids(static_cast<size_t>(n_)) {
  for (Index i = 0; i < n; ++i) ids[i] = i;
}

namespace {

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

}  // namespace

Model make_model(int dim, Scalar spacing, Scalar rho0, std::vector<Scalar> boundary,
                 const Scalar* lower, const Scalar* upper) {
  if (dim != 2 && dim != 3) throw InvalidArgument("positions: expected d = 2 or 3 columns");
  if (!(spacing > 0) || !std::isfinite(spacing))
    throw InvalidArgument("spacing: expected a finite number > 0, got " + std::to_string(spacing));
  if (!(rho0 > 0) || !std::isfinite(rho0))
    throw InvalidArgument("rho0: expected a finite number > 0, got " + std::to_string(rho0));
  if (boundary.size() % static_cast<size_t>(dim) != 0)
    throw InvalidArgument("boundary: expected shape (M, " + std::to_string(dim) + ")");
  Model model;
  model.dim = dim;
  model.spacing = spacing;
  model.h = 2 * spacing;
  model.mass = rho0 * std::pow(spacing, dim);
  model.boundary_x = std::move(boundary);
  model.boundary_psi = dim == 2 ? akinci_psi<2>(model.boundary_x, model.h, rho0)
                                : akinci_psi<3>(model.boundary_x, model.h, rho0);
  if (lower && upper) {
    model.has_domain = true;
    for (int a = 0; a < dim; ++a) {
      if (!(upper[a] > lower[a]))
        throw InvalidArgument("domain: expected lower < upper on every axis");
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
