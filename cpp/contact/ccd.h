// Continuous collision detection by additive conservative advancement (ACCD: Li, Kaufman &
// Jiang, "Codimensional Incremental Potential Contact", ACM TOG 40(4), 2021, algorithm 1).
// For primitives moving linearly from x to x + t dx, the distance can shrink no faster than
//   l_p = max |dx_a - mean| + max |dx_b - mean|       (a, b: the two primitives' vertices)
// so advancing t by 0.9 d(t) / l_p never passes through contact: each advance is safe, and the
// loop stops at the first time the distance has fallen below a tenth of its initial value.
// The returned time of impact is conservative (never later than the first contact, up to the
// rounding of the distance evaluations), and a later Newton iteration may advance further.
#pragma once

#include <cmath>

#include "contact/distance.h"

namespace kinema::contact {

struct CcdOptions {
  Scalar gap_fraction = 0.1;  // stop once the distance falls below this share of the initial one
  Index max_iterations = 100000;
};

// Time of impact in [0, t_max] of the pair `x` (count vertices, the first `split` of which
// form one primitive) moving by `dx`; t_max when no contact is met before t_max. `distance`
// returns the squared distance of four positions.
template <class Distance>
Scalar additive_ccd(Vec3 x[4], Vec3 dx[4], int split, Scalar t_max, Distance&& distance,
                    const CcdOptions& options = {}) {
  Vec3 mean = Vec3::Zero();
  for (int k = 0; k < 4; ++k) mean += dx[k];
  mean /= 4;
  Scalar max_a = 0, max_b = 0;
  for (int k = 0; k < 4; ++k) {
    dx[k] -= mean;
    const Scalar len = dx[k].norm();
    if (k < split)
      max_a = std::max(max_a, len);
    else
      max_b = std::max(max_b, len);
  }
  const Scalar lp = max_a + max_b;
  if (lp == 0) return t_max;
  Scalar d = std::sqrt(distance(x));
  if (d == 0) return 0;
  const Scalar gap = options.gap_fraction * d;
  Scalar t = 0;
  Scalar tl = (1 - options.gap_fraction) * d / lp;
  // The first advance is safe from t = 0: when it already covers t_max (most candidate pairs of
  // a step), the pair cannot meet before t_max.
  if (tl >= t_max) return t_max;
  for (Index it = 0; it < options.max_iterations; ++it) {
    for (int k = 0; k < 4; ++k) x[k] += tl * dx[k];
    d = std::sqrt(distance(x));
    if (t > 0 && d < gap) return t;
    t += tl;
    if (t > t_max) return t_max;
    tl = 0.9 * d / lp;
  }
  return t;
}

inline Scalar point_triangle_ccd(const Vec3& p, const Vec3& t0, const Vec3& t1, const Vec3& t2,
                                 const Vec3& dp, const Vec3& dt0, const Vec3& dt1, const Vec3& dt2,
                                 Scalar t_max, const CcdOptions& options = {}) {
  Vec3 x[4] = {p, t0, t1, t2}, dx[4] = {dp, dt0, dt1, dt2};
  return additive_ccd(x, dx, 1, t_max,
                      [](const Vec3* y) { return point_triangle_distance(y[0], y[1], y[2], y[3]); }, options);
}

inline Scalar edge_edge_ccd(const Vec3& a0, const Vec3& a1, const Vec3& b0, const Vec3& b1, const Vec3& da0,
                            const Vec3& da1, const Vec3& db0, const Vec3& db1, Scalar t_max,
                            const CcdOptions& options = {}) {
  Vec3 x[4] = {a0, a1, b0, b1}, dx[4] = {da0, da1, db0, db1};
  return additive_ccd(x, dx, 2, t_max,
                      [](const Vec3* y) { return edge_edge_distance(y[0], y[1], y[2], y[3]); }, options);
}

// A point against the half-space n . (x - q) >= 0 (n unit): linear in t, solved exactly, with
// the same gap fraction kept.
inline Scalar point_plane_ccd(Scalar signed_distance, Scalar normal_motion, Scalar t_max,
                              const CcdOptions& options = {}) {
  if (signed_distance <= 0) return 0;
  if (normal_motion >= 0) return t_max;
  const Scalar t = (1 - options.gap_fraction) * signed_distance / -normal_motion;
  return std::min(t, t_max);
}

}  // namespace kinema::contact
