// Collision queries on the model's collision mesh at given positions: the active constraint set
// of IPC (every point-triangle and edge-edge pair closer than dhat, each reduced to the formula
// of its closest-point region, Li et al. 2020 sec. 4). Pairs are not merged when two reduce to
// the same vertices (a vertex near an edge seen from both of its triangles): each term is the
// exact distance of its own pair, continuous across region switches, so the barrier sum is
// continuous, where merging makes terms appear with a non-zero value at region boundaries.
// Also: the largest safe step along a displacement (ACCD over the pairs whose swept boxes
// overlap), and exact checks (minimum distance, edge-triangle
// intersections) for validation. Broad phase: geometry/bvh.h over the faces and the edges.
#pragma once

#include <array>
#include <string>
#include <vector>

#include "contact/ccd.h"
#include "contact/model.h"

namespace kinema::contact {

// One active pair: vertices in formula order (unused slots -1), or a vertex against a plane.
struct Constraint {
  PairKind kind;
  std::array<Index, 4> v;
  Index plane = -1;  // >= 0: vertex v[0] against model.planes[plane] (kind PP unused)
  Scalar d = 0;      // squared distance at the positions it was found at
};

// Every pair of non-adjacent primitives with squared distance < dhat2 at x (planes included),
// in a deterministic order. Pairs made only of fixed vertices are skipped.
std::vector<Constraint> find_constraints(const Model& model, const Scalar* x, Scalar dhat2);

// Squared distance of a constraint at x, and its gradient/Hessian over its vertices.
Scalar constraint_distance(const Model& model, const Constraint& c, const Scalar* x);
void constraint_derivatives(const Model& model, const Constraint& c, const Scalar* x, Vec<12>& g, Mat<12>& H);

// Largest t in [0, 1] such that moving x -> x + t dx keeps every pair apart (conservative).
Scalar max_safe_step(const Model& model, const Scalar* x, const Scalar* dx, const CcdOptions& options);

// Smallest exact distance [m] between non-adjacent primitives (point-triangle, edge-edge) and
// from vertices to planes, over the pairs closer than `radius`; +inf when none is.
Scalar min_distance(const Model& model, const Scalar* x, Scalar radius);

// Non-adjacent edge-triangle pairs that intersect at x, and vertices on the wrong side of a
// plane, described for an error message (at most `limit` entries).
std::vector<std::string> find_intersections(const Model& model, const Scalar* x, Index limit);

}  // namespace kinema::contact
