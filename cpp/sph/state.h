// Everything a km.sph liquid evolves, including what a step reads from earlier steps (the
// Verlet neighbour lists, DFSPH's warm-start stiffnesses, the last dt, the reordering
// schedule): a copy of a State resumes bit for bit. The neighbour lists are shared, immutable
// once built, so copying a State (a checkpoint, a step's rollback copy) copies a pointer.
#pragma once

#include <memory>
#include <vector>

#include "core/types.h"
#include "particles/neighbor_lists.h"

namespace kinema::sph {

// Verlet lists (Verlet 1967) of radius h (1 + skin) at the positions x they were built at:
// every pair closer than h is in them as long as no particle has moved skin h / 2 since.
struct VerletLists {
  std::vector<Scalar> x;  // (n, d) positions at the build [m]
  Scalar skin = 0;        // fraction of h (0: the lists are exact at x and live one step)
  NeighborLists fluid;    // fluid neighbours of each particle
  NeighborLists boundary; // boundary samples near each particle
};

// Arrays are never reallocated by a step, so numpy views of them stay valid. Reordering for
// locality permutes the rows in place: `ids` holds each row's original index.
struct State {
  State(int dim, Index n);
  int dim;
  Index n;
  std::vector<Scalar> x;         // (n, d) positions [m]
  std::vector<Scalar> v;         // (n, d) velocities [m/s]
  std::vector<Scalar> density;   // (n,) [kg/m^d], at the start of the last step
  std::vector<Scalar> pressure;  // (n,) [Pa], of the last step
  std::vector<Index> ids;        // (n,) original index of each row
  Scalar time = 0;               // [s]
  Index steps = 0;
  // What the next step reads from the earlier ones.
  Scalar last_dt = 0;                          // the previous step's dt [s]; 0: none yet (DFSPH solves cold)
  Index reorder_step = -1;                     // step of the last Morton reordering (-1: none yet)
  // DFSPH's stiffnesses k_i = kappa_i / rho_i (the pressure p_i / rho_i^2 whose force the
  // solve applied), (n,) each; empty for WCSPH.
  std::vector<Scalar> kappa_density;           // of the constant-density solve
  std::vector<Scalar> kappa_divergence;        // of the divergence-free solve
  std::shared_ptr<const VerletLists> lists;    // null: the next step searches afresh
};

}  // namespace kinema::sph
