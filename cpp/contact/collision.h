// Collision queries on the model's collision mesh at given positions: the active constraint set
// of IPC (every point-triangle and edge-edge pair closer than dhat, each reduced to the formula
// of its closest-point region, Li et al. 2020 sec. 4). Pairs are not merged when two reduce to
// the same vertices (a vertex near an edge seen from both of its triangles): each term is the
// exact distance of its own pair, continuous across region switches, so the barrier sum is
// continuous, where merging makes terms appear with a non-zero value at region boundaries.
// Also: the barrier terms of the active pairs (barrier.h, with the edge-edge mollifier), the
// largest safe step along a displacement (ACCD over the pairs whose swept boxes overlap), and
// exact checks (minimum distance, edge-triangle intersections) for validation. Broad phase:
// geometry/bvh.h over the faces and the edges, kept and refit between queries (BroadPhase).
#pragma once

#include <array>
#include <string>
#include <vector>

#include "contact/ccd.h"
#include "contact/model.h"
#include "geometry/bvh.h"

namespace kinema::contact {

// One active pair: vertices in formula order (unused slots -1), or a vertex against a plane.
struct Constraint {
  PairKind kind;
  std::array<Index, 4> v;
  // >= 0: vertex v[0] against model.planes[plane] (kind PP unused); v[1] is the plane's driven
  // vertex when it moves (the term then reads both), else -1.
  Index plane = -1;
  Scalar d = 0;      // squared distance at the positions it was found at
  // Edge-edge pairs, whatever formula they reduce to: the two edges (a0, a1, b0, b1) and the
  // mollifier threshold eps_x > 0 (barrier.h); other pairs: -1 and 0.
  std::array<Index, 4> edges{{-1, -1, -1, -1}};
  Scalar eps_x = 0;

  // The vertices the barrier term reads; its gradient and Hessian are over these, 3 entries each.
  int stencil_size() const { return eps_x > 0 ? 4 : plane >= 0 ? (v[1] >= 0 ? 2 : 1) : vertex_count(kind); }
  const Index* stencil() const { return eps_x > 0 ? edges.data() : v.data(); }
};

// Pairs of non-adjacent primitives whose boxes meet: (surface point, face) and (edge, edge)
// with the lower edge first; pairs made only of fixed vertices are left out.
struct Candidates {
  std::vector<std::array<Index, 2>> point_face, edge_edge;
};

// The broad phase: BVHs over the boxes of the faces and the edges, kept between queries. Built
// with the binned SAH on first use, then refit to each query's boxes (O(n)); rebuilt when the
// refit tree's area ratio (bvh.h) exceeds twice its build's. The trees only group primitives,
// so a query's result is the same whatever their state. A Solver owns one; not thread-safe.
class BroadPhase {
 public:
  // Pairs whose boxes, swept over x -> x + dx (dx may be null) and grown by r, meet, in a
  // deterministic order (the same for any thread count).
  void find(const Model& model, const Scalar* x, const Scalar* dx, Scalar r, Candidates& out);
  // Candidate storage kept between one-shot queries (find_constraints, max_safe_step), so that
  // its vectors are not grown from empty on every query.
  Candidates& scratch() { return scratch_candidates_; }

 private:
  struct Tree {
    geometry::Bvh bvh;
    std::vector<Index> ids;        // primitive k of the tree is point / face / edge ids[k]
    std::vector<Index> prims;      // its vertices, 1, 3 or 2 per primitive
    std::vector<Scalar> lo, hi;    // its current boxes
    Scalar built_ratio = 0;
    // A tree of static collider primitives (fixed, not driven vertices) keeps its boxes while
    // its vertices stay where they were at its last update (positions kept), do not move in
    // the query and r is the same: the colliders' boxes are not recomputed on every query.
    bool still = false;
    std::vector<Index> verts;      // its vertices, once each (still trees)
    std::vector<Scalar> kept;      // their positions at the last update
    Scalar r = -1;                 // the growth of the last update
  };
  void update(Tree& tree, int k, const Scalar* x, const Scalar* dx, Scalar r);

  Tree moving_points_, fixed_points_, moving_faces_, fixed_faces_, moving_edges_, fixed_edges_;
  // Sort scratch of the point-face and of the edge-edge pairs (found by two threads).
  std::vector<Index> bucket_start_, edge_bucket_start_;
  std::vector<std::array<Index, 2>> scratch_, edge_scratch_;
  Candidates scratch_candidates_;
  bool ready_ = false;
};

// Every pair of non-adjacent primitives with squared distance < dhat2 at x (planes included),
// in a deterministic order. Pairs made only of fixed vertices are skipped.
std::vector<Constraint> find_constraints(const Model& model, const Scalar* x, Scalar dhat2);
std::vector<Constraint> find_constraints(const Model& model, BroadPhase& broad, const Scalar* x, Scalar dhat2);
// The same from candidates whose boxes, grown by at least dhat, contain x (narrow phase only).
// prefilter: first drop the pairs whose boxes at x, one grown by dhat, do not meet (false when
// the candidates were found for exactly those boxes: every pair passes).
std::vector<Constraint> find_constraints(const Model& model, const Candidates& candidates, const Scalar* x,
                                         Scalar dhat2, bool prefilter = true);

// Barrier terms of many constraints at once (in parallel, in the constraints' order): the sum of
// the energies, and per constraint its gradient (g) and Hessian (H) over c.stencil() when the
// vectors are given (H projected when `project`).
Scalar evaluate_barriers(const Model& model, const std::vector<Constraint>& constraints, const Scalar* x,
                         Scalar dhat2, std::vector<Vec<12>>* g, std::vector<Mat<12>>* H, Projection projection);

// Barrier term m(s) b(d) of a constraint at x (barrier.h; m = 1 but for edge pairs) and, when g
// is given, its gradient over c.stencil(); when H is given too, its Hessian, projected to the
// positive semidefinite by `projection`.
Scalar constraint_barrier(const Model& model, const Constraint& c, const Scalar* x, Scalar dhat2, Vec<12>* g,
                          Mat<12>* H, Projection projection);

// Largest t in [0, 1] such that moving x -> x + t dx keeps every pair apart (conservative).
Scalar max_safe_step(const Model& model, const Scalar* x, const Scalar* dx, const CcdOptions& options);
Scalar max_safe_step(const Model& model, BroadPhase& broad, const Scalar* x, const Scalar* dx,
                     const CcdOptions& options);
// The same over candidates whose boxes were swept over (at least) x -> x + dx.
Scalar max_safe_step(const Model& model, const Candidates& candidates, const Scalar* x, const Scalar* dx,
                     const CcdOptions& options);

// Smallest exact distance [m] between non-adjacent primitives (point-triangle, edge-edge) and
// from vertices to planes, over the pairs closer than `radius`; +inf when none is.
Scalar min_distance(const Model& model, const Scalar* x, Scalar radius);

// Non-adjacent edge-triangle pairs that intersect at x, and vertices on the wrong side of a
// plane, described for an error message (at most `limit` entries).
std::vector<std::string> find_intersections(const Model& model, const Scalar* x, Index limit);

}  // namespace kinema::contact
