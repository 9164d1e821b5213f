#include "fem/model.h"

#include <algorithm>
#include <array>
#include <cstdint>
#include <cmath>
#include <limits>
#include <string>
#include <unordered_map>
#include <utility>

#include "core/errors.h"
#include "mesh/vertex_set.h"

namespace kinema::fem {

namespace {

template <int D>
void build_rest_shape(Model& m) {
  m.Dm_inv.resize(m.element_count * D * D);
  m.volume.resize(m.element_count);
  for (Index e = 0; e < m.element_count; ++e) {
    const Index* el = m.elements.data() + e * (D + 1);
    Mat<D> Dinv;
    const Scalar vol = rest_shape<D>(m.rest.data(), el, Dinv);
    // Degenerate when the volume is negligible next to the element's own edge lengths.
    Scalar longest = 0;
    for (int a = 0; a <= D; ++a)
      for (int b = a + 1; b <= D; ++b) {
        Scalar len2 = 0;
        for (int r = 0; r < D; ++r) {
          const Scalar t = m.rest[el[a] * D + r] - m.rest[el[b] * D + r];
          len2 += t * t;
        }
        longest = std::max(longest, std::sqrt(len2));
      }
    if (!(std::abs(vol) > 1e-12 * std::pow(longest, D)) || !Dinv.allFinite())
      throw InvalidArgument("elements: element " + std::to_string(e) +
                            " is degenerate (rest " + (D == 2 ? "area " : "volume ") + format_real(vol) +
                            "); remove it or fix its vertices");
    if (vol < 0)
      throw InvalidArgument("elements: element " + std::to_string(e) +
                            " is inverted in the rest shape (signed " +
                            (D == 2 ? "area " : "volume ") + format_real(vol) +
                            "); swap two of its vertices to orient it positively");
    m.volume[e] = vol;
    Eigen::Map<Mat<D>>(m.Dm_inv.data() + e * D * D) = Dinv;
  }
}

// One value or one per element, each passing `ok`; names the element of a bad value.
template <class Ok>
void check_per_element(const std::vector<Scalar>& a, Index element_count, const char* name,
                       const char* expected, Ok&& ok) {
  if (a.size() != 1 && static_cast<Index>(a.size()) != element_count)
    throw InvalidArgument(std::string(name) + ": expected a scalar or " +
                          std::to_string(element_count) + " values (one per element), got " +
                          std::to_string(a.size()));
  for (std::size_t e = 0; e < a.size(); ++e)
    if (!ok(a[e]))
      throw InvalidArgument(std::string(name) + ": expected " + expected + ", got " +
                            format_real(a[e]) +
                            (a.size() > 1 ? " at element " + std::to_string(e) : std::string()));
}

// Two elements on the same vertex set (in any order) double its mass and stiffness: refused,
// naming both. Each element's sorted vertices are hashed; O(m).
void check_duplicates(const std::vector<Index>& elements, Index element_count, int nodes) {
  struct Key {
    std::array<Index, 4> v{};
    bool operator==(const Key& o) const { return v == o.v; }
  };
  struct Hash {
    std::size_t operator()(const Key& k) const {
      std::uint64_t h = 1469598103934665603ull;
      for (Index i : k.v) h = (h ^ static_cast<std::uint64_t>(i)) * 1099511628211ull;
      return static_cast<std::size_t>(h);
    }
  };
  std::unordered_map<Key, Index, Hash> seen;
  seen.reserve(static_cast<std::size_t>(element_count));
  for (Index e = 0; e < element_count; ++e) {
    Key k;
    std::copy(elements.begin() + e * nodes, elements.begin() + (e + 1) * nodes, k.v.begin());
    // An insertion sort of <= 4 keys (std::sort's 16-wide insertion pass draws a false
    // -Warray-bounds from GCC 12 here).
    for (int a = 1; a < nodes; ++a)
      for (int b = a; b > 0 && k.v[b] < k.v[b - 1]; --b) std::swap(k.v[b], k.v[b - 1]);
    auto [it, inserted] = seen.emplace(k, e);
    if (!inserted)
      throw InvalidArgument("elements: elements " + std::to_string(it->second) + " and " + std::to_string(e) +
                            " have the same vertices (a duplicate doubles their mass and stiffness); "
                            "remove one");
  }
}

}  // namespace

Model make_model(int dim, const Scalar* rest, Index vertex_count, const Index* elements,
                 Index element_count, Parameters parameters, const Index* fixed,
                 Index fixed_count) {
  if (dim != 2 && dim != 3) throw InvalidArgument("vertices: expected d = 2 or 3 columns");
  if (element_count < 1) throw InvalidArgument("elements: expected at least one element");
  const Parameters& p = parameters;
  check_per_element(p.youngs_modulus, element_count, "youngs_modulus", "a finite number > 0",
                    [](Scalar E) { return E > 0 && std::isfinite(E); });
  check_per_element(p.poisson_ratio, element_count, "poisson_ratio", "a number in (-1, 0.5)",
                    [](Scalar nu) { return nu > -1 && nu < 0.5; });
  if (!(p.density > 0) || !std::isfinite(p.density))
    throw InvalidArgument("density: expected a finite number > 0, got " + format_real(p.density));
  if (!(p.damping >= 0) || !std::isfinite(p.damping))
    throw InvalidArgument("damping: expected a finite number >= 0, got " + format_real(p.damping));
  if (!p.gravity.empty() && static_cast<int>(p.gravity.size()) != dim)
    throw InvalidArgument("gravity: expected " + std::to_string(dim) + " components");
  bool any_gravity = false;
  for (Scalar g : p.gravity) {
    if (!std::isfinite(g)) throw InvalidArgument("gravity: expected finite components");
    any_gravity = any_gravity || g != 0;
  }
  if (!any_gravity) parameters.gravity.clear();

  Model m;
  m.dim = dim;
  m.vertex_count = vertex_count;
  m.element_count = element_count;
  m.rest.assign(rest, rest + vertex_count * dim);
  m.elements.assign(elements, elements + element_count * (dim + 1));
  for (Index s = 0; s < element_count * (dim + 1); ++s)
    if (elements[s] < 0 || elements[s] >= vertex_count)
      throw InvalidArgument("elements: element " + std::to_string(s / (dim + 1)) +
                            " refers to vertex " + std::to_string(elements[s]) +
                            ", outside [0, " + std::to_string(vertex_count) + ")");
  check_duplicates(m.elements, element_count, dim + 1);
  if (dim == 2) build_rest_shape<2>(m);
  else build_rest_shape<3>(m);

  m.mu.resize(element_count);
  m.lam.resize(element_count);
  const bool uniform_E = p.youngs_modulus.size() == 1, uniform_nu = p.poisson_ratio.size() == 1;
  for (Index e = 0; e < element_count; ++e) {
    const Scalar E = p.youngs_modulus[uniform_E ? 0 : e], nu = p.poisson_ratio[uniform_nu ? 0 : e];
    lame(E, nu, m.mu[e], m.lam[e]);
    // The element's stiffness scale (2 mu + |lam|) V |Dm^-1|_F^2 [N/m] must be a float64.
    const Scalar k = (2 * m.mu[e] + std::abs(m.lam[e])) * m.volume[e] *
                     Eigen::Map<const Eigen::Matrix<Scalar, Eigen::Dynamic, 1>>(
                         m.Dm_inv.data() + e * dim * dim, dim * dim).squaredNorm();
    if (!std::isfinite(m.lam[e]) || !std::isfinite(k))
      throw InvalidArgument("youngs_modulus, poisson_ratio: the stiffness of element " + std::to_string(e) +
                            " overflows float64 (E = " + format_real(E) + ", lam = " + format_real(m.lam[e]) +
                            "); choose other units");
  }

  // Lumped masses: each element gives rho V / (d + 1) to each of its vertices.
  m.mass.assign(vertex_count, 0);
  for (Index e = 0; e < element_count; ++e)
    for (int a = 0; a <= dim; ++a)
      m.mass[m.elements[e * (dim + 1) + a]] += p.density * m.volume[e] / (dim + 1);
  for (Index i = 0; i < vertex_count; ++i)
    if (!std::isfinite(m.mass[i]))
      throw InvalidArgument("density: the mass of vertex " + std::to_string(i) + " overflows float64 (density " +
                            format_real(p.density) + "); choose other units");
  for (Index i = 0; i < vertex_count; ++i)
    if (m.mass[i] == 0)
      throw InvalidArgument("vertices: vertex " + std::to_string(i) +
                            " belongs to no element (it would have no mass)");

  m.fixed = vertex_flags(fixed, fixed_count, vertex_count, "fixed");
  for (Index i = 0; i < vertex_count; ++i) m.fixed_count += m.fixed[i];
  m.parameters = std::move(parameters);
  return m;
}

State initial_state(const Model& model) {
  State s;
  s.x = model.rest;
  s.v.assign(model.rest.size(), 0);
  return s;
}

}  // namespace kinema::fem
