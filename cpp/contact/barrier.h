// The IPC log barrier and the smoothed Coulomb friction of Li et al., "Incremental Potential
// Contact", ACM TOG 39(4), 2020 (eq. 6 and section 5), on squared distances d and the squared
// activation distance dhat2 = dhat^2:
//   b(d) = -(d - dhat2)^2 ln(d / dhat2) for 0 < d < dhat2, 0 beyond     (C^2 at dhat2, +inf at 0)
// Friction of one contact, lagged normal force lambda and sliding displacement u (2D, in the
// contact's tangent plane) over a step h, with the relative tangential speed y = |u| / h:
//   D(u) = mu lambda h f0(y),  f0' = f1,  f1(y) = 2 y / eps_v - y^2 / eps_v^2 for y < eps_v, else 1
// so that -dD/du = -mu lambda f1(y) u / |u| is Coulomb's force smoothed below the speed eps_v
// (eq. 14-16). Its Hessian is positive semidefinite as written (eigenvalues mu lambda / h times
// f1'(y) along u and f1(y) / y across it), so no projection is needed.
#pragma once

#include <cmath>

#include "core/types.h"

namespace kinema::contact {

inline Scalar barrier(Scalar d, Scalar dhat2) {
  if (d >= dhat2) return 0;
  return -(d - dhat2) * (d - dhat2) * std::log(d / dhat2);
}

inline Scalar barrier_first(Scalar d, Scalar dhat2) {
  if (d >= dhat2) return 0;
  return (dhat2 - d) * (2 * std::log(d / dhat2) - dhat2 / d + 1);
}

inline Scalar barrier_second(Scalar d, Scalar dhat2) {
  if (d >= dhat2) return 0;
  const Scalar r = dhat2 / d;
  return -2 * std::log(d / dhat2) + r * r + 2 * r - 3;
}

// f0 with f0(0) = eps_v / 3 so that it is continuous with f0(y) = y at eps_v.
inline Scalar friction_f0(Scalar y, Scalar eps_v) {
  if (y >= eps_v) return y;
  return -y * y * y / (3 * eps_v * eps_v) + y * y / eps_v + eps_v / 3;
}

// f1(y) / y, finite at y = 0.
inline Scalar friction_f1_over_y(Scalar y, Scalar eps_v) {
  if (y >= eps_v) return 1 / y;
  return 2 / eps_v - y / (eps_v * eps_v);
}

// f1'(y), the stiffness along the sliding direction.
inline Scalar friction_f1_derivative(Scalar y, Scalar eps_v) {
  if (y >= eps_v) return 0;
  return 2 / eps_v - 2 * y / (eps_v * eps_v);
}

}  // namespace kinema::contact
