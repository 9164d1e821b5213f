// Per-ray math of the path tracer as free functions: ray/primitive intersection, random numbers,
// direction sampling and the scattering (BSDF) formulas of the three materials.
//
//   Rendering equation: L_o(x, w_o) = L_e(x, w_o) + int f(x, w_i, w_o) L_i(x, w_i) cos(theta_i) dw_i,
// estimated along a path by beta * L_e with beta *= f cos / pdf at each bounce (Kajiya 1986).
//
// References: P. Shirley, "Ray Tracing in One Weekend" / "... The Next Week" / "... The Rest of
// Your Life" (2020-2024) for the material models; M. Pharr, W. Jakob, G. Humphreys, "Physically
// Based Rendering", 3rd ed. (2016) [PBRT] for the robust slab test (sec. 3.9.2), cosine sampling
// by Malley's method (sec. 13.6.3) and Russian roulette (sec. 13.7); Moller & Trumbore,
// "Fast, minimum storage ray-triangle intersection", JGT 1997; Haines et al., "Precision
// improvements for ray/sphere intersection", Ray Tracing Gems ch. 7 (2019); C. Schlick, "An
// inexpensive BRDF model for physically-based rendering", CGF 13(3) 1994; Duff et al., "Building
// an orthonormal basis, revisited", JCGT 6(1) 2017; M. O'Neill, "PCG: a family of simple fast
// space-efficient statistically good algorithms for random number generation" (2014).
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>

#include "core/types.h"

namespace kinema::render {

using Vec3 = Eigen::Matrix<Scalar, 3, 1>;
using Color = Eigen::Array<Scalar, 3, 1>;  // linear RGB radiance or reflectance

constexpr Scalar kPi = 3.14159265358979323846;
constexpr Scalar kInfinity = std::numeric_limits<Scalar>::infinity();

// A ray o + t d with unit d, valid for t in (t_min, t_max).
struct Ray {
  Vec3 origin;
  Vec3 direction;
};

// ------------------------------------------------------------------ random numbers

// SplitMix64 finaliser (Steele, Lea & Flood 2014): a bijective 64-bit mix, used to derive an
// independent stream for each (seed, pixel, sample).
inline std::uint64_t splitmix64(std::uint64_t x) {
  x += 0x9e3779b97f4a7c15ULL;
  x = (x ^ (x >> 30)) * 0xbf58476d1ce4e5b9ULL;
  x = (x ^ (x >> 27)) * 0x94d049bb133111ebULL;
  return x ^ (x >> 31);
}

// PCG32 (XSH-RR output, O'Neill 2014). Each sample of each pixel owns one, so an image does not
// depend on which thread traced which pixel.
class Rng {
 public:
  Rng(std::uint64_t seed, std::uint64_t pixel, std::uint64_t sample) {
    const std::uint64_t h = splitmix64(splitmix64(splitmix64(seed) ^ pixel) ^ sample);
    state_ = 0;
    next_u32();
    state_ += h;
    next_u32();
  }
  std::uint32_t next_u32() {
    const std::uint64_t old = state_;
    state_ = old * 6364136223846793005ULL + kIncrement;
    const auto xorshifted = static_cast<std::uint32_t>(((old >> 18u) ^ old) >> 27u);
    const auto rot = static_cast<std::uint32_t>(old >> 59u);
    return (xorshifted >> rot) | (xorshifted << ((32u - rot) & 31u));
  }
  // Uniform in [0, 1), 32 bits of resolution.
  Scalar uniform() { return next_u32() * 0x1p-32; }

 private:
  static constexpr std::uint64_t kIncrement = 1442695040888963407ULL;
  std::uint64_t state_;
};

// ------------------------------------------------------------------ intersection

// Nearest root t in (t_min, t_max) of |o + t d - c|^2 = r^2 for unit d, or kInfinity. The
// discriminant is formed as r^2 - |(o - c) - b d|^2 (Haines et al. 2019, eq. 7.5) rather than
// b^2 - c, which loses all digits when the sphere is small and far; the second root comes from
// Vieta's formula (no cancellation).
inline Scalar intersect_sphere(const Ray& ray, const Vec3& center, Scalar radius, Scalar t_min,
                               Scalar t_max) {
  const Vec3 f = ray.origin - center;
  const Scalar b = -f.dot(ray.direction);
  const Vec3 l = f + b * ray.direction;  // from the centre to the closest point of the line
  const Scalar disc = radius * radius - l.squaredNorm();
  if (disc < 0) return kInfinity;
  const Scalar c = f.squaredNorm() - radius * radius;
  const Scalar q = b + std::copysign(std::sqrt(disc), b);
  Scalar t0 = q != 0 ? c / q : 0;
  Scalar t1 = q;
  if (t0 > t1) std::swap(t0, t1);
  if (t0 > t_min && t0 < t_max) return t0;
  if (t1 > t_min && t1 < t_max) return t1;
  return kInfinity;
}

// Moller-Trumbore (1997): t of the hit of triangle (v0, v0 + e1, v0 + e2) in (t_min, t_max), or
// kInfinity. Both faces count (the materials decide what a back face does).
inline Scalar intersect_triangle(const Ray& ray, const Vec3& v0, const Vec3& e1, const Vec3& e2,
                                 Scalar t_min, Scalar t_max) {
  const Vec3 p = ray.direction.cross(e2);
  const Scalar det = e1.dot(p);
  if (det == 0) return kInfinity;
  const Scalar inv_det = 1 / det;
  const Vec3 s = ray.origin - v0;
  const Scalar u = s.dot(p) * inv_det;
  if (u < 0 || u > 1) return kInfinity;
  const Vec3 q = s.cross(e1);
  const Scalar v = ray.direction.dot(q) * inv_det;
  if (v < 0 || u + v > 1) return kInfinity;
  const Scalar t = e2.dot(q) * inv_det;
  return (t > t_min && t < t_max) ? t : kInfinity;
}

// t of the hit of the plane {x : (x - p) . n = 0} in (t_min, t_max), or kInfinity.
inline Scalar intersect_plane(const Ray& ray, const Vec3& point, const Vec3& normal, Scalar t_min,
                              Scalar t_max) {
  const Scalar denom = normal.dot(ray.direction);
  if (denom == 0) return kInfinity;
  const Scalar t = normal.dot(point - ray.origin) / denom;
  return (t > t_min && t < t_max) ? t : kInfinity;
}

// ------------------------------------------------------------------ sampling

// An orthonormal basis (t, b, n) around the unit vector n, branch-free except for the sign
// (Duff et al. 2017, listing 3).
inline void orthonormal_basis(const Vec3& n, Vec3& t, Vec3& b) {
  const Scalar sign = std::copysign(Scalar(1), n.z());
  const Scalar a = -1 / (sign + n.z());
  const Scalar c = n.x() * n.y() * a;
  t = Vec3(1 + sign * n.x() * n.x() * a, sign * c, -sign * n.x());
  b = Vec3(c, sign + n.y() * n.y() * a, -n.y());
}

// Cosine-weighted direction about +z from two uniforms: a uniform point on the unit disk
// lifted to the hemisphere (Malley's method, PBRT sec. 13.6.3); pdf(w) = cos(theta) / pi.
inline Vec3 cosine_hemisphere_local(Scalar u1, Scalar u2) {
  const Scalar r = std::sqrt(u1);
  const Scalar phi = 2 * kPi * u2;
  return Vec3(r * std::cos(phi), r * std::sin(phi), std::sqrt(std::max(Scalar(0), 1 - u1)));
}

inline Scalar cosine_hemisphere_pdf(Scalar cos_theta) { return cos_theta > 0 ? cos_theta / kPi : 0; }

// Cosine-weighted direction about the unit normal n.
inline Vec3 cosine_hemisphere(const Vec3& n, Scalar u1, Scalar u2) {
  Vec3 t, b;
  orthonormal_basis(n, t, b);
  const Vec3 l = cosine_hemisphere_local(u1, u2);
  return (l.x() * t + l.y() * b + l.z() * n).normalized();
}

// A uniform point in the unit ball (radius u^(1/3), uniform direction), for the metal's fuzz.
inline Vec3 uniform_ball(Scalar u1, Scalar u2, Scalar u3) {
  const Scalar z = 1 - 2 * u1;
  const Scalar s = std::sqrt(std::max(Scalar(0), 1 - z * z));
  const Scalar phi = 2 * kPi * u2;
  return std::cbrt(u3) * Vec3(s * std::cos(phi), s * std::sin(phi), z);
}

// ------------------------------------------------------------------ scattering

// Mirror direction of d about the unit normal n: d - 2 (d . n) n.
inline Vec3 reflect(const Vec3& d, const Vec3& n) { return d - 2 * d.dot(n) * n; }

// Snell's law eta_i sin(theta_i) = eta_t sin(theta_t) for unit d arriving against the unit
// normal n (d . n < 0), eta = eta_i / eta_t. Returns false on total internal reflection
// (sin^2 theta_t > 1); otherwise the unit transmitted direction and cos(theta_t).
inline bool refract(const Vec3& d, const Vec3& n, Scalar eta, Vec3& out, Scalar& cos_t) {
  const Scalar cos_i = std::min(Scalar(1), -d.dot(n));
  const Scalar sin2_t = eta * eta * std::max(Scalar(0), 1 - cos_i * cos_i);
  if (sin2_t > 1) return false;
  cos_t = std::sqrt(1 - sin2_t);
  out = (eta * d + (eta * cos_i - cos_t) * n).normalized();
  return true;
}

// Schlick's approximation (1994, eq. 24) of the Fresnel reflectance of an interface between
// media of indices eta_i and eta_t: R = R0 + (1 - R0)(1 - cos)^5, R0 = ((eta_i - eta_t) /
// (eta_i + eta_t))^2, where cos is the cosine on the optically thinner side: cos_i when entering
// a denser medium, cos_t when leaving it (so R -> 1 continuously at the critical angle).
// Transmittance is 1 - R: the estimator conserves energy at the interface by construction.
inline Scalar schlick(Scalar cos_i, Scalar cos_t, Scalar eta_i, Scalar eta_t) {
  const Scalar r0 = (eta_i - eta_t) / (eta_i + eta_t);
  const Scalar cos = eta_i <= eta_t ? cos_i : cos_t;
  const Scalar m = 1 - cos;
  const Scalar m2 = m * m;
  return r0 * r0 + (1 - r0 * r0) * m2 * m2 * m;
}

// Survival probability of Russian roulette: the largest component of the path throughput,
// capped at 1; dividing the surviving throughput by it keeps the estimator unbiased (PBRT sec.
// 13.7): E[beta'] = p * beta / p = beta.
inline Scalar roulette_survival(const Color& beta) { return std::min(Scalar(1), beta.maxCoeff()); }

}  // namespace kinema::render
