// The 3D Laplace (gravitational) potential of point charges and its derivatives,
//   phi(x) = sum_j q_j / |x - y_j|,   grad phi(x) = -sum_j q_j (x - y_j) / |x - y_j|^3,
// by the adaptive fast multipole method (Greengard & Rokhlin 1997; Cheng, Greengard & Rokhlin
// 1999) with solid-harmonic expansions and precomputed dense M2L operators applied as matrix
// products, in O(N + M) work, or by the direct O(N M) sum. The self term (when the targets are
// the sources) is left out of both, and with the 1/r kernel so are all pairs at distance zero
// (coincident points); a smooth near kernel counts a distinct source at a target's position.
// The near field (adjacent leaves) can use a softened or regularised kernel instead of 1/r
// (Plummer softening for N-body, a Gaussian blob for vortex particles): every pair in
// non-adjacent boxes is at least `Fmm3dConfig::min_width` apart and sees 1/r.
#pragma once

#include "core/interrupt.h"
#include "core/types.h"
#include "fmm/p2p3d.h"

namespace kinema::fmm3 {

// How the M2L translations are applied: dense (p+1)^2 x (p+1)^2 matrices batched as matrix
// products (O(p^4) per translation, fastest at low order), or by rotation to the z axis
// (rotation3d.h, O(p^3)); Auto picks by the order.
enum class M2lMethod { Auto = 0, Dense = 1, Rotation = 2 };

struct Fmm3dConfig {
  Scalar eps = 1e-10;   // relative 2-norm error asked for phi
  int derivatives = 0;  // 0: phi; 1: phi and gradient; 2: also the Hessian
  int order = 0;        // expansion order p; 0: chosen from eps
  Index leaf_size = 0;  // most sources or targets in a leaf; 0: chosen from the order
  NearKernel kernel = NearKernel::Laplace;  // kernel of the near field
  Scalar length = 0;    // softening / core length of the near-field kernel [m]
  Scalar min_width = 0; // leaves are not split below this width [m]
  M2lMethod m2l = M2lMethod::Auto;
};

struct Fmm3dStats {
  int order = 0;
  bool rotation = false;  // the M2L ran by rotation
  Index leaf_size = 0;
  Scalar root_scale = 1;  // the root box over the points' bounding cube
  Index box_count = 0;
  int depth = 0;
  // Laplace kernel: pairs of a target and a charged source (not the target itself) at the
  // same position, left out of the sums (their interaction is infinite).
  Index coincident = 0;
  double seconds_tree = 0, seconds_upward = 0, seconds_m2l = 0, seconds_downward = 0,
         seconds_leaves = 0;
};

constexpr int kMaxOrder3d = 40;

// Expansion order that meets eps (measured over uniform and clustered distributions).
int order_for(Scalar eps);
// Whether Auto applies the M2L by rotation at order p.
bool rotate_m2l(int order, const Fmm3dConfig& config);
// Mean leaf occupancy that balances the near-field sums against the translations at order p,
// and the leaf size (split threshold) that gives it.
Scalar occupancy_for(int order);
Index leaf_size_for(int order);
// Factor in [1, 2) enlarging the root box so that evenly spread points fill the leaves of some
// level with `occupancy` points (the targets: nullptr / m = 0 when they are the sources).
Scalar root_scale_for(const Scalar* const sources[3], Index n, const Scalar* const targets[3],
                      Index m, Scalar occupancy);

// Output width per target and charge component: 1 (phi), 4 (phi, grad) or 10 (phi, grad,
// hess xx xy xz yy yz zz).
inline int output_width(int derivatives) { return derivatives == 0 ? 1 : derivatives == 1 ? 4 : 10; }

// sources: n x 3 row-major; charges: n x components row-major; targets: m x 3, or nullptr for
// the sources themselves (m must then equal n). out: m x components x output_width.
Fmm3dStats fmm3d(const Scalar* sources, Index n, const Scalar* charges, int components,
                 const Scalar* targets, Index m, const Fmm3dConfig& config, Scalar* out,
                 Interrupt& interrupt);

// The same sums directly (the exact reference), parallel over targets; returns the count of
// coincident pairs left out (Fmm3dStats::coincident).
Index direct3d(const Scalar* sources, Index n, const Scalar* charges, int components,
               const Scalar* targets, Index m, const Fmm3dConfig& config, Scalar* out,
               Interrupt& interrupt);

}  // namespace kinema::fmm3
