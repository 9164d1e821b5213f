// Broad phase on BVHs of face and edge boxes, narrow phase by the closest-point regions of
// distance.h, ACCD for the safe step.
#include "contact/collision.h"


#include <algorithm>
#include <cmath>
#include <limits>

#include "contact/barrier.h"
#include "core/parallel.h"
#include "geometry/bvh.h"

namespace kinema::contact {

namespace {

Vec3 at(const Scalar* x, Index i) { return Eigen::Map<const Vec3>(x + 3 * i); }

// Box of the primitive (K vertices at prim) at x, swept to x + dx when Swept, grown by r.
template <int K, bool Swept>
inline void primitive_box(const Index* prim, const Scalar* x, const Scalar* dx, Scalar r, Scalar* lo, Scalar* hi) {
  const Scalar* y[K];
  const Scalar* z[K];
  for (int a = 0; a < K; ++a) {
    y[a] = x + 3 * prim[a];
    if constexpr (Swept) z[a] = dx + 3 * prim[a];
  }
  for (int c = 0; c < 3; ++c) {
    Scalar l = y[0][c], h = l;
    if constexpr (Swept) {
      const Scalar w = l + z[0][c];
      l = std::min(l, w);
      h = std::max(h, w);
    }
    for (int a = 1; a < K; ++a) {
      const Scalar v = y[a][c];
      l = std::min(l, v);
      h = std::max(h, v);
      if constexpr (Swept) {
        const Scalar w = v + z[a][c];
        l = std::min(l, w);
        h = std::max(h, w);
      }
    }
    lo[c] = l - r;
    hi[c] = h + r;
  }
}

// The same for k = 1, 2 or 3 vertices, swept when dx is given.
void primitive_box(const Index* prim, int k, const Scalar* x, const Scalar* dx, Scalar r, Scalar* lo, Scalar* hi) {
  if (dx) {
    if (k == 1) return primitive_box<1, true>(prim, x, dx, r, lo, hi);
    if (k == 2) return primitive_box<2, true>(prim, x, dx, r, lo, hi);
    return primitive_box<3, true>(prim, x, dx, r, lo, hi);
  }
  if (k == 1) return primitive_box<1, false>(prim, x, dx, r, lo, hi);
  if (k == 2) return primitive_box<2, false>(prim, x, dx, r, lo, hi);
  return primitive_box<3, false>(prim, x, dx, r, lo, hi);
}

geometry::Bvh primitive_bvh(const std::vector<Index>& prims, int k, const Scalar* x, const Scalar* dx, Scalar r) {
  const size_t count = prims.size() / static_cast<size_t>(k);
  std::vector<Scalar> lo(3 * count), hi(3 * count);
  for (size_t p = 0; p < count; ++p) primitive_box(&prims[p * static_cast<size_t>(k)], k, x, dx, r, &lo[3 * p], &hi[3 * p]);
  return geometry::Bvh(lo, hi);
}

void edge_box(const Scalar* x, const Scalar* dx, Index i, Index j, Scalar r, Scalar lo[3], Scalar hi[3]) {
  const Index e[2] = {i, j};
  primitive_box(e, 2, x, dx, r, lo, hi);
}

bool overlap(const Scalar* lo, const Scalar* hi, const Scalar* lo2, const Scalar* hi2) {
  return lo[0] <= hi2[0] && lo2[0] <= hi[0] && lo[1] <= hi2[1] && lo2[1] <= hi[1] && lo[2] <= hi2[2] &&
         lo2[2] <= hi[2];
}

bool all_fixed(const Model& model, std::initializer_list<Index> vs) {
  for (Index v : vs)
    if (!model.fixed[static_cast<size_t>(v)]) return false;
  return true;
}

using Pairs = std::vector<std::array<Index, 2>>;

// out = the pairs body(i, part) appends for i = 0, 1, ..., n - 1, in that order: threads fill
// contiguous blocks of i (static schedule) and the blocks are joined in order, so the result
// is the serial one for any thread count.
template <class T, class Body>
void collect_in_order(Index n, std::vector<T>& out, Body&& body) {
  out.clear();
  const int threads = n > 256 ? num_threads() : 1;
  if (threads == 1) {
    for (Index i = 0; i < n; ++i) body(i, out);
    return;
  }
  std::vector<std::vector<T>> parts(static_cast<size_t>(threads));
#pragma omp parallel num_threads(threads)
  {
    std::vector<T>& part = parts[static_cast<size_t>(omp_get_thread_num())];
#pragma omp for schedule(static)
    for (Index i = 0; i < n; ++i) body(i, part);
  }
  for (const std::vector<T>& part : parts) out.insert(out.end(), part.begin(), part.end());
}

}  // namespace

// Leaves of up to 12 primitives (the Bvh's default, 4, suits ray walks): the pair descents
// test fewer node pairs and a leaf pair's primitives in contiguous memory; measured on the
// kernel bench's pile and cloth frames, BroadPhase::find took 15-20 % less time than with 4
// (8: 12-15 %, 16: 10-15 %).
constexpr int kLeafSize = 12;

void BroadPhase::update(Tree& tree, int k, const Scalar* x, const Scalar* dx, Scalar r) {
  const Index count = static_cast<Index>(tree.ids.size());
  if (tree.still) {
    bool same = r == tree.r && !tree.bvh.nodes().empty();
    for (size_t a = 0; same && a < tree.verts.size(); ++a)
      for (int c = 0; same && c < 3; ++c) {
        const size_t i = static_cast<size_t>(3 * tree.verts[a] + c);
        same = x[i] == tree.kept[3 * a + static_cast<size_t>(c)] && (!dx || dx[i] == 0);
      }
    if (same) return;
    tree.r = r;
    tree.kept.resize(3 * tree.verts.size());
    for (size_t a = 0; a < tree.verts.size(); ++a)
      for (int c = 0; c < 3; ++c) tree.kept[3 * a + static_cast<size_t>(c)] = x[static_cast<size_t>(3 * tree.verts[a] + c)];
  }
  tree.lo.resize(static_cast<size_t>(3 * count));
  tree.hi.resize(static_cast<size_t>(3 * count));
  auto boxes = [&](auto vertices, auto swept) {
    constexpr int K = decltype(vertices)::value;
    parallel_for(count, [&](Index p) {
      primitive_box<K, decltype(swept)::value>(&tree.prims[static_cast<size_t>(K * p)], x, dx, r,
                                                &tree.lo[static_cast<size_t>(3 * p)],
                                                &tree.hi[static_cast<size_t>(3 * p)]);
    });
  };
  using Yes = std::true_type;
  using No = std::false_type;
  if (k == 1) dx ? boxes(std::integral_constant<int, 1>{}, Yes{}) : boxes(std::integral_constant<int, 1>{}, No{});
  else if (k == 2) dx ? boxes(std::integral_constant<int, 2>{}, Yes{}) : boxes(std::integral_constant<int, 2>{}, No{});
  else dx ? boxes(std::integral_constant<int, 3>{}, Yes{}) : boxes(std::integral_constant<int, 3>{}, No{});
  if (count == 0) return;
  if (tree.bvh.nodes().empty()) {
    tree.bvh = geometry::Bvh(tree.lo, tree.hi, kLeafSize);
    tree.built_ratio = tree.bvh.area_ratio();
    return;
  }
  tree.bvh.refit(tree.lo, tree.hi);
  if (tree.bvh.area_ratio() > 2 * tree.built_ratio) {
    tree.bvh = geometry::Bvh(tree.lo, tree.hi, kLeafSize);
    tree.built_ratio = tree.bvh.area_ratio();
  }
}

namespace {

// Sorts pairs lexicographically: bucketed by the first index (counting sort over [0, n)), each
// bucket sorted by the second; O(pairs + n) but for the buckets' small sorts.
void sort_pairs(Pairs& pairs, Index n, std::vector<Index>& start, Pairs& scratch) {
  start.assign(static_cast<size_t>(n) + 1, 0);
  for (const auto& q : pairs) ++start[static_cast<size_t>(q[0]) + 1];
  for (Index i = 0; i < n; ++i) start[static_cast<size_t>(i) + 1] += start[static_cast<size_t>(i)];
  scratch.resize(pairs.size());
  for (const auto& q : pairs) scratch[static_cast<size_t>(start[static_cast<size_t>(q[0])]++)] = q;
  for (Index i = n; i > 0; --i) start[static_cast<size_t>(i)] = start[static_cast<size_t>(i) - 1];
  start[0] = 0;
  for (Index i = 0; i < n; ++i) {
    auto first = scratch.begin() + start[static_cast<size_t>(i)], last = scratch.begin() + start[static_cast<size_t>(i) + 1];
    if (last - first > 1) std::sort(first, last);
  }
  pairs.swap(scratch);
}

}  // namespace

// Pairs from simultaneous descents of two trees that test the primitives' own boxes in the
// leaves (Bvh::query_box_pairs / query_box_self: exactly the overlapping pairs), every box
// grown by r / 2 (two boxes grown by r / 2 meet exactly where one grown by r meets the other):
// moving points against the moving and the fixed faces, fixed points against the moving ones; moving edges
// against each other (the lower edge first) and against the fixed edges. The pairs are sorted,
// so the result does not depend on the trees' state.
void BroadPhase::find(const Model& model, const Scalar* x, const Scalar* dx, Scalar r, Candidates& out) {
  const auto& F = model.faces;
  const auto& E = model.edges;
  auto moving = [&](Index v) { return !model.fixed[static_cast<size_t>(v)]; };
  if (!ready_) {
    for (Index p : model.points) {
      Tree& t = moving(p) ? moving_points_ : fixed_points_;
      t.ids.push_back(p);
      t.prims.push_back(p);
    }
    for (Index f = 0; f < static_cast<Index>(F.size() / 3); ++f) {
      const Index* v = &F[3 * f];
      Tree& t = moving(v[0]) || moving(v[1]) || moving(v[2]) ? moving_faces_ : fixed_faces_;
      t.ids.push_back(f);
      t.prims.insert(t.prims.end(), v, v + 3);
    }
    for (Index e = 0; e < static_cast<Index>(E.size() / 2); ++e) {
      const Index* v = &E[2 * e];
      Tree& t = moving(v[0]) || moving(v[1]) ? moving_edges_ : fixed_edges_;
      t.ids.push_back(e);
      t.prims.insert(t.prims.end(), v, v + 2);
    }
    // The fixed trees are still unless a driven (scripted) vertex is among theirs.
    for (Tree* t : {&fixed_points_, &fixed_faces_, &fixed_edges_}) {
      t->verts = t->prims;
      std::sort(t->verts.begin(), t->verts.end());
      t->verts.erase(std::unique(t->verts.begin(), t->verts.end()), t->verts.end());
      t->still = std::none_of(t->verts.begin(), t->verts.end(),
                              [&](Index v) { return model.driven[static_cast<size_t>(v)] != 0; });
    }
    ready_ = true;
  }
  const Scalar half = r / 2;
  update(moving_points_, 1, x, dx, half);
  update(fixed_points_, 1, x, dx, half);
  update(moving_faces_, 3, x, dx, half);
  update(fixed_faces_, 3, x, dx, half);
  update(moving_edges_, 2, x, dx, half);
  update(fixed_edges_, 2, x, dx, half);
  auto point_faces = [&](const Tree& points, const Tree& faces) {
    // The pairs of overlapping boxes (the trees test the primitives' boxes they were refit
    // to), then the shared vertices from the trees' own copies of the vertex indices (no
    // lookup through the mesh arrays).
    points.bvh.query_box_pairs(faces.bvh, [&](Index i, Index k) {
      const Index p = points.prims[static_cast<size_t>(i)];
      const Index* v = &faces.prims[static_cast<size_t>(3 * k)];
      if (p == v[0] || p == v[1] || p == v[2]) return;
      out.point_face.push_back({p, faces.ids[static_cast<size_t>(k)]});
    });
  };
  auto edge_pair = [&](const Tree& a, Index i, const Tree& b, Index j) {
    const Index a0 = a.prims[static_cast<size_t>(2 * i)], a1 = a.prims[static_cast<size_t>(2 * i + 1)];
    const Index b0 = b.prims[static_cast<size_t>(2 * j)], b1 = b.prims[static_cast<size_t>(2 * j + 1)];
    if (a0 == b0 || a0 == b1 || a1 == b0 || a1 == b1) return;
    const Index e = a.ids[static_cast<size_t>(i)], f = b.ids[static_cast<size_t>(j)];
    if (&a == &b && f < e)
      out.edge_edge.push_back({f, e});
    else
      out.edge_edge.push_back({e, f});
  };
  // The point-face and the edge-edge pairs are two independent tasks (each with its own output
  // and sort scratch; each sorted, so the result is the serial one): two threads take one each.
  const bool both = num_threads() > 1 && moving_points_.ids.size() + moving_edges_.ids.size() > 512;
#pragma omp parallel sections num_threads(2) if (both)
  {
#pragma omp section
    {
      out.point_face.clear();
      point_faces(moving_points_, moving_faces_);
      point_faces(moving_points_, fixed_faces_);
      point_faces(fixed_points_, moving_faces_);
      sort_pairs(out.point_face, model.vertex_count, bucket_start_, scratch_);
    }
#pragma omp section
    {
      out.edge_edge.clear();
      moving_edges_.bvh.query_box_self([&](Index i, Index j) { edge_pair(moving_edges_, i, moving_edges_, j); });
      moving_edges_.bvh.query_box_pairs(fixed_edges_.bvh,
                                    [&](Index i, Index j) { edge_pair(moving_edges_, i, fixed_edges_, j); });
      sort_pairs(out.edge_edge, static_cast<Index>(E.size() / 2), edge_bucket_start_, edge_scratch_);
    }
  }
}

namespace {

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

namespace {

// True when the pair (point-triangle: p, t0, t1, t2; edge-edge: a0, a1, b0, b1) is certainly
// not closer than sqrt(dhat2), by a lower bound of its distance that is cheaper than the
// closest-point region: the distance between the point and the triangle's plane, or between
// the two edges' lines (every region's formula measures a distance at least this large: a
// point of one primitive to a point of the other's plane or line), |a| / |n| with
// n = e1 x e2 and a = n . r. Only where both are computed to a relative accuracy far inside
// the margin (1e-5 on the squared distance): |n|^2 >= 1e-4 |e1|^2 |e2|^2 (the angle between
// e1 and e2 above 0.01 rad, so n's relative rounding error is below ~1e-13) and
// |a| >= 1e-8 |e1| |e2| |r| (a's absolute rounding error is a few eps |e1| |e2| |r|, so its
// relative one is below ~1e-7); elsewhere (near-parallel edges, coplanar primitives) it
// decides nothing and the region decides.
inline bool farther_than_plane_or_line(const Vec3 y[4], bool edge_edge, Scalar dhat2) {
  const Vec3 e1 = y[1] - y[0], e2 = edge_edge ? Vec3(y[3] - y[2]) : Vec3(y[2] - y[0]);
  const Vec3 r = edge_edge ? Vec3(y[2] - y[0]) : Vec3(y[3] - y[0]);  // triangle: p - t0 (p in y[3] below)
  const Vec3 n = e1.cross(e2);
  const Scalar a = n.dot(r), nn = n.squaredNorm(), l2 = e1.squaredNorm() * e2.squaredNorm();
  return nn >= 1e-4 * l2 && a * a >= 1e-16 * l2 * r.squaredNorm() && a * a > (1 + 1e-5) * dhat2 * nn;
}

}  // namespace

std::vector<Constraint> find_constraints(const Model& model, const Candidates& candidates, const Scalar* x,
                                         Scalar dhat2, bool prefilter) {
  const auto& F = model.faces;
  const auto& E = model.edges;
  // Reduces a pair given by its four vertices to its closest-point formula; keeps it if close.
  // Candidates are found for sweeps grown by a margin: most are farther apart at x than their
  // boxes grown by dhat, which rejects them before the closest-point computation (boxes are
  // closer than the primitives, so no pair within dhat is lost; the growth is widened by far
  // more than the rounding of the two tests). Candidates whose boxes were grown by dhat at x
  // itself pass that test by construction: `prefilter` false skips it. Then the plane / line
  // bound (above) rejects most of the rest before the region search.
  const Scalar dhat = std::sqrt(dhat2) * (1 + 1e-9);
  auto consider = [&](const Index ids[4], bool edge_edge, std::vector<Constraint>& out) {
    const int k = edge_edge ? 2 : 1;
    if (prefilter) {
      Scalar lo[3], hi[3], lo2[3], hi2[3];
      primitive_box(ids, k, x, nullptr, dhat, lo, hi);
      primitive_box(ids + k, 4 - k, x, nullptr, 0, lo2, hi2);
      if (!overlap(lo, hi, lo2, hi2)) return;
    }
    const Vec3 y[4] = {at(x, ids[0]), at(x, ids[1]), at(x, ids[2]), at(x, ids[3])};
    if (edge_edge) {
      if (farther_than_plane_or_line(y, true, dhat2)) return;
    } else {
      const Vec3 t[4] = {y[1], y[2], y[3], y[0]};
      if (farther_than_plane_or_line(t, false, dhat2)) return;
    }
    const Reduced r = edge_edge ? edge_edge_region(y[0], y[1], y[2], y[3]) : point_triangle_region(y[0], y[1], y[2], y[3]);
    Vec3 v[4];
    for (int k = 0; k < vertex_count(r.kind); ++k) v[k] = y[r.slot[k]];
    const Scalar d = reduced_distance(r.kind, v);
    if (!(d < dhat2)) return;
    Constraint c = reduce(r, ids);
    c.d = d;
    if (edge_edge) {
      c.edges = {ids[0], ids[1], ids[2], ids[3]};
      const Scalar* X = model.rest.data();
      c.eps_x = edge_mollifier_threshold((at(X, ids[1]) - at(X, ids[0])).squaredNorm(),
                                         (at(X, ids[3]) - at(X, ids[2])).squaredNorm());
    }
    out.push_back(c);
  };
  std::vector<Constraint> out, ee;
  collect_in_order(static_cast<Index>(candidates.point_face.size()), out, [&](Index i, std::vector<Constraint>& part) {
    const auto [p, f] = candidates.point_face[static_cast<size_t>(i)];
    const Index ids[4] = {p, F[3 * f], F[3 * f + 1], F[3 * f + 2]};
    consider(ids, false, part);
  });
  collect_in_order(static_cast<Index>(candidates.edge_edge.size()), ee, [&](Index i, std::vector<Constraint>& part) {
    const auto [e, f] = candidates.edge_edge[static_cast<size_t>(i)];
    const Index ids[4] = {E[2 * e], E[2 * e + 1], E[2 * f], E[2 * f + 1]};
    consider(ids, true, part);
  });
  out.insert(out.end(), ee.begin(), ee.end());
  // Vertices against planes: every dynamic vertex (a solid's interior vertices cannot reach a
  // plane before its surface, so checking them costs little and needs no surface lookup).
  for (size_t pl = 0; pl < model.planes.size(); ++pl) {
    const Plane& plane = model.planes[pl];
    const Vec3 point = plane.point_at(x);
    for (Index v : model.points) {
      if (model.fixed[static_cast<size_t>(v)]) continue;
      const Scalar s = plane.normal.dot(at(x, v) - point);
      if (s * s >= dhat2 || s < 0) continue;
      Constraint c;
      c.kind = PairKind::PP;
      c.v = {v, plane.vertex, -1, -1};
      c.plane = static_cast<Index>(pl);
      c.d = s * s;
      out.push_back(c);
    }
  }
  return out;
}

std::vector<Constraint> find_constraints(const Model& model, BroadPhase& broad, const Scalar* x, Scalar dhat2) {
  Candidates& candidates = broad.scratch();
  broad.find(model, x, nullptr, std::sqrt(dhat2), candidates);
  return find_constraints(model, candidates, x, dhat2, false);
}

std::vector<Constraint> find_constraints(const Model& model, const Scalar* x, Scalar dhat2) {
  BroadPhase broad;
  return find_constraints(model, broad, x, dhat2);
}

Scalar constraint_barrier(const Model& model, const Constraint& c, const Scalar* x, Scalar dhat2, Vec<12>* g,
                          Mat<12>* H, Projection projection) {
  const bool project = projection != Projection::None;
  if (c.plane >= 0) {
    // s = n . (x_v - p): a moving plane's point p is the stencil's second vertex, and the
    // term's derivatives in it are those in x_v with the sign changed.
    const Plane& plane = model.planes[static_cast<size_t>(c.plane)];
    const Scalar s = plane.normal.dot(at(x, c.v[0]) - plane.point_at(x)), d = s * s;
    const bool moving = c.v[1] >= 0;
    if (g) {
      g->setZero();
      g->head<3>() = barrier_first(d, dhat2) * 2 * s * plane.normal;
      if (moving) g->segment<3>(3) = -g->head<3>();
    }
    if (H) {
      // b'' (2 s n)(2 s n)^T + b' 2 n n^T: rank one along n (along (n, -n) for a moving plane).
      Scalar k = 4 * d * barrier_second(d, dhat2) + 2 * barrier_first(d, dhat2);
      if (project) k = std::max(k, Scalar(0));
      H->setZero();
      const Mat3 K = k * plane.normal * plane.normal.transpose();
      H->topLeftCorner<3, 3>() = K;
      if (moving) {
        H->block<3, 3>(0, 3) = -K;
        H->block<3, 3>(3, 0) = -K;
        H->block<3, 3>(3, 3) = K;
      }
    }
    return barrier(d, dhat2);
  }
  const int n = c.stencil_size();
  const Index* ids = c.stencil();
  Vec3 y[4];
  for (int a = 0; a < n; ++a) y[a] = at(x, ids[a]);
  Reduced r{c.kind, {0, 1, 2, 3}};
  if (c.eps_x > 0)
    for (int a = 0; a < vertex_count(c.kind); ++a)
      r.slot[a] = static_cast<int>(std::find(ids, ids + 4, c.v[static_cast<size_t>(a)]) - ids);
  // A point-point term's clamp is its rank-one matrix exactly (barrier.h), so it is formed
  // directly; an edge pair reduced to a point-edge formula with its mollifier inactive has a
  // Hessian on those three vertices only, projected as such.
  bool rank_one = false;
  const bool want_rank_one = projection == Projection::RankOne || (project && c.kind == PairKind::PP);
  const Scalar e = pair_barrier(r, y, c.eps_x, dhat2, g, H, want_rank_one, &rank_one);
  if (H && project && !rank_one) {
    if (n == 4 && c.kind == PairKind::PE && !(c.eps_x > 0 && (y[1] - y[0]).cross(y[3] - y[2]).squaredNorm() < c.eps_x))
      project_psd_on_vertices<3>(*H, r.slot);
    else if (n == 4)
      project_psd_translation_free<4>(*H);
    else if (n == 3)
      project_psd_translation_free<3>(*H);
    else
      project_psd_translation_free<2>(*H);
  }
  return e;
}

Scalar evaluate_barriers(const Model& model, const std::vector<Constraint>& constraints, const Scalar* x,
                         Scalar dhat2, std::vector<Vec<12>>* g, std::vector<Mat<12>>* H, Projection projection) {
  const Index n = static_cast<Index>(constraints.size());
  if (g) g->resize(static_cast<size_t>(n));
  if (H) H->resize(static_cast<size_t>(n));
  std::vector<Scalar> energy(static_cast<size_t>(n));
#pragma omp parallel for schedule(dynamic, 16) if (n > 64)
  for (Index i = 0; i < n; ++i) {
    const size_t k = static_cast<size_t>(i);
    energy[k] = constraint_barrier(model, constraints[k], x, dhat2, g ? &(*g)[k] : nullptr,
                                   g && H ? &(*H)[k] : nullptr, projection);
  }
  Scalar sum = 0;
  for (Scalar e : energy) sum += e;
  return sum;
}

Scalar max_safe_step(const Model& model, const Candidates& candidates, const Scalar* x, const Scalar* dx,
                     const CcdOptions& options) {
  const auto& F = model.faces;
  const auto& E = model.edges;
  // The minimum over pairs does not depend on their order (each pair's time of impact below the
  // running minimum is found exactly), so threads may share the running bound.
  Scalar t = 1;
  const Index pf = static_cast<Index>(candidates.point_face.size());
  const Index ee = static_cast<Index>(candidates.edge_edge.size());
#pragma omp parallel if (pf + ee > 256)
  {
  Scalar local = 1;
#pragma omp for schedule(dynamic, 32) nowait
  for (Index i = 0; i < pf + ee; ++i) {
    Index ids[4];
    int k;
    if (i < pf) {
      const auto [p, f] = candidates.point_face[static_cast<size_t>(i)];
      ids[0] = p, ids[1] = F[3 * f], ids[2] = F[3 * f + 1], ids[3] = F[3 * f + 2];
      k = 1;
    } else {
      const auto [e, f] = candidates.edge_edge[static_cast<size_t>(i - pf)];
      ids[0] = E[2 * e], ids[1] = E[2 * e + 1], ids[2] = E[2 * f], ids[3] = E[2 * f + 1];
      k = 2;
    }
    // Candidates may be grown for the barrier: CCD needs only pairs whose swept boxes meet.
    Scalar lo[3], hi[3], lo2[3], hi2[3];
    primitive_box(ids, k, x, dx, 0, lo, hi);
    primitive_box(ids + k, 4 - k, x, dx, 0, lo2, hi2);
    if (!overlap(lo, hi, lo2, hi2)) continue;
    const Scalar bound = local;
    const Scalar s = k == 1 ? point_triangle_ccd(at(x, ids[0]), at(x, ids[1]), at(x, ids[2]), at(x, ids[3]),
                                                 at(dx, ids[0]), at(dx, ids[1]), at(dx, ids[2]), at(dx, ids[3]),
                                                 bound, options)
                            : edge_edge_ccd(at(x, ids[0]), at(x, ids[1]), at(x, ids[2]), at(x, ids[3]),
                                            at(dx, ids[0]), at(dx, ids[1]), at(dx, ids[2]), at(dx, ids[3]),
                                            bound, options);
    local = std::min(local, s);
  }
#pragma omp critical(kinema_contact_ccd)
  t = std::min(t, local);
  }
  for (const Plane& plane : model.planes) {
    // A moving plane's point travels with its vertex: the motion that counts is the relative one.
    const Vec3 point = plane.point_at(x);
    const Scalar plane_motion = plane.vertex >= 0 ? plane.normal.dot(at(dx, plane.vertex)) : Scalar(0);
    for (Index v : model.points) {
      if (model.fixed[static_cast<size_t>(v)]) continue;
      t = std::min(t, point_plane_ccd(plane.normal.dot(at(x, v) - point), plane.normal.dot(at(dx, v)) - plane_motion,
                                      t, options));
    }
  }
  return t;
}

Scalar max_safe_step(const Model& model, BroadPhase& broad, const Scalar* x, const Scalar* dx,
                     const CcdOptions& options) {
  Candidates& candidates = broad.scratch();
  broad.find(model, x, dx, 0, candidates);
  return max_safe_step(model, candidates, x, dx, options);
}

Scalar max_safe_step(const Model& model, const Scalar* x, const Scalar* dx, const CcdOptions& options) {
  BroadPhase broad;
  return max_safe_step(model, broad, x, dx, options);
}

Scalar min_distance(const Model& model, const Scalar* x, Scalar radius) {
  Scalar best = std::numeric_limits<Scalar>::infinity();
  const Scalar r2 = radius * radius;
  const auto& F = model.faces;
  const auto& E = model.edges;
  BroadPhase broad;
  Candidates candidates;
  broad.find(model, x, nullptr, radius, candidates);
  for (const auto& [p, f] : candidates.point_face) {
    const Scalar d = point_triangle_distance(at(x, p), at(x, F[3 * f]), at(x, F[3 * f + 1]), at(x, F[3 * f + 2]));
    if (d < r2) best = std::min(best, d);
  }
  for (const auto& [e, f] : candidates.edge_edge) {
    const Scalar d = edge_edge_distance(at(x, E[2 * e]), at(x, E[2 * e + 1]), at(x, E[2 * f]), at(x, E[2 * f + 1]));
    if (d < r2) best = std::min(best, d);
  }
  best = std::sqrt(best);
  for (const Plane& plane : model.planes) {
    const Vec3 point = plane.point_at(x);
    for (Index v : model.points) {
      if (model.fixed[static_cast<size_t>(v)]) continue;
      const Scalar s = plane.normal.dot(at(x, v) - point);
      if (s < radius) best = std::min(best, s);
    }
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
      const Scalar s = model.planes[pl].normal.dot(at(x, v) - model.planes[pl].point_at(x));
      if (!(s > 0))
        out.push_back("vertex " + std::to_string(v) + " lies on or behind plane " + std::to_string(pl) +
                      " (signed distance " + format_real(s) + ")");
    }
  return out;
}

}  // namespace kinema::contact
