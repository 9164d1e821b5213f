// Squared distances between the primitives of triangle meshes, with their gradients and
// Hessians, as Incremental Potential Contact uses them (Li et al., "Incremental Potential
// Contact", ACM TOG 39(4), 2020, section 4 and supplement): the closest-point region of a pair
// picks one smooth formula,
//   PP: |p - q|^2
//   PE: |(e0 - p) x (e1 - p)|^2 / |e1 - e0|^2                 (point to the edge's line)
//   PT: ((t1 - t0) x (t2 - t0) . (p - t0))^2 / |(t1 - t0) x (t2 - t0)|^2   (point to the plane)
//   EE: ((a1 - a0) x (b1 - b0) . (b0 - a0))^2 / |(a1 - a0) x (b1 - b0)|^2 (line to line)
// and each formula is differentiated in closed form: PT and EE are a^2 / b with a a triple
// product and b a squared cross product, PE is b / c with c a squared length. Every distance
// is squared (no square roots, smooth where it is positive).
// Edge-edge pairs that are parallel to rounding fall back to the point-edge formulas; the
// distance of two segments has a kink where they turn parallel (the closest points jump from one
// end to the other), which the barrier's mollifier on s = |(a1 - a0) x (b1 - b0)|^2 removes
// (barrier.h, edge_mollifier; ee_cross_derivatives below gives s and its derivatives).
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>

#include "core/types.h"

namespace kinema::contact {

using Vec3 = Eigen::Matrix<Scalar, 3, 1>;
using Mat3 = Eigen::Matrix<Scalar, 3, 3>;
template <int N>
using Vec = Eigen::Matrix<Scalar, N, 1>;
template <int N>
using Mat = Eigen::Matrix<Scalar, N, N>;

// The primitive pair a distance reduces to, with its vertices in formula order.
enum class PairKind { PP = 2, PE = 3, PT = 4, EE = 5 };

// Vertices a reduced pair's formula reads.
inline int vertex_count(PairKind kind) { return kind == PairKind::EE ? 4 : static_cast<int>(kind); }

inline Mat3 cross_matrix(const Vec3& v) {
  Mat3 m;
  m << 0, -v.z(), v.y(), v.z(), 0, -v.x(), -v.y(), v.x(), 0;
  return m;
}

// ----------------------------------------------------------------- closest-point regions

// Parameter of the point of segment [a, b] closest to p, in [0, 1].
inline Scalar segment_parameter(const Vec3& p, const Vec3& a, const Vec3& b) {
  const Vec3 e = b - a;
  const Scalar ee = e.squaredNorm();
  if (ee <= 0) return 0;
  return std::clamp((p - a).dot(e) / ee, Scalar(0), Scalar(1));
}

// The reduced pair of a point and a triangle: kind and the local vertex slots (0 = p, 1..3 =
// t0..t2) that the formula uses, in its order.
struct Reduced {
  PairKind kind;
  int slot[4];
};

// `dist`, when given, receives the squared distance found on the way (the exact distance of
// the point to the triangle, whatever the region).
inline Reduced point_triangle_region(const Vec3& p, const Vec3& t0, const Vec3& t1, const Vec3& t2,
                                     Scalar* dist = nullptr) {
  const Vec3 e1 = t1 - t0, e2 = t2 - t0, r = p - t0;
  // Barycentric coordinates of p's projection on the plane (Gram system of e1, e2).
  const Scalar a11 = e1.dot(e1), a12 = e1.dot(e2), a22 = e2.dot(e2);
  const Scalar b1 = e1.dot(r), b2 = e2.dot(r);
  const Scalar det = a11 * a22 - a12 * a12;
  if (det > 0) {
    const Scalar u = (a22 * b1 - a12 * b2) / det, v = (a11 * b2 - a12 * b1) / det;
    if (u >= 0 && v >= 0 && u + v <= 1) {
      if (dist) {
        const Vec3 n = e1.cross(e2);
        const Scalar a = n.dot(r);
        *dist = a * a / n.squaredNorm();
      }
      return {PairKind::PT, {0, 1, 2, 3}};
    }
  }
  // Outside (or a degenerate triangle): the nearest of the three edges.
  const Vec3* t[3] = {&t0, &t1, &t2};
  Scalar best = -1;
  Reduced out{PairKind::PP, {0, 1, -1, -1}};
  for (int k = 0; k < 3; ++k) {
    const Vec3& a = *t[k];
    const Vec3& b = *t[(k + 1) % 3];
    const Scalar s = segment_parameter(p, a, b);
    const Scalar d = (p - (a + s * (b - a))).squaredNorm();
    if (best < 0 || d < best) {
      best = d;
      if (s <= 0)
        out = {PairKind::PP, {0, 1 + k, -1, -1}};
      else if (s >= 1)
        out = {PairKind::PP, {0, 1 + (k + 1) % 3, -1, -1}};
      else
        out = {PairKind::PE, {0, 1 + k, 1 + (k + 1) % 3, -1}};
    }
  }
  if (dist) *dist = best;
  return out;
}

// Edge-edge: slots 0, 1 = a0, a1 and 2, 3 = b0, b1. Closest parameters of two segments
// (Ericson, "Real-Time Collision Detection", 2005, sec. 5.1.9), then the region they lie in.
// `dist` as for point_triangle_region.
inline Reduced edge_edge_region(const Vec3& a0, const Vec3& a1, const Vec3& b0, const Vec3& b1,
                                Scalar* dist = nullptr) {
  const Vec3 d1 = a1 - a0, d2 = b1 - b0, r = a0 - b0;
  const Scalar a = d1.dot(d1), e = d2.dot(d2), f = d2.dot(r);
  const Scalar c = d1.dot(r), b = d1.dot(d2);
  const Scalar denom = a * e - b * b;
  // Parallel to rounding: the line-line formula is 0/0, use the nearest endpoint-edge pair.
  const bool parallel = !(denom > 1e-12 * a * e);
  if (!parallel) {
    Scalar s = std::clamp((b * f - c * e) / denom, Scalar(0), Scalar(1));
    Scalar t = (b * s + f) / e;
    if (t < 0) {
      t = 0;
      s = std::clamp(-c / a, Scalar(0), Scalar(1));
    } else if (t > 1) {
      t = 1;
      s = std::clamp((b - c) / a, Scalar(0), Scalar(1));
    }
    if (dist) *dist = (r + s * d1 - t * d2).squaredNorm();
    const bool s_in = s > 0 && s < 1, t_in = t > 0 && t < 1;
    if (s_in && t_in) return {PairKind::EE, {0, 1, 2, 3}};
    if (!s_in && !t_in) return {PairKind::PP, {s <= 0 ? 0 : 1, t <= 0 ? 2 : 3, -1, -1}};
    if (!s_in) return {PairKind::PE, {s <= 0 ? 0 : 1, 2, 3, -1}};
    return {PairKind::PE, {t <= 0 ? 2 : 3, 0, 1, -1}};
  }
  // Nearest of the four endpoint-to-segment pairs.
  const Vec3* v[4] = {&a0, &a1, &b0, &b1};
  Reduced best{PairKind::PP, {0, 2, -1, -1}};
  Scalar best_d = -1;
  for (int k = 0; k < 4; ++k) {
    const int e0 = k < 2 ? 2 : 0;
    const Vec3& p = *v[k];
    const Scalar s = segment_parameter(p, *v[e0], *v[e0 + 1]);
    const Scalar d = (p - (*v[e0] + s * (*v[e0 + 1] - *v[e0]))).squaredNorm();
    if (best_d < 0 || d < best_d) {
      best_d = d;
      if (s <= 0)
        best = {PairKind::PP, {k, e0, -1, -1}};
      else if (s >= 1)
        best = {PairKind::PP, {k, e0 + 1, -1, -1}};
      else
        best = {PairKind::PE, {k, e0, e0 + 1, -1}};
    }
  }
  if (dist) *dist = best_d;
  return best;
}

// ----------------------------------------------------------------- values

inline Scalar pp_distance(const Vec3& p, const Vec3& q) { return (p - q).squaredNorm(); }

inline Scalar pe_distance(const Vec3& p, const Vec3& e0, const Vec3& e1) {
  const Scalar len = (e1 - e0).squaredNorm();
  if (len <= 0) return (p - e0).squaredNorm();
  return (e0 - p).cross(e1 - p).squaredNorm() / len;
}

// Squared distance from p to the plane of the triangle.
inline Scalar pt_distance(const Vec3& p, const Vec3& t0, const Vec3& t1, const Vec3& t2) {
  const Vec3 n = (t1 - t0).cross(t2 - t0);
  const Scalar a = n.dot(p - t0);
  return a * a / n.squaredNorm();
}

// Squared distance between the lines of the two edges.
inline Scalar ee_distance(const Vec3& a0, const Vec3& a1, const Vec3& b0, const Vec3& b1) {
  const Vec3 n = (a1 - a0).cross(b1 - b0);
  const Scalar a = n.dot(b0 - a0);
  return a * a / n.squaredNorm();
}

// Squared distance of a reduced pair; v holds its vertices in formula order.
inline Scalar reduced_distance(PairKind kind, const Vec3* v) {
  switch (kind) {
    case PairKind::PP: return pp_distance(v[0], v[1]);
    case PairKind::PE: return pe_distance(v[0], v[1], v[2]);
    case PairKind::PT: return pt_distance(v[0], v[1], v[2], v[3]);
    case PairKind::EE: return ee_distance(v[0], v[1], v[2], v[3]);
  }
  return 0;
}

// Exact (unsigned, squared) point-triangle and segment-segment distances, whatever the region
// (computed directly from the closest points; equal to the region's formula up to rounding).
inline Scalar point_triangle_distance(const Vec3& p, const Vec3& t0, const Vec3& t1, const Vec3& t2) {
  Scalar d;
  point_triangle_region(p, t0, t1, t2, &d);
  return d;
}

inline Scalar edge_edge_distance(const Vec3& a0, const Vec3& a1, const Vec3& b0, const Vec3& b1) {
  Scalar d;
  edge_edge_region(a0, a1, b0, b1, &d);
  return d;
}

// ----------------------------------------------------------------- derivatives

namespace detail {

// Value, gradient and (when H is given) Hessian of b = |e1 x e2|^2 over (e1, e2).
inline void cross_sq(const Vec3& e1, const Vec3& e2, Scalar& b, Vec<6>& g, Mat<6>* H) {
  const Vec3 n = e1.cross(e2);
  b = n.squaredNorm();
  g.head<3>() = 2 * e2.cross(n);
  g.tail<3>() = 2 * n.cross(e1);
  if (!H) return;
  // dn / de1 = -[e2]x, dn / de2 = [e1]x; [v]x^T [v]x = |v|^2 I - v v^T.
  const Mat3 C1 = cross_matrix(e1), C2 = cross_matrix(e2), N = cross_matrix(n);
  H->block<3, 3>(0, 0) = 2 * (e2.squaredNorm() * Mat3::Identity() - e2 * e2.transpose());
  H->block<3, 3>(3, 3) = 2 * (e1.squaredNorm() * Mat3::Identity() - e1 * e1.transpose());
  H->block<3, 3>(0, 3) = 2 * (C2 * C1) - 2 * N;  // -[e2]x^T [e1]x = [e2]x [e1]x
  H->block<3, 3>(3, 0) = H->block<3, 3>(0, 3).transpose();
}

// d = a^2 / b with a = (e1 x e2) . r and b = |e1 x e2|^2, over y = (e1, e2, r). With
// q = grad a - (a / b) grad b the Hessian is (2 / b) q q^T + (2 a / b) Hess a - (a / b)^2 Hess b.
inline void triple_over_cross(const Vec3& e1, const Vec3& e2, const Vec3& r, Vec<9>& g, Mat<9>* H) {
  const Vec3 n = e1.cross(e2);
  const Scalar a = n.dot(r);
  Vec<9> ga;
  ga << e2.cross(r), r.cross(e1), n;
  Scalar b;
  Vec<6> gb;
  Mat<6> Hb;
  cross_sq(e1, e2, b, gb, H ? &Hb : nullptr);
  const Scalar ab = a / b;
  g = 2 * ab * ga;
  g.head<6>() -= ab * ab * gb;
  if (!H) return;
  Vec<9> q = ga;
  q.head<6>() -= ab * gb;
  H->noalias() = (2 / b) * q * q.transpose();
  H->topLeftCorner<6, 6>() -= ab * ab * Hb;
  // Hess a: the off-diagonal blocks -[r]x (e1, e2), [e2]x (e1, r), -[e1]x (e2, r).
  const Scalar s = 2 * ab;
  const Mat3 Cr = s * cross_matrix(r), C1 = s * cross_matrix(e1), C2 = s * cross_matrix(e2);
  H->block<3, 3>(0, 3) -= Cr;
  H->block<3, 3>(3, 0) += Cr;
  H->block<3, 3>(0, 6) += C2;
  H->block<3, 3>(6, 0) -= C2;
  H->block<3, 3>(3, 6) -= C1;
  H->block<3, 3>(6, 3) += C1;
}

// A formula of K vertices that depends only on their differences: given its gradient and
// Hessian over K - 1 "free" vertices (all but `dep`, in order) with the dependent vertex held
// still, the full ones follow from translation invariance (the gradient sums to zero over the
// vertices and every block row of the Hessian sums to zero). Block sums, no dense products.
// Hf is read only when H is given.
template <int K>
inline void complete_translation_free(const Vec<3 * (K - 1)>& gf, const Mat<3 * (K - 1)>& Hf, int dep,
                                      Vec<12>& g, Mat<12>* H) {
  int slot[K - 1];
  for (int a = 0, k = 0; a < K; ++a)
    if (a != dep) slot[k++] = a;
  Vec3 gsum = Vec3::Zero();
  for (int a = 0; a < K - 1; ++a) {
    g.segment<3>(3 * slot[a]) = gf.template segment<3>(3 * a);
    gsum += gf.template segment<3>(3 * a);
  }
  g.segment<3>(3 * dep) = -gsum;
  if (!H) return;
  Mat3 total = Mat3::Zero();
  for (int a = 0; a < K - 1; ++a) {
    Mat3 row = Mat3::Zero();
    for (int b = 0; b < K - 1; ++b) {
      const Mat3 blk = Hf.template block<3, 3>(3 * a, 3 * b);
      H->block<3, 3>(3 * slot[a], 3 * slot[b]) = blk;
      row += blk;
    }
    H->block<3, 3>(3 * slot[a], 3 * dep) = -row;
    H->block<3, 3>(3 * dep, 3 * slot[a]) = -row.transpose();
    total += row;
  }
  H->block<3, 3>(3 * dep, 3 * dep) = total;
}

}  // namespace detail

// Gradient and (when H is given) Hessian of each formula with respect to its vertices (3
// entries per vertex, in formula order), in the first 3k entries of g and the top-left
// 3k x 3k block of H.
inline void pp_derivatives(const Vec3& p, const Vec3& q, Vec<12>& g, Mat<12>* H) {
  detail::complete_translation_free<2>(2 * (q - p), 2 * Mat3::Identity(), 0, g, H);
}

inline void pe_derivatives(const Vec3& p, const Vec3& e0, const Vec3& e1, Vec<12>& g, Mat<12>* H) {
  // d = b / c over the free vertices (e0, e1) with p held: u = e0 - p, w = e1 - p,
  // b = |u x w|^2, c = |w - u|^2.
  const Vec3 u = e0 - p, w = e1 - p, e = w - u;
  Scalar b;
  Vec<6> gb;
  Mat<6> Hb;
  detail::cross_sq(u, w, b, gb, H ? &Hb : nullptr);
  const Scalar c = e.squaredNorm();
  Vec<6> gc;
  gc << -2 * e, 2 * e;
  Mat<6> Hy;
  if (H) {
    // Hess c = 2 [[I, -I], [-I, I]]; with q = gb - (b / c) gc the Hessian is
    // Hb / c - (q gc^T + gc q^T) / c^2 - (b / c^2) Hess c.
    const Vec<6> q = gb - (b / c) * gc;
    Hy = Hb / c;
    Hy.noalias() -= (q * gc.transpose() + gc * q.transpose()) / (c * c);
    const Scalar k = 2 * b / (c * c);
    for (int i = 0; i < 3; ++i) {
      Hy(i, i) -= k, Hy(i + 3, i + 3) -= k;
      Hy(i, i + 3) += k, Hy(i + 3, i) += k;
    }
  }
  detail::complete_translation_free<3>(gb / c - (b / (c * c)) * gc, Hy, 0, g, H);
}

inline void pt_derivatives(const Vec3& p, const Vec3& t0, const Vec3& t1, const Vec3& t2, Vec<12>& g,
                           Mat<12>* H) {
  // Over y = (t1 - t0, t2 - t0, p - t0): with t0 held still, y is the free vertices (t1, t2, p).
  Vec<9> gy;
  Mat<9> Hy;
  detail::triple_over_cross(t1 - t0, t2 - t0, p - t0, gy, H ? &Hy : nullptr);
  // Reorder to the free vertices in formula order (p, t1, t2) = (y2, y0, y1).
  const int from[3] = {2, 0, 1};
  Vec<9> gf;
  Mat<9> Hf;
  for (int a = 0; a < 3; ++a) {
    gf.segment<3>(3 * a) = gy.segment<3>(3 * from[a]);
    if (H)
      for (int b = 0; b < 3; ++b) Hf.block<3, 3>(3 * a, 3 * b) = Hy.block<3, 3>(3 * from[a], 3 * from[b]);
  }
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"  // Hf is read only when H is given
#endif
  detail::complete_translation_free<4>(gf, Hf, 1, g, H);
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic pop
#endif
}

inline void ee_derivatives(const Vec3& a0, const Vec3& a1, const Vec3& b0, const Vec3& b1, Vec<12>& g,
                           Mat<12>* H) {
  // Over y = (a1 - a0, b1 - b0, b0 - a0); with a0 held still the free vertices are
  // a1 = y0, b0 = y2 - y1, b1 = y1 (as displacements: d a1 -> d y0, d b0 -> d y2 - d y1,
  // d b1 -> d y1), so the free derivatives are block sums of y's.
  Vec<9> gy;
  Mat<9> Hy;
  detail::triple_over_cross(a1 - a0, b1 - b0, b0 - a0, gy, H ? &Hy : nullptr);
  Vec<9> gf;
  gf << gy.segment<3>(0), gy.segment<3>(6) - gy.segment<3>(3), gy.segment<3>(3);
  Mat<9> Hf;
  if (H) {
    auto blk = [&](int i, int j) { return Hy.block<3, 3>(3 * i, 3 * j); };
    const Mat3 A02 = blk(0, 2) - blk(0, 1), A12 = blk(1, 2) - blk(1, 1);
    Hf.block<3, 3>(0, 0) = blk(0, 0);
    Hf.block<3, 3>(0, 3) = A02;
    Hf.block<3, 3>(0, 6) = blk(0, 1);
    Hf.block<3, 3>(3, 3) = blk(2, 2) - blk(2, 1) - A12;
    Hf.block<3, 3>(3, 6) = blk(2, 1) - blk(1, 1);
    Hf.block<3, 3>(6, 6) = blk(1, 1);
    Hf.block<3, 3>(3, 0) = A02.transpose();
    Hf.block<3, 3>(6, 0) = blk(1, 0);
    Hf.block<3, 3>(6, 3) = Hf.block<3, 3>(3, 6).transpose();
  }
  detail::complete_translation_free<4>(gf, Hf, 0, g, H);
}

// s = |(a1 - a0) x (b1 - b0)|^2 of an edge pair with its gradient and (when H is given)
// Hessian over (a0, a1, b0, b1): the quantity the edge-edge mollifier is a function of.
inline Scalar ee_cross_derivatives(const Vec3& a0, const Vec3& a1, const Vec3& b0, const Vec3& b1, Vec<12>& g,
                                   Mat<12>* H) {
  Scalar s;
  Vec<6> g6;
  Mat<6> H6;
  detail::cross_sq(a1 - a0, b1 - b0, s, g6, H ? &H6 : nullptr);
  // (e1, e2) = (a1 - a0, b1 - b0): d/da0 = -d/de1, d/da1 = d/de1, likewise for b.
  const int sign[4] = {-1, 1, -1, 1};
  for (int a = 0; a < 4; ++a) {
    g.segment<3>(3 * a) = sign[a] * g6.segment<3>(3 * (a / 2));
    if (H)
      for (int b = 0; b < 4; ++b)
        H->block<3, 3>(3 * a, 3 * b) = (sign[a] * sign[b]) * H6.block<3, 3>(3 * (a / 2), 3 * (b / 2));
  }
  return s;
}

// Gradient (first 3k entries of g) and, when H is given, Hessian (top-left 3k x 3k of H) of a
// reduced pair; the rest of g and H is zero.
inline void reduced_derivatives(PairKind kind, const Vec3* v, Vec<12>& g, Mat<12>* H) {
  g.setZero();
  if (H) H->setZero();
  switch (kind) {
    case PairKind::PP: pp_derivatives(v[0], v[1], g, H); break;
    case PairKind::PE: pe_derivatives(v[0], v[1], v[2], g, H); break;
    case PairKind::PT: pt_derivatives(v[0], v[1], v[2], v[3], g, H); break;
    case PairKind::EE: ee_derivatives(v[0], v[1], v[2], v[3], g, H); break;
  }
}

inline void reduced_derivatives(PairKind kind, const Vec3* v, Vec<12>& g, Mat<12>& H) {
  reduced_derivatives(kind, v, g, &H);
}

}  // namespace kinema::contact
