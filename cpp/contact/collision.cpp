// Broad phase on BVHs of face and edge boxes, narrow phase by the closest-point regions of
// distance.h, ACCD for the safe step.
#include "contact/collision.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include "geometry/bvh.h"

namespace kinema::contact {

namespace {

Vec3 at(const Scalar* x, Index i) { return Eigen::Map<const Vec3>(x + 3 * i); }

// Boxes of the primitives (k vertices each) at x, swept to x + dx when dx is given, grown by r.
geometry::Bvh primitive_bvh(const std::vector<Index>& prims, int k, const Scalar* x, const Scalar* dx,
                            Scalar r) {
  const size_t count = prims.size() / static_cast<size_t>(k);
  std::vector<Scalar> lo(3 * count), hi(3 * count);
  for (size_t p = 0; p < count; ++p) {
    Vec3 l = Vec3::Constant(std::numeric_limits<Scalar>::infinity()), h = -l;
    for (int a = 0; a < k; ++a) {
      const Index v = prims[p * static_cast<size_t>(k) + static_cast<size_t>(a)];
      const Vec3 y = at(x, v);
      l = l.cwiseMin(y);
      h = h.cwiseMax(y);
      if (dx) {
        const Vec3 z = y + at(dx, v);
        l = l.cwiseMin(z);
        h = h.cwiseMax(z);
      }
    }
    for (int c = 0; c < 3; ++c) {
      lo[3 * p + c] = l[c] - r;
      hi[3 * p + c] = h[c] + r;
    }
  }
  return geometry::Bvh(lo, hi);
}

void point_box(const Scalar* x, const Scalar* dx, Index v, Scalar r, Scalar lo[3], Scalar hi[3]) {
  for (int c = 0; c < 3; ++c) {
    Scalar a = x[3 * v + c], b = a;
    if (dx) b += dx[3 * v + c];
    lo[c] = std::min(a, b) - r;
    hi[c] = std::max(a, b) + r;
  }
}

void edge_box(const Scalar* x, const Scalar* dx, Index i, Index j, Scalar r, Scalar lo[3], Scalar hi[3]) {
  Scalar l1[3], h1[3], l2[3], h2[3];
  point_box(x, dx, i, r, l1, h1);
  point_box(x, dx, j, r, l2, h2);
  for (int c = 0; c < 3; ++c) {
    lo[c] = std::min(l1[c], l2[c]);
    hi[c] = std::max(h1[c], h2[c]);
  }
}

// Whether the box of the vertices `vs` (swept by dx when given, grown by r) meets [lo, hi]:
// the BVH reports whole leaves, this keeps the narrow phase to the pairs whose boxes meet.
bool boxes_meet(const Scalar* x, const Scalar* dx, std::initializer_list<Index> vs, Scalar r, const Scalar lo[3],
                const Scalar hi[3]) {
  for (int c = 0; c < 3; ++c) {
    Scalar l = std::numeric_limits<Scalar>::infinity(), h = -l;
    for (Index v : vs) {
      const Scalar a = x[3 * v + c], b = dx ? a + dx[3 * v + c] : a;
      l = std::min(l, std::min(a, b));
      h = std::max(h, std::max(a, b));
    }
    if (l - r > hi[c] || h + r < lo[c]) return false;
  }
  return true;
}

bool all_fixed(const Model& model, std::initializer_list<Index> vs) {
  for (Index v : vs)
    if (!model.fixed[static_cast<size_t>(v)]) return false;
  return true;
}

// Calls pt(p, face) for every surface point and face whose boxes meet (p not in the face), and
// ee(e, f) once for every pair of edges whose boxes meet and that share no vertex; pairs made
// only of fixed vertices (obstacle against obstacle) are never visited: moving points query
// every face and fixed points only the faces that move, moving edges query every edge.
template <class PT, class EE>
void candidate_pairs(const Model& model, const Scalar* x, const Scalar* dx, Scalar r, PT&& pt, EE&& ee) {
  const auto& F = model.faces;
  const auto& E = model.edges;
  auto moving = [&](Index v) { return !model.fixed[static_cast<size_t>(v)]; };
  if (!F.empty()) {
    const geometry::Bvh faces = primitive_bvh(F, 3, x, dx, r);
    std::vector<Index> moving_faces, moving_face_ids;
    bool any_fixed_point = false;
    for (Index p : model.points) any_fixed_point |= !moving(p);
    if (any_fixed_point) {
      for (Index f = 0; f < static_cast<Index>(F.size() / 3); ++f)
        if (moving(F[3 * f]) || moving(F[3 * f + 1]) || moving(F[3 * f + 2])) {
          moving_faces.insert(moving_faces.end(), &F[3 * f], &F[3 * f] + 3);
          moving_face_ids.push_back(f);
        }
    }
    const geometry::Bvh moving_bvh = primitive_bvh(moving_faces, 3, x, dx, r);
    for (Index p : model.points) {
      Scalar lo[3], hi[3];
      point_box(x, dx, p, 0, lo, hi);
      auto visit = [&](Index f) {
        const Index a = F[3 * f], b = F[3 * f + 1], c = F[3 * f + 2];
        if (p == a || p == b || p == c) return;
        if (!boxes_meet(x, dx, {a, b, c}, r, lo, hi)) return;
        pt(p, f);
      };
      if (moving(p))
        faces.query(lo, hi, visit);
      else
        moving_bvh.query(lo, hi, [&](Index k) { visit(moving_face_ids[static_cast<size_t>(k)]); });
    }
  }
  if (!E.empty()) {
    const geometry::Bvh edges = primitive_bvh(E, 2, x, dx, r);
    const Index edge_count = static_cast<Index>(E.size() / 2);
    for (Index e = 0; e < edge_count; ++e) {
      if (!moving(E[2 * e]) && !moving(E[2 * e + 1])) continue;
      Scalar lo[3], hi[3];
      edge_box(x, dx, E[2 * e], E[2 * e + 1], 0, lo, hi);
      edges.query(lo, hi, [&](Index f) {
        const Index a0 = E[2 * e], a1 = E[2 * e + 1], b0 = E[2 * f], b1 = E[2 * f + 1];
        const bool f_moves = moving(b0) || moving(b1);
        if (f_moves && f <= e) return;  // a pair of moving edges is visited from the lower one
        if (a0 == b0 || a0 == b1 || a1 == b0 || a1 == b1) return;
        if (!boxes_meet(x, dx, {b0, b1}, r, lo, hi)) return;
        ee(e, f);
      });
    }
  }
}

// The reduced constraint of a pair given by its four vertices (point-triangle: p, t0, t1, t2;
// edge-edge: a0, a1, b0, b1), vertices in a canonical order.
Constraint reduce(const Reduced& r, const Index* ids) {
  Constraint c;
  c.kind = r.kind;
  c.v = {-1, -1, -1, -1};
  for (int k = 0; k < vertex_count(r.kind); ++k) c.v[static_cast<size_t>(k)] = ids[r.slot[k]];
  switch (r.kind) {
    case PairKind::PP:
      if (c.v[0] > c.v[1]) std::swap(c.v[0], c.v[1]);
      break;
    case PairKind::PE:
      if (c.v[1] > c.v[2]) std::swap(c.v[1], c.v[2]);
      break;
    case PairKind::PT:
      std::sort(c.v.begin() + 1, c.v.end());
      break;
    case PairKind::EE:
      if (c.v[0] > c.v[1]) std::swap(c.v[0], c.v[1]);
      if (c.v[2] > c.v[3]) std::swap(c.v[2], c.v[3]);
      if (c.v[0] > c.v[2] || (c.v[0] == c.v[2] && c.v[1] > c.v[3])) {
        std::swap(c.v[0], c.v[2]);
        std::swap(c.v[1], c.v[3]);
      }
      break;
  }
  return c;
}

// Sign of the orientation of (a, b, c, d): +1, -1, or 0 when the determinant is within
// rounding of zero (relative to the product of the edge lengths), so that nearly coplanar
// configurations are never taken for a crossing. A touching pair is caught by the distance
// checks instead.
int orient(const Vec3& a, const Vec3& b, const Vec3& c, const Vec3& d) {
  const Vec3 u = b - a, v = c - a, w = d - a;
  const Scalar det = u.cross(v).dot(w);
  const Scalar scale = u.norm() * v.norm() * w.norm();
  if (std::abs(det) <= 1e-12 * scale) return 0;
  return det > 0 ? 1 : -1;
}

}  // namespace

std::vector<Constraint> find_constraints(const Model& model, const Scalar* x, Scalar dhat2) {
  std::vector<Constraint> out;
  const Scalar dhat = std::sqrt(dhat2);
  const auto& F = model.faces;
  const auto& E = model.edges;
  // Reduces a pair given by its four vertices to its closest-point formula; keeps it if close.
  auto consider = [&](const Index ids[4], bool edge_edge) {
    if (all_fixed(model, {ids[0], ids[1], ids[2], ids[3]})) return;
    const Vec3 y[4] = {at(x, ids[0]), at(x, ids[1]), at(x, ids[2]), at(x, ids[3])};
    const Reduced r = edge_edge ? edge_edge_region(y[0], y[1], y[2], y[3]) : point_triangle_region(y[0], y[1], y[2], y[3]);
    Vec3 v[4];
    for (int k = 0; k < vertex_count(r.kind); ++k) v[k] = y[r.slot[k]];
    const Scalar d = reduced_distance(r.kind, v);
    if (d >= dhat2) return;
    Constraint c = reduce(r, ids);
    c.d = d;
    out.push_back(c);
  };
  candidate_pairs(
      model, x, nullptr, dhat,
      [&](Index p, Index f) {
        const Index ids[4] = {p, F[3 * f], F[3 * f + 1], F[3 * f + 2]};
        consider(ids, false);
      },
      [&](Index e, Index f) {
        const Index ids[4] = {E[2 * e], E[2 * e + 1], E[2 * f], E[2 * f + 1]};
        consider(ids, true);
      });
  // Vertices against planes: every dynamic vertex (a solid's interior vertices cannot reach a
  // plane before its surface, so checking them costs little and needs no surface lookup).
  for (size_t pl = 0; pl < model.planes.size(); ++pl) {
    const Plane& plane = model.planes[pl];
    for (Index v : model.points) {
      if (model.fixed[static_cast<size_t>(v)]) continue;
      const Scalar s = plane.normal.dot(at(x, v) - plane.point);
      if (s * s >= dhat2 || s < 0) continue;
      Constraint c;
      c.kind = PairKind::PP;
      c.v = {v, -1, -1, -1};
      c.plane = static_cast<Index>(pl);
      c.d = s * s;
      out.push_back(c);
    }
  }
  return out;
}

Scalar constraint_distance(const Model& model, const Constraint& c, const Scalar* x) {
  if (c.plane >= 0) {
    const Plane& plane = model.planes[static_cast<size_t>(c.plane)];
    const Scalar s = plane.normal.dot(at(x, c.v[0]) - plane.point);
    return s * s;
  }
  Vec3 v[4];
  for (int k = 0; k < vertex_count(c.kind); ++k) v[k] = at(x, c.v[static_cast<size_t>(k)]);
  return reduced_distance(c.kind, v);
}

void constraint_derivatives(const Model& model, const Constraint& c, const Scalar* x, Vec<12>& g, Mat<12>& H) {
  if (c.plane >= 0) {
    const Plane& plane = model.planes[static_cast<size_t>(c.plane)];
    const Scalar s = plane.normal.dot(at(x, c.v[0]) - plane.point);
    g.setZero();
    H.setZero();
    g.head<3>() = 2 * s * plane.normal;
    H.topLeftCorner<3, 3>() = 2 * plane.normal * plane.normal.transpose();
    return;
  }
  Vec3 v[4];
  for (int k = 0; k < vertex_count(c.kind); ++k) v[k] = at(x, c.v[static_cast<size_t>(k)]);
  reduced_derivatives(c.kind, v, g, H);
}

Scalar max_safe_step(const Model& model, const Scalar* x, const Scalar* dx, const CcdOptions& options) {
  Scalar t = 1;
  const auto& F = model.faces;
  const auto& E = model.edges;
  candidate_pairs(
      model, x, dx, 0,
      [&](Index p, Index f) {
        const Index a = F[3 * f], b = F[3 * f + 1], c = F[3 * f + 2];
        t = std::min(t, point_triangle_ccd(at(x, p), at(x, a), at(x, b), at(x, c), at(dx, p), at(dx, a),
                                           at(dx, b), at(dx, c), t, options));
      },
      [&](Index e, Index f) {
        const Index a0 = E[2 * e], a1 = E[2 * e + 1], b0 = E[2 * f], b1 = E[2 * f + 1];
        t = std::min(t, edge_edge_ccd(at(x, a0), at(x, a1), at(x, b0), at(x, b1), at(dx, a0), at(dx, a1),
                                      at(dx, b0), at(dx, b1), t, options));
      });
  for (const Plane& plane : model.planes)
    for (Index v : model.points) {
      if (model.fixed[static_cast<size_t>(v)]) continue;
      t = std::min(t, point_plane_ccd(plane.normal.dot(at(x, v) - plane.point), plane.normal.dot(at(dx, v)), t,
                                      options));
    }
  return t;
}

Scalar min_distance(const Model& model, const Scalar* x, Scalar radius) {
  Scalar best = std::numeric_limits<Scalar>::infinity();
  const Scalar r2 = radius * radius;
  const auto& F = model.faces;
  const auto& E = model.edges;
  candidate_pairs(
      model, x, nullptr, radius,
      [&](Index p, Index f) {
        if (all_fixed(model, {p, F[3 * f], F[3 * f + 1], F[3 * f + 2]})) return;
        const Scalar d = point_triangle_distance(at(x, p), at(x, F[3 * f]), at(x, F[3 * f + 1]), at(x, F[3 * f + 2]));
        if (d < r2) best = std::min(best, d);
      },
      [&](Index e, Index f) {
        if (all_fixed(model, {E[2 * e], E[2 * e + 1], E[2 * f], E[2 * f + 1]})) return;
        const Scalar d = edge_edge_distance(at(x, E[2 * e]), at(x, E[2 * e + 1]), at(x, E[2 * f]), at(x, E[2 * f + 1]));
        if (d < r2) best = std::min(best, d);
      });
  best = std::sqrt(best);
  for (const Plane& plane : model.planes)
    for (Index v : model.points) {
      if (model.fixed[static_cast<size_t>(v)]) continue;
      const Scalar s = plane.normal.dot(at(x, v) - plane.point);
      if (s < radius) best = std::min(best, s);
    }
  return best;
}

std::vector<std::string> find_intersections(const Model& model, const Scalar* x, Index limit) {
  std::vector<std::string> out;
  const auto& F = model.faces;
  const auto& E = model.edges;
  auto full = [&] { return static_cast<Index>(out.size()) >= limit; };
  if (!F.empty() && !E.empty()) {
    const geometry::Bvh faces = primitive_bvh(F, 3, x, nullptr, 0);
    const Index edge_count = static_cast<Index>(E.size() / 2);
    for (Index e = 0; e < edge_count && !full(); ++e) {
      Scalar lo[3], hi[3];
      const Index a = E[2 * e], b = E[2 * e + 1];
      edge_box(x, nullptr, a, b, 0, lo, hi);
      faces.query(lo, hi, [&](Index f) {
        if (full()) return;
        const Index t0 = F[3 * f], t1 = F[3 * f + 1], t2 = F[3 * f + 2];
        if (a == t0 || a == t1 || a == t2 || b == t0 || b == t1 || b == t2) return;
        if (all_fixed(model, {a, b, t0, t1, t2})) return;
        const Vec3 pa = at(x, a), pb = at(x, b), q0 = at(x, t0), q1 = at(x, t1), q2 = at(x, t2);
        // A strict crossing: the endpoints strictly on both sides of the plane, and the
        // segment strictly inside the three edge planes.
        const int sa = orient(q0, q1, q2, pa), sb = orient(q0, q1, q2, pb);
        if (sa == 0 || sb == 0 || sa == sb) return;
        const int w0 = orient(pa, pb, q0, q1), w1 = orient(pa, pb, q1, q2), w2 = orient(pa, pb, q2, q0);
        if (w0 == 0 || w0 != w1 || w1 != w2) return;
        out.push_back("edge (" + std::to_string(a) + ", " + std::to_string(b) + ") crosses triangle (" +
                      std::to_string(t0) + ", " + std::to_string(t1) + ", " + std::to_string(t2) + ")");
      });
    }
  }
  for (size_t pl = 0; pl < model.planes.size() && !full(); ++pl)
    for (Index v = 0; v < model.vertex_count && !full(); ++v) {
      if (model.fixed[static_cast<size_t>(v)]) continue;
      const Scalar s = model.planes[pl].normal.dot(at(x, v) - model.planes[pl].point);
      if (!(s > 0))
        out.push_back("vertex " + std::to_string(v) + " lies on or behind plane " + std::to_string(pl) +
                      " (signed distance " + format_real(s) + ")");
    }
  return out;
}

}  // namespace kinema::contact
