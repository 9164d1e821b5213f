// Reverse-mode gradients of one WCSPH step (Solver::step_adjoint in adjoint.cpp): the
// vector-Jacobian product of (x, v, forces, viscosity) -> (x', v') for the step of solver.cpp,
//   rho_i = m W(0) + sum_j m W_ij + sum_b psi_b W_ib,  P_i = p(rho_i) / rho_i^2,
//   a_i = g + f_i / m + sum_j 2 (d + 2) nu (m / rho_j) (v_ij . x_ij) / (|x_ij|^2 + 0.01 h^2) grad W_ij
//         - m sum_j (P_i + P_j) grad W_ij - sum_b psi_b (P_i + P_b) grad W_ib,
//   P_b = p(rho_b) / rho_b^2, rho_b = wall_rho_b + sum_i m W_ib on the walls that carry
//   pressure (Model::wall_begin on; P_b = 0 on the others),
//   v' = v + dt a,  x' = x + dt v'  (then the domain clamp),
// Becker and Teschner 2007 (eqs. 5-6), Akinci et al. 2012 (boundary), Koschier et al. 2019
// (eq. 33, viscosity).
#pragma once

#include "core/types.h"

namespace kinema::sph {

// dL/d(parameters) of one step.
struct ParamsAdjoint {
  Scalar viscosity = 0;  // dL/d(nu) [per m^2/s]
};

}  // namespace kinema::sph
